"""End-to-end frame-to-pose latency (p50/p99), throughput and each process's CPU use for every split k
on loopback.

Starts edge_infer, robot_infer and the demo camera (15 fps, 3-4 tags in view) as separate
processes, then for each k sets the split through the Zenoh query, waits for the change to take
effect, and measures capture->pose latency over a window.

    .venv/bin/python -m bench.pipeline [--fps 15] [--window-secs 10] [--ks 0 5 7]
        [--auto [--auto-from 0] [--auto-settle-secs 8]]
        [--tracking off|on|both]
        [--precision fp32|bf16|int8] [--pace on|off|both] [--aruco on|off|both]
        [--lines on|off|both] [--overlap on|off|both] [--fresh 0 0.33 ...]

`--tracking both` runs everything twice, robot_infer's track-then-refine off and then on, in one run;
`--aruco both` likewise with stage 1's ArUco proposer (shared.vision.proposals) off and on, `--lines both`
with its line-quad proposer (shared.vision.linequads), `--overlap both` with robot_infer's stage 1 of the
next frame running alongside the network (`overlap_stage1`); `--fresh` takes one or more values of
robot_infer's `fresh_frame_fraction` (0 = take the newest frame at once), a table each.
`--auto` adds a row where the adaptive split controller chooses k: after the fixed cuts (each a
person's pinned setting) it sets k = `--auto-from` (0), starts the controller (services/controller; a
fresh one, so the pinned rows neither feed its estimates nor carry its probes), releases the pin, waits
`--auto-settle-secs` and measures a row `auto`. Its `k` column is the cut most of its frames took, `k
share` says how many did and `switch` how often the split changed in the window; its figures are those
frames' (fps over the share of the window's time spent at that cut). A line after the table gives the
frames per cut, the controller's last predicted T(k), its current and chosen k and its reason, and says
when the row is not the controller's choice (no prediction, still pinned, exited, or the window ended at
another cut).
"""

from __future__ import annotations

import argparse
import itertools
import tempfile
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import psutil
import zenoh

from bench.machine import cpu_label
from services.robot_infer.settings import RobotInferSettings
from shared.model.precision import resolve_for_folder
from shared.runtime.cpus import allowed_cpus
from shared.tools.launch import (
    Monitor,
    Service,
    attach_monitor,
    demo_tag_map,
    loopback_config,
    start_service,
    stop_services,
)
from shared.transport.session import ZenohSettings, open_session, wait_for_liveliness
from shared.transport.split_client import query_split
from shared.wire import keys
from shared.wire.cuts import CUTS
from shared.wire.messages import ControllerState

ROBOT = "bench"


def main() -> None:
    """Run and print the table."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--window-secs", type=float, default=10.0)
    ap.add_argument("--settle-secs", type=float, default=2.0)
    ap.add_argument("--ks", type=int, nargs="*", choices=[c.k for c in CUTS], default=[c.k for c in CUTS])
    ap.add_argument("--auto", action="store_true", help="add a row where the adaptive split controller chooses k")
    ap.add_argument(
        "--auto-settle-secs", type=float, default=8.0, help="after releasing the pin, before the auto row's window"
    )
    ap.add_argument(
        "--auto-from",
        type=int,
        choices=[c.k for c in CUTS],
        default=0,
        help="the cut the auto row starts from (pinned, then released)",
    )
    ap.add_argument("--rerun", action="store_true", help="log everything to Rerun (to measure its cost)")
    ap.add_argument("--rerun-image-every", type=int, default=1)
    ap.add_argument("--tracking", choices=("off", "on", "both"), default="off")
    ap.add_argument(
        "--precision", choices=("auto", "fp32", "bf16", "int8"), default="auto", help="robot and edge network"
    )
    ap.add_argument("--pace", choices=("on", "off", "both"), default="on", help="robot_infer's edge pacer")
    ap.add_argument("--aruco", choices=("on", "off", "both"), default="on", help="stage 1's ArUco proposer")
    ap.add_argument("--lines", choices=("on", "off", "both"), default="on", help="stage 1's line-quad proposer")
    ap.add_argument(
        "--overlap", choices=("on", "off", "both"), default="on", help="robot_infer's stage 1 ahead of the network"
    )
    ap.add_argument(
        "--fresh",
        type=float,
        nargs="+",
        default=[RobotInferSettings.model_fields["fresh_frame_fraction"].default],
        help="robot_infer's fresh_frame_fraction (one table per value; default: the service's)",
    )
    args = ap.parse_args()
    for name in ("window_secs", "settle_secs", "auto_settle_secs"):
        if getattr(args, name) < 0 or (name == "window_secs" and args.window_secs == 0):
            ap.error(f"--{name.replace('_', '-')} must be {'positive' if name == 'window_secs' else '0 or more'}")
    args.precision = resolve_for_folder(args.precision, Path("models"))  # what auto stands for here
    print(f"CPU: {cpu_label()}", flush=True)
    modes = {"off": [False], "on": [True], "both": [False, True]}
    runs = [
        Mode(tracking, pace, aruco, lines, overlap, fresh)
        for tracking in modes[args.tracking]
        for pace in modes[args.pace]
        for aruco in modes[args.aruco]
        for lines in modes[args.lines]
        for overlap in modes[args.overlap]
        for fresh in args.fresh
    ]
    tables = []
    for mode in runs:
        notes: list[str] = []
        tables.append((mode, measure(args, mode, notes), notes))
    for mode, rows, notes in tables:
        print_table(args, rows, mode)
        for note in notes:
            print(note)


@dataclass(frozen=True)
class Mode:
    """robot_infer's switches for one table."""

    tracking: bool
    pace: bool
    aruco: bool
    lines: bool
    overlap: bool = True
    fresh: float = 0.5


