"""The launcher's restart policy: doubling backoff for quick deaths, reset after a healthy run, and a
finished camera ends the deployment."""

from __future__ import annotations

import json
from functools import partial
from pathlib import Path

from shared.runtime.settings import SOURCE_ENDED_EXIT
from shared.tools.supervise import (
    RestartPolicy,
    Supervisor,
    incidents_file,
    read_incidents,
    summarise_incidents,
)
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


def test_a_process_back_from_an_exit_is_named_for_a_while() -> None:
    clock = FakeClock()
    sup = Supervisor(clock=clock)
    sup.started("robot_infer")
    assert sup.ready("robot_infer") is None and sup.back(20.0) == {}  # a first start: not "back"
    clock.now += 5.0
    sup.exited("robot_infer", -9)
    assert sup.down() == ["robot_infer"] and sup.back(20.0) == {}
    clock.now += 2.0
    sup.started("robot_infer")
    clock.now += 9.0
    assert sup.ready("robot_infer") == 11.0
    assert sup.down() == [] and sup.back(20.0) == {"robot_infer": clock.now}
    clock.now += 20.5
    assert sup.back(20.0) == {}


def test_a_finished_camera_ends_the_run_and_a_crashed_or_stopped_one_restarts() -> None:
    sup = Supervisor(clock=FakeClock())
    sup.started("camera")
    assert sup.exited("camera", SOURCE_ENDED_EXIT) is None
    assert Supervisor(clock=FakeClock()).exited("camera", 1) == 1.0
    # stopped by a signal the launcher did not send (a trial's SIGTERM): exit 0, restarted, not "ended"
    assert Supervisor(clock=FakeClock()).exited("camera", 0) == 1.0
    # a fleet names its cameras per robot: the kind decides, not the name
    assert sup.exited("robot2_camera", SOURCE_ENDED_EXIT, service="camera") is None
    assert sup.exited("robot2_robot_infer", SOURCE_ENDED_EXIT, service="robot_infer") == 1.0


def test_every_exit_and_restart_is_an_incident_the_run_keeps(tmp_path: Path) -> None:
    """A fleet trial SIGKILLed four processes and the run folder said nothing of it (every exit code 0:
    the restarted processes'); each exit and restart is now recorded as it happens."""
    clock = FakeClock()
    path = tmp_path / "incidents.jsonl"
    hosts = {"slam": "it is the edge tier's router"}
    sup = Supervisor(clock=clock, record=incidents_file(path), wall_clock=lambda: 7, hosts=hosts)
    sup.started("slam", pid=100)
    sup.started("robot1_camera", pid=101)
    assert sup.incidents == []  # a first start is not an incident
    clock.now += 5.0
    delay = sup.exited("slam", -9)
    assert sup.exit_line("slam", -9, delay or 0) == "slam exited (-9) (it is the edge tier's router); restart #1 in 1 s"
    sup.started("slam", pid=102)
    assert sup.exited("robot1_camera", SOURCE_ENDED_EXIT, service="camera") is None
    assert sup.exited("robot1_camera", SOURCE_ENDED_EXIT, service="camera") is None  # asked every second: said once
    lines = [json.loads(line) for line in path.read_text().splitlines()]
    assert lines == sup.incidents
    assert lines == [
        {
            "unix_nanos": 7,
            "event": "exited",
            "name": "slam",
            "code": -9,
            "up_secs": 5.0,
            "restart": 1,
            "restart_in_secs": 1.0,
            "takes_down": "it is the edge tier's router",
        },
        {"unix_nanos": 7, "event": "restarted", "name": "slam", "restart": 1, "pid": 102},
        {"unix_nanos": 7, "event": "exited", "name": "robot1_camera", "code": 3, "up_secs": 5.0, "source_ended": True},
    ]
    assert sup.summary() == {"restarts": {"slam": 1}, "exits": 2}


