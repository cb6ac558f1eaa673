"""The launcher's live monitor stays bounded in a deployment that runs for days."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from shared.tools.launch import Monitor
from shared.wire.messages import CameraPose, FrameStamp, TagPoses, encode
from tests.examples import example_messages

EXAMPLES = example_messages()


def test_records_and_ground_truth_are_bounded() -> None:
    poses = EXAMPLES[TagPoses.SCHEMA]
    gt = EXAMPLES[CameraPose.SCHEMA]
    assert isinstance(poses, TagPoses) and isinstance(gt, CameraPose)
    monitor = Monitor(None, max_records=10, max_ground_truth=5)
    for seq in range(25):
        monitor.on_gt(encode(gt.model_copy(update={"seq": seq})))
        monitor.on_poses(encode(poses.model_copy(update={"seq": seq})))
    assert len(monitor.records) <= 10 and monitor.frames_total == 25
    assert [r["seq"] for r in monitor.records][-1] == 24  # the newest are kept
    assert sorted(monitor.gt) == [20, 21, 22, 23, 24]
    summary = monitor.summary()
    assert summary["frames_total"] == 25 and summary["frames"] == len(monitor.records)
    assert summary["frames_captured"] == 25 and summary["frames_skipped"] == 0


def test_the_summary_says_how_many_captured_frames_the_robot_skipped() -> None:
    """robot_infer takes the newest frame; a camera faster than the robot skips frames, which a data-set
    trial found said nowhere (144 of 150 posed). The camera's ground truth and data-set stamps count
    what it captured."""
    from shared.wire.messages import FrameStamp

    poses, stamp = EXAMPLES[TagPoses.SCHEMA], EXAMPLES[FrameStamp.SCHEMA]
    assert isinstance(poses, TagPoses) and isinstance(stamp, FrameStamp)
    monitor = Monitor(None)
    assert "frames_captured" not in monitor.summary()  # a source that says neither: unknown
    for seq in range(10):
        monitor.on_stamp(encode(stamp.model_copy(update={"seq": seq})))
        if seq % 3:
            monitor.on_poses(encode(poses.model_copy(update={"seq": seq})))
    summary = monitor.summary()
    assert (summary["frames_captured"], summary["frames_total"], summary["frames_skipped"]) == (10, 6, 4)


def test_unbounded_by_default_for_benchmarks() -> None:
    poses = EXAMPLES[TagPoses.SCHEMA]
    assert isinstance(poses, TagPoses)
    monitor = Monitor(None)
    for seq in range(50):
        monitor.on_poses(encode(poses.model_copy(update={"seq": seq})))
    assert len(monitor.records) == 50  # benchmarks slice records by index


def test_the_live_line_and_summary_say_how_sure_slam_is_and_how_far_off() -> None:
    """SLAM poses with covariance: the line shows slam's status, median position sigma and error against
    ground truth (with a tag map that fixes slam's world), the summary counts statuses."""
    import numpy as np

    from shared.tools.launch import demo_tag_map

    poses, gt = EXAMPLES[TagPoses.SCHEMA], EXAMPLES[CameraPose.SCHEMA]
    assert isinstance(poses, TagPoses) and isinstance(gt, CameraPose)
    monitor = Monitor(demo_tag_map())
    cov = np.diag([1e-4, 1e-4, 2e-4, 1e-6, 1e-6, 1e-6])  # position sigma sqrt(4e-4) = 2 cm
    for seq in range(5):
        truth = gt.model_copy(update={"seq": seq, "status": "ground_truth", "covariance_world": None})
        monitor.on_gt(encode(truth))
        slam_pose = np.array(truth.world_from_camera)
        status = "tracking" if seq < 2 else "bridged" if seq < 4 else "lost"
        slam_pose[0, 3] += 0.03 if status == "tracking" else 0.5  # a bridged or repeated pose is no measure
        cam = truth.model_copy(
            update={"status": status, "world_from_camera": slam_pose, "covariance_world": None if seq == 4 else cov}
        )
        monitor.on_camera(encode(cam))
        monitor.on_poses(encode(poses.model_copy(update={"seq": seq})))
    monitor.on_camera(b"not a message")
    line = monitor.line()
    assert "| slam lost sigma 2.0 cm e 3.0 cm" in line, line
    assert poses.link is not None and "k=" in line and "on board" not in line
    monitor.on_poses(encode(poses.model_copy(update={"seq": 5, "link": None})))  # computed on board
    assert "on board (the edge away)" in monitor.line() and "payload" not in monitor.line()
    summary = monitor.summary()
    assert summary["slam_frames"] == {"tracking": 2, "bridged": 2, "lost": 1}
    assert summary["frames_without_slam_pose"] == 1  # the on-board frame's pose never came (slam down)
    assert abs(summary["slam_sigma_cm_median"] - 2.0) < 1e-9
    assert abs(summary["slam_online_error_cm_median"] - 3.0) < 1e-9
    assert summary["bad_messages"] == 1
    # NEES of the two tracking poses: 3 cm along x under a 1 cm x sigma is 9 (calibrated would be 3 on
    # average): the covariance understates by 3x here, the factor slam's covariance_scale would take
    assert summary["slam_position_nees_mean"] == pytest.approx(9.0)
    assert summary["slam_covariance_scale_measured"] == pytest.approx(3.0)
    assert summary["slam_position_nees_median"] == pytest.approx(9.0)  # the two regimes: see the median
    assert summary["slam_position_inside95_pct"] == 0.0  # 9 > 7.81, the 95 % quantile of chi-square(3)


def test_the_monitor_says_where_frames_wait_outside_their_compute() -> None:
    """From a TagPoses' stamps: captured at C, sent at C + 30 ms after 20 ms of robot compute (the frame
    was 10 ms old when taken), received at C + 32, its pose at C + 60 after 25 ms of edge compute (3 ms
    queued). A frame computed on board (no link) has no such split."""
    poses = EXAMPLES[TagPoses.SCHEMA]
    assert isinstance(poses, TagPoses) and poses.link is not None
    c = 1_000_000_000_000
    ms = 1_000_000
    timed = poses.model_copy(
        update={
            "capture_nanos": c,
            "link": poses.link.model_copy(update={"sent_nanos": c + 30 * ms, "received_nanos": c + 32 * ms}),
            "timings": poses.timings.model_copy(
                update={
                    "robot_compute_secs": 0.020,
                    "transport_secs": 0.002,
                    "edge_compute_secs": 0.025,
                    "capture_to_pose_secs": 0.060,
                }
            ),
        }
    )
    monitor = Monitor(None)
    monitor.on_poses(encode(timed))
    monitor.on_poses(encode(timed.model_copy(update={"seq": 2, "link": None})))
    first, on_board = monitor.records
    assert abs(first["before_robot_ms"] - 10.0) < 1e-6 and abs(first["at_edge_ms"] - 3.0) < 1e-6
    assert np.isnan(on_board["before_robot_ms"]) and np.isnan(on_board["at_edge_ms"])
    assert first["edge_done_nanos"] == c + 60 * ms and np.isnan(on_board["edge_done_nanos"])
    assert "capture->pose   60.0 ms (frame age 10.0)" in monitor.line(), monitor.line()
    summary = monitor.summary()
    assert abs(summary["frame_age_ms_p50"] - 10.0) < 1e-6 and abs(summary["edge_queue_ms_p50"] - 3.0) < 1e-6


def test_the_monitor_measures_in_the_world_of_the_map_slam_is_given(tmp_path: Path) -> None:
    """The launcher's monitor takes the run config's `slam.tag_map` (none when it names none)."""
    from shared.tools.launch import run_tag_map
    from shared.vision.tagmap import TagMapFile, TagSpec, write_tag_map

    own = TagMapFile(
        tags=[TagSpec(id=42, size_m=0.2, world_from_tag=[[1, 0, 0, 1], [0, 1, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])]
    )
    write_tag_map(tmp_path / "map.json", own)
    config = tmp_path / "config.toml"
    config.write_text(f'[slam]\ntag_map = "{tmp_path / "map.json"}"\n')
    assert run_tag_map(config) == own
    config.write_text("[slam]\n")
    assert run_tag_map(config) is None


def test_the_live_line_says_how_long_the_poses_have_stopped() -> None:
    """Before the first TagPoses it waits; once they stop it says for how long and since which frame,
    and where to look: the edge while the robot's camera still streams (the robot computes on board,
    out of a monitor's sight at the edge), the robot's host when its ground truth stopped too."""
    now = [100.0]
    monitor = Monitor(None, clock=lambda: now[0])
    assert monitor.line() == "waiting for TagPoses..."
    poses = EXAMPLES[TagPoses.SCHEMA]
    assert isinstance(poses, TagPoses)
    monitor.on_poses(encode(poses.model_copy(update={"seq": 41})))
    now[0] += 5.0
    line = monitor.line()
    assert line.startswith("no TagPoses for 5.0 s (the last: frame 41)") and "is the robot up, and the edge?" in line
    # The camera's ground truth still streaming: the robot's side is up, the poses stopped: the edge.
    truth = EXAMPLES[CameraPose.SCHEMA]
    assert isinstance(truth, CameraPose)
    monitor.on_gt(encode(truth.model_copy(update={"seq": 60})))
    now[0] += 1.0
    line = monitor.line()
    assert line.startswith("no TagPoses for 6.0 s") and "while its camera streams; is the edge up?" in line, line
    # Both stopped (a robot's host went down: found by a fresh-clone trial, which was told to check the edge).
    now[0] += 4.0
    line = monitor.line()
    assert "nor its camera's ground truth or stamps for 5.0 s; is the robot's host up" in line, line
    # The poses caught up with the camera's last frame (a folder's end): the camera went quiet, not the edge
    # (a trial's runs ended with 'is the edge up?' in 3 of 9).
    ended = Monitor(None, clock=lambda: now[0])
    ended.on_gt(encode(truth.model_copy(update={"seq": 299})))
    ended.on_poses(encode(poses.model_copy(update={"seq": 299})))
    now[0] += 1.1
    assert "the camera has sent nothing newer for 1.1 s" in ended.line(), ended.line()
    # A data set without ground truth (a video, a folder with rgb.txt): its stamps say the same (a trial's
    # video run, ended by max_frames, was asked 'is the robot up?').
    stamped = Monitor(None, clock=lambda: now[0])
    stamp = EXAMPLES[FrameStamp.SCHEMA]
    assert isinstance(stamp, FrameStamp)
    stamped.on_stamp(encode(stamp.model_copy(update={"seq": 119})))
    stamped.on_poses(encode(poses.model_copy(update={"seq": 119})))
    now[0] += 1.3
    assert "the camera has sent nothing newer for 1.3 s" in stamped.line(), stamped.line()
    # At the robot's own router (a fleet's robot host), on-board poses arrive: the silence is robot_infer's.
    at_robot = Monitor(None, clock=lambda: now[0], at_robot=True)
    at_robot.on_poses(encode(poses.model_copy(update={"seq": 41})))
    at_robot.on_gt(encode(truth.model_copy(update={"seq": 60})))
    now[0] += 1.5
    assert "is robot_infer running?" in at_robot.line(), at_robot.line()
    # The launcher knows which process is restarting: that, not a guess (a trial's monitor asked whether
    # the edge was up while robot_infer was the one killed).
    assert at_robot.line(down=["robot_infer"]).endswith(": robot_infer exited and is not back yet")
    assert monitor.line(down=["edge_infer", "slam"]).endswith(": edge_infer and slam exited and are not back yet")
    # ... and which came back moments ago, still starting (a trial was asked about the edge just after
    # robot_infer came back, loading its network)
    assert at_robot.line(back={"robot_infer": now[0] - 0.5}).endswith(
        ": robot_infer came back from a restart moments ago and may still be starting up"
    )
    # a silence that began after it came back is not its restart's (review)
    assert "came back" not in at_robot.line(back={"robot_infer": now[0] - 3.0})


def test_no_slam_error_when_slam_works_in_a_world_of_its_own() -> None:
    """A slam without a tag map (a fleet's, by default) works in its anchor tag's frame: its poses are
    not comparable with ground truth, so the monitor reports no error rather than a meaningless one."""
    import numpy as np

    from shared.tools.launch import demo_tag_map

    gt = EXAMPLES[CameraPose.SCHEMA]
    assert isinstance(gt, CameraPose)
    monitor = Monitor(demo_tag_map(), slam_has_map=False)
    truth = gt.model_copy(update={"seq": 3, "status": "ground_truth", "covariance_world": None})
    monitor.on_gt(encode(truth))
    cam = truth.model_copy(update={"status": "tracking", "covariance_world": np.eye(6) * 1e-4})
    monitor.on_camera(encode(cam))
    summary = monitor.summary()
    assert summary["slam_frames"] == {"tracking": 1} and "slam_online_error_cm_median" not in summary, summary


def test_the_run_has_one_tag_map_and_the_demos_only_for_the_demo(tmp_path: Path) -> None:
    """A run config's tag map: the one the config names, under [slam] alone, is given to edge_infer and
    robot_infer too (the edge solving tags at other sizes than slam maps them with gave a 22 cm ATE);
    none named: the demo scene's map for the demo source only. Another source without a map used to
    get the demo's map silently (a user's tags at the demo's sizes and poses: 37 cm ATE)."""
    import tomllib

    from shared.tools.launch import MAP_USERS, demo_tag_map, write_run_config
    from shared.vision.tagmap import load_tag_map

    def tables(base: str, name: str) -> dict[str, dict[str, object]]:
        (tmp_path / f"{name}.toml").write_text(base)
        run = tmp_path / name
        run.mkdir()
        return tomllib.loads(write_run_config(run, tmp_path / f"{name}.toml").read_text())

    demo = tables("[camera]\n", "demo")
    assert {demo[s]["tag_map"] for s in MAP_USERS} == {str(tmp_path / "demo" / "tag_map.yaml")}
    assert load_tag_map(tmp_path / "demo" / "tag_map.yaml") == demo_tag_map()
    folder = tables('[camera]\nsource = "folder"\n', "folder")
    assert all("tag_map" not in folder.get(s, {}) for s in MAP_USERS)
    assert not (tmp_path / "folder" / "tag_map.yaml").exists()
    own = tables('[camera]\nsource = "folder"\n[slam]\ntag_map = "mine.yaml"\n', "own")
    assert {own[s]["tag_map"] for s in MAP_USERS} == {"mine.yaml"}
    both = tables('[edge_infer]\ntag_map = "edge.yaml"\n[slam]\ntag_map = "mine.yaml"\n', "both")
    assert [both[s]["tag_map"] for s in MAP_USERS] == ["edge.yaml", "mine.yaml", "mine.yaml"]


def test_a_fleets_demo_map_leaves_slam_to_map_and_relative_maps_are_the_services(tmp_path: Path) -> None:
    """The fleet runner takes the same one-map rule, the demo's map for the robots' perception only
    (slam builds the fleet's map); a relative tag_map is read from the repository root, as the services
    (started there) read it, wherever the launcher runs."""
    from shared.tools.launch import REPO, run_map_tables, run_tag_map

    tables, path = run_map_tables({}, tmp_path, demo_users=("edge_infer", "robot_infer"))
    assert set(tables) == {"edge_infer", "robot_infer"} and path == tmp_path / "tag_map.yaml"
    tables, path = run_map_tables({"camera": {"source": "folder"}, "robot_infer": {"tag_map": "m.yaml"}}, tmp_path)
    assert tables == {"edge_infer": {"tag_map": "m.yaml"}, "slam": {"tag_map": "m.yaml"}} and path == REPO / "m.yaml"
    config = tmp_path / "config.toml"
    config.write_text('[slam]\ntag_map = "deploy/fleet_tag_map_that_is_not_there.yaml"\n')
    from shared.vision.tagmap import TagMapError

    with pytest.raises(TagMapError, match=str(REPO / "deploy")):
        run_tag_map(config)


def test_a_run_started_from_another_directory_gets_an_absolute_folder_and_a_refused_one_none(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The services start in the repository, the launcher anywhere: the run folder it hands them is
    absolute (a trial's `splittag up` from another directory failed: 'config file runs/... does not
    exist'), and a run refused before anything started (a tag map naming a tag twice) leaves no runs/
    behind, in one line and exit 2."""
    import subprocess
    import sys
    import time

    from shared.tools.launch import preparing_run_dir

    monkeypatch.chdir(tmp_path)
    with preparing_run_dir(Path("runs")) as run:
        assert run.is_absolute() and run.parent == tmp_path / "runs"
    assert (tmp_path / "runs" / "current").resolve() == run
    # a second run refused: the first stays, and runs/current still points at it (`splittag down` finds it)
    time.sleep(1.1)
    with pytest.raises(RuntimeError), preparing_run_dir(Path("runs")) as refused:
        raise RuntimeError("a refused configuration")
    assert run.is_dir() and not refused.exists() and (tmp_path / "runs" / "current").resolve() == run
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "map.yaml").write_text("tags:\n- {id: 286, size_m: 0.166}\n- {id: 286, size_m: 0.2}\n")
    (elsewhere / "mine.toml").write_text(f'[slam]\ntag_map = "{elsewhere / "map.yaml"}"\n')
    out = subprocess.run(
        [sys.executable, "-m", "shared.tools.cli", "up", "--config", str(elsewhere / "mine.toml"), "--duration", "1"],
        cwd=elsewhere,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 2 and "listed more than once: [286]" in out.stderr, out.stderr
    assert len(out.stderr.strip().splitlines()) == 1 and not (elsewhere / "runs").exists(), out.stderr


def test_frames_csv_joins_each_frame_with_the_controller_and_the_link_as_of_its_send(tmp_path: Path) -> None:
    """frames.csv (a fresh-clone trial had to as-of join the recording's controller rows to frames by
    hand): T(k) for the frame's k from the controller's last decision before the frame was sent, even
    when that state arrives after the frame's poses (it crosses the uplink behind the frames: review),
    only decisions that are predictions (before both compute profiles the state carries zeros), and the
    link profile applied before the send; a frame computed on board crossed no link."""
    import csv

    from shared.tools.launch import FRAME_COLUMNS, frame_rows, write_frames_csv
    from shared.wire.messages import CONTROLLER_WAITING, ControllerState, LinkStamps

    poses, state = EXAMPLES[TagPoses.SCHEMA], EXAMPLES[ControllerState.SCHEMA]
    assert isinstance(poses, TagPoses) and isinstance(state, ControllerState) and poses.link is not None
    t = poses.link.sent_nanos
    monitor = Monitor(None)

    def frame(seq: int, sent: int | None) -> None:
        link = None
        if sent is not None:
            link = LinkStamps(sent_nanos=sent, received_nanos=sent + 40_000_000, previous_received_nanos=0)
        monitor.on_poses(encode(poses.model_copy(update={"seq": seq, "link": link})))

    zeros = [0.0] * 8
    waiting = state.model_copy(
        update={"stamp_nanos": t, "robot_ms_by_k": zeros, "predicted_ms_by_k": zeros, "reason": CONTROLLER_WAITING}
    )
    first = state.model_copy(update={"stamp_nanos": t + 10, "predicted_ms_by_k": [100.0 + k for k in range(8)]})
    second = state.model_copy(update={"stamp_nanos": t + 30, "predicted_ms_by_k": [200.0 + k for k in range(8)]})
    assert not waiting.has_prediction and first.has_prediction
    monitor.on_controller(encode(waiting))
    assert monitor._controller_part() == f"  | controller: {CONTROLLER_WAITING}"
    frame(0, t + 5)  # sent while the controller waited
    frame(1, t + 20)  # sent after the first prediction ...
    monitor.on_controller(encode(second))  # ... whose state arrives late, after a newer one
    monitor.on_controller(encode(first))
    frame(2, t + 40)
    frame(3, None)  # computed on board
    events = [
        {"unix_nanos": t + 1, "profile": "5g", "rate_mbit": 45.51, "delay_ms": 39.9},
        {"unix_nanos": t + 25, "profile": "5g-pre-tdd", "rate_mbit": 14.2, "delay_ms": 39.9},
    ]
    records, predictions = monitor.snapshot()
    rows = frame_rows(records, events, predictions)
    k = poses.split_k
    assert [r["predicted_ms"] for r in rows] == [None, 100.0 + k, 200.0 + k, None]
    assert rows[1]["controller_best_k"] == state.best_k and rows[0]["controller_t0_ms"] is None
    assert [r["link_profile"] for r in rows] == ["5g", "5g", "5g-pre-tdd", None]
    assert rows[2]["link_rate_mbit"] == 14.2 and rows[3]["frame_age_ms"] is None
    write_frames_csv(tmp_path / "frames.csv", rows)
    with (tmp_path / "frames.csv").open() as f:
        read = list(csv.DictReader(f))
    assert tuple(read[0]) == FRAME_COLUMNS and len(read) == 4
    assert read[0]["predicted_ms"] == "" and float(read[2]["predicted_ms"]) == 200.0 + k
    assert int(read[1]["sent_unix_nanos"]) == t + 20 and read[3]["sent_unix_nanos"] == ""
    assert float(read[2]["e2e_ms"]) == pytest.approx(1e3 * poses.timings.capture_to_pose_secs)


def test_frames_csv_is_written_as_the_run_goes_every_frame_once(tmp_path: Path) -> None:
    """frames.csv used to be written at the run's end from the monitor's newest 200,000 records: a long
    run lost its first frames, and a launcher that died left none. Now each frame is written `lag_secs`
    after its poses arrived (the controller's decision and the link profile are known by then), once."""
    import csv

    from shared.tools.launch import FramesCsv

    poses = EXAMPLES[TagPoses.SCHEMA]
    assert isinstance(poses, TagPoses)
    now = [0.0]
    monitor = Monitor(None, max_records=4, clock=lambda: now[0])
    path = tmp_path / "frames.csv"
    frames_csv = FramesCsv(path, monitor, lambda: [], lag_secs=10.0)

    def seqs() -> list[int]:
        with path.open() as f:
            return [int(row["seq"]) for row in csv.DictReader(f)]

    assert seqs() == []  # the header is there from the start
    for seq in range(3):  # arrive at t = 0, 1, 2
        now[0] = float(seq)
        monitor.on_poses(encode(poses.model_copy(update={"seq": seq})))
    now[0] = 11.5
    frames_csv.flush()
    assert seqs() == [0, 1] and frames_csv.rows == 2
    frames_csv.flush()
    assert seqs() == [0, 1]  # nothing twice
    for seq in range(3, 9):  # the monitor keeps at most 4 records
        now[0] = 12.0 + seq
        monitor.on_poses(encode(poses.model_copy(update={"seq": seq})))
    # The monitor halved its records twice meanwhile; frames it dropped before they were written are counted.
    now[0] = 100.0
    frames_csv.flush()
    kept = [r["seq"] for r in monitor.records]
    assert seqs() == [0, 1, *kept] and frames_csv.missed == 9 - 2 - len(kept)
    now[0] = 101.0
    monitor.on_poses(encode(poses.model_copy(update={"seq": 9})))
    frames_csv.flush()
    assert seqs()[-1] != 9  # not yet: it arrived a second ago
    frames_csv.flush(final=True)
    assert seqs() == [0, 1, *kept, 9] and frames_csv.rows == 3 + len(kept)


def test_a_frames_csv_that_cannot_be_written_does_not_stop_the_run(tmp_path: Path) -> None:
    """A failed write (disk full, the run folder removed) used to raise out of the launcher's loop, stop
    every service and lose the summary (review): it is said, and the rows are counted as missed."""
    from shared.tools.launch import FramesCsv

    poses = EXAMPLES[TagPoses.SCHEMA]
    assert isinstance(poses, TagPoses)
    now = [0.0]
    monitor = Monitor(None, clock=lambda: now[0])
    (tmp_path / "run").mkdir()
    frames_csv = FramesCsv(tmp_path / "run" / "frames.csv", monitor, lag_secs=0.0)
    monitor.on_poses(encode(poses.model_copy(update={"seq": 1})))
    (tmp_path / "run" / "frames.csv").unlink()
    (tmp_path / "run").rmdir()  # the folder is gone: the append fails
    frames_csv.flush()
    assert (frames_csv.rows, frames_csv.missed, frames_csv.failed) == (0, 1, 1)
    (tmp_path / "run").mkdir()  # back: later frames are written, the failed one is not retried
    monitor.on_poses(encode(poses.model_copy(update={"seq": 2})))
    frames_csv.flush(final=True)
    assert (frames_csv.rows, frames_csv.missed) == (1, 1)


def test_the_summary_says_what_the_split_did() -> None:
    """Frames per cut, frames computed on board and the controller's decisions, switches and time under
    a pin are in summary.json (a trial over the emulated link had to grep controller.log for them)."""
    from shared.wire.messages import ControllerState

    monitor = Monitor(None)
    poses = EXAMPLES[TagPoses.SCHEMA]
    state = EXAMPLES[ControllerState.SCHEMA]
    assert isinstance(poses, TagPoses) and isinstance(state, ControllerState) and poses.link is not None
    for seq, k in enumerate([7, 7, 5, 7]):
        monitor.on_poses(encode(poses.model_copy(update={"seq": seq, "split_k": k})))
    monitor.on_poses(encode(poses.model_copy(update={"seq": 4, "link": None, "payload_bytes": 0})))  # on board
    for applied, pinned in [(False, False), (True, False), (False, True), (False, True)]:
        monitor.on_controller(encode(state.model_copy(update={"applied": applied, "pinned": pinned})))
    summary = monitor.summary()
    assert summary["frames_by_k"] == {"5": 1, "7": 3} and summary["frames_on_board"] == 1
    assert summary["controller"] == {"decisions": 4, "switches": 1, "pinned_fraction": 0.5}


def test_a_tag_missing_from_the_runs_map_is_said_once_and_listed() -> None:
    """A trial's map listed three of its four tags: the fourth was solved at the default size and the
    ATE went from 0.15 to 19.6 cm with no word anywhere. The monitor says it once and the summary lists it;
    a run without a map (every tag at the default size, warned at start) says nothing per tag."""
    from shared.vision.tagmap import TagMapFile, TagSpec

    poses = EXAMPLES[TagPoses.SCHEMA]
    assert isinstance(poses, TagPoses) and poses.tags
    seen = {t.tag_id for t in poses.tags}
    listed = TagMapFile(default_size_m=0.16, tags=[TagSpec(id=max(seen) + 1, size_m=0.1)])  # not those seen
    monitor = Monitor(listed)
    for seq in range(3):
        monitor.on_poses(encode(poses.model_copy(update={"seq": seq})))
    missing = sorted(seen)
    said = monitor.notices()
    assert (
        missing
        and len(said) == len(missing)
        and all("not in the run's tag map: solved at the default size" in n for n in said)
    )
    assert monitor.notices() == []  # once
    sizes = {t.tag_id: t.tag_size_m for t in poses.tags}
    assert monitor.summary()["tags_not_in_map"] == {str(i): sizes[i] for i in missing}
    for tag_map in (None, TagMapFile(default_size_m=0.2)):
        quiet = Monitor(tag_map)
        quiet.on_poses(encode(poses))
        assert quiet.notices() == [] and "tags_not_in_map" not in quiet.summary()


def test_frames_csv_carries_the_data_sets_own_stamp(tmp_path: Path) -> None:
    """A data-set trial could not join frames.csv with trajectory.tum (keyed by rgb.txt's stamps): each
    row now has the frame's `source_stamp` as trajectory.tum writes it, written exactly; empty for a
    source without stamps. Frames written as the run goes get it too."""
    import csv

    from shared.tools.launch import FramesCsv
    from shared.vision.trajectory import format_stamp_nanos
    from shared.wire.messages import FrameStamp

    poses, stamp = EXAMPLES[TagPoses.SCHEMA], EXAMPLES[FrameStamp.SCHEMA]
    assert isinstance(poses, TagPoses) and isinstance(stamp, FrameStamp)
    clock = [0.0]
    monitor = Monitor(None, clock=lambda: clock[0])
    frames_csv = FramesCsv(tmp_path / "frames.csv", monitor, lag_secs=1.0)
    source = [1305031102_175304000 + 33_333_333 * i for i in range(3)]
    for seq in range(3):
        capture = poses.capture_nanos + seq
        if seq != 1:  # frame 1 came from a source without a stamp for it
            monitor.on_stamp(
                encode(
                    stamp.model_copy(update={"seq": seq, "capture_nanos": capture, "source_stamp_nanos": source[seq]})
                )
            )
        monitor.on_poses(encode(poses.model_copy(update={"seq": seq, "capture_nanos": capture})))
    clock[0] = 5.0
    frames_csv.flush()
    with (tmp_path / "frames.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [r["source_stamp"] for r in rows] == [format_stamp_nanos(source[0]), "", format_stamp_nanos(source[2])]
    assert rows[0]["source_stamp"] == "1305031102.175304000"
    records, _ = monitor.snapshot()
    assert [r["source_stamp_nanos"] for r in records] == [source[0], None, source[2]]


def test_a_repeated_tag_poses_message_is_counted_not_recorded_again() -> None:
    """A trial re-sent 53 TagPoses: slam refused them, but the monitor counted 168 frames of 115 and
    frames.csv had a row for each. The same frame (capture time and seq) is now counted as repeated."""
    poses = EXAMPLES[TagPoses.SCHEMA]
    assert isinstance(poses, TagPoses)
    monitor = Monitor(None)
    for seq in range(5):
        frame = encode(poses.model_copy(update={"seq": seq, "capture_nanos": poses.capture_nanos + seq}))
        monitor.on_poses(frame)
        monitor.on_poses(frame)  # the same message again
    summary = monitor.summary()
    assert (summary["frames"], summary["frames_total"], summary["repeated_messages"]) == (5, 5, 5)
    assert sorted(r["seq"] for r in monitor.records) == [0, 1, 2, 3, 4]


def test_a_message_naming_another_robot_than_its_key_is_counted_bad_not_recorded() -> None:
    """A fleet trial published robot2's TagPoses on robot1's key: slam, the controller and the edge refused
    it, the launcher's monitor made it a robot1 frame (frames.csv, frames, repeated). Refused here too."""
    poses = EXAMPLES[TagPoses.SCHEMA]
    assert isinstance(poses, TagPoses)
    monitor = Monitor(None, robot_id=poses.robot_id)
    monitor.on_poses(encode(poses.model_copy(update={"robot_id": "someone_else"})))
    assert monitor.bad == 1 and not monitor.records
    monitor.on_poses(encode(poses))
    assert monitor.bad == 1 and len(monitor.records) == 1


def test_every_controller_state_is_kept_in_the_run_folder(tmp_path: Path) -> None:
    """A researcher's trial had to record the controller's stream itself: C(k), E(k), S(k), the reason,
    the pin were only live. controller.jsonl has every state, one JSON line each, as they come (the
    bounded history's dropped ones aside), each once."""
    import json

    from shared.tools.launch import FramesCsv
    from shared.wire.messages import ControllerState

    state = EXAMPLES[ControllerState.SCHEMA]
    assert isinstance(state, ControllerState)
    monitor = Monitor(None)
    path = tmp_path / "controller.jsonl"
    frames_csv = FramesCsv(tmp_path / "frames.csv", monitor, lag_secs=10.0, controller_path=path)
    for i in range(3):
        monitor.on_controller(encode(state.model_copy(update={"stamp_nanos": 1_000 + i, "chosen_k": i})))
    frames_csv.flush()  # (states need no lag: written at once)
    frames_csv.flush()
    monitor.on_controller(encode(state.model_copy(update={"stamp_nanos": 2_000, "reason": "pinned"})))
    frames_csv.flush(final=True)
    lines = [json.loads(line) for line in path.read_text().splitlines()]
    assert [line["stamp_nanos"] for line in lines] == [1_000, 1_001, 1_002, 2_000] and frames_csv.controller_lines == 4
    assert [line["chosen_k"] for line in lines[:3]] == [0, 1, 2] and lines[3]["reason"] == "pinned"
    assert set(lines[0]) >= {"robot_ms_by_k", "edge_ms_by_k", "payload_kB_by_k", "predicted_ms_by_k", "pinned", "t0_ms"}
    assert ControllerState.model_validate(lines[0]) == state.model_copy(update={"stamp_nanos": 1_000, "chosen_k": 0})


def test_the_edges_busy_share_is_the_union_of_its_frames_compute_over_their_span() -> None:
    """bench.pipeline's `edge busy`: frames computed 0-40 and 50-90 ms (idle 10 ms), one inside another's
    interval not counted twice (a second robot's lane), span 0-100 ms with one more frame at 95-100."""
    from bench.pipeline import busy_share

    assert busy_share([(50.0, 90.0), (0.0, 40.0), (60.0, 70.0), (95.0, 100.0)]) == pytest.approx(0.85)
    assert busy_share([(0.0, 10.0), (5.0, 20.0)]) == pytest.approx(1.0)
    assert np.isnan(busy_share([]))


def test_the_controllers_model_is_set_against_the_pinned_rows_paths() -> None:
    """bench.pipeline's third auto line: predicted T(k) at the end of the auto row over each pinned row's
    robot + link + edge; nothing without a prediction."""
    from bench.pipeline import Row, _model_against_pinned
    from shared.wire.messages import CONTROLLER_WAITING, ControllerState

    state = example_messages()[ControllerState.SCHEMA]
    assert isinstance(state, ControllerState)  # predicted 100 ms at k = 0, 90 at k = 5

    def row(k: int, robot: float, link: float, edge: float) -> Row:
        return Row(str(k), k, 1.0, 0, 15.0, 90.0, 120.0, robot, link, edge, 3.5, 1e3, 4.0, 0.5, 0.5, {})

    line = _model_against_pinned(state, [row(5, 50.0, 5.0, 20.0), row(0, 30.0, 10.0, 40.0)])
    assert line.endswith("k = 0 100 / 80 ms = 1.25, k = 5 90 / 75 ms = 1.20")
    waiting = state.model_copy(update={"reason": CONTROLLER_WAITING})
    assert _model_against_pinned(waiting, [row(0, 30.0, 10.0, 40.0)]) == "" == _model_against_pinned(state, [])


def test_poses_captured_ahead_of_the_clock_or_before_the_run_are_counted_not_recorded() -> None:
    """A trial's made-up Features an hour ahead were posed by the edge (before it refused them) and a
    TagPoses captured in 1970 was re-published: frames.csv read e2e -3598793 ms and a frame age of 1.8e12 ms.
    The run's records keep this run's frames only; slam refuses those poses as well."""
    poses = example_messages()[TagPoses.SCHEMA]
    assert isinstance(poses, TagPoses)
    now = poses.capture_nanos + 50_000_000  # the example frame was captured 50 ms ago
    monitor = Monitor(None, run_started_nanos=now, wall_clock_nanos=lambda: now)
    monitor.on_poses(encode(poses))
    ahead = poses.model_copy(update={"seq": poses.seq + 1, "capture_nanos": now + 3600 * 10**9})
    before = poses.model_copy(update={"seq": poses.seq + 2, "capture_nanos": 1_000})
    for msg in (ahead, before):
        monitor.on_poses(encode(msg))
    assert [r["seq"] for r in monitor.records] == [poses.seq] and monitor.frames_total == 1
    summary = monitor.summary()
    assert summary["out_of_time_messages"] == 2 and summary["frames"] == 1
    late_ok = poses.model_copy(update={"seq": poses.seq + 3, "capture_nanos": now + 59 * 10**9})  # within the bound
    monitor.on_poses(encode(late_ok))
    assert monitor.frames_total == 2
