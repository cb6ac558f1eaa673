"""The one inference path: every caller (robot and edge steps, `splittag detect` and `eval`, the
learning curve, profiling) prepares inputs and runs the network through these functions, so what is
measured is what is deployed. Preparation: ROI pixels (cut 0) normalised to [-1, 1]; 4-D tensors in
channels_last (the bf16 convolutions are ~2.5x faster on these CPUs); bf16 autocast when asked."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch
from torch import Tensor

from shared.model.net import SplitKeypointNet


def prepare(x: Tensor, k: int, *, channels_last: bool = True) -> Tensor:
    """The input of the stages after cut k. At k = 0 uint8 ROI pixels are normalised; a float tensor there
    is the normalised ROI already (what `head(rois, 0)` gives and OpenVINO's tail takes: an integrator's
    `tail(head(rois, 0), 0)` had it cast to uint8, 7 ROI px off)."""
    x = SplitKeypointNet.normalise_input(x) if k == 0 and x.dtype == torch.uint8 else x.float()
    if channels_last and x.ndim == 4:
        x = x.contiguous(memory_format=torch.channels_last)
    return x


@contextmanager
def autocast(*, bf16: bool, device_type: str = "cpu") -> Iterator[None]:
    """bf16 autocast (or nothing) around the network."""
    with torch.autocast(device_type, dtype=torch.bfloat16, enabled=bf16):
        yield


@torch.no_grad()
def run_head(model: SplitKeypointNet, rois_u8: Tensor, k: int, *, bf16: bool) -> Tensor:
    """Cut-k tensors (float32) for uint8 ROIs (N,1,S,S): blocks 1..k on the robot."""
    with autocast(bf16=bf16):
        return model.forward_head(prepare(rois_u8, 0), k).float()


@torch.no_grad()
def run_tail(model: SplitKeypointNet, z: Tensor, k: int, *, bf16: bool) -> Tensor:
    """Normalised keypoints (N,16,2, float32) from cut-k tensors: the rest of the network on the edge."""
    with autocast(bf16=bf16):
        return model.forward_tail(prepare(z, k), k).float()


@torch.no_grad()
def keypoints(
    model: SplitKeypointNet, rois_u8: Tensor, *, bf16: bool, channels_last: bool = True, batch: int = 128
) -> Tensor:
    """Normalised keypoints (N,16,2, float32) for uint8 ROIs (N,1,S,S) on the model's device, in batches."""
    model.eval()
    outs = []
    for i in range(0, len(rois_u8), batch):
        x = prepare(rois_u8[i : i + batch], 0, channels_last=channels_last)
        with autocast(bf16=bf16, device_type=rois_u8.device.type):
            outs.append(model(x).float())
    return torch.cat(outs) if outs else torch.zeros((0, 16, 2))


def forward_train(model: SplitKeypointNet, rois_u8: Tensor, *, bf16: bool, channels_last: bool) -> Tensor:
    """The training forward pass (with gradients) through the same preparation."""
    x = prepare(rois_u8, 0, channels_last=channels_last)
    with autocast(bf16=bf16, device_type=rois_u8.device.type):
        return model(x)
