"""`splittag export`: the head and tail of every cut as standalone graphs, for robots (or edges) that
run another runtime than ours.

Formats:
- onnx (fp32 or int8): one `head_k.onnx` (k = 1..7) and `tail_k.onnx` (k = 0..6) per cut, exported
  from the PyTorch weights with dynamic batch, each one self-contained file (weights inside); int8 is
  quantised for ONNX Runtime here (`shared/model/onnx_int8.py`), its cost measured into the manifest.
- openvino (fp32 or int8): the same halves as IR (`head_k.xml`/`tail_k.xml` + .bin), cut from the
  all-cuts graph exactly as the services cut it; int8 is the weights folder's int8 variant.
In both, a half that starts at the image (every head, `tail_0`) takes the uint8 ROIs (N,1,256,256) and
normalises them itself (u8 / 127.5 - 1, in the graph); every other input is the float32 cut tensor.
`manifest.json` lists each file with its cut, input and output names, shapes and dtypes and every file
it needs, plus the weights' data contract (ROI size, margin, keypoint layout, coordinates) and, for
OpenVINO, the compile settings the services use: without `INFERENCE_PRECISION_HINT` f32 a CPU with bf16
runs the int8 graph's float parts in bf16, which moves the keypoints by up to ~1 ROI px (a trial).
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path
from typing import Any, Final, Literal

import numpy as np
import torch
from numpy.typing import NDArray
from torch import Tensor, nn

from shared.model.net import AllCuts, SplitKeypointNet
from shared.model.onnx_files import inline_weights, quiet_exporter
from shared.model.openvino_net import COMPILE_CONFIG, OpenVINOSplitNet, export_ir, variant_path
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
        module = (_Head(net, k) if side == "head" else _Tail(net, k)).eval()  # (the wrapper too)
        example = torch.zeros(
            [1, *io["input"]["shape"][1:]], dtype=torch.uint8 if io["input"]["dtype"] == "uint8" else torch.float32
        )
        path = out / f"{side}_{k}.onnx"
        with torch.no_grad(), quiet_exporter():
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
        inline_weights(path)
        files.append({"file": path.name, "needs": [path.name], "side": side, "k": k, **io})
    return files


def _export_onnx_int8(
    net: SplitKeypointNet,
    out: Path,
    cuts: tuple[int, ...],
    calibration: NDArray[np.uint8] | None,
    evaluation: tuple[NDArray[np.uint8], NDArray[np.float64]] | None,
    calibration_source: str,
) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    from shared.model import onnx_int8

    if calibration is None or not len(calibration):
        raise ExportError("int8 ONNX is calibrated on ROIs: give some (splittag export makes them)")
    if evaluation is None:
        evaluation = (np.zeros((0, 256, 256), np.uint8), np.zeros((0, 16, 2)))
    quantised = "every Conv but the first"
    checked: dict[str, Any] = {
        "calibration": {"samples": len(calibration), "source": calibration_source, "quantised": quantised}
    }
    with tempfile.TemporaryDirectory() as tmp:
        fp32, int8 = Path(tmp) / "all_fp32.onnx", Path(tmp) / "all_int8.onnx"
        onnx_int8.export_all_cuts(net, fp32)
        onnx_int8.quantise(fp32, int8, calibration)
        if len(evaluation[0]):
            checked["accuracy"] = onnx_int8.accuracy(fp32, int8, *evaluation)
        import onnx

        graph = onnx.load(str(int8))
        files = []
        for side, k in _halves(cuts):
            path = out / f"{side}_{k}.onnx"
            grid = onnx_int8.cut(graph, path, side, k)
            io = _io(k, side)
            if grid is not None:  # the cut's values lie on a uint8 grid: it may travel as its codes
                end = "output" if side == "head" else "input"
                io[end] = {**io[end], "uint8_grid": {**grid, "value": "scale * (code - zero_point)"}}
            files.append({"file": path.name, "needs": [path.name], "side": side, "k": k, **io})
    return files, checked


def _export_openvino(ir: Path, out: Path, cuts: tuple[int, ...]) -> list[dict[str, Any]]:
    import openvino as ov

    split = OpenVINOSplitNet(ir)
    files = []
    for side, k in _halves(cuts):
        model = split.head_model(k) if side == "head" else split.tail_model(k)
        io = _io(k, side)
        if io["input"]["name"] == "roi":
            # The ROI in as uint8, normalised in the graph as the ONNX halves do: the IR took the
            # normalised float ROI, and a uint8 ROI fed to it was accepted silently, keypoints 21 px off.
            model = _uint8_roi_input(model)
        model.get_parameters()[0].output(0).get_tensor().set_names({io["input"]["name"]})
        model.outputs[0].get_tensor().set_names({io["output"]["name"]})  # (the manifest's names, by name)
        path = out / f"{side}_{k}.xml"
        ov.save_model(model, str(path), compress_to_fp16=False)
        needs = [path.name, path.with_suffix(".bin").name]
        files.append({"file": path.name, "needs": needs, "side": side, "k": k, **io})
    return files


def _uint8_roi_input(model: Any) -> Any:
    """`model` with a uint8 ROI input, converted and normalised (x * (1 / 127.5) - 1, float32) in the
    graph with the services' own arithmetic (`openvino_net.normalise`)."""
    import openvino as ov
    import openvino.opset13 as ops

    model = model.clone()  # (the halves share the all-cuts graph's nodes)
    (old,) = model.get_parameters()
    new = ops.parameter(old.get_partial_shape(), ov.Type.u8, name="roi")
    x = ops.convert(new, ov.Type.f32)
    x = ops.multiply(x, ops.constant(np.float32(1 / 127.5)))
    x = ops.subtract(x, ops.constant(np.float32(1.0)))
    for target in list(old.output(0).get_target_inputs()):
        target.replace_source_output(x.output(0))
    return ov.Model([r.get_node() for r in model.outputs], [new], model.get_friendly_name())


