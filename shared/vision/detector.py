"""Stage 1: the classical AprilTag (tag36h11) detector, corners in our convention.

pupil-apriltags returns corners p0..p3 = BL, BR, TR, TL of the tag (counter-clockwise on screen)
with pixel centres at +0.5 relative to OpenCV's convention. `detect` reorders them to TL, TR, BR,
BL and subtracts `CORNER_OFFSET_PX` (measured on exact renders by tests/test_geometry.py).
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import Final, Protocol

import numpy as np
import pupil_apriltags
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from shared.vision.geometry import Array, check_image
from shared.vision.proposers import Proposer

CORNER_OFFSET_PX: Final[float] = 0.5
_TO_TL_TR_BR_BL: Final[list[int]] = [3, 2, 1, 0]


class DetectorSettings(BaseModel):
    """pupil-apriltags settings (see its docs); tag36h11 only."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    nthreads: int = Field(default=1, ge=1)  # AprilTag's own threads
    # AprilTag finds quads on the image reduced by this (1 = full resolution)
    quad_decimate: float = Field(default=2.0, ge=1.0)
    quad_sigma: float = Field(default=0.0, ge=0.0)  # Gaussian blur before the quad search (0 = none)
    refine_edges: bool = True  # snap the quads' edges to the full-resolution image
    decode_sharpening: float = Field(default=0.25, ge=0.0)  # sharpening of the decoded cells
    max_hamming: int = Field(default=1, ge=0, le=2)  # bit errors a decode may correct
    min_decision_margin: float = Field(default=20.0, ge=0.0)  # weaker decodes are dropped


@dataclass(frozen=True)
class Detection:
    """One decoded tag: id, decode quality, the black square's corners TL, TR, BR, BL, and which stage-1
    proposer found it (`Proposer`; shared.vision.proposals)."""

    tag_id: int
    decision_margin: float
    hamming: int
    corners_px: Array
    proposer: Proposer = "apriltag"


class Stage1(Protocol):
    """What the perception cores need of stage 1: TagDetector, shared.vision.proposals.Stage1Detector,
    or a test's scripted fake."""

    def detect(self, image: NDArray[np.uint8]) -> list[Detection]: ...


def destroy_detector(det: pupil_apriltags.Detector) -> None:
    """Free a pupil-apriltags detector in the safe order: the detector first (its destructor still
    reads the tag family), then the family. pupil-apriltags 1.0.4's own __del__ frees the family first,
    a use-after-free that segfaults intermittently (pupil-labs/apriltags#46, fix in PR #65, unreleased).
    Clearing the pointer afterwards turns its __del__ into a no-op."""
    ptr = getattr(det, "tag_detector_ptr", None)
    if ptr is None:
        return
    det.libc.apriltag_detector_destroy.restype = None
    det.libc.apriltag_detector_destroy(ptr)
    for tf in det.tag_families.values():
        det.libc.tag36h11_destroy.restype = None
        det.libc.tag36h11_destroy(tf)
    det.tag_families = {}
    det.tag_detector_ptr = None


class TagDetector:
    """A reusable pupil-apriltags detector (not thread-safe: one per thread)."""

    def __init__(self, settings: DetectorSettings | None = None) -> None:
        self.settings = settings or DetectorSettings()
        s = self.settings
        self._det = pupil_apriltags.Detector(
            families="tag36h11",
            nthreads=s.nthreads,
            quad_decimate=s.quad_decimate,
            quad_sigma=s.quad_sigma,
            refine_edges=int(s.refine_edges),
            decode_sharpening=s.decode_sharpening,
        )
        self._finalizer = weakref.finalize(self, destroy_detector, self._det)

    def close(self) -> None:
        """Free the C detector now (also done when the object is collected); idempotent."""
        self._finalizer()

    def detect(self, image: NDArray[np.uint8]) -> list[Detection]:
        """Detect tags in a uint8 grayscale image, sorted by id."""
        img = np.ascontiguousarray(check_image(image))
        out = []
        for r in self._det.detect(img):
            if r.hamming > self.settings.max_hamming:
                continue
            if r.decision_margin < self.settings.min_decision_margin:
                continue
            corners = np.asarray(r.corners, np.float64)[_TO_TL_TR_BR_BL] - CORNER_OFFSET_PX
            out.append(Detection(int(r.tag_id), float(r.decision_margin), int(r.hamming), corners))
        return sorted(out, key=lambda d: d.tag_id)


def quad_side_px(corners_px: Array) -> float:
    """Mean side length of a quad (px)."""
    return float(np.mean(np.linalg.norm(corners_px - np.roll(corners_px, -1, axis=0), axis=1)))


def merge_proposals(
    primary: list[Detection], secondary: list[Detection], *, same_tag_fraction: float = 0.5
) -> tuple[list[Detection], list[Detection]]:
    """(new, duplicates) among the secondary detections: one is a duplicate when a primary detection
    (or an earlier new one) has its id and a centre closer than `same_tag_fraction` of the larger
    quad side. Pure."""
    new: list[Detection] = []
    duplicates: list[Detection] = []
    for d in secondary:
        centre = d.corners_px.mean(axis=0)
        same = any(
            p.tag_id == d.tag_id
            and float(np.linalg.norm(p.corners_px.mean(axis=0) - centre))
            < same_tag_fraction * max(quad_side_px(p.corners_px), quad_side_px(d.corners_px))
            for p in (*primary, *new)
        )
        (duplicates if same else new).append(d)
    return new, duplicates
