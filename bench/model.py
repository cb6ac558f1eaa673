"""The paper's Table on this machine, side by side in one run: payload S(k) and cumulative
single-thread compute C(k) per cut for every way we can run the network, against the core's measured
peak; then what the edge adds per tag after the network (keypoint fusion, PnP).

Columns (the same weights, batch 1, one thread, median):
- eager fp32 (NCHW), the reference everything is compared with;
- bf16: autocast + channels_last, what the services ran before int8 (`precision = "bf16"`);
- int8 (ours): the weights folder's int8 variant (`splittag quantize`: quantisation-aware fine-tuned,
  every convolution int8, the fully connected layers fp32) cut at k by shared.model.openvino_net,
  exactly as robot_infer runs it (`precision = "int8"`);
- OpenVINO int8 (reference): what an engineer gets from NNCF's default post-training quantisation of
  the fp32 weights (every convolution and linear layer), cut the same way; calibrated on 300 training
  ROIs with `--data` (else 64 random ones: then only its speed means something).
With `--data`, each column's keypoint error (e_px, ROI px, mean) on that data set's test split too.
Peak: a tight 3x3 convolution (256 -> 256 channels on 32x32, block 4's shape) per dtype, the fastest
of PyTorch and OpenVINO, as GFLOP/s (int8: GOP/s); each full network then reads as a fraction of it.

    .venv/bin/python -m bench.model [--weights models] [--repetitions 30] [--data data/synth2 --samples 1000]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from bench.machine import cpu_label
from shared.model.net import AllCuts, SplitKeypointNet
from shared.model.openvino_net import OpenVINOSplitNet, export_ir, variant_path
from shared.model.profile import profile_cuts
from shared.model.weights import load_model
from shared.perception.single import run_network
from shared.vision.fusion import KeypointFusion, edge_width_px
from shared.vision.geometry import CORNER_KEYPOINTS, apply_homography, default_camera, lattice_in_tag
from shared.vision.metrics import e_px
from shared.vision.pnp import solve_planar_pnp
from shared.wire.cuts import CUTS

NETWORK_GFLOP = 7.4  # multiply-adds x 2 of the whole network (shared.model.net), batch 1
PEAK_SHAPE = (1, 256, 32, 32)
PEAK_GFLOP = 2 * 256 * 256 * 9 * 32 * 32 / 1e9


def _median_ms(fn: Callable[[], object], repetitions: int, warmup: int = 3) -> float:
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repetitions):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


def _ov_cumulative_ms(net: OpenVINOSplitNet, repetitions: int) -> list[float]:
    x = np.random.default_rng(0).integers(0, 256, (1, 256, 256), dtype=np.uint8)
    out = []
    for cut in CUTS:
        k = cut.k
        out.append(_median_ms(lambda: net.head(x, k), repetitions))  # noqa: B023 (called at once)
    return out


def _ort_cumulative_ms(folder: Path, repetitions: int) -> list[float]:
    """Each exported head_k in ONNX Runtime, one thread (k = 0 is the normalisation: nothing to run)."""
    import onnxruntime as ort

    x = np.random.default_rng(0).integers(0, 256, (1, 1, 256, 256), dtype=np.uint8)
    out = [0.0]
    for k in range(1, len(CUTS)):
        options = ort.SessionOptions()
        options.intra_op_num_threads, options.inter_op_num_threads = 1, 1
        session = ort.InferenceSession(str(folder / f"head_{k}.onnx"), options, providers=["CPUExecutionProvider"])
        out.append(_median_ms(lambda: session.run(None, {"roi": x}), repetitions))  # noqa: B023 (called at once)
    return out


def _ort_keypoints(folder: Path, rois: np.ndarray) -> np.ndarray:
    import onnxruntime as ort

    session = ort.InferenceSession(str(folder / "tail_0.onnx"), providers=["CPUExecutionProvider"])
    return np.concatenate([session.run(None, {"roi": rois[i : i + 64, None]})[0] for i in range(0, len(rois), 64)])


def reference_int8_ir(weights: Path | None, folder: Path, calibration_rois: np.ndarray | None) -> Path:
    """NNCF's default post-training quantisation of the fp32 weights' all-cuts graph, as IR in `folder`."""
    import nncf
    import openvino as ov

    from shared.model.openvino_net import normalise

    net = load_model(weights) if weights else SplitKeypointNet(roi_margin=0.2)
    fp32_ir = export_ir(AllCuts(net.to(memory_format=torch.contiguous_format)), folder / "fp32")  # type: ignore[call-overload]
    if calibration_rois is None:
        calibration_rois = np.random.default_rng(0).integers(0, 256, (64, 256, 256), dtype=np.uint8)
    calibration = nncf.Dataset([normalise(r) for r in calibration_rois])
    quantised = nncf.quantize(
        ov.Core().read_model(str(fp32_ir)), calibration, subset_size=len(calibration_rois), fast_bias_correction=False
    )
    (folder / "int8").mkdir(parents=True, exist_ok=True)
    path = folder / "int8" / "model.xml"
    ov.save_model(quantised, str(path), compress_to_fp16=False)
    return path


def _ov_conv_gflops(dtype: str, repetitions: int) -> float:
    """One 3x3 conv 256->256 on 32x32 through OpenVINO: f32, bf16 (precision hint) or int8 (FakeQuantize)."""
    import openvino as ov
    import openvino.opset13 as ops

    x = ops.parameter(list(PEAK_SHAPE), ov.Type.f32)
    w = np.random.default_rng(0).standard_normal((256, 256, 3, 3)).astype(np.float32) * 0.05
    src: object = x
    weights: object = ops.constant(w)
    if dtype == "int8":
        lo, hi = ops.constant(np.float32(-4.0)), ops.constant(np.float32(4.0))
        src = ops.fake_quantize(x, lo, hi, lo, hi, 256)
        wl, wh = ops.constant(np.float32(-0.3)), ops.constant(np.float32(0.3))
        weights = ops.fake_quantize(ops.constant(w), wl, wh, wl, wh, 255)
    conv = ops.convolution(src, weights, [1, 1], [1, 1], [1, 1], [1, 1])
    model = ov.Model([conv], [x])
    hint = "bf16" if dtype == "bf16" else "f32"
    compiled = ov.Core().compile_model(
        model, "CPU", {"INFERENCE_NUM_THREADS": 1, "PERFORMANCE_HINT": "LATENCY", "INFERENCE_PRECISION_HINT": hint}
    )
    req = compiled.create_infer_request()
    data = np.random.default_rng(1).standard_normal(PEAK_SHAPE).astype(np.float32)
    ms = _median_ms(lambda: req.infer({0: data}), repetitions, warmup=5)
    return PEAK_GFLOP / (ms / 1e3)


@torch.no_grad()
def _torch_conv_gflops(bf16: bool, repetitions: int) -> float:
    conv = torch.nn.Conv2d(256, 256, 3, padding=1, bias=False).eval().to(memory_format=torch.channels_last)  # type: ignore[call-overload]
    x = torch.randn(PEAK_SHAPE).contiguous(memory_format=torch.channels_last)

    def run() -> None:
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            conv(x)

    return PEAK_GFLOP / (_median_ms(run, repetitions, warmup=5) / 1e3)


def peak_gflops(repetitions: int) -> dict[str, float]:
    """The fastest measured 3x3 convolution per dtype, GFLOP/s (int8: GOP/s)."""
    return {
        "fp32": max(_torch_conv_gflops(False, repetitions), _ov_conv_gflops("f32", repetitions)),
        "bf16": max(_torch_conv_gflops(True, repetitions), _ov_conv_gflops("bf16", repetitions)),
        "int8": _ov_conv_gflops("int8", repetitions),
    }


def per_tag_post_ms(repetitions: int = 2000) -> dict[str, float]:
    """Median ms per tag, one thread, on a typical tag (1.5 m, tilted): the edge width the robot measures,
    keypoint fusion and PnP on the edge."""
    rng = np.random.default_rng(0)
    unit_to_image = np.array([[120.0, 14.0, 580.0], [-9.0, 110.0, 300.0], [0.0002, -0.0001, 1.0]])
    unit = np.array([[x, y] for y in (0, 1 / 3, 2 / 3, 1) for x in (0, 1 / 3, 2 / 3, 1)])
    keypoints = apply_homography(unit_to_image, unit) + rng.normal(0, 0.2, (16, 2))
    corners = keypoints[list(CORNER_KEYPOINTS)] + rng.normal(0, 0.1, (4, 2))
    roi_to_image = np.array([[0.5, 0.0, 540.0], [0.0, 0.5, 260.0], [0.0, 0.0, 1.0]])
    fusion = KeypointFusion(keypoint_sigma_roi_px=0.3, corner_sigma_px=0.15)
    camera, obj = default_camera(), lattice_in_tag(0.15)

    def median_ms(fn: Callable[[], object]) -> float:
        return _median_ms(fn, repetitions, warmup=0)

    roi = np.full((256, 256), 200, np.uint8)
    roi[51:205, 51:205] = 30
    return {
        "edge_width": median_ms(lambda: edge_width_px(roi, roi_to_image)),
        "fusion": median_ms(lambda: fusion.apply(keypoints, corners, roi_to_image, 2.0)),
        "pnp": median_ms(lambda: solve_planar_pnp(camera, obj, keypoints)),
    }


def main() -> None:
    """Print the table."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--weights", type=Path, default=Path("models"))
    ap.add_argument("--repetitions", type=int, default=30)
    ap.add_argument("--data", type=Path, help="a data set (splittag data synth): calibration + keypoint error")
    ap.add_argument("--samples", type=int, default=1000, help="test ROIs for the keypoint error")
    ap.add_argument(
        "--onnx",
        action="store_true",
        help="also `splittag export --format onnx` fp32 and int8 in ONNX Runtime (the int8 quantised here, ~1 min)",
    )
    args = ap.parse_args()
    print(f"CPU: {cpu_label()}", flush=True)
    torch.set_num_threads(1)
    model = load_model(args.weights)
    columns: dict[str, list[float]] = {}
    columns["eager fp32"] = [t.median_ms for t in profile_cuts(model, variant="fp32", repetitions=args.repetitions)]
    columns["bf16"] = [
        t.median_ms for t in profile_cuts(model, variant="bf16-channels-last", repetitions=args.repetitions)
    ]
    ours = OpenVINOSplitNet(variant_path(args.weights, "int8"), threads=1)
    columns["int8 (ours)"] = _ov_cumulative_ms(ours, args.repetitions)
    errors: dict[str, float] = {}
    test_rois = test_kp = calibration = None
    if args.data is not None:
        from shared.datasets.shards import load_dataset

        ds = load_dataset(args.data)
        rows = ds.split("test")[: args.samples]
        test_rois, test_kp = ds.arrays["roi"][rows], ds.arrays["keypoints"][rows]
        calibration = ds.arrays["roi"][np.random.default_rng(1).permutation(ds.split("train"))[:300]]
    with tempfile.TemporaryDirectory() as tmp:
        reference = OpenVINOSplitNet(reference_int8_ir(args.weights, Path(tmp), calibration), threads=1)
        columns["OpenVINO int8 (ref)"] = _ov_cumulative_ms(reference, args.repetitions)
        onnx_folders: dict[str, Path] = {}
        if args.onnx:
            from shared.datasets.synth import CALIBRATION_SEED, mixed_rois
            from shared.model.export import export

            if calibration is None:
                calibration, _ = mixed_rois(300, CALIBRATION_SEED)  # what `splittag export` calibrates on
            for precision in ("fp32", "int8"):
                folder = Path(tmp) / f"onnx_{precision}"
                export(args.weights, folder, fmt="onnx", precision=precision, calibration=calibration)
                onnx_folders[f"ORT {precision} (export)"] = folder
                columns[f"ORT {precision} (export)"] = _ort_cumulative_ms(folder, args.repetitions)
        if test_rois is not None and test_kp is not None:
            for name, run in (
                ("eager fp32", lambda r: run_network(model, r)),
                ("bf16", lambda r: run_network(model, r, bf16=True)),
                ("int8 (ours)", lambda r: ours.tail(r, 0)),
                ("OpenVINO int8 (ref)", lambda r: reference.tail(r, 0)),
                *((name, lambda r, f=folder: _ort_keypoints(f, r)) for name, folder in onnx_folders.items()),
            ):
                pred = np.concatenate([run(test_rois[i : i + 64]) for i in range(0, len(test_rois), 64)])
                errors[name] = float(e_px(pred, test_kp).mean())
    peak = peak_gflops(args.repetitions)
    names = list(columns)
    print(
        f"1 thread, batch 1, median of {args.repetitions}; C(k) = cumulative head time in ms, S(k) = one tag's "
        "tensor on the wire (codec fp16: the ROI uint8, feature maps float16, keypoints float32)"
    )
    print(f"{'k':>2} {'cut':<10} {'S(k) kB':>9}" + "".join(f"{n:>21}" for n in names))
    for cut in CUTS:
        cells = "".join(f"{columns[n][cut.k]:>21.2f}" for n in names)
        print(f"{cut.k:>2} {cut.name:<10} {cut.tensor_bytes('fp16') / 1024:>9.2f}{cells}")
    full = {n: columns[n][-1] for n in names}
    dtype_of = {
        "eager fp32": "fp32",
        "bf16": "bf16",
        "int8 (ours)": "int8",
        "OpenVINO int8 (ref)": "int8",
        "ORT fp32 (export)": "fp32",
        "ORT int8 (export)": "int8",
    }
    print(
        "peak (3x3 conv 256->256 @ 32x32, fastest of PyTorch/OpenVINO): "
        + ", ".join(f"{d} {g:.0f} G/s" for d, g in peak.items())
    )
    for n in names:
        rate = NETWORK_GFLOP / (full[n] / 1e3)
        err = (
            f"; e_px {errors[n]:.4f} ({errors[n] - errors['eager fp32']:+.4f} vs fp32, {len(test_rois)} test ROIs)"
            if errors and test_rois is not None
            else ""
        )
        print(
            f"  {n:<20} full network {full[n]:7.2f} ms = {rate:6.0f} G/s = {100 * rate / peak[dtype_of[n]]:5.1f} % of "
            f"{dtype_of[n]} peak; {full['eager fp32'] / full[n]:.2f}x eager fp32{err}"
        )
    ref = full["OpenVINO int8 (ref)"]
    print(f"int8 (ours) / OpenVINO int8 (ref): {full['int8 (ours)'] / ref:.2f}x (full network)")
    post = per_tag_post_ms()
    print(
        f"beside the network, per tag: edge width (robot) {post['edge_width']:.3f} ms, keypoint fusion (edge) "
        f"{post['fusion']:.3f} ms, PnP {post['pnp']:.3f} ms"
    )


if __name__ == "__main__":
    main()
