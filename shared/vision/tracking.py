"""Track-then-refine: carry tags that stage 1 missed from frame to frame (pure; robot_infer wires it).

Stage 1 (AprilTag 3) decodes a tag or loses it; under motion blur it loses half of them. A tag seen a
moment ago has not gone anywhere, so:

- `TagTracker` keeps each tag's last two quads (black-square corners TL, TR, BR, BL in OpenCV pixels)
  with their frame numbers, and its last two stage-1 detections. `predict(frame, detected)` proposes a
  quad for every tag seen within `max_age_frames` that stage 1 did not report now: the centre at
  constant velocity, the shape of the last detection scaled at the detections' rate.
- `verify_tag` is the gate a predicted tag must pass before it is used: the tag region is rectified
  through the quad (searching small shifts, the prediction's error), every cell's mean intensity is
  correlated with the tag's own 10x10 pattern and with every other tag36h11 code word in all four
  rotations, each pattern blurred along the tag's image motion (the exposure time is unknown, so
  several lengths). It passes when its own pattern correlates well and beats every other candidate by
  a margin: a soft decode that still works where blur has smeared the bits past a hard decode, and
  refuses a blank wall, another tag or a rotated view of itself (the rectification, code book and
  blur operators are `shared.vision.softdecode`'s, which the line quads' blind decode uses too).
- The verified quad (with the shift that aligned it best) becomes the ROI, the network refines the
  keypoints, and `update` records the refined corners for the next prediction.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from shared.vision.geometry import Array, clear_of_border
from shared.vision.softdecode import DATA_CELLS, SIDE_PX, blur_operator, code_book, normalise, rectify


class TrackingSettings(BaseModel):
    """When a missed tag is predicted and what it takes to accept it."""

    model_config = ConfigDict(extra="forbid")
    enabled: bool = False  # off by default: on bench/slam's fast sequence it adds frames but costs accuracy
    max_age_frames: int = Field(default=8, ge=1)  # predict a tag this many frames after its last sighting
    # Predict a tag at most this many frames after stage 1 last decoded it: under heavy blur the refined
    # quads drift in scale (a few % in 10-20 frames, measured on bench/slam's fast sequence), so a track
    # must be re-anchored.
    max_coasting_frames: int = Field(default=12, ge=1)
    max_tracked_per_frame: int = Field(default=8, ge=0)  # bounds the cost on a frame
    search_px: float = Field(default=6.0, ge=0)  # shifts searched around the predicted quad (+-, image px)
    search_step_px: float = Field(default=1.5, gt=0)  # the coarse grid; then a finer one around its best
    min_correlation: float = Field(default=0.75, gt=0, le=1)  # own pattern vs the rectified cells
    min_margin: float = Field(default=0.15, ge=0)  # own pattern's correlation minus the best other's
    min_side_px: float = Field(default=12.0, gt=0)  # smaller predicted quads are not verifiable
    # A predicted quad must lie this far inside the image's edge, plus search_px (the gate may move it
    # that far): as stage 1's border_margin_px, a tag at the edge cannot be measured.
    border_margin_px: float = Field(default=4.0, ge=0)
    # The keypoint-confidence gate after the network refined a tracked tag: the 16 points must lie on a
    # plane's projection (RMS PnP reprojection error), as a sure keypoint set does.
    max_refined_reprojection_px: float = Field(default=1.0, gt=0)


@dataclass
class _Track:
    frames: list[int] = field(default_factory=list)  # the last two sightings (detected or tracked)
    quads: list[Array] = field(default_factory=list)
    detected_frames: list[int] = field(default_factory=list)  # the last two stage-1 detections
    detected_quads: list[Array] = field(default_factory=list)

    @property
    def last_detected(self) -> int:
        return self.detected_frames[-1] if self.detected_frames else -1


@dataclass(frozen=True)
class Prediction:
    """A quad predicted for a tag stage 1 missed."""

    tag_id: int
    corners_px: Array  # (4, 2) TL, TR, BR, BL
    velocity_px: Array  # (4, 2) per frame
    age_frames: int  # frames since the last sighting


class TagTracker:
    """Per-tag quads over time (see the module docstring). Frame numbers must increase."""

    def __init__(self, settings: TrackingSettings | None = None) -> None:
        self.settings = settings or TrackingSettings()
        self._tracks: dict[int, _Track] = {}
        self.last_frame = -1  # the newest frame `update` saw
        code_book()  # built once here (587 code words x 4 rotations), not on the first missed tag

    def predict(self, frame: int, detected: set[int], image_size: tuple[int, int]) -> list[Prediction]:
        """Quads for the recently seen tags stage 1 missed in `frame`, the freshest first; only those
        clear of the image's edge (width, height; see border_margin_px) and large enough to verify."""
        s = self.settings
        out = []
        width, height = image_size
        for tag_id, tr in self._tracks.items():
            age = frame - tr.frames[-1]
            if tag_id in detected or not 0 < age <= s.max_age_frames:
                continue
            if frame - tr.last_detected > s.max_coasting_frames:
                continue
            quad, velocity = self._extrapolate(tr, frame)
            sides = np.linalg.norm(quad - np.roll(quad, 1, axis=0), axis=1)
            inside = clear_of_border(quad, (height, width), s.border_margin_px + s.search_px)
            if sides.min() < s.min_side_px or not inside:
                continue
            out.append(Prediction(tag_id, quad, velocity, age))
        out.sort(key=lambda p: p.age_frames)
        return out[: s.max_tracked_per_frame]

    @staticmethod
    def _extrapolate(tr: _Track, frame: int) -> tuple[Array, Array]:
        """The quad at `frame`: its centre at constant velocity from the last two sightings; its shape
        from the last stage-1 detection, scaled at the rate between the last two detections. Tracked
        quads move the centre but never the shape: under heavy blur their scale drifts (measured)."""
        centres = [q.mean(axis=0) for q in tr.quads]
        if len(tr.frames) >= 2:
            centre_velocity = (centres[-1] - centres[-2]) / (tr.frames[-1] - tr.frames[-2])
        else:
            centre_velocity = np.zeros(2)
        centre = centres[-1] + centre_velocity * (frame - tr.frames[-1])
        base = tr.detected_quads[-1] if tr.detected_quads else tr.quads[-1]
        shape = base - base.mean(axis=0)
        rate = 0.0
        if len(tr.detected_frames) >= 2 and 0 < tr.detected_frames[-1] - tr.detected_frames[-2] <= 3:
            size = [float(np.linalg.norm(q - q.mean(axis=0), axis=1).mean()) for q in tr.detected_quads]
            rate = (size[-1] / max(size[-2], 1e-9) - 1.0) / (tr.detected_frames[-1] - tr.detected_frames[-2])
        since = frame - (tr.detected_frames[-1] if tr.detected_frames else tr.frames[-1])
        quad = centre + shape * (1.0 + rate * since)
        velocity = np.tile(centre_velocity, (4, 1)) + shape * rate
        return quad, velocity

    def update(self, frame: int, quads: dict[int, Array], detected: set[int]) -> None:
        """Record this frame's quads (the refined corners of stage 1's tags, `detected`, and of the
        verified tracked ones); forget tags unseen for longer than the prediction reaches."""
        for tag_id, quad in quads.items():
            tr = self._tracks.setdefault(tag_id, _Track())
            if tr.frames and frame <= tr.frames[-1]:
                continue
            q = np.asarray(quad, np.float64).reshape(4, 2)
            if tag_id in detected:
                tr.detected_frames = [*tr.detected_frames[-1:], frame]
                tr.detected_quads = [*tr.detected_quads[-1:], q]
            tr.frames = [*tr.frames[-1:], frame]
            tr.quads = [*tr.quads[-1:], q]
        self.last_frame = max(self.last_frame, frame)
        horizon = self.settings.max_age_frames
        for tag_id in [t for t, tr in self._tracks.items() if frame - tr.frames[-1] > horizon]:
            del self._tracks[tag_id]

    def reset(self) -> None:
        """Forget every track (a new camera session)."""
        self._tracks.clear()
        self.last_frame = -1


