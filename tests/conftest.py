"""Suite-wide fixtures and hooks: deployment configs from the one topology (shared.tools.topology),
and a closing section that says which tests were skipped and why, so a green run on a machine without
root, network namespaces or a V4L2 device never hides what it did not test."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from _pytest.terminal import TerminalReporter

from shared.tools.launch import write_run_config
from shared.tools.topology import Topology, merge

REPO = Path(__file__).resolve().parent.parent
LOCAL = REPO / "deploy" / "local.toml"

DeployConfig = Callable[..., tuple[Path, Topology]]


@pytest.fixture
def deploy_config(tmp_path: Path) -> DeployConfig:
    """deploy/local.toml on free loopback ports, as a run config in tmp_path/run (demo tag map, run_dir),
    Rerun off unless `extra` turns it on: `cfg, topology = deploy_config({"camera": {"fps": 2.0}})`."""

    def make(extra: dict[str, dict[str, Any]] | None = None, *, base: Path = LOCAL) -> tuple[Path, Topology]:
        topology = Topology.loopback()
        run = tmp_path / "run"
        run.mkdir(exist_ok=True)
        defaults: dict[str, dict[str, Any]] = {"common": {"rerun": {"enabled": False}}}
        return write_run_config(run, base, topology=topology, extra=merge(defaults, extra or {})), topology

    return make


def pytest_terminal_summary(terminalreporter: TerminalReporter, exitstatus: int, config: pytest.Config) -> None:
    """Print every skip reason with the tests it covered (nothing when none were skipped)."""
    skipped = terminalreporter.stats.get("skipped", [])
    if not skipped:
        terminalreporter.write_sep("=", "skipped: none (every test ran on this machine)")
        return
    reasons: Counter[str] = Counter()
    tests: dict[str, list[str]] = {}
    for report in skipped:
        longrepr = report.longrepr
        reason = longrepr[2] if isinstance(longrepr, tuple) else str(longrepr)
        reason = reason.removeprefix("Skipped: ")
        reasons[reason] += 1
        tests.setdefault(reason, []).append(report.nodeid)
    terminalreporter.write_sep("=", f"skipped: {len(skipped)} test(s), and why")
    for reason, n in reasons.most_common():
        terminalreporter.write_line(f"{n} x {reason}")
        for nodeid in tests[reason]:
            terminalreporter.write_line(f"    {nodeid}")
