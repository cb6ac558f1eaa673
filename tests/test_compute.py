"""ComputeEstimator: calibration scaled by live evidence where it is informative, forgetting when stale."""

from __future__ import annotations

import pytest

from shared.control.compute import ComputeEstimator, head_per_tag_ms, tail_per_tag_ms

CUMULATIVE = [0.1, 15.0, 19.0, 22.0, 23.0, 27.0, 28.0, 32.0]
TAILS = [32.0 - c for c in CUMULATIVE]  # (the edge times each tail on its own: calibrate_tail_ms)


def test_robot_scale_learnt_at_heavy_cuts_applies_to_all() -> None:
    est = ComputeEstimator(head_per_tag_ms(CUMULATIVE))
    for _ in range(3 + 10):  # the first 3 are start-up transients and ignored
        est.observe(k=7, tags=4, network_ms=2.0 * 4 * 32.0, fixed_ms=8.0)
    assert est.live_scale == pytest.approx(2.0)
    assert est.tags_per_frame == 4
    ms = est.ms_by_k()
    assert ms[7] == pytest.approx(8.0 + 4 * 32.0 * 2.0)
    assert ms[3] == pytest.approx(8.0 + 4 * 22.0 * 2.0)
    assert ms[0] == pytest.approx(8.0 + 4 * 0.1 * 2.0)


def test_the_period_is_the_whole_frame_or_with_overlap_the_longer_part() -> None:
    est = ComputeEstimator(head_per_tag_ms(CUMULATIVE))
    for _ in range(3 + 10):
        est.observe(k=7, tags=1, network_ms=32.0, fixed_ms=25.0)
    serial, overlapped = est.period_ms_by_k(overlapped=False), est.period_ms_by_k(overlapped=True)
    assert serial == pytest.approx(est.ms_by_k())
    assert overlapped[0] == pytest.approx(25.0)  # stage 1 alone: the head of k = 0 is nothing
    assert overlapped[3] == pytest.approx(25.0)  # 22 ms of network beside 25 of stage 1
    assert overlapped[7] == pytest.approx(32.0)  # the network is the longer part
    msg = est.message(robot_id="r1", side="robot", stamp_nanos=1, factor=2.0, overlapped=True, frame_interval_ms=33.3)
    assert msg.period_ms_by_k == pytest.approx([2.0 * v for v in overlapped])
    assert msg.ms_by_k == pytest.approx([2.0 * v for v in serial]) and msg.frame_interval_ms == 33.3


def test_light_cuts_teach_nothing_and_stale_scale_decays_to_calibration() -> None:
    est = ComputeEstimator(tail_per_tag_ms(TAILS, pnp_ms=0.1))  # edge: heavy at k = 0
    for _ in range(13):
        est.observe(k=0, tags=3, network_ms=1.5 * 3 * (31.9 + 0.1))
    assert est.live_scale == pytest.approx(1.5)
    for _ in range(ComputeEstimator.STALE_HALF_LIFE_FRAMES):  # at k = 7 the edge only solves PnP: overheads
        est.observe(k=7, tags=3, network_ms=5.0)
    assert est.live_scale == pytest.approx(1.25)  # one half-life back towards the calibration
    for _ in range(10 * ComputeEstimator.STALE_HALF_LIFE_FRAMES):
        est.observe(k=7, tags=3, network_ms=5.0)
    assert est.live_scale == pytest.approx(1.0, abs=1e-3)


