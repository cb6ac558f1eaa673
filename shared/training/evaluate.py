"""`splittag eval`: keypoint errors (paper's e_px, e_rel) and the pose comparison against the
classical baseline (PnP on the 4 AprilTag corners), over a whole data set split."""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np
from tqdm import tqdm

from shared.datasets.generate import DISTANCE_BINS_M, TILT_BINS_DEG
from shared.datasets.shards import Dataset
from shared.model.net import SplitKeypointNet
from shared.model.runtime import SplitNet
from shared.perception.single import run_network
from shared.training.train import evaluate_arrays
from shared.vision.camera import CameraIntrinsics
from shared.vision.fusion import KeypointFusion, edge_width_px, roi_zoom
from shared.vision.geometry import (
    CORNER_KEYPOINTS,
    apply_homography,
    corners_in_tag,
    keypoints_to_image,
    lattice_in_tag,
    roi_square,
)
from shared.vision.metrics import rotation_error_deg, summary, translation_error_cm
from shared.vision.pnp import solve_planar_pnp


def predict_dataset(
    model: SplitKeypointNet | SplitNet, ds: Dataset, rows: np.ndarray, *, bf16: bool = False, batch: int = 64
) -> np.ndarray:
    """Normalised keypoint predictions for the given rows: PyTorch weights (fp32, or bf16 with `bf16`) or
    a SplitNet at its own precision (the whole network: tail from cut 0)."""
    out = []
    for i in tqdm(range(0, len(rows), batch), desc="inference", leave=False):
        rois = ds.arrays["roi"][rows[i : i + batch]]
        if isinstance(model, SplitKeypointNet):
            out.append(run_network(model, rois, bf16=bf16))
        else:
            out.append(model.tail(rois, 0))
    return np.concatenate(out) if out else np.zeros((0, 16, 2), np.float32)


def _binned(values: dict[str, np.ndarray], key: np.ndarray, edges: tuple[float, ...]) -> list[dict[str, Any]]:
    rows = []
    for lo, hi in itertools.pairwise(edges):
        sel = (key >= lo) & (key < hi)
        row: dict[str, Any] = {"range": [lo, hi if hi < 1e8 else None], "n": int(sel.sum())}
        for name, v in values.items():
            row[name] = summary(v[sel]) if sel.any() else None
        rows.append(row)
    return rows


def pose_comparison(camera: CameraIntrinsics, ds: Dataset, rows: np.ndarray, pred: np.ndarray) -> dict[str, Any]:
    """e_t (cm) and e_r (deg) of PnP on the 16 predicted keypoints vs on the 4 AprilTag corners."""
    a = ds.arrays
    n = len(rows)
    et = {"keypoints": np.zeros(n), "corners": np.zeros(n)}
    er = {"keypoints": np.zeros(n), "corners": np.zeros(n)}
    wrong = {"keypoints": np.zeros(n, bool), "corners": np.zeros(n, bool)}
    for j, i in enumerate(rows):
        size = float(a["tag_size_m"][i])
        gt = a["camera_from_tag"][i]
        kp_px = keypoints_to_image(pred[j], a["roi_to_image"][i])
        for name, cand in (
            ("keypoints", solve_planar_pnp(camera, lattice_in_tag(size), kp_px)),
            ("corners", solve_planar_pnp(camera, corners_in_tag(size), a["corners_px"][i])),
        ):
            et[name][j] = translation_error_cm(cand.camera_from_tag[:3, 3], gt[:3, 3])
            er[name][j] = rotation_error_deg(cand.camera_from_tag[:3, :3], gt[:3, :3])
            wrong[name][j] = rotation_error_deg(cand.alt_camera_from_tag[:3, :3], gt[:3, :3]) < er[name][j]
    values = {
        "e_t_cm_keypoints": et["keypoints"],
        "e_t_cm_corners": et["corners"],
        "e_r_deg_keypoints": er["keypoints"],
        "e_r_deg_corners": er["corners"],
    }
    return {
        "overall": {k: summary(v) for k, v in values.items()},
        "by_distance_m": _binned(values, a["distance_m"][rows], DISTANCE_BINS_M),
        "by_tilt_deg": _binned(values, a["tilt_deg"][rows], TILT_BINS_DEG),
        "wrong_branch_rate": {k: float(v.mean()) for k, v in wrong.items()},
        "different_branch_rate": float((wrong["keypoints"] != wrong["corners"]).mean()),
    }


def evaluate(
    model: SplitKeypointNet | SplitNet,
    ds: Dataset,
    *,
    split: str = "test",
    bf16: bool = False,
    limit: int | None = None,
) -> dict[str, Any]:
    """Everything `splittag eval` writes to its JSON."""
    rows = ds.split(split)[:limit]
    pred = predict_dataset(model, ds, rows, bf16=bf16)
    keypoint_metrics = evaluate_arrays(pred, ds.arrays["keypoints"][rows])
    camera = CameraIntrinsics.model_validate(ds.info["settings"]["camera"])
    return {
        **keypoint_metrics,
        "data": str(ds.root),
        "split": split,
        "kind": ds.info.get("kind"),
        "pose": pose_comparison(camera, ds, rows, pred),
    }


def _robust_sigma(errors: np.ndarray) -> float:
    """Per-coordinate sigma from the median absolute error (1.4826 MAD about zero: unbiased errors)."""
    return float(1.4826 * np.median(np.abs(errors)))


