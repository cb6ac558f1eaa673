"""Start the services as separate processes, watch the pipeline live, stop everything cleanly.

`splittag up` (and deploy/up.sh) writes runs/<run_id>/: one log per service, the resolved config,
the demo tag map, `pids`, and `summary.json` at exit. runs/current points at the newest run.
"""

from __future__ import annotations

import contextlib
import functools
import json
import logging
import os
import re
import signal
import subprocess
import sys
import threading
import time
import tomllib
from collections import Counter, deque
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar, cast

import numpy as np
import yaml
import zenoh

from shared.runtime.guard import input_counts_summary
from shared.runtime.settings import CONFIG_EXIT, CURRENT_RUN
from shared.runtime.signals import SignalStop
from shared.runtime.sources import demo_scene
from shared.tools.supervise import Supervisor, incidents_file
from shared.tools.topology import Topology, merge, write_config
from shared.transport.session import TlsSettings, ZenohSettings, open_session, wait_for_liveliness
from shared.vision.files import atomic_write_text
from shared.vision.metrics import translation_error_cm
from shared.vision.tagmap import TagMapFile, TagSpec, load_tag_map
from shared.vision.trajectory import format_stamp_nanos
from shared.viz.recording import merge_recordings
from shared.wire import keys
from shared.wire.codec import SchemaError, WireError
from shared.wire.messages import (
    MAX_CAPTURE_AHEAD_SECS,
    CameraPose,
    ControllerState,
    FrameStamp,
    Message,
    TagPoses,
    decode,
    decode_for_robot,
    refuse_future_capture,
)

if TYPE_CHECKING:
    from shared.tools.linkemu import LinkEmulator, LinkEmulatorSettings

log = logging.getLogger(__name__)
M = TypeVar("M", bound=Message)
REPO = Path(__file__).resolve().parents[2]
SERVICES = ("edge_infer", "slam", "robot_infer", "camera")
# `splittag up --only PART`: one host's part of a two-host deployment (the controller joins the robot's).
PARTS: dict[str, tuple[str, ...]] = {"edge": ("edge_infer", "slam"), "robot": ("robot_infer", "camera")}

CHI2_3_95 = 7.8147  # the 95 % quantile of chi-square with 3 degrees of freedom (a position's NEES)


def demo_tag_map() -> TagMapFile:
    """Sizes and world poses of the demo scene's tags."""
    scene = demo_scene()
    return TagMapFile(
        default_size_m=0.2,
        anchor_tag_id=scene.tags[0].id,
        tags=[TagSpec(id=t.id, size_m=t.size_m, world_from_tag=t.world_from_tag) for t in scene.tags],
    )


def new_run_dir(root: Path = CURRENT_RUN.parent) -> Path:
    """runs/<timestamp>-<pid>, absolute: the services start in the repository, the launcher anywhere (a
    relative run folder made under another directory was handed to them as is: 'config file runs/...
    does not exist'). `link_current` points runs/current at it once the run is accepted."""
    root = Path(root).resolve()
    run = root / time.strftime(f"%Y%m%d-%H%M%S-{os.getpid()}")
    run.mkdir(parents=True, exist_ok=True)
    return run


def link_current(run: Path) -> None:
    """runs/current (the services' default run_dir, what `splittag down` finds) -> this run."""
    current = run.parent / CURRENT_RUN.name
    if current.is_symlink() or current.exists():
        current.unlink()
    current.symlink_to(run.name)


@contextlib.contextmanager
def preparing_run_dir(root: Path) -> Iterator[Path]:
    """A new run folder (`new_run_dir`) for the block that checks the run's configuration: refused
    there, the folder is discarded (`discard_run_dir`) and runs/current still points where it did;
    accepted, runs/current points at it."""
    made_root = not Path(root).exists()
    run = new_run_dir(root)
    try:
        yield run
    except BaseException:
        discard_run_dir(run, made_root=made_root)  # refused before anything started
        raise
    link_current(run)


def listen_endpoints(config: Path, services: Sequence[str] | None = None) -> list[str]:
    """Every endpoint a run config's processes (or those of `services`) listen on (each table's `zenoh.listen`)."""
    found: list[str] = []
    for name, table in tomllib.loads(Path(config).read_text()).items():
        if services is not None and name not in services:
            continue
        zenoh_table = table.get("zenoh") if isinstance(table, dict) else None
        if isinstance(zenoh_table, dict):
            found += [e for e in zenoh_table.get("listen", []) if isinstance(e, str) and e not in found]
    return found


def _endpoint_trouble(endpoints: list[str]) -> tuple[list[str], list[str]]:
    """(busy, foreign): the tcp/ and tls/ endpoints something on this host already listens on (another
    deployment's routers: a run started beside it joined them, counted their liveliness tokens as its own
    and mixed both runs' data, found by a trial), and those at an address this host does not have (a part
    started on the wrong host: a two-host trial's `--only robot` on the edge host could not start
    robot_infer, but its camera joined the real robot's router across the network and doubled its
    frames)."""
    import errno
    import socket

    busy: list[str] = []
    foreign: list[str] = []
    for endpoint in endpoints:
        proto, _, rest = endpoint.partition("/")
        host, _, port = rest.split("#", 1)[0].split("?", 1)[0].rpartition(":")  # Zenoh's #config / ?metadata
        if proto not in ("tcp", "tls") or not port.isdigit():
            continue
        try:
            addresses = socket.getaddrinfo(host.strip("[]"), int(port), type=socket.SOCK_STREAM)
        except OSError:
            continue  # a name this host cannot resolve: the service itself will say so
        for family, kind, _, _, address in addresses:
            try:
                with socket.socket(family, kind) as probe:
                    probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as a listener binds
                    probe.bind(address)
            except OSError as exc:
                if exc.errno == errno.EADDRINUSE:
                    busy.append(endpoint)
                    break
                if exc.errno == errno.EADDRNOTAVAIL:
                    foreign.append(endpoint)
                    break
    return busy, foreign


def refuse_busy_endpoints(configs: list[Path], services: Sequence[str] | None = None) -> None:
    """LaunchError (exit 2) naming the endpoints of the run (of its `services`) that something already
    listens on, or that are at an address this host does not have (the part is another host's)."""
    endpoints = [e for c in configs for e in listen_endpoints(c, services)]
    busy, foreign = _endpoint_trouble(endpoints)
    if foreign:
        raise LaunchError(
            f"this run would listen on {', '.join(foreign)}, an address this host does not have: is this the "
            "right host for it? (`--only` picks the part a host runs; its config's zenoh listen endpoints say "
            "where each listens)",
            exit_code=2,
        )
    if busy:
        raise LaunchError(
            f"{', '.join(busy)} already in use on this host: another deployment (`splittag down` stops the one in "
            "runs/current, `splittag down --runs FOLDER` one started with --runs) or another program; give this "
            "run other ports (its config's zenoh listen endpoints)",
            exit_code=2,
        )


def discard_run_dir(run: Path, *, made_root: bool) -> None:
    """A run refused before anything started: its folder goes, and the runs folder too when this run
    made it and nothing else is in it (no stray runs/ for a mistyped tag map; runs/current still points
    where it did)."""
    import shutil

    shutil.rmtree(run, ignore_errors=True)
    if made_root:
        with contextlib.suppress(OSError):
            run.parent.rmdir()  # only when empty


@dataclass
class Service:
    """One running process (a service or a helper) in its own process group, output in its log."""

    name: str
    popen: subprocess.Popen[bytes]
    log_path: Path
    log_start_bytes: int = 0  # the log's size when this process started (the log is shared by its restarts)

    def stop(self, timeout_secs: float = 15.0) -> int | None:
        """SIGINT to the process group; after timeout_secs its thread stacks go to its log (faulthandler
        on SIGUSR1 in every service) and it gets SIGKILL. Returns the exit code."""
        if self.popen.poll() is None:
            os.killpg(self.popen.pid, signal.SIGINT)
        try:
            self.popen.wait(timeout=timeout_secs)
        except subprocess.TimeoutExpired:
            log.warning(
                "%s did not stop within %.0f s: its stacks go to its log, then SIGKILL", self.name, timeout_secs
            )
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.popen.pid, signal.SIGUSR1)
            time.sleep(1.0)
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.popen.pid, signal.SIGKILL)
            self.popen.wait()
        return self.popen.returncode

    def log_text(self) -> str:
        """Everything the process printed so far."""
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""

    def last_error(self, *, max_chars: int = 300) -> str | None:
        """Why this process (this start of it, not an earlier one) ended, from its log: the last ERROR
        line, else the last line of a traceback; None when it said neither."""
        try:
            with self.log_path.open("rb") as f:
                f.seek(self.log_start_bytes)
                tail = f.read().decode(errors="replace")
        except OSError:
            return None
        return last_error_line(tail, max_chars=max_chars)


# A service's log line of a warning or worse (shared.runtime.logs' format: time, process, level, logger).
_PROBLEM_LINE = re.compile(r"^\S+ \S+ (WARNING|ERROR|CRITICAL) \S+: (.*)$")


def last_error_line(log_text: str, *, max_chars: int = 300) -> str | None:
    """Why a service ended, from its log text: the later of its last ERROR line (without its time and
    logger: `cannot open its Zenoh session: ...`) and the exception line that ends its last traceback;
    an ERROR line followed by its traceback (`slam failed`, then the exception) gives both. None when
    there is neither."""
    lines = log_text.splitlines()
    error_at, error = -1, ""
    for i in range(len(lines) - 1, -1, -1):
        found = _PROBLEM_LINE.match(lines[i])
        if found and found[1] != "WARNING":
            error_at, error = i, found[2]
            break
    tracebacks = [i for i, line in enumerate(lines) if line.startswith("Traceback (most recent call last)")]
    exception = ""
    if tracebacks and tracebacks[-1] > error_at:
        after = [line for line in lines[tracebacks[-1] + 1 :] if line and not line[0].isspace()]
        exception = after[0] if after else ""
    if exception and error_at >= 0 and tracebacks[-1] == error_at + 1:
        text = f"{error}: {exception}"  # logger.exception: its message, then the traceback
    else:
        text = exception or error
    if not text:
        return None
    return text if len(text) <= max_chars else text[: max_chars - 3] + "..."


