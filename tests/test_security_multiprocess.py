"""deploy/secure.toml: every link over mutual TLS, the routers enforcing access control by certificate
name. The whole pipeline runs under deploy/up.sh with certificates from deploy/make-certs.sh; then
sessions with other identities try what they must not do, over real Zenoh."""

from __future__ import annotations

import os
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
import zenoh

from shared.runtime.guard import service_stats
from shared.tools.topology import Topology, write_config
from shared.transport.session import TlsSettings, ZenohSettings, open_session, wait_for_liveliness
from shared.transport.split_client import SplitQueryError, query_split
from shared.wire import keys
from shared.wire.messages import TagPoses, decode
from tests.examples import injected_tag_poses
from tests.procs import REPO

pytestmark = pytest.mark.multiprocess

ROBOT = "secure1"
SERVICES = ("camera", "robot_infer", "edge_infer", "slam")
IDENTITY = {"edge_infer": "edge", "robot_infer": "robot", "camera": "camera", "slam": "slam"}
ACL_LOG = "error,zenoh::net::routing::interceptor::access_control=trace"


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("certs")
    done = subprocess.run(["bash", "deploy/make-certs.sh", str(out)], cwd=REPO, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    return out


def _session(topology: Topology, certs: Path, identity: str) -> zenoh.Session:
    tls = TlsSettings.from_dir(certs, identity)
    return open_session(ZenohSettings(mode="client", connect=[topology.edge_router], tls=tls, connect_timeout_secs=60))


@contextmanager
def secure_deployment(tmp_path: Path, certs: Path) -> Iterator[tuple[Topology, zenoh.Session]]:
    """deploy/up.sh with deploy/secure.toml on free loopback ports; yields an operator session."""
    topology = Topology.loopback(protocol="tls")
    per_service = {
        name: {"zenoh": {"tls": {"certificate": str(certs / f"{who}.pem"), "private_key": str(certs / f"{who}.key")}}}
        for name, who in IDENTITY.items()
    }
    cfg = write_config(
        tmp_path / "secure.toml",
        base=REPO / "deploy" / "secure.toml",
        topology=topology,
        extra={
            "common": {
                "robot_id": ROBOT,
                "rerun": {"enabled": False},
                "zenoh": {"tls": {"root_ca_certificate": str(certs / "ca.pem")}},
            },
            "camera": {"fps": 3.0},
            "monitor": {"tls": TlsSettings.from_dir(certs, "operator").model_dump(mode="json")},
            **per_service,
        },
    )
    log_path = tmp_path / "up.log"
    with log_path.open("wb") as log:
        up = subprocess.Popen(
            ["bash", "deploy/up.sh", "--config", str(cfg), "--runs", str(tmp_path / "runs")],
            cwd=REPO,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            env={**os.environ, "RUST_LOG": ACL_LOG},  # zenoh's refusals in the routers' logs (docs/security.md)
        )
        operator = _session(topology, certs, "operator")
        failed = True
        try:
            wait_for_liveliness(operator, [keys.alive(ROBOT, s) for s in SERVICES], timeout_secs=150)
            yield topology, operator
            failed = False
        finally:
            operator.close()
            if up.poll() is None:
                os.killpg(up.pid, signal.SIGINT)
                try:
                    up.wait(timeout=60)
                except subprocess.TimeoutExpired:
                    os.killpg(up.pid, signal.SIGKILL)
                    up.wait()
            if failed:
                print(log_path.read_text(errors="replace"))
                for f in sorted((tmp_path / "runs").glob("*/*.log")):
                    print(f"----- {f.name} -----\n{f.read_text(errors='replace')[-4000:]}")


def test_only_authorised_identities_steer_and_publish(tmp_path: Path, certs: Path) -> None:
    with secure_deployment(tmp_path, certs) as (topology, operator):
        # The pipeline works over TLS: poses reach the operator.
        seqs: list[int] = []
        lock = threading.Lock()

        def on_poses(sample: zenoh.Sample) -> None:
            with lock:
                seqs.append(decode(sample.payload.to_bytes(), TagPoses).seq)

        # Everything of the robot the operator may read reaches it at the edge, but no camera frame:
        # robot_infer's router keeps them (a deny on the way out, on top of the roles' rules).
        seen_keys: dict[str, int] = {}

        def on_any(sample: zenoh.Sample) -> None:
            with lock:
                seen_keys[str(sample.key_expr)] = seen_keys.get(str(sample.key_expr), 0) + 1

        sub = operator.declare_subscriber(keys.tag_poses(ROBOT), on_poses)
        everything = operator.declare_subscriber(f"splittag/{ROBOT}/**", on_any)
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline and len(seqs) < 3:
            time.sleep(0.2)
        assert len(seqs) >= 3, "no poses over the TLS deployment"
        with lock:
            assert seen_keys.get(keys.tag_poses(ROBOT), 0) >= 3 and keys.ground_truth(ROBOT) in seen_keys, seen_keys
            assert keys.frames(ROBOT) not in seen_keys, seen_keys
        everything.undeclare()

        # slam's stats queryable (declared through the edge router's ACL) answers the operator.
        assert "accepted" in service_stats(operator, ROBOT, "slam", timeout_secs=10)

        # The operator steers.
        assert query_split(operator, ROBOT, params="k=5", timeout_secs=10).k == 5

        # The camera's identity may not: its query is dropped by the edge router; nothing changes.
        camera = _session(topology, certs, "camera")
        try:
            with pytest.raises(SplitQueryError, match="access control does not let 'camera' ask it"):
                query_split(camera, ROBOT, params="k=2", timeout_secs=2, identity="camera")
            assert query_split(operator, ROBOT, timeout_secs=10).k == 5
            # The refusal leaves a trace where an operator looks (a trial found none): the edge router's
            # log, with zenoh's access-control log on (RUST_LOG), names the identity, the act and the key.
            (edge_log,) = {p.resolve() for p in (tmp_path / "runs").glob("*/edge_infer.log")}  # (and runs/current)
            refused = [
                line
                for line in edge_log.read_text(errors="replace").splitlines()
                if "is unauthorized to Query" in line and keys.split(ROBOT) in line
            ]
            assert refused and "camera" in refused[0] and "\x1b[" not in refused[0], refused

            # Nor query (or save) the map, which the operator may (the rule once named an old map key);
            # the camera's queries do reach other queryables (a positive control from the same session).
            assert "accepted" in service_stats(camera, ROBOT, "slam", timeout_secs=10)
            assert not [r for r in camera.get(keys.tag_map(ROBOT) + "?save=1", timeout=3) if r.ok is not None]
            assert [r for r in operator.get(keys.tag_map(ROBOT), timeout=10) if r.ok is not None]

            # Nor get round the rules with a wildcard key: a put on splittag/<robot>/** reaches every
            # subscriber of that robot, and a queryable on splittag/** would answer every get.
            camera.put(f"splittag/{ROBOT}/**", injected_tag_poses(ROBOT, seq=2**39))
            fake = camera.declare_queryable("splittag/**", lambda q: q.reply(q.key_expr, b"{}"))
            # Readiness, not a sleep: a get the camera sends after the declaration, answered, has passed the
            # edge router (the operator's too) after the declaration on the same link; were the declaration
            # let through, the operator's get below would reach the fake queryable.
            assert "accepted" in service_stats(camera, ROBOT, "slam", timeout_secs=10)
            every = zenoh.ConsolidationMode.NONE  # each reply, not the latest per key
            got = [
                r.ok.payload.to_bytes()
                for r in operator.get(keys.stats(ROBOT, "slam"), timeout=5, consolidation=every)
                if r.ok
            ]
            assert got and b"{}" not in got, got  # slam answered; the camera's queryable was never declared
            fake.undeclare()

            # Nor may it publish TagPoses; the same message from the robot's identity goes through.
            forged = injected_tag_poses(ROBOT, seq=2**40)
            camera.put(keys.tag_poses(ROBOT), forged)
            robot = _session(topology, certs, "robot")
            try:
                time.sleep(0.5)  # the robot session's routes
                robot.put(keys.tag_poses(ROBOT), injected_tag_poses(ROBOT, seq=2**41))
                deadline = time.monotonic() + 10
                while time.monotonic() < deadline and 2**41 not in seqs:
                    time.sleep(0.1)
            finally:
                robot.close()
            with lock:
                assert 2**41 in seqs, "the positive control (robot identity) did not arrive"
                assert 2**40 not in seqs, "the camera identity published TagPoses"
                assert 2**39 not in seqs, "the camera identity published TagPoses through a wildcard key"
        finally:
            camera.close()
        sub.undeclare()

        # Without a certificate from this CA, or without TLS, no connection at all.
        stranger = tmp_path / "stranger"
        subprocess.run(["bash", "deploy/make-certs.sh", str(stranger)], cwd=REPO, check=True, capture_output=True)
        plain_tcp = topology.edge_router.replace("tls/", "tcp/")
        for settings in (
            ZenohSettings(
                mode="client",
                connect=[topology.edge_router],
                tls=TlsSettings.from_dir(stranger, "operator"),
                connect_timeout_secs=3,
            ),
            ZenohSettings(mode="client", connect=[plain_tcp], connect_timeout_secs=3),
        ):
            with pytest.raises(zenoh.ZError):
                open_session(settings).close()
