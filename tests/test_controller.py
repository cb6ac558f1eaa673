"""The controller's pure core: payload sizes, probe scheduling, decisions, pinning."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from shared.control.controller import ControllerTuning, SplitController
from shared.wire.messages import ComputeProfile, Features, decode, encode
from shared.wire.sizing import features_payload_bytes, probe_features
from tests.fakes import FakeClock


def _profile(side: str, ms: list[float], tags: float = 4.0) -> ComputeProfile:
    return ComputeProfile(
        robot_id="r1",
        side=side,  # type: ignore[arg-type]
        stamp_nanos=1,
        current_k=7,
        tags_per_frame=tags,
        live_scale=1.0,
        ms_by_k=ms,
    )


def test_payload_bytes_are_exact_wire_sizes() -> None:
    for tags, k in ((1, 0), (3, 5), (4, 7), (0, 3)):
        n = features_payload_bytes(tags, k)
        assert n > 0
    one = features_payload_bytes(1, 5)
    msg = probe_features(256 * 8 * 8 * 2)
    assert one == len(encode(msg))
    assert decode(encode(msg), Features).tags[0].tensor.nbytes == 256 * 8 * 8 * 2
    assert features_payload_bytes(4, 1) > features_payload_bytes(4, 0) > features_payload_bytes(4, 7)


def test_decision_follows_the_link_and_respects_pinning() -> None:
    clock = FakeClock(100.0)
    core = SplitController(ControllerTuning(dwell=1), clock=clock)
    state = core.decide(robot_id="r1", current_k=7, pinned=False)
    assert state.chosen_k == 7 and "waiting" in state.reason
    # A slow robot (C grows fast with k) and an edge that does the rest: cheap link -> k = 0.
    c = [5.0, 60.0, 80.0, 95.0, 100.0, 110.0, 112.0, 115.0]
    e = [60.0, 40.0, 30.0, 20.0, 15.0, 5.0, 3.0, 1.0]
    core.add_compute(_profile("robot", c))
    core.add_compute(_profile("edge", e))
    rng = np.random.default_rng(0)
    for _ in range(200):  # a fast link: t0 10 ms, beta 0.01 ms/kB
        size = float(rng.choice([1024, 65536, 262144]))
        core.add_link_sample(int(size), 10.0 + 0.01 * size / 1024 + rng.normal(0, 0.2))
    state = core.decide(robot_id="r1", current_k=7, pinned=False)
    assert abs(state.t0_ms - 10.0) < 1.0 and abs(state.beta_ms_per_kB - 0.01) < 0.005
    expected = np.asarray(c) + 10.0 + 0.01 * np.asarray(state.payload_kB_by_k) + np.asarray(e)
    assert state.best_k == int(np.argmin(expected)) == 0
    assert state.chosen_k == 0 and "switch" in state.reason
    assert np.allclose(state.predicted_ms_by_k, expected, atol=1.5)
    pinned = core.decide(robot_id="r1", current_k=5, pinned=True)
    assert pinned.chosen_k == 5 and "pinned" in pinned.reason and pinned.best_k == 0


def test_probe_sizes_rotate_to_what_was_not_seen() -> None:
    clock = FakeClock(100.0)
    core = SplitController(clock=clock)
    sizes = [16 * 1024, 64 * 1024]
    assert core.probe_size_due(sizes, 0.3) in sizes
    core.add_link_sample(16 * 1024, 40.0)
    assert core.probe_size_due(sizes, 0.3) == 64 * 1024
    clock.now += 0.1
    core.add_link_sample(64 * 1024, 50.0)
    assert core.probe_size_due(sizes, 0.3) is None  # everything fresh
    clock.now += 1.0
    assert core.probe_size_due(sizes, 0.3) == 16 * 1024  # both stale: the older one first
    core.add_link_sample(100, -1.0)  # nonsense samples are ignored
    assert core.link.n == 2


def test_controller_service_rejects_bad_messages_and_keeps_running(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Real Zenoh on loopback: garbage on its inputs is rejected, counted and logged; the loop goes on."""
    import json
    import logging
    import threading
    import time

    from services.controller.service import run
    from services.controller.settings import ControllerSettings
    from shared.transport.session import ZenohSettings, free_tcp_port, open_session
    from shared.wire import keys

    port = free_tcp_port()
    hub = open_session(ZenohSettings(mode="peer", listen=[f"tcp/127.0.0.1:{port}"]))
    ctl_session = open_session(ZenohSettings(mode="client", connect=[f"tcp/127.0.0.1:{port}"]))
    settings = ControllerSettings(robot_id="ctl1", run_dir=tmp_path, probe_period_secs=10.0)
    stop = threading.Event()
    worker = threading.Thread(target=run, args=(settings,), kwargs={"session": ctl_session, "stop": stop})
    caplog.set_level(logging.WARNING, logger="services.controller.service")
    worker.start()
    try:
        time.sleep(1.0)
        hub.put(keys.tag_poses("ctl1"), b"not msgpack at all")
        hub.put(keys.compute("ctl1", "edge"), encode(_profile("edge", [1.0] * 8))[:-5])  # truncated
        hub.put(keys.compute("ctl1", "robot"), encode(_profile("robot", [1.0] * 8)))  # robot r1's, on ctl1's key
        fine = _profile("robot", [1.0] * 8).model_copy(update={"robot_id": "ctl1"})
        hub.put(keys.compute("ctl1", "robot"), encode(fine))
        deadline = time.monotonic() + 10
        stats: dict = {}
        while time.monotonic() < deadline and (stats.get("rejected", 0) < 3 or stats.get("accepted", 0) < 1):
            time.sleep(0.05)
            replies = [r.ok for r in hub.get(keys.stats("ctl1", "controller"), timeout=5) if r.ok is not None]
            stats = json.loads(replies[0].payload.to_bytes()) if replies else {}
        # Counted by reason on the stats queryable; logged (at most one line a second).
        assert stats["rejected_by_reason"] == {
            "TagPoses: MalformedFrame": 1,
            "ComputeProfile: MalformedFrame": 1,
            "ComputeProfile: SchemaError": 1,
        }
        # ... with why, for a sender that cannot read this service's log
        assert "not a splittag message" in stats["last_rejected"]["TagPoses: MalformedFrame"]
        assert "of robot 'r1' on robot 'ctl1'" in stats["last_rejected"]["ComputeProfile: SchemaError"]
        assert stats["accepted"] >= 1
        assert any("controller rejected" in r.message for r in caplog.records)
        assert worker.is_alive()
    finally:
        stop.set()
        worker.join(timeout=20)
        ctl_session.close()
        hub.close()
    assert not worker.is_alive()


