"""Deterministic example messages shared by the round-trip, golden-bytes and fuzzing tests."""

from __future__ import annotations

from typing import Final

import numpy as np

from shared.wire.messages import (
    LEGACY_SCHEMAS,
    SCHEMAS,
    CameraIntrinsics,
    CameraPose,
    ComputeProfile,
    ControllerState,
    Features,
    Frame,
    FrameSent,
    FrameStamp,
    HopTimings,
    LinkStamps,
    MapTag,
    Message,
    ProbeAck,
    SplitConfig,
    TagFeature,
    TagMap,
    TagPose,
    TagPoses,
)

INTRINSICS = CameraIntrinsics(
    width=8,
    height=6,
    fx=1045.0,
    fy=1045.0,
    cx=3.5,
    cy=2.5,
    distortion_model="plumb_bob",
    distortion=[0.01, -0.002, 0.0, 0.0, 0.0],
)


# Rigid poses (rotation + translation rows; the last row is 0 0 0 1) written out as literals: they were
# made by a QR decomposition, whose last bits differ between CPUs (AVX-512 vs AVX2 LAPACK kernels), and
# the golden files must not depend on which machine runs the tests.
_POSE_ROWS: dict[int, tuple[tuple[float, ...], ...]] = {
    1: (
        (-0.23813772081825824, -0.9553295832313821, -0.1750308924916958, -1.8897635470277265),
        (0.8979892602955535, -0.14791815932940133, -0.41440982919622743, 1.0140524346992263),
        (0.37000772196986603, -0.25586247388696176, 0.8931005991147437, 0.15257325287711287),
    ),
    2: (
        (-0.07653039693522024, -0.5783494998566865, 0.812191451789822, 0.6297320595023703),
        (0.9883265040023365, -0.151625835805481, -0.014843429617472117, 0.249062651121712),
        (0.13173389780712164, 0.8015743645675117, 0.5832021246846865, -1.3997509467786555),
    ),
    3: (
        (-0.6972437296974106, -0.7055049849538615, 0.12694052781872384, -1.5453119203143864),
        (0.1939683908281411, -0.3561643451747411, -0.9140695939510237, -0.43508723801735183),
        (0.6900923450938911, -0.6127068429775365, 0.38517902306760476, 0.0669607304854547),
    ),
    4: (
        (-0.5834432847763826, -0.5364250393248788, -0.6097885786357817, 0.1757656030539927),
        (0.5900284573887218, -0.7959108880210977, 0.13561813227202704, 1.6088603188639534),
        (-0.5580863310643168, -0.28066712581770215, 0.7808749013538595, -0.09138590464317486),
    ),
}


def _pose(seed: int) -> np.ndarray:
    pose = np.eye(4)
    pose[:3] = np.array(_POSE_ROWS[seed], dtype=np.float64)
    return pose


