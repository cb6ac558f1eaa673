"""End-to-end frame-to-pose latency (p50/p99), throughput and each process's CPU use for every split k
on loopback.

Starts edge_infer, robot_infer and the demo camera (15 fps, 3-4 tags in view) as separate
processes, then for each k sets the split through the Zenoh query, waits for the change to take
effect, and measures capture->pose latency over a window.

    .venv/bin/python -m bench.pipeline [--fps 15] [--window-secs 10] [--tracking off|on|both]
        [--precision fp32|bf16|int8] [--pace on|off|both] [--aruco on|off|both]
        [--lines on|off|both] [--overlap on|off|both] [--fresh 0 0.33 ...]

`--tracking both` runs everything twice, robot_infer's track-then-refine off and then on, in one run;
`--aruco both` likewise with stage 1's ArUco proposer (shared.vision.proposals) off and on, `--lines both`
with its line-quad proposer (shared.vision.linequads), `--overlap both` with robot_infer's stage 1 of the
next frame running alongside the network (`overlap_stage1`); `--fresh` takes one or more values of
robot_infer's `fresh_frame_fraction` (0 = take the newest frame at once), a table each.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import psutil

from bench.machine import cpu_label
from services.robot_infer.settings import RobotInferSettings
from shared.model.precision import resolve_for_folder
from shared.runtime.cpus import allowed_cpus
from shared.tools.launch import Monitor, attach_monitor, demo_tag_map, loopback_config, start_service, stop_services
from shared.transport.session import ZenohSettings, open_session, wait_for_liveliness
from shared.transport.split_client import query_split
from shared.wire import keys
from shared.wire.cuts import CUTS, CutInfo

ROBOT = "bench"


def main() -> None:
    """Run and print the table."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--window-secs", type=float, default=10.0)
    ap.add_argument("--settle-secs", type=float, default=2.0)
    ap.add_argument("--ks", type=int, nargs="*", default=[c.k for c in CUTS])
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
    tables = [(mode, measure(args, mode)) for mode in runs]
    for mode, rows in tables:
        print_table(args, rows, mode)


@dataclass(frozen=True)
class Mode:
    """robot_infer's switches for one table."""

    tracking: bool
    pace: bool
    aruco: bool
    lines: bool
    overlap: bool = True
    fresh: float = 0.5


Row = tuple[CutInfo, float, float, float, float, float, float, float, float, float, float, dict[str, float]]
CPU_OF = ("robot_infer", "edge_infer", "camera", "bench")  # the processes whose CPU time a table shows


def _cpu_secs(procs: dict[str, psutil.Process]) -> dict[str, float]:
    """User + system CPU seconds each process has used so far (all its threads)."""
    return {name: sum(p.cpu_times()[:2]) for name, p in procs.items()}


def measure(args: argparse.Namespace, mode: Mode) -> list[Row]:
    """Start the services (robot_infer's tracking, pacing and stage-1 proposers on or off), sweep k, stop them."""
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
    }
    services = [start_service(n, cfg, tmp, env) for n in ("edge_infer", "robot_infer", "camera")]
    rows: list[Row] = []
    try:
        session = open_session(ZenohSettings(mode="client", connect=[topology.robot_router]))
        monitor = Monitor(demo_tag_map())
        subs = attach_monitor(session, ROBOT, monitor)
        wait_for_liveliness(
            session, [keys.alive(ROBOT, s) for s in ("edge_infer", "robot_infer", "camera")], timeout_secs=120
        )
        procs = {s.name: psutil.Process(s.popen.pid) for s in services} | {"bench": psutil.Process()}
        for cut in (CUTS[k] for k in args.ks):
            query_split(session, ROBOT, params=f"k={cut.k}")
            time.sleep(args.settle_secs)
            start = len(monitor.records)
            t0, cpu0 = time.monotonic(), _cpu_secs(procs)
            psutil.cpu_percent()  # the host's busy share from here on
            time.sleep(args.window_secs)
            recs = [r for r in monitor.records[start:] if r["k"] == cut.k]
            elapsed, cpu1 = time.monotonic() - t0, _cpu_secs(procs)
            cpu = {name: 100 * (cpu1[name] - cpu0[name]) / elapsed for name in procs}
            cpu["host"] = psutil.cpu_percent()  # every process on the machine, % of all its CPUs
            e2e = np.array([r["e2e_ms"] for r in recs])
            rows.append(
                (
                    cut,
                    len(recs) / elapsed,
                    np.percentile(e2e, 50),
                    np.percentile(e2e, 99),
                    np.median([r["robot_ms"] for r in recs]),
                    np.median([r["transport_ms"] for r in recs]),
                    np.median([r["edge_ms"] for r in recs]),
                    np.mean([r["tags"] for r in recs]),
                    np.median([r["payload_bytes"] for r in recs]),
                    float(np.nanmedian([r["before_robot_ms"] for r in recs])),
                    float(np.nanmedian([r["at_edge_ms"] for r in recs])),
                    cpu,
                )
            )
        for s in subs:
            s.undeclare()
        session.close()
    finally:
        stop_services(services)
    return rows


