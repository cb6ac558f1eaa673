"""An independent renderer of single-tag36h11 images with exact ground truth, for accuracy benchmarks.

Nothing here comes from `shared/`: the tag bits come from OpenCV's ArUco dictionary, the geometry is
re-derived from the conventions in the README, and the image is formed by per-pixel area coverage
through the tag-plane homography (not a texture warp), so a method trained on `shared/`'s generator
gets no home advantage.

Conventions (the README's, restated so this file stands alone):
- Pixels: OpenCV's; pixel (u, v) has its centre at integer (u, v) and covers [u - 0.5, u + 0.5].
- Tag frame: origin at the tag centre, x right, y down, z into the tag (AprilTag 3's pose frame);
  `camera_from_tag` maps tag points into the camera frame.
- Tag size: the side of the black square (8 of the tag's 10x10 cells; the outer cell is white).
- Keypoints: the 4x4 lattice at {0, 1/3, 2/3, 1} of the black square, row-major from the top-left;
  indices 0, 3, 15, 12 are the corners TL, TR, BR, BL.

Image formation, in linear radiance: background texture and distractors, motion blur (the average of
several exact renders along a camera rotation; ground truth is the mid-exposure pose), occluders,
lighting gradient and vignetting, defocus (disc PSF), shot and read noise, the camera response (gamma,
contrast), 8-bit quantisation and JPEG.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field, replace
from typing import Any, Final

import cv2
import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

NUM_TAG36H11_IDS: Final[int] = 587
CELLS: Final[int] = 10  # 1 white border cell + 8 cells of black square (incl. its 1-cell black frame)
BLACK_CELLS: Final[int] = 8
LATTICE_FRACTIONS: Final[tuple[float, ...]] = (0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0)
CORNER_INDICES: Final[tuple[int, int, int, int]] = (0, 3, 15, 12)  # TL, TR, BR, BL in the lattice
_AA_SHIFT: Final[int] = 4  # sub-pixel bits for OpenCV's anti-aliased polygon fill


@dataclass(frozen=True)
class RenderSettings:
    """What `render_sample` draws: camera, tag and pose ranges, and the degradation probabilities.

    `clean=True` turns every degradation off (flat grey background, fixed albedos, identity response):
    the mode the renderer's own proof against AprilTag 3 uses.
    """

    width: int = 1280
    height: int = 720
    fx: float = 1045.0
    fy: float = 1045.0
    cx: float = 639.5
    cy: float = 359.5
    clean: bool = False
    tag_size_m: tuple[float, float] = (0.10, 0.20)
    # Side of the black square in px when facing the camera; sampled log-uniformly, distance follows.
    span_px: tuple[float, float] = (40.0, 360.0)
    tilt_deg: tuple[float, float] = (0.0, 65.0)
    image_margin_px: float = 4.0  # the whole tag, white border included, stays this far inside the image
    supersample: int = 16  # samples per pixel side on pixels that straddle an edge (static renders)
    supersample_blurred: int = 8  # per sub-exposure when motion blur averages many renders
    p_motion_blur: float = 0.6
    max_motion_blur_px: float = 15.0
    p_defocus: float = 0.3
    defocus_radius_px: tuple[float, float] = (0.5, 2.5)
    p_gradient: float = 0.7
    p_vignette: float = 0.5
    p_jpeg: float = 0.7
    jpeg_quality: tuple[int, int] = (50, 95)
    p_occluder: float = 0.3
    p_distractors: float = 0.5
    max_distractors: int = 4
    # The camera response's gamma (out = in ** (1 / gamma)), uniform in this range. An sRGB camera is
    # ~2.2, outside the default range: `bench.accuracy --gamma 2.2 2.2` renders that case alone.
    gamma: tuple[float, float] = (0.6, 1.6)

    def camera_matrix(self) -> FloatArray:
        """The 3x3 pinhole matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


CLEAN_SETTINGS: Final[RenderSettings] = RenderSettings(clean=True)


@dataclass(frozen=True)
class TagTruth:
    """Exact ground truth of one rendered tag (mid-exposure pose under motion blur)."""

    tag_id: int
    size_m: float
    camera_from_tag: FloatArray  # 4x4
    corners_px: FloatArray  # (4, 2): TL, TR, BR, BL of the black square
    keypoints_px: FloatArray  # (16, 2): the lattice, row-major from the top-left


@dataclass
class Sample:
    """One rendered image, its tags' truth and how it was made (bins and applied degradations)."""

    image: NDArray[np.uint8]  # (height, width) grayscale
    tags: list[TagTruth]
    meta: dict[str, Any] = field(default_factory=dict)


