"""Training pieces: Wing loss, edge weights, dihedral relabelling, weights contract, a tiny real run."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from shared.datasets.generate import generate
from shared.datasets.synth import SynthMaker, SynthSettings
from shared.model.net import SplitKeypointNet, canonical_keypoints
from shared.model.weights import WeightsError, load_model, save_weights
from shared.training.train import WING_C, TrainSettings, dihedral, train, wing_loss
from shared.vision.geometry import ROI_MARGIN, default_camera


def test_wing_loss_values_and_weights() -> None:
    gt = torch.tensor([[[0.5, 0.5]]])
    # 1 px error on one coordinate at the patch centre (omega = 1): w * ln(1 + 1/eps).
    pred = gt + torch.tensor([[[1 / 256, 0.0]]])
    assert math.isclose(float(wing_loss(pred, gt)), 10 * math.log(1.5), rel_tol=1e-5)
    # Large error: linear branch |d| - C.
    pred = gt + torch.tensor([[[20 / 256, 0.0]]])
    assert math.isclose(float(wing_loss(pred, gt)), 20 - WING_C, rel_tol=1e-5)
    # Near the edge the weight is clamped to 0.3.
    gt_edge = torch.tensor([[[0.05, 0.5]]])
    pred = gt_edge + torch.tensor([[[1 / 256, 0.0]]])
    assert math.isclose(float(wing_loss(pred, gt_edge)), 0.3 * 10 * math.log(1.5), rel_tol=1e-5)


@pytest.mark.parametrize("t", range(8))
def test_dihedral_moves_pixels_and_keypoints_together(t: int) -> None:
    """A bright dot drawn at each keypoint stays under its (relabelled) keypoint after the transform."""
    rng = np.random.default_rng(t)
    kp = canonical_keypoints(ROI_MARGIN) + rng.uniform(-0.03, 0.03, (16, 2)).astype(np.float32)
    img = torch.zeros(1, 1, 256, 256, dtype=torch.uint8)
    for j, (x, y) in enumerate(kp * 256 - 0.5):
        img[0, 0, round(y), round(x)] = 10 + j
    out_img, out_kp = dihedral(img, torch.from_numpy(kp)[None], t)
    for x, y in out_kp[0].numpy() * 256 - 0.5:
        assert int(out_img[0, 0, round(y), round(x)]) > 0
    # Relabelled keypoints stay in canonical lattice order.
    assert np.abs(out_kp[0].numpy() - canonical_keypoints(ROI_MARGIN)).max() < 0.05


def test_weights_round_trip_and_contract(tmp_path: Path) -> None:
    model = SplitKeypointNet(roi_margin=ROI_MARGIN)
    save_weights(model, tmp_path / "w")
    loaded = load_model(tmp_path / "w")
    x = torch.randn(1, 1, 256, 256)
    torch.testing.assert_close(loaded(x), model.eval()(x))
    cfg = json.loads((tmp_path / "w" / "config.json").read_text())
    cfg["input_size"] = 224
    (tmp_path / "w" / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(WeightsError, match="input_size is 224"):
        load_model(tmp_path / "w")
    with pytest.raises(WeightsError, match="does not exist"):
        load_model(tmp_path / "nothing")


@pytest.mark.slow
def test_tiny_training_run_writes_weights_and_resumes(tmp_path: Path) -> None:
    cam, s = default_camera(), SynthSettings(seed=9)
    generate(
        tmp_path / "d",
        n=40,
        seed=9,
        kind="synth",
        settings=s.model_dump(mode="json"),
        maker=SynthMaker(cam, s),
        shard_size=20,
        workers=2,
    )
    settings = TrainSettings(
        data=[tmp_path / "d"], out=tmp_path / "run", epochs=2, batch_size=8, warmup_steps=2, lr=3e-4, eval_samples=12
    )
    first = train(settings)
    assert (tmp_path / "run" / "best" / "model.safetensors").is_file()
    assert len(first["history"]) == 2
    again = train(settings.model_copy(update={"epochs": 3}))  # resumes at epoch 2 of the saved plan
    assert len(again["history"]) == 2
    assert (tmp_path / "run" / "curve.jsonl").read_text().count("\n") == 2


def test_weights_made_for_another_roi_margin_are_refused(tmp_path: Path) -> None:
    """The ROI warp that feeds the net uses ROI_MARGIN: a file saying otherwise is another contract
    (the check used to compare the file's margin with itself)."""
    save_weights(SplitKeypointNet(roi_margin=0.25), tmp_path / "w")
    with pytest.raises(WeightsError, match=r"roi_margin is 0\.25"):
        load_model(tmp_path / "w")


def test_train_options_are_generated_from_the_settings() -> None:
    """`splittag train` declares no option of its own: every TrainSettings field, same defaults."""
    from shared.tools.cli import build_parser
    from shared.tools.options import model_from_args

    args = build_parser().parse_args(
        ["train", "--data", "a", "--data", "b", "--out", "o", "--no-bf16", "--epochs", "3", "--device", "cpu"]
    )
    got = model_from_args(TrainSettings, args)
    want = TrainSettings(data=[Path("a"), Path("b")], out=Path("o"), bf16=False, epochs=3)
    assert got == want
    with pytest.raises(SystemExit):
        build_parser().parse_args(["train", "--out", "o"])  # --data is required


@pytest.mark.slow
def test_tiny_quantisation_run_installs_an_int8_variant_that_resumes_and_runs(tmp_path: Path) -> None:
    """`splittag quantize` end to end on a tiny data set: NNCF ranges from real ROIs, fine-tuning steps,
    the exported IR validated, the best kept with its curve, installed into a copy of the weights folder
    (config.json lists it), loadable as precision int8 at any cut; a second run resumes."""
    import shutil

    from shared.model.runtime import load_split_net
    from shared.training.quantize import quantize
    from shared.training.settings import QuantizeSettings

    models = Path(__file__).resolve().parent.parent / "models"
    weights = tmp_path / "w"
    weights.mkdir()
    for name in ("model.safetensors", "config.json"):
        shutil.copy(models / name, weights / name)
    config = json.loads((weights / "config.json").read_text())
    config.pop("variants", None)
    (weights / "config.json").write_text(json.dumps(config))
    cam, s = default_camera(), SynthSettings(seed=3)
    generate(
        tmp_path / "d",
        n=24,
        seed=3,
        kind="synth",
        settings=s.model_dump(mode="json"),
        maker=SynthMaker(cam, s),
        shard_size=24,
        workers=1,
    )
    settings = QuantizeSettings(
        weights=weights,
        data=[tmp_path / "d"],
        out=tmp_path / "run",
        calibration_samples=4,
        steps=2,
        batch_size=2,
        eval_every=2,
        val_samples=4,
        threads=2,
        install=True,
    )
    metrics = quantize(settings)
    assert metrics["steps"] == 2 and metrics["val_e_px"] > 0
    assert (weights / "int8" / "model.xml").is_file() and (weights / "int8" / "curve.jsonl").is_file()
    listed = json.loads((weights / "config.json").read_text())["variants"]["int8"]
    assert listed["path"] == "int8/model.xml" and listed["fp32_val_e_px"] > 0
    net = load_split_net(weights, "int8", threads=1)
    rois = np.zeros((1, 256, 256), np.uint8)
    assert net.tail(net.head(rois, 4), 4).shape == (1, 16, 2)
    again = quantize(settings.model_copy(update={"steps": 3, "install": False}))
    assert again["steps"] == 3  # resumed at step 2, one more step
