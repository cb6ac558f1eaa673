"""Rendered room sequences with exact ground truth, for SLAM and tracking benchmarks.

A camera moves through a box-shaped room whose walls carry tag36h11 tags; every frame averages the
tags over the exposure time (exact motion blur, rendered by bench/tagrender.py's coverage renderer at
sub-exposure poses), the walls are ray-cast and textured, and the sensor adds lighting flicker,
vignetting, shot and read noise, a tone curve and JPEG. Like bench/tagrender.py it imports nothing
from `shared/`: the product is judged on images its own code did not make.

World frame: z up, the room spans [0, W] x [0, D] x [0, H] metres. Tags follow the README's
convention (x right, y down, z into the tag, i.e. into the wall); the camera is OpenCV's (x right,
y down, z forward). Ground truth is the pose at mid-exposure; `world_from_camera` and every tag's
`world_from_tag` are 4x4 matrices.

    .venv/bin/python -m bench.tagseq --sequence fast --out /tmp/fast   # PNGs + groundtruth.tum + tags.json
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Final

import cv2
import numpy as np
from numpy.typing import NDArray

from bench.tagrender import (
    BLACK_CELLS,
    CELLS,
    NUM_TAG36H11_IDS,
    _line_kernel,
    corners_in_tag,
    project_points,
    render_tag_layer,
    tag_cells,
    tag_plane_homography,
)

FloatArray = NDArray[np.float64]

TEXEL_M: Final[float] = 0.01  # wall texture resolution


@dataclass(frozen=True)
class SequenceSpec:
    """One sequence: the room, its tags, the camera's motion and the sensor."""

    name: str
    seed: int
    speed_mps: float  # mean camera speed
    turn_dps: float  # mean yaw rate (peaks are 1.7x)
    exposure_s: float  # blur length follows from the motion during the exposure
    flicker: float = 0.0  # lighting varies by +- this fraction (50 Hz mains beating with the frame rate, plus noise)
    duration_s: float = 10.0
    fps: float = 30.0
    width: int = 1280
    height: int = 720
    fx: float = 1045.0
    fy: float = 1045.0
    cx: float = 639.5
    cy: float = 359.5
    room_m: tuple[float, float, float] = (5.0, 4.5, 2.8)
    n_tags: int = 12
    tag_size_m: tuple[float, float] = (0.10, 0.20)
    jpeg_quality: int = 90
    supersample: int = 6  # per sub-exposure render on pixels that straddle an edge

    def camera_matrix(self) -> FloatArray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def n_frames(self) -> int:
        return round(self.duration_s * self.fps)


SEQUENCES: Final[dict[str, SequenceSpec]] = {
    "slow": SequenceSpec("slow", seed=11, speed_mps=0.37, turn_dps=10.0, exposure_s=0.008),
    "medium": SequenceSpec("medium", seed=12, speed_mps=0.55, turn_dps=15.0, exposure_s=0.012, flicker=0.25),
    "fast": SequenceSpec("fast", seed=13, speed_mps=0.52, turn_dps=25.0, exposure_s=0.02, n_tags=10),
}


@dataclass(frozen=True)
class WallTag:
    """A tag on the wall: id, size (side of the black square) and world pose."""

    tag_id: int
    size_m: float
    world_from_tag: FloatArray


@dataclass
class Frame:
    """One rendered frame and its truth."""

    index: int
    stamp_s: float
    image: NDArray[np.uint8]
    world_from_camera: FloatArray  # mid-exposure
    in_view: list[int]  # tags whose whole black square is inside the image (2 px margin), in front
    blur_px: dict[int, float] = field(default_factory=dict)  # per tag in view: longest corner streak
    gain: float = 1.0


# ----------------------------------------------------------------------------------------------------
# Scene


def _wall_frame(normal_in: FloatArray) -> FloatArray:
    """Tag axes for a wall whose inward normal is `normal_in`: z into the wall, y down, x right."""
    z = -normal_in
    y = np.array([0.0, 0.0, -1.0])
    x = np.cross(y, z)
    return np.column_stack([x, y, z])


