"""robot_infer loop: newest frame -> stage 1 + head(k) -> Features, with the split set live over Zenoh."""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from functools import partial

import torch
import zenoh

from services.robot_infer.settings import RobotInferSettings
from shared.control.compute import ComputeEstimator, head_per_tag_ms
from shared.control.throughput import CameraInterval
from shared.model.runtime import calibrate_cumulative_ms, load_split_net
from shared.model.views import with_views
from shared.model.weights import load_keypoint_fusion
from shared.perception.split import RobotTimings, Stage1Output, edge_step, robot_head, robot_stage1
from shared.runtime.guard import InputGuard, persist_input_counts, serve_stats
from shared.runtime.logs import SpellCount
from shared.runtime.service_main import started_by_run_launcher
from shared.runtime.waiting import result_of
from shared.transport.flow import (
    EdgePacer,
    EdgeWatch,
    InFlightWindow,
    UplinkQueue,
    credits_needed,
    may_run_ahead,
)
from shared.transport.latest import LatestValid, declare_latest_valid
from shared.transport.session import declare_tensor_publisher, encoding_for
from shared.transport.split_control import SplitState, remember_split, resumed_split, serve_split, split_memory
from shared.vision.proposals import Stage1Detector
from shared.vision.tagmap import TagMapFile, load_tag_map
from shared.vision.tracking import TagTracker
from shared.wire import keys
from shared.wire.cuts import N_CUTS, CodecName
from shared.wire.messages import (
    ComputeProfile,
    Features,
    Frame,
    FrameSent,
    SplitConfig,
    TagFeature,
    TagPoses,
    decode_for_robot,
    decode_view,
    encode,
    refuse_future_capture,
)

log = logging.getLogger(__name__)
ON_BOARD_LOG_SECS = 10.0  # while the edge is away, the count of frames computed on board is logged this often
EXPECTED_ANSWERS = 512  # the newest frames sent whose answers may steer the pacing and the stall watch


def checked_frame(
    payload: bytes, robot_id: str, *, max_bytes: int, ahead_nanos: int, now_nanos: Callable[[], int] = time.time_ns
) -> Frame:
    """A Frame for this robot (decode_for_robot), captured at most `ahead_nanos` ahead of this host's clock."""
    frame = decode_for_robot(payload, Frame, robot_id, max_bytes=max_bytes)
    refuse_future_capture(frame, now_nanos=now_nanos(), ahead_nanos=ahead_nanos)
    return frame


class _Skipped:
    """The look-ahead did not run (the next frame would not have gone out at once)."""


_SKIPPED = _Skipped()


def run(settings: RobotInferSettings, *, session: zenoh.Session, stop: threading.Event) -> None:
    """Process frames until `stop` is set."""
    torch.set_num_threads(settings.threads)
    node = RobotInfer(settings, session)
    log.info(
        "robot_infer ready: k=%d codec=%s precision=%s (configured %s) views=%d gamma=%.2f",
        node.state.get().k,
        node.state.get().codec,
        node.net.precision,
        settings.precision,
        getattr(node.net, "views", 1),  # what runs, not only what was asked
        settings.gamma,
    )
    try:
        node.serve(stop)
    finally:
        node.close()


