"""Rerun logging: one recording per run shared by every service (same recording id), each process
saving `<service>.rrd` in the run folder; the launcher merges them into `recording.rrd` at exit.
Everything is on the `capture_time` timeline so processes line up. Off by default: `NullViz`.

Entity paths (what the viewer shows):
- `camera/image`                       the mono8 frame (every `image_every`-th)
- `camera/image/keypoints_gt`          ground-truth keypoints (demo scene), blue
- `camera/image/keypoints`             the 16 predicted keypoints per tag, yellow
- `camera/image/tag_quads`             AprilTag quads (stage 1), green
- `latency/{robot_compute,transport,edge_compute,capture_to_pose}_ms`, `link/payload_kB`, `split/k`
- `world/camera`                       SLAM camera pose (with a pinhole frustum)
- `world/trajectory`, `world/groundtruth`  SLAM trajectory and ground truth, 3D line strips
- `world/tags`                         tag map as flat boxes with their ids
- `controller/...`                     controller state, when one runs
"""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Final, Protocol

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from shared.vision.camera import CameraIntrinsics
from shared.vision.geometry import Array
from shared.wire.messages import TagPoses

log = logging.getLogger(__name__)


TRAJECTORY_PERIOD_NANOS = 1_000_000_000


class RerunSettings(BaseModel):
    """Rerun logging of one service."""

    model_config = ConfigDict(extra="forbid")
    enabled: bool = False  # write a Rerun recording (runs/<run_id>/recording.rrd)
    recording_id: str = ""  # empty: the run folder's name, shared by every service of the run
    image_every: int = Field(default=1, ge=1)  # log every n-th camera image (JPEG encoding costs CPU)
    # A fleet's processes: the .rrd part's name (empty: the service's) and a prefix for the per-robot
    # entities (camera/, latency/, link/, split/, controller/), e.g. "robots/robot2/"; "{robot}" is
    # replaced by each message's robot id (an edge worker serving several robots). world/ is shared.
    part_name: str = ""
    entity_prefix: str = ""  # (above) the per-robot entities' prefix
    jpeg_quality: int = Field(default=80, ge=10, le=100)  # of the logged camera images
    # Each process starts a new .rrd part this often, as Rerun's file sink holds an index of every chunk
    # until its file closes (one file per process grew slam and edge_infer by ~2 MB a minute at 5 fps,
    # without end: a fresh-clone soak; docs/reliability.md *Long runs*).
    rotate_secs: float = Field(default=300.0, gt=0)
    # When a process's parts exceed this (MB), its oldest are deleted at the next rotation, so a long run
    # keeps its latest stretch; 0 keeps every part (the merged recording.rrd holds the whole run).
    keep_mb: float = Field(default=0.0, ge=0)


def sigma_ellipsoid(position_covariance: Array, *, sigmas: float) -> tuple[Array, Array, float]:
    """A 3x3 position covariance (m^2) as an ellipsoid: half sizes (m, `sigmas` standard deviations along
    its principal axes) and the axis-angle rotation (unit axis, radians) that turns x, y, z onto them."""
    import cv2  # only where Rerun draws: the services that never do need not load it

    values, vectors = np.linalg.eigh((np.asarray(position_covariance, np.float64) + position_covariance.T) / 2)
    if np.linalg.det(vectors) < 0:
        vectors[:, 0] = -vectors[:, 0]  # a rotation, not a reflection
    rvec = cv2.Rodrigues(vectors)[0].ravel()
    angle = float(np.linalg.norm(rvec))
    axis = rvec / angle if angle > 1e-12 else np.array([0.0, 0.0, 1.0])
    return sigmas * np.sqrt(np.clip(values, 0.0, None)), axis, angle


