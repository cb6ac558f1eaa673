"""Soak: the whole pipeline for a long time on loopback, watching for leaks, latency drift and stalls.

Starts edge_infer, robot_infer, the demo camera, slam and the controller as separate processes (the
deployment's shape, Rerun off), then every `--sample-secs` records each service's RSS and, per
minute, the poses' capture-to-pose latency (p50, p99), stalls (no pose for `--stall-secs`) and
robot_infer's expired credits. At the end it prints the table and the verdicts the reliability
issue asks for: RSS growth per service under 10 % (last samples against the first samples after
`--warmup-minutes`), 0 credits expired without a fault, p99 stable (worst minute / median minute).

    .venv/bin/python -m bench.soak [--minutes 30] [--fps 15] [--json soak.json]
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import psutil

from bench.machine import cpu_label
from shared.runtime.guard import service_stats
from shared.tools.launch import Monitor, attach_monitor, demo_tag_map, loopback_config, start_service, stop_services
from shared.transport.session import ZenohSettings, open_session, wait_for_liveliness
from shared.wire import keys

ROBOT = "soak"
SERVICES = ("edge_infer", "robot_infer", "camera", "slam", "controller")


def minute_rows(records: list[dict[str, Any]], t0: float, minutes: int, stall_secs: float) -> list[dict[str, Any]]:
    """Per-minute poses, latency percentiles and stalls from the monitor's records (times in t)."""
    rows = []
    times = [r["t"] for r in records]
    for m in range(minutes):
        lo, hi = t0 + 60 * m, t0 + 60 * (m + 1)
        recs = [r for r in records if lo <= r["t"] < hi]
        e2e = np.array([r["e2e_ms"] for r in recs]) if recs else np.zeros(0)
        inside = [t for t in times if lo <= t < hi]
        edges = [lo, *inside, hi]
        stalls = sum(1 for a, b in itertools.pairwise(edges) if b - a > stall_secs)
        rows.append(
            {
                "minute": m + 1,
                "poses": len(recs),
                "e2e_p50_ms": float(np.percentile(e2e, 50)) if len(e2e) else None,
                "e2e_p99_ms": float(np.percentile(e2e, 99)) if len(e2e) else None,
                "stalls": stalls,
            }
        )
    return rows


def rss_growth_pct(samples: list[tuple[float, int]], t0: float, warmup_secs: float) -> float | None:
    """Mean RSS of the last three samples against the first three after the warm-up, in %."""
    after = [rss for t, rss in samples if t >= t0 + warmup_secs]
    if len(after) < 6:
        return None
    first, last = statistics.mean(after[:3]), statistics.mean(after[-3:])
    return 100.0 * (last - first) / first


