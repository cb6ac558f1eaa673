"""tag36h11 in AprilTag's canonical orientation, and anti-aliased rendering of a planar tag.

OpenCV's DICT_APRILTAG_36h11 holds the same code words, but `generateImageMarker` draws each tag
rotated by 180 degrees relative to AprilTag's official images (measured: rendering OpenCV's image
as-is makes the AprilTag 3 detector report pose R = diag(-1, -1, 1); rotated by 180 degrees it
reports the identity). `tag_cells` returns the canonical orientation.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Final, Literal

import cv2
import numpy as np
from numpy.typing import NDArray

from shared.vision.geometry import Array, check_image

NUM_TAG36H11: Final[int] = 587
CELLS: Final[int] = 10  # 1 white border + 1 black border + 6 data + 1 black + 1 white
BLACK_CELLS: Final[int] = 8  # the outer black square = tag size
_TEXEL_PER_CELL: Final[int] = 32


@lru_cache(maxsize=NUM_TAG36H11)
def tag_cells(tag_id: int) -> NDArray[np.uint8]:
    """10x10 cells of tag `tag_id` (1 = white), AprilTag's canonical orientation, white border."""
    if not 0 <= tag_id < NUM_TAG36H11:
        raise ValueError(f"tag36h11 ids are 0..{NUM_TAG36H11 - 1}, got {tag_id}")
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    px = 20
    img = cv2.aruco.generateImageMarker(dictionary, tag_id, BLACK_CELLS * px, borderBits=1)
    inner = (img[px // 2 :: px, px // 2 :: px] > 127).astype(np.uint8)
    cells = np.ones((CELLS, CELLS), np.uint8)
    cells[1:-1, 1:-1] = np.rot90(inner, 2)
    return cells


@lru_cache(maxsize=64)
def tag_texture(tag_id: int) -> NDArray[np.uint8]:
    """The tag as a uint8 texture, `_TEXEL_PER_CELL` texels per cell, white border included."""
    cells = tag_cells(tag_id)
    return np.kron(cells, np.ones((_TEXEL_PER_CELL, _TEXEL_PER_CELL), np.uint8)) * 255


def texture_to_tag_plane(tag_size_m: float) -> Array:
    """Homography from texture pixel coords (OpenCV convention) to tag-plane metres (x right, y down)."""
    cell_m = tag_size_m / BLACK_CELLS
    s = cell_m / _TEXEL_PER_CELL
    off = -CELLS / 2 * cell_m + 0.5 * s  # texel centre i sits at (i + 0.5) texels from the edge
    return np.array([[s, 0, off], [0, s, off], [0, 0, 1.0]])


def render_tag(
    canvas: NDArray[np.float32],
    *,
    tag_id: int,
    tag_size_m: float,
    tag_plane_to_image: Array,
    origin_px: tuple[int, int] = (0, 0),
    supersample: int = 4,
    albedo: tuple[float, float] = (0.08, 0.92),
    texture_sampling: Literal["nearest", "bilinear"] = "bilinear",
) -> None:
    """Paint an anti-aliased tag (white border included) into `canvas` in place (float32 in [0, 1]).

    `tag_plane_to_image` maps tag-plane metres (z = 0) to full-image pixels; `canvas` is the window
    of the image whose top-left pixel is `origin_px`. Rendering is supersampled by `supersample`
    per axis and box-filtered, with exact pixel-centre bookkeeping. `texture_sampling="nearest"`
    keeps the cell edges exactly where the tag's geometry puts them (area coverage up to the
    supersampling); "bilinear" (the first data sets) softens them by one texel.
    """
    f = supersample
    tex = tag_texture(tag_id).astype(np.float32) / 255.0
    lo, hi = albedo
    tex = lo + (hi - lo) * tex
    # canvas coords -> image coords: +origin; hi-res coords u' = f (u + 0.5) - 0.5.
    ox, oy = origin_px
    canvas_to_hires = np.array([[f, 0, f * (0.5 - ox) - 0.5], [0, f, f * (0.5 - oy) - 0.5], [0, 0, 1.0]])
    tex_to_hires = canvas_to_hires @ tag_plane_to_image @ texture_to_tag_plane(tag_size_m)
    h, w = canvas.shape
    hi_tex = cv2.warpPerspective(
        tex,
        tex_to_hires,
        (w * f, h * f),
        flags=cv2.INTER_NEAREST if texture_sampling == "nearest" else cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=-1.0,
    )
    mask = (hi_tex >= 0).astype(np.float32)
    hi_tex = np.where(mask > 0, hi_tex, 0.0)
    cov = cv2.resize(mask, (w, h), interpolation=cv2.INTER_AREA)
    val = cv2.resize(hi_tex, (w, h), interpolation=cv2.INTER_AREA)
    canvas *= 1.0 - cov
    canvas += val


def to_uint8(image: NDArray[np.float32]) -> NDArray[np.uint8]:
    """[0, 1] float image -> uint8 with rounding and clipping."""
    return check_image(np.clip(np.rint(image * 255.0), 0, 255).astype(np.uint8))
