"""The paper's Table on this machine: payload S(k) and cumulative single-thread compute C(k) per cut,
for fp32 NCHW, fp32 channels_last and bf16 autocast + channels_last, all measured in one run; then
what the edge adds per tag after the network: keypoint fusion (the weighted homography fit of the
16 points and stage 1's corners) and planar PnP, beside the full network.

    .venv/bin/python -m bench.model [--weights models] [--repetitions 30] [--threads 1]
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from bench.machine import cpu_label
from shared.model.net import SplitKeypointNet
from shared.model.profile import VARIANTS, profile_cuts
from shared.model.weights import load_model
from shared.vision.fusion import KeypointFusion, edge_width_px
from shared.vision.geometry import CORNER_KEYPOINTS, apply_homography, default_camera, lattice_in_tag
from shared.vision.pnp import solve_planar_pnp
from shared.wire.cuts import CUTS


def per_tag_post_ms(repetitions: int = 2000) -> dict[str, float]:
    """Median ms per tag, one thread, on a typical tag (1.5 m, tilted): the edge width the robot measures,
    keypoint fusion and PnP on the edge."""
    rng = np.random.default_rng(0)
    unit_to_image = np.array([[120.0, 14.0, 580.0], [-9.0, 110.0, 300.0], [0.0002, -0.0001, 1.0]])
    unit = np.array([[x, y] for y in (0, 1 / 3, 2 / 3, 1) for x in (0, 1 / 3, 2 / 3, 1)])
    keypoints = apply_homography(unit_to_image, unit) + rng.normal(0, 0.2, (16, 2))
    corners = keypoints[list(CORNER_KEYPOINTS)] + rng.normal(0, 0.1, (4, 2))
    roi_to_image = np.array([[0.5, 0.0, 540.0], [0.0, 0.5, 260.0], [0.0, 0.0, 1.0]])
    fusion = KeypointFusion(keypoint_sigma_roi_px=0.3, corner_sigma_px=0.15)
    camera, obj = default_camera(), lattice_in_tag(0.15)

    def median_ms(fn: Callable[[], object]) -> float:
        times = []
        for _ in range(repetitions):
            t0 = time.perf_counter()
            fn()
            times.append((time.perf_counter() - t0) * 1e3)
        return statistics.median(times)

    roi = np.full((256, 256), 200, np.uint8)
    roi[51:205, 51:205] = 30
    return {
        "edge_width": median_ms(lambda: edge_width_px(roi, roi_to_image)),
        "fusion": median_ms(lambda: fusion.apply(keypoints, corners, roi_to_image, 2.0)),
        "pnp": median_ms(lambda: solve_planar_pnp(camera, obj, keypoints)),
    }


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
    post = per_tag_post_ms()
    print(
        f"beside the network, per tag: edge width (robot) {post['edge_width']:.3f} ms, keypoint fusion (edge) "
        f"{post['fusion']:.3f} ms, PnP {post['pnp']:.3f} ms; width + fusion = "
        f"{100 * (post['edge_width'] + post['fusion']) / full['bf16-channels-last']:.2f} % of the bf16 network"
    )


if __name__ == "__main__":
    main()
