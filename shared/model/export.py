"""`splittag export`: the head and tail of every cut as standalone graphs, for robots (or edges) that
run another runtime than ours.

Formats:
- onnx (fp32): one `head_k.onnx` (k = 1..7) and `tail_k.onnx` (k = 0..6) per cut, exported from the
  PyTorch weights with dynamic batch. The head takes the uint8 ROIs (N,1,256,256) and normalises them
  itself; `tail_0` takes the uint8 ROIs too; every other input is the float32 cut tensor.
- openvino (fp32 or int8): the same halves as IR (`head_k.xml`/`tail_k.xml` + .bin), cut from the
  all-cuts graph exactly as the services cut it; int8 is the weights folder's int8 variant.
`manifest.json` lists each file with its cut, input and output names, shapes and dtypes, plus the
weights' data contract (ROI size, margin, keypoint layout, coordinates).
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any, Literal

import torch
from torch import Tensor, nn

from shared.model.net import AllCuts, SplitKeypointNet
from shared.model.openvino_net import OpenVINOSplitNet, export_ir, variant_path
from shared.model.precision import ModelFileError, Precision
from shared.model.weights import data_contract, load_model
from shared.wire.cuts import CUTS, N_CUTS

ExportFormat = Literal["onnx", "openvino"]


class ExportError(ModelFileError):
    """A format/precision combination we do not export."""


class _Head(nn.Module):
    def __init__(self, net: SplitKeypointNet, k: int) -> None:
        super().__init__()
        self.net, self.k = net, k

    def forward(self, roi_u8: Tensor) -> Tensor:
        return self.net.forward_head(SplitKeypointNet.normalise_input(roi_u8), self.k)


class _Tail(nn.Module):
    def __init__(self, net: SplitKeypointNet, k: int) -> None:
        super().__init__()
        self.net, self.k = net, k

    def forward(self, z: Tensor) -> Tensor:
        x = SplitKeypointNet.normalise_input(z) if self.k == 0 else z
        return self.net.forward_tail(x, self.k)


def _io(k: int, side: str) -> dict[str, Any]:
    cut_in = "roi" if k == 0 or side == "head" else f"cut{k}"
    in_shape = [-1, 1, 256, 256] if cut_in == "roi" else [-1, *CUTS[k].shape]
    out = "keypoints" if side == "tail" or k == N_CUTS - 1 else f"cut{k}"
    out_shape = [-1, 16, 2] if out == "keypoints" else [-1, *CUTS[k].shape]
    return {
        "input": {"name": cut_in, "shape": in_shape, "dtype": "uint8" if cut_in == "roi" else "float32"},
        "output": {"name": out, "shape": out_shape, "dtype": "float32"},
    }


def _halves(cuts: tuple[int, ...]) -> list[tuple[str, int]]:
    return [("head", k) for k in cuts if k > 0] + [("tail", k) for k in cuts if k < N_CUTS - 1]


def _export_onnx(net: SplitKeypointNet, out: Path, cuts: tuple[int, ...]) -> list[dict[str, Any]]:
    net = net.to(memory_format=torch.contiguous_format).eval()  # type: ignore[call-overload]
    files = []
    for side, k in _halves(cuts):
        io = _io(k, side)
        module = _Head(net, k) if side == "head" else _Tail(net, k)
        example = torch.zeros(
            [1, *io["input"]["shape"][1:]], dtype=torch.uint8 if io["input"]["dtype"] == "uint8" else torch.float32
        )
        path = out / f"{side}_{k}.onnx"
        with torch.no_grad():
            torch.onnx.export(
                module,
                (example,),
                str(path),
                input_names=[io["input"]["name"]],
                output_names=[io["output"]["name"]],
                dynamic_axes={io["input"]["name"]: {0: "n"}, io["output"]["name"]: {0: "n"}},
                dynamo=True,
                verbose=False,
            )
        files.append({"file": path.name, "side": side, "k": k, **io})
    return files


def _export_openvino(ir: Path, out: Path, cuts: tuple[int, ...]) -> list[dict[str, Any]]:
    import openvino as ov

    split = OpenVINOSplitNet(ir)
    files = []
    for side, k in _halves(cuts):
        model = split.head_model(k) if side == "head" else split.tail_model(k)
        path = out / f"{side}_{k}.xml"
        ov.save_model(model, str(path), compress_to_fp16=False)
        io = _io(k, side)
        # The IR halves take the normalised ROI (u8 / 127.5 - 1, float32) where the ONNX ones take uint8.
        if io["input"]["name"] == "roi":
            io["input"] = {**io["input"], "dtype": "float32", "normalised": "u8 / 127.5 - 1"}
        files.append({"file": path.name, "side": side, "k": k, **io})
    return files


def export(
    weights: Path,
    out: Path,
    *,
    fmt: ExportFormat,
    precision: Precision,
    cuts: tuple[int, ...] = tuple(range(N_CUTS)),
) -> Path:
    """Write the halves of every cut in `cuts` and manifest.json to `out`; returns the manifest."""
    if precision == "bf16":
        raise ExportError("bf16 is a runtime setting, not a weights format: export fp32 and run it in bf16")
    if fmt == "onnx" and precision == "int8":
        raise ExportError("the int8 variant is an OpenVINO graph: export it with --format openvino")
    out.mkdir(parents=True, exist_ok=True)
    if fmt == "onnx":
        files = _export_onnx(load_model(weights), out, cuts)
    elif precision == "int8":
        files = _export_openvino(variant_path(weights, "int8"), out, cuts)
    else:
        with tempfile.TemporaryDirectory() as tmp:
            ir = export_ir(AllCuts(load_model(weights).to(memory_format=torch.contiguous_format)), Path(tmp))  # type: ignore[call-overload]
            files = _export_openvino(ir, out, cuts)
    manifest = out / "manifest.json"
    manifest.write_text(
        json.dumps(
            {
                "version": "splittag/export-manifest/v1",
                "format": fmt,
                "precision": precision,
                "weights": str(weights),
                "contract": data_contract(),
                "files": files,
            },
            indent=2,
        )
    )
    return manifest