def example_messages() -> dict[str, Message]:
    """One instance of every schema, small enough for golden files, with every array dtype used."""
    rng = np.random.default_rng(7)
    corners = rng.uniform(0, 8, (4, 2)).astype(np.float32)
    frame = Frame(
        robot_id="robot1",
        seq=3,
        capture_nanos=1_700_000_000_123_456_789,
        intrinsics=INTRINSICS,
        image=rng.integers(0, 256, (6, 8), dtype=np.uint8),
    )
    tags = [
        TagFeature(
            tag_id=5,
            decision_margin=61.5,
            hamming=0,
            corners_px=corners,
            roi_to_image=np.arange(9, dtype=np.float64).reshape(3, 3) + 10 * np.eye(3),
            tensor=rng.standard_normal((4, 2, 2)).astype(np.float16),
            edge_width_px=1.5,
            tracked=False,
            proposer="lines_soft",
        ),
        TagFeature(
            tag_id=9,
            decision_margin=40.25,
            hamming=1,
            corners_px=corners,
            roi_to_image=np.eye(3),
            tensor=rng.integers(-128, 127, (2, 3), dtype=np.int8),
            edge_width_px=1.5,
            tracked=True,
            proposer="tracker",
        ),
    ]
    features = Features(
        robot_id="robot1",
        seq=3,
        capture_nanos=1_700_000_000_123_456_789,
        publish_nanos=1_700_000_000_140_000_000,
        split_k=3,
        codec="fp16",
        intrinsics=INTRINSICS,
        robot_compute_secs=0.0125,
        tags=tags,
    )
    tag_pose = TagPose(
        tag_id=5,
        tag_size_m=0.16,
        keypoints_px=rng.uniform(0, 8, (16, 2)).astype(np.float32),
        corners_px=corners,
        camera_from_tag=_pose(1),
        reprojection_error_px=0.31,
        alt_camera_from_tag=_pose(2),
        alt_reprojection_error_px=2.5,
        tracked=True,
        proposer="tracker",
    )
    poses = TagPoses(
        robot_id="robot1",
        seq=3,
        capture_nanos=1_700_000_000_123_456_789,
        split_k=3,
        payload_bytes=4242,
        intrinsics=INTRINSICS,
        link=LinkStamps(
            sent_nanos=1_700_000_000_140_000_000,
            received_nanos=1_700_000_000_181_000_000,
            previous_received_nanos=1_700_000_000_150_000_000,
        ),
        timings=HopTimings(
            robot_compute_secs=0.0125,
            transport_secs=0.041,
            edge_compute_secs=0.004,
            capture_to_pose_secs=0.07,
        ),
        tags=[tag_pose],
    )
    camera_pose = CameraPose(
        robot_id="robot1",
        seq=3,
        capture_nanos=1_700_000_000_123_456_789,
        world_from_camera=_pose(3),
        status="tracking",
        tags_used=1,
        covariance_world=_covariance6(),
    )
    tag_map = TagMap(
        robot_id="robot1",
        revision=2,
        anchor_tag_id=5,
        tags=[
            MapTag(tag_id=5, size_m=0.16, world_from_tag=np.eye(4), observations=10, bridged=False),
            MapTag(
                tag_id=9,
                size_m=0.2,
                world_from_tag=_pose(4),
                observations=3,
                bridged=True,
                position_sigma_m=0.004,
                rotation_sigma_deg=0.3,
            ),
        ],
    )
    split = SplitConfig(k=5, codec="fp16", pinned=True, source="user")
    ack = ProbeAck(
        received_bytes=1024,
        decoded_ok=True,
        error="",
        link=LinkStamps(
            sent_nanos=1_700_000_000_140_000_000, received_nanos=1_700_000_000_181_000_000, previous_received_nanos=0
        ),
    )
    sent = FrameSent(robot_id="robot1", seq=3, sent_nanos=1_700_000_000_140_000_000, payload_bytes=4242)
    per_cut = [0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0]
    compute = ComputeProfile(
        robot_id="robot1",
        side="robot",
        stamp_nanos=1_700_000_000_123_456_789,
        current_k=7,
        tags_per_frame=3.5,
        live_scale=1.08,
        ms_by_k=per_cut,
        period_ms_by_k=[0.5, 1.0, 2.0, 4.0, 8.0, 8.0, 16.0, 32.0],
        frame_interval_ms=33.3,
    )
    controller = ControllerState(
        robot_id="robot1",
        stamp_nanos=1_700_000_000_123_456_789,
        t0_ms=39.9,
        beta_ms_per_kB=0.18,
        link_samples=120,
        link_changes=1,
        robot_ms_by_k=per_cut,
        edge_ms_by_k=per_cut[::-1],
        payload_kB_by_k=[256.0, 4096.0, 2048.0, 1024.0, 512.0, 128.0, 32.0, 0.5],
        predicted_ms_by_k=[100.0, 800.0, 400.0, 250.0, 150.0, 90.0, 95.0, 105.0],
        current_k=7,
        best_k=5,
        chosen_k=7,
        pinned=False,
        applied=False,
        reason="keep k=7: k=5 better by 15.0 ms (1/3)",
        period_ms_by_k=[256.0, 4096.0, 2048.0, 1024.0, 512.0, 128.0, 32.0, 64.0],
        achieved_ms_by_k=[None, None, None, None, None, 41.5, None, 33.4],
        frame_interval_ms=33.3,
        frame_share_by_k=[0.13, 0.01, 0.02, 0.03, 0.07, 0.8, 1.0, 1.0],
        min_frame_share=0.9,
    )
    stamp = FrameStamp(
        robot_id="robot1", seq=3, capture_nanos=1_700_000_000_123_456_789, source_stamp_nanos=1_305_031_102_175_304_000
    )
    msgs: list[Message] = [frame, features, poses, camera_pose, tag_map, split, ack, compute, controller, sent, stamp]
    return {m.SCHEMA: m for m in msgs}


