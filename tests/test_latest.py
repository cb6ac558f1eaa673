"""The newest-valid slot robot_infer takes its frames from: bad samples are counted and never displace
the good one waiting; the consumer gets the newest good one."""

from __future__ import annotations

import threading

import numpy as np

from shared.runtime.guard import InputGuard
from shared.transport.latest import LatestValid
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
