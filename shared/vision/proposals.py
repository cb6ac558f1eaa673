"""Stage 1 with three proposers: AprilTag 3 first, OpenCV's ArUco detector and the line-quad proposer
for what it misses.

AprilTag 3 finds a quad by clustering gradient edges and fitting lines; at `quad_decimate = 2` small
tags vanish, and a border that is partly covered or smeared breaks the quad. OpenCV's ArUco detector
finds quads another way (adaptive thresholds at several window sizes, contours, polygon fits) and
decodes the same tag36h11 code book (`DICT_APRILTAG_36h11`), so it recovers tags AprilTag lost and
vice versa. `Stage1Detector.detect` runs both and merges them by id and place: where both report a
tag, AprilTag's corners stay (its edge refinement is the better corner estimate); a tag only ArUco
decoded is added, marked with `proposer = "aruco"`, once it passes the gate that tracked tags pass
(`shared.vision.tracking.verify_tag`, a soft decode against every tag36h11 code word): OpenCV corrects
up to 3 bit errors, the gate refuses what is not clearly the tag it claims to be.

A quad with a corner within `border_margin_px` (4 px) of the image's edge is refused whoever found it:
with no white beyond its outer edge there, its corners and the network's keypoints are guesses.

Conventions: OpenCV's `DICT_APRILTAG_36h11` marker images are AprilTag's canonical tags rotated by
180 deg, so ArUco's corner 0 (its marker's top-left) is the canonical tag's bottom-right: ArUco's
corners c0..c3 are our BR, BL, TL, TR. OpenCV's corners are in OpenCV's pixel convention already
(no +0.5 as pupil-apriltags has). Both are checked on exact renders by tests/test_proposals.py.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

import cv2
import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, field_validator

from shared.vision.detector import (
    Detection,
    DetectorSettings,
    Stage1,
    TagDetector,
    merge_proposals,
    quad_side_px,
)
from shared.vision.geometry import check_image, clear_of_border
from shared.vision.linequads import LineQuadProposer, LineQuadSettings
from shared.vision.tracking import Prediction as TrackPrediction
from shared.vision.tracking import TrackingSettings, verify_tag

_ARUCO_TO_TL_TR_BR_BL: Final[list[int]] = [2, 3, 0, 1]


class ArucoSettings(BaseModel):
    """The second proposer: OpenCV's ArUco detector on the AprilTag 36h11 dictionary."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    enabled: bool = True  # the ArUco proposer, for the tags AprilTag missed
    # Bits the decoder may correct, as a fraction of the dictionary's capacity (OpenCV's default 0.6:
    # 3 of 36h11's 5 bits); the gate below then refuses what is not the tag.
    error_correction_rate: float = Field(default=0.6, ge=0.0, le=1.0)
    # Adaptive-threshold window sizes (px): min, max, step. OpenCV's defaults (3, 23, 10) threshold
    # three times; 7 and 17 find as many tags on bench/accuracy's renders for 25-50 % less time
    # (bench/photos: 2 fewer real-photo tags from ArUco alone, none fewer after merging at decimate 1).
    threshold_window_px: tuple[int, int, int] = (7, 17, 10)
    min_perimeter_rate: float = Field(default=0.03, gt=0.0)  # of the image's larger side (OpenCV's default)
    corner_refinement: bool = True  # sub-pixel corners (OpenCV's CORNER_REFINE_SUBPIX)
    # The gate an ArUco-only tag passes (shared.vision.tracking.verify_tag, the soft decode of tracked
    # tags): its own pattern must correlate this well with the rectified cells and beat every other
    # code word and rotation by this margin; a small shift search absorbs corner error.
    gate_min_correlation: float = Field(default=0.75, gt=0.0, le=1.0)
    # (the gate above) own pattern's correlation minus the best other's
    gate_min_margin: float = Field(default=0.15, ge=0.0)
    gate_search_px: float = Field(default=1.0, ge=0.0)  # (the gate above) shifts searched around the quad, image px

    @field_validator("threshold_window_px")
    @classmethod
    def _windows(cls, v: tuple[int, int, int]) -> tuple[int, int, int]:
        lo, hi, step = v
        if lo < 3 or hi < lo or step < 1:
            raise ValueError(f"threshold_window_px is (min >= 3, max >= min, step >= 1) px, got {v}")
        return v


