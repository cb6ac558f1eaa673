"""AchievedIntervals: what each cut achieved between consecutive posed frames, from their capture stamps."""

from __future__ import annotations

import pytest

from shared.control.throughput import AchievedIntervals, CameraInterval
from tests.fakes import FakeClock

MS = 1_000_000  # nanoseconds


def test_intervals_at_one_cut_after_the_first_few() -> None:
    clock = FakeClock(10.0)
    got = AchievedIntervals(window_secs=60.0, min_gaps=5, clock=clock)
    for i in range(4):  # the first SKIP_AFTER_CHANGE intervals at a cut are frames of the cut before
        got.add(3, i * 200 * MS)
    assert got.interval_ms(3) is None
    for i in range(4, 4 + 5):
        got.add(3, i * 200 * MS)
    assert got.interval_ms(3) == pytest.approx(200.0)
    assert got.interval_ms(0) is None  # k = 0 has not run


def test_a_change_of_cut_restarts_the_count_and_no_interval_spans_two_cuts() -> None:
    clock = FakeClock(10.0)
    got = AchievedIntervals(window_secs=60.0, min_gaps=3, clock=clock)
    stamp = 0
    for k, every_ms in ((0, 50), (7, 33), (0, 50)):
        for _ in range(AchievedIntervals.SKIP_AFTER_CHANGE + 4):
            stamp += every_ms * MS
            got.add(k, stamp)
    assert got.interval_ms(0) == pytest.approx(50.0)
    assert got.interval_ms(7) == pytest.approx(33.0)


def test_pauses_repeats_and_a_restarted_camera_are_not_rates() -> None:
    clock = FakeClock(10.0)
    got = AchievedIntervals(window_secs=60.0, min_gaps=3, clock=clock)
    stamps = [0, 40, 80, 120, 160, 160, 5160, 5200, 20, 60, 100, 140, 180, 220]  # ms: a repeat, a pause, a restart
    for s in stamps:
        got.add(5, s * MS)
    assert got.interval_ms(5) == pytest.approx(40.0)


def test_intervals_age_out_of_the_window() -> None:
    clock = FakeClock(10.0)
    got = AchievedIntervals(window_secs=30.0, min_gaps=3, clock=clock)
    for i in range(10):
        got.add(4, i * 70 * MS)
    assert got.interval_ms(4) == pytest.approx(70.0)
    clock.now += 31.0
    assert got.interval_ms(4) is None


def test_settings_are_checked() -> None:
    with pytest.raises(ValueError, match="window_secs"):
        AchievedIntervals(window_secs=0.0)


def test_the_cameras_interval_from_its_own_stamps() -> None:
    cam = CameraInterval()
    assert cam.interval_ms() is None
    stamps = [(0, 0), (1, 33), (3, 100), (4, 133), (5, 166)]  # frame 2 skipped (not received)
    for seq, ms in stamps:
        cam.add(seq, ms * MS)
    assert cam.interval_ms() == pytest.approx(33.3, abs=0.5)
    cam.add(500, 20_000 * MS)  # a jump of frame numbers is not a steady camera's interval
    assert cam.interval_ms() == pytest.approx(33.3, abs=0.5)
    cam.add(0, 10 * MS)  # the camera restarted, at 20 fps: what it was before is forgotten
    assert cam.interval_ms() is None
    for seq in range(1, 4):
        cam.add(seq, (10 + 50 * seq) * MS)
    assert cam.interval_ms() == pytest.approx(50.0)
