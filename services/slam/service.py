"""slam loop: TagPoses -> MarkerSlam -> CameraPose every frame, TagMap on change; files at exit/on request.

Map queryable on `splittag/<robot_id>/map/v1`: a get replies the current TagMap; `?save=1` also
writes trajectory.tum, map.json (a tag map), slam.json (run statistics) and, when ground truth was seen,
groundtruth.tum / ate.json now.
"""

from __future__ import annotations

import contextlib
import json
import logging
import queue
import threading
import time
from collections import OrderedDict
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from services.slam.settings import SlamServiceSettings
from shared.runtime.guard import InputGuard, serve_stats
from shared.runtime.memory import release_free_memory
from shared.slam.marker_slam import (
    FrameIndexer,
    MarkerSlam,
    Observation,
    absolute_trajectory_error_arrays,
    check_observation,
)
from shared.transport.session import declare_fifo_subscriber, encoding_for
from shared.vision.camera import CameraIntrinsics
from shared.vision.files import atomic_write_text
from shared.vision.geometry import check_rigid
from shared.vision.tagmap import load_tag_map, tag_map_from_poses, write_tag_map
from shared.vision.trajectory import PoseLog, StampMap, read_tum, write_tum_arrays
from shared.viz.recording import make_viz
from shared.wire import keys
from shared.wire.messages import CameraPose, FrameStamp, MapTag, TagMap, TagPoses, decode, encode

log = logging.getLogger(__name__)

GT_WAITING_FRAMES = 1024  # ground truth held for frames whose TagPoses have not come yet