class FullResSettings(BaseModel):
    """Small tags at full resolution where they were seen (module docstring). Only when AprilTag runs
    decimated (`apriltag.quad_decimate > 1`); state carries from frame to frame, so a detector that is
    fed unrelated images (single-image benches) should turn it off."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    enabled: bool = True  # full-resolution sweeps and windows around small tags
    # A whole frame at full resolution every this many frames (the first frame is one; 0: never): finds
    # the small tags decimation loses, at AprilTag's full-resolution cost on that frame only.
    sweep_every_frames: int = Field(default=30, ge=0)
    # Tags up to this side (px) found in the last `remember_frames` frames are looked for again at full
    # resolution in a window around their last quad (`margin_sides` of their side on each side, for the
    # motion) when the decimated pass misses them; at most `max_regions` windows a frame.
    small_side_px: float = Field(default=64.0, gt=0.0)
    remember_frames: int = Field(default=30, ge=1)  # (above) how long a small tag is looked for again
    margin_sides: float = Field(default=1.0, ge=0.0)  # (above) the window's margin, in tag sides
    max_regions: int = Field(default=8, ge=0)  # (above) full-resolution windows per frame at most


class Stage1Settings(BaseModel):
    """Stage 1 as robot_infer, `splittag detect` and the benches run it."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    apriltag: DetectorSettings = Field(default_factory=DetectorSettings)
    aruco: ArucoSettings = Field(default_factory=ArucoSettings)
    lines: LineQuadSettings = Field(default_factory=LineQuadSettings)
    full_res: FullResSettings = Field(default_factory=FullResSettings)
    # A tag both proposers report is one tag when their centres are closer than this fraction of the
    # larger quad side (one id may appear several times in one image: all are kept).
    same_tag_fraction: float = Field(default=0.5, gt=0.0, le=1.0)
    # A quad with a corner closer than this to the image's edge is refused: the tag's outer edge has no
    # white beyond it there, so neither its corners nor the network's keypoints can be measured (bench.slam's
    # slow room: a tag 0.3 px from the edge read 42 deg off, 29 cm off through its other branch, and
    # SLAM's ATE went 0.85 -> 1.25 cm because of that one read).
    border_margin_px: float = Field(default=4.0, ge=0.0)


@dataclass
class Stage1Counts:
    """What each proposer contributed since start-up."""

    frames: int = 0
    apriltag: int = 0  # tags AprilTag decoded
    aruco_added: int = 0  # tags only ArUco decoded that passed the gate
    aruco_merged: int = 0  # ArUco tags that AprilTag had already
    aruco_refused: int = 0  # ArUco-only tags the gate refused
    lines_added: int = 0  # tags only the line-quad proposer decoded
    lines_merged: int = 0  # line-quad tags the others had already
    lines_soft: int = 0  # line-quad tags read by the blind soft decode (added or merged)
    fullres_sweeps: int = 0  # frames AprilTag ran on at full resolution (FullResSettings.sweep_every_frames)
    fullres_windows: int = 0  # windows around small tags seen before, searched at full resolution
    fullres_added: int = 0  # tags those windows found that the decimated pass had missed
    at_border: int = 0  # quads refused for touching the image's edge (Stage1Settings.border_margin_px)


@dataclass(frozen=True)
class _Seen:
    """A small tag's last sighting: the frame, its id and its quad (one id may be on several tags), with
    the quad's centre and side worked out once."""

    frame: int
    tag_id: int
    corners_px: NDArray[np.float64]
    centre_px: NDArray[np.float64]
    side_px: float

    @staticmethod
    def of(frame: int, d: Detection) -> _Seen:
        corners = np.array(d.corners_px, np.float64)
        return _Seen(frame, d.tag_id, corners, corners.mean(axis=0), max(quad_side_px(corners), 1e-9))

    def gap_sides(self, d: Detection) -> float:
        """How far `d` is from this sighting, in sides of this quad (inf for another id)."""
        if d.tag_id != self.tag_id:
            return float("inf")
        return float(np.linalg.norm(d.corners_px.mean(axis=0) - self.centre_px)) / self.side_px


_MAX_SEEN: Final[int] = 256  # sightings remembered at most (the oldest go first)
# A detection of the same id this close (in sides) is the sighting moved on (one id may be on tags a
# few sides apart: the nearest takes it).
_SAME_SIGHTING_SIDES: Final[float] = 1.5
# AprilTag thresholds on 4 x 4 px tiles counted from the image origin: a window that starts on that grid
# finds the tag exactly as the whole image would (off the grid its corners differ by up to ~0.9 px).
_TILE_PX: Final[int] = 4


