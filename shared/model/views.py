"""Test-time views of an ROI: the network run on dihedral transforms of it, its keypoints mapped back
and averaged.

The network was trained on all 8 dihedral transforms of its ROIs (shared.training.train), yet its
errors on an ROI and on that ROI turned over are not the same: averaging the views cancels part of
them. Measured on synth7's test split (blurred small tags, 300 ROIs, fp32, sixth weights): e_px 0.409
-> 0.372 with 2 views -> 0.362 with 4, the pose's rotation error p90 2.66 -> 2.32 -> 2.28 deg. Each
view is one more network pass per tag.

Transform t (0..7) of an ROI array (..., H, W): bit 2 transposes, then bit 0 flips x (columns), then
bit 1 flips y (rows); keypoints are normalised (x, y) in [0, 1] (pixel edges at 0 and 1, so a flip is
1 - x) in the 4x4 lattice's row-major order, which the transform permutes like the image's pixels.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import lru_cache
from typing import TYPE_CHECKING, Annotated, Any

import numpy as np
from numpy.typing import NDArray
from pydantic import AfterValidator

from shared.wire.cuts import N_CUTS

if TYPE_CHECKING:
    from shared.model.precision import Precision
    from shared.model.runtime import SplitNet

LAST_CUT = N_CUTS - 1
MAX_PASS_BATCH = 64  # ROI views per inner network call

VIEW_COUNTS: tuple[int, ...] = (1, 2, 4, 8)
# Which transforms each count uses: 2 = the ROI and its half turn (flip x and y), 4 = every flip.
_TRANSFORMS: dict[int, tuple[int, ...]] = {1: (0,), 2: (0, 3), 4: (0, 1, 2, 3), 8: tuple(range(8))}


def transforms(views: int) -> tuple[int, ...]:
    """The dihedral transforms a view count uses (ValueError for a count not in VIEW_COUNTS)."""
    if isinstance(views, bool) or views not in _TRANSFORMS:
        raise ValueError(f"views must be one of {VIEW_COUNTS}, got {views!r}")
    return _TRANSFORMS[views]


def _check_views(views: int) -> int:
    transforms(views)
    return views


# A settings field: an int (from TOML, the environment or the command line) that is a view count.
Views = Annotated[int, AfterValidator(_check_views)]


def transform_image(a: NDArray[np.generic], t: int) -> NDArray[np.generic]:
    """Dihedral transform t of the last two axes (a view, not a copy)."""
    if t & 4:
        a = np.swapaxes(a, -1, -2)
    if t & 1:
        a = a[..., ::-1]
    if t & 2:
        a = a[..., ::-1, :]
    return a


@lru_cache(maxsize=8)
def _source_index(t: int) -> NDArray[np.intp]:
    """For each lattice slot of the transformed ROI, the original keypoint it shows."""
    return np.ascontiguousarray(transform_image(np.arange(16).reshape(4, 4), t)).ravel()


def untransform_keypoints(kp: NDArray[np.floating], t: int) -> NDArray[np.float32]:
    """Keypoints (..., 16, 2) predicted on transform t of an ROI, as keypoints of the ROI itself."""
    x, y = kp[..., 0], kp[..., 1]
    if t & 2:
        y = 1 - y
    if t & 1:
        x = 1 - x
    if t & 4:
        x, y = y, x
    out = np.empty(np.shape(kp), np.float32)
    out[..., _source_index(t), 0] = x
    out[..., _source_index(t), 1] = y
    return out


def expand_views(rois: NDArray[np.uint8], views: int) -> NDArray[np.uint8]:
    """ROIs (N, H, W) or (N, 1, H, W) -> (N * views, ...), each ROI's views consecutive (tag-major)."""
    ts = transforms(views)
    if views == 1:
        return rois
    stacked = np.stack([transform_image(rois, t) for t in ts], axis=1)  # (N, V, H, W)
    return np.ascontiguousarray(stacked.reshape(-1, *rois.shape[1:]))


def merge_views(kp: NDArray[np.floating], views: int) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Keypoints (N * views, 16, 2) of `expand_views`' ROIs -> the mean over each ROI's views
    (N, 16, 2) and their spread (N,): the RMS distance of the views' keypoints from that mean, in the
    same normalised units (0 for one view)."""
    ts = transforms(views)
    kp = np.asarray(kp, np.float32)
    if kp.ndim != 3 or kp.shape[1:] != (16, 2) or kp.shape[0] % views:
        raise ValueError(f"expected (N * {views}, 16, 2) keypoints, got {kp.shape}")
    per = kp.reshape(-1, views, 16, 2)
    back = np.stack([untransform_keypoints(per[:, i], t) for i, t in enumerate(ts)], axis=1)
    mean = back.mean(axis=1)
    spread = np.sqrt(np.mean(np.sum((back - mean[:, None]) ** 2, axis=-1), axis=(1, 2)))
    return mean.astype(np.float32), spread.astype(np.float32)


class ViewAveragedNet:
    """A SplitNet whose whole-network passes average `views` dihedral views of each ROI: `head` at the
    last cut (the robot runs everything: keypoints out) and `tail` from cut 0 (the edge, or one
    process, runs everything). Where the network is split across the link (cuts 1..6) each half runs
    once per ROI as the wrapped net does: views there would multiply the tensors on the wire."""

    def __init__(self, net: SplitNet, views: int) -> None:
        transforms(views)
        self.net = net
        self.views = views

    @property
    def precision(self) -> Precision:
        """The wrapped net's."""
        return self.net.precision

    def _averaged(self, run: Callable[[NDArray[Any]], NDArray[Any]], rois: NDArray[Any]) -> NDArray[np.float32]:
        # at most MAX_PASS_BATCH ROIs per inner call: a batch of 64 at 8 views is 512 ROIs (GBs of activations)
        step = max(1, MAX_PASS_BATCH // self.views)
        parts = []
        for i in range(0, len(rois), step):
            out = np.asarray(run(expand_views(rois[i : i + step], self.views)), np.float32)
            kp, _ = merge_views(out.reshape(-1, 16, 2), self.views)
            parts.append(kp.reshape(len(kp), *out.shape[1:]))
        return np.concatenate(parts)

    def head(self, rois_u8: NDArray[np.uint8], k: int) -> NDArray[np.float32]:
        """The wrapped head; at the last cut (the whole network) averaged over the views."""
        if k != LAST_CUT or len(rois_u8) == 0:
            return self.net.head(rois_u8, k)
        return self._averaged(lambda r: self.net.head(r, k), rois_u8)

    def tail(self, z: NDArray[Any], k: int) -> NDArray[np.float32]:
        """The wrapped tail; from cut 0 (the whole network, on ROIs) averaged over the views."""
        if k != 0 or len(z) == 0:
            return self.net.tail(z, k)
        return self._averaged(lambda r: self.net.tail(r, 0), z)

    def warm_up(self, k: int, *, max_batch: int = 1) -> None:
        """The wrapped net's, then at the cuts where the views apply (0 and the last) the whole network
        once per batch of 1..max_batch ROIs (max_batch * views passes: shapes specialise on first use)."""
        self.net.warm_up(k, max_batch=max_batch)
        if k in (0, LAST_CUT):
            for n in range(1, max_batch + 1):
                x = np.zeros((n, 256, 256), np.uint8)
                if k == LAST_CUT:
                    self.head(x, k)
                else:
                    self.tail(x, 0)


def with_views(net: SplitNet, views: int) -> SplitNet:
    """`net` itself for one view, else wrapped in ViewAveragedNet."""
    return net if views == 1 else ViewAveragedNet(net, views)
