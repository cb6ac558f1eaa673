"""What each cut achieved: the interval between the frames it posed one after another (pure; clock injected).

A cut's period, the time between frames the slower side needs, is modelled from both sides' compute
profiles (`ComputeProfile.period_ms_by_k`). Where robot and edge share cores, or the robot's look-ahead
overlaps less than the model assumes, the model misjudges it both ways (bench.pipeline at 30 fps on one
2-core box: k = 3 predicted at 31-44 ms a frame ran at 61-69 ms). The frames themselves say what a cut
achieved: the capture stamps of consecutive frames posed at it are one camera interval apart when it
keeps up, and its real period when it does not (robot_infer keeps only the newest camera frame).
"""

from __future__ import annotations

import statistics
import threading
import time
from collections import deque
from collections.abc import Callable

from shared.wire.cuts import N_CUTS


class AchievedIntervals:
    """Mean interval between the capture stamps of consecutive frames posed at the same cut, per cut,
    within the last `window_secs` (None with fewer than `min_gaps` such intervals)."""

    # Intervals left out after each change of cut: the frames still in flight at the old cut, and the
    # first frames of a head or tail that has not run for a while.
    SKIP_AFTER_CHANGE = 3
    # A longer interval is a pause (the camera stopped, the edge gone), not the pipeline's rate ...
    MAX_GAP_MS = 1000.0
    # ... unless frames were computed on board meanwhile with the edge there (`missed`) and the cut's next
    # interval missed frames too: then the cut delivers too late, and the intervals are its rate, each
    # counted up to this long. A single such interval (one refused Features, an edge paused for a moment)
    # is left out: a review found that one 1.6 s hiccup made a cut that kept up look failing for the
    # whole throughput window.
    MAX_MISSED_GAP_MS = 3_000.0
    MAX_GAPS = 60  # per cut: 2-4 s at 15-30 fps

    def clear(self) -> None:
        """Forget what every cut achieved (the camera's rate changed: intervals of the old rate say
        nothing of the new)."""
        for gaps in self._gaps.values():
            gaps.clear()

    def __init__(self, *, window_secs: float, min_gaps: int = 8, clock: Callable[[], float] = time.monotonic) -> None:
        if window_secs <= 0 or min_gaps < 1:
            raise ValueError(f"need window_secs > 0 and min_gaps >= 1, got {window_secs}, {min_gaps}")
        self.window_secs = window_secs
        self.min_gaps = min_gaps
        self._clock = clock
        self._last: tuple[int, int] | None = None  # the last frame's (k, capture_nanos)
        self._run = 0  # intervals at the last frame's k since the cut changed
        self._missed = False  # frames computed on board, the edge there, since the last frame posed
        self._pending: tuple[float, float] | None = None  # a long interval with misses, waiting for a second
        # the latest intervals only, so the cut in use shows a change within seconds at 30 fps
        self._gaps: dict[int, deque[tuple[float, float]]] = {k: deque(maxlen=self.MAX_GAPS) for k in range(N_CUTS)}

    def add(self, k: int, capture_nanos: int) -> None:
        """A frame posed at cut k (in the order the poses arrive)."""
        if not 0 <= k < N_CUTS:
            return
        last = self._last
        if last is not None and last[0] == k:
            gap_ms = (capture_nanos - last[1]) / 1e6
            if gap_ms <= 0:  # a repeated or older frame (a camera restarted): not a rate
                if gap_ms < 0:
                    self._last, self._run, self._pending = (k, capture_nanos), 0, None
                return
            self._run += 1
            if self._run > self.SKIP_AFTER_CHANGE:
                if gap_ms <= self.MAX_GAP_MS:
                    self._gaps[k].append((self._clock(), gap_ms))
                    self._pending = None
                elif self._missed:
                    gap_ms = min(gap_ms, self.MAX_MISSED_GAP_MS)
                    if self._pending is not None:  # missed again: both are the cut's rate
                        self._gaps[k].append(self._pending)
                        self._gaps[k].append((self._clock(), gap_ms))
                        self._pending = None
                    else:
                        self._pending = (self._clock(), gap_ms)
                else:
                    self._pending = None
        else:
            self._run, self._pending = 0, None
        self._last = (k, capture_nanos)
        self._missed = False

    def missed(self) -> None:
        """A frame computed on board while the edge was there (an answer overdue at the cut in use: its
        link or edge too slow for the camera): the interval to the next frame posed at the cut is its
        rate, not a pause, once the interval after it missed frames too. A trial's 4 Mbit/s uplink at
        k = 0 posed one frame per 1.5 s (robot_infer's answer timeout: the rest went on board); each such
        interval was dropped as a pause, k = 0 kept the share it had on the fast link, and the controller
        stayed there for 14-18 s."""
        self._missed = self._last is not None

    def pause(self) -> None:
        """The stream paused (the edge gone): the next interval is not a cut's rate."""
        self._last, self._run, self._missed, self._pending = None, 0, False, None

    def interval_ms(self, k: int) -> float | None:
        """The mean interval between consecutive frames posed at cut k lately (None: too few)."""
        start = self._clock() - self.window_secs
        recent = [gap for when, gap in self._gaps[k] if when >= start]
        return sum(recent) / len(recent) if len(recent) >= self.min_gaps else None


class CameraInterval:
    """The camera's frame interval from its own stamps: the median of (capture time difference / frame
    number difference) over the last `window` frames received. Arrival times would not do: a receiver
    short of CPU gets frames in bunches, and its median gap moved with the load (a trial's controller
    read a 30 fps camera as 50 ms and took a cut at 60 % of the frames for one that kept up). Frames may
    be skipped (the number difference accounts for them); a camera that restarted (numbers or stamps
    going back) starts the count afresh. Thread-safe: fed on Zenoh's threads."""

    MAX_SKIPPED = 10  # a longer jump in frame numbers is not a steady camera's interval

    def __init__(self, *, window: int = 30) -> None:
        self._lock = threading.Lock()
        self._last: tuple[int, int] | None = None  # (seq, capture_nanos)
        self._intervals: deque[float] = deque(maxlen=window)

    def add(self, seq: int, capture_nanos: int) -> None:
        """One frame as it arrived."""
        with self._lock:
            last, self._last = self._last, (seq, capture_nanos)
            if last is None:
                return
            frames, nanos = seq - last[0], capture_nanos - last[1]
            if frames <= 0 or nanos <= 0:  # a camera restarted (perhaps at another rate): start afresh
                self._intervals.clear()
            elif frames <= self.MAX_SKIPPED:
                self._intervals.append(nanos / 1e6 / frames)

    def interval_ms(self) -> float | None:
        """The camera's interval (None before three intervals)."""
        with self._lock:
            return statistics.median(self._intervals) if len(self._intervals) >= 3 else None
