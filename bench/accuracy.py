"""Keypoint and pose accuracy on independently rendered images, one column group per method.

The images come from bench/tagrender.py, which shares no code with the training-data generator, so a
learned method cannot win by fitting its own renderer. Every method sees the image and the camera
matrix only; the bench matches its predictions to the truth by id, solves the pose itself with the
tag size from the truth (IPPE_SQUARE on 4 corners, IPPE on 16 lattice points) and bins the errors by
motion blur, distance, tilt and occlusion. Always in the table: AprilTag 3 and OpenCV's ArUco (36h11) as a
user runs them, the product's line-quad proposer alone, and the product's stage 1 (all three, merged and
gated); with --weights, the whole chain.

    .venv/bin/python -m bench.accuracy --n 600 --seed 0 [--json out.json] [--weights models] [--workers 2]

Metrics per method and bin: detection % (right id), corner error (px, per corner), keypoint error over the 16
lattice points (kp16, px; a corners4 method's lattice is its corners' homography), e_t (cm), e_r (deg),
the lattice's signed scale bias (least-squares scale of the predicted 16 points about their centroid
against the truth's, in %; a corners4 method's lattice is its corners' homography), its scale along the
motion blur's direction on images blurred by >= 3 px (blur-axis %: a blurred black square that looks
narrower along the blur shortens the grid there, which PnP reads as a tilt), wrong ids (a
decoded tag on a true tag with another id) and ghosts (a decoded tag where there is none).
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import shlex
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Final, Literal

import cv2
import numpy as np
import pupil_apriltags
from numpy.typing import NDArray

from bench.machine import cpu_label
from bench.tagrender import CORNER_INDICES, RenderSettings, Sample, TagTruth, lattice_in_tag, render_sample
from shared.vision.detector import destroy_detector

FloatArray = NDArray[np.float64]
PointLayout = Literal["corners4", "lattice16"]


@dataclass(frozen=True)
class Prediction:
    """One tag a method reports: its id and its points in OpenCV pixel coordinates."""

    tag_id: int
    points_px: FloatArray  # (4, 2) TL, TR, BR, BL for "corners4"; (16, 2) row-major lattice for "lattice16"
    point_layout: PointLayout


Method = Callable[[NDArray[np.uint8], FloatArray], list[Prediction]]


# ----------------------------------------------------------------------------------------------------
# Methods


class AprilTagMethod:
    """AprilTag 3 (pupil-apriltags) as the product's stage 1 runs its first proposer: corners only, +0.5 px removed.

    The defaults mirror the product's stage-1 settings (quad_decimate 2, refine_edges, sharpening 0.25,
    hamming <= 1, decision margin >= 20); they are restated here so the baseline shares nothing with the
    product but the workaround that frees pupil-apriltags' detector safely.
    """

    # pupil-apriltags reports p0..p3 = BL, BR, TR, TL, with pixel centres at +0.5 against OpenCV's.
    _TO_TL_TR_BR_BL: Final[list[int]] = [3, 2, 1, 0]
    _OFFSET_PX: Final[float] = 0.5

    def __init__(
        self,
        *,
        quad_decimate: float = 2.0,
        decode_sharpening: float = 0.25,
        max_hamming: int = 1,
        min_decision_margin: float = 20.0,
    ) -> None:
        self._det: pupil_apriltags.Detector | None = pupil_apriltags.Detector(
            families="tag36h11",
            nthreads=1,
            quad_decimate=quad_decimate,
            quad_sigma=0.0,
            refine_edges=True,
            decode_sharpening=decode_sharpening,
        )
        self.max_hamming = max_hamming
        self.min_decision_margin = min_decision_margin

    def __call__(self, image: NDArray[np.uint8], camera_matrix: FloatArray) -> list[Prediction]:
        """Decoded tags of one grayscale image (the camera matrix is not needed for corners)."""
        if self._det is None:
            raise RuntimeError("AprilTagMethod used after close()")
        out = []
        for r in self._det.detect(np.ascontiguousarray(image)):
            if r.hamming > self.max_hamming or r.decision_margin < self.min_decision_margin:
                continue
            corners = np.asarray(r.corners, np.float64)[self._TO_TL_TR_BR_BL] - self._OFFSET_PX
            out.append(Prediction(int(r.tag_id), corners, "corners4"))
        return out

    def close(self) -> None:
        """Free the C detector before its tag family (pupil-apriltags 1.0.4 frees them the other way
        round in __del__, a use-after-free); idempotent."""
        det, self._det = self._det, None
        if det is not None:
            # A library workaround, not the product under test: the same safe order the product uses.
            destroy_detector(det)


class ArucoMethod:
    """OpenCV's ArUco detector on its AprilTag 36h11 dictionary, OpenCV's default parameters plus
    sub-pixel corners: what an OpenCV user reaches for. OpenCV's marker images are AprilTag's canonical
    tags rotated by 180 deg, so its corners c0..c3 are the canonical BR, BL, TL, TR."""

    _TO_TL_TR_BR_BL: Final[list[int]] = [2, 3, 0, 1]

    def __init__(self) -> None:
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        self._det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11), params)

    def __call__(self, image: NDArray[np.uint8], camera_matrix: FloatArray) -> list[Prediction]:
        """Decoded tags of one grayscale image."""
        corners, ids, _ = self._det.detectMarkers(image)
        if ids is None:
            return []
        return [
            Prediction(int(i), np.asarray(c, np.float64).reshape(4, 2)[self._TO_TL_TR_BR_BL], "corners4")
            for c, i in zip(corners, ids.ravel(), strict=True)
        ]


def stage1_method(
    quad_decimate: float = 2.0, *, aruco: bool = True, lines: bool = True, soft_decode: bool = True
) -> Method:
    """The product's stage 1 alone (shared.vision.proposals.Stage1Detector: AprilTag 3, then the gated
    ArUco proposer and the line-quad proposer) as a "corners4" method; imports the project here only."""
    from shared.vision.detector import DetectorSettings
    from shared.vision.linequads import LineQuadSettings
    from shared.vision.proposals import ArucoSettings, FullResSettings, Stage1Detector, Stage1Settings

    detector = Stage1Detector(
        Stage1Settings(
            apriltag=DetectorSettings(quad_decimate=quad_decimate),
            aruco=ArucoSettings(enabled=aruco),
            lines=LineQuadSettings(enabled=lines, soft_decode=soft_decode),
            full_res=FullResSettings(enabled=False),  # unrelated single images: no history to carry
        )
    )

    def method(image: NDArray[np.uint8], camera_matrix: FloatArray) -> list[Prediction]:
        return [Prediction(d.tag_id, d.corners_px, "corners4") for d in detector.detect(image)]

    return method


def line_quads_method(*, soft_decode: bool = True) -> Method:
    """The product's line-quad proposer alone (shared.vision.linequads) as a "corners4" method."""
    from shared.vision.linequads import LineQuadProposer, LineQuadSettings

    proposer = LineQuadProposer(LineQuadSettings(soft_decode=soft_decode))

    def method(image: NDArray[np.uint8], camera_matrix: FloatArray) -> list[Prediction]:
        return [Prediction(d.tag_id, d.corners_px, "corners4") for d in proposer.detect(image)]

    return method


