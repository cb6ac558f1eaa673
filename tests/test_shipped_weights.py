"""Regression test of what we ship: models/ on freshly regenerated samples stays within 10 % of the
e_px that models/MODEL.md reports for exactly this check."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from shared.datasets.generate import generate
from shared.datasets.shards import load_dataset
from shared.datasets.synth import SynthMaker, SynthSettings
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


def regression_e_px(tmp: Path) -> float:
    """Regenerate N synthetic samples with SEED and measure the shipped weights on all of them."""
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
    ds = load_dataset(tmp)
    rows = ds.split("all")
    pred = predict_dataset(load_model(MODELS), ds, rows)
    return float(evaluate_arrays(pred, ds.arrays["keypoints"][rows])["e_px_mean"])


@pytest.mark.slow
def test_shipped_weights_keep_their_reported_accuracy(tmp_path: Path) -> None:
    want = reported_e_px()
    got = regression_e_px(tmp_path)
    print(f"shipped weights: e_px {got:.3f} px on {N} regenerated samples (MODEL.md says {want:.3f})")
    assert abs(got - want) <= 0.1 * want


if __name__ == "__main__":
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        value = regression_e_px(Path(d))
    print(f"Regression check (synthetic seed {SEED}, {N} samples, all of them): e_px = {value:.3f} px")