def test_comings_and_goings_say_who_is_back_and_which_robots_move() -> None:
    """A fleet trial saw hand-overs only in the workers' logs and no word when a restarted process was
    ready again: the launcher now says both, from the liveliness tokens."""
    from types import SimpleNamespace

    import zenoh

    from shared.tools.fleet import FleetPlan, fleet_process_of_token
    from shared.tools.launch import ComingsAndGoings
    from shared.transport.fleet import assign
    from shared.wire import keys

    plan = FleetPlan(robots=["robot1", "robot2"], edge_workers=["edge1", "edge2"])
    names = {"slam", "edge1", "edge2", "robot1_robot_infer", "robot1_camera", "robot2_robot_infer", "robot2_camera"}
    name_of = partial(fleet_process_of_token, plan, names)
    assert name_of(keys.fleet_service("slam")) == "slam"
    assert name_of(keys.edge_worker("fleet", "edge2")) == "edge2"
    assert name_of(keys.alive("robot1", "robot_infer")) == "robot1_robot_infer"
    assert name_of(keys.alive("robot1", "edge_infer")) is None  # a lane's token, not a process
    assert name_of(keys.alive("robot9", "camera")) is None and name_of(keys.edge_worker("other", "edge1")) is None

    clock = FakeClock()
    sup = Supervisor(clock=clock, wall_clock=lambda: 0)
    comings = ComingsAndGoings(sup, name_of, robots=plan.robots, workers=plan.edge_workers)

    def token(key: str, up: bool) -> None:
        kind = zenoh.SampleKind.PUT if up else zenoh.SampleKind.DELETE
        comings.on_token(SimpleNamespace(key_expr=key, kind=kind))  # type: ignore[arg-type]

    token(keys.edge_worker("fleet", "edge1"), True)  # the run coming up: not news
    assert comings.lines() == []
    comings.arm()
    served = assign(plan.robots, plan.edge_workers)
    victim = served["robot1"]
    other = next(w for w in plan.edge_workers if w != victim)
    sup.started(victim)
    clock.now += 10.0
    sup.exited(victim, -9)
    token(keys.edge_worker("fleet", victim), False)
    assert comings.lines() == [f"edge worker {victim} gone: robot1 -> {other}"]
    # kept in the run's record too (a fleet trial found hand-overs only in the live lines)
    assert sup.incidents[-1] == {
        "unix_nanos": 0,
        "event": "handover",
        "name": victim,
        "worker": "gone",
        "moved": {"robot1": other},
    }
    clock.now += 7.5
    token(keys.edge_worker("fleet", victim), True)
    assert comings.lines() == [
        f"{victim} is back: ready 7.5 s after it exited",
        f"edge worker {victim} up: robot1 -> {victim}",
    ]
    assert sup.incidents[-2] == {"unix_nanos": 0, "event": "ready", "name": victim, "down_secs": 7.5}
    assert sup.incidents[-1]["event"] == "handover" and sup.incidents[-1]["moved"] == {"robot1": victim}
    token(keys.alive("robot2", "camera"), True)  # a token that comes back without an exit (the network)
    assert comings.lines() == []
    token(keys.edge_worker("fleet", "edge1"), False)
    token(keys.edge_worker("fleet", "edge2"), False)
    assert comings.lines()[-1] == "edge worker edge2 gone: no edge worker left, every robot computes on board"
    assert sup.incidents[-1]["moved"] == {"robot1": None, "robot2": None}  # (on board)
    assert summarise_incidents(sup.incidents)["handovers"] == 4


def test_an_incidents_file_that_cannot_be_written_does_not_stop_the_run(tmp_path: Path) -> None:
    sup = Supervisor(clock=FakeClock(), record=incidents_file(tmp_path / "gone" / "incidents.jsonl"))
    sup.started("slam")
    assert sup.exited("slam", -9) == 1.0  # said once in the log; the supervisor goes on
    assert sup.summary() == {"restarts": {"slam": 1}, "exits": 1}
    written = tmp_path / "incidents.jsonl"
    written.write_text('{"event": "exited", "name": "slam", "restart": 1}\n{"event": "exi')  # cut short
    assert summarise_incidents(read_incidents(written)) == {"restarts": {"slam": 1}, "exits": 1}


def test_an_exit_says_why_from_this_start_of_the_service_only(tmp_path: Path) -> None:
    """The launcher's line for a death carries the last error its log holds since that process started
    (the log is shared by every restart of it): an ERROR line without its stamp and logger, else the
    exception that ended a traceback, else nothing."""
    import subprocess

    from shared.tools.launch import Service, last_error_line

    log = (
        "12:00:01.000 slam INFO slam: started\n"
        "12:00:02.000 slam ERROR slam: slam: cannot open its Zenoh session: Unable to connect to any of [tcp/x]\n"
    )
    assert last_error_line(log) == "slam: cannot open its Zenoh session: Unable to connect to any of [tcp/x]"
    crash = (
        "12:00:01.000 slam INFO slam: started\nTraceback (most recent call last):\n"
        '  File "x.py", line 1\n    boom()\nRuntimeError: boom\n'
    )
    assert last_error_line(crash) == "RuntimeError: boom"
    assert last_error_line("12:00:01.000 slam INFO slam: started\n") is None
    # logger.exception: its ERROR line, then the traceback: both (the exception is the cause)
    died = "12:00:03.000 slam ERROR slam: slam failed\n" + crash.split("\n", 1)[1]
    assert last_error_line(log + died) == "slam failed: RuntimeError: boom"
    # a traceback after an older ERROR line: the traceback's exception is the later news
    assert last_error_line(log + crash) == "RuntimeError: boom"
    assert last_error_line("12:00:02.000 slam ERROR slam: " + "x" * 500, max_chars=50) == "x" * 47 + "..."

    path = tmp_path / "slam.log"
    path.write_text(log)  # an earlier start's error
    popen = subprocess.Popen(["true"])
    popen.wait()
    assert Service("slam", popen, path, log_start_bytes=len(log)).last_error() is None  # not this start's
    with path.open("a") as f:
        f.write(crash)
    assert Service("slam", popen, path, log_start_bytes=len(log)).last_error() == "RuntimeError: boom"
    sup = Supervisor(clock=FakeClock())
    sup.started("slam")
    delay = sup.exited("slam", 1) or 0
    assert (
        sup.exit_line("slam", 1, delay, why="RuntimeError: boom")
        == "slam exited (1): RuntimeError: boom; restart #1 in 1 s"
    )