def start_process(
    name: str,
    argv: list[str],
    log_dir: Path,
    env: dict[str, str] | None = None,
    *,
    wrapper: list[str] | None = None,
) -> Service:
    """Start `python <argv>` from the repository root in its own process group, output appended to
    log_dir/<name>.log; `wrapper` prefixes the command line (e.g. `ip netns exec st-robot`)."""
    log_path = log_dir / f"{name}.log"
    full_env = {**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})}
    with log_path.open("ab") as out:
        start_bytes = out.tell()
        popen = subprocess.Popen(
            [*(wrapper or []), sys.executable, *argv],
            cwd=REPO,
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            env=full_env,
        )
    return Service(name, popen, log_path, start_bytes)


def start_service(
    name: str,
    config: Path,
    run_dir: Path,
    env: dict[str, str] | None = None,
    *,
    wrapper: list[str] | None = None,
) -> Service:
    """Start `python -m services.<name> --config <config>` (see start_process)."""
    return start_process(name, ["-m", f"services.{name}", "--config", str(config)], run_dir, env, wrapper=wrapper)


def stop_services(services: list[Service], timeout_secs: float = 15.0) -> dict[str, int | None]:
    """Stop in reverse start order, one at a time: producers (camera, robot side) finish before the
    consumers they feed, so nobody blocks sending into a peer that is already gone, and the edge and
    SLAM see the last frames."""
    codes = {s.name: s.stop(timeout_secs) for s in reversed(services)}
    return {s.name: codes[s.name] for s in services}


# A controller decision in a run's history: (stamp nanos, T(k) per k, best k, t0 ms, beta ms/kB).
Prediction = tuple[int, tuple[float, ...], int, float, float]


def _waits_ms(msg: TagPoses) -> dict[str, float]:
    """Where a frame waited outside the critical path (robot + link + edge compute), from its stamps:
    `before_robot_ms` = capture -> sent minus the robot's compute (the frame's age when the robot took it,
    plus any wait between its stage 1 and its network); `at_edge_ms` = received -> pose minus the edge's
    compute (queueing behind earlier frames); `edge_done_nanos`: when the edge finished it (its clock).
    NaN for a frame computed on board (no link stamps). Each difference is on one clock (the robot's,
    the edge's)."""
    t, link = msg.timings, msg.link
    if link is None:
        return {"before_robot_ms": float("nan"), "at_edge_ms": float("nan"), "edge_done_nanos": float("nan")}
    done_nanos = msg.capture_nanos + t.capture_to_pose_secs * 1e9  # on the edge's clock
    return {
        "before_robot_ms": (link.sent_nanos - msg.capture_nanos) / 1e6 - 1e3 * t.robot_compute_secs,
        "at_edge_ms": (done_nanos - link.received_nanos) / 1e6 - 1e3 * t.edge_compute_secs,
        "edge_done_nanos": done_nanos,
    }