class SplittagUnavailable(RuntimeError):
    """The product's perception chain could not be imported or loaded."""


def splittag_method(
    weights_dir: Path, *, fuse: bool = True, precision: str = "fp32", soft_decode: bool = True, views: int = 1
) -> Method:
    """The product's chain (stage 1 -> ROI -> split network) as a "lattice16" method; imports the project here only.

    `fuse=True` is the product's default (the lattice fitted to the network's points and stage 1's
    corners with the sigmas calibrated into the weights' config.json); `fuse=False` scores the
    network's 16 points as they are. `precision`: fp32 (PyTorch, as `splittag detect`), bf16, or int8
    (the weights folder's OpenVINO variant). `views`: test-time views per ROI (shared.model.views).
    The tag map's size only affects `perceive`'s own pose, which the bench ignores (it solves the pose
    from the keypoints with the true size).
    """
    from shared.model.runtime import TorchSplitNet, load_split_net
    from shared.model.views import with_views
    from shared.model.weights import load_keypoint_fusion, load_model
    from shared.perception.single import perceive
    from shared.vision.camera import CameraIntrinsics
    from shared.vision.linequads import LineQuadSettings
    from shared.vision.proposals import FullResSettings, Stage1Detector, Stage1Settings
    from shared.vision.tagmap import TagMapFile

    try:
        model = (
            load_model(Path(weights_dir)) if precision == "fp32" else load_split_net(Path(weights_dir), precision)  # type: ignore[arg-type]
        )
        if views > 1:
            model = with_views(TorchSplitNet(model, bf16=False) if precision == "fp32" else model, views)  # type: ignore[arg-type]
        fusion = load_keypoint_fusion(Path(weights_dir)) if fuse else None
    except Exception as exc:
        raise SplittagUnavailable(f"cannot load weights from {weights_dir}: {exc}") from exc
    # the services' stage 1, on unrelated single images: no frame history (full-resolution windows off)
    detector = Stage1Detector(
        Stage1Settings(lines=LineQuadSettings(soft_decode=soft_decode), full_res=FullResSettings(enabled=False))
    )
    tag_map = TagMapFile(default_size_m=0.15)

    def method(image: NDArray[np.uint8], camera_matrix: FloatArray) -> list[Prediction]:
        camera = CameraIntrinsics(
            width=int(image.shape[1]),
            height=int(image.shape[0]),
            fx=float(camera_matrix[0, 0]),
            fy=float(camera_matrix[1, 1]),
            cx=float(camera_matrix[0, 2]),
            cy=float(camera_matrix[1, 2]),
            distortion_model="none",
            distortion=[],
        )
        results = perceive(image, camera=camera, detector=detector, model=model, tag_map=tag_map, fusion=fusion)
        return [
            Prediction(int(r.detection.tag_id), np.asarray(r.keypoints_px, np.float64), "lattice16")
            for r in results
            if r.keypoints_px is not None
        ]

    return method


