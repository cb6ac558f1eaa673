"""Link model fit, online estimator, and the split decision."""

from __future__ import annotations

import numpy as np
import pytest

from shared.control.linkmodel import (
    HysteresisChooser,
    LinkOccupancy,
    OnlineLinkEstimator,
    ProbeBudget,
    fit_link,
    split_costs,
)
from shared.transport.probe import ArrivalClock
from shared.wire.cuts import CUTS
from tests.fakes import FakeClock
from tests.linksim import Crossing, late_stamps, simulate

SIZES_KB = [c.tensor_bytes() / 1024 for c in CUTS]


def _samples(rng: np.random.Generator, t0: float, beta: float, n: int) -> list[tuple[float, float]]:
    out = []
    for _ in range(n):
        s = float(rng.choice(SIZES_KB))
        rtt = t0 + beta * s + rng.normal(0, 2.0)
        if rng.random() < 0.05:
            rtt += rng.uniform(50, 200)  # outliers: retransmissions, scheduling hiccups
        out.append((s, rtt))
    return out


def test_batch_fit_recovers_the_paper_link() -> None:
    rng = np.random.default_rng(0)
    s, r = zip(*[(s, 39.9 + 0.18 * s + rng.normal(0, 1.5)) for s in SIZES_KB for _ in range(200)], strict=True)
    fit = fit_link(s, r)
    assert fit.t0_ms == pytest.approx(39.9, rel=0.05)
    assert fit.beta_ms_per_kB == pytest.approx(0.18, rel=0.05)
    assert fit.floor_ms == pytest.approx(39.9, abs=1.0)
    with pytest.raises(ValueError, match="2 different"):
        fit_link([1.0, 1.0], [2.0, 3.0])
    # A probe's six repetitions per size, one held up by the host (CI: beta read 0.218 for 0.18, the test
    # asks for 10 %): the per-size medians keep the fit.
    sizes = [0.0625, 1.0, 16.0, 64.0, 256.0, 512.0, 1024.0, 2048.0]
    s2 = [z for z in sizes for _ in range(6)]
    r2 = [39.9 + 0.18 * z + rng.normal(0, 0.3) for z in s2]
    r2[6 * 6] += 120.0  # one round trip at 1 MiB 120 ms late
    held = fit_link(s2, r2)
    assert held.beta_ms_per_kB == pytest.approx(0.18, rel=0.02) and held.t0_ms == pytest.approx(39.9, rel=0.02)


def test_online_estimator_recovers_and_follows_a_change() -> None:
    rng = np.random.default_rng(1)
    est = OnlineLinkEstimator()
    for s, r in _samples(rng, 39.9, 0.18, 400):
        est.add(s, r)
    assert est.t0_ms == pytest.approx(39.9, rel=0.1)
    assert est.beta_ms_per_kB == pytest.approx(0.18, rel=0.1)
    # TDD rebalancing reverted: the uplink is ~3x slower (43.5 -> 14.2 Mbit/s).
    for s, r in _samples(rng, 39.9, 0.55, 150):
        est.add(s, r)
    assert est.beta_ms_per_kB == pytest.approx(0.55, rel=0.1)
    assert est.changes >= 1


def test_decision_matches_brute_force_on_random_tables() -> None:
    rng = np.random.default_rng(2)
    for _ in range(200):
        c, e = np.cumsum(rng.uniform(0, 20, 8)), rng.uniform(0, 5, 8)
        t0, beta, gamma = rng.uniform(1, 60), rng.uniform(0.001, 1), rng.uniform(1, 8)
        t = split_costs(compute_ms=c, edge_ms=e, payload_kB=SIZES_KB, t0_ms=t0, beta_ms_per_kB=beta, gamma=gamma)
        brute = min(range(8), key=lambda k: gamma * c[k] + t0 + beta * SIZES_KB[k] + e[k])
        chooser = HysteresisChooser(min_gain_ms=0.0, min_gain_rel=0.0, dwell=1)
        assert chooser.choose(t, current=int(rng.integers(0, 8))).k == brute


