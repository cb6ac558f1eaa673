"""Settings of the slam service."""

from __future__ import annotations

from pathlib import Path
from typing import ClassVar

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from shared.runtime.settings import ServedRobots, ServiceSettings
from shared.slam.marker_slam import SlamSettings


class SlamServiceSettings(ServiceSettings):
    """Where the map comes from and where the outputs go (run_dir)."""

    SERVICE: ClassVar[str] = "slam"
    model_config = SettingsConfigDict(**{**ServiceSettings.model_config, "env_prefix": "SPLITTAG_SLAM_"})

    slam: SlamSettings = Field(default_factory=SlamSettings)
    # None: `robot_id` alone (trajectory.tum). A list, or "*" for every robot that sends TagPoses: one
    # graph and one tag map for all, a trajectory per robot (trajectory_<robot>.tum).
    robots: ServedRobots = None
    tag_map: Path | None = None  # anchor world pose, and all poses in localisation-only mode
    map_publish_every: int = Field(default=30, ge=1)  # frames; plus whenever a tag is added
    checkpoint_period_secs: float = Field(default=5.0, gt=0)  # map + trajectory written atomically this often
    max_pending_map_queries: int = Field(default=4, ge=1)  # more are refused (reply_err), counted
    resume: bool = True  # start from run_dir's map.json / trajectory.tum when a previous slam left them
    # Multiplies every published pose covariance (CameraPose.covariance_world). The graph's marginal is
    # deliberately pessimistic (docs/slam.md, *Pose covariance*): an EKF that wants it calibrated sets the
    # factor a run with ground truth measures (summary.json's slam_covariance_scale_measured).
    covariance_scale: float = Field(default=1.0, gt=0, le=1000, allow_inf_nan=False)
