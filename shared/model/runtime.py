"""The split network as the services run it, whatever executes it: `SplitNet.head(rois, k)` on the
robot, `SplitNet.tail(z, k)` on the edge, numpy in and out.

Precisions (chosen per side by configuration, `precision = "fp32" | "bf16" | "int8"`):
- fp32 and bf16: PyTorch eager on the safetensors weights (bf16 = autocast + channels_last).
- int8: OpenVINO on the weights folder's int8 variant (shared.model.openvino_net), made by
  `splittag quantize`; config.json lists it under `variants`.
Both sides of a link may use different precisions: the cut tensor is float on the wire either way.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
from numpy.typing import NDArray

from shared.model.infer import run_head, run_tail
from shared.model.net import SplitKeypointNet
from shared.model.openvino_net import OpenVINOSplitNet, variant_path
from shared.model.precision import Precision, PrecisionChoice, resolve_for_folder
from shared.model.weights import load_model
from shared.wire.cuts import CUTS, INPUT_SIZE, check_net_cut, check_net_rois


class SplitNet(Protocol):
    """What the robot and edge steps need from the network."""

    @property
    def precision(self) -> Precision: ...

    def head(self, rois_u8: NDArray[np.uint8], k: int) -> NDArray[np.float32]: ...

    def tail(self, z: NDArray[Any], k: int) -> NDArray[np.float32]: ...

    def warm_up(self, k: int, *, max_batch: int = 1) -> None: ...


class TorchSplitNet:
    """PyTorch eager, fp32 or bf16 autocast (channels_last)."""

    def __init__(self, model: SplitKeypointNet, *, bf16: bool) -> None:
        self.model = model.eval()
        self.precision: Precision = "bf16" if bf16 else "fp32"
        self._bf16 = bf16

    def head(self, rois_u8: NDArray[np.uint8], k: int) -> NDArray[np.float32]:
        check_net_rois(np.asarray(rois_u8))
        x = torch.from_numpy(np.ascontiguousarray(rois_u8).reshape(-1, 1, INPUT_SIZE, INPUT_SIZE))
        return run_head(self.model, x, k, bf16=self._bf16).contiguous().numpy()

    def tail(self, z: NDArray[Any], k: int) -> NDArray[np.float32]:
        """Normalised keypoints (N,16,2) from cut-k tensors (k = 0: uint8 ROIs, or the normalised floats
        `head(rois, 0)` gives, as OpenVINO's tail takes them)."""
        z = np.asarray(z)
        check_net_cut(z, k)
        x = torch.from_numpy(z if k == 0 and z.dtype == np.uint8 else np.asarray(z, np.float32))
        if k == 0:
            x = x.reshape(-1, 1, INPUT_SIZE, INPUT_SIZE)
        return run_tail(self.model, x, k, bf16=self._bf16).numpy()

    def warm_up(self, k: int, *, max_batch: int = 1) -> None:
        """oneDNN builds its kernels per shape: run the whole network once per batch size."""
        for n in range(1, max_batch + 1):
            self.tail(self.head(np.zeros((n, INPUT_SIZE, INPUT_SIZE), np.uint8), 0), 0)


def load_split_net(weights: Path, precision: PrecisionChoice, *, threads: int | None = None) -> SplitNet:
    """The network of a weights folder at a precision (int8: its OpenVINO variant, else VariantError;
    auto: the fastest this CPU and folder allow, see shared.model.precision); `.precision` says which."""
    precision = resolve_for_folder(precision, weights)
    if precision == "int8":
        return OpenVINOSplitNet(variant_path(weights, "int8"), threads=threads)
    return TorchSplitNet(load_model(weights), bf16=precision == "bf16")


def _min_ms_each(calls: Sequence[Callable[[], object]], repetitions: int) -> list[float]:
    """The fastest of `repetitions` timed runs of each call (ms), after one untimed run of each (OpenVINO
    compiles a half on its first use). The calls take turns, a round of all of them per repetition, each
    round starting one call further on: a spell of load (services start together and calibrate while their
    neighbours load) then slows some rounds of every call rather than all rounds of a few. Timed one call
    after another, a researcher's `link cost` under load read C(2..5) all equal: cuts 2-4 were timed
    during the spell, and the clamp that keeps C(k) from falling with k flattened them to C(5)."""
    for call in calls:
        call()
    best = [float("inf")] * len(calls)
    for r in range(repetitions):
        for j in range(len(calls)):
            i = (r + j) % len(calls)
            t0 = time.perf_counter()
            calls[i]()
            best[i] = min(best[i], (time.perf_counter() - t0) * 1e3)
    return best


def calibrate_tail_ms(net: SplitNet, *, repetitions: int = 5) -> list[float]:
    """Tail time per tag (batch 1) from every cut to the keypoints, ms, each timed on an input of its
    own cut's shape (the minimum over repetitions, the cuts taking turns: `_min_ms_each`): what the edge
    computes. Not the whole network
    minus the head: each half is its own compiled graph, and a fresh trial read E(4) = 0.2 ms (PnP
    alone) and E(6) > E(5) from that difference. The inputs are made, not computed by the heads, so
    the edge compiles no head it never runs (the times of these dense layers do not depend on the
    values)."""
    rng = np.random.default_rng(0)
    calls = []
    for cut in CUTS:
        z: NDArray[Any]
        if cut.k == 0:
            z = rng.integers(0, 256, (1, *cut.shape), dtype=np.uint8)
        else:  # the edge runs its tails on float32 (split.edge_step)
            z = np.abs(rng.standard_normal((1, *cut.shape))).astype(np.float32)
        calls.append(partial(net.tail, z, cut.k))
    return _min_ms_each(calls, repetitions)


def calibrate_cumulative_ms(net: SplitNet, *, repetitions: int = 5) -> list[float]:
    """Cumulative head time per tag (batch 1) at every cut, ms: the minimum over repetitions, the cuts
    taking turns (`_min_ms_each`; services start together and calibrate while their neighbours load;
    live measurements scale it later)."""
    x = np.random.default_rng(0).integers(0, 256, (1, INPUT_SIZE, INPUT_SIZE), dtype=np.uint8)
    return _min_ms_each([partial(net.head, x, cut.k) for cut in CUTS], repetitions)
