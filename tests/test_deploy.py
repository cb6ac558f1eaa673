"""deploy/up.sh starts every service; deploy/down.sh stops the running deployment cleanly."""

from __future__ import annotations

import contextlib
import csv
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
from shared.transport.split_client import query_split
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
def deployment(tmp_path: Path, robot_id: str, env: dict[str, str] | None = None) -> Iterator[Deployment]:
    """Start deploy/up.sh with deploy/local.toml on free ports (`env`: more environment for it and its
    services); kill it if the test left it running."""
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
            env={**os.environ, **(env or {})},
        )
        session = open_session(ZenohSettings(mode="client", connect=[topology.edge_router], connect_timeout_secs=60))
        seen: set[int] = set()  # every service pid the run listed: each runs in a session of its own
        deployment = Deployment(up, runs, session, log_path)
        try:
            wait_for_liveliness(session, [keys.alive(robot_id, s) for s in SERVICES], timeout_secs=120)
            seen |= set(deployment.pids().values())
            yield deployment
        finally:
            session.close()
            with contextlib.suppress(OSError, ValueError, IndexError):
                seen |= set(deployment.pids().values())  # restarted ones too (the file is gone after a down)
            if up.poll() is None:
                # A test that failed midway: stop the launcher, then whatever service it left (a service
                # is in a session of its own, out of the launcher's process group: a failed run left them).
                os.killpg(up.pid, signal.SIGKILL)
                up.wait()
            for pid in seen:  # only a process that is still one of this run's services (a pid may be reused)
                with contextlib.suppress(OSError):
                    cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
                    if b"services." in cmdline and str(runs).encode() in cmdline:
                        os.kill(pid, signal.SIGKILL)
            if up.returncode not in (0, None, -signal.SIGKILL):
                print(log_path.read_text(errors="replace"))


def test_up_then_down_stops_every_service(tmp_path: Path) -> None:
    # A setting given by the environment only: the run folder must still record it (a fresh-clone trial's
    # run folder said fps 15 for a camera that ran at 30 through SPLITTAG_CAMERA_FPS).
    with deployment(tmp_path, "deploy1", env={"SPLITTAG_SLAM_MAP_PUBLISH_EVERY": "7"}) as d:
        pids = d.pids()
        assert set(pids) == set(SERVICES)
        time.sleep(3.0)  # a few frames through the pipeline
        # Each service answers on its own key: a wildcard get of the stats gets one reply per service
        # (on the asker's key they were consolidated into one).
        replied = {str(r.ok.key_expr) for r in d.session.get("splittag/deploy1/*/stats", timeout=10) if r.ok}
        assert replied == {keys.stats("deploy1", s) for s in ("robot_infer", "edge_infer", "slam")}, replied
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
            who = "edge1" if name == "edge_infer" else "deploy1"  # an edge worker is named by its worker_id
            resolved = json.loads((d.runs / "current" / "settings" / f"{name}-{who}.json").read_text())
            assert resolved["robot_id"] == "deploy1"
        slam = json.loads((d.runs / "current" / "settings" / "slam-deploy1.json").read_text())
        assert slam["map_publish_every"] == 7
        with (d.runs / "current" / "frames.csv").open() as f:
            frames = list(csv.DictReader(f))
        assert frames and all(float(r["e2e_ms"]) > 0 and r["k"] == "7" for r in frames)
        assert summary["frames_csv"].endswith("frames.csv") and len(summary["settings"]) == len(SERVICES)
        # The run is over: its pid files are gone, so a later down cannot signal whatever reuses the pids.
        assert not (d.runs / "current" / "pids").exists() and not (d.runs / "current" / "launcher.pid").exists()
        again = d.down()
        assert again.returncode == 1 and "no running deployment" in again.stdout


