"""Suite-wide pytest hooks: a closing section that says which tests were skipped and why, so a green
run on a machine without root, network namespaces or a V4L2 device never hides what it did not test."""

from __future__ import annotations

from collections import Counter

import pytest
from _pytest.terminal import TerminalReporter


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
