"""deploy/up.sh starts every service; deploy/down.sh stops the running deployment cleanly."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path

import pytest

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


def test_up_then_down_stops_every_service(tmp_path: Path) -> None:
    topology = Topology.loopback()
    cfg = write_config(
        tmp_path / "deploy.toml",
        base=REPO / "deploy" / "local.toml",
        topology=topology,
        extra={"common": {"robot_id": "deploy1"}, "camera": {"fps": 2.0}},
    )
    runs = tmp_path / "runs"
    log = (tmp_path / "up.log").open("wb")
    up = subprocess.Popen(
        ["bash", "deploy/up.sh", "--config", str(cfg), "--runs", str(runs)],
        cwd=REPO,
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    session = open_session(ZenohSettings(mode="client", connect=[topology.edge_router], connect_timeout_secs=60))
    try:
        wait_for_liveliness(session, [keys.alive("deploy1", s) for s in SERVICES], timeout_secs=120)
        pids_file = runs / "current" / "pids"
        pids = {line.split()[0]: int(line.split()[1]) for line in pids_file.read_text().splitlines()}
        assert set(pids) == set(SERVICES)
        time.sleep(3.0)  # a few frames through the pipeline
        down = subprocess.run(
            ["bash", "deploy/down.sh", "--runs", str(runs)], cwd=REPO, capture_output=True, text=True, timeout=60
        )
        assert down.returncode == 0, down.stdout + down.stderr
        assert all(f"stopping {name}" in down.stdout for name in SERVICES)
        assert up.wait(timeout=60) == 0
        deadline = time.monotonic() + 10
        while any(_alive(p) for p in pids.values()) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not any(_alive(p) for p in pids.values()), "a service outlived deploy/down.sh"
        summary = json.loads((runs / "current" / "summary.json").read_text())
        assert all(code == 0 for code in summary["exit_codes"].values()), summary["exit_codes"]
        assert (runs / "current" / "trajectory.tum").is_file()
        for name in SERVICES:
            assert (runs / "current" / f"{name}.log").is_file()
    finally:
        session.close()
        if up.poll() is None:
            os.killpg(up.pid, signal.SIGKILL)
            up.wait()
        log.close()
        if up.returncode not in (0, None):
            print((tmp_path / "up.log").read_text(errors="replace"))


def test_down_without_a_deployment_says_so(tmp_path: Path) -> None:
    down = subprocess.run(
        ["bash", "deploy/down.sh", "--runs", str(tmp_path)], cwd=REPO, capture_output=True, text=True, timeout=60
    )
    assert down.returncode == 1
    assert "no running deployment" in down.stdout


def test_up_restarts_a_killed_service(tmp_path: Path) -> None:
    """Supervision: SIGKILL edge_infer under deploy/up.sh; it comes back (new pid, alive again) and the
    deployment goes on until a person stops it."""
    topology = Topology.loopback()
    cfg = write_config(
        tmp_path / "deploy.toml",
        base=REPO / "deploy" / "local.toml",
        topology=topology,
        extra={"common": {"robot_id": "sup1", "rerun": {"enabled": False}}, "camera": {"fps": 2.0}},
    )
    runs = tmp_path / "runs"
    log = (tmp_path / "up.log").open("wb")
    up = subprocess.Popen(
        ["bash", "deploy/up.sh", "--config", str(cfg), "--runs", str(runs)],
        cwd=REPO,
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    session = open_session(ZenohSettings(mode="client", connect=[topology.edge_router], connect_timeout_secs=60))
    try:
        wait_for_liveliness(session, [keys.alive("sup1", s) for s in SERVICES], timeout_secs=120)
        pids_file = runs / "current" / "pids"
        first = {line.split()[0]: int(line.split()[1]) for line in pids_file.read_text().splitlines()}
        os.kill(first["edge_infer"], signal.SIGKILL)
        deadline = time.monotonic() + 60
        pids = first
        while time.monotonic() < deadline and pids["edge_infer"] == first["edge_infer"]:
            time.sleep(0.2)
            pids = {line.split()[0]: int(line.split()[1]) for line in pids_file.read_text().splitlines()}
        assert pids["edge_infer"] != first["edge_infer"], "edge_infer was not restarted"
        wait_for_liveliness(session, [keys.alive("sup1", "edge_infer")], timeout_secs=90)
        assert up.poll() is None, "the deployment ended with the service"
        down = subprocess.run(
            ["bash", "deploy/down.sh", "--runs", str(runs)], cwd=REPO, capture_output=True, text=True, timeout=60
        )
        assert down.returncode == 0, down.stdout + down.stderr
        assert up.wait(timeout=60) == 0
        assert "edge_infer exited (-9); restart #1" in (tmp_path / "up.log").read_text()
    finally:
        session.close()
        if up.poll() is None:
            os.killpg(up.pid, signal.SIGKILL)
            up.wait()
        log.close()
