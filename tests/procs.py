"""Real processes for multi-process tests, through the launcher's one runner (shared.tools.launch):
own process group, logs to files, SIGINT teardown, every log printed when the test failed."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from shared.tools.launch import REPO, Service, start_process

__all__ = ["REPO", "Service", "processes", "start_process", "wait_until"]


@contextmanager
def processes(log_dir: Path) -> Iterator[list[Service]]:
    """Yield a list to append started processes to; all are stopped at exit (reverse order), logs
    printed if the body failed."""
    procs: list[Service] = []
    failed = True
    try:
        yield procs
        failed = False
    finally:
        for p in reversed(procs):
            p.stop(timeout_secs=10.0)
        if failed:
            for p in procs:
                print(f"----- log of {p.name} (exit {p.popen.returncode}) -----\n{p.log_text()}")


def wait_until(predicate: Callable[[], object], timeout_secs: float, what: str, *, poll_secs: float = 0.05) -> None:
    """Poll until predicate() is true, or fail saying what was awaited."""
    deadline = time.monotonic() + timeout_secs
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(poll_secs)
    raise AssertionError(f"timed out after {timeout_secs} s waiting for {what}")