class Viz(Protocol):
    """What services log; implemented by RerunViz and NullViz."""

    def image(self, capture_nanos: int, image: np.ndarray, camera: CameraIntrinsics, seq: int) -> None: ...
    def keypoints_gt(self, capture_nanos: int, points_px: list[Array]) -> None: ...
    def tag_poses(self, msg: TagPoses) -> None: ...
    def camera_pose(
        self,
        capture_nanos: int,
        world_from_camera: Array,
        camera: CameraIntrinsics | None,
        robot: str = "",
        *,
        bridged: bool = False,
        covariance_world: Array | None = None,
    ) -> None: ...
    def trajectory(self, capture_nanos: int, path: str, positions: Array) -> None: ...
    def tag_map(self, capture_nanos: int, tags: dict[int, tuple[float, Array]]) -> None: ...
    def scalars(self, capture_nanos: int, values: dict[str, float]) -> None: ...
    def close(self) -> None: ...


class NullViz:
    """Logging off: every call is a no-op."""

    def image(self, capture_nanos: int, image: np.ndarray, camera: CameraIntrinsics, seq: int) -> None:
        """No-op."""

    def keypoints_gt(self, capture_nanos: int, points_px: list[Array]) -> None:
        """No-op."""

    def tag_poses(self, msg: TagPoses) -> None:
        """No-op."""

    def camera_pose(
        self,
        capture_nanos: int,
        world_from_camera: Array,
        camera: CameraIntrinsics | None,
        robot: str = "",
        *,
        bridged: bool = False,
        covariance_world: Array | None = None,
    ) -> None:
        """No-op."""

    def trajectory(self, capture_nanos: int, path: str, positions: Array) -> None:
        """No-op."""

    def tag_map(self, capture_nanos: int, tags: dict[int, tuple[float, Array]]) -> None:
        """No-op."""

    def scalars(self, capture_nanos: int, values: dict[str, float]) -> None:
        """No-op."""

    def close(self) -> None:
        """No-op."""


