"""deploy/up.sh starts every service; deploy/down.sh stops the running deployment cleanly."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import pytest
import zenoh

from shared.tools.topology import Topology, write_config
from shared.transport.session import ZenohSettings, open_session, wait_for_liveliness
from shared.wire import keys
from tests.procs import REPO

pytestmark = pytest.mark.multiprocess

SERVICES = ("camera", "robot_infer", "edge_infer", "slam")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


@dataclass
class Deployment:
    """`deploy/up.sh` running in the background on free loopback ports, and a session to its edge."""

    up: subprocess.Popen[bytes]
    runs: Path
    session: zenoh.Session
    log_path: Path

    def pids(self) -> dict[str, int]:
        lines = (self.runs / "current" / "pids").read_text().splitlines()
        return {line.split()[0]: int(line.split()[1]) for line in lines}

    def down(self) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            ["bash", "deploy/down.sh", "--runs", str(self.runs)], cwd=REPO, capture_output=True, text=True, timeout=60
        )


@contextmanager
def deployment(tmp_path: Path, robot_id: str) -> Iterator[Deployment]:
    """Start deploy/up.sh with deploy/local.toml on free ports; kill it if the test left it running."""
    topology = Topology.loopback()
    cfg = write_config(
        tmp_path / "deploy.toml",
        base=REPO / "deploy" / "local.toml",
        topology=topology,
        extra={"common": {"robot_id": robot_id, "rerun": {"enabled": False}}, "camera": {"fps": 2.0}},
    )
    runs = tmp_path / "runs"
    log_path = tmp_path / "up.log"
    with log_path.open("wb") as log:
        up = subprocess.Popen(
            ["bash", "deploy/up.sh", "--config", str(cfg), "--runs", str(runs)],
            cwd=REPO,
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        session = open_session(ZenohSettings(mode="client", connect=[topology.edge_router], connect_timeout_secs=60))
        try:
            wait_for_liveliness(session, [keys.alive(robot_id, s) for s in SERVICES], timeout_secs=120)
            yield Deployment(up, runs, session, log_path)
        finally:
            session.close()
            if up.poll() is None:
                os.killpg(up.pid, signal.SIGKILL)
                up.wait()
            if up.returncode not in (0, None, -signal.SIGKILL):
                print(log_path.read_text(errors="replace"))


def test_up_then_down_stops_every_service(tmp_path: Path) -> None:
    with deployment(tmp_path, "deploy1") as d:
        pids = d.pids()
        assert set(pids) == set(SERVICES)
        time.sleep(3.0)  # a few frames through the pipeline
        down = d.down()
        assert down.returncode == 0, down.stdout + down.stderr
        assert all(f"stopping {name}" in down.stdout for name in SERVICES)
        assert d.up.wait(timeout=60) == 0
        deadline = time.monotonic() + 10
        while any(_alive(p) for p in pids.values()) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not any(_alive(p) for p in pids.values()), "a service outlived deploy/down.sh"
        summary = json.loads((d.runs / "current" / "summary.json").read_text())
        assert all(code == 0 for code in summary["exit_codes"].values()), summary["exit_codes"]
        assert (d.runs / "current" / "trajectory.tum").is_file()
        for name in SERVICES:
            assert (d.runs / "current" / f"{name}.log").is_file()


def test_down_without_a_deployment_says_so(tmp_path: Path) -> None:
    down = subprocess.run(
        ["bash", "deploy/down.sh", "--runs", str(tmp_path)], cwd=REPO, capture_output=True, text=True, timeout=60
    )
    assert down.returncode == 1
    assert "no running deployment" in down.stdout


def test_up_restarts_a_killed_service(tmp_path: Path) -> None:
    """Supervision: SIGKILL edge_infer under deploy/up.sh; it comes back (new pid, alive again) and the
    deployment goes on until a person stops it."""
    with deployment(tmp_path, "sup1") as d:
        first = d.pids()
        os.kill(first["edge_infer"], signal.SIGKILL)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and d.pids()["edge_infer"] == first["edge_infer"]:
            time.sleep(0.2)
        assert d.pids()["edge_infer"] != first["edge_infer"], (
            "edge_infer was not restarted; up.sh said:\n" + (d.log_path.read_text(errors="replace")[-4000:])
        )
        wait_for_liveliness(d.session, [keys.alive("sup1", "edge_infer")], timeout_secs=90)
        assert d.up.poll() is None, "the deployment ended with the service"
        down = d.down()
        assert down.returncode == 0, down.stdout + down.stderr
        assert d.up.wait(timeout=60) == 0
        assert "edge_infer exited (-9); restart #1" in d.log_path.read_text()
