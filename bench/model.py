"""The paper's Table on this machine: payload S(k) and cumulative single-thread compute C(k) per cut,
for fp32 NCHW, fp32 channels_last and bf16 autocast + channels_last, all measured in one run.

    .venv/bin/python -m bench.model [--weights models] [--repetitions 30] [--threads 1]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from bench.machine import cpu_label
from shared.model.net import SplitKeypointNet
from shared.model.profile import VARIANTS, profile_cuts
from shared.model.weights import load_model
from shared.wire.cuts import CUTS


def main() -> None:
    """Print the table."""
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--weights", type=Path, default=None)
    ap.add_argument("--repetitions", type=int, default=30)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--batch", type=int, default=1, help="tags per frame")
    args = ap.parse_args()
    print(f"CPU: {cpu_label()}", flush=True)
    torch.set_num_threads(args.threads)
    model = load_model(args.weights) if args.weights else SplitKeypointNet(roi_margin=0.2)
    results = {v: profile_cuts(model, variant=v, batch=args.batch, repetitions=args.repetitions) for v in VARIANTS}
    print(f"{args.threads} thread(s), batch {args.batch}, median of {args.repetitions}; C(k) in ms, S(k) per tag")
    head = "".join(f"{v:>20}" for v in VARIANTS)
    print(f"{'k':>2} {'cut':<10} {'S(k) bytes':>11} {'S(k) kB fp16':>13}{head}")
    for cut in CUTS:
        cells = "".join(f"{results[v][cut.k].median_ms:>20.2f}" for v in VARIANTS)
        print(f"{cut.k:>2} {cut.name:<10} {cut.tensor_bytes():>11} {cut.payload_bytes_fp16 / 1024:>13.2f}{cells}")
    full = {v: results[v][-1].median_ms for v in VARIANTS}
    print("full-network speed-up vs fp32 NCHW: " + ", ".join(f"{v} {full['fp32'] / full[v]:.2f}x" for v in VARIANTS))


if __name__ == "__main__":
    main()