# ----------------------------------------------------------------------------------------------------
# Tag geometry


def lattice_in_tag(size_m: float) -> FloatArray:
    """The 16 lattice points (x, y, 0) in the tag frame, row-major from the top-left."""
    h = size_m / 2.0
    coords = [-h + size_m * f for f in LATTICE_FRACTIONS]
    return np.array([[x, y, 0.0] for y in coords for x in coords])


def corners_in_tag(size_m: float) -> FloatArray:
    """The black square's corners TL, TR, BR, BL as (x, y, 0) in the tag frame."""
    return lattice_in_tag(size_m)[list(CORNER_INDICES)]


def project_points(camera_matrix: FloatArray, camera_from_tag: FloatArray, points_in_tag: FloatArray) -> FloatArray:
    """Pinhole projection (no distortion) of tag-frame points to OpenCV pixel coordinates."""
    p_cam = points_in_tag @ camera_from_tag[:3, :3].T + camera_from_tag[:3, 3]
    uvw = p_cam @ camera_matrix.T
    return uvw[:, :2] / uvw[:, 2:3]


def tag_plane_homography(camera_matrix: FloatArray, camera_from_tag: FloatArray) -> FloatArray:
    """H mapping tag-plane (x, y, 1) in metres to image pixels (homogeneous)."""
    r = camera_from_tag[:3, :3]
    return camera_matrix @ np.column_stack([r[:, 0], r[:, 1], camera_from_tag[:3, 3]])


def _apply_h(h: FloatArray, pts: FloatArray) -> FloatArray:
    q = pts @ h[:, :2].T + h[:, 2]
    return q[:, :2] / q[:, 2:3]


@functools.lru_cache(maxsize=NUM_TAG36H11_IDS)
def tag_cells(tag_id: int) -> NDArray[np.uint8]:
    """The 10x10 cell pattern (0 black, 1 white) of tag36h11 `tag_id` in AprilTag's canonical orientation.

    OpenCV's `generateImageMarker` for DICT_APRILTAG_36h11 draws the code words rotated by 180 degrees
    relative to AprilTag's own images; rotating back makes AprilTag 3 decode the id with its corners
    in the expected order (tests/test_tagrender.py checks both).
    """
    if not 0 <= tag_id < NUM_TAG36H11_IDS:
        raise ValueError(f"tag36h11 ids are 0..{NUM_TAG36H11_IDS - 1}, got {tag_id}")
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    marker = cv2.aruco.generateImageMarker(dictionary, tag_id, BLACK_CELLS, borderBits=1)
    bits = (np.rot90(marker, 2) > 127).astype(np.uint8)
    cells = np.ones((CELLS, CELLS), np.uint8)
    cells[1:-1, 1:-1] = bits
    return cells


# ----------------------------------------------------------------------------------------------------
# The coverage renderer


