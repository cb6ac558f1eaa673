"""Per-split compute estimates C(k) (robot) and E(k) (edge) for the controller.

Each side only ever runs its own part of the network at the k in use, so it cannot time the other
cuts live. It calibrates per-tag cumulative block times once at start-up (`profile_cuts`, batch 1)
and scales them by the running median of live / calibrated time at the k in use: CPU contention, a
slower machine or the gamma slowdown move every cut's estimate together. Pure: no I/O, no clocks.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Sequence

import numpy as np

from shared.wire.cuts import N_CUTS
from shared.wire.messages import ComputeProfile

# A reference CPU's per-tag cumulative head time at every cut (ms), shaped like the paper network's
# blocks and above what either CPU kind here takes (AMD EPYC Zen 4 bf16: 8, 17, 26, 35, 38, 39, 40 ms),
# for tests and scenarios that must not depend on the machine (`emulated_ms_per_tag_by_k`).
REFERENCE_HEAD_MS_PER_TAG: tuple[float, ...] = (0.0, 10.0, 20.0, 30.0, 40.0, 44.0, 44.0, 45.0)


class _RunningMedian:
    def __init__(self, window: int) -> None:
        self._values: deque[float] = deque(maxlen=window)

    def add(self, value: float) -> None:
        self._values.append(value)

    def get(self, default: float) -> float:
        return float(np.median(self._values)) if self._values else default


class ComputeEstimator:
    """ms per frame for every cut: fixed_ms + tags * per_tag_ms[k] * live_scale.

    `per_tag_ms` is the calibrated per-tag time of this side's network part at each cut (robot: the
    head up to k; edge: the tail from k plus PnP). `fixed_ms` (robot: detection and ROI warping) is a
    running median of its own. Frames without tags teach only the fixed part.
    """

    LEARN_FROM_FRACTION = 0.3
    SKIP_FIRST = 3  # the first frames after start-up carry one-time costs, not the steady state

    # Frames for a stale scale (no evidence at the k in use) to fall halfway back to the calibration.
    # 30 (the window) made the controller flap under a load on both sides (a trial: 46 switches in 5.5
    # min at load 6-7): at k = 7 the edge's learnt slowdown faded within 2 s, k = 0 looked faster, the
    # next profile from there taught it again and the robot's faded in turn. Each fade is a trip to a
    # worse k for about a second: the simulated chain in tests/test_compute.py (3x load on both sides,
    # profiles once a second at 15 fps) switches 124 times in 2800 frames at 30, 34 at 300, and keeps
    # the best cut for 67 % and 91 % of the frames.
    STALE_HALF_LIFE_FRAMES = 300

    def __init__(
        self, per_tag_ms: Sequence[float], *, window: int = 30, stale_half_life_frames: float = STALE_HALF_LIFE_FRAMES
    ) -> None:
        if len(per_tag_ms) != N_CUTS or min(per_tag_ms) < 0:
            raise ValueError(f"need {N_CUTS} non-negative per-tag times, got {list(per_tag_ms)}")
        self.per_tag_ms = np.asarray(per_tag_ms, np.float64)
        self._scale = _RunningMedian(window)
        self._fixed = _RunningMedian(window)
        self._tags = _RunningMedian(window)
        self._seen = 0
        self._stale = 0  # frames since the last scale evidence
        self._half_life = float(stale_half_life_frames)
        self.current_k = 0

    def observe(self, *, k: int, tags: int, network_ms: float, fixed_ms: float = 0.0) -> None:
        """One frame computed at cut k: `network_ms` in the network part, `fixed_ms` outside it."""
        self.current_k = k
        self._tags.add(float(tags))
        self._fixed.add(max(0.0, fixed_ms))
        predicted = tags * self.per_tag_ms[k]
        # Learn the scale only where most of this side's network runs: where little of it runs, the
        # per-frame overheads (dispatch, tensor conversion, PnP) and the batch-friendly FC layers
        # dominate, and their ratio says nothing about the convolutions the other cuts would run.
        if tags and self.per_tag_ms[k] >= self.LEARN_FROM_FRACTION * float(self.per_tag_ms.max()):
            self._seen += 1
            if self._seen > self.SKIP_FIRST:
                self._scale.add(max(0.0, network_ms) / predicted)
                self._stale = 0
                return
        self._stale += 1

    @property
    def live_scale(self) -> float:
        """Running median of live / calibrated network time; 1.0 before any evidence, and decaying back
        towards 1.0 (half-life `stale_half_life_frames`) while the k in use gives no evidence: a scale
        learnt long ago, perhaps under start-up load, must not decide the other cuts forever."""
        learnt = self._scale.get(1.0)
        return 1.0 + (learnt - 1.0) * 0.5 ** (self._stale / self._half_life)

    @property
    def tags_per_frame(self) -> float:
        """Running median of tags per frame."""
        return self._tags.get(0.0)

    def ms_by_k(self, tags: float | None = None) -> list[float]:
        """Estimated ms per frame at every cut for `tags` tags (default: the running median)."""
        fixed, network = self._parts(tags)
        return [float(v) for v in fixed + network]

    def period_ms_by_k(self, *, overlapped: bool) -> list[float]:
        """The time between frames this side needs at every cut when it never waits: the whole frame's
        compute, or with `overlapped` (the fixed part of the next frame runs beside this frame's network,
        on a thread of its own) the longer of the two."""
        fixed, network = self._parts(None)
        return [float(v) for v in (np.maximum(fixed, network) if overlapped else fixed + network)]

    def _parts(self, tags: float | None) -> tuple[float, np.ndarray]:
        """ms per frame outside the network, and in it at every cut, for `tags` (default: the median)."""
        n = self.tags_per_frame if tags is None else tags
        return self._fixed.get(0.0), n * self.per_tag_ms * self.live_scale

    def message(
        self,
        *,
        robot_id: str,
        side: str,
        stamp_nanos: int,
        factor: float = 1.0,
        overlapped: bool = False,
        frame_interval_ms: float | None = None,
    ) -> ComputeProfile:
        """The ComputeProfile to publish: ms per frame and the period at every cut, times `factor` (robot:
        gamma), and the camera's frame interval where this side sees the camera (the robot)."""
        return ComputeProfile(
            robot_id=robot_id,
            side=side,  # type: ignore[arg-type]
            stamp_nanos=stamp_nanos,
            current_k=self.current_k,
            tags_per_frame=self.tags_per_frame,
            live_scale=self.live_scale,
            ms_by_k=[factor * v for v in self.ms_by_k()],
            period_ms_by_k=[factor * v for v in self.period_ms_by_k(overlapped=overlapped)],
            frame_interval_ms=frame_interval_ms,
        )