def _switches(
    load_robot: float, load_edge: float, *, stale_half_life_frames: float, frames: int = 3000
) -> tuple[int, int]:
    """A simulated chain (3 tags, robot stage 1 35 ms, 20 ms + 0.18 ms/kB uplink) whose compute runs
    `load_*` times slower on each side after 200 calibration-speed frames, each side's estimator fed
    what the k in use shows it, the controller's chooser deciding every frame. (switches, frames at the
    truly best k)."""
    from shared.control.linkmodel import HysteresisChooser, split_costs
    from shared.wire.sizing import features_payload_bytes

    robot = ComputeEstimator(head_per_tag_ms(CUMULATIVE), stale_half_life_frames=stale_half_life_frames)
    edge = ComputeEstimator(tail_per_tag_ms(TAILS, pnp_ms=0.5), stale_half_life_frames=stale_half_life_frames)
    chooser = HysteresisChooser(min_gain_ms=3.0, min_gain_rel=0.05, dwell=2)
    payload_kB = [features_payload_bytes(3, k, "fp16") / 1024 for k in range(8)]
    truth = split_costs(
        compute_ms=[load_robot * (35 + 3 * c) for c in CUMULATIVE],
        edge_ms=[load_edge * 3 * (t + 0.5) for t in TAILS],
        payload_kB=payload_kB,
        t0_ms=20.0,
        beta_ms_per_kB=0.18,
    )
    k, switches, at_best = 7, 0, 0
    robot_ms, edge_ms = robot.ms_by_k(), edge.ms_by_k()
    for i in range(frames):
        lr, le = (1.0, 1.0) if i < 200 else (load_robot, load_edge)
        robot.observe(k=k, tags=3, network_ms=lr * 3 * CUMULATIVE[k], fixed_ms=lr * 35.0)
        edge.observe(k=k, tags=3, network_ms=le * 3 * (TAILS[k] + 0.5))
        if i % 15 == 0:  # each side publishes its profile once a second (profile_period_secs): 15 fps
            robot_ms, edge_ms = robot.ms_by_k(), edge.ms_by_k()
        costs = split_costs(
            compute_ms=robot_ms, edge_ms=edge_ms, payload_kB=payload_kB, t0_ms=20.0, beta_ms_per_kB=0.18
        )
        chosen = chooser.choose(costs, k).k
        switches += chosen != k
        k = chosen
        at_best += i >= 200 and k == int(truth.argmin())
    return switches, at_best


@pytest.mark.parametrize(("load_robot", "load_edge"), [(3.0, 3.0), (3.0, 1.0), (1.0, 3.0)])
def test_a_lasting_load_does_not_make_the_split_flap(load_robot: float, load_edge: float) -> None:
    """Each side learns its slowdown only at cuts where it runs most of the network; its stale scale
    fades back to the calibration. Faded within 30 frames, a load on both sides made the controller
    leave the best cut again and again (a trial: 46 switches in 5.5 min), each time for about a second
    (until the next profile tells it); now it looks again every few hundred frames."""
    switches, at_best = _switches(load_robot, load_edge, stale_half_life_frames=ComputeEstimator.STALE_HALF_LIFE_FRAMES)
    fast_fade, fast_at_best = _switches(load_robot, load_edge, stale_half_life_frames=30)
    print(
        f"load {load_robot}/{load_edge}: {switches} switches, {at_best} of 2800 frames at the best cut "
        f"(fade in 30 frames: {fast_fade}, {fast_at_best})"
    )
    assert switches <= 40 and at_best >= 0.9 * 2800 and at_best >= fast_at_best
    assert load_robot == load_edge == 1.0 or fast_fade == switches == 0 or fast_fade > 3 * switches  # what it was


def test_bad_calibration_is_rejected() -> None:
    with pytest.raises(ValueError, match="8 non-negative"):
        ComputeEstimator([1.0, 2.0])


def test_views_multiply_only_the_whole_network_passes() -> None:
    """Test-time views run where one side has the whole network: the robot at the last cut, the edge
    from cut 0; at the split cuts each half runs once per tag."""
    robot = head_per_tag_ms(CUMULATIVE, views=4)
    assert robot[:7] == head_per_tag_ms(CUMULATIVE)[:7]
    assert robot[7] == pytest.approx(4 * 32.0)
    edge = tail_per_tag_ms(TAILS, pnp_ms=0.1, views=4)
    assert edge[1:] == tail_per_tag_ms(TAILS, pnp_ms=0.1)[1:]
    assert edge[0] == pytest.approx(4 * (32.0 - 0.1) + 0.1)


