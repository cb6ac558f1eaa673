"""Waits on a service's main thread that a stop signal can end.

A process's signals may be taken by any of its threads (Zenoh's and torch's included), and Python runs
its handler only when the main thread next executes bytecode. A main thread blocked in a wait without a
timeout (`Future.result()`, `Event.wait()`) then never runs the SIGINT handler that would end the wait:
robot_infer, waiting for the look-ahead thread's stage 1 while that thread waited for a frame from a
camera that had stopped, ignored `splittag down` for 90 s (3 runs in 12 of a test, with its stacks)."""

from __future__ import annotations

import threading
from concurrent.futures import Future
from typing import TypeVar

T = TypeVar("T")

POLL_SECS = 0.1  # how soon a stop signal taken by another thread runs its handler on the main thread


def result_of(future: Future[T], *, poll_secs: float = POLL_SECS) -> T:
    """`future.result()`, returning to the interpreter every `poll_secs` so that signal handlers run."""
    while True:
        try:
            return future.result(timeout=poll_secs)
        except TimeoutError:
            continue


def until_set(event: threading.Event, *, poll_secs: float = POLL_SECS) -> None:
    """`event.wait()`, returning to the interpreter every `poll_secs` so that signal handlers run."""
    while not event.wait(poll_secs):
        pass


def result_unless_set(future: Future[T], stop: threading.Event, *, poll_secs: float = POLL_SECS) -> T | None:
    """`future.result()` (its exception raised alike), or None as soon as `stop` is set first; returning
    to the interpreter every `poll_secs` so that signal handlers run."""
    while not stop.is_set():
        try:
            return future.result(timeout=poll_secs)
        except TimeoutError:
            continue
    return None
