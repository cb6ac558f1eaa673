"""The cut table: every question about a split point answered in one place, without torch.

Where the network can be cut (k = 0..7), what crosses the link there (shape per tag, dtype per codec,
bytes), and the check a receiver makes. The network (`shared.model.net`) builds its blocks from the
same constants, the controller and the link tools size payloads from it, the edge validates with it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final, Literal

import numpy as np

from shared.wire.codec import WireError

INPUT_SIZE: Final[int] = 256  # the ROI is INPUT_SIZE x INPUT_SIZE mono8
NUM_KEYPOINTS: Final[int] = 16
CHANNELS: Final[tuple[int, ...]] = (32, 64, 128, 256, 256)  # blocks 1..5
POOLED_SIZE: Final[int] = 4
CUT_NAMES: Final[tuple[str, ...]] = ("roi", "block1", "block2", "block3", "block4", "block5", "avgpool", "keypoints")
N_CUTS: Final[int] = len(CUT_NAMES)  # split points k = 0 .. N_CUTS - 1

CodecName = Literal["fp32", "fp16"]  # how feature maps (cuts 1..6) travel; ROI pixels and keypoints are fixed


@dataclass(frozen=True)
class CutInfo:
    """What crosses the link when the net is cut at k (per tag)."""

    k: int
    name: str
    shape: tuple[int, ...]  # per tag, without the batch dimension

    @property
    def elements(self) -> int:
        """Number of tensor elements per tag."""
        return int(np.prod(self.shape))

    def dtype(self, codec: CodecName) -> np.dtype[np.generic]:
        """The dtype the tensor travels in: ROI pixels uint8, keypoints fp32, feature maps per codec."""
        if self.k == 0:
            return np.dtype(np.uint8)
        if self.k == N_CUTS - 1:
            return np.dtype(np.float32)
        return np.dtype(np.float16 if codec == "fp16" else np.float32)

    def tensor_bytes(self, codec: CodecName = "fp16") -> int:
        """Tensor bytes per tag on the wire."""
        return self.elements * self.dtype(codec).itemsize

    @property
    def payload_bytes_fp16(self) -> int:
        """Tensor bytes per tag if every cut were sent as fp16 (the paper's table)."""
        return self.elements * 2


def _cut_table() -> tuple[CutInfo, ...]:
    cuts = [CutInfo(0, CUT_NAMES[0], (1, INPUT_SIZE, INPUT_SIZE))]
    size = INPUT_SIZE
    for i, ch in enumerate(CHANNELS, start=1):
        size //= 2
        cuts.append(CutInfo(i, CUT_NAMES[i], (ch, size, size)))
    cuts.append(CutInfo(6, CUT_NAMES[6], (CHANNELS[-1], POOLED_SIZE, POOLED_SIZE)))
    cuts.append(CutInfo(7, CUT_NAMES[7], (NUM_KEYPOINTS, 2)))
    return tuple(cuts)


CUTS: Final[tuple[CutInfo, ...]] = _cut_table()


def check_cut(k: int) -> int:
    """Return k if it is a valid cut index, else raise ValueError."""
    if not isinstance(k, int) or isinstance(k, bool) or not 0 <= k < N_CUTS:
        raise ValueError(f"split index must be an int in 0..{N_CUTS - 1}, got {k!r}")
    return k


def tensor_bytes(k: int, codec: CodecName = "fp16") -> int:
    """Bytes of one tag's tensor at cut k on the wire."""
    return CUTS[k].tensor_bytes(codec)


class FeatureShapeError(WireError):
    """A Features tensor that does not match the announced split index and codec."""


def check_tensor(tensor: np.ndarray, k: int, codec: CodecName) -> None:
    """Raise FeatureShapeError unless the tensor has the shape and dtype of cut k."""
    want_shape, want_dtype = CUTS[k].shape, CUTS[k].dtype(codec)
    if tensor.shape != want_shape or tensor.dtype != want_dtype:
        raise FeatureShapeError(
            f"tensor {tensor.dtype}{list(tensor.shape)} does not match k={k} ({CUTS[k].name}), "
            f"which needs {want_dtype}{list(want_shape)} with codec {codec}"
        )


def check_net_rois(rois: np.ndarray) -> None:
    """The split API's head takes uint8 ROIs, (N, 256, 256) or (N, 1, 256, 256), and normalises them
    itself: a float ROI, already normalised or not, was taken silently and gave garbage (a trial)."""
    if rois.dtype != np.uint8:
        raise TypeError(f"head takes uint8 ROIs (N, 256, 256), not {rois.dtype}: it normalises them itself")
    side = CUTS[0].shape[-1]
    if rois.ndim not in (3, 4) or rois.shape[-2:] != (side, side) or (rois.ndim == 4 and rois.shape[1] != 1):
        raise ValueError(f"head takes ROIs (N, {side}, {side}), got {list(rois.shape)}")


def check_net_cut(z: np.ndarray, k: int) -> None:
    """tail(z, k) takes cut k's tensor: (N, *CUTS[k].shape) (k = 0: the ROIs). A tensor of another cut
    went to the runtime and came back as its raw shape error (a trial)."""
    if k == 0:
        return check_net_rois(z) if z.dtype == np.uint8 else None
    want = CUTS[k].shape
    if z.ndim != len(want) + 1 or tuple(z.shape[1:]) != want:
        raise ValueError(f"tail at k={k} ({CUTS[k].name}) takes (N, {', '.join(map(str, want))}), got {list(z.shape)}")