# ----------------------------------------------------------------------------------------------------
# Scoring one image


@dataclass
class TagScore:
    """A method's result on one true tag (errors are None when it was not detected)."""

    detected: bool
    corner_errors_px: list[float] = field(default_factory=list)
    lattice_errors_px: list[float] = field(default_factory=list)
    e_t_cm: float | None = None
    e_r_deg: float | None = None
    scale_bias_pct: float | None = None
    blur_axis_scale_pct: float | None = None  # the lattice's scale along the blur (images blurred >= 3 px)


@dataclass
class ImageScore:
    """A method's result on one image: a score per true tag, plus its wrong ids and ghosts."""

    tags: list[TagScore]
    wrong_ids: int
    ghosts: int


def _square_object_points_ippe(size_m: float) -> FloatArray:
    """IPPE_SQUARE's required object points (its y up): TL, TR, BR, BL on screen when facing it."""
    h = size_m / 2
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


# IPPE_SQUARE's frame is ours rotated by 180 deg about x: (x, y, z)_ours = (x, -y, -z)_ippe.
_OURS_FROM_IPPE: Final[FloatArray] = np.diag([1.0, -1.0, -1.0])


def solve_pose(
    points_px: FloatArray, layout: PointLayout, size_m: float, camera_matrix: FloatArray
) -> FloatArray | None:
    """camera_from_tag (4x4) from a method's points: IPPE_SQUARE on corners, IPPE on the lattice."""
    if layout == "corners4":
        ok, rvec, tvec = cv2.solvePnP(
            _square_object_points_ippe(size_m), points_px, camera_matrix, None, flags=cv2.SOLVEPNP_IPPE_SQUARE
        )
        fix = _OURS_FROM_IPPE
    else:
        ok, rvec, tvec = cv2.solvePnP(lattice_in_tag(size_m), points_px, camera_matrix, None, flags=cv2.SOLVEPNP_IPPE)
        fix = np.eye(3)
    if not ok:
        return None
    rot, _ = cv2.Rodrigues(rvec)
    pose = np.eye(4)
    pose[:3, :3] = np.asarray(rot) @ fix
    pose[:3, 3] = np.asarray(tvec).ravel()
    return pose


