"""Settings of edge_infer."""

from __future__ import annotations

from pathlib import Path
from typing import ClassVar

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from shared.model.precision import PrecisionChoice
from shared.runtime.settings import ServiceSettings
from shared.wire.messages import PerCut


class EdgeInferSettings(ServiceSettings):
    """The edge side of the split."""

    SERVICE: ClassVar[str] = "edge_infer"
    model_config = SettingsConfigDict(**{**ServiceSettings.model_config, "env_prefix": "SPLITTAG_EDGE_INFER_"})

    weights: Path = Path("models")
    # Fit each tag's 16 points to the network's keypoints and stage 1's corners, weighted by the
    # sigmas calibrated into the weights' config.json (no calibration there: the network's points).
    fuse_corners: bool = True
    # A tracked tag (robot_infer's tracking) whose 16 keypoints fit a plane worse than this (RMS px) gets no pose.
    tracked_max_reprojection_px: float = Field(default=1.0, gt=0)
    tag_map: Path | None = None  # YAML/JSON with per-tag sizes; unknown ids use default_tag_size_m
    default_tag_size_m: float = Field(default=0.2, gt=0)
    # auto | fp32 | bf16 | int8: as robot_infer's (shared.model.precision says what auto picks)
    precision: PrecisionChoice = "auto"
    threads: int = Field(default=1, ge=1)
    serve_echo: bool = True  # the link-probe echo queryable lives on the edge
    queue_depth: int = Field(default=2, ge=1)  # Features waiting for the edge; small = bounded latency
    profile_period_secs: float = Field(default=1.0, gt=0)  # ComputeProfile E(k) publication period
    # Emulating another edge CPU: a fixed per-tag tail time (PnP included) at every cut, ms. Frames are
    # padded by sleeping up to it and E(k) is published from it, independent of this CPU; a frame
    # whose real compute exceeds it takes the real time. None: calibrated and measured live.
    emulated_ms_per_tag_by_k: PerCut | None = None
