"""The adaptive split controller's pure core: evidence in, a decision and its explanation out.

Evidence: every frame's and probe's one-way crossing of the uplink (send and arrival stamps, and the
arrival of the message ahead of it, so waiting in the queue is not mistaken for the link: see
`OnlineLinkEstimator`), FrameSent notices (probes wait for an idle link), and the ComputeProfiles of
robot_infer (C(k), gamma included: the slowdown is real) and edge_infer (E(k)).
Decision: T(k) = C(k) + t0 + beta S(k) + E(k) for every k, argmin with hysteresis (HysteresisChooser)
among the cuts that keep up with the camera: expected to pose at least min_frame_share of its frames,
by what the cut achieved lately where it ran (AchievedIntervals, from the poses' capture stamps), else
by its period, the time between frames the uplink and the slower side need (robot_infer's profile says
the camera's rate; where no cut keeps up, those close to the best share).
The floor t0 is the uplink's: the emulated link (like the paper's probes) delays only the uplink, and
the pipeline's latency ends at the edge, so frames and probes are timed one way, on the same line.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from shared.control.linkmodel import HysteresisChooser, LinkOccupancy, OnlineLinkEstimator, split_costs
from shared.control.throughput import AchievedIntervals
from shared.wire.cuts import N_CUTS, CodecName
from shared.wire.messages import CONTROLLER_WAITING, ComputeProfile, ControllerState, FrameSent, LinkStamps
from shared.wire.sizing import features_payload_bytes


class ControllerTuning(BaseModel):
    """How the controller estimates and decides: the one home of these defaults (the service's
    settings inherit them, so TOML and environment set them by the same names)."""

    model_config = ConfigDict(frozen=True)

    min_gain_ms: float = Field(default=3.0, ge=0)  # switch only for at least this much ...
    min_gain_rel: float = Field(default=0.05, ge=0)  # ... and this fraction of T(current)
    dwell: int = Field(default=2, ge=1)  # consecutive decisions that must agree before a switch
    half_life_samples: float = Field(default=40.0, gt=1)  # forgetting of the link estimator
    change_threshold: float = Field(default=5.0, gt=0)  # CUSUM threshold (robust sigmas) for a link alarm
    # The change detector normalises residuals by no less than this: smaller shifts cannot change a
    # decision, and a quiet link's sub-millisecond scale made them alarms (each starts a challenger fit)
    change_floor_ms: float = Field(default=2.0, ge=0)
    # A switch the model asks for is vetoed while the frames measured at both cuts within this many
    # seconds (on the link the model now predicts for them) say the new cut is no faster: where two cuts
    # nearly tie and the model is biased (a loaded link's queue, each side slower when it does the work),
    # a trial's controller went 0 -> 7 -> 0 -> 7 -> 0 within 9 s. 0 turns the check off.
    measured_window_secs: float = Field(default=20.0, ge=0)
    # Ping-pong: after a -> b -> a, going to b again within this long of the first switch, for latency
    # alone, needs reversal_gain_factor times the usual gain (a link change lifts it; one return is free:
    # new evidence may undo a switch). Under a shifting load two nearly tied cuts took turns in a trial,
    # 0 -> 6 -> 0 -> 6 -> 0 within 4.4 s, each 'predicted 10-17 ms faster'. A cut left because it could not
    # keep up is taken back for latency within this long only for that gain too (a trial: 7 -> 5 -> 7 -> 5
    # within 0.8 s where no cut kept up). A cut that cannot keep up is left at once whatever this says.
    # 0 turns the hold off.
    reversal_hold_secs: float = Field(default=10.0, ge=0)
    reversal_gain_factor: float = Field(default=4.0, ge=1)  # (above) the gain a held switch needs, x the usual
    codec: CodecName = "fp16"  # the codec robot_infer uses at cuts 1..6 (payload sizes)
    # Throughput: a cut keeps up with the camera when it is expected to pose at least this share of the
    # camera's frames; the controller chooses the fastest cut among those that keep up (where none does,
    # among those close to the best share). Expected: what the cut achieved lately where it ran
    # (AchievedIntervals), else the camera's frame interval / the cut's period. On a 2-core box at 30 fps
    # k = 0 left the edge 42 ms a frame for 33 ms between frames and posed a fifth fewer frames
    # (bench.pipeline --auto, docs/link_and_controller.md). 0 turns the check off (latency alone).
    min_frame_share: float = Field(default=0.9, ge=0, le=1)
    # Where no cut keeps up, those within this fraction of the best share a cut achieved count as keeping
    # up. On one 2-core box at 30 fps the cuts posed 45-73 % of the frames, a cut's share moving by 0.05-0.1
    # from one visit to the next: at 0.1 the controller went 0 -> 3 -> 0 -> 3 on that noise.
    throughput_slack_rel: float = Field(default=0.2, ge=0, lt=1)
    # The cut in use stays eligible down to this much below the bar, so a share near it does not flap.
    frame_share_hysteresis: float = Field(default=0.05, ge=0, lt=1)
    # A cut's period is the uplink's (beta S(k)) and, with this on, the slower side's compute too (the
    # profiles' periods); off: the uplink's alone.
    compute_keeps_up: bool = True
    # How long what a cut achieved stands for it; the model's period takes over after that (and a cut the
    # model thinks keeps up is tried again).
    throughput_window_secs: float = Field(default=120.0, gt=0)


class SplitController:
    """Fuses evidence and decides; `clock` is injectable for tests."""

    UNTRIED_MARGIN = 1.1  # a cut not run lately keeps up only with its period this much within the bar
    DOUBT_REACH = 2  # cuts at most this far from one that fell behind its model are doubted as much ...
    MAX_DOUBT = 3.0  # ... by at most this factor
    BAR_RAMP = 0.1  # the bar goes from min_frame_share to its lower value as the best share falls this much

    def __init__(
        self, settings: ControllerTuning | None = None, *, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.settings = settings or ControllerTuning()
        self.link = OnlineLinkEstimator(
            half_life=self.settings.half_life_samples,
            cusum_threshold=self.settings.change_threshold,
            change_floor_ms=self.settings.change_floor_ms,
        )
        self.chooser = HysteresisChooser(
            min_gain_ms=self.settings.min_gain_ms, min_gain_rel=self.settings.min_gain_rel, dwell=self.settings.dwell
        )
        self.occupancy = LinkOccupancy()
        self.robot: ComputeProfile | None = None
        self.edge: ComputeProfile | None = None
        self._clock = clock
        self.last_sizes: dict[int, float] = {}  # payload bucket (log2 kB) -> when last seen
        # each cut's measured frames (when, ms, tags, the link time the model predicted for them then):
        # robot + link + edge compute, what T(k) predicts
        self.measured: dict[int, deque[tuple[float, float, int, float]]] = {k: deque(maxlen=120) for k in range(N_CUTS)}
        self.vetoed = 0  # switches the measured frame times vetoed
        self.held = 0  # switches back to a cut just left that the reversal hold kept
        self._switches: deque[tuple[float, int, int, int]] = deque(maxlen=2)  # (when, from, to, link changes)
        # cuts left because they could not keep up: k -> (when, link changes), and the switch decided so
        self._fell_behind: dict[int, tuple[float, int]] = {}
        self._forced_switch: tuple[int, int] | None = None
        self.achieved = AchievedIntervals(window_secs=self.settings.throughput_window_secs, clock=clock)
        self.camera_interval_ms: float | None = None  # the last the robot said (kept while it says none)
        self._achieved_at_ms: float | None = None  # the camera's interval what the cuts achieved was timed at

    # -- evidence ----------------------------------------------------------------------------------
    def add_link_sample(self, payload_bytes: int, ms: float) -> None:
        """A latency sample of a message that found the link idle (a probe's RTT without stamps)."""
        if ms <= 0 or not np.isfinite(ms):
            return
        self.link.add(payload_bytes / 1024.0, ms)
        self.last_sizes[self._bucket(payload_bytes)] = self._clock()

    def add_crossing(self, payload_bytes: int, link: LinkStamps) -> None:
        """A frame's or probe's crossing of the uplink, with what was ahead of it (queue-aware)."""
        self.link.add_crossing(
            size_kB=payload_bytes / 1024.0,
            sent_ms=link.sent_nanos / 1e6,
            received_ms=link.received_nanos / 1e6,
            previous_received_ms=link.previous_received_nanos / 1e6 if link.previous_received_nanos else None,
        )
        self.last_sizes[self._bucket(payload_bytes)] = self._clock()

    def _link_ms(self, k: int, tags: int) -> float:
        """The link time the model predicts now for a frame of `tags` tags at cut k."""
        size_kB = features_payload_bytes(tags, k, self.settings.codec) / 1024.0
        return self.link.t0_ms + self.link.beta_ms_per_kB * size_kB

    def add_measured(self, k: int, frame_ms: float, tags: int) -> None:
        """A frame of `tags` tags posed at cut k took frame_ms of robot compute + link + edge compute (what
        T(k) predicts). Frames without tags say nothing of the network's cost: left out."""
        if 0 <= k < N_CUTS and tags > 0 and math.isfinite(frame_ms) and frame_ms > 0:
            self.measured[k].append((self._clock(), frame_ms, tags, self._link_ms(k, tags)))

    def add_posed(self, k: int, capture_nanos: int) -> None:
        """A frame posed at cut k, with or without tags (in the order the poses arrive): what each cut
        achieves."""
        self.achieved.add(k, capture_nanos)

    def add_on_board(self, *, edge_alive: bool) -> None:
        """robot_infer posed a frame on board. With the edge's liveliness token there, an answer at the
        cut in use was overdue (its link or edge too slow for it): that cut missed the frame
        (AchievedIntervals.missed). Without it the edge is gone: a pause, not the cut's rate."""
        if edge_alive:
            self.achieved.missed()
        else:
            self.edge_gone()

    def edge_gone(self) -> None:
        """edge_infer's liveliness token went: the stream pauses (the frames it misses are no cut's)."""
        self.achieved.pause()

    def measured_ms(self, k: int, *, min_frames: int = 3) -> float | None:
        """The median measured time at cut k of frames with as many tags as the prediction is for, within
        the window, measured on the link the model predicts now (None: too few such frames).

        A frame is compared while the link time the model predicted for it then is within the chooser's
        smallest gain of what it predicts now (max(min_gain_ms, min_gain_rel of it)): once the link has
        changed, a frame timed on the old one says nothing of the cut. Before, every frame measured before
        the last alarm of the change detector was dropped, and under CPU load the detector fired on a
        steady link every 15 s or so: the veto rarely had its frames (a trial: 11 switches in 97 s, none
        vetoed)."""
        start = self._clock() - self.settings.measured_window_secs
        tags = self.tags()
        now = self._link_ms(k, tags)
        tolerance = max(self.settings.min_gain_ms, self.settings.min_gain_rel * now)
        recent = [
            ms for t, ms, n, then in self.measured[k] if n == tags and t >= start and abs(then - now) <= tolerance
        ]
        return float(np.median(recent)) if len(recent) >= min_frames else None

    def frame_sent(self, msg: FrameSent) -> None:
        """robot_infer put a frame on the uplink: the link is busy for about beta * size from then."""
        self.occupancy.sent(
            sent_ms=msg.sent_nanos / 1e6, size_kB=msg.payload_bytes / 1024.0, beta_ms_per_kB=self.link.beta_ms_per_kB
        )

    def link_idle(self, now_nanos: int, *, guard_ms: float = 2.0) -> bool:
        """True when every frame sent so far should have left the robot (a probe now waits for none)."""
        return self.occupancy.idle(now_nanos / 1e6, guard_ms=guard_ms)

    def add_compute(self, profile: ComputeProfile) -> None:
        """The latest ComputeProfile of either side."""
        if profile.side == "robot":
            self.robot = profile
            # a restarted robot_infer says none for its first frames: the camera has not changed for that
            ms = profile.frame_interval_ms
            if ms is not None and ms > 0:
                self.camera_interval_ms = ms
                # what the cuts achieved at another camera rate says nothing of this one (a webcam that
                # slows in the dark and recovers): forgotten when the rate moves by more than 15 %
                then = self._achieved_at_ms
                if then is None or abs(ms - then) > 0.15 * then:
                    self.achieved.clear()
                    self._achieved_at_ms = ms
        else:
            self.edge = profile

    @staticmethod
    def _bucket(payload_bytes: int) -> int:
        return int(np.log2(max(payload_bytes, 1024) / 1024.0))

    def probe_size_due(self, candidates: list[int], max_age_secs: float) -> int | None:
        """The candidate probe size whose neighbourhood (log2 kB bucket) was seen longest ago, if that
        is more than max_age_secs ago. Sizes alternate, so t0 and beta stay identifiable whatever the
        frames carry, and a rate change shows up in the large probes within a period or two."""
        now = self._clock()
        age, size = max((now - self.last_sizes.get(self._bucket(c), -1e9), c) for c in candidates)
        return size if age >= max_age_secs else None

    # -- decision ----------------------------------------------------------------------------------
    def tags(self) -> int:
        """Tags per frame the prediction is for (robot's running median, at least 1)."""
        n = self.robot.tags_per_frame if self.robot else 1.0
        return max(1, round(n))

    def payload_kB(self) -> list[float]:
        """S(k) for the current tag count."""
        n = self.tags()
        return [features_payload_bytes(n, k, self.settings.codec) / 1024.0 for k in range(N_CUTS)]

    def predict(self) -> np.ndarray | None:
        """T(k) for every k, or None while a compute profile is missing."""
        if self.robot is None or self.edge is None:
            return None
        return split_costs(
            compute_ms=self.robot.ms_by_k,  # gamma is already in the robot's profile
            edge_ms=self.edge.ms_by_k,
            payload_kB=self.payload_kB(),
            t0_ms=self.link.t0_ms,
            beta_ms_per_kB=self.link.beta_ms_per_kB,
        )

    def frame_interval_ms(self) -> float | None:
        """The camera's frame interval from its stamps, as robot_infer's profile last said (None: never)."""
        return self.camera_interval_ms

    def periods(self) -> np.ndarray | None:
        """The time between frames each cut needs: the uplink's (beta S(k): t0 delays but does not occupy
        it) and, with compute_keeps_up, the slower side's, or None while a compute profile is missing. A
        side whose profile predates periods is taken to overlap nothing (its ms per frame)."""
        if self.robot is None or self.edge is None:
            return None
        link = self.link.beta_ms_per_kB * np.asarray(self.payload_kB(), np.float64)
        if not self.settings.compute_keeps_up:
            return link
        robot = np.asarray(self.robot.period_ms_by_k or self.robot.ms_by_k, np.float64)
        edge = np.asarray(self.edge.period_ms_by_k or self.edge.ms_by_k, np.float64)
        return np.maximum.reduce([robot, edge, link])

    def achieved_ms(self) -> list[float | None]:
        """What each cut achieved lately between frames (None where it has not run for a while)."""
        return [self.achieved.interval_ms(k) for k in range(N_CUTS)]

    def frame_shares(self, periods: np.ndarray | None, achieved: list[float | None]) -> np.ndarray | None:
        """The share of the camera's frames each cut is expected to pose, at most 1: interval / what it
        achieved where it ran lately; elsewhere interval / its period, times how much longer than its
        period the nearest cut that fell behind the camera took (never less: evidence only corrects the
        model's optimism) and UNTRIED_MARGIN (an untried cut must beat the bar by a margin to be
        believed). None: not checked, for want of the camera's rate or with min_frame_share 0.

        Uncorrected, the model's periods on one 2-core box were 1.1-1.7x short of what the cuts achieved
        (the robot's look-ahead overlaps less than modelled beside the edge), each cut not yet tried
        looked best in turn, and the controller toured all eight within seconds, once ending at k = 2
        (2 MB a frame, the slowest but one by T(k)). The nearest cut, because neighbours share their
        bottleneck (k = 0 the edge's, the later cuts the robot's)."""
        interval = self.frame_interval_ms()
        if periods is None or interval is None or self.settings.min_frame_share <= 0:
            return None
        # Only a cut that fell behind the camera tells how long its frames really take; one that kept up
        # achieved the camera's interval, whatever its period (a 2.5 fps camera's 400 ms against k = 0's
        # 100: taken as a ratio, every other cut was doubted 4x and the controller stayed at k = 0 on a
        # slower link, where k = 7 was faster: bench.controller "reach never")
        ran = [k for k, a in enumerate(achieved) if a is not None and interval / a < self.settings.min_frame_share]
        margin = self.UNTRIED_MARGIN
        expected = []
        for k, (period, got) in enumerate(zip(periods, achieved, strict=True)):
            if got is not None:
                expected.append(got)
                continue
            ratio = 1.0
            near = min((abs(j - k) for j in ran), default=N_CUTS)
            if near <= self.DOUBT_REACH:  # the nearest cut that fell behind (of two, the one further behind)
                ratios = [
                    got_j / periods[j] for j in ran if abs(j - k) == near and (got_j := achieved[j]) and periods[j] > 0
                ]
                ratio = min(max(ratios, default=1.0), self.MAX_DOUBT)
            expected.append(max(1.0, ratio) * margin * period)
        return np.minimum(1.0, interval / np.maximum(np.asarray(expected, np.float64), 1e-6))

    def min_share(self, shares: np.ndarray, achieved: list[float | None]) -> float:
        """The share a cut must reach to count: min_frame_share where some cut gets there (by what it
        achieved, or if it has not run lately by its period); where none does, the best share a cut
        achieved, less throughput_slack_rel of it. Only achieved shares set that lower bar: the model's
        are optimistic where robot and edge share cores, and every cut it overrated would be tried in
        turn (a trial's controller went to k = 1, the slowest by T(k), for 4 MB a frame at 4 fps); a cut
        not tried lately is tried when its period promises at least that bar and its T(k) is the least.

        Between the two the bar ramps down over BAR_RAMP of the best share, never above it: a jump from
        0.9 to 0.8 x the best when the best fell from 0.91 to 0.89 made a cut at 0.76 eligible at once,
        and the controller left the one at 0.89 for it on latency (found in review)."""
        floor = self.settings.min_frame_share
        top = float(shares.max())
        if top >= floor:
            return floor
        ran = [float(v) for v, got in zip(shares, achieved, strict=True) if got is not None]
        low = (1 - self.settings.throughput_slack_rel) * max(ran or [top])
        ramp = min(1.0, (floor - top) / self.BAR_RAMP)
        return min(top, floor - ramp * (floor - low))

    def eligible(self, shares: np.ndarray, limit: float, current_k: int) -> np.ndarray:
        """The cuts that keep up; the cut in use down to frame_share_hysteresis below the limit."""
        ok = shares >= limit
        ok[current_k] |= bool(shares[current_k] >= limit - self.settings.frame_share_hysteresis)
        return ok

    def switched(self, from_k: int, to_k: int) -> None:
        """The split went from_k -> to_k as decided (the caller's apply succeeded): what the ping-pong hold
        reads. Decided switches that were not applied (the controller off, a pin meanwhile) count for
        nothing (review)."""
        if to_k != from_k:
            self._switches.append((self._clock(), from_k, to_k, self.link.changes))
            if self._forced_switch == (from_k, to_k):  # left because it could not keep up
                self._fell_behind[from_k] = (self._clock(), self.link.changes)

    def _short_of_held_gain(self, t: np.ndarray, current_k: int, chosen: int) -> tuple[float, float] | None:
        """(the gain a held switch needs, the predicted gain) when the switch falls short of it, else None."""
        usual = max(self.settings.min_gain_ms, self.settings.min_gain_rel * float(t[current_k]))
        needed = self.settings.reversal_gain_factor * usual
        gain = float(t[current_k] - t[chosen])
        return None if gain > needed else (needed, gain)

    def _reversal_hold(self, t: np.ndarray, current_k: int, chosen: int) -> str | None:
        """Why a switch is held as ping-pong (None: it is not): the last two switches were `current_k` ->
        `chosen` -> `current_k`, the first less than reversal_hold_secs ago, on the same link, and this
        one would go to `chosen` a second time for less than reversal_gain_factor x the usual gain."""
        hold = self.settings.reversal_hold_secs
        if hold <= 0 or len(self._switches) < 2:
            return None
        (first_at, a, b, changes), (_, b2, a2, changes2) = self._switches
        if not (a == current_k == a2 and b == chosen == b2):
            return None
        ago = self._clock() - first_at
        if ago >= hold or not changes == changes2 == self.link.changes:
            return None
        if (held := self._short_of_held_gain(t, current_k, chosen)) is None:
            return None
        needed, gain = held
        return (
            f"keep k={current_k}: to k={chosen} a second time in {ago:.1f} s needs {needed:.1f} ms (ping-pong, "
            f"for {hold:g} s); predicted {gain:.1f} ms faster"
        )

    def _fell_behind_hold(self, t: np.ndarray, current_k: int, chosen: int) -> str | None:
        """Why a switch for latency back to a cut left less than reversal_hold_secs ago because it could
        not keep up is held (None: it is not). Where no cut keeps up, the bar moves with the shares each
        decision: a two-host trial's controller went 7 -> 5 (k = 7 'cannot keep up', 72 % of the frames,
        90 % needed) -> 7 ('22 ms faster') -> 5 within 0.8 s, 10-16 switches a run on a link that never
        changed. A link change lifts it; so does reversal_gain_factor x the usual gain."""
        hold = self.settings.reversal_hold_secs
        left = self._fell_behind.get(chosen)
        if hold <= 0 or left is None:
            return None
        ago = self._clock() - left[0]
        if ago >= hold or left[1] != self.link.changes:
            return None
        if (held := self._short_of_held_gain(t, current_k, chosen)) is None:
            return None
        needed, gain = held
        return (
            f"keep k={current_k}: k={chosen} fell behind the camera {ago:.1f} s ago (held for {hold:g} s unless "
            f"{needed:.1f} ms faster); predicted {gain:.1f} ms faster"
        )

    def decide(self, *, robot_id: str, current_k: int, pinned: bool) -> ControllerState:
        """One decision; the caller applies chosen_k when it differs from current_k (and says so)."""
        t = self.predict()
        periods = self.periods()
        achieved = self.achieved_ms()
        shares = self.frame_shares(periods, achieved)
        limit = None if shares is None else self.min_share(shares, achieved)
        ok = None if shares is None or limit is None else self.eligible(shares, limit, current_k)
        zeros = [0.0] * N_CUTS
        if t is None:
            chosen, best, reason, pred = current_k, current_k, CONTROLLER_WAITING, zeros
        elif pinned:
            best = int(np.argmin(t if ok is None else np.where(ok, t, np.inf)))
            chosen, reason, pred = current_k, f"pinned at k={current_k} by a user (best would be k={best})", list(t)
        else:
            d = self.chooser.choose(t, current_k, ok)
            chosen, best, reason, pred = d.k, d.best_k, d.reason, list(d.predicted_ms)
            forced = ok is not None and not ok[current_k]
            if forced and shares is not None and limit is not None and periods is not None:
                got = achieved[current_k]
                how = (
                    f"ran at {got:.0f} ms a frame" if got is not None else f"needs {periods[current_k]:.0f} ms a frame"
                )
                reason += (
                    f" (k={current_k} cannot keep up: {how} at {self.frame_interval_ms():.0f} ms between frames, "
                    f"{shares[current_k]:.0%} of them, {limit:.0%} needed)"
                )
            elif ok is not None and not ok.all():
                slow = ", ".join(f"{k}" for k in np.flatnonzero(~ok))
                reason += f"; cannot keep up: k={slow}"
            if chosen != current_k and not forced and self.settings.measured_window_secs > 0:
                there, here = self.measured_ms(chosen), self.measured_ms(current_k)
                if there is not None and here is not None and there >= here:
                    self.vetoed += 1
                    gain = float(t[current_k] - t[chosen])
                    reason = (
                        f"keep k={current_k}: k={chosen} predicted {gain:.1f} ms faster, but its frames took "
                        f"{there:.0f} ms against {here:.0f} ms here (last {self.settings.measured_window_secs:g} s)"
                    )
                    chosen = current_k
            if chosen != current_k and not forced:
                hold = self._reversal_hold(t, current_k, chosen) or self._fell_behind_hold(t, current_k, chosen)
                if hold is not None:
                    self.held += 1
                    reason, chosen = hold, current_k
            self._forced_switch = (current_k, chosen) if forced and chosen != current_k else None
        return ControllerState(
            robot_id=robot_id,
            stamp_nanos=time.time_ns(),
            t0_ms=self.link.t0_ms,
            beta_ms_per_kB=self.link.beta_ms_per_kB,
            link_samples=self.link.n,
            link_changes=self.link.changes,
            robot_ms_by_k=list(self.robot.ms_by_k) if self.robot else zeros,
            edge_ms_by_k=list(self.edge.ms_by_k) if self.edge else zeros,
            payload_kB_by_k=self.payload_kB(),
            predicted_ms_by_k=[max(0.0, float(v)) for v in pred],
            current_k=current_k,
            best_k=best,
            chosen_k=chosen,
            pinned=pinned,
            applied=False,
            reason=reason,
            period_ms_by_k=None if periods is None else [max(0.0, float(v)) for v in periods],
            achieved_ms_by_k=None if t is None else achieved,
            frame_interval_ms=self.frame_interval_ms(),
            frame_share_by_k=None if shares is None else [float(v) for v in shares],
            min_frame_share=limit,
        )