class ArucoProposer:
    """OpenCV's ArUco detector on DICT_APRILTAG_36h11, corners in our order and convention."""

    def __init__(self, settings: ArucoSettings | None = None) -> None:
        self.settings = s = settings or ArucoSettings()
        params = cv2.aruco.DetectorParameters()
        params.errorCorrectionRate = s.error_correction_rate
        lo, hi, step = s.threshold_window_px
        params.adaptiveThreshWinSizeMin = lo
        params.adaptiveThreshWinSizeMax = hi
        params.adaptiveThreshWinSizeStep = step
        params.minMarkerPerimeterRate = s.min_perimeter_rate
        params.cornerRefinementMethod = (
            cv2.aruco.CORNER_REFINE_SUBPIX if s.corner_refinement else cv2.aruco.CORNER_REFINE_NONE
        )
        dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
        self._det = cv2.aruco.ArucoDetector(dictionary, params)

    def detect(self, image: NDArray[np.uint8]) -> list[Detection]:
        """Decoded tags of one grayscale image (decision margin and hamming are not reported: 0)."""
        corners, ids, _ = self._det.detectMarkers(check_image(image))
        if ids is None:
            return []
        out = [
            Detection(int(i), 0.0, 0, np.asarray(c, np.float64).reshape(4, 2)[_ARUCO_TO_TL_TR_BR_BL], "aruco")
            for c, i in zip(corners, ids.ravel(), strict=True)
        ]
        return sorted(out, key=lambda d: d.tag_id)