def render_tag_layer(
    *,
    cells: NDArray[np.uint8],
    size_m: float,
    homography: FloatArray,
    albedo: tuple[float, float],
    shape: tuple[int, int],
    supersample: int,
) -> tuple[NDArray[np.float32], NDArray[np.float32], tuple[int, int, int, int]]:
    """Area-average the tag over every pixel it touches: (radiance, coverage, (x0, y0, x1, y1)).

    radiance is the integral of the tag's albedo (`albedo` = (black, white)) over each pixel of the
    bounding box [x0, x1) x [y0, y1), coverage the fraction of the pixel inside the tag's outer square.
    A pixel whose preimage (a convex quad) has all four corners in one colour and holds no cell vertex
    is uniform; only the others are supersampled (S x S samples mapped to the tag plane).
    """
    height, width = shape
    cell_m = size_m / BLACK_CELLS
    # cell coordinates (gx, gy) in [0, 10) cover the outer square; tag metres -> cells -> pixels
    tag_from_cells = np.array([[cell_m, 0.0, -CELLS / 2 * cell_m], [0.0, cell_m, -CELLS / 2 * cell_m], [0, 0, 1]])
    img_from_cells = homography @ tag_from_cells
    cells_from_img = np.linalg.inv(img_from_cells)

    outer = _apply_h(img_from_cells, np.array([[0.0, 0.0], [CELLS, 0.0], [CELLS, CELLS], [0.0, CELLS]]))
    x0 = max(math.floor(outer[:, 0].min()) - 1, 0)
    y0 = max(math.floor(outer[:, 1].min()) - 1, 0)
    x1 = min(math.ceil(outer[:, 0].max()) + 2, width)
    y1 = min(math.ceil(outer[:, 1].max()) + 2, height)
    bw, bh = x1 - x0, y1 - y0
    if bw <= 0 or bh <= 0:
        return np.zeros((0, 0), np.float32), np.zeros((0, 0), np.float32), (0, 0, 0, 0)

    colour_lum = np.array([albedo[0], albedo[1], 0.0])  # colour code 2 = outside the tag
    colour_cov = np.array([1.0, 1.0, 0.0])

    def colour_codes(u: FloatArray, v: FloatArray) -> NDArray[np.intp]:
        den = cells_from_img[2, 0] * u + cells_from_img[2, 1] * v + cells_from_img[2, 2]
        gx = (cells_from_img[0, 0] * u + cells_from_img[0, 1] * v + cells_from_img[0, 2]) / den
        gy = (cells_from_img[1, 0] * u + cells_from_img[1, 1] * v + cells_from_img[1, 2]) / den
        inside = (gx >= 0) & (gx < CELLS) & (gy >= 0) & (gy < CELLS)
        ix = np.clip(np.floor(gx), 0, CELLS - 1).astype(np.intp)
        iy = np.clip(np.floor(gy), 0, CELLS - 1).astype(np.intp)
        return np.where(inside, cells[iy, ix].astype(np.intp), 2)

    # colour at every pixel corner (u +- 0.5, v +- 0.5)
    cu, cv_ = np.meshgrid(np.arange(x0, x1 + 1) - 0.5, np.arange(y0, y1 + 1) - 0.5)
    corner_code = colour_codes(cu, cv_)
    tl, tr = corner_code[:-1, :-1], corner_code[:-1, 1:]
    bl, br = corner_code[1:, :-1], corner_code[1:, 1:]
    mixed = (tl != tr) | (tl != bl) | (tl != br)
    # pixels holding a cell vertex may hide a notch of another colour even with uniform corners
    grid = np.arange(CELLS + 1, dtype=np.float64)
    vx, vy = np.meshgrid(grid, grid)
    vertices = _apply_h(img_from_cells, np.column_stack([vx.ravel(), vy.ravel()]))
    vi = np.floor(vertices + 0.5).astype(np.intp) - np.array([x0, y0])
    ok = (vi[:, 0] >= 0) & (vi[:, 0] < bw) & (vi[:, 1] >= 0) & (vi[:, 1] < bh)
    mixed[vi[ok, 1], vi[ok, 0]] = True

    radiance = colour_lum[tl].astype(np.float32)
    coverage = colour_cov[tl].astype(np.float32)

    my, mx = np.nonzero(mixed)
    if my.size:
        s = supersample
        offsets = (np.arange(s) + 0.5) / s - 0.5
        ox, oy = np.meshgrid(offsets, offsets)
        su = (mx + x0)[:, None] + ox.ravel()[None, :]
        sv = (my + y0)[:, None] + oy.ravel()[None, :]
        codes = colour_codes(su, sv)
        radiance[my, mx] = colour_lum[codes].mean(axis=1)
        coverage[my, mx] = colour_cov[codes].mean(axis=1)
    return radiance, coverage, (x0, y0, x1, y1)


# ----------------------------------------------------------------------------------------------------
# Sampling the scene


def _rotation(axis: FloatArray, angle_rad: float) -> FloatArray:
    rvec = np.asarray(axis, np.float64) / np.linalg.norm(axis) * angle_rad
    r, _ = cv2.Rodrigues(rvec)
    return np.asarray(r, np.float64)


def _ray_frame(ray: FloatArray) -> FloatArray:
    """Rotation whose z axis is `ray` (identity for the optical axis)."""
    z = ray / np.linalg.norm(ray)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.column_stack([x, y, z])


@dataclass(frozen=True)
class _Pose:
    camera_from_tag: FloatArray
    distance_m: float
    tilt_deg: float
    span_px: float


