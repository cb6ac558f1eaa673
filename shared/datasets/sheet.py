"""Contact sheets: ROIs with keypoints drawn, so a person can look at a data set or predictions."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from shared.vision.geometry import denormalise_roi


def contact_sheet(
    rois: NDArray[np.uint8],
    keypoints: NDArray[np.float32],
    *,
    predicted: NDArray[np.float32] | None = None,
    labels: list[str] | None = None,
    columns: int = 4,
) -> NDArray[np.uint8]:
    """Tile ROIs (N,256,256) with ground truth (blue) and optional predictions (yellow) drawn."""
    tiles = []
    for i, roi in enumerate(rois):
        tile = cv2.cvtColor(roi, cv2.COLOR_GRAY2BGR)
        tile = cv2.resize(tile, (512, 512), interpolation=cv2.INTER_NEAREST)
        for pts, colour in [(keypoints[i], (255, 80, 0)), (None if predicted is None else predicted[i], (0, 220, 255))]:
            if pts is None:
                continue
            for j, (x, y) in enumerate(denormalise_roi(pts)):
                # Pixel centres: roi px u -> tile px 2u + 0.5; drawn with 4 fractional bits.
                c = (round((2 * x + 0.5) * 16), round((2 * y + 0.5) * 16))
                cv2.circle(tile, c, 4 * 16, colour, -1, lineType=cv2.LINE_AA, shift=4)
                if j in (0, 3, 12, 15) and colour[0] == 255:
                    cv2.putText(
                        tile,
                        str(j),
                        (c[0] // 16 + 6, c[1] // 16 - 6),
                        cv2.FONT_HERSHEY_SIMPLEX,
                        0.5,
                        colour,
                        1,
                        cv2.LINE_AA,
                    )
        if labels:
            cv2.putText(tile, labels[i], (6, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (0, 255, 0), 1, cv2.LINE_AA)
        tiles.append(tile)
    rows = math.ceil(len(tiles) / columns)
    blank = np.zeros_like(tiles[0])
    tiles += [blank] * (rows * columns - len(tiles))
    return np.vstack([np.hstack(tiles[r * columns : (r + 1) * columns]) for r in range(rows)])


def write_sheet(path: Path, sheet: NDArray[np.uint8]) -> None:
    """Write a PNG, creating the folder."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), sheet):
        raise OSError(f"could not write {path}")
