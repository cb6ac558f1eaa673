"""Per-cut compute profile: cumulative robot-side time C(k) of `forward_head(x, k)` (the paper's Table)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from shared.model import CUTS, SplitKeypointNet

Variant = Literal["fp32", "fp32-channels-last", "bf16-channels-last"]
VARIANTS: tuple[Variant, ...] = ("fp32", "fp32-channels-last", "bf16-channels-last")


@dataclass(frozen=True)
class CutTiming:
    """Median cumulative compute up to cut k, milliseconds."""

    k: int
    median_ms: float
    p90_ms: float


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
            z = SplitKeypointNet.normalise_input(x)
            if cl:
                z = z.contiguous(memory_format=torch.channels_last)
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=variant.startswith("bf16")):
                model.forward_head(z, cut.k)
            if i >= warmup:
                times.append((time.perf_counter() - t0) * 1e3)
        out.append(CutTiming(cut.k, float(np.median(times)), float(np.percentile(times, 90))))
    return out