def _sample_pose(rng: np.random.Generator, s: RenderSettings, size_m: float) -> _Pose:
    k = s.camera_matrix()
    outer_h = size_m / 2 * CELLS / BLACK_CELLS
    outer_corners = np.array(
        [[-outer_h, -outer_h, 0], [outer_h, -outer_h, 0], [outer_h, outer_h, 0], [-outer_h, outer_h, 0]]
    )
    m = s.image_margin_px
    for _ in range(200):
        span = float(math.exp(rng.uniform(math.log(s.span_px[0]), math.log(s.span_px[1]))))
        distance = s.fx * size_m / span
        tilt = float(rng.uniform(*s.tilt_deg))
        tilt_axis_angle = rng.uniform(0, 2 * math.pi)
        roll = rng.uniform(0, 2 * math.pi)
        for _ in range(20):
            u, v = rng.uniform(0, s.width), rng.uniform(0, s.height)
            ray = np.linalg.solve(k, np.array([u, v, 1.0]))
            ray /= np.linalg.norm(ray)
            tilt_axis = np.array([math.cos(tilt_axis_angle), math.sin(tilt_axis_angle), 0.0])
            rot = _ray_frame(ray) @ _rotation(tilt_axis, math.radians(tilt)) @ _rotation(np.array([0, 0, 1.0]), roll)
            pose = np.eye(4)
            pose[:3, :3] = rot
            pose[:3, 3] = ray * distance
            p_cam = outer_corners @ rot.T + pose[:3, 3]
            if np.any(p_cam[:, 2] < 0.05):
                continue
            px = project_points(k, pose, outer_corners)
            if (
                px[:, 0].min() >= m
                and px[:, 1].min() >= m
                and px[:, 0].max() <= s.width - 1 - m
                and px[:, 1].max() <= s.height - 1 - m
            ):
                return _Pose(pose, distance, tilt, span)
    raise RuntimeError("could not place a tag inside the image; check span_px and the image size")