class RobotInfer:
    """The robot side: its model, split state, flow-control window, edge watch and Zenoh endpoints."""

    def __init__(
        self, settings: RobotInferSettings, session: zenoh.Session, *, clock: Callable[[], float] = time.monotonic
    ) -> None:
        """`clock` (monotonic seconds) times the frames in flight: the window, the edge watch and the pacer
        (a test moves it by hand, so an answer is overdue by the clock, not by how fast the CPU is)."""
        self.settings = s = settings
        self._clock = clock
        one_view = load_split_net(s.weights, s.precision, threads=s.threads)
        self.net = with_views(one_view, s.views)
        self.fusion = load_keypoint_fusion(s.weights) if s.fuse_corners else None
        # The split a person set (pinned or released) survives a restart of this service within its run (the
        # launcher restarts a service that dies: a fresh-clone trial's pin was lost that way, silently). One
        # file per robot (a fleet's robot_infer processes share the run folder); only a person's setting
        # resumes: the controller, which reads the split before every decision, sets its own k again, and a
        # k that made this process die is not forced on the next one unless a person chose it.
        memory = split_memory(s.run_dir, s.robot_id) if started_by_run_launcher(s.run_dir) else None
        initial = SplitConfig(k=s.split_k, codec=s.codec, pinned=False, source="default")
        resumed = resumed_split(memory) if memory is not None else None
        if resumed is not None:
            how = "pinned" if resumed.pinned else "released"
            log.info("split resumed from %s: k=%d, set by a person (%s)", memory, resumed.k, how)
        self.state = SplitState(
            resumed or initial, on_change=None if memory is None else lambda c: remember_split(memory, c)
        )
        self.net.warm_up(self.state.get().k, max_batch=6)
        # an emulated robot CPU's fixed profile is one view's: its whole-network pass runs once per view too
        emulated = s.emulated_ms_per_tag_by_k
        self.emulated = head_per_tag_ms(emulated, views=s.views) if emulated else None
        self.per_tag_ms = self.emulated or head_per_tag_ms(calibrate_cumulative_ms(one_view), views=s.views)
        self.estimator = ComputeEstimator(self.per_tag_ms)
        self.detector = Stage1Detector(s.stage1)
        self.tracker = TagTracker(s.tracking) if s.tracking.enabled else None
        self.tag_map = load_tag_map(s.tag_map) if s.tag_map else TagMapFile(default_size_m=s.default_tag_size_m)
        # Each frame in flight keeps its Features: if its edge vanishes, the robot computes it on board.
        self.window: InFlightWindow[Features] = InFlightWindow(
            s.max_in_flight, timeout_secs=s.in_flight_timeout_secs, clock=clock
        )
        self._expected: OrderedDict[int, None] = OrderedDict()  # frames sent to the edge, not yet answered
        self._expected_lock = threading.Lock()
        uplink = UplinkQueue() if s.pace_to_link else None  # the uplink as a queue, not a delay
        paced = s.pace_to_edge and s.max_in_flight
        self.pacer = (
            EdgePacer(
                uplink=uplink, stale_secs=s.in_flight_timeout_secs, margin_spreads=s.pace_margin_spreads, clock=clock
            )
            if paced
            else None
        )
        self.watch = EdgeWatch(answer_timeout_secs=s.edge_answer_timeout_secs, clock=clock)
        self.guard = InputGuard("robot_infer")
        persist_input_counts(self.guard, s.run_dir, label=s.robot_id)
        # stage 1 of the next frame while the network runs (settings.overlap_stage1)
        # Not with tracking (its prediction needs the frame before's network output) nor when emulating
        # another CPU (the emulation pads the whole frame's compute on this thread).
        emulating = s.gamma != 1.0 or s.emulated_ms_per_tag_by_k is not None
        ahead = s.overlap_stage1 and self.tracker is None and not emulating
        self.ahead = ThreadPoolExecutor(1, "stage1") if ahead else None
        self.halt = threading.Event()  # set when serve() ends, however it ends: the look-ahead stops too
        self.stage1_ahead_frames = 0
        # what stage 1 and the rest of a frame took lately (exponential averages, seconds): stage 1 of the
        # next frame starts so that it ends as this frame's network does, not before (it would only age)
        self.stage1_secs = 0.0
        self.rest_secs = 0.0
        # frames computed on board, logged at an outage's first, every 10 s while it lasts and at its end
        self.on_board_count = SpellCount(every_secs=ON_BOARD_LOG_SECS)
        self.recovered_frames = 0
        self.last_profile = 0.0
        rid = s.robot_id
        # Frames are checked as they arrive: a bad one is counted and never displaces the good one waiting.
        max_bytes = s.max_payload_bytes
        ahead_nanos = round(s.max_capture_ahead_secs * 1e9)
        self.camera = CameraInterval()  # the camera's rate from its stamps, every good frame (ComputeProfile)

        def check(payload: bytes) -> Frame:
            frame = checked_frame(payload, rid, max_bytes=max_bytes, ahead_nanos=ahead_nanos)
            self.camera.add(frame.seq, frame.capture_nanos)
            return frame

        self.frames: LatestValid[Frame] = LatestValid(check, self.guard, "frame")
        self.sub = declare_latest_valid(session, keys.frames(rid), self.frames)
        self.pub = declare_tensor_publisher(session, keys.features(rid), Features.SCHEMA)
        self.poses_pub = declare_tensor_publisher(session, keys.tag_poses(rid), TagPoses.SCHEMA)
        self.compute_pub = session.declare_publisher(
            keys.compute(rid, "robot"), encoding=encoding_for(ComputeProfile.SCHEMA)
        )
        self.sent_pub = session.declare_publisher(keys.frame_sent(rid), encoding=encoding_for(FrameSent.SCHEMA))
        self.queryable = serve_split(session, keys.split(rid), self.state, refused=self.guard.reject)
        self.acks = session.declare_subscriber(keys.tag_poses(rid), self._on_poses) if s.max_in_flight else None
        self._edge_lost_at: float | None = None  # when edge_infer's token went (None: up, or never seen)
        self.edge_token = session.liveliness().declare_subscriber(
            keys.alive(rid, "edge_infer"), self._on_edge, history=True
        )
        self.token = session.liveliness().declare_token(keys.alive(rid, "robot_infer"))
        self.stats = serve_stats(session, keys.stats(rid, "robot_infer"), self.guard, self.counters)

    def counters(self) -> dict[str, int]:
        """Flow and fallback counters, served with the input counters on the stats key."""
        return {
            "in_flight": self.window.in_flight,
            "in_flight_capacity": self.window.capacity,
            "credits_expired": self.window.expired,
            "on_board_frames": self.on_board_frames,
            "recovered_frames": self.recovered_frames,
            "stage1_ahead_frames": self.stage1_ahead_frames,
            "fresh_frame_waits": self.frames.fresh_waits,
            "fresh_frame_wait_ms": round(1e3 * self.frames.fresh_wait_secs),
            "edge_outages": self.watch.outages,
            "edge_stalls": self.watch.stalls,  # an answer overdue with the edge's token there
            "stage1_frames": self.detector.counts.frames,
            "stage1_apriltag_tags": self.detector.counts.apriltag,
            "stage1_aruco_added": self.detector.counts.aruco_added,
            "stage1_aruco_refused": self.detector.counts.aruco_refused,
            "stage1_lines_added": self.detector.counts.lines_added,
            "stage1_lines_soft": self.detector.counts.lines_soft,
            "stage1_fullres_sweeps": self.detector.counts.fullres_sweeps,
            "stage1_fullres_windows": self.detector.counts.fullres_windows,
            "stage1_fullres_added": self.detector.counts.fullres_added,
            "stage1_at_border": self.detector.counts.at_border,
        }

    # Zenoh callbacks: bookkeeping only.
    def _on_poses(self, sample: zenoh.Sample) -> None:
        payload = sample.payload.to_bytes()
        self.guard.run("tag_poses", len(payload), partial(self._take_poses, payload))

    def _take_poses(self, payload: bytes) -> None:
        """An answer: its credit back, and what it says of the edge and the link. Another robot's (refused:
        counted by the guard) or one for no frame this robot sent and still waits for (ignored: its own
        on-board poses, a duplicate, a forged one) cannot steer the pacing or the stall watch (a
        trial's one forged TagPoses, another robot's id and timings of 1e12 s, held the robot to 3 fps
        for 13 s, uncounted)."""
        # Every check, but no model: this runs on Zenoh's thread and reads a few fields.
        poses = decode_view(payload, TagPoses).fields
        if poses.robot_id != self.settings.robot_id:
            raise ValueError(f"TagPoses of robot {poses.robot_id[:40]!r} on {self.settings.robot_id}'s key")
        # Frames are keyed by capture time, not seq: seq starts again with a camera session (a restart,
        # a looped folder's next pass) while frames of the last one may still be in flight (review).
        if poses.link is None or not self._answering(poses.capture_nanos):
            self.window.done(poses.capture_nanos)  # (an orphan's answer from the race, if any)
            return
        # the edge's answer: prompt, or late? (before the credit returns: the main loop must not take it
        # while the stall still holds)
        self.watch.answered((time.time_ns() - poses.link.sent_nanos) / 1e9)  # both stamps the robot's
        self.window.done(poses.capture_nanos)
        if self.pacer is not None:
            timings = poses.timings
            self.pacer.answered(
                poses.capture_nanos,
                tags=len(poses.tags),
                link_secs=timings.transport_secs,
                edge_secs=timings.edge_compute_secs,
                edge_received_nanos=poses.link.received_nanos,
                # capture_to_pose is the edge's done stamp minus the capture stamp: done on the edge's clock (the
                # pacer bounds what it makes of it)
                edge_done_nanos=poses.capture_nanos + round(timings.capture_to_pose_secs * 1e9),
                link=poses.link,
            )
            if self.pacer.uplink is not None:  # the link as a delay would grow the window on its own queue
                camera = self.frames.interval_secs() or 0.0
                self.window.set_capacity(
                    credits_needed(
                        cycle_secs=self.pacer.robot_secs + self.window.typical_answer_secs,
                        period_secs=max(self.pacer.period_secs(), camera),
                        floor=self.settings.max_in_flight,
                        ceiling=self.settings.in_flight_limit,
                    )
                )

    def _answering(self, capture_nanos: int) -> bool:
        """Whether this answers a frame this robot sent to the edge and has not had an answer for (each
        counts once). Not the window's frames in flight: the window forgets a trial frame as the robot
        computes on board while the edge is overdue, and that trial's answer is what ends the stall."""
        with self._expected_lock:
            return self._expected.pop(capture_nanos, False) is None

    def _on_edge(self, sample: zenoh.Sample) -> None:
        # (rare, so logged here on Zenoh's thread: the way back was unsaid, a soak trial found only the loss)
        if sample.kind == zenoh.SampleKind.PUT:
            self.watch.edge_up()
            if self._edge_lost_at is not None:
                log.warning(
                    "edge_infer back after %.1f s: frames go to the edge again", time.monotonic() - self._edge_lost_at
                )
                self._edge_lost_at = None
        else:
            self.watch.edge_down()
            self._edge_lost_at = time.monotonic()
            log.warning("edge_infer gone (its liveliness token): the whole chain runs on board until it is back")
            self.window.clear(recover=True)  # the frames it held: the main loop computes them on board
            if self.pacer is not None:
                self.pacer.forget()

    def serve(self, stop: threading.Event) -> None:
        """Take a frame only with a credit in hand: the ring keeps the newest one while the edge catches up.
        With `overlap_stage1`, the next frame's stage 1 runs on the look-ahead thread while this frame's
        network runs, when that frame would go out as soon as it is made (`may_run_ahead`, checked there
        just before it starts)."""

        def give_up() -> bool:  # the edge is gone (or an answer overdue): stop waiting for credits
            return self.watch.on_board(self.window.oldest_age_secs())

        ahead: Future[Stage1Output | _Skipped | None] | None = None
        try:
            while self.window.acquire(stop, abandon=give_up, recover=lambda: not self.watch.alive):
                self._recover_orphans()
                s1: Stage1Output | _Skipped | None = _SKIPPED
                if ahead is not None:  # stage 1 of this frame may have run while the last one's network did
                    s1, ahead = result_of(ahead), None  # (a stop signal must still run its handler)
                    self.stage1_ahead_frames += isinstance(s1, Stage1Output)
                if isinstance(s1, _Skipped):
                    # Start when this frame would reach the edge as it becomes free (the camera ring keeps
                    # the newest frame meanwhile): waiting here is free, waiting in the edge's queue is latency.
                    # (none on board: without the edge the frame crosses no link and waits for no edge)
                    delay = self.pacer.start_delay_secs() if self.pacer is not None and self.watch.usable else 0.0
                    if delay > 0 and stop.wait(min(delay, self.settings.edge_answer_timeout_secs)):
                        break
                    s1 = self._stage1(stop)
                if s1 is None:
                    if stop.is_set():
                        break
                    continue  # frames to recover first, or a frame stage 1 refused (counted)
                if self.ahead is not None:
                    # timed to end as this frame's network does: earlier, it would only age waiting for it
                    lead = max(0.0, self.rest_secs - self.stage1_secs)
                    ahead = self.ahead.submit(self._stage1_ahead, stop, lead)
                self.guard.run("frame", s1.frame.image.nbytes, partial(self.process, s1))
        finally:
            self.halt.set()
            if ahead is not None:
                ahead.cancel()

    def _stage1(self, stop: threading.Event) -> Stage1Output | None:
        """The newest frame's stage 1 (None: stopping, orphans to recover first, or a frame it refused)."""
        # self.halt: serve() ended (the look-ahead thread must not wait for frames then)
        wake = lambda: self.window.has_orphans or self.halt.is_set()  # noqa: E731
        if (frame := self.frames.take(stop, wake=wake, fresh_fraction=self.settings.fresh_frame_fraction)) is None:
            return None
        try:
            return robot_stage1(frame, detector=self.detector, tracker=self.tracker)
        except Exception as exc:  # counted and logged like any bad input; the next frame goes on
            self.guard.reject("frame", frame.image.nbytes, exc)
            return None

    def _stage1_ahead(self, stop: threading.Event, after_secs: float) -> Stage1Output | _Skipped | None:
        """On the look-ahead thread: the next frame's stage 1 in `after_secs`, if it may run ahead then
        (else _SKIPPED: the main loop takes the frame itself, paced and fresh)."""
        if stop.wait(after_secs) or self.halt.is_set():
            return None
        w = self.window
        pace = self.pacer.start_delay_secs() if self.pacer is not None else 0.0
        if not may_run_ahead(
            in_flight=w.in_flight,
            capacity=w.capacity,
            pace_delay_secs=pace,
            edge_alive=self.watch.usable,
        ):
            return _SKIPPED
        return self._stage1(stop)

    def _recover_orphans(self) -> None:
        """Compute on board the frames whose edge vanished before answering (their Features are kept)."""
        orphans = self.window.take_orphans()
        for features in orphans:
            if self.guard.run("recovered frame", 0, partial(self._finish_on_board, features)):
                self.recovered_frames += 1
        if orphans:
            log.warning("edge vanished with %d frame(s) unanswered: computed on board", len(orphans))

    def process(self, s1: Stage1Output) -> None:
        """One frame after stage 1: head(k), Features out (raises on input the maths cannot take; the
        guard counts it)."""
        frame = s1.frame
        if self.watch.on_board(self.window.oldest_age_secs()) and not self.watch.trial_due():
            # frames sent to an edge whose token is gone are recomputed here; an answer that is merely
            # overdue may still come, so those are dropped
            self.window.clear(recover=not self.watch.alive)
            # the older frames first: slam refuses a frame older than one it has fused (a trial lost the
            # recovered frame 2 kills in 4, computed after the next one: 'out of order')
            self._recover_orphans()
            self.on_board(s1)
            return
        if self.watch.usable:  # (not a trial frame sent to an edge whose answers are overdue)
            self._edge_back()
        split = self.state.get()  # changes apply from the next frame; each message says its k
        tags, timings = robot_head(s1, net=self.net, k=split.k, codec=split.codec, tracker=self.tracker)
        network_ms, compute_secs = self._pace(split.k, len(tags), timings)
        stage1 = timings.detect_secs + timings.warp_secs
        self.stage1_secs += 0.3 * (stage1 - self.stage1_secs)
        self.rest_secs += 0.3 * (compute_secs - stage1 - self.rest_secs)
        features = self._features(frame, tags, split.k, split.codec, compute_secs)
        wire = encode(features)
        sent_nanos, sent_at = time.time_ns(), self._clock()
        key = frame.capture_nanos  # unique and in send order across camera sessions (see _on_poses)
        with self._expected_lock:  # (before the put: the answer may come before send returns)
            self._expected[key] = None
            while len(self._expected) > EXPECTED_ANSWERS:
                self._expected.popitem(last=False)
        self.window.send(key, lambda: self.pub.put(wire), keep=features, gone=lambda: not self.watch.alive)
        if self.pacer is not None:
            self.pacer.sent(key, tags=len(tags), robot_secs=compute_secs, payload_bytes=len(wire), sent_at=sent_at)
        sent = FrameSent(robot_id=self.settings.robot_id, seq=frame.seq, sent_nanos=sent_nanos, payload_bytes=len(wire))
        self.sent_pub.put(encode(sent))
        fixed_ms = (timings.detect_secs + timings.warp_secs) * 1e3
        self.estimator.observe(k=split.k, tags=len(tags), network_ms=network_ms, fixed_ms=fixed_ms)
        self._publish_profile()

    def _pace(self, k: int, n_tags: int, timings: RobotTimings) -> tuple[float, float]:
        """Emulate the robot's CPU: the latency really grows to gamma x the reference, not just a model.
        Returns (the head's network ms, the frame's robot compute seconds)."""
        network_ms = n_tags * self.per_tag_ms[k] if self.emulated else timings.head_secs * 1e3
        target = self.settings.gamma * (timings.detect_secs + timings.warp_secs + network_ms / 1e3)
        if target > timings.total_secs:
            time.sleep(target - timings.total_secs)
        return network_ms, max(target, timings.total_secs)

    def _features(
        self, frame: Frame, tags: list[TagFeature], k: int, codec: CodecName, compute_secs: float
    ) -> Features:
        return Features(
            robot_id=self.settings.robot_id,
            seq=frame.seq,
            capture_nanos=frame.capture_nanos,
            publish_nanos=time.time_ns(),
            split_k=k,
            codec=codec,
            intrinsics=frame.intrinsics,
            robot_compute_secs=compute_secs,
            tags=tags,
        )

    def _publish_profile(self) -> None:
        if time.monotonic() - self.last_profile < self.settings.profile_period_secs:
            return
        self.last_profile = time.monotonic()
        profile = self.estimator.message(
            robot_id=self.settings.robot_id,
            side="robot",
            stamp_nanos=time.time_ns(),
            factor=self.settings.gamma,
            overlapped=self.ahead is not None,
            frame_interval_ms=self.camera.interval_ms(),
        )
        self.compute_pub.put(encode(profile))

    def on_board(self, s1: Stage1Output) -> None:
        """The whole chain here (k = 7, PnP) while the edge is gone: TagPoses published by the robot."""
        frame = s1.frame
        k = N_CUTS - 1
        tags, timings = robot_head(s1, net=self.net, k=k, codec="fp32", tracker=self.tracker)
        _, compute_secs = self._pace(k, len(tags), timings)  # the robot's CPU, as emulated for the split
        self._finish_on_board(self._features(frame, tags, k, "fp32", compute_secs))
        said = self.on_board_count.add(time.monotonic())
        count = self.on_board_count
        if said == "first":
            log.warning(
                "edge unavailable (no edge_infer token, or an answer overdue): computing frames on board, "
                "the first now (%d before in this run; a count follows every %g s while it lasts; the edge's "
                "router: %s)",
                count.total - 1,
                count.every_secs,
                ", ".join(self.settings.zenoh.connect) or "none configured",
            )
        elif said == "running":
            log.warning(
                "edge still unavailable: %d frames computed on board in this outage so far (%d in the last "
                "%g s or more; %d in this run)",
                count.spell,
                count.since_said,
                count.every_secs,
                count.total,
            )

    @property
    def on_board_frames(self) -> int:
        """Frames computed on board (the whole chain here) in this run."""
        return self.on_board_count.total

    def _edge_back(self) -> None:
        """A frame goes to the edge again: say how many the outage computed on board, once."""
        if spell := self.on_board_count.end():
            log.warning(
                "edge back: %d frames computed on board during the outage (%d in this run)",
                spell,
                self.on_board_count.total,
            )

    def _finish_on_board(self, features: Features) -> bool:
        """The edge's half of one frame here (any k: the robot holds the whole network): TagPoses out."""
        poses = edge_step(
            features,
            net=self.net,
            tag_map=self.tag_map,
            receive_nanos=features.publish_nanos,
            previous_receive_nanos=0,
            payload_bytes=0,  # nothing crossed the link
            tracked_max_reprojection_px=self.settings.tracking.max_refined_reprojection_px,
            fusion=self.fusion,
        )
        self.poses_pub.put(encode(poses.model_copy(update={"link": None})))  # nothing crossed the link
        return True

    def close(self) -> None:
        """Undeclare everything and log the run's counts."""
        if self.ahead is not None:
            self.ahead.shutdown(wait=True, cancel_futures=True)
        self.detector.close()
        self.token.undeclare()
        if self.acks is not None:
            self.acks.undeclare()
        self.queryable.undeclare()
        self.stats.undeclare()
        self.edge_token.undeclare()
        self.guard.close()  # the last interval's rejections said, the counts written
        log.info(
            "robot_infer: %s, %d credits expired, %d frames on board in %d edge outages and %d stalls; stage 1: %s",
            self.guard.stats(),
            self.window.expired,
            self.on_board_frames,
            self.watch.outages,
            self.watch.stalls,
            self.detector.counts,
        )
