"""Settings of edge_infer."""

from __future__ import annotations

from pathlib import Path
from typing import ClassVar

from pydantic import Field, model_validator
from pydantic_settings import SettingsConfigDict

from shared.model.precision import PrecisionChoice
from shared.model.views import Views
from shared.runtime.settings import ServedRobots, ServiceSettings
from shared.wire.messages import MAX_CAPTURE_AHEAD_SECS, PerCut, RobotId


class EdgeInferSettings(ServiceSettings):
    """The edge side of the split: one worker of the edge tier, serving one robot or many."""

    SERVICE: ClassVar[str] = "edge_infer"
    model_config = SettingsConfigDict(**{**ServiceSettings.model_config, "env_prefix": "SPLITTAG_EDGE_INFER_"})

    weights: Path = Path("models")  # model folder (config.json, weights, the int8 variant)
    # Which robots this edge tier serves: None = `robot_id` alone; a list = those robots; "*" = every
    # robot whose robot_infer is alive (its liveliness token). Several workers with the same setting
    # share the robots by rendezvous hashing over the workers' tokens (shared.transport.fleet): a
    # worker that appears takes its share, one that dies hands its robots to the others.
    robots: ServedRobots = None
    worker_id: RobotId = "edge1"  # unique in the edge tier (its liveliness token)
    # The workers that share robots: the same tier name and the same `robots` on each. None: the robot id
    # for a single-robot edge (so two robots' own edges on one network never take each other's robot),
    # "fleet" otherwise.
    tier: RobotId | None = None
    # Features of several robots that are waiting together go through one tail pass (per cut k).
    batch_max_messages: int = Field(default=8, ge=1)
    # Per-robot tag maps (robot id -> file), over `tag_map` for that robot.
    tag_maps: dict[RobotId, Path] = Field(default_factory=dict)
    # Fit each tag's 16 points to the network's keypoints and stage 1's corners, weighted by the
    # sigmas calibrated into the weights' config.json (no calibration there: the network's points).
    fuse_corners: bool = True
    # A tracked tag (robot_infer's tracking) whose 16 keypoints fit a plane worse than this (RMS px) gets no pose.
    tracked_max_reprojection_px: float = Field(default=1.0, gt=0)
    tag_map: Path | None = None  # YAML/JSON with per-tag sizes; unknown ids use default_tag_size_m
    default_tag_size_m: float = Field(default=0.2, gt=0)  # black square's side for ids the tag map does not list
    # auto | fp32 | bf16 | int8: as robot_infer's (shared.model.precision says what auto picks)
    precision: PrecisionChoice = "auto"
    threads: int = Field(default=1, ge=1)  # torch / OpenVINO threads for the network
    # Test-time views (shared/model/views.py): where this side runs the whole network (k = 0), each
    # ROI also goes through 1, 3 or 7 of its flips and turns and the keypoints are averaged (docs/network.md,
    # *Test-time views*: synth7 int8 e_px 0.419 -> 0.383 / 0.372 / 0.360 with 2 / 4 / 8 views) for
    # 2x / 4x / 8x that network time.
    # Where the network is split (cuts 1..6) it runs once per ROI whatever this says.
    views: Views = 1
    serve_echo: bool = True  # the link-probe echo queryable lives on the edge
    # Features captured further ahead of this host's clock are refused, as robot_infer refuses such frames
    # (a robot sending Features of its own with its clock set wrong, or a made-up message): slam refuses
    # their poses anyway, and their latencies read negative in the run's records.
    max_capture_ahead_secs: float = Field(default=MAX_CAPTURE_AHEAD_SECS, gt=0)
    queue_depth: int = Field(default=2, ge=1)  # Features waiting for the edge; small = bounded latency
    profile_period_secs: float = Field(default=1.0, gt=0)  # ComputeProfile E(k) publication period
    # Emulating another edge CPU: a fixed per-tag tail time (PnP included) at every cut, ms. Frames are
    # padded by sleeping up to it and E(k) is published from it, independent of this CPU; a frame
    # whose real compute exceeds it takes the real time. None: calibrated and measured live.
    emulated_ms_per_tag_by_k: PerCut | None = None  # fixed per-tag tail time per cut (8 values, ms), padded by sleeping

    @model_validator(mode="after")
    def _tag_maps_of_served_robots(self) -> EdgeInferSettings:
        served = [self.robot_id] if self.robots is None else self.robots
        unknown = sorted(set(self.tag_maps) - set(served)) if served != "*" else []
        if unknown:
            raise ValueError(f"tag_maps for robots this edge does not serve: {unknown} (robots: {served})")
        return self