def lattice_points(pred: Prediction, size_m: float) -> FloatArray:
    """The 16 lattice points a prediction implies (through its corners' homography for corners4)."""
    if pred.point_layout == "lattice16":
        return pred.points_px
    lat = lattice_in_tag(size_m)[:, :2]
    src = lat[list(CORNER_INDICES)]
    hom = cv2.getPerspectiveTransform(src.astype(np.float32), pred.points_px.astype(np.float32)).astype(np.float64)
    q = lat @ hom[:, :2].T + hom[:, 2]
    return q[:, :2] / q[:, 2:3]


def scale_bias_pct(pred_px: FloatArray, true_px: FloatArray) -> float:
    """Signed least-squares scale of the predicted points about their centroid against the truth, in %."""
    p = pred_px - pred_px.mean(axis=0)
    q = true_px - true_px.mean(axis=0)
    return float((np.sum(p * q) / np.sum(q * q) - 1.0) * 100.0)


def axis_scale_pct(pred_px: FloatArray, true_px: FloatArray, direction: FloatArray) -> float:
    """Signed scale of the predicted points along one image direction against the truth, in %: the
    least-squares linear map from the truth's centred points to the prediction's, read along the
    (unit) direction."""
    p = pred_px - pred_px.mean(axis=0)
    q = true_px - true_px.mean(axis=0)
    m, *_ = np.linalg.lstsq(q, p, rcond=None)  # p ~ q @ m
    return float((direction @ m.T @ direction - 1.0) * 100.0)


def rotation_error_deg(r_a: FloatArray, r_b: FloatArray) -> float:
    """Angle of the rotation between two rotation matrices, in degrees."""
    c = (np.trace(r_a.T @ r_b) - 1.0) / 2.0
    return math.degrees(math.acos(float(np.clip(c, -1.0, 1.0))))


def _inside_outer_square(point: FloatArray, truth: TagTruth) -> bool:
    outer = truth.corners_px.mean(axis=0) + (truth.corners_px - truth.corners_px.mean(axis=0)) * 1.25
    return cv2.pointPolygonTest(outer.astype(np.float32), (float(point[0]), float(point[1])), False) >= 0


def score_image(
    predictions: list[Prediction],
    truths: list[TagTruth],
    camera_matrix: FloatArray,
    blur_direction: FloatArray | None = None,
) -> ImageScore:
    """Match predictions to true tags by id (nearest centre) and measure each matched tag's errors
    (with the image's motion-blur direction, if any, also the grid's scale along it)."""
    unused = list(predictions)
    scores = []
    for truth in truths:
        centre = truth.corners_px.mean(axis=0)
        same_id = [p for p in unused if p.tag_id == truth.tag_id]
        if not same_id:
            scores.append(TagScore(detected=False))
            continue
        pred = min(same_id, key=lambda p: float(np.linalg.norm(p.points_px.mean(axis=0) - centre)))
        unused.remove(pred)
        lattice = lattice_points(pred, truth.size_m)
        corners = pred.points_px if pred.point_layout == "corners4" else pred.points_px[list(CORNER_INDICES)]
        score = TagScore(
            detected=True,
            corner_errors_px=np.linalg.norm(corners - truth.corners_px, axis=1).tolist(),
            lattice_errors_px=np.linalg.norm(lattice - truth.keypoints_px, axis=1).tolist(),
            scale_bias_pct=scale_bias_pct(lattice, truth.keypoints_px),
            blur_axis_scale_pct=None
            if blur_direction is None
            else axis_scale_pct(lattice, truth.keypoints_px, blur_direction),
        )
        pose = solve_pose(pred.points_px, pred.point_layout, truth.size_m, camera_matrix)
        if pose is not None:
            score.e_t_cm = float(np.linalg.norm(pose[:3, 3] - truth.camera_from_tag[:3, 3]) * 100.0)
            score.e_r_deg = rotation_error_deg(pose[:3, :3], truth.camera_from_tag[:3, :3])
        scores.append(score)
    wrong = sum(1 for p in unused if any(_inside_outer_square(p.points_px.mean(axis=0), t) for t in truths))
    return ImageScore(tags=scores, wrong_ids=wrong, ghosts=len(unused) - wrong)


