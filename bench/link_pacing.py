"""robot_infer's pacer on the emulated 5G uplink, side by side in one run at pinned cuts (root; run by
hand): `queue`, the defaults (the link as a queue, pace_to_link; the in-flight window sized by the
chain, up to in_flight_limit); `fixed2`, the same in a fixed window of 2; `delay`, session 23's pacer
(the link as a delay, a window of 2).

    sudo .venv/bin/python -m bench.link_pacing [--ks 4 3] [--profile 5g-pre-tdd] [--repetitions 2]
        [--modes queue fixed2 delay]

Robot side (camera at --fps, robot_infer) and edge side (edge_infer) in two network namespaces joined by
the shaped veth (shared/tools/linkemu.py), as bench.controller. Where a cut's tensor takes longer to
cross the uplink than the robot takes to make the next one, a pacer that reads the uplink as a delay
takes the time a frame waited behind the one ahead for a slower link and keeps its whole in-flight
window queued there; the link as a queue starts each frame as the one ahead has crossed. The two
modes alternate (which goes first changes every repetition). Printed per run: frames/s and kB/s over
the frames' capture span, `use` = kB/s over the link's nominal rate, e2e p50 / p90, the medians of
robot compute, link (send -> arrival, queue included), edge compute and payload (the demo scene's tag
count varies, and with it the payload at cuts 0-6); `ideal` = robot + the profile's t0 + beta S + edge
of those medians, one frame's time on a free link (without the frame's age at pickup or the protocol's
overhead); `e2e/ideal` = the median over the frames of each one's e2e over its own ideal.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from bench.controller import stream
from bench.machine import cpu_label
from shared.tools.linkemu import PROFILES, LinkEmulator, LinkEmulatorSettings, LinkProfile, unavailable_reason

# robot_infer's settings per mode: the defaults (the link as a queue, the window sized by the chain),
# the link as a queue in a fixed window of 2, and session 23's pacer (the link as a delay, window 2).
MODES: dict[str, dict[str, Any]] = {
    "queue": {},
    "fixed2": {"in_flight_limit": 2},
    "delay": {"pace_to_link": False, "in_flight_limit": 2},
}


def summarise(records: list[dict[str, Any]], profile: LinkProfile) -> dict[str, float] | None:
    """The figures of one run's frames (None without any). fps and kB/s over the span of their
    capture stamps; `use` = kB/s over the link's nominal rate."""
    if len(records) < 2:
        return None
    span = (max(r["capture_nanos"] for r in records) - min(r["capture_nanos"] for r in records)) / 1e9
    robot = float(np.median([r["robot_ms"] for r in records]))
    edge = float(np.median([r["edge_ms"] for r in records]))
    kB = float(np.median([r["payload_bytes"] for r in records])) / 1024.0
    kB_per_s = sum(r["payload_bytes"] for r in records[1:]) / 1024.0 / span
    e2e = [r["e2e_ms"] for r in records]
    assert profile.rate_mbit is not None
    return {
        "frames": len(records),
        "fps": (len(records) - 1) / span,
        "e2e_p50_ms": float(np.median(e2e)),
        "e2e_p90_ms": float(np.percentile(e2e, 90)),
        "robot_ms": robot,
        "link_ms": float(np.median([r["transport_ms"] for r in records])),
        "edge_ms": edge,
        "payload_kB": kB,
        "kB_per_s": kB_per_s,
        "use": kB_per_s * 1024 * 8 / (profile.rate_mbit * 1e6),
        "ideal_ms": robot + profile.delay_ms + profile.beta_ms_per_kB * kB + edge,
        # frame by frame: the demo's tag count, and with it the payload, varies within a run
        "ratio": float(
            np.median(
                [
                    r["e2e_ms"]
                    / (
                        r["robot_ms"]
                        + profile.delay_ms
                        + profile.beta_ms_per_kB * r["payload_bytes"] / 1024
                        + r["edge_ms"]
                    )
                    for r in records
                ]
            )
        ),
    }


def main() -> int:
    """Both pacer modes at every cut asked for, alternating, `--repetitions` times, on one link."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ks", type=int, nargs="+", default=[4, 3])
    ap.add_argument("--profile", default="5g-pre-tdd", choices=sorted(PROFILES))
    ap.add_argument("--fps", type=float, default=15.0)
    ap.add_argument("--window-secs", type=float, default=20.0)
    ap.add_argument("--repetitions", type=int, default=2)
    ap.add_argument("--modes", nargs="+", choices=sorted(MODES), default=["queue", "delay"])
    args = ap.parse_args()
    print(f"CPU: {cpu_label()}", flush=True)
    reason = unavailable_reason()
    if reason is not None:
        raise SystemExit(reason)
    profile = PROFILES[args.profile]
    print(f"link {profile.name}: {profile.rate_mbit} Mbit/s, {profile.delay_ms} ms; camera {args.fps} fps", flush=True)
    header = (
        f"{'k':>2} {'rep':>3} {'mode':<6} {'fps':>5} {'e2e p50':>8} {'e2e p90':>8} {'robot':>6} {'link':>7} "
        f"{'edge':>6} {'kB':>5} {'kB/s':>6} {'use':>5} {'ideal':>6} {'e2e/ideal':>9}"
    )
    print(header, flush=True)
    ratios: dict[tuple[int, str], list[float]] = {}
    with tempfile.TemporaryDirectory() as tmp, LinkEmulator(LinkEmulatorSettings(prefix="stp")) as emu:
        emu.up(profile)
        for k in args.ks:
            for rep in range(args.repetitions):
                modes = list(args.modes)
                for mode in modes if rep % 2 == 0 else modes[::-1]:
                    run_dir = Path(tmp) / f"k{k}-{rep}-{mode}"
                    run_dir.mkdir()
                    run = stream(
                        run_dir,
                        emu,
                        controller=False,
                        oracle_k=[k],
                        phase_secs=args.window_secs,
                        gamma=1.0,
                        fps=args.fps,
                        robot_extra=MODES[mode],
                        schedule=(profile.name,),
                    )
                    f = summarise([r for r in run.frames() if r["k"] == k], profile)
                    if f is None:
                        print(f"{k:>2} {rep:>3} {mode:<6} no frames", flush=True)
                        continue
                    ratios.setdefault((k, mode), []).append(f["ratio"])
                    print(
                        f"{k:>2} {rep:>3} {mode:<6} {f['fps']:>5.2f} {f['e2e_p50_ms']:>8.1f} {f['e2e_p90_ms']:>8.1f} "
                        f"{f['robot_ms']:>6.1f} {f['link_ms']:>7.1f} {f['edge_ms']:>6.1f} {f['payload_kB']:>5.0f} "
                        f"{f['kB_per_s']:>6.0f} {f['use']:>5.2f} {f['ideal_ms']:>6.1f} "
                        f"{f['ratio']:>9.2f}",
                        flush=True,
                    )
    for (k, mode), values in sorted(ratios.items()):
        print(
            f"k = {k} {mode}: e2e / ideal, median of the runs' medians {np.median(values):.2f} ({len(values)} runs)",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