def _covariance6() -> np.ndarray:
    """A fixed symmetric positive-definite 6x6 (position m^2, then rotation rad^2), with correlations."""
    a = np.arange(36, dtype=np.float64).reshape(6, 6) % 7 / 7 - 0.4
    return a @ a.T * 1e-4 + np.diag([4e-4, 4e-4, 9e-4, 1e-5, 1e-5, 4e-5])


# The framings golden files are kept in: 3 is what encode writes, 2 and 1 what older peers send.
GOLDEN_FRAMINGS: Final[tuple[int, ...]] = (1, 2, 3)


def golden_name(schema: str, framing: int = 3) -> str:
    """Path of a schema's golden bytes under tests/golden/: framing3/ (what encode writes, regenerated on
    purpose), framing2/ (named header, tensors out of band) or framing1/ (plain msgpack); the last two
    are frozen: older peers' bytes must keep decoding (`regenerate --missing` adds a new version's, never
    rewrites one)."""
    name = schema.replace("splittag/", "").replace("/", "_")
    return f"framing1/{name}.msgpack" if framing == 1 else f"framing{framing}/{name}.splittag"


def golden_names() -> set[str]:
    """Every golden file the tests read: each current schema in every framing, and each legacy version in
    framing 1 (its bytes from when it was current; test_wire's legacy test decodes them)."""
    current = {golden_name(schema, framing) for schema in SCHEMAS for framing in GOLDEN_FRAMINGS}
    return current | {golden_name(schema, framing=1) for schema in LEGACY_SCHEMAS}


def assert_messages_equal(a: Message, b: Message) -> None:
    """Deep equality that compares arrays by dtype, shape and exact bytes."""
    assert type(a) is type(b)
    _assert_equal(a.model_dump(), b.model_dump(), type(a).__name__)


def _assert_equal(x: object, y: object, path: str) -> None:
    if isinstance(x, np.ndarray):
        assert isinstance(y, np.ndarray), path
        assert x.dtype == y.dtype and x.shape == y.shape, (path, x.dtype, y.dtype, x.shape, y.shape)
        assert x.tobytes() == y.tobytes(), path
    elif isinstance(x, dict):
        assert isinstance(y, dict) and x.keys() == y.keys(), path
        for k in x:
            _assert_equal(x[k], y[k], f"{path}.{k}")
    elif isinstance(x, list):
        assert isinstance(y, list) and len(x) == len(y), path
        for i, (xi, yi) in enumerate(zip(x, y, strict=True)):
            _assert_equal(xi, yi, f"{path}[{i}]")
    else:
        assert x == y and type(x) is type(y), (path, x, y)


def injected_tag_poses(robot_id: str, seq: int, capture_nanos: int | None = None) -> bytes:
    """Wire bytes of a schema-valid TagPoses with no tags: what an intruder would send (access tests), or
    a stand-in pipeline's answer to a frame (`capture_nanos`: the frame's)."""
    import time

    from shared.vision.geometry import default_camera
    from shared.wire.messages import encode

    timings = HopTimings(robot_compute_secs=0, transport_secs=0, edge_compute_secs=0, capture_to_pose_secs=0)
    message = TagPoses(
        robot_id=robot_id,
        seq=seq,
        capture_nanos=time.time_ns() if capture_nanos is None else capture_nanos,
        split_k=7,
        payload_bytes=1,
        intrinsics=default_camera(),
        link=None,
        timings=timings,
        tags=[],
    )
    return encode(message)
