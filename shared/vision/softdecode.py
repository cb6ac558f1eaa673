"""Soft decoding of tag36h11 quads under motion blur (pure; shared by the tracker and the line quads).

A hard decode thresholds each of the 36 data cells; a motion blur of two cells or more smears black
and white cells into each other and the bits are lost, although the blurred pattern is still a
fingerprint of the tag. A soft decode compares the rectified cell means with every code word in all
four rotations *blurred the same way* and asks for one clear winner:

- `rectify`: the 10 x 10-cell tag region behind a quad (black-square corners TL, TR, BR, BL),
  `PX_PER_CELL` pixels a cell, reduced to cell means.
- `blur_operator(dx, dy)`: (100, 100), code-word cells -> cell means of the pattern rendered and
  blurred by a linear motion of (dx, dy) rectified pixels. In the rectified patch an image-space
  motion blur is (locally) a linear blur too.
- The tracker knows the tag (its id and image motion): `shared.vision.tracking.verify_tag` scores
  its own pattern against every other one.
- The line quads know neither: `blind_decode` treats the blur as a nuisance parameter. For every
  hypothesis on a grid of blur vectors (length up to `max_blur_cells`, every `angle_step_deg`) and
  every code word and rotation it correlates the 36 data cells with the blurred word (one matrix
  product per quad: the blurred words' norms are precomputed per hypothesis). The best (hypothesis,
  word) must correlate >= `min_correlation` on the data cells and >= `min_full_correlation` on all
  100 cells (the rings and the white border must fit the same blur as well), and beat every other
  word and rotation under *every* hypothesis by `min_margin` (a generalised likelihood-ratio test:
  a blur that would make another word fit as well makes the read ambiguous).

Calibrated on bench/accuracy's renders (seed 0, 600 images): of 6658 quads the line proposer finds
away from any tag, none reaches even thresholds 0.05 looser than the defaults.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Final

import cv2
import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from shared.vision.blur import line_kernel
from shared.vision.geometry import Array
from shared.vision.tags import CELLS, NUM_TAG36H11, tag_cells

PX_PER_CELL: Final[int] = 6
SIDE_PX: Final[int] = CELLS * PX_PER_CELL
_DATA: Final[NDArray[np.bool_]] = np.zeros((CELLS, CELLS), bool)
_DATA[2:-2, 2:-2] = True  # the 6x6 data bits: the borders are the same in every tag
DATA_CELLS: Final[NDArray[np.intp]] = np.flatnonzero(_DATA.ravel())


@lru_cache(maxsize=1)
def code_book() -> tuple[NDArray[np.float64], NDArray[np.int64], NDArray[np.int64]]:
    """Every tag36h11 pattern (10x10 cells, 1 = white) in 4 rotations: rows (4 * 587, 100), the id and
    the rotation of each row; row 4 * id + r is np.rot90(tag_cells(id), r)."""
    rows, ids, rots = [], [], []
    for tag_id in range(NUM_TAG36H11):
        cells = tag_cells(tag_id).astype(np.float64)
        for rot in range(4):
            rows.append(np.rot90(cells, rot).ravel())
            ids.append(tag_id)
            rots.append(rot)
    return np.array(rows), np.array(ids), np.array(rots)


@lru_cache(maxsize=256)
def blur_operator(dx_q: int, dy_q: int) -> NDArray[np.float64]:
    """(100, 100): cell pattern -> cell means of the pattern rendered at PX_PER_CELL and blurred by a
    linear motion of (dx, dy) rectified pixels (given in half pixels). Blur is shift-invariant, so
    one blurred cell gives how any cell spreads into its neighbours (the tag's surroundings are taken
    as the same as its white border)."""
    dx, dy = dx_q / 2.0, dy_q / 2.0
    p, n = PX_PER_CELL, 2 * CELLS - 1
    canvas = np.zeros((n * p, n * p))
    canvas[(CELLS - 1) * p : CELLS * p, (CELLS - 1) * p : CELLS * p] = 1.0
    if math.hypot(dx, dy) >= 0.5:
        canvas = np.asarray(
            cv2.filter2D(
                canvas, -1, line_kernel(math.hypot(dx, dy), math.atan2(dy, dx)), borderType=cv2.BORDER_CONSTANT
            ),
            np.float64,
        )
    spread = canvas.reshape(n, p, n, p).mean(axis=(1, 3))  # spread[oy + 9, ox + 9]: into the cell at offset
    iy, ix = np.divmod(np.arange(CELLS * CELLS), CELLS)
    return np.asarray(spread[iy[:, None] - iy[None, :] + CELLS - 1, ix[:, None] - ix[None, :] + CELLS - 1], np.float64)


def normalise(rows: NDArray[np.float64]) -> NDArray[np.float64]:
    """Each row (last axis) made zero-mean and unit-norm (a zero row stays zero)."""
    centred = rows - rows.mean(axis=-1, keepdims=True)
    return centred / np.maximum(np.linalg.norm(centred, axis=-1, keepdims=True), 1e-9)


def rectify(image: NDArray[np.uint8], corners_px: Array) -> tuple[NDArray[np.float64], Array]:
    """Cell means (100,) of the 10x10-cell tag region behind the quad, and the rectified-from-image
    homography."""
    p = PX_PER_CELL
    # black square corners sit at cells 1 and 9 of the 10-cell grid (pixel edges, so -0.5 for centres)
    dst = np.array([[p, p], [9 * p, p], [9 * p, 9 * p], [p, 9 * p]], np.float32) - 0.5
    h = cv2.getPerspectiveTransform(np.asarray(corners_px, np.float32), dst)
    patch = cv2.warpPerspective(image, h, (SIDE_PX, SIDE_PX), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    means = patch.astype(np.float64).reshape(CELLS, p, CELLS, p).mean(axis=(1, 3)).ravel()
    return means, h


@dataclass(frozen=True)
class _Hypotheses:
    blur_q: list[tuple[int, int]]  # blur vectors in half rectified pixels
    data_ops_t: NDArray[np.float32]  # (H, 100, 36): each operator's data rows, transposed
    inv_norms: NDArray[np.float32]  # (H, 4 * 587): 1 / the centred blurred data cells' norm of every word
    book: NDArray[np.float32]  # code_book()'s rows


@lru_cache(maxsize=4)
def _hypotheses(max_blur_cells: float, step_cells: float, angle_step_deg: float) -> _Hypotheses:
    """The blur grid: no blur, then lengths step, 2 step, ... <= max, at every angle step in [0, 180)."""
    blur_q = [(0, 0)]
    n_len = math.floor(max_blur_cells / step_cells + 1e-9)
    for i in range(1, n_len + 1):
        length_px = i * step_cells * PX_PER_CELL
        for a in np.arange(0.0, 180.0, angle_step_deg):
            q = (round(2 * length_px * math.cos(math.radians(a))), round(2 * length_px * math.sin(math.radians(a))))
            if q not in blur_q:
                blur_q.append(q)
    book, _, _ = code_book()
    ops = np.stack([blur_operator(dx, dy)[DATA_CELLS] for dx, dy in blur_q])  # (H, 36, 100)
    norms = np.empty((len(blur_q), len(book)))
    for h, op in enumerate(ops):
        blurred = book @ op.T  # (W, 36)
        norms[h] = np.linalg.norm(blurred - blurred.mean(axis=1, keepdims=True), axis=1)
    return _Hypotheses(
        blur_q,
        np.ascontiguousarray(ops.transpose(0, 2, 1), np.float32),
        (1.0 / np.maximum(norms, 1e-9)).astype(np.float32),
        book.astype(np.float32),
    )


@dataclass(frozen=True)
class BlindDecode:
    """The best reading of a quad: id, its rotation, the scores and the gate's verdict; `corners_px`
    is the quad reordered TL, TR, BR, BL of the tag read."""

    accepted: bool
    tag_id: int
    rotation: int
    correlation: float  # the 36 data cells vs the blurred word
    full_correlation: float  # all 100 cells vs the blurred pattern
    margin: float  # correlation minus the best other word or rotation's under any blur hypothesis
    blur_cells: tuple[float, float]  # the best hypothesis's blur vector in cells of the rectified tag
    corners_px: Array


class BlindDecodeSettings(BaseModel):
    """The hypothesis grid and the gate (module docstring); blur in cells of the rectified tag."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    max_blur_cells: float = Field(default=3.5, ge=0.0, le=8.0)  # longest motion blur hypothesised, in tag cells
    step_cells: float = Field(default=0.5, ge=0.25)  # finer grids cost time and memory for nothing
    angle_step_deg: float = Field(default=15.0, ge=1.0, le=90.0)  # blur directions tried
    min_correlation: float = Field(default=0.8, gt=0.0, le=1.0)  # data cells
    min_full_correlation: float = Field(default=0.85, gt=0.0, le=1.0)  # all 100 cells
    min_margin: float = Field(default=0.15, ge=0.0)  # own code word's correlation minus the best other's


