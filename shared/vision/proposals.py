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

from shared.vision.detector import Detection, DetectorSettings, Stage1, TagDetector, merge_proposals
from shared.vision.geometry import check_image
from shared.vision.linequads import LineQuadProposer, LineQuadSettings
from shared.vision.tracking import Prediction as TrackPrediction
from shared.vision.tracking import TrackingSettings, verify_tag

_ARUCO_TO_TL_TR_BR_BL: Final[list[int]] = [2, 3, 0, 1]


class ArucoSettings(BaseModel):
    """The second proposer: OpenCV's ArUco detector on the AprilTag 36h11 dictionary."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    enabled: bool = True
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
    gate_min_margin: float = Field(default=0.15, ge=0.0)
    gate_search_px: float = Field(default=1.0, ge=0.0)

    @field_validator("threshold_window_px")
    @classmethod
    def _windows(cls, v: tuple[int, int, int]) -> tuple[int, int, int]:
        lo, hi, step = v
        if lo < 3 or hi < lo or step < 1:
            raise ValueError(f"threshold_window_px is (min >= 3, max >= min, step >= 1) px, got {v}")
        return v


class Stage1Settings(BaseModel):
    """Stage 1 as robot_infer, `splittag detect` and the benches run it."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    apriltag: DetectorSettings = Field(default_factory=DetectorSettings)
    aruco: ArucoSettings = Field(default_factory=ArucoSettings)
    lines: LineQuadSettings = Field(default_factory=LineQuadSettings)
    # A tag both proposers report is one tag when their centres are closer than this fraction of the
    # larger quad side (one id may appear several times in one image: all are kept).
    same_tag_fraction: float = Field(default=0.5, gt=0.0, le=1.0)


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
        found = self._apriltag.detect(img)
        self.counts.frames += 1
        self.counts.apriltag += len(found)
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
            lines = self._lines.detect(img, known=[d.corners_px for d in found])
            self.counts.lines_soft += self._lines.soft_decoded - soft_before
            new, duplicates = merge_proposals(found, lines, same_tag_fraction=self.settings.same_tag_fraction)
            self.counts.lines_merged += len(duplicates)
            self.counts.lines_added += len(new)
            found.extend(new)
        return sorted(found, key=lambda d: d.tag_id)

    def close(self) -> None:
        """Free the AprilTag detector now; idempotent."""
        self._apriltag.close()
