"""SIGINT/SIGTERM as a stop Event (shared.runtime.signals): a signal that arrives while the main thread
holds the Event's lock inside `stop.wait` must stop the process, not deadlock it (a trial's slam hung
there on a launcher's stop and was SIGKILLed 15 s later)."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

# The main thread holds the stop Event's lock (as it does for a few bytecodes of every `stop.wait`) when
# the signal is handled: a handler that calls stop.set() itself waits for that lock forever.
_CHILD = textwrap.dedent(
    """
    import os, signal, sys, threading
    sys.path.insert(0, {root!r})
    from shared.runtime.signals import SignalStop
    stop = threading.Event()
    if sys.argv[1] == "naive":
        signal.signal(signal.SIGTERM, lambda *_: stop.set())
    else:
        signals = SignalStop(stop)
    with stop._cond:  # (CPython: Event.wait holds this lock around Condition.wait)
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(1000):  # the handler runs between these bytecodes, the lock still held
            pass
    print("stopped" if stop.wait(3) else "not stopped", flush=True)
    if sys.argv[1] != "naive":
        assert signals.received == [signal.SIGTERM]
        signals.restore()
        assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
    """
)


def _run(kind: str, timeout_secs: float = 20.0) -> subprocess.CompletedProcess[str] | None:
    code = _CHILD.format(root=str(ROOT))
    try:
        return subprocess.run([sys.executable, "-c", code, kind], capture_output=True, text=True, timeout=timeout_secs)
    except subprocess.TimeoutExpired:
        return None


def test_a_signal_while_the_main_thread_holds_the_stop_lock_stops_it() -> None:
    done = _run("signal_stop")
    assert done is not None, "deadlocked"
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "stopped"


@pytest.mark.skipif(sys.implementation.name != "cpython", reason="CPython's Event lock")
def test_the_scenario_deadlocks_a_handler_that_sets_the_event_itself() -> None:
    """The test above can fail: the same scenario with the handler the services had hangs."""
    assert _run("naive", timeout_secs=6.0) is None
