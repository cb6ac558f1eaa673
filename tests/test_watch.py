"""`splittag watch`, `map` and `stats`: the formats (pure), and the commands run as a light client would
run them (a separate process in which torch, OpenCV, GTSAM, Rerun, SciPy... cannot be imported),
against real Zenoh sessions on loopback."""

from __future__ import annotations

import json
import queue
import re
import signal
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import zenoh
from scipy.spatial.transform import Rotation

from shared.runtime.guard import InputGuard, serve_stats
from shared.tools.watch import (
    PUBLISHERS,
    QUIET_HINT_SECS,
    TOPICS,
    controller_text,
    json_line,
    key_for,
    map_text,
    pose_text,
    quaternion_xyzw,
    render,
    stats_text,
    tag_poses_text,
    tum_line,
)
from shared.transport.session import ZenohSettings, free_tcp_port, open_session
from shared.transport.split_control import SplitState, serve_split
from shared.wire import keys
from shared.wire.messages import CameraPose, ControllerState, FrameStamp, SplitConfig, TagMap, TagPoses, encode
from tests.examples import example_messages
from tests.procs import REPO

# What an integrator's light install does not have (README *Reading poses from your own process*).
HEAVY = [
    *("torch", "cv2", "gtsam", "rerun", "openvino", "mujoco", "scipy", "matplotlib", "pupil_apriltags"),
    *("safetensors", "onnx", "onnxruntime", "nncf", "yaml", "tqdm"),
]
LIGHT_CLI = textwrap.dedent(
    f"""
    import importlib.abc, sys
    HEAVY = {HEAVY!r}
    class Absent(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in HEAVY:
                raise ModuleNotFoundError(f"No module named {{name!r}} (a light client)")
    sys.meta_path.insert(0, Absent())
    from shared.tools.cli import main
    raise SystemExit(main(sys.argv[1:]))
    """
)


def _messages() -> dict[str, object]:
    return {m.SCHEMA.split("/")[1]: m for m in example_messages().values()}


def _pose(status: str = "tracking", seq: int = 3, robot_id: str = "robot1") -> CameraPose:
    pose = _messages()["CameraPose"]
    assert isinstance(pose, CameraPose)
    return pose.model_copy(update={"status": status, "seq": seq, "robot_id": robot_id})


def test_every_topic_says_who_publishes_it() -> None:
    """(the hint for a silent topic looks its publisher up: review)"""
    assert set(PUBLISHERS) == set(TOPICS)


def test_quaternions_agree_with_scipy_everywhere_including_half_turns() -> None:
    rng = np.random.default_rng(3)
    rotations = [*Rotation.random(500, random_state=4)]
    rotations += [Rotation.from_rotvec(np.pi * axis / np.linalg.norm(axis)) for axis in rng.normal(size=(50, 3))]
    rotations += [Rotation.from_rotvec([np.pi - 1e-9, 0, 0]), Rotation.identity()]
    for r in rotations:
        q = np.array(quaternion_xyzw(r.as_matrix()))
        expected = r.as_quat()
        expected = -expected if expected[3] < 0 else expected
        assert q[3] >= 0
        # the same rotation (q and -q are one rotation when w = 0)
        assert min(np.abs(q - expected).max(), np.abs(q + expected).max()) < 1e-9


def test_tum_lines_are_exact_and_only_in_the_world_frame() -> None:
    pose = _pose()
    line = tum_line(pose)
    assert line is not None
    fields = line.split()
    assert fields[0] == "1700000000.123456789"  # exact nanoseconds, not a rounded float
    m = np.asarray(pose.world_from_camera)
    np.testing.assert_allclose([float(v) for v in fields[1:4]], m[:3, 3], atol=1e-9)
    back = Rotation.from_quat([float(v) for v in fields[4:8]]).as_matrix()
    np.testing.assert_allclose(back, m[:3, :3], atol=1e-8)
    assert tum_line(_pose("lost")) is None and tum_line(_pose("bridged")) is None
    assert render(_pose("lost"), "tum", 0) == []
    with pytest.raises(ValueError, match="poses only"):
        render(_messages()["TagMap"], "tum", 0)  # type: ignore[arg-type]


