"""`splittag detect`: the whole chain on image files; unreadable files are reported, the rest run."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from shared.tools.cli import main
from shared.vision.geometry import camera_to_yaml, default_camera, make_pose
from shared.vision.tags import render_tag, to_uint8


def _tag_image(folder: Path) -> np.ndarray:
    """tag.png: tag 17 (0.2 m) 1.5 m before the default camera, and cam.yaml; returns the tag's pose."""
    cam = default_camera()
    pose = make_pose(np.eye(3), [0.1, -0.05, 1.5])
    canvas = np.full((cam.height, cam.width), 0.55, np.float32)
    h = cam.matrix() @ np.column_stack([pose[:3, 0], pose[:3, 1], pose[:3, 3]])
    render_tag(canvas, tag_id=17, tag_size_m=0.2, tag_plane_to_image=h)
    cv2.imwrite(str(folder / "tag.png"), to_uint8(canvas))
    (folder / "cam.yaml").write_text(camera_to_yaml(cam))
    return pose


def test_detect_reports_keypoints_poses_and_bad_files(tmp_path: Path) -> None:
    pose = _tag_image(tmp_path)
    (tmp_path / "broken.png").write_text("not an image")
    out = tmp_path / "out.json"
    code = main(
        ["detect", str(tmp_path), "--camera", str(tmp_path / "cam.yaml"), "--tag-size", "0.2", "--json", str(out)]
    )
    assert code == 0
    images = {Path(i["path"]).name: i for i in json.loads(out.read_text())["images"]}
    assert "cannot read image" in images["broken.png"]["error"]
    (tag,) = images["tag.png"]["tags"]
    assert tag["id"] == 17
    assert len(tag["keypoints_px"]) == 16
    assert len(tag["stage1_corners_px"]) == 4
    # AprilTag's own corners only where AprilTag found the tag (else another proposer's: null)
    assert tag["apriltag_corners_px"] == (
        tag["stage1_corners_px"] if tag["proposer"] in ("apriltag", "fullres") else None
    )
    chosen = tag["camera_from_tag"]["chosen"]
    assert np.linalg.norm(np.array(chosen["t_m"]) - pose[:3, 3]) < 0.01
    assert tag["camera_from_tag"]["alternative"]["reprojection_error_px"] >= chosen["reprojection_error_px"]
    # the network's own keypoints, unfused (the fused ones carry AprilTag's corners: a "network vs AprilTag"
    # comparison on them was partly AprilTag against itself), and the pose from them alone
    network = np.array(tag["network_keypoints_px"])
    fused = np.array(tag["keypoints_px"])
    assert network.shape == (16, 2) and not np.array_equal(network, fused)
    assert np.abs(network - fused).max() < 0.5
    alone = tag["camera_from_tag_network_only"]["chosen"]
    assert np.linalg.norm(np.array(alone["t_m"]) - pose[:3, 3]) < 0.01


def test_detect_says_in_one_line_what_is_wrong_with_a_camera_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A distortion model it cannot use, or a plumb_bob with the wrong number of coefficients: one line,
    exit 2, like the services (a trial got a traceback)."""
    text = camera_to_yaml(default_camera())
    cases = {
        "equidistant.yaml": text.replace("distortion_model: none", "distortion_model: equidistant"),
        "no_coefficients.yaml": text.replace("distortion_model: none", "distortion_model: plumb_bob"),
    }
    for name, body in cases.items():
        assert body != text, name  # the edit applied
        (tmp_path / name).write_text(body)
        code = main(["detect", str(tmp_path), "--camera", str(tmp_path / name), "--json", str(tmp_path / "o.json")])
        err = capsys.readouterr().err
        assert code == 2 and "Traceback" not in err, err
        assert f"camera file {tmp_path / name}" in err, err


def test_detect_without_a_camera_file_assumes_one_and_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A trial had to write a camera file by hand before detect would look at three photos of unknown
    cameras. Without one each image gets an assumed pinhole camera, said on stderr and in the JSON; the
    keypoints are the same as with the true camera (they do not depend on it)."""
    _tag_image(tmp_path)
    cam = default_camera()
    known, assumed = tmp_path / "known.json", tmp_path / "assumed.json"
    assert (
        main(["detect", str(tmp_path / "tag.png"), "--camera", str(tmp_path / "cam.yaml"), "--json", str(known)]) == 0
    )
    capsys.readouterr()
    assert main(["detect", str(tmp_path / "tag.png"), "--json", str(assumed)]) == 0
    assert "no --camera: each image is solved with an assumed pinhole camera" in capsys.readouterr().err
    doc = json.loads(assumed.read_text())
    (image,) = doc["images"]
    assert doc["camera"] is None and image["assumed_camera"]["fx"] == cam.width
    (with_camera,) = json.loads(known.read_text())["images"][0]["tags"]
    (tag,) = image["tags"]
    assert tag["id"] == 17
    np.testing.assert_allclose(tag["keypoints_px"], with_camera["keypoints_px"], atol=1e-6)


def test_without_fusion_the_keypoints_are_the_networks_own(tmp_path: Path) -> None:
    """perceive() without a fusion reports the network's keypoints as they are, under both names."""
    from shared.model.weights import load_model
    from shared.perception.single import perceive
    from shared.tools.detect import DEFAULT_WEIGHTS
    from shared.vision.proposals import Stage1Detector, Stage1Settings
    from shared.vision.tagmap import TagMapFile

    _tag_image(tmp_path)
    image = np.asarray(cv2.imread(str(tmp_path / "tag.png"), cv2.IMREAD_GRAYSCALE), np.uint8)
    detector = Stage1Detector(Stage1Settings())
    try:
        (tag,) = perceive(
            image,
            camera=default_camera(),
            detector=detector,
            model=load_model(DEFAULT_WEIGHTS),
            tag_map=TagMapFile(default_size_m=0.2),
        )
    finally:
        detector.close()
    assert tag.keypoints_px is not None and tag.network_keypoints_px is not None
    np.testing.assert_array_equal(tag.keypoints_px, tag.network_keypoints_px)
    assert tag.to_json()["camera_from_tag_network_only"] == tag.to_json()["camera_from_tag"]