def place_tags(spec: SequenceSpec) -> list[WallTag]:
    """Tags around the walls, spread in azimuth from the room centre, at 1.0-1.9 m height."""
    rng = np.random.default_rng([spec.seed, 1])
    w, d, _ = spec.room_m
    centre = np.array([w / 2, d / 2])
    ids = rng.choice(NUM_TAG36H11_IDS, size=spec.n_tags, replace=False)
    base = rng.uniform(0, 2 * math.pi)
    tags = []
    for i, tag_id in enumerate(ids):
        az = base + 2 * math.pi * (i + rng.uniform(-0.25, 0.25)) / spec.n_tags
        ray = np.array([math.cos(az), math.sin(az)])
        # first wall hit from the centre
        ts = []
        for axis, lim in ((0, 0.0), (0, w), (1, 0.0), (1, d)):
            if abs(ray[axis]) > 1e-9:
                t = (lim - centre[axis]) / ray[axis]
                if t > 0:
                    ts.append((t, axis, lim))
        t, axis, lim = min(ts)
        p = centre + t * ray
        other = 1 - axis
        p[other] = float(np.clip(p[other], 0.35, (d if other == 1 else w) - 0.35))
        normal_in = np.zeros(3)
        normal_in[axis] = 1.0 if lim == 0.0 else -1.0
        pose = np.eye(4)
        pose[:3, :3] = _wall_frame(normal_in)
        pose[:3, 3] = [p[0], p[1], rng.uniform(1.0, 1.9)]
        pose[:3, 3] += normal_in * 1e-3  # on the wall's surface
        tags.append(WallTag(int(tag_id), float(rng.uniform(*spec.tag_size_m)), pose))
    return tags


class Trajectory:
    """Smooth camera motion: a Lissajous path round the room centre, yaw turning one way at a varying
    rate, pitch and roll oscillating. Scaled so the mean speed and yaw rate match the spec."""

    def __init__(self, spec: SequenceSpec) -> None:
        rng = np.random.default_rng([spec.seed, 2])
        self.spec = spec
        w, d, _ = spec.room_m
        self.centre = np.array([w / 2, d / 2, 1.45])
        self.periods = np.array([spec.duration_s, spec.duration_s * 0.7, spec.duration_s * 0.45])
        self.phases = rng.uniform(0, 2 * math.pi, 3)
        shape = np.array([1.0, 0.8, 0.08])
        ts = np.linspace(0, spec.duration_s, 4001)
        p = self._path(ts, shape)
        mean_speed = float(np.mean(np.linalg.norm(np.diff(p, axis=0), axis=1)) / (ts[1] - ts[0]))
        self.amplitude = shape * spec.speed_mps / mean_speed
        self.yaw0 = rng.uniform(0, 2 * math.pi)
        self.yaw_phase = rng.uniform(0, 2 * math.pi)
        self.pitch_phase, self.roll_phase = rng.uniform(0, 2 * math.pi, 2)

    def _path(self, t: FloatArray, amplitude: FloatArray) -> FloatArray:
        t = np.atleast_1d(t)[:, None]
        return self.centre + amplitude * np.sin(2 * math.pi * t / self.periods + self.phases)

    def yaw_rate_dps(self, t: float) -> float:
        return self.spec.turn_dps * (1.0 + 0.7 * math.sin(2 * math.pi * t / 4.0 + self.yaw_phase))

    def world_from_camera(self, t: float) -> FloatArray:
        s = self.spec
        pos = self._path(np.array([t]), self.amplitude)[0]
        # yaw = yaw0 + integral of the rate (closed form)
        omega = 2 * math.pi / 4.0
        integral = t - 0.7 / omega * (math.cos(omega * t + self.yaw_phase) - math.cos(self.yaw_phase))
        yaw = self.yaw0 + math.radians(s.turn_dps) * integral
        pitch = math.radians(-4.0 + 6.0 * math.sin(2 * math.pi * t / 3.3 + self.pitch_phase))
        roll = math.radians(3.0 * math.sin(2 * math.pi * t / 5.1 + self.roll_phase))
        fwd = np.array([math.cos(yaw) * math.cos(pitch), math.sin(yaw) * math.cos(pitch), math.sin(pitch)])
        right = np.cross(fwd, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        down = np.cross(fwd, right)
        r = np.column_stack([right, down, fwd])
        c, sn = math.cos(roll), math.sin(roll)
        r = r @ np.array([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]])
        pose = np.eye(4)
        pose[:3, :3] = r
        pose[:3, 3] = pos
        return pose


# ----------------------------------------------------------------------------------------------------
# Walls