def test_the_recording_gets_no_prediction_before_both_compute_profiles() -> None:
    """A fresh-clone trial plotted T(k) = 0 for the first 12 s of a run: the controller sends zeros
    while it waits for the compute profiles. The recording now gets T(k) only once it is a prediction,
    and the link estimate only once there is a link sample."""
    from services.controller.service import _log_state

    class Scalars:
        def __init__(self) -> None:
            self.logged: list[dict[str, float]] = []

        def scalars(self, capture_nanos: int, values: dict[str, float]) -> None:
            self.logged.append(values)

    core = SplitController(ControllerTuning(), clock=FakeClock())
    viz = Scalars()
    _log_state(viz, core.decide(robot_id="r1", current_k=7, pinned=False))  # type: ignore[arg-type]
    assert not any(k.startswith(("controller/predicted_ms", "controller/t0_ms")) for k in viz.logged[-1])
    assert viz.logged[-1]["controller/chosen_k"] == 7.0
    core.add_compute(_profile("robot", [10.0 * k + 30 for k in range(8)]))
    core.add_compute(_profile("edge", [10.0 * (7 - k) for k in range(8)]))
    for i in range(40):
        core.add_link_sample(16 * 1024 if i % 2 else 64 * 1024, 40.0 + 0.18 * (16 if i % 2 else 64))
    _log_state(viz, core.decide(robot_id="r1", current_k=7, pinned=False))  # type: ignore[arg-type]
    assert {f"controller/predicted_ms/k{k}" for k in range(8)} <= set(viz.logged[-1])
    assert viz.logged[-1]["controller/t0_ms"] > 0


def test_failed_probes_are_said_once_a_run_and_why(caplog: pytest.LogCaptureFixture) -> None:
    """A trial's controller logged 6.5 warnings a second while robot_infer (the robot's router) was down,
    each asking whether the edge was running: now the first failure of a run says why, once."""
    from services.controller.service import ProbeFailures
    from shared.transport.probe import ProbeError

    routed = [True]
    now = [0.0]
    failures = ProbeFailures(lambda: routed[0], clock=lambda: now[0])
    caplog.set_level(logging.INFO, logger="services.controller.service")
    failures.failure(16384, ProbeError("no reply"))  # the edge still starting: info
    failures.success()
    routed[0] = False
    for _ in range(50):
        failures.failure(16384, ProbeError("no reply from the echo queryable (is the edge running?)"))
        now[0] += 0.15
    failures.success()
    said = [(r.levelname, r.getMessage()) for r in caplog.records]
    assert [level for level, _ in said] == ["INFO", "WARNING", "WARNING"], said
    assert "reaches no router" in said[1][1] and "is the edge running" not in said[1][1]
    assert "after 50 failed over 7.5 s" in said[2][1]


