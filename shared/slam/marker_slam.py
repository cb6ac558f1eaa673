"""Marker SLAM core: a factor graph over camera poses X_i and tag poses L_j, solved incrementally
with GTSAM's iSAM2. No I/O: the slam service feeds it TagPoses and publishes what it returns.

- World frame: anchored at a configured tag (or the first one seen), whose pose gets a tight prior
  (identity, or its world pose from a tag map).
- Each tag observation is a BetweenFactorPose3(X_i, L_j, camera_from_tag) with a Huber-robust
  Gaussian noise model from the viewing geometry: pixel noise (>= the observation's reprojection
  error) propagated to lateral (d / f), depth (d^2 / (f s)) and rotation (1 / (f s / d)), inflated
  with the tilt; the covariance is rotated into the tag frame, where GTSAM's Pose3 error lives.
- New tags are initialised from the current camera estimate; a frame with no known tag cannot be
  localised ("lost") unless it is the very first.
- A constant-velocity motion prior (BetweenFactor predicting this frame's motion from the last one,
  sigma growing with the frame gap) ties consecutive camera poses: with tags near one plane, pitch
  and height trade off within a single frame.
- Ambiguity guard: an observation whose two IPPE branches have similar reprojection error and
  whose chosen branch disagrees with the map's prediction is rejected and counted, not fused.
- Localisation-only mode: all tag poses fixed from a tag-map file; unknown tags are ignored.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Final

import gtsam
import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from shared.vision.geometry import Array
from shared.wire.messages import TagPose

X = gtsam.symbol_shorthand.X
L = gtsam.symbol_shorthand.L


class SlamSettings(BaseModel):
    """Tuning of the SLAM core."""

    model_config = ConfigDict(extra="forbid")
    anchor_tag_id: int | None = None  # None: the first tag seen
    localisation_only: bool = False
    focal_px: float = Field(default=1045.0, gt=0)  # only for observations whose message had no intrinsics (v1)
    min_pixel_sigma: float = Field(default=0.5, gt=0)
    anchor_sigma: float = 1e-6
    # Tags whose world pose a tag map (or a resumed checkpoint) gives are priors with this sigma
    # (rad and m) when first seen, so the map is kept and any mapped tag in view localises the camera.
    known_tag_sigma: float = Field(default=1e-3, gt=0)
    ambiguity_ratio: float = Field(default=2.0, gt=1)  # alt/chosen error below this = ambiguous
    disagreement_deg: float = Field(default=10.0, gt=0)
    huber_k: float = 1.5
    relinearize_threshold: float = 0.01
    # Measured on PnP from 16 keypoints with 0.4 px noise: rotation errors are ~3x the naive
    # pixel/size estimate and depth errors ~0.3x of it (16 points average the scale).
    rotation_sigma_scale: float = 3.0
    depth_sigma_scale: float = 0.3
    # Smooth-motion prior between consecutive frames (no odometry): sigma per frame of gap.
    motion_sigma_m: float = Field(default=0.03, gt=0)
    motion_sigma_deg: float = Field(default=1.5, gt=0)
    motion_max_gap_frames: int = 15


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
        )


@dataclass
class FrameResult:
    """What one update produced."""

    world_from_camera: Array | None
    status: str  # "tracking" | "lost"
    tags_used: int
    rejected_ambiguous: int
    map_changed: bool


@dataclass
class SlamState:
    """Counters."""

    frames: int = 0
    lost: int = 0
    rejected_ambiguous: int = 0
    observations: dict[int, int] = field(default_factory=dict)


def _pose3(m: Array) -> gtsam.Pose3:
    return gtsam.Pose3(np.asarray(m, np.float64))


def _rot_deg(a: Array, b: Array) -> float:
    c = (np.trace(a[:3, :3] @ b[:3, :3].T) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(c, -1, 1))))


class SlamInputError(ValueError):
    """A frame or observation the SLAM core refuses (the state is unchanged)."""


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
    camera session the index follows seq (so gaps of dropped frames stay gaps for the motion prior);
    a seq that goes back while the capture time goes forward is a new camera session, which continues
    the index after a break wider than any motion prior; a (seq, time) seen before, or a frame older
    than the last one, is refused."""

    def __init__(
        self,
        *,
        session_break: int = 1_000,
        remember: int = 4_096,
        max_future_secs: float = 60.0,
        clock_nanos: Callable[[], int] = time.time_ns,
    ) -> None:
        self.session_break = session_break
        # A capture time far in the future would make every real frame after it look stale.
        self.max_future_nanos = int(max_future_secs * 1e9)
        self._clock_nanos = clock_nanos
        self._offset = 0
        self._last: tuple[int, int] | None = None  # (seq, capture_nanos) of the newest frame
        self._seen: dict[tuple[int, int], int] = {}
        self._remember = remember
        self.sessions = 1

    def index(self, seq: int, capture_nanos: int) -> int:
        """The SLAM frame index for this frame; SlamInputError for a repeated or stale one."""
        key = (seq, capture_nanos)
        if capture_nanos > self._clock_nanos() + self.max_future_nanos:
            raise SlamInputError(f"frame seq {seq} was captured {capture_nanos} ns, in the future beyond the bound")
        if key in self._seen:
            raise SlamInputError(f"frame seq {seq} (captured {capture_nanos}) was already fused: a repeated message")
        if self._last is not None:
            last_seq, last_time = self._last
            if capture_nanos <= last_time:
                raise SlamInputError(f"frame seq {seq} is older than the last one (seq {last_seq}): out of order")
            if seq <= last_seq:  # the camera restarted: a new session after a break
                self._offset = self._offset + last_seq + self.session_break - seq
                self.sessions += 1
        index = self._offset + seq
        self._last = key
        self._seen[key] = index
        if len(self._seen) > self._remember:
            self._seen.pop(next(iter(self._seen)))
        return index