def test_hysteresis_needs_a_real_and_lasting_gain() -> None:
    chooser = HysteresisChooser(min_gain_ms=2.0, min_gain_rel=0.05, dwell=3)
    flat = [100.0, 99.0, 100.0, 100.0, 100.0, 100.0, 100.0, 100.0]
    assert chooser.choose(flat, current=7).k == 7  # 1 ms gain: not worth a switch
    better = [100.0, 100.0, 50.0, 100.0, 100.0, 100.0, 100.0, 100.0]
    assert [chooser.choose(better, current=7).k for _ in range(3)] == [7, 7, 2]


def test_online_estimator_refits_within_a_few_samples_of_a_change() -> None:
    """Detection plus re-fit must be quick: the controller's 1 s goal allows only a handful of samples."""
    rng = np.random.default_rng(3)
    est = OnlineLinkEstimator(cusum_threshold=5.0)
    for s, r in _samples(rng, 39.9, 0.577, 300):
        est.add(s, r)
    needed = None
    for i, (s, r) in enumerate(_samples(rng, 39.9, 0.18, 60)):
        est.add(s, r)
        if needed is None and abs(est.beta_ms_per_kB - 0.18) <= 0.15 * 0.18 and abs(est.t0_ms - 39.9) <= 4.0:
            needed = i + 1
    print(f"re-fit after {needed} samples")
    assert needed is not None and needed <= 12
    assert est.beta_ms_per_kB == pytest.approx(0.18, rel=0.15)  # and stays there (outliers included)


def _feed(est: OnlineLinkEstimator, crossings: list[Crossing]) -> None:
    for c in crossings:
        est.add_crossing(
            size_kB=c.payload_bytes / 1024,
            sent_ms=c.sent_ms,
            received_ms=c.received_ms,
            previous_received_ms=c.previous_received_ms,
        )


ROI_3_TAGS = 3 * 65_536 + 1_500  # k = 0 with three tags: ~194 kB, 112 ms on the 14.2 Mbit/s uplink
KEYPOINTS = 1_800  # k = 7


@pytest.mark.parametrize("window", [1, 2, 3, 4])
@pytest.mark.parametrize(("floor_ms", "beta"), [(39.9, 0.18), (39.9, 0.577), (12.0, 0.577)])
@pytest.mark.parametrize("frames", [[ROI_3_TAGS], [ROI_3_TAGS, KEYPOINTS, KEYPOINTS]], ids=["roi", "mixed"])
def test_estimator_learns_the_link_not_the_queue(window: int, floor_ms: float, beta: float, frames: list[int]) -> None:
    """Frames pipelined on a rate-limited link (an independent packet-level simulation): the estimate is
    within 10 % whatever the in-flight window, where per-frame transport time reads the queue as floor."""
    crossings = simulate(floor_ms=floor_ms, beta_ms_per_kB=beta, window=window, frame_bytes=frames, fps=15.0)
    est = OnlineLinkEstimator(half_life=40, cusum_threshold=5.0)
    _feed(est, crossings)
    assert est.t0_ms == pytest.approx(floor_ms, rel=0.1)
    assert est.beta_ms_per_kB == pytest.approx(beta, rel=0.1)
    if window >= 2 and beta > 0.5 and len(frames) == 1:
        # The naive sample (received - sent) is badly wrong here: the simulation does queue.
        naive = OnlineLinkEstimator(half_life=40, cusum_threshold=5.0)
        for c in crossings:
            naive.add(c.payload_bytes / 1024, c.received_ms - c.sent_ms)
        assert abs(naive.t0_ms - floor_ms) > 0.3 * floor_ms
        assert est.busy > 0.5 * est.n


def test_estimator_with_a_clock_offset() -> None:
    """A receiver clock 5 ms ahead of the sender's shows up in t0 only (every sample carries it)."""
    crossings = simulate(
        floor_ms=39.9, beta_ms_per_kB=0.577, window=2, frame_bytes=[ROI_3_TAGS, KEYPOINTS], clock_offset_ms=5.0
    )
    est = OnlineLinkEstimator(half_life=40, cusum_threshold=5.0)
    _feed(est, crossings)
    assert est.t0_ms == pytest.approx(44.9, rel=0.1)
    assert est.beta_ms_per_kB == pytest.approx(0.577, rel=0.1)