def print_table(args: argparse.Namespace, rows: list[Row], mode: Mode) -> None:
    """One table per mode. `path` = robot + link + edge medians (the critical path); `e2e/path` is what
    waiting adds; `fps x slowest` = throughput x the slower side's per-frame time (1.0 = that side never
    idles); `fps/cap` = throughput / min(camera rate, 1 / slower side's per-frame time): the share of
    the frames the pipeline could have turned into poses (1.0 = nothing lost to waiting). Where the
    waiting is: `age` = capture -> sent minus the robot's compute (how old the frame was when the robot
    took it, and any wait inside the robot), `edge q` = received -> pose minus the edge's compute
    (queueing at the edge); medians. `cpu %`: each process's CPU time over the window (all its threads;
    100 = one core; `bench` is this process, the monitor), `4 procs` = their sum / the CPUs this run may
    use, `host` = the whole machine's busy share (anything else running shows as host - 4 procs): near
    1.0 the services wait for a core, not for each other."""
    print(
        f"camera {args.fps} fps, window {args.window_secs} s per k, loopback, 2-core CPU, {args.precision}, rerun "
        f"{'on' if args.rerun else 'off'}, tracking {'on' if mode.tracking else 'off'}, "
        f"pacing {'on' if mode.pace else 'off'}, aruco {'on' if mode.aruco else 'off'}, "
        f"lines {'on' if mode.lines else 'off'}, overlap {'on' if mode.overlap else 'off'}, "
        f"fresh frame fraction {mode.fresh:.2f}; "
        "latencies in ms"
    )
    print(
        f"{'k':>2} {'cut':<10} {'fps':>6} {'e2e p50':>8} {'e2e p99':>8} {'robot':>7} {'link':>6} {'edge':>6} "
        f"{'path':>6} {'e2e/path':>9} {'age':>6} {'edge q':>7} {'fps x slowest':>14} {'fps/cap':>8} {'tags':>5} "
        f"{'msg kB':>8} {'cpu % ' + '/'.join(n.removesuffix('_infer') for n in CPU_OF):>31} {'4 procs':>7} "
        f"{'host':>5}"
    )
    cores = len(allowed_cpus())
    for cut, fps, p50, p99, rb, tr, ed, tags, size, age, edge_q, cpu in rows:
        path = rb + tr + ed
        cap = min(args.fps, 1e3 / max(rb, ed))
        print(
            f"{cut.k:>2} {cut.name:<10} {fps:>6.1f} {p50:>8.1f} {p99:>8.1f} {rb:>7.1f} {tr:>6.1f} {ed:>6.1f} "
            f"{path:>6.1f} {p50 / path:>9.2f} {age:>6.1f} {edge_q:>7.1f} {fps * max(rb, ed) / 1e3:>14.2f} "
            f"{fps / cap:>8.2f} {tags:>5.1f} {size / 1024:>8.1f} "
            f"{'/'.join(f'{cpu[n]:.0f}' for n in CPU_OF):>31} {sum(cpu[n] for n in CPU_OF) / (100 * cores):>7.2f} "
            f"{cpu['host'] / 100:>5.2f}"
        )


if __name__ == "__main__":
    main()
