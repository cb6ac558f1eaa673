"""The camera loop: read a source, publish Frame (and ground-truth CameraPose) at a fixed rate."""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import zenoh

from services.camera.settings import CameraSettings
from shared.runtime.service_main import started_by_run_launcher
from shared.runtime.settings import ConfigurationError
from shared.runtime.sources import (
    CaptureSource,
    DemoSource,
    FolderSource,
    FrameSource,
    SourceFrame,
    SourceSizeError,
    VideoSource,
)
from shared.transport.session import declare_tensor_publisher, encoding_for, wait_for_liveliness
from shared.viz.recording import make_viz
from shared.wire import keys
from shared.wire.codec import WireError
from shared.wire.messages import CameraPose, Frame, FrameStamp, TagPoses, decode_view, encode

log = logging.getLogger(__name__)


class SourceProgress:
    """Where a folder or video camera is in its data set, kept in the run folder so that a camera the
    run's launcher restarts goes on from the next image or video frame instead of replaying the data set
    from its first (a trial's restart at 17 s gave trajectory.tum 220 rows for 150 stamps, jumping back in
    time; another's killed video camera replayed frames 0-49). Written after each frame (a rename, no
    fsync: it has to survive the process, not the host)."""

    def __init__(self, path: Path, identity: dict[str, object]) -> None:
        self.path, self.identity = path, identity

    @classmethod
    def of_run(cls, settings: CameraSettings, source: FolderSource | VideoSource) -> SourceProgress:
        return cls(settings.run_dir / f"camera_{settings.robot_id}.progress.json", source.identity)

    def read(self) -> tuple[int, int, int] | None:
        """(completed passes, index of the next image, frames published in the run), or None (no progress,
        unreadable, or of another listing: from the start)."""
        try:
            doc = json.loads(self.path.read_text())
            if {k: doc.get(k) for k in self.identity} != self.identity:
                return None
            return int(doc["passes"]), int(doc["next_index"]), int(doc["published"])
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            return None

    def write(self, passes: int, next_index: int, published: int) -> None:
        tmp = self.path.with_name(f".{self.path.name}.tmp")
        doc = {**self.identity, "passes": passes, "next_index": next_index, "published": published}
        try:
            tmp.write_text(json.dumps(doc))
            os.replace(tmp, self.path)
        except OSError as exc:  # a side record: the stream goes on
            log.debug("camera progress not written to %s: %s", self.path, exc)


def make_source(settings: CameraSettings) -> FrameSource:
    """The configured frame source."""
    if settings.source == "demo":
        return DemoSource(n_frames=settings.demo_frames, cache_dir=settings.cache_dir)
    if settings.camera_info is None:
        raise ValueError(f"source {settings.source!r} needs camera_info (a ROS camera_info YAML)")
    if settings.source == "folder":
        return FolderSource(Path(settings.path), settings.camera_info, settings.groundtruth)
    if settings.source == "video" and _local_file(settings.path):
        return VideoSource(Path(settings.path), settings.camera_info, settings.groundtruth)
    target: str | int = int(settings.path) if settings.path.isdigit() else settings.path
    return CaptureSource(target, settings.camera_info)


def _local_file(path: str) -> bool:
    """A video path names a file (not a URL, rtsp://..., or a GStreamer pipeline, ... ! ..., OpenCV's to open)."""
    return "://" not in path and "!" not in path


class _Stopped(Exception):
    """SIGINT/SIGTERM while waiting for the services the camera streams to."""


def check_source(settings: CameraSettings) -> FrameSource | None:
    """The configured source, made and checked before any Zenoh session (service_main's `check`): a
    missing folder, video file or camera_info, a malformed listing, a video OpenCV cannot read or of
    another size than the camera_info's, is a configuration error said at once, not a crash-and-restart
    loop behind a connection timeout. None for the demo scene (rendered or read from its cache when
    streaming starts); V4L2 devices and streams open when streaming starts (their size is checked at
    their first frame)."""
    if settings.source == "demo":
        return None
    if settings.groundtruth is not None and not (
        settings.source == "folder" or (settings.source == "video" and _local_file(settings.path))
    ):  # (a trial's groundtruth was silently ignored for a video)
        raise ConfigurationError(
            f"groundtruth: a {settings.source} source {settings.path!r} has no time of its own to match it by "
            "(an image folder or a video file has)"
        )
    try:
        source = make_source(settings)
        if isinstance(source, FolderSource):
            source.check()
    except (OSError, ValueError) as exc:  # FileNotFoundError is an OSError; GeometryError a ValueError
        raise ConfigurationError(f"source {settings.source} {settings.path!r}: {exc}") from None
    return source