def test_a_switch_the_measured_frames_contradict_is_vetoed_until_they_age_or_the_link_changes() -> None:
    """A trial: two cuts nearly tied on a loaded link (the model biased: the queue, each side slower when
    it does the work) and the controller went 0 -> 7 -> 0 -> 7 -> 0 within 9 s, each time 'predicted
    24-36 ms faster'. What the frames at both cuts took in the last 20 s now has the last word."""
    clock = FakeClock(100.0)
    core = SplitController(ControllerTuning(dwell=1), clock=clock)
    c = [5.0, 60.0, 80.0, 95.0, 100.0, 110.0, 112.0, 115.0]
    e = [160.0, 140.0, 130.0, 120.0, 115.0, 25.0, 8.0, 1.0]  # the model: k = 7 (116 ms) beats k = 0 (165 ms)
    core.add_compute(_profile("robot", c))  # 4 tags a frame
    core.add_compute(_profile("edge", e))
    for i in range(60):
        core.add_link_sample(1024 if i % 2 else 65536, 1.0 + (0.0 if i % 2 else 0.5))

    def measure(k: int, ms: float, frames: int = 5, tags: int = 4) -> None:
        for _ in range(frames):
            core.add_measured(k, ms, tags)
            clock.now += 0.1

    measure(0, 150.0)  # yet measured: k = 0 took 150 ms a frame, k = 7 took 190
    measure(7, 190.0)
    measure(7, 40.0, tags=0)  # (frames without tags, or with other tag counts, are not compared)
    measure(7, 60.0, tags=1)
    state = core.decide(robot_id="r1", current_k=0, pinned=False)
    assert state.best_k == 7 and state.chosen_k == 0 and core.vetoed == 1
    assert "its frames took 190 ms against 150 ms here" in state.reason, state.reason
    clock.now += 21.0  # the measurements age out: the model decides again
    state = core.decide(robot_id="r1", current_k=0, pinned=False)
    assert state.chosen_k == 7 and "switch" in state.reason
    # Measured where the model says too: no veto.
    measure(0, 170.0)
    measure(7, 120.0)
    assert core.decide(robot_id="r1", current_k=0, pinned=False).chosen_k == 7
    # A link change forgets what was measured on the old link: frames are compared only while the link time
    # the model predicted for them is within the smallest gain of what it predicts now.
    measure(0, 150.0)
    measure(7, 190.0)
    for _ in range(40):  # the link becomes 30 ms slower: the estimator raises the alarm as it happens
        core.add_link_sample(1024, 31.0)
        if core.link.changes:
            break
    assert core.link.changes >= 1
    clock.now += 0.1
    assert core.measured_ms(7) is None
    measure(0, 150.0)  # measured since the change, before the next decision: the veto holds again
    measure(7, 190.0)
    assert core.decide(robot_id="r1", current_k=0, pinned=False).chosen_k == 0
    off = SplitController(ControllerTuning(dwell=1, measured_window_secs=0), clock=clock)
    off.add_compute(_profile("robot", c))
    off.add_compute(_profile("edge", e))
    for i in range(60):
        off.add_link_sample(1024 if i % 2 else 65536, 1.0 + (0.0 if i % 2 else 0.5))
    for _ in range(5):
        off.add_measured(0, 150.0, 4)
        off.add_measured(7, 190.0, 4)
    assert off.decide(robot_id="r1", current_k=0, pinned=False).chosen_k == 7


@pytest.mark.parametrize("late", [3, 8], ids=["dismissed", "taken-and-back"])
def test_an_alarm_that_leaves_the_link_as_it_was_keeps_the_veto(late: int) -> None:
    """A trial under CPU load: the change detector fired about every 15 s on a steady 5g link (stamps
    delayed by the scheduler), the veto forgot every frame measured before each alarm, rarely had its
    three, and the controller switched 11 times in 97 s, none vetoed. Frames now stay comparable while
    the model predicts the same link for them. Three late stamps raise an alarm whose challenger never
    predicts better (dismissed: no change, the fit as it was); more, all late by the same 40 ms, are a
    floor that rose (taken as a change), and the steady samples after them the change back."""
    clock = FakeClock(100.0)
    core = SplitController(ControllerTuning(dwell=1), clock=clock)
    core.add_compute(_profile("robot", [5.0, 60.0, 80.0, 95.0, 100.0, 110.0, 112.0, 115.0]))
    core.add_compute(_profile("edge", [160.0, 140.0, 130.0, 120.0, 115.0, 25.0, 8.0, 1.0]))
    rng = np.random.default_rng(0)

    def steady(n: int) -> None:
        for i in range(n):
            size = 1024 if i % 2 else 65536
            core.add_link_sample(size, 40.0 + 0.18 * size / 1024 + rng.normal(0, 0.5))

    steady(80)
    for _ in range(5):
        core.add_measured(0, 150.0, 4)
        core.add_measured(7, 190.0, 4)
        clock.now += 0.1
    before, dismissed = core.link.changes, core.link.dismissed
    for _ in range(late):  # the edge's CPU is late for a few stamps: a burst of +40 ms
        core.add_link_sample(1024, 40.0 + 0.18 + 40.0)
    steady(60)
    if late == 3:  # the detector fired, and its challenger lost ...
        assert core.link.changes == before and core.link.dismissed == dismissed + 1
    else:  # ... or won, and lost its place to the next one
        assert core.link.changes == before + 2 and core.link.dismissed == dismissed
    assert core.link.beta_ms_per_kB == pytest.approx(0.18, rel=0.05)  # on a link that is as it was
    assert core.measured_ms(7) == 190.0 and core.measured_ms(0) == 150.0
    state = core.decide(robot_id="r1", current_k=0, pinned=False)
    assert state.best_k == 7 and state.chosen_k == 0 and core.vetoed == 1, state.reason