def head_per_tag_ms(cumulative_ms: Sequence[float], *, views: int = 1) -> list[float]:
    """Robot side: the cumulative head time up to each cut is what the robot computes per tag; at the
    last cut (the whole network) once per test-time view (shared.model.views).

    The head up to k contains the head up to every earlier cut, so its time cannot fall with k; each
    timing is an upper bound of its cut's (contention only adds), so a cut's time is the least of its
    own and every later cut's. A trial's start-up calibration under load read 118, 213, 230, 221, 260,
    293, 269, 272 ms: block 1 dearer than block 3, block 5 than the whole network, and the controller
    saw gains that were noise."""
    times = np.maximum(np.asarray(cumulative_ms, np.float64), 0.0)
    out = [float(v) for v in np.minimum.accumulate(times[::-1])[::-1]]
    out[-1] *= views
    return out


def tail_per_tag_ms(tail_ms: Sequence[float], pnp_ms: float, *, views: int = 1) -> list[float]:
    """Edge side: the rest of the network after each cut (`tail_ms`, one view's, timed per cut:
    shared.model.runtime.calibrate_tail_ms), plus PnP, per tag; from cut 0 (the whole network) once per
    test-time view. The tail from k contains the tail from every later cut: a cut's time is the least
    of its own and every earlier cut's (as head_per_tag_ms)."""
    times = np.minimum.accumulate(np.maximum(np.asarray(tail_ms, np.float64), 0.0))
    out = [float(v) + pnp_ms for v in times]
    out[0] = views * float(times[0]) + pnp_ms
    return out
