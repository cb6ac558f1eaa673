"""A fleet deployment in one place: N robots (camera + robot_infer [+ controller] each) and M edge_infer
workers sharing one edge tier with one slam, on one host or several.

The shape: slam opens the edge tier's router (it is the one process per edge tier; a worker may die
without taking the network with it); every edge worker and every robot router connects to it; each
robot runs its own router (camera frames never leave the robot) that its camera and controller join.
The workers share the robots by their liveliness tokens (shared.transport.fleet); slam keeps one map
and a trajectory per robot. `FleetPlan` says who runs where; `fleet_configs` writes one run config per
process (the deploy TOML's tables, then that process's robot id, worker id and endpoints), so every
process is an ordinary service started with `--config`. Used by `splittag fleet`, bench/fleet.py and
tests/test_fleet_multiprocess.py.
"""

from __future__ import annotations

import os
import tomllib
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any, Final

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from shared.tools.topology import merge, write_config
from shared.transport.session import TlsSettings, ZenohSettings, free_tcp_port
from shared.vision.files import atomic_write_text
from shared.wire import keys
from shared.wire.messages import RobotId


class FleetConfigError(ValueError):
    """A deploy TOML's fleet tables that cannot make a fleet (said in one line, exit 2)."""


class FleetPlan(BaseModel):
    """Who runs where. Hosts are as seen from the robots (`edge_host`) and as bound (`robot_hosts`)."""

    model_config = ConfigDict(extra="forbid")

    robots: list[RobotId] = Field(min_length=1)
    edge_workers: list[RobotId] = Field(min_length=1)
    edge_host: str = "127.0.0.1"  # where the edge tier's router (slam) listens / is reached
    edge_port: int = Field(default=7447, gt=0, lt=65536)
    robot_hosts: dict[RobotId, str] = Field(default_factory=dict)  # robot -> its host (default 127.0.0.1)
    robot_ports: dict[RobotId, int] = Field(default_factory=dict)  # robot -> its router's port (default 7448 + i)
    controller: bool = False
    tier: RobotId = "fleet"  # the edge tier's name (its workers' tokens); one fleet, one tier
    # Mutual TLS with an identity per process (`identities`; `splittag fleet --make-certs` issues
    # them into this folder) and access control on the edge tier's and every robot's router: each
    # robot's router, camera and controller act for that robot alone. None: plain TCP, no control.
    certs: Path | None = None

    @model_validator(mode="after")
    def _distinct(self) -> FleetPlan:
        for what, ids in (("robots", self.robots), ("edge_workers", self.edge_workers)):
            if len(set(ids)) != len(ids):
                raise ValueError(f"fleet {what} repeat an id: {ids}")
        unknown = (set(self.robot_hosts) | set(self.robot_ports)) - set(self.robots)
        if unknown:
            raise ValueError(f"robot_hosts / robot_ports name robots not in the fleet: {sorted(unknown)}")
        # Every process has its own certificate name: a robot called like a worker, slam, the operator
        # or another robot's camera would share a certificate with it (and its rights).
        taken = [*self.robots, *self.edge_workers]
        reserved = [n for n in taken if n in ("slam", "operator") or n.endswith(("-camera", "-controller"))]
        if reserved or len(set(taken)) != len(taken):
            clash = reserved or sorted({n for n in taken if taken.count(n) > 1})
            raise ValueError(
                f"fleet names {clash} clash (robots and workers need names of their own, not slam, "
                "operator or <x>-camera / <x>-controller)"
            )
        return self

    @classmethod
    def loopback(cls, robots: int, workers: int, *, controller: bool = False) -> FleetPlan:
        """`robots` robots and `workers` edge workers on this host, on free ports (tests, benchmarks)."""
        names = [f"robot{i + 1}" for i in range(robots)]
        return cls(
            robots=names,
            edge_workers=[f"edge{i + 1}" for i in range(workers)],
            edge_port=free_tcp_port(),
            robot_ports={r: free_tcp_port() for r in names},
            controller=controller,
        )

    @classmethod
    def from_config(cls, config: Path) -> FleetPlan:
        """The `[fleet]` table of a deploy TOML (deploy/fleet.toml)."""
        table = tomllib.loads(Path(config).read_text()).get("fleet")
        if not isinstance(table, dict):
            raise FleetConfigError(f"{config} has no [fleet] table (see deploy/fleet.toml)")
        try:
            return cls.model_validate(table)
        except ValidationError as exc:
            from shared.runtime.errors import one_line_error

            raise FleetConfigError(f"{config} [fleet]: {one_line_error(exc)}") from None

    def robot_port(self, robot: str) -> int:
        """The port robot's own router listens on."""
        return self.robot_ports.get(robot, self.edge_port + 1 + self.robots.index(robot))

    @property
    def protocol(self) -> str:
        """tls with certificates, else tcp."""
        return "tcp" if self.certs is None else "tls"

    @property
    def edge_router(self) -> str:
        """The edge tier's router endpoint (slam listens on it; workers, robots and tools connect)."""
        return f"{self.protocol}/{self.edge_host}:{self.edge_port}"

    def robot_router(self, robot: str) -> str:
        """Robot's own router endpoint (its camera and controller connect to it)."""
        return f"{self.protocol}/{self.robot_hosts.get(robot, '127.0.0.1')}:{self.robot_port(robot)}"

    def identities(self) -> dict[str, str | None]:
        """Certificate name -> the robot it acts for (None: the whole edge tier, or a person): slam
        (the edge tier's router), every worker, every robot's router (robot_infer: the robot's id), its
        camera and controller (`<robot>-camera`, `<robot>-controller`), and `operator` (people, the
        launcher's monitor, `splittag split`)."""
        names: dict[str, str | None] = {"slam": None, **{w: None for w in self.edge_workers}}
        for robot in self.robots:
            names[robot] = robot
            names[f"{robot}-camera"] = robot
            if self.controller:
                names[f"{robot}-controller"] = robot
        names["operator"] = None
        return names

    def access_control(self) -> dict[str, Any]:
        """The routers' access control settings (shared.transport.access) for these identities."""
        return {
            "enabled": True,
            "trusted": ["slam", *self.robots],  # the routers
            "trusted_clients": list(self.edge_workers),  # everything but steering
            "operators": ["operator"],
            "controllers": [f"{r}-controller" for r in self.robots] if self.controller else [],
            "slam": [],  # slam is the edge tier's router itself, trusted by the robots' routers
            "cameras": [f"{r}-camera" for r in self.robots],
            "robot_of_name": {n: r for n, r in self.identities().items() if r is not None},
        }

    def tls(self, name: str) -> dict[str, str]:
        """The zenoh.tls table of the process with this certificate name."""
        assert self.certs is not None
        d = Path(self.certs)
        return {
            "root_ca_certificate": str(d / "ca.pem"),
            "certificate": str(d / f"{name}.pem"),
            "private_key": str(d / f"{name}.key"),
        }


