"""robot_infer loop: newest frame -> stage 1 + head(k) -> Features, with the split set live over Zenoh."""

from __future__ import annotations

import contextlib
import logging
import threading
import time

import torch
import zenoh

from services.robot_infer.settings import RobotInferSettings
from shared.control.compute import ComputeEstimator, head_per_tag_ms
from shared.model.profile import calibrate_cumulative_ms, warm_up
from shared.model.weights import load_model
from shared.perception.split import robot_step
from shared.runtime.guard import InputGuard, serve_stats
from shared.transport.flow import InFlightWindow
from shared.transport.session import declare_latest_subscriber, declare_tensor_publisher, encoding_for, next_sample
from shared.transport.split_control import SplitState, serve_split
from shared.vision.detector import TagDetector
from shared.wire import keys
from shared.wire.codec import WireError
from shared.wire.messages import ComputeProfile, Features, Frame, FrameSent, SplitConfig, TagPoses, decode, encode

log = logging.getLogger(__name__)


def run(settings: RobotInferSettings, *, session: zenoh.Session, stop: threading.Event) -> None:
    """Process frames until `stop` is set."""
    torch.set_num_threads(settings.threads)
    model = load_model(settings.weights)
    warm_up(model, bf16=settings.bf16)
    emulated = settings.emulated_ms_per_tag_by_k
    per_tag_ms = emulated or head_per_tag_ms(calibrate_cumulative_ms(model, bf16=settings.bf16))
    estimator = ComputeEstimator(per_tag_ms)
    detector = TagDetector(settings.detector)
    state = SplitState(SplitConfig(k=settings.split_k, codec=settings.codec, pinned=False, source="default"))
    rid = settings.robot_id
    sub = declare_latest_subscriber(session, keys.frames(rid))
    pub = declare_tensor_publisher(session, keys.features(rid), Features.SCHEMA)
    compute_pub = session.declare_publisher(keys.compute(rid, "robot"), encoding=encoding_for(ComputeProfile.SCHEMA))
    sent_pub = session.declare_publisher(keys.frame_sent(rid), encoding=encoding_for(FrameSent.SCHEMA))
    queryable = serve_split(session, keys.split(rid), state)
    window = InFlightWindow(settings.max_in_flight, timeout_secs=settings.in_flight_timeout_secs)

    def on_poses(sample: zenoh.Sample) -> None:
        # A bad TagPoses is edge_infer's problem to report; that frame's credit expires on its own.
        with contextlib.suppress(WireError):
            window.done(decode(sample.payload.to_bytes(), TagPoses).seq)

    acks = session.declare_subscriber(keys.tag_poses(rid), on_poses) if settings.max_in_flight else None
    token = session.liveliness().declare_token(keys.alive(rid, "robot_infer"))
    guard = InputGuard("robot_infer")
    stats = serve_stats(session, keys.stats(rid, "robot_infer"), guard)
    last_profile = 0.0

    def process(payload: bytes) -> None:
        """One frame: decode, stage 1 + head(k), Features out (raises on bad input; the guard counts it)."""
        nonlocal last_profile
        frame = decode(payload, Frame, max_bytes=settings.max_payload_bytes)
        split = state.get()  # changes apply from the next frame; each message says its k
        tags, timings = robot_step(
            frame, detector=detector, model=model, k=split.k, codec=split.codec, bf16=settings.bf16
        )
        # Emulate the robot's CPU: the latency really grows to gamma x the reference, not just a model.
        network_ms = len(tags) * per_tag_ms[split.k] if emulated else timings.head_secs * 1e3
        fixed_secs = timings.detect_secs + timings.warp_secs
        target = settings.gamma * (fixed_secs + network_ms / 1e3)
        if target > timings.total_secs:
            time.sleep(target - timings.total_secs)
        compute = max(target, timings.total_secs)
        wire = encode(
            Features(
                robot_id=rid,
                seq=frame.seq,
                capture_nanos=frame.capture_nanos,
                publish_nanos=time.time_ns(),
                split_k=split.k,
                codec=split.codec,
                intrinsics=frame.intrinsics,
                robot_compute_secs=compute,
                tags=tags,
            )
        )
        sent_nanos = time.time_ns()
        window.send(frame.seq, lambda: pub.put(wire))
        sent_pub.put(encode(FrameSent(robot_id=rid, seq=frame.seq, sent_nanos=sent_nanos, payload_bytes=len(wire))))
        estimator.observe(k=split.k, tags=len(tags), network_ms=network_ms, fixed_ms=fixed_secs * 1e3)
        if time.monotonic() - last_profile >= settings.profile_period_secs:
            last_profile = time.monotonic()
            profile = estimator.message(robot_id=rid, side="robot", stamp_nanos=time.time_ns(), factor=settings.gamma)
            compute_pub.put(encode(profile))

    log.info("robot_infer ready: k=%d codec=%s gamma=%.2f", settings.split_k, settings.codec, settings.gamma)
    try:
        # Take a frame only with a credit in hand: the ring keeps the newest one while the edge catches up.
        while window.acquire(stop) and (sample := next_sample(sub, stop)) is not None:
            payload = sample.payload.to_bytes()
            guard.run("frame", len(payload), lambda: process(payload))  # noqa: B023 (called at once)
    finally:
        detector.close()
        token.undeclare()
        if acks is not None:
            acks.undeclare()
        queryable.undeclare()
        stats.undeclare()
        log.info("robot_infer: %s, %d credits expired", guard.stats(), window.expired)