# ----------------------------------------------------------------------------------------------------
# The verification gate


@dataclass(frozen=True)
class Verdict:
    """What the gate found: accepted or not, the scores, and the best-aligned quad."""

    accepted: bool
    correlation: float  # own pattern
    best_other: float  # the best other id or rotation
    corners_px: Array  # the predicted quad moved by the shift that aligned best


def verify_tag(image: NDArray[np.uint8], prediction: Prediction, settings: TrackingSettings | None = None) -> Verdict:
    """The soft decode of a predicted tag (module docstring): correlations over the 36 data cells of
    the blurred patterns (all 100 cells blur into them), best over a coarse-to-fine search of shifts
    and over the blur lengths; every other code word and rotation at the best alignment."""
    s = settings or TrackingSettings()
    book, ids, rots = code_book()
    own = int(np.flatnonzero((ids == prediction.tag_id) & (rots == 0))[0])
    _, h0 = rectify(image, prediction.corners_px)
    ops = _blur_candidates(prediction, h0)
    # only the data cells' rows of each blur operator are ever compared
    data_ops = [op[DATA_CELLS] for op in ops]
    own_blurred = normalise(np.stack([op @ book[own] for op in data_ops]))

    def score_at(shift: Array) -> tuple[float, int, NDArray[np.float64]]:
        means, _ = rectify(image, prediction.corners_px + shift)
        cand = normalise(means[DATA_CELLS][None, :])[0]
        scores = own_blurred @ cand
        k = int(np.argmax(scores))
        return float(scores[k]), k, cand

    best = (-2.0, 0, np.zeros(2), np.zeros(len(DATA_CELLS)))
    coarse = np.arange(-s.search_px, s.search_px + 1e-9, s.search_step_px)
    fine = np.arange(-s.search_step_px / 2, s.search_step_px / 2 + 1e-9, s.search_step_px / 4)
    for grid, centre in ((coarse, np.zeros(2)), (fine, None)):
        origin = best[2] if centre is None else centre
        for dx in grid:
            for dy in grid:
                shift = origin + np.array([dx, dy])
                sc, k, cand = score_at(shift)
                if sc > best[0]:
                    best = (sc, k, shift, cand)
    score, k, shift, cand = best
    quad = prediction.corners_px + shift
    others = normalise(book @ data_ops[k].T) @ cand
    others[own] = -1.0
    best_other = float(others.max())
    accepted = score >= s.min_correlation and score - best_other >= s.min_margin
    return Verdict(accepted, score, best_other, quad)


def _blur_candidates(prediction: Prediction, rect_from_image: Array) -> list[NDArray[np.float64]]:
    """Blur operators for exposures of 0, 1/3, 2/3 and all of the frame interval, along the tag's image
    motion mapped into the rectified patch."""
    centre = prediction.corners_px.mean(axis=0)
    motion = prediction.velocity_px.mean(axis=0)
    a = _apply(rect_from_image, centre[None, :])[0]
    b = _apply(rect_from_image, (centre + motion)[None, :])[0]
    d = b - a
    ops = []
    for frac in (0.0, 1.0 / 3.0, 2.0 / 3.0, 1.0):
        dq = np.round(d * frac * 2).astype(int)
        dq = np.clip(dq, -2 * SIDE_PX, 2 * SIDE_PX)
        ops.append(blur_operator(int(dq[0]), int(dq[1])))
    return ops


def _apply(h: Array, pts: Array) -> Array:
    q = np.column_stack([pts, np.ones(len(pts))]) @ h.T
    return q[:, :2] / q[:, 2:3]
