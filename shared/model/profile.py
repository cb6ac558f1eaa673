"""Per-cut compute profile: cumulative robot-side time C(k) of `forward_head(x, k)` (the paper's Table)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from shared.model.infer import autocast, prepare
from shared.model.net import SplitKeypointNet
from shared.wire.cuts import CUTS

Variant = Literal["fp32", "fp32-channels-last", "bf16-channels-last"]
VARIANTS: tuple[Variant, ...] = ("fp32", "fp32-channels-last", "bf16-channels-last")


@dataclass(frozen=True)
class CutTiming:
    """Median cumulative compute up to cut k, milliseconds."""

    k: int
    median_ms: float
    p90_ms: float
    min_ms: float


@torch.no_grad()
def profile_cuts(
    model: SplitKeypointNet, *, variant: Variant, batch: int = 1, repetitions: int = 30, warmup: int = 5
) -> list[CutTiming]:
    """Time forward_head(x, k) for every k (k = 0 is the input normalisation only)."""
    model = model.eval()
    x = torch.randint(0, 256, (batch, 1, 256, 256), dtype=torch.uint8)
    cl = variant != "fp32"
    if cl:
        model = model.to(memory_format=torch.channels_last)  # type: ignore[call-overload]
    out = []
    for cut in CUTS:
        times = []
        for i in range(warmup + repetitions):
            t0 = time.perf_counter()
            z = prepare(x, 0, channels_last=cl)
            with autocast(bf16=variant.startswith("bf16")):
                model.forward_head(z, cut.k)
            if i >= warmup:
                times.append((time.perf_counter() - t0) * 1e3)
        out.append(CutTiming(cut.k, float(np.median(times)), float(np.percentile(times, 90)), float(min(times))))
    return out


def calibrate_pnp_ms(repetitions: int = 20) -> float:
    """Median time to map 16 keypoints to the image and solve both PnP branches for one tag, ms."""
    from shared.vision.geometry import default_camera, lattice_in_tag, make_pose
    from shared.vision.pnp import solve_planar_pnp

    cam = default_camera()
    obj = lattice_in_tag(0.16)
    pose = make_pose(np.eye(3), [0.05, -0.02, 1.2])
    pts = (cam.matrix() @ (pose[:3, :3] @ obj.T + pose[:3, 3:4])).T
    img = pts[:, :2] / pts[:, 2:3]
    times = []
    for _ in range(repetitions):
        t0 = time.perf_counter()
        solve_planar_pnp(cam, obj, img)
        times.append((time.perf_counter() - t0) * 1e3)
    return float(np.median(times))
