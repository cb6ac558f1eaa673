"""robot_infer computes on board the frames a vanished edge held before the next frame: slam refuses a
frame older than one it has fused, and a fresh-clone trial lost the recovered frame that way in 2 of 4
edge kills ('out of order'). A real RobotInfer on a real Zenoh session; the edge is a liveliness token
of a second session that goes away with a frame in flight."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from services.robot_infer.service import RobotInfer
from services.robot_infer.settings import RobotInferSettings
from shared.perception.split import robot_stage1
from shared.transport.session import ZenohSettings, free_tcp_port, open_session
from shared.vision.geometry import default_camera, make_pose
from shared.vision.tags import render_tag, to_uint8
from shared.wire import keys
from shared.wire.messages import Frame, TagPoses, decode, encode
from tests.fakes import FakeClock
from tests.procs import REPO, wait_until

ROBOT = "recover1"


def _frame(seq: int, capture_nanos: int) -> Frame:
    cam = default_camera()
    pose = make_pose(np.eye(3), [0.05 * seq, -0.05, 1.5])
    canvas = np.full((cam.height, cam.width), 0.55, np.float32)
    h = cam.matrix() @ np.column_stack([pose[:3, 0], pose[:3, 1], pose[:3, 3]])
    render_tag(canvas, tag_id=17, tag_size_m=0.2, tag_plane_to_image=h)
    return Frame(robot_id=ROBOT, seq=seq, capture_nanos=capture_nanos, intrinsics=cam, image=to_uint8(canvas))


class _Rig:
    """A real RobotInfer on its own Zenoh session and an "edge": a second session that holds edge_infer's
    liveliness token, hears every TagPoses of the robot (capture stamps in `got`) and may answer."""

    def __init__(self, node: RobotInfer, edge: zenoh.Session) -> None:
        self.node, self.edge = node, edge
        self.got: list[int] = []
        self._lock = threading.Lock()

    def on_poses(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.got.append(decode(sample.payload.to_bytes(), TagPoses).capture_nanos)

    def posed(self, frame: Frame) -> bool:
        with self._lock:
            return frame.capture_nanos in self.got

    def poses(self) -> list[int]:
        with self._lock:
            return list(self.got)

    def process(self, frame: Frame) -> None:
        self.node.process(robot_stage1(frame, detector=self.node.detector))


@contextlib.contextmanager
def _rig(tmp_path: Path, clock: Callable[[], float] = time.monotonic, **settings: Any) -> Iterator[_Rig]:
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    robot_settings = RobotInferSettings(
        robot_id=ROBOT,
        weights=REPO / "models",
        run_dir=tmp_path,
        split_k=5,
        overlap_stage1=False,
        zenoh=ZenohSettings(mode="peer", listen=[endpoint]),
        **settings,
    )
    session = open_session(robot_settings.zenoh)
    edge = open_session(ZenohSettings(mode="peer", connect=[endpoint]))
    node = RobotInfer(robot_settings, session, clock=clock)
    rig = _Rig(node, edge)
    sub = edge.declare_subscriber(keys.tag_poses(ROBOT), rig.on_poses)
    try:
        yield rig
    finally:
        node.halt.set()
        node.close()
        sub.undeclare()
        edge.close()
        session.close()


def test_the_frames_a_vanished_edge_held_go_out_before_the_next(tmp_path: Path) -> None:
    with _rig(tmp_path) as rig:
        node = rig.node
        token = rig.edge.liveliness().declare_token(keys.alive(ROBOT, "edge_infer"))
        wait_until(lambda: node.watch.alive, 30, "robot_infer sees the edge's token")
        now = time.time_ns()
        held, following = _frame(0, now), _frame(1, now + 66_000_000)
        rig.process(held)  # sent to the edge, which never answers
        assert node.window.in_flight == 1
        next_one = robot_stage1(following, detector=node.detector)  # taken before the edge goes
        token.undeclare()
        wait_until(lambda: not node.watch.alive, 30, "robot_infer sees the token go")
        node.process(next_one)  # on board: the held frame first, then this one
        wait_until(lambda: len(rig.poses()) >= 2, 30, "poses of both frames")
        time.sleep(0.3)
        assert rig.poses() == [held.capture_nanos, following.capture_nanos]
        assert node.recovered_frames == 1 and node.on_board_frames == 1


def test_the_on_board_count_is_said_at_the_first_frame_then_rate_limited_then_at_the_end() -> None:
    """A researcher read "1 frames computed on board" (logged at the 1st and every 100th frame) as the run's
    total when 17 had been: the count is said at an outage's first frame, then every `every_secs` while it
    lasts with the outage's count so far, and in full when the edge is back."""
    from shared.runtime.logs import SpellCount

    count = SpellCount(every_secs=10.0)
    said = [count.add(t) for t in (0.0, 1.0, 5.0, 9.9, 10.0, 12.0, 19.9, 20.5)]
    assert said == ["first", None, None, None, "running", None, None, "running"]
    assert count.spell == 8 and count.since_said == 3  # frames 5..7 since the report at 10.0 s
    assert count.end() == 8 and count.end() == 0  # the edge is back: the outage's total, said once
    assert count.add(30.0) == "first" and count.spell == 1 and count.total == 9
    with pytest.raises(ValueError):
        SpellCount(every_secs=0)


