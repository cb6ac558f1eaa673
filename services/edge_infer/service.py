"""edge_infer loop: Features -> tail(k) -> keypoints in the image -> PnP -> TagPoses, for every robot it serves.

One process is one worker of the edge tier. It serves one robot (the default), a list, or every live
robot; several workers share the robots through their liveliness tokens (shared.transport.fleet).
Each served robot is a `Lane`: its Features subscriber, TagPoses and ComputeProfile publishers, probe
echo, liveliness token (what robot_infer waits for), arrival clock, compute estimate and tag map.
Lanes are opened and closed by the main loop when the assignment changes (Zenoh's callbacks only
record the change), and Features of several robots waiting together share one tail pass.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import torch
import zenoh

from services.edge_infer.settings import EdgeInferSettings
from shared.control.compute import ComputeEstimator, tail_per_tag_ms
from shared.model.profile import calibrate_pnp_ms
from shared.model.runtime import calibrate_tail_ms, load_split_net
from shared.model.views import with_views
from shared.model.weights import load_keypoint_fusion
from shared.perception.split import EdgeInput, check_features, edge_batch
from shared.runtime.guard import InputGuard, persist_input_counts, serve_stats
from shared.transport.fleet import FleetView
from shared.transport.probe import ArrivalClock, serve_echo
from shared.transport.session import declare_tensor_publisher, encoding_for
from shared.vision.tagmap import TagMapFile, load_tag_map
from shared.viz.recording import make_viz
from shared.wire import keys
from shared.wire.messages import ComputeProfile, Features, TagPoses, decode_for_robot, encode, refuse_future_capture

log = logging.getLogger(__name__)


def run(settings: EdgeInferSettings, *, session: zenoh.Session, stop: threading.Event) -> None:
    """Serve until `stop` is set. Malformed or inconsistent Features are rejected, counted and logged."""
    torch.set_num_threads(settings.threads)
    node = EdgeInfer(settings, session, stop)
    log.info(
        "edge_infer worker %s ready: precision=%s (configured %s) views=%d, robots %s",
        settings.worker_id,
        node.net.precision,
        settings.precision,
        getattr(node.net, "views", 1),  # what runs, not only what was asked
        settings.robots or [settings.robot_id],
    )
    try:
        node.serve(stop)
    finally:
        node.close()


@dataclass
class Lane:
    """One robot served by this worker: its endpoints and its per-robot state."""

    robot_id: str
    tag_map: TagMapFile
    estimator: ComputeEstimator
    arrivals: ArrivalClock
    pub: zenoh.Publisher
    compute_pub: zenoh.Publisher
    endpoints: list[Any] = field(default_factory=list)  # subscriber, queryables, token: undeclared in reverse
    last_profile: float = 0.0
    frames: int = 0


def _on_token(
    sample: zenoh.Sample,
    parse: Callable[[str], str],
    up: Callable[[str], None],
    down: Callable[[str], None],
    guard: InputGuard,
) -> None:
    """A liveliness token appeared (up) or went (down); a key that does not parse is counted and logged."""
    try:
        ident = parse(str(sample.key_expr))
    except ValueError as exc:
        guard.reject("liveliness", 0, exc)
        return
    (up if sample.kind == zenoh.SampleKind.PUT else down)(ident)


@dataclass(frozen=True)
class _Item:
    robot_id: str
    received: int
    previous: int
    payload: bytes


class EdgeInfer:
    """One edge worker: its model, its lanes (one per robot served), the inbox and the fleet view."""

    def __init__(self, settings: EdgeInferSettings, session: zenoh.Session, stop: threading.Event) -> None:
        self.settings = s = settings
        self.session = session
        self.stop = stop
        one_view = load_split_net(s.weights, s.precision, threads=s.threads)
        self.net = with_views(one_view, s.views)
        self.fusion = load_keypoint_fusion(s.weights) if s.fuse_corners else None
        self.net.warm_up(0, max_batch=6)
        # an emulated edge CPU's fixed profile is one view's: from cut 0 (the whole network, PnP included:
        # the profile does not separate them) it runs once per view
        emulated = s.emulated_ms_per_tag_by_k
        self.emulated = [emulated[0] * s.views, *emulated[1:]] if emulated else None
        self.per_tag_ms = self.emulated or tail_per_tag_ms(
            calibrate_tail_ms(one_view), pnp_ms=calibrate_pnp_ms(), views=s.views
        )
        self.default_map = load_tag_map(s.tag_map) if s.tag_map else TagMapFile(default_size_m=s.default_tag_size_m)
        # Every robot's own map is read now: a bad file stops the worker at start, not when the robot arrives.
        self.tag_maps = {robot: load_tag_map(path) for robot, path in s.tag_maps.items()}
        # A short queue: when the edge is the bottleneck, backpressure reaches robot_infer (its publisher
        # blocks) and the robot's latest-only frame ring drops stale frames, so latency stays bounded.
        # Arrival is stamped in the subscriber callback, so a frame's transport time excludes the time it
        # then waits for the edge (the controller fits the link to it; queueing is not the link's).
        # Probes and Features of one robot share its uplink: one arrival clock per robot.
        served = len(s.robots) if isinstance(s.robots, list) else (8 if s.robots == "*" else 1)
        self.inbox: queue.Queue[_Item] = queue.Queue(maxsize=s.queue_depth * served)
        self.lanes: dict[str, Lane] = {}
        self.guard = InputGuard("edge_infer")
        persist_input_counts(self.guard, s.run_dir, label=s.worker_id)
        self.viz = make_viz(s.rerun, service="edge_infer", run_dir=s.run_dir)
        self.dropped_unassigned = 0
        self.batches = 0
        self.batched_messages = 0
        # The fleet: this worker's token, the other workers', the robots' (with robots = "*").
        self._wanted: frozenset[str] | None = None
        self._wanted_lock = threading.Lock()
        fixed = None if s.robots == "*" else (s.robots or [s.robot_id])
        self.tier = s.tier or (s.robot_id if s.robots is None else "fleet")
        self.fleet = FleetView(s.worker_id, robots=fixed, on_change=self._on_assignment)
        liveliness = session.liveliness()
        for reply in liveliness.get(keys.edge_workers(self.tier), timeout=2.0):  # the workers already there
            if reply.ok is not None:
                _on_token(reply.ok, keys.worker_of, self.fleet.worker_up, self.fleet.worker_down, self.guard)
        self.worker_token = liveliness.declare_token(keys.edge_worker(self.tier, s.worker_id))
        self.workers_sub = liveliness.declare_subscriber(keys.edge_workers(self.tier), self._on_worker, history=True)
        self.robots_sub = (
            liveliness.declare_subscriber(
                keys.for_every_robot(keys.alive("any", "robot_infer")), self._on_robot, history=True
            )
            if fixed is None
            else None
        )
        self.fleet.refresh()
        self._apply_assignment()  # the lanes exist before serve() starts (tests wait for their tokens)

    # Zenoh callbacks: bookkeeping only; lanes are opened and closed on the main loop.
    def _on_worker(self, sample: zenoh.Sample) -> None:
        _on_token(sample, keys.worker_of, self.fleet.worker_up, self._worker_gone, self.guard)

    def _worker_gone(self, worker: str) -> None:
        log.warning("edge worker %s is gone: its robots move", worker)
        self.fleet.worker_down(worker)

    def _on_robot(self, sample: zenoh.Sample) -> None:
        _on_token(sample, keys.robot_of, self.fleet.robot_up, self.fleet.robot_down, self.guard)

    def _on_assignment(self, robots: frozenset[str]) -> None:
        with self._wanted_lock:
            self._wanted = robots

    def _on_features(self, robot_id: str, arrivals: ArrivalClock, sample: zenoh.Sample) -> None:
        item = _Item(robot_id, *arrivals.stamp(), sample.payload.to_bytes())
        while not self.stop.is_set():  # a full inbox blocks Zenoh's delivery: backpressure up to the robot
            try:
                self.inbox.put(item, timeout=0.1)
                return
            except queue.Full:
                continue

    # Lanes.
    def _apply_assignment(self) -> None:
        with self._wanted_lock:
            wanted, self._wanted = self._wanted, None
        if wanted is None:
            return
        for robot in sorted(set(self.lanes) - wanted):
            self._close_lane(self.lanes.pop(robot))
            log.info("worker %s no longer serves %s", self.settings.worker_id, robot)
        for robot in sorted(wanted - set(self.lanes)):
            self.lanes[robot] = self._open_lane(robot)
            log.info("worker %s serves %s (workers %s)", self.settings.worker_id, robot, sorted(self.fleet.workers))

    def _open_lane(self, robot: str) -> Lane:
        s = self.settings
        session = self.session
        lane = Lane(
            robot,
            self.tag_maps.get(robot, self.default_map),
            ComputeEstimator(self.per_tag_ms),
            ArrivalClock(),
            pub=declare_tensor_publisher(session, keys.tag_poses(robot), TagPoses.SCHEMA),
            compute_pub=session.declare_publisher(
                keys.compute(robot, "edge"), encoding=encoding_for(ComputeProfile.SCHEMA)
            ),
        )
        arrivals = lane.arrivals
        lane.endpoints.append(
            session.declare_subscriber(keys.features(robot), lambda sample: self._on_features(robot, arrivals, sample))
        )
        if s.serve_echo:
            lane.endpoints.append(
                serve_echo(
                    session,
                    keys.echo(robot),
                    max_bytes=s.max_payload_bytes,
                    arrivals=arrivals,
                    refused=self.guard.reject,
                )
            )
        lane.endpoints.append(
            serve_stats(session, keys.stats(robot, "edge_infer"), self.guard, lambda: self.counters(lane))
        )
        # Last: robot_infer sends to the edge once this token is there.
        lane.endpoints.append(session.liveliness().declare_token(keys.alive(robot, "edge_infer")))
        return lane

    @staticmethod
    def _close_lane(lane: Lane) -> None:
        for endpoint in reversed(lane.endpoints):  # the token first: the robot stops sending here
            endpoint.undeclare()
        lane.pub.undeclare()
        lane.compute_pub.undeclare()

    def counters(self, lane: Lane) -> dict[str, object]:
        """Served on the lane's stats key with the input counters."""
        return {
            "worker": self.settings.worker_id,
            "tier": self.tier,
            "workers": sorted(self.fleet.workers),
            "robots_served": sorted(self.lanes),
            "frames_for_robot": lane.frames,
            "reassignments": self.fleet.reassignments,
            "dropped_unassigned": self.dropped_unassigned,
            "batches": self.batches,
            "batched_messages": self.batched_messages,
        }

    # The loop.
    def serve(self, stop: threading.Event) -> None:
        """Handle queued Features until `stop`: every waiting message of every robot in one batch."""
        while not stop.is_set():
            self._apply_assignment()
            try:
                first = self.inbox.get(timeout=0.05)
            except queue.Empty:
                continue
            items = [first]
            while len(items) < self.settings.batch_max_messages:
                try:
                    items.append(self.inbox.get_nowait())
                except queue.Empty:
                    break
            self.process(items)

    def process(self, items: list[_Item]) -> None:
        """Decode and check each message (a bad one is counted and dropped alone), run the good ones as
        one batch, publish each result; a message whose tensors turn out non-finite is refused alone."""
        decoded: list[tuple[Lane, EdgeInput]] = []
        for item in items:
            lane = self.lanes.get(item.robot_id)
            if lane is None:  # arrived just before its robot moved to another worker: its credit expires
                self.dropped_unassigned += 1
                continue
            try:
                decoded.append((lane, self._decode(item, lane)))
            except Exception as exc:  # the guard's point: counted, logged, the others go on
                self.guard.reject("features", len(item.payload), exc)
        if not decoded:
            return
        inputs = [p for _, p in decoded]
        try:
            results = edge_batch(
                inputs,
                net=self.net,
                fusion=self.fusion,
                tracked_max_reprojection_px=self.settings.tracked_max_reprojection_px,
            )
        except Exception as exc:  # the tail itself failed on checked inputs (not expected): counted per message
            for p in inputs:
                self.guard.reject("features", p.payload_bytes, exc)
            return
        if len(decoded) > 1:
            self.batches += 1
            self.batched_messages += len(decoded)
        for (lane, edge_input), result in zip(decoded, results, strict=True):
            if isinstance(result, Exception):
                self.guard.reject("features", edge_input.payload_bytes, result)
            else:
                self.guard.run("features", edge_input.payload_bytes, partial(self._publish, lane, result))

    def _decode(self, item: _Item, lane: Lane) -> EdgeInput:
        s, emulated = self.settings, self.emulated
        features = decode_for_robot(item.payload, Features, item.robot_id, max_bytes=s.max_payload_bytes)
        refuse_future_capture(features, now_nanos=time.time_ns(), ahead_nanos=round(s.max_capture_ahead_secs * 1e9))
        check_features(features)
        min_secs = len(features.tags) * emulated[features.split_k] / 1e3 if emulated else 0.0
        return EdgeInput(features, item.received, item.previous, len(item.payload), lane.tag_map, min_secs)

    def _publish(self, lane: Lane, poses: TagPoses) -> None:
        s, emulated = self.settings, self.emulated
        lane.pub.put(encode(poses))
        lane.frames += 1
        self.viz.tag_poses(poses)
        # An emulated edge publishes its fixed profile (reality only pads up to it).
        live_ms = poses.timings.edge_compute_secs * 1e3
        network_ms = len(poses.tags) * emulated[poses.split_k] if emulated else live_ms
        lane.estimator.observe(k=poses.split_k, tags=len(poses.tags), network_ms=network_ms)
        if time.monotonic() - lane.last_profile >= s.profile_period_secs:
            lane.last_profile = time.monotonic()
            message = lane.estimator.message(robot_id=lane.robot_id, side="edge", stamp_nanos=time.time_ns())
            lane.compute_pub.put(encode(message))

    def close(self) -> None:
        """Undeclare everything and log the run's counts."""
        for undeclare in (self.workers_sub, self.robots_sub):
            if undeclare is not None:
                undeclare.undeclare()
        for lane in self.lanes.values():
            self._close_lane(lane)
        self.worker_token.undeclare()
        self.viz.close()
        self.guard.close()  # the last interval's rejections said, the counts written
        log.info(
            "edge_infer %s: %s, %d batches of %d messages, %d dropped after a reassignment",
            self.settings.worker_id,
            self.guard.stats(),
            self.batches,
            self.batched_messages,
            self.dropped_unassigned,
        )