@dataclass(frozen=True)
class FleetProcess:
    """One process of the fleet: its name (for logs and pids), service and run config."""

    name: str
    service: str
    config: Path
    robot_id: str | None  # the robot it belongs to (None: the edge tier's)


def demo_tables(run_dir: Path, *, slam_map: bool = False) -> dict[str, Any]:
    """The demo scene's tag map (sizes and world poses) for edge_infer and robot_infer, and for slam
    with `slam_map` (then its poses are priors; without, slam builds the map from what the robots see):
    launch.run_map_tables for the demo source."""
    from shared.tools.launch import run_map_tables

    users = ("edge_infer", "robot_infer", "slam") if slam_map else ("edge_infer", "robot_infer")
    return run_map_tables({}, run_dir, demo_users=users)[0]


def fleet_configs(
    plan: FleetPlan, run_dir: Path, base: Path, extra: dict[str, Any] | None = None
) -> list[FleetProcess]:
    """Write a run config per process into run_dir (the base TOML's tables with run_dir, then the
    process's own identity and endpoints, then `extra`); returns the processes in start order: the
    edge tier (slam first: its router), then each robot (robot_infer before its camera)."""
    doc = tomllib.loads(base.read_text())
    doc.pop("fleet", None)
    per_robot = robot_tables(doc.pop("robots", {}), plan, base)
    doc = merge(doc, {"common": {"run_dir": str(run_dir)}})
    doc = merge(doc, extra or {})
    run_dir.mkdir(parents=True, exist_ok=True)
    out: list[FleetProcess] = []

    def add(name: str, service: str, robot: str | None, tables: dict[str, Any]) -> None:
        # Rerun: a part file per process, per-robot entities under robots/<robot>/ (the workers' by message).
        prefix = "robots/{robot}/" if service == "edge_infer" else (f"robots/{robot}/" if robot else "")
        rerun = {"common": {"rerun": {"part_name": name, "entity_prefix": prefix}}}
        own = merge(doc, per_robot.get(robot, {})) if robot else doc  # [robots.<robot>.<service>] over the rest
        path = write_config(run_dir / f"config_{name}.toml", extra=merge(merge(own, rerun), tables))
        out.append(FleetProcess(name, service, path, robot))

    edge = plan.edge_router
    robots = list(plan.robots)

    def z(name: str, table: dict[str, Any], *, router: bool = False) -> dict[str, Any]:
        """A process's zenoh table, with its identity (and, for a router, access control) under TLS."""
        if plan.certs is None:
            return table
        secured = {**table, "tls": plan.tls(name)}
        return {**secured, "access_control": plan.access_control()} if router else secured

    add(
        "slam",
        "slam",
        None,
        {"slam": {"robots": robots, "zenoh": z("slam", {"mode": "router", "listen": [edge]}, router=True)}},
    )
    for worker in plan.edge_workers:
        zenoh = z(worker, {"mode": "client", "connect": [edge]})
        add(
            worker,
            "edge_infer",
            None,
            {"edge_infer": {"worker_id": worker, "tier": plan.tier, "robots": robots, "zenoh": zenoh}},
        )
    for robot in robots:
        own = plan.robot_router(robot)
        common = {"robot_id": robot}
        router = z(robot, {"mode": "router", "listen": [own], "connect": [edge]}, router=True)
        add(f"{robot}_robot_infer", "robot_infer", robot, {"common": common, "robot_infer": {"zenoh": router}})
        if plan.controller:
            client = z(f"{robot}-controller", {"mode": "client", "connect": [own]})
            add(f"{robot}_controller", "controller", robot, {"common": common, "controller": {"zenoh": client}})
        camera = z(f"{robot}-camera", {"mode": "client", "connect": [own]})
        add(f"{robot}_camera", "camera", robot, {"common": common, "camera": {"zenoh": camera}})
    return out


