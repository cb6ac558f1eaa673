"""edge_infer loop: Features -> tail(k) -> keypoints in the image -> PnP -> TagPoses, every frame."""

from __future__ import annotations

import logging
import queue
import threading
import time

import torch
import zenoh

from services.edge_infer.settings import EdgeInferSettings
from shared.control.compute import ComputeEstimator, tail_per_tag_ms
from shared.model.profile import calibrate_pnp_ms
from shared.model.runtime import calibrate_cumulative_ms, load_split_net
from shared.model.weights import load_keypoint_fusion
from shared.perception.split import edge_step
from shared.runtime.guard import InputGuard, serve_stats
from shared.transport.probe import ArrivalClock, serve_echo
from shared.transport.session import declare_tensor_publisher, encoding_for
from shared.vision.tagmap import TagMapFile, load_tag_map
from shared.viz.recording import make_viz
from shared.wire import keys
from shared.wire.messages import ComputeProfile, Features, TagPoses, decode, encode

log = logging.getLogger(__name__)


def run(settings: EdgeInferSettings, *, session: zenoh.Session, stop: threading.Event) -> None:
    """Serve until `stop` is set. Malformed or inconsistent Features are rejected, counted and logged."""
    torch.set_num_threads(settings.threads)
    node = EdgeInfer(settings, session, stop)
    log.info("edge_infer ready: precision=%s (configured %s)", node.net.precision, settings.precision)
    try:
        node.serve(stop)
    finally:
        node.close()


class EdgeInfer:
    """The edge side: its model, tag map, compute estimate, inbox and Zenoh endpoints."""

    def __init__(self, settings: EdgeInferSettings, session: zenoh.Session, stop: threading.Event) -> None:
        self.settings = s = settings
        self.stop = stop
        self.net = load_split_net(s.weights, s.precision, threads=s.threads)
        self.fusion = load_keypoint_fusion(s.weights) if s.fuse_corners else None
        self.net.warm_up(0, max_batch=6)
        self.emulated = s.emulated_ms_per_tag_by_k
        self.estimator = ComputeEstimator(
            self.emulated or tail_per_tag_ms(calibrate_cumulative_ms(self.net), pnp_ms=calibrate_pnp_ms())
        )
        self.last_profile = 0.0
        self.tag_map = load_tag_map(s.tag_map) if s.tag_map else TagMapFile(default_size_m=s.default_tag_size_m)
        rid = s.robot_id
        # A short queue: when the edge is the bottleneck, backpressure reaches robot_infer (its publisher
        # blocks) and the robot's latest-only frame ring drops stale frames, so latency stays bounded.
        # Arrival is stamped in the subscriber callback, so a frame's transport time excludes the time it
        # then waits for the edge (the controller fits the link to it; queueing is not the link's).
        # Probes and Features share the uplink: one arrival clock tells each message what was ahead of it.
        self.inbox: queue.Queue[tuple[int, int, bytes]] = queue.Queue(maxsize=s.queue_depth)
        self.arrivals = ArrivalClock()
        self.sub = session.declare_subscriber(keys.features(rid), self._on_features)
        self.pub = declare_tensor_publisher(session, keys.tag_poses(rid), TagPoses.SCHEMA)
        self.compute_pub = session.declare_publisher(
            keys.compute(rid, "edge"), encoding=encoding_for(ComputeProfile.SCHEMA)
        )
        self.echo = (
            serve_echo(session, keys.echo(rid), max_bytes=s.max_payload_bytes, arrivals=self.arrivals)
            if s.serve_echo
            else None
        )
        self.token = session.liveliness().declare_token(keys.alive(rid, "edge_infer"))
        self.viz = make_viz(s.rerun, service="edge_infer", run_dir=s.run_dir)
        self.guard = InputGuard("edge_infer")
        self.stats = serve_stats(session, keys.stats(rid, "edge_infer"), self.guard)

    def _on_features(self, sample: zenoh.Sample) -> None:
        item = (*self.arrivals.stamp(), sample.payload.to_bytes())
        while not self.stop.is_set():  # a full inbox blocks Zenoh's delivery: backpressure up to the robot
            try:
                self.inbox.put(item, timeout=0.1)
                return
            except queue.Full:
                continue

    def serve(self, stop: threading.Event) -> None:
        """Handle queued Features until `stop`; each goes through the input guard."""
        while not stop.is_set():
            try:
                received, previous, payload = self.inbox.get(timeout=0.05)
            except queue.Empty:
                continue
            self.guard.run("features", len(payload), lambda: self.process(received, previous, payload))  # noqa: B023

    def process(self, received: int, previous: int, payload: bytes) -> None:
        """One Features message: decode, tail + PnP, TagPoses out (raises on bad input; the guard counts it)."""
        s, emulated = self.settings, self.emulated
        features = decode(payload, Features, max_bytes=s.max_payload_bytes)
        poses = edge_step(
            features,
            net=self.net,
            tag_map=self.tag_map,
            receive_nanos=received,
            previous_receive_nanos=previous,
            payload_bytes=len(payload),
            fusion=self.fusion,
            tracked_max_reprojection_px=self.settings.tracked_max_reprojection_px,
            min_compute_secs=len(features.tags) * emulated[features.split_k] / 1e3 if emulated else 0.0,
        )
        self.pub.put(encode(poses))
        self.viz.tag_poses(poses)
        # An emulated edge publishes its fixed profile (reality only pads up to it).
        live_ms = poses.timings.edge_compute_secs * 1e3
        network_ms = len(poses.tags) * emulated[poses.split_k] if emulated else live_ms
        self.estimator.observe(k=poses.split_k, tags=len(poses.tags), network_ms=network_ms)
        if time.monotonic() - self.last_profile >= s.profile_period_secs:
            self.last_profile = time.monotonic()
            message = self.estimator.message(robot_id=s.robot_id, side="edge", stamp_nanos=time.time_ns())
            self.compute_pub.put(encode(message))

    def close(self) -> None:
        """Undeclare everything and log the run's counts."""
        self.sub.undeclare()
        self.token.undeclare()
        if self.echo is not None:
            self.echo.undeclare()
        self.viz.close()
        self.stats.undeclare()
        log.info("edge_infer: %s", self.guard.stats())
