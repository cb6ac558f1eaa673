"""The rendered (photoreal) data set: MuJoCo rooms replacing the paper's Gazebo Harmonic set.

Gazebo cannot be installed here; MuJoCo renders complete 3D scenes headless (EGL) with lights,
shadows, textured walls, clutter and tags at known poses. Each shard is one random room; each
sample is a random viewpoint aimed near a random tag of that room (distance log-uniform, viewing
tilt uniform, roll and aim jittered). Stage 1 runs on the full 1280x720 render; labels come from
exact projection, exactly as for the synthetic set (shared.datasets.synth.label_sample).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from shared.datasets.generate import STRIDE
from shared.datasets.synth import label_sample
from shared.sim.scene import SceneRenderer, look_at, random_room
from shared.vision.camera import CameraIntrinsics
from shared.vision.detector import DetectorSettings, TagDetector
from shared.vision.geometry import ROI_MARGIN, corners_in_tag, project, tilt_deg
from shared.vision.tags import to_uint8


class RenderSettings(BaseModel):
    """Generator settings; saved into info.json."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    seed: int = 0
    distance_m: tuple[float, float] = (0.4, 4.0)
    max_tilt_deg: float = Field(default=65.0, ge=0, lt=89)
    max_roll_deg: float = 20.0
    perturb_frac: float = 0.06
    roi_margin: float = ROI_MARGIN
    max_noise_sigma: float = 0.015
    tags_per_room: int = 10
    detector: DetectorSettings = DetectorSettings()


class RenderMaker:
    """Per-process sample maker; keeps the current shard's room compiled."""

    def __init__(self, camera: CameraIntrinsics, settings: RenderSettings) -> None:
        self.camera, self.settings = camera, settings
        self._room_id = -1
        self._renderer: SceneRenderer | None = None
        self._detector: TagDetector | None = None

    def _room(self, room_id: int) -> SceneRenderer:
        if self._renderer is None or room_id != self._room_id:
            if self._renderer is not None:
                self._renderer.close()
            spec = random_room(self.settings.seed * 100_003 + room_id, n_tags=self.settings.tags_per_room)
            self._renderer = SceneRenderer(spec, self.camera)
            self._room_id = room_id
        return self._renderer

    def __call__(self, index: int) -> tuple[dict[str, Any] | None, dict[str, float]]:
        s, cam = self.settings, self.camera
        if self._detector is None:
            self._detector = TagDetector(s.detector)
        renderer = self._room(index // STRIDE)
        spec = renderer.spec
        rng = np.random.default_rng([s.seed, index])
        hx, hy, hz = spec.room_m[0] / 2, spec.room_m[1] / 2, spec.room_m[2]
        half_fov = math.atan(cam.height / 2 / cam.fy)
        for _ in range(100):
            tag = spec.tags[int(rng.integers(0, len(spec.tags)))]
            world_from_tag = tag.pose()
            centre, normal = world_from_tag[:3, 3], world_from_tag[:3, 2]
            dist = math.exp(rng.uniform(math.log(s.distance_m[0]), math.log(s.distance_m[1])))
            tilt = math.radians(rng.uniform(0, s.max_tilt_deg))
            perp = np.cross(normal, rng.normal(size=3))
            perp /= np.linalg.norm(perp)
            direction = -normal * math.cos(tilt) + perp * math.sin(tilt)
            eye = centre + dist * direction
            if not (abs(eye[0]) < hx - 0.15 and abs(eye[1]) < hy - 0.15 and 0.15 < eye[2] < hz - 0.15):
                continue
            jitter = rng.uniform(-0.6, 0.6, 3) * dist * math.tan(half_fov)
            world_from_camera = look_at(
                eye, centre + jitter, roll_rad=math.radians(rng.uniform(-1, 1) * s.max_roll_deg)
            )
            pose = np.linalg.inv(world_from_camera) @ world_from_tag
            px = project(cam, pose, corners_in_tag(tag.size_m * 1.25))
            if (
                pose[2, 3] > 0.1
                and (px >= 2).all()
                and (px[:, 0] <= cam.width - 3).all()
                and (px[:, 1] <= cam.height - 3).all()
            ):
                break
        else:
            raise RuntimeError(f"no valid viewpoint in room {spec.seed} after 100 tries")
        meta = {"distance_m": float(np.linalg.norm(pose[:3, 3])), "tilt_deg": tilt_deg(pose)}
        image = renderer.render(world_from_camera)
        sigma = rng.uniform(0, s.max_noise_sigma)
        noisy = image.astype(np.float32) / 255.0 + rng.normal(0, sigma, image.shape).astype(np.float32)
        image = to_uint8(np.clip(noisy, 0, 1).astype(np.float32))
        found = [d for d in self._detector.detect(image) if d.tag_id == tag.id]
        if not found:
            return None, meta
        return label_sample(
            rng,
            image,
            (0, 0),
            found[0].corners_px,
            camera=cam,
            pose=pose,
            size_m=tag.size_m,
            tag_id=tag.id,
            index=index,
            perturb_frac=s.perturb_frac,
            roi_margin=s.roi_margin,
        ), meta
