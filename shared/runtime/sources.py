"""Frame sources for the camera service: the demo scene (default), an image folder, a video file,
a V4L2 camera. Each yields (grayscale image, ground-truth world_from_camera or None, and the data
set's own time of the frame when it has one)."""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import logging
import math
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Final, Protocol

import cv2
import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from shared.sim.scene import BoxObject, LightSpec, SceneSpec, look_at, tag_on_wall
from shared.vision.camera import CameraIntrinsics
from shared.vision.geometry import (
    Array,
    GeometryError,
    camera_from_yaml,
    default_camera,
    lattice_in_tag,
    project,
)
from shared.vision.trajectory import parse_stamp_nanos, read_tum

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SourceFrame:
    """One frame from a source."""

    image: NDArray[np.uint8]
    world_from_camera: Array | None  # ground truth, when the source knows it
    stamp_nanos: int | None = None  # the data set's time of this frame (TUM rgb.txt, a video's), when it has one
    index: int | None = None  # its place in a folder's listing or a video (unreadable or mis-sized ones are skipped)


class FrameSource(Protocol):
    """What the camera service reads from."""

    camera: CameraIntrinsics

    def frames(self) -> Iterator[SourceFrame]:
        """Yield frames once through the source."""
        ...


# ----------------------------------------------------------------------------------------------
# Demo scene
# ----------------------------------------------------------------------------------------------


def demo_scene() -> SceneSpec:
    """A room with nine 0.2 m tags along one wall and two on the side walls, lit from the ceiling."""
    room = (8.0, 6.0, 3.0)
    tags = [
        tag_on_wall(i, 0.2, wall=0, along_m=-3.2 + 0.8 * i, height_m=1.1 + 0.35 * (i % 2), room_m=room)
        for i in range(9)
    ]
    tags += [
        tag_on_wall(9, 0.2, wall=1, along_m=-1.5, height_m=1.2, room_m=room),
        tag_on_wall(10, 0.2, wall=3, along_m=1.5, height_m=1.2, room_m=room),
    ]
    objects = [
        BoxObject(kind="box", pos=[-2.5, -1.5, 0.3], size=[0.4, 0.3, 0.3], rgba=[0.6, 0.3, 0.2, 1]),
        BoxObject(kind="cylinder", pos=[2.0, -2.0, 0.5], size=[0.25, 0.5, 0.5], rgba=[0.2, 0.4, 0.6, 1]),
        BoxObject(kind="sphere", pos=[0.5, -2.2, 0.35], size=[0.35, 0.35, 0.35], rgba=[0.7, 0.7, 0.3, 1]),
    ]
    lights = [LightSpec(pos=[-2.0, 0.0, 2.9], diffuse=0.5), LightSpec(pos=[2.0, 0.5, 2.9], diffuse=0.45)]
    return SceneSpec(seed=2026, room_m=room, tags=tags, objects=objects, lights=lights, ambient=0.3, texture_seed=7)


def demo_trajectory(n_frames: int) -> list[Array]:
    """The robot drives along the room 2.2-2.8 m from the tag wall and back (3.6 m each way), camera
    at 1.2 m, panning +-15 degrees; one closed loop in `n_frames` frames (~5 cm per frame at 150)."""
    poses = []
    for i in range(n_frames):
        phase = 2 * math.pi * i / n_frames
        x = -1.8 * math.cos(phase)
        y = 0.5 + 0.3 * math.sin(2 * phase)
        eye = np.array([x, y, 1.2])
        yaw = math.radians(15) * math.sin(3 * phase)
        target = eye + np.array([math.sin(yaw), math.cos(yaw), 0.05])
        poses.append(look_at(eye, target, roll_rad=math.radians(2) * math.sin(5 * phase)))
    return poses


