"""A fleet over mutual TLS with an identity per process (`[fleet] certs`, `splittag fleet --make-certs`):
both robots' frames get poses through the edge tier, and each robot's identities act for that robot
alone: robot1's router identity cannot publish another robot's TagPoses (its own still go through),
a robot's camera identity cannot publish poses at all, and the operator steers any robot."""

from __future__ import annotations

import threading
import time
from functools import partial
from pathlib import Path

import pytest
import zenoh

from shared.tools.fleet import FleetPlan, demo_tables, fleet_configs, make_certs, operator_settings
from shared.tools.topology import merge
from shared.transport.session import TlsSettings, ZenohSettings, open_session, wait_for_liveliness
from shared.transport.split_client import SplitQueryError, query_split
from shared.wire import keys
from shared.wire.messages import TagPoses, decode
from tests.examples import injected_tag_poses
from tests.procs import REPO, processes, start_process, wait_until

pytestmark = pytest.mark.multiprocess


def test_a_secure_fleet_scopes_each_robots_identities_to_that_robot(tmp_path: Path) -> None:
    plan = FleetPlan.loopback(2, 1, controller=True).model_copy(update={"certs": tmp_path / "certs"})
    names = make_certs(plan)
    assert {"slam", "edge1", "robot1", "robot2", "robot1-camera", "robot2-controller", "operator"} <= set(names)
    assert plan.edge_router.startswith("tls/")
    run = tmp_path / "run"
    patient = {"rerun": {"enabled": False}, "zenoh": {"connect_timeout_secs": 120.0}}  # a loaded machine
    extra = merge(demo_tables(run), {"common": patient, "camera": {"fps": 3.0}})
    specs = fleet_configs(plan, run, REPO / "deploy" / "fleet.toml", extra=extra)
    seen: dict[str, set[int]] = {}
    robot_side: dict[str, set[str]] = {}  # key kind -> robots whose robot-side messages reached the edge
    lock = threading.Lock()

    def on_poses(sample: zenoh.Sample) -> None:
        msg = decode(sample.payload.to_bytes(), TagPoses)
        with lock:
            seen.setdefault(msg.robot_id, set()).add(msg.seq)

    def on_robot_side(kind: str, sample: zenoh.Sample) -> None:
        with lock:
            robot_side.setdefault(kind, set()).add(keys.robot_of(str(sample.key_expr)))

    with processes(tmp_path) as procs:
        for spec in specs:
            procs.append(
                start_process(spec.name, ["-m", f"services.{spec.service}", "--config", str(spec.config)], tmp_path)
            )
        settings = operator_settings(plan).model_copy(update={"connect_timeout_secs": 60.0})
        operator = open_session(settings)
        try:
            subs = [operator.declare_subscriber(keys.for_every_robot(keys.tag_poses("x")), on_poses)]
            # Through wildcard subscriptions at the edge, as a fleet slam subscribes: what the robots'
            # cameras and controllers publish on their side must reach it through their routers.
            for kind, key in (("ground_truth", keys.ground_truth("x")), ("controller", keys.controller("x"))):
                subs.append(operator.declare_subscriber(keys.for_every_robot(key), partial(on_robot_side, kind)))
            wait_for_liveliness(
                operator,
                [keys.alive(r, s) for r in plan.robots for s in ("robot_infer", "edge_infer", "camera", "controller")],
                timeout_secs=150,
            )
            # The whole fleet works over TLS under the rules: both robots' frames get poses.
            wait_until(lambda: all(len(seen.get(r, ())) >= 3 for r in plan.robots), 120, "poses of both robots")
            want = set(plan.robots)
            wait_until(lambda: robot_side.get("ground_truth") == want, 60, "both cameras' ground truth at the edge")
            wait_until(lambda: robot_side.get("controller") == want, 60, "both controllers' states at the edge")
            # The operator steers any robot.
            assert query_split(operator, "robot2", params="k=5", timeout_secs=10).k == 5

            def as_identity(name: str) -> zenoh.Session:
                tls = TlsSettings.from_dir(plan.certs, name) if plan.certs else None
                return open_session(ZenohSettings(mode="client", connect=[plan.edge_router], tls=tls))

            # A controller steers its own robot on the controller's key, as a controller: the operator's
            # pin holds (one that asked the person's key pinned over the operator: a fresh-clone trial).
            ctl2, ctl1 = as_identity("robot2-controller"), as_identity("robot1-controller")
            try:
                with pytest.raises(SplitQueryError, match="no reply"):
                    query_split(ctl2, "robot2", params="k=6", timeout_secs=3)  # the person's key: denied
                with pytest.raises(SplitQueryError, match="pinned"):
                    query_split(ctl2, "robot2", params="k=6", auto=True, timeout_secs=10)
                with pytest.raises(SplitQueryError, match="no reply"):
                    query_split(ctl1, "robot2", params="k=6", auto=True, timeout_secs=3)  # not its robot
                worker = as_identity("edge1")  # trusted with every robot's data, not with steering
                try:
                    for auto in (False, True):
                        with pytest.raises(SplitQueryError, match="no reply"):
                            query_split(worker, "robot2", params="release=1", auto=auto, timeout_secs=3)
                finally:
                    worker.close()
                assert query_split(operator, "robot2", timeout_secs=10).k == 5
                query_split(operator, "robot2", params="release=1", timeout_secs=10)
                assert query_split(ctl2, "robot2", params="k=6", auto=True, timeout_secs=10).k == 6
            finally:
                ctl2.close()
                ctl1.close()

            robot1 = as_identity("robot1")
            camera1 = as_identity("robot1-camera")
            try:
                # Positive controls first (re-sent until routed): robot1 publishes its own TagPoses, and
                # its camera reads its own robot's keys (slam's stats), not another robot's.
                deadline = time.monotonic() + 30
                while 2**41 not in seen.get("robot1", set()):
                    assert time.monotonic() < deadline, "robot1's own TagPoses never arrived"
                    robot1.put(keys.tag_poses("robot1"), injected_tag_poses("robot1", 2**41))
                    time.sleep(0.5)
                assert [r for r in camera1.get(keys.stats("robot1", "slam"), timeout=10) if r.ok is not None]
                assert not [r for r in camera1.get(keys.stats("robot2", "slam"), timeout=3) if r.ok is not None]
                robot1.put(keys.tag_poses("robot2"), injected_tag_poses("robot2", 2**40))  # another robot's: refused
                robot1.put("splittag/**", injected_tag_poses("robot2", 2**38))  # every key at once: refused
                camera1.put(keys.tag_poses("robot1"), injected_tag_poses("robot1", 2**39))  # a camera's poses: refused
                robot1.put(keys.tag_poses("robot1"), injected_tag_poses("robot1", 2**42))  # sent after them: arrives
                wait_until(lambda: 2**42 in seen.get("robot1", set()), 20, "robot1's TagPoses after the refused")
                time.sleep(0.5)
                with lock:
                    assert 2**40 not in seen.get("robot2", set()), "robot1's identity published for robot2"
                    assert 2**38 not in seen.get("robot2", set()), "robot1's identity published through splittag/**"
                    assert 2**39 not in seen.get("robot1", set()), "a camera identity published TagPoses"
            finally:
                robot1.close()
                camera1.close()
            for sub in subs:
                sub.undeclare()
        finally:
            operator.close()


