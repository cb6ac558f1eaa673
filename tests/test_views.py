"""Test-time views (shared/model/views.py): the dihedral transforms, mapping keypoints back, averaging,
the SplitNet wrapper at each cut, and the settings that turn it on."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import torch
from numpy.typing import NDArray

from services.edge_infer.settings import EdgeInferSettings
from services.robot_infer.settings import RobotInferSettings
from shared.model.precision import Precision
from shared.model.runtime import load_split_net
from shared.model.views import (
    MAX_PASS_BATCH,
    VIEW_COUNTS,
    ViewAveragedNet,
    expand_views,
    merge_views,
    transform_image,
    transforms,
    untransform_keypoints,
    with_views,
)
from shared.perception.single import extract_rois
from shared.perception.split import edge_step, robot_step
from shared.training.train import dihedral
from shared.vision.camera import CameraIntrinsics
from shared.vision.detector import Detection
from shared.vision.proposals import Stage1Detector, Stage1Settings
from shared.vision.tagmap import TagMapFile
from shared.vision.tags import render_tag, to_uint8
from shared.wire.messages import Features, Frame

S = 256
MODELS = Path(__file__).resolve().parent.parent / "models"


def dot_roi(points_norm: NDArray[np.float64]) -> NDArray[np.uint8]:
    """An ROI with one bright pixel per keypoint (normalised, pixel edges at 0 and 1)."""
    roi = np.zeros((S, S), np.uint8)
    for x, y in points_norm:
        roi[int(y * S), int(x * S)] = 255
    return roi


def lattice_points(rng: np.random.Generator) -> NDArray[np.float64]:
    """A jittered 4x4 lattice in row-major order, each point at a pixel centre."""
    g = np.stack(np.meshgrid(np.arange(4), np.arange(4)), -1).reshape(16, 2)  # (col, row)
    px = 40 + 55 * g + rng.integers(-8, 9, size=(16, 2))
    return (px + 0.5) / S


class DotNet:
    """An exactly equivariant 'network': finds the bright pixels of each ROI and returns them in
    row-major lattice order of the image it is given (rows by y, then x within a row). Optionally adds
    a fixed offset in its own image frame, the kind of error that views cancel."""

    precision: Precision = "fp32"

    def __init__(self, bias: tuple[float, float] = (0.0, 0.0)) -> None:
        self.bias = np.asarray(bias)
        self.calls: list[tuple[str, int, int]] = []

    def _keypoints(self, rois: NDArray[Any]) -> NDArray[np.float32]:
        out = []
        for roi in np.asarray(rois).reshape(-1, S, S):
            ys, xs = np.nonzero(roi)
            if len(xs) != 16:  # a blank warm-up ROI
                out.append(np.zeros((16, 2)))
                continue
            pts = np.stack([(xs + 0.5) / S, (ys + 0.5) / S], -1)
            pts = pts[np.argsort(pts[:, 1])].reshape(4, 4, 2)
            pts = np.take_along_axis(pts, np.argsort(pts[..., 0], axis=1)[..., None], axis=1).reshape(16, 2)
            out.append(pts + self.bias)
        return np.asarray(out, np.float32)

    def head(self, rois_u8: NDArray[np.uint8], k: int) -> NDArray[np.float32]:
        self.calls.append(("head", k, len(rois_u8)))
        if k == 7:
            return self._keypoints(rois_u8).reshape(len(rois_u8), 32)
        return np.zeros((len(rois_u8), 4, 2, 2), np.float32)  # a stand-in feature map

    def tail(self, z: NDArray[Any], k: int) -> NDArray[np.float32]:
        self.calls.append(("tail", k, len(z)))
        if k == 0:
            return self._keypoints(z)
        return np.zeros((len(z), 16, 2), np.float32)

    def warm_up(self, k: int, *, max_batch: int = 1) -> None:
        self.calls.append(("warm_up", k, max_batch))


@pytest.mark.parametrize("t", range(8))
def test_each_transform_maps_keypoints_back_exactly(t: int) -> None:
    truth = lattice_points(np.random.default_rng(t))
    seen = DotNet()._keypoints(np.ascontiguousarray(transform_image(dot_roi(truth), t))[None])
    np.testing.assert_allclose(untransform_keypoints(seen, t)[0], truth, atol=1e-6)


@pytest.mark.parametrize("t", range(8))
def test_views_are_the_training_augmentations(t: int) -> None:
    """Transform t here is training's dihedral transform t (shared.training.train.dihedral): the same
    image, and keypoints that map back to the sample's own."""
    rng = np.random.default_rng(t)
    roi = rng.integers(0, 256, (S, S), dtype=np.uint8)
    kp = lattice_points(rng).astype(np.float32)
    img_t, kp_t = dihedral(torch.from_numpy(roi)[None, None], torch.from_numpy(kp)[None], t)
    np.testing.assert_array_equal(img_t[0, 0].numpy(), transform_image(roi, t))
    np.testing.assert_allclose(untransform_keypoints(kp_t.numpy(), t)[0], kp, atol=1e-6)


