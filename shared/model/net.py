"""The paper's split keypoint CNN (section IV-A1) with a cut-anywhere head/tail API.

Stages: k=0 is the ROI itself (1x256x256); blocks 1..5 are two 3x3 conv+BN+ReLU and a 2x2
max-pool (32-64-128-256-256 channels); the head is a 3x3 conv + ReLU, adaptive average pooling to
4x4 (k=6), then FC 4096->512->32 read as 16 (x, y) keypoints in normalised ROI coordinates (k=7).

Output parameterisation: the last FC predicts *offsets from the canonical keypoint lattice* (where
the keypoints fall when the detected quad is exact), scaled by `OFFSET_SCALE`, and is zero-
initialised. The untrained net therefore already predicts the lattice, and training only has to
learn the small corrections caused by detector noise and quad perturbation; this is what makes
training converge in minutes instead of hours. The output is still plain normalised keypoints.
"""

from __future__ import annotations

from typing import Final

import numpy as np
import torch
from torch import Tensor, nn

from shared.wire.cuts import CHANNELS, N_CUTS, NUM_KEYPOINTS, POOLED_SIZE, check_cut

HIDDEN: Final[int] = 512
OFFSET_SCALE: Final[float] = 0.1


def canonical_keypoints(margin: float) -> np.ndarray:
    """The 4x4 lattice in normalised ROI coordinates when the quad maps exactly onto the ROI square.

    Row-major from the tag's top-left corner; `margin` is the ROI border as a fraction of the side.
    """
    fr = np.array([0.0, 1 / 3, 2 / 3, 1.0])
    xs = margin + (1 - 2 * margin) * fr
    gx, gy = np.meshgrid(xs, xs)
    return np.stack([gx.ravel(), gy.ravel()], axis=1).astype(np.float32)


def _block(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
        nn.Conv2d(cout, cout, 3, padding=1, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
        nn.MaxPool2d(2),
    )


class SplitKeypointNet(nn.Module):
    """VGG-style keypoint regressor; `forward_head(x, k)` / `forward_tail(z, k)` split it at cut k."""

    def __init__(self, *, roi_margin: float) -> None:
        super().__init__()
        chans = (1, *CHANNELS)
        self.blocks = nn.ModuleList(_block(chans[i], chans[i + 1]) for i in range(len(CHANNELS)))
        self.head_conv = nn.Sequential(nn.Conv2d(CHANNELS[-1], CHANNELS[-1], 3, padding=1), nn.ReLU(inplace=True))
        self.pool = nn.AdaptiveAvgPool2d(POOLED_SIZE)
        self.fc = nn.Sequential(
            nn.Flatten(),
            nn.Linear(CHANNELS[-1] * POOLED_SIZE * POOLED_SIZE, HIDDEN),
            nn.ReLU(inplace=True),
            nn.Linear(HIDDEN, NUM_KEYPOINTS * 2),
        )
        last = self.fc[-1]
        assert isinstance(last, nn.Linear)
        nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        self.roi_margin = roi_margin
        self.register_buffer(
            "anchor",
            torch.from_numpy(canonical_keypoints(roi_margin)).reshape(1, -1),
            persistent=False,
        )

    @staticmethod
    def normalise_input(roi_u8: Tensor) -> Tensor:
        """uint8 ROI pixels (B,1,256,256) -> float input in [-1, 1]."""
        return roi_u8.float().div_(127.5).sub_(1.0)

    def _stage(self, z: Tensor, k: int) -> Tensor:
        """Run stage k (producing cut k from cut k-1)."""
        if 1 <= k <= len(CHANNELS):
            return self.blocks[k - 1](z)
        if k == 6:
            return self.pool(self.head_conv(z))
        if k == 7:
            # The add happens in fp32 even under bf16 autocast: bf16 resolves only ~2e-3 near 0.5,
            # i.e. ~0.5 ROI px, which would quantise every keypoint.
            offsets = self.fc(z).float()
            out = self.anchor + OFFSET_SCALE * offsets
            return out.view(-1, NUM_KEYPOINTS, 2)
        raise ValueError(f"no stage {k}")

    def forward_head(self, x: Tensor, k: int) -> Tensor:
        """Run the robot side: from the normalised ROI (cut 0) up to cut k."""
        check_cut(k)
        z = x
        for stage in range(1, k + 1):
            z = self._stage(z, stage)
        return z

    def forward_tail(self, z: Tensor, k: int) -> Tensor:
        """Run the edge side: from cut k to keypoints (B,16,2) in normalised ROI coordinates."""
        check_cut(k)
        for stage in range(k + 1, N_CUTS):
            z = self._stage(z, stage)
        return z

    def forward(self, x: Tensor) -> Tensor:
        """Whole network: normalised ROI (B,1,256,256) -> keypoints (B,16,2)."""
        return self.forward_tail(self.forward_head(x, 0), 0)


class AllCuts(nn.Module):
    """The whole network with every cut as an output: `forward(x)` returns the tensors at cuts 1..7
    (cut 7 = keypoints). This is the graph that is exported and quantised once; the split runtimes
    cut it at any k (head: input to output k-1; tail: a new input replacing that output)."""

    def __init__(self, net: SplitKeypointNet) -> None:
        super().__init__()
        self.net = net

    def forward(self, x: Tensor) -> tuple[Tensor, ...]:
        outs = []
        z = x
        for stage in range(1, N_CUTS):
            z = self.net._stage(z, stage)
            outs.append(z)
        return tuple(outs)


def count_parameters(model: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)