def test_a_robots_host_runs_its_part_from_its_own_bundle(tmp_path: Path) -> None:
    """`splittag fleet --only robot1` on a robot's host whose certs folder is hosts/robot1/ of what
    `--make-certs` wrote (the CA's certificate and that robot's identities, nothing else): the launcher's
    monitor reads the robot's own router as its camera, so the host comes up and its frames get poses,
    computed on board while no edge is there (it asked for the operator's key, which only the edge's
    host holds, and exited at once: found by a fresh-clone trial)."""
    import json
    import os
    import subprocess
    import sys

    plan = FleetPlan.loopback(1, 1, controller=True).model_copy(update={"certs": tmp_path / "certs"})
    make_certs(plan)
    bundle = tmp_path / "certs" / "hosts" / "robot1"
    assert not (bundle / "operator.key").exists()
    config = tmp_path / "robot1.toml"
    config.write_text(
        f"""
[fleet]
robots = ["robot1"]
edge_workers = ["edge1"]
edge_port = {plan.edge_port}
robot_ports = {{ robot1 = {plan.robot_port("robot1")} }}
controller = true
certs = "{bundle}"

[common.rerun]
enabled = false

[common.zenoh]
connect_timeout_secs = 120.0

[robot_infer]
weights = "{REPO / "models"}"
split_k = 7

[camera]
source = "demo"
fps = 3.0
demo_frames = 12  # its own short cache: rendered in seconds even on a fresh clone
"""
    )
    runs = tmp_path / "runs"
    cli = [sys.executable, "-m", "shared.tools.cli"]
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    launcher = subprocess.Popen(
        [*cli, "fleet", "--config", str(config), "--only", "robot1", "--duration", "12", "--runs", str(runs)],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        out, _ = launcher.communicate(timeout=300)
    except subprocess.TimeoutExpired:
        launcher.terminate()  # the launcher stops its services
        out, _ = launcher.communicate(timeout=60)
        raise
    finally:
        if launcher.poll() is None:
            launcher.kill()
        subprocess.run([*cli, "down", "--runs", str(runs)], cwd=REPO, env=env, capture_output=True, timeout=60)
    assert launcher.returncode == 0, out[-3000:]
    assert "holds private keys" not in out  # the bundle is this host's alone
    summary = json.loads(next(runs.glob("*/summary.json")).read_text())["robots"]["robot1"]
    # poses, and the camera's ground truth (each pose's error): the monitor reads both as the camera
    assert summary["frames"] >= 3 and summary.get("tag_observations", 0) >= 3, summary
