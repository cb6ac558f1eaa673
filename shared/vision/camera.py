"""The camera model every layer shares: pinhole intrinsics with optional plumb-bob distortion."""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, model_validator

MAX_PIXELS = 65_536
DISTORTION_LENGTHS = (0, 4, 5, 8, 12, 14)  # what cv2.undistortPoints / solvePnP accept


class CameraIntrinsics(BaseModel):
    """Pinhole intrinsics in the ROS camera_info sense (pixels, OpenCV pixel-centre convention).
    Also a wire type (inside Frame and Features): frozen, strict, no unknown fields."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)

    # Bounded, so that no downstream division or projection can overflow (fx = 1e-300 used to).
    width: int = Field(gt=0, le=MAX_PIXELS)
    height: int = Field(gt=0, le=MAX_PIXELS)
    fx: float = Field(ge=1.0, le=1e6, allow_inf_nan=False)
    fy: float = Field(ge=1.0, le=1e6, allow_inf_nan=False)
    cx: float = Field(ge=-1e6, le=1e6, allow_inf_nan=False)
    cy: float = Field(ge=-1e6, le=1e6, allow_inf_nan=False)
    distortion_model: Literal["plumb_bob", "none"]
    distortion: list[Annotated[float, Field(ge=-1e3, le=1e3, allow_inf_nan=False)]]

    @model_validator(mode="after")  # also run on wire structs (shared.wire.messages marks it so)
    def _distortion_opencv_can_use(self) -> CameraIntrinsics:
        if len(self.distortion) not in DISTORTION_LENGTHS:
            raise ValueError(f"{len(self.distortion)} distortion coefficients; OpenCV takes {DISTORTION_LENGTHS}")
        if self.distortion_model == "none" and any(self.distortion):
            # Silently using them (or silently not) would both surprise someone: one of the two is a typo.
            raise ValueError(
                f"distortion_model 'none' with non-zero coefficients {self.distortion}: "
                "say plumb_bob to use them, or leave them out"
            )
        return self

    def matrix(self) -> NDArray[np.float64]:
        """The 3x3 camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=np.float64)

    def dist_coeffs(self) -> NDArray[np.float64]:
        """Distortion coefficients as OpenCV expects them (k1, k2, p1, p2[, k3[, k4, k5, k6[, ...]]])."""
        return np.asarray(self.distortion, dtype=np.float64)
