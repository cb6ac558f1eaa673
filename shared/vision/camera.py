"""The camera model every layer shares: pinhole intrinsics with optional plumb-bob distortion."""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]


class CameraIntrinsics(BaseModel):
    """Pinhole intrinsics in the ROS camera_info sense (pixels, OpenCV pixel-centre convention).
    Also a wire type (inside Frame and Features): frozen, strict, no unknown fields."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)

    width: int = Field(gt=0)
    height: int = Field(gt=0)
    fx: float = Field(gt=0, allow_inf_nan=False)
    fy: float = Field(gt=0, allow_inf_nan=False)
    cx: FiniteFloat
    cy: FiniteFloat
    distortion_model: Literal["plumb_bob", "none"]
    distortion: list[FiniteFloat]

    def matrix(self) -> NDArray[np.float64]:
        """The 3x3 camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=np.float64)

    def dist_coeffs(self) -> NDArray[np.float64]:
        """Distortion coefficients as OpenCV expects them (k1, k2, p1, p2[, k3])."""
        return np.asarray(self.distortion, dtype=np.float64)