def export(
    weights: Path,
    out: Path,
    *,
    fmt: ExportFormat,
    precision: Precision,
    cuts: tuple[int, ...] = tuple(range(N_CUTS)),
    calibration: NDArray[np.uint8] | None = None,
    evaluation: tuple[NDArray[np.uint8], NDArray[np.float64]] | None = None,
    calibration_source: str = "given",
) -> Path:
    """Write the halves of every cut in `cuts` and manifest.json to `out`; returns the manifest.
    ONNX int8 only: `calibration` ROIs (uint8, N x 256 x 256), where they came from (`calibration_source`,
    for the manifest), and `evaluation` (ROIs, keypoints) on which its cost is measured and written into
    the manifest (None: not measured)."""
    if precision == "bf16":
        raise ExportError("bf16 is a runtime setting, not a weights format: export fp32 and run it in bf16")
    if out.exists() and not out.is_dir():
        raise ExportError(f"--out {out} is a file: give a folder (made if missing)")
    out.mkdir(parents=True, exist_ok=True)
    # Written to a folder of its own inside `out` first: an export that fails leaves the earlier one as
    # it was (a trial's failed export had deleted it), one that succeeds replaces it whole.
    with tempfile.TemporaryDirectory(dir=out, prefix=".export-") as staging_dir:
        staging = Path(staging_dir)
        checked: dict[str, Any] = {}
        if fmt == "onnx" and precision == "int8":
            net = load_model(weights)
            files, checked = _export_onnx_int8(net, staging, cuts, calibration, evaluation, calibration_source)
        elif fmt == "onnx":
            files = _export_onnx(load_model(weights), staging, cuts)
        elif precision == "int8":
            files = _export_openvino(variant_path(weights, "int8"), staging, cuts)
        else:
            with tempfile.TemporaryDirectory() as tmp, quiet_exporter():
                ir = export_ir(AllCuts(load_model(weights).to(memory_format=torch.contiguous_format)), Path(tmp))  # type: ignore[call-overload]
                files = _export_openvino(ir, staging, cuts)
        (staging / "manifest.json").write_text(
            json.dumps(
                {
                    "version": "splittag/export-manifest/v1",
                    "format": fmt,
                    "precision": precision,
                    "weights": {"folder": str(weights), "sha256": _weights_digests(weights, fmt, precision)},
                    "contract": data_contract(),
                    "roi": ROI_WARP,
                    **({"onnx": _onnx_versions(staging, files)} if fmt == "onnx" else {}),
                    **({"openvino_compile": COMPILE_CONFIG} if fmt == "openvino" else {}),  # (an IR cannot carry them)
                    **checked,
                    "files": files,
                },
                indent=2,
            )
        )
        replaced = stale_export_files(out)
        for path in replaced:
            path.unlink()
        for path in staging.iterdir():
            path.replace(out / path.name)
    return out / "manifest.json"