def test_down_finishes_a_run_whose_launcher_died(tmp_path: Path) -> None:
    """A fleet trial SIGKILLed the launcher: its services ran on unsupervised (down stopped them), but the
    run never got its summary or merged recording, and stale pid files stayed. down now finishes it."""
    with deployment(tmp_path, "orphan1") as d:
        pids = d.pids()
        frames_csv = d.runs / "current" / "frames.csv"

        def rows() -> int:
            with frames_csv.open() as f:
                return sum(1 for _ in csv.DictReader(f))

        deadline = time.monotonic() + 60  # rows are written 10 s after their poses arrived
        while rows() == 0 and time.monotonic() < deadline:
            time.sleep(0.5)
        assert rows() > 0, "frames.csv got no row while the run went on"
        os.killpg(d.up.pid, signal.SIGKILL)  # the launcher (and up.sh), not the services: own sessions
        d.up.wait()
        assert all(_alive(p) for p in pids.values())
        down = d.down()
        assert down.returncode == 0 and "the run's launcher had died: wrote" in down.stdout, down.stdout + down.stderr
        deadline = time.monotonic() + 30
        while any(_alive(p) for p in pids.values()) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not any(_alive(p) for p in pids.values())
        run = (d.runs / "current").resolve()
        summary = json.loads((run / "summary.json").read_text())
        assert summary["launcher"].startswith("died") and sorted(summary["stopped_by_down"]) == sorted(SERVICES)
        # the rows written before the launcher died are kept, and counted
        assert summary["frames_csv_rows"] == rows() > 0 and "slam" in summary  # slam wrote its outputs as it stopped
        # what frames.csv and the run folder still tell (a trial: no frames, e2e, link or refusal figures)
        assert summary["frames"] == rows() and summary["e2e_ms_p50"] > 0 and summary["frames_by_k"], summary
        inputs = summary["inputs"]
        assert {"robot_infer", "edge_infer", "slam"} <= set(inputs), inputs
        assert inputs["robot_infer"]["processes"] == 1 and inputs["slam"]["accepted_by_input"]["tag_poses"] > 0, inputs
        assert not (run / "pids").exists() and not (run / "launcher.pid").exists()
        again = d.down()
        assert again.returncode == 1 and "no running deployment" in again.stdout


def test_up_refuses_ports_another_deployment_holds(tmp_path: Path) -> None:
    """A data-set trial's run started beside someone else's demo on the same ports: its routers could not
    listen, it joined the other run's, counted their liveliness tokens as its own and mixed both runs'
    data (14 tags, ATE 44 cm, exit 0). The launcher now refuses, before starting anything."""
    import socket

    topology = Topology.loopback()
    cfg = write_config(tmp_path / "deploy.toml", base=REPO / "deploy" / "local.toml", topology=topology)
    runs = tmp_path / "runs"
    with socket.socket() as other:  # another deployment's edge router
        other.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        other.bind(("127.0.0.1", topology.edge_port))
        other.listen()
        up = subprocess.run(
            ["bash", "deploy/up.sh", "--config", str(cfg), "--runs", str(runs)],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=60,
        )
    assert up.returncode == 2, up.stdout + up.stderr
    assert f"tcp/127.0.0.1:{topology.edge_port} already in use on this host" in up.stderr, up.stderr
    assert "Traceback" not in up.stderr and not runs.exists()  # nothing started, no run folder