class DemoSource:
    """The demo scene rendered with MuJoCo along its trajectory; renders are cached on disk so the
    stream keeps its rate (first run renders, ~0.15 s per frame on this CPU)."""

    # Its trajectory is one closed loop: looping it goes on moving as before (a folder or video jumps
    # back to its start, a new camera session: the camera starts seq again there).
    continuous_loop = True

    def __init__(self, *, n_frames: int, cache_dir: Path, camera: CameraIntrinsics | None = None) -> None:
        self.camera = camera or default_camera()
        self.scene = demo_scene()
        self.trajectory = demo_trajectory(n_frames)
        self.cache = self.cache_folder(cache_dir, n_frames=n_frames, camera=self.camera)
        self._ensure_rendered()
        self._decoded = self._decoded_frames()

    @staticmethod
    def cache_folder(cache_dir: Path, *, n_frames: int, camera: CameraIntrinsics) -> Path:
        """Where the renders of this scene, camera and length are cached (under `cache_dir`)."""
        key = hashlib.sha256(
            json.dumps([demo_scene().model_dump(), camera.model_dump(), n_frames, "render-v1"]).encode()
        ).hexdigest()[:16]
        return Path(cache_dir) / f"demo-{key}"

    def _missing(self) -> list[int]:
        return [i for i in range(len(self.trajectory)) if not (self.cache / f"{i:05d}.png").is_file()]

    def _ensure_rendered(self) -> None:
        """Render the frames the cache lacks. One process renders at a time (a lock file in the cache):
        a fleet's cameras start together on a fresh clone, and two renderers writing the same temporary
        file had one's rename fail and that camera exit (found by a fresh-clone trial); the one that
        waited finds the frames there."""
        if not self._missing():
            return
        from shared.sim.scene import SceneRenderer

        self.cache.mkdir(parents=True, exist_ok=True)
        with self._cache_lock():
            missing = self._missing()  # what another camera left, if it rendered meanwhile
            if not missing:
                return
            renderer = SceneRenderer(self.scene, self.camera)
            try:
                for i in tqdm(missing, desc="rendering demo scene (cached)", leave=False):
                    tmp = self.cache / f"{i:05d}.{os.getpid()}.tmp.png"
                    cv2.imwrite(str(tmp), renderer.render(self.trajectory[i]))
                    tmp.replace(self.cache / f"{i:05d}.png")
            finally:
                renderer.close()
            tmp = self.cache / f"scene.{os.getpid()}.tmp.json"
            tmp.write_text(self.scene.model_dump_json(indent=2))
            tmp.replace(self.cache / "scene.json")

    @contextlib.contextmanager
    def _cache_lock(self) -> Iterator[None]:
        """The cache's lock (one process writes it at a time; released when the file closes, or the
        process dies); its holder first removes what a writer killed mid-file left (`*.tmp.*`)."""
        with open(self.cache / ".render.lock", "a") as lock:
            try:
                fcntl.flock(lock, fcntl.LOCK_EX)
            except OSError as exc:  # a file system without locks (some NFS, CIFS, FUSE mounts)
                log.warning("%s: no lock (%s): writing alongside any other camera", self.cache, exc)
            else:
                for stale in self.cache.glob("*.tmp.*"):
                    stale.unlink(missing_ok=True)
            yield

    def _decoded_frames(self) -> Path | None:
        """Every render decoded once into one raw file beside them (`decoded-<n>x<h>x<w>.u8`): a frame is
        then one read from the page cache, as a camera driver hands over its buffer. Decoding a 1280x720
        PNG per frame took 5.7 ms, 17 % of a core at 30 fps on the robot's host, a cost no real camera
        has. Written once, atomically (a new file renamed over), under the render lock, and written again
        when its size is wrong or a render is newer; None (decode per frame, as before) where it cannot
        be written. Read, not mapped: a mapped file cut short under a running camera would kill it
        (SIGBUS), a short read is an error that names the file."""
        n, h, w = len(self.trajectory), self.camera.height, self.camera.width
        path = self.cache / f"decoded-{n}x{h}x{w}.u8"

        def current() -> bool:
            if not path.is_file() or (made := path.stat()).st_size != n * h * w:
                return False
            return all((self.cache / f"{i:05d}.png").stat().st_mtime_ns <= made.st_mtime_ns for i in range(n))

        try:
            if current():
                return path
            with self._cache_lock():  # (its holder removes what a camera killed while writing left: 138 MB)
                if not current():
                    tmp = self.cache / f"{path.name}.tmp.{os.getpid()}"
                    try:
                        with open(tmp, "wb") as out:
                            for i in range(n):
                                out.write(self._read_png(i).tobytes())
                        tmp.replace(path)
                    finally:
                        tmp.unlink(missing_ok=True)
        except (OSError, ValueError) as exc:
            log.warning("demo frames decoded per frame: no decoded cache in %s (%s)", self.cache, exc)
            return None
        return path

    def _read_png(self, i: int) -> NDArray[np.uint8]:
        img = cv2.imread(str(self.cache / f"{i:05d}.png"), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise OSError(f"demo cache frame {i} unreadable in {self.cache}")
        if img.shape != (self.camera.height, self.camera.width):
            raise ValueError(f"demo cache frame {i} is {img.shape[1]}x{img.shape[0]}, not the camera's")
        return np.ascontiguousarray(img)

    def gt_keypoints(self, world_from_camera: Array) -> list[Array]:
        """Exact image keypoints of every tag fully in view from `world_from_camera`."""
        out = []
        for tag in self.scene.tags:
            camera_from_tag = np.linalg.inv(world_from_camera) @ tag.pose()
            if camera_from_tag[2, 3] <= 0.1 or camera_from_tag[2, 2] <= 0:  # behind, or seen from the back
                continue
            px = project(self.camera, camera_from_tag, lattice_in_tag(tag.size_m))
            if (px >= 0).all() and (px[:, 0] < self.camera.width).all() and (px[:, 1] < self.camera.height).all():
                out.append(px)
        return out

    def frames(self) -> Iterator[SourceFrame]:
        """One pass along the trajectory."""
        if self._decoded is None:
            for i, pose in enumerate(self.trajectory):
                yield SourceFrame(self._read_png(i), pose)
            return
        h, w = self.camera.height, self.camera.width
        with open(self._decoded, "rb") as f:  # (buffered: readinto fills the array or meets the end)
            for i, pose in enumerate(self.trajectory):
                img = np.empty((h, w), np.uint8)
                if f.readinto(img.data) != h * w:
                    raise OSError(f"demo frame {i}: {self._decoded} was cut short (delete it: it is rebuilt)")
                img.flags.writeable = False
                yield SourceFrame(img, pose)


# ----------------------------------------------------------------------------------------------
# Folder, video, V4L2
# ----------------------------------------------------------------------------------------------

IMAGE_SUFFIXES: Final[frozenset[str]] = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".pgm", ".tif", ".tiff"})


