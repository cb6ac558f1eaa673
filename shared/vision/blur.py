"""Motion-blur kernels, shared by the training-data generator and the tracker's soft decode."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray


def line_kernel(length_px: float, angle_rad: float) -> NDArray[np.float32]:
    """Linear motion-blur kernel of `length_px` at `angle_rad`, centred on its middle pixel."""
    r = math.ceil(length_px / 2) + 1
    k = np.zeros((2 * r + 1, 2 * r + 1), np.float32)
    n = max(2, math.ceil(length_px * 4) + 1)
    for t in np.linspace(-length_px / 2, length_px / 2, n):
        x, y = r + t * math.cos(angle_rad), r + t * math.sin(angle_rad)
        ix, iy = math.floor(x), math.floor(y)
        fx, fy = x - ix, y - iy
        k[iy, ix] += (1 - fx) * (1 - fy)
        k[iy, ix + 1] += fx * (1 - fy)
        k[iy + 1, ix] += (1 - fx) * fy
        k[iy + 1, ix + 1] += fx * fy
    return k / float(k.sum())
