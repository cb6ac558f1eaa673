"""SIGINT/SIGTERM as a stop Event, safely.

A handler that calls `stop.set()` itself can deadlock the process: Python runs signal handlers in the
main thread between two bytecodes, and when that thread is inside `stop.wait(...)` holding the Event's
(non-reentrant) lock, `set()` waits for that lock forever. A trial's slam hung that way on a
launcher's stop and was SIGKILLed 15 s later (its stack: `Event.set` <- the handler <- `Condition.wait`
<- `stop.wait`). Here the handler only writes a byte to a pipe (async-signal-safe, no Python lock) and
a thread of its own sets the Event.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
from collections.abc import Callable, Iterable
from types import FrameType

_Handler = Callable[[int, FrameType | None], object] | int | signal.Handlers | None

STOP_SIGNALS: tuple[signal.Signals, ...] = (signal.SIGINT, signal.SIGTERM)


class SignalStop:
    """Sets `stop` when one of `signals` arrives; `restore()` puts the previous handlers back (and ends
    the watcher thread). Install it from the main thread, as any signal handler."""

    def __init__(self, stop: threading.Event, signals: Iterable[signal.Signals] = STOP_SIGNALS) -> None:
        if threading.current_thread() is not threading.main_thread():  # (before any pipe or thread: review)
            raise ValueError("signal handlers can only be installed from the main thread")
        self.stop = stop
        self.received: list[int] = []  # the signals that came, in order (read after the stop)
        self._read, self._write = os.pipe()
        os.set_blocking(self._write, False)  # a burst of signals must never block the handler
        self._watcher = threading.Thread(target=self._watch, name="signal-stop", daemon=True)
        self._watcher.start()
        self._previous: dict[signal.Signals, _Handler] = {}
        for sig in signals:
            self._previous[sig] = signal.signal(sig, self._on_signal)

    def _on_signal(self, signum: int, _frame: FrameType | None) -> None:
        self.received.append(signum)  # (a list append takes no lock a waiting thread could hold)
        with contextlib.suppress(BlockingIOError, OSError):  # full pipe: the stop is on its way already
            os.write(self._write, b"\0")

    def _watch(self) -> None:
        while True:
            try:
                data = os.read(self._read, 64)
            except OSError:
                return
            if not data:  # restore() closed the write end
                os.close(self._read)
                return
            self.stop.set()

    def restore(self) -> None:
        """The previous handlers back; the watcher ends. Idempotent. Restore in the reverse order of
        installation when several are nested (each puts back what it found)."""
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous = {}
        if self._write >= 0:
            os.close(self._write)
            self._write = -1