@dataclass(frozen=True)
class Row:
    """One window's figures: medians unless named otherwise, latencies in ms."""

    label: str  # the cut's k, or AUTO
    k: int  # the cut (for AUTO: the one most of the window's frames took)
    k_share: float  # the share of the window's frames at k (below 1.0 for a fixed cut: its pin took late)
    switches: int  # split changes seen in the window's frames
    fps: float
    e2e_p50: float
    e2e_p99: float
    robot: float
    link: float
    edge: float
    tags: float  # mean
    payload_bytes: float
    age: float
    edge_q: float
    edge_busy: float  # share of the frames' span the edge spent computing them (NaN: none split)
    cpu: dict[str, float]  # % of one core per process, and "host"


AUTO = "auto"  # the row's label when the controller chose k
CPU_OF = ("robot_infer", "edge_infer", "camera", "bench")  # the processes whose CPU time a table shows


def _cpu_secs(procs: dict[str, psutil.Process]) -> dict[str, float]:
    """User + system CPU seconds each process has used so far (all its threads)."""
    return {name: sum(p.cpu_times()[:2]) for name, p in procs.items()}


def _row(label: str, recs: list[dict[str, Any]], elapsed: float, cpu: dict[str, float]) -> Row:
    """The figures of one window's frames at the cut most of them took (a window where the controller
    switched would otherwise mix two cuts' compute times into one critical path). Their throughput is
    their count over the share of the window's time spent at that cut (from the capture stamps: the gap
    after each frame counts for that frame's cut); the CPU columns stay the whole window's."""
    if not recs:
        raise SystemExit(
            f"no frame was posed in the {label} window: the pipeline stalled, or the split never took the cut"
        )
    recs = sorted(recs, key=lambda r: int(r["capture_nanos"]))
    ks = [int(r["k"]) for r in recs]
    k, n_at_k = Counter(ks).most_common(1)[0]
    gaps = np.diff([int(r["capture_nanos"]) for r in recs]).astype(float)
    total = float(gaps.sum())
    time_share = float(gaps[np.array(ks[:-1]) == k].sum()) / total if total > 0 else n_at_k / len(ks)
    switches = sum(a != b for a, b in itertools.pairwise(ks))
    at_k = [r for r in recs if r["k"] == k]
    e2e = np.array([r["e2e_ms"] for r in at_k])
    return Row(
        label=label,
        k=k,
        k_share=n_at_k / len(ks),
        switches=switches,
        fps=n_at_k / (elapsed * time_share) if time_share > 0 else len(recs) / elapsed,
        e2e_p50=float(np.percentile(e2e, 50)),
        e2e_p99=float(np.percentile(e2e, 99)),
        robot=float(np.median([r["robot_ms"] for r in at_k])),
        link=float(np.median([r["transport_ms"] for r in at_k])),
        edge=float(np.median([r["edge_ms"] for r in at_k])),
        tags=float(np.mean([r["tags"] for r in at_k])),
        payload_bytes=float(np.median([r["payload_bytes"] for r in at_k])),
        age=float(np.nanmedian([r["before_robot_ms"] for r in at_k])),
        edge_q=float(np.nanmedian([r["at_edge_ms"] for r in at_k])),
        edge_busy=busy_share(
            [
                (r["edge_done_nanos"] - 1e6 * r["edge_ms"], r["edge_done_nanos"])
                for r in recs
                if r["sent_nanos"] is not None
            ]
        ),
        cpu=cpu,
    )


