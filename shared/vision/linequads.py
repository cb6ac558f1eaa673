"""Stage 1's third proposer: tag quads from straight edges, for borders a finger or a cable interrupts.

AprilTag 3 and OpenCV's ArUco detector both need the black square's outline as one closed boundary
(gradient clusters, or a thresholded contour). An occluder crossing the border breaks that boundary
and both lose the tag, even though its four corners and most of its bits are in plain view. This
proposer works from straight edges instead:

1. Line segments: OpenCV's LSD on the image reduced by `scale` (INTER_AREA), mapped back to full-size
   pixel coordinates.
2. Each segment's dark side: the mean grey level 2 px either side (5 samples along it); segments with
   less contrast than `min_edge_contrast` are dropped.
3. Collinear segments with the same dark side merge into one line (angle, perpendicular offset and gap
   tolerances; connected components, a length-weighted total-least-squares fit): the two pieces of a
   side an occluder interrupts become one line again.
4. Corners: two lines whose intersection lies near an end of each, at least `corner_min_angle_deg`
   apart, with both dark sides inside the angle (the black square is dark inside every corner).
5. Quads: four lines joined by four corners; and, where a side is covered over most of its length,
   three lines joined by two corners, the fourth side through the far ends of the outer two.
6. Decode: the whole tag, white ring included, must lie inside the image; the quad's 10 x 10 cells
   (inner 60 % of each) are read; the black ring's and white ring's
   medians give the threshold; at least `min_ring_fraction` of each ring must be on its side of it
   (an occluder may cover a few border cells); the 36 data bits must be within `max_hamming` of one
   tag36h11 code word in one rotation (its distance to every other word and rotation is then >= 11 -
   `max_hamming`: 36h11's minimum distance is 11). The rotation gives the corner order TL, TR, BR, BL.
7. Duplicates (the same tag from several quads) keep the best decode; each side is refitted at full
   size (the strongest dark-inward step near it, sub-pixel, weak steps such as an occluder's stretch
   dropped, a Huber line fit) and the corners are the refitted sides' intersections.

Pure: image in, detections out; `shared.vision.proposals.Stage1Detector` merges them with AprilTag's
and ArUco's. Measured on bench/accuracy's renders in docs/stage1.md.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import lru_cache
from typing import Final

import cv2
import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from shared.vision.detector import Detection, merge_proposals, quad_side_px
from shared.vision.geometry import Array, check_image
from shared.vision.softdecode import DATA_CELLS, BlindDecodeSettings, blind_decode, code_book, prepare
from shared.vision.tags import CELLS

_PX: Final[int] = 10  # rectified pixels per cell when decoding


class LineQuadSettings(BaseModel):
    """The line-quad proposer (module docstring); lengths in full-size image pixels."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    enabled: bool = True  # the line-quad proposer (LSD segments to quads, for tags the others miss)
    scale: float = Field(default=0.5, gt=0.0, le=1.0)  # LSD runs on the image reduced by this
    min_segment_px: float = Field(default=6.0, gt=0.0)  # shorter LSD segments are ignored
    min_edge_contrast: float = Field(default=8.0, ge=0.0)  # grey levels between the two sides
    merge_angle_deg: float = Field(default=3.0, gt=0.0, le=20.0)  # collinear pieces within this angle are merged
    merge_offset_px: float = Field(default=1.5, gt=0.0)  # ... and this distance between their lines
    merge_gap_fraction: float = Field(default=0.6, ge=0.0)  # of the longer piece
    corner_min_angle_deg: float = Field(default=25.0, gt=0.0, lt=90.0)  # two lines closer to parallel make no corner
    corner_end_px: float = Field(default=4.0, ge=0.0)  # an end is near a corner within this
    corner_end_fraction: float = Field(default=0.25, ge=0.0)  # ... plus this fraction of the line
    corner_end_max_px: float = Field(default=15.0, gt=0.0)  # cap of the corner tolerance
    three_sided: bool = True  # also quads with one side covered over most of its length
    min_area_px2: float = Field(default=100.0, ge=0.0)  # smaller quads are dropped
    max_hamming: int = Field(default=3, ge=0, le=4)  # bit errors the hard decode may correct
    # of the black and white rings on their side of the threshold
    min_ring_fraction: float = Field(default=0.75, gt=0.5, le=1.0)
    min_ring_contrast: float = Field(default=20.0, ge=0.0)  # white ring median - black ring median
    refine_corners: bool = True  # sub-pixel corners from the edges
    # Quads whose hard decode failed but whose rings stand out are read by a blind soft decode.
    # Its tags (proposer "lines_soft") are right (no wrong id or ghost measured), but under 10-17 px of
    # blur their keypoints are off by several times a detected tag's: slam localises with them against
    # tags of a known map, and maps nothing from them (SlamSettings.soft_reads).
    soft_decode: bool = True
    soft_min_ring_fraction: float = Field(default=0.6, gt=0.5, le=1.0)  # the rings' test for a quad read blind
    soft_max_per_frame: int = Field(default=8, ge=0)  # bounds the cost (1.5-3 ms a quad) on cluttered frames
    soft_min_side_px: float = Field(default=24.0, ge=0.0)  # smaller quads have too few pixels a cell
    # the quad as found must read at least this well (data and all cells) before it is refitted and
    # gated: on bench/accuracy's renders it drops 93 % of the quads away from tags and no tag the gate takes
    soft_min_first_correlation: float = Field(default=0.7, ge=0.0, le=1.0)
    soft: BlindDecodeSettings = BlindDecodeSettings()