ROBOT_SERVICES: Final[tuple[str, ...]] = ("common", "robot_infer", "camera", "controller")


def robot_tables(tables: Any, plan: FleetPlan, base: Path) -> dict[str, dict[str, Any]]:
    """The deploy TOML's `[robots.<robot>.<service>]` tables: one robot's settings over every robot's
    (its camera's source, calibration or start frame, its split...); ValueError naming what is wrong."""
    if not isinstance(tables, dict):
        raise FleetConfigError(f"{base}: robots must be a table of robot ids ([robots.robot2.camera])")
    unknown = sorted(set(tables) - set(plan.robots))
    if unknown:
        raise FleetConfigError(f"{base}: [robots] names {unknown}, not robots of the fleet ({plan.robots})")
    for robot, services in tables.items():
        if isinstance(services, dict) and not all(isinstance(v, dict) for v in services.values()):
            raise FleetConfigError(
                f"{base}: [robots.{robot}] holds tables ([robots.{robot}.camera] fps = 5), not values: "
                f"{sorted(k for k, v in services.items() if not isinstance(v, dict))}"
            )
        if not isinstance(services, dict) or not set(services) <= set(ROBOT_SERVICES):
            got = sorted(services) if isinstance(services, dict) else services
            raise FleetConfigError(
                f"{base}: [robots.{robot}] may hold only {', '.join(ROBOT_SERVICES)} tables (a robot's own "
                f"processes), got {got}"
            )
    return tables


def fleet_process_of_token(plan: FleetPlan, names: set[str], key: str) -> str | None:
    """A liveliness token's process name in a fleet run (slam, a worker, `<robot>_<service>`), or None
    (an edge lane's `alive/edge_infer`, another run's)."""
    parts = key.split("/")
    name = None
    if key == keys.fleet_service("slam"):
        name = "slam"
    elif key.startswith(f"{keys.FLEET}/{plan.tier}/edge_worker/"):
        name = parts[-1]
    elif len(parts) == 4 and parts[0] == keys.ROOT and parts[2] == "alive" and parts[3] != "edge_infer":
        name = f"{parts[1]}_{parts[3]}"
    return name if name in names else None


