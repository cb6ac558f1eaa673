"""slam loop: TagPoses -> MarkerSlam -> CameraPose every frame, TagMap when a tag is added and every 30
frames; files at exit/on request.

Map queryable on `splittag/<robot_id>/map/v3` (`keys.tag_map`): a get replies the current TagMap; `?save=1`
(through the robot's own key, never a wildcard) also writes trajectory.tum, map.json (a tag map),
slam.json (run statistics) and, when ground truth was seen, groundtruth.tum / ate.json now.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import os
import queue
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import zenoh

from services.slam.settings import SlamServiceSettings
from shared.runtime.guard import InputGuard, persist_input_counts, serve_stats
from shared.runtime.memory import release_free_memory
from shared.slam.marker_slam import (
    FrameIndexer,
    MarkerSlam,
    Observation,
    SlamInputError,
    absolute_trajectory_error_arrays,
    check_observation,
    check_robot_count,
    rescale_observation,
    truth_in_estimate_frame,
)
from shared.transport.access import MAP_KEY
from shared.transport.session import declare_fifo_subscriber, encoding_for
from shared.transport.split_control import SplitRequestError, parse_parameters
from shared.vision.camera import CameraIntrinsics
from shared.vision.files import atomic_write_text
from shared.vision.geometry import check_rigid
from shared.vision.tagmap import TagMapFile, TagSpec, load_tag_map, tag_map_from_poses, write_tag_map
from shared.vision.trajectory import PoseLog, StampMap, read_tum_nanos, write_tum_arrays
from shared.viz.recording import make_viz
from shared.wire import keys
from shared.wire.messages import CameraPose, FrameStamp, MapTag, TagMap, TagPoses, decode, decode_for_robot, encode

log = logging.getLogger(__name__)
MAX_RESIZED_WARNINGS = 64  # tags whose size mismatch is said (each once)

GT_WAITING_FRAMES = 1024  # ground truth held for frames whose TagPoses have not come yet


class JournalRead(NamedTuple):
    """What a journal holds, sorted by stamp: the poses, and the ground truth of those that had one."""

    stamps_nanos: np.ndarray
    poses: np.ndarray
    truth_stamps_nanos: np.ndarray
    truths: np.ndarray


class PoseJournal:
    """The poses slam placed since its last checkpoint, one line each as they come (capture time, the
    data set's stamp or -1, the 3x4 world_from_camera, then the frame's 3x4 ground truth when it had
    one): a slam killed between checkpoints (every few seconds) lost those poses from trajectory.tum
    although it had published them (a trial: 19 poses, a 6.4 s hole after a SIGKILL), and their ground
    truth from groundtruth.tum (a trial: ATE over 175 of 185 poses). A checkpoint rotates it (`rotate`,
    then `drop_rotated` once trajectory.tum holds what it had); a restarted slam appends what both files
    hold after its trajectory's last stamp (`read`). Each line is written through to the OS: it survives
    the process."""

    WITHOUT_TRUTH, WITH_TRUTH = 14, 26  # numbers on a line

    def __init__(self, path: Path) -> None:
        self.path = path
        self.rotated = path.with_name(path.name + ".old")
        self._file: Any = None
        self.failed = False

    def append(
        self,
        capture_nanos: int,
        source_nanos: int | None,
        world_from_camera: np.ndarray,
        truth: np.ndarray | None = None,
    ) -> None:
        """One placed pose, and its frame's ground truth if it had one (a write that fails, a full disk
        say, is said once and the journal stops: the poses are published all the same)."""
        if self.failed:
            return
        rows = [world_from_camera] if truth is None else [world_from_camera, truth]
        values = " ".join(f"{v:.9f}" for m in rows for v in np.asarray(m, np.float64)[:3].ravel())
        try:
            if self._file is None:
                if not self.path.parent.is_dir():
                    return  # no run folder: nothing to resume from either
                self._file = self.path.open("a", buffering=1)  # line-buffered: each pose reaches the OS
            self._file.write(f"{capture_nanos} {-1 if source_nanos is None else source_nanos} {values}\n")
        except OSError as exc:
            self.failed = True
            log.warning("%s: cannot write (%s): a kill now loses the poses since the last checkpoint", self.path, exc)

    def rotate(self) -> None:
        """A checkpoint is being written from the state up to now: later poses go to a fresh file (what a
        checkpoint that never finished had rotated stays, with these lines after it)."""
        if self._file is not None:
            with contextlib.suppress(OSError):
                self._file.close()
            self._file = None
        if not self.path.is_file():
            return
        if self.rotated.is_file():
            with self.rotated.open("a") as out:
                out.write(self.path.read_text())
            self.path.unlink()
        else:
            os.replace(self.path, self.rotated)

    def discard(self, why: str) -> None:
        """A journal this process cannot resume from (no checkpoint to append it to): said, then removed."""
        lines = 0
        for path in (self.rotated, self.path):
            with contextlib.suppress(OSError):
                lines += len(path.read_text().splitlines())
                path.unlink()
        if lines:
            log.warning("%s: %d poses of a previous process not resumed (%s)", self.path.name, lines, why)

    def drop_rotated(self) -> None:
        """The checkpoint holds what the rotated file had."""
        self.rotated.unlink(missing_ok=True)

    def read(self, *, source_time: bool) -> JournalRead:
        """The poses of both files and the ground truth of those that had one, in the data set's time
        (lines without a data-set stamp left out) or capture time, sorted; a line cut short by the kill
        is skipped."""
        poses: dict[int, np.ndarray] = {}
        truths: dict[int, np.ndarray] = {}
        for path in (self.rotated, self.path):
            try:
                lines = path.read_text().splitlines()
            except OSError:
                continue
            for line in lines:
                parts = line.split()
                if len(parts) not in (self.WITHOUT_TRUTH, self.WITH_TRUTH):
                    continue
                try:
                    capture, source = int(parts[0]), int(parts[1])
                    rows = np.array([float(v) for v in parts[2:]], np.float64).reshape(-1, 3, 4)
                except ValueError:
                    continue
                stamp = source if source_time else capture
                if stamp < 0:
                    continue
                poses[stamp] = _homogeneous(rows[0])
                if len(rows) == 2:
                    truths[stamp] = _homogeneous(rows[1])
                else:
                    truths.pop(stamp, None)

        def arrays(by_stamp: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
            order = sorted(by_stamp)
            return np.array(order, np.int64), np.array([by_stamp[t] for t in order], np.float64).reshape(-1, 4, 4)

        return JournalRead(*arrays(poses), *arrays(truths))


def _homogeneous(rows: np.ndarray) -> np.ndarray:
    return np.vstack([rows, [0.0, 0.0, 0.0, 1.0]])


@dataclass
class RobotRun:
    """What slam keeps per robot beside the shared graph: frame indexing (repeats, camera restarts),
    ground truth and data-set stamps waiting for their frames, the resumed trajectory, the last pose."""

    robot_id: str
    indexer: FrameIndexer = field(default_factory=FrameIndexer)
    # Ground truth (simulated sources): the camera sends it for every frame it captures, slam keeps
    # it for the frames it gets poses for (a recent window waits for them), compactly.
    gt: PoseLog = field(default_factory=PoseLog)
    gt_recent: OrderedDict[int, np.ndarray] = field(default_factory=OrderedDict)
    # A data set's own frame times (folder source with rgb.txt), held like ground truth until the
    # frame's TagPoses come; trajectory.tum is written in that time when every pose has one.
    source_stamps: StampMap = field(default_factory=StampMap)
    stamp_recent: OrderedDict[int, int] = field(default_factory=OrderedDict)
    # the resumed run's trajectory, as arrays (nanoseconds, poses): written first, never shortened
    previous_stamps_nanos: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    previous_poses: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4), np.float64))
    previous_time: str | None = None  # the time the resumed files are in (slam.json's `time`)
    # and its ground truth (the ATE covers the whole run, not only what this process placed)
    previous_gt_stamps_nanos: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    previous_gt_poses: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4), np.float64))
    last_pose: np.ndarray | None = None
    frames: int = 0  # TagPoses fused for this robot (the periodic map publication and drawing count them)
    map_due: bool = False  # the shared map changed since this robot's map key last carried it
    intrinsics: CameraIntrinsics | None = None  # the frustum is logged again when they change
    unanchored: int = 0  # frames lost waiting for the tag map's anchor tag to come into view
    seen_before_anchor: set[int] = field(default_factory=set)  # what was seen meanwhile (for the warning)
    journal: PoseJournal | None = None  # the poses since the last checkpoint (a kill loses none)


class CheckpointWrites:
    """The periodic checkpoint's writes: a failure (a full disk, a folder made read-only) is counted and
    said once, its recovery said too, and the service goes on (the poses wait in the journal). They
    were counted as a refused input named "checkpoint", once a warning per 5 s, and the recovery went
    unsaid (a soak trial)."""

    def __init__(self) -> None:
        self.failed = 0
        self.failing = False

    def write(self, checkpoint: Callable[[], object]) -> None:
        """Run one checkpoint write."""
        try:
            checkpoint()
        except Exception as exc:  # a checkpoint is never fatal: the run goes on without it
            self.failed += 1
            if not self.failing:
                log.warning(
                    "checkpoint failed (trying again every period; poses kept in the journal): %s: %s",
                    type(exc).__name__,
                    exc,
                )
            self.failing = True
            return
        if self.failing:
            log.warning("checkpoint written again after %d failed", self.failed)
        self.failing = False


class SlamNode:
    """The service's state: the SLAM core (one graph, one tag map, a trajectory per robot) plus ground
    truth and output writing (no Zenoh here). One robot (`robots` unset) writes trajectory.tum; a
    fleet writes trajectory_<robot>.tum (and groundtruth_<robot>.tum) per robot."""

    def __init__(self, settings: SlamServiceSettings) -> None:
        self.settings = settings
        self.fleet = settings.robots is not None
        known: dict[int, tuple[float, np.ndarray]] = {}
        known_sigmas: dict[int, tuple[float | None, float | None]] = {}
        slam_settings = settings.slam
        # A restarted slam resumes from its last checkpoint in run_dir: the map it had (as priors, its
        # anchor fixing the world frame) and each trajectory so far (kept, continued, never shortened).
        checkpoint = settings.run_dir / "map.json"
        self.resumed = load_tag_map(checkpoint) if settings.resume and checkpoint.is_file() else None
        configured = load_tag_map(settings.tag_map) if settings.tag_map is not None else None
        # soft reads place the camera only by the configured map's tags, never by the checkpoint's (this
        # SLAM's own estimates: SlamSettings.soft_reads)
        surveyed = {t.id for t in configured.tags if t.pose() is not None} if configured is not None else set()
        for tm in (self.resumed, configured):
            if tm is None:
                continue  # the configured map (second) wins over the checkpoint
            known |= {t.id: (t.size_m, pose) for t in tm.tags if (pose := t.pose()) is not None}
            known_sigmas |= {t.id: t.stated_sigmas() for t in tm.tags if t.world_from_tag is not None}
            if tm.anchor_tag_id is not None:
                slam_settings = slam_settings.model_copy(
                    update={"anchor_tag_id": slam_settings.anchor_tag_id or tm.anchor_tag_id}
                )
        self.slam = MarkerSlam(slam_settings, known_tags=known, known_sigmas=known_sigmas, surveyed=surveyed)
        if self.resumed is not None:  # each tag's observations go on counting (a trial read 0 after a restart)
            listed = {t.id for t in self.resumed.tags}
            self.slam.state.observations |= _resumed_observations(settings.run_dir / "slam.json", listed)
        # The sizes slam's map gives: a tag the edge solved at another size (its own tag map, or none) is
        # rescaled to this one (PnP's translation scales with the size), said once per tag.
        self.sizes = configured  # (its sizes by id below: looked up for every tag of every frame)
        self._size_by_id = {t.id: t.size_m for t in configured.tags} if configured else {}
        # the tags whose world the configured map gives (a checkpoint's poses are in slam's own world)
        self.world_tags = {t.id for t in configured.tags if t.world_from_tag is not None} if configured else set()
        self._resized: set[int] = set()
        self._time_warned: set[str] = set()  # robots whose resumed time base left poses out (said once)
        self.runs: dict[str, RobotRun] = {}
        for robot in (
            settings.robots if isinstance(settings.robots, list) else [] if self.fleet else [settings.robot_id]
        ):
            self.run_of(robot)
        if self.resumed is not None:
            log.info("resuming from %s: %d tags, robots %s", checkpoint, len(known), sorted(self.runs))
        # The map's revision increases over the run, across restarts (a fresh-clone trial saw revision 6
        # before a restart and 1, then 6 again with other content, after it): a new process's map is a
        # new map, one past the last revision this run wrote (the checkpoint may be older, or missing),
        # written at once.
        self.revision_path = settings.run_dir / "map_revision"
        previous = _read_revision(self.revision_path)
        self.revision = 0 if previous is None else previous + 1
        _write_revision(self.revision_path, self.revision)
        # (revision, content digest) of the last map handed out: a map whose content differs gets the
        # next revision, so one revision is one map (poses and counts are refined every frame, and a
        # client that cached the map by revision kept stale poses: a fresh-clone trial)
        self.given: tuple[int, bytes] | None = None
        self.lock = threading.Lock()

    def _sized(self, o: Observation) -> Observation:
        """The observation at the size slam's tag map gives its tag (unchanged without a map)."""
        if self.sizes is None:
            return o
        size = self._size_by_id.get(o.tag_id, self.sizes.default_size_m)
        if abs(size - o.size_m) <= 1e-3 * size:
            return o
        if o.tag_id not in self._resized and len(self._resized) < MAX_RESIZED_WARNINGS:
            self._resized.add(o.tag_id)
            log.warning(
                "tag %d was solved at %.4f m but slam's tag map says %.4f m: rescaled (give edge_infer and "
                "robot_infer the same tag_map)",
                o.tag_id,
                o.size_m,
                size,
            )
        return rescale_observation(o, size)

    def _trajectory_file(self, robot: str, what: str = "trajectory") -> str:
        return f"{what}_{robot}.tum" if self.fleet else f"{what}.tum"

    def serves(self, robot: str) -> bool:
        """Whether this slam takes `robot`'s messages."""
        robots = self.settings.robots
        return robots == "*" or (robot in robots if isinstance(robots, list) else robot == self.settings.robot_id)

    def run_of(self, robot: str) -> RobotRun:
        """The per-robot state (made on the robot's first message; a resumed trajectory is read then)."""
        run = self.runs.get(robot)
        if run is None:
            if not self.serves(robot):
                raise SlamInputError(f"robot {robot!r} is not one this slam serves ({self.settings.robots})")
            check_robot_count(len(self.runs), robot)  # any id may arrive with robots = "*": bounded here
            run = self.runs[robot] = RobotRun(robot)
            path = self.settings.run_dir / self._trajectory_file(robot)
            journal = PoseJournal(path.with_name(path.name + ".journal"))
            if self.resumed is not None and path.is_file():
                run.previous_stamps_nanos, run.previous_poses = read_tum_nanos(path)
                gt_path = self.settings.run_dir / self._trajectory_file(robot, "groundtruth")
                if gt_path.is_file():
                    run.previous_gt_stamps_nanos, run.previous_gt_poses = read_tum_nanos(gt_path)
                run.previous_time = self._resumed_time(robot)
                if self.resumed.anchor_tag_id is None and not self.world_tags:
                    journal.discard("the checkpoint names no anchor: their world may not be this one")
                else:  # what the killed process placed after its last checkpoint
                    stamps, poses, truth_stamps, truths = journal.read(source_time=run.previous_time != "capture")
                    run.previous_stamps_nanos, run.previous_poses = _after(
                        run.previous_stamps_nanos, run.previous_poses, stamps, poses
                    )
                    run.previous_gt_stamps_nanos, run.previous_gt_poses = _after(
                        run.previous_gt_stamps_nanos, run.previous_gt_poses, truth_stamps, truths
                    )
                    if len(stamps):
                        log.info(
                            "resumed %s and %d poses of its journal (%s)", path.name, len(stamps), journal.path.name
                        )
                    if len(run.previous_poses):
                        # a lost frame repeats the last pose: the killed process's, in this world (an EKF
                        # integrator's trial read the identity from a restarted slam until it placed a frame)
                        run.last_pose = run.previous_poses[-1]
            else:  # killed before its first checkpoint (or this robot before it was in one)
                journal.discard("no checkpoint of this robot's trajectory to resume them after")
            # (the journal's lines stay on disk until this process's first checkpoint holds them: killed
            # before it, the next process reads them again)
            run.journal = journal if self.settings.resume else None
        return run

    def _resumed_time(self, robot: str) -> str:
        """The time base a previous process wrote `robot`'s files in (slam.json; capture if it says none)."""
        try:
            stats = json.loads((self.settings.run_dir / "slam.json").read_text())
            entry = stats.get("robots", {}).get(robot, {}) if self.fleet else stats
            return str(entry.get("time", "capture"))
        except (OSError, ValueError, AttributeError):
            return "capture"

    def _warn_once(self, robot: str, text: str) -> None:
        if robot not in self._time_warned:
            self._time_warned.add(robot)
            log.warning("%s", text)

    @property
    def indexer(self) -> FrameIndexer:
        """The single robot's frame indexer."""
        return self.run_of(self.settings.robot_id).indexer

    def on_ground_truth(self, capture_nanos: int, world_from_camera: np.ndarray, robot: str | None = None) -> None:
        """Hold a frame's ground truth until its TagPoses come (bounded: the oldest goes first)."""
        with self.lock:
            run = self.run_of(robot or self.settings.robot_id)
            run.gt_recent[capture_nanos] = world_from_camera
            while len(run.gt_recent) > GT_WAITING_FRAMES:
                run.gt_recent.popitem(last=False)

    def on_frame_stamp(self, capture_nanos: int, source_nanos: int, robot: str | None = None) -> None:
        """Hold a frame's data-set time until its TagPoses come (bounded as ground truth is)."""
        with self.lock:
            run = self.run_of(robot or self.settings.robot_id)
            run.stamp_recent[capture_nanos] = source_nanos
            while len(run.stamp_recent) > GT_WAITING_FRAMES:
                run.stamp_recent.popitem(last=False)

    def on_poses(self, msg: TagPoses) -> tuple[CameraPose, TagMap | None]:
        """Fuse one frame; returns the camera pose message and the map if it should be published."""
        with self.lock:
            robot = msg.robot_id if self.fleet else self.settings.robot_id  # one robot: its key decided
            run = self.run_of(robot)
            focal = None if msg.intrinsics is None else (msg.intrinsics.fx + msg.intrinsics.fy) / 2
            observations = [Observation.from_message(t, focal) for t in msg.tags]
            for o in observations:
                check_observation(o)  # before the indexer remembers the frame (the size as sent, too)
            observations = [self._sized(o) for o in observations]
            strays = run.indexer.strays
            frame = run.indexer.index(msg.seq, msg.capture_nanos)
            if run.indexer.strays != strays:
                log.warning(
                    "%s: %d frames in a row came older than the newest fused one: it was a stray (a capture time "
                    "ahead of its camera's); going on from frame seq %d as a new camera session (%d strays)",
                    robot,
                    run.indexer.stray_confirm,
                    msg.seq,
                    run.indexer.strays,
                )
            res = self.slam.update(frame, msg.capture_nanos, observations, robot=robot)
            truth = run.gt_recent.pop(msg.capture_nanos, None)
            source_nanos = run.stamp_recent.pop(msg.capture_nanos, None)
            if truth is not None:
                run.gt.append(msg.capture_nanos, truth)
            if source_nanos is not None:
                run.source_stamps.add(msg.capture_nanos, source_nanos)
            if res.world_from_camera is not None:
                run.last_pose = res.world_from_camera
                if run.journal is not None:
                    run.journal.append(msg.capture_nanos, source_nanos, res.world_from_camera, truth)
            pose = run.last_pose if run.last_pose is not None else np.eye(4)
            cam = CameraPose(
                robot_id=msg.robot_id,
                seq=msg.seq,
                capture_nanos=msg.capture_nanos,
                world_from_camera=pose,
                status=res.status,  # "tracking" | "bridged" (a fragment not yet tied to the world) | "lost"
                tags_used=res.tags_used,
                # None when lost (the pose is the last one repeated); scaled as configured (calibration)
                covariance_world=None
                if res.covariance_world is None
                else res.covariance_world * self.settings.covariance_scale,
            )
            run.frames += 1
            wanted = self.slam.settings.anchor_tag_id
            # nothing mapped yet (a known or resumed map places frames before the anchor is seen, and
            # localisation never sets one: a frame without tags there is lost for another reason)
            if self.slam.anchor is None and wanted is not None and res.status == "lost" and not self.slam.tags:
                run.unanchored += 1
                run.seen_before_anchor.update(o.tag_id for o in observations)
                if run.unanchored in (30, 300) or run.unanchored % 3000 == 0:  # said when it matters
                    # any tag the map places relocalises, not only the anchor (a trial's restarted slam said
                    # it waited for 'the tag map's anchor_tag_id', of a map that named none: the checkpoint's)
                    placed = sorted(self.slam.known)
                    log.warning(
                        "%s: %d frames lost waiting for the anchor tag %d%s of the %s to come into view; tags seen "
                        "so far: %s",
                        robot,
                        run.unanchored,
                        wanted,
                        f" (or any of the {len(placed)} tags it places: {placed[:20]})" if placed else "",
                        "resumed map (map.json of the run before the restart)" if self.resumed else "tag map",
                        sorted(run.seen_before_anchor)[:20] or "none",
                    )
            if res.map_changed:  # one shared map: every robot's map key carries the change
                self.revision += 1
                _write_revision(self.revision_path, self.revision)
                for other in self.runs.values():
                    other.map_due = True
            publish_map = run.map_due or run.frames % self.settings.map_publish_every == 0
            run.map_due = False
            return cam, (self._map(msg.robot_id) if publish_map else None)

    def _tag_sigmas(self, tag_map: dict[int, tuple[float, np.ndarray]]) -> dict[int, tuple[float, float]]:
        """(rotation rad, position m) per mapped tag but the anchor (call with the lock held): the graph's
        marginal. In localisation-only mode the map is held fixed: what the tag map stated (a tag it
        stated nothing for stays as surveyed). Where GTSAM gives no marginal: what the map stated, else
        as loose as a tag map may state (a pose whose uncertainty is unknown must not come back as
        surveyed)."""
        marginals = self.slam.tag_sigmas()
        anchors = {self.slam.anchor, self.slam.settings.anchor_tag_id}
        out = {}
        for t in tag_map:
            if t in anchors:
                continue
            rot, pos = self.slam.known_sigmas.get(t, (None, None))
            if t in marginals:
                out[t] = _clip_sigmas(marginals[t])
            elif rot is not None and pos is not None:
                out[t] = _clip_sigmas((rot, pos))
            elif not self.slam.settings.localisation_only:
                out[t] = _clip_sigmas((math.inf, math.inf))
        return out

    def _map(self, robot_id: str) -> TagMap:
        mapped = self.slam.tag_map()
        sigmas = self._tag_sigmas(mapped)
        tags = []
        for t, (size, pose) in sorted(mapped.items()):
            bridged = self.slam.tag_bridged(t)
            rot, pos = sigmas[t] if t in sigmas and not bridged else (None, None)  # the anchor has none
            tags.append(
                MapTag(
                    tag_id=t,
                    size_m=size,
                    world_from_tag=pose,
                    observations=self.slam.state.observations.get(t, 0),
                    bridged=bridged,
                    position_sigma_m=pos,
                    rotation_sigma_deg=None if rot is None else math.degrees(rot),
                )
            )
        # The tags whose world pose slam holds as priors (a configured map's, a checkpoint's) and has not
        # seen (again), as it holds them (a configured map's wins over the checkpoint's): a map fed back as
        # tag_map keeps them (a trial's surveyed tags 9 and 10, never in view, dropped out of map.json).
        for tag_id in sorted(self.slam.known):
            if tag_id not in mapped:
                size, prior_pose = self.slam.known[tag_id]
                rot, pos = self.slam.known_sigmas.get(tag_id, (None, None))
                tags.append(
                    MapTag(
                        tag_id=tag_id,
                        size_m=size,
                        world_from_tag=prior_pose,
                        observations=self.slam.state.observations.get(tag_id, 0),  # (a resumed count)
                        bridged=False,
                        position_sigma_m=pos,
                        rotation_sigma_deg=None if rot is None else math.degrees(rot),
                    )
                )
        tags.sort(key=lambda m: m.tag_id)
        anchor = self._anchor_id()
        anchor_id = anchor or 0
        digest = map_digest(anchor_id, tags)
        if self.given is not None and self.given[0] == self.revision and self.given[1] != digest:
            self.revision += 1
            _write_revision(self.revision_path, self.revision)
        self.given = (self.revision, digest)
        return TagMap(robot_id=robot_id, revision=self.revision, anchor_tag_id=anchor_id, tags=tags)

    def _anchor_id(self) -> int | None:
        """The map's anchor: slam's, else the checkpoint's, else the configured one (its priors are
        published before slam has chosen: a map fed back must keep it)."""
        if self.slam.anchor is not None:
            return self.slam.anchor
        if self.resumed is not None and self.resumed.anchor_tag_id is not None:
            return self.resumed.anchor_tag_id
        return self.slam.settings.anchor_tag_id

    def current_map(self, robot_id: str) -> TagMap:
        """Thread-safe map snapshot (the one shared map, addressed to `robot_id`)."""
        with self.lock:
            return self._map(robot_id)

    def write_outputs(self, run_dir: Path) -> dict[str, Any]:
        """Per robot trajectory(_<robot>).tum and, with ground truth, groundtruth(_<robot>).tum; the
        shared map.json (a tag map), slam.json, and with ground truth ate.json."""
        run_dir.mkdir(parents=True, exist_ok=True)
        with self.lock:
            tag_map = self.slam.tag_map()
            bridged = {t for t in tag_map if self.slam.tag_bridged(t)}
            marginals = self._tag_sigmas(tag_map)
            state = self.slam.state
            frames, lost, rejected = state.frames, state.lost, state.rejected_ambiguous
            fragments, jumps = state.fragments, state.jumps
            disagreeing = {f"{a}-{b}": round(100 * m, 1) for (a, b), m in sorted(state.map_disagreement_m.items())}
            observations = dict(state.observations)
            soft_skipped, soft_localised = state.soft_reads_skipped, state.soft_reads_localised
            tracked_skipped, tracked_localised = state.tracked_skipped, state.tracked_localised
            robots = sorted(self.runs)
        per_robot = {robot: self._write_robot(run_dir, robot) for robot in robots}
        sizes_only: dict[int, float] = {}
        # How well each tag is known goes with it (the graph's marginals), so a resumed slam, or a run fed
        # this map as its tag_map, believes each pose only as far as this run could place it.
        sigmas = dict(marginals)
        # tags not seen (again) whose world pose slam holds as a prior (a configured map's over the
        # checkpoint's), as the map publishes them; the checkpoint's tags without one by their size
        for tag_id, known in self.slam.known.items():
            if tag_id not in tag_map:
                tag_map[tag_id] = known
                rot, pos = self.slam.known_sigmas.get(tag_id, (None, None))
                if rot is not None and pos is not None:
                    sigmas[tag_id] = (rot, pos)
        if self.resumed is not None:
            sizes_only |= {t.id: t.size_m for t in self.resumed.tags if t.id not in tag_map}
        # map.json is a tag map (loadable as slam's or edge_infer's `tag_map`); run statistics go apart.
        # A tag in a fragment not tied to the world goes in with its size but no pose: its pose is a
        # gap's guess, and a resumed slam takes every pose in map.json as a world prior.
        anchor = self._anchor_id()
        world = {t: v for t, v in tag_map.items() if t not in bridged}
        posed = tag_map_from_poses(world, anchor_tag_id=None, sigmas=sigmas)
        sizes_only |= {t: tag_map[t][0] for t in bridged}
        # built whole, then checked once (each id once, the anchor among them) as a reader will check it
        tags = sorted(
            [*posed.tags, *(TagSpec(id=t, size_m=size) for t, size in sizes_only.items())], key=lambda t: t.id
        )
        if anchor not in {t.id for t in tags}:
            anchor = None  # (a configured anchor not placed yet: a map names only an anchor it lists)
        checkpoint = TagMapFile(default_size_m=posed.default_size_m, anchor_tag_id=anchor, tags=tags)
        write_tag_map(run_dir / "map.json", checkpoint)
        out: dict[str, Any] = {
            "frames": frames,
            "poses": sum(r["poses"] for r in per_robot.values()),
            "tags": len(tag_map),
            # per tag: the views slam used over the run (a restarted slam goes on from these)
            "observations_by_tag": {str(t): n for t, n in sorted(observations.items())},
            "lost_frames": lost,
            "rejected_ambiguous": rejected,
            "fragments": fragments,  # map fragments begun after long gaps without tags
            "jumps": jumps,  # frames placed away from the motion by their views (SlamSettings.jump_margin_m)
            # pairs of surveyed tags ("a-b") the views put > 5 cm further apart (or closer: negative) than the
            # tag map does, median cm: a map wrong there
            "map_disagreement_cm": disagreeing,
            "soft_reads_skipped": soft_skipped,  # blind soft reads left out (SlamSettings.soft_reads)
            "soft_reads_localised": soft_localised,  # soft reads that placed the camera against a known tag
            "tracked_skipped": tracked_skipped,  # tracked views left out (SlamSettings.tracked_reads)
            "tracked_localised": tracked_localised,  # tracked views that placed the camera against a known tag
        }
        if self.fleet:
            out["robots"] = per_robot
        else:
            out |= per_robot.get(self.settings.robot_id, {"poses": 0, "time": "capture"})
        atomic_write_text(run_dir / "slam.json", json.dumps(out, indent=2))
        if any("ate_m" in r or "ate_error" in r for r in per_robot.values()):
            (run_dir / "ate.json").write_text(json.dumps(out, indent=2))
        return out

    def _write_robot(self, run_dir: Path, robot: str) -> dict[str, Any]:
        # Arrays throughout: a long run writes its whole trajectory every few seconds, and a Python
        # object per pose each time fragments the heap (RSS that only grows).
        with self.lock:
            run = self.runs[robot]
            journal = run.journal if run_dir.resolve() == self.settings.run_dir.resolve() else None
            if journal is not None:
                journal.rotate()  # the poses after this snapshot go to a fresh journal
            traj_stamps, traj_poses = self.slam.trajectory_arrays(robot)
            gt_stamps, gt_poses = run.gt.arrays()
            source_traj, traj_found = run.source_stamps.lookup(traj_stamps)
            source_gt, gt_found = run.source_stamps.lookup(gt_stamps)
        # The data set's time when every pose has one (a TUM tool compares trajectory.tum with the data
        # set's ground truth as it is); else the live capture time. A resumed run keeps the time its files
        # are in (poses in two time bases in one file would never be appended to again, silently: review):
        # in the data set's, this process's poses without a data-set stamp are left out (said).
        # A few poses without one (their FrameStamp never came) are left out, said once and counted: an
        # EKF integrator's trial had 2 of 402 without, the whole file went out in capture time, and the
        # README's evo_ape against the data set's ground truth failed.
        in_source_time = len(run.source_stamps) > 0 and 2 * int(traj_found.sum()) >= len(traj_found)
        if run.previous_time is not None:
            in_source_time = run.previous_time != "capture"
        left_out = int((~traj_found).sum()) if in_source_time else 0
        if in_source_time and not (traj_found.all() and gt_found.all()):
            self._warn_once(
                robot,
                f"{self._trajectory_file(robot)}: in the data set's time; {left_out} of this process's poses "
                "have no data-set stamp and are left out",
            )
            traj_poses, source_traj = traj_poses[traj_found], source_traj[traj_found]
            gt_poses, source_gt = gt_poses[gt_found], source_gt[gt_found]
        elif len(run.source_stamps) and not in_source_time and run.previous_time is None:
            log.warning(
                "%s in capture time: %d of %d poses have no data-set stamp",
                self._trajectory_file(robot),
                int((~traj_found).sum()),
                len(traj_found),
            )
        # stamps in integer nanoseconds throughout: written exactly (a data set's stamps come back as given)
        stamps, poses = _after(
            run.previous_stamps_nanos,
            run.previous_poses,
            np.asarray(source_traj if in_source_time else traj_stamps, np.int64),
            traj_poses,
        )
        write_tum_arrays(run_dir / self._trajectory_file(robot), stamps, poses)
        if journal is not None:
            journal.drop_rotated()  # trajectory.tum holds those poses now
        # `poses` counts the trajectory as written, a resumed run's earlier poses first (`resumed_poses` of
        # them); `frames` (slam.json) counts what this process placed since it started. Ground truth is
        # kept the same way, so the ATE covers the whole run (a restarted slam's used to cover only the
        # frames since its restart: a fleet trial read 859 of 1511 frames, nothing said so).
        out: dict[str, Any] = {
            "poses": len(stamps),
            "resumed_poses": len(run.previous_stamps_nanos),
            "time": "data set (rgb.txt or the video's own)" if in_source_time else "capture",
            "poses_without_data_set_stamp": left_out,  # left out of the files, in the data set's time
        }
        gt_stamps, gt_poses = _after(
            run.previous_gt_stamps_nanos,
            run.previous_gt_poses,
            np.asarray(source_gt if in_source_time else gt_stamps, np.int64),
            gt_poses,
        )
        if len(gt_stamps):
            write_tum_arrays(run_dir / self._trajectory_file(robot, "groundtruth"), gt_stamps, gt_poses)
            try:
                # TUM's ATE (after SE(3) alignment); and, when a tag map gives slam's world (its anchor's
                # pose), the error in that world as it is, which counts the map's placement too
                ate, n = absolute_trajectory_error_arrays(stamps, poses[:, :3, 3], gt_stamps, gt_poses[:, :3, 3])
                out.update({"ate_m": ate, "ate_frames": n, "ate_aligned": True})
                if self.slam.anchor is not None and self.slam.anchor in self.world_tags:
                    raw, _ = absolute_trajectory_error_arrays(
                        stamps, poses[:, :3, 3], gt_stamps, gt_poses[:, :3, 3], align=False
                    )
                    out["ate_unaligned_m"] = raw
            except ValueError as exc:
                out["ate_error"] = str(exc)
        return out