def busy_share(intervals: list[tuple[float, float]]) -> float:
    """The share of the span from the first interval's start to the last one's end that the union of
    the (start, end) intervals covers: how much of the time a server was busy (NaN for no interval)."""
    if not intervals:
        return float("nan")
    intervals = sorted(intervals)
    covered, end = 0.0, intervals[0][0]
    for lo, hi in intervals:
        lo = max(lo, end)
        if hi > lo:
            covered += hi - lo
            end = hi
    span = max(hi for _, hi in intervals) - intervals[0][0]
    return covered / span if span > 0 else float("nan")


def _controller_note(
    state: ControllerState | None, controller: Service, recs: list[dict[str, Any]], row: Row, auto_from: int
) -> str:
    """What the controller believed at the end of the auto row's window (`recs`, summed up in `row`), and
    whether the row is its choice."""
    counts = ", ".join(f"k = {k}: {n}" for k, n in sorted(Counter(int(r["k"]) for r in recs).items()))
    head = f"controller (auto row, from k = {auto_from}; frames in the window {counts or 'none'}): "
    if controller.popen.poll() is not None:
        return head + f"EXITED with code {controller.popen.returncode}: the row is not the controller's choice"
    if state is None:
        return head + "no ControllerState arrived: the row is not the controller's choice"
    if not state.has_prediction:
        return head + f"no prediction yet ({state.reason}): the row is not the controller's choice"
    age_s = (time.time_ns() - state.stamp_nanos) / 1e9
    predicted = " ".join(f"{k}:{t:.0f}" for k, t in enumerate(state.predicted_ms_by_k))
    flags = []
    if state.pinned:
        flags.append("the split is PINNED: the row is not the controller's choice")
    if age_s > 2.0:
        flags.append(f"its last state is {age_s:.1f} s old")
    if row.k != state.current_k:
        flags.append(f"the split ended the window at k = {state.current_k}, not the row's k = {row.k}")
    throughput = ""
    if state.period_ms_by_k is not None:
        throughput = "; period ms by k " + " ".join(f"{k}:{t:.0f}" for k, t in enumerate(state.period_ms_by_k))
    if state.achieved_ms_by_k is not None:
        ran = [f"{k}:{t:.0f}" for k, t in enumerate(state.achieved_ms_by_k) if t is not None]
        throughput += f"; achieved ms between frames {' '.join(ran) or 'none'}"
    if state.frame_share_by_k is not None and state.min_frame_share is not None:
        shares = " ".join(f"{k}:{v:.2f}" for k, v in enumerate(state.frame_share_by_k))
        throughput += f"; frame share {shares} (keeps up: >= {state.min_frame_share:.2f})"
    return (
        head
        + f"predicted ms by k {predicted}{throughput}; at k = {state.current_k}, chose k = {state.chosen_k} "
        + f"({state.reason})"
        + ("; " + "; ".join(flags) if flags else "")
    )


def _against_pinned(auto: Row, pinned: list[Row]) -> str:
    """The auto row against the best pinned rows of the same run, in the user's terms: frames a second
    and median latency ('' without pinned rows). The pipeline goals are ratios to each row's own
    critical path; this says whether the controller's cut was as good as the best fixed one."""
    if not pinned:
        return ""
    most = max(pinned, key=lambda r: r.fps)
    fastest = min(pinned, key=lambda r: r.e2e_p50)
    return (
        f"auto against the pinned rows: {auto.fps:.1f} fps = {auto.fps / most.fps:.2f} of the most (k = {most.k}, "
        f"{most.fps:.1f}); e2e p50 {auto.e2e_p50:.1f} ms = {auto.e2e_p50 / fastest.e2e_p50:.2f} of the least "
        f"(k = {fastest.k}, {fastest.e2e_p50:.1f} ms)"
    )


