"""A fleet over mutual TLS with an identity per process (`[fleet] certs`, `splittag fleet --make-certs`):
both robots' frames get poses through the edge tier, and each robot's identities act for that robot
alone: robot1's router identity cannot publish another robot's TagPoses (its own still go through),
a robot's camera identity cannot publish poses at all, and the operator steers any robot."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest
import zenoh

from shared.tools.fleet import FleetPlan, demo_tables, fleet_configs, make_certs, operator_settings
from shared.tools.topology import merge
from shared.transport.session import TlsSettings, ZenohSettings, open_session, wait_for_liveliness
from shared.transport.split_client import query_split
from shared.vision.geometry import default_camera
from shared.wire import keys
from shared.wire.messages import HopTimings, TagPoses, decode, encode
from tests.procs import REPO, processes, start_process, wait_until

pytestmark = pytest.mark.multiprocess


def _poses(robot: str, seq: int) -> bytes:
    """A schema-valid TagPoses with no tags (what an injector would send)."""
    timings = HopTimings(robot_compute_secs=0, transport_secs=0, edge_compute_secs=0, capture_to_pose_secs=0)
    msg = TagPoses(
        robot_id=robot,
        seq=seq,
        capture_nanos=time.time_ns(),
        split_k=7,
        payload_bytes=1,
        intrinsics=default_camera(),
        link=None,
        timings=timings,
        tags=[],
    )
    return encode(msg)


def test_a_secure_fleet_scopes_each_robots_identities_to_that_robot(tmp_path: Path) -> None:
    plan = FleetPlan.loopback(2, 1).model_copy(update={"certs": tmp_path / "certs"})
    names = make_certs(plan)
    assert {"slam", "edge1", "robot1", "robot2", "robot1-camera", "robot2-camera", "operator"} <= set(names)
    assert plan.edge_router.startswith("tls/")
    run = tmp_path / "run"
    extra = merge(demo_tables(run), {"common": {"rerun": {"enabled": False}}, "camera": {"fps": 3.0}})
    specs = fleet_configs(plan, run, REPO / "deploy" / "fleet.toml", extra=extra)
    seen: dict[str, set[int]] = {}
    lock = threading.Lock()

    def on_poses(sample: zenoh.Sample) -> None:
        msg = decode(sample.payload.to_bytes(), TagPoses)
        with lock:
            seen.setdefault(msg.robot_id, set()).add(msg.seq)

    with processes(tmp_path) as procs:
        for spec in specs:
            procs.append(
                start_process(spec.name, ["-m", f"services.{spec.service}", "--config", str(spec.config)], tmp_path)
            )
        settings = operator_settings(plan).model_copy(update={"connect_timeout_secs": 60.0})
        operator = open_session(settings)
        try:
            sub = operator.declare_subscriber(keys.for_every_robot(keys.tag_poses("x")), on_poses)
            wait_for_liveliness(
                operator,
                [keys.alive(r, s) for r in plan.robots for s in ("robot_infer", "edge_infer", "camera")],
                timeout_secs=150,
            )
            # The whole fleet works over TLS under the rules: both robots' frames get poses.
            wait_until(lambda: all(len(seen.get(r, ())) >= 3 for r in plan.robots), 120, "poses of both robots")
            # The operator steers any robot.
            assert query_split(operator, "robot2", params="k=5", timeout_secs=10).k == 5

            def as_identity(name: str) -> zenoh.Session:
                tls = TlsSettings.from_dir(plan.certs, name) if plan.certs else None
                return open_session(ZenohSettings(mode="client", connect=[plan.edge_router], tls=tls))

            robot1 = as_identity("robot1")
            camera1 = as_identity("robot1-camera")
            try:
                time.sleep(1.0)  # their routes
                robot1.put(keys.tag_poses("robot2"), _poses("robot2", 2**40))  # another robot's: refused
                camera1.put(keys.tag_poses("robot1"), _poses("robot1", 2**39))  # a camera's poses: refused
                robot1.put(keys.tag_poses("robot1"), _poses("robot1", 2**41))  # its own: the positive control
                wait_until(lambda: 2**41 in seen.get("robot1", set()), 10, "robot1's own TagPoses")
                time.sleep(1.0)
                with lock:
                    assert 2**40 not in seen.get("robot2", set()), "robot1's identity published for robot2"
                    assert 2**39 not in seen.get("robot1", set()), "a camera identity published TagPoses"
            finally:
                robot1.close()
                camera1.close()
            sub.undeclare()
        finally:
            operator.close()
