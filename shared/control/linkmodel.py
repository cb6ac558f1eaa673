"""Link model RTT = t0 + beta * S and the split cost T(k) = gamma C(k) + t0 + beta S(k) + E(k).

Pure functions and small classes: the controller service and `splittag link ...` wire them to data.
Units: milliseconds and kilobytes (1 kB = 1024 bytes, as the paper's table).
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

FLOOR_BELOW_KB = 32.0  # the paper: payloads below ~32 kB see the same latency (scheduling floor)


@dataclass(frozen=True)
class LinkFit:
    """A least-squares fit of RTT against payload size."""

    t0_ms: float  # fitted intercept
    beta_ms_per_kB: float
    floor_ms: float  # measured: median RTT of the payloads below FLOOR_BELOW_KB (or of the smallest)
    rmse_ms: float
    n: int


def fit_link(sizes_kB: Sequence[float], rtts_ms: Sequence[float]) -> LinkFit:
    """Fit RTT = t0 + beta * S by least squares over each payload size's median RTT (a probe repeats
    each size: one round trip held up by the host, 38 ms late at 1 MiB in one run, moved an all-samples
    fit's beta by 20 %); report the measured floor, and the RMSE over all samples, too."""
    s = np.asarray(sizes_kB, np.float64)
    r = np.asarray(rtts_ms, np.float64)
    if len(s) != len(r) or len(s) < 2 or np.ptp(s) == 0:
        raise ValueError("need >= 2 samples at >= 2 different payload sizes")
    sizes = np.unique(s)
    medians = np.array([np.median(r[s == size]) for size in sizes])
    (t0, beta), *_ = np.linalg.lstsq(np.column_stack([np.ones_like(sizes), sizes]), medians, rcond=None)
    a = np.column_stack([np.ones_like(s), s])
    small = r[s < FLOOR_BELOW_KB]
    floor = float(np.median(small)) if len(small) else float(np.median(r[s == s.min()]))
    rmse = float(np.sqrt(np.mean((a @ np.array([t0, beta]) - r) ** 2)))
    return LinkFit(float(t0), float(beta), floor, rmse, len(s))


def _capped(p: np.ndarray, variances: tuple[float, float]) -> np.ndarray:
    """P with each variance at most `variances`' (its row and column scaled together: P stays positive
    definite)."""
    cap = np.sqrt(np.minimum(1.0, np.asarray(variances) / np.maximum(np.diag(p), 1e-300)))
    return p * np.outer(cap, cap)