class SlamNode:
    """The service's state: the SLAM core plus ground truth and output writing (no Zenoh here)."""

    def __init__(self, settings: SlamServiceSettings) -> None:
        self.settings = settings
        known: dict[int, tuple[float, np.ndarray]] = {}
        slam_settings = settings.slam
        # A restarted slam resumes from its last checkpoint in run_dir: the map it had (as priors, its
        # anchor fixing the world frame) and the trajectory so far (kept, continued, never shortened).
        checkpoint = settings.run_dir / "map.json"
        self.resumed = load_tag_map(checkpoint) if settings.resume and checkpoint.is_file() else None
        previous = (
            read_tum(settings.run_dir / "trajectory.tum")
            if self.resumed is not None and (settings.run_dir / "trajectory.tum").is_file()
            else []
        )
        # the resumed run's trajectory, as arrays (seconds, poses): written first, never shortened
        self.previous_stamps_s = np.array([t for t, _ in previous], np.float64)
        self.previous_poses = np.array([p for _, p in previous], np.float64).reshape(-1, 4, 4)
        for tm in (self.resumed, load_tag_map(settings.tag_map) if settings.tag_map is not None else None):
            if tm is None:
                continue  # the configured map (second) wins over the checkpoint
            known |= {t.id: (t.size_m, pose) for t in tm.tags if (pose := t.pose()) is not None}
            if tm.anchor_tag_id is not None:
                slam_settings = slam_settings.model_copy(
                    update={"anchor_tag_id": slam_settings.anchor_tag_id or tm.anchor_tag_id}
                )
        if self.resumed is not None:
            log.info("resuming from %s: %d tags, %d poses", checkpoint, len(known), len(self.previous_stamps_s))
        self.slam = MarkerSlam(slam_settings, known_tags=known)
        self.indexer = FrameIndexer()  # repeated messages and restarted cameras (seq from 0 again)
        # Ground truth (simulated sources): the camera sends it for every frame it captures, slam keeps
        # it for the frames it gets poses for (a recent window waits for them), compactly.
        self.gt = PoseLog()
        self._gt_recent: OrderedDict[int, np.ndarray] = OrderedDict()
        # A data set's own frame times (folder source with rgb.txt), held like ground truth until the
        # frame's TagPoses come; trajectory.tum is written in that time when every pose has one.
        self.source_stamps = StampMap()
        self._stamp_recent: OrderedDict[int, int] = OrderedDict()
        self.revision = 0
        self.last_pose: np.ndarray | None = None
        self.lock = threading.Lock()

    def on_ground_truth(self, capture_nanos: int, world_from_camera: np.ndarray) -> None:
        """Hold a frame's ground truth until its TagPoses come (bounded: the oldest goes first)."""
        with self.lock:
            self._gt_recent[capture_nanos] = world_from_camera
            while len(self._gt_recent) > GT_WAITING_FRAMES:
                self._gt_recent.popitem(last=False)

    def on_frame_stamp(self, capture_nanos: int, source_nanos: int) -> None:
        """Hold a frame's data-set time until its TagPoses come (bounded as ground truth is)."""
        with self.lock:
            self._stamp_recent[capture_nanos] = source_nanos
            while len(self._stamp_recent) > GT_WAITING_FRAMES:
                self._stamp_recent.popitem(last=False)

    def on_poses(self, msg: TagPoses) -> tuple[CameraPose, TagMap | None]:
        """Fuse one frame; returns the camera pose message and the map if it should be published."""
        with self.lock:
            truth = self._gt_recent.pop(msg.capture_nanos, None)
            source_nanos = self._stamp_recent.pop(msg.capture_nanos, None)
            focal = None if msg.intrinsics is None else (msg.intrinsics.fx + msg.intrinsics.fy) / 2
            observations = [Observation.from_message(t, focal) for t in msg.tags]
            for o in observations:
                check_observation(o)  # before the indexer remembers the frame
            frame = self.indexer.index(msg.seq, msg.capture_nanos)
            res = self.slam.update(frame, msg.capture_nanos, observations)
            if truth is not None:
                self.gt.append(msg.capture_nanos, truth)
            if source_nanos is not None:
                self.source_stamps.add(msg.capture_nanos, source_nanos)
            if res.world_from_camera is not None:
                self.last_pose = res.world_from_camera
            pose = self.last_pose if self.last_pose is not None else np.eye(4)
            cam = CameraPose(
                robot_id=msg.robot_id,
                seq=msg.seq,
                capture_nanos=msg.capture_nanos,
                world_from_camera=pose,
                status="tracking" if res.world_from_camera is not None else "lost",
                tags_used=res.tags_used,
            )
            publish_map = res.map_changed or self.slam.state.frames % self.settings.map_publish_every == 0
            if res.map_changed:
                self.revision += 1
            return cam, (self._map(msg.robot_id) if publish_map else None)

    def _map(self, robot_id: str) -> TagMap:
        tags = [
            MapTag(tag_id=t, size_m=size, world_from_tag=pose, observations=self.slam.state.observations.get(t, 0))
            for t, (size, pose) in sorted(self.slam.tag_map().items())
        ]
        return TagMap(robot_id=robot_id, revision=self.revision, anchor_tag_id=self.slam.anchor or 0, tags=tags)

    def current_map(self, robot_id: str) -> TagMap:
        """Thread-safe map snapshot."""
        with self.lock:
            return self._map(robot_id)

    def write_outputs(self, run_dir: Path) -> dict[str, Any]:
        """trajectory.tum, map.json (a tag map), slam.json, and with ground truth groundtruth.tum + ate.json."""
        run_dir.mkdir(parents=True, exist_ok=True)
        # Arrays throughout: a long run writes its whole trajectory every few seconds, and a Python
        # object per pose each time fragments the heap (RSS that only grows).
        with self.lock:
            traj_stamps, traj_poses = self.slam.trajectory_arrays()
            tag_map = self.slam.tag_map()
            gt_stamps, gt_poses = self.gt.arrays()
            state = self.slam.state
            source_traj, traj_found = self.source_stamps.lookup(traj_stamps)
            source_gt, gt_found = self.source_stamps.lookup(gt_stamps)
        # The data set's time when every pose has one (a TUM tool compares trajectory.tum with the data
        # set's ground truth as it is); else the live capture time.
        in_source_time = len(self.source_stamps) > 0 and bool(traj_found.all()) and bool(gt_found.all())
        if len(self.source_stamps) and not in_source_time:
            log.warning(
                "trajectory.tum in capture time: %d of %d poses have no data-set stamp",
                int((~traj_found).sum()),
                len(traj_found),
            )
        out_stamps = source_traj if in_source_time else traj_stamps
        stamps_s, poses = out_stamps / 1e9, traj_poses
        if len(self.previous_stamps_s):  # a resumed run: the earlier trajectory first, never less
            newer = stamps_s > self.previous_stamps_s[-1]
            stamps_s = np.concatenate([self.previous_stamps_s, stamps_s[newer]])
            poses = np.concatenate([self.previous_poses, poses[newer]])
        write_tum_arrays(run_dir / "trajectory.tum", stamps_s, poses)
        if self.resumed is not None:  # tags of the checkpoint not seen again are kept as they were
            for t in self.resumed.tags:
                if t.id not in tag_map and (pose := t.pose()) is not None:
                    tag_map[t.id] = (t.size_m, pose)
        # map.json is a tag map (loadable as slam's or edge_infer's `tag_map`); run statistics go apart.
        anchor = (
            self.slam.anchor if self.slam.anchor is not None else (self.resumed.anchor_tag_id if self.resumed else None)
        )
        write_tag_map(run_dir / "map.json", tag_map_from_poses(tag_map, anchor_tag_id=anchor))
        out: dict[str, Any] = {
            "frames": state.frames,
            "poses": len(stamps_s),
            "tags": len(tag_map),
            "lost_frames": state.lost,
            "rejected_ambiguous": state.rejected_ambiguous,
            "time": "data set (rgb.txt)" if in_source_time else "capture",
        }
        atomic_write_text(run_dir / "slam.json", json.dumps(out, indent=2))
        if len(gt_stamps):
            write_tum_arrays(run_dir / "groundtruth.tum", (source_gt if in_source_time else gt_stamps) / 1e9, gt_poses)
            try:
                ate, n = absolute_trajectory_error_arrays(
                    traj_stamps, traj_poses[:, :3, 3], gt_stamps, gt_poses[:, :3, 3]
                )
                out.update({"ate_m": ate, "ate_frames": n})
            except ValueError as exc:
                out["ate_error"] = str(exc)
            (run_dir / "ate.json").write_text(json.dumps(out, indent=2))
        return out