# ----------------------------------------------------------------------------------------------------
# Bins and the table


@dataclass(frozen=True)
class Bin:
    """A named subset of the images, chosen from a sample's metadata."""

    group: str
    label: str
    contains: Callable[[dict[str, Any]], bool]


def _range_bin(group: str, key: str, lo: float, hi: float, unit: str) -> Bin:
    label = f"{lo:g}-{hi:g} {unit}" if math.isfinite(hi) else f">= {lo:g} {unit}"
    return Bin(group, label, lambda m: lo <= float(m[key]) < hi)


BINS: Final[list[Bin]] = [
    Bin("all", "all", lambda m: True),
    _range_bin("blur", "blur_px", 0, 3, "px"),
    _range_bin("blur", "blur_px", 3, 8, "px"),
    _range_bin("blur", "blur_px", 8, math.inf, "px"),
    # blur that is large for the tag's size (what the fast room of bench/slam.py is full of)
    Bin("blur / tag span", ">= 0.15", lambda m: float(m["blur_px"]) >= 0.15 * float(m["span_px"])),
    _range_bin("distance", "distance_m", 0, 1, "m"),
    _range_bin("distance", "distance_m", 1, 2, "m"),
    _range_bin("distance", "distance_m", 2, 3, "m"),
    _range_bin("distance", "distance_m", 3, math.inf, "m"),
    _range_bin("tilt", "tilt_deg", 0, 30, "deg"),
    _range_bin("tilt", "tilt_deg", 30, 50, "deg"),
    _range_bin("tilt", "tilt_deg", 50, math.inf, "deg"),
    Bin("occluded", "no", lambda m: float(m["occluded_fraction"]) == 0.0),
    Bin("occluded", "yes", lambda m: float(m["occluded_fraction"]) > 0.0),
]


def summarise(records: list[tuple[dict[str, Any], ImageScore]]) -> dict[str, Any]:
    """Detection %, median/p90 errors, median scale bias, wrong ids and ghosts over some images."""
    tags = [t for _, img in records for t in img.tags]
    found = [t for t in tags if t.detected]

    def stats(values: list[float]) -> dict[str, float | None]:
        if not values:
            return {"median": None, "p90": None, "mean": None}
        a = np.asarray(values, np.float64)
        return {"median": float(np.median(a)), "p90": float(np.percentile(a, 90)), "mean": float(a.mean())}

    return {
        "images": len(records),
        "tags": len(tags),
        "detected": len(found),
        "detection_pct": 100.0 * len(found) / len(tags) if tags else None,
        "corner_err_px": stats([e for t in found for e in t.corner_errors_px]),
        "lattice_err_px": stats([e for t in found for e in t.lattice_errors_px]),
        "e_t_cm": stats([t.e_t_cm for t in found if t.e_t_cm is not None]),
        "e_r_deg": stats([t.e_r_deg for t in found if t.e_r_deg is not None]),
        "scale_bias_pct": stats([t.scale_bias_pct for t in found if t.scale_bias_pct is not None]),
        "blur_axis_scale_pct": stats([t.blur_axis_scale_pct for t in found if t.blur_axis_scale_pct is not None]),
        "wrong_ids": sum(img.wrong_ids for _, img in records),
        "ghosts": sum(img.ghosts for _, img in records),
    }


def _pair(s: dict[str, float | None], digits: int) -> str:
    if s["median"] is None or s["p90"] is None:
        return "-"
    return f"{s['median']:.{digits}f}/{s['p90']:.{digits}f}"


_COLUMNS: Final[list[tuple[str, int]]] = [
    ("det %", 6),
    ("corner px", 11),
    ("kp16 px", 11),
    ("e_t cm", 11),
    ("e_r deg", 11),
    ("scale %", 7),
    ("blur-axis %", 11),
    ("wrong", 5),
    ("ghost", 5),
]