def operator_settings(plan: FleetPlan) -> ZenohSettings:
    """The ZenohSettings of a person's (or the launcher's monitor's) session to the edge tier."""
    tls = TlsSettings.from_dir(plan.certs, "operator") if plan.certs is not None else None
    return ZenohSettings(mode="client", connect=[plan.edge_router], tls=tls)


def launcher_monitor_settings(plan: FleetPlan, only: str | None) -> ZenohSettings:
    """The launcher's monitor session: the operator's to the edge tier when this host runs the edge
    (or everything); on a robot's host (`only` = that robot) a session to the robot's own router, which
    is up whether or not the edge is, as the robot's camera: the one identity of that host's bundle
    (hosts/<robot>/) that may read its robot's keys and nothing else's, and may not steer (the operator's
    key belongs on the edge's host; asked for it, a robot host could not start: found by a fresh-clone
    trial)."""
    if only is None or only == "edge":
        return operator_settings(plan)
    tls = TlsSettings.from_dir(plan.certs, f"{only}-camera") if plan.certs is not None else None
    return ZenohSettings(mode="client", connect=[plan.robot_router(only)], tls=tls)


def foreign_keys(plan: FleetPlan, only: str | None) -> list[str]:
    """On a host that runs one part of a TLS fleet (`--only`), the private keys in the certs folder
    that are not that part's: each is another process's identity (and ca.key mints any), so a robot
    host holding them could act as the edge or as another robot. `make_certs` writes each host's bundle
    (hosts/<part>/: ca.pem and the part's own certificates and keys) to copy instead."""
    if plan.certs is None or only is None:
        return []
    ours = {n for n, robot in plan.identities().items() if (robot is None if only == "edge" else robot == only)}
    found = sorted(p.stem for p in Path(plan.certs).glob("*.key"))
    foreign = [n for n in found if n not in ours]
    if not foreign:
        return []
    return [
        f"{plan.certs} holds private keys that are not {only}'s: {', '.join(foreign)} (copy hosts/{only}/ of "
        "the folder `splittag fleet --make-certs` wrote to this host as its certs folder; keep ca.key offline)"
    ]


def host_parts(plan: FleetPlan) -> dict[str, list[str]]:
    """The certificate names each host of the fleet runs (`--only` parts): "edge" (slam, the workers,
    and the operator's, which people use from there) and each robot (its router, camera, controller)."""
    parts: dict[str, list[str]] = {"edge": []}
    for name, robot in plan.identities().items():
        parts.setdefault(robot or "edge", []).append(name)
    return parts


def make_certs(plan: FleetPlan, *, extra_names: list[str] | None = None) -> list[str]:
    """Issue every identity of the plan into plan.certs with deploy/make-certs.sh (the edge's and the
    robots' hosts as extra names), and a bundle per host in plan.certs/hosts/<part>/: ca.pem and that
    part's certificates and keys alone, what to copy to that host as its certs folder (ca.key stays
    here, offline). Returns the names."""
    import shutil
    import subprocess

    assert plan.certs is not None, "the plan has no certs folder"
    names = list(plan.identities())
    hosts = sorted({plan.edge_host, *plan.robot_hosts.values()} - {"127.0.0.1", "localhost"})
    script = Path(__file__).resolve().parents[2] / "deploy" / "make-certs.sh"
    env = {**os.environ, "SPLITTAG_CERT_NAMES": " ".join([*names, *(extra_names or [])])}
    subprocess.run(["bash", str(script), str(plan.certs), *hosts], check=True, env=env, capture_output=True)
    certs = Path(plan.certs)
    for part, members in host_parts(plan).items():
        bundle = certs / "hosts" / part
        if bundle.exists():
            shutil.rmtree(bundle)  # a bundle holds exactly this files
        bundle.mkdir(parents=True, mode=0o700)
        shutil.copy2(certs / "ca.pem", bundle / "ca.pem")
        for name in members:
            for suffix in (".pem", ".key"):
                shutil.copy2(certs / f"{name}{suffix}", bundle / f"{name}{suffix}")
    return names