class MarkerSlam:
    """Incremental marker SLAM (see module docstring)."""

    def __init__(self, settings: SlamSettings, known_tags: dict[int, tuple[float, Array]] | None = None) -> None:
        self.settings = settings
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(settings.relinearize_threshold)
        self.isam = gtsam.ISAM2(params)
        self.known = known_tags or {}  # id -> (size, world_from_tag) from a tag map
        self.tags: dict[int, float] = {}  # ids in the graph -> size
        self.poses: dict[int, Array] = {}  # frame index -> current estimate
        self.stamps: dict[int, int] = {}
        self.state = SlamState()
        self.anchor: int | None = None
        self._estimate = gtsam.Values()
        if settings.localisation_only:
            if not self.known:
                raise ValueError("localisation-only mode needs a tag map with world poses")
            graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
            for tag_id, (size, pose) in self.known.items():
                graph.add(
                    gtsam.PriorFactorPose3(
                        L(tag_id), _pose3(pose), gtsam.noiseModel.Isotropic.Sigma(6, settings.anchor_sigma)
                    )
                )
                values.insert(L(tag_id), _pose3(pose))
                self.tags[tag_id] = size
            self.isam.update(graph, values)
            self._estimate = self.isam.calculateEstimate()

    # ------------------------------------------------------------------------------------------

    def noise(self, obs: Observation) -> gtsam.noiseModel.Base:
        """Robust Gaussian noise of one observation, in the tag frame (rotation first, as GTSAM)."""
        s = self.settings
        t = obs.camera_from_tag[:3, 3]
        d = max(0.05, float(np.linalg.norm(t)))
        normal = obs.camera_from_tag[:3, 2]
        cos_tilt = max(0.2, abs(float(np.dot(normal, t / d))))
        px = max(s.min_pixel_sigma, obs.reprojection_error_px)
        focal = obs.focal_px if obs.focal_px is not None else s.focal_px
        size_px = focal * obs.size_m / d
        lateral = d * px / focal
        depth = s.depth_sigma_scale * d * px / size_px / cos_tilt
        rot = s.rotation_sigma_scale * px / size_px / cos_tilt
        cov_t_cam = np.diag([lateral**2, lateral**2, depth**2])
        r = obs.camera_from_tag[:3, :3]
        cov = np.zeros((6, 6))
        cov[:3, :3] = np.eye(3) * rot**2
        cov[3:, 3:] = r.T @ cov_t_cam @ r
        gauss = gtsam.noiseModel.Gaussian.Covariance(cov)
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(s.huber_k), gauss)

    def _check_input(self, frame: int, observations: list[Observation]) -> None:
        if not 0 <= frame <= MAX_FRAME_INDEX:
            raise SlamInputError(f"frame index {frame} is outside 0..2**56-1")
        if frame in self.stamps or self._estimate.exists(X(frame)):
            raise SlamInputError(f"frame {frame} was already fused (a repeated message or a restarted camera)")
        for o in observations:
            check_observation(o)

    def _world_from_tag(self, tag_id: int) -> Array | None:
        if tag_id in self.tags and self._estimate.exists(L(tag_id)):
            return np.asarray(self._estimate.atPose3(L(tag_id)).matrix())
        return None

    def update(self, frame: int, stamp_nanos: int, observations: list[Observation]) -> FrameResult:
        """Fuse one frame's observations; returns the camera pose estimate for it. Raises SlamInputError,
        before touching any state, for a frame it has seen, a frame index GTSAM cannot key, or an
        observation that is no rigid pose in front of the camera."""
        self._check_input(frame, observations)
        s = self.settings
        self.state.frames += 1
        graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
        map_changed = False
        for o in observations:
            if o.tag_id in self.known and o.tag_id not in self.tags:
                size, pose = self.known[o.tag_id]
                anchor = o.tag_id == s.anchor_tag_id or (self.anchor is None and s.anchor_tag_id is None)
                sigma = s.anchor_sigma if anchor else s.known_tag_sigma
                graph.add(gtsam.PriorFactorPose3(L(o.tag_id), _pose3(pose), gtsam.noiseModel.Isotropic.Sigma(6, sigma)))
                values.insert(L(o.tag_id), _pose3(pose))
                self.tags[o.tag_id] = size
                self._estimate.insert(L(o.tag_id), _pose3(pose))
                if anchor:
                    self.anchor = o.tag_id
                map_changed = True
        if self.anchor is None and not s.localisation_only:
            chosen = [o for o in observations if s.anchor_tag_id is None or o.tag_id == s.anchor_tag_id]
            if chosen:
                a = min(chosen, key=lambda o: o.reprojection_error_px)
                self.anchor = a.tag_id
                pose = self.known[a.tag_id][1] if a.tag_id in self.known else np.eye(4)
                graph.add(
                    gtsam.PriorFactorPose3(
                        L(a.tag_id), _pose3(pose), gtsam.noiseModel.Isotropic.Sigma(6, s.anchor_sigma)
                    )
                )
                values.insert(L(a.tag_id), _pose3(pose))
                self.tags[a.tag_id] = a.size_m
                self._estimate.insert(L(a.tag_id), _pose3(pose))
                map_changed = True
        # Camera initial guess from the known tags in view (median position of the per-tag guesses).
        guesses = []
        for o in observations:
            wt = self._world_from_tag(o.tag_id)
            if wt is not None:
                guesses.append((o, wt @ np.linalg.inv(o.camera_from_tag)))
        if not guesses:
            self.state.lost += 1
            return FrameResult(None, "lost", 0, 0, map_changed)
        centre = np.median(np.array([g[:3, 3] for _, g in guesses]), axis=0)
        init = min(guesses, key=lambda og: np.linalg.norm(og[1][:3, 3] - centre))[1]
        used, rejected = 0, 0
        for o in observations:
            wt = self._world_from_tag(o.tag_id)
            if wt is not None:
                ambiguous = o.alt_reprojection_error_px < s.ambiguity_ratio * max(1e-6, o.reprojection_error_px)
                predicted = np.linalg.inv(init) @ wt
                if ambiguous and len(guesses) > 1 and _rot_deg(o.camera_from_tag, predicted) > s.disagreement_deg:
                    rejected += 1
                    continue
            elif s.localisation_only:
                continue
            else:
                new = init @ o.camera_from_tag
                values.insert(L(o.tag_id), _pose3(new))
                self.tags[o.tag_id] = o.size_m
                map_changed = True
            graph.add(gtsam.BetweenFactorPose3(X(frame), L(o.tag_id), _pose3(o.camera_from_tag), self.noise(o)))
            self.state.observations[o.tag_id] = self.state.observations.get(o.tag_id, 0) + 1
            used += 1
        self.state.rejected_ambiguous += rejected
        if used == 0:
            self.state.lost += 1
            return FrameResult(None, "lost", 0, rejected, map_changed)
        values.insert(X(frame), _pose3(init))
        graph_motion = self._motion_factor(frame)
        if graph_motion is not None:
            graph.add(graph_motion)
        self.isam.update(graph, values)
        self._estimate = self.isam.calculateEstimate()
        pose = np.asarray(self._estimate.atPose3(X(frame)).matrix())
        self.poses[frame] = pose
        self.stamps[frame] = stamp_nanos
        return FrameResult(pose, "tracking", used, rejected, map_changed)

    def _motion_factor(self, frame: int) -> gtsam.BetweenFactorPose3 | None:
        """Constant-velocity prior: the last frame-to-frame motion predicts this one (no odometry)."""
        s = self.settings
        done = sorted(self.poses)
        if not done or not 0 < frame - done[-1] <= s.motion_max_gap_frames:
            return None
        prev = done[-1]
        gap = frame - prev
        if len(done) < 2 or done[-1] - done[-2] != gap:
            return None  # velocity unknown: no prior rather than a biased one
        delta = np.linalg.inv(self.poses[done[-2]]) @ self.poses[prev]
        sig = np.array([math.radians(s.motion_sigma_deg)] * 3 + [s.motion_sigma_m] * 3) * gap
        return gtsam.BetweenFactorPose3(X(prev), X(frame), _pose3(delta), gtsam.noiseModel.Diagonal.Sigmas(sig))

    def trajectory(self) -> list[tuple[int, Array]]:
        """Smoothed (final) camera poses: (stamp_nanos, world_from_camera) in frame order."""
        out = []
        for frame in sorted(self.stamps):
            if self._estimate.exists(X(frame)):
                out.append((self.stamps[frame], np.asarray(self._estimate.atPose3(X(frame)).matrix())))
        return out

    def tag_map(self) -> dict[int, tuple[float, Array]]:
        """Current tag poses: id -> (size, world_from_tag)."""
        return {t: (size, pose) for t, size in self.tags.items() if (pose := self._world_from_tag(t)) is not None}


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
    if len(common) < 3:
        raise ValueError(f"need >= 3 matching stamps, have {len(common)}")
    a = np.array([est[s][:3, 3] for s in common])
    b = np.array([gt[s][:3, 3] for s in common])
    t = umeyama_se3(a, b)
    aligned = (t[:3, :3] @ a.T).T + t[:3, 3]
    return float(np.sqrt(np.mean(np.sum((aligned - b) ** 2, axis=1)))), len(common)
