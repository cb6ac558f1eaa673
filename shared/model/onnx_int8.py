"""int8 ONNX halves for ONNX Runtime (`splittag export --format onnx --precision int8`).

The whole network is exported once with every cut as an output, quantised once with ONNX Runtime's
static quantisation (QDQ, per-channel int8 weights, uint8 activations, min-max calibration on real
ROIs), and then cut into head_k / tail_k by tensor name, so every half of every k is the same
quantised graph, as the services' OpenVINO variant is.

What is quantised was chosen by measurement (ROIs of the training generator and the 45 tags of the
three real photos in bench/data/apriltag_photos, against the fp32 graph; *AMD EPYC family 25 model 17*):
- every convolution but the first: its input is the image, whose 256 levels no int8 grid holds;
- with the ReLU after it folded into its output grid (ONNX Runtime quantises Relu by removing it: the
  grid then starts at 0, which clips exactly as the ReLU did). With convolutions alone each one's
  output was rounded on a grid spanning its negative values too, half of it spent on what the ReLU
  then zeroes, and rounded again after the ReLU. On the real photos' 45 tags the keypoints move from
  the fp32 graph's by 0.033 px mean as exported (`python -m bench.int8_photos`, session 31, which puts
  the services' OpenVINO int8 at 0.046), 0.072 in session 30's export (convolutions alone, default
  calibration); ad hoc, one change at a time: convolutions alone with `TRAINING_MIX` 0.062, the ReLU
  folded with the default calibration 0.043;
- nothing else. Quantising every op ONNX Runtime can (pools, the keypoint head's adds and multiplies)
  put the keypoints themselves on a 1/255 grid: +0.31 px (session 30).
Each export measures its own cost on held-out ROIs and writes it into the manifest (`accuracy`).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray
from torch import Tensor, nn

from shared.model.net import AllCuts, SplitKeypointNet
from shared.model.onnx_files import DropAdvice, inline_weights, lowest_ir_version, quiet_exporter
from shared.vision.metrics import e_px
from shared.wire.cuts import N_CUTS

OUTPUT_NAMES = [*(f"cut{k}" for k in range(1, N_CUTS - 1)), "keypoints"]


class _AllCutsFromImage(nn.Module):
    def __init__(self, net: SplitKeypointNet) -> None:
        super().__init__()
        self.all = AllCuts(net)

    def forward(self, roi_u8: Tensor) -> tuple[Tensor, ...]:
        return self.all(SplitKeypointNet.normalise_input(roi_u8))


def export_all_cuts(net: SplitKeypointNet, path: Path) -> None:
    """The fp32 network, uint8 ROI in, every cut out (`cut1`..`cut6`, `keypoints`), one file."""
    module = _AllCutsFromImage(net.to(memory_format=torch.contiguous_format)).eval()  # type: ignore[call-overload]
    with torch.no_grad(), quiet_exporter():
        torch.onnx.export(
            module,
            (torch.zeros(1, 1, 256, 256, dtype=torch.uint8),),
            str(path),
            input_names=["roi"],
            output_names=OUTPUT_NAMES,
            dynamic_axes={"roi": {0: "n"}, **{name: {0: "n"} for name in OUTPUT_NAMES}},
            dynamo=True,
            verbose=False,
        )
    inline_weights(path)


def quantise(fp32_path: Path, int8_path: Path, calibration: NDArray[np.uint8]) -> None:
    """ONNX Runtime static quantisation of the all-cuts graph: every Conv but the first, each with
    the ReLU after it (see above)."""
    import onnx
    from onnxruntime.quantization import CalibrationDataReader

    convs = [n.name for n in onnx.load(str(fp32_path)).graph.node if n.op_type == "Conv"]

    class Reader(CalibrationDataReader):
        def __init__(self) -> None:
            self.batches: Iterator[dict[str, Any]] = iter(
                {"roi": calibration[i : i + 1, None]} for i in range(len(calibration))
            )

        def get_next(self) -> dict[str, Any] | None:
            return next(self.batches, None)

    root, advice = logging.getLogger(), DropAdvice()
    root.addFilter(advice)
    try:
        with quiet_exporter():
            _quantize_static(fp32_path, int8_path, Reader(), convs[:1])
    finally:
        root.removeFilter(advice)


def _quantize_static(fp32_path: Path, int8_path: Path, reader: Any, exclude: list[str]) -> None:
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static

    quantize_static(
        str(fp32_path),
        str(int8_path),
        reader,
        quant_format=QuantFormat.QDQ,
        per_channel=True,
        activation_type=QuantType.QUInt8,
        weight_type=QuantType.QInt8,
        op_types_to_quantize=["Conv", "Relu"],  # a Relu after a quantised Conv is folded into its grid
        nodes_to_exclude=exclude,
        calibrate_method=CalibrationMethod.MinMax,
    )


def cut(model: Any, out: Path, side: str, k: int) -> dict[str, float] | None:
    """head_k (roi -> cut k, or keypoints at k = 7) or tail_k (cut k, or roi at k = 0 -> keypoints),
    extracted by tensor name from the all-cuts graph (`model`, loaded once for every half). Returns the
    cut tensor's uint8 grid (scale, zero point) where it is quantised, else None."""
    import onnx
    from onnx import helper
    from onnx.numpy_helper import to_array
    from onnx.utils import Extractor

    source = "roi" if side == "head" or k == 0 else f"cut{k}"
    target = "keypoints" if side == "tail" or k == N_CUTS - 1 else f"cut{k}"
    half = Extractor(model).extract_model([source], [target])
    grid = None
    producer = {o: n for n in model.graph.node for o in n.output}.get(f"cut{k}")
    if producer is not None and producer.op_type == "DequantizeLinear":
        # The head ends on the cut's uint8 grid (quantise, dequantise); the tail must start on it again,
        # or its first convolution takes the float tensor and runs in fp32 (a trial: tail_3 1.8x slower,
        # and a rounding step from the whole graph). With the pair at its input it is the whole graph's.
        scale_name, zero_name = producer.input[1], producer.input[2]
        initialisers = {i.name: i for i in model.graph.initializer}
        grid = {
            "scale": float(to_array(initialisers[scale_name])),
            "zero_point": int(to_array(initialisers[zero_name])),
        }
        if side == "tail":
            quantised, restored = f"cut{k}_quantised", f"cut{k}_on_grid"
            for node in half.graph.node:
                for i, name in enumerate(node.input):
                    if name == source:
                        node.input[i] = restored
            pair = [
                helper.make_node("QuantizeLinear", [source, scale_name, zero_name], [quantised]),
                helper.make_node("DequantizeLinear", [quantised, scale_name, zero_name], [restored]),
            ]
            nodes = [*pair, *half.graph.node]
            del half.graph.node[:]
            half.graph.node.extend(nodes)
            have = {i.name for i in half.graph.initializer}
            half.graph.initializer.extend(initialisers[n] for n in (scale_name, zero_name) if n not in have)
            onnx.checker.check_model(half)
    lowest_ir_version(half)
    onnx.save_model(half, str(out), save_as_external_data=False)
    return grid