def test_up_refuses_a_part_whose_router_listens_at_another_hosts_address(tmp_path: Path) -> None:
    """A two-host trial started `--only robot` on the edge host: robot_infer could not listen at the
    robot's address, but the run's camera joined the real robot's router across the network and doubled
    its frames (exit 0). Refused now, before anything starts: the address is not this host's."""
    import sys

    cfg = write_config(
        tmp_path / "two.toml",
        base=REPO / "deploy" / "two_host.toml",
        extra={"robot_infer": {"zenoh": {"listen": ["tcp/192.0.2.1:7448"]}}},  # TEST-NET-1: no host has it
    )
    runs = tmp_path / "runs"
    up = subprocess.run(
        [sys.executable, "-m", "shared.tools.cli", "up", "--config", str(cfg), "--only", "robot", "--runs", str(runs)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert up.returncode == 2, up.stdout + up.stderr
    assert "would listen on tcp/192.0.2.1:7448, an address this host does not have" in up.stderr, up.stderr
    assert "Traceback" not in up.stderr and not runs.exists()


def test_up_refuses_a_run_dir_in_the_config(tmp_path: Path) -> None:
    """A soak trial set `[common] run_dir` to go on in a stopped run's folder: `up` replaced it without a
    word and slam started from nothing. Refused, naming what carries a map over."""
    import sys

    cfg = write_config(
        tmp_path / "mine.toml", base=REPO / "deploy" / "local.toml", extra={"common": {"run_dir": "runs/old"}}
    )
    runs = tmp_path / "runs"
    up = subprocess.run(
        [sys.executable, "-m", "shared.tools.cli", "up", "--config", str(cfg), "--runs", str(runs)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert up.returncode == 2, up.stdout + up.stderr
    assert (
        "run_dir in [common] is the launcher's to set" in up.stderr and 'tag_map = "<that run>/map.json"' in up.stderr
    )
    assert "Traceback" not in up.stderr and not runs.exists()


def test_down_without_a_deployment_says_so(tmp_path: Path) -> None:
    down = subprocess.run(
        ["bash", "deploy/down.sh", "--runs", str(tmp_path)], cwd=REPO, capture_output=True, text=True, timeout=60
    )
    assert down.returncode == 1
    assert "no running deployment" in down.stdout


def test_down_leaves_alone_a_process_that_reuses_a_stale_pid(tmp_path: Path) -> None:
    """A run killed without cleaning up leaves its pid files; by the time someone runs down, those pids
    may be other programs': down signals only processes that are still splittag's."""
    stranger = subprocess.Popen(["sleep", "60"], start_new_session=True)
    try:
        run = tmp_path / "runs" / "20260101-000000-1"
        run.mkdir(parents=True)
        (tmp_path / "runs" / "current").symlink_to(run.name)
        (run / "pids").write_text(f"camera {stranger.pid}\nslam {stranger.pid}\n")
        (run / "launcher.pid").write_text(f"{stranger.pid}\n")
        down = subprocess.run(
            ["bash", "deploy/down.sh", "--runs", str(tmp_path / "runs")],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert down.returncode == 1 and "no running deployment" in down.stdout, down.stdout + down.stderr
        assert stranger.poll() is None, "down signalled a process that was not the deployment's"
    finally:
        stranger.kill()
        stranger.wait()


@pytest.mark.parametrize("service", ["robot_infer", "edge_infer"])
def test_up_stops_at_once_on_settings_a_service_refuses(tmp_path: Path, service: str) -> None:
    """A typo in a service's table: the service exits with the configuration error's code, and the
    launcher, instead of restarting it every 30 s for ever, stops everything and says which setting in
    one line, exit 2, no traceback; nothing is left running. edge_infer's own router is the one the
    launcher connects to: it must not wait out a connection timeout first."""
    topology = Topology.loopback()
    cfg = write_config(
        tmp_path / "deploy.toml",
        base=REPO / "deploy" / "local.toml",
        topology=topology,
        extra={"common": {"robot_id": "typo1", "rerun": {"enabled": False}}, service: {"split_kk": 7}},
    )
    start = time.monotonic()
    out = subprocess.run(
        ["bash", "deploy/up.sh", "--config", str(cfg), "--runs", str(tmp_path / "runs")],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    said = out.stdout + out.stderr
    assert out.returncode == 2, said
    assert f"{service}: configuration error: split_kk: Extra inputs are not permitted" in said, said
    assert "Traceback" not in said, said
    print(f"{service}: refused in {time.monotonic() - start:.1f} s")
    run = (tmp_path / "runs" / "current").resolve()
    for name in SERVICES:
        log = (run / f"{name}.log").read_text(errors="replace")
        assert "Traceback" not in log, f"{name}: {log[-2000:]}"
    assert not (run / "pids").exists()
    # the run is finished all the same (a trial found one without summary.json, its recording unmerged)
    summary = json.loads((run / "summary.json").read_text())
    assert "split_kk: Extra inputs are not permitted" in summary["stopped_by"], summary
    assert summary["logged"][service]["errors"] >= 1 and "configuration error" in summary["logged"][service]["first"][0]


def test_a_service_refusing_its_settings_says_why_before_any_connection(tmp_path: Path) -> None:
    """Bad settings from the environment, or a camera folder that is not there: one line and exit 2
    at once (before: a traceback, and the camera first waited 30 s for a router that was not up)."""
    import sys

    env = {**os.environ, "SPLITTAG_CAMERA_SOURCE": "folder", "SPLITTAG_CAMERA_PATH": str(tmp_path / "nope")}
    from shared.vision.geometry import camera_to_yaml, default_camera

    info = tmp_path / "camera_info.yaml"
    info.write_text(camera_to_yaml(default_camera()))
    env["SPLITTAG_CAMERA_CAMERA_INFO"] = str(info)
    # Nothing listens there, and it would wait 10 minutes for it: the check must come first.
    env["SPLITTAG_CAMERA_ZENOH__CONNECT"] = '["tcp/127.0.0.1:9"]'
    env["SPLITTAG_CAMERA_ZENOH__CONNECT_TIMEOUT_SECS"] = "600"
    solo = {"SPLITTAG_SLAM_ZENOH__MODE": "peer", "SPLITTAG_SLAM_RUN_DIR": str(tmp_path / "run")}  # no router needed
    bad = [
        (["-m", "services.camera"], env, "camera: configuration error: source folder"),
        (["-m", "services.slam"], {**os.environ, "SPLITTAG_SLAM_MAX_PENDING_MAP_QUERIES": "x"}, "max_pending_map_q"),
        # A tag map that is not there: found once slam starts; restarting it could not help.
        (
            ["-m", "services.slam"],
            {**os.environ, **solo, "SPLITTAG_SLAM_TAG_MAP": str(tmp_path / "no.yaml")},
            "tag map",
        ),
    ]
    for argv, environ, expected in bad:
        out = subprocess.run(
            [sys.executable, *argv], cwd=REPO, env=environ, capture_output=True, text=True, timeout=300
        )
        assert out.returncode == 2, out.stderr
        assert expected in out.stderr and "Traceback" not in out.stderr, out.stderr


def test_a_session_that_can_never_open_is_a_configuration_error(tmp_path: Path) -> None:
    """A router whose certificate is not valid for the address dialled: no restart can cure it, so the
    client says what is wrong in one line and exits with the configuration error's code (before: exit 1
    with only "Timeout!", restarted for ever). A listen address this host does not have may yet come (Wi-Fi,
    DHCP): exit 1, retried, but said plainly. The router not up yet: exit 1, retried."""
    import sys

    from shared.transport.session import TlsSettings, free_tcp_port

    solo = {**os.environ, "SPLITTAG_SLAM_RUN_DIR": str(tmp_path / "run"), "SPLITTAG_SLAM_ZENOH__MODE": "peer"}

    def slam(environ: dict[str, str]) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "services.slam"], cwd=REPO, env=environ, capture_output=True, text=True, timeout=300
        )

    out = slam({**solo, "SPLITTAG_SLAM_ZENOH__LISTEN": '["tcp/192.0.2.1:7447"]'})
    assert out.returncode == 1 and "Cannot assign requested address" in out.stderr, out.stderr
    assert "no such address on this host, or not yet" in out.stderr and "Traceback" not in out.stderr, out.stderr
    certs = tmp_path / "certs"
    made = subprocess.run(["bash", "deploy/make-certs.sh", str(certs)], cwd=REPO, capture_output=True, text=True)
    assert made.returncode == 0, made.stderr
    port = free_tcp_port()
    # Valid for localhost and 127.0.0.1 only; dialled at 127.0.0.2 (loopback too, but another name).
    edge = TlsSettings.from_dir(certs, "edge")
    router = open_session(ZenohSettings(mode="router", listen=[f"tls/127.0.0.2:{port}"], tls=edge))
    tls = {
        **solo,
        "SPLITTAG_SLAM_ZENOH__MODE": "client",
        "SPLITTAG_SLAM_ZENOH__CONNECT": f'["tls/127.0.0.2:{port}"]',
        "SPLITTAG_SLAM_ZENOH__CONNECT_TIMEOUT_SECS": "2",
        "SPLITTAG_SLAM_ZENOH__TLS__ROOT_CA_CERTIFICATE": str(certs / "ca.pem"),
        "SPLITTAG_SLAM_ZENOH__TLS__CERTIFICATE": str(certs / "slam.pem"),
        "SPLITTAG_SLAM_ZENOH__TLS__PRIVATE_KEY": str(certs / "slam.key"),
    }
    try:
        out = slam(tls)
        assert out.returncode == 2, out.stderr
        expected = "certificate is refused here: IP address mismatch, certificate is not valid for '127.0.0.2'"
        assert "slam: configuration error: zenoh: " in out.stderr and expected in out.stderr, out.stderr
        assert "Traceback" not in out.stderr, out.stderr
    finally:
        router.close()
    # The router not up yet is not such an error: exit 1, and the launcher tries again.
    out = slam(tls)
    assert out.returncode == 1 and "cannot open its Zenoh session" in out.stderr, out.stderr


def test_a_stop_while_the_session_opens_ends_the_service_at_once(tmp_path: Path) -> None:
    """A launcher stopping the run while the router a service dials is not up (robot_infer refused its
    settings, so the robot's router never came): the camera sat in zenoh.open for its 30 s connect
    timeout, ignored the SIGINT and was killed after 15 s (a trial). Now it stops at once, exit 0."""
    import signal
    import sys
    import time

    from shared.transport.session import free_tcp_port

    environ = {
        **os.environ,
        "SPLITTAG_SLAM_RUN_DIR": str(tmp_path / "run"),
        "SPLITTAG_SLAM_ZENOH__MODE": "client",
        "SPLITTAG_SLAM_ZENOH__CONNECT": f'["tcp/127.0.0.1:{free_tcp_port()}"]',  # nothing listens there
        "SPLITTAG_SLAM_ZENOH__CONNECT_TIMEOUT_SECS": "60",
    }
    log = tmp_path / "slam.log"
    with log.open("w") as out:
        proc = subprocess.Popen([sys.executable, "-m", "services.slam"], cwd=REPO, env=environ, stderr=out)
    try:
        deadline = time.monotonic() + 60
        while "zenoh" not in log.read_text() and time.monotonic() < deadline:  # its settings logged: opening
            time.sleep(0.1)
        time.sleep(0.5)
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=10) == 0, log.read_text()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert "stopped before its Zenoh session opened" in log.read_text(), log.read_text()


def test_up_only_runs_one_hosts_part_of_two_hosts(tmp_path: Path) -> None:
    """deploy/two_host.toml as two launchers, one per host (`up --only edge`, `up --only robot`, the same
    config, runs folders of their own): each starts its own part, the robot's watches the poses at the
    robot's router, and the edge's slam makes the trajectory. A part that cannot be is refused (exit 2,
    no run folder)."""
    import sys

    cfg = write_config(
        tmp_path / "two.toml",
        base=REPO / "deploy" / "two_host.toml",
        extra={"common": {"robot_id": "twohost1", "rerun": {"enabled": False}}, "camera": {"fps": 2.0}},
    )
    up = [sys.executable, "-m", "shared.tools.cli", "up", "--config", str(cfg), "--duration"]
    refused = subprocess.run(
        [*up, "5", "--only", "edge", "--controller", "--runs", str(tmp_path / "nope")],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert refused.returncode == 2 and "the controller runs with the robot's part" in refused.stderr, refused.stderr
    assert not (tmp_path / "nope").exists()
    parts = {
        part: subprocess.Popen(
            [*up, "25", "--only", part, "--runs", str(tmp_path / part)],
            cwd=REPO,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            start_new_session=True,
        )
        for part in ("edge", "robot")
    }
    said = {}
    try:
        for part, proc in parts.items():
            said[part], _ = proc.communicate(timeout=240)
            assert proc.returncode == 0, said[part]
    finally:
        for proc in parts.values():
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
    summaries = {part: json.loads((tmp_path / part / "current" / "summary.json").read_text()) for part in parts}
    assert set(summaries["edge"]["exit_codes"]) == {"edge_infer", "slam"}, said["edge"]
    assert set(summaries["robot"]["exit_codes"]) == {"robot_infer", "camera"}, said["robot"]
    assert "edge_infer, slam alive" in said["edge"] and "robot_infer, camera alive" in said["robot"]
    for part in parts:  # poses reach both hosts' monitors
        assert summaries[part]["frames"] >= 10, (part, summaries[part])
    trajectory = (tmp_path / "edge" / "current" / "trajectory.tum").read_text().splitlines()
    assert len(trajectory) >= 10
    assert not list((tmp_path / "robot" / "current").glob("trajectory*"))  # slam is the edge's


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
        # A person's pin survives robot_infer's restart (it was lost, silently: a fresh-clone trial). The
        # robot's router reconnects to the new edge router first (this session is the edge's).
        wait_for_liveliness(d.session, [keys.alive("sup1", "robot_infer")], timeout_secs=90)
        assert query_split(d.session, "sup1", params="k=3", timeout_secs=20).pinned
        os.kill(first["robot_infer"], signal.SIGKILL)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and d.pids()["robot_infer"] == first["robot_infer"]:
            time.sleep(0.2)
        assert d.pids()["robot_infer"] != first["robot_infer"], "robot_infer was not restarted"
        wait_for_liveliness(d.session, [keys.alive("sup1", "robot_infer")], timeout_secs=90)
        resumed = query_split(d.session, "sup1")
        assert (resumed.k, resumed.pinned, resumed.source) == (3, True, "user"), resumed
        down = d.down()
        assert down.returncode == 0, down.stdout + down.stderr
        assert d.up.wait(timeout=60) == 0
        assert "edge_infer exited (-9) (it is the edge's router" in d.log_path.read_text()
        # The run keeps what happened (a fleet trial's summary said every exit code was 0, the restarted
        # processes', and nothing in the run folder told of the kills).
        summary = json.loads((d.runs / "current" / "summary.json").read_text())
        assert summary["restarts"] == {"edge_infer": 1, "robot_infer": 1} and summary["exits"] == 2, summary
        # every process's input counts, the killed ones' included (each kept them in the run folder)
        inputs = summary["inputs"]
        assert inputs["edge_infer"]["processes"] == 2 and inputs["robot_infer"]["processes"] == 2, inputs
        assert inputs["slam"]["processes"] == 1 and inputs["robot_infer"]["accepted_by_input"]["frame"] > 0, inputs
        incidents = [json.loads(line) for line in Path(summary["incidents"]).read_text().splitlines()]
        assert [(i["event"], i["name"], i.get("code")) for i in incidents if i["event"] != "ready"] == [
            ("exited", "edge_infer", -9),
            ("restarted", "edge_infer", None),
            ("exited", "robot_infer", -9),
            ("restarted", "robot_infer", None),
        ]
        # ... and when each was ready again (robot_infer's token may come back after the stop began)
        ready = [i for i in incidents if i["event"] == "ready"]
        assert ready and ready[0]["name"] == "edge_infer" and ready[0]["down_secs"] > 0, incidents
        assert "edge_infer is back: ready" in d.log_path.read_text()
        # While edge_infer (and its router) was away, slam and the launcher's monitor went on through the
        # robot's router with the poses the robot computed on board (they were cut off until it was back).
        gone = next(i for i in incidents if i["event"] == "exited" and i["name"] == "edge_infer")["unix_nanos"] / 1e9
        back = ready[0]["unix_nanos"] / 1e9
        run = d.runs / "current"
        lines = (run / "trajectory.tum").read_text().splitlines()
        posed = [float(line.split()[0]) for line in lines if line[:1].isdigit()]
        seen = [int(row["capture_unix_nanos"]) / 1e9 for row in csv.DictReader((run / "frames.csv").open())]
        assert len(seen) == len(set(seen)), "a frame's poses arrived twice"  # (slam as a peer of both: twice)
        # the frames the edge held when it died are computed on board before the next one: slam refused
        # them as out of order when they came after it (a trial: one frame lost in 2 kills of 4)
        refused = [line for line in (run / "slam.log").read_text().splitlines() if "out of order" in line]
        assert not refused, refused
        for name, stamps in (("slam", posed), ("monitor", seen)):
            during = [t for t in stamps if gone + 0.5 < t < back - 0.5]
            assert len(during) >= 3, f"{name}: {len(during)} poses in the {back - gone:.1f} s without the edge"
        assert "slam and the monitor fail over to the robot's router" in d.log_path.read_text()


def test_a_secure_config_stays_tls_across_the_emulated_link(tmp_path: Path) -> None:
    """A trial's `up --config deploy/secure.toml --link 5g` rewrote every endpoint to plain tcp/ while
    access control stayed on: no process had an identity, nothing connected, the camera restarted for
    ever. The link's endpoints keep the config's protocol, the certificates name the link's addresses,
    and an edge certificate made without them is refused before anything starts, saying how to fix it."""
    from shared.tools.launch import LaunchError, _placement, link_certificate_problem
    from shared.tools.linkemu import LinkEmulatorSettings

    certs = tmp_path / "certs"
    made = subprocess.run(["bash", "deploy/make-certs.sh", str(certs)], cwd=REPO, capture_output=True, text=True)
    assert made.returncode == 0, made.stderr
    config = tmp_path / "secure.toml"
    config.write_text((REPO / "deploy" / "secure.toml").read_text().replace('"certs/', f'"{certs}/'))
    link = LinkEmulatorSettings()
    topology, _, emu = _placement(config, ("camera", "robot_infer", "edge_infer", "slam"), "5g")
    assert emu is not None and topology.protocol == "tls"
    tables = topology.zenoh_tables()
    assert tables["robot_infer"]["zenoh"]["connect"] == [f"tls/{link.edge_addr}:7447"]
    assert tables["edge_infer"]["zenoh"]["listen"] == ["tls/0.0.0.0:7447"]
    assert tables["monitor"]["connect"][0] == f"tls/{link.mgmt_edge_addr}:7447"
    assert link_certificate_problem(config, (link.edge_addr, link.mgmt_edge_addr)) is None
    # Certificates made before the link's addresses were named: refused, with the command that fixes it.
    old = tmp_path / "old"
    old.mkdir()
    subprocess.run(
        ["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes", "-days", "2",
         "-subj", "/CN=edge", "-addext", "subjectAltName=DNS:localhost,IP:127.0.0.1",
         "-keyout", str(old / "edge.key"), "-out", str(old / "edge.pem")],
        check=True, capture_output=True,
    )  # fmt: skip
    config.write_text(config.read_text().replace(f'"{certs}/edge.', f'"{old}/edge.'))
    with pytest.raises(LaunchError) as refused:
        _placement(config, ("camera", "robot_infer", "edge_infer", "slam"), "5g")
    assert refused.value.exit_code == 2
    assert f"does not name {link.edge_addr}, {link.mgmt_edge_addr}" in str(refused.value)
    # the command as it runs: the script names the link's addresses itself in a certificate named edge
    assert f"SPLITTAG_CERT_NAMES=edge deploy/make-certs.sh {old} (plus" in str(refused.value)


def test_a_reader_with_a_certificate_of_another_ca_is_told_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A trial's operator certificate from another CA: `splittag split get` said only zenoh's "Unable to
    connect ... Timeout!". The readers now find what the services find (`certificate_problem`)."""
    from shared.tools.cli import main
    from shared.transport.session import TlsSettings, free_tcp_port

    ours, theirs = tmp_path / "ours", tmp_path / "theirs"
    for out in (ours, theirs):
        made = subprocess.run(["bash", "deploy/make-certs.sh", str(out)], cwd=REPO, capture_output=True, text=True)
        assert made.returncode == 0, made.stderr
    endpoint = f"tls/127.0.0.1:{free_tcp_port()}"
    router = open_session(ZenohSettings(mode="router", listen=[endpoint], tls=TlsSettings.from_dir(ours, "edge")))
    try:
        assert main(["split", "get", "--connect", endpoint, "--certs", str(theirs)]) == 1
    finally:
        router.close()
    err = capsys.readouterr().err
    assert "splittag split: Zenoh: " in err and "its certificate is refused here" in err, err
    assert len(err.strip().splitlines()) == 1, err


def test_a_reader_is_pointed_at_a_fleets_edge_router(tmp_path: Path) -> None:
    """A fleet trial's `splittag stats` without --connect, while its fleet ran on port 7547, was told "no
    deployment is running here": the hint read only runs/current/config.toml, and a fleet writes one
    config per process. A fleet's edge router is slam's."""
    import argparse

    from shared.tools.cli import _endpoint_hint

    run = tmp_path / "runs" / "20261127-000000-1"
    run.mkdir(parents=True)
    (run / "config_slam.toml").write_text('[slam.zenoh]\nmode = "router"\nlisten = ["tcp/0.0.0.0:7547"]\n')
    (tmp_path / "runs" / "current").symlink_to(run.name)
    import sys

    launcher = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)", "shared.tools.fleet"])
    try:  # (a live launcher: a process of ours whose command line says so)
        (run / "launcher.pid").write_text(f"{launcher.pid}\n")
        args = argparse.Namespace(identity="operator", connect=None, certs=None)
        hint = _endpoint_hint(args, runs=tmp_path / "runs")
    finally:
        launcher.kill()
        launcher.wait()
    expected = "listens at tcp/127.0.0.1:7547 (--connect tcp/127.0.0.1:7547)"
    assert hint == f"; the deployment in {tmp_path / 'runs'}/current {expected}", hint