@pytest.mark.parametrize("views", VIEW_COUNTS)
def test_views_of_an_equivariant_net_give_its_answer_with_no_spread(views: int) -> None:
    rng = np.random.default_rng(views)
    truths = [lattice_points(rng) for _ in range(3)]
    rois = np.stack([dot_roi(p) for p in truths])
    expanded = expand_views(rois, views)
    assert expanded.shape == (3 * views, S, S)
    np.testing.assert_array_equal(expanded[::views], rois)  # tag-major: each ROI's own view first
    kp, spread = merge_views(DotNet()._keypoints(expanded), views)
    np.testing.assert_allclose(kp, np.stack(truths), atol=1e-6)
    np.testing.assert_allclose(spread, 0, atol=1e-6)


@pytest.mark.parametrize("views", [2, 4, 8])
def test_views_cancel_an_error_the_net_makes_in_its_own_frame(views: int) -> None:
    truth = lattice_points(np.random.default_rng(0))
    rois = dot_roi(truth)[None]
    biased = DotNet(bias=(0.01, -0.004))
    one, _ = merge_views(biased._keypoints(rois), 1)
    np.testing.assert_allclose(one[0] - truth, np.broadcast_to([0.01, -0.004], (16, 2)), atol=1e-6)
    kp, spread = merge_views(biased._keypoints(expand_views(rois, views)), views)
    np.testing.assert_allclose(kp[0], truth, atol=1e-6)
    assert spread[0] == pytest.approx(np.hypot(0.01, 0.004), rel=1e-4)


def test_the_wrapper_averages_where_the_whole_network_runs_and_nowhere_else() -> None:
    truth = lattice_points(np.random.default_rng(1))
    rois = np.stack([dot_roi(truth)] * 2)
    inner = DotNet(bias=(0.02, 0.0))
    net = ViewAveragedNet(inner, 2)
    assert net.precision == "fp32"
    # robot at the last cut: keypoints out, in the head's own shape
    out = net.head(rois, 7)
    assert out.shape == (2, 32)
    np.testing.assert_allclose(out.reshape(2, 16, 2), np.stack([truth] * 2), atol=1e-6)
    assert inner.calls[-1] == ("head", 7, 4)
    # edge from cut 0, ROIs as the wire carries them (N, 1, 256, 256)
    np.testing.assert_allclose(net.tail(rois[:, None], 0), np.stack([truth] * 2), atol=1e-6)
    assert inner.calls[-1] == ("tail", 0, 4)
    # a split cut: each half once per ROI, as the wrapped net
    for k in range(1, 7):
        net.tail(net.head(rois, k), k)
        assert inner.calls[-2:] == [("head", k, 2), ("tail", k, 2)]
    # the last cut's tail and cut 0's head pass through too; so do empty batches
    net.tail(out, 7)
    assert inner.calls[-1] == ("tail", 7, 2)
    assert net.head(rois[:0], 7).shape[0] == 0


def test_large_batches_go_through_in_bounded_passes() -> None:
    """70 ROIs at 8 views: no inner call gets more than MAX_PASS_BATCH ROI views, and every ROI's
    answer comes back in order."""
    rng = np.random.default_rng(2)
    truths = [lattice_points(rng) for _ in range(70)]
    inner = DotNet()
    out = ViewAveragedNet(inner, 8).tail(np.stack([dot_roi(p) for p in truths]), 0)
    np.testing.assert_allclose(out, np.stack(truths), atol=1e-6)
    sizes = [n for name, _, n in inner.calls if name == "tail"]
    assert max(sizes) <= MAX_PASS_BATCH and sum(sizes) == 70 * 8


