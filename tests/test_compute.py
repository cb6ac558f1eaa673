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


def test_light_cuts_teach_nothing_and_stale_scale_decays_to_calibration() -> None:
    est = ComputeEstimator(tail_per_tag_ms(TAILS, pnp_ms=0.1))  # edge: heavy at k = 0
    for _ in range(13):
        est.observe(k=0, tags=3, network_ms=1.5 * 3 * (31.9 + 0.1))
    assert est.live_scale == pytest.approx(1.5)
    for _ in range(30):  # at k = 7 the edge only solves PnP: overheads, not the convolutions
        est.observe(k=7, tags=3, network_ms=5.0)
    assert est.live_scale == pytest.approx(1.25)  # one half-life back towards the calibration
    for _ in range(300):
        est.observe(k=7, tags=3, network_ms=5.0)
    assert est.live_scale == pytest.approx(1.0, abs=1e-3)


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
