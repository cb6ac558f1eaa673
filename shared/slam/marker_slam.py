"""Marker SLAM core: a factor graph over camera poses X_i and tag poses L_j, solved incrementally
with GTSAM's iSAM2. No I/O: the slam service feeds it TagPoses and publishes what it returns.

- World frame: anchored at a configured tag (or, of the first unambiguous view's tags, the one whose
  pose that view pins best), whose pose gets a tight prior
  (identity, or its world pose from a tag map).
- Each tag observation is a BetweenFactorPose3(X_i, L_j, camera_from_tag) with a Huber-robust
  Gaussian noise model: the 16-keypoint PnP fit's covariance at that pose (pixel noise >= the
  observation's reprojection error through the projection's Jacobian, in the tag frame where GTSAM's
  Pose3 error lives), plus the IPPE flip uncertainty below.
- New tags are initialised from the current camera estimate. A frame with only new tags shortly
  after the last pose is bridged by the motion prior; long after it (a gap without tags), it starts
  a map fragment where the robot was last seen, tied by a weak link, and its poses are "bridged"
  until a view shared with the world's tags joins the fragment (bridge_long_gaps). Solved with QR
  (such weakly tied fragments make Cholesky's normal equations indeterminate).
- A constant-velocity motion prior (BetweenFactor predicting this frame's motion from the last one,
  sigma growing with the frame gap) ties consecutive camera poses: with tags near one plane, pitch
  and height trade off within a single frame.
- Ambiguity guard: an observation whose two IPPE branches have similar reprojection error and
  whose chosen branch disagrees with the map's prediction is rejected and counted, not fused.
- Localisation-only mode: all tag poses fixed from a tag-map file; unknown tags are ignored.
- Several robots: each has its own trajectory (its own camera-pose symbols, motion prior, pending
  tags and marginalised log) in the one graph with one tag map, so a tag seen by two robots ties
  their trajectories together. The first robot's anchor fixes the world; another robot is lost until
  it sees a tag already in the map (or a tag-map prior), then it is localised in the same world.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Final, Literal

import gtsam
import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, model_validator

from shared.vision.geometry import Array, lattice_in_tag
from shared.vision.proposers import Proposer
from shared.vision.trajectory import PoseLog
from shared.wire.messages import TagPose

L = gtsam.symbol_shorthand.L


JUMP_SIGMAS: Final[float] = 3.0  # a view says the camera jumped only this many of its sigmas beyond the envelope


class SlamSettings(BaseModel):
    """Tuning of the SLAM core."""

    model_config = ConfigDict(extra="forbid")
    anchor_tag_id: int | None = None  # None: of the first clear view's tags, the best-determined one
    localisation_only: bool = False  # hold the tag map fixed and only place the camera (needs a tag map)
    focal_px: float = Field(default=1045.0, gt=0)  # only for observations whose message had no intrinsics (v1)
    # floor of a view's pixel noise (its PnP reprojection error otherwise)
    min_pixel_sigma: float = Field(default=0.5, gt=0)
    anchor_sigma: float = 1e-6  # prior sigma of the anchor tag, which defines the world (rad and m)
    # Tags whose world pose a tag map (or a resumed checkpoint) gives are priors with this sigma
    # (rad and m) when first seen, so the map is kept and any mapped tag in view localises the camera.
    known_tag_sigma: float = Field(default=1e-3, gt=0)
    ambiguity_ratio: float = Field(default=2.0, gt=1)  # alt / max(chosen, keypoint sigma) below this = ambiguous
    # the fused keypoints' median error (bench/accuracy: p50 0.05 px)
    keypoint_sigma_px: float = Field(default=0.05, gt=0)
    # a view further than this from the other tags' camera is rejected
    disagreement_deg: float = Field(default=10.0, gt=0)
    huber_k: float = 1.5  # Huber loss threshold in sigmas (views)
    # The robust kernel of a frame's views when every tag the frame fuses is surveyed (the tag map states it to
    # within soft_surveyed_sigma_m / _deg, or gives it without sigmas), and of the blind priors placed against such
    # tags (always: they exist only for surveyed tags). There a view that disagrees with the map and with the motion
    # is more likely a bad read (a blurred far tag whose tilt is off) than news. "cauchy" (default) lets such a view
    # fade: at 3 x map_view_kernel_k sigmas (of the whole 6-D whitened error) it weighs 10 %, where Huber keeps
    # pulling; it also leans the frame more on the motion prior, and the pose covariance there grows with the views'
    # disagreement (bench.slam's fast room: median position sigma 5.1 -> 7.0 cm, 96 % of the errors inside the 95 %
    # ellipsoid). "huber": Huber at huber_k, as before this setting. Every other frame keeps Huber (huber_k) for
    # every view: where the map's views compete with slam's own (a tag slam maps, or one the map states only
    # roughly), fading them let the map drift or follow a wrong map. Measured: Cauchy on every view of every frame
    # took medium rooms without a map from 1.11 to 2.52 cm mean ATE; Cauchy on views of any tag-map tag took the 0.2
    # px noisy run, with only the anchor in the map, from 4.9 to 34 cm, and bench.slam's SLAM + rough map (2 cm / 1
    # deg per axis, so stated) from 3.60 / 2.71 / 7.01 to 5.74 / 3.26 / 9.81 cm on slow / medium / fast. With this
    # rule (docs/slam.md): the sixteen tuning rooms with the map, fast 4.90 -> 3.98 cm mean ATE (the default
    # room 4.48 -> 2.81, its spread over 1-nm perturbations 2.86-5.26 -> 2.70-2.84), medium 0.48 -> 0.44; sixteen
    # new rooms, fast 3.75 -> 3.00 (every room better), medium 0.40 -> 0.39. Without a map nothing changes, nor with
    # a map that states its sigmas roughly, except in frames of its tags given without sigmas (bench.slam's rough
    # map gives its anchor so: fast 7.01 -> 6.97). A rough map given without sigmas is taken as surveyed and then
    # trusted over the views.
    map_view_kernel: Literal["cauchy", "huber"] = "cauchy"
    map_view_kernel_k: float = Field(default=0.5, gt=0)  # the Cauchy kernel's scale, whitened sigmas
    relinearize_threshold: float = 0.01  # iSAM2's relinearisation threshold
    # Smooth-motion prior between consecutive frames (no odometry): sigma per frame of gap.
    # Constant-velocity prior between a frame and the last one with a pose: sigma per frame of gap
    # (velocity noise) plus per frame squared (acceleration); it also bridges frames with only new tags.
    motion_sigma_m: float = Field(default=0.002, gt=0)
    motion_sigma_deg: float = Field(default=0.05, gt=0)  # (above) for rotation
    motion_accel_m: float = Field(default=0.002, ge=0)  # (above) acceleration noise, per frame squared
    motion_accel_deg: float = Field(default=0.1, ge=0)  # (above) for rotation
    # The constant-velocity prior's loss: "gaussian" (the default) holds a frame to the motion however far
    # its views are; "cauchy" (scale motion_kernel_k whitened sigmas) lets views that disagree with it by
    # far more than its noise place the frame, for a camera whose motion is jerkier than the prior (hand
    # held, a robot that turns on the spot). A trial's sequence, a 75 deg pitch turn at up to 280 deg/s,
    # surveyed map: online error 1.75 -> 0.51 cm RMS, 7.7 -> 0.6 cm in the turn. On bench.slam's rooms,
    # whose motion is smooth and whose far blurred views the prior holds back, it is worse (fast room
    # without a map 7.97 -> 16.95 cm, with it 2.64 -> 3.10): docs/slam.md, Motion kernel.
    motion_kernel: Literal["gaussian", "cauchy"] = "gaussian"
    motion_kernel_k: float = Field(default=1.0, gt=0)  # (above) the Cauchy scale, in whitened sigmas
    # The constant-velocity prior bridges at most this many frames (0.5 s at 30 fps): extrapolated further
    # under a fast camera (25 deg/s) the guess is off by tens of cm, and a new tag mapped from it stays
    # wrong for good (bench.slam's held-out fast room: 28 frames bridged, the map 50 cm off, ATE 58 cm
    # over 76 % of the frames; at 15 frames a fragment starts instead and joins honestly: 5.6 cm over
    # 17 % + 59 % bridged). Longer gaps start a fragment (bridge_long_gaps).
    motion_max_gap_frames: int = Field(default=15, ge=1)
    anchor_wait_frames: int = Field(default=15, ge=0)  # frames to wait for an unambiguous anchor view
    # Frames kept in the graph; then older frames are marginalised into priors (bounded memory).
    window_frames: int = Field(default=300, ge=3)
    # Tags the tracker carried through blur: their quads drift in scale by a few % (bench/slam), so
    # every sigma of theirs is this much larger.
    tracked_sigma_scale: float = Field(default=4.0, ge=1)
    # What tracked views do, as soft_reads (below) for soft reads. "localise" (default, since session 19):
    # like a soft read, a tracked view of a surveyed tag places a frame no detected tag places, and
    # nothing is mapped from it. "map" (until session 19): fused like a detected view; on bench.slam's
    # eight fast rooms (8 runs each, 1 nm apart, medians) that drifted the map: SLAM without a map 15.2
    # cm mean ATE over 59 % of the frames against 11.0 over 48 % with the tracked views localising only,
    # with the map 5.23 against 4.81 cm over the same 96 %. "ignore": left out. A localising tracked
    # view's prior has the view's covariance (tracked_sigma_scale included) times soft_sigma_scale^2.
    tracked_reads: Literal["ignore", "localise", "map"] = "localise"
    # Tags stage 1 read blind (the line quads' soft decode, proposer "lines_soft") are the most blurred:
    # their ids are right but their keypoints are off by about five times a detected tag's (bench/slam's
    # fast room, seventh weights: corner error p50 / p90 0.51 / 0.72 px against 0.10 / 0.41), biased alike
    # from frame to frame, so mapped from they move the map (SLAM without a map on that room: 8.0 -> 39 cm).
    # "localise" (default): in a frame no detected tag places, a soft read of a surveyed tag (one the
    # tag map states to within soft_surveyed_sigma_m / _deg, or gives without sigmas) places the camera
    # (a prior on the camera pose: camera_prior, its view covariance scaled by soft_sigma_scale). No
    # tag is measured from it: it maps no tag (nor any tag new in that frame), seeds no anchor, joins no
    # fragment; through the motion prior it still pulls the neighbouring frames a little. "ignore":
    # left out. "map": fused like any other view.
    soft_reads: Literal["ignore", "localise", "map"] = "localise"
    # a localising soft or tracked read's covariance is scaled by its square
    soft_sigma_scale: float = Field(default=1.0, ge=1)
    # a tag-map tag stated within this is surveyed (soft reads, the kernel)
    soft_surveyed_sigma_m: float = Field(default=0.01, gt=0)
    soft_surveyed_sigma_deg: float = Field(default=1.0, gt=0)  # ... and within this
    # After a gap longer than motion_max_gap_frames, a frame whose tags are all new would be lost for
    # good (nothing ties them to the map). With this on, it continues the trajectory instead: its pose
    # starts where the robot was last seen, tied to it by a weak link (these sigmas), and the tags it
    # maps form a new fragment whose poses are "bridged" until a view shared with the world's fragment
    # (a tag mapped before the gap, or a tag-map prior) joins them and the graph corrects the fragment.
    # The link's sigmas grow with the gap (a robot up to ~1.5 m/s and 60 deg/s at 30 fps; rotation
    # capped at 180 deg). A join removes the link: the fragment is then placed by the shared views alone.
    bridge_long_gaps: bool = True
    # (above) the weak link's position sigma per frame of gap
    long_gap_sigma_m_per_frame: float = Field(default=0.05, gt=0)
    long_gap_sigma_deg_per_frame: float = Field(default=2.0, gt=0)  # (above) its rotation sigma per frame of gap
    # Motion envelope: the constant-velocity prior (prediction and factor) extrapolates the last two
    # poses' motion only when a robot can have made it in their stamps' gap (max_speed_m_s,
    # max_turn_deg_s, plus one pose's own uncertainty: envelope_margin_m / _deg). Two poses from a
    # tracked quad gone astray or a far tag's wrong branch can be a metre apart a frame apart; twelve
    # frames of that velocity put the next new tag metres off, and every tag mapped after it stays wrong
    # (bench.slam's fast room offset 20 with tracking: ATE 399 cm; without extrapolating it, 32 cm).
    # The stamps are capture times: a recording replayed faster than it was made looks faster too.
    max_speed_m_s: float = Field(default=2.0, gt=0)
    max_turn_deg_s: float = Field(default=180.0, gt=0)  # (above)
    envelope_margin_m: float = Field(default=0.15, ge=0)  # (above)
    envelope_margin_deg: float = Field(default=10.0, ge=0)  # (above)
    # A jump: the unambiguous views of the robot's own fragment's tags place the camera farther from its
    # last pose than the motion envelope allows, by more than these margins and by more than JUMP_SIGMAS
    # of a view's own uncertainty, and none agrees with the motion (a recording replayed from its start,
    # a robot carried elsewhere). That frame gets no constant-velocity prior and no prediction: the
    # views place it, and the frames before it are not bent towards it (a folder replayed in a loop had
    # each pass's first pose 1.6 m off and the 9 frames before it pulled up to 4 m). The margins alone
    # do not tell a bad read from a jump (two blurred far reads put the default fast room's camera
    # 1.27 m off at frame 67): the sigma test does.
    jump_margin_m: float = Field(default=0.5, ge=0)
    jump_margin_deg: float = Field(default=30.0, ge=0)  # (above)

    @model_validator(mode="before")
    @classmethod
    def _old_soft_reads_switch(cls, data: object) -> object:
        """`use_soft_reads` (until session 18) still reads: true = "map", false = "ignore"."""
        if isinstance(data, dict) and "use_soft_reads" in data:
            data = dict(data)
            old = TypeAdapter(bool).validate_python(data.pop("use_soft_reads"))  # "false" is False
            data.setdefault("soft_reads", "map" if old else "ignore")
            logging.getLogger(__name__).warning(
                "slam: use_soft_reads is replaced by soft_reads (now %r)", data["soft_reads"]
            )
        return data


@dataclass(frozen=True)
class Observation:
    """One tag seen in one frame."""

    tag_id: int
    size_m: float
    camera_from_tag: Array
    reprojection_error_px: float
    alt_camera_from_tag: Array
    alt_reprojection_error_px: float
    focal_px: float | None = None  # the camera's focal length when the message said (else the settings')
    tracked: bool = False  # carried by the tracker through frames stage 1 missed (noisier: see settings)
    proposer: Proposer | None = None  # who found it (None: the message did not say)

    @staticmethod
    def from_message(tag: TagPose, focal_px: float | None = None) -> Observation:
        """From a TagPoses entry (and its message's intrinsics' focal length)."""
        return Observation(
            tag.tag_id,
            tag.tag_size_m,
            np.asarray(tag.camera_from_tag),
            tag.reprojection_error_px,
            np.asarray(tag.alt_camera_from_tag),
            tag.alt_reprojection_error_px,
            focal_px,
            tag.tracked,
            tag.proposer,
        )


@dataclass
class FrameResult:
    """What one update produced."""

    world_from_camera: Array | None
    status: Literal["tracking", "bridged", "lost"]  # bridged: in a fragment not yet tied to the world
    tags_used: int
    rejected_ambiguous: int
    map_changed: bool
    # 6x6 covariance of world_from_camera in the world frame: position (m), then rotation (rad) about the
    # world's axes (ROS PoseWithCovariance's order); None when lost or when the graph could not give it.
    covariance_world: Array | None = None


@dataclass
class SlamState:
    """Counters."""

    frames: int = 0
    lost: int = 0
    rejected_ambiguous: int = 0
    observations: dict[int, int] = field(default_factory=dict)
    fragments: int = 0  # fragments started after long gaps (see SlamSettings.bridge_long_gaps)
    soft_reads_skipped: int = 0  # observations of blind soft reads left out (SlamSettings.soft_reads)
    soft_reads_localised: int = 0  # soft reads that placed the camera against a mapped tag ("localise")
    tracked_skipped: int = 0  # tracked views left out (SlamSettings.tracked_reads)
    tracked_localised: int = 0  # tracked views that placed the camera against a mapped tag ("localise")
    jumps: int = 0  # frames whose views placed the camera beyond the motion envelope (SlamSettings.jump_margin_m)
    # pairs of surveyed tags whose views put them this much further apart (m, median; negative: closer)
    # than the map does (MarkerSlam.MAP_DISAGREEMENT_M): a map taken as surveyed that is wrong there
    map_disagreement_m: dict[tuple[int, int], float] = field(default_factory=dict)


def _central(poses: list[Array]) -> Array:
    """Of candidate poses, the one nearest their median position (robust to a few outliers)."""
    centre = np.median(np.array([g[:3, 3] for g in poses]), axis=0)
    return min(poses, key=lambda g: float(np.linalg.norm(g[:3, 3] - centre)))


def _pose3(m: Array) -> gtsam.Pose3:
    return gtsam.Pose3(np.asarray(m, np.float64))


def _rot_deg(a: Array, b: Array) -> float:
    c = (np.trace(a[:3, :3] @ b[:3, :3].T) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(c, -1, 1))))


class SlamInputError(ValueError):
    """A frame or observation the SLAM core refuses (the state is unchanged)."""


def check_robot_count(robots: int, newcomer: str) -> None:
    """SlamInputError when one map already holds as many robots as it can (one symbol letter each)."""
    if robots >= len(_TRACK_LETTERS):
        raise SlamInputError(f"at most {len(_TRACK_LETTERS)} robots share one map; {newcomer!r} is one more")


MAX_FRAME_INDEX: Final[int] = 2**56 - 1  # gtsam.Symbol keeps 56 bits for the index
MAX_RANGE_M: Final[float] = 1e3


def check_observation(o: Observation) -> None:
    """Raise SlamInputError unless both pose candidates are rigid transforms of a tag in front of the
    camera, within MAX_RANGE_M, and the size is a plausible tag size."""
    if not (math.isfinite(o.size_m) and 1e-3 <= o.size_m <= 10.0):
        raise SlamInputError(f"tag {o.tag_id}: size {o.size_m} m is not in 1 mm .. 10 m")
    if o.focal_px is not None and not (math.isfinite(o.focal_px) and 1.0 <= o.focal_px <= 1e6):
        raise SlamInputError(f"tag {o.tag_id}: focal length {o.focal_px} px is not in 1 .. 1e6")
    for name, m in (("camera_from_tag", o.camera_from_tag), ("alt_camera_from_tag", o.alt_camera_from_tag)):
        m = np.asarray(m, np.float64)
        r, t = m[:3, :3], m[:3, 3]
        if (
            m.shape != (4, 4)
            or not np.isfinite(m).all()
            or not np.allclose(m[3], [0, 0, 0, 1])
            or not np.allclose(r @ r.T, np.eye(3), atol=1e-4)
            or np.linalg.det(r) < 0
        ):
            raise SlamInputError(f"tag {o.tag_id}: {name} is not a rigid transform")
        if not (t[2] > 0 and np.linalg.norm(t) <= MAX_RANGE_M):
            raise SlamInputError(f"tag {o.tag_id}: {name} puts the tag at {t.tolist()} m, not in front within range")


class FrameIndexer:
    """Frame indices for SLAM from what the camera stamps (seq, capture time), per robot.

    A camera numbers its frames from 0 at every start, and a message can arrive twice. Within one
    camera session the index follows seq (so gaps of dropped frames stay gaps for the motion prior),
    counted from the session's first frame; a seq that goes back while the capture time goes forward is
    a new camera session, which continues the index after a break wider than any motion prior, and so
    is a seq that jumps ahead by more than that break (no motion prior spans it). Each frame thus moves
    the index on by at most `session_break`, whatever its seq says: a frame numbered 2**56 - 10 used to
    push every later index past what the graph can hold, and slam refused every frame after it for
    the rest of the run (found by a trial). A (seq, time) seen before, or a frame older than the last
    one, is refused. A *stray*: when `stray_confirm` frames in a row come older than the last one, each
    newer than the one before it and all newer than the frame before the last, the last was the odd one
    out (a frame stamped ahead of its camera's clock, a hostile peer's: one 45 s ahead made slam refuse
    every real frame for 44 s, found by a trial); the stream goes on from them as a new camera session,
    counted in `strays` (the frames refused meanwhile stay refused)."""

    def __init__(
        self,
        *,
        session_break: int = 1_000,
        remember: int = 4_096,
        max_future_secs: float = 60.0,
        stray_confirm: int = 5,
        clock_nanos: Callable[[], int] = time.time_ns,
    ) -> None:
        self.session_break = session_break
        self.stray_confirm = stray_confirm
        self.strays = 0
        self._before_last: int | None = None  # the capture time of the frame before the newest
        self._behind: list[int] = []  # capture times of the frames refused in a row as older, in order
        # A capture time far in the future would make every real frame after it look stale.
        self.max_future_nanos = int(max_future_secs * 1e9)
        self._clock_nanos = clock_nanos
        self._base = 0  # the index of this camera session's first frame
        self._first_seq = 0  # and its seq
        self._last: tuple[int, int] | None = None  # (seq, capture_nanos) of the newest frame
        self._last_index = -1
        self._seen: dict[tuple[int, int], int] = {}
        self._remember = remember
        self.sessions = 0

    def index(self, seq: int, capture_nanos: int) -> int:
        """The SLAM frame index for this frame; SlamInputError for a repeated or stale one."""
        key = (seq, capture_nanos)
        if capture_nanos > self._clock_nanos() + self.max_future_nanos:
            raise SlamInputError(f"frame seq {seq} was captured {capture_nanos} ns, in the future beyond the bound")
        if key in self._seen:
            raise SlamInputError(f"frame seq {seq} (captured {capture_nanos}) was already fused: a repeated message")
        if self._last is None:
            self._new_session(seq)
        else:
            last_seq, last_time = self._last
            if capture_nanos <= last_time:
                in_order = not self._behind or capture_nanos > self._behind[-1]
                after_before = self._before_last is None or capture_nanos > self._before_last
                self._behind = [*self._behind, capture_nanos] if in_order and after_before else []
                if len(self._behind) < self.stray_confirm:
                    raise SlamInputError(f"frame seq {seq} is older than the last one (seq {last_seq}): out of order")
                self.strays += 1  # the last one was the stray: go on from these, as a new session
                self._new_session(seq)
            elif seq <= last_seq or seq - last_seq > self.session_break:  # the camera restarted, or a jump
                self._new_session(seq)
            self._before_last = last_time if capture_nanos > last_time else None
        self._behind = []
        index = self._base + seq - self._first_seq
        self._last = key
        self._last_index = index
        self._seen[key] = index
        if len(self._seen) > self._remember:
            self._seen.pop(next(iter(self._seen)))
        return index

    def _new_session(self, seq: int) -> None:
        self._base = 0 if self._last is None else self._last_index + self.session_break
        self._first_seq = seq
        self.sessions += 1


@dataclass
class _Pending:
    """A new tag seen only ambiguously so far: its two world-pose hypotheses from that view."""

    frame: int
    hypotheses: tuple[Array, Array]


WORLD_FRAGMENT: Final[int] = 0
JOIN_ITERATIONS: Final[int] = 5
# A frame this close after the robot's last pose is held to it by the motion prior as firmly as by a
# tag: it joins their fragments.
TIED_FRAMES: Final[int] = 2


class _Fragments:
    """Which parts of the map are tied to the world: union-find over fragment ids. Fragment 0 holds the
    anchor and any tag-map prior; a long gap starts a new one; a frame that sees tags of several joins
    them (the smallest id, so the world's, survives)."""

    def __init__(self) -> None:
        self._parent: dict[int, int] = {WORLD_FRAGMENT: WORLD_FRAGMENT}

    def new(self) -> int:
        f = len(self._parent)
        self._parent[f] = f
        return f

    def find(self, f: int) -> int:
        while self._parent[f] != f:
            self._parent[f] = self._parent[self._parent[f]]
            f = self._parent[f]
        return f

    def union(self, fragments: set[int]) -> int:
        roots = {self.find(f) for f in fragments}
        root = min(roots)
        for r in roots:
            self._parent[r] = root
        return root


# Camera-pose symbol letters per robot: the first robot keeps X (as a single-robot graph), the others
# take letters no other symbol uses (L is the tags').
_TRACK_LETTERS: Final[str] = "xabcdefghijkmnopqrstuvwyzABCDEFGHIJKMNOPQRSTUVWXYZ"


@dataclass
class _Track:
    """One robot's trajectory in the graph: its camera-pose symbols and the frames still in the graph,
    its marginalised poses, and its new tags waiting for a second view."""

    letter: str
    stamps: dict[int, int] = field(default_factory=dict)  # frame index -> stamp, frames still in the graph
    done: PoseLog = field(default_factory=PoseLog)  # frames marginalised out, compact
    last_done_frame: int = -1
    pending: dict[int, _Pending] = field(default_factory=dict)
    fragment: int = 0  # the map fragment of its last frame with a pose (see SlamSettings.bridge_long_gaps)
    # (first stamp, fragment) each time the fragment changed: a frame's fragment is the last start at or
    # before its stamp (one entry per long gap or join, so bounded by the gaps, not the frames)
    fragment_starts: list[tuple[int, int]] = field(default_factory=lambda: [(-1, 0)])
    # (first, last stamp) of frames that left the graph while their fragment was not tied to the world:
    # they stay bridged (their poses are final as they were; a later join no longer moves them)
    sealed: list[tuple[int, int]] = field(default_factory=list)

    def key(self, frame: int) -> int:
        """The GTSAM key of this robot's camera pose at `frame`."""
        return int(gtsam.symbol(self.letter, frame))


class MarkerSlam:
    # Two surveyed tags whose views put them this much further apart or closer than the map does (median
    # of their last MAP_CHECK_VIEWS views together) are said once: an EKF integrator's trial moved one tag
    # of a surveyed map by 15 cm, the frames that saw it were 35 cm off (up to 65) and nothing said why.
    # Distances, not where the frame's pose puts a tag: a pose the motion prior pulled off in a sharp turn
    # put a tag of the exact map 5.2 cm off (a first version said so).
    MAP_DISAGREEMENT_M = 0.05
    MAP_DISAGREEMENT_REL = 0.03  # ... or this share of the pair's distance, if more (a tag size or focal off by %)
    MAP_CHECK_VIEWS = 20
    MAP_CHECK_TAGS = 8  # pairs of at most this many surveyed views a frame (the nearest ids): bounded cost
    """Incremental marker SLAM (see module docstring)."""

    def __init__(
        self,
        settings: SlamSettings,
        known_tags: dict[int, tuple[float, Array]] | None = None,
        known_sigmas: dict[int, tuple[float | None, float | None]] | None = None,
        surveyed: set[int] | None = None,
    ) -> None:
        self.settings = settings
        self.known = known_tags or {}  # id -> (size, world_from_tag) from a tag map
        # id -> (rotation rad, position m): how well the tag map says it knows a pose (None: known_tag_sigma)
        self.known_sigmas = known_sigmas or {}
        # Tags soft reads may place the camera by: of `surveyed` (default: every known tag; the slam
        # service passes its configured map's, not a checkpoint's, which is this SLAM's own estimate),
        # those the map states to within soft_surveyed_sigma_m / _deg.
        self.surveyed = {
            t for t in (self.known if surveyed is None else surveyed) if t in self.known and self._stated_precisely(t)
        }
        self.tags: dict[int, float] = {}  # ids in the graph -> size
        # One trajectory per robot ("" = a single-robot graph's); frames marginalised out of the graph
        # (memory stays bounded) keep their stamps and final poses in the track's compact log.
        self._tracks: dict[str, _Track] = {}
        self.state = SlamState()
        self.anchor: int | None = None
        self._fragments = _Fragments()
        self._tag_fragment: dict[int, int] = {}  # tag id -> the fragment it was mapped in
        self._fragment_links: dict[int, int] = {}  # fragment -> its weak link's factor index in iSAM2
        # pair of surveyed tags -> their latest views' distance apart less the map's (m)
        self._map_views: dict[tuple[int, int], deque[float]] = {}
        self._map_said: set[tuple[int, int]] = set()
        self._new_isam()
        if settings.localisation_only:
            if not self.known:
                raise ValueError("localisation-only mode needs a tag map with world poses")
            graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
            for tag_id, (size, pose) in self.known.items():
                graph.add(gtsam.PriorFactorPose3(L(tag_id), _pose3(pose), self._iso(settings.anchor_sigma)))
                values.insert(L(tag_id), _pose3(pose))
                self.tags[tag_id] = size
                self._tag_fragment[tag_id] = WORLD_FRAGMENT
            self.isam.update(graph, values)
            self._estimate = self.isam.calculateEstimate()

    def _track(self, robot: str) -> _Track:
        track = self._tracks.get(robot)
        if track is None:
            check_robot_count(len(self._tracks), robot)
            track = self._tracks[robot] = _Track(_TRACK_LETTERS[len(self._tracks)])
        return track

    @property
    def robots(self) -> list[str]:
        """The robots with a trajectory, in the order they first came."""
        return list(self._tracks)

    @property
    def stamps(self) -> dict[int, int]:
        """The first robot's frames still in the graph (frame index -> stamp)."""
        return self._tracks[next(iter(self._tracks))].stamps if self._tracks else {}

    def _new_isam(self) -> None:
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(self.settings.relinearize_threshold)
        params.setFactorization("QR")
        self.isam = gtsam.ISAM2(params)
        self._estimate = gtsam.Values()

    @staticmethod
    def _iso(sigma: float) -> gtsam.noiseModel.Base:
        return gtsam.noiseModel.Isotropic.Sigma(6, sigma)

    # ------------------------------------------------------------------------------------------

    def is_ambiguous(self, obs: Observation) -> bool:
        """Both IPPE branches explain the points within the keypoint noise: the tag's tilt is unsure."""
        floor = max(self.settings.keypoint_sigma_px, obs.reprojection_error_px)
        return obs.alt_reprojection_error_px < self.settings.ambiguity_ratio * floor

    def noise(self, obs: Observation, *, alt: bool = False, map_frame: bool = False) -> gtsam.noiseModel.Base:
        """Robust Gaussian noise of one observation: `covariance` in GTSAM's model, under Huber, or under
        map_view_kernel for a surveyed tag in a frame whose fused tags are all surveyed (`map_frame`)."""
        return self._robust(self.covariance(obs, alt=alt), map_view=map_frame and obs.tag_id in self.surveyed)

    def _robust(self, cov: Array, *, map_view: bool = False) -> gtsam.noiseModel.Base:
        """A view's noise model: Huber (huber_k) over the Gaussian of `cov`, or map_view_kernel for a view
        in a frame of surveyed tags only and for a blind prior (`map_view`)."""
        s = self.settings
        gauss = gtsam.noiseModel.Gaussian.Covariance(cov)
        kernel: gtsam.noiseModel.mEstimator.Base
        if map_view and s.map_view_kernel == "cauchy":
            kernel = gtsam.noiseModel.mEstimator.Cauchy.Create(s.map_view_kernel_k)
        else:
            kernel = gtsam.noiseModel.mEstimator.Huber.Create(s.huber_k)
        return gtsam.noiseModel.Robust.Create(kernel, gauss)

    def covariance(self, obs: Observation, *, alt: bool = False) -> Array:
        """Covariance (6x6) of one observation, in the tag frame (rotation first, as GTSAM).

        The PnP estimate's covariance at this pose: sigma_px^2 (J^T J)^-1, J the Jacobian of the 16
        lattice keypoints' pixels with respect to the pose (the Cramer-Rao bound of the 16-point fit;
        it holds the far, small, tilted tag's weak rotation and depth and their correlations). The pixel
        sigma is the observation's reprojection error, at least min_pixel_sigma. Added to it, about the
        axis that turns this IPPE branch into the other, the angle between them scaled by keypoint noise
        / the other branch's reprojection error: a tag whose two branches fit almost equally well
        (small, far, blurred) tells its position, barely its tilt. `alt`: the observation is used with
        its other branch."""
        s = self.settings
        m, other = obs.camera_from_tag, obs.alt_camera_from_tag
        mine_err, other_err = obs.reprojection_error_px, obs.alt_reprojection_error_px
        if alt:
            m, other, mine_err, other_err = other, m, other_err, mine_err
        px = max(s.min_pixel_sigma, mine_err)
        focal = obs.focal_px if obs.focal_px is not None else s.focal_px
        cov = pnp_covariance(m, obs.size_m, focal, px)
        r = m[:3, :3]
        omega = np.asarray(gtsam.Rot3.Logmap(gtsam.Rot3(r.T @ np.asarray(other)[:3, :3])))
        angle = float(np.linalg.norm(omega))
        if angle > 1e-9:
            axis = omega / angle
            kp = max(s.keypoint_sigma_px, mine_err)
            flip_sigma = min(angle, angle * kp / max(other_err - mine_err, 1e-6))
            cov[:3, :3] += flip_sigma**2 * np.outer(axis, axis)
        if obs.tracked:
            cov *= s.tracked_sigma_scale**2
        return cov

    def _check_input(self, robot: str, frame: int, observations: list[Observation]) -> None:
        if not 0 <= frame <= MAX_FRAME_INDEX:
            raise SlamInputError(f"frame index {frame} is outside 0..2**56-1")
        track = self._tracks.get(robot)
        if track is None:
            check_robot_count(len(self._tracks), robot)
        if track is not None and (
            frame in track.stamps or frame <= track.last_done_frame or self._estimate.exists(track.key(frame))
        ):
            raise SlamInputError(f"frame {frame} was already fused (a repeated message or a restarted camera)")
        for o in observations:
            check_observation(o)

    def _world_from_tag(self, tag_id: int) -> Array | None:
        if tag_id in self.tags and self._estimate.exists(L(tag_id)):
            return np.asarray(self._estimate.atPose3(L(tag_id)).matrix())
        return None

    def _add_tag(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        tag_id: int,
        size: float,
        pose: Array,
        noise: gtsam.noiseModel.Base | None,
    ) -> None:
        if noise is not None:
            graph.add(gtsam.PriorFactorPose3(L(tag_id), _pose3(pose), noise))
        values.insert(L(tag_id), _pose3(pose))
        self.tags[tag_id] = size
        self._tag_fragment[tag_id] = WORLD_FRAGMENT  # the anchor and tag-map priors are in the world
        self._estimate.insert(L(tag_id), _pose3(pose))

    def _seed_map(
        self,
        observations: list[Observation],
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        *,
        blind: list[Observation] | None = None,
    ) -> bool:
        """Known tags in view enter as priors; the first anchor fixes the world frame. A known tag only a
        blind read (a soft read or tracked view that only localises) sees enters too (its pose is the
        map's, not the read's), but never as the anchor: not
        the anchor tag itself, and not before there is an anchor unless the settings name which tag it
        is to be. Returns whether the map changed."""
        s = self.settings
        changed = False
        for o in observations:
            if o.tag_id in self.known and o.tag_id not in self.tags:
                size, pose = self.known[o.tag_id]
                anchor = o.tag_id == s.anchor_tag_id or (self.anchor is None and s.anchor_tag_id is None)
                self._add_tag(
                    graph,
                    values,
                    o.tag_id,
                    size,
                    pose,
                    self._iso(s.anchor_sigma) if anchor else self._known_noise(o.tag_id),
                )
                if anchor:
                    self.anchor = o.tag_id
                changed = True
        for o in blind or []:
            if (
                (self.anchor is not None or s.anchor_tag_id is not None)
                and o.tag_id != s.anchor_tag_id
                and o.tag_id in self.surveyed
                and o.tag_id not in self.tags
            ):
                size, pose = self.known[o.tag_id]
                self._add_tag(graph, values, o.tag_id, size, pose, self._known_noise(o.tag_id))
                changed = True
        if self.anchor is None and not s.localisation_only:
            chosen = [
                o
                for o in observations
                if (s.anchor_tag_id is None or o.tag_id == s.anchor_tag_id) and o.tag_id not in self.tags
            ]  # (a named anchor already mapped as an ordinary tag stays one: no second insert of its key)
            # The anchor's view sets the first camera pose: wait a little for an unambiguous one.
            clear = [o for o in chosen if not self.is_ambiguous(o)]
            if clear or (chosen and self.state.frames > s.anchor_wait_frames):
                # the world is this tag's frame: the one whose pose the view pins best (the smallest
                # rotation uncertainty: a near, large, face-on tag), not the luck of a reprojection error
                a = min(clear or chosen, key=self._rotation_variance)
                pose = self.known[a.tag_id][1] if a.tag_id in self.known else np.eye(4)
                self.anchor = a.tag_id
                self._add_tag(graph, values, a.tag_id, a.size_m, pose, self._iso(s.anchor_sigma))
                changed = True
        return changed

    def _known_noise(self, tag_id: int) -> gtsam.noiseModel.Base:
        """A tag-map pose's prior: the sigmas the map states for it, else known_tag_sigma (rad and m)."""
        rot, pos = self._stated_sigmas(tag_id)
        return gtsam.noiseModel.Diagonal.Sigmas(np.array([rot] * 3 + [pos] * 3))

    def _stated_precisely(self, tag_id: int) -> bool:
        """The map states this tag to within soft_surveyed_sigma_deg / _m (or without sigmas: surveyed)."""
        rot, pos = self._stated_sigmas(tag_id)
        s = self.settings
        return rot <= math.radians(s.soft_surveyed_sigma_deg) and pos <= s.soft_surveyed_sigma_m

    def _stated_sigmas(self, tag_id: int) -> tuple[float, float]:
        """A known tag's (rotation rad, position m) sigmas: the map's, else known_tag_sigma."""
        rot, pos = self.known_sigmas.get(tag_id, (None, None))
        default = self.settings.known_tag_sigma
        return default if rot is None else rot, default if pos is None else pos

    def tag_sigmas(self) -> dict[int, tuple[float, float]]:
        """How well the graph knows each mapped tag's pose (not the anchor, which defines the world):
        id -> (rotation rad, position m), each the largest axis of its marginal covariance (in the tag's
        frame, as a prior takes it). Tags whose marginal GTSAM cannot give are left out; so is every tag
        in localisation-only mode, where the map is held fixed (its marginals say nothing of it)."""
        out: dict[int, tuple[float, float]] = {}
        if self.settings.localisation_only:
            return out
        for tag_id in self.tags:
            if tag_id in (self.anchor, self.settings.anchor_tag_id) or not self._estimate.exists(L(tag_id)):
                continue
            try:
                cov = np.asarray(self.isam.marginalCovariance(L(tag_id)))
            except RuntimeError:
                continue
            if not np.isfinite(cov).all():
                continue
            rot = math.sqrt(max(0.0, float(np.linalg.eigvalsh(cov[:3, :3]).max())))
            pos = math.sqrt(max(0.0, float(np.linalg.eigvalsh(cov[3:, 3:]).max())))
            if rot > 0 and pos > 0:
                out[tag_id] = (rot, pos)
        return out

    def _rotation_variance(self, obs: Observation) -> float:
        """Total rotation variance (rad^2) of an observation's noise model, flip included."""
        return float(np.trace(self.covariance(obs)[:3, :3]))

    def _pose(self, track: _Track, frame: int) -> Array:
        return np.asarray(self._estimate.atPose3(track.key(frame)).matrix())

    def _motion_frames(self, track: _Track, frame: int) -> tuple[int, int] | None:
        """The robot's last two frames with a pose, when they and `frame` are within the bridging gap of
        each other: what the motion prediction and the constant-velocity factor both stand on."""
        gap = self.settings.motion_max_gap_frames
        done = sorted(track.stamps)
        if len(done) < 2:
            return None
        a, b = done[-2], done[-1]
        if not (0 < frame - b <= gap and b - a <= gap):
            return None
        # A velocity no robot has (two poses from a tracked quad gone astray, a wrong branch) is not
        # extrapolated: twelve frames of a 10 m/s jitter put the next new tag metres off.
        secs = (track.stamps[b] - track.stamps[a]) / 1e9
        if not self._within_envelope(self._pose(track, a), self._pose(track, b), secs):
            return None
        return a, b

    def predict(self, frame: int, *, robot: str = "") -> Array | None:
        """Constant-velocity camera pose for `frame` of `robot` from its last two frames with a pose
        (None beyond the bridging gap)."""
        track = self._tracks.get(robot)
        ab = self._motion_frames(track, frame) if track is not None else None
        if track is None or ab is None:
            return None
        a, b = ab
        pa, pb = self._pose(track, a), self._pose(track, b)
        twist = np.asarray(gtsam.Pose3.Logmap(_pose3(np.linalg.inv(pa) @ pb))) / (b - a)
        return pb @ np.asarray(gtsam.Pose3.Expmap(twist * (frame - b)).matrix())

    def _use_alt(self, o: Observation, world_from_tag: Array, reference: Array | None) -> bool:
        """Whether a mapped tag's observation is used with its other branch: only when ambiguous and the
        other one agrees better with the reference camera pose (the motion prediction or the other tags)."""
        if reference is None or not self.is_ambiguous(o):
            return False
        predicted = np.linalg.inv(reference) @ world_from_tag
        return _rot_deg(o.alt_camera_from_tag, predicted) < _rot_deg(o.camera_from_tag, predicted)

    def update(self, frame: int, stamp_nanos: int, observations: list[Observation], *, robot: str = "") -> FrameResult:
        """Fuse one frame of `robot` (frame indices are per robot); returns the camera pose estimate for
        it. Raises SlamInputError, before touching any state, for a frame it has seen, a frame index
        GTSAM cannot key, or an observation that is no rigid pose in front of the camera."""
        self._check_input(robot, frame, observations)
        track = self._track(robot)
        s = self.settings
        self.state.frames += 1
        # Blind reads: soft reads and tracked views, each kind fused, localising only or left out by its
        # setting (soft_reads, tracked_reads).
        fused: list[Observation] = []
        blind: list[Observation] = []  # the ones that localise only
        for o in observations:
            mode = s.tracked_reads if o.tracked else s.soft_reads if o.proposer == "lines_soft" else "map"
            if mode == "map":
                fused.append(o)
            elif mode == "localise":
                blind.append(o)
            else:
                self._count_blind(o, localised=False)
        observations = fused
        # map_view_kernel only where the surveyed map is the whole story of the frame (see the setting);
        # in localisation-only mode a tag the map lacks adds nothing, so it does not count
        map_frame = all(
            o.tag_id in self.surveyed for o in observations if not (s.localisation_only and o.tag_id not in self.known)
        )
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        map_changed = self._seed_map(observations, graph, values, blind=blind)
        predicted = self.predict(frame, robot=robot)
        still_from: int | None = None
        joined = False
        mapped = [(o, wt) for o in observations if (wt := self._world_from_tag(o.tag_id)) is not None]
        jumped = predicted is not None and self._jumped(track, stamp_nanos, mapped)
        if jumped:
            predicted = None  # the views say the camera is elsewhere: they place it, not the motion
            self.state.jumps += 1
            logging.getLogger(__name__).info(
                "slam: frame %d of %r jumped away from the motion (no motion prior for it)", frame, robot
            )
        # Camera initial guess: each mapped tag's view (branch chosen against the prediction or, without
        # one, against the unambiguous views), the one nearest the median position wins.
        reference = predicted
        if reference is None:
            clear = [wt @ np.linalg.inv(o.camera_from_tag) for o, wt in mapped if not self.is_ambiguous(o)]
            if clear:
                reference = _central(clear)
        alt = {o.tag_id: self._use_alt(o, wt, reference) for o, wt in mapped}
        # Tags of several fragments in view (a join): the camera is placed by the world's tags (else the
        # robot's own fragment's); the others are fused without the disagreement test, as their fragment
        # is placed by the gap's guess and the join is what corrects it.
        roots = {o.tag_id: self._fragments.find(self._tag_fragment[o.tag_id]) for o, _ in mapped}
        lead = min(
            roots.values(),
            key=lambda r: (r != self._fragments.find(WORLD_FRAGMENT), r != self._fragments.find(track.fragment), r),
            default=None,
        )
        guesses = [
            wt @ np.linalg.inv(o.alt_camera_from_tag if alt[o.tag_id] else o.camera_from_tag)
            for o, wt in mapped
            if roots[o.tag_id] == lead
        ]
        # Blind reads of surveyed tags (soft_reads / tracked_reads = "localise"): camera priors, in the
        # fragment the camera is placed in; an ambiguous one only with a reference to pick its branch.
        target = lead if lead is not None else self._fragments.find(track.fragment)
        # (read, world_from_camera, its covariance in GTSAM's order)
        blind_priors: list[tuple[Observation, Array, Array]] = []
        for o in blind:
            wt = self._world_from_tag(o.tag_id) if o.tag_id in self.surveyed else None
            if (
                guesses  # only where nothing else places
                or wt is None
                or self._fragments.find(self._tag_fragment[o.tag_id]) != target
                or (self.is_ambiguous(o) and reference is None)
            ):
                self._count_blind(o, localised=False)
                continue
            use_alt = self._use_alt(o, wt, reference)
            measured = o.alt_camera_from_tag if use_alt else o.camera_from_tag
            view = s.soft_sigma_scale**2 * self.covariance(o, alt=use_alt)
            blind_priors.append((o, *camera_prior(wt, measured, view, self._tag_covariance(o.tag_id))))
        if guesses:
            init = _central(guesses)
        elif blind_priors:
            init = _central([g for _, g, _ in blind_priors])
        elif predicted is not None and not s.localisation_only:
            init = predicted  # only new tags in view, shortly after the last pose: bridge with the motion
        elif (last := self._still_origin(track, observations)) is not None:
            # only new tags and no motion to extrapolate (a long gap, or a single recent pose): held still
            # from the last pose, tied to it by a weak link; after a long gap in a new fragment
            init = self._pose(track, last)
            still_from = last
        else:
            self._lost_frame(graph, values)
            return FrameResult(None, "lost", 0, 0, map_changed)
        used, rejected = 0, 0
        surveyed_views: list[tuple[int, Array]] = []  # (tag, camera_from_tag as fused) of surveyed tags
        seen_fragments: set[int] = set()
        new_tags: list[int] = []
        for o in observations:
            wt = self._world_from_tag(o.tag_id)
            if wt is not None:
                use_alt = alt[o.tag_id]
                measured = o.alt_camera_from_tag if use_alt else o.camera_from_tag
                if (
                    roots[o.tag_id] == lead
                    and len(guesses) > 1
                    and _rot_deg(measured, np.linalg.inv(init) @ wt) > s.disagreement_deg
                ):
                    rejected += 1  # disagrees with the other tags in view in either branch: an outlier
                    continue
                if roots[o.tag_id] != lead and self.is_ambiguous(o):
                    rejected += 1  # a join (and its link's removal) only on a view whose branch is sure
                    continue
                seen_fragments.add(self._fragments.find(self._tag_fragment[o.tag_id]))
                if o.tag_id in self.surveyed:
                    surveyed_views.append((o.tag_id, measured))
            elif s.localisation_only:
                continue
            elif blind_priors:
                rejected += 1  # the camera is placed by blind reads alone: nothing is mapped from such a frame
                continue
            else:
                admitted = self._admit_new_tag(track, o, frame, init)
                if admitted is None:
                    rejected += 1  # ambiguous and not yet disambiguated by a second view
                    continue
                use_alt = admitted
                measured = o.alt_camera_from_tag if use_alt else o.camera_from_tag
                values.insert(L(o.tag_id), _pose3(init @ measured))
                self.tags[o.tag_id] = o.size_m
                new_tags.append(o.tag_id)
                map_changed = True
            graph.add(
                gtsam.BetweenFactorPose3(
                    track.key(frame), L(o.tag_id), _pose3(measured), self.noise(o, alt=use_alt, map_frame=map_frame)
                )
            )
            self.state.observations[o.tag_id] = self.state.observations.get(o.tag_id, 0) + 1
            used += 1
        for o, prior, cov in blind_priors:
            if _rot_deg(prior, init) > s.disagreement_deg:
                self._count_blind(o, localised=False)  # disagrees with the other views in this frame
                continue
            graph.add(gtsam.PriorFactorPose3(track.key(frame), _pose3(prior), self._robust(cov, map_view=True)))
            self._count_blind(o, localised=True)
            used += 1
        self.state.rejected_ambiguous += rejected
        if used == 0:
            self._lost_frame(graph, values)
            return FrameResult(None, "lost", 0, rejected, map_changed)
        values.insert(track.key(frame), _pose3(init))
        remove: list[int] = []
        link_at: int | None = None
        long_gap = still_from is not None and frame - still_from > s.motion_max_gap_frames
        if still_from is not None:
            gap = frame - still_from
            rot_sigma = math.radians(min(180.0, s.long_gap_sigma_deg_per_frame * gap))
            sigmas = [rot_sigma] * 3 + [s.long_gap_sigma_m_per_frame * gap] * 3
            if long_gap:
                link_at = graph.size()
            graph.add(
                gtsam.BetweenFactorPose3(
                    track.key(still_from),
                    track.key(frame),
                    gtsam.Pose3(),  # held still: a guess either way, and one that cannot fly off
                    gtsam.noiseModel.Diagonal.Sigmas(np.array(sigmas)),
                )
            )
        # Not None when this frame is bridged by the prediction (the same last two poses); None when the
        # velocity is beyond the motion envelope or the last two poses are too far apart.
        motion = None if jumped else self._motion_factor(track, frame)
        if motion is not None:
            graph.add(motion)
        if long_gap:
            fragment = self._fragments.new()
            self.state.fragments += 1
        else:
            last = max(track.stamps, default=None)
            linked = motion is not None or still_from is not None  # a factor ties this frame to earlier ones
            if not seen_fragments or (linked and last is not None and frame - last <= TIED_FRAMES):
                # this frame is tied to the robot's last ones (its only tags are new: held still or bridged,
                # or it comes right after them and a motion factor holds it): their fragment is in view too.
                # Without such a factor a view of the world's tags right after a fragment's frames joins
                # nothing: the fragment keeps its weak link (else nothing would tie it to the world)
                seen_fragments.add(self._fragments.find(track.fragment))
            joined = len(seen_fragments) > 1
            fragment = self._fragments.union(seen_fragments)  # a view shared by fragments joins them
            # The joined fragments' weak links go: the shared view places them now, not the gap's guess.
            remove = [
                self._fragment_links.pop(f) for f in seen_fragments if f != fragment and f in self._fragment_links
            ]
        for tag_id in new_tags:
            self._tag_fragment[tag_id] = fragment
        if fragment != track.fragment:
            track.fragment_starts.append((stamp_nanos, fragment))
        track.fragment = fragment
        result = self.isam.update(graph, values, remove)
        if link_at is not None:
            self._fragment_links[fragment] = int(result.getNewFactorsIndices()[link_at])
        for _ in range(JOIN_ITERATIONS if joined else 0):  # a join moves a whole fragment: relinearise it
            self.isam.update()
        self._estimate = self.isam.calculateEstimate()
        pose = self._pose(track, frame)
        self._check_map(surveyed_views)
        covariance = self._covariance_world(track, frame, pose)
        track.stamps[frame] = stamp_nanos
        if sum(len(t.stamps) for t in self._tracks.values()) >= s.window_frames:
            self._marginalise_old_frames()
        status: Literal["tracking", "bridged"] = "tracking" if self._tied(fragment) else "bridged"
        return FrameResult(pose, status, used, rejected, map_changed, covariance)

    def _check_map(self, views: list[tuple[int, Array]]) -> None:
        """How far apart this frame's views put each pair of surveyed tags against the map's distance
        between them (positions in the camera are sure where a far tag's tilt is not, and the camera's own
        error cancels): a pair that stays MAP_DISAGREEMENT_M off is said once and kept in the state."""
        views = sorted(views, key=lambda v: v[0])[: self.MAP_CHECK_TAGS]
        for i, (a, camera_from_a) in enumerate(views):
            for b, camera_from_b in views[i + 1 :]:
                pair = (min(a, b), max(a, b))
                seen = float(np.linalg.norm(camera_from_a[:3, 3] - camera_from_b[:3, 3]))
                mapped = float(np.linalg.norm(self.known[a][1][:3, 3] - self.known[b][1][:3, 3]))
                recent = self._map_views.setdefault(pair, deque(maxlen=self.MAP_CHECK_VIEWS))
                recent.append(seen - mapped)
                median = float(np.median(recent))
                limit = max(self.MAP_DISAGREEMENT_M, self.MAP_DISAGREEMENT_REL * mapped)
                if len(recent) < self.MAP_CHECK_VIEWS or abs(median) <= limit:
                    self.state.map_disagreement_m.pop(pair, None)
                    continue
                if pair not in self._map_said:  # once a run (a median near the limit would say it again and again)
                    self._map_said.add(pair)
                    logging.getLogger(__name__).warning(
                        "slam: the views put tags %d and %d %.1f cm %s than the tag map does (median of their last "
                        "%d views together), and the map states both as surveyed: if it is only roughly right "
                        "there, give its tags position_sigma_m / rotation_sigma_deg (or fix it)",
                        *pair,
                        100 * abs(median),
                        "further apart" if median > 0 else "closer",
                        len(recent),
                    )
                self.state.map_disagreement_m[pair] = median

    def _count_blind(self, o: Observation, *, localised: bool) -> None:
        """Count a blind read (a soft read or a tracked view that is not fused) as localised or skipped."""
        st = self.state
        if o.tracked:
            st.tracked_localised += localised
            st.tracked_skipped += not localised
        else:
            st.soft_reads_localised += localised
            st.soft_reads_skipped += not localised

    def _tag_covariance(self, tag_id: int) -> Array:
        """How well a mapped tag is known (6x6, its tangent, rotation first): the graph's marginal, or
        for a known tag seeded in this very frame, what its map states."""
        key = L(tag_id)
        if self.isam.valueExists(key):
            with contextlib.suppress(RuntimeError):  # a marginal GTSAM cannot give: what the map states
                return np.asarray(self.isam.marginalCovariance(key))
        if tag_id == self.anchor:
            return np.eye(6) * self.settings.anchor_sigma**2
        rot, pos = self._stated_sigmas(tag_id)
        return np.diag([rot**2] * 3 + [pos**2] * 3)

    def _lost_frame(self, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> None:
        """A frame without a pose: the known tags it seeded still enter the graph (they are in the map
        from now on; left out, a later view of one would name a key iSAM2 never got)."""
        self.state.lost += 1
        if graph.size():
            self.isam.update(graph, values)
            self._estimate = self.isam.calculateEstimate()

    def _covariance_world(self, track: _Track, frame: int, world_from_camera: Array) -> Array | None:
        """The camera pose's marginal covariance (everything fused so far, this frame included), in the
        world frame (`world_covariance`); None if GTSAM cannot give it (an indeterminate system raises, a
        near-singular one returns non-finite or negative variances): the pose itself is still returned."""
        try:
            tangent = np.asarray(self.isam.marginalCovariance(track.key(frame)))
        except RuntimeError:
            return None
        out = world_covariance(tangent, world_from_camera)
        # A near-singular marginal comes back without an exception: never publish it (the wire refuses it).
        return out if np.isfinite(out).all() and float(np.diag(out).min()) >= 0 else None

    def _within_envelope(self, before: Array, after: Array, secs: float) -> bool:
        """Whether a camera can have gone from pose `before` to `after` in `secs` seconds (stamps out of
        order allow only the margin)."""
        s = self.settings
        secs = max(secs, 0.0)
        moved_m = float(np.linalg.norm(after[:3, 3] - before[:3, 3]))
        return (
            moved_m <= s.envelope_margin_m + s.max_speed_m_s * secs
            and _rot_deg(after, before) <= s.envelope_margin_deg + s.max_turn_deg_s * secs
        )

    def _jumped(self, track: _Track, stamp_nanos: int, mapped: list[tuple[Observation, Array]]) -> bool:
        """Whether this frame's views of mapped tags say the camera jumped: no unambiguous view places it
        within the motion envelope (plus the jump margins) of the robot's last pose, and at least one
        places it beyond by more than JUMP_SIGMAS of its own uncertainty (the view's and its tag's): a
        far or face-on tag, whose tilt barely holds, moves the camera by decimetres and is no jump."""
        s = self.settings
        # Only tags of the robot's own fragment: the last pose of a robot in a fragment placed by a long
        # gap's guess may be metres from the world's tags, and a view of those is the join, not a jump.
        own = self._fragments.find(track.fragment)
        clear = [
            (o, wt)
            for o, wt in mapped
            if not self.is_ambiguous(o) and self._fragments.find(self._tag_fragment[o.tag_id]) == own
        ]
        if not clear or not track.stamps:
            return False
        last = max(track.stamps)
        before = self._pose(track, last)
        secs = max((stamp_nanos - track.stamps[last]) / 1e9, 0.0)
        reach_m = s.jump_margin_m + s.envelope_margin_m + s.max_speed_m_s * secs
        reach_rad = math.radians(s.jump_margin_deg + s.envelope_margin_deg + s.max_turn_deg_s * secs)
        beyond: list[tuple[float, float, Observation, Array]] = []
        for o, wt in clear:
            seen = wt @ np.linalg.inv(o.camera_from_tag)
            moved_m = float(np.linalg.norm(seen[:3, 3] - before[:3, 3]))
            turned_rad = math.radians(_rot_deg(seen, before))
            if moved_m <= reach_m and turned_rad <= reach_rad:
                return False  # a view agrees with the motion
            beyond.append((moved_m - reach_m, turned_rad - reach_rad, o, wt))
        for over_m, over_rad, o, wt in beyond:
            _, cov = camera_prior(wt, o.camera_from_tag, self.covariance(o), self._tag_covariance(o.tag_id))
            sigma_rad, sigma_m = math.sqrt(np.trace(cov[:3, :3])), math.sqrt(np.trace(cov[3:, 3:]))
            if over_m > JUMP_SIGMAS * sigma_m or over_rad > JUMP_SIGMAS * sigma_rad:
                return True
        return False

    def _still_origin(self, track: _Track, observations: list[Observation]) -> int | None:
        """The robot's last frame with a pose, when this frame (only new tags in view, no motion to
        extrapolate: past the bridging gap, a single recent pose, or a velocity beyond the motion
        envelope) should be held still from it (see bridge_long_gaps)."""
        s = self.settings
        if not s.bridge_long_gaps or s.localisation_only or not observations or not track.stamps:
            return None
        return max(track.stamps)

    def _admit_new_tag(self, track: _Track, o: Observation, frame: int, world_from_camera: Array) -> bool | None:
        """The branch a new tag enters the map with (True: the other one), or None while it is ambiguous:
        then both world-pose
        hypotheses are kept, and a later view (within the bridging gap) that agrees with exactly one
        of them decides."""
        s = self.settings
        if not self.is_ambiguous(o):
            track.pending.pop(o.tag_id, None)
            return False
        now = (world_from_camera @ o.camera_from_tag, world_from_camera @ o.alt_camera_from_tag)
        before = track.pending.get(o.tag_id)
        if before is None or frame - before.frame > s.motion_max_gap_frames:
            track.pending[o.tag_id] = _Pending(frame, now)
            return None
        # Disagreement of each current branch with the closest earlier hypothesis.
        score = [min(_rot_deg(h, p) for p in before.hypotheses) for h in now]
        best = int(np.argmin(score))
        if score[best] < s.disagreement_deg / 2 and score[1 - best] > s.disagreement_deg:
            track.pending.pop(o.tag_id, None)
            return best == 1
        track.pending[o.tag_id] = _Pending(frame, now)
        return None

    def _motion_factor(self, track: _Track, frame: int) -> gtsam.CustomFactor | None:
        """Constant-velocity prior over the last two frames with a pose and this one (no odometry):
        their twists per frame agree up to an acceleration noise that grows with the gaps. A three-pose
        factor, so the velocity is estimated with the poses rather than frozen from noisy estimates."""
        s = self.settings
        ab = self._motion_frames(track, frame)
        if ab is None:
            return None
        a, b = ab
        g1, g2 = b - a, frame - b
        span = g2 * (g1 + g2) / 2  # frames^2 over which an acceleration changes the twist
        rot = math.radians(s.motion_accel_deg) * span + math.radians(s.motion_sigma_deg) * g2
        pos = s.motion_accel_m * span + s.motion_sigma_m * g2
        noise: gtsam.noiseModel.Base = gtsam.noiseModel.Diagonal.Sigmas(np.array([rot] * 3 + [pos] * 3))
        if s.motion_kernel == "cauchy":
            noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(s.motion_kernel_k), noise)
        return gtsam.CustomFactor(
            noise, [track.key(a), track.key(b), track.key(frame)], _constant_velocity_error(g1, g2)
        )

    def _marginalise_old_frames(self) -> None:
        """Bound memory: start a fresh graph from the current estimate. Every tag keeps its estimate as a
        prior with its marginal covariance (the anchor and a localisation map stay fixed); the last two
        frames keep theirs (the motion prior needs them); older frames are final and leave the graph."""
        s = self.settings
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        for tag_id in self.tags:
            if not self._estimate.exists(L(tag_id)):
                continue
            pose = self._estimate.atPose3(L(tag_id))
            if tag_id == self.anchor or s.localisation_only:
                noise = self._iso(s.anchor_sigma)
            else:
                noise = gtsam.noiseModel.Gaussian.Covariance(_spd(self.isam.marginalCovariance(L(tag_id))))
            graph.add(gtsam.PriorFactorPose3(L(tag_id), pose, noise))
            values.insert(L(tag_id), pose)
        for track in self._tracks.values():  # every robot keeps its last two frames (its motion prior)
            keep = sorted(track.stamps)[-2:]
            poses = {f: self._pose(track, f) for f in track.stamps}
            for f in keep:
                cov = _spd(self.isam.marginalCovariance(track.key(f)))
                graph.add(
                    gtsam.PriorFactorPose3(track.key(f), _pose3(poses[f]), gtsam.noiseModel.Gaussian.Covariance(cov))
                )
                values.insert(track.key(f), _pose3(poses[f]))
            old = [f for f in sorted(track.stamps) if f not in keep]
            run_open = False  # runs of consecutive bridged frames leaving the graph, one entry each
            for f in old:
                stamp = track.stamps[f]
                if self._bridged_in(track, stamp):
                    if run_open:
                        track.sealed[-1] = (track.sealed[-1][0], stamp)
                    else:
                        track.sealed.append((stamp, stamp))
                    run_open = True
                else:
                    run_open = False
            track.done.extend([track.stamps[f] for f in old], [poses[f] for f in old])
            for f in old:
                del track.stamps[f]
            track.last_done_frame = max(track.last_done_frame, old[-1]) if old else track.last_done_frame
        self._new_isam()
        self.isam.update(graph, values)
        self._estimate = self.isam.calculateEstimate()
        # The links left with the old graph; an unjoined fragment's tags keep their (loose) marginals.
        self._fragment_links.clear()

    def trajectory(self, robot: str | None = None) -> list[tuple[int, Array]]:
        """One robot's camera poses in frame order (None: the first robot's): (stamp_nanos,
        world_from_camera); the frames still in the graph are smoothed by every later observation,
        older ones are as they were when they left it."""
        track = self._tracks.get(robot if robot is not None else next(iter(self._tracks), ""))
        if track is None:
            return []
        out = track.done.items()
        for frame in sorted(track.stamps):
            if self._estimate.exists(track.key(frame)):
                out.append((track.stamps[frame], self._pose(track, frame)))
        return out

    def trajectory_arrays(self, robot: str | None = None) -> tuple[Array, Array]:
        """`trajectory()` as arrays (stamps (n,) ns, poses (n, 4, 4)), without a Python object per pose."""
        track = self._tracks.get(robot if robot is not None else next(iter(self._tracks), ""))
        if track is None:
            return np.zeros(0, np.int64), np.zeros((0, 4, 4))
        done_stamps, done_poses = track.done.arrays()
        window = [f for f in sorted(track.stamps) if self._estimate.exists(track.key(f))]
        stamps = np.concatenate([done_stamps, np.array([track.stamps[f] for f in window], np.int64)])
        live = [self._pose(track, f) for f in window]
        poses = np.concatenate([done_poses, np.array(live, np.float64).reshape(-1, 4, 4)])
        return stamps, poses

    def bridged(self, stamp_nanos: int, robot: str | None = None) -> bool:
        """Whether the robot's pose at this stamp lies in a fragment not (yet) tied to the world: begun
        after a long gap and never seen together with the world's tags since (then its placement is
        the gap's guess; its poses relative to each other and its own tags are as good as any). A frame
        that left the graph while bridged stays bridged."""
        track = self._tracks.get(robot if robot is not None else next(iter(self._tracks), ""))
        return track is not None and self._bridged_in(track, stamp_nanos)

    def _bridged_in(self, track: _Track, stamp_nanos: int) -> bool:
        if any(first <= stamp_nanos <= last for first, last in track.sealed):
            return True
        fragment = WORLD_FRAGMENT
        for start, f in track.fragment_starts:
            if start > stamp_nanos:
                break
            fragment = f
        return not self._tied(fragment)

    def tag_bridged(self, tag_id: int) -> bool:
        """Whether a mapped tag lies in a fragment not (yet) tied to the world (its pose is a gap's guess)."""
        return not self._tied(self._tag_fragment.get(tag_id, WORLD_FRAGMENT))

    def _tied(self, fragment: int) -> bool:
        """Whether a fragment has been joined to the world's."""
        return self._fragments.find(fragment) == self._fragments.find(WORLD_FRAGMENT)

    def tag_map(self) -> dict[int, tuple[float, Array]]:
        """Current tag poses: id -> (size, world_from_tag)."""
        return {t: (size, pose) for t, size in self.tags.items() if (pose := self._world_from_tag(t)) is not None}


def _constant_velocity_error(
    g1: int, g2: int
) -> Callable[[gtsam.CustomFactor, gtsam.Values, list[Array] | None], NDArray[np.float64]]:
    """Error of poses (A, B, C) taken g1 and g2 frames apart: Log(B^-1 C) - (g2 / g1) Log(A^-1 B), with
    its Jacobians (GTSAM's chain rule through between and Logmap)."""
    ratio = g2 / g1

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jacobians: list[Array] | None) -> NDArray[np.float64]:
        ka, kb, kc = this.keys()
        pa, pb, pc = values.atPose3(ka), values.atPose3(kb), values.atPose3(kc)
        h = [np.zeros((6, 6), order="F") for _ in range(6)]
        d1 = pa.between(pb, h[0], h[1])
        d2 = pb.between(pc, h[2], h[3])
        log1 = gtsam.Pose3.Logmap(d1, h[4])
        log2 = gtsam.Pose3.Logmap(d2, h[5])
        if jacobians is not None:
            jacobians[0] = -ratio * h[4] @ h[0]
            jacobians[1] = h[5] @ h[2] - ratio * h[4] @ h[1]
            jacobians[2] = h[5] @ h[3]
        return np.asarray(log2 - ratio * log1, np.float64)

    return error