def _model_against_pinned(state: ControllerState | None, pinned: list[Row]) -> str:
    """The controller's predicted T(k) at the end of the auto row against each pinned row's measured
    critical path (robot + link + edge medians) in the same run: how well its model of the cuts held
    ('' without a prediction or pinned rows). The pinned rows ran earlier, under the same load."""
    if state is None or not state.has_prediction or not pinned:
        return ""
    paths = {r.k: r.robot + r.link + r.edge for r in pinned}
    cells = [
        f"k = {k} {state.predicted_ms_by_k[k]:.0f} / {path:.0f} ms = {state.predicted_ms_by_k[k] / path:.2f}"
        for k, path in sorted(paths.items())
        if path > 0
    ]
    return "controller's T(k) against the pinned rows' path (predicted / measured): " + ", ".join(cells)


def measure(args: argparse.Namespace, mode: Mode, notes: list[str]) -> list[Row]:
    """Start the services (robot_infer's tracking, pacing and stage-1 proposers on or off), sweep k, then
    (`--auto`) start the controller, pin k = --auto-from, release the pin and let the controller choose;
    stop them. `notes` gets what the controller last predicted and chose (`--auto`)."""
    tmp = Path(tempfile.mkdtemp(prefix="splittag-bench-"))
    cfg, topology = loopback_config(
        tmp, robot_id=ROBOT, rerun=args.rerun, image_every=args.rerun_image_every, fps=args.fps
    )
    env = {
        "SPLITTAG_ROBOT_INFER_TRACKING__ENABLED": "true" if mode.tracking else "false",
        "SPLITTAG_ROBOT_INFER_PACE_TO_EDGE": "true" if mode.pace else "false",
        "SPLITTAG_ROBOT_INFER_STAGE1__ARUCO__ENABLED": "true" if mode.aruco else "false",
        "SPLITTAG_ROBOT_INFER_STAGE1__LINES__ENABLED": "true" if mode.lines else "false",
        "SPLITTAG_ROBOT_INFER_OVERLAP_STAGE1": "true" if mode.overlap else "false",
        "SPLITTAG_ROBOT_INFER_FRESH_FRAME_FRACTION": str(mode.fresh),
        "SPLITTAG_ROBOT_INFER_PRECISION": args.precision,
        "SPLITTAG_EDGE_INFER_PRECISION": args.precision,
        "SPLITTAG_CONTROLLER_ENABLED": "true",  # (not an observer inherited from the caller's environment)
    }
    services: list[Service] = []
    rows: list[Row] = []
    session: zenoh.Session | None = None
    try:
        for name in ("edge_infer", "robot_infer", "camera"):
            services.append(start_service(name, cfg, tmp, env))
        session = open_session(ZenohSettings(mode="client", connect=[topology.robot_router]))
        monitor = Monitor(demo_tag_map())
        attach_monitor(session, ROBOT, monitor)
        wait_for_liveliness(
            session, [keys.alive(ROBOT, s) for s in ("edge_infer", "robot_infer", "camera")], timeout_secs=120
        )
        procs = {s.name: psutil.Process(s.popen.pid) for s in services} | {"bench": psutil.Process()}

        def window(label: str) -> tuple[Row, list[dict[str, Any]]]:
            """Every frame posed in the window (a fixed row whose pin did not take shows it in `k share`)."""
            start = len(monitor.records)
            t0, cpu0 = time.monotonic(), _cpu_secs(procs)
            psutil.cpu_percent()  # the host's busy share from here on
            time.sleep(args.window_secs)
            recs = monitor.records[start:]
            elapsed, cpu1 = time.monotonic() - t0, _cpu_secs(procs)
            cpu = {name: 100 * (cpu1[name] - cpu0[name]) / elapsed for name in procs}
            cpu["host"] = psutil.cpu_percent()  # every process on the machine, % of all its CPUs
            return _row(label, recs, elapsed, cpu), recs

        for cut in (CUTS[k] for k in args.ks):
            query_split(session, ROBOT, params=f"k={cut.k}")  # a person's setting: pinned
            time.sleep(args.settle_secs)
            rows.append(window(str(cut.k))[0])
        if args.auto:
            # A controller started now (no memory of the pinned rows, none of its probes during them), from
            # a given cut rather than whichever fixed one ran last, so the row shows it choosing.
            query_split(session, ROBOT, params=f"k={args.auto_from}")
            controller = start_service("controller", cfg, tmp, env)
            services.append(controller)
            wait_for_liveliness(session, [keys.alive(ROBOT, "controller")], timeout_secs=120)
            procs["controller"] = psutil.Process(controller.popen.pid)
            time.sleep(args.settle_secs)
            query_split(session, ROBOT, params="release=1")  # the controller's from here on
            time.sleep(args.auto_settle_secs)
            row, recs = window(AUTO)
            rows.append(row)
            notes.append(
                _controller_note(monitor.controller, controller, recs, row, args.auto_from)
                + f"; its CPU {row.cpu['controller']:.0f} % of a core"
            )
            if against := _against_pinned(row, rows[:-1]):
                notes.append(against)
            if model := _model_against_pinned(monitor.controller, rows[:-1]):
                notes.append(model)
    finally:
        if session is not None:
            session.close()
        stop_services(services)
    return rows