class SlamBusyError(RuntimeError):
    """More map queries pending than slam answers at once."""


def _refuse_busy(query: zenoh.Query) -> None:
    with query:
        query.reply_err(b"slam is busy: too many map queries pending")
    raise SlamBusyError("map query refused: too many pending")


def run(settings: SlamServiceSettings, *, session: zenoh.Session, stop: threading.Event) -> None:
    """Serve until `stop`; writes the outputs into run_dir at exit."""
    node = SlamNode(settings)
    rid = settings.robot_id
    poses_sub = declare_fifo_subscriber(session, keys.tag_poses(rid))
    cam_pub = session.declare_publisher(keys.camera_pose(rid), encoding=encoding_for(CameraPose.SCHEMA))
    map_pub = session.declare_publisher(keys.tag_map(rid), encoding=encoding_for(TagMap.SCHEMA))

    guard = InputGuard("slam")

    def on_gt(sample: zenoh.Sample) -> None:
        def keep(payload: bytes) -> None:
            msg = decode(payload, CameraPose)
            check_rigid(msg.world_from_camera, "ground truth world_from_camera")  # it is written out as TUM
            node.on_ground_truth(msg.capture_nanos, np.asarray(msg.world_from_camera))

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
            if query.parameters.get("save") in ("1", "true"):
                node.write_outputs(settings.run_dir)
            query.reply(query.key_expr, encode(node.current_map(rid)), encoding=encoding_for(TagMap.SCHEMA))

    def on_stamp(sample: zenoh.Sample) -> None:
        def keep(payload: bytes) -> None:
            msg = decode(payload, FrameStamp)
            node.on_frame_stamp(msg.capture_nanos, msg.source_stamp_nanos)

        payload = sample.payload.to_bytes()
        guard.run("frame_stamp", len(payload), lambda: keep(payload))

    gt_sub = session.declare_subscriber(keys.ground_truth(rid), on_gt)
    stamp_sub = session.declare_subscriber(keys.frame_stamp(rid), on_stamp)
    queryable = session.declare_queryable(keys.tag_map(rid), on_map_query)
    token = session.liveliness().declare_token(keys.alive(rid, "slam"))
    viz = make_viz(settings.rerun, service="slam", run_dir=settings.run_dir)
    stats = serve_stats(session, keys.stats(rid, "slam"), guard)
    camera: CameraIntrinsics | None = None  # the frustum is logged with the pose when the intrinsics change

    def process(payload: bytes) -> None:
        """One TagPoses: fuse, publish the camera pose (and the map on change), log (raises on bad input)."""
        nonlocal camera
        msg = decode(payload, TagPoses)
        cam, tag_map = node.on_poses(msg)
        cam_pub.put(encode(cam))
        if cam.status == "tracking":
            new_camera = msg.intrinsics if msg.intrinsics != camera else None
            camera = msg.intrinsics or camera
            viz.camera_pose(cam.capture_nanos, cam.world_from_camera, new_camera)
        if tag_map is not None:
            map_pub.put(encode(tag_map))
            viz.tag_map(cam.capture_nanos, {t.tag_id: (t.size_m, t.world_from_tag) for t in tag_map.tags})
        if settings.rerun.enabled and node.slam.state.frames % 10 == 0:  # O(trajectory): only when drawn
            with node.lock:
                traj = node.slam.trajectory_arrays()[1][:, :3, 3]
                gt = node.gt.positions()
            viz.trajectory(cam.capture_nanos, "world/trajectory", traj)
            viz.trajectory(cam.capture_nanos, "world/groundtruth", gt)

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
                guard.run("tag_poses", len(payload), lambda: process(payload))  # noqa: B023 (called at once)
            if time.monotonic() - last_checkpoint >= settings.checkpoint_period_secs:
                # Atomic: a kill never leaves half a file, or less. A failing write is counted, not fatal.
                guard.run("checkpoint", 0, lambda: node.write_outputs(settings.run_dir))
                release_free_memory()  # the graph marginalised and the checkpoint texts freed: give pages back
                last_checkpoint = time.monotonic()
    finally:
        stats.undeclare()
        token.undeclare()
        queryable.undeclare()
        gt_sub.undeclare()
        stamp_sub.undeclare()
        summary = guard.run("final save", 0, lambda: node.write_outputs(settings.run_dir))
        log.info("slam outputs in %s: %s", settings.run_dir, summary)
        viz.close()