class RerunViz:
    """Logs to `<run_dir>/<service>.rrd` under the run's shared recording id."""

    def __init__(
        self,
        settings: RerunSettings,
        *,
        service: str,
        run_dir: Path,
        clock_secs: Callable[[], float] = time.monotonic,
    ) -> None:
        import rerun as rr

        self._rr: Any = rr
        self.settings = settings
        run_dir.mkdir(parents=True, exist_ok=True)
        self.rec = rr.RecordingStream("splittag", recording_id=settings.recording_id or run_dir.name)
        self._run_dir, self._name = run_dir, settings.part_name or service
        self._clock_secs = clock_secs
        self.path = part_path(run_dir, self._name)
        self.rec.save(self.path)
        self.parts = [self.path]  # this process's .rrd parts, oldest first (the last one open)
        self.dropped_parts = 0  # deleted for keep_mb
        self._rotate_at = clock_secs() + settings.rotate_secs
        self._prefix = settings.entity_prefix
        self._robot = ""
        self._time_set = False
        self._trajectory_logged: dict[str, int] = {}
        self._sigma_drawn: set[str] = set()  # entities whose covariance ellipsoid is shown

    def _log(self, path: str, *args: Any, **kwargs: Any) -> None:
        if self._clock_secs() >= self._rotate_at:
            self._rotate()
        if self._prefix and not path.startswith("world/"):
            path = self._prefix.replace("{robot}", self._robot) + path
        self.rec.log(path, *args, **kwargs)

    def _at(self, capture_nanos: int) -> None:
        # exact nanoseconds (float seconds of this size are good to ~0.2 us): joins frames.csv's capture_unix_nanos
        self.rec.set_time("capture_time", timestamp=np.datetime64(int(capture_nanos), "ns"))

    def image(self, capture_nanos: int, image: np.ndarray, camera: CameraIntrinsics, seq: int) -> None:
        """The frame (subsampled by image_every)."""
        if seq % self.settings.image_every:
            return
        self._at(capture_nanos)
        # JPEG keeps a run's recording small (~60 kB instead of 0.9 MB per frame) for ~4 ms per frame.
        import cv2

        ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, self.settings.jpeg_quality])
        if ok:
            self._log("camera/image", self._rr.EncodedImage(contents=buf.tobytes(), media_type="image/jpeg"))

    def keypoints_gt(self, capture_nanos: int, points_px: list[Array]) -> None:
        """Ground-truth keypoints of the tags in view."""
        if not points_px:
            return
        self._at(capture_nanos)
        pts = np.concatenate(points_px)
        self._log("camera/image/keypoints_gt", self._rr.Points2D(pts + 0.5, colors=[60, 120, 255], radii=2.5))

    def tag_poses(self, msg: TagPoses) -> None:
        """Keypoints, quads, per-hop latency, payload and k of one frame."""
        rr = self._rr
        self._robot = msg.robot_id
        self._at(msg.capture_nanos)
        # Rerun's 2D space puts pixel centres at +0.5; our convention has them at integers.
        if msg.tags:
            # detected tags yellow keypoints / green quads; tracked ones (stage 1 missed them) magenta;
            # blind soft reads (slam leaves them out by default) orange; the label says the proposer
            kps = np.concatenate([t.keypoints_px for t in msg.tags]) + 0.5
            kp_colors = np.repeat([_tag_rgb(t.tracked, t.proposer, [255, 210, 0]) for t in msg.tags], 16, axis=0)
            self._log("camera/image/keypoints", rr.Points2D(kps, colors=kp_colors, radii=2.0))
            quads = [np.vstack([t.corners_px, t.corners_px[:1]]) + 0.5 for t in msg.tags]
            self._log(
                "camera/image/tag_quads",
                rr.LineStrips2D(
                    quads,
                    colors=[_tag_rgb(t.tracked, t.proposer, [0, 220, 0]) for t in msg.tags],
                    labels=[f"{t.tag_id} ({t.proposer or 'detected'})" for t in msg.tags],
                ),
            )
        else:
            self._log("camera/image/keypoints", rr.Clear(recursive=False))
        t = msg.timings
        self.scalars(
            msg.capture_nanos,
            {
                "latency/robot_compute_ms": 1e3 * t.robot_compute_secs,
                "latency/transport_ms": 1e3 * t.transport_secs,
                "latency/edge_compute_ms": 1e3 * t.edge_compute_secs,
                "latency/capture_to_pose_ms": 1e3 * t.capture_to_pose_secs,
                "link/payload_kB": msg.payload_bytes / 1024,
                "split/k": float(msg.split_k),
            },
        )

    def camera_pose(
        self,
        capture_nanos: int,
        world_from_camera: Array,
        camera: CameraIntrinsics | None,
        robot: str = "",
        *,
        bridged: bool = False,
        covariance_world: Array | None = None,
    ) -> None:
        """SLAM camera pose (and its frustum); a fleet's robots each at world/robots/<robot>/camera. A
        bridged pose (in a map fragment not yet tied to the world) goes to .../camera_bridged instead, so
        the world's trajectory never jumps to a gap's guess and both can be shown or hidden apart. With
        `covariance_world` (CameraPose's), the position's 2-sigma ellipsoid goes to <entity>_sigma."""
        rr = self._rr
        self._at(capture_nanos)
        entity = f"world/robots/{robot}/camera" if robot else "world/camera"
        entity += "_bridged" if bridged else ""
        self._log(entity, rr.Transform3D(translation=world_from_camera[:3, 3], mat3x3=world_from_camera[:3, :3]))
        if covariance_world is None:
            if f"{entity}_sigma" in self._sigma_drawn:  # no stale ellipsoid left at an older pose
                self._log(f"{entity}_sigma", rr.Clear(recursive=False))
                self._sigma_drawn.discard(f"{entity}_sigma")
        else:
            self._sigma_drawn.add(f"{entity}_sigma")
            half_sizes, axis, angle_rad = sigma_ellipsoid(covariance_world[:3, :3], sigmas=2.0)
            self._log(
                f"{entity}_sigma",
                rr.Ellipsoids3D(
                    centers=[world_from_camera[:3, 3]],
                    half_sizes=[half_sizes],
                    rotation_axis_angles=[rr.RotationAxisAngle(axis=axis, angle=rr.Angle(rad=angle_rad))],
                    colors=[255, 200, 0, 90],
                ),
            )
        if camera is not None:
            self._log(
                entity,
                rr.Pinhole(
                    image_from_camera=camera.matrix(),
                    resolution=[camera.width, camera.height],
                    image_plane_distance=0.3,
                ),
            )

    def trajectory(self, capture_nanos: int, path: str, positions: Array) -> None:
        """A whole 3D trajectory as one line strip (re-logged as it grows)."""
        if len(positions) < 2:
            return
        # The strip is re-logged whole, so its cost grows with the run: once per second of capture time.
        if capture_nanos - self._trajectory_logged.get(path, -(10**18)) < TRAJECTORY_PERIOD_NANOS:
            return
        self._trajectory_logged[path] = capture_nanos
        self._at(capture_nanos)
        colour = [255, 120, 0] if path.endswith("trajectory") else [60, 120, 255]
        self._log(path, self._rr.LineStrips3D([positions], colors=colour, radii=0.01))

    def tag_map(self, capture_nanos: int, tags: dict[int, tuple[float, Array]]) -> None:
        """Tags as flat boxes with their ids."""
        if not tags:
            return
        self._at(capture_nanos)
        ids = sorted(tags)
        centres = [tags[i][1][:3, 3] for i in ids]
        quats = []
        from scipy.spatial.transform import Rotation

        for i in ids:
            quats.append(self._rr.Quaternion(xyzw=Rotation.from_matrix(tags[i][1][:3, :3]).as_quat()))
        halves = [[tags[i][0] / 2, tags[i][0] / 2, 0.005] for i in ids]
        self._log(
            "world/tags",
            self._rr.Boxes3D(
                centers=centres, half_sizes=halves, quaternions=quats, labels=[str(i) for i in ids], colors=[0, 220, 0]
            ),
        )

    def scalars(self, capture_nanos: int, values: dict[str, float]) -> None:
        """Time series values."""
        self._at(capture_nanos)
        for path, value in values.items():
            self._log(path, self._rr.Scalars([value]))

    def text(self, capture_nanos: int, path: str, text: str) -> None:
        """A text entry (an event: a link profile applied)."""
        self._at(capture_nanos)
        self._log(path, self._rr.TextLog(text))

    def _rotate(self) -> None:
        """Close this part (its file sink frees the index it kept) and go on in a new one; with keep_mb, the
        oldest closed parts go while the closed ones exceed it."""
        self.rec.flush()
        self.path = part_path(self._run_dir, self._name)
        self.rec.save(self.path)  # the stream's new sink: the old file is finished and closed
        self.parts.append(self.path)
        self._rotate_at = self._clock_secs() + self.settings.rotate_secs
        budget = self.settings.keep_mb * 1e6
        if not budget:
            return
        closed = self.parts[:-1]
        sizes = {p: p.stat().st_size if p.exists() else 0 for p in closed}
        while closed and sum(sizes[p] for p in closed) > budget:
            oldest = closed.pop(0)
            oldest.unlink(missing_ok=True)
            self.parts.remove(oldest)
            self.dropped_parts += 1
            log.info(
                "rerun: deleted %s (%.1f MB): this process's parts exceed keep_mb", oldest.name, sizes[oldest] / 1e6
            )

    def close(self) -> None:
        """Flush and close the .rrd file."""
        self.rec.flush()
        self.rec.disconnect()


