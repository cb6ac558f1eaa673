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
from shared.model.profile import calibrate_cumulative_ms, calibrate_pnp_ms, warm_up
from shared.model.weights import load_keypoint_fusion, load_model
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
    model = load_model(settings.weights)
    fusion = load_keypoint_fusion(settings.weights) if settings.fuse_corners else None
    warm_up(model, bf16=settings.bf16)
    emulated = settings.emulated_ms_per_tag_by_k
    estimator = ComputeEstimator(
        emulated or tail_per_tag_ms(calibrate_cumulative_ms(model, bf16=settings.bf16), pnp_ms=calibrate_pnp_ms())
    )
    last_profile = 0.0
    tag_map = (
        load_tag_map(settings.tag_map) if settings.tag_map else TagMapFile(default_size_m=settings.default_tag_size_m)
    )
    rid = settings.robot_id
    # A short queue: when the edge is the bottleneck, backpressure reaches robot_infer (its publisher
    # blocks) and the robot's latest-only frame ring drops stale frames, so latency stays bounded.
    # Arrival is stamped in the subscriber callback, so a frame's transport time excludes the time it
    # then waits for the edge (the controller fits the link to it; queueing is not the link's).
    # Probes and Features share the uplink: one arrival clock tells each message what was ahead of it.
    inbox: queue.Queue[tuple[int, int, bytes]] = queue.Queue(maxsize=settings.queue_depth)
    arrivals = ArrivalClock()

    def on_features(sample: zenoh.Sample) -> None:
        item = (*arrivals.stamp(), sample.payload.to_bytes())
        while not stop.is_set():  # a full inbox blocks Zenoh's delivery: backpressure up to the robot
            try:
                inbox.put(item, timeout=0.1)
                return
            except queue.Full:
                continue

    sub = session.declare_subscriber(keys.features(rid), on_features)
    pub = declare_tensor_publisher(session, keys.tag_poses(rid), TagPoses.SCHEMA)
    compute_pub = session.declare_publisher(keys.compute(rid, "edge"), encoding=encoding_for(ComputeProfile.SCHEMA))
    echo = (
        serve_echo(session, keys.echo(rid), max_bytes=settings.max_payload_bytes, arrivals=arrivals)
        if settings.serve_echo
        else None
    )
    token = session.liveliness().declare_token(keys.alive(rid, "edge_infer"))
    viz = make_viz(settings.rerun, service="edge_infer", run_dir=settings.run_dir)
    guard = InputGuard("edge_infer")
    stats = serve_stats(session, keys.stats(rid, "edge_infer"), guard)

    def process(received: int, previous: int, payload: bytes) -> None:
        """One Features message: decode, tail + PnP, TagPoses out (raises on bad input; the guard counts it)."""
        nonlocal last_profile
        features = decode(payload, Features, max_bytes=settings.max_payload_bytes)
        poses = edge_step(
            features,
            model=model,
            tag_map=tag_map,
            receive_nanos=received,
            previous_receive_nanos=previous,
            payload_bytes=len(payload),
            bf16=settings.bf16,
            fusion=fusion,
            min_compute_secs=len(features.tags) * emulated[features.split_k] / 1e3 if emulated else 0.0,
        )
        pub.put(encode(poses))
        viz.tag_poses(poses)
        # An emulated edge publishes its fixed profile (reality only pads up to it).
        live_ms = poses.timings.edge_compute_secs * 1e3
        network_ms = len(poses.tags) * emulated[poses.split_k] if emulated else live_ms
        estimator.observe(k=poses.split_k, tags=len(poses.tags), network_ms=network_ms)
        if time.monotonic() - last_profile >= settings.profile_period_secs:
            last_profile = time.monotonic()
            compute_pub.put(encode(estimator.message(robot_id=rid, side="edge", stamp_nanos=time.time_ns())))

    log.info("edge_infer ready")
    try:
        while not stop.is_set():
            try:
                received, previous, payload = inbox.get(timeout=0.05)
            except queue.Empty:
                continue
            guard.run("features", len(payload), lambda: process(received, previous, payload))  # noqa: B023
    finally:
        sub.undeclare()
        token.undeclare()
        if echo is not None:
            echo.undeclare()
        viz.close()
        stats.undeclare()
        log.info("edge_infer: %s", guard.stats())
