"""Keypoint and pose error measures exactly as the paper defines them."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from shared.vision.geometry import ROI_SIZE


def e_px(pred_norm: NDArray[np.floating], gt_norm: NDArray[np.floating]) -> NDArray[np.float64]:
    """Per-sample mean keypoint error in ROI pixels: S/K * sum_i ||k_hat_i - k_i|| (S = 256)."""
    d = np.linalg.norm(np.asarray(pred_norm, np.float64) - np.asarray(gt_norm, np.float64), axis=-1)
    return ROI_SIZE * d.mean(axis=-1)


def l_tag(gt_norm: NDArray[np.floating]) -> NDArray[np.float64]:
    """Projected diagonal of the ground-truth grid: S * ||k_max - k_min|| (component-wise extremes)."""
    g = np.asarray(gt_norm, np.float64)
    return ROI_SIZE * np.linalg.norm(g.max(axis=-2) - g.min(axis=-2), axis=-1)


def e_rel(pred_norm: NDArray[np.floating], gt_norm: NDArray[np.floating]) -> NDArray[np.float64]:
    """Per-sample relative keypoint error in percent: e_px / L_tag * 100."""
    return 100.0 * e_px(pred_norm, gt_norm) / l_tag(gt_norm)


def translation_error_cm(t_est: NDArray[np.floating], t_true: NDArray[np.floating]) -> NDArray[np.float64]:
    """||t_hat - t|| in centimetres (inputs in metres, last axis xyz)."""
    return 100.0 * np.linalg.norm(np.asarray(t_est, np.float64) - np.asarray(t_true, np.float64), axis=-1)


def rotation_error_deg(r_est: NDArray[np.floating], r_true: NDArray[np.floating]) -> NDArray[np.float64]:
    """arccos((tr(R_hat R^T) - 1) / 2) in degrees, batched over leading axes."""
    r_est = np.asarray(r_est, np.float64)
    r_true = np.asarray(r_true, np.float64)
    tr = np.einsum("...ij,...ij->...", r_est, r_true)
    return np.degrees(np.arccos(np.clip((tr - 1) / 2, -1.0, 1.0)))


def summary(values: NDArray[np.floating]) -> dict[str, float]:
    """mean, std, median, p90 of a 1-D array."""
    v = np.asarray(values, np.float64)
    return {
        "mean": float(v.mean()),
        "std": float(v.std()),
        "median": float(np.median(v)),
        "p90": float(np.percentile(v, 90)),
        "n": int(v.size),
    }
