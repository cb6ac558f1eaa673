"""Track-then-refine (shared/vision/tracking.py): prediction, the soft-decode gate, the robot's half."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from shared.perception.split import robot_step
from shared.vision.camera import CameraIntrinsics
from shared.vision.detector import Detection
from shared.vision.tags import render_tag, to_uint8
from shared.vision.tracking import Prediction, TagTracker, TrackingSettings, verify_tag
from shared.wire.messages import Frame

SIZE_M = 0.16


def _quad(centre: tuple[float, float], side_px: float) -> np.ndarray:
    cx, cy = centre
    h = side_px / 2
    return np.array([[cx - h, cy - h], [cx + h, cy - h], [cx + h, cy + h], [cx - h, cy + h]])


def _image(
    tag_id: int | None,
    *,
    centre: tuple[float, float] = (200.0, 150.0),
    side_px: float = 60.0,
    turn_deg: float = 0.0,
    blur_px: float = 0.0,
) -> np.ndarray:
    """A grey 400x300 image with one fronto-parallel tag (turned in its plane), optionally blurred
    horizontally by a linear motion of `blur_px`."""
    canvas = np.full((300, 400), 0.5, np.float32)
    if tag_id is not None:
        s = side_px / SIZE_M
        c, sn = math.cos(math.radians(turn_deg)), math.sin(math.radians(turn_deg))
        tag_plane_to_image = np.array([[s * c, -s * sn, centre[0]], [s * sn, s * c, centre[1]], [0, 0, 1.0]])
        render_tag(canvas, tag_id=tag_id, tag_size_m=SIZE_M, tag_plane_to_image=tag_plane_to_image)
    if blur_px > 0:
        n = round(blur_px)
        kernel = np.full((1, n), 1.0 / n, np.float32)
        canvas = np.asarray(cv2.filter2D(canvas, -1, kernel, borderType=cv2.BORDER_REPLICATE), np.float32)
    return to_uint8(canvas)


def _prediction(tag_id: int, quad: np.ndarray, velocity: tuple[float, float] = (0.0, 0.0)) -> Prediction:
    return Prediction(tag_id, quad, np.tile(np.array(velocity, np.float64), (4, 1)), 1)


def test_a_missed_tag_is_predicted_at_constant_velocity() -> None:
    tracker = TagTracker(TrackingSettings(max_age_frames=4, max_coasting_frames=6))
    for frame in (0, 1):
        tracker.update(frame, {7: _quad((100.0 + 5 * frame, 100.0), 40.0)}, detected={7})
    [p] = tracker.predict(3, detected=set(), image_size=(400, 300))
    np.testing.assert_allclose(p.corners_px, _quad((115.0, 100.0), 40.0))
    assert p.age_frames == 2
    assert tracker.predict(3, detected={7}, image_size=(400, 300)) == []  # stage 1 has it
    assert tracker.predict(6, detected=set(), image_size=(400, 300)) == []  # older than max_age
    assert tracker.predict(3, detected=set(), image_size=(110, 300)) == []  # would leave the image
    # its right edge at x = 135: it must stay border_margin_px + search_px (4 + 6 px) inside the image
    assert tracker.predict(3, detected=set(), image_size=(145, 300)) == []
    assert len(tracker.predict(3, detected=set(), image_size=(146, 300))) == 1


def test_tracking_stops_coasting_without_a_fresh_detection() -> None:
    """Tracked quads drift under blur: a track must be re-anchored by stage 1 within max_coasting."""
    tracker = TagTracker(TrackingSettings(max_age_frames=4, max_coasting_frames=3))
    tracker.update(0, {7: _quad((100.0, 100.0), 40.0)}, detected={7})
    for frame in (1, 2, 3):  # carried by the tracker (not detected)
        assert tracker.predict(frame, set(), (400, 300))
        tracker.update(frame, {7: _quad((100.0, 100.0), 40.0)}, detected=set())
    assert tracker.predict(4, set(), (400, 300)) == []


def test_the_gate_accepts_the_tag_from_an_offset_prediction() -> None:
    image = _image(42)
    verdict = verify_tag(image, _prediction(42, _quad((203.0, 148.0), 60.0)))
    assert verdict.accepted, verdict
    np.testing.assert_allclose(verdict.corners_px, _quad((200.0, 150.0), 60.0), atol=0.8)


def test_the_gate_accepts_a_tag_smeared_past_a_hard_decode() -> None:
    """12 px of motion blur on a 60 px tag (cells of 6 px): the bits are smeared over two cells."""
    image = _image(42, blur_px=12.0)
    verdict = verify_tag(image, _prediction(42, _quad((202.0, 150.0), 60.0), velocity=(12.0, 0.0)))
    assert verdict.accepted, verdict


@pytest.mark.parametrize(
    ("what", "image"),
    [
        ("a blank wall", _image(None)),
        ("another tag", _image(43)),
        ("the tag turned by 90 degrees", _image(42, turn_deg=90.0)),
    ],
)
def test_the_gate_refuses(what: str, image: np.ndarray) -> None:
    verdict = verify_tag(image, _prediction(42, _quad((200.0, 150.0), 60.0)))
    assert not verdict.accepted, f"{what}: {verdict}"


class _ScriptedDetector:
    """Stage 1 that finds the tag in the first frames only (a fake: the real one is tested elsewhere)."""

    def __init__(self, quads: dict[int, np.ndarray]) -> None:
        self.quads = quads

    def detect(self, image: np.ndarray) -> list[Detection]:
        del image
        out = []
        for tag_id, quad in self.quads.items():
            out.append(Detection(tag_id, 80.0, 0, quad))
        return out


def test_robot_step_sends_a_tracked_tag_flagged() -> None:
    """Stage 1 sees tag 42 in frames 0 and 1 and misses it in frame 2: the robot tracks it and sends
    it with `tracked` set (and stage 1's tags without)."""
    from shared.model.runtime import load_split_net

    net = load_split_net(Path("models"), "fp32")
    camera = CameraIntrinsics(
        width=400, height=300, fx=400.0, fy=400.0, cx=199.5, cy=149.5, distortion_model="none", distortion=[]
    )
    tracker = TagTracker(TrackingSettings(enabled=True))
    for seq, x in enumerate((190.0, 195.0, 200.0)):
        image = _image(42, centre=(x, 150.0))
        detector = _ScriptedDetector({42: _quad((x, 150.0), 60.0)} if seq < 2 else {})
        frame = Frame(robot_id="r1", seq=seq, capture_nanos=1_000 + seq, image=image, intrinsics=camera)
        tags, _ = robot_step(frame, detector=detector, net=net, k=7, codec="fp32", tracker=tracker)
        assert [(t.tag_id, t.tracked) for t in tags] == [(42, seq == 2)]
    np.testing.assert_allclose(tags[0].corners_px, _quad((200.0, 150.0), 60.0), atol=1.0)