class OnlineLinkEstimator:
    """Robust recursive least squares for the uplink's floor t0 and slope beta, with forgetting.

    The link is a FIFO pipe: a message of S kB sent at p (sender clock) starts crossing once the
    message ahead of it has arrived, so it arrives at

        a = max(p + t0, a_prev) + beta * S        (a, a_prev: receiver clock)

    where a_prev is the arrival of the message just ahead of it on the same link (any kind: frames
    and probes share the uplink). An idle link (p + t0 >= a_prev) gives a sample of t0 + beta S from
    a - p; a busy one only of beta S from a - a_prev, because the floor overlapped with the message
    ahead. The time a message waited behind others is therefore never read as floor latency
    (`add_crossing`). Which case a sample is in is decided with the current t0 estimate. A clock
    offset between sender and receiver enters t0, the same for every sample. `add` takes a plain
    (size, latency) sample of a message that found the link idle (a probe's round trip).

    Samples whose residual exceeds `gate` robust standard deviations are down-weighted (Huber);
    a two-sided CUSUM on the clamped, normalised residuals raises an alarm. The CUSUM normalises by
    the robust scale but never by less than `change_floor_ms`: on a quiet link the scale falls below a
    millisecond, and shifts that no decision could notice then raised alarms (a simulated steady 5g link:
    7 alarms in 170 s, each a reset). While only busy samples
    arrive t0 is unobserved: its variance grows with the forgetting but is capped at the prior's.

    An alarm is a question, not an answer: it starts a **challenger**, a fit that forgot everything
    (covariance reset) and was fitted to the samples that raised the alarm, beside the current fit,
    which goes on as before. Both predict each following sample before fusing it (squared errors in
    robust scales, the scale no less than `change_floor_ms` as for the CUSUM, each clipped at
    `challenge_clip`). The challenger takes over (`changes` rises) once
    it has predicted two samples clearly better (by 3) and leads by `challenge_margin` (27), or one
    sample and leads by 64 (a miss of 8 scales that it explains: a change to 5g-pre-tdd does that at
    64 kB on a quiet link). It is dropped (`dismissed`) once it trails by the margin while the current
    fit explains the latest sample, or after `challenge_samples` samples. It fuses its first samples at
    full weight, as a first fit does. While one is pending `alarm_level` is 1, and the controller probes
    every size at the alarm and then the largest at once, which settles it. Before, every alarm reset
    the fit at once: under CPU load the receiver stamps some messages late (a trial on this 2-core
    machine: ~11 alarms in 170 s on a steady link), and in ten simulated minutes with a fifth of the
    stamps late by an exponential 20 ms (`tests/linksim.py`, seeds 0-5, k = 0, 7 and both) the detector
    fired 40-79 times a run, and right after each reset one late sample carried the fit (beta 0.0-8.2
    ms/kB on a 0.18 link, more than 25 % off in 2.7-22 % of the samples). Now 0-3 changes are taken a
    run (11 in the 18; 34-68 alarms dismissed), beta is more than 25 % off in 0-7.8 % of the samples
    and reads 0.0-0.62, but for one run where four late stamps in a row won and carried it to 2.66.
    """

    RESET_VARIANCE = (400.0, 0.25)  # after a change: t0 within ~20 ms, beta within ~0.5 ms/kB
    BUNCHED_FRACTION = 0.2  # a busy sample under this fraction of beta S was stamped late, not carried fast
    PRIOR_VARIANCE = (1e4, 1.0)
    RUN_SAMPLES = 16  # an alarm's challenger is fitted to at most this many of its latest samples
    CHALLENGE_WINS = 2  # samples a challenger must predict clearly better to take over ...
    CHALLENGE_WIN = 3.0  # ... by this much of squared error, in robust scales squared
    CHALLENGE_STRONG = 64.0  # ... or one such sample, when the lead is this large (a miss of 8 scales)
    TAKEOVER_LOOSEN = 25.0  # a challenger that takes over is believed 5x less (in sigma) than it claims
    CHALLENGE_FRESH = 10  # a challenger fuses its replayed samples and its next 9 at full weight

    def __init__(
        self,
        *,
        half_life: float = 50.0,
        gate: float = 3.0,
        cusum_drift: float = 0.5,
        cusum_threshold: float = 8.0,
        change_floor_ms: float = 2.0,
        challenge_margin: float = 27.0,
        challenge_clip: float = 100.0,
        challenge_samples: int = 30,
        prior_t0_ms: float = 40.0,
        prior_beta: float = 0.2,
    ) -> None:
        self.lam = 0.5 ** (1.0 / half_life)
        self.gate = gate
        self.drift, self.threshold = cusum_drift, cusum_threshold
        self.change_floor_ms = change_floor_ms
        self.challenge_margin, self.challenge_clip = challenge_margin, challenge_clip
        self.challenge_samples = challenge_samples
        self.theta = np.array([prior_t0_ms, prior_beta])
        self.p = np.diag(list(self.PRIOR_VARIANCE))
        self.scale = 5.0  # robust residual scale, ms
        self.n = 0
        self.busy = 0  # samples that crossed a busy link
        self.bunched = 0  # busy samples left out: stamped at once by a stalled receiver
        # the last crossing fused (its receipt stamp, the state before it): undone when a message
        # bunched behind it shows that it was stamped at a stall's end
        self._last_fused: tuple[float, tuple[Any, ...]] | None = None
        self._burst_heads: deque[float] = deque(maxlen=32)  # stamps at a stall's end not yet seen
        self._g_pos = self._g_neg = 0.0
        # the pending challenger after an alarm: (theta, P, samples since, clear wins, current fit's and
        # its own clipped squared errors on them, in robust scales, its alarm's number)
        self._challenger: tuple[np.ndarray, np.ndarray, int, int, float, float, int] | None = None
        self._counted = 0  # the last alarm counted as a change or dismissed (each is counted once)
        # the samples each side of the CUSUM has summed since it was last at zero: an alarm's evidence,
        # replayed into its challenger (which then predicts from the first sample after the alarm)
        self._runs: tuple[list[tuple[np.ndarray, float]], list[tuple[np.ndarray, float]]] = ([], [])
        # Counters only ever rise, and each alarm ends up in exactly one of `changes` and `dismissed` (or is
        # pending): a stall's rollback that undoes a take-over or a dismissal does not count it again, and
        # one that undoes the alarm itself counts it dismissed.
        self.alarms = 0  # alarms raised, each a challenger
        self.changes = 0  # alarms whose challenger took over: link changes
        self.dismissed = 0  # alarms whose challenger did not predict better (or was undone): no change
        self.resets = 0  # covariances found no longer positive definite and reset (rounding; never seen)

    def add(self, size_kB: float, rtt_ms: float) -> None:
        """Fuse a (payload, latency) sample of a message that found the link idle."""
        if not (math.isfinite(size_kB) and math.isfinite(rtt_ms)) or size_kB < 0 or rtt_ms <= 0:
            return
        self._last_fused = None
        self._fuse(np.array([1.0, size_kB]), rtt_ms)

    def add_crossing(
        self, *, size_kB: float, sent_ms: float, received_ms: float, previous_received_ms: float | None
    ) -> None:
        """Fuse one message's crossing of the link: sent at sent_ms (sender clock), received at
        received_ms, the message ahead of it received at previous_received_ms (receiver clock; None
        when unknown). See the class docstring for the model."""
        values = (size_kB, sent_ms, received_ms, 0.0 if previous_received_ms is None else previous_received_ms)
        if not all(math.isfinite(v) for v in values) or size_kB < 0:
            return
        if received_ms in self._burst_heads:
            self.bunched += 1  # (stamped at a stall's end: a message bunched behind it came in first)
            return
        if previous_received_ms is not None and received_ms <= previous_received_ms:
            return  # out of order: not a FIFO crossing we can explain
        gap = math.inf if previous_received_ms is None else received_ms - previous_received_ms
        if gap < self.BUNCHED_FRACTION * self.beta_ms_per_kB * size_kB:
            # On a FIFO link a message arrives at least beta S after the one ahead of it, whether it
            # queued or not. Stamped far sooner, it was not carried that fast: the receiver was stalled
            # (no CPU) and stamped what had arrived meanwhile at once, the message ahead included (its
            # latency is the stall's). Neither is the link (a trial's 1.5 s stall read as t0 0 ms and
            # beta 1.54 ms/kB, and switched the split there and back): this one is left out, and so is
            # the message ahead: its update undone when it was the last one fused, or refused when it
            # comes (a probe's answer comes before the poses of the frame ahead of it). A link that did
            # become this much faster shows it in its idle samples.
            self.bunched += 1
            if self._last_fused is not None and self._last_fused[0] == previous_received_ms:
                self._restore(self._last_fused[1])
                self._last_fused = None
            elif previous_received_ms is not None:
                self._burst_heads.append(previous_received_ms)
            return
        if previous_received_ms is not None and previous_received_ms > sent_ms + self.t0_ms:
            self._last_fused = (received_ms, self._snapshot())
            self.busy += 1
            self._fuse(np.array([0.0, size_kB]), gap)
        elif received_ms > sent_ms:
            self._last_fused = (received_ms, self._snapshot())
            self._fuse(np.array([1.0, size_kB]), received_ms - sent_ms)

    def _snapshot(self) -> tuple[Any, ...]:
        ch = self._challenger
        ch = None if ch is None else (ch[0].copy(), ch[1].copy(), *ch[2:])
        runs = (list(self._runs[0]), list(self._runs[1]))
        return (self.theta.copy(), self.p.copy(), self.scale, self.n, self.busy, self._g_pos, self._g_neg, ch, runs)

    def _restore(self, state: tuple[Any, ...]) -> None:
        # (`alarms`, `changes` and `dismissed` stay: they count, and readers act on each rise once)
        theta, p, self.scale, self.n, self.busy, self._g_pos, self._g_neg, ch, runs = state
        self.theta, self.p = theta.copy(), p.copy()
        self._runs = (list(runs[0]), list(runs[1]))
        if self._challenger is not None and ch is None:  # the alarm itself was undone
            self._count(self._challenger[6], changed=False)
        self._challenger = None if ch is None else (ch[0].copy(), ch[1].copy(), *ch[2:])

    def _count(self, alarm: int, *, changed: bool) -> None:
        if alarm > self._counted:
            self._counted = alarm
            if changed:
                self.changes += 1
            else:
                self.dismissed += 1

    def _fuse(self, x: np.ndarray, y_ms: float) -> None:
        resid = y_ms - float(x @ self.theta)
        scale = max(self.scale, self.change_floor_ms, 1e-3)
        alarm = False
        if self._challenger is not None:
            if self._challenge(x, y_ms, resid, scale):
                return
        elif self.n >= 10:
            zc = max(-self.gate, min(self.gate, resid / scale))
            self._g_pos = max(0.0, self._g_pos + zc - self.drift)
            self._g_neg = max(0.0, self._g_neg - zc - self.drift)
            for g, run, push in zip((self._g_pos, self._g_neg), self._runs, (zc, -zc), strict=True):
                if g <= 0.0:
                    run.clear()
                elif push > self.drift:  # (a sample that raised it: one the link as it was does not explain)
                    run.append((x, y_ms))
                    del run[: -self.RUN_SAMPLES]
            if max(self._g_pos, self._g_neg) > self.threshold:
                alarm = True
        if alarm:  # a fit that forgot everything, fitted to the alarm's samples, challenges the current one
            theta, p = self.theta, np.diag(list(self.RESET_VARIANCE))
            for xs, ys in self._runs[0 if self._g_pos >= self._g_neg else 1]:
                theta, p = self._step(theta, p, xs, ys - float(xs @ theta), 1.0)
            self.alarms += 1
            self._challenger = (theta, p, 0, 0, 0.0, 0.0, self.alarms)
            self._g_pos = self._g_neg = 0.0
            self._runs = ([], [])
        self.theta, self.p = self._step(self.theta, self.p, x, resid, self._huber(resid))
        self._update_scale(resid)

    def _challenge(self, x: np.ndarray, y_ms: float, resid: float, scale: float) -> bool:
        """Score both fits on this sample (before either fuses it), fuse it into the challenger, and
        decide: True when the challenger took over (it has fused the sample for both)."""
        assert self._challenger is not None
        theta, p, n, wins, err_current, err_challenger, alarm = self._challenger
        resid_c = y_ms - float(x @ theta)
        current = min((resid / scale) ** 2, self.challenge_clip)
        challenger = min((resid_c / scale) ** 2, self.challenge_clip)
        err_current, err_challenger = err_current + current, err_challenger + challenger
        wins += current - challenger >= self.CHALLENGE_WIN  # (a sample it predicts clearly better)
        # (a fresh fit: not down-weighted by the scale of residuals about the other fit until it has seen
        # as many samples as a first fit is given; a bench run's challenger crept towards the new link
        # for seven samples and took over half-way, t0 45.8 ms, beta 0.31 on a 39.9 / 0.577 link)
        weight = 1.0 if n + 1 < self.CHALLENGE_FRESH else self._huber(resid_c)
        theta, p = self._step(theta, p, x, resid_c, weight)
        lead = err_current - err_challenger
        if (wins >= self.CHALLENGE_WINS and lead >= self.challenge_margin) or (wins and lead >= self.CHALLENGE_STRONG):
            # The challenger's estimate, with a looser covariance than its own: it has seen a few samples,
            # some of them from across the change, and its own covariance held on to them (a CI run's
            # controller ended the 9 s after a change back to 5g at beta 0.43 ms/kB; reset outright, one
            # late stamp after a take-over that late stamps had won carried beta to 2.7 in a simulation)
            self.theta, self.p, self._challenger = theta, self._loosened(p), None
            self._count(alarm, changed=True)
            self._update_scale(resid_c)
            return True
        # Dismissed when it trails by as much and the current fit explains the latest sample: right after
        # a change neither fit may predict well yet (a challenger fitted to four samples can mistake a
        # steeper slope for a higher floor), and the current one must not win by being less wrong.
        behind = err_challenger - err_current >= self.challenge_margin and current <= self.gate**2
        if behind or n + 1 >= self.challenge_samples:
            self._challenger = None  # late stamps, not the link: the current fit stands
            self._count(alarm, changed=False)
        else:
            self._challenger = (theta, p, n + 1, wins, err_current, err_challenger, alarm)
        return False

    def _loosened(self, p: np.ndarray) -> np.ndarray:
        """A covariance TAKEOVER_LOOSEN times wider, no variance above the reset's."""
        return _capped(p * self.TAKEOVER_LOOSEN, self.RESET_VARIANCE)

    def _huber(self, resid: float) -> float:
        z = abs(resid) / max(self.scale, 1e-3)
        return 1.0 if z <= self.gate or self.n < 10 else self.gate / z

    def _update_scale(self, resid: float) -> None:
        self.scale = 0.95 * self.scale + 0.05 * min(abs(resid), 5 * self.scale) * 1.25
        self.n += 1

    def _step(
        self, theta: np.ndarray, p: np.ndarray, x: np.ndarray, resid: float, weight: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """One weighted recursive least squares update with forgetting: the new (theta, P)."""
        px = p @ x
        k = weight * px / (self.lam + weight * float(x @ px))
        # A link has no negative floor or slope: clamping keeps a half-re-fitted estimate physical
        # (a negative beta would make the biggest payload look cheapest for a moment). The other
        # parameter then carries what the update fitted at this sample: clamped alone, a run of one
        # payload size (robot_infer's frames at one k; the fit's two parameters then seen only as
        # t0 + beta S) walked t0 from 0 to 1500 ms while every sample said 5 (tests/test_linkmodel.py).
        new = theta + k * resid
        if new.min() < 0.0:
            fitted = float(x @ new)
            new = np.maximum(new, 0.0)
            carriers = [i for i in range(2) if new[i] > 0.0 and x[i] > 0.0]
            if carriers:
                i = carriers[0]
                new[i] = max(0.0, new[i] + (fitted - float(x @ new)) / x[i])
        p = (p - np.outer(k, px)) / self.lam
        # Kept symmetric by hand: the update is symmetric only in exact arithmetic, and the rounding's
        # antisymmetric part grows by 1 / lam a sample in the directions no sample excites (tenfold every
        # 133 samples at the controller's half-life of 40). On a steady simulated 5g link P turned
        # indefinite after ~1500 samples (2.5 min) and the fit leapt to t0 0 ms, beta 7.5 ms/kB, where the
        # stall check then refused nearly every frame: stuck (a trial saw beta 1.65 on a 0.18 link). Only
        # the change detector's resets had hidden it.
        p = 0.5 * (p + p.T)
        if not (p[0, 0] > 0.0 and p[1, 1] > 0.0 and p[0, 0] * p[1, 1] > p[0, 1] * p[1, 0]):
            self.resets += 1  # (not seen with the symmetric update; a guard, counted)
            p = np.diag(list(self.RESET_VARIANCE))
        return new, _capped(p, self.PRIOR_VARIANCE)

    @property
    def judging(self) -> bool:
        """An alarm's challenger is pending (alarms = changes + dismissed + this)."""
        return self._challenger is not None

    @property
    def alarm_level(self) -> float:
        """How close the change detector is to firing: 0 (quiet) .. 1 (at its threshold, or fired: a
        challenger is pending)."""
        if self.judging:
            return 1.0
        return max(self._g_pos, self._g_neg) / self.threshold

    @property
    def t0_ms(self) -> float:
        """Current intercept estimate."""
        return float(self.theta[0])

    @property
    def beta_ms_per_kB(self) -> float:
        """Current slope estimate."""
        return float(self.theta[1])


def split_costs(
    *,
    compute_ms: ArrayLike,
    edge_ms: ArrayLike,
    payload_kB: ArrayLike,
    t0_ms: float,
    beta_ms_per_kB: float,
    gamma: float = 1.0,
) -> np.ndarray:
    """T(k) = gamma C(k) + t0 + beta S(k) + E(k) for every split point."""
    c, e, s = (np.asarray(v, np.float64) for v in (compute_ms, edge_ms, payload_kB))
    return gamma * c + t0_ms + beta_ms_per_kB * s + e


@dataclass(frozen=True)
class Decision:
    """What the controller chose and why."""

    k: int
    best_k: int
    predicted_ms: tuple[float, ...]
    reason: str


class HysteresisChooser:
    """argmin T(k), switching only when the best beats the current k by more than
    max(min_gain_ms, min_gain_rel * T(current)) for `dwell` consecutive decisions."""

    def __init__(self, *, min_gain_ms: float = 2.0, min_gain_rel: float = 0.05, dwell: int = 3) -> None:
        self.min_gain_ms, self.min_gain_rel, self.dwell = min_gain_ms, min_gain_rel, dwell
        self._streak = 0
        self._candidate: int | None = None

    def choose(self, costs: ArrayLike, current: int, eligible: ArrayLike | None = None) -> Decision:
        """One decision given the predicted T(k) and the k in effect, among the `eligible` cuts (all by
        default). From a cut that is not eligible any eligible one is a gain (the dwell still applies)."""
        t = np.asarray(costs, np.float64)
        ok = np.ones(t.shape, bool) if eligible is None else np.asarray(eligible, bool)
        if not ok.any():  # (not from the controller's shares; a NaN somewhere): latency alone
            ok = np.ones(t.shape, bool)
        best = int(np.argmin(np.where(ok, t, np.inf)))
        forced = not ok[current]
        gain = float(t[current] - t[best])
        needed = -np.inf if forced else max(self.min_gain_ms, self.min_gain_rel * float(t[current]))
        pred = tuple(float(v) for v in t)
        if best == current or gain <= needed:
            self._streak, self._candidate = 0, None
            why = "already optimal" if best == current else f"gain {gain:.1f} ms <= {needed:.1f} ms"
            return Decision(current, best, pred, f"keep k={current}: {why}")
        self._streak = self._streak + 1 if self._candidate == best else 1
        self._candidate = best
        better = "is eligible" if forced else f"better by {gain:.1f} ms"
        if self._streak < self.dwell:
            return Decision(current, best, pred, f"keep k={current}: k={best} {better} ({self._streak}/{self.dwell})")
        self._streak, self._candidate = 0, None
        why = "the fastest eligible cut" if forced else f"predicted {gain:.1f} ms faster"
        return Decision(best, best, pred, f"switch k={current}->{best}: {why}")


class LinkOccupancy:
    """Sender side: when the uplink will have sent everything put on it, predicted from the send times
    and sizes of the messages and the current beta (the floor delays bytes but does not occupy the
    sender). Lets a prober wait for an idle link instead of queueing behind, or delaying, frames."""

    def __init__(self) -> None:
        self.busy_until_ms = 0.0

    def sent(self, *, sent_ms: float, size_kB: float, beta_ms_per_kB: float) -> None:
        """A message of size_kB left the sender at sent_ms."""
        self.busy_until_ms = max(self.busy_until_ms, sent_ms) + beta_ms_per_kB * size_kB

    def idle(self, now_ms: float, *, guard_ms: float = 0.0) -> bool:
        """True when the link is predicted to have drained guard_ms ago."""
        return now_ms >= self.busy_until_ms + guard_ms


class ProbeBudget:
    """At most `share` of the uplink's rate for probes: a token bucket that refills at share / beta and
    holds one burst (`depth_bytes`, every probe size once, as after a detected change). Probes wait
    for an idle link, but a frame that comes meanwhile waits behind the probe: a paper-reproduction
    trial's 4 Mbit/s uplink at k = 7 carried 1.6 Mbit/s of 16 and 64 kB probes (40 %; a 64 kB probe
    is 128 ms of that link) for 0.04 Mbit/s of frames."""

    def __init__(self, *, share: float, depth_bytes: int, clock: Callable[[], float] = time.monotonic) -> None:
        if not 0 < share <= 1 or depth_bytes <= 0:
            raise ValueError(f"need 0 < share <= 1 and depth_bytes > 0, got {share}, {depth_bytes}")
        self.share, self.depth_bytes = share, depth_bytes
        self._clock = clock
        self._tokens = float(depth_bytes)
        self._at = clock()

    def take(self, size_bytes: int, *, beta_ms_per_kB: float, force: bool = False) -> bool:
        """Whether a probe of size_bytes may go now (and its bytes are spent). `force`: it goes whatever the
        budget holds, and its bytes are spent all the same (the bucket may go below empty): the burst of
        every size after a detected change, which the challenger fit needs whole (a review found the
        budget refusing half of it, emptied by the probes just before the alarm)."""
        now = self._clock()
        bytes_per_sec = self.share * 1024.0 * 1000.0 / max(beta_ms_per_kB, 1e-6)
        self._tokens = min(float(self.depth_bytes), self._tokens + max(0.0, now - self._at) * bytes_per_sec)
        self._at = now
        if self._tokens < size_bytes and not force:
            return False
        self._tokens -= size_bytes
        return True
