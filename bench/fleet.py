"""The edge tier under a growing fleet: capture-to-pose latency (p50/p95) and poses per second against
the number of robots (1, 2, 4, 8 demo cameras at a fixed rate each), with 1 and 2 edge_infer workers,
in one run.

Every configuration is a real fleet on loopback (shared.tools.fleet: slam with the edge router, the
workers, and per robot its own router with robot_infer and a camera), Rerun off. The robots cut at
k = 0 by default (the edge runs the whole network: the load the edge tier is for); the robots'
processes share this machine's 2 cores with the edge, so the curve is that of one 2-core box, not of
a real fleet whose robots bring their own CPUs. A pose is an edge-computed TagPoses (on-board
fallbacks are counted apart); "offered" is robots x fps.

    .venv/bin/python -m bench.fleet [--robots 1 2 4 8] [--workers 1 2] [--fps 5] [--k 0] [--window-secs 10]
        [--json fleet.json] [--plot docs/fleet.png]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from bench.machine import cpu_label
from shared.runtime.guard import service_stats
from shared.tools.fleet import FleetPlan, demo_tables, fleet_configs
from shared.tools.launch import REPO, Monitor, attach_monitor, demo_tag_map, start_process, stop_services
from shared.tools.topology import merge
from shared.transport.session import ZenohSettings, open_session, wait_for_liveliness
from shared.wire import keys


@dataclass(frozen=True)
class Row:
    """One configuration's figures."""

    robots: int
    workers: int
    offered_fps: float
    poses_per_sec: float
    on_board_per_sec: float
    p50_ms: float
    p95_ms: float
    batched_share: float  # of the messages the workers handled in the run, the share that shared a tail pass


def measure(robots: int, workers: int, *, fps: float, k: int, window_secs: float, settle_secs: float) -> Row:
    """Start one fleet, let it settle, count the window's poses, stop it."""
    run = Path(tempfile.mkdtemp(prefix="splittag-fleet-"))
    plan = FleetPlan.loopback(robots, workers)
    extra = merge(
        demo_tables(run),
        {
            "common": {"rerun": {"enabled": False}},
            "camera": {"fps": fps, "loop": True},
            "robot_infer": {"split_k": k, "threads": 1},
            "edge_infer": {"threads": 1},
        },
    )
    specs = fleet_configs(plan, run, REPO / "deploy" / "fleet.toml", extra=extra)
    procs = []
    try:
        for n, spec in enumerate(specs):
            env = {"SPLITTAG_CAMERA_START_FRAME": str(17 * n % 150)} if spec.service == "camera" else None
            argv = ["-m", f"services.{spec.service}", "--config", str(spec.config)]
            procs.append(start_process(spec.name, argv, run, env=env))
        session = open_session(ZenohSettings(mode="client", connect=[plan.edge_router]))
        monitors = {r: Monitor(demo_tag_map()) for r in plan.robots}
        subs = [s for r, m in monitors.items() for s in attach_monitor(session, r, m)]
        wait_for_liveliness(
            session,
            [keys.alive(r, s) for r in plan.robots for s in ("robot_infer", "edge_infer", "camera")],
            timeout_secs=300,
        )
        time.sleep(settle_secs)
        marks = {r: len(m.records) for r, m in monitors.items()}
        t0 = time.monotonic()
        time.sleep(window_secs)
        elapsed = time.monotonic() - t0
        recs = [rec for r, m in monitors.items() for rec in m.records[marks[r] :]]
        edge = [rec for rec in recs if rec["payload_bytes"] > 0]
        e2e = np.array([rec["e2e_ms"] for rec in edge]) if edge else np.array([np.nan])
        per_worker: dict[str, tuple[int, int]] = {}
        for r in plan.robots:  # each robot's lane reports its worker's counters
            stats = service_stats(session, r, "edge_infer")
            per_worker[stats["worker"]] = (stats.get("accepted", 0), stats.get("batched_messages", 0))
        handled = sum(a for a, _ in per_worker.values())
        batched = sum(b for _, b in per_worker.values())
        for s in subs:
            s.undeclare()
        session.close()
    finally:
        stop_services(procs)
    return Row(
        robots=robots,
        workers=workers,
        offered_fps=robots * fps,
        poses_per_sec=len(edge) / elapsed,
        on_board_per_sec=(len(recs) - len(edge)) / elapsed,
        p50_ms=float(np.percentile(e2e, 50)),
        p95_ms=float(np.percentile(e2e, 95)),
        batched_share=min(1.0, batched / handled) if handled else 0.0,  # counted apart: a batch may be mid-way
    )


