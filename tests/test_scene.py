"""MuJoCo scenes: rendered tags decode, and their corners agree with exact projection."""

from __future__ import annotations

import numpy as np
import pytest

from shared.sim.scene import SceneRenderer, look_at, random_room
from shared.vision.camera import CameraIntrinsics
from shared.vision.detector import DetectorSettings, TagDetector
from shared.vision.geometry import corners_in_tag, default_camera, project


def test_rendered_tags_decode_with_corners_at_their_projection() -> None:
    cam = default_camera()
    spec = random_room(3, n_tags=4, n_objects=0)
    renderer = SceneRenderer(spec, cam)
    det = TagDetector(DetectorSettings(quad_decimate=1.0))
    errs = []
    try:
        for k, tag in enumerate(spec.tags):
            world_from_tag = tag.pose()
            eye = world_from_tag[:3, 3] - 1.0 * world_from_tag[:3, 2] + np.array([0.15 * k, 0.1, 0.05])
            world_from_camera = look_at(eye, world_from_tag[:3, 3], roll_rad=0.2 * k)
            img = renderer.render(world_from_camera)
            found = [d for d in det.detect(img) if d.tag_id == tag.id]
            assert found, f"tag {tag.id} not decoded"
            gt = project(cam, np.linalg.inv(world_from_camera) @ world_from_tag, corners_in_tag(tag.size_m))
            errs.append(found[0].corners_px - gt)
    finally:
        renderer.close()
    err = np.linalg.norm(np.concatenate(errs), axis=1)
    print(f"MuJoCo corner error after bias correction: mean {err.mean():.3f} px, max {err.max():.3f} px")
    assert err.mean() < 0.3


def test_renderer_refuses_cameras_it_cannot_model() -> None:
    cam = default_camera().model_copy(update={"cx": 600.0})
    with pytest.raises(ValueError, match="principal point"):
        SceneRenderer(random_room(0, n_tags=1, n_objects=0), CameraIntrinsics.model_validate(cam.model_dump()))
