"""robot_infer's pacer on the emulated 5G uplink: the link as a queue (pace_to_link, the default) or as
a delay, side by side in one run, at pinned cuts (root; run by hand).

    sudo .venv/bin/python -m bench.link_pacing [--ks 0 3 4] [--profile 5g] [--window-secs 20]

Robot side (camera at --fps, robot_infer) and edge side (edge_infer) in two network namespaces joined by
the shaped veth (shared/tools/linkemu.py), as bench.controller. Where a cut's tensor takes longer to
cross the uplink than the robot takes to make the next one, a pacer that reads the uplink as a delay
takes the time a frame waited behind the one ahead for a slower link and keeps its whole in-flight
window queued there; the link as a queue starts each frame as the one ahead has crossed. Printed per
cut and mode: frames/s, e2e p50 / p99, and the medians of robot compute, link (send -> arrival, queue
included) and edge compute; `ideal` = robot + the link's own time (t0 + beta S at the profile's
nominal rate, no queue) + edge: what one frame alone would take.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from bench.controller import stream
from bench.machine import cpu_label
from shared.tools.linkemu import PROFILES, LinkEmulator, LinkEmulatorSettings, unavailable_reason


def summarise(
    records: list[dict[str, Any]], window_secs: float, beta_ms_per_kB: float, t0_ms: float
) -> dict[str, float]:
    """The figures of one run's frames."""
    robot = float(np.median([r["robot_ms"] for r in records]))
    edge = float(np.median([r["edge_ms"] for r in records]))
    kB = float(np.median([r["payload_bytes"] for r in records])) / 1024.0
    e2e = [r["e2e_ms"] for r in records]
    return {
        "frames": len(records),
        "fps": len(records) / window_secs,
        "e2e_p50_ms": float(np.median(e2e)),
        "e2e_p99_ms": float(np.percentile(e2e, 99)),
        "robot_ms": robot,
        "link_ms": float(np.median([r["transport_ms"] for r in records])),
        "edge_ms": edge,
        "payload_kB": kB,
        "ideal_ms": robot + t0_ms + beta_ms_per_kB * kB + edge,
    }


def main() -> int:
    """Both pacer modes at every cut asked for, one after the other, on one link."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ks", type=int, nargs="+", default=[0, 3, 4])
    ap.add_argument("--profile", default="5g", choices=sorted(PROFILES))
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--window-secs", type=float, default=20.0)
    args = ap.parse_args()
    print(f"CPU: {cpu_label()}", flush=True)
    reason = unavailable_reason()
    if reason is not None:
        raise SystemExit(reason)
    profile = PROFILES[args.profile]
    print(f"link {profile.name}: {profile.rate_mbit} Mbit/s, {profile.delay_ms} ms; camera {args.fps} fps", flush=True)
    header = (
        f"{'k':>2} {'pacer':<6} {'fps':>6} {'e2e p50':>8} {'e2e p99':>8} {'robot':>6} {'link':>7} {'edge':>6} "
        f"{'kB':>6} {'ideal':>6} {'p50/ideal':>9}"
    )
    print(header, flush=True)
    with tempfile.TemporaryDirectory() as tmp, LinkEmulator(LinkEmulatorSettings(prefix="stp")) as emu:
        emu.up(profile)
        for k in args.ks:
            for mode, pace_to_link in (("queue", True), ("delay", False)):
                run_dir = Path(tmp) / f"k{k}-{mode}"
                run_dir.mkdir()
                run = stream(
                    run_dir,
                    emu,
                    controller=False,
                    oracle_k=[k],
                    phase_secs=args.window_secs,
                    gamma=1.0,
                    fps=args.fps,
                    robot_extra={"pace_to_link": pace_to_link},
                    schedule=(profile.name,),
                )
                records = [r for r in run.frames() if r["k"] == k]
                f = summarise(records, args.window_secs, profile.beta_ms_per_kB, profile.delay_ms)
                print(
                    f"{k:>2} {mode:<6} {f['fps']:>6.2f} {f['e2e_p50_ms']:>8.1f} {f['e2e_p99_ms']:>8.1f} "
                    f"{f['robot_ms']:>6.1f} {f['link_ms']:>7.1f} {f['edge_ms']:>6.1f} {f['payload_kB']:>6.0f} "
                    f"{f['ideal_ms']:>6.1f} {f['e2e_p50_ms'] / f['ideal_ms']:>9.2f}",
                    flush=True,
                )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
