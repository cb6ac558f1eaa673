"""Versioned message schemas that travel over Zenoh, and their encode/decode functions.

Every message is a frozen pydantic model with a schema id `splittag/<Name>/v<N>`. `encode` writes framing
3 (a positional msgpack header checked natively, arrays out of band: `shared.wire.positional`); framing 2
(the envelope `{"schema": id, "body": {...}}` as a named header) and framing 1 (plain msgpack) are still
read and written on request (`shared.wire.codec`). Decoding checks, in order: size limit, framing,
header, schema id and version, array framing, then the model's own field checks (dtypes, shapes,
ranges, finiteness of every array but the split tensor, whose values the edge checks through its
keypoints). Any failure is a `WireError` subclass whose message says what was received; nothing is
defaulted silently. `decode` returns the model; `decode_view` makes the same checks and returns a
`View` of the fields without building the model, for hot-path readers of a few fields.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Annotated, Any, ClassVar, Final, Generic, Literal, Self, TypeAlias, TypeVar, cast, get_args

import numpy as np
from numpy.typing import NDArray
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    GetCoreSchemaHandler,
    ValidationError,
    model_validator,
)
from pydantic_core import core_schema

from shared.vision.camera import CameraIntrinsics
from shared.vision.proposers import Proposer
from shared.wire.codec import (
    DEFAULT_MAX_BYTES,
    FRAME_MAGIC,
    FRAMING,
    WIRE_DTYPES,
    ArrayError,
    MalformedFrame,
    SchemaError,
    pack,
    pack_framing1,
    unpack,
    wire_dtype_name,
)
from shared.wire.cuts import N_CUTS, CodecName
from shared.wire.positional import FRAMING3, PositionalCodec, UnknownSchema, flat, wire_safe

# ----------------------------------------------------------------------------------------------
# Array fields
# ----------------------------------------------------------------------------------------------


def _all_finite(value: np.ndarray) -> bool:
    if value.size <= 16:  # 3x3, 4x4, 4x2: Python floats beat a numpy call
        return all(map(math.isfinite, value.ravel().tolist()))
    if value.dtype.itemsize == 2:
        # float16: an all-ones exponent is inf or NaN; integer bit test is ~2.5x faster than isfinite.
        return not bool(((value.view(np.uint16) & 0x7C00) == 0x7C00).any())
    return bool(np.isfinite(value).all())


@dataclass(frozen=True)
class ArraySpec:
    """Pydantic metadata that validates an ndarray field: allowed dtypes, shape, finiteness.

    `finite=False` for the split tensor: a feature map can be megabytes, and checking it would make
    decoding O(tensor) instead of O(header); a non-finite tensor is caught where it matters, by the
    edge refusing non-finite keypoints (shared.perception.split)."""

    dtypes: tuple[str, ...]
    shape: tuple[int | None, ...] | None = None  # None entries match any size
    ndims: tuple[int, ...] | None = None  # alternative to `shape` when only ndim is fixed
    finite: bool = True
    _numpy: frozenset[np.dtype[Any]] = field(default=frozenset(), init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_numpy", frozenset(WIRE_DTYPES[d] for d in self.dtypes))

    def validate(self, value: Any) -> np.ndarray:
        if not isinstance(value, np.ndarray):
            raise ValueError(f"expected an ndarray, got {type(value).__name__}")
        if value.dtype not in self._numpy:  # fast path: the little-endian wire dtypes
            try:
                name = wire_dtype_name(value.dtype)
            except ArrayError as exc:
                raise ValueError(str(exc)) from exc
            if name not in self.dtypes:
                raise ValueError(f"dtype {name} not allowed here (allowed: {', '.join(self.dtypes)})")
        self.check_shape(value.shape)
        if self.finite and value.dtype.kind == "f" and not _all_finite(value):
            bad = int(np.size(value) - np.count_nonzero(np.isfinite(value)))
            raise ValueError(f"{bad} non-finite values (NaN or inf) in a {wire_dtype_name(value.dtype)} array")
        return value

    def check_shape(self, shape: tuple[int, ...]) -> None:
        """ValueError unless an array of this shape may travel in the field (an ndarray's shape, or a wire
        reference's before any array is made)."""
        if self.shape is not None and (
            len(shape) != len(self.shape)
            or any(w is not None and w != got for w, got in zip(self.shape, shape, strict=True))
        ):
            want = tuple("*" if w is None else w for w in self.shape)
            raise ValueError(f"shape {shape} does not match {want}")
        if self.ndims is not None and len(shape) not in self.ndims:
            raise ValueError(f"ndim {len(shape)} not in {self.ndims} (shape {shape})")

    def __get_pydantic_core_schema__(self, source: Any, handler: GetCoreSchemaHandler) -> core_schema.CoreSchema:
        return core_schema.no_info_plain_validator_function(
            self.validate,
            serialization=core_schema.plain_serializer_function_ser_schema(lambda v: v),
        )


# CameraIntrinsics (shared.vision, a layer below this one) is also a wire type; its one after-validator
# reads len(distortion), the same on a wire struct: decode_view may run it there.
wire_safe(CameraIntrinsics.__pydantic_decorators__.model_validators["_distortion_opencv_can_use"].func)

F32 = ("float32",)
F64 = ("float64",)
Image8 = Annotated[NDArray[np.uint8], ArraySpec(("uint8",), shape=(None, None))]
Points2D = Annotated[NDArray[np.float32], ArraySpec(F32, shape=(None, 2))]
Corners = Annotated[NDArray[np.float32], ArraySpec(F32, shape=(4, 2))]
Keypoints16 = Annotated[NDArray[np.float32], ArraySpec(F32, shape=(16, 2))]
Homography = Annotated[NDArray[np.float64], ArraySpec(F64, shape=(3, 3))]
Pose4x4 = Annotated[NDArray[np.float64], ArraySpec(F64, shape=(4, 4))]
Covariance6 = Annotated[NDArray[np.float64], ArraySpec(F64, shape=(6, 6))]
# Split tensors: ROI pixels (k=0, uint8), feature maps (k=1..5), pooled/keypoints (k=6,7).
SplitTensor = Annotated[NDArray[Any], ArraySpec(("float16", "float32", "uint8", "int8"), ndims=(1, 2, 3), finite=False)]

FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
NonNegFloat = Annotated[float, Field(ge=0.0, allow_inf_nan=False)]
RobotId = Annotated[str, Field(pattern=r"^[A-Za-z0-9_\-]{1,64}$")]
SplitIndex = Annotated[int, Field(ge=0, le=N_CUTS - 1)]


class WireModel(BaseModel):
    """Base for everything inside a message: frozen, strict, no unknown fields."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True, arbitrary_types_allowed=True)


class Message(WireModel):
    """A top-level message with a versioned schema id."""

    SCHEMA: ClassVar[str]


class FrameMessage(Message):
    """A message about one camera frame: whose, which one, when it was captured (these fields first)."""

    robot_id: RobotId
    seq: int = Field(ge=0)
    capture_nanos: int = Field(ge=0)


# ----------------------------------------------------------------------------------------------
# Schemas
# ----------------------------------------------------------------------------------------------


class Frame(FrameMessage):
    """One mono8 camera image with its intrinsics and capture time."""

    SCHEMA: ClassVar[str] = "splittag/Frame/v1"
    intrinsics: CameraIntrinsics
    image: Image8

    @model_validator(mode="after")
    @wire_safe
    def _image_matches_intrinsics(self) -> Frame:
        h, w = self.image.shape
        if (w, h) != (self.intrinsics.width, self.intrinsics.height):
            raise ValueError(f"image is {w}x{h} but intrinsics say {self.intrinsics.width}x{self.intrinsics.height}")
        return self


class TagFeatureV1(WireModel):
    """One detected tag's stage-1 result and the split tensor computed from its ROI (Features v1)."""

    tag_id: int = Field(ge=0)
    decision_margin: FiniteFloat
    hamming: int = Field(ge=0)
    corners_px: Corners
    roi_to_image: Homography
    tensor: SplitTensor

    @model_validator(mode="after")
    @wire_safe
    def _homography_invertible(self) -> Self:
        m = flat(self.roi_to_image)  # 3x3 floats: Python beats numpy here
        a, b, c, d, e, f, g, h, i = m
        scale = max(abs(a), abs(b), abs(c), abs(d), abs(e), abs(f), abs(g), abs(h), abs(i))
        if scale == 0:
            raise ValueError("roi_to_image is not an invertible homography")
        if not 1e-90 < scale < 1e90:
            # scale first: cubing a huge entry (a finite 1e200) would overflow; divide (1 / a subnormal
            # scale would be inf, and an inf determinant passes any threshold)
            a, b, c, d, e, f, g, h, i = (v / scale for v in m)
            scale = 1.0
        det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
        if abs(det) < 1e-12 * (scale * scale * scale):  # relative to scale**3, which cannot overflow here
            raise ValueError("roi_to_image is not an invertible homography")
        return self


class TagFeatureV2(TagFeatureV1):
    """TagFeatureV1 plus how blurred the tag's border is in the image (shared.vision.fusion.edge_width_px,
    image pixels; None when the robot could not measure it): keypoint fusion weighs by it."""

    edge_width_px: float | None = Field(ge=0, le=1000, allow_inf_nan=False)


class TagFeatureV3(TagFeatureV2):
    """TagFeatureV2 plus whether stage 1 decoded the tag (False) or the tracker carried it from earlier
    frames and the soft decode accepted it (True: its corners are a prediction, not a detection)."""

    tracked: bool


def _check_proposer(tracked: bool, proposer: str | None) -> None:
    if proposer is not None and tracked != (proposer == "tracker"):
        raise ValueError(f"tracked={tracked} but proposer={proposer!r}: tracked tags are the tracker's")


class TagFeature(TagFeatureV3):
    """TagFeatureV3 plus who found the tag (`shared.vision.detector.Proposer`; "tracker" exactly when
    tracked; None in messages upgraded from v3 and older): slam weighs blind soft reads apart."""

    proposer: Proposer | None = None

    @model_validator(mode="after")
    @wire_safe
    def _proposer_agrees(self) -> Self:
        _check_proposer(self.tracked, self.proposer)
        return self


class Features(FrameMessage):
    """Everything robot_infer computed for one frame at split k (possibly zero tags)."""

    SCHEMA: ClassVar[str] = "splittag/Features/v4"
    publish_nanos: int = Field(ge=0)
    split_k: SplitIndex
    codec: CodecName
    intrinsics: CameraIntrinsics
    robot_compute_secs: NonNegFloat
    tags: list[TagFeature]


class FeaturesV3(FrameMessage):
    """Features before the proposer; still decoded (as v4 with proposer None)."""

    SCHEMA: ClassVar[str] = "splittag/Features/v3"
    publish_nanos: int = Field(ge=0)
    split_k: SplitIndex
    codec: CodecName
    intrinsics: CameraIntrinsics
    robot_compute_secs: NonNegFloat
    tags: list[TagFeatureV3]

    def upgrade(self) -> Features:
        """The same content as the current schema."""
        fields = {name: getattr(self, name) for name in FeaturesV3.model_fields if name != "tags"}
        return Features(**fields, tags=[TagFeature(**dict(t), proposer=None) for t in self.tags])


class FeaturesV2(FrameMessage):
    """Features before tracking; still decoded (as v3 with every tag detected, tracked False)."""

    SCHEMA: ClassVar[str] = "splittag/Features/v2"
    publish_nanos: int = Field(ge=0)
    split_k: SplitIndex
    codec: CodecName
    intrinsics: CameraIntrinsics
    robot_compute_secs: NonNegFloat
    tags: list[TagFeatureV2]

    def upgrade(self) -> Features:
        """The same content as the current schema."""
        fields = {name: getattr(self, name) for name in FeaturesV2.model_fields if name != "tags"}
        return Features(**fields, tags=[TagFeature(**dict(t), tracked=False, proposer=None) for t in self.tags])


class FeaturesV1(FrameMessage):
    """Features before the edge width; still decoded (as v3 with edge_width_px None, tracked False)."""

    SCHEMA: ClassVar[str] = "splittag/Features/v1"
    publish_nanos: int = Field(ge=0)
    split_k: SplitIndex
    codec: CodecName
    intrinsics: CameraIntrinsics
    robot_compute_secs: NonNegFloat
    tags: list[TagFeatureV1]

    def upgrade(self) -> Features:
        """The same content as the current schema."""
        fields = {name: getattr(self, name) for name in FeaturesV1.model_fields if name != "tags"}
        tags = [TagFeature(**dict(t), edge_width_px=None, tracked=False, proposer=None) for t in self.tags]
        return Features(**fields, tags=tags)


class HopTimings(WireModel):
    """Per-hop latency of one frame, seconds."""

    robot_compute_secs: NonNegFloat
    transport_secs: FiniteFloat  # may be slightly negative across hosts with imperfect clocks
    edge_compute_secs: NonNegFloat
    capture_to_pose_secs: FiniteFloat


class TagPoseV2(WireModel):
    """One tag's keypoints and pose; both PnP branches are kept for the SLAM ambiguity guard."""

    tag_id: int = Field(ge=0)
    tag_size_m: float = Field(ge=1e-3, le=10.0, allow_inf_nan=False)  # 1 mm .. 10 m
    keypoints_px: Keypoints16
    corners_px: Corners
    camera_from_tag: Pose4x4
    reprojection_error_px: NonNegFloat
    alt_camera_from_tag: Pose4x4
    alt_reprojection_error_px: NonNegFloat


class TagPoseV3(TagPoseV2):
    """TagPoseV2 plus whether the tag was detected by stage 1 (False) or tracked (True; see TagFeature)."""

    tracked: bool


class TagPose(TagPoseV3):
    """TagPoseV3 plus who found the tag (as TagFeature.proposer; None in messages upgraded from v3)."""

    proposer: Proposer | None = None

    @model_validator(mode="after")
    @wire_safe
    def _proposer_agrees(self) -> Self:
        _check_proposer(self.tracked, self.proposer)
        return self


class LinkStamps(WireModel):
    """How one message crossed the uplink: sent on the sender's clock, received on the receiver's,
    and when the message just ahead of it on the same link was received (0: none since the receiver
    started). With these the link estimator tells the link's own time from waiting behind others."""

    sent_nanos: int = Field(ge=0)
    received_nanos: int = Field(ge=0)
    previous_received_nanos: int = Field(ge=0)


class TagPoses(FrameMessage):
    """Edge output for one frame: the tags' poses, the frame's per-hop timings, its link stamps and the
    camera intrinsics the poses were solved with (both None only in messages upgraded from v1)."""

    SCHEMA: ClassVar[str] = "splittag/TagPoses/v4"
    split_k: SplitIndex
    payload_bytes: int = Field(ge=0)
    timings: HopTimings
    link: LinkStamps | None
    intrinsics: CameraIntrinsics | None
    tags: list[TagPose]


class TagPosesV3(FrameMessage):
    """TagPoses before the proposer; still decoded (as v4 with proposer None)."""

    SCHEMA: ClassVar[str] = "splittag/TagPoses/v3"
    split_k: SplitIndex
    payload_bytes: int = Field(ge=0)
    timings: HopTimings
    link: LinkStamps | None
    intrinsics: CameraIntrinsics | None
    tags: list[TagPoseV3]

    def upgrade(self) -> TagPoses:
        """The same content as the current schema."""
        fields = {name: getattr(self, name) for name in TagPosesV3.model_fields if name != "tags"}
        return TagPoses(**fields, tags=[TagPose(**dict(t), proposer=None) for t in self.tags])


class TagPosesV2(FrameMessage):
    """TagPoses before tracking; still decoded (as v3 with every tag detected, tracked False)."""

    SCHEMA: ClassVar[str] = "splittag/TagPoses/v2"
    split_k: SplitIndex
    payload_bytes: int = Field(ge=0)
    timings: HopTimings
    link: LinkStamps | None
    intrinsics: CameraIntrinsics | None
    tags: list[TagPoseV2]

    def upgrade(self) -> TagPoses:
        """The same content as the current schema."""
        fields = {name: getattr(self, name) for name in TagPosesV2.model_fields if name != "tags"}
        return TagPoses(**fields, tags=[TagPose(**dict(t), tracked=False, proposer=None) for t in self.tags])


class TagPosesV1(FrameMessage):
    """TagPoses before the link stamps; still decoded (as a v3 TagPoses with link and intrinsics None,
    every tag detected)."""

    SCHEMA: ClassVar[str] = "splittag/TagPoses/v1"
    split_k: SplitIndex
    payload_bytes: int = Field(ge=0)
    timings: HopTimings
    tags: list[TagPoseV2]

    def upgrade(self) -> TagPoses:
        """The same content as the current schema."""
        fields = {name: getattr(self, name) for name in TagPosesV1.model_fields if name != "tags"}
        tags = [TagPose(**dict(t), tracked=False, proposer=None) for t in self.tags]
        return TagPoses(**fields, link=None, intrinsics=None, tags=tags)


class CameraPose(FrameMessage):
    """SLAM (or ground-truth) camera pose for one frame. "bridged": slam has a pose, but in a map
    fragment begun after a long gap without tags, not yet tied to the world (its placement is a guess
    until a view shared with the world's tags joins them); "lost": no pose (the last one is repeated).
    `covariance_world`: how sure slam is of the pose, 6x6, position (m) then rotation (rad) about the
    world's axes (ROS PoseWithCovariance's order), the factor graph's marginal with everything fused up
    to this frame; None for ground truth, "lost" and older peers. It follows the observation noise
    model, which is deliberately pessimistic (docs/slam.md, *Pose covariance*)."""

    SCHEMA: ClassVar[str] = "splittag/CameraPose/v3"
    world_from_camera: Pose4x4
    status: Literal["tracking", "bridged", "lost", "ground_truth"]
    tags_used: int = Field(ge=0)
    covariance_world: Covariance6 | None = None

    @model_validator(mode="after")
    @wire_safe
    def _covariance_is_one(self) -> Self:
        c = self.covariance_world
        if c is not None:
            c = np.asarray(c, np.float64).reshape(6, 6)  # the wire struct's is a flat tuple
            if not np.allclose(c, c.T, rtol=0, atol=1e-9 * max(1e-300, float(np.abs(c).max()))):
                raise ValueError("covariance_world is not symmetric")
            if float(np.diag(c).min()) < 0:
                raise ValueError("covariance_world has a negative variance")
        return self


class CameraPoseV2(FrameMessage):
    """CameraPose before the covariance; still decoded (as v3 with covariance_world None)."""

    SCHEMA: ClassVar[str] = "splittag/CameraPose/v2"
    world_from_camera: Pose4x4
    status: Literal["tracking", "bridged", "lost", "ground_truth"]
    tags_used: int = Field(ge=0)

    def upgrade(self) -> CameraPose:
        """The same content as the current schema."""
        return CameraPose(**{name: getattr(self, name) for name in CameraPoseV2.model_fields})


class CameraPoseV1(FrameMessage):
    """CameraPose before "bridged"; still decoded (as v3: every v1 status is a v3 status; no covariance)."""

    SCHEMA: ClassVar[str] = "splittag/CameraPose/v1"
    world_from_camera: Pose4x4
    status: Literal["tracking", "lost", "ground_truth"]
    tags_used: int = Field(ge=0)

    def upgrade(self) -> CameraPose:
        """The same content as the current schema."""
        return CameraPose(**{name: getattr(self, name) for name in CameraPoseV1.model_fields})


class FrameStamp(FrameMessage):
    """The time a data set gives a frame (TUM `rgb.txt`): camera -> slam, which writes trajectory.tum in
    the data set's own time. `capture_nanos` stays the live clock every latency is measured on."""

    SCHEMA: ClassVar[str] = "splittag/FrameStamp/v1"
    source_stamp_nanos: int = Field(ge=0)


class MapTagV1(WireModel):
    """One tag in the map (TagMap v1)."""

    tag_id: int = Field(ge=0)
    size_m: float = Field(gt=0, allow_inf_nan=False)
    world_from_tag: Pose4x4
    observations: int = Field(ge=0)


class MapTagV2(MapTagV1):
    """MapTagV1 plus whether the tag lies in a map fragment not (yet) tied to the world: mapped after a
    long gap without tags, its world pose is the gap's guess (see CameraPose "bridged")."""

    bridged: bool


class MapTag(MapTagV2):
    """MapTagV2 plus how well slam knows the pose (its marginal's largest axis, 1 sigma, in the tag's
    frame; as a tag map file states it): None for the anchor (it defines the world), bridged tags and
    older peers."""

    position_sigma_m: float | None = Field(default=None, gt=0, le=100, allow_inf_nan=False)
    rotation_sigma_deg: float | None = Field(default=None, gt=0, le=180, allow_inf_nan=False)


class TagMap(Message):
    """The SLAM map: tag poses in the world frame anchored at `anchor_tag_id`."""

    SCHEMA: ClassVar[str] = "splittag/TagMap/v3"
    robot_id: RobotId
    revision: int = Field(ge=0)
    anchor_tag_id: int = Field(ge=0)
    tags: list[MapTag]


class TagMapV2(Message):
    """TagMap before the per-tag uncertainty; still decoded (as v3 with no sigmas)."""

    SCHEMA: ClassVar[str] = "splittag/TagMap/v2"
    robot_id: RobotId
    revision: int = Field(ge=0)
    anchor_tag_id: int = Field(ge=0)
    tags: list[MapTagV2]

    def upgrade(self) -> TagMap:
        """The same content as the current schema."""
        fields = {name: getattr(self, name) for name in TagMapV2.model_fields if name != "tags"}
        return TagMap(**fields, tags=[MapTag(**dict(t)) for t in self.tags])


class TagMapV1(Message):
    """TagMap before `bridged`; still decoded (as v3 with every tag tied to the world, no sigmas)."""

    SCHEMA: ClassVar[str] = "splittag/TagMap/v1"
    robot_id: RobotId
    revision: int = Field(ge=0)
    anchor_tag_id: int = Field(ge=0)
    tags: list[MapTagV1]

    def upgrade(self) -> TagMap:
        """The same content as the current schema."""
        fields = {name: getattr(self, name) for name in TagMapV1.model_fields if name != "tags"}
        return TagMap(**fields, tags=[MapTag(**dict(t), bridged=False) for t in self.tags])


class SplitConfig(Message):
    """Where the CNN is cut (k in 0..7) and how the tensor is encoded."""

    SCHEMA: ClassVar[str] = "splittag/SplitConfig/v1"
    k: SplitIndex
    codec: CodecName
    pinned: bool  # True when a person set k; the controller leaves it alone until released
    source: Literal["default", "user", "controller"]


class ProbeAck(Message):
    """The edge echo's tiny reply to a link probe (so the probe loads only the uplink), with the
    probe's link stamps (None only in messages upgraded from v1)."""

    SCHEMA: ClassVar[str] = "splittag/ProbeAck/v2"
    received_bytes: int = Field(ge=0)
    decoded_ok: bool
    error: str
    link: LinkStamps | None


class ProbeAckV1(Message):
    """ProbeAck before the link stamps; still decoded (as a v2 ProbeAck with link None)."""

    SCHEMA: ClassVar[str] = "splittag/ProbeAck/v1"
    received_bytes: int = Field(ge=0)
    decoded_ok: bool
    error: str

    def upgrade(self) -> ProbeAck:
        """The same content as the current schema."""
        return ProbeAck(**{name: getattr(self, name) for name in ProbeAckV1.model_fields}, link=None)


class FrameSent(Message):
    """robot_infer put one Features message on the uplink (tiny, robot-local: lets the controller
    keep its probes out of a busy link)."""

    SCHEMA: ClassVar[str] = "splittag/FrameSent/v1"
    robot_id: RobotId
    seq: int = Field(ge=0)
    sent_nanos: int = Field(ge=0)
    payload_bytes: int = Field(ge=0)


PerCut = Annotated[list[NonNegFloat], Field(min_length=N_CUTS, max_length=N_CUTS)]
MaybePerCut = Annotated[list[NonNegFloat | None], Field(min_length=N_CUTS, max_length=N_CUTS)]


class _ComputeProfileFields(Message):
    """The fields every version of ComputeProfile has, in wire order (no schema of its own)."""

    robot_id: RobotId
    side: Literal["robot", "edge"]
    stamp_nanos: int = Field(ge=0)
    current_k: SplitIndex
    tags_per_frame: NonNegFloat
    live_scale: NonNegFloat  # live / calibrated time at current_k (1.0 until measured)
    ms_by_k: PerCut


class ComputeProfileV1(_ComputeProfileFields):
    """ComputeProfile before the throughput fields; still decoded (as v2 with both None: a side's period
    is then its ms per frame, and without the camera's rate the controller decides on latency alone).
    Published on the v1 key, which the current controller does not read: recorded bytes decode."""

    SCHEMA: ClassVar[str] = "splittag/ComputeProfile/v1"

    def upgrade(self) -> ComputeProfile:
        """The same content as the current schema."""
        fields = {name: getattr(self, name) for name in ComputeProfileV1.model_fields}
        return ComputeProfile(**fields, period_ms_by_k=None, frame_interval_ms=None)


class ComputeProfile(_ComputeProfileFields):
    """One side's compute estimate for every split point, ms per frame at `tags_per_frame` tags.

    robot: C(k), everything the robot computes when cutting at k (stage 1 + head), gamma included;
    edge: E(k), everything the edge computes (tail + PnP). A start-up calibration per block, scaled by
    the running median of live measurements at the k in use. Published at most once per second.
    `period_ms_by_k`: the time between frames this side needs at each cut when it never waits (its
    throughput limit): `ms_by_k`, or less where parts overlap (the robot's stage 1 of the next frame
    beside this frame's network). `frame_interval_ms`: the camera's interval from its capture stamps and
    frame numbers, as the robot receives its frames (robot only; None where unknown or for the edge).
    """

    SCHEMA: ClassVar[str] = "splittag/ComputeProfile/v2"
    period_ms_by_k: PerCut | None
    frame_interval_ms: NonNegFloat | None


# ControllerState.reason while the controller waits for both sides' ComputeProfiles (its T(k) are zeros then).
CONTROLLER_WAITING: Final[str] = "waiting for the compute profiles of both sides"


class _ControllerStateFields(Message):
    """The fields every version of ControllerState has, in wire order (no schema of its own)."""

    robot_id: RobotId
    stamp_nanos: int = Field(ge=0)
    t0_ms: FiniteFloat
    beta_ms_per_kB: FiniteFloat
    link_samples: int = Field(ge=0)
    link_changes: int = Field(ge=0)
    robot_ms_by_k: PerCut
    edge_ms_by_k: PerCut
    payload_kB_by_k: PerCut
    predicted_ms_by_k: PerCut
    current_k: SplitIndex
    best_k: SplitIndex
    chosen_k: SplitIndex
    pinned: bool
    applied: bool  # True when this decision changed the split through the split query
    reason: str

    @property
    def has_prediction(self) -> bool:
        """predicted_ms_by_k is a prediction: both sides' compute profiles had arrived (before that the
        controller sends zeros there, with the reason CONTROLLER_WAITING)."""
        return not self.reason.startswith(CONTROLLER_WAITING)


class ControllerStateV1(_ControllerStateFields):
    """ControllerState before throughput; still decoded (as v2 with the throughput fields None)."""

    SCHEMA: ClassVar[str] = "splittag/ControllerState/v1"

    def upgrade(self) -> ControllerState:
        """The same content as the current schema."""
        fields = {name: getattr(self, name) for name in ControllerStateV1.model_fields}
        return ControllerState(
            **fields,
            period_ms_by_k=None,
            achieved_ms_by_k=None,
            frame_interval_ms=None,
            frame_share_by_k=None,
            min_frame_share=None,
        )


class ControllerState(_ControllerStateFields):
    """What the adaptive split controller believes, predicts and did (one per decision).

    Throughput (None before both profiles, or where the camera's rate is unknown): `period_ms_by_k` is
    the time between frames each cut needs by the model (the uplink's beta S(k); with
    ControllerTuning.compute_keeps_up the slower side's too), `achieved_ms_by_k` what each cut achieved
    lately between consecutive posed frames (None where it has not run), `frame_interval_ms` the
    camera's, `frame_share_by_k` the share of the camera's frames each cut is expected to pose (by what
    it achieved, else by its period), and a cut keeps up at `min_frame_share` or more: the controller
    chooses among those."""

    SCHEMA: ClassVar[str] = "splittag/ControllerState/v2"
    period_ms_by_k: PerCut | None
    achieved_ms_by_k: MaybePerCut | None
    frame_interval_ms: NonNegFloat | None
    frame_share_by_k: PerCut | None
    min_frame_share: NonNegFloat | None


MESSAGE_TYPES: Final[tuple[type[Message], ...]] = (
    Frame,
    Features,
    TagPoses,
    CameraPose,
    TagMap,
    SplitConfig,
    ProbeAck,
    ComputeProfile,
    ControllerState,
    FrameSent,
    FrameStamp,
)
SCHEMAS: Final[dict[str, type[Message]]] = {m.SCHEMA: m for m in MESSAGE_TYPES}
# Older versions still accepted: each has `upgrade()` to the current message of its name. The union is
# the one list: LEGACY_SCHEMAS is read from it, and its type says every value has `upgrade()`.
LegacyMessage: TypeAlias = (
    TagPosesV1
    | TagPosesV2
    | TagPosesV3
    | ProbeAckV1
    | ComputeProfileV1
    | ControllerStateV1
    | FeaturesV1
    | FeaturesV2
    | FeaturesV3
    | CameraPoseV1
    | CameraPoseV2
    | TagMapV1
    | TagMapV2
)
LEGACY_SCHEMAS: Final[dict[str, type[LegacyMessage]]] = {m.SCHEMA: m for m in get_args(LegacyMessage)}
_CURRENT_BY_NAME: Final[dict[str, type[Message]]] = {m.SCHEMA.rpartition("/")[0]: m for m in MESSAGE_TYPES}
ENVELOPE_KEYS: Final[frozenset[str]] = frozenset({"schema", "body"})

M = TypeVar("M", bound=Message)


# ----------------------------------------------------------------------------------------------
# Encode / decode
# ----------------------------------------------------------------------------------------------


# What `encode` writes: framing 3 (positional header, shared.wire.positional). Framings 1 and 2 are
# still read, and written on request for older peers.
WRITE_FRAMING: Final[int] = FRAMING3


@functools.cache
def positional_codec() -> PositionalCodec:
    """Framing 3's codec, compiled from every message model (once, on first use)."""
    return PositionalCodec(MESSAGE_TYPES, legacy=LEGACY_SCHEMAS.values())


FRAMING1_MAP: Final[int] = 0x82  # msgpack's fixmap of two entries: how every framing 1 message starts


def framing_of(payload: bytes | bytearray | memoryview | None) -> int:
    """The framing a request came in (1, 2 or 3), so a reply can be one the asker reads: an older
    peer's probe or split request gets its answer in its own framing. Unknown or no payload: ours (a
    trial's garbage was answered in framing 1, as if from the oldest peer: only framing 1's two-key map
    {schema, body} reads as framing 1)."""
    if not payload:
        return WRITE_FRAMING
    if payload[0] != FRAME_MAGIC:
        return 1 if payload[0] == FRAMING1_MAP else WRITE_FRAMING
    return payload[1] if len(payload) > 1 and payload[1] in (FRAMING, FRAMING3) else WRITE_FRAMING


def encode(message: Message, *, framing: int = WRITE_FRAMING) -> bytes:
    """Serialise a message to its wire bytes: framing 3 (positional header, tensors out of band), or
    framing 2 (the envelope {schema, body} as a named msgpack header) / 1 (plain msgpack) for older peers."""
    if framing == FRAMING3:
        return positional_codec().pack(message)
    if framing == FRAMING:
        return pack({"schema": message.SCHEMA, "body": message})
    if framing == 1:
        return pack_framing1({"schema": message.SCHEMA, "body": message})
    raise ValueError(f"framing must be 1, {FRAMING} or {FRAMING3}, got {framing!r}")


def encode_values(model: type[Message], *values: Any) -> bytes:
    """Framing 3 bytes of a `model` message given as its field values in declaration order (nested
    messages as sequences of theirs), checked natively by the wire type the receiver parses with (a
    SchemaError names the field), without building the model: for a tiny message made only to be sent
    (the probe echo's ack). Messages with out-of-band arrays or validators: TypeError (use `encode`)."""
    return positional_codec().pack_values(model, values)


def _not_a_message(payload: bytes | bytearray | memoryview, why: str) -> MalformedFrame:
    """A payload that is no splittag message: say how one starts (an integrator's bytes, or a framing 1/2
    error alone, named nothing a sender of framing 3 would recognise: a fresh-clone trial)."""
    if len(payload) >= 1 and (payload[0] == FRAME_MAGIC or payload[0] in (0x82, 0xDE)):
        return MalformedFrame(why)  # a damaged framed message (3 or 2), or framing 1's two-key map
    if len(payload) == 0:
        return MalformedFrame("empty payload: not a splittag message")
    return MalformedFrame(
        f"not a splittag message: it starts with {bytes(payload[:4]).hex(' ')}, not the framing-3 head c1 03 00 00 "
        f"(docs/wire.md), nor does it read as an older framing ({why})"
    )


def decode_for_robot(
    payload: bytes | bytearray | memoryview, expected: type[M], robot_id: str, *, max_bytes: int = DEFAULT_MAX_BYTES
) -> M:
    """decode(), and a message that names another robot than the key it came on (`robot_id`) refused:
    someone published under another robot's key (it was fused and relabelled: a fresh-clone trial)."""
    message = decode(payload, expected, max_bytes=max_bytes)
    claimed = getattr(message, "robot_id", robot_id)
    if claimed != robot_id:
        raise SchemaError(f"{type(message).__name__} of robot {claimed!r} on robot {robot_id!r}'s key")
    return cast(M, message)


# How far ahead of a host's clock a frame's capture time may be before it is refused (robot_infer's and
# edge_infer's `max_capture_ahead_secs`, the launcher's monitor): clocks a little apart pass, a clock set
# wrong or a made-up stamp does not.
MAX_CAPTURE_AHEAD_SECS = 60.0


def refuse_future_capture(message: FrameMessage, *, now_nanos: int, ahead_nanos: int) -> None:
    """A message captured more than `ahead_nanos` ahead of `now_nanos` (this host's clock) is refused
    (SchemaError): a clock set wrong on the robot, or a made-up message. Its latencies would read
    negative, and slam refuses its poses anyway."""
    ahead = message.capture_nanos - now_nanos
    if ahead > ahead_nanos:
        raise SchemaError(
            f"{type(message).__name__} seq {message.seq} captured {ahead / 1e9:.1f} s ahead of this host's clock "
            f"(more than {ahead_nanos / 1e9:g} s: is the camera's clock set?)"
        )


def _schema_error(schema: Any) -> SchemaError:
    if not isinstance(schema, str):
        return SchemaError(f"schema id must be a string, got {type(schema).__name__}")
    name, _, version = schema.rpartition("/")
    known_versions = sorted(s for s in (*SCHEMAS, *LEGACY_SCHEMAS) if s.rpartition("/")[0] == name)
    if known_versions:
        return SchemaError(f"unsupported version {version!r} of {name} (supported: {', '.join(known_versions)})")
    return SchemaError(f"unknown schema id {schema!r} (known: {', '.join(SCHEMAS)})")


def _check_expected(schema: str, current: type[Message], expected: type[M] | Sequence[type[Message]] | None) -> None:
    if expected is not None:
        allowed = (expected,) if isinstance(expected, type) else tuple(expected)
        if current not in allowed:
            names = ", ".join(m.SCHEMA for m in allowed)
            raise SchemaError(f"received {schema} where {names} was expected")


def _decode_positional(
    payload: bytes | bytearray | memoryview, expected: type[M] | Sequence[type[Message]] | None
) -> Any:
    """Framing 3: the header parsed and checked natively, the model assembled (shared.wire.positional)."""
    mv = memoryview(payload).toreadonly()  # arrays view it read-only, a bytearray payload included
    try:
        schema, model = positional_codec().unpack(mv)
    except UnknownSchema as exc:
        raise _schema_error(exc.schema) from None
    legacy = LEGACY_SCHEMAS.get(schema)
    current = _CURRENT_BY_NAME[schema.rpartition("/")[0]] if legacy is not None else cast(type[Message], type(model))
    _check_expected(schema, current, expected)
    if legacy is None:
        return model
    try:
        return model.upgrade()  # type: ignore[attr-defined]
    except ValidationError as exc:
        raise SchemaError(f"invalid {schema}: cannot upgrade: {exc.errors(include_url=False)[0]['msg']}") from None


class View(Generic[M]):
    """A received message that passed every check `decode` makes, not yet built into its model: for a
    reader that needs a few fields of it, fast (no pydantic model, no ndarray is made).

    `fields` has the message's fields by name: scalars and strings as in the model; nested messages as
    the same kind of object; small float arrays (corners, homographies, poses) as flat tuples in C
    order; other arrays as references (`.shape`; the data stays in the payload). `model()` builds the
    message itself, once, arrays viewing the payload as `decode`'s do. Messages in framings 1 and 2
    and older schemas are built at once (their `fields` is the model: arrays as ndarrays), so a reader
    of `fields` should keep to scalars, strings, nested messages' scalars and lengths, which read the
    same either way (an inline float32 array's values are also the sender's, not yet rounded to
    float32); for arrays, use `model()`. The fields are frozen: they were checked once."""

    __slots__ = ("_model", "_mv", "fields", "schema")

    def __init__(self, schema: str, fields: Any, *, model: M | None = None, mv: memoryview | None = None) -> None:
        self.schema = schema
        self.fields = fields
        self._model = model
        self._mv = mv

    def model(self) -> M:
        """The message (built on the first call)."""
        if self._model is None:
            assert self._mv is not None
            self._model = cast(M, positional_codec().build(self.schema, self.fields, self._mv))
        return self._model


def decode_view(
    payload: bytes | bytearray | memoryview,
    expected: type[M] | Sequence[type[Message]] | None = None,
    *,
    max_bytes: int = DEFAULT_MAX_BYTES,
) -> View[M]:
    """Like `decode` (the same checks, the same errors), but the message comes as a `View`: what a reader
    of a few fields on a hot path (the link probe's echo, its ack) takes, skipping the model's assembly."""
    payload = _as_bytes_view(payload)
    if not (len(payload) >= 2 and payload[0] == FRAME_MAGIC and payload[1] == FRAMING3 and len(payload) <= max_bytes):
        model = decode(payload, expected, max_bytes=max_bytes)
        return View(model.SCHEMA, model, model=model)
    mv = memoryview(payload).toreadonly()
    codec = positional_codec()
    try:
        schema, wire = codec.unpack_wire(mv)
    except UnknownSchema as exc:
        raise _schema_error(exc.schema) from None
    if schema in LEGACY_SCHEMAS:
        model = _decode_positional(mv, expected)
        return View(model.SCHEMA, model, model=model)
    current = codec.models[schema]
    if current is not expected:
        _check_expected(schema, current, expected)  # type: ignore[arg-type]
    return View(schema, wire, mv=mv)


def _require_all_fields(model: type[WireModel], body: Any, where: str) -> None:
    """Missing fields are errors even where a model could default them: no silent defaults."""
    if not isinstance(body, dict):
        raise SchemaError(f"{where}: expected a map, got {type(body).__name__}")
    missing = [name for name in model.model_fields if name not in body]
    if missing:
        raise SchemaError(f"{where}: missing fields {missing}")


def _as_bytes_view(payload: bytes | bytearray | memoryview) -> bytes | bytearray | memoryview:
    """Sizes and the frame head in bytes, whatever a memoryview's items; a strided view is copied."""
    if isinstance(payload, memoryview):
        if not payload.c_contiguous:
            return payload.tobytes()
        if payload.format != "B" or payload.ndim != 1:
            return payload.cast("B")
    return payload


def decode(
    payload: bytes | bytearray | memoryview,
    expected: type[M] | Sequence[type[Message]] | None = None,
    *,
    max_bytes: int = DEFAULT_MAX_BYTES,
) -> Any:
    """Decode wire bytes into a message, checking everything (see module docstring).

    `expected` restricts which message types are acceptable; arrays in the result view `payload`.
    """
    payload = _as_bytes_view(payload)
    if len(payload) >= 2 and payload[0] == FRAME_MAGIC and payload[1] == FRAMING3 and len(payload) <= max_bytes:
        return _decode_positional(payload, expected)
    if len(payload) >= 2 and payload[0] == FRAME_MAGIC and payload[1] not in (FRAMING, FRAMING3):
        raise MalformedFrame(
            f"framing version {payload[1]} is unknown: this release reads framings 1, {FRAMING} and {FRAMING3} "
            f"(docs/wire.md; a message starts c1 03 00 00)"
        )
    try:
        doc = unpack(payload, max_bytes=max_bytes)
    except MalformedFrame as exc:
        raise _not_a_message(payload, str(exc)) from exc
    if not isinstance(doc, dict) or doc.keys() != ENVELOPE_KEYS:
        got = sorted(doc) if isinstance(doc, dict) else type(doc).__name__
        raise _not_a_message(payload, f"an older framing's envelope is a map with keys schema and body, got {got}")
    schema = doc["schema"]
    legacy = LEGACY_SCHEMAS.get(schema) if isinstance(schema, str) else None
    model = legacy or (SCHEMAS.get(schema) if isinstance(schema, str) else None)
    if model is None:
        raise _schema_error(schema)
    current = _CURRENT_BY_NAME[schema.rpartition("/")[0]] if legacy is not None else model
    _check_expected(schema, current, expected)
    _require_all_fields(model, doc["body"], schema)
    try:
        if legacy is not None:
            return legacy.model_validate(doc["body"]).upgrade()
        return model.model_validate(doc["body"])
    except ValidationError as exc:
        details = "; ".join(
            f"{'.'.join(str(p) for p in err['loc']) or '<body>'}: {err['msg']}" for err in exc.errors(include_url=False)
        )
        raise SchemaError(f"invalid {schema}: {details}") from None