def run_fleet(
    config: Path,
    *,
    duration_secs: float | None,
    runs_root: Path = Path("runs"),
    only: str | None = None,
    quiet: bool = False,
) -> dict[str, Any]:
    """Start the fleet of `config` (or only its edge tier, `only="edge"`, or one robot's processes),
    print a line per robot per second until duration/SIGINT, stop everything, write summary.json.
    A process that dies is restarted after the supervisor's backoff (as `splittag up` does)."""
    import json
    import threading
    import time

    import zenoh

    from shared.runtime.settings import CONFIG_EXIT
    from shared.runtime.signals import SignalStop
    from shared.tools.launch import (
        ComingsAndGoings,
        FramesCsv,
        LaunchError,
        Monitor,
        Service,
        Started,
        attach_monitor,
        configuration_error_line,
        forget_run_files,
        incidents_summary,
        preparing_run_dir,
        refuse_busy_endpoints,
        run_for,
        run_map_tables,
        start_process,
        stop_services,
        wait_for_run,
    )
    from shared.tools.supervise import Supervisor, incidents_file
    from shared.vision.tagmap import load_tag_map
    from shared.viz.recording import merge_recordings

    plan = FleetPlan.from_config(config)
    if only is not None and only != "edge" and only not in plan.robots:
        raise ValueError(f"--only is 'edge' or one of the fleet's robots {plan.robots}, not {only!r}")
    for line in foreign_keys(plan, only):
        print(f"warning: {line}", flush=True)
    with preparing_run_dir(runs_root) as run_dir:
        base = tomllib.loads(Path(config).read_text())
        # One tag map for the run (launch.run_map_tables); the demo scene's goes to edge_infer and robot_infer
        # only: without a map of its own, slam builds the fleet's map from what the robots see.
        extra, run_map = run_map_tables(base, run_dir, demo_users=("edge_infer", "robot_infer"))
        specs = [
            s
            for s in fleet_configs(plan, run_dir, config, extra=extra)
            if only is None or (s.robot_id or "edge") == only
        ]
        run_tags = load_tag_map(run_map) if run_map is not None else None
        refuse_busy_endpoints([s.config for s in specs])
    stop = threading.Event()
    hosts = {"slam": "it is the edge tier's router: every robot and worker is cut off from the edge until it is back"}
    hosts |= {f"{r}_robot_infer": f"it is {r}'s router: {r}'s camera frames wait until it is back" for r in plan.robots}
    supervisor = Supervisor(record=incidents_file(run_dir / "incidents.jsonl"), hosts=hosts)
    running: list[tuple[FleetProcess, Service]] = []
    restart_at: dict[str, float] = {}
    names = {s.name for s in specs}
    comings = ComingsAndGoings(
        supervisor,
        partial(fleet_process_of_token, plan, names),
        robots=list(plan.robots) if only in (None, "edge") else None,
        workers=list(plan.edge_workers),
    )

    def start(spec: FleetProcess) -> Service:
        argv = ["-m", f"services.{spec.service}", "--config", str(spec.config)]
        process = start_process(spec.name, argv, run_dir)
        supervisor.started(spec.name, pid=process.popen.pid)
        return process

    def write_pids() -> None:  # what `splittag down` signals when the launcher itself is gone
        atomic_write_text(run_dir / "pids", "".join(f"{s.name} {p.popen.pid}\n" for s, p in running))  # read meanwhile

    def restart_dead() -> None:  # what died, after its backoff (also while the fleet comes up)
        for i, (spec, proc) in enumerate(running):
            code = proc.popen.poll()
            if code is None or spec.name in supervisor.ended:  # a camera whose source ended is not restarted
                continue
            if code == CONFIG_EXIT:  # it refused its settings: a restart would only refuse them again
                raise LaunchError(configuration_error_line(proc), exit_code=CONFIG_EXIT)
            if spec.name not in restart_at:
                delay = supervisor.exited(spec.name, code, service=spec.service)
                if delay is None:  # a camera whose source ended (its robot's other processes run on)
                    print(f"{spec.name}: its source ended", flush=True)
                    continue
                print(supervisor.exit_line(spec.name, code, delay, why=proc.last_error()), flush=True)
                restart_at[spec.name] = time.monotonic() + delay
            elif time.monotonic() >= restart_at[spec.name]:
                del restart_at[spec.name]
                running[i] = (spec, start(spec))
                write_pids()

    # Tag errors against the run's map; slam's pose error only when slam works in that map's world
    # (without a map its world is its anchor tag's, and the error read 369 cm for poses 0.1 cm right).
    slam_has_map = "tag_map" in {**base.get("slam", {}), **extra.get("slam", {})}
    monitors = {
        r: Monitor(
            run_tags,
            max_records=200_000,
            slam_has_map=slam_has_map,
            at_robot=only == r,
            run_started_nanos=time.time_ns(),  # (frames of this run only)
        )
        for r in plan.robots
        if only in (None, "edge", r)
    }
    # Every frame's timings, per robot, written as the run goes (as `splittag up`'s frames.csv).
    frames_csvs = {
        r: FramesCsv(
            run_dir / f"frames_{r}.csv",
            m,
            controller_path=run_dir / f"controller_{r}.jsonl" if plan.controller else None,
        )
        for r, m in monitors.items()
    }

    def write_frames() -> None:
        for frames_csv in frames_csvs.values():
            frames_csv.flush()

    started = Started()
    signals = SignalStop(stop)  # (restored in the finally below, however the run ends: review)
    try:
        (run_dir / "launcher.pid").write_text(f"{os.getpid()}\n")
        for spec in specs:  # one at a time: a start that fails leaves the ones before it to be stopped
            running.append((spec, start(spec)))
        write_pids()
        wanted = [keys.edge_worker(plan.tier, w) for w in plan.edge_workers if only in (None, "edge")]
        wanted += [keys.alive(r, "robot_infer") for r in monitors if only != "edge"]

        def attach(session: zenoh.Session) -> list[Any]:
            subs = [sub for r, m in monitors.items() for sub in attach_monitor(session, r, m)]
            for key in (f"{keys.ROOT}/*/alive/*", f"{keys.FLEET}/**"):
                subs.append(session.liveliness().declare_subscriber(key, comings.on_token))
            return subs

        started = wait_for_run(
            launcher_monitor_settings(plan, only),
            wanted,
            attach=attach,
            supervise=restart_dead,
            stop=stop,
            timeout_secs=180,
            run_dir=run_dir,
        )
        if started.up:
            print(f"fleet run {run_dir}: {', '.join(s.name for s in specs)} up; Ctrl-C stops", flush=True)
            comings.arm()
            run_for(
                stop,
                duration_secs,
                lines=lambda: [
                    *comings.lines(),
                    *(f"{robot:>10} {n}" for robot, m in monitors.items() for n in m.notices()),
                    *(f"{robot:>10} {m.line()}" for robot, m in monitors.items()),
                ],
                quiet=quiet,
                supervise=restart_dead,
                every_second=write_frames,
            )
        for sub in started.subscriptions:
            sub.undeclare()
    finally:
        if started.session is not None:
            started.session.close()
        codes = stop_services([p for _, p in running])
        signals.restore()
        forget_run_files(run_dir)
    summary: dict[str, Any] = {
        "run_dir": str(run_dir),
        "robots": {r: m.summary() for r, m in monitors.items()},
        **incidents_summary(run_dir, codes, supervisor),
    }
    for robot, frames_csv in frames_csvs.items():
        frames_csv.flush(final=True)
        summary["robots"][robot]["frames_csv"] = str(frames_csv.path)
        summary["robots"][robot]["frames_csv_rows"] = frames_csv.rows
        if frames_csv.controller_lines:
            summary["robots"][robot]["controller_jsonl_lines"] = frames_csv.controller_lines
        if frames_csv.missed:
            summary["robots"][robot]["frames_csv_missed"] = frames_csv.missed
    if (run_dir / "settings").is_dir():
        summary["settings"] = sorted(str(p) for p in (run_dir / "settings").glob("*.json"))
    from shared.runtime.guard import input_counts_summary

    if inputs := input_counts_summary(run_dir):  # every process's, per robot and edge worker, restarts included
        summary["inputs"] = inputs
    slam_json = run_dir / "slam.json"
    if slam_json.is_file():
        summary["slam"] = json.loads(slam_json.read_text())
    recording = merge_recordings(run_dir)
    if recording is not None:
        summary["recording"] = str(recording)
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary
