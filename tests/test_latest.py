"""The newest-valid slot robot_infer takes its frames from: bad samples are counted and never displace
the good one waiting; the consumer gets the newest good one."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from shared.runtime.guard import InputGuard
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
