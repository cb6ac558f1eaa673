"""The newest-valid slot robot_infer takes its frames from: bad samples are counted and never displace
the good one waiting; the consumer gets the newest good one."""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from shared.runtime.guard import InputGuard, input_counts_summary
from shared.transport.latest import LatestValid, fresh_wait_secs
from shared.wire.messages import Frame, decode, encode
from tests.examples import example_messages


def _frame(seq: int) -> bytes:
    frame = example_messages()["splittag/Frame/v1"]
    assert isinstance(frame, Frame)
    return encode(frame.model_copy(update={"seq": seq}))


def test_a_bad_sample_never_displaces_the_good_frame_waiting() -> None:
    guard = InputGuard("test", log_every_secs=0.0)
    slot: LatestValid[Frame] = LatestValid(lambda b: decode(b, Frame), guard, "frame")
    stop = threading.Event()
    assert slot.offer(_frame(1))
    assert not slot.offer(b"\xc1\x02 not a frame")
    assert not slot.offer(_frame(2)[:-3])  # truncated
    taken = slot.take(stop)
    assert taken is not None and taken.seq == 1
    assert guard.stats()["rejected"] == 2 and guard.stats()["accepted"] == 0  # accepted: counted by the consumer
    # The newest good one wins; the displaced one is counted.
    assert slot.offer(_frame(3)) and slot.offer(_frame(4))
    taken = slot.take(stop)
    assert taken is not None and taken.seq == 4 and slot.replaced == 1 and slot.received == 3
    np.testing.assert_array_equal(taken.image, decode(_frame(4), Frame).image)


def test_take_waits_for_a_frame_and_returns_none_once_stopped() -> None:
    slot: LatestValid[Frame] = LatestValid(lambda b: decode(b, Frame), InputGuard("test"), "frame")
    stop = threading.Event()
    timer = threading.Timer(0.05, lambda: slot.offer(_frame(7)))
    timer.start()
    taken = slot.take(stop, poll_secs=0.01)
    assert taken is not None and taken.seq == 7
    stop.set()
    assert slot.take(stop, poll_secs=0.01) is None


def test_take_returns_early_when_the_consumer_has_other_work() -> None:
    """robot_infer waits for a frame with `wake`: frames a vanished edge held are recovered at once, not
    after the next camera frame (which may never come)."""
    slot: LatestValid[Frame] = LatestValid(lambda b: decode(b, Frame), InputGuard("test"), "frame")
    stop, work = threading.Event(), threading.Event()
    threading.Timer(0.1, work.set).start()
    assert slot.take(stop, poll_secs=0.01, wake=work.is_set) is None
    assert not stop.is_set()
    assert slot.offer(_frame(5))
    taken = slot.take(stop, wake=work.is_set)  # a frame waiting is returned even with work pending
    assert taken is not None and taken.seq == 5


def test_fresh_wait_waits_only_when_the_next_message_is_due_within_the_fraction() -> None:
    assert fresh_wait_secs(age_secs=0.030, interval_secs=0.033, fraction=1 / 3) == pytest.approx(0.003)
    assert fresh_wait_secs(age_secs=0.0225, interval_secs=0.033, fraction=1 / 3) == pytest.approx(0.0105)
    assert fresh_wait_secs(age_secs=0.021, interval_secs=0.033, fraction=1 / 3) == 0.0  # due in 12 ms > 11
    assert fresh_wait_secs(age_secs=0.001, interval_secs=0.033, fraction=1 / 3) == 0.0
    assert fresh_wait_secs(age_secs=0.050, interval_secs=0.033, fraction=1 / 3) == 0.0  # overdue: none coming
    assert fresh_wait_secs(age_secs=0.030, interval_secs=None, fraction=1 / 3) == 0.0  # rate not known yet
    assert fresh_wait_secs(age_secs=0.030, interval_secs=0.033, fraction=0.0) == 0.0  # off