def _frames_from(source: FrameSource, start: int) -> Iterator[SourceFrame]:
    """One pass over the source; a video from frame `start` (a seek: the caller skips a folder's first
    images itself). A live source whose frames are not of the camera_info's size is a configuration
    error (restarting cannot help)."""
    try:
        yield from source.frames(start) if isinstance(source, VideoSource) else source.frames()
    except SourceSizeError as exc:
        raise ConfigurationError(f"source: {exc}") from None


def run(
    settings: CameraSettings, *, session: zenoh.Session, stop: threading.Event, source: FrameSource | None = None
) -> int:
    """Stream until the source ends (loop off), max_frames is reached, or `stop` is set. `source`: the
    one `check_source` made (else made here)."""
    source = source if source is not None else make_source(settings)
    pub = declare_tensor_publisher(session, keys.frames(settings.robot_id), Frame.SCHEMA)
    gt_pub = session.declare_publisher(keys.ground_truth(settings.robot_id), encoding=encoding_for(CameraPose.SCHEMA))
    # reliable and blocking: a lost stamp would leave its frame in live time in trajectory.tum
    stamp_pub = session.declare_publisher(
        keys.frame_stamp(settings.robot_id),
        encoding=encoding_for(FrameStamp.SCHEMA),
        congestion_control=zenoh.CongestionControl.BLOCK,
    )
    token = session.liveliness().declare_token(keys.alive(settings.robot_id, "camera"))
    if settings.wait_for:

        def stopped_meanwhile() -> None:  # a run stopped before robot_infer was up: go, don't wait it out
            if stop.is_set():
                raise _Stopped

        try:
            wait_for_liveliness(
                session,
                [keys.alive(settings.robot_id, s) for s in settings.wait_for],
                timeout_secs=settings.liveliness_timeout_secs,
                every_second=stopped_meanwhile,
            )
        except _Stopped:
            token.undeclare()
            return 0
    posed = PosesPacer(session, settings.robot_id) if settings.pace == "poses" else None
    viz = make_viz(settings.rerun, service="camera", run_dir=settings.run_dir)
    gt_keypoints = source.gt_keypoints if isinstance(source, DemoSource) else None
    period = 1.0 / settings.fps
    # `seq` numbers the frames of one pass over a folder or video: its next pass starts at 0 again, as a
    # restarted camera does, so slam takes the jump back to the start as a new camera session and does not
    # carry its motion prior across it (a data-set trial's 1 m wrap at 10 fps was within the motion
    # envelope, not a jump: poses 10-50 cm off for a dozen frames around each wrap, with a 2 cm sigma).
    # The demo scene's path is a closed loop: its passes go on as one session.
    continuous = bool(getattr(source, "continuous_loop", False))
    seq = 0
    published = 0  # frames over all passes (max_frames, the return value)
    passes = 0  # completed passes over the source
    span = source.span_nanos if isinstance(source, FolderSource | VideoSource) else None
    first = settings.start_frame  # the first pass starts later in the source (a fleet's robots at different places)
    progress = None
    resumed = None
    if isinstance(source, FolderSource | VideoSource) and started_by_run_launcher(settings.run_dir):
        progress = SourceProgress.of_run(settings, source)
        resumed = progress.read()
        if resumed is not None:
            passes, first, published = resumed  # (max_frames counts the run's frames, not this process's)
            log.info("restarted in this run: the data set goes on from image %d (pass %d)", first, passes + 1)
    next_t = time.monotonic()
    try:
        if settings.max_frames and published >= settings.max_frames:
            log.info("the run's %d frames (max_frames) were sent before the restart", published)
            return published
        while not stop.is_set():
            produced = False
            if isinstance(source, VideoSource):  # (known better once a pass was read: review)
                span = source.span_nanos
            shift = passes * span if span is not None else 0
            sent_this_pass = 0
            for index, item in enumerate(_frames_from(source, first)):
                produced = True
                position = item.index if item.index is not None else index  # (a folder's skips unreadable images)
                if position < first and not sent_this_pass:
                    continue  # not yet at the first pass's (or the resumed) start
                if posed is not None and not posed.wait(stop, settings.poses_timeout_secs):
                    return published
                now = time.monotonic()
                if now < next_t and stop.wait(next_t - now):
                    return published
                # (a live camera catches up one period after a late frame; paced by poses, fps is the
                # upper bound: the next frame a period after this one at the earliest, however long this
                # one waited for poses; a review found two frames 50 ms apart at fps 5)
                next_t = max(next_t + period, time.monotonic() + (period if posed is not None else -period))
                capture = time.time_ns()
                if posed is not None:
                    posed.sent(seq, capture)
                pub.put(
                    encode(
                        Frame(
                            robot_id=settings.robot_id,
                            seq=seq,
                            capture_nanos=capture,
                            intrinsics=source.camera,
                            image=item.image,
                        )
                    )
                )
                if item.stamp_nanos is not None:
                    stamp_pub.put(
                        encode(
                            FrameStamp(
                                robot_id=settings.robot_id,
                                seq=seq,
                                capture_nanos=capture,
                                source_stamp_nanos=item.stamp_nanos + shift,
                            )
                        )
                    )
                if item.world_from_camera is not None:
                    gt_pub.put(
                        encode(
                            CameraPose(
                                robot_id=settings.robot_id,
                                seq=seq,
                                capture_nanos=capture,
                                world_from_camera=item.world_from_camera,
                                status="ground_truth",
                                tags_used=0,
                            )
                        )
                    )
                viz.image(capture, item.image, source.camera, seq)
                if gt_keypoints is not None and item.world_from_camera is not None:
                    viz.keypoints_gt(capture, gt_keypoints(item.world_from_camera))
                seq += 1
                published += 1
                sent_this_pass += 1
                if progress is not None:
                    progress.write(passes, position + 1, published)
                if settings.max_frames and published >= settings.max_frames:
                    log.info("published %d frames (max_frames)", published)
                    if posed is not None:  # the last frame's poses too, before the run may stop
                        posed.wait(stop, settings.poses_timeout_secs)
                    return published
                if stop.is_set():
                    return published
            if not produced and not (isinstance(source, VideoSource) and first > 0):
                # (a video seeked to `first` yields nothing when it was played to its end before a restart,
                # or `start_frame` is past it: the branches below, as a folder's; review)
                raise RuntimeError("the source produced no frames")
            if not sent_this_pass and resumed is not None:
                log.info("the pass was played to its end before the restart")
            elif not published:  # the whole first pass was skipped: looping again would skip it again, forever
                raise ValueError(f"start_frame {first} is past the source's last frame")
            first = 0  # later passes start at the beginning
            if not settings.loops:
                log.info("source ended after %d frames", published)
                if posed is not None:  # the last frame's poses too, before the run may stop
                    posed.wait(stop, settings.poses_timeout_secs)
                return published
            passes += 1
            if not continuous:
                seq = 0  # a new pass: a new camera session for whoever reads the frames
            if span is not None:
                log.info(
                    "pass %d: data-set stamps shifted by %.3f s so time keeps going forward",
                    passes + 1,
                    passes * span / 1e9,
                )
    finally:
        if posed is not None:
            posed.close()
        token.undeclare()
        viz.close()
    return published


