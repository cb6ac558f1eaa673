"""Stage 1 on real photos with annotated corners, every method side by side in one run.

The photos (bench/data/apriltag_photos: three NASA Swarmathon photos, 47 annotated tag36h11 tags,
many of them 12-30 px wide) are AprilRobotics/apriltag's own test data: not ours, not rendered. A
method finds an annotated tag when it reports the tag's id with a centre within half the tag's side
of the annotation's. Detections far from every annotation are listed as "other": the annotations
leave out faces seen at grazing angles, so they are not counted as false positives here (the
rendered benches count ghosts exactly).

    .venv/bin/python -m bench.photos [--repetitions 5]

Methods: AprilTag 3 at quad_decimate 2 (the services' stage-1 speed setting) and 1; OpenCV's ArUco
on DICT_APRILTAG_36h11 with OpenCV's defaults; splittag's stage 1 (AprilTag, then the gated ArUco
proposer: shared.vision.proposals) at decimate 2 (robot_infer's default) and 1 (`splittag detect`'s);
and robot_infer's stage 1 on each photo as a still video (its first frame a full-resolution sweep,
the frames after it decimated with full-resolution windows around the small tags seen).
Time: median over repetitions of one detect call per photo, one thread (the sweep frame: one call).
"""

from __future__ import annotations

import argparse
import shlex
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Final

import cv2
import numpy as np
from numpy.typing import NDArray

from bench.accuracy import AprilTagMethod, ArucoMethod, Method, Prediction, line_quads_method, stage1_method
from bench.machine import cpu_label

PHOTOS: Final[Path] = Path(__file__).resolve().parent / "data" / "apriltag_photos"
_PUPIL_OFFSET_PX: Final[float] = 0.5  # the annotations are in AprilTag's pixel convention
_TO_TL_TR_BR_BL: Final[list[int]] = [3, 2, 1, 0]  # ... and corner order (BL, BR, TR, TL)


@dataclass(frozen=True)
class Annotated:
    """One photo and its annotated tags (corners in OpenCV's pixel convention)."""

    name: str
    image: NDArray[np.uint8]
    tags: list[tuple[int, NDArray[np.float64]]]


def parse_annotations(text: str) -> list[tuple[int, NDArray[np.float64]]]:
    """AprilRobotics' format: `id, (x y), (x y), (x y), (x y)` per line, corners BL, BR, TR, TL in the
    +0.5 px convention; returned as TL, TR, BR, BL in OpenCV's."""
    tags = []
    for line in text.splitlines():
        if not line.strip():
            continue
        tag_id, _, rest = line.partition(",")
        points = [[float(v) for v in p.strip(" ()").split()] for p in rest.split("),")]
        tags.append((int(tag_id), np.asarray(points, np.float64)[_TO_TL_TR_BR_BL] - _PUPIL_OFFSET_PX))
    return tags