TRACKED_RGB: Final[list[int]] = [255, 0, 200]
SOFT_READ_RGB: Final[list[int]] = [255, 120, 0]


def _tag_rgb(tracked: bool, proposer: str | None, detected: list[int]) -> list[int]:
    """A tag's colour in the image: tracked magenta, a blind soft read orange, else `detected`."""
    return TRACKED_RGB if tracked else SOFT_READ_RGB if proposer == "lines_soft" else detected


def make_viz(settings: RerunSettings, *, service: str, run_dir: Path) -> Viz:
    """RerunViz when enabled, else NullViz."""
    if not settings.enabled:
        return NullViz()
    return RerunViz(settings, service=service, run_dir=run_dir)


def part_path(run_dir: Path, name: str) -> Path:
    """A process's own .rrd part: `<name>.rrd`, or `<name>.<n>.rrd` for the n-th process of that name in
    the run (a restarted service used to re-create the dead one's part, and the merged recording lost
    everything before the restart: found by a fleet trial). n is one past the highest in the folder, so a
    part is never named as an earlier one that keep_mb deleted (the names keep their order in time)."""
    numbers = [1] if (run_dir / f"{name}.rrd").exists() else []
    pattern = re.compile(rf"{re.escape(name)}\.([0-9]+)\.rrd")
    numbers += [int(m.group(1)) for p in run_dir.glob(f"{name}.*.rrd") if (m := pattern.fullmatch(p.name))]
    return run_dir / f"{name}.{max(numbers) + 1}.rrd" if numbers else run_dir / f"{name}.rrd"