def _value_noise(rng: np.random.Generator, shape: tuple[int, int], cell_px: int) -> NDArray[np.float32]:
    h, w = shape
    small = rng.random((h // cell_px + 3, w // cell_px + 3)).astype(np.float32)
    big = cv2.resize(small, ((w // cell_px + 3) * cell_px, (h // cell_px + 3) * cell_px), interpolation=cv2.INTER_CUBIC)
    oy, ox = int(rng.integers(0, cell_px)), int(rng.integers(0, cell_px))
    return np.ascontiguousarray(big[oy : oy + h, ox : ox + w])


def _blend_polygon(img: NDArray[np.float32], polygon_px: FloatArray, value: float) -> None:
    """Anti-aliased fill of a polygon with `value`, in place."""
    mask = np.zeros(img.shape, np.uint8)
    pts = np.round(polygon_px * (1 << _AA_SHIFT)).astype(np.int32)
    cv2.fillPoly(mask, [pts], 255, lineType=cv2.LINE_AA, shift=_AA_SHIFT)
    a = mask.astype(np.float32) / 255.0
    img *= 1.0 - a
    img += a * value


def _background(rng: np.random.Generator, s: RenderSettings) -> tuple[NDArray[np.float32], dict[str, Any]]:
    shape = (s.height, s.width)
    weights = rng.dirichlet([1.0, 1.0, 1.0])
    tex = sum(float(wt) * _value_noise(rng, shape, c) for wt, c in zip(weights, (6, 40, 200), strict=True))
    tex = np.asarray(tex, np.float32)
    kind = ["noise"]
    if rng.random() < 0.3:
        period = rng.uniform(6, 60)
        theta = rng.uniform(0, math.pi)
        yy, xx = np.mgrid[0 : s.height, 0 : s.width].astype(np.float32)
        grating = 0.5 + 0.5 * np.sin((xx * math.cos(theta) + yy * math.sin(theta)) * (2 * math.pi / period))
        tex = 0.5 * tex + 0.5 * grating.astype(np.float32)
        kind.append("grating")
    lo, hi = float(rng.uniform(0.05, 0.4)), float(rng.uniform(0.55, 0.95))
    tmin, tmax = float(tex.min()), float(tex.max())
    bg = (lo + (tex - tmin) / max(tmax - tmin, 1e-6) * (hi - lo)).astype(np.float32)
    n_clutter = int(rng.integers(0, 12))
    for _ in range(n_clutter):
        c = rng.uniform([0, 0], [s.width, s.height])
        r = rng.uniform(5, 120)
        n = int(rng.integers(3, 9))
        ang = np.sort(rng.uniform(0, 2 * math.pi, n))
        poly = c + np.column_stack([np.cos(ang), np.sin(ang)]) * r * rng.uniform(0.5, 1.0, (n, 1))
        _blend_polygon(bg, poly, float(rng.uniform(0.05, 0.95)))
    if n_clutter:
        kind.append("clutter")
    return bg, {"background": "+".join(kind), "clutter_shapes": n_clutter}


def _add_distractors(
    rng: np.random.Generator, bg: NDArray[np.float32], s: RenderSettings, keep_out: tuple[float, float, float, float]
) -> int:
    """Dark (partly tag-like) quads that do not touch the tag's box `keep_out` (x0, y0, x1, y1)."""
    n_wanted = int(rng.integers(1, s.max_distractors + 1))
    placed = 0
    for _ in range(n_wanted * 10):
        if placed == n_wanted:
            break
        side = rng.uniform(20, 150)
        c = rng.uniform([side, side], [s.width - side, s.height - side])
        ang = rng.uniform(0, math.pi / 2)
        rot = np.array([[math.cos(ang), -math.sin(ang)], [math.sin(ang), math.cos(ang)]])
        unit = np.array([[-0.5, -0.5], [0.5, -0.5], [0.5, 0.5], [-0.5, 0.5]])
        quad = c + (unit * side + rng.normal(0, 0.06 * side, (4, 2))) @ rot.T
        margin = 12
        if (
            quad[:, 0].max() > keep_out[0] - margin
            and quad[:, 0].min() < keep_out[2] + margin
            and quad[:, 1].max() > keep_out[1] - margin
            and quad[:, 1].min() < keep_out[3] + margin
        ):
            continue
        _blend_polygon(bg, quad, float(rng.uniform(0.02, 0.2)))
        style = rng.random()
        if style < 0.6:  # an inner pattern: white square or random bits, so quad finders bite
            src = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
            hq = cv2.getPerspectiveTransform(src, quad.astype(np.float32)).astype(np.float64)
            if style < 0.3:
                inner = np.array([[0.3, 0.3], [0.7, 0.3], [0.7, 0.7], [0.3, 0.7]])
                _blend_polygon(bg, _apply_h(hq, inner), float(rng.uniform(0.6, 0.95)))
            else:
                bits = rng.random((6, 6)) < 0.5
                for by, bx in zip(*np.nonzero(bits), strict=True):
                    cell = (np.array([[0, 0], [1, 0], [1, 1], [0, 1]]) + np.array([bx + 1, by + 1])) / 8.0
                    _blend_polygon(bg, _apply_h(hq, cell), float(rng.uniform(0.6, 0.95)))
        placed += 1
    return placed


# ----------------------------------------------------------------------------------------------------
# Occluders: shapes lying on the tag plane (a finger holding the tag, a cable across it)


def _capsule(a: FloatArray, b: FloatArray, radius: float, n_arc: int = 12) -> FloatArray:
    d = (b - a) / np.linalg.norm(b - a)
    nrm = np.array([-d[1], d[0]])
    base = math.atan2(nrm[1], nrm[0])
    arc_a = [a + radius * np.array([math.cos(t), math.sin(t)]) for t in np.linspace(base, base + math.pi, n_arc)]
    arc_b = [
        b + radius * np.array([math.cos(t), math.sin(t)])
        for t in np.linspace(base + math.pi, base + 2 * math.pi, n_arc)
    ]
    return np.array(arc_a + arc_b)


def _thick_polyline(points: FloatArray, radius: float) -> FloatArray:
    d = np.gradient(points, axis=0)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    nrm = np.column_stack([-d[:, 1], d[:, 0]])
    return np.vstack([points + radius * nrm, (points - radius * nrm)[::-1]])


def _segment_distance(p: FloatArray, a: FloatArray, b: FloatArray) -> float:
    ab = b - a
    t = float(np.clip(np.dot(p - a, ab) / np.dot(ab, ab), 0.0, 1.0))
    return float(np.linalg.norm(p - (a + t * ab)))


@dataclass(frozen=True)
class _Occluder:
    kind: str
    polygon_in_tag: FloatArray  # (N, 2) metres in the tag plane
    albedo: float


def _sample_occluder(rng: np.random.Generator, size_m: float, pose: FloatArray) -> _Occluder | None:
    """A finger or cable crossing the black square's edges, clear of its four corners by one cell."""
    h = size_m / 2
    clearance = size_m / BLACK_CELLS
    corners = corners_in_tag(size_m)[:, :2]
    edges = [  # (point on the edge's middle, inward normal, tangent)
        (np.array([0.0, -h]), np.array([0.0, 1.0]), np.array([1.0, 0.0])),
        (np.array([h, 0.0]), np.array([-1.0, 0.0]), np.array([0.0, 1.0])),
        (np.array([0.0, h]), np.array([0.0, -1.0]), np.array([1.0, 0.0])),
        (np.array([-h, 0.0]), np.array([1.0, 0.0]), np.array([0.0, 1.0])),
    ]
    for _ in range(30):
        k = int(rng.integers(0, 4))
        mid, inward, tangent = edges[k]
        if rng.random() < 0.5:
            kind = "finger"
            radius = rng.uniform(0.06, 0.15) * size_m
            entry = mid + tangent * rng.uniform(-0.5, 0.5) * h
            ang = rng.uniform(-0.6, 0.6)
            axis_in = _rotation(np.array([0, 0, 1.0]), ang)[:2, :2] @ inward
            depth = rng.uniform(0.15, 0.55) * size_m
            tip = entry + axis_in * depth / max(math.cos(ang), 0.3)
            root = entry - axis_in * rng.uniform(0.5, 1.2) * size_m
            clear = min(_segment_distance(c, tip, root) for c in corners) - radius
            poly = _capsule(tip, root, radius)
            albedo = float(rng.uniform(0.35, 0.75))
        else:
            kind = "cable"
            radius = rng.uniform(0.015, 0.04) * size_m
            a = mid + tangent * rng.uniform(-0.6, 0.6) * h
            b = mid + 2 * h * inward + tangent * rng.uniform(-0.6, 0.6) * h
            d = (b - a) / np.linalg.norm(b - a)
            a_far = a - d * rng.uniform(0.4, 1.0) * size_m
            b_far = b + d * rng.uniform(0.4, 1.0) * size_m
            sag = np.array([-d[1], d[0]]) * rng.uniform(-0.15, 0.15) * size_m
            t = np.linspace(0.0, 1.0, 40)[:, None]
            curve = (1 - t) ** 2 * a_far + 2 * t * (1 - t) * ((a_far + b_far) / 2 + 2 * sag) + t**2 * b_far
            clear = float(np.min(np.linalg.norm(curve[None, :, :] - corners[:, None, :], axis=2))) - radius
            poly = _thick_polyline(curve, radius)
            albedo = float(rng.uniform(0.02, 0.6))
        if clear < clearance:
            continue
        p_cam = np.column_stack([poly, np.zeros(len(poly))]) @ pose[:3, :3].T + pose[:3, 3]
        if np.all(p_cam[:, 2] > 0.05):
            return _Occluder(kind, poly, albedo)
    return None


def _polygon_mask(shape: tuple[int, int], polygon_px: FloatArray) -> NDArray[np.float32]:
    mask = np.zeros(shape, np.uint8)
    pts = np.round(polygon_px * (1 << _AA_SHIFT)).astype(np.int32)
    cv2.fillPoly(mask, [pts], 255, lineType=cv2.LINE_AA, shift=_AA_SHIFT)
    return mask.astype(np.float32) / 255.0


# ----------------------------------------------------------------------------------------------------
# Optics and sensor


def _line_kernel(length_px: float, angle_rad: float) -> NDArray[np.float32]:
    """Normalised box PSF of a linear motion of `length_px`, splatted bilinearly."""
    half = math.ceil(length_px / 2) + 1
    k = np.zeros((2 * half + 1, 2 * half + 1), np.float64)
    n = math.ceil(length_px * 4) + 1
    for t in np.linspace(-0.5, 0.5, n):
        x = half + t * length_px * math.cos(angle_rad)
        y = half + t * length_px * math.sin(angle_rad)
        ix, iy = math.floor(x), math.floor(y)
        fx, fy = x - ix, y - iy
        k[iy, ix] += (1 - fx) * (1 - fy)
        k[iy, ix + 1] += fx * (1 - fy)
        k[iy + 1, ix] += (1 - fx) * fy
        k[iy + 1, ix + 1] += fx * fy
    return (k / k.sum()).astype(np.float32)


def _centre_sweep_px(camera_matrix: FloatArray, point_cam: FloatArray, axis: FloatArray, omega_rad: float) -> float:
    """Image length swept by `point_cam` while the camera turns by `omega_rad` (centred on mid-exposure)."""
    ends = [camera_matrix @ (_rotation(axis, omega_rad * e) @ point_cam) for e in (-0.5, 0.5)]
    return float(np.linalg.norm(ends[1][:2] / ends[1][2] - ends[0][:2] / ends[0][2]))


def _disc_kernel(radius_px: float) -> NDArray[np.float32]:
    """Normalised disc PSF (defocus), 8x8 supersampled at its rim."""
    half = math.ceil(radius_px) + 1
    s = 8
    off = (np.arange(s) + 0.5) / s - 0.5
    coords = np.arange(-half, half + 1)
    xs = (coords[:, None] + off[None, :]).ravel()
    xx, yy = np.meshgrid(xs, xs)
    inside = (xx**2 + yy**2 <= radius_px**2).astype(np.float64)
    k = inside.reshape(2 * half + 1, s, 2 * half + 1, s).mean(axis=(1, 3))
    return (k / k.sum()).astype(np.float32)


# ----------------------------------------------------------------------------------------------------
# The sample


def render_sample(index: int, seed: int, settings: RenderSettings = RenderSettings()) -> Sample:
    """Render image `index` of the set `seed`: deterministic from (seed, index) and the settings."""
    s = settings
    rng = np.random.default_rng([seed, index])
    shape = (s.height, s.width)
    k = s.camera_matrix()
    tag_id = int(rng.integers(0, NUM_TAG36H11_IDS))
    size_m = float(rng.uniform(*s.tag_size_m))
    pose = _sample_pose(rng, s, size_m)
    cam_from_tag = pose.camera_from_tag
    applied: list[str] = []
    meta: dict[str, Any] = {
        "index": index,
        "seed": seed,
        "clean": s.clean,
        "tag_id": tag_id,
        "size_m": size_m,
        "distance_m": pose.distance_m,
        "tilt_deg": pose.tilt_deg,
        "span_px": pose.span_px,
    }

    if s.clean:
        albedo = (0.1, 0.9)
        bg = np.full(shape, 0.5, np.float32)
        meta["background"] = "flat"
    else:
        black = float(rng.uniform(0.02, 0.15))
        albedo = (black, float(rng.uniform(max(0.55, black + 0.4), 0.95)))
        bg, bg_meta = _background(rng, s)
        meta.update(bg_meta)
        applied.append("background_texture")
    meta["albedo_black_white"] = list(albedo)

    outer_h = size_m / 2 * CELLS / BLACK_CELLS
    outer = project_points(
        k,
        cam_from_tag,
        np.array([[-outer_h, -outer_h, 0], [outer_h, -outer_h, 0], [outer_h, outer_h, 0], [-outer_h, outer_h, 0]]),
    )
    if not s.clean and rng.random() < s.p_distractors:
        box = (float(outer[:, 0].min()), float(outer[:, 1].min()), float(outer[:, 0].max()), float(outer[:, 1].max()))
        meta["distractors"] = _add_distractors(rng, bg, s, box)
        applied.append("distractors")
    else:
        meta["distractors"] = 0

    # Motion: a camera rotation about an axis in the image plane, centred on mid-exposure (the truth).
    blur_len, blur_angle = 0.0, 0.0
    if not s.clean and rng.random() < s.p_motion_blur:
        blur_len = float(rng.uniform(0.0, s.max_motion_blur_px))
        blur_angle = float(rng.uniform(0, 2 * math.pi))
    centre_cam = cam_from_tag[:3, 3]
    if blur_len > 0:
        # small rotation omega moves a point near the optical axis by about f * omega
        omega_axis = np.array([-math.sin(blur_angle), math.cos(blur_angle), 0.0])
        omega = blur_len / s.fx
        for _ in range(3):  # off-axis points sweep more than f * omega: rescale to the sampled length
            omega *= blur_len / _centre_sweep_px(k, centre_cam, omega_axis, omega)
        n_sub = math.ceil(blur_len / 0.75) + 1
        times = (np.arange(n_sub) + 0.5) / n_sub - 0.5
        sub_poses = []
        for t in times:
            p = np.eye(4)
            p[:3, :3] = _rotation(omega_axis, omega * float(t))
            sub_poses.append(p @ cam_from_tag)
        blur_len = _centre_sweep_px(k, centre_cam, omega_axis, omega)
        bg = np.asarray(
            cv2.filter2D(bg, -1, _line_kernel(blur_len, blur_angle), borderType=cv2.BORDER_REFLECT), np.float32
        )
        applied.append("motion_blur")
        supersample = s.supersample_blurred
    else:
        sub_poses = [cam_from_tag]
        supersample = s.supersample
    meta["blur_px"] = blur_len
    meta["blur_angle_deg"] = math.degrees(blur_angle)
    meta["exposure_subrenders"] = len(sub_poses)

    # Tag layer, averaged over the exposure, composited over the (equally blurred) background.
    cells = tag_cells(tag_id)
    tag_rad = np.zeros(shape, np.float32)
    tag_cov = np.zeros(shape, np.float32)
    for p in sub_poses:
        rad, cov, (x0, y0, x1, y1) = render_tag_layer(
            cells=cells,
            size_m=size_m,
            homography=tag_plane_homography(k, p),
            albedo=albedo,
            shape=shape,
            supersample=supersample,
        )
        tag_rad[y0:y1, x0:x1] += rad
        tag_cov[y0:y1, x0:x1] += cov
    tag_rad /= len(sub_poses)
    tag_cov /= len(sub_poses)
    img = tag_rad + (1.0 - tag_cov) * bg

    # Occluder on the tag plane, moving with it.
    occluded_fraction = 0.0
    occluder = _sample_occluder(rng, size_m, cam_from_tag) if not s.clean and rng.random() < s.p_occluder else None
    if occluder is not None:
        occ = np.zeros(shape, np.float32)
        for p in sub_poses:
            occ += _polygon_mask(shape, _apply_h(tag_plane_homography(k, p), occluder.polygon_in_tag))
        occ /= len(sub_poses)
        img = img * (1.0 - occ) + occ * occluder.albedo
        mid_h = tag_plane_homography(k, cam_from_tag)
        occ_mid = _polygon_mask(shape, _apply_h(mid_h, occluder.polygon_in_tag))
        square = _polygon_mask(shape, project_points(k, cam_from_tag, corners_in_tag(size_m))[:, :2])
        occluded_fraction = float((occ_mid * square).sum() / max(square.sum(), 1e-9))
        applied.append(f"occluder_{occluder.kind}")
        meta["occluder"] = occluder.kind
        meta["occluder_polygon_px"] = _apply_h(mid_h, occluder.polygon_in_tag).tolist()  # at mid-exposure
        meta["occluder_albedo"] = occluder.albedo
    meta["occluded_fraction"] = occluded_fraction

    if not s.clean:
        img = _degrade(rng, img, s, applied, meta)
        out = np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)
        if rng.random() < s.p_jpeg:
            quality = int(rng.integers(s.jpeg_quality[0], s.jpeg_quality[1] + 1))
            ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, quality])
            if not ok:
                raise RuntimeError("JPEG encoding failed")
            decoded = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
            if decoded is None:
                raise RuntimeError("JPEG decoding failed")
            out = np.asarray(decoded, np.uint8)
            applied.append("jpeg")
            meta["jpeg_quality"] = quality
    else:
        out = np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)
    meta["applied"] = applied

    keypoints = project_points(k, cam_from_tag, lattice_in_tag(size_m))
    truth = TagTruth(
        tag_id=tag_id,
        size_m=size_m,
        camera_from_tag=cam_from_tag,
        corners_px=keypoints[list(CORNER_INDICES)],
        keypoints_px=keypoints,
    )
    return Sample(image=np.ascontiguousarray(out), tags=[truth], meta=meta)


def _degrade(
    rng: np.random.Generator, img: NDArray[np.float32], s: RenderSettings, applied: list[str], meta: dict[str, Any]
) -> NDArray[np.float32]:
    """Lighting, defocus, noise and camera response on a linear image in [0, 1]."""
    h, w = img.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    gain = np.full((h, w), float(rng.uniform(0.6, 1.3)), np.float32)
    meta["exposure_gain"] = float(gain[0, 0])
    if rng.random() < s.p_gradient:
        theta = rng.uniform(0, 2 * math.pi)
        strength = float(rng.uniform(0.2, 0.8))
        ramp = ((xx - w / 2) * math.cos(theta) + (yy - h / 2) * math.sin(theta)) / (w / 2)
        gain *= np.clip(1.0 + strength * ramp, 0.15, None)
        applied.append("lighting_gradient")
        meta["gradient_strength"] = strength
    if rng.random() < s.p_vignette:
        strength = float(rng.uniform(0.2, 0.8))
        r2 = ((xx - s.cx) ** 2 + (yy - s.cy) ** 2) / float(s.cx**2 + s.cy**2)
        gain /= (1.0 + strength * r2) ** 2
        applied.append("vignetting")
        meta["vignette_strength"] = strength
    img = img * gain
    if rng.random() < s.p_defocus:
        radius = float(rng.uniform(*s.defocus_radius_px))
        img = np.asarray(cv2.filter2D(img, -1, _disc_kernel(radius), borderType=cv2.BORDER_REFLECT), np.float32)
        applied.append("defocus")
        meta["defocus_radius_px"] = radius
    # shot noise (variance proportional to the signal) plus read noise, in linear units
    full_well = float(math.exp(rng.uniform(math.log(400.0), math.log(5000.0))))
    read_sigma = float(rng.uniform(0.5, 3.0)) / 255.0
    sigma = np.sqrt(np.clip(img, 0, None) / full_well + read_sigma**2)
    img = img + sigma * rng.standard_normal(img.shape, dtype=np.float32)
    applied.append("noise")
    meta["full_well_e"] = full_well
    meta["read_noise_dn"] = read_sigma * 255.0
    gamma = float(rng.uniform(*s.gamma))
    contrast = float(rng.uniform(0.7, 1.2))
    brightness = float(rng.uniform(-0.08, 0.08))
    img = np.clip(img, 0.0, 1.0) ** (1.0 / gamma)
    img = (img - 0.5) * contrast + 0.5 + brightness
    applied.append("gamma_contrast")
    meta.update(gamma=gamma, contrast=contrast, brightness=brightness)
    return img.astype(np.float32)


def clean_settings(settings: RenderSettings = RenderSettings(), **overrides: Any) -> RenderSettings:
    """`settings` with every degradation off (and any field overridden)."""
    return replace(settings, clean=True, **overrides)