def test_a_stalled_edge_is_worked_around_until_it_answers_again(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A trial SIGSTOPped edge_infer: its token stays for Zenoh's whole lease (~10 s), and the robot,
    which forgot each overdue frame, sent the next one to the stalled edge too: no pose for ~10 s
    instead of on board after edge_answer_timeout_secs. Now an overdue answer holds the robot on board
    until the edge answers again; one frame per timeout still goes to the edge to find out."""
    from tests.examples import example_messages

    # The robot's in-flight clock is moved by hand: frames 1 and 2 are made at one instant however slow the
    # CPU, and an answer is overdue only when the test says. The edge's answers are judged by their wall-clock
    # round trip (sent_nanos stamps the test writes), so the timeout is long next to Zenoh's delivery.
    timeout_secs = 30.0
    clock = FakeClock(1000.0)
    with _rig(tmp_path, clock, edge_answer_timeout_secs=timeout_secs) as rig:
        node = rig.node
        answers = rig.edge.declare_publisher(keys.tag_poses(ROBOT))
        token = rig.edge.liveliness().declare_token(keys.alive(ROBOT, "edge_infer"))
        wait_until(lambda: node.watch.alive, 30, "robot_infer sees the edge's token")
        now = time.time_ns()
        frames = [_frame(i, now + i * 66_000_000) for i in range(7)]
        # stage 1 of every frame first: only the network and PnP run between the steps below
        made = [robot_stage1(f, detector=node.detector) for f in frames]
        node.process(made[0])  # to the edge, which is stalled
        assert node.window.in_flight == 1
        clock.now += timeout_secs + 0.1
        node.process(made[1])  # the answer is overdue: on board
        node.process(made[2])  # still on board (sent to the edge before)
        wait_until(lambda: rig.posed(frames[1]) and rig.posed(frames[2]), 10, "frames 1 and 2 posed on board")
        assert node.watch.overdue and node.watch.stalls == 1 and node.on_board_frames == 2
        clock.now += timeout_secs + 0.1
        node.process(made[3])  # a trial: to the edge
        assert node.window.in_flight == 1 and node.on_board_frames == 2
        node.process(made[6])  # the next frame, on board before the trial's answer (the window forgets the trial)
        assert node.on_board_frames == 3
        # the edge answers the trial: back to the split
        answer = example_messages()[TagPoses.SCHEMA]
        assert isinstance(answer, TagPoses) and answer.link is not None  # an edge's answer carries link stamps
        late_nanos = time.time_ns() - round(2 * timeout_secs * 1e9)
        late = answer.link.model_copy(update={"sent_nanos": late_nanos})  # a held frame's, late
        answers.put(
            encode(
                answer.model_copy(update={"robot_id": ROBOT, "capture_nanos": frames[0].capture_nanos, "link": late})
            )
        )
        prompt = answer.link.model_copy(update={"sent_nanos": time.time_ns() - 50_000_000})
        reply = answer.model_copy(update={"robot_id": ROBOT, "capture_nanos": frames[3].capture_nanos, "link": prompt})
        # taken by robot_infer itself (the test's own subscriber hears it sooner): its own three on-board
        # poses (frames 1, 2 and 6) and this one are all the TagPoses it can have handled
        taken = node.guard.accepted_by_input
        wait_until(lambda: taken.get("tag_poses", 0) >= 4, 30, "robot_infer takes the late answer")
        assert node.watch.overdue  # a late answer does not end the stall
        answers.put(encode(reply))
        wait_until(lambda: not node.watch.overdue, 30, "the edge's answer ends the stall")
        node.process(made[4])  # to the edge again
        assert node.window.in_flight == 1 and node.on_board_frames == 3 and not rig.posed(frames[4])
        logged = [r.getMessage() for r in caplog.records if r.name.startswith("services.robot_infer")]
        assert any("computing frames on board, the first now (0 before in this run" in m for m in logged), logged
        assert any("edge back: 3 frames computed on board during the outage (3 in this run)" in m for m in logged), (
            logged
        )
        token.undeclare()
        answers.undeclare()


def test_a_forged_answer_cannot_steer_the_robots_pacing(tmp_path: Path) -> None:
    """A trial's one 92-byte TagPoses (another robot's id, timings of 1e12 s, for no frame of this
    robot's) held robot_infer to 3 fps for 13 s, uncounted. Another robot's is refused and counted; one
    for no frame in flight here moves neither the pacing nor the stall watch; timings are bounded."""
    from tests.examples import example_messages

    template = example_messages()[TagPoses.SCHEMA]
    assert isinstance(template, TagPoses) and template.link is not None
    with _rig(tmp_path) as rig:
        node = rig.node
        pacer = node.pacer
        assert pacer is not None
        publisher = rig.edge.declare_publisher(keys.tag_poses(ROBOT))
        huge = template.timings.model_copy(update={"capture_to_pose_secs": 1e12, "edge_compute_secs": 0.0})
        link = template.link.model_copy(update={"sent_nanos": time.time_ns(), "received_nanos": 0})
        forged = template.model_copy(update={"robot_id": "robot2", "capture_nanos": 1, "timings": huge, "link": link})
        publisher.put(encode(forged))
        wait_until(lambda: node.guard.rejected.get("tag_poses: ValueError", 0) == 1, 30, "the foreign one refused")
        ours = forged.model_copy(update={"robot_id": ROBOT})  # this robot's id, but no frame of its in flight
        publisher.put(encode(ours))
        wait_until(lambda: node.guard.accepted_by_input.get("tag_poses", 0) >= 1, 30, "this robot's taken")
        assert pacer.edge_wait_secs == 0.0 and not node.watch.overdue
        pacer.answered(1, tags=1, link_secs=1e12, edge_secs=0.0, edge_received_nanos=0, edge_done_nanos=10**21)
        assert pacer.edge_wait_secs <= 10.0 and abs(pacer.link_secs) <= 10.0  # (MAX_ANSWER_SECS)
        publisher.undeclare()