def rescale_observation(o: Observation, size_m: float) -> Observation:
    """The same view of a tag of another size: a planar PnP's pose scales its translation with the
    tag's size (the same pixels), rotations and reprojection errors unchanged."""
    k = size_m / o.size_m

    def scaled(m: Array) -> Array:
        out = np.array(m, np.float64, copy=True)
        out[:3, 3] *= k
        return out

    return replace(
        o, size_m=size_m, camera_from_tag=scaled(o.camera_from_tag), alt_camera_from_tag=scaled(o.alt_camera_from_tag)
    )


def camera_prior(world_from_tag: Array, camera_from_tag: Array, view_cov: Array, tag_cov: Array) -> tuple[Array, Array]:
    """A view of a tag as a prior on the camera alone: (world_from_camera, its 6x6 covariance in GTSAM's
    tangent, rotation first). BetweenFactor(camera, tag, m) perturbs m on the right, m exp(xi); the
    camera, t m^-1, then moves by exp(-Ad_m xi). The tag's own uncertainty, t exp(eta), moves it by
    exp(Ad_m eta). So the covariance is Ad_m (S_view + S_tag) Ad_m^T; for a tag held fixed the prior's
    Mahalanobis distance equals the view's at every camera pose (tested)."""
    ad = np.asarray(_pose3(camera_from_tag).AdjointMap())
    return world_from_tag @ np.linalg.inv(camera_from_tag), _spd(ad @ (view_cov + tag_cov) @ ad.T)