class _Clock:
    """A clock the test moves."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def _slot_at_10_hz(clock: _Clock) -> LatestValid[Frame]:
    """Frames 0..3 offered 0.1 s apart; the clock is at frame 3's arrival."""
    slot: LatestValid[Frame] = LatestValid(lambda b: decode(b, Frame), InputGuard("test"), "frame", clock=clock)
    for seq in range(4):
        if seq:
            clock.now += 0.1
        assert slot.offer(_frame(seq))
    assert slot.interval_secs() == pytest.approx(0.1)
    return slot


def test_take_waits_for_the_next_frame_when_it_is_due_soon() -> None:
    """robot_infer's `fresh_frame_fraction`: a frame 80 ms old with the next due in 20 ms is not taken;
    the next one is, as it arrives."""
    clock, stop = _Clock(), threading.Event()
    slot = _slot_at_10_hz(clock)
    clock.now += 0.08
    replaced = slot.replaced

    def next_frame() -> None:
        clock.now += 0.02
        slot.offer(_frame(4))

    threading.Timer(0.05, next_frame).start()
    taken = slot.take(stop, poll_secs=0.01, fresh_fraction=1 / 3)
    assert taken is not None and taken.seq == 4
    assert slot.fresh_waits == 1 and slot.fresh_wait_secs == pytest.approx(0.02)
    assert slot.replaced == replaced + 1  # frame 3, displaced while the consumer waited


def test_take_does_not_wait_when_the_next_frame_is_far_or_never_comes() -> None:
    clock, stop = _Clock(), threading.Event()
    slot = _slot_at_10_hz(clock)
    clock.now += 0.02  # the next is 80 ms away: frame 3 at once
    taken = slot.take(stop, fresh_fraction=1 / 3)
    assert taken is not None and taken.seq == 3 and slot.fresh_waits == 0
    # The camera stops: the wait ends half the fraction of an interval after the frame was due.
    assert slot.offer(_frame(4))
    clock.now += 0.09

    def time_passes() -> None:
        clock.now += 0.01 + 0.5 * 0.1 / 3 + 1e-6

    threading.Timer(0.05, time_passes).start()
    taken = slot.take(stop, poll_secs=0.01, fresh_fraction=1 / 3)
    assert taken is not None and taken.seq == 4 and slot.fresh_waits == 1
    # Stopping ends the wait too; the frame waiting is still handed over.
    assert slot.offer(_frame(5))
    clock.now += 0.09
    threading.Timer(0.05, stop.set).start()
    taken = slot.take(stop, poll_secs=0.01, fresh_fraction=1 / 3)
    assert taken is not None and taken.seq == 5 and slot.fresh_waits == 2


def test_a_burst_of_bad_inputs_is_summed_up_once_its_interval_ends(caplog: pytest.LogCaptureFixture) -> None:
    """A trial's burst of 10 bad frames showed in robot_infer.log as "rejected frame #1" alone (the "+N
    not logged" waited for a next rejection that never came). The rest is said in one line when the
    interval ends, by reason with the newest text, and at shutdown; the rate stays one line a second."""
    now = [0.0]
    due: list[tuple[float, Callable[[], None]]] = []
    guard = InputGuard("robot_infer", clock=lambda: now[0], schedule=lambda secs, call: due.append((secs, call)))

    def bad(what: str, why: str) -> None:
        guard.run(what, 7, lambda: (_ for _ in ()).throw(ValueError(why)))

    with caplog.at_level(logging.WARNING, logger="shared.runtime.guard"):
        for i in range(10):
            now[0] = 0.05 * i
            bad("frame" if i < 8 else "frame_stamp", f"bad {i}")
        assert len(caplog.records) == 1 and "rejected frame #1" in caplog.text
        assert [secs for secs, _ in due] == [pytest.approx(0.95)]  # one flush, when the interval ends (t = 1 s)
        now[0] = 1.0
        due.pop()[1]()
        assert len(caplog.records) == 2
        line = caplog.records[1].getMessage()
        assert "rejected 9 more inputs not logged one by one (10 in all)" in line, line
        assert "frame: ValueError x7, frame_stamp: ValueError x2" in line and "bad 7 (7 bytes)" in line, line
        assert "bad 9 (7 bytes)" in line, line
        guard.flush()  # nothing left: nothing said
        assert len(caplog.records) == 2
        now[0] = 1.5
        bad("frame", "late")  # within the interval of the summary: counted, said at shutdown
        assert len(caplog.records) == 2 and len(due) == 1
        guard.flush()
        assert len(caplog.records) == 3 and "rejected 1 more inputs" in caplog.records[2].getMessage()
    assert guard.stats()["rejected"] == 11