def keypoints_of(path: Path, rois: NDArray[np.uint8]) -> NDArray[np.float32]:
    """The graph's keypoints (normalised) for uint8 ROIs, with ONNX Runtime on this CPU."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.log_severity_level = 3
    session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    out = [session.run(["keypoints"], {"roi": rois[i : i + 32, None]})[0] for i in range(0, len(rois), 32)]
    return np.concatenate(out).astype(np.float32)


def accuracy(
    fp32_path: Path, int8_path: Path, rois: NDArray[np.uint8], keypoints: NDArray[np.float64]
) -> dict[str, Any]:
    """Both graphs on held-out ROIs: e_px against the labels, and how far int8 moves each ROI's keypoints."""
    ref, int8 = keypoints_of(fp32_path, rois), keypoints_of(int8_path, rois)
    moved = e_px(int8, ref)
    fp32_err, int8_err = float(e_px(ref, keypoints).mean()), float(e_px(int8, keypoints).mean())
    return {
        "units": "ROI px (the ROI is 256 px wide), each ROI's mean over its 16 keypoints",
        "samples": len(rois),
        "e_px_fp32": round(fp32_err, 4),
        "e_px_int8": round(int8_err, 4),
        "e_px_change": round(int8_err - fp32_err, 4),
        "moved_px_mean": round(float(moved.mean()), 4),
        "moved_px_p99": round(float(np.percentile(moved, 99)), 4),
    }