def _fit_sigma_model(cells: list[tuple[float, float, float]]) -> tuple[float, float]:
    """(a, b) with sigma^2 = a^2 x + b^2 y from cells (x, y, measured sigma), non-negative least squares."""
    from scipy.optimize import nnls

    design = np.array([[x, y] for x, y, _ in cells])
    target = np.array([s**2 for _, _, s in cells])
    coef, _ = nnls(design, target)
    return float(np.sqrt(coef[0])), float(np.sqrt(coef[1]))


def _cells(key_a: np.ndarray, key_b: np.ndarray, n_a: int, n_b: int, min_count: int = 20) -> list[np.ndarray]:
    """Quantile cells over two keys: the sample indices of each cell with enough samples."""
    out = []
    qa = np.quantile(key_a, np.linspace(0, 1, n_a + 1))
    qb = np.quantile(key_b, np.linspace(0, 1, n_b + 1))
    for i in range(n_a):
        for j in range(n_b):
            sel = (key_a >= qa[i]) & (key_a <= qa[i + 1]) & (key_b >= qb[j]) & (key_b <= qb[j + 1])
            if sel.sum() >= min_count:
                out.append(np.flatnonzero(sel))
    return out


def calibrate_fusion(
    model: SplitKeypointNet, ds: Dataset, *, split: str = "test", limit: int | None = None, command: str = ""
) -> KeypointFusion:
    """Measure the sigma models keypoint fusion weighs by, on a split the network was not trained on:
    samples whose ROI is warped from stage 1's quad as it is (as at inference), each with its edge
    width; AprilTag's corner error and the network's keypoint error (image pixels) fitted as
    sigma^2 = sigma_0^2 + (slope * width)^2 (the network's sigma_0 in ROI pixels, times the zoom)."""
    a = ds.arrays
    square = roi_square()
    rows = [
        int(i)
        for i in ds.split(split)
        if np.abs(apply_homography(a["roi_to_image"][i], square) - a["corners_px"][i]).max() < 1e-3
    ][:limit]
    if len(rows) < 200:
        raise ValueError(f"{ds.root}: {len(rows)} unperturbed samples in the {split} split; need >= 200")
    pred = predict_dataset(model, ds, np.asarray(rows))
    keep, widths, zooms, net_err, corner_err = [], [], [], [], []
    for j, i in enumerate(rows):
        h = a["roi_to_image"][i]
        width = edge_width_px(a["roi"][i], h)
        if width is None:
            continue
        keep.append(j)
        widths.append(width)
        zooms.append(roi_zoom(h))
        net_err.append(np.abs(keypoints_to_image(pred[j], h) - a["keypoints_px"][i]).ravel())
        corner_err.append(np.abs(a["corners_px"][i] - a["keypoints_px"][i][list(CORNER_KEYPOINTS)]).ravel())
    w, z = np.asarray(widths), np.asarray(zooms)
    # Corners: sigma^2 = c0^2 + c1^2 w^2, cells over the width.
    corner = np.asarray(corner_err)
    cells = [(1.0, float(np.median(w[idx]) ** 2), _robust_sigma(corner[idx])) for idx in _cells(w, w, 8, 1)]
    c0, c1 = _fit_sigma_model(cells)
    # Network: sigma^2 = n0^2 z^2 + n1^2 w^2, cells over width and zoom.
    net = np.asarray(net_err)
    cells = [
        (float(np.median(z[idx] ** 2)), float(np.median(w[idx]) ** 2), _robust_sigma(net[idx]))
        for idx in _cells(w, z, 5, 4)
    ]
    n0, n1 = _fit_sigma_model(cells)
    return KeypointFusion(
        keypoint_sigma_roi_px=round(max(n0, 1e-3), 4),
        keypoint_sigma_per_blur=round(n1, 4),
        corner_sigma_px=round(max(c0, 1e-3), 4),
        corner_sigma_per_blur=round(c1, 4),
        nominal_width_px=round(float(np.median(w)), 3),
        calibrated_on=f"{ds.root} {split} split, {len(keep)} unperturbed samples" + (f": {command}" if command else ""),
    )


def format_report(result: dict[str, Any]) -> str:
    """Human-readable summary of an evaluation."""
    lines = [
        f"{result['kind']} {result['split']} split, {result['n']} samples ({result['data']})",
        f"  e_px  = {result['e_px_mean']:.3f} px  (sigma {result['e_px_std']:.3f})",
        f"  e_rel = {result['e_rel_mean']:.3f} %   (sigma {result['e_rel_std']:.3f})",
        "  pose vs ground truth      mean   median    p90",
    ]
    ov = result["pose"]["overall"]
    for key, label in [
        ("e_t_cm_keypoints", "e_t cm, 16 keypoints"),
        ("e_t_cm_corners", "e_t cm, 4 corners"),
        ("e_r_deg_keypoints", "e_r deg, 16 keypoints"),
        ("e_r_deg_corners", "e_r deg, 4 corners"),
    ]:
        s = ov[key]
        lines.append(f"  {label:<24}{s['mean']:>6.2f} {s['median']:>8.2f} {s['p90']:>6.2f}")
    wb = result["pose"]["wrong_branch_rate"]
    lines.append(
        f"  wrong IPPE branch: keypoints {100 * wb['keypoints']:.1f} %, corners {100 * wb['corners']:.1f} %;"
        f" methods on different branches {100 * result['pose']['different_branch_rate']:.1f} %"
    )
    return "\n".join(lines)