class Room:
    """Textured walls, floor and ceiling, ray-cast per pixel (bilinear texture lookup)."""

    def __init__(self, spec: SequenceSpec) -> None:
        rng = np.random.default_rng([spec.seed, 3])
        self.spec = spec
        w, d, h = spec.room_m
        # faces: (axis, value, u-axis, v-axis); u, v are the in-plane world coordinates
        self.faces = [
            (0, 0.0, 1, 2),
            (0, w, 1, 2),
            (1, 0.0, 0, 2),
            (1, d, 0, 2),
            (2, 0.0, 0, 1),
            (2, h, 0, 1),
        ]
        self.textures = []
        for axis, _, ua, va in self.faces:
            size_u, size_v = spec.room_m[ua], spec.room_m[va]
            self.textures.append(self._texture(rng, size_u, size_v, floor_or_ceiling=axis == 2))
        k = spec.camera_matrix()
        u, v = np.meshgrid(np.arange(spec.width, dtype=np.float64), np.arange(spec.height, dtype=np.float64))
        rays = np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones_like(u)], axis=-1)
        self.rays_cam = rays.reshape(-1, 3)

    @staticmethod
    def _texture(
        rng: np.random.Generator, size_u: float, size_v: float, *, floor_or_ceiling: bool
    ) -> NDArray[np.float32]:
        nu, nv = math.ceil(size_u / TEXEL_M) + 2, math.ceil(size_v / TEXEL_M) + 2
        tex = np.zeros((nv, nu), np.float32)
        for cell_m, weight in ((0.04, 0.25), (0.25, 0.35), (1.2, 0.4)):
            cells = int(cell_m / TEXEL_M)
            small = rng.random((nv // cells + 3, nu // cells + 3)).astype(np.float32)
            big = cv2.resize(small, (small.shape[1] * cells, small.shape[0] * cells), interpolation=cv2.INTER_CUBIC)
            tex += weight * big[:nv, :nu]
        lo, hi = (0.25, 0.55) if floor_or_ceiling else (0.35, 0.8)
        tex = lo + (tex - tex.min()) / max(float(tex.max() - tex.min()), 1e-6) * (hi - lo)
        # posters, frames, sockets: rectangles with hard edges (quad-like clutter for stage 1)
        for _ in range(int(rng.integers(3, 9))):
            rw, rh = rng.uniform(0.05, 0.9, 2) / TEXEL_M
            x0, y0 = rng.uniform(0, nu - rw), rng.uniform(0, nv - rh)
            value = float(rng.uniform(0.05, 0.95))
            cv2.rectangle(tex, (int(x0), int(y0)), (int(x0 + rw), int(y0 + rh)), value, thickness=-1)
        return np.ascontiguousarray(tex.astype(np.float32))

    def render(self, world_from_camera: FloatArray) -> NDArray[np.float32]:
        """Linear radiance (albedo) of the room at every pixel."""
        s = self.spec
        dirs = self.rays_cam @ world_from_camera[:3, :3].T
        origin = world_from_camera[:3, 3]
        best_t = np.full(len(dirs), np.inf)
        best_face = np.zeros(len(dirs), np.int8)
        with np.errstate(divide="ignore", invalid="ignore"):
            for i, (axis, value, _, _) in enumerate(self.faces):
                t = (value - origin[axis]) / dirs[:, axis]
                better = (t > 1e-6) & (t < best_t)
                best_t[better] = t[better]
                best_face[better] = i
        hit = origin + dirs * best_t[:, None]
        out = np.zeros((s.height, s.width), np.float32)
        face_img = best_face.reshape(s.height, s.width)
        for i, (_, _, ua, va) in enumerate(self.faces):
            sel = face_img == i
            if not sel.any():
                continue
            mu = (hit[:, ua] / TEXEL_M).astype(np.float32).reshape(s.height, s.width)
            mv = (hit[:, va] / TEXEL_M).astype(np.float32).reshape(s.height, s.width)
            looked = cv2.remap(self.textures[i], mu, mv, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            out[sel] = looked[sel]
        return out


# ----------------------------------------------------------------------------------------------------
# Frames


class SequenceRenderer:
    """Renders frame i of a sequence deterministically (frames are independent: render in any order)."""

    def __init__(self, spec: SequenceSpec) -> None:
        self.spec = spec
        self.tags = place_tags(spec)
        self.trajectory = Trajectory(spec)
        self.room = Room(spec)
        self.k = spec.camera_matrix()

    def stamp_s(self, index: int) -> float:
        return index / self.spec.fps

    def _gain(self, index: int, rng: np.random.Generator) -> float:
        s = self.spec
        if s.flicker <= 0:
            return 1.0
        t = self.stamp_s(index)
        # mains flicker aliased by the frame rate (a slow beat) plus a faster component and noise
        g = (
            0.6 * math.sin(2 * math.pi * 1.3 * t)
            + 0.3 * math.sin(2 * math.pi * 7.1 * t + 1.0)
            + 0.1 * rng.uniform(-1, 1)
        )
        return 1.0 + s.flicker * g

    def camera_from_tag(self, world_from_camera: FloatArray, tag: WallTag) -> FloatArray:
        return np.linalg.inv(world_from_camera) @ tag.world_from_tag

    def render(self, index: int) -> Frame:
        s = self.spec
        rng = np.random.default_rng([s.seed, 4, index])
        t = self.stamp_s(index)
        mid = self.trajectory.world_from_camera(t)
        start = self.trajectory.world_from_camera(t - s.exposure_s / 2)
        end = self.trajectory.world_from_camera(t + s.exposure_s / 2)

        # Walls at mid-exposure, streaked along the motion of the image centre's wall point.
        bg = self.room.render(mid)
        centre_world = self._centre_point(mid)
        a = self._project_world(start, centre_world)
        b = self._project_world(end, centre_world)
        streak = float(np.linalg.norm(b - a)) if a is not None and b is not None else 0.0
        if a is not None and b is not None and streak > 0.5:
            angle = math.atan2(float(b[1] - a[1]), float(b[0] - a[0]))
            bg = np.asarray(
                cv2.filter2D(bg, -1, _line_kernel(streak, angle), borderType=cv2.BORDER_REFLECT), np.float32
            )

        shape = (s.height, s.width)
        tag_rad = np.zeros(shape, np.float32)
        tag_cov = np.zeros(shape, np.float32)
        in_view, blur = [], {}
        outer_h = 0.5 * CELLS / BLACK_CELLS
        for tag in self.tags:
            outer = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float64) * outer_h * tag.size_m
            poses = [self.camera_from_tag(p, tag) for p in (start, mid, end)]
            if any((outer @ p[:3, :3].T + p[:3, 3])[:, 2].min() < 0.1 for p in poses):
                continue  # behind or beside the camera at some point of the exposure
            ends = [project_points(self.k, p, outer) for p in (poses[0], poses[2])]
            lo = np.minimum(ends[0].min(0), ends[1].min(0))
            hi = np.maximum(ends[0].max(0), ends[1].max(0))
            if hi[0] < -2 or hi[1] < -2 or lo[0] > s.width + 1 or lo[1] > s.height + 1:
                continue
            sweep = float(np.linalg.norm(ends[1] - ends[0], axis=1).max())
            n_sub = min(48, math.ceil(sweep / 0.75) + 1)
            times = t + ((np.arange(n_sub) + 0.5) / n_sub - 0.5) * s.exposure_s
            cells = tag_cells(tag.tag_id)
            for ts in times:
                cam_from_tag = self.camera_from_tag(self.trajectory.world_from_camera(float(ts)), tag)
                rad, cov, (x0, y0, x1, y1) = render_tag_layer(
                    cells=cells,
                    size_m=tag.size_m,
                    homography=tag_plane_homography(self.k, cam_from_tag),
                    albedo=(0.06, 0.85),
                    shape=shape,
                    supersample=s.supersample,
                )
                tag_rad[y0:y1, x0:x1] += rad / n_sub
                tag_cov[y0:y1, x0:x1] += cov / n_sub
            square = project_points(self.k, poses[1], corners_in_tag(tag.size_m))
            if (
                square[:, 0].min() >= 2
                and square[:, 1].min() >= 2
                and square[:, 0].max() <= s.width - 3
                and square[:, 1].max() <= s.height - 3
            ):
                in_view.append(tag.tag_id)
                blur[tag.tag_id] = sweep
        img = tag_rad + (1.0 - tag_cov) * bg

        # Sensor: exposure (longer is brighter), flicker, vignetting, noise, tone curve, JPEG.
        gain = self._gain(index, rng)
        yy, xx = np.mgrid[0 : s.height, 0 : s.width].astype(np.float32)
        r2 = ((xx - s.cx) ** 2 + (yy - s.cy) ** 2) / float(s.cx**2 + s.cy**2)
        img = img * (0.9 * gain) / (1.0 + 0.35 * r2) ** 2
        full_well, read_sigma = 1500.0, 1.5 / 255.0
        sigma = np.sqrt(np.clip(img, 0, None) / full_well + read_sigma**2)
        img = img + sigma * rng.standard_normal(img.shape, dtype=np.float32)
        img = np.clip(img, 0.0, 1.0) ** (1.0 / 2.2)
        out = np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)
        ok, buf = cv2.imencode(".jpg", out, [cv2.IMWRITE_JPEG_QUALITY, s.jpeg_quality])
        if not ok:
            raise RuntimeError("JPEG encoding failed")
        out = np.asarray(cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE), np.uint8)
        return Frame(index, t, np.ascontiguousarray(out), mid, in_view, blur, gain)

    def _centre_point(self, world_from_camera: FloatArray) -> FloatArray:
        """The wall point seen at the principal point."""
        d = world_from_camera[:3, 2]
        o = world_from_camera[:3, 3]
        best = math.inf
        for axis, value, _, _ in self.room.faces:
            if abs(d[axis]) > 1e-9:
                t = (value - o[axis]) / d[axis]
                if 1e-6 < t < best:
                    best = t
        return o + best * d

    def _project_world(self, world_from_camera: FloatArray, p: FloatArray) -> FloatArray | None:
        q = np.linalg.inv(world_from_camera) @ np.append(p, 1.0)
        if q[2] <= 1e-6:
            return None
        uvw = self.k @ q[:3]
        return uvw[:2] / uvw[2]

    def tag_map_json(self) -> dict[str, Any]:
        """The true tag map in the README's tag-map format (sizes and world poses)."""
        return {
            "default_size_m": float(np.mean(self.spec.tag_size_m)),
            "anchor_tag_id": self.tags[0].tag_id,
            "tags": [
                {"id": t.tag_id, "size_m": t.size_m, "world_from_tag": t.world_from_tag.tolist()} for t in self.tags
            ],
        }