@dataclass(frozen=True)
class _Lines:
    """Merged lines: a point, unit direction, unit normal towards the dark side, extent along the
    direction (lo, hi) from the point."""

    p: Array
    d: Array
    n: Array
    lo: Array
    hi: Array

    def __len__(self) -> int:
        return len(self.p)


def segments(image: NDArray[np.uint8], scale: float, lsd: cv2.LineSegmentDetector | None = None) -> Array:
    """LSD segments (N, 4) x1 y1 x2 y2 in full-size pixel coordinates (pixel centres at integers)."""
    small = image if scale == 1.0 else cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    found = (lsd or cv2.createLineSegmentDetector(cv2.LSD_REFINE_NONE)).detect(small)[0]
    if found is None:
        return np.zeros((0, 4))
    # A reduced pixel i covers full-size pixels [i/scale - 0.5, (i+1)/scale - 0.5): its centre is at
    # (i + 0.5)/scale - 0.5.
    return (found.reshape(-1, 4).astype(np.float64) + 0.5) / scale - 0.5


def _side_means(image: NDArray[np.uint8], pts: Array) -> Array:
    """Mean grey level of each row of points (M, K, 2), bilinear."""
    flat = pts.reshape(-1, 2).astype(np.float32)
    vals = cv2.remap(image, flat[:, :1], flat[:, 1:], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return np.asarray(vals, np.float64).reshape(pts.shape[0], -1).mean(axis=1)


def oriented_lines(image: NDArray[np.uint8], segs: Array, s: LineQuadSettings) -> _Lines:
    """Segments with their dark side, merged into lines (steps 2 and 3)."""
    a, b = segs[:, :2], segs[:, 2:]
    length = np.linalg.norm(b - a, axis=1)
    keep = length >= s.min_segment_px
    a, b, length = a[keep], b[keep], length[keep]
    if not len(a):
        return _empty_lines()
    d = (b - a) / length[:, None]
    n = np.column_stack([d[:, 1], -d[:, 0]])
    along = a[:, None, :] + (np.linspace(0.2, 0.8, 5)[None, :, None] * length[:, None, None]) * d[:, None, :]
    plus = _side_means(image, along + 2.0 * n[:, None, :])
    minus = _side_means(image, along - 2.0 * n[:, None, :])
    contrast = minus - plus  # > 0: the +n side is darker
    ok = np.abs(contrast) >= max(s.min_edge_contrast, 1e-9)
    n = n[ok] * np.sign(contrast[ok])[:, None]
    return _merge(a[ok], b[ok], d[ok], n, length[ok], s)


def _empty_lines() -> _Lines:
    z2, z1 = np.zeros((0, 2)), np.zeros(0)
    return _Lines(z2, z2, z2, z1, z1)


def _merge(a: Array, b: Array, d: Array, n: Array, length: Array, s: LineQuadSettings) -> _Lines:
    m = len(a)
    tol = math.radians(s.merge_angle_deg)
    # Candidate pairs: dark-side normals within the angle tolerance (angles sorted, a window each).
    ang = np.arctan2(n[:, 1], n[:, 0]) % (2 * math.pi)
    order = np.argsort(ang)
    sorted_ang = np.concatenate([ang[order], ang[order] + 2 * math.pi])
    ends = np.searchsorted(sorted_ang, sorted_ang[:m] + tol, side="right")
    counts = ends - np.arange(m) - 1
    if counts.sum():
        # pair (k, k + 1 .. ends[k] - 1) in sorted positions, for every k at once
        i = np.repeat(order, counts)
        starts = np.repeat(np.cumsum(counts) - counts, counts)
        positions = np.repeat(np.arange(m) + 1, counts) + np.arange(int(counts.sum())) - starts
        j = np.concatenate([order, order])[positions]
        keep = i != j
        i, j = i[keep], j[keep]
        ok = _collinear(a, b, d, n, length, i, j, s) & _collinear(a, b, d, n, length, j, i, s)
        i, j = i[ok], j[ok]
    else:
        i = j = np.zeros(0, np.int64)
    graph = coo_matrix((np.ones(len(i)), (i, j)), shape=(m, m))
    groups, roots = connected_components(graph, directed=False)
    # Each group's line: the length-weighted total-least-squares fit through its segments' end points
    # (closed form from the weighted second moments), its extent the end points' span along it.
    w = np.concatenate([length, length])
    pts = np.vstack([a, b])
    g = np.concatenate([roots, roots])
    sw = np.bincount(g, w, groups)
    c = np.column_stack([np.bincount(g, w * pts[:, 0], groups), np.bincount(g, w * pts[:, 1], groups)]) / sw[:, None]
    q = pts - c[g]
    sxx = np.bincount(g, w * q[:, 0] ** 2, groups)
    sxy = np.bincount(g, w * q[:, 0] * q[:, 1], groups)
    syy = np.bincount(g, w * q[:, 1] ** 2, groups)
    theta = 0.5 * np.arctan2(2 * sxy, sxx - syy)
    direction = np.column_stack([np.cos(theta), np.sin(theta)])
    normal = np.column_stack([direction[:, 1], -direction[:, 0]])
    first = np.full(groups, -1)
    first[roots[::-1]] = np.arange(m)[::-1]  # one member segment of each group
    flip = np.einsum("pk,pk->p", normal, n[first]) < 0
    normal[flip] *= -1
    t = np.einsum("pk,pk->p", q, direction[g])
    lo = np.full(groups, np.inf)
    hi = np.full(groups, -np.inf)
    np.minimum.at(lo, g, t)
    np.maximum.at(hi, g, t)
    return _Lines(c, direction, normal, lo, hi)


def _collinear(
    a: Array, b: Array, d: Array, n: Array, length: Array, i: NDArray[np.intp], j: NDArray[np.intp], s: LineQuadSettings
) -> NDArray[np.bool_]:
    """Segment j lies on segment i's line (offset) and continues it across a bounded gap."""
    base_n = np.einsum("pk,pk->p", a[i], n[i])
    base_d = np.einsum("pk,pk->p", a[i], d[i])
    off = np.maximum(
        np.abs(np.einsum("pk,pk->p", a[j], n[i]) - base_n), np.abs(np.einsum("pk,pk->p", b[j], n[i]) - base_n)
    )
    ta = np.einsum("pk,pk->p", a[j], d[i]) - base_d
    tb = np.einsum("pk,pk->p", b[j], d[i]) - base_d
    t0, t1 = np.minimum(ta, tb), np.maximum(ta, tb)
    gap = np.maximum(np.maximum(t0 - length[i], -t1), 0.0)
    return (off <= s.merge_offset_px) & (gap <= s.merge_gap_fraction * np.maximum(length[i], t1 - t0))


def corner_graph(lines: _Lines, s: LineQuadSettings) -> dict[int, set[int]]:
    """Which lines meet at a dark-inside corner near an end of both (step 4)."""
    m = len(lines)
    if m < 3:
        return {}
    p, d, n, lo, hi = lines.p, lines.d, lines.n, lines.lo, lines.hi
    end_pts = np.vstack([p + lo[:, None] * d, p + hi[:, None] * d])
    owner = np.concatenate([np.arange(m), np.arange(m)])
    pairs = cKDTree(end_pts).query_pairs(2 * s.corner_end_max_px, output_type="ndarray")
    if not len(pairs):
        return {}
    i, j = owner[pairs[:, 0]], owner[pairs[:, 1]]
    key = np.unique(np.minimum(i, j) * m + np.maximum(i, j))
    i, j = key // m, key % m
    keep = i != j
    i, j = i[keep], j[keep]
    cross = d[i, 0] * d[j, 1] - d[i, 1] * d[j, 0]
    ok = np.abs(cross) >= math.sin(math.radians(s.corner_min_angle_deg))
    i, j, cross = i[ok], j[ok], cross[ok]
    dp = p[j] - p[i]
    t_i = (dp[:, 0] * d[j, 1] - dp[:, 1] * d[j, 0]) / cross  # the corner along line i
    t_j = (dp[:, 0] * d[i, 1] - dp[:, 1] * d[i, 0]) / cross  # ... along line j
    tol_i = np.minimum(s.corner_end_px + s.corner_end_fraction * (hi[i] - lo[i]), s.corner_end_max_px)
    tol_j = np.minimum(s.corner_end_px + s.corner_end_fraction * (hi[j] - lo[j]), s.corner_end_max_px)
    i_lo, i_hi = np.abs(t_i - lo[i]), np.abs(t_i - hi[i])
    j_lo, j_hi = np.abs(t_j - lo[j]), np.abs(t_j - hi[j])
    ok = (np.minimum(i_lo, i_hi) <= tol_i) & (np.minimum(j_lo, j_hi) <= tol_j)
    # From the corner, each line runs towards its far end; the other line's dark side faces it.
    away_i = np.where(i_lo < i_hi, 1.0, -1.0)[:, None] * d[i]
    away_j = np.where(j_lo < j_hi, 1.0, -1.0)[:, None] * d[j]
    ok &= (np.einsum("pk,pk->p", n[i], away_j) > 0.2) & (np.einsum("pk,pk->p", n[j], away_i) > 0.2)
    graph: dict[int, set[int]] = {}
    for u, v in zip(i[ok].tolist(), j[ok].tolist(), strict=True):
        graph.setdefault(u, set()).add(v)
        graph.setdefault(v, set()).add(u)
    return graph


def _meet(lines: _Lines, u: int, v: int) -> Array | None:
    m = np.column_stack([lines.d[u], -lines.d[v]])
    if abs(np.linalg.det(m)) < 1e-9:
        return None
    t = np.linalg.solve(m, lines.p[v] - lines.p[u])
    return np.asarray(lines.p[u] + t[0] * lines.d[u])


def _far_end(lines: _Lines, u: int, corner: Array) -> Array:
    a = lines.p[u] + lines.lo[u] * lines.d[u]
    b = lines.p[u] + lines.hi[u] * lines.d[u]
    return np.asarray(b if np.linalg.norm(a - corner) < np.linalg.norm(b - corner) else a)


def _clockwise(q: Array, min_area: float) -> Array | None:
    """The quad ordered clockwise on screen (y down), or None if not convex or too small."""
    e = np.roll(q, -1, axis=0) - q
    f = np.roll(e, -1, axis=0)
    cross = e[:, 0] * f[:, 1] - e[:, 1] * f[:, 0]
    if not (np.all(cross > 0) or np.all(cross < 0)):
        return None
    area = 0.5 * abs(float(np.sum(q[:, 0] * np.roll(q[:, 1], -1) - np.roll(q[:, 0], -1) * q[:, 1])))
    if area < min_area:
        return None
    return q if cross[0] > 0 else q[::-1].copy()


def quads(lines: _Lines, graph: dict[int, set[int]], s: LineQuadSettings) -> list[tuple[Array, int]]:
    """(quad, sides seen: 4 or 3) candidates, clockwise on screen (step 5)."""
    out: list[tuple[Array, int]] = []
    full: set[frozenset[int]] = set()
    for a in graph:
        for b in graph[a]:
            for c in graph.get(b, ()):
                if c == a:
                    continue
                for d in graph.get(c, ()):
                    if d in (a, b) or a not in graph.get(d, ()):
                        continue
                    key = frozenset((a, b, c, d))
                    if key in full:
                        continue
                    full.add(key)
                    pts = [_meet(lines, u, v) for u, v in ((a, b), (b, c), (c, d), (d, a))]
                    if any(pt is None for pt in pts):
                        continue
                    q = _clockwise(np.array(pts), s.min_area_px2)
                    if q is not None:
                        out.append((q, 4))
    if not s.three_sided:
        return out
    for b in graph:
        around = sorted(graph[b])
        for x, a in enumerate(around):
            for c in around[x + 1 :]:
                if any(frozenset((a, b, c, d)) in full for d in graph.get(a, set()) & graph.get(c, set())):
                    continue  # four sides seen: that quad is already a candidate
                ab, bc = _meet(lines, a, b), _meet(lines, b, c)
                if ab is None or bc is None:
                    continue
                q = _clockwise(np.array([ab, bc, _far_end(lines, c, bc), _far_end(lines, a, ab)]), s.min_area_px2)
                if q is not None:
                    out.append((q, 3))
    return out


@lru_cache(maxsize=1)
def _data_book() -> tuple[NDArray[np.bool_], NDArray[np.int64], NDArray[np.int64]]:
    """The 36 data bits of every tag36h11 word in 4 rotations (np.rot90 k times), with id and k: the
    data cells of `shared.vision.softdecode.code_book`."""
    book, ids, rots = code_book()
    return book[:, DATA_CELLS] > 0, ids, rots


_RING_BLACK: Final[NDArray[np.bool_]] = np.zeros((CELLS, CELLS), bool)
_RING_BLACK[1:-1, 1:-1] = True
_RING_BLACK[2:-2, 2:-2] = False
_RING_WHITE: Final[NDArray[np.bool_]] = np.ones((CELLS, CELLS), bool)
_RING_WHITE[1:-1, 1:-1] = False


@dataclass(frozen=True)
class QuadDecode:
    """A quad read as a tag: id, bit errors, ring contrast, corners TL, TR, BR, BL."""

    tag_id: int
    hamming: int
    contrast: float
    corners_px: Array


@dataclass(frozen=True)
class _Cells:
    """A quad's 10 x 10 cell means and what the hard decode reads from its rings."""

    cells: Array
    contrast: float  # white ring median - black ring median
    threshold: float
    black_fraction: float  # of the black ring's cells below the threshold
    white_fraction: float  # of the white ring's cells above it


def _read_cells(image: NDArray[np.uint8], quad: Array) -> _Cells | None:
    """The cell means behind a quad (clockwise on screen); None when the whole tag, white ring
    included, is not inside the image: a tag the image edge cuts would be read from replicated border
    pixels (and its ROI would reach outside the image)."""
    dst = np.array([[1, 1], [9, 1], [9, 9], [1, 9]], np.float32) * _PX - 0.5
    h = cv2.getPerspectiveTransform(np.asarray(quad, np.float32), dst)
    outer = np.array([[[0, 0]], [[CELLS, 0]], [[CELLS, CELLS]], [[0, CELLS]]], np.float32) * _PX - 0.5
    ring = cv2.perspectiveTransform(outer, np.linalg.inv(h)).reshape(4, 2)
    height, width = image.shape
    if ring.min() < 0 or np.any(ring[:, 0] > width - 1) or np.any(ring[:, 1] > height - 1):
        return None
    side = CELLS * _PX
    patch = cv2.warpPerspective(image, h, (side, side), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    lo, hi = round(0.2 * _PX), round(0.8 * _PX)
    cells = patch.reshape(CELLS, _PX, CELLS, _PX)[:, lo:hi, :, lo:hi].astype(np.float64).mean(axis=(1, 3))
    black, white = float(np.median(cells[_RING_BLACK])), float(np.median(cells[_RING_WHITE]))
    threshold = (black + white) / 2
    return _Cells(
        cells,
        white - black,
        threshold,
        float(np.mean(cells[_RING_BLACK] < threshold)),
        float(np.mean(cells[_RING_WHITE] > threshold)),
    )


def _hard_decode(quad: Array, c: _Cells, s: LineQuadSettings) -> QuadDecode | None:
    if c.contrast < s.min_ring_contrast:
        return None
    if c.black_fraction < s.min_ring_fraction or c.white_fraction < s.min_ring_fraction:
        return None
    bits = c.cells[2:-2, 2:-2].ravel() > c.threshold
    book, ids, rots = _data_book()
    dist = np.count_nonzero(book != bits[None, :], axis=1)
    k = int(np.argmin(dist))
    if dist[k] > s.max_hamming:
        return None
    # The patch is the tag turned by np.rot90 rots[k] times (counter-clockwise on screen): the tag's
    # top-left corner is the quad's corner -rots[k] (mod 4).
    corners = np.roll(np.asarray(quad, np.float64), int(rots[k]), axis=0)
    return QuadDecode(int(ids[k]), int(dist[k]), c.contrast, corners)


def decode_quad(image: NDArray[np.uint8], quad: Array, s: LineQuadSettings) -> QuadDecode | None:
    """Step 6: the quad (clockwise on screen) as a tag36h11 tag by hard decoding, or None."""
    c = _read_cells(image, quad)
    return None if c is None else _hard_decode(quad, c, s)


def _soft_candidate(c: _Cells, s: LineQuadSettings) -> bool:
    """Worth a blind soft decode: the rings still stand out although the bits did not read."""
    return (
        c.contrast >= s.min_ring_contrast
        and c.black_fraction >= s.soft_min_ring_fraction
        and c.white_fraction >= s.soft_min_ring_fraction
    )


def soft_decode_quad(image: NDArray[np.uint8], quad: Array, s: LineQuadSettings) -> QuadDecode | None:
    """Step 8: a quad whose bits blur smeared, read by `shared.vision.softdecode.blind_decode`: first
    as found (a quad that reads nothing like a tag ends here; one the gate accepts is read), else
    refitted at full size and gated again (under heavy blur either can sit closer to the tag).
    hamming is the hard read's distance to the word found (often above max_hamming: the bits did not
    read, which is why the soft decode was needed)."""
    r = blind_decode(image, quad, s.soft)
    if r is None or min(r.correlation, r.full_correlation) < s.soft_min_first_correlation:
        return None
    if not r.accepted:
        r = blind_decode(image, refine_corners(image, np.asarray(quad, np.float64)), s.soft)
        if r is None or not r.accepted:
            return None
    c = _read_cells(image, r.corners_px)
    if c is None:
        return None
    bits = c.cells[2:-2, 2:-2].ravel() > c.threshold
    book, ids, rots = _data_book()
    # c was read in the tag's own orientation (corners TL first): rotation 0
    row = int(np.flatnonzero((ids == r.tag_id) & (rots == 0))[0])
    return QuadDecode(r.tag_id, int(np.count_nonzero(book[row] != bits)), c.contrast, r.corners_px)


def _edge_line(image: NDArray[np.uint8], p0: Array, p1: Array, inward: Array, reach_px: float) -> Array | None:
    """The side p0 -> p1 refitted at full size: along it, the strongest dark-inward step within
    `reach_px` of the side (sub-pixel, parabola), weak steps dropped (an occluder's stretch), a Huber
    line fit. Returns (point, direction) as a (2, 2) array, or None with too few edge points."""
    length = float(np.linalg.norm(p1 - p0))
    k = int(np.clip(length / 2, 8, 40))
    t = np.linspace(0.15, 0.85, k)
    offsets = np.arange(-reach_px, reach_px + 1e-9, 0.5)
    base = p0[None, :] + t[:, None] * (p1 - p0)[None, :]
    pts = base[:, None, :] + offsets[None, :, None] * inward[None, None, :]
    flat = pts.reshape(-1, 2).astype(np.float32)
    prof = cv2.remap(image, flat[:, :1], flat[:, 1:], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    prof = np.asarray(prof, np.float64).reshape(k, len(offsets))
    step = prof[:, :-2] - prof[:, 2:]  # light outside -> dark inside: positive on the edge
    j = np.argmax(step, axis=1)
    strength = step[np.arange(k), j]
    good = (strength > 0.5 * np.median(strength)) & (strength > 4.0) & (j > 0) & (j < step.shape[1] - 1)
    if good.sum() < 5:
        return None
    jj, rows = j[good], np.flatnonzero(good)
    left, mid, right = step[rows, jj - 1], step[rows, jj], step[rows, jj + 1]
    denom = left - 2 * mid + right
    frac = np.where(np.abs(denom) > 1e-9, 0.5 * (left - right) / np.where(np.abs(denom) > 1e-9, denom, 1.0), 0.0)
    off = offsets[1:-1][jj] + np.clip(frac, -0.5, 0.5) * 0.5
    edge = base[rows] + off[:, None] * inward[None, :]
    vx, vy, x0, y0 = cv2.fitLine(edge.astype(np.float32), cv2.DIST_HUBER, 0, 0.01, 0.01).ravel()
    return np.array([[x0, y0], [vx, vy]], np.float64)


def refine_corners(image: NDArray[np.uint8], corners: Array) -> Array:
    """Corners TL, TR, BR, BL from the four sides refitted at full size (`_edge_line`); a side that
    cannot be refitted keeps its line through the two corners."""
    centre = corners.mean(axis=0)
    reach = float(np.clip(quad_side_px(corners) / 20, 2.0, 4.0))
    sides = []
    for k in range(4):
        p0, p1 = corners[k], corners[(k + 1) % 4]
        d = (p1 - p0) / max(float(np.linalg.norm(p1 - p0)), 1e-9)
        inward = np.array([-d[1], d[0]])
        if inward @ (centre - p0) < 0:
            inward = -inward
        fit = _edge_line(image, p0, p1, inward, reach)
        sides.append(fit if fit is not None else np.array([p0, d]))
    out = []
    for k in range(4):
        (pa, da), (pb, db) = sides[(k - 1) % 4], sides[k]
        m = np.column_stack([da, -db])
        if abs(np.linalg.det(m)) < 1e-9:
            return corners
        t = np.linalg.solve(m, pb - pa)
        out.append(pa + t[0] * da)
    refined = np.array(out)
    # a refit that moved a corner further than the search reach is not trusted
    if np.max(np.linalg.norm(refined - corners, axis=1)) > 2 * reach:
        return corners
    return refined


class LineQuadProposer:
    """Tags from straight edges (module docstring); not thread-safe (one LSD object): one per thread."""

    def __init__(self, settings: LineQuadSettings | None = None) -> None:
        self.settings = settings or LineQuadSettings()
        self._lsd = cv2.createLineSegmentDetector(cv2.LSD_REFINE_NONE)
        self.soft_decoded = 0  # tags read by the soft decode since start-up
        if self.settings.soft_decode:
            prepare(self.settings.soft)

    def detect(
        self,
        image: NDArray[np.uint8],
        known: Sequence[Array] = (),
        *,
        others: Sequence[Detection] = (),
        same_tag_fraction: float = 0.5,
    ) -> list[Detection]:
        """Decoded tags of one grayscale image, sorted by id (decision_margin = ring contrast). `known`:
        quads of tags already found (another proposer's); quads centred inside one are not soft-decoded.
        `others`: tags another proposer found (their quads count as `known` too); a tag read here that is
        clearly one of them (`merge_proposals`' test at half `same_tag_fraction`, the caller's: refined or
        not, the caller then finds it a duplicate) comes back with its corners as read, not refined: the
        caller keeps its own (refining them took 1.9 ms of a 1280x720 demo frame's ~23 ms stage 1, for tags
        AprilTag had already found)."""
        s = self.settings
        known = [*known, *(d.corners_px for d in others)]
        img = np.ascontiguousarray(check_image(image))
        lines = oriented_lines(img, segments(img, s.scale, self._lsd), s)
        found: list[tuple[QuadDecode, int]] = []
        unread: list[tuple[Array, int, float]] = []
        for quad, sides in quads(lines, corner_graph(lines, s), s):
            c = _read_cells(img, quad)
            if c is None:
                continue
            r = _hard_decode(quad, c, s)
            if r is not None:
                found.append((r, sides))
            elif s.soft_decode and quad_side_px(quad) >= s.soft_min_side_px and _soft_candidate(c, s):
                unread.append((quad, sides, c.contrast))
        # best first (fewest bit errors, four sides seen, most contrast); the merge keeps the first of
        # the quads that are one tag
        found.sort(key=lambda x: (x[0].hamming, -x[1], -x[0].contrast))
        taken = [*known, *(r.corners_px for r, _ in found)]
        soft: list[QuadDecode] = []
        tried = 0
        for quad, _, _ in sorted(unread, key=lambda x: (-x[1], -x[2])):
            if tried >= s.soft_max_per_frame:
                break
            if any(_inside(quad.mean(axis=0), t) for t in taken):
                continue
            tried += 1
            r = soft_decode_quad(img, quad, s)
            if r is not None:
                soft.append(r)
                taken.append(r.corners_px)
        hard, _ = merge_proposals(
            [], [Detection(r.tag_id, r.contrast, r.hamming, r.corners_px, "lines") for r, _ in found]
        )
        read, _ = merge_proposals(
            hard, [Detection(r.tag_id, r.contrast, r.hamming, r.corners_px, "lines_soft") for r in soft]
        )
        self.soft_decoded += len(read)
        best = hard + read
        if s.refine_corners:
            new, _ = merge_proposals(list(others), best, same_tag_fraction=same_tag_fraction / 2)
            fresh = {id(d) for d in new}
            best = [replace(d, corners_px=refine_corners(img, d.corners_px)) if id(d) in fresh else d for d in best]
        return sorted(best, key=lambda d: d.tag_id)


def _inside(point: Array, quad: Array) -> bool:
    contour = np.asarray(quad, np.float32).reshape(-1, 1, 2)
    return cv2.pointPolygonTest(contour, (float(point[0]), float(point[1])), False) >= 0