def _cells(summary: dict[str, Any]) -> list[str]:
    det = summary["detection_pct"]
    scale = summary["scale_bias_pct"]["median"]
    along = summary["blur_axis_scale_pct"]["median"]
    return [
        "-" if det is None else f"{det:.1f}",
        _pair(summary["corner_err_px"], 2),
        _pair(summary["lattice_err_px"], 2),
        _pair(summary["e_t_cm"], 2),
        _pair(summary["e_r_deg"], 2),
        "-" if scale is None else f"{scale:+.2f}",
        "-" if along is None else f"{along:+.2f}",
        str(summary["wrong_ids"]),
        str(summary["ghosts"]),
    ]


def format_table(table: dict[str, dict[str, dict[str, Any]]], method_names: list[str]) -> str:
    """Rows = bins, one column group per method: det %, corner / e_t / e_r as median/p90, scale, wrong, ghost."""
    label_w = 22
    group_w = sum(w for _, w in _COLUMNS) + 2 * (len(_COLUMNS) - 1)
    lines = [" " * label_w + " | " + " | ".join(f"{name:^{group_w}}" for name in method_names)]
    header = "  ".join(f"{title:>{w}}" for title, w in _COLUMNS)
    lines.append(f"{'bin (images)':<{label_w}} | " + " | ".join(header for _ in method_names))
    lines.append("-" * len(lines[-1]))
    previous_group = "all"
    for key, per_method in table.items():
        group = key.split(":", 1)[0]
        if group != previous_group:
            lines.append("")
            previous_group = group
        first = per_method[method_names[0]]
        label = f"{key} ({first['images']})"
        groups = [
            "  ".join(f"{c:>{w}}" for c, (_, w) in zip(_cells(per_method[m]), _COLUMNS, strict=True))
            for m in method_names
        ]
        lines.append(f"{label:<{label_w}} | " + " | ".join(groups))
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------------------
# Running


def _render(job: tuple[int, int, RenderSettings]) -> Sample:
    index, seed, settings = job
    return render_sample(index, seed, settings)


def _samples(n: int, seed: int, settings: RenderSettings, workers: int) -> Iterator[Sample]:
    jobs = [(i, seed, settings) for i in range(n)]
    if workers <= 1:
        yield from map(_render, jobs)
        return
    with multiprocessing.get_context("spawn").Pool(workers) as pool:
        yield from pool.imap(_render, jobs, chunksize=4)


# Below this the blur direction says little about a grid's shape.
MIN_BLUR_FOR_AXIS_PX: Final[float] = 3.0


def _blur_direction(meta: dict[str, Any]) -> FloatArray | None:
    """The image's motion-blur direction (unit, image x right, y down), if it is blurred enough."""
    if float(meta.get("blur_px", 0.0)) < MIN_BLUR_FOR_AXIS_PX:
        return None
    a = math.radians(float(meta["blur_angle_deg"]))
    return np.array([math.cos(a), math.sin(a)])


def run(
    *, n: int, seed: int, settings: RenderSettings, methods: dict[str, Method], workers: int = 1
) -> tuple[dict[str, dict[str, dict[str, Any]]], list[dict[str, Any]], dict[str, float]]:
    """Render n images, run every method on each, and summarise by bin: (table, per-image rows, seconds)."""
    k = settings.camera_matrix()
    per_method: dict[str, list[tuple[dict[str, Any], ImageScore]]] = {name: [] for name in methods}
    rows: list[dict[str, Any]] = []
    secs = {"render": 0.0, **{name: 0.0 for name in methods}}
    t_render = time.perf_counter()
    for sample in _samples(n, seed, settings, workers):
        secs["render"] += time.perf_counter() - t_render
        row: dict[str, Any] = {"meta": {k_: v for k_, v in sample.meta.items() if k_ != "occluder_polygon_px"}}
        for name, method in methods.items():
            t0 = time.perf_counter()
            preds = method(sample.image, k)
            secs[name] += time.perf_counter() - t0
            score = score_image(preds, sample.tags, k, _blur_direction(sample.meta))
            per_method[name].append((sample.meta, score))
            row[name] = asdict(score)
        rows.append(row)
        t_render = time.perf_counter()
    table: dict[str, dict[str, dict[str, Any]]] = {}
    for b in BINS:
        key = b.label if b.group == "all" else f"{b.group}: {b.label}"
        table[key] = {name: summarise([r for r in recs if b.contains(r[0])]) for name, recs in per_method.items()}
    return table, rows, secs


