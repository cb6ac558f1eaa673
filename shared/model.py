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

from dataclasses import dataclass
from typing import Final, Literal

import numpy as np
import torch
from torch import Tensor, nn

INPUT_SIZE: Final[int] = 256
NUM_KEYPOINTS: Final[int] = 16
CHANNELS: Final[tuple[int, ...]] = (32, 64, 128, 256, 256)
POOLED_SIZE: Final[int] = 4
HIDDEN: Final[int] = 512
OFFSET_SCALE: Final[float] = 0.1
CUT_NAMES: Final[tuple[str, ...]] = (
    "roi",
    "block1",
    "block2",
    "block3",
    "block4",
    "block5",
    "avgpool",
    "keypoints",
)
NUM_CUTS: Final[int] = len(CUT_NAMES)


@dataclass(frozen=True)
class CutInfo:
    """What crosses the link when the net is cut at k (per tag)."""

    k: int
    name: str
    shape: tuple[int, ...]  # per tag, without the batch dimension
    wire_dtype: Literal["uint8", "float16", "float32"]

    @property
    def elements(self) -> int:
        """Number of tensor elements per tag."""
        return int(np.prod(self.shape))

    @property
    def payload_bytes(self) -> int:
        """Tensor bytes per tag with the default fp16 codec (ROI pixels stay uint8, keypoints fp32)."""
        return self.elements * np.dtype(self.wire_dtype).itemsize

    @property
    def payload_bytes_fp16(self) -> int:
        """Tensor bytes per tag if every cut were sent as fp16 (the paper's table)."""
        return self.elements * 2


def _cut_table() -> tuple[CutInfo, ...]:
    cuts = [CutInfo(0, "roi", (1, INPUT_SIZE, INPUT_SIZE), "uint8")]
    size = INPUT_SIZE
    for i, ch in enumerate(CHANNELS, start=1):
        size //= 2
        cuts.append(CutInfo(i, f"block{i}", (ch, size, size), "float16"))
    cuts.append(CutInfo(6, "avgpool", (CHANNELS[-1], POOLED_SIZE, POOLED_SIZE), "float16"))
    cuts.append(CutInfo(7, "keypoints", (NUM_KEYPOINTS, 2), "float32"))
    return tuple(cuts)


CUTS: Final[tuple[CutInfo, ...]] = _cut_table()


def check_cut(k: int) -> int:
    """Return k if it is a valid cut index, else raise ValueError."""
    if not isinstance(k, int) or isinstance(k, bool) or not 0 <= k < NUM_CUTS:
        raise ValueError(f"split index must be an int in 0..{NUM_CUTS - 1}, got {k!r}")
    return k


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
        for stage in range(k + 1, NUM_CUTS):
            z = self._stage(z, stage)
        return z

    def forward(self, x: Tensor) -> Tensor:
        """Whole network: normalised ROI (B,1,256,256) -> keypoints (B,16,2)."""
        return self.forward_tail(self.forward_head(x, 0), 0)


def count_parameters(model: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)
