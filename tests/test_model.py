"""The split network: parameter count, cut table, and head∘tail == forward at every cut."""

from __future__ import annotations

import pytest
import torch

from shared.model.net import SplitKeypointNet, canonical_keypoints, count_parameters
from shared.wire.cuts import CUTS, N_CUTS, check_cut


@pytest.fixture(scope="module")
def net() -> SplitKeypointNet:
    torch.manual_seed(0)
    model = SplitKeypointNet(roi_margin=0.2).eval()
    # Non-zero last layer so the test also covers the regression path, not just the anchor.
    last = model.fc[-1]
    assert isinstance(last, torch.nn.Linear)
    torch.nn.init.normal_(last.weight, std=0.01)
    return model


def test_parameter_count_matches_paper() -> None:
    n = count_parameters(SplitKeypointNet(roi_margin=0.2))
    assert 5.05e6 <= n <= 5.07e6, n


@pytest.mark.parametrize("k", range(N_CUTS))
def test_head_then_tail_equals_forward(net: SplitKeypointNet, k: int) -> None:
    x = torch.randn(3, 1, 256, 256, generator=torch.Generator().manual_seed(k))
    with torch.no_grad():
        full = net(x)
        z = net.forward_head(x, k)
        assert tuple(z.shape[1:]) == CUTS[k].shape
        split = net.forward_tail(z, k)
    torch.testing.assert_close(split, full, rtol=0, atol=0)


def test_cut_table_payloads_match_paper_table() -> None:
    # The paper's Table: 1024, 512, 256, 128, 32, 8, 0.06 kB for blocks 1..5, avgpool, keypoints.
    kib = [c.payload_bytes_fp16 / 1024 for c in CUTS[1:]]
    assert kib == [1024, 512, 256, 128, 32, 8, 0.0625]
    assert CUTS[0].tensor_bytes() == 256 * 256


def test_untrained_net_predicts_the_canonical_lattice() -> None:
    model = SplitKeypointNet(roi_margin=0.25).eval()
    with torch.no_grad():
        out = model(torch.zeros(1, 1, 256, 256))
    torch.testing.assert_close(out[0], torch.from_numpy(canonical_keypoints(0.25)))


@pytest.mark.parametrize("bad", [-1, 8, 2.0, True, "3"])
def test_invalid_cut_is_refused(bad: object) -> None:
    with pytest.raises(ValueError, match="split index"):
        check_cut(bad)  # type: ignore[arg-type]
