"""The adaptive controller on the emulated 5G uplink (network namespaces; needs root).

Robot side (camera, robot_infer with gamma = 1.75, controller) and edge side (edge_infer) run in two
namespaces joined by the shaped veth. The link goes 5g -> 5g-pre-tdd -> 5g while frames stream.
Run 1: the controller decides. Run 2: an oracle that knows the schedule pins the best k (computed
from the measured C(k), E(k) and the profiles' link parameters) at the instant of each change.
The controller must reach the new optimum soon after each change (goal 1 s), and its mean end-to-end
latency must stay close to the oracle's (goal 5 %); CI bounds below.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from shared import keys
from shared.launch import Monitor, attach_monitor
from shared.linkemu import PROFILES, LinkEmulator, LinkEmulatorSettings, LinkProfile, in_netns, unavailable_reason
from shared.messages import ControllerState, decode
from shared.split_client import query_split
from shared.transport import ZenohSettings, open_session, wait_for_liveliness
from tests.procs import Proc, processes

pytestmark = pytest.mark.multiprocess

ROBOT = "emu1"
# A robot CPU 1.75x slower than the edge. T(0) < T(7) iff beta * 64 kB < (gamma - 1) * c7, with c7 the
# network's time per tag (23-36 ms here, with contention): 11.5 ms on 5g, 36.9 ms on 5g-pre-tdd, so
# gamma = 1.75 puts the optimum at k = 0 on 5g and at a late cut on 5g-pre-tdd with margin both ways.
GAMMA = 1.75
FPS = 3.0  # below every stage's service time at every k here, so latency is T(k), not queueing
WARMUP_SECS = 6.0
PHASE_SECS = 9.0
SCHEDULE = ("5g", "5g-pre-tdd", "5g")
# The goals are 1 s and 5 %; measured here 0.65-0.97 s and 1.02-1.06 (see the README). CI asserts
# looser bounds so that a loaded 2-core runner cannot turn noise into a red build.
REACH_SECS = 1.5
TOLERANCE = 1.05  # "within the hysteresis margin of the optimum" for the reach check
MEAN_LATENCY_RATIO_MAX = 1.10


def _config(tmp: Path, emu: LinkEmulatorSettings) -> Path:
    cfg = tmp / "emulated.toml"
    cfg.write_text(f"""
[common]
robot_id = "{ROBOT}"
run_dir = "{tmp}"
[common.rerun]
enabled = false
[edge_infer.zenoh]
mode = "router"
listen = ["tcp/0.0.0.0:7447"]
[robot_infer]
split_k = 7
gamma = {GAMMA}
[robot_infer.zenoh]
mode = "router"
listen = ["tcp/127.0.0.1:7448"]
connect = ["tcp/{emu.edge_addr}:7447"]
[camera]
fps = {FPS}
loop = true
[camera.zenoh]
mode = "client"
connect = ["tcp/127.0.0.1:7448"]
[controller.zenoh]
mode = "client"
connect = ["tcp/127.0.0.1:7448"]
""")
    return cfg


@dataclass
class Run:
    monitor: Monitor
    states: list[tuple[int, ControllerState]] = field(default_factory=list)
    changes_nanos: list[int] = field(default_factory=list)
    start_nanos: int = 0
    end_nanos: int = 0

    def frames(self) -> list[dict[str, Any]]:
        return [r for r in self.monitor.records if self.start_nanos <= r["capture_nanos"] < self.end_nanos]


def true_costs(state: ControllerState, p: LinkProfile) -> np.ndarray:
    """T(k) from the measured C, E, S in a controller state and the profile's nominal link."""
    return (
        np.asarray(state.robot_ms_by_k)
        + p.delay_ms
        + p.beta_ms_per_kB * np.asarray(state.payload_kB_by_k)
        + np.asarray(state.edge_ms_by_k)
    )