def test_json_lines_carry_every_field_and_the_derived_ones() -> None:
    pose = _pose()
    body = json.loads(json_line(pose))
    assert body["schema"] == CameraPose.SCHEMA and body["seq"] == 3 and body["status"] == "tracking"
    np.testing.assert_allclose(body["world_from_camera"], np.asarray(pose.world_from_camera))
    np.testing.assert_allclose(body["covariance_world"], np.asarray(pose.covariance_world))
    np.testing.assert_allclose(body["position_m"], np.asarray(pose.world_from_camera)[:3, 3])
    cov = np.asarray(pose.covariance_world)
    assert body["position_sigma_m"] == pytest.approx(np.sqrt(np.trace(cov[:3, :3])))
    tags = json.loads(json_line(_messages()["TagPoses"]))  # type: ignore[arg-type]
    assert tags["tags"][0]["tag_id"] == 5 and len(tags["tags"][0]["keypoints_px"]) == 16
    assert tags["timings"]["transport_secs"] == pytest.approx(0.041)


def test_text_lines_say_what_an_operator_needs() -> None:
    pose = _pose()
    now = pose.capture_nanos + 91_000_000
    line = pose_text(pose, now)
    assert line.startswith("robot1 #3 tracking") and "age 91 ms" in line and "tags 1" in line
    sigma = np.sqrt(np.trace(np.asarray(pose.covariance_world)[:3, :3])) * 100
    assert f"sigma {sigma:.1f} cm" in line
    assert "sigma -" in pose_text(pose.model_copy(update={"covariance_world": None}), now)
    tag_poses = _messages()["TagPoses"]
    assert isinstance(tag_poses, TagPoses)
    text = tag_poses_text(tag_poses, now)
    assert "k=3 4242 B" in text and "link 41.0" in text and "5 (tracked," in text
    state = _messages()["ControllerState"]
    assert isinstance(state, ControllerState)
    text = controller_text(state)
    assert "k=7 best=5 chosen=7" in text and "5:90.0" in text and "t0 39.9 ms" in text
    assert "frame share 0:0.13 " in text and "5:0.80* 6:1.00 7:1.00*" in text
    assert "(keeps up: >= 0.90, camera every 33.3 ms; * measured)" in text
    unknown = state.model_copy(update={"frame_interval_ms": None, "frame_share_by_k": None, "min_frame_share": None})
    assert "camera's rate unknown: latency alone" in controller_text(unknown)
    waiting = state.model_copy(update={"reason": "waiting for the compute profiles of both sides"})
    assert "no prediction yet" in controller_text(waiting) and "0:" not in controller_text(waiting)
    tag_map = _messages()["TagMap"]
    assert isinstance(tag_map, TagMap)
    lines = map_text(tag_map)
    assert lines[0] == "robot1 map revision 2, anchor 5, 2 tags"
    assert "tag     9" in lines[2] and "sigma 0.40 cm / 0.30 deg" in lines[2] and lines[2].endswith("bridged")
    stats = {
        "splittag/r1/slam/stats": {
            "service": "slam",
            "accepted": 3,
            "accepted_by_input": {"tag_poses": 3},
            "rejected": 1,
            "rejected_by_reason": {"tag_poses: SchemaError": 1},
        }
    }
    assert stats_text(stats) == [
        "r1/slam                  accepted 3 (tag_poses 3)  refused 1 (tag_poses: SchemaError: 1)"
    ]


def test_tum_lines_keep_one_time_for_the_whole_output() -> None:
    """The stamps' subscription reaches the camera later than the poses' reaches slam: the first poses
    used to go out in capture time, the rest in data-set time, in one file (review). Poses wait for a
    stamp up to a grace period; then one time throughout."""
    from shared.tools.watch import DataSetTime

    now = [0.0]
    first = _pose("tracking", 1)
    second = first.model_copy(update={"seq": 2, "capture_nanos": first.capture_nanos + 10**8})
    stamped = DataSetTime(grace_secs=2.0, clock=lambda: now[0])
    assert stamped.lines(first) == []  # waits for a stamp
    stamped.add(FrameStamp(robot_id="robot1", seq=2, capture_nanos=second.capture_nanos, source_stamp_nanos=5 * 10**9))
    assert stamped.lines(second) == [tum_line(second, 5 * 10**9)]  # the first has no stamp: left out
    assert stamped.unstamped == 1 and stamped.mode == "data set"
    unstamped = DataSetTime(grace_secs=2.0, clock=lambda: now[0])
    assert unstamped.lines(first) == []
    now[0] = 2.5  # no stamp in the grace period: capture time throughout, a late stamp changes nothing
    unstamped.add(FrameStamp(robot_id="robot1", seq=2, capture_nanos=second.capture_nanos, source_stamp_nanos=1))
    assert unstamped.lines(second) == [tum_line(first), tum_line(second)] and unstamped.mode == "capture"
    ended = DataSetTime(grace_secs=2.0, clock=lambda: 0.0)
    assert ended.lines(first) == [] and ended.lines(final=True) == [tum_line(first)]  # the watch ended first
    # a watch started well before the run (to catch every pose): the grace period starts at the first pose
    early = DataSetTime(grace_secs=2.0, clock=lambda: now[0])
    now[0] = 30.0
    assert early.lines(first) == []
    now[0] = 30.5
    early.add(FrameStamp(robot_id="robot1", seq=2, capture_nanos=second.capture_nanos, source_stamp_nanos=7))
    assert early.lines(second) == [tum_line(second, 7)] and early.mode == "data set"