def prepare(settings: BlindDecodeSettings) -> None:
    """Build the code book and the blur grid now (~0.3 s), not on the first quad."""
    _hypotheses(settings.max_blur_cells, settings.step_cells, settings.angle_step_deg)


def blind_decode(image: NDArray[np.uint8], corners_px: Array, settings: BlindDecodeSettings) -> BlindDecode | None:
    """The soft decode of a quad whose id and blur are unknown (module docstring); None when the
    region is flat (nothing to correlate)."""
    hyp = _hypotheses(settings.max_blur_cells, settings.step_cells, settings.angle_step_deg)
    book, ids, rots = code_book()
    means, _ = rectify(image, corners_px)
    cand = means[DATA_CELLS] - means[DATA_CELLS].mean()
    norm = float(np.linalg.norm(cand))
    if norm < 1e-6:
        return None
    cand = (cand / norm).astype(np.float32)
    # cand is zero-mean, so cand . (blurred word - its mean) = cand . blurred word = (op^T cand) . word
    scores = (hyp.data_ops_t @ cand) @ hyp.book.T * hyp.inv_norms  # (H, W), float32
    h, w = np.unravel_index(int(np.argmax(scores)), scores.shape)
    best = float(scores[h, w])
    scores[:, w] = -2.0  # every other word and every other rotation of this one, under any blur
    margin = best - float(scores.max())
    full = blur_operator(*hyp.blur_q[h]) @ book[w]
    full_corr = float(normalise(means[None, :])[0] @ normalise(full[None, :])[0])
    s = settings
    accepted = best >= s.min_correlation and full_corr >= s.min_full_correlation and margin >= s.min_margin
    rot = int(rots[w])
    dq = hyp.blur_q[h]
    return BlindDecode(
        accepted=accepted,
        tag_id=int(ids[w]),
        rotation=rot,
        correlation=best,
        full_correlation=full_corr,
        margin=margin,
        blur_cells=(dq[0] / 2 / PX_PER_CELL, dq[1] / 2 / PX_PER_CELL),
        # the patch is the tag turned by np.rot90 `rot` times: its top-left corner is the quad's -rot
        corners_px=np.roll(np.asarray(corners_px, np.float64), rot, axis=0),
    )
