"""Settings of robot_infer."""

from __future__ import annotations

from pathlib import Path
from typing import ClassVar

from pydantic import Field, model_validator
from pydantic_settings import SettingsConfigDict

from shared.model.precision import PrecisionChoice
from shared.model.views import Views
from shared.runtime.settings import ServiceSettings
from shared.transport.access import DATA_KEYS
from shared.vision.proposals import Stage1Settings
from shared.vision.tracking import TrackingSettings
from shared.wire.cuts import CodecName
from shared.wire.messages import MAX_CAPTURE_AHEAD_SECS, PerCut

FRAME_KEYS = DATA_KEYS["frame"]  # every robot's, every version


class RobotInferSettings(ServiceSettings):
    """The robot side of the split."""

    SERVICE: ClassVar[str] = "robot_infer"
    model_config = SettingsConfigDict(**{**ServiceSettings.model_config, "env_prefix": "SPLITTAG_ROBOT_INFER_"})

    weights: Path = Path("models")  # model folder (config.json, weights, the int8 variant)
    # Fit each tag's 16 points to the network's keypoints and stage 1's corners, weighted by the
    # sigmas calibrated into the weights' config.json (no calibration there: the network's points).
    fuse_corners: bool = True
    split_k: int = Field(default=7, ge=0, le=7)  # start-up cut: 0 = the edge runs the whole network, 7 = the robot does
    codec: CodecName = "fp16"  # how the split tensor travels at cuts 1..6
    # Stage 1: AprilTag 3 (stage1.apriltag: quad_decimate, ...) and two proposers for the tags it misses
    # (stage1.aruco: OpenCV's ArUco on tag36h11, gated by a soft decode; stage1.lines: quads from
    # straight edges, for borders an occluder interrupts; .enabled = false drops either)
    stage1: Stage1Settings = Field(default_factory=Stage1Settings)
    # Track-then-refine for tags stage 1 missed (shared/vision/tracking.py; off by default, see docs/tracking.md)
    tracking: TrackingSettings = Field(default_factory=TrackingSettings)
    # auto (int8 if the folder has it, else bf16 where the CPU has it in hardware, else fp32) | fp32 | bf16
    # (PyTorch) | int8 (OpenVINO, the weights folder's int8 variant: splittag quantize)
    precision: PrecisionChoice = "auto"
    threads: int = Field(default=1, ge=1)  # torch / OpenVINO threads for the network
    # Test-time views (shared/model/views.py): where this side runs the whole network (k = 7, and on
    # board without the edge), each ROI also goes through 1, 3 or 7 of its flips and turns and the
    # keypoints are averaged (docs/network.md, *Test-time views*: synth7 int8 e_px 0.419 -> 0.383 / 0.372 /
    # 0.360 with 2 / 4 / 8 views) for 2x / 4x / 8x that network time.
    # Where the network is split (cuts 1..6) it runs once per ROI whatever this says.
    views: Views = 1
    # Stage 1 of the next frame on a thread of its own while the network runs on this one, whenever
    # that frame can be sent as soon as it is made (a credit free, the edge keeping up): the robot's
    # frame time becomes max(stage 1, head) instead of their sum. Not with tracking (its prediction
    # needs the frame before's network output) nor when emulating another CPU (gamma != 1 or
    # emulated_ms_per_tag_by_k: the padding assumes one thread). The robot then uses two cores.
    overlap_stage1: bool = True
    # When the robot is about to take a camera frame and the next one is due within this fraction of
    # the camera's interval (measured from the frames' arrivals), it waits for that one instead: the
    # frame it then takes is fresh rather than most of an interval old. The robot's time per frame grows
    # by f^2/2 of an interval on average and the frames' median age at pickup falls from 1/2 of one to
    # 1/2 - f. The default 0.5 waits exactly when the next frame comes sooner than the one waiting is
    # old (docs/pipeline.md, *Fresh frames*). 0 = always take the newest frame at once.
    fresh_frame_fraction: float = Field(default=0.5, ge=0.0, lt=1.0)
    max_in_flight: int = Field(default=2, ge=0)  # frames sent without TagPoses back yet; 0 = no limit
    # With the pacer on, the window grows up to this many when a credit's cycle (the robot's compute of
    # a frame, then its time in flight) spans more of the chain's periods (its slowest stage, or the
    # camera) than max_in_flight: an uplink's floor would otherwise set the frame rate
    # (flow.credits_needed). Unset: 6, or max_in_flight when that is set alone (a window asked for stays
    # that window); = max_in_flight: a fixed window.
    in_flight_limit: int = Field(default=6, ge=1)
    # Start each frame when it would reach the edge as the edge becomes free (shared.transport.flow.EdgePacer).
    pace_to_edge: bool = True
    # Start each frame when it would reach the uplink as the frame ahead has crossed it: the pacer models the
    # link as a queue (shared.transport.flow.UplinkQueue, from the answers' link stamps) instead of a delay.
    pace_to_link: bool = True
    # The pacer starts each frame this many mean absolute deviations of the robot's compute time earlier
    # than its mean alone says: a frame whose stage 1 runs long then still reaches an edge-bound chain's
    # edge before it frees (EdgePacer); the price is that much wait at the edge, or on a link-bound
    # chain's uplink. 0 = aim at the mean (the edge idles by every overrun).
    pace_margin_spreads: float = Field(default=1.0, ge=0.0, allow_inf_nan=False)
    in_flight_timeout_secs: float = Field(default=2.0, gt=0)  # a frame never answered returns its credit
    # A frame captured further ahead of this host's clock is refused (a camera's clock set wrong): slam
    # refuses its poses anyway, and its latencies read negative on the way there.
    max_capture_ahead_secs: float = Field(default=MAX_CAPTURE_AHEAD_SECS, gt=0)
    profile_period_secs: float = Field(default=1.0, gt=0)  # ComputeProfile C(k) publication period
    # Without the edge (its liveliness token gone, or an answer this late) the robot runs the whole
    # chain on board (k = 7 + PnP) and publishes TagPoses itself; back to the split when the edge is
    # (its token back, or, after a late answer, an answer within this time again: one frame per this
    # time goes to it to find out).
    edge_answer_timeout_secs: float = Field(default=1.5, gt=0)
    tag_map: Path | None = None  # sizes for on-board PnP (as edge_infer's); unknown ids: default_tag_size_m
    default_tag_size_m: float = Field(default=0.2, gt=0)  # black square's side for ids the tag map does not list
    # Emulating another robot CPU. The robot's compute is gamma times a reference: this CPU's own
    # (calibrated at start-up and measured live) or, when set, a fixed per-tag head time at every cut
    # (ms, cumulative up to k), which makes C(k) independent of the CPU the service runs on. Frames
    # are padded by sleeping up to the target; a CPU cannot be made faster, so gamma < 1 needs the
    # fixed reference, and a frame whose real compute exceeds its target takes the real time.
    gamma: float = Field(default=1.0, gt=0)
    emulated_ms_per_tag_by_k: PerCut | None = None  # fixed per-tag head time per cut (8 values, ms), see gamma
    # Where robot_infer's session is a router (every deploy config: the camera joins it), the camera's
    # frames stop there: its router forwards them to no other process, whoever subscribes (an edge-side
    # tool on `splittag/<robot>/**` once pulled every frame over the uplink and, the camera publishing
    # with congestion control BLOCK, took the pipeline from 15 fps to 2). true: frames go to any
    # subscriber, on the robot or across the link (recording raw frames at the edge).
    frames_leave_robot: bool = False

    @model_validator(mode="after")
    def _faster_needs_a_reference(self) -> RobotInferSettings:
        if self.gamma < 1.0 and self.emulated_ms_per_tag_by_k is None:
            raise ValueError(
                f"gamma {self.gamma} < 1 would make the robot faster than this CPU: "
                "set emulated_ms_per_tag_by_k (a fixed reference profile) to emulate a faster robot"
            )
        return self

    @model_validator(mode="after")
    def _window_limits(self) -> RobotInferSettings:
        if "in_flight_limit" not in self.model_fields_set:
            given = "max_in_flight" in self.model_fields_set
            self.in_flight_limit = max(1, self.max_in_flight) if given else max(6, self.max_in_flight)
        if self.max_in_flight and self.in_flight_limit < self.max_in_flight:
            raise ValueError(f"in_flight_limit {self.in_flight_limit} < max_in_flight {self.max_in_flight}")
        return self

    @model_validator(mode="after")
    def _frames_stay_on_the_router(self) -> RobotInferSettings:
        if self.frames_leave_robot and FRAME_KEYS in self.zenoh.keep_local:
            raise ValueError(f"frames_leave_robot = true, but zenoh.keep_local keeps {FRAME_KEYS} on the robot")
        if not self.frames_leave_robot and self.zenoh.mode == "router" and FRAME_KEYS not in self.zenoh.keep_local:
            self.zenoh = self.zenoh.model_copy(update={"keep_local": [*self.zenoh.keep_local, FRAME_KEYS]})
        return self