class Stage1Detector:
    """AprilTag 3, then ArUco for the tags it missed, each ArUco-only tag checked by the soft decode
    (module docstring). `detect` returns the merged list sorted by id; each Detection says its
    proposer. Not thread-safe: one per thread."""

    def __init__(self, settings: Stage1Settings | None = None, *, second: Stage1 | None = None) -> None:
        """`second` replaces the ArUco proposer (a test's scripted fake); the gate still applies."""
        self.settings = s = settings or Stage1Settings()
        self._apriltag = TagDetector(s.apriltag)
        self._aruco: Stage1 | None = second or (ArucoProposer(s.aruco) if s.aruco.enabled else None)
        self._lines = LineQuadProposer(s.lines) if s.lines.enabled else None
        full = s.full_res.enabled and s.apriltag.quad_decimate > 1.0
        self._full = TagDetector(s.apriltag.model_copy(update={"quad_decimate": 1.0})) if full else None
        self._seen: list[_Seen] = []  # small tags seen lately (the latest sighting of each)
        self._shape: tuple[int, ...] | None = None  # the last image's shape
        self._since_sweep = 0  # frames since the last full-resolution sweep
        self._gate = TrackingSettings(
            search_px=s.aruco.gate_search_px,
            search_step_px=max(s.aruco.gate_search_px, 0.5),
            min_correlation=s.aruco.gate_min_correlation,
            min_margin=s.aruco.gate_min_margin,
        )
        self.counts = Stage1Counts()

    def detect(self, image: NDArray[np.uint8]) -> list[Detection]:
        """Both proposers on one uint8 grayscale image, merged."""
        img = np.ascontiguousarray(check_image(image))
        frame = self.counts.frames
        every = self.settings.full_res.sweep_every_frames
        resized = img.shape != self._shape
        if resized:  # a new camera (or resolution): old sightings are elsewhere; look at it all at once
            self._seen, self._shape, self._since_sweep = [], img.shape, every
        sweep = self._full is not None and every > 0 and self._since_sweep >= every
        self._since_sweep = 1 if sweep else self._since_sweep + 1
        found = (self._full if sweep and self._full is not None else self._apriltag).detect(img)
        self.counts.frames += 1
        self.counts.apriltag += len(found)
        self.counts.fullres_sweeps += int(sweep)
        if self._full is not None and not sweep:
            windows = self._windows(img, found, frame)
            self.counts.fullres_added += len(windows)
            found.extend(windows)
        if self._aruco is not None:
            new, duplicates = merge_proposals(
                found, self._aruco.detect(img), same_tag_fraction=self.settings.same_tag_fraction
            )
            self.counts.aruco_merged += len(duplicates)
            for d in new:
                verdict = verify_tag(img, TrackPrediction(d.tag_id, d.corners_px, np.zeros((4, 2)), 0), self._gate)
                if verdict.accepted:
                    found.append(d)
                    self.counts.aruco_added += 1
                else:
                    self.counts.aruco_refused += 1
        if self._lines is not None:
            # its own decode is its gate (shared.vision.linequads: <= max_hamming bit errors and both
            # rings, or the blind soft decode's); quads inside tags already found are not soft-decoded
            soft_before = self._lines.soft_decoded
            lines = self._lines.detect(img, others=found, same_tag_fraction=self.settings.same_tag_fraction)
            self.counts.lines_soft += self._lines.soft_decoded - soft_before
            new, duplicates = merge_proposals(found, lines, same_tag_fraction=self.settings.same_tag_fraction)
            self.counts.lines_merged += len(duplicates)
            self.counts.lines_added += len(new)
            found.extend(new)
        if self._full is not None:
            self._remember(found, frame)
        inside = [d for d in found if clear_of_border(d.corners_px, img.shape, self.settings.border_margin_px)]
        self.counts.at_border += len(found) - len(inside)
        return sorted(inside, key=lambda d: d.tag_id)

    def _windows(self, img: NDArray[np.uint8], found: list[Detection], frame: int) -> list[Detection]:
        """Full-resolution AprilTag in a window around each small tag seen lately that the decimated
        pass missed (most recently seen first); what it finds that is new, as proposer "fullres"."""
        s = self.settings.full_res
        assert self._full is not None
        out: list[Detection] = []
        searched = 0
        h, w = img.shape[:2]
        # Each detection takes the nearest sighting of its id within _SAME_SIGHTING_SIDES (as _remember
        # will): a tag that moved is found, not looked for again where it was; one id on tags a side
        # apart still leaves the missed one's sighting free.
        taken = {
            min(near, key=lambda i: self._seen[i].gap_sides(d))
            for d in found
            if (near := [i for i, x in enumerate(self._seen) if x.gap_sides(d) < _SAME_SIGHTING_SIDES])
        }
        for i in sorted(range(len(self._seen)), key=lambda i: -self._seen[i].frame):
            seen = self._seen[i]
            if searched >= s.max_regions:
                break
            if i in taken or any(seen.gap_sides(d) < 0.5 for d in out):
                continue  # found: nothing to look for
            pad = s.margin_sides * seen.side_px + 8.0
            x0, y0 = np.floor(seen.corners_px.min(axis=0) - pad).astype(int)
            x1, y1 = np.ceil(seen.corners_px.max(axis=0) + pad).astype(int)
            x0, y0 = max(0, x0) // _TILE_PX * _TILE_PX, max(0, y0) // _TILE_PX * _TILE_PX
            x1, y1 = min(w, x1), min(h, y1)
            if x1 - x0 < 16 or y1 - y0 < 16:
                continue  # left the image
            searched += 1
            offset = np.array([x0, y0], np.float64)
            hits = [
                Detection(d.tag_id, d.decision_margin, d.hamming, d.corners_px + offset, "fullres")
                for d in self._full.detect(np.ascontiguousarray(img[y0:y1, x0:x1]))
            ]
            new, _ = merge_proposals([*found, *out], hits, same_tag_fraction=self.settings.same_tag_fraction)
            out.extend(new)
        self.counts.fullres_windows += searched
        return out

    def _remember(self, found: list[Detection], frame: int) -> None:
        """Keep this frame's small tags as the latest sightings (each replacing the one it moved on
        from) and forget what the next frame would no longer look for."""
        s = self.settings.full_res
        old = [x for x in self._seen if frame + 1 - x.frame <= s.remember_frames]  # kept for the next frame
        new: list[_Seen] = []
        for d in found:
            if quad_side_px(d.corners_px) <= s.small_side_px:
                # the sighting it updates: the nearest of its id within 1.5 sides (it may have moved)
                gaps = [x.gap_sides(d) for x in old]
                if gaps and min(gaps) < _SAME_SIGHTING_SIDES:
                    del old[int(np.argmin(gaps))]
                new.append(_Seen.of(frame, d))
        self._seen = (old + new)[-_MAX_SEEN:]

    def close(self) -> None:
        """Free the AprilTag detectors now; idempotent."""
        self._apriltag.close()
        if self._full is not None:
            self._full.close()