def print_table(args: argparse.Namespace, rows: list[Row], mode: Mode) -> None:
    """One table per mode. `path` = robot + link + edge medians (the critical path); `e2e/path` is what
    waiting adds; `fps x slowest` = throughput x the slower side's per-frame time (1.0 = that side never
    idles); `fps/cap` = throughput / min(camera rate, 1 / slower side's per-frame time): the share of
    the frames the pipeline could have turned into poses (1.0 = nothing lost to waiting). Where the
    waiting is: `age` = capture -> sent minus the robot's compute (how old the frame was when the robot
    took it, and any wait inside the robot), `edge q` = received -> pose minus the edge's compute
    (queueing at the edge); medians. `edge busy` = the share of the time from the window's first split
    frame's edge compute to its last one's end that the edge spent computing frames (any cut's; the
    row's other columns are its main cut's): below 1.0 on an edge-bound cut the edge was not computing,
    mostly waiting for frames (the robot's or the pacer's doing), partly its own decoding, checks and
    publishing, which its compute time leaves out. `cpu %`: each process's CPU time
    over the window (all its threads; 100 = one core; `bench` is this process, the monitor), `4 procs` =
    their sum / the CPUs this run may use, `host` = the whole machine's busy share (anything else running
    shows as host - 4 procs): near 1.0 the services wait for a core, not for each other. The `auto` row
    (`--auto`): the controller chose k; `k share` = the window's frames at the `k` shown, `switch` = split
    changes among all the window's frames; its latencies, compute times and fps are the frames' at that k
    (see _row)."""
    print(
        f"camera {args.fps} fps, window {args.window_secs} s per k, loopback, 2-core CPU, {args.precision}, rerun "
        f"{'on' if args.rerun else 'off'}, tracking {'on' if mode.tracking else 'off'}, "
        f"pacing {'on' if mode.pace else 'off'}, aruco {'on' if mode.aruco else 'off'}, "
        f"lines {'on' if mode.lines else 'off'}, overlap {'on' if mode.overlap else 'off'}, "
        f"fresh frame fraction {mode.fresh:.2f}; "
        "latencies in ms"
    )
    print(
        f"{'row':>4} {'k':>2} {'cut':<10} {'k share':>7} {'switch':>6} {'fps':>6} {'e2e p50':>8} {'e2e p99':>8} "
        f"{'robot':>7} {'link':>6} {'edge':>6} "
        f"{'path':>6} {'e2e/path':>9} {'age':>6} {'edge q':>7} {'edge busy':>9} {'fps x slowest':>14} "
        f"{'fps/cap':>8} {'tags':>5} "
        f"{'msg kB':>8} {'cpu % ' + '/'.join(n.removesuffix('_infer') for n in CPU_OF):>31} {'4 procs':>7} "
        f"{'host':>5}"
    )
    cores = len(allowed_cpus())
    for r in rows:
        path = r.robot + r.link + r.edge
        slower = max(r.robot, r.edge)
        cap = min(args.fps, 1e3 / slower)
        print(
            f"{r.label:>4} {r.k:>2} {CUTS[r.k].name:<10} {r.k_share:>7.2f} {r.switches:>6d} {r.fps:>6.1f} "
            f"{r.e2e_p50:>8.1f} {r.e2e_p99:>8.1f} {r.robot:>7.1f} {r.link:>6.1f} {r.edge:>6.1f} "
            f"{path:>6.1f} {r.e2e_p50 / path:>9.2f} {r.age:>6.1f} {r.edge_q:>7.1f} {r.edge_busy:>9.2f} "
            f"{r.fps * slower / 1e3:>14.2f} "
            f"{r.fps / cap:>8.2f} {r.tags:>5.1f} {r.payload_bytes / 1024:>8.1f} "
            f"{'/'.join(f'{r.cpu[n]:.0f}' for n in CPU_OF):>31} "
            f"{sum(r.cpu[n] for n in CPU_OF) / (100 * cores):>7.2f} {r.cpu['host'] / 100:>5.2f}"
        )


if __name__ == "__main__":
    main()
