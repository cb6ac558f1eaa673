"""A stop signal taken by another thread than the main one still ends the main thread's waits
(`shared.runtime.waiting`): robot_infer once ignored `splittag down` for 90 s, its main thread in
`Future.result()` while the look-ahead thread waited for a frame from a camera that had stopped."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.procs import REPO

SCRIPT = """
import signal, sys, threading, time
from concurrent.futures import ThreadPoolExecutor
from shared.runtime.signals import SignalStop
from shared.runtime.waiting import result_of, until_set

stop = threading.Event()
SignalStop(stop)  # as service_main
wait = sys.argv[1]

def kick():  # SIGINT handled on this thread (as on a Zenoh or torch thread), not on the main one
    time.sleep(0.3)
    signal.pthread_kill(threading.get_ident(), signal.SIGINT)

threading.Thread(target=kick).start()
start = time.monotonic()
if wait == "until_set":
    until_set(stop)
    said = "stopped"
else:
    # the look-ahead's part: ends when stop is set, else after 8 s
    future = ThreadPoolExecutor(1).submit(lambda: "stopped" if stop.wait(8) else "timed out")
    said = future.result() if wait == "plain" else result_of(future)
print(said, round(time.monotonic() - start, 1))
"""


@pytest.mark.parametrize("wait", ["result_of", "until_set"])
def test_a_stop_signal_on_another_thread_ends_the_main_threads_wait(wait: str) -> None:
    out = subprocess.run([sys.executable, "-c", SCRIPT, wait], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert out.stdout.split()[0] == "stopped", out.stdout + out.stderr  # the handler ran: not "timed out"


def test_an_untimed_wait_misses_it() -> None:
    """What the helpers are for: the same wait without them sits out its whole 8 s."""
    out = subprocess.run([sys.executable, "-c", SCRIPT, "plain"], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert out.stdout.startswith("timed out"), out.stdout + out.stderr


def test_result_unless_set_gives_the_result_its_error_or_none_once_stopped() -> None:
    import threading
    from concurrent.futures import Future

    from shared.runtime.waiting import result_unless_set

    stop = threading.Event()
    done: Future[int] = Future()
    done.set_result(3)
    assert result_unless_set(done, stop) == 3
    failed: Future[int] = Future()
    failed.set_exception(ValueError("no router"))
    with pytest.raises(ValueError, match="no router"):
        result_unless_set(failed, stop)
    pending: Future[int] = Future()
    threading.Timer(0.2, stop.set).start()
    assert result_unless_set(pending, stop, poll_secs=0.05) is None