def _after(
    earlier_stamps: np.ndarray, earlier_poses: np.ndarray, stamps: np.ndarray, poses: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """A resumed run's earlier poses first, then this process's newer ones: never less than was written."""
    if not len(earlier_stamps):
        return stamps, poses
    newer = stamps > earlier_stamps[-1]
    return np.concatenate([earlier_stamps, stamps[newer]]), np.concatenate([earlier_poses, poses[newer]])


def _clip_sigmas(sigmas: tuple[float, float]) -> tuple[float, float]:
    """(rotation rad, position m) within what a tag map may state (0 < rotation <= 180 deg, position <=
    100 m): a tag the graph barely holds is written as barely known, not refused."""
    rot, pos = sigmas
    return min(max(rot, 1e-9), math.pi), min(max(pos, 1e-9), 100.0)


class SlamBusyError(RuntimeError):
    """More map queries pending than slam answers at once."""


class SlamQueryError(ValueError):
    """A map query slam refuses (a save through a wildcard key)."""


def map_digest(anchor_tag_id: int, tags: list[MapTag]) -> bytes:
    """What a map's revision stands for: its anchor and every tag's fields, exactly."""
    h = hashlib.blake2b(str(anchor_tag_id).encode(), digest_size=16)
    for t in tags:
        fields = (t.tag_id, t.size_m, t.observations, t.bridged, t.position_sigma_m, t.rotation_sigma_deg)
        h.update(repr(fields).encode())
        h.update(np.ascontiguousarray(t.world_from_tag, np.float64).tobytes())
    return h.digest()


def _read_revision(path: Path) -> int | None:
    """The map revision a previous slam of this run reached (None: none written; unreadable: said, and
    taken as far ahead as a run could have got, so no revision is given twice)."""
    if not path.is_file():
        return None
    try:
        return max(0, int(path.read_text().strip()))
    except (OSError, ValueError) as exc:
        log.warning("map revision file %s unreadable (%s): revisions go on from 1000000", path, exc)
        return 1_000_000


def _write_revision(path: Path, revision: int) -> None:
    if not path.parent.is_dir():
        return  # no run folder (a slam run without one): nothing to resume from either
    try:
        atomic_write_text(path, f"{revision}\n")
    except OSError as exc:
        log.warning("map revision not written to %s: %s", path, exc)


def map_request(parameters: str, has_payload: bool) -> bool:
    """Whether a map query asks for a save (`save=1` / `true`; `0` / `false` or nothing: a plain get).
    Anything else is refused, as the split's queryable refuses what it does not know (a fresh-clone
    trial's `?foo=1`, `?save=abc` and a payload all got the map back, nothing saved and nothing said)."""
    if has_payload:
        raise SlamQueryError("a map query takes no payload (a get, or ?save=1)")
    try:
        params = parse_parameters(parameters)  # the split query's parser: the same rules
    except SplitRequestError as exc:
        raise SlamQueryError(str(exc)) from None
    unknown = sorted(set(params) - {"save"})
    if unknown:
        raise SlamQueryError(
            f"unknown parameters {unknown} (a map query takes only save: 1 or true to save, 0 or false for a plain get)"
        )
    save = params.get("save", "0")
    if save not in ("1", "true", "0", "false"):
        raise SlamQueryError(f"save must be 1, true, 0 or false, got {save!r}")
    return save in ("1", "true")


def _refuse_busy(query: zenoh.Query) -> None:
    with query:
        query.reply_err(b"slam is busy: too many map queries pending", encoding=zenoh.Encoding.TEXT_PLAIN)
    raise SlamBusyError("map query refused: too many pending")


def run(settings: SlamServiceSettings, *, session: zenoh.Session, stop: threading.Event) -> None:
    """Serve until `stop`; writes the outputs into run_dir at exit. One robot (`robots` unset) or a fleet:
    the listed robots, or every robot ("*"), read through wildcard keys; each gets its camera poses
    and the shared map on its own keys."""
    node = SlamNode(settings)
    rid = settings.robot_id

    def key(per_robot: Callable[[str], str]) -> str:  # the key of one robot, or of every robot for a fleet
        return keys.for_every_robot(per_robot(rid)) if node.fleet else per_robot(rid)

    poses_sub = declare_fifo_subscriber(session, key(keys.tag_poses))
    cam_pubs: dict[str, zenoh.Publisher] = {}
    map_pubs: dict[str, zenoh.Publisher] = {}
    robot_tokens: dict[str, zenoh.LivelinessToken] = {}

    def publishers(robot: str) -> tuple[zenoh.Publisher, zenoh.Publisher]:
        """The robot's camera-pose and map publishers and its slam token (made on its first frame)."""
        if robot not in cam_pubs:
            cam_pubs[robot] = session.declare_publisher(
                keys.camera_pose(robot), encoding=encoding_for(CameraPose.SCHEMA)
            )
            map_pubs[robot] = session.declare_publisher(keys.tag_map(robot), encoding=encoding_for(TagMap.SCHEMA))
            if robot not in robot_tokens:
                robot_tokens[robot] = session.liveliness().declare_token(keys.alive(robot, "slam"))
        return cam_pubs[robot], map_pubs[robot]

    guard = InputGuard("slam")
    persist_input_counts(guard, settings.run_dir)

    def robot_of(sample_key: object) -> str:
        robot = keys.robot_of(str(sample_key))
        if not node.serves(robot):
            raise SlamInputError(f"robot {robot!r} is not one this slam serves")
        return robot

    def on_gt(sample: zenoh.Sample) -> None:
        def keep(payload: bytes) -> None:
            robot = robot_of(sample.key_expr)
            msg = decode(payload, CameraPose)
            check_rigid(msg.world_from_camera, "ground truth world_from_camera")  # it is written out as TUM
            node.on_ground_truth(msg.capture_nanos, np.asarray(msg.world_from_camera), robot)

        payload = sample.payload.to_bytes()
        guard.run("ground_truth", len(payload), lambda: keep(payload))

    # Map gets (and ?save=1) are answered by the main loop, not on Zenoh's thread: a save is ~1 s of work.
    requests: queue.Queue[zenoh.Query] = queue.Queue(maxsize=settings.max_pending_map_queries)

    def on_map_query(query: zenoh.Query) -> None:
        try:
            requests.put_nowait(query)
        except queue.Full:
            guard.run("map query", 0, lambda: _refuse_busy(query))

    def answer(query: zenoh.Query) -> None:
        with query:  # the query is finalised (its asker told "no more replies") on exit
            if not zenoh.KeyExpr(MAP_KEY).includes(query.key_expr):
                # A wildcard get beyond the map keys (`splittag/r1/**`) reaches this queryable past access
                # control's deny rule on them, which applies to the keys it includes, so any identity read
                # the map that way (an adversarial trial, as the secure config's camera): no answer.
                return
            try:
                save = map_request(str(query.parameters), query.payload is not None)
            except SlamQueryError as exc:
                query.reply_err(str(exc).encode(), encoding=zenoh.Encoding.TEXT_PLAIN)
                raise
            if save:
                if keys.is_wildcard(str(query.key_expr)):
                    # A wildcard reaches every queryable under it, past access control's deny rule on the
                    # map key (which sees only the query's own key): a save names the map it saves.
                    query.reply_err(
                        b"save=1 needs the robot's own map key, not a wildcard", encoding=zenoh.Encoding.TEXT_PLAIN
                    )
                    raise SlamQueryError(f"map save through a wildcard key refused: {query.key_expr}")
                try:
                    node.write_outputs(settings.run_dir)
                except Exception as exc:  # said to the asker, not a silent end (a getter asks again then)
                    query.reply_err(
                        f"map save failed: {type(exc).__name__}: {exc}".encode(), encoding=zenoh.Encoding.TEXT_PLAIN
                    )
                    raise
            try:
                asker = keys.robot_of(str(query.key_expr))
            except ValueError:
                asker = rid  # a wildcard get: the map is one for every robot
            # On a map key (the only keys access control lets slam reply on), one that intersects what
            # was asked: the asker's, or the queryable's own for a fleet's wildcard get.
            reply_key = keys.tag_map(asker)
            if not zenoh.KeyExpr(reply_key).intersects(query.key_expr):
                reply_key = key(keys.tag_map)
            query.reply(reply_key, encode(node.current_map(asker)), encoding=encoding_for(TagMap.SCHEMA))

    def on_stamp(sample: zenoh.Sample) -> None:
        def keep(payload: bytes) -> None:
            robot = robot_of(sample.key_expr)
            msg = decode(payload, FrameStamp)
            node.on_frame_stamp(msg.capture_nanos, msg.source_stamp_nanos, robot)

        payload = sample.payload.to_bytes()
        guard.run("frame_stamp", len(payload), lambda: keep(payload))

    gt_sub = session.declare_subscriber(key(keys.ground_truth), on_gt)
    stamp_sub = session.declare_subscriber(key(keys.frame_stamp), on_stamp)
    queryable = session.declare_queryable(key(keys.tag_map), on_map_query)
    for robot in sorted(node.runs):  # the configured robots: tokens at once (tests and tools wait for them)
        robot_tokens[robot] = session.liveliness().declare_token(keys.alive(robot, "slam"))
    fleet_token = session.liveliness().declare_token(keys.fleet_service("slam")) if node.fleet else None
    viz = make_viz(settings.rerun, service="slam", run_dir=settings.run_dir)

    checkpoints = CheckpointWrites()

    def robots_served() -> dict[str, object]:
        with node.lock:  # on Zenoh's thread while the main loop may add a robot
            state = node.slam.state
            return {
                "robots": sorted(node.runs),
                "fragments": state.fragments,
                "jumps": state.jumps,
                "strays": sum(r.indexer.strays for r in node.runs.values()),  # frames stamped ahead, undone
                "soft_reads_skipped": state.soft_reads_skipped,
                "soft_reads_localised": state.soft_reads_localised,
                "tracked_skipped": state.tracked_skipped,
                "tracked_localised": state.tracked_localised,
                "checkpoints_failed": checkpoints.failed,  # writes of the 5 s checkpoint that failed
                "checkpoint_failing": checkpoints.failing,  # the last one failed (its poses wait in the journal)
            }

    stats = serve_stats(session, key(lambda r: keys.stats(r, "slam")), guard, robots_served)

    def process(payload: bytes, sample_key: object) -> None:
        """One TagPoses: fuse, publish the camera pose (and the map on change), log (raises on bad input)."""
        robot = robot_of(sample_key)
        msg = decode_for_robot(payload, TagPoses, robot)  # (one robot's slam fused and relabelled another's)
        cam, tag_map = node.on_poses(msg)
        cam_pub, map_pub = publishers(robot)
        cam_pub.put(encode(cam))
        run = node.runs[robot]
        if cam.status in ("tracking", "bridged"):
            new_camera = msg.intrinsics if msg.intrinsics != run.intrinsics else None
            run.intrinsics = msg.intrinsics or run.intrinsics
            viz.camera_pose(
                cam.capture_nanos,
                cam.world_from_camera,
                msg.intrinsics if cam.status == "bridged" else new_camera,  # (rare: its own frustum each time)
                robot if node.fleet else "",
                bridged=cam.status == "bridged",
                covariance_world=cam.covariance_world,
            )
        if tag_map is not None:
            map_pub.put(encode(tag_map))
            viz.tag_map(cam.capture_nanos, {t.tag_id: (t.size_m, t.world_from_tag) for t in tag_map.tags})
        if settings.rerun.enabled and run.frames % 10 == 0:  # O(trajectory): only when drawn
            with node.lock:
                stamps, poses = node.slam.trajectory_arrays(robot)
                gt_stamps, gt_poses = node.runs[robot].gt.arrays()
                in_truths_world = node.slam.anchor is not None and node.slam.anchor in node.world_tags
            traj = poses[:, :3, 3]
            gt: np.ndarray | None = gt_poses[:, :3, 3]
            if not in_truths_world and len(gt_stamps):  # slam's world is its anchor tag's: the truth fitted to it
                gt = truth_in_estimate_frame(stamps, traj, gt_stamps, gt_poses[:, :3, 3])
            where = f"world/robots/{robot}" if node.fleet else "world"  # the fleet view: a trajectory each
            viz.trajectory(cam.capture_nanos, f"{where}/trajectory", traj)
            if gt is not None:
                viz.trajectory(cam.capture_nanos, f"{where}/groundtruth", gt)

    last_checkpoint = time.monotonic()
    try:
        while not stop.is_set():
            with contextlib.suppress(queue.Empty):
                query = requests.get_nowait()
                guard.run("map query", 0, lambda: answer(query))  # noqa: B023 (called at once)
            sample = poses_sub.try_recv()
            if sample is None:
                stop.wait(0.001)
            else:
                payload = sample.payload.to_bytes()
                guard.run("tag_poses", len(payload), lambda: process(payload, sample.key_expr))  # noqa: B023
            if time.monotonic() - last_checkpoint >= settings.checkpoint_period_secs:
                # Atomic: a kill never leaves half a file, or less. A failing write is counted, not fatal.
                checkpoints.write(lambda: node.write_outputs(settings.run_dir))
                release_free_memory()  # the graph marginalised and the checkpoint texts freed: give pages back
                last_checkpoint = time.monotonic()
    finally:
        stats.undeclare()
        for token in robot_tokens.values():
            token.undeclare()
        if fleet_token is not None:
            fleet_token.undeclare()
        queryable.undeclare()
        gt_sub.undeclare()
        stamp_sub.undeclare()
        summary = guard.run("final save", 0, lambda: node.write_outputs(settings.run_dir))
        guard.close()  # the last interval's rejections said, the counts written
        log.info("slam outputs in %s: %s (inputs: %s)", settings.run_dir, summary, guard.stats())
        viz.close()


def _resumed_observations(stats_path: Path, listed: set[int]) -> dict[int, int]:
    """Each checkpointed tag's observation count as slam.json states it (`observations_by_tag`), for the
    tags the checkpoint lists; nothing when the file is missing or damaged (the
    counts are statistics: slam resumes all the same)."""
    try:
        stats = json.loads(stats_path.read_text())
        counts = stats.get("observations_by_tag", {}) if isinstance(stats, dict) else {}
        out = {int(t): int(n) for t, n in counts.items()}
    except (OSError, ValueError, TypeError, AttributeError):
        return {}
    return {t: n for t, n in out.items() if t in listed and n >= 0}