def merge_recordings(run_dir: Path) -> Path | None:
    """Merge the services' .rrd files of a run into recording.rrd (the rerun CLI ships with rerun-sdk)."""
    import shutil
    import subprocess
    import sys

    parts = sorted(p for p in run_dir.glob("*.rrd") if p.name != "recording.rrd")
    if not parts:
        return None
    exe = shutil.which("rerun") or str(Path(sys.executable).parent / "rerun")
    out = run_dir / "recording.rrd"
    with out.open("wb") as f:
        done = subprocess.run([exe, "rrd", "merge", *map(str, parts)], stdout=f, stderr=subprocess.PIPE, check=False)
    if done.returncode != 0:
        log.warning("rerun rrd merge failed: %s", done.stderr.decode(errors="replace")[-500:])
        return None
    for p in parts:
        p.unlink()
    return out


def _rrd_stats(path: Path) -> str:
    """The rerun CLI's `rrd stats` report of an .rrd file."""
    import shutil
    import subprocess
    import sys

    exe = shutil.which("rerun") or str(Path(sys.executable).parent / "rerun")
    return subprocess.run([exe, "rrd", "stats", str(path)], capture_output=True, text=True, check=True).stdout


def recording_entities(path: Path) -> set[str]:
    """Entity paths stored in an .rrd file."""
    import re

    return {m.group(1) for m in re.finditer(r"^(/[A-Za-z0-9_/]+)", _rrd_stats(path), re.MULTILINE)}


def recording_components(path: Path) -> set[str]:
    """Components stored in an .rrd file, as `Archetype:field` (e.g. `Pinhole:image_from_camera`)."""
    import re

    section = _rrd_stats(path).partition("Num chunks per component")[2]
    return {m.group(1) for m in re.finditer(r"^([A-Za-z0-9]+:[A-Za-z0-9_]+): \d+$", section, re.MULTILINE)}


def recording_scalars(path: Path, entity: str) -> list[tuple[int, float]]:
    """(capture time in unix ns, value) of each scalar logged at `entity` (e.g. `/latency/capture_to_pose_ms`)
    in an .rrd file, in time order: rerun-sdk's own chunk reader (README *Run folder*: no datafusion needed)."""
    import pyarrow as pa
    import rerun.chunk as rc

    chunks = rc.RrdReader(str(path)).store().stream().to_chunks()
    batches = [c.to_record_batch() for c in chunks if str(c.entity_path) == entity]
    if not batches:
        return []
    table = pa.Table.from_batches(batches)
    stamps = table.column("capture_time").cast(pa.int64()).to_pylist()
    values = [float(v[0]) for v in table.column("Scalars:scalars").to_pylist()]
    return sorted(zip(stamps, values, strict=True))
