"""The launcher's restart policy: doubling backoff for quick deaths, reset after a healthy run, and a
finished camera ends the deployment."""

from __future__ import annotations

from shared.tools.supervise import RestartPolicy, Supervisor
from tests.fakes import FakeClock


def test_backoff_doubles_for_quick_deaths_and_resets_after_a_healthy_run() -> None:
    clock = FakeClock()
    sup = Supervisor(RestartPolicy(initial_backoff_secs=1.0, max_backoff_secs=8.0, healthy_after_secs=60.0), clock)
    sup.started("edge_infer")
    delays = []
    for _ in range(6):
        clock.now += 2.0  # dies 2 s after each start
        delays.append(sup.exited("edge_infer", -9))
        sup.started("edge_infer")
    assert delays == [1.0, 2.0, 4.0, 8.0, 8.0, 8.0]
    clock.now += 120.0  # then it ran for two minutes
    assert sup.exited("edge_infer", 1) == 1.0
    assert sup.restarts["edge_infer"] == 7


def test_a_finished_camera_ends_the_run_and_a_crashed_one_restarts() -> None:
    sup = Supervisor(clock=FakeClock())
    sup.started("camera")
    assert sup.exited("camera", 0) is None
    assert sup.exited("camera", 1) == 1.0
    # a fleet names its cameras per robot: the kind decides, not the name
    assert sup.exited("robot2_camera", 0, service="camera") is None
    assert sup.exited("robot2_robot_infer", 0, service="robot_infer") == 1.0