def to_tum_row(stamp_s: float, pose: FloatArray) -> str:
    """`timestamp tx ty tz qx qy qz qw` (Hamilton quaternion of the rotation)."""
    r = pose[:3, :3]
    w = math.sqrt(max(0.0, 1.0 + r[0, 0] + r[1, 1] + r[2, 2])) / 2
    x = math.copysign(math.sqrt(max(0.0, 1.0 + r[0, 0] - r[1, 1] - r[2, 2])) / 2, r[2, 1] - r[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1.0 - r[0, 0] + r[1, 1] - r[2, 2])) / 2, r[0, 2] - r[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1.0 - r[0, 0] - r[1, 1] + r[2, 2])) / 2, r[1, 0] - r[0, 1])
    t = pose[:3, 3]
    return f"{stamp_s:.6f} {t[0]:.6f} {t[1]:.6f} {t[2]:.6f} {x:.9f} {y:.9f} {z:.9f} {w:.9f}"


def write_sequence(spec: SequenceSpec, out: Path, *, frames: int | None = None) -> None:
    """A TUM-style folder: rgb/<stamp>.png, rgb.txt, groundtruth.tum, tags.json, camera.json, truth.json."""
    r = SequenceRenderer(spec)
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    rows, gt, truth = [], [], []
    for i in range(frames if frames is not None else spec.n_frames):
        f = r.render(i)
        name = f"rgb/{f.stamp_s:.6f}.png"
        cv2.imwrite(str(out / name), f.image)
        rows.append(f"{f.stamp_s:.6f} {name}")
        gt.append(to_tum_row(f.stamp_s, f.world_from_camera))
        truth.append({"index": i, "in_view": f.in_view, "blur_px": f.blur_px, "gain": f.gain})
    (out / "rgb.txt").write_text("# timestamp filename\n" + "\n".join(rows) + "\n")
    (out / "groundtruth.tum").write_text("# timestamp tx ty tz qx qy qz qw\n" + "\n".join(gt) + "\n")
    (out / "tags.json").write_text(json.dumps(r.tag_map_json(), indent=1))
    k = spec.camera_matrix()
    camera = {"width": spec.width, "height": spec.height, "fx": k[0, 0], "fy": k[1, 1], "cx": k[0, 2], "cy": k[1, 2]}
    (out / "camera.json").write_text(json.dumps(camera, indent=1))
    (out / "truth.json").write_text(json.dumps({"spec": asdict(spec), "frames": truth}))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sequence", choices=sorted(SEQUENCES), required=True)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--frames", type=int, default=None, help="only the first N frames")
    a = p.parse_args()
    write_sequence(SEQUENCES[a.sequence], a.out, frames=a.frames)


if __name__ == "__main__":
    main()
