"""Stage 1's extra proposers (shared.vision.proposals): conventions on exact renders, merging, the gate,
and recall on real photos that nobody on the team made (bench/data/apriltag_photos)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from numpy.typing import NDArray

from bench.accuracy import Prediction
from bench.photos import load_photos, match
from bench.tagrender import clean_settings, render_sample
from shared.vision.detector import Detection, DetectorSettings, Stage1, TagDetector, merge_proposals
from shared.vision.linequads import LineQuadProposer, LineQuadSettings
from shared.vision.proposals import ArucoProposer, Stage1Detector, Stage1Settings


def _square(centre: tuple[float, float], side: float) -> NDArray[np.float64]:
    x, y = centre
    h = side / 2
    return np.array([[x - h, y - h], [x + h, y - h], [x + h, y + h], [x - h, y + h]])


@pytest.mark.parametrize(
    ("make", "name", "max_tilt_deg"), [(ArucoProposer, "aruco", 30.0), (LineQuadProposer, "lines", 40.0)]
)
def test_proposer_corners_are_ours_in_order_and_pixel_convention(
    make: Callable[[], Stage1], name: str, max_tilt_deg: float
) -> None:
    """On exact clean renders each extra proposer's corners lie on the true TL, TR, BR, BL (OpenCV pixels)."""
    proposer = make()
    errors = []
    for index in range(8):
        sample = render_sample(index, 11, clean_settings(span_px=(80.0, 200.0), tilt_deg=(0.0, max_tilt_deg)))
        truth = sample.tags[0]
        found = proposer.detect(sample.image)
        assert [(d.tag_id, d.proposer) for d in found] == [(truth.tag_id, name)], sample.meta
        errors.append(np.linalg.norm(found[0].corners_px - truth.corners_px, axis=1))
    err = np.concatenate(errors)
    assert float(np.median(err)) < 0.3, err  # a wrong order or a half-pixel shift would be >= 0.5


def test_merge_keeps_new_tags_and_repeats_of_one_id_drops_duplicates() -> None:
    at = [Detection(5, 50.0, 0, _square((100, 100), 40))]
    aruco = [
        Detection(5, 0.0, 0, _square((103, 98), 41), "aruco"),  # AprilTag's tag again
        Detection(5, 0.0, 0, _square((300, 100), 40), "aruco"),  # another copy of id 5
        Detection(7, 0.0, 0, _square((100, 100), 40), "aruco"),  # another id at the same place: not merged
        Detection(7, 0.0, 0, _square((101, 101), 40), "aruco"),  # ... reported twice by the second proposer
    ]
    new, duplicates = merge_proposals(at, aruco)
    assert [(d.tag_id, tuple(d.corners_px.mean(0).round())) for d in new] == [(5, (300, 100)), (7, (100, 100))]
    assert len(duplicates) == 2


class _Scripted:
    """A second proposer that reports what the test says."""

    def __init__(self, detections: list[Detection]) -> None:
        self.detections = detections

    def detect(self, image: NDArray[np.uint8]) -> list[Detection]:
        return list(self.detections)


def test_gate_refuses_a_second_proposer_claiming_the_wrong_id_or_a_blank_quad() -> None:
    """A quad on a real tag with another id, or on the background, never becomes a detection."""
    sample = render_sample(3, 11, clean_settings(span_px=(120.0, 200.0), tilt_deg=(0.0, 20.0)))
    truth = sample.tags[0]
    off_tag = truth.corners_px - truth.corners_px.mean(0) + np.array([[80.0, 80.0]])  # on the background
    wrong = Detection((truth.tag_id + 1) % 587, 0.0, 0, truth.corners_px, "aruco")
    blank = Detection(truth.tag_id, 0.0, 0, off_tag, "aruco")
    right = Detection(truth.tag_id, 0.0, 0, truth.corners_px + 0.4, "aruco")
    # AprilTag finds nothing; the line-quad proposer (its own tests: tests/test_linequads.py) is off
    no_apriltag = Stage1Settings(
        apriltag=DetectorSettings(min_decision_margin=1e9), lines=LineQuadSettings(enabled=False)
    )
    stage1 = Stage1Detector(no_apriltag, second=_Scripted([wrong, blank]))
    assert stage1.detect(sample.image) == []
    assert (stage1.counts.aruco_refused, stage1.counts.aruco_added) == (2, 0)
    stage1 = Stage1Detector(no_apriltag, second=_Scripted([right]))
    assert [(d.tag_id, d.proposer) for d in stage1.detect(sample.image)] == [(truth.tag_id, "aruco")]
    stage1.close()


def _found(detector: Stage1Detector | TagDetector) -> int:
    total = 0
    for photo in load_photos():
        found = [Prediction(d.tag_id, d.corners_px, "corners4") for d in detector.detect(photo.image)]
        total += match(photo.tags, found)[0]
    return total


def test_real_photos_second_proposer_recovers_what_decimation_and_apriltag_lose() -> None:
    """AprilRobotics' three test photos (47 annotated tags): AprilTag 3 finds 29 at decimate 2 and 44 at
    decimate 1; stage 1 with the second proposer finds more at either setting, and >= 46 at decimate 1."""
    full = DetectorSettings(quad_decimate=1.0)
    apriltag_d2, apriltag_d1 = TagDetector(), TagDetector(full)
    stage1_d2, stage1_d1 = Stage1Detector(), Stage1Detector(Stage1Settings(apriltag=full))
    base_d2, base_d1 = _found(apriltag_d2), _found(apriltag_d1)
    ours_d2, ours_d1 = _found(stage1_d2), _found(stage1_d1)
    print(f"\nreal photos, 47 tags: AprilTag d2 {base_d2}, d1 {base_d1}; stage 1 d2 {ours_d2}, d1 {ours_d1}")
    assert ours_d2 >= base_d2 + 6
    assert ours_d1 >= 46
    for d in (apriltag_d2, apriltag_d1, stage1_d2, stage1_d1):
        d.close()


def test_bad_threshold_windows_are_refused_with_the_values() -> None:
    import pydantic
    import pytest

    from shared.vision.proposals import ArucoSettings

    for bad in ((2, 17, 10), (17, 7, 10), (7, 17, 0)):
        with pytest.raises(pydantic.ValidationError, match="threshold_window_px"):
            ArucoSettings(threshold_window_px=bad)