def pnp_covariance(camera_from_tag: Array, size_m: float, focal_px: float, pixel_sigma: float) -> Array:
    """Covariance (6x6, GTSAM's Pose3 tangent in the tag frame: rotation, then translation) of a pose
    fitted to the tag's 16 lattice keypoints with independent pixel noise `pixel_sigma`: sigma^2 (J^T
    J)^-1, J = d(pixels) / d(pose) at the pose (a right perturbation T Exp(xi), as BetweenFactor's error).
    Variances are capped at 1 (rad^2 or m^2): a degenerate view tells nothing more, not an infinite
    nothing (the graph stays well conditioned)."""
    r, t = np.asarray(camera_from_tag, np.float64)[:3, :3], np.asarray(camera_from_tag, np.float64)[:3, 3]
    pts = lattice_in_tag(size_m)
    cam = pts @ r.T + t  # (16, 3) in the camera
    z = np.maximum(cam[:, 2], 1e-6)
    x, y = cam[:, 0] / z, cam[:, 1] / z
    jac_proj = np.zeros((16, 2, 3))
    jac_proj[:, 0, 0] = jac_proj[:, 1, 1] = focal_px / z
    jac_proj[:, 0, 2] = -focal_px * x / z
    jac_proj[:, 1, 2] = -focal_px * y / z
    skew = np.zeros((16, 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -pts[:, 2], pts[:, 1], -pts[:, 0]
    skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = pts[:, 2], -pts[:, 1], pts[:, 0]
    d_cam = np.concatenate([-r @ skew, np.broadcast_to(r, (16, 3, 3))], axis=2)  # (16, 3, 6)
    jac = (jac_proj @ d_cam).reshape(32, 6)
    vals, vecs = np.linalg.eigh(jac.T @ jac)
    variances = np.minimum(pixel_sigma**2 / np.maximum(vals, 1e-300), 1.0)
    return (vecs * variances) @ vecs.T


def world_covariance(tangent: Array, world_from_camera: Array) -> Array:
    """GTSAM's Pose3 covariance (6x6: rotation, then translation, as a right perturbation T Exp(xi) in the
    camera frame) -> the same uncertainty in the world frame, position (m) first, then rotation (rad)
    about the world's axes (ROS PoseWithCovariance's order). To first order T Exp(xi) moves the camera
    centre by R v and turns it by R w about the world's axes (R: world_from_camera's rotation)."""
    r = np.asarray(world_from_camera, np.float64)[:3, :3]
    c = np.asarray(tangent, np.float64)
    swap = np.block([[c[3:, 3:], c[3:, :3]], [c[:3, 3:], c[:3, :3]]])  # (v, w) order
    rot = np.zeros((6, 6))
    rot[:3, :3] = rot[3:, 3:] = r
    out = rot @ swap @ rot.T
    return (out + out.T) / 2


def _spd(cov: Array) -> Array:
    """A symmetric positive-definite copy of a marginal covariance (tiny jitter against round-off)."""
    c = np.asarray(cov, np.float64)
    c = (c + c.T) / 2
    return c + np.eye(len(c)) * 1e-12


def umeyama_se3(src: Array, dst: Array) -> Array:
    """Rigid transform T (4x4) minimising ||T src - dst|| for Nx3 point sets (no scale)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    cov = (dst - mu_d).T @ (src - mu_s) / len(src)
    u, _, vt = np.linalg.svd(cov)
    d = np.eye(3)
    d[2, 2] = math.copysign(1.0, float(np.linalg.det(u @ vt)))
    r = u @ d @ vt
    t = np.eye(4)
    t[:3, :3] = r
    t[:3, 3] = mu_d - r @ mu_s
    return t


def absolute_trajectory_error(est: dict[int, Array], gt: dict[int, Array]) -> tuple[float, int]:
    """ATE RMSE (metres) after SE(3) alignment over the stamps both trajectories share."""
    common = sorted(set(est) & set(gt))
    return absolute_trajectory_error_arrays(
        np.array(common, np.int64),
        np.array([est[s][:3, 3] for s in common]).reshape(-1, 3),
        np.array(common, np.int64),
        np.array([gt[s][:3, 3] for s in common]).reshape(-1, 3),
    )


def _matched(est_stamps: Array, est_positions: Array, gt_stamps: Array, gt_positions: Array) -> tuple[Array, Array]:
    """The estimate's and the truth's positions at the stamps both have (m, 3) each."""
    _, ie, ig = np.intersect1d(est_stamps, gt_stamps, assume_unique=False, return_indices=True)
    return np.asarray(est_positions)[ie], np.asarray(gt_positions)[ig]


def truth_in_estimate_frame(
    est_stamps: Array, est_positions: Array, gt_stamps: Array, gt_positions: Array
) -> Array | None:
    """Ground-truth positions (n, 3) moved into the estimate's frame by the SE(3) fit over the stamps
    both have (None with fewer than 3): what a viewer draws beside a trajectory whose world is not the
    truth's (slam without world poses works in its anchor tag's frame)."""
    a, b = _matched(est_stamps, est_positions, gt_stamps, gt_positions)
    if len(a) < 3:
        return None
    t = umeyama_se3(b, a)
    return np.asarray((t[:3, :3] @ np.asarray(gt_positions).T).T + t[:3, 3])


def absolute_trajectory_error_arrays(
    est_stamps: Array, est_positions: Array, gt_stamps: Array, gt_positions: Array, *, align: bool = True
) -> tuple[float, int]:
    """`absolute_trajectory_error` for arrays of stamps (n,) and positions (n, 3): after SE(3) alignment
    (TUM's ATE), or as they are (`align=False`: the trajectory is in the ground truth's world)."""
    a, b = _matched(est_stamps, est_positions, gt_stamps, gt_positions)
    if len(a) < 3:
        raise ValueError(f"need >= 3 matching stamps, have {len(a)}")
    if align:
        t = umeyama_se3(a, b)
        a = (t[:3, :3] @ a.T).T + t[:3, 3]
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1)))), len(a)
