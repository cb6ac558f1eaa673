"""Regression test of what we ship: models/ on freshly regenerated samples stays within 10 % of the
e_px that models/MODEL.md reports for exactly this check."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from shared.datasets.generate import generate
from shared.datasets.shards import Dataset, load_dataset
from shared.datasets.synth import SynthMaker, SynthSettings
from shared.model.runtime import TorchSplitNet
from shared.model.views import with_views
from shared.model.weights import load_model
from shared.training.evaluate import predict_dataset
from shared.training.train import evaluate_arrays
from shared.vision.geometry import default_camera

MODELS = Path(__file__).resolve().parent.parent / "models"
SEED, N = 12345, 300
# The generator settings the shipped weights' regression figure was measured with (the current ones).
GENERATOR: dict[str, object] = {}


def reported_e_px() -> float:
    """The figure in MODEL.md's line `Regression check ... e_px = X px`."""
    text = (MODELS / "MODEL.md").read_text()
    m = re.search(r"Regression check .*?e_px = ([0-9.]+) px", text)
    assert m, "MODEL.md has no 'Regression check ... e_px = X px' line"
    return float(m.group(1))


def regression_set(tmp: Path) -> Dataset:
    """Regenerate the N synthetic samples of SEED."""
    cam, s = default_camera(), SynthSettings(seed=SEED, **GENERATOR)
    generate(
        tmp,
        n=N,
        seed=SEED,
        kind="synth",
        settings=s.model_dump(mode="json"),
        maker=SynthMaker(cam, s),
        shard_size=150,
        workers=2,
    )
    return load_dataset(tmp)


def shipped_e_px(ds: Dataset, *, views: int = 1) -> float:
    """The shipped weights (fp32) on every sample of `ds`, with that many test-time views."""
    rows = ds.split("all")
    model = load_model(MODELS)
    pred = predict_dataset(model if views == 1 else with_views(TorchSplitNet(model, bf16=False), views), ds, rows)
    return float(evaluate_arrays(pred, ds.arrays["keypoints"][rows])["e_px_mean"])


def regression_e_px(tmp: Path) -> float:
    """Regenerate N synthetic samples with SEED and measure the shipped weights on all of them."""
    return shipped_e_px(regression_set(tmp))


@pytest.fixture(scope="module")
def samples(tmp_path_factory: pytest.TempPathFactory) -> Dataset:
    return regression_set(tmp_path_factory.mktemp("regression"))


@pytest.mark.slow
def test_shipped_weights_keep_their_reported_accuracy(samples: Dataset) -> None:
    want = reported_e_px()
    got = shipped_e_px(samples)
    print(f"shipped weights: e_px {got:.3f} px on {N} regenerated samples (MODEL.md says {want:.3f})")
    assert abs(got - want) <= 0.1 * want


@pytest.mark.slow
def test_two_views_are_more_accurate_than_one(samples: Dataset) -> None:
    one, two = shipped_e_px(samples), shipped_e_px(samples, views=2)
    print(f"shipped weights on {N} regenerated samples: e_px 1 view {one:.4f}, 2 views {two:.4f} px")
    assert two < 0.97 * one  # the measured figures: models/MODEL.md


if __name__ == "__main__":
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        value = regression_e_px(Path(d))
    print(f"Regression check (synthetic seed {SEED}, {N} samples, all of them): e_px = {value:.3f} px")
