"""robot_infer computes on board the frames a vanished edge held before the next frame: slam refuses a
frame older than one it has fused, and a fresh-clone trial lost the recovered frame that way in 2 of 4
edge kills ('out of order'). A real RobotInfer on a real Zenoh session; the edge is a liveliness token
of a second session that goes away with a frame in flight."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import numpy as np
import zenoh

from services.robot_infer.service import RobotInfer
from services.robot_infer.settings import RobotInferSettings
from shared.perception.split import robot_stage1
from shared.transport.session import ZenohSettings, free_tcp_port, open_session
from shared.vision.geometry import default_camera, make_pose
from shared.vision.tags import render_tag, to_uint8
from shared.wire import keys
from shared.wire.messages import Frame, TagPoses, decode
from tests.procs import REPO, wait_until

ROBOT = "recover1"


def _frame(seq: int, capture_nanos: int) -> Frame:
    cam = default_camera()
    pose = make_pose(np.eye(3), [0.05 * seq, -0.05, 1.5])
    canvas = np.full((cam.height, cam.width), 0.55, np.float32)
    h = cam.matrix() @ np.column_stack([pose[:3, 0], pose[:3, 1], pose[:3, 3]])
    render_tag(canvas, tag_id=17, tag_size_m=0.2, tag_plane_to_image=h)
    return Frame(robot_id=ROBOT, seq=seq, capture_nanos=capture_nanos, intrinsics=cam, image=to_uint8(canvas))


def test_the_frames_a_vanished_edge_held_go_out_before_the_next(tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    settings = RobotInferSettings(
        robot_id=ROBOT,
        weights=REPO / "models",
        run_dir=tmp_path,
        split_k=5,
        overlap_stage1=False,
        zenoh=ZenohSettings(mode="peer", listen=[endpoint]),
    )
    session = open_session(settings.zenoh)
    edge = open_session(ZenohSettings(mode="peer", connect=[endpoint]))
    got: list[int] = []
    lock = threading.Lock()

    def on_poses(sample: zenoh.Sample) -> None:
        with lock:
            got.append(decode(sample.payload.to_bytes(), TagPoses).capture_nanos)

    sub = edge.declare_subscriber(keys.tag_poses(ROBOT), on_poses)
    node = RobotInfer(settings, session)
    try:
        token = edge.liveliness().declare_token(keys.alive(ROBOT, "edge_infer"))
        wait_until(lambda: node.watch.alive, 30, "robot_infer sees the edge's token")
        now = time.time_ns()
        held, following = _frame(0, now), _frame(1, now + 66_000_000)
        node.process(robot_stage1(held, detector=node.detector))  # sent to the edge, which never answers
        assert node.window.in_flight == 1
        next_one = robot_stage1(following, detector=node.detector)  # taken before the edge goes
        token.undeclare()
        wait_until(lambda: not node.watch.alive, 30, "robot_infer sees the token go")
        node.process(next_one)  # on board: the held frame first, then this one
        wait_until(lambda: len(got) >= 2, 30, "poses of both frames")
        time.sleep(0.3)
        with lock:
            assert got == [held.capture_nanos, following.capture_nanos]
        assert node.recovered_frames == 1 and node.on_board_frames == 1
    finally:
        node.halt.set()
        node.close()
        sub.undeclare()
        edge.close()
        session.close()