def main() -> None:
    """Run every configuration and print the table."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--robots", type=int, nargs="*", default=[1, 2, 4, 8])
    ap.add_argument("--workers", type=int, nargs="*", default=[1, 2])
    ap.add_argument("--fps", type=float, default=5.0, help="each robot's camera rate")
    ap.add_argument("--k", type=int, default=0, help="the robots' split (0: the edge runs the whole network)")
    ap.add_argument("--window-secs", type=float, default=10.0)
    ap.add_argument("--settle-secs", type=float, default=4.0)
    ap.add_argument("--json", type=Path, default=None, help="write the rows as JSON")
    ap.add_argument("--plot", type=Path, default=None, help="write the curves as a PNG")
    args = ap.parse_args()
    print(f"CPU: {cpu_label()}", flush=True)
    rows = []
    for workers in args.workers:
        for robots in args.robots:
            row = measure(
                robots, workers, fps=args.fps, k=args.k, window_secs=args.window_secs, settle_secs=args.settle_secs
            )
            print(f"  measured {robots} robots x {workers} workers: {row.poses_per_sec:.1f} poses/s", flush=True)
            rows.append(row)
    print(
        f"fleet on loopback, one 2-core machine for everything, k = {args.k}, {args.fps:g} fps per robot, "
        f"window {args.window_secs:g} s; latency = capture to pose, edge-computed poses only"
    )
    print(
        f"{'robots':>6} {'workers':>7} {'offered/s':>9} {'poses/s':>8} {'on board/s':>10} "
        f"{'p50 ms':>8} {'p95 ms':>8} {'batched':>8}"
    )
    for r in rows:
        print(
            f"{r.robots:>6} {r.workers:>7} {r.offered_fps:>9.1f} {r.poses_per_sec:>8.1f} {r.on_board_per_sec:>10.1f} "
            f"{r.p50_ms:>8.1f} {r.p95_ms:>8.1f} {r.batched_share:>8.0%}"
        )
    if args.json is not None:
        args.json.write_text(
            json.dumps(
                {
                    "cpu": cpu_label(),
                    "args": vars(args) | {"json": str(args.json), "plot": str(args.plot)},
                    "rows": [asdict(r) for r in rows],
                },
                indent=2,
            )
        )
    if args.plot is not None:
        plot(
            rows,
            args.plot,
            title=f"bench/fleet: k = {args.k}, {args.fps:g} fps per robot, all on one 2-core machine\n{cpu_label()}",
        )


def plot(rows: list[Row], path: Path, *, title: str) -> None:
    """Poses per second and p50/p95 latency against robots, a line per worker count."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 4))
    for workers in sorted({r.workers for r in rows}):
        mine = sorted((r for r in rows if r.workers == workers), key=lambda r: r.robots)
        n = [r.robots for r in mine]
        left.plot(n, [r.poses_per_sec for r in mine], "o-", label=f"{workers} worker(s)")
        right.plot(n, [r.p50_ms for r in mine], "o-", label=f"p50, {workers} worker(s)")
        right.plot(n, [r.p95_ms for r in mine], "o--", label=f"p95, {workers} worker(s)")
    offered = sorted({(r.robots, r.offered_fps) for r in rows})
    left.plot([o[0] for o in offered], [o[1] for o in offered], "k:", label="offered")
    left.set(xlabel="robots", ylabel="edge-computed poses / s", xscale="log", title="throughput")
    right.set(xlabel="robots", ylabel="capture to pose, ms", xscale="log", title="latency")
    for ax in (left, right):
        ticks = sorted({r.robots for r in rows})
        ax.set_xticks(ticks, labels=[str(t) for t in ticks])
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