def _keep_newest(d: dict[Any, Any], limit: int) -> None:
    """Drop the oldest half of an insertion-ordered dict grown past `limit`."""
    if len(d) > limit:
        for old in list(d)[: limit // 2]:
            del d[old]


@dataclass
class Monitor:
    """Subscribes to TagPoses, SLAM poses and ground truth; keeps per-frame records and prints a line per
    second (with slam's status, position sigma and, against ground truth, its error).

    `max_records` bounds the records a long deployment keeps (the oldest half is dropped when full; the
    summary then covers the newest ones, `frames_total` counts all); ground truth is kept for the newest
    `max_ground_truth` frames (a pose arrives well within that of its frame's ground truth)."""

    tag_map: TagMapFile | None
    records: list[dict[str, Any]] = field(default_factory=list)
    gt: dict[int, np.ndarray] = field(default_factory=dict)
    bad: int = 0
    max_records: int | None = None
    max_ground_truth: int = 3000
    frames_total: int = 0
    controller: ControllerState | None = None
    # The controller's predictions by decision time (stamp, T(k) per k, best k, t0, beta): a bounded
    # history (10 decisions a second: 2.8 hours), joined to the frames at the end of the run.
    predictions: deque[Prediction] = field(default_factory=lambda: deque(maxlen=100_000))
    # The controller states not yet written to controller.jsonl (a researcher's trial had to record the
    # stream itself for C(k), E(k), S(k), the reason and the pin): drained by the writer every second,
    # bounded (~2.6 kB each: a review), the ones it had to drop counted.
    controller_states: deque[ControllerState] = field(default_factory=lambda: deque(maxlen=5_000))
    controller_states_dropped: int = 0
    slam_status: dict[str, int] = field(default_factory=dict)  # CameraPose status -> frames
    _recent: deque[dict[str, Any]] = field(default_factory=lambda: deque(maxlen=400))
    _slam_recent: deque[dict[str, Any]] = field(default_factory=lambda: deque(maxlen=400))
    _slam_sigma_cm: deque[float] = field(default_factory=lambda: deque(maxlen=200_000))
    _slam_error_cm: deque[float] = field(default_factory=lambda: deque(maxlen=200_000))
    # each tracking pose's position NEES against ground truth (e' S^-1 e; 3 on average when the published
    # covariance is calibrated)
    _slam_nees: deque[float] = field(default_factory=lambda: deque(maxlen=200_000))
    _lock: threading.Lock = field(default_factory=threading.Lock)
    clock: Callable[[], float] = time.monotonic  # when each message arrived (a fake in tests)
    # slam was given `tag_map` (its world is the map's): only then is its pose comparable with ground truth
    slam_has_map: bool = True
    # when the camera's ground truth or data-set stamp last arrived (this monitor's clock): its sign of life
    _last_gt_at: float | None = None
    _last_gt_seq: int = -1  # the frame the camera last sent ground truth or a stamp for
    # frames the camera captured, as far as this monitor sees them (ground truth or data-set stamps)
    gt_total: int = 0
    stamps_total: int = 0
    # listening at the robot's own router (a fleet's robot host), which sees the poses computed on board
    at_robot: bool = False
    robot_id: str | None = None  # the robot whose keys it watches (attach_monitor sets it): others refused
    # What the split did over the whole run (a trial had to grep controller.log for it): frames per cut
    # and computed on board, and the controller's decisions, switches and decisions under a pin.
    frames_by_k: Counter[int] = field(default_factory=Counter)
    frames_on_board: int = 0
    # Tags seen that a run's tag map listing some tags does not list, with the size they were solved at
    # (its default_size_m): a trial's map missing one tag of four took its ATE from 0.15 to 19.6 cm and
    # nothing said so. Each is said once (`notices`) and listed in the summary.
    tags_not_in_map: dict[int, float] = field(default_factory=dict)
    _notices: list[str] = field(default_factory=list)
    # TagPoses of a frame already recorded (the same capture time and seq: a message sent again, by a
    # replay or a duplicating route): counted, not recorded again (a trial's 53 repeats read as 168 frames of 115)
    repeated: int = 0
    _recent_frames: dict[tuple[int, int], None] = field(default_factory=dict)
    # TagPoses of a frame captured more than MAX_CAPTURE_AHEAD_SECS ahead of this host's clock, or as long
    # before `run_started_nanos` (the launchers' run): counted, not recorded (a trial's made-up Features an
    # hour ahead were posed by the edge, and frames.csv read e2e -3598793 ms; one captured in 1970, frame age
    # 1.8e12 ms). slam refuses such poses too. Their latencies are not this run's. Said for the 1st, 2nd,
    # 4th, 8th ... such message (a flood of them does not flood the launcher's output).
    out_of_time: int = 0
    run_started_nanos: int | None = None
    wall_clock_nanos: Callable[[], int] = time.time_ns  # (a fake in tests)
    # the data set's own stamp of each frame (FrameStamp), by capture time: frames.csv's `source_stamp`,
    # the key of the run's trajectory.tum and of the data set's ground truth (the newest 20000 frames)
    _source_stamps: dict[int, int] = field(default_factory=dict)
    controller_decisions: int = 0
    controller_switches: int = 0
    controller_pinned: int = 0

    def _decode(self, payload: bytes, kind: type[M]) -> M | None:
        """One message of `kind`, or None (counted in `bad`, logged) when the payload is not one, or names
        another robot than the one this monitor watches (a fleet trial's robot2 TagPoses published on
        robot1's key became a robot1 frame here, while slam and the edge refused it)."""
        try:
            if self.robot_id is not None:
                return decode_for_robot(payload, kind, self.robot_id)
            return cast(M, decode(payload, kind))
        except WireError as exc:
            with self._lock:
                self.bad += 1
            log.warning("monitor: bad %s: %s", kind.__name__, exc)
            return None

    def on_poses(self, payload: bytes) -> None:
        """Record one TagPoses message."""
        msg = self._decode(payload, TagPoses)
        if msg is None:
            return
        margin = round(MAX_CAPTURE_AHEAD_SECS * 1e9)
        try:
            refuse_future_capture(msg, now_nanos=self.wall_clock_nanos(), ahead_nanos=margin)
            if self.run_started_nanos is not None and msg.capture_nanos < self.run_started_nanos - margin:
                raise SchemaError(f"TagPoses seq {msg.seq} captured before this run began")
        except SchemaError as exc:
            with self._lock:
                self.out_of_time += 1
                count = self.out_of_time
            if count & (count - 1) == 0:
                log.warning("monitor: %s: not recorded (%d such so far)", exc, count)
            return
        with self._lock:
            if (msg.capture_nanos, msg.seq) in self._recent_frames:
                self.repeated += 1
                return
            self._recent_frames[(msg.capture_nanos, msg.seq)] = None
            _keep_newest(self._recent_frames, 20_000)
        rec: dict[str, Any] = {
            "seq": msg.seq,
            "capture_nanos": msg.capture_nanos,
            "k": msg.split_k,
            "payload_bytes": msg.payload_bytes,
            "tags": len(msg.tags),
            "robot_ms": 1e3 * msg.timings.robot_compute_secs,
            "transport_ms": 1e3 * msg.timings.transport_secs,
            "edge_ms": 1e3 * msg.timings.edge_compute_secs,
            "e2e_ms": 1e3 * msg.timings.capture_to_pose_secs,
            **_waits_ms(msg),
            "t": self.clock(),
            "errors_cm": self._errors(msg),
            "sent_nanos": msg.link.sent_nanos if msg.link is not None else None,  # None: computed on board
        }
        listed = self._listed_ids
        unlisted = {t.tag_id: t.tag_size_m for t in msg.tags if listed and t.tag_id not in listed}
        with self._lock:
            for tag_id, size_m in unlisted.items():
                if tag_id not in self.tags_not_in_map:
                    self.tags_not_in_map[tag_id] = size_m
                    self._notices.append(
                        f"tag {tag_id} is not in the run's tag map: solved at the default size {size_m:g} m "
                        "(its poses and slam's are wrong if that is not its size: list it in the map)"
                    )
            self.records.append(rec)
            self._recent.append(rec)
            self.frames_total += 1
            if msg.link is None:
                self.frames_on_board += 1
            else:
                self.frames_by_k[msg.split_k] += 1
            if self.max_records is not None and len(self.records) > self.max_records:
                del self.records[: len(self.records) // 2]

    @functools.cached_property
    def _listed_ids(self) -> frozenset[int]:
        """The ids the run's tag map lists (none: no map, or sizes by default only)."""
        return frozenset(t.id for t in self.tag_map.tags) if self.tag_map is not None else frozenset()

    def notices(self) -> list[str]:
        """What the run should be told once, since the last call (a tag missing from its map)."""
        with self._lock:
            out, self._notices = self._notices, []
        return out

    def on_controller(self, payload: bytes) -> None:
        """Keep the latest controller state for the live line, and its predictions (when it has them) by
        the time it decided, for frames.csv (joined there by each frame's send time: a state crosses the
        uplink behind the frames and may arrive after the poses of the frame it concerns)."""
        state = self._decode(payload, ControllerState)
        if state is None:
            return
        self.controller = state
        with self._lock:
            if len(self.controller_states) == self.controller_states.maxlen:
                self.controller_states_dropped += 1
            self.controller_states.append(state)
            self.controller_decisions += 1
            self.controller_switches += int(state.applied)
            self.controller_pinned += int(state.pinned)
        if state.has_prediction:
            with self._lock:
                self.predictions.append(
                    (state.stamp_nanos, tuple(state.predicted_ms_by_k), state.best_k, state.t0_ms, state.beta_ms_per_kB)
                )

    def take_controller_states(self) -> list[ControllerState]:
        """The controller states that came since the last call (they are no longer kept here)."""
        with self._lock:
            states = list(self.controller_states)
            self.controller_states.clear()
            return states

    def records_since(self, first: int, arrived_by: float | None) -> tuple[int, list[dict[str, Any]], list[Prediction]]:
        """The records of the run's `first`-th frame on (counting every frame, as `frames_total`) that
        arrived by `arrived_by` on this monitor's clock (None: all), and the controller's predictions;
        returned with the index of the first record returned, which is past `first` when the monitor had
        already dropped those frames (a run that outgrew `max_records` before they were asked for)."""
        with self._lock:
            start = self.frames_total - len(self.records)
            i = max(first, start) - start
            out = []
            for rec in self.records[i:]:
                if arrived_by is not None and rec["t"] > arrived_by:
                    break
                out.append({**rec, "source_stamp_nanos": self._source_stamps.get(rec["capture_nanos"])})
            return start + i, out, sorted(self.predictions) if out else []

    def snapshot(self) -> tuple[list[dict[str, Any]], list[Prediction]]:
        """Copies of the frame records and the controller's predictions, for a run's files."""
        with self._lock:
            stamps = self._source_stamps
            records = [{**r, "source_stamp_nanos": stamps.get(r["capture_nanos"])} for r in self.records]
            return records, sorted(self.predictions)

    def on_camera(self, payload: bytes) -> None:
        """Record one SLAM CameraPose: its status, its position sigma (sqrt of the covariance's position
        trace) and, with ground truth and a tag map that fixes slam's world, its position error."""
        msg = self._decode(payload, CameraPose)
        if msg is None:
            return
        cov = msg.covariance_world
        sigma = None if cov is None else 100 * float(np.sqrt(np.trace(cov[:3, :3])))
        with self._lock:
            mapped = (
                self.slam_has_map
                and self.tag_map is not None
                and any(t.world_from_tag is not None for t in self.tag_map.tags)
            )
            truth = self.gt.get(msg.seq) if mapped else None  # slam's world is the map's only with poses
            error = nees = None
            if truth is not None and msg.status == "tracking":
                delta = np.asarray(msg.world_from_camera[:3, 3] - truth[:3, 3], np.float64)
                error = 100 * float(np.linalg.norm(delta))
                if cov is not None:
                    with contextlib.suppress(np.linalg.LinAlgError):
                        nees = float(delta @ np.linalg.solve(np.asarray(cov, np.float64)[:3, :3], delta))
            self.slam_status[msg.status] = self.slam_status.get(msg.status, 0) + 1
            self._slam_recent.append({"t": self.clock(), "status": msg.status, "sigma": sigma, "error": error})
            if sigma is not None:
                self._slam_sigma_cm.append(sigma)
            if error is not None:
                self._slam_error_cm.append(error)
            if nees is not None and np.isfinite(nees):
                self._slam_nees.append(nees)

    def on_gt(self, payload: bytes) -> None:
        """Record one ground-truth camera pose."""
        msg = self._decode(payload, CameraPose)
        if msg is None:
            return
        with self._lock:
            self.gt_total += 1
            self._last_gt_at = self.clock()
            self._last_gt_seq = msg.seq  # the latest (seq starts again with each camera session or pass)
            self.gt[msg.seq] = msg.world_from_camera
            while len(self.gt) > self.max_ground_truth:
                del self.gt[next(iter(self.gt))]  # the oldest (insertion order)

    def on_stamp(self, payload: bytes) -> None:
        """Count one data-set stamp (FrameStamp): the camera captured that frame; keep its stamp."""
        stamp = self._decode(payload, FrameStamp)
        if stamp is not None:
            with self._lock:
                self.stamps_total += 1
                self._source_stamps[stamp.capture_nanos] = stamp.source_stamp_nanos
                _keep_newest(self._source_stamps, 20_000)
                # (a data set without ground truth says the camera is there too: a trial's video run, ended
                # by max_frames, was asked 'is the robot up?' as the camera stopped)
                self._last_gt_at = self.clock()
                self._last_gt_seq = stamp.seq

    def _errors(self, msg: TagPoses) -> list[float]:
        if self.tag_map is None:
            return []
        with self._lock:
            world_from_camera = self.gt.get(msg.seq)
        if world_from_camera is None:
            return []
        poses = {t.id: t.world_from_tag for t in self.tag_map.tags if t.world_from_tag is not None}
        out = []
        for tag in msg.tags:
            if tag.tag_id in poses:
                true = np.linalg.inv(world_from_camera) @ np.asarray(poses[tag.tag_id])
                out.append(float(translation_error_cm(tag.camera_from_tag[:3, 3], true[:3, 3])))
        return out

    def line(self, down: Sequence[str] = (), back: Mapping[str, float] | None = None) -> str:
        """One status line over the last second. `down`: the run's processes that exited and are not
        back yet (the supervisor's), named first when the poses stopped (a trial's monitor asked
        whether the edge was up while robot_infer was the one restarting); `back`: those that came back
        moments ago, name -> when (this monitor's clock), said next when the poses stopped before it came
        back (a trial was asked whether the edge was up just after robot_infer came back; a silence that
        began after is not put down to the restart: review)."""
        now = self.clock()
        with self._lock:
            recent = [r for r in self._recent if now - r["t"] <= 1.0]
            last = self._recent[-1] if self._recent else None
            gt_at, gt_seq = self._last_gt_at, self._last_gt_seq
        if not recent:
            if last is None:
                return "waiting for TagPoses..."
            # Say what a silence means. The camera's ground truth still coming: the robot's side is up and
            # reaches this monitor, so the poses are what stopped (a monitor that cannot reach the robot's
            # router does not see those the robot computes on board while the edge is down). Both stopped:
            # the robot.
            silent = f"no TagPoses for {now - last['t']:.1f} s (the last: frame {last['seq']})"
            if down:
                return f"{silent}: {' and '.join(down)} exited and {'is' if len(down) == 1 else 'are'} not back yet"
            restarted = [name for name, at in (back or {}).items() if at >= last["t"]]
            if restarted:
                return (
                    f"{silent}: {' and '.join(restarted)} came back from a restart moments ago and may still be "
                    "starting up"
                )
            # the poses caught up and the camera went quiet (a restarted camera counts from 0 again: only
            # a second's silence of its own says so)
            if gt_at is not None and gt_seq <= last["seq"] and now - gt_at > 1.0:
                return (
                    f"{silent}: the camera has sent nothing newer for {now - gt_at:.1f} s (its source ended or "
                    "paused, or the robot's host is down?)"
                )
            if gt_at is not None and now - gt_at <= 2.0 and self.at_robot:
                return (
                    f"{silent} while its camera streams; is robot_infer running? (this monitor listens at the "
                    "robot's router, where even the poses computed on board arrive)"
                )
            if gt_at is not None and now - gt_at <= 2.0:
                return (
                    f"{silent} while its camera streams; is the edge up? The robot computes on board while it "
                    "is not, and a monitor that cannot reach the robot's router does not see those poses"
                )
            if gt_at is not None:
                return (
                    f"{silent}, nor its camera's ground truth or stamps for {now - gt_at:.1f} s; is the robot's host "
                    "up (its camera, robot_infer), and its link to the edge?"
                )
            return (
                f"{silent}; is the robot up, and the edge? (a monitor that cannot reach the robot's router sees "
                "no on-board poses)"
            )
        med = {k: float(np.median([r[k] for r in recent])) for k in ("robot_ms", "transport_ms", "edge_ms", "e2e_ms")}
        errs = [e for r in recent for e in r["errors_cm"]]
        err = f" e_t {np.median(errs):.2f} cm" if errs else ""
        ages = [r["before_robot_ms"] for r in recent if not np.isnan(r["before_robot_ms"])]
        age = f" (frame age {np.median(ages):.1f})" if ages else ""
        # (a trial saw the robot go on board only as 'payload 0.0 kB')
        where = (
            f"k={recent[-1]['k']}  payload {recent[-1]['payload_bytes'] / 1024:7.1f} kB"
            if recent[-1]["sent_nanos"] is not None
            else "on board (the edge away)"
        )
        return (
            f"{len(recent):>3} fps  {where}  "
            f"robot {med['robot_ms']:6.1f} ms  link {med['transport_ms']:5.1f} ms  edge {med['edge_ms']:5.1f} ms  "
            f"capture->pose {med['e2e_ms']:6.1f} ms{age}  tags {recent[-1]['tags']}{err}{self._slam_part(now)}"
            f"{self._controller_part()}"
        )

    def _slam_part(self, now: float) -> str:
        with self._lock:
            recent = [r for r in self._slam_recent if now - r["t"] <= 1.0]
        if not recent:
            return ""
        sigmas = [r["sigma"] for r in recent if r["sigma"] is not None]
        errors = [r["error"] for r in recent if r["error"] is not None]
        sigma = f" sigma {np.median(sigmas):.1f} cm" if sigmas else ""
        error = f" e {np.median(errors):.1f} cm" if errors else ""
        return f"  | slam {recent[-1]['status']}{sigma}{error}"

    def _controller_part(self) -> str:
        c = self.controller
        if c is None:
            return ""
        if not c.has_prediction:
            return f"  | controller: {c.reason}"
        t = c.predicted_ms_by_k
        pin = " pinned" if c.pinned else ""
        return (
            f"  | controller t0 {c.t0_ms:.1f} ms beta {c.beta_ms_per_kB:.3f} ms/kB "
            f"best k={c.best_k} ({t[c.best_k]:.0f} ms){pin}"
        )

    def summary(self) -> dict[str, Any]:
        """Totals over the whole run."""
        with self._lock:
            recs = list(self.records)
        errs = [e for r in recs for e in r["errors_cm"]]
        out: dict[str, Any] = {"frames": len(recs), "frames_total": self.frames_total, "bad_messages": self.bad}
        if self.repeated:
            out["repeated_messages"] = self.repeated
        if self.out_of_time:
            out["out_of_time_messages"] = self.out_of_time
        captured = max(self.gt_total, self.stamps_total)
        if captured:  # robot_infer takes the newest frame: a camera faster than the robot skips frames
            out["frames_captured"] = captured
            out["frames_skipped"] = max(0, captured - self.frames_total)
        if recs:
            e2e = [r["e2e_ms"] for r in recs]
            out.update({"e2e_ms_p50": float(np.percentile(e2e, 50)), "e2e_ms_p99": float(np.percentile(e2e, 99))})
            split = [r for r in recs if not np.isnan(r["before_robot_ms"])]  # not computed on board
            if split:  # where frames waited outside robot + link + edge compute (medians)
                out["frame_age_ms_p50"] = float(np.median([r["before_robot_ms"] for r in split]))
                out["edge_queue_ms_p50"] = float(np.median([r["at_edge_ms"] for r in split]))
        with self._lock:
            if self.frames_by_k:
                out["frames_by_k"] = {str(k): n for k, n in sorted(self.frames_by_k.items())}
            out["frames_on_board"] = self.frames_on_board  # 0 too: the README's sum frames_by_k + this = frames
            if self.tags_not_in_map:  # tag id -> the size it was solved at
                out["tags_not_in_map"] = {str(i): m for i, m in sorted(self.tags_not_in_map.items())}
            if self.controller_decisions:
                out["controller"] = {
                    "decisions": self.controller_decisions,
                    "switches": self.controller_switches,
                    "pinned_fraction": round(self.controller_pinned / self.controller_decisions, 4),
                }
            if self.slam_status:
                out["slam_frames"] = dict(self.slam_status)
                # posed frames slam gave no camera pose for (it was down, or refused them): a soak trial's
                # kill of slam left a 3 s hole in trajectory.tum that the summary did not point out
                out["frames_without_slam_pose"] = max(0, self.frames_total - sum(self.slam_status.values()))
            if self._slam_sigma_cm:
                out["slam_sigma_cm_median"] = float(np.median(self._slam_sigma_cm))
            if self._slam_error_cm:
                out["slam_online_error_cm_median"] = float(np.median(self._slam_error_cm))
            if self._slam_nees:
                # 3 when the covariance is calibrated; slam's covariance_scale that would make it so
                mean_nees = float(np.mean(self._slam_nees))
                out["slam_position_nees_mean"] = mean_nees
                out["slam_covariance_scale_measured"] = mean_nees / 3.0
                # The mean is set by the worst frames: an EKF integrator's trial read 0.035 in calm frames and
                # 38 in a sharp turn. The median (2.37 when calibrated) and the share inside the 95 %
                # ellipsoid (NEES <= 7.81) tell the two apart.
                nees = np.asarray(self._slam_nees, np.float64)
                out["slam_position_nees_median"] = float(np.median(nees))
                out["slam_position_inside95_pct"] = 100.0 * float(np.mean(nees <= CHI2_3_95))
        if errs:
            out.update(
                {
                    "e_t_cm_median": float(np.median(errs)),
                    "e_t_cm_mean": float(np.mean(errs)),
                    "tag_observations": len(errs),
                }
            )
        return out


def attach_monitor(session: zenoh.Session, robot_id: str, monitor: Monitor) -> list[Any]:
    """Subscribe the monitor (callbacks) to TagPoses, SLAM poses, the controller and ground truth of
    `robot_id` (a message naming another robot is counted as bad, as the services count it)."""
    monitor.robot_id = robot_id
    return [
        session.declare_subscriber(keys.ground_truth(robot_id), lambda s: monitor.on_gt(s.payload.to_bytes())),
        session.declare_subscriber(keys.camera_pose(robot_id), lambda s: monitor.on_camera(s.payload.to_bytes())),
        session.declare_subscriber(keys.tag_poses(robot_id), lambda s: monitor.on_poses(s.payload.to_bytes())),
        session.declare_subscriber(keys.controller(robot_id), lambda s: monitor.on_controller(s.payload.to_bytes())),
        session.declare_subscriber(keys.frame_stamp(robot_id), lambda s: monitor.on_stamp(s.payload.to_bytes())),
    ]


MAP_USERS = ("edge_infer", "robot_infer", "slam")  # the services that read `tag_map`


def repo_path(path: str | Path) -> Path:
    """A path as the services read it: they run from the repository root (start_process), so a relative
    path in a config is relative to it, wherever the launcher was started."""
    p = Path(path).expanduser()
    return p if p.is_absolute() else REPO / p


def run_map_tables(
    tables: dict[str, Any], run_dir: Path, *, demo_users: tuple[str, ...] = MAP_USERS
) -> tuple[dict[str, dict[str, Any]], Path | None]:
    """One tag map for a run whose config `tables` are given: (the tables that give it to the services
    that name none, the map's path or None).

    The map the tables name (slam's, else edge_infer's, else robot_infer's) goes to each of the three that
    names none, so the edge solves every tag at the size slam maps it with; different maps are warned
    about. None named: the demo scene's map for the demo source (written to run_dir/tag_map.yaml, for
    `demo_users`); for any other source no map (every tag at the services' default_tag_size_m, slam's
    world its anchor tag's), with a warning: the demo's map would give a user's tags the demo's sizes
    and poses."""
    named = {svc: tables.get(svc, {}).get("tag_map") for svc in MAP_USERS}
    given = [str(named[svc]) for svc in ("slam", "edge_infer", "robot_infer") if named[svc]]
    if len({repo_path(g).resolve() for g in given}) > 1:
        log.warning(
            "the services name different tag maps (%s): a tag solved at one size and mapped at another is "
            "rescaled by slam, but give them one map",
            ", ".join(f"{svc}: {named[svc]}" for svc in MAP_USERS if named[svc]),
        )
    if given:
        return {svc: {"tag_map": given[0]} for svc in MAP_USERS if not named[svc]}, repo_path(given[0])
    if tables.get("camera", {}).get("source", "demo") == "demo":
        path = run_dir / "tag_map.yaml"
        run_dir.mkdir(parents=True, exist_ok=True)
        path.write_text(yaml.safe_dump(demo_tag_map().model_dump(), sort_keys=False))
        return {svc: {"tag_map": str(path)} for svc in demo_users}, path
    log.warning(
        "no tag_map: every tag is solved at the services' default size (default_tag_size_m, 0.2 m) and slam's "
        "world is the frame of the tag it anchors on; name a tag map (README: Your own data) under [slam] "
        "(the launcher gives it to edge_infer and robot_infer too)"
    )
    return {}, None


def write_run_config(
    run_dir: Path,
    base_config: Path,
    *,
    topology: Topology | None = None,
    extra: dict[str, dict[str, Any]] | None = None,
) -> Path:
    """The run's config.toml: the deploy TOML with run_dir and one tag map for the whole run
    (`run_map_tables`), its endpoints from `topology` when given (shared.tools.topology), then `extra`."""
    base = tomllib.loads(base_config.read_text())
    maps, _ = run_map_tables(merge(base, extra or {}), run_dir)
    run_tables = merge({"common": {"run_dir": str(run_dir)}}, maps)
    return write_config(
        run_dir / "config.toml", base=base_config, topology=topology, extra=merge(run_tables, extra or {})
    )


def loopback_config(
    run_dir: Path,
    *,
    robot_id: str,
    rerun: bool = False,
    image_every: int = 5,
    fps: float = 15.0,
    split_k: int = 7,
    base_config: Path = Path("deploy/local.toml"),
    rerun_rotate_secs: float | None = None,
) -> tuple[Path, Topology]:
    """deploy/local.toml on free loopback ports (for benchmarks): the run config and its topology."""
    topology = Topology.loopback()
    rerun_table: dict[str, Any] = {"enabled": rerun, "image_every": image_every}
    if rerun_rotate_secs is not None:
        rerun_table["rotate_secs"] = rerun_rotate_secs
    extra: dict[str, dict[str, Any]] = {
        "common": {"robot_id": robot_id, "rerun": rerun_table},
        "robot_infer": {"split_k": split_k},
        "camera": {"source": "demo", "fps": fps},
    }
    return write_run_config(run_dir, base_config, topology=topology, extra=extra), topology


def run_tag_map(config: Path) -> TagMapFile | None:
    """The tag map the run's slam uses (its config's `slam.tag_map`), so the monitor measures errors in
    slam's world; None when it names none (slam's world is then its anchor tag's: no error is measured)."""
    path = tomllib.loads(config.read_text()).get("slam", {}).get("tag_map")
    return load_tag_map(repo_path(path)) if path else None


def monitor_settings(config: Path, *, at_robot: bool = False) -> tuple[str, ZenohSettings]:
    """robot_id and a client session to the edge router (and the robot's, where the edge side reaches
    it), from the run config; `at_robot` (the robot's host of `up --only robot`): to the robot's router."""
    doc = tomllib.loads(config.read_text())
    robot_id = doc.get("common", {}).get("robot_id", "robot1")
    tls_table = doc.get("monitor", {}).get("tls")  # the operator's certificate in a TLS deployment
    tls = TlsSettings.model_validate(tls_table) if tls_table is not None else None
    topology = Topology.from_config(config)
    # the robot's router second, where reachable: a client fails over to it while the edge's is away
    endpoints = [topology.robot_router] if at_robot else topology.edge_side_endpoints(topology.edge_router)
    return robot_id, ZenohSettings(mode="client", connect=endpoints, tls=tls)


# How long after a restarted process is back (its liveliness token) a silence of the poses that began before
# is put down to its restart: the pipeline's first frames after it (a restarted edge_infer, slam) follow.
RESTART_WARMUP_SECS = 20.0


class LaunchError(RuntimeError):
    """The run cannot go on: a service refused its settings (restarting it cannot help: `exit_code`
    CONFIG_EXIT), or the services did not come up in time (1). The launcher stops every service first."""

    def __init__(self, message: str, *, exit_code: int = 1) -> None:
        super().__init__(message)
        self.exit_code = exit_code


class _StopRequested(Exception):
    """SIGINT/SIGTERM while the services were still coming up."""


def configuration_error_line(service: Service) -> str:
    """What a service that exited with CONFIG_EXIT said about its settings (the last such line of its
    log), for the one line the launcher prints."""
    lines = [line for line in service.log_text().splitlines() if "configuration error" in line]
    if not lines:
        return f"{service.name} exited with code {CONFIG_EXIT} (configuration error; see {service.log_path})"
    found = re.search(r"(\S+): (configuration error: .*)$", lines[-1])
    return f"{service.name}: {found[2]}" if found else lines[-1]


def open_monitor_session(
    settings: ZenohSettings, tick: Callable[[], object], *, timeout_secs: float = 120.0
) -> zenoh.Session:
    """The launcher's session to a router one of the run's services opens (the edge's; on a fleet's
    robot host the robot's): tried in
    2 s attempts with `tick` (supervision) between them, so a service that refused its settings or a
    Ctrl-C ends the wait at once instead of after one long connection timeout."""
    attempt = settings.model_copy(update={"connect_timeout_secs": min(2.0, settings.connect_timeout_secs)})
    deadline = time.monotonic() + timeout_secs
    while True:
        try:
            return open_session(attempt)
        except zenoh.ZError:
            if time.monotonic() > deadline:
                raise
            tick()


@dataclass
class Started:
    """The launcher's session to the run and its monitor's subscriptions; `up`: every process's token
    came (False: a person stopped the run while it came up)."""

    session: zenoh.Session | None = None
    subscriptions: list[Any] = field(default_factory=list)
    up: bool = False


def run_for(
    stop: threading.Event,
    duration_secs: float | None,
    *,
    lines: Callable[[], list[str]],
    quiet: bool,
    supervise: Callable[[], object],
    every_second: Callable[[], None] | None = None,
) -> None:
    """A started run, once a second: print the live `lines` (unless `quiet`), `every_second` (writing
    the run's files as it goes) and `supervise` (restart the dead; a False return ends the run: its
    camera's source ended); until `stop`, `duration_secs`."""
    t_end = None if duration_secs is None else time.monotonic() + duration_secs
    while not stop.wait(1.0):
        if every_second is not None:
            every_second()
        if not quiet:
            for line in lines():
                print(line, flush=True)
        if (t_end is not None and time.monotonic() > t_end) or supervise() is False:
            break


def wait_for_run(
    settings: ZenohSettings,
    wanted: list[str],
    *,
    attach: Callable[[zenoh.Session], list[Any]],
    supervise: Callable[[], object],
    stop: threading.Event,
    timeout_secs: float,
    run_dir: Path,
) -> Started:
    """Join the run's edge router (a service of the run opens it) and wait for every wanted liveliness
    token, supervising meanwhile: a service that refuses its settings ends the wait (LaunchError, from
    `supervise`), Ctrl-C (`stop`) ends it quietly, tokens that never come are a LaunchError naming them.
    On an error the session is closed here; otherwise the caller closes it."""
    started = Started()

    def tick() -> None:
        if stop.is_set():
            raise _StopRequested
        supervise()

    try:
        started.session = open_monitor_session(settings, tick, timeout_secs=timeout_secs)
        started.subscriptions = attach(started.session)
        wait_for_liveliness(started.session, wanted, timeout_secs=timeout_secs, every_second=tick)
        started.up = True
    except _StopRequested:
        print("stopped before every process was up", flush=True)
    except BaseException as exc:
        if started.session is not None:
            started.session.close()  # Zenoh's threads would keep the interpreter from exiting
        if isinstance(exc, TimeoutError):
            raise LaunchError(f"{exc} (each process's log is in {run_dir})") from None
        raise
    return started


def forget_run_files(run_dir: Path) -> None:
    """A run has ended: its pid files go, so `splittag down` cannot signal whatever reuses the pids."""
    for name in ("launcher.pid", "pids"):
        (run_dir / name).unlink(missing_ok=True)


class ComingsAndGoings:
    """The run's liveliness tokens as live lines (Zenoh's callback only enqueues): a process that had
    exited is back when its token returns (said with how long it was out, and kept as an incident),
    and a fleet's edge worker that goes or comes hands robots on (`robots`: the fleet's, whose
    assignment every worker computes the same way). `name_of` maps a token's key to the launcher's
    process name (None: not a process of this run). Events before `arm()` (the run coming up) are
    dropped."""

    def __init__(
        self,
        supervisor: Supervisor,
        name_of: Callable[[str], str | None],
        *,
        robots: list[str] | None = None,
        workers: list[str] | None = None,
    ) -> None:
        self.supervisor, self.name_of, self.robots = supervisor, name_of, robots or []
        self.workers = set(workers or [])
        self._events: deque[tuple[str, bool]] = deque(maxlen=10_000)
        self._armed = False

    def on_token(self, sample: zenoh.Sample) -> None:
        """Liveliness subscriber callback: a token appeared (PUT) or went (DELETE)."""
        self._events.append((str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT))

    def arm(self) -> None:
        """The run is up: from now on every coming and going is news."""
        self._events.clear()
        self._armed = True

    def lines(self) -> list[str]:
        """What came and went since the last call."""
        out: list[str] = []
        while self._events:
            key, up = self._events.popleft()
            if not self._armed:
                continue
            name = self.name_of(key)
            if name is None:
                continue
            if up:
                down = self.supervisor.ready(name)
                if down is not None:
                    out.append(f"{name} is back: ready {down:.1f} s after it exited")
            if self.robots and "/edge_worker/" in key:  # a fleet worker: its robots move
                out += self._handover(name, up)
        return out

    def _handover(self, worker: str, up: bool) -> list[str]:
        from shared.transport.fleet import assign

        before = assign(self.robots, self.workers)
        self.workers = self.workers | {worker} if up else self.workers - {worker}
        after = assign(self.robots, self.workers)
        what = "up" if up else "gone"
        moved = {r: after.get(r) for r in self.robots if before.get(r) != after.get(r)}
        if moved:
            self.supervisor.handover(worker, up=up, moved=moved)
        if not after:
            return [f"edge worker {worker} {what}: no edge worker left, every robot computes on board"]
        moves = [f"{r} -> {after[r]}" for r in self.robots if before.get(r) != after.get(r)]
        return [f"edge worker {worker} {what}: " + (", ".join(moves) if moves else "no robot moves")]


def _service_of_token(robot_id: str, services: tuple[str, ...], key: str) -> str | None:
    """`splittag/<robot_id>/alive/<service>` -> the service, for a service of this run."""
    parts = key.split("/")
    if len(parts) == 4 and parts[:3] == [keys.ROOT, robot_id, "alive"] and parts[3] in services:
        return parts[3]
    return None


def _remove_orphaned_link(run_config: Path) -> str:
    """The emulated link of a run whose launcher died (its namespaces and delay line stayed: a trial):
    removed as the launcher would have, unless something else now uses it. Which link: the run config's
    [link] table (the default one without it)."""
    from shared.tools.linkemu import LinkEmulator, LinkEmulatorSettings, delay_line_owner, netns_pids

    try:
        settings = LinkEmulatorSettings.from_config(run_config) if run_config.is_file() else LinkEmulatorSettings()
    except (OSError, ValueError) as exc:  # (LinkProfileError is a ValueError)
        return f"left up: cannot tell which link the run had ({exc})"
    emu = LinkEmulator(settings)
    s = emu.settings
    owners = [o for ns in (s.robot_ns, s.edge_ns) for p in netns_pids(ns) if (o := delay_line_owner(p)) is not None]
    if emu.services_inside() or owners:
        return "left up: another deployment or `link up` uses it now"
    if not emu.is_up():
        return "already gone"
    emu.down()
    print("removed the run's emulated link (its launcher had died)", flush=True)
    return "removed by `splittag down`"


def finish_orphaned_run(run_dir: Path, stopped: list[str], *, still_running: list[str] | None = None) -> dict[str, Any]:
    """What the launcher would have done at the end, for a run whose launcher died (`splittag down`
    stopped its services): pid files gone, the recording parts merged, and a summary.json that says so,
    with what the run folder still tells (frames.csv's rows and from them the frames, e2e and frames by k;
    incidents, link profiles, every process's input counts, slam's outputs). The monitor's other figures
    (slam's online error, the controller's decisions) died with the launcher. Services `still_running`
    (they did not stop in time) keep their recording parts unmerged: they are still being written."""
    import csv

    from shared.tools.supervise import read_incidents, summarise_incidents

    forget_run_files(run_dir)
    summary: dict[str, Any] = {
        "run_dir": str(run_dir),
        "launcher": "died before the run ended; `splittag down` stopped the services and wrote this summary",
        "stopped_by_down": stopped,
    }
    from shared.tools.linkemu import EVENTS_FILE

    if (run_dir / EVENTS_FILE).is_file() and not still_running:  # (the run had an emulated link)
        summary["emulated_link"] = _remove_orphaned_link(run_dir / "config.toml")
    for name in ("frames.csv", *sorted(p.name for p in run_dir.glob("frames_*.csv"))):
        if (run_dir / name).is_file():
            with (run_dir / name).open() as f:
                rows = list(csv.DictReader(f))
            summary[f"{name.removesuffix('.csv')}_csv_rows"] = len(rows)
            e2e = [float(r["e2e_ms"]) for r in rows if r.get("e2e_ms")]
            if e2e:  # (the monitor's figures died with it; frames.csv has each frame's; a fleet's, per robot)
                figures = {
                    "frames": len(rows),
                    "e2e_ms_p50": float(np.percentile(e2e, 50)),
                    "e2e_ms_p99": float(np.percentile(e2e, 99)),
                    "frames_by_k": {k: n for k, n in sorted(Counter(r["k"] for r in rows).items())},
                }
                if name == "frames.csv":
                    summary |= figures
                else:
                    summary.setdefault("robots", {})[name.removeprefix("frames_").removesuffix(".csv")] = figures
    from shared.tools.linkemu import read_events

    if events := read_events(run_dir):
        summary["link_profiles"] = events
    if inputs := input_counts_summary(run_dir):  # every service process's input counts, restarts included
        summary["inputs"] = inputs
    incidents = run_dir / "incidents.jsonl"
    if incidents.is_file():
        summary |= {**summarise_incidents(read_incidents(incidents)), "incidents": str(incidents)}
    for name in ("slam.json", "ate.json"):
        with contextlib.suppress(OSError, ValueError):  # a file cut short by the crash is left out
            summary["slam"] = json.loads((run_dir / name).read_text())
    if still_running:
        summary["still_running"] = still_running
    else:
        recording = merge_recordings(run_dir)
        if recording is not None:
            summary["recording"] = str(recording)
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def router_hosts(run_config: Path, *, only: str | None = None) -> dict[str, str]:
    """What each router's process takes down with it, for the supervisor's line when it dies (`only`:
    this launcher runs one host's part, `up --only`)."""
    fails_over = Topology.from_config(run_config).robot_from_edge is not None
    if only == "robot":  # this host's monitor listens at the robot's router alone
        return {
            "robot_infer": "it is the robot's router: the camera's frames and this host's monitor wait until it is "
            "back" + (" (slam, if on it since an edge restart, fails over to the edge's)" if fails_over else "")
        }
    edge = (
        "it is the edge's router: slam and the monitor fail over to the robot's router and stay there (the "
        "robot computes on board until it is back)"
        if fails_over
        else "it is the edge's router: robot, slam and monitor are cut off until it is back"
    )
    robot = "it is the robot's router: the camera's frames wait until it is back" + (
        " (slam and the monitor, if on it since an edge restart, fail over to the edge's)" if fails_over else ""
    )
    return {"edge_infer": edge, "robot_infer": robot}


class _Services:
    """The services of one run: started, their pids written, restarted by the supervisor's policy."""

    def __init__(
        self, run_config: Path, run_dir: Path, wrappers: dict[str, list[str]], *, only: str | None = None
    ) -> None:
        self.run_config, self.run_dir, self.wrappers = run_config, run_dir, wrappers
        self.started: list[Service] = []
        hosts = router_hosts(run_config, only=only)
        self.supervisor = Supervisor(record=incidents_file(run_dir / "incidents.jsonl"), hosts=hosts)
        self.restart_at: dict[str, float] = {}

    def _start(self, name: str) -> Service:
        service = start_service(name, self.run_config, self.run_dir, wrapper=self.wrappers.get(name))
        self.supervisor.started(name, pid=service.popen.pid)
        return service

    def _write_pids(self) -> None:
        # Atomic: `down` and the tests read it while a restart rewrites it (a clean-clone CI run read a
        # truncated file that had lost robot_infer's line mid-restart).
        atomic_write_text(self.run_dir / "pids", "\n".join(f"{s.name} {s.popen.pid}" for s in self.started) + "\n")

    def start_all(self, names: tuple[str, ...]) -> None:
        for name in names:
            self.started.append(self._start(name))
        self._write_pids()

    def supervise(self) -> bool:
        """Restart dead services after their backoff; False when the camera's source has ended the run.
        LaunchError when a service refused its settings (exit code CONFIG_EXIT): it would only refuse
        them again."""
        for i, service in enumerate(self.started):
            code = service.popen.poll()
            if code is None:
                continue
            if code == CONFIG_EXIT:
                raise LaunchError(configuration_error_line(service), exit_code=CONFIG_EXIT)
            if service.name not in self.restart_at:
                delay = self.supervisor.exited(service.name, code)
                if delay is None:
                    print("the camera's source ended; stopping", flush=True)
                    time.sleep(1.0)  # let the last frames arrive
                    return False
                # Printed once (it was also logged, and a terminal showed every restart twice), with why.
                print(self.supervisor.exit_line(service.name, code, delay, why=service.last_error()), flush=True)
                self.restart_at[service.name] = time.monotonic() + delay
            elif time.monotonic() >= self.restart_at[service.name]:
                del self.restart_at[service.name]
                self.started[i] = self._start(service.name)
                self._write_pids()
        return True


def refuse_own_run_dir(config: Path) -> None:
    """A config's `run_dir` is refused: the launcher gives each run a new folder, and a soak trial's
    `[common] run_dir` (to go on in the folder of a run it had stopped) was replaced without a word, so
    slam started from nothing. Carrying a map over is `[slam] tag_map = "<that run>/map.json"`."""
    import tomllib

    try:
        doc = tomllib.loads(config.read_text())
    except (OSError, ValueError):
        return  # (said where the config is read)
    tables = [name for name, table in doc.items() if isinstance(table, dict) and "run_dir" in table]
    if tables:
        raise LaunchError(
            f"{config}: run_dir in [{tables[0]}] is the launcher's to set (each run gets a new folder under "
            '--runs); to go on with an earlier run\'s map, give [slam] tag_map = "<that run>/map.json"',
            exit_code=2,
        )


def _placement(
    config: Path, services: tuple[str, ...], link: str | None
) -> tuple[Topology, dict[str, list[str]], LinkEmulator | None]:
    """Where the services run: loopback per the config, or both sides of an emulated uplink (its
    namespaces and addresses from the config's [link] table, the ports from its routers' listen
    endpoints)."""
    from shared.tools.linkemu import LinkEmulator, LinkEmulatorSettings, LinkProfileError, in_netns

    own = Topology.from_config(config)
    if link is None:
        return own, {}, None
    try:
        emu = LinkEmulator(LinkEmulatorSettings.from_config(config))  # the config's [link] table
    except LinkProfileError as exc:
        raise LaunchError(str(exc), exit_code=2) from None
    topology = emulated_topology(emu.settings, own)
    s = emu.settings
    if own.protocol == "tls":
        problem = link_certificate_problem(config, (s.edge_addr, s.mgmt_edge_addr))
        if problem is not None:
            raise LaunchError(problem, exit_code=2)
    side = {"camera": s.robot_ns, "robot_infer": s.robot_ns, "controller": s.robot_ns}
    return topology, {name: in_netns(side.get(name, s.edge_ns), []) for name in services}, emu


def emulated_topology(link: LinkEmulatorSettings, own: Topology) -> Topology:
    """The endpoints under --link: the emulated link's addresses (`link`, the config's [link] table) with
    the config's own protocol and ports (`own`, Topology.from_config). Pure."""
    return Topology.emulated_link(
        edge_addr=link.edge_addr,
        mgmt_edge_addr=link.mgmt_edge_addr,
        protocol=own.protocol,
        edge_port=own.edge_port,
        robot_port=own.robot_port,
    )


def link_certificate_problem(config: Path, addresses: tuple[str, ...]) -> str | None:
    """Under --link the robot dials the edge's router at the link's address and tools at the management
    one: the edge's certificate must name both (TLS checks the address dialled). What is missing, said
    with the command that makes such certificates; None when it names them (or openssl cannot tell)."""
    doc = tomllib.loads(config.read_text())
    edge = merge(doc.get("common", {}), doc.get("edge_infer", {}))  # (as the edge's settings layer them)
    certificate = edge.get("zenoh", {}).get("tls", {}).get("certificate")
    if not certificate:
        return None
    try:
        shown = subprocess.run(
            ["openssl", "x509", "-noout", "-ext", "subjectAltName", "-in", str(repo_path(certificate))],
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        ).stdout
    except (OSError, subprocess.SubprocessError) as exc:  # (no openssl, or no such file: the edge says which)
        log.warning("--link with TLS: cannot read the names of the edge's certificate %s: %s", certificate, exc)
        return None
    named = set(re.findall(r"IP Address:([0-9A-Fa-f.:]+)", shown))
    missing = [a for a in addresses if a not in named]
    if not missing:
        return None
    stem = Path(certificate).stem
    # deploy/make-certs.sh names the link's addresses itself in a certificate named edge (given again they
    # were listed twice: a trial); any other name needs them given
    names = "" if stem == "edge" else " " + " ".join(missing)
    return (
        f"--link with TLS: the edge's certificate {certificate} does not name {', '.join(missing)}, the emulated "
        f"link's addresses at which the robot and the tools reach the edge; make its certificates again with "
        f"those names, e.g. SPLITTAG_CERT_NAMES={stem} deploy/make-certs.sh {Path(certificate).parent}{names} "
        "(plus any other names it had; deploy/make-certs.sh adds the link's addresses itself to a certificate "
        "named edge)"
    )


FRAME_COLUMNS: tuple[str, ...] = (
    "seq",
    "source_stamp",
    "capture_unix_nanos",
    "sent_unix_nanos",
    "k",
    "payload_bytes",
    "tags",
    "robot_ms",
    "transport_ms",
    "edge_ms",
    "e2e_ms",
    "frame_age_ms",
    "edge_queue_ms",
    "predicted_ms",
    "controller_best_k",
    "controller_t0_ms",
    "controller_beta_ms_per_kB",
    "link_profile",
    "link_rate_mbit",
    "link_delay_ms",
    "tag_error_cm_median",
)


def frame_rows(
    records: list[dict[str, Any]], link_events: list[dict[str, Any]], predictions: list[Prediction] | None = None
) -> list[dict[str, Any]]:
    """One row per frame with poses (FRAME_COLUMNS): the monitor's record; the controller's last
    prediction decided before the frame was sent (`predictions` sorted by stamp; both stamps are the
    robot's clock), T(k) for the frame's k; and the link profile applied before the frame was sent, as
    it crossed the uplink after that (link_events.jsonl, stamped when each change began). None where a
    value is not known (no controller or no prediction yet, no emulated link, no ground truth); a frame
    computed on board (no link stamps) crossed no link: no link, prediction or wait columns."""
    import bisect

    link_stamps = [e["unix_nanos"] for e in link_events]
    predictions = predictions or []
    decided = [p[0] for p in predictions]
    out = []
    for r in records:
        sent = r.get("sent_nanos")
        event = prediction = None
        if sent is not None:
            i = bisect.bisect_right(link_stamps, sent) - 1
            event = link_events[i] if i >= 0 else None
            j = bisect.bisect_right(decided, sent) - 1
            prediction = predictions[j] if j >= 0 else None
        nan_to_none = {k: (None if np.isnan(r[k]) else r[k]) for k in ("before_robot_ms", "at_edge_ms")}
        out.append(
            {
                "seq": r["seq"],
                # the data set's stamp (rgb.txt), seconds as trajectory.tum writes it
                "source_stamp": None
                if r.get("source_stamp_nanos") is None
                else format_stamp_nanos(r["source_stamp_nanos"]),
                "capture_unix_nanos": r["capture_nanos"],
                "sent_unix_nanos": sent,
                "k": r["k"],
                "payload_bytes": r["payload_bytes"],
                "tags": r["tags"],
                "robot_ms": r["robot_ms"],
                # computed on board (no send): nothing crossed the link (a trial's rows read 0.0 and pulled
                # its statistics down)
                "transport_ms": r["transport_ms"] if sent is not None else None,
                "edge_ms": r["edge_ms"],
                "e2e_ms": r["e2e_ms"],
                "frame_age_ms": nan_to_none["before_robot_ms"],
                "edge_queue_ms": nan_to_none["at_edge_ms"],
                "predicted_ms": prediction[1][r["k"]] if prediction else None,
                "controller_best_k": prediction[2] if prediction else None,
                "controller_t0_ms": prediction[3] if prediction else None,
                "controller_beta_ms_per_kB": prediction[4] if prediction else None,
                "link_profile": event["profile"] if event else None,
                "link_rate_mbit": event.get("rate_mbit") if event else None,
                "link_delay_ms": event.get("delay_ms") if event else None,
                "tag_error_cm_median": float(np.median(r["errors_cm"])) if r["errors_cm"] else None,
            }
        )
    return out


def write_frames_csv(path: Path, rows: list[dict[str, Any]], *, append: bool = False) -> None:
    """frames.csv: FRAME_COLUMNS, an empty cell where a value is not known (`append`: rows only)."""
    import csv

    with path.open("a" if append else "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=FRAME_COLUMNS)
        if not append:
            writer.writeheader()
        for row in rows:
            writer.writerow({k: ("" if v is None else v) for k, v in row.items()})


class FramesCsv:
    """A run's frames.csv, written as the run goes: a long run's file holds every frame (not only the
    newest the monitor keeps) and a launcher that dies leaves the rows written until then. Each frame is
    written once, `lag_secs` after its poses arrived, when the controller's last decision before its
    send (a state crosses the uplink behind the frames) and the link profile it crossed are known;
    the rest at the end (`flush(final=True)`)."""

    def __init__(
        self,
        path: Path,
        monitor: Monitor,
        events: Callable[[], list[dict[str, Any]]] = list,
        *,
        lag_secs: float = 10.0,
        controller_path: Path | None = None,
    ) -> None:
        self.path, self.monitor, self.events, self.lag_secs = path, monitor, events, lag_secs
        # Every controller state, one JSON line each, as they come (`controller.jsonl`): what it knew
        # (t0, beta, C(k), E(k), S(k)), predicted, chose and why, stamped on the robot's clock.
        self.controller_path = controller_path
        self.keeps_controller_states = controller_path is not None
        self.controller_lines = 0
        self.next_frame = 0  # the run's first frame not yet written (Monitor.frames_total counts them)
        self.rows = 0
        self.missed = 0  # frames never written: the monitor dropped them first (it outgrew its cap), or a write failed
        self.failed = 0  # of those, the ones whose write failed
        write_frames_csv(path, [])

    def flush(self, *, final: bool = False) -> None:
        """Write the frames whose poses arrived `lag_secs` ago or earlier (every frame when `final`). A
        write that fails (disk full, the folder gone) is said once and those rows are counted missed:
        the file is a side record, not a reason to stop the run."""
        arrived_by = None if final else self.monitor.clock() - self.lag_secs
        first, records, predictions = self.monitor.records_since(self.next_frame, arrived_by)
        written = 0
        if records:
            try:
                write_frames_csv(self.path, frame_rows(records, self.events(), predictions), append=True)
                written = len(records)
            except OSError as exc:
                if not self.failed:
                    log.warning("cannot write %s (%s): its rows are counted as missed", self.path, exc)
                self.failed += len(records)
        self.missed += (first - self.next_frame) + (len(records) - written)
        self.next_frame = first + len(records)
        self.rows += written
        self._write_controller_states()

    def _write_controller_states(self) -> None:
        if self.controller_path is None:
            return
        states = self.monitor.take_controller_states()
        if not states:
            return
        lines = "".join(json.dumps(s.model_dump(mode="json")) + "\n" for s in states)
        try:
            with self.controller_path.open("a") as f:
                f.write(lines)
        except OSError as exc:  # (a side record, as frames.csv: said once, the run goes on)
            if self.controller_path is not None:
                log.warning("cannot write %s (%s): the controller's states are not kept", self.controller_path, exc)
            self.controller_path = None
            return
        self.controller_lines += len(states)


class LinkEventsTail:
    """The link profiles applied since the last call (the run's link_events.jsonl), as live lines."""

    def __init__(self, run_dir: Path) -> None:
        self.run_dir = run_dir
        self.seen = 0

    def new_lines(self) -> list[str]:
        """A line per profile applied since the last call."""
        from shared.tools.linkemu import describe, read_events

        events = read_events(self.run_dir)
        fresh, self.seen = events[self.seen :], len(events)
        return [f"link profile -> {describe(e)}" for e in fresh]


def _record_link_events(run_dir: Path, events: list[dict[str, Any]], recording_id: str = "") -> None:
    """The link profiles into the run's recording (a part merged with the services'): `link/profile` (a
    text entry per change), `link/rate_mbit` and `link/floor_ms`, on the frames' capture_time timeline.
    Only when the run records (some service wrote a part)."""
    if not events or not any(p.name != "recording.rrd" for p in run_dir.glob("*.rrd")):
        return
    from shared.tools.linkemu import describe
    from shared.viz.recording import RerunSettings, RerunViz

    settings = RerunSettings(enabled=True, part_name="link", recording_id=recording_id)  # the services' recording
    viz = RerunViz(settings, service="link", run_dir=run_dir)
    try:
        for e in events:
            viz.text(e["unix_nanos"], "link/profile", describe(e))
            rate = float(e["rate_mbit"]) if e.get("rate_mbit") else float("nan")  # unshaped: a gap, not 0
            viz.scalars(e["unix_nanos"], {"link/floor_ms": float(e.get("delay_ms") or 0.0), "link/rate_mbit": rate})
    finally:
        viz.close()


def _recording_id(run_config: Path) -> str:
    """The run's Rerun recording id as its config sets it ("" = the run folder's name, the default)."""
    try:
        rerun = tomllib.loads(run_config.read_text()).get("common", {}).get("rerun", {})
    except (OSError, tomllib.TOMLDecodeError):
        return ""
    return str(rerun.get("recording_id", "")) if isinstance(rerun, dict) else ""


def incidents_summary(run_dir: Path, codes: dict[str, int | None], supervisor: Supervisor) -> dict[str, Any]:
    """summary.json's account of the processes: each one's exit code when the run stopped (the last
    process of each name), restarts per name and how many exits the run had, each in incidents.jsonl."""
    out: dict[str, Any] = {"exit_codes": codes, **supervisor.summary()}
    if supervisor.incidents:
        out["incidents"] = str(run_dir / "incidents.jsonl")
    return out


def logged_problems(run_dir: Path, *, examples: int = 3) -> dict[str, dict[str, Any]]:
    """Per process log of the run, how many WARNING and ERROR lines it holds and its first few distinct
    messages (stamps and logger names left out): what a run said only in a log, such as a data set's
    unreadable image, is in summary.json too (a trial found it only in camera.log)."""
    out: dict[str, dict[str, Any]] = {}
    for path in sorted(run_dir.glob("*.log")):
        counts: Counter[str] = Counter()
        first: list[str] = []
        try:
            with path.open(errors="replace") as f:  # line by line: a long run's log may be large
                for line in f:
                    found = _PROBLEM_LINE.match(line.rstrip("\n"))
                    if found is None:
                        continue
                    counts["errors" if found[1] != "WARNING" else "warnings"] += 1
                    message = found[2] if len(found[2]) <= 300 else found[2][:297] + "..."
                    if len(first) < examples and message not in first:
                        first.append(message)
        except OSError:
            continue
        if counts:
            out[path.stem] = {**counts, "first": first}
    return out


def _summarise_run(
    run_dir: Path,
    monitor: Monitor,
    codes: dict[str, int | None],
    frames_csv: FramesCsv,
    supervisor: Supervisor,
    *,
    stopped_by: str | None = None,
) -> dict[str, Any]:
    """summary.json: the monitor's figures, the services' exits and restarts, the link profiles applied,
    the merged recording and slam's ATE; frames.csv (written as the run went): the frames not yet written.
    `stopped_by`: why the launcher ended the run (a service refused its settings, the run did not come up)."""
    from shared.tools.linkemu import read_events

    summary = {**monitor.summary(), **incidents_summary(run_dir, codes, supervisor), "run_dir": str(run_dir)}
    if stopped_by is not None:
        summary["stopped_by"] = stopped_by
    inputs = input_counts_summary(run_dir)
    if inputs:  # every process's, restarted ones included (each service's stats key has only its own)
        summary["inputs"] = inputs
    logged = logged_problems(run_dir)
    if logged:
        summary["logged"] = logged
    events = read_events(run_dir)
    if events:
        summary["link_profiles"] = events
    frames_csv.flush(final=True)
    summary["frames_csv"] = str(frames_csv.path)
    summary["frames_csv_rows"] = frames_csv.rows
    if frames_csv.controller_lines:
        summary["controller_jsonl_lines"] = frames_csv.controller_lines
    if frames_csv.keeps_controller_states and monitor.controller_states_dropped:  # (5,000 behind: a stalled disk)
        summary["controller_jsonl_missed"] = monitor.controller_states_dropped
    if frames_csv.missed:
        summary["frames_csv_missed"] = frames_csv.missed
    settings_dir = run_dir / "settings"
    if settings_dir.is_dir():
        summary["settings"] = sorted(str(p) for p in settings_dir.glob("*.json"))
    _record_link_events(run_dir, events, _recording_id(run_dir / "config.toml"))
    recording = merge_recordings(run_dir)
    if recording is not None:
        summary["recording"] = str(recording)
    ate_path = run_dir / "ate.json"
    if ate_path.is_file():
        with contextlib.suppress(OSError, ValueError):  # slam killed mid-write: the rest of the summary stands
            summary["slam"] = json.loads(ate_path.read_text())
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary


def run_pipeline(
    config: Path,
    *,
    duration_secs: float | None,
    services: tuple[str, ...] = SERVICES,
    extra: dict[str, dict[str, Any]] | None = None,
    quiet: bool = False,
    runs_root: Path = Path("runs"),
    controller: bool = False,
    link: str | None = None,
    only: str | None = None,
) -> dict[str, Any]:
    """Start the services, print a live line per second until duration/SIGINT/camera end, stop all.

    `controller` adds the adaptive split controller. `link` (a profile name, root only) runs the robot
    side (camera, robot_infer, controller) and the edge side (edge_infer, slam) in the namespaces of
    an emulated uplink with that profile (switch it live with `splittag link set`), rewriting the
    endpoints: edge router on 0.0.0.0 at the config's edge port, robot router connecting over the shaped
    veth; the link's prefix and addresses from the config's [link] table.
    `only` ("edge" or "robot", PARTS): this host's part of a two-host deployment; the other host runs
    the other part with the same config. The robot's part watches the poses at the robot's router.
    """
    from shared.tools.linkemu import DEFAULT_PREFIX, profile

    if only is not None:
        if only not in PARTS:
            raise LaunchError(f"--only is one of {', '.join(PARTS)}, not {only!r}", exit_code=2)
        if link is not None:
            raise LaunchError("--only runs one host's part; --link emulates both hosts on this one", exit_code=2)
        if controller and only != "robot":
            raise LaunchError("the controller runs with the robot's part (--only robot --controller)", exit_code=2)
        services = tuple(s for s in services if s in PARTS[only])
    if controller and "controller" not in services:
        services = (*services, "controller")
    refuse_own_run_dir(config)
    topology, wrappers, emu = _placement(config, services, link)
    initial = profile(link) if link is not None else None  # refused before the run folder exists
    if emu is not None:
        emu.refuse_if_in_use()  # (up() checks again)
    with preparing_run_dir(runs_root) as run_dir:
        run_config = write_run_config(run_dir, config, topology=topology, extra=extra)
        robot_id, zs = monitor_settings(run_config, at_robot=only == "robot")
        run_tags = run_tag_map(run_config)
        if link is None:  # under --link the routers listen in namespaces of the run's own
            refuse_busy_endpoints([run_config], services)
    if emu is not None:
        emu.log_dir = run_dir
        emu.up(initial or profile("5g"))
        cli = Path(sys.executable).parent / "splittag"
        # (a secure deployment's operator shows its certificate: the monitor's folder holds the operator's)
        certs = f" --certs {Path(zs.tls.certificate).parent}" if zs.tls is not None else ""
        sudo = "" if os.geteuid() == 0 else "sudo "  # (a root shell may have no sudo at all: a trial)
        prefix = "" if emu.settings.prefix == DEFAULT_PREFIX else f" --prefix {emu.settings.prefix}"
        print(
            f"emulated link up: profile {link}; `{sudo}{cli} link set PROFILE{prefix}` switches it live; the edge's "
            f"router is {zs.connect[0]}: `{cli} split get --connect {zs.connect[0]}{certs}` (and set, release) "
            "steers the split",
            flush=True,
        )
    stop = threading.Event()
    from shared.tools.linkemu import read_events

    monitor = Monitor(  # a deployment may run for days
        run_tags, max_records=200_000, at_robot=only == "robot", run_started_nanos=time.time_ns()
    )
    frames_csv = FramesCsv(
        run_dir / "frames.csv",
        monitor,
        lambda: read_events(run_dir),
        controller_path=run_dir / "controller.jsonl" if "controller" in services else None,
    )
    running = _Services(run_config, run_dir, wrappers, only=only)
    comings = ComingsAndGoings(running.supervisor, partial(_service_of_token, robot_id, services))

    def attach(session: zenoh.Session) -> list[Any]:
        tokens = session.liveliness().declare_subscriber(f"{keys.ROOT}/{robot_id}/alive/*", comings.on_token)
        return [*attach_monitor(session, robot_id, monitor), tokens]

    started = Started()
    failure: LaunchError | None = None
    signals = SignalStop(stop)  # (restored in the finally below, however the run ends: review)
    try:
        (run_dir / "launcher.pid").write_text(f"{os.getpid()}\n")  # `splittag down` stops the run through it
        running.start_all(services)
        # Supervised while it comes up: a service that dies now is restarted (its token then appears);
        # one that refuses its settings ends the run (LaunchError), as does Ctrl-C.
        started = wait_for_run(
            zs,  # the edge router is a service's
            [keys.alive(robot_id, s) for s in services],
            attach=attach,
            supervise=running.supervise,
            stop=stop,
            timeout_secs=120,
            run_dir=run_dir,
        )
        if started.up:
            print(f"run {run_dir}: {', '.join(services)} alive; Ctrl-C stops", flush=True)
            link_lines = LinkEventsTail(run_dir)
            link_lines.seen = 1 if emu is not None else 0  # the initial profile was printed above
            comings.arm()
            run_for(
                stop,
                duration_secs,
                lines=lambda: [
                    *link_lines.new_lines(),
                    *comings.lines(),
                    *monitor.notices(),
                    monitor.line(running.supervisor.down(), running.supervisor.back(RESTART_WARMUP_SECS)),
                ],
                quiet=quiet,
                supervise=running.supervise,
                every_second=frames_csv.flush,
            )
        for sub in started.subscriptions:
            sub.undeclare()
    except LaunchError as exc:  # the run is finished all the same (a trial found one left half-written)
        failure = exc
    finally:
        if started.session is not None:
            started.session.close()
        codes = stop_services(running.started)
        if emu is not None:
            emu.down()
        signals.restore()
        forget_run_files(run_dir)
    if failure is None:
        return _summarise_run(run_dir, monitor, codes, frames_csv, running.supervisor)
    try:  # the run is finished all the same; the reason it stopped is what the user must see
        _summarise_run(run_dir, monitor, codes, frames_csv, running.supervisor, stopped_by=str(failure))
    except Exception:
        log.exception("could not finish the run's files in %s", run_dir)
    raise failure