class PosesPacer:
    """`pace = "poses"`: the next frame goes out once the previous frame's TagPoses came back (from the
    edge, or robot_infer on board), so every frame of a data set is processed; a frame whose TagPoses do
    not come within the timeout (refused on the way, or lost with a restarted service) is said and
    counted, and the camera goes on. A trial had to guess an fps low enough for its robot (27 of 200
    frames skipped at 5 fps, 7 at 3)."""

    def __init__(self, session: zenoh.Session, robot_id: str) -> None:
        self._cond = threading.Condition()
        self._waiting: int | None = None  # the capture time of the frame whose TagPoses are awaited
        self._seq = -1
        self.timeouts = 0
        self.bad = 0
        self._sub = session.declare_subscriber(keys.tag_poses(robot_id), self._on_poses)

    def _on_poses(self, sample: zenoh.Sample) -> None:
        try:  # (on Zenoh's thread: a field read, no model built)
            capture = decode_view(sample.payload.to_bytes(), TagPoses).fields.capture_nanos
        except WireError as exc:
            self.bad += 1
            if self.bad == 1:
                log.warning("pace = poses: a TagPoses message that does not decode was ignored: %s", exc)
            return
        with self._cond:
            if self._waiting is not None and capture >= self._waiting:
                self._waiting = None
                self._cond.notify_all()

    def sent(self, seq: int, capture_nanos: int) -> None:
        """A frame went out: the next waits for its TagPoses."""
        with self._cond:
            self._waiting, self._seq = capture_nanos, seq

    def wait(self, stop: threading.Event, timeout_secs: float) -> bool:
        """Until the last frame sent is posed, its timeout passes (said, counted) or `stop` (False)."""
        deadline = time.monotonic() + timeout_secs
        with self._cond:
            while self._waiting is not None and not stop.is_set():
                left = deadline - time.monotonic()
                if left <= 0:
                    self.timeouts += 1
                    log.warning(
                        "pace = poses: no TagPoses for frame seq %d within %.1f s (%d such frames): going on",
                        self._seq,
                        timeout_secs,
                        self.timeouts,
                    )
                    self._waiting = None
                    break
                self._cond.wait(min(left, 0.1))  # (a stop is noticed within 0.1 s)
        return not stop.is_set()

    def close(self) -> None:
        """Undeclare the subscriber."""
        self._sub.undeclare()
