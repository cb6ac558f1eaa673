"""What int8 costs on real photos, every int8 graph side by side in one run.

The ROIs are those of the tags robot_infer's stage 1 finds (`Stage1Detector()`, the services' default
settings, quad_decimate 2: 45 tags; `splittag detect`, at 1, finds 51) in the three real photos of
bench/data/apriltag_photos (AprilRobotics/apriltag's test data: not ours, not rendered), warped as the
services warp them. Each int8 graph's keypoints are compared with the fp32 network's (the fp32 ONNX
export, which is PyTorch's fp32 to < 1e-4 px): the services' OpenVINO int8 variant (models/int8) and the
int8 ONNX graph `splittag export --format onnx --precision int8` makes (exported in this run with its
default calibration, under a minute). Figures in ROI px (the ROI is 256 px wide), each tag's mean over
its 16 keypoints, then the mean, p99 and max over the tags.

    .venv/bin/python -m bench.int8_photos [--weights models] [--onnx-int8 DIR]

`--onnx-int8 DIR` takes an existing export instead of making one.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from bench.machine import cpu_label
from bench.photos import load_photos
from shared.model import onnx_int8
from shared.model.runtime import load_split_net
from shared.model.weights import load_model
from shared.perception.single import extract_rois
from shared.vision.metrics import e_px
from shared.vision.proposals import Stage1Detector


def photo_rois() -> NDArray[np.uint8]:
    """The ROIs of every tag stage 1 finds in the real photos, in photo and detection order."""
    detector = Stage1Detector()
    rois = [extract_rois(photo.image, detector.detect(photo.image))[0] for photo in load_photos()]
    return np.concatenate(rois)


def _moved(name: str, keypoints: NDArray[np.float32], reference: NDArray[np.float32]) -> str:
    moved = e_px(keypoints, reference)
    return f"{name:<34} {moved.mean():>8.4f} {np.percentile(moved, 99):>8.4f} {moved.max():>8.4f}"


def main() -> None:
    """Export what is missing, run every graph on the photos' ROIs, print the table."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--weights", type=Path, default=Path("models"))
    ap.add_argument("--onnx-int8", type=Path, help="an int8 ONNX export to use (default: exported in this run)")
    args = ap.parse_args()
    print(f"CPU: {cpu_label()}", flush=True)
    rois = photo_rois()
    with tempfile.TemporaryDirectory() as tmp:
        fp32_graph = Path(tmp) / "fp32.onnx"
        onnx_int8.export_all_cuts(load_model(args.weights), fp32_graph)
        reference = onnx_int8.keypoints_of(fp32_graph, rois)
        folder = args.onnx_int8
        if folder is None:
            from shared.datasets.synth import CALIBRATION_SEED, mixed_rois
            from shared.model.export import export

            print("exporting int8 ONNX with the default calibration (under a minute)", flush=True)
            folder = Path(tmp) / "onnx_int8"
            calibration, _ = mixed_rois(300, CALIBRATION_SEED)
            export(args.weights, folder, fmt="onnx", precision="int8", cuts=(0,), calibration=calibration)
        openvino = load_split_net(args.weights, "int8", threads=1)
        services = np.concatenate([openvino.tail(rois[i : i + 16], 0) for i in range(0, len(rois), 16)])
        exported = onnx_int8.keypoints_of(folder / "tail_0.onnx", rois)
    print(f"{len(rois)} tags in {len(load_photos())} real photos; keypoints moved from the fp32 network, ROI px")
    print(f"{'int8 graph':<34} {'mean':>8} {'p99':>8} {'max':>8}")
    print(_moved("OpenVINO int8 (the services')", services, reference))
    print(_moved("ONNX Runtime int8 (splittag export)", exported, reference))


if __name__ == "__main__":
    main()
