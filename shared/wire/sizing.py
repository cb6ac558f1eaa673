"""Features messages of a given size: link probes, and the exact wire size of a frame at any cut."""

from __future__ import annotations

import time
from functools import lru_cache

import numpy as np

from shared.vision.geometry import default_camera
from shared.wire.cuts import CodecName, tensor_bytes
from shared.wire.messages import Features, TagFeature, encode


def probe_features(tensor_bytes: int, *, robot_id: str = "probe", seq: int = 0) -> Features:
    """A Features message whose single tensor holds `tensor_bytes` bytes of fp16 (rounded down to even)."""
    n = max(0, tensor_bytes // 2)
    rng = np.random.default_rng(seq)
    tensor = rng.standard_normal(n).astype(np.float16) if n else np.zeros(0, np.float16)
    tag = TagFeature(
        tag_id=0,
        decision_margin=0.0,
        hamming=0,
        corners_px=np.zeros((4, 2), np.float32),
        roi_to_image=np.eye(3),
        tensor=tensor,
        edge_width_px=1.0,  # a measured width (a float), as real Features carry
        tracked=False,
        proposer="apriltag",  # as real Features say
    )
    now = time.time_ns()
    return Features(
        robot_id=robot_id,
        seq=seq,
        capture_nanos=now,
        publish_nanos=now,
        split_k=0,
        codec="fp16",
        intrinsics=default_camera(),
        robot_compute_secs=0.0,
        tags=[tag],
    )


@lru_cache(maxsize=64)
def features_payload_bytes(tags: int, k: int, codec: CodecName = "fp16") -> int:
    """Exact wire size of a Features message with `tags` tags at cut k (envelope included)."""
    if tags == 0:
        return len(encode(probe_features(0)))
    msg = probe_features(tensor_bytes(k, codec))
    return len(encode(msg.model_copy(update={"tags": msg.tags * tags})))