def _stream(tmp: Path, emu: LinkEmulator, *, controller: bool, oracle_k: list[int] | None) -> Run:
    s = emu.settings
    cfg = _config(tmp, s)
    robot, edge = in_netns(s.robot_ns, []), in_netns(s.edge_ns, [])
    emu.set_profile(PROFILES[SCHEDULE[0]])
    with processes(tmp) as procs:
        procs.append(Proc("edge_infer", ["-m", "services.edge_infer", "--config", str(cfg)], tmp, wrapper=edge))
        session = open_session(
            ZenohSettings(mode="client", connect=[f"tcp/{s.mgmt_edge_addr}:7447"], connect_timeout_secs=90)
        )
        # One at a time: each side calibrates its per-cut compute at start-up, best not side by side.
        wait_for_liveliness(session, [keys.alive(ROBOT, "edge_infer")], timeout_secs=120)
        procs.append(Proc("robot_infer", ["-m", "services.robot_infer", "--config", str(cfg)], tmp, wrapper=robot))
        if controller:
            procs.append(Proc("controller", ["-m", "services.controller", "--config", str(cfg)], tmp, wrapper=robot))
        run = Run(Monitor(None))
        lock = threading.Lock()

        def on_state(sample: Any) -> None:
            with lock:
                run.states.append((time.time_ns(), decode(sample.payload.to_bytes(), ControllerState)))

        subs = [
            *attach_monitor(session, ROBOT, run.monitor),
            session.declare_subscriber(keys.controller(ROBOT), on_state),
        ]
        try:
            services = ["edge_infer", "robot_infer", *(["controller"] if controller else [])]
            wait_for_liveliness(session, [keys.alive(ROBOT, n) for n in services], timeout_secs=120)
            procs.append(Proc("camera", ["-m", "services.camera", "--config", str(cfg)], tmp, wrapper=robot))
            if oracle_k is not None:
                query_split(session, ROBOT, params=f"k={oracle_k[0]}")
            time.sleep(WARMUP_SECS)
            run.start_nanos = time.time_ns()
            for i, name in enumerate(SCHEDULE):
                if i:
                    emu.set_profile(PROFILES[name])
                    if oracle_k is not None:
                        query_split(session, ROBOT, params=f"k={oracle_k[i]}")
                    run.changes_nanos.append(time.time_ns())
                time.sleep(PHASE_SECS)
            run.end_nanos = time.time_ns()
            time.sleep(2.0)  # frames captured before the end are still on their way
        finally:
            for sub in subs:
                sub.undeclare()
            session.close()
    return run


@pytest.fixture(scope="module")
def emulator(tmp_path_factory: pytest.TempPathFactory) -> Any:
    reason = unavailable_reason()
    if reason is not None:
        pytest.skip(reason)
    log_dir = tmp_path_factory.mktemp("link")
    with LinkEmulator(LinkEmulatorSettings(prefix="stt"), log_dir=log_dir) as emu:
        emu.up(PROFILES["5g"])
        yield emu


def test_controller_tracks_link_changes_like_an_oracle(emulator: LinkEmulator, tmp_path: Path) -> None:
    (tmp_path / "ctl").mkdir()
    (tmp_path / "oracle").mkdir()
    ctl = _stream(tmp_path / "ctl", emulator, controller=True, oracle_k=None)
    assert ctl.states, "no ControllerState published"
    assert len(ctl.frames()) >= 0.8 * FPS * PHASE_SECS * len(SCHEDULE), "frames were lost"

    # The oracle's choice per phase, from what was measured (C, E, S at the end of the phase) and the
    # profile's nominal link parameters.
    bounds = [ctl.start_nanos, *ctl.changes_nanos, ctl.end_nanos]
    measured = [next(st for stamp, st in reversed(ctl.states) if stamp < end) for end in bounds[1:]]
    oracle_k = [int(np.argmin(true_costs(m, PROFILES[name]))) for m, name in zip(measured, SCHEDULE, strict=True)]
    for m, name, k in zip(measured, SCHEDULE, oracle_k, strict=True):
        print(f"{name}: oracle k={k}, T(k) = {np.round(true_costs(m, PROFILES[name]), 1).tolist()}")
    assert oracle_k[0] != oracle_k[1] and oracle_k[1] != oracle_k[2], "the scenario must move the optimum"

    # Within 1 s of each change the controller's choice is optimal (or within its hysteresis margin).
    for change, name, m in zip(ctl.changes_nanos, SCHEDULE[1:], measured[1:], strict=True):
        t = true_costs(m, PROFILES[name])
        good = {k for k in range(len(t)) if t[k] <= TOLERANCE * t.min()}
        after = [(stamp, s.chosen_k) for stamp, s in ctl.states if stamp >= change]
        reached = next((stamp for stamp, k in after if k in good), None)
        for stamp, st in [(a, b) for a, b in ctl.states if change - 1e9 <= a <= change + 3e9][::3]:
            print(
                f"  {(stamp - change) / 1e9:+.2f} s t0 {st.t0_ms:.1f} beta {st.beta_ms_per_kB:.3f} n {st.link_samples} "
                f"ch {st.link_changes} T {np.round(st.predicted_ms_by_k, 0).tolist()} k {st.chosen_k}: {st.reason}"
            )
        assert reached is not None, f"never reached k in {good} after switching to {name}"
        lag = (reached - change) / 1e9
        print(f"-> {name}: controller at a k in {sorted(good)} after {lag:.2f} s")
        assert lag <= REACH_SECS, f"took {lag:.2f} s to reach the optimum after switching to {name}"
        assert all(k in good for stamp, k in after if stamp >= reached + 1e9 and stamp < change + PHASE_SECS * 1e9), (
            "flapped away from the optimum"
        )

    oracle = _stream(tmp_path / "oracle", emulator, controller=False, oracle_k=oracle_k)
    mean_ctl = float(np.mean([r["e2e_ms"] for r in ctl.frames()]))
    mean_oracle = float(np.mean([r["e2e_ms"] for r in oracle.frames()]))
    print(f"mean end-to-end latency: controller {mean_ctl:.1f} ms, oracle {mean_oracle:.1f} ms")
    assert mean_ctl <= MEAN_LATENCY_RATIO_MAX * mean_oracle