def test_the_edge_times_each_tail_on_its_own_cuts_input_and_runs_no_head() -> None:
    """calibrate_tail_ms feeds each tail an input of its cut's shape and dtype, as edge_step does (ROI
    pixels uint8 at cut 0, float32 after), and never runs a head: the edge compiles none it never uses."""
    import numpy as np

    from shared.model.runtime import calibrate_tail_ms
    from shared.wire.cuts import CUTS

    class Recording:
        def __init__(self) -> None:
            self.calls: list[tuple[int, tuple[int, ...], str]] = []

        def head(self, rois: object, k: int) -> object:
            raise AssertionError("the edge's calibration ran a head")

        def tail(self, z: np.ndarray, k: int) -> np.ndarray:
            self.calls.append((k, z.shape, str(z.dtype)))
            return np.zeros((z.shape[0], 16, 2), np.float32)

    net = Recording()
    out = calibrate_tail_ms(net, repetitions=2)  # type: ignore[arg-type]
    assert len(out) == len(CUTS) and all(v >= 0 for v in out)
    expected = [(c.k, (1, *c.shape), "uint8" if c.k == 0 else "float32") for c in CUTS]
    assert sorted(set(net.calls)) == expected and len(net.calls) == 3 * len(CUTS)  # one untimed + 2 timed each


def test_a_calibration_under_load_cannot_make_a_shorter_head_dearer() -> None:
    """A trial's start-up calibration read the head up to block 1 dearer than up to block 3, and up to
    block 5 dearer than the whole network; a head contains every shorter head (a tail every later tail),
    and each timing is an upper bound, so a cut takes the least of its own and the longer part's."""
    robot = head_per_tag_ms([0.0, 213.0, 230.0, 221.0, 260.0, 293.0, 269.0, 272.0])
    assert robot == [0.0, 213.0, 221.0, 221.0, 260.0, 269.0, 269.0, 272.0]
    edge = tail_per_tag_ms([40.0, 45.0, 30.0, 31.0, 20.0, 5.0, 6.0, 0.5], pnp_ms=1.0, views=2)
    assert edge == [81.0, 41.0, 31.0, 31.0, 21.0, 6.0, 6.0, 1.5]


def test_the_cuts_take_turns_so_a_spell_of_load_slows_no_cut_throughout() -> None:
    """A researcher's `link cost` under load printed C(2..5) all equal: each cut was timed all at once, a
    spell of load slowed every run of cuts 2-4, and the clamp flattened them. The cuts now take turns, a
    round each per repetition: a spell of load as long as four rounds leaves every cut clean rounds."""
    import time

    import numpy as np

    from shared.model.runtime import calibrate_cumulative_ms
    from shared.wire.cuts import CUTS

    class Loaded:
        """Head up to k takes (1 + 3 k) ms, 15 ms more while calls 8 to 39 run (the spell): 3 ms apart, so
        a sleep's overshoot on a loaded box does not reorder them."""

        def __init__(self) -> None:
            self.order: list[int] = []

        def head(self, rois: np.ndarray, k: int) -> np.ndarray:
            spell = 8 <= len(self.order) < 40
            self.order.append(k)
            time.sleep((1 + 3 * k + (15 if spell else 0)) / 1e3)
            return rois

        def tail(self, z: np.ndarray, k: int) -> np.ndarray:
            raise AssertionError("the robot's calibration ran a tail")

    net = Loaded()
    ms = calibrate_cumulative_ms(net, repetitions=10)  # type: ignore[arg-type]
    n = len(CUTS)
    assert len(net.order) == n * 11
    assert all(sorted(net.order[i : i + n]) == list(range(n)) for i in range(0, len(net.order), n))  # rounds
    assert all(m < 1 + 3 * k + 10 for k, m in enumerate(ms)), ms  # no cut timed only under the spell
    assert ms == sorted(ms), ms  # nothing for the clamp to flatten
