"""Model weights on disk: `model.safetensors` + `config.json` holding the data contract.

Loading checks the contract (input size, ROI margin, keypoint layout, normalisation, output
parameterisation) against this code and refuses a mismatched file with a message naming the field.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Final

import torch
from safetensors.torch import load_file, save_file

from shared.model.net import OFFSET_SCALE, SplitKeypointNet
from shared.model.precision import ModelFileError
from shared.vision.fusion import KeypointFusion
from shared.vision.geometry import ROI_MARGIN, ROI_SIZE

CONFIG_VERSION: Final[str] = "splittag/model-config/v1"


class WeightsError(ModelFileError):
    """A weights folder that is missing, malformed or made for another data contract."""


def data_contract(roi_margin: float = ROI_MARGIN) -> dict[str, Any]:
    """What a weights file must agree on with the code that feeds it."""
    return {
        "version": CONFIG_VERSION,
        "architecture": "splittag-vgg5-k16",
        "input_size": ROI_SIZE,
        "input_channels": 1,
        "input_normalisation": "u8 / 127.5 - 1",
        "roi_margin": roi_margin,
        "keypoint_layout": "4x4 lattice at {0,1/3,2/3,1} of the black square, row-major from TL",
        "keypoint_coordinates": "normalised ROI: (u_px + 0.5) / input_size",
        "output_parameterisation": f"canonical lattice + {OFFSET_SCALE} * fc output",
    }


def save_weights(model: SplitKeypointNet, folder: Path, *, extra: dict[str, Any] | None = None) -> None:
    """Write model.safetensors and config.json (contract + free-form provenance under 'extra')."""
    folder.mkdir(parents=True, exist_ok=True)
    state = {
        k: v.detach().to("cpu", torch.float32).contiguous()
        for k, v in model.state_dict().items()
        if v.dtype.is_floating_point
    }
    state.update(
        {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items() if not v.dtype.is_floating_point}
    )
    save_file(state, str(folder / "model.safetensors"))
    config = {**data_contract(model.roi_margin), "extra": extra or {}}
    (folder / "config.json").write_text(json.dumps(config, indent=2))


def load_model(folder: Path, *, device: str = "cpu") -> SplitKeypointNet:
    """Load weights from a folder (or its model.safetensors), checking the data contract."""
    folder = Path(folder)
    if folder.is_file():
        folder = folder.parent
    cfg_path, w_path = folder / "config.json", folder / "model.safetensors"
    for p in (cfg_path, w_path):
        if not p.is_file():
            raise WeightsError(f"{p} does not exist (a weights folder holds model.safetensors + config.json)")
    try:
        config = json.loads(cfg_path.read_text())
    except json.JSONDecodeError as exc:
        raise WeightsError(f"{cfg_path}: not JSON ({exc})") from exc
    # The code's contract, not the file's: the ROI warp that feeds the net uses ROI_MARGIN.
    want = data_contract()
    for key, value in want.items():
        if config.get(key) != value:
            raise WeightsError(
                f"{cfg_path}: {key} is {config.get(key)!r} but this code expects {value!r}; "
                "these weights were made for another data contract"
            )
    model = SplitKeypointNet(roi_margin=float(config["roi_margin"]))
    try:
        model.load_state_dict(load_file(str(w_path)), strict=True)
    except (RuntimeError, OSError) as exc:
        raise WeightsError(f"{w_path}: does not fit the network: {exc}") from exc
    model = model.to(device).eval()
    # channels_last weights: the bf16 convolutions are ~2.5x faster on this CPU than with NCHW weights.
    return model.to(memory_format=torch.channels_last)  # type: ignore[call-overload]


def _read_config(folder: Path) -> dict[str, Any]:
    cfg_path = Path(folder) / "config.json"
    try:
        config = json.loads(cfg_path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise WeightsError(f"{cfg_path}: cannot read ({exc})") from exc
    if not isinstance(config, dict):
        raise WeightsError(f"{cfg_path}: not a JSON object")
    return config


def load_keypoint_fusion(folder: Path) -> KeypointFusion | None:
    """The model's calibrated keypoint/corner sigmas (config.json `keypoint_fusion`), or None when the
    weights were never calibrated (then the network's 16 points are used as they are)."""
    folder = Path(folder)
    if folder.is_file():
        folder = folder.parent
    block = _read_config(folder).get("keypoint_fusion")
    if block is None:
        return None
    try:
        return KeypointFusion.model_validate(block)
    except ValueError as exc:
        raise WeightsError(f"{folder / 'config.json'}: keypoint_fusion: {exc}") from exc


def write_keypoint_fusion(folder: Path, fusion: KeypointFusion) -> None:
    """Store the calibrated sigmas in the weights folder's config.json (the rest is kept)."""
    config = _read_config(folder)
    config["keypoint_fusion"] = fusion.model_dump(mode="json")
    (Path(folder) / "config.json").write_text(json.dumps(config, indent=2))