def test_warm_up_covers_the_view_batches() -> None:
    inner = DotNet()
    ViewAveragedNet(inner, 4).warm_up(7, max_batch=2)
    assert inner.calls[0] == ("warm_up", 7, 2)
    assert ("head", 7, 4) in inner.calls and ("head", 7, 8) in inner.calls


def test_one_view_is_the_net_itself_and_other_counts_are_refused() -> None:
    inner = DotNet()
    assert with_views(inner, 1) is inner
    assert transforms(2) == (0, 3)
    for bad in (0, 3, 16, True):
        with pytest.raises(ValueError, match="views must be one of"):
            transforms(bad)
    with pytest.raises(ValueError, match=r"expected \(N \* 4, 16, 2\)"):
        merge_views(np.zeros((6, 16, 2), np.float32), 4)


def test_services_take_views_from_their_settings_and_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    assert RobotInferSettings().views == 1 and EdgeInferSettings().views == 1
    monkeypatch.setenv("SPLITTAG_ROBOT_INFER_VIEWS", "4")  # environment values arrive as strings
    assert RobotInferSettings.load().views == 4
    with pytest.raises(ValueError, match="views must be one of"):
        EdgeInferSettings(views=3)


def _tag_image() -> tuple[NDArray[np.uint8], NDArray[np.float64]]:
    """A grey 400x300 image with tag 42 (0.1 m) turned 20 deg in its plane, 60 px wide, blurred 5 px
    horizontally; and its plane->image homography."""
    canvas = np.full((300, 400), 0.5, np.float32)
    s, c, sn = 600.0, math.cos(math.radians(20)), math.sin(math.radians(20))
    h = np.array([[s * c, -s * sn, 200.0], [s * sn, s * c, 150.0], [0, 0, 1.0]])
    render_tag(canvas, tag_id=42, tag_size_m=0.1, tag_plane_to_image=h)
    canvas = np.asarray(cv2.filter2D(canvas, -1, np.full((1, 5), 0.2, np.float32)), np.float32)
    return to_uint8(canvas), h


def test_robot_at_the_last_cut_and_edge_from_cut_0_average_the_same_views_of_the_real_network() -> None:
    """With the shipped weights: the robot's views at k = 7 and the edge's at k = 0 give the same poses,
    the robot's keypoints are the mean of the ROI's and its half turn's, and differ from one view."""
    image, _ = _tag_image()
    camera = CameraIntrinsics(
        width=400, height=300, fx=600.0, fy=600.0, cx=199.5, cy=149.5, distortion_model="none", distortion=[]
    )
    frame = Frame(robot_id="r1", seq=1, capture_nanos=1, image=image, intrinsics=camera)
    plain = load_split_net(MODELS, "fp32")
    net = with_views(plain, 2)
    tag_map = TagMapFile(default_size_m=0.1)
    poses = {}
    for k in (0, 7):
        tags, _ = robot_step(frame, detector=Stage1Detector(Stage1Settings()), net=net, k=k, codec="fp32")
        assert [t.tag_id for t in tags] == [42]
        if k == 7:
            rois, _ = extract_rois(image, [Detection(42, 0.0, 0, np.asarray(tags[0].corners_px, np.float64))])
            one = plain.tail(rois, 0)[0]
            turned = untransform_keypoints(plain.tail(np.ascontiguousarray(rois[:, ::-1, ::-1]), 0), 3)[0]
            np.testing.assert_allclose(np.asarray(tags[0].tensor).reshape(16, 2), (one + turned) / 2, atol=1e-5)
            assert np.abs(one - turned).max() * S > 0.01  # the two views do differ
        features = Features(
            robot_id="r1",
            seq=1,
            capture_nanos=1,
            publish_nanos=2,
            split_k=k,
            codec="fp32",
            intrinsics=camera,
            robot_compute_secs=0.0,
            tags=tags,
        )
        out = edge_step(features, net=net, tag_map=tag_map, receive_nanos=3, previous_receive_nanos=0, payload_bytes=1)
        poses[k] = out.tags[0].camera_from_tag
    np.testing.assert_allclose(poses[0], poses[7], atol=1e-5)
    assert poses[0][2, 3] == pytest.approx(1.0, rel=0.01)  # 0.1 m drawn 60 px wide at f = 600 px: 1 m away
