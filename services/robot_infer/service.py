"""robot_infer loop: newest frame -> stage 1 + head(k) -> Features, with the split set live over Zenoh."""

from __future__ import annotations

import logging
import threading
import time

import torch
import zenoh

from services.robot_infer.settings import RobotInferSettings
from shared import keys
from shared.codec import WireError
from shared.detector import TagDetector
from shared.messages import Features, Frame, SplitConfig, decode, encode
from shared.pipeline import robot_step
from shared.split_control import SplitState, serve_split
from shared.transport import declare_latest_subscriber, declare_tensor_publisher, next_sample
from shared.weights import load_model

log = logging.getLogger(__name__)


def run(settings: RobotInferSettings, *, session: zenoh.Session, stop: threading.Event) -> None:
    """Process frames until `stop` is set."""
    torch.set_num_threads(settings.threads)
    model = load_model(settings.weights)
    detector = TagDetector(settings.detector)
    state = SplitState(SplitConfig(k=settings.split_k, codec=settings.codec, pinned=False, source="default"))
    rid = settings.robot_id
    sub = declare_latest_subscriber(session, keys.frames(rid))
    pub = declare_tensor_publisher(session, keys.features(rid), Features.SCHEMA)
    queryable = serve_split(session, keys.split(rid), state)
    token = session.liveliness().declare_token(keys.alive(rid, "robot_infer"))
    rejected = processed = 0
    log.info("robot_infer ready: k=%d codec=%s gamma=%.2f", settings.split_k, settings.codec, settings.gamma)
    try:
        while (sample := next_sample(sub, stop)) is not None:
            payload = sample.payload.to_bytes()
            try:
                frame = decode(payload, Frame, max_bytes=settings.max_payload_bytes)
            except WireError as exc:
                rejected += 1
                log.warning("rejected frame #%d (%d bytes): %s", rejected, len(payload), exc)
                continue
            split = state.get()  # changes apply from the next frame; each message says its k
            tags, timings = robot_step(
                frame, detector=detector, model=model, k=split.k, codec=split.codec, bf16=settings.bf16
            )
            compute = timings.total_secs
            if settings.gamma > 1.0:
                # Emulate a robot CPU `gamma` times slower: the latency really grows, not just a model.
                time.sleep((settings.gamma - 1.0) * compute)
                compute *= settings.gamma
            pub.put(
                encode(
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
            )
            processed += 1
    finally:
        token.undeclare()
        queryable.undeclare()
        log.info("robot_infer: %d frames processed, %d rejected", processed, rejected)