def load_photos(folder: Path = PHOTOS) -> list[Annotated]:
    """Every `*.jpg` with its `*.txt` annotations, sorted by name."""
    out = []
    for jpg in sorted(folder.glob("*.jpg")):
        image = cv2.imread(str(jpg), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise FileNotFoundError(f"cannot read {jpg}")
        out.append(
            Annotated(jpg.stem, np.asarray(image, np.uint8), parse_annotations(jpg.with_suffix(".txt").read_text()))
        )
    return out


def match(tags: list[tuple[int, NDArray[np.float64]]], found: list[Prediction]) -> tuple[int, int, list[float]]:
    """(annotated tags found, other detections, mean corner error of each found tag in px)."""
    used: set[int] = set()
    errors = []
    for tag_id, corners in tags:
        side = float(np.mean(np.linalg.norm(corners - np.roll(corners, -1, axis=0), axis=1)))
        for j, p in enumerate(found):
            if j in used or p.tag_id != tag_id:
                continue
            if float(np.linalg.norm(p.points_px.mean(axis=0) - corners.mean(axis=0))) < 0.5 * side:
                used.add(j)
                errors.append(float(np.linalg.norm(p.points_px - corners, axis=1).mean()))
                break
    return len(errors), len(found) - len(used), errors


def main() -> None:
    """Run every method on every photo, print one row per method."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repetitions", type=int, default=5)
    args = ap.parse_args()
    print(f"CPU: {cpu_label()}")
    print("command: python -m bench.photos " + shlex.join(sys.argv[1:]), flush=True)
    photos = load_photos()
    total = sum(len(p.tags) for p in photos)
    cv2.setNumThreads(1)
    apriltag_d2, apriltag_d1 = AprilTagMethod(quad_decimate=2.0), AprilTagMethod(quad_decimate=1.0)
    methods: dict[str, Method] = {
        "apriltag3, decimate 2": apriltag_d2,
        "apriltag3, decimate 1": apriltag_d1,
        "opencv aruco 36h11": ArucoMethod(),
        "line quads (shared.vision.linequads)": line_quads_method(),
        "splittag stage 1, decimate 2, no frame history": stage1_method(2.0),
        "splittag stage 1, decimate 1 (splittag detect)": stage1_method(1.0),
    }
    no_camera = np.eye(3)
    video_rows = video_stage1(photos, args.repetitions)
    print(f"\n{len(photos)} photos, {total} annotated tags ({', '.join(f'{p.name}: {len(p.tags)}' for p in photos)})")
    head = f"{'method':48s} {'found':>8s} {'per photo':>12s} {'other':>6s} {'corner px p50':>14s}"
    print(f"{head} {'ms per photo (median)':>24s}")
    try:
        for name, method in methods.items():
            per_photo, other, errors, ms = [], 0, [], []
            for photo in photos:
                found = method(photo.image, no_camera)
                n, o, e = match(photo.tags, found)
                per_photo.append(n)
                other += o
                errors += e
                times = []
                for _ in range(args.repetitions):
                    t0 = time.perf_counter()
                    method(photo.image, no_camera)
                    times.append(time.perf_counter() - t0)
                ms.append(1e3 * statistics.median(times))
            print(
                f"{name:48s} {sum(per_photo):>3d} / {total:<2d} {'/'.join(map(str, per_photo)):>12s} {other:>6d} "
                f"{statistics.median(errors) if errors else float('nan'):>14.2f} "
                f"{' / '.join(f'{m:.1f}' for m in ms):>24s}"
            )
        for name, (per_photo, other, errors, ms) in video_rows.items():
            print(
                f"{name:48s} {sum(per_photo):>3d} / {total:<2d} {'/'.join(map(str, per_photo)):>12s} {other:>6d} "
                f"{statistics.median(errors) if errors else float('nan'):>14.2f} "
                f"{' / '.join(f'{m:.1f}' for m in ms):>24s}"
            )
    finally:
        apriltag_d2.close()
        apriltag_d1.close()


def video_stage1(
    photos: list[Annotated], repetitions: int
) -> dict[str, tuple[list[int], int, list[float], list[float]]]:
    """robot_infer's stage 1 (decimate 2) with its full-resolution sweep and windows, each photo as a
    still video: one detector per photo; frame 0 is the full-resolution sweep, the tags found and the
    time are those of the frames after it (decimated, with windows around the small tags seen). Rows
    for the sweep frame, the frames after, and AprilTag alone with the windows."""
    from shared.vision.linequads import LineQuadSettings
    from shared.vision.proposals import ArucoSettings, Stage1Detector, Stage1Settings

    configs = {
        "splittag stage 1, robot_infer: sweep frame": (Stage1Settings(), True),
        "splittag stage 1, robot_infer: frames after it": (Stage1Settings(), False),
        "apriltag3 d2 + full-res windows: frames after": (
            Stage1Settings(aruco=ArucoSettings(enabled=False), lines=LineQuadSettings(enabled=False)),
            False,
        ),
    }
    rows: dict[str, tuple[list[int], int, list[float], list[float]]] = {}
    for name, (settings, sweep_frame) in configs.items():
        per_photo, other, errors, ms = [], 0, [], []
        for photo in photos:
            detector = Stage1Detector(settings)
            t0 = time.perf_counter()
            found = detector.detect(photo.image)  # frame 0: the sweep
            sweep_ms = 1e3 * (time.perf_counter() - t0)
            times = []
            if not sweep_frame:
                for _ in range(max(1, repetitions)):
                    t0 = time.perf_counter()
                    found = detector.detect(photo.image)
                    times.append(time.perf_counter() - t0)
            detector.close()
            n, o, e = match(photo.tags, [Prediction(d.tag_id, d.corners_px, "corners4") for d in found])
            per_photo.append(n)
            other += o
            errors += e
            ms.append(sweep_ms if sweep_frame else 1e3 * statistics.median(times))
        rows[name] = (per_photo, other, errors, ms)
    return rows


if __name__ == "__main__":
    main()
