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
from shared.wire.messages import Frame, TagPoses, decode, encode
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


def test_a_stalled_edge_is_worked_around_until_it_answers_again(tmp_path: Path) -> None:
    """A trial SIGSTOPped edge_infer: its token stays for Zenoh's whole lease (~10 s), and the robot,
    which forgot each overdue frame, sent the next one to the stalled edge too: no pose for ~10 s
    instead of on board after edge_answer_timeout_secs. Now an overdue answer holds the robot on board
    until the edge answers again; one frame per timeout still goes to the edge to find out."""
    from tests.examples import example_messages

    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    timeout_secs = 0.4
    settings = RobotInferSettings(
        robot_id=ROBOT,
        weights=REPO / "models",
        run_dir=tmp_path,
        split_k=5,
        overlap_stage1=False,
        edge_answer_timeout_secs=timeout_secs,
        zenoh=ZenohSettings(mode="peer", listen=[endpoint]),
    )
    session = open_session(settings.zenoh)
    edge = open_session(ZenohSettings(mode="peer", connect=[endpoint]))
    got: list[int] = []
    lock = threading.Lock()

    def on_poses(sample: zenoh.Sample) -> None:
        with lock:
            got.append(decode(sample.payload.to_bytes(), TagPoses).capture_nanos)

    def posed(frame: Frame) -> bool:
        with lock:
            return frame.capture_nanos in got

    sub = edge.declare_subscriber(keys.tag_poses(ROBOT), on_poses)
    answers = edge.declare_publisher(keys.tag_poses(ROBOT))
    node = RobotInfer(settings, session)
    try:
        token = edge.liveliness().declare_token(keys.alive(ROBOT, "edge_infer"))
        wait_until(lambda: node.watch.alive, 30, "robot_infer sees the edge's token")
        now = time.time_ns()
        frames = [_frame(i, now + i * 66_000_000) for i in range(6)]
        node.process(robot_stage1(frames[0], detector=node.detector))  # to the edge, which is stalled
        assert node.window.in_flight == 1
        time.sleep(timeout_secs + 0.1)
        node.process(robot_stage1(frames[1], detector=node.detector))  # the answer is overdue: on board
        node.process(robot_stage1(frames[2], detector=node.detector))  # still on board (sent to the edge before)
        wait_until(lambda: posed(frames[1]) and posed(frames[2]), 10, "frames 1 and 2 posed on board")
        assert node.watch.overdue and node.watch.stalls == 1 and node.on_board_frames == 2
        time.sleep(timeout_secs + 0.1)
        node.process(robot_stage1(frames[3], detector=node.detector))  # a trial: to the edge
        assert node.window.in_flight == 1 and node.on_board_frames == 2
        # the edge answers the trial: back to the split
        answer = example_messages()[TagPoses.SCHEMA]
        assert isinstance(answer, TagPoses) and answer.link is not None  # an edge's answer carries link stamps
        answers.put(encode(answer.model_copy(update={"robot_id": ROBOT, "capture_nanos": frames[3].capture_nanos})))
        wait_until(lambda: not node.watch.overdue, 30, "the edge's answer ends the stall")
        node.process(robot_stage1(frames[4], detector=node.detector))  # to the edge again
        assert node.window.in_flight == 1 and node.on_board_frames == 2 and not posed(frames[4])
        token.undeclare()
    finally:
        node.halt.set()
        node.close()
        answers.undeclare()
        sub.undeclare()
        edge.close()
        session.close()