def main(argv: list[str] | None = None) -> None:
    """Parse the command line, run the benchmark, print the table (and write JSON when asked)."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=600, help="images to render")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, help="write the table, the settings and per-image scores here")
    ap.add_argument("--weights", type=Path, help="add the split network's column (a weights folder, e.g. models)")
    ap.add_argument("--workers", type=int, default=1, help="rendering processes (the methods run in this one)")
    ap.add_argument(
        "--precisions",
        nargs="+",
        default=["fp32"],
        choices=["fp32", "bf16", "int8"],
        help="the split network's columns, one pair per precision (int8: the weights' OpenVINO variant)",
    )
    ap.add_argument(
        "--soft-decode",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="stage 1 with the line quads' blind soft decode (stage1.lines.soft_decode; on by default)",
    )
    ap.add_argument(
        "--views",
        type=int,
        nargs="+",
        default=[1],
        choices=[1, 2, 4, 8],
        help="test-time views per ROI (shared/model/views.py): the split network's columns per count",
    )
    ap.add_argument(
        "--gamma",
        type=float,
        nargs=2,
        metavar=("LO", "HI"),
        default=None,
        help="the rendered camera response's gamma range (default: the renderer's 0.6-1.6; an sRGB camera "
        "is 2.2: --gamma 2.2 2.2)",
    )
    args = ap.parse_args(argv)
    if args.gamma is not None and not 0 < args.gamma[0] <= args.gamma[1]:
        ap.error(f"--gamma needs 0 < LO <= HI, got {args.gamma}")
    soft = args.soft_decode
    command = "python -m bench.accuracy " + shlex.join(sys.argv[1:] if argv is None else argv)
    print(f"CPU: {cpu_label()}")
    print(f"command: {command}", flush=True)

    settings = RenderSettings() if args.gamma is None else RenderSettings(gamma=(args.gamma[0], args.gamma[1]))
    apriltag = AprilTagMethod()
    methods: dict[str, Method] = {
        "apriltag3 (corners)": apriltag,
        "opencv aruco (corners)": ArucoMethod(),
        "line quads (corners)": line_quads_method(soft_decode=soft),
        "splittag stage 1 (corners)": stage1_method(soft_decode=soft),
    }
    if args.weights is not None:
        from shared.model.weights import load_keypoint_fusion

        for precision in args.precisions:
            for views in args.views:
                tag = ("" if precision == "fp32" else f" {precision}") + ("" if views == 1 else f" x{views}")
                methods[f"splittag{tag} (network)"] = splittag_method(
                    args.weights, fuse=False, precision=precision, soft_decode=soft, views=views
                )
                if load_keypoint_fusion(args.weights) is not None:
                    methods[f"splittag{tag} (fused)"] = splittag_method(
                        args.weights, precision=precision, soft_decode=soft, views=views
                    )
    t0 = time.perf_counter()
    try:
        table, rows, secs = run(n=args.n, seed=args.seed, settings=settings, methods=methods, workers=args.workers)
    finally:
        apriltag.close()
    wall = time.perf_counter() - t0

    names = list(methods)
    print(
        f"\n{args.n} images from bench/tagrender.py (seed {args.seed}), 1 tag each; "
        "cells: median/p90, scale = median signed lattice scale bias, blur-axis = its median along the blur "
        f"(images blurred >= {MIN_BLUR_FOR_AXIS_PX:g} px); camera gamma {settings.gamma[0]:g}-{settings.gamma[1]:g}"
    )
    print(format_table(table, names))
    timing = ", ".join(f"{name} {s:.1f} s" for name, s in secs.items())
    print(f"\nwall {wall:.1f} s ({timing})")
    if args.json is not None:
        doc = {
            "command": command,
            "cpu": cpu_label(),
            "render_settings": asdict(settings),
            "methods": names,
            "table": table,
            "seconds": {"wall": wall, **secs},
            "images": rows,
        }
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(doc, indent=1))
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
