"""`splittag detect`: the whole chain on image files; unreadable files are reported, the rest run."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from shared.tools.cli import main
from shared.vision.geometry import camera_to_yaml, default_camera, make_pose
from shared.vision.tags import render_tag, to_uint8


def test_detect_reports_keypoints_poses_and_bad_files(tmp_path: Path) -> None:
    cam = default_camera()
    pose = make_pose(np.eye(3), [0.1, -0.05, 1.5])
    canvas = np.full((cam.height, cam.width), 0.55, np.float32)
    h = cam.matrix() @ np.column_stack([pose[:3, 0], pose[:3, 1], pose[:3, 3]])
    render_tag(canvas, tag_id=17, tag_size_m=0.2, tag_plane_to_image=h)
    cv2.imwrite(str(tmp_path / "tag.png"), to_uint8(canvas))
    (tmp_path / "broken.png").write_text("not an image")
    (tmp_path / "cam.yaml").write_text(camera_to_yaml(cam))
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
    assert len(tag["apriltag_corners_px"]) == 4
    chosen = tag["camera_from_tag"]["chosen"]
    assert np.linalg.norm(np.array(chosen["t_m"]) - pose[:3, 3]) < 0.01
    assert tag["camera_from_tag"]["alternative"]["reprojection_error_px"] >= chosen["reprojection_error_px"]