def test_input_counts_are_written_again_once_the_folder_takes_them(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A soak trial made the run folder read-only for a minute: the first failed write stopped every later
    one, at exit too, and the summary said 0 refused. A failed write is said once and tried again."""
    blocker = tmp_path / "inputs"
    blocker.write_text("a file where the folder goes: every write fails")
    guard = InputGuard("slam", schedule=lambda secs, call: None)
    counts = blocker / "slam.7.json"
    with caplog.at_level("WARNING"):
        guard.persist(counts, every_secs=0.01)
        for _ in range(2):
            guard.run("tag_poses", 8, lambda: (_ for _ in ()).throw(ValueError("bad")))
        time.sleep(0.1)  # several failed periods: said once
        blocker.unlink()
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and not (counts.exists() and '"rejected": 2' in counts.read_text()):
            time.sleep(0.01)
        guard.run("tag_poses", 8, lambda: (_ for _ in ()).throw(ValueError("bad")))
        guard.close()
    assert json.loads(counts.read_text())["rejected"] == 3  # the exit's write too
    said = [r.getMessage() for r in caplog.records if "input counts" in r.getMessage()]
    assert len(said) == 2 and "trying again" in said[0] and "written to" in said[1] and "again" in said[1], said


def test_input_counts_outlive_their_process_in_the_run_folder(tmp_path: Path) -> None:
    """A trial's end-of-run lines said 0 rejected after two SIGKILL restarts that had refused 19 and 10.
    Each process keeps its counts in the run folder as they change (and at close); the summary adds up
    every process's per service, or per label where a service's processes name several (a fleet's
    workers). A file cut short is skipped; without a run folder nothing is written."""
    first = InputGuard("edge_infer", schedule=lambda secs, call: None)
    first.persist(tmp_path / "inputs" / "edge_infer.101.json", label="edge1", every_secs=3600)
    first.run("features", 8, lambda: (_ for _ in ()).throw(ValueError("bad")))
    first.run("features", 8, lambda: None)
    first.close()
    second = InputGuard("edge_infer", schedule=lambda secs, call: None)
    second.persist(tmp_path / "inputs" / "edge_infer.102.json", label="edge1", every_secs=0.01)
    try:
        for _ in range(3):
            second.run("probe", 8, lambda: (_ for _ in ()).throw(KeyError("x")))
        counts = tmp_path / "inputs" / "edge_infer.102.json"
        deadline = time.monotonic() + 10  # killed without close: what the last periodic write held
        while time.monotonic() < deadline and '"rejected": 3' not in counts.read_text():
            time.sleep(0.01)
        (tmp_path / "inputs" / "slam.103.json").write_text('{"service": "slam", "accep')  # cut short
        assert input_counts_summary(tmp_path) == {
            "edge_infer": {
                "processes": 2,
                "accepted": 1,
                "accepted_by_input": {"features": 1},
                "rejected": 4,
                "rejected_by_reason": {"features: ValueError": 1, "probe: KeyError": 3},
            }
        }
    finally:
        second.close()
    other = InputGuard("edge_infer", schedule=lambda secs, call: None)  # a fleet's second worker
    other.persist(tmp_path / "inputs" / "edge_infer.104.json", label="edge2", every_secs=3600)
    other.run("features", 8, lambda: None)
    other.close()
    summary = input_counts_summary(tmp_path)
    assert set(summary) == {"edge_infer@edge1", "edge_infer@edge2"}
    assert summary["edge_infer@edge1"]["processes"] == 2 and summary["edge_infer@edge2"]["accepted"] == 1
    alone = InputGuard("slam")
    alone.persist(tmp_path / "no such run" / "inputs" / "slam.1.json")
    alone.close()
    assert not (tmp_path / "no such run").exists()