def test_estimator_follows_a_change_of_a_loaded_link() -> None:
    """5g -> 5g-pre-tdd while k = 0 keeps the link busy: the new slope is found within the phase."""
    est = OnlineLinkEstimator(half_life=40, cusum_threshold=5.0)
    _feed(est, simulate(floor_ms=39.9, beta_ms_per_kB=0.18, window=2, frame_bytes=[ROI_3_TAGS], duration_ms=9_000))
    assert est.beta_ms_per_kB == pytest.approx(0.18, rel=0.1)
    slow = simulate(floor_ms=39.9, beta_ms_per_kB=0.577, window=2, frame_bytes=[ROI_3_TAGS], duration_ms=9_000, seed=1)
    _feed(est, slow[: len(slow) // 2])
    assert est.changes >= 1
    _feed(est, slow[len(slow) // 2 :])
    assert est.t0_ms == pytest.approx(39.9, rel=0.1)
    assert est.beta_ms_per_kB == pytest.approx(0.577, rel=0.1)


def _ten_steady_minutes(
    frames: list[int], *, seed: int, late_fraction: float = 0.0
) -> tuple[OnlineLinkEstimator, OnlineLinkEstimator, list[float]]:
    """Ten simulated minutes of a steady 5g uplink (~6000 samples; `late_fraction` of the stamps late by
    an exponential 20 ms): the estimator, a copy of it after the first 100 samples, and beta after each
    later sample (whose covariance is checked symmetric and positive definite at every one)."""
    import copy

    crossings = simulate(
        floor_ms=40.7, beta_ms_per_kB=0.18, window=2, frame_bytes=frames, fps=10.0, duration_ms=600_000.0, seed=seed
    )
    if late_fraction:
        crossings = late_stamps(crossings, fraction=late_fraction, mean_ms=20.0, seed=seed)
    est = OnlineLinkEstimator(half_life=40, cusum_threshold=5.0)
    _feed(est, crossings[:100])
    first = copy.deepcopy(est)
    betas = []
    for c in crossings[100:]:
        _feed(est, [c])
        betas.append(est.beta_ms_per_kB)
        assert est.p[0, 1] == est.p[1, 0] and est.p[0, 0] > 0 and np.linalg.det(est.p) > 0
    return est, first, betas


@pytest.mark.parametrize(
    "frames", [[ROI_3_TAGS], [KEYPOINTS], [ROI_3_TAGS, KEYPOINTS, KEYPOINTS]], ids=["k0", "k7", "mixed"]
)
def test_ten_minutes_of_a_steady_link_keep_the_fit_and_raise_no_alarm(frames: list[int]) -> None:
    """Ten simulated minutes of a steady 5g uplink (~6000 samples). Two faults hid behind each other. The
    fit's covariance lost its symmetry by rounding, tenfold every 133 samples, until it was indefinite
    (~1500 samples) and the fit leapt to t0 0 ms, beta 7.5 ms/kB, where the stall check refused nearly
    every frame for good. Only the change detector's alarms, which reset the covariance, mostly kept that
    from showing, and those alarms were themselves spurious: normalised by a quiet link's sub-millisecond
    scale, shifts no decision can notice raised 5-17 alarms in ten minutes (seeds 0-5, these three
    mixes), each a reset; beta read 0.0-1.59 in two of the k = 0 runs. Now: the covariance is symmetric
    and positive definite at every sample, no alarm after the first fit, beta within 5 % throughout
    (0 alarms, 0.177-0.185 over the same 18 runs; seed 2 here)."""
    est, first, betas = _ten_steady_minutes(frames, seed=2)
    assert est.alarms == first.alarms and est.resets == 0  # (not even one dismissed)
    assert min(betas) > 0.95 * 0.18 and max(betas) < 1.05 * 0.18, (min(betas), max(betas))
    assert est.t0_ms == pytest.approx(40.7, rel=0.05)


@pytest.mark.parametrize(
    "frames", [[ROI_3_TAGS], [KEYPOINTS], [ROI_3_TAGS, KEYPOINTS, KEYPOINTS]], ids=["k0", "k7", "mixed"]
)
def test_late_stamps_of_a_loaded_receiver_take_no_change_and_keep_the_fit(frames: list[int]) -> None:
    """Ten simulated minutes of a steady 5g uplink whose receiver stamps a fifth of the messages late by
    an exponential 20 ms (CPU load; a trial's loaded machine fired the detector ~11 times in 170 s).
    Every alarm used to reset the fit, and right after it one late sample carried beta: seeds 0-5, these
    three mixes, 40-79 alarms per run, beta 0.0-8.2 ms/kB, 2.7-22 % of the samples more than 25 % off.
    An alarm now starts a challenger that must predict the next samples better before it takes over:
    0-3 changes taken a run (11 in the 18), 34-68 alarms dismissed, beta 0.0-0.62 (one run: 2.66),
    0-7.8 % of the samples more than 25 % off (seed 0 here: no change taken)."""
    est, first, betas = _ten_steady_minutes(frames, seed=0, late_fraction=0.2)
    off = np.abs(np.array(betas) / 0.18 - 1.0)
    assert est.changes == first.changes and est.dismissed >= 10  # alarms raised, none taken
    assert off.max() < 0.75 and np.mean(off > 0.25) < 0.1, (min(betas), max(betas), np.mean(off > 0.25))


@pytest.mark.parametrize("frames", [[ROI_3_TAGS], [ROI_3_TAGS, KEYPOINTS, KEYPOINTS]], ids=["k0", "mixed"])
def test_a_real_change_is_taken_through_late_stamps(frames: list[int]) -> None:
    """The same late stamps, and the link turns into 5g-pre-tdd after a minute: a challenger wins and
    the fit stays within 25 % of the new slope from 5 s after the change on (in ad-hoc runs of seeds
    0-2 with these mixes, within 0.4-2.4 s of the change)."""

    def link(beta: float, seed: int, offset_ms: float) -> list[Crossing]:
        crossings = simulate(
            floor_ms=40.7, beta_ms_per_kB=beta, window=2, frame_bytes=frames, fps=10.0, duration_ms=60_000.0, seed=seed
        )
        return [
            Crossing(c.payload_bytes, c.sent_ms + offset_ms, c.received_ms + offset_ms, None, c.kind) for c in crossings
        ]

    chained = sorted(link(0.18, 0, 0.0) + link(0.577, 1, 60_000.0), key=lambda c: c.received_ms)
    late = late_stamps(chained, fraction=0.2, mean_ms=20.0, seed=1)  # (which also chains the previous stamps)
    est = OnlineLinkEstimator(half_life=40, cusum_threshold=5.0)
    _feed(est, [c for c in late if c.received_ms < 60_000.0])
    assert est.beta_ms_per_kB == pytest.approx(0.18, rel=0.25)
    before = est.changes
    after = [c for c in late if c.received_ms >= 60_000.0]
    _feed(est, [c for c in after if c.received_ms < 65_000.0])
    assert est.changes > before
    for c in after:
        if c.received_ms >= 65_000.0:
            _feed(est, [c])
            assert est.beta_ms_per_kB == pytest.approx(0.577, rel=0.25), c.received_ms


def test_busy_only_evidence_keeps_t0_and_bounded_variance() -> None:
    """A link that never drains says nothing about t0: the estimate keeps it, its variance stays capped."""
    est = OnlineLinkEstimator(prior_t0_ms=39.9, prior_beta=0.577)
    arrival = 100.0
    for i in range(20_000):
        previous, arrival = arrival, arrival + 0.577 * 190.0
        est.add_crossing(size_kB=190.0, sent_ms=float(i), received_ms=arrival, previous_received_ms=previous)
    assert est.t0_ms == pytest.approx(39.9)
    assert est.beta_ms_per_kB == pytest.approx(0.577, rel=1e-3)
    assert np.all(np.isfinite(est.p)) and est.p[0, 0] <= OnlineLinkEstimator.PRIOR_VARIANCE[0] + 1e-6


def test_arrival_clock_and_link_occupancy() -> None:
    ticks = iter([10, 25, 20, 40])
    clock = ArrivalClock(clock=lambda: next(ticks))
    assert [clock.stamp() for _ in range(4)] == [(10, 0), (25, 10), (20, 25), (40, 25)]
    occ = LinkOccupancy()
    occ.sent(sent_ms=100.0, size_kB=100.0, beta_ms_per_kB=0.5)  # busy until 150
    occ.sent(sent_ms=120.0, size_kB=20.0, beta_ms_per_kB=0.5)  # queued behind: until 160
    assert not occ.idle(159.0) and occ.idle(160.0) and not occ.idle(161.0, guard_ms=2.0)


def test_one_payload_size_keeps_the_fit_on_what_it_saw() -> None:
    """robot_infer's frames at one k cross with one payload size: the samples only say t0 + beta S.
    The fit must keep predicting that (5 ms here) sample after sample; clamping a negative beta to 0
    alone once walked t0 from 0 to 1500 ms (and the pacer then held every frame back by seconds)."""
    est = OnlineLinkEstimator(prior_t0_ms=1.0)
    previous = None
    for i in range(300):
        sent = 150.0 * i
        est.add_crossing(size_kB=300.0, sent_ms=sent, received_ms=sent + 5.0, previous_received_ms=previous)
        previous = sent + 5.0
        assert est.t0_ms + 300.0 * est.beta_ms_per_kB == pytest.approx(5.0, abs=0.5), i
        assert 0.0 <= est.t0_ms <= 5.5


def _stalled(crossings: list[Crossing], start_ms: float, stall_ms: float) -> list[Crossing]:
    """The receiver's process got no CPU from start_ms for stall_ms (a trial's CLI start-up on a 2-core
    host): what arrived meanwhile is stamped at the stall's end, a few hundredths of a ms apart."""
    from dataclasses import replace

    end = start_ms + stall_ms
    out: list[Crossing] = []
    previous: float | None = None
    for c in crossings:
        received = c.received_ms
        if start_ms <= received < end:
            received = end + 0.05 * sum(1 for o in out if o.received_ms >= end)
        elif received >= end:
            received = max(received, (previous or 0.0) + 0.05)
        out.append(replace(c, received_ms=received, previous_received_ms=previous))
        previous = received
    return out


@pytest.mark.parametrize("poses_after_ms", [0.0, 30.0], ids=["in-order", "probes-first"])
@pytest.mark.parametrize("frame_bytes", [[ROI_3_TAGS], [KEYPOINTS]], ids=["k0", "k7"])
def test_a_receiver_stall_is_not_taken_for_a_change_of_the_link(frame_bytes: list[int], poses_after_ms: float) -> None:
    """A trial: a 1.5 s CPU stall on an unchanged 5g link published t0 0.0 ms and beta 1.54 ms/kB and
    switched the split there and back within 0.2 s. The frames a stalled receiver stamps at once did not
    cross the link 100x faster than its rate: they say nothing about beta, and the one late frame
    before them is an outlier, not a new link."""
    steady = simulate(floor_ms=39.9, beta_ms_per_kB=0.18, window=2, frame_bytes=frame_bytes, duration_ms=20_000)
    est = OnlineLinkEstimator(half_life=40, cusum_threshold=5.0)
    worst = [0.0, 0.0]
    # The controller learns a frame's crossing from its poses, after the edge computed it, and a probe's
    # at once: in the burst after a stall, probes stamped behind a frame reach it first (a review).
    crossings = sorted(
        _stalled(steady, 8_000.0, 1_500.0),
        key=lambda c: c.received_ms + (poses_after_ms if c.kind == "frame" else 0.0),
    )
    for i, c in enumerate(crossings):
        _feed(est, [c])
        # (the late message before a burst moves the estimate until the burst's next stamp, microseconds
        # later, undoes it: judged once each message's successor is in)
        burst_next = i + 1 < len(crossings) and crossings[i + 1].received_ms - c.received_ms < 1.0
        if c.received_ms > 8_000.0 and not burst_next:
            worst[0] = max(worst[0], abs(est.t0_ms - 39.9) / 39.9)
            worst[1] = max(worst[1], abs(est.beta_ms_per_kB - 0.18) / 0.18)
    # (the late message may raise the alarm before the burst behind it shows the stall: its update is
    # undone and the alarm counted dismissed; it never refits the link from the burst)
    assert est.changes == 0 and est.alarms <= 1 and est.bunched > 10, (est.changes, est.alarms, est.bunched)
    assert est.alarms == est.changes + est.dismissed + est.judging
    assert worst[0] < 0.25 and worst[1] < 0.35, worst


def test_a_stall_that_undoes_a_take_over_does_not_count_the_change_twice() -> None:
    """A review: a stall's rollback undid the sample on which a challenger took over, the challenger came
    back pending and took over again, and `link_changes` said 2 for one change of the link (alarms 1).
    Each alarm is now counted once, as a change or dismissed."""
    est = OnlineLinkEstimator(half_life=40, cusum_threshold=5.0)
    _feed(est, simulate(floor_ms=39.9, beta_ms_per_kB=0.18, window=2, frame_bytes=[ROI_3_TAGS], duration_ms=9_000))
    slow = [
        Crossing(c.payload_bytes, c.sent_ms + 9_000.0, c.received_ms + 9_000.0, None, c.kind)
        for c in simulate(floor_ms=39.9, beta_ms_per_kB=0.577, window=2, frame_bytes=[ROI_3_TAGS], duration_ms=9_000)
    ]
    previous: float | None = None
    taken_at = None
    for i, c in enumerate(slow):
        est.add_crossing(
            size_kB=c.payload_bytes / 1024, sent_ms=c.sent_ms, received_ms=c.received_ms, previous_received_ms=previous
        )
        previous = c.received_ms
        if est.changes:
            taken_at = i
            break
    assert taken_at is not None and previous is not None and est.changes == 1
    # a message stamped 0.05 ms behind the take-over's: the receiver was stalled, the take-over is undone
    est.add_crossing(size_kB=64.0, sent_ms=previous - 5.0, received_ms=previous + 0.05, previous_received_ms=previous)
    assert est.bunched == 1 and est.judging
    previous += 0.05
    for c in slow[taken_at + 1 :]:
        est.add_crossing(
            size_kB=c.payload_bytes / 1024, sent_ms=c.sent_ms, received_ms=c.received_ms, previous_received_ms=previous
        )
        previous = c.received_ms
    assert est.changes == 1 and est.alarms == est.changes + est.dismissed + est.judging, (est.alarms, est.dismissed)
    assert est.beta_ms_per_kB == pytest.approx(0.577, rel=0.1)


def test_probes_stay_within_their_share_of_a_slow_uplink_and_pass_on_a_fast_one() -> None:
    """A trial's 4 Mbit/s uplink at k = 7 carried 1.6 Mbit/s of probes. The probe loop asks for a 16 or
    64 kB probe every 0.15 s (its routine pace); the budget lets 10 % of the link's rate through, one
    burst of both sizes deep, and on the 5G link (beta 0.18 ms/kB) every probe."""
    for beta, share_used in ((2.05, 0.1), (0.18, None)):
        clock = FakeClock(0.0)
        budget = ProbeBudget(share=0.1, depth_bytes=80 * 1024, clock=clock)
        sent = asked = 0
        for i in range(400):  # 60 s
            clock.now += 0.15
            size = (16 if i % 2 else 64) * 1024
            asked += size
            sent += size if budget.take(size, beta_ms_per_kB=beta) else 0
        rate = 1024 * 1000 / beta  # the link's bytes a second
        if share_used is None:
            assert sent == asked
        else:
            assert 0.8 * share_used * rate * 60 <= sent <= share_used * rate * 60 + 80 * 1024
    # The burst after a detected change goes whole, even from an empty bucket, and is paid for after
    clock = FakeClock(0.0)
    budget = ProbeBudget(share=0.1, depth_bytes=80 * 1024, clock=clock)
    assert budget.take(80 * 1024, beta_ms_per_kB=2.05) and not budget.take(16 * 1024, beta_ms_per_kB=2.05)
    assert all(budget.take(s * 1024, beta_ms_per_kB=2.05, force=True) for s in (16, 64))
    clock.now += 1.0  # ~50 kB refilled: the 80 kB forced below empty are owed first
    assert not budget.take(16 * 1024, beta_ms_per_kB=2.05)
    with pytest.raises(ValueError):
        ProbeBudget(share=0.0, depth_bytes=1)