def main() -> None:
    """Run the soak and print the table and verdicts."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=int, default=30)
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--split-k", type=int, default=5, help="the controller may move it")
    ap.add_argument("--sample-secs", type=float, default=10.0)
    ap.add_argument("--warmup-minutes", type=float, default=2.0)
    ap.add_argument("--stall-secs", type=float, default=1.5)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--rerun", action="store_true", help="record to Rerun as deploy/*.toml do (off: the services only)")
    ap.add_argument("--rerun-rotate-secs", type=float, help="a new .rrd part this often (default: the setting's)")
    args = ap.parse_args()
    print(f"CPU: {cpu_label()}", flush=True)
    tmp = Path(tempfile.mkdtemp(prefix="splittag-soak-"))
    cfg, topology = loopback_config(
        tmp,
        robot_id=ROBOT,
        fps=args.fps,
        split_k=args.split_k,
        rerun=args.rerun,
        rerun_rotate_secs=args.rerun_rotate_secs,
    )
    services = [start_service(n, cfg, tmp) for n in SERVICES]
    rss: dict[str, list[tuple[float, int]]] = {s.name: [] for s in services}
    try:
        session = open_session(ZenohSettings(mode="client", connect=[topology.edge_router]))
        monitor = Monitor(demo_tag_map())
        subs = attach_monitor(session, ROBOT, monitor)
        wait_for_liveliness(session, [keys.alive(ROBOT, s) for s in SERVICES], timeout_secs=180)
        procs = {s.name: psutil.Process(s.popen.pid) for s in services}
        t0 = time.monotonic()
        end = t0 + 60 * args.minutes
        next_print = t0 + 60
        while time.monotonic() < end:
            now = time.monotonic()
            for name, proc in procs.items():
                rss[name].append((now, proc.memory_info().rss))
            dead = [s.name for s in services if s.popen.poll() is not None]
            if dead:
                raise RuntimeError(f"services died during the soak: {dead}")
            if now >= next_print:
                next_print += 60
                minute = minute_rows(monitor.records, t0, int((now - t0) // 60), args.stall_secs)[-1]
                print(f"minute {minute['minute']}: {json.dumps(minute)}", flush=True)
            time.sleep(min(args.sample_secs, max(0.0, end - time.monotonic())))
        stats = {name: service_stats(session, ROBOT, name) for name in SERVICES if name != "camera"}  # no inputs
        for sub in subs:
            sub.undeclare()
        session.close()
    finally:
        codes = stop_services(services)
    rows = minute_rows(monitor.records, t0, args.minutes, args.stall_secs)
    growth = {name: rss_growth_pct(samples, t0, 60 * args.warmup_minutes) for name, samples in rss.items()}
    p99 = [r["e2e_p99_ms"] for r in rows if r["e2e_p99_ms"] is not None]
    p99_ratio = max(p99) / statistics.median(p99) if p99 else None
    robot = stats["robot_infer"]
    print(f"\n{args.minutes} min soak, camera {args.fps} fps demo, loopback, start k={args.split_k}, controller on")
    print(f"{'min':>4} {'poses':>6} {'p50 ms':>7} {'p99 ms':>7} {'stalls':>6}")
    for r in rows:
        p50 = "-" if r["e2e_p50_ms"] is None else f"{r['e2e_p50_ms']:.0f}"
        p99s = "-" if r["e2e_p99_ms"] is None else f"{r['e2e_p99_ms']:.0f}"
        print(f"{r['minute']:>4} {r['poses']:>6} {p50:>7} {p99s:>7} {r['stalls']:>6}")
    print(
        "RSS MB first -> last (growth): "
        + ", ".join(
            f"{n} {rss[n][0][1] / 2**20:.0f} -> {rss[n][-1][1] / 2**20:.0f} ({'-' if g is None else f'{g:+.1f} %'})"
            for n, g in growth.items()
        )
    )
    recorded = {p.name: p.stat().st_size for p in sorted(tmp.glob("*.rrd"))}
    if recorded:  # (--rerun) each process's parts, before any merge: what a shift's run folder holds
        print(
            f"Rerun parts: {len(recorded)} files, {sum(recorded.values()) / 1e6:.1f} MB, "
            f"{sum(recorded.values()) / 1e6 * 60 / args.minutes:.0f} MB/h"
        )
    stalls = sum(r["stalls"] for r in rows)
    print(
        f"verdicts: RSS growth < 10 %: {all(g is not None and g < 10 for g in growth.values())}; "
        f"credits expired {robot['credits_expired']} (want 0); stalls {stalls}; "
        f"p99 worst/median minute {p99_ratio:.2f}; exits {codes}"
        if p99_ratio is not None
        else "no poses"
    )
    if args.json is not None:
        doc = {
            "cpu": cpu_label(),
            "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
            "minutes": rows,
            "rss_growth_pct": growth,
            "rss_samples": {n: [[t - t0, b] for t, b in s] for n, s in rss.items()},
            "stats": stats,
            "p99_worst_over_median": p99_ratio,
            "exit_codes": codes,
            "rerun_part_bytes": recorded,
        }
        args.json.write_text(json.dumps(doc, indent=1))
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