# How the services cut the ROI out of the image (`shared.vision.geometry.warp_roi`, docs/geometry.md):
# what a robot of another runtime must do alike to feed the exported head (a trial found it in the code).
ROI_WARP = {
    "image": "grayscale uint8, the camera's own pixels (undistorted when the camera has distortion)",
    "quad": "the tag's 4 outer black corners (TL, TR, BR, BL in the tag's frame), OpenCV pixel centres; from "
    "pupil-apriltags (or AprilTag's C library): corners[[3, 2, 1, 0]] - 0.5 (it gives BL, BR, TR, TL with pixel "
    "centres at +0.5: a trial found both only in docs/geometry.md; in its order the keypoints come back with "
    "their rows flipped, unshifted 0.06 px off)",
    "homography": "image -> ROI pixels mapping the quad to the square [margin, 1 - margin] in normalised ROI "
    "coordinates ((u + 0.5) / input_size), margin = contract.roi_margin",
    "warp": "cv2.warpPerspective, INTER_LINEAR, BORDER_REPLICATE; while the mapping shrinks the image more "
    "than 2x around the ROI's centre, the image is first halved with cv2.pyrDown (and the homography with it)",
    "keypoints_to_image": "the inverse homography of the network's keypoints x input_size - 0.5",
    "checks": "the network has no confidence output: a ROI without a tag gives lattice-like keypoints, so a tag "
    "is what stage 1 decoded; an int8 tail maps a non-finite cut tensor to finite keypoints (its first step "
    "quantises), so check the cut is finite before the tail, as edge_infer does",
}


def _onnx_versions(folder: Path, files: list[dict[str, Any]]) -> dict[str, Any]:
    """The ONNX files' IR version and opset, and the oldest ONNX Runtime they were run on (a trial's
    robot pinned to 1.16 found out by a load error)."""
    import onnx

    models = [onnx.load(str(folder / f["file"]), load_external_data=False) for f in files]
    opset = max(o.version for m in models for o in m.opset_import if o.domain in ("", "ai.onnx"))
    oldest = OLDEST_ONNXRUNTIME.get(opset)
    return {
        "ir_version": max(m.ir_version for m in models),
        "opset": opset,
        "onnxruntime": f"{oldest} or later (the oldest with opset {opset}; tested: the same keypoints bit for bit as "
        "the newest)"
        if oldest
        else f"one that runs opset {opset} (not tested on an older one)",
    }


# The oldest ONNX Runtime each exported opset was run on (the same keypoints bit for bit as the newest):
# ONNX Runtime's own table gives the first release of each opset.
OLDEST_ONNXRUNTIME: Final = {20: "1.17.3"}


def _weights_digests(weights: Path, fmt: str, precision: str) -> dict[str, str]:
    """SHA-256 of the weights file(s) the export was made from: which weights these graphs are."""
    import hashlib

    files = [weights / "model.safetensors"]
    if precision == "int8" and fmt == "openvino":
        files = [variant_path(weights, "int8"), variant_path(weights, "int8").with_suffix(".bin")]
    out = {}
    for path in files:
        if path.is_file():
            out[str(path.relative_to(weights))] = hashlib.sha256(path.read_bytes()).hexdigest()
    return out


def stale_export_files(out: Path) -> list[Path]:
    """An earlier export's files in `out` (its halves, their weights, its manifest): a folder holds one
    export, all of it listed; other files stay."""
    halves = [*out.glob("head_*.*"), *out.glob("tail_*.*")]
    return [
        p
        for p in [*halves, out / "manifest.json"]
        if p.is_file() and p.suffix in {".onnx", ".data", ".xml", ".bin", ".json"}
    ]