def test_keys_for_one_robot_or_every_robot() -> None:
    assert key_for("poses", "r1") == keys.camera_pose("r1")
    assert key_for("map", "*") == "splittag/*/" + keys.tag_map("r1").split("/", 2)[2]
    with pytest.raises(ValueError, match="robot id"):
        key_for("poses", "r1/**")


@contextmanager
def _router() -> Iterator[tuple[str, zenoh.Session]]:
    """A router on a free loopback port (what the CLI connects to) and a session on it."""
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    session = open_session(ZenohSettings(mode="router", listen=[endpoint]))
    try:
        yield endpoint, session
    finally:
        session.close()


def _light_cli(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-c", LIGHT_CLI, *args],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _finish(proc: subprocess.Popen[str], timeout_secs: float = 20.0) -> tuple[str, str]:
    try:
        return proc.communicate(timeout=timeout_secs)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def _wait_subscribed(publisher: zenoh.Publisher, proc: subprocess.Popen[str]) -> None:
    deadline = time.monotonic() + 20.0
    while not publisher.matching_status.matching:  # type: ignore[attr-defined]  # the stub says bool; 1.10 gives MatchingStatus
        assert proc.poll() is None, f"watch exited early: {_finish(proc)}"
        assert time.monotonic() < deadline, "the watch never subscribed"
        time.sleep(0.05)


@pytest.mark.multiprocess
def test_watch_poses_as_a_light_client_refuses_bad_input_and_goes_on() -> None:
    with _router() as (endpoint, session):
        publisher = session.declare_publisher(keys.camera_pose("r1"))
        proc = _light_cli(
            "watch", "poses", "--robot-id", "r1", "--connect", endpoint, "--count", "3", "--format", "json"
        )
        try:
            _wait_subscribed(publisher, proc)
            publisher.put(b"\x00not a message")
            publisher.put(encode(_pose(robot_id="r2")))  # another robot's pose on r1's key
            publisher.put(encode(_messages()["TagMap"]))  # type: ignore[arg-type]  # another schema
            for seq, status in ((10, "tracking"), (11, "lost"), (12, "bridged")):
                publisher.put(encode(_pose(status, seq, "r1")))
            out, err = _finish(proc)
        finally:
            publisher.undeclare()
    assert proc.returncode == 0, err
    bodies = [json.loads(line) for line in out.splitlines()]
    assert [(b["seq"], b["status"]) for b in bodies] == [(10, "tracking"), (11, "lost"), (12, "bridged")]
    assert "3 messages, 3 refused" in err and "0 dropped" in err, err
    assert "No module named" not in err


@pytest.mark.multiprocess
def test_watch_every_robot_and_one_robots_tum_trajectory() -> None:
    """`*` reads every robot; `--format tum` is one robot's trajectory, in the data set's time when the
    camera sends it (as trajectory.tum is written: a trial had to join live lines through frames.csv)."""
    later = _pose("tracking", 3, "r2").model_copy(update={"capture_nanos": _pose().capture_nanos + 10**8})
    data_set_nanos = 1_305_031_102_175_304_000
    with _router() as (endpoint, session):
        pubs = {r: session.declare_publisher(keys.camera_pose(r)) for r in ("r1", "r2")}
        stamp_pub = session.declare_publisher(keys.frame_stamp("r2"))
        every = _light_cli("watch", "poses", "--robot-id", "*", "--connect", endpoint, "--count", "3")
        tum = _light_cli("watch", "poses", "--robot-id", "r2", "--connect", endpoint, "--count", "3", "--format", "tum")
        try:
            for pub in pubs.values():
                _wait_subscribed(pub, every)
            _wait_subscribed(pubs["r2"], tum)
            _wait_subscribed(stamp_pub, tum)
            stamp = FrameStamp(
                robot_id="r2", seq=2, capture_nanos=_pose().capture_nanos, source_stamp_nanos=data_set_nanos
            )
            stamp_pub.put(encode(stamp))
            time.sleep(0.2)
            pubs["r1"].put(encode(_pose("tracking", 1, "r1")))
            pubs["r2"].put(encode(_pose("lost", 1, "r2")))
            pubs["r2"].put(encode(_pose("tracking", 2, "r2")))
            pubs["r2"].put(encode(later))  # its frame's stamp never came: left out, not mixed in capture time
            out, err = _finish(every)
            tum_out, tum_err = _finish(tum)
        finally:
            for pub in [*pubs.values(), stamp_pub]:
                pub.undeclare()
    assert every.returncode == 0 and tum.returncode == 0, err + tum_err
    assert [line.split()[:3] for line in out.splitlines()] == [
        ["r1", "#1", "tracking"],
        ["r2", "#1", "lost"],
        ["r2", "#2", "tracking"],
    ]
    assert "3 messages from r1, r2" in err
    assert tum_out.splitlines() == [tum_line(_pose("tracking", 2, "r2"), data_set_nanos)]  # lost left out too
    assert tum_out.startswith("1305031102.175304000 ") and "1 left out (no data-set stamp)" in tum_err
    assert "TUM lines in the data set's time" in tum_err  # it says which time the file is in


@pytest.mark.multiprocess
def test_watch_into_a_reader_that_goes_away_exits_quietly() -> None:
    """`splittag watch poses | head -3` ended with a BrokenPipeError traceback, exit 1 (a trial): it
    exits as a command killed by SIGPIPE does (141), without a traceback."""
    with _router() as (endpoint, session):
        publisher = session.declare_publisher(keys.camera_pose("robot1"))
        proc = _light_cli("watch", "poses", "--connect", endpoint)
        try:
            _wait_subscribed(publisher, proc)
            publisher.put(encode(_pose("tracking", 1)))
            assert proc.stdout is not None and proc.stdout.readline().startswith("robot1 #1 tracking")
            proc.stdout.close()  # the reader goes away, as head does
            for seq in range(2, 6):
                publisher.put(encode(_pose("tracking", seq)))
                time.sleep(0.1)
            assert proc.wait(timeout=20) == 141
            assert proc.stderr is not None and "Traceback" not in proc.stderr.read()
        finally:
            publisher.undeclare()
            if proc.poll() is None:
                proc.kill()
                proc.wait()


@pytest.mark.multiprocess
def test_watch_says_when_the_messages_stop() -> None:
    """A watch whose deployment stopped waited in silence (a trial): it says so once, and SIGTERM ends it
    with its summary, as Ctrl-C does."""
    with _router() as (endpoint, session):
        publisher = session.declare_publisher(keys.controller("robot1"))
        proc = _light_cli("watch", "controller", "--connect", endpoint)
        try:
            _wait_subscribed(publisher, proc)
            publisher.put(encode(_messages()["ControllerState"]))  # type: ignore[arg-type]
            time.sleep(QUIET_HINT_SECS + 1.5)
            proc.terminate()
            time.sleep(0.05)
            proc.send_signal(signal.SIGINT)  # a second one while it ends (`timeout` and its child both signalled)
            out, err = _finish(proc)
        finally:
            publisher.undeclare()
    assert proc.returncode == 0 and out.startswith("robot1 k=7"), err
    assert "nothing more on splittag/robot1/controller/v2 for 5 s: has the deployment stopped?" in err
    assert "1 message, 0 refused" in err and "Traceback" not in err  # the summary, after SIGTERM, once


@pytest.mark.multiprocess
def test_watch_says_when_nothing_comes_and_exits_nonzero() -> None:
    with _router() as (endpoint, _session):
        proc = _light_cli("watch", "controller", "--connect", endpoint, "--duration", str(QUIET_HINT_SECS + 1))
        out, err = _finish(proc)
        # ended before the hint's 5 s: said at the end all the same, with who publishes it (a trial's
        # `watch controller` with no controller running said only '0 messages')
        short = _light_cli("watch", "controller", "--connect", endpoint, "--duration", "1")
        _, short_err = _finish(short)
    assert proc.returncode == 1 and out == ""
    assert "nothing on splittag/robot1/controller/v2 yet" in err and "0 messages" in err
    assert "`splittag up --controller`" in err and err.count("nothing") == 1  # (once)
    assert short.returncode == 1 and "nothing came on splittag/robot1/controller/v2" in short_err
    assert "runs only when asked" in short_err


@pytest.mark.multiprocess
def test_split_map_and_stats_as_a_light_client() -> None:
    tag_map = _messages()["TagMap"]
    asked: list[str] = []

    def on_map(query: zenoh.Query) -> None:
        asked.append(str(query.selector))
        query.reply(keys.tag_map("robot1"), encode(tag_map))  # type: ignore[arg-type]

    guard = InputGuard("slam")
    guard.run("tag_poses", 10, lambda: None)
    with _router() as (endpoint, session):
        queryables = [
            serve_split(
                session,
                keys.split("robot1"),
                SplitState(SplitConfig(k=7, codec="fp16", pinned=False, source="default")),
            ),
            session.declare_queryable(keys.tag_map("robot1"), on_map),
            serve_stats(session, keys.stats("robot1", "slam"), guard, lambda: {"frames": 7}),
        ]
        try:
            proc = _light_cli("map", "--connect", endpoint, "--json", "--save")
            out, err = _finish(proc)
            assert proc.returncode == 0, err
            assert json.loads(out)["revision"] == 2 and asked[-1].endswith("?save=1") and "saved: slam wrote" in err
            proc = _light_cli("map", "--connect", endpoint)
            out, err = _finish(proc)
            assert proc.returncode == 0 and out.splitlines() == map_text(tag_map), err  # type: ignore[arg-type]
            proc = _light_cli("stats", "--connect", endpoint)
            out, err = _finish(proc)
            assert proc.returncode == 0, err
            assert out.strip() == "robot1/slam              accepted 1 (tag_poses 1)  refused 0  frames=7"
            # a reply that is not what it should be is refused in one line, not shown
            queryables.append(
                session.declare_queryable(keys.tag_map("bad"), lambda q: q.reply(keys.tag_map("bad"), b"junk"))
            )
            queryables.append(
                session.declare_queryable(
                    keys.stats("bad", "slam"), lambda q: q.reply(keys.stats("bad", "slam"), b"not json")
                )
            )
            for args, said in (
                (("map",), "refused a reply from splittag/bad/map/v3"),
                (("stats",), "splittag/bad/slam/stats answered no JSON"),
            ):
                proc = _light_cli(*args, "--connect", endpoint, "--robot-id", "bad")
                out, err = _finish(proc)
                assert proc.returncode == 1 and said in err and "Traceback" not in err and out == "", err
            # every robot's: the good map shown, the bad reply said beside it
            proc = _light_cli("map", "--robot-id", "*", "--connect", endpoint)
            out, err = _finish(proc)
            assert proc.returncode == 0 and out.splitlines() == map_text(tag_map), err  # type: ignore[arg-type]
            assert "refused a reply from splittag/bad/map/v3" in err
            proc = _light_cli("stats", "--connect", endpoint, "--robot-id", "nobody")
            out, err = _finish(proc)
            assert proc.returncode == 1 and "splittag stats: no reply on splittag/nobody/*/stats" in err
            proc = _light_cli("split", "set", "3", "--connect", endpoint)
            out, err = _finish(proc)
            assert proc.returncode == 0 and out.strip() == "robot1 k=3 codec=fp16 pinned=True source=user", err
            proc = _light_cli("split", "get", "--robot-id", "*", "--connect", endpoint)
            out, err = _finish(proc)
            assert proc.returncode == 0 and out.strip() == "robot1 k=3 codec=fp16 pinned=True source=user", err

            proc = _light_cli("split", "set", "9", "--connect", endpoint)
            out, err = _finish(proc)
            assert proc.returncode == 2 and "Traceback" not in err, err
        finally:
            for q in queryables:
                q.undeclare()


def _lines_into(proc: subprocess.Popen[str], lines: queue.Queue[str]) -> None:
    for line in proc.stdout or ():
        lines.put(line)


def readme_example() -> str:
    """The README's pose listener (the python block after its marker)."""
    text = (REPO / "README.md").read_text()
    after = text.split("<!-- pose listener example -->", 1)[1]
    return after.split("```python\n", 1)[1].split("```", 1)[0]


@pytest.mark.multiprocess
def test_the_readme_pose_listener_runs_as_a_light_client() -> None:
    code = readme_example()
    assert '"tcp/127.0.0.1:7447"' in code
    lines: queue.Queue[str] = queue.Queue()
    with _router() as (endpoint, session):
        publisher = session.declare_publisher(keys.camera_pose("robot1"))
        program = LIGHT_CLI.split("from shared.tools.cli import")[0] + code.replace("tcp/127.0.0.1:7447", endpoint)
        proc = subprocess.Popen(
            [sys.executable, "-u", "-c", program], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        threading.Thread(target=_lines_into, args=(proc, lines), daemon=True).start()
        try:
            _wait_subscribed(publisher, proc)
            publisher.put(b"garbage")
            publisher.put(encode(_pose("lost", 1)))
            publisher.put(encode(_pose("tracking", 2)))
            publisher.put(encode(_pose("tracking", 3).model_copy(update={"covariance_world": None})))
            got = [lines.get(timeout=20.0) for _ in range(3)]
        finally:
            publisher.undeclare()
            proc.kill()
            _finish(proc)
    pose = _pose()
    xyz = np.asarray(pose.world_from_camera)[:3, 3].round(3)
    sigma = np.trace(np.asarray(pose.covariance_world)[:3, :3]) ** 0.5 * 100
    assert got[0].startswith("refused: ")
    assert got[1] == f"2 {pose.capture_nanos} {xyz} {sigma:.1f} cm\n"
    assert got[2] == f"3 {pose.capture_nanos} {xyz} -\n"


@pytest.mark.multiprocess
def test_no_router_is_one_line_in_a_light_client() -> None:
    port = free_tcp_port()  # nothing listens there
    for args in (["split", "get"], ["map"], ["stats"], ["watch", "poses", "--wait-secs", "0"]):
        proc = _light_cli(*args, "--connect", f"tcp/127.0.0.1:{port}")
        _out, err = _finish(proc, 30.0)
        assert proc.returncode == 1 and "Unable to connect" in err and "Traceback" not in err, (args, err)


@pytest.mark.multiprocess
def test_a_watch_started_before_the_run_waits_for_its_router() -> None:
    """`splittag watch` just before `splittag up`: the router comes up seconds later (a trial's watch
    failed with "Unable to connect" and its run's poses were lost); it now keeps trying, and says so."""
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    proc = _light_cli("watch", "poses", "--robot-id", "r1", "--connect", endpoint, "--count", "1", "--wait-secs", "40")
    try:
        assert proc.stderr is not None
        line = proc.stderr.readline()  # after the first attempt
        assert re.search(rf"no router at {endpoint} yet; trying for 3\d s more", line), line
        session = open_session(ZenohSettings(mode="router", listen=[endpoint]))
        try:
            publisher = session.declare_publisher(keys.camera_pose("r1"))
            _wait_subscribed(publisher, proc)
            publisher.put(encode(_pose(robot_id="r1")))
            out, err = _finish(proc)
            publisher.undeclare()
        finally:
            session.close()
    finally:
        _finish(proc, 1.0)
    assert proc.returncode == 0, err
    assert out.split()[:3] == ["r1", "#3", "tracking"] and "1 message" in err, (out, err)


def test_a_command_a_light_install_cannot_run_says_so_in_one_line() -> None:
    proc = _light_cli("settings", "camera")
    _out, err = _finish(proc)
    assert proc.returncode == 2 and "Traceback" not in err, err
    assert "this command needs the full install" in err and "a light install runs only split, watch" in err


def test_bad_arguments_are_one_line_before_any_connection() -> None:
    for args, said in (
        (["watch", "tags", "--format", "tum"], "--format tum is for poses"),
        (["watch", "poses", "--count", "0"], "must be positive"),
        (["watch", "poses", "--robot-id", "a/b"], "robot id 'a/b'"),
        (["map", "--robot-id", "*", "--save"], "--save names one robot"),
        (["stats", "--connect", "tls/127.0.0.1:7447"], "give --certs"),
        (["watch", "poses", "--robot-id", "*", "--format", "tum"], "one robot's trajectory"),
        (["split", "set", "4", "--robot-id", "*"], "names one robot"),
        (["split", "get", "--robot-id", "a b"], "robot id 'a b'"),
    ):
        proc = _light_cli(*args)
        _out, err = _finish(proc)
        assert proc.returncode == 2 and said in err and "Traceback" not in err, (args, err)


def test_a_reader_that_cannot_connect_is_told_where_the_run_listens(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Under --link the edge's router is on the emulated link's address: a trial's `split get` without
    --connect only heard that 127.0.0.1:7447 was unreachable."""
    import argparse
    import os

    from shared.tools.cli import _endpoint_hint

    runs = tmp_path / "runs"
    args = argparse.Namespace(connect=["tcp/127.0.0.1:7447"], identity="operator")
    assert _endpoint_hint(args, runs) == "; no deployment is running here (`splittag up` or `make demo` starts one)"
    remote = argparse.Namespace(connect=["tcp/192.0.2.7:7447"], identity="operator")
    assert _endpoint_hint(remote, runs) == ""  # another host's deployment: nothing to say about this one
    (runs / "current").mkdir(parents=True)
    config = runs / "current" / "config.toml"
    config.write_text('[monitor]\nconnect = ["tcp/10.78.0.2:7447"]\n')
    assert _endpoint_hint(args, runs) == ""  # just written: its launcher may still be starting
    (runs / "current" / "summary.json").write_text("{}")  # ... unless it has finished (a trial waited 2 minutes)
    assert _endpoint_hint(args, runs) == "; no deployment is running here (the last one, current, has ended)"
    (runs / "current" / "summary.json").unlink()
    old = time.time() - 600
    os.utime(config, (old, old))
    # A run that has ended: its address is not where to go (two trials were sent to a finished run's)
    assert _endpoint_hint(args, runs) == "; no deployment is running here (the last one, current, has ended)"
    assert _endpoint_hint(remote, runs) == ""
    # a live one (a process standing in for its camera service)
    service = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)", "services.camera"])
    try:
        (runs / "current" / "pids").write_text(f"camera {service.pid}\n")
        assert _endpoint_hint(args, runs).endswith("listens at tcp/10.78.0.2:7447 (--connect tcp/10.78.0.2:7447)")
        assert _endpoint_hint(argparse.Namespace(connect=None, identity="operator"), runs) != ""
        assert _endpoint_hint(argparse.Namespace(connect=["tcp/10.78.0.2:7447"], identity="operator"), runs) == ""
        # a reader left at the default endpoint while the live run listens elsewhere is told at once (the
        # default may be another deployment's: a trial recorded a second deployment's poses)
        from shared.tools.cli import _reader_settings

        default = argparse.Namespace(connect=[], certs=None, identity="operator", robot_id="robot1")
        assert _reader_settings(default, "watch", runs) is not None
        assert capsys.readouterr().err == (
            "splittag watch: note: reading the default tcp/127.0.0.1:7447; the deployment in "
            f"{runs}/current listens at tcp/10.78.0.2:7447 (--connect tcp/10.78.0.2:7447)\n"
        )
        # steering it is refused: it would change whoever owns the default endpoint (an integrator's note)
        assert _reader_settings(default, "split set", runs, steers=True) is None
        assert capsys.readouterr().err.startswith(
            f"splittag split set: not sent to the default tcp/127.0.0.1:7447; the deployment in {runs}/current "
            "listens at tcp/10.78.0.2:7447 (--connect tcp/10.78.0.2:7447): give --connect"
        )
        given = argparse.Namespace(connect=["tcp/127.0.0.1:7447"], certs=None, identity="operator", robot_id="r1")
        assert _reader_settings(given, "split", runs, steers=True) is not None  # asked for it
        assert _reader_settings(given, "watch", runs) is not None and capsys.readouterr().err == ""  # asked for it
    finally:
        service.kill()
        service.wait()
    # the launcher's own failure (not a reader) names its endpoints itself: no hint that repeats them
    assert _endpoint_hint(argparse.Namespace(config=Path("x.toml")), runs) == ""


def test_a_reader_takes_a_second_endpoint() -> None:
    """`--connect` twice: a trial's second endpoint silently replaced the first."""
    from shared.tools.cli import build_parser, split_endpoint

    args = build_parser().parse_args(
        ["watch", "poses", "--connect", "tcp/10.0.0.2:7447", "--connect", "tcp/10.0.0.3:7448"]
    )
    assert split_endpoint(args.connect, tls=False) == ["tcp/10.0.0.2:7447", "tcp/10.0.0.3:7448"]
    assert split_endpoint(None, tls=True) == ["tls/127.0.0.1:7447"]