def expand_paths(paths: list[Path]) -> list[Path]:
    """Files as given, folders expanded to their image files (sorted)."""
    out: list[Path] = []
    for p in paths:
        if p.is_dir():
            out += sorted(f for f in p.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES)
        else:
            out.append(p)
    return out


def parse_rgb_list(text: str, root: Path, *, name: str = "rgb.txt") -> list[tuple[int, Path]]:
    """A TUM-style image list: `timestamp filename` per line (seconds; filename relative to `root`), `#`
    comments; [(nanoseconds, exact to the digits given, path)] in file order. Raises GeometryError
    naming the line on anything else."""
    out = []
    for n, line in enumerate(text.splitlines(), start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        parts = line.split()
        if len(parts) != 2:
            raise GeometryError(f"{name}:{n}: expected 'timestamp filename', got {line.strip()!r}")
        try:
            stamp = parse_stamp_nanos(parts[0])
        except GeometryError as exc:
            raise GeometryError(f"{name}:{n}: {exc}") from None
        out.append((stamp, root / parts[1]))
    return out


def associate_stamps(stamps_s: list[float], gt_stamps_s: NDArray[np.float64], max_dt_s: float) -> list[int | None]:
    """For each image stamp, the index of the ground-truth stamp nearest to it if within `max_dt_s`
    (TUM's association: ground truth runs at another rate than the images). Pure."""
    if len(gt_stamps_s) == 0:
        return [None] * len(stamps_s)
    order = np.argsort(gt_stamps_s, kind="stable")
    best = nearest_sorted(np.asarray(gt_stamps_s, np.float64)[order], np.asarray(stamps_s, np.float64), max_dt_s)
    return [None if b < 0 else int(order[b]) for b in best]


def nearest_sorted(sorted_s: NDArray[np.float64], t_s: NDArray[np.float64], max_dt_s: float) -> NDArray[np.intp]:
    """For each time in `t_s`, the index of the nearest in `sorted_s` (ascending, not empty) if within
    `max_dt_s`, else -1 (vectorised: a long video's nominal frame times are checked at start-up)."""
    j = np.searchsorted(sorted_s, t_s)
    before = np.clip(j - 1, 0, len(sorted_s) - 1)
    after = np.clip(j, 0, len(sorted_s) - 1)
    best = np.where(np.abs(sorted_s[before] - t_s) <= np.abs(sorted_s[after] - t_s), before, after)
    return np.where(np.abs(sorted_s[best] - t_s) <= max_dt_s, best, -1)


RGB_LIST: Final[str] = "rgb.txt"
GT_MAX_DT_S: Final[float] = 0.02  # TUM's tools associate within 20 ms


class FolderSource:
    """The images of a folder with a camera_info YAML; optional TUM ground truth.

    With a TUM-style `rgb.txt` in the folder or its parent (a TUM data set: `rgb.txt` beside `rgb/`),
    the images are the ones it lists, in its order, each stamped with its time, and ground truth is
    associated by time (nearest within 20 ms; frames without one carry none). Without it: the sorted
    image files, unstamped, ground-truth row i = image i."""

    def __init__(self, folder: Path, camera_info: Path, groundtruth: Path | None = None) -> None:
        self.camera = camera_from_yaml(camera_info)
        folder = Path(folder)
        if not folder.is_dir():
            raise FileNotFoundError(f"no images in {folder}: not a folder")
        listing = next((d / RGB_LIST for d in (folder, folder.parent) if (d / RGB_LIST).is_file()), None)
        self.stamps_nanos: list[int] | None = None
        if listing is not None:
            entries = parse_rgb_list(listing.read_text(), listing.parent, name=str(listing))
            missing = [str(p) for _, p in entries if not p.is_file()]
            if missing:
                count = f"{len(missing)} missing image" + ("s" if len(missing) > 1 else "")
                raise FileNotFoundError(f"{listing} lists {count}, e.g. {missing[0]}")
            self.files = [p for _, p in entries]
            self.stamps_nanos = [t for t, _ in entries]
            log.info("%s: %d images with their time stamps", listing, len(entries))
        else:
            self.files = expand_paths([folder])
        if not self.files:
            raise FileNotFoundError(f"no images in {folder}")
        self.gt: list[Array | None] | None = None
        if groundtruth:
            rows = read_tum(groundtruth)
            if self.stamps_nanos is not None:
                seconds = [t / 1e9 for t in self.stamps_nanos]
                gt_seconds = np.array([t for t, _ in rows], np.float64)
                nearest = associate_stamps(seconds, gt_seconds, GT_MAX_DT_S)
                self.gt = [None if j is None else rows[j][1] for j in nearest]
                matched = sum(j is not None for j in nearest)
                if rows and not matched:
                    raise GeometryError(
                        f"{groundtruth}: none of its {len(rows)} poses is within {GT_MAX_DT_S * 1e3:.0f} ms of "
                        f"an image of {listing} (images {seconds[0]:.6f}-{seconds[-1]:.6f} s, ground truth "
                        f"{gt_seconds.min():.6f}-{gt_seconds.max():.6f} s): another recording, or another clock?"
                    )
                if matched < len(nearest):
                    log.warning(
                        "%s: %d of %d images have no ground-truth pose within %.0f ms (they go without truth)",
                        groundtruth,
                        len(nearest) - matched,
                        len(nearest),
                        GT_MAX_DT_S * 1e3,
                    )
            elif len(rows) != len(self.files):
                raise GeometryError(f"{groundtruth} has {len(rows)} poses for {len(self.files)} images")
            else:
                self.gt = [p for _, p in rows]

    @property
    def identity(self) -> dict[str, object]:
        """What a restarted camera checks its progress record against (the same listing)."""
        return {"images": len(self.files), "first": str(self.files[0])}

    @property
    def span_nanos(self) -> int | None:
        """How long one pass of the stamped images lasts (latest - earliest stamp plus the median frame
        period), the shift of each new pass when the source loops; None without stamps."""
        if not self.stamps_nanos:
            return None
        stamps = sorted(self.stamps_nanos)  # (rgb.txt's order is the images', not necessarily time's)
        period = int(np.median(np.diff(stamps))) if len(stamps) > 1 else 0
        return stamps[-1] - stamps[0] + max(period, 1)

    def check(self) -> None:
        """Read the first image: unreadable, or of another size than the camera_info's, is a GeometryError
        said at once (the service would otherwise skip every image and find no frames)."""
        first = self.files[0]
        img = cv2.imread(str(first), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise GeometryError(f"{first}: not an image OpenCV can read")
        if img.shape != (self.camera.height, self.camera.width):
            raise GeometryError(
                f"{first} is {img.shape[1]}x{img.shape[0]} but the camera_info says "
                f"{self.camera.width}x{self.camera.height}"
            )

    def frames(self) -> Iterator[SourceFrame]:
        for i, f in enumerate(self.files):
            img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
            if img is None or img.shape != (self.camera.height, self.camera.width):
                log.warning("skipping %s: unreadable or not %dx%d", f, self.camera.width, self.camera.height)
                continue
            stamp = None if self.stamps_nanos is None else self.stamps_nanos[i]
            yield SourceFrame(np.ascontiguousarray(img), None if self.gt is None else self.gt[i], stamp, index=i)


VIDEO_SIZE_WARNINGS: Final[int] = 3  # frames of another size said one by one; then only counted
VIDEO_GT_CHECK_FRAMES: Final[int] = 30  # a video without a frame count: its ground truth's clock checked over these


class VideoSource:
    """A video file: a data set whose time is the video's own (each frame's timestamp from the start of
    the video, as OpenCV reads it from the container), so `trajectory.tum` is in that time and a TUM
    ground truth in it (seconds from the first frame) is associated by time, nearest within 20 ms, as a
    folder's with `rgb.txt`. Opened, its first frame read and its size checked against the camera_info
    at construction: a file OpenCV cannot read, or frames of another size (a trial's 640x480 video with a
    1280x720 camera_info was resized silently and posed metres off), is a GeometryError said at once."""

    def __init__(self, path: Path, camera_info: Path, groundtruth: Path | None = None) -> None:
        self.camera = camera_from_yaml(camera_info)
        self.path = Path(path)
        if self.path.is_dir():
            raise FileNotFoundError(f"{self.path} is a folder, not a video file (images in a folder: source = folder)")
        if not self.path.is_file():
            raise FileNotFoundError(f"{self.path}: no such file")
        cap = cv2.VideoCapture(str(self.path))
        try:
            if not cap.isOpened():
                raise GeometryError(
                    f"{self.path}: not a video OpenCV can open (damaged or cut short, or in a container or codec "
                    "this OpenCV build lacks)"
                )
            ok, frame = cap.read()
            if not ok:
                raise GeometryError(f"{self.path}: OpenCV opens it but reads no frame from it (damaged or empty?)")
            # The first frame's time is 0: OpenCV's own MJPEG reader gives each frame the next one's time
            # (FFmpeg its own), which would shift the ground truth by a frame (review).
            origin_ms = float(cap.get(cv2.CAP_PROP_POS_MSEC))
            self._origin_ms = origin_ms if math.isfinite(origin_ms) else 0.0
            height, width = frame.shape[:2]
            if (height, width) != (self.camera.height, self.camera.width):
                raise GeometryError(
                    f"{self.path}: its frames are {width}x{height} but the camera_info says "
                    f"{self.camera.width}x{self.camera.height} (a camera_info of this video's camera, at its size)"
                )
            count = float(cap.get(cv2.CAP_PROP_FRAME_COUNT))  # the container's say: approximate, or none (0, < 0)
            self.frame_count = int(count) if math.isfinite(count) and 0 < count < 1e9 else 0
            fps = float(cap.get(cv2.CAP_PROP_FPS))
            self.fps = fps if math.isfinite(fps) and 0 < fps < 1000 else None
        finally:
            cap.release()
        self._gt_seconds: NDArray[np.float64] | None = None
        self._gt_poses: list[Array] = []
        self._gt_name = ""
        if groundtruth:
            rows = read_tum(groundtruth)
            rows = sorted(rows, key=lambda row: row[0])  # (sorted once: each frame's truth is a bisection)
            self._gt_seconds = np.array([t for t, _ in rows], np.float64)
            self._gt_poses = [pose for _, pose in rows]
            if rows and self.frame_count and self.fps:  # the container's nominal frame times: a clock check
                seconds = list(np.arange(self.frame_count, dtype=np.float64) / self.fps)
                nearest = associate_stamps(seconds, self._gt_seconds, GT_MAX_DT_S)
                matched = sum(j is not None for j in nearest)
                if not matched:
                    raise GeometryError(
                        f"{groundtruth}: none of its {len(rows)} poses is within {GT_MAX_DT_S * 1e3:.0f} ms of a "
                        f"frame of {self.path} (frames 0-{seconds[-1]:.3f} s from the video's start, ground truth "
                        f"{self._gt_seconds.min():.6f}-{self._gt_seconds.max():.6f} s): a video's ground truth is "
                        "in the video's time, seconds from its first frame"
                    )
                if matched < len(nearest):
                    log.warning(
                        "%s: about %d of the video's about %d frames have no ground-truth pose within %.0f ms (they go "
                        "without truth)",
                        groundtruth,
                        len(nearest) - matched,
                        len(nearest),
                        GT_MAX_DT_S * 1e3,
                    )
            elif rows:
                log.warning(
                    "%s does not say how many frames it holds at what rate: its ground truth's clock is checked "
                    "over the first %d frames",
                    self.path,
                    VIDEO_GT_CHECK_FRAMES,
                )
            self._gt_name = str(groundtruth)
        self.other_size = 0  # frames skipped for another size than the camera_info's
        self._last_stamp: int | None = None  # the latest frame time read, and the step to it: the pass's span
        self._step = 0
        self._gt_checked = 0  # frames whose truth was looked up, before the first match

    @property
    def identity(self) -> dict[str, object]:
        """What a restarted camera checks its progress record against (the same file, as long)."""
        return {"images": self.frame_count, "first": str(self.path)}

    @property
    def span_nanos(self) -> int | None:
        """How long one pass lasts, where the next pass's stamps go on from: the frame times read so far
        (the last plus one step) or the container's frames / fps, whichever is longer (a variable frame
        rate's nominal rate is too high; a raw stream says neither: review); None before either is known."""
        header = round(self.frame_count / self.fps * 1e9) if self.frame_count and self.fps else 0
        seen = self._last_stamp + max(self._step, 1) if self._last_stamp is not None else 0
        return max(header, seen) or None

    def _truth(self, seconds: float) -> Array | None:
        if self._gt_seconds is None:
            return None
        found = int(nearest_sorted(self._gt_seconds, np.array([seconds]), GT_MAX_DT_S)[0]) if self._gt_poses else -1
        j = None if found < 0 else found
        if j is None and self._gt_checked >= 0:
            self._gt_checked += 1
            if self._gt_checked == VIDEO_GT_CHECK_FRAMES:  # (said once: a clock the start-up check could not see)
                log.warning(
                    "%s: none of the first %d frames of %s has a ground-truth pose within %.0f ms: a video's ground "
                    "truth is in the video's time, seconds from its first frame",
                    self._gt_name,
                    VIDEO_GT_CHECK_FRAMES,
                    self.path,
                    GT_MAX_DT_S * 1e3,
                )
        elif j is not None:
            self._gt_checked = -1  # matched: checked
        return None if j is None else self._gt_poses[j]

    def frames(self, start: int = 0) -> Iterator[SourceFrame]:
        """The video from frame `start` (a restarted camera's place in it), each frame with its own time."""
        cap = cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            raise OSError(f"cannot open video {str(self.path)!r}")
        try:
            if start:
                cap.set(cv2.CAP_PROP_POS_FRAMES, start)
            while True:
                ok, frame = cap.read()
                if not ok:
                    return
                index = max(0, int(cap.get(cv2.CAP_PROP_POS_FRAMES)) - 1)
                millis = float(cap.get(cv2.CAP_PROP_POS_MSEC)) - self._origin_ms
                stamp = max(0, round(millis * 1e6)) if math.isfinite(millis) else None
                if stamp is not None:
                    if self._last_stamp is not None and stamp > self._last_stamp:
                        self._step = stamp - self._last_stamp
                    self._last_stamp = max(stamp, self._last_stamp or 0)
                gray = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY) if frame.ndim == 3 else frame
                if gray.shape != (self.camera.height, self.camera.width):
                    self.other_size += 1
                    if self.other_size <= VIDEO_SIZE_WARNINGS:
                        log.warning(
                            "skipping frame %d of %s: %dx%d, not the camera_info's %dx%d (%d so far)",
                            index,
                            self.path,
                            gray.shape[1],
                            gray.shape[0],
                            self.camera.width,
                            self.camera.height,
                            self.other_size,
                        )
                    continue
                truth = None if stamp is None else self._truth(stamp / 1e9)
                yield SourceFrame(np.ascontiguousarray(gray, np.uint8), truth, stamp, index=index)
        finally:
            cap.release()


class CaptureSource:
    """A V4L2 device, a stream URL or a GStreamer pipeline through OpenCV (live: no time of its own, no
    ground truth); frames converted to grayscale. The device is asked for the camera_info's size; one
    that gives another is refused (SourceSizeError) at its first frame rather than resized, which would
    break the intrinsics."""

    def __init__(self, target: str | int, camera_info: Path) -> None:
        self.camera = camera_from_yaml(camera_info)
        self.target = target

    def frames(self) -> Iterator[SourceFrame]:
        cap = cv2.VideoCapture(self.target)
        if not cap.isOpened():
            raise OSError(f"cannot open video source {self.target!r}")
        cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.camera.width)
        cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.camera.height)
        first = True
        skipped = 0
        try:
            while True:
                ok, frame = cap.read()
                if not ok:
                    return
                gray = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY) if frame.ndim == 3 else frame
                if gray.shape != (self.camera.height, self.camera.width):
                    if first:
                        raise SourceSizeError(
                            f"{self.target!r} gives {gray.shape[1]}x{gray.shape[0]} frames but the camera_info "
                            f"says {self.camera.width}x{self.camera.height} (it was asked for that size)"
                        )
                    skipped += 1
                    if skipped <= VIDEO_SIZE_WARNINGS:
                        log.warning("skipping a %dx%d frame of %r", gray.shape[1], gray.shape[0], self.target)
                    continue
                first = False
                yield SourceFrame(np.ascontiguousarray(gray, np.uint8), None)
        finally:
            cap.release()


class SourceSizeError(GeometryError):
    """A live source's frames are not of the camera_info's size."""
