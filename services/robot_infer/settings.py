"""Settings of robot_infer."""

from __future__ import annotations

from pathlib import Path
from typing import ClassVar, Literal

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from shared.detector import DetectorSettings
from shared.settings import ServiceSettings


class RobotInferSettings(ServiceSettings):
    """The robot side of the split."""

    SERVICE: ClassVar[str] = "robot_infer"
    model_config = SettingsConfigDict(**{**ServiceSettings.model_config, "env_prefix": "SPLITTAG_ROBOT_INFER_"})

    weights: Path = Path("models")
    split_k: int = Field(default=7, ge=0, le=7)
    codec: Literal["fp16", "fp32"] = "fp16"
    detector: DetectorSettings = Field(default_factory=DetectorSettings)
    bf16: bool = True
    threads: int = Field(default=1, ge=1)
    max_in_flight: int = Field(default=2, ge=0)  # frames sent without TagPoses back yet; 0 = no limit
    in_flight_timeout_secs: float = Field(default=2.0, gt=0)  # a frame never answered returns its credit
    profile_period_secs: float = Field(default=1.0, gt=0)  # ComputeProfile C(k) publication period
    gamma: float = Field(default=1.0, ge=1.0)  # >1 emulates a slower robot CPU by sleeping (gamma-1)*compute
