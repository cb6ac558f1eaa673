"""Real processes for multi-process tests, through the launcher's one runner (shared.tools.launch):
own process group, logs to files, SIGINT teardown, every log printed when the test failed."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from shared.tools.launch import REPO, Service, start_process

__all__ = ["REPO", "Service", "processes", "start_process"]


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
