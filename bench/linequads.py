"""What the line-quad proposer (shared.vision.linequads) costs per 1280x720 frame, step by step, one thread.

The frames are bench/tagrender.py's single-tag renders (textured backgrounds, distractors, blur,
occluders), the same as bench/accuracy's; medians over the frames, and the CPU first.

    .venv/bin/python -m bench.linequads [--n 60] [--seed 0] [--no-soft-decode]

`--no-soft-decode`: the whole proposer ("detect") without its blind soft decode (stage1.lines.soft_decode).
"""

from __future__ import annotations

import argparse
import statistics
import time

import cv2

from bench.machine import cpu_label
from bench.tagrender import render_sample
from shared.vision import linequads as lq


def main() -> None:
    """Time each step on --n renders and print the medians (ms)."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--n", type=int, default=60)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--soft-decode",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="detect with the blind soft decode (on by default, as stage 1 runs it)",
    )
    args = ap.parse_args()
    cv2.setNumThreads(1)
    print(f"CPU: {cpu_label()}", flush=True)
    s = lq.LineQuadSettings(soft_decode=args.soft_decode)
    lsd = cv2.createLineSegmentDetector(cv2.LSD_REFINE_NONE)
    proposer = lq.LineQuadProposer(s)
    steps: dict[str, list[float]] = {k: [] for k in ("lsd", "lines", "corners", "quads", "decode", "detect")}
    for index in range(args.n):
        image = render_sample(index, args.seed).image
        t = [time.perf_counter()]
        segs = lq.segments(image, s.scale, lsd)
        t.append(time.perf_counter())
        lines = lq.oriented_lines(image, segs, s)
        t.append(time.perf_counter())
        graph = lq.corner_graph(lines, s)
        t.append(time.perf_counter())
        candidates = lq.quads(lines, graph, s)
        t.append(time.perf_counter())
        for quad, _ in candidates:
            lq.decode_quad(image, quad, s)
        t.append(time.perf_counter())
        proposer.detect(image)  # the whole proposer, refit of the found tags' sides included
        t.append(time.perf_counter())
        for name, a, b in zip(steps, t, t[1:], strict=False):
            steps[name].append((b - a) * 1e3)
    print(f"{args.n} renders of {image.shape[1]}x{image.shape[0]} (bench/tagrender, seed {args.seed}), medians in ms:")
    print("  " + ", ".join(f"{k} {statistics.median(v):.1f}" for k, v in steps.items()))


if __name__ == "__main__":
    main()
