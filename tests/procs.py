"""Start real processes for multi-process tests: own process group, logs to files, SIGINT teardown."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


class Proc:
    """A child process whose combined output goes to a log file."""

    def __init__(
        self,
        name: str,
        argv: list[str],
        log_dir: Path,
        env: dict[str, str] | None = None,
        *,
        wrapper: list[str] | None = None,
    ):
        self.name = name
        self.log_path = log_dir / f"{name}.log"
        self._log = self.log_path.open("wb")
        full_env = {**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})}
        self.popen = subprocess.Popen(
            [*(wrapper or []), sys.executable, *argv],  # wrapper: e.g. `ip netns exec NS`
            cwd=REPO,
            stdout=self._log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            env=full_env,
        )

    def stop(self, timeout_secs: float = 10.0) -> int:
        """SIGINT the process group, escalate to SIGKILL; returns the exit code."""
        if self.popen.poll() is None:
            os.killpg(self.popen.pid, signal.SIGINT)
            try:
                self.popen.wait(timeout=timeout_secs)
            except subprocess.TimeoutExpired:
                os.killpg(self.popen.pid, signal.SIGKILL)
                self.popen.wait()
        self._log.close()
        return self.popen.returncode

    def log_text(self) -> str:
        """Everything the process printed so far."""
        return self.log_path.read_text(errors="replace")


@contextmanager
def processes(log_dir: Path) -> Iterator[list[Proc]]:
    """Yield a list to append Procs to; all are stopped at exit, logs printed if the body failed."""
    procs: list[Proc] = []
    failed = True
    try:
        yield procs
        failed = False
    finally:
        for p in reversed(procs):
            p.stop()
        if failed:
            for p in procs:
                print(f"----- log of {p.name} (exit {p.popen.returncode}) -----\n{p.log_text()}")
