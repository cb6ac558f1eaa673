"""3D scenes rendered with MuJoCo: rooms with lights, shadows, textured walls, objects and tags at
known world poses. Used for the rendered (photoreal) data set, replacing the paper's Gazebo set,
and for the camera service's demo scene (a robot moving through a room).

Conventions: world z up. Tags hang on walls; each tag's frame follows shared.vision.geometry (x right,
y down, z into the tag = into the wall). Camera poses are `world_from_camera` in the OpenCV camera
convention (x right, y down, z forward); MuJoCo's camera looks along -z with y up, so
world_from_mujoco_cam = world_from_camera @ diag(1, -1, -1).
Tags are textured quads (a mesh with explicit texture coordinates), so the texture's orientation
is exact; tests check it by decoding the rendered tags and comparing their corners with projection.
"""

from __future__ import annotations

import math
import os
import tempfile
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from shared.sim.backgrounds import procedural_background
from shared.vision.camera import CameraIntrinsics
from shared.vision.geometry import Array, make_pose
from shared.vision.tagmap import TagSpec
from shared.vision.tags import BLACK_CELLS, CELLS, NUM_TAG36H11, tag_texture

os.environ.setdefault("MUJOCO_GL", "egl")

_CV_FROM_MJ = np.diag([1.0, -1.0, -1.0])


class TagPlacement(TagSpec):
    """A tag placed in a scene: a tag-map entry whose pose is required."""

    id: int = Field(ge=0, lt=NUM_TAG36H11)
    world_from_tag: list[list[float]]

    def pose(self) -> Array:
        """4x4 world_from_tag."""
        return np.asarray(self.world_from_tag, np.float64)


class BoxObject(BaseModel):
    """Clutter: a box, cylinder or sphere resting in the room."""

    model_config = ConfigDict(extra="forbid")
    kind: str  # "box" | "cylinder" | "sphere"
    pos: list[float]
    size: list[float]
    rgba: list[float]
    yaw: float = 0.0


class LightSpec(BaseModel):
    """A light near the ceiling."""

    model_config = ConfigDict(extra="forbid")
    pos: list[float]
    diffuse: float
    castshadow: bool = True


class SceneSpec(BaseModel):
    """Everything needed to rebuild a scene exactly: saved next to data sets and demo runs."""

    model_config = ConfigDict(extra="forbid")
    seed: int
    room_m: tuple[float, float, float]  # x extent, y extent, height; room spans [-x/2, x/2] x [-y/2, y/2]
    tags: list[TagPlacement]
    objects: list[BoxObject] = Field(default_factory=list)
    lights: list[LightSpec] = Field(default_factory=list)
    ambient: float = 0.25
    texture_seed: int = 0


def tag_on_wall(
    tag_id: int, size_m: float, *, wall: int, along_m: float, height_m: float, room_m: tuple[float, float, float]
) -> TagPlacement:
    """A tag on wall 0..3 (+y, +x, -y, -x), `along_m` from the wall's centre, centre `height_m` up."""
    hx, hy = room_m[0] / 2, room_m[1] / 2
    z_in = [np.array([0, 1.0, 0]), np.array([1.0, 0, 0]), np.array([0, -1.0, 0]), np.array([-1.0, 0, 0])][wall]
    y_down = np.array([0, 0, -1.0])
    x_right = np.cross(y_down, z_in)  # right-handed: x = y x z
    centre_on_wall = [
        np.array([along_m, hy, 0]),
        np.array([hx, -along_m, 0]),
        np.array([-along_m, -hy, 0]),
        np.array([-hx, along_m, 0]),
    ][wall]
    centre = centre_on_wall + np.array([0, 0, height_m]) - 0.002 * z_in  # 2 mm proud of the wall
    pose = make_pose(np.column_stack([x_right, y_down, z_in]), centre)
    return TagPlacement(id=tag_id, size_m=size_m, world_from_tag=pose.tolist())


def random_room(seed: int, *, n_tags: int = 10, n_objects: int = 8) -> SceneSpec:
    """A random room with tags on its walls, clutter on the floor and 2-4 lights."""
    rng = np.random.default_rng([seed, 0x5CE])
    room = (float(rng.uniform(5, 9)), float(rng.uniform(5, 9)), float(rng.uniform(2.6, 3.5)))
    ids = rng.choice(NUM_TAG36H11, size=n_tags, replace=False)
    tags = []
    for i, tag_id in enumerate(ids):
        wall = i % 4
        width = room[0] if wall % 2 == 0 else room[1]
        size = float(rng.uniform(0.12, 0.3))
        tags.append(
            tag_on_wall(
                int(tag_id),
                size,
                wall=wall,
                along_m=float(rng.uniform(-0.4, 0.4) * width),
                height_m=float(rng.uniform(0.4, 2.0)),
                room_m=room,
            )
        )
    objects = []
    for _ in range(n_objects):
        kind = str(rng.choice(["box", "cylinder", "sphere"]))
        s = rng.uniform(0.1, 0.5, 3)
        pos = [float(rng.uniform(-0.4, 0.4) * room[0]), float(rng.uniform(-0.4, 0.4) * room[1]), float(s[2])]
        objects.append(
            BoxObject(
                kind=kind,
                pos=pos,
                size=s.tolist(),
                rgba=[*rng.uniform(0.1, 0.9, 3).tolist(), 1.0],
                yaw=float(rng.uniform(0, np.pi)),
            )
        )
    lights = [
        LightSpec(
            pos=[float(rng.uniform(-0.4, 0.4) * room[0]), float(rng.uniform(-0.4, 0.4) * room[1]), room[2] - 0.1],
            diffuse=float(rng.uniform(0.3, 0.7)),
        )
        for _ in range(int(rng.integers(2, 5)))
    ]
    return SceneSpec(
        seed=seed,
        room_m=room,
        tags=tags,
        objects=objects,
        lights=lights,
        ambient=float(rng.uniform(0.15, 0.35)),
        texture_seed=int(rng.integers(0, 2**31)),
    )


def _write_png(path: Path, img: NDArray[np.uint8]) -> str:
    if not cv2.imwrite(str(path), img):
        raise OSError(f"cannot write texture {path}")
    return str(path)


def build_mjcf(spec: SceneSpec, camera: CameraIntrinsics, asset_dir: Path) -> str:
    """MJCF XML of the scene (textures written as PNGs into `asset_dir`)."""
    rng = np.random.default_rng([spec.texture_seed, 1])
    fovy = math.degrees(2 * math.atan(camera.height / 2 / camera.fy))
    hx, hy, hz = spec.room_m[0] / 2, spec.room_m[1] / 2, spec.room_m[2]
    assets, geoms = [], []
    for w in range(6):  # 4 walls, floor, ceiling
        tex = (procedural_background(rng, 256, 256) * 255).astype(np.uint8)
        grey3 = cv2.cvtColor(tex, cv2.COLOR_GRAY2BGR).astype(np.float64)
        colour = np.clip(grey3 * rng.uniform(0.6, 1.1, 3), 0, 255).astype(np.uint8)
        f = _write_png(asset_dir / f"wall{w}.png", colour)
        assets.append(
            f'<texture name="t{w}" type="2d" file="{f}"/>'
            f'<material name="m{w}" texture="t{w}" texrepeat="{rng.uniform(1, 4):.2f} '
            f'{rng.uniform(1, 4):.2f}" texuniform="true" specular="{rng.uniform(0, 0.3):.2f}"/>'
        )
    t = 0.05
    walls = [
        ((0, hy + t, hz / 2), (hx + t, t, hz / 2)),
        ((hx + t, 0, hz / 2), (t, hy + t, hz / 2)),
        ((0, -hy - t, hz / 2), (hx + t, t, hz / 2)),
        ((-hx - t, 0, hz / 2), (t, hy + t, hz / 2)),
        ((0, 0, -t), (hx + t, hy + t, t)),
        ((0, 0, hz + t), (hx + t, hy + t, t)),
    ]
    for w, (pos, size) in enumerate(walls):
        geoms.append(
            f'<geom type="box" pos="{pos[0]} {pos[1]} {pos[2]}" size="{size[0]} {size[1]} {size[2]}" material="m{w}"/>'
        )
    for i, tag in enumerate(spec.tags):
        f = _write_png(asset_dir / f"tag{tag.id}.png", tag_texture(tag.id))
        half = tag.size_m * CELLS / BLACK_CELLS / 2
        # Quad in the tag frame (x right, y down); texture v = 0 is the image's top row in MuJoCo.
        verts = f"{-half} {-half} 0  {half} {-half} 0  {half} {half} 0  {-half} {half} 0"
        assets.append(
            f'<texture name="tagtex{i}" type="2d" file="{f}"/>'
            f'<material name="tagmat{i}" texture="tagtex{i}" specular="0.1"/>'
            f'<mesh name="tagmesh{i}" vertex="{verts}" face="0 2 1  0 3 2" '
            f'texcoord="0 0  1 0  1 1  0 1" inertia="shell"/>'
        )
        pose = tag.pose()
        quat = _mat_to_quat(pose[:3, :3])
        p = pose[:3, 3]
        geoms.append(
            f'<geom type="mesh" mesh="tagmesh{i}" material="tagmat{i}" pos="{p[0]} {p[1]} {p[2]}" '
            f'quat="{quat[0]} {quat[1]} {quat[2]} {quat[3]}" contype="0" conaffinity="0"/>'
        )
    for o in spec.objects:
        dims = {"box": o.size, "cylinder": o.size[:2], "sphere": o.size[:1]}[o.kind]
        geoms.append(
            f'<geom type="{o.kind}" pos="{o.pos[0]} {o.pos[1]} {o.pos[2]}" '
            f'size="{" ".join(f"{v:.3f}" for v in dims)}" rgba="{" ".join(f"{v:.3f}" for v in o.rgba)}" '
            f'euler="0 0 {o.yaw:.3f}"/>'
        )
    lights = "".join(
        f'<light pos="{lt.pos[0]} {lt.pos[1]} {lt.pos[2]}" dir="0 0 -1" '
        f'diffuse="{lt.diffuse} {lt.diffuse} {lt.diffuse}" castshadow="{str(lt.castshadow).lower()}"/>'
        for lt in spec.lights
    )
    a = spec.ambient
    return f"""<mujoco model="splittag-scene">
  <compiler angle="radian"/>
  <visual>
    <global offwidth="{camera.width}" offheight="{camera.height}" fovy="{fovy}"/>
    <quality shadowsize="2048" offsamples="8"/>
    <headlight ambient="{a} {a} {a}" diffuse="0.4 0.4 0.4" specular="0 0 0"/>
    <map znear="0.01" zfar="50"/>
  </visual>
  <asset>{"".join(assets)}</asset>
  <worldbody>
    {lights}
    {"".join(geoms)}
    <camera name="cam" pos="0 0 1" fovy="{fovy}"/>
  </worldbody>
</mujoco>"""


def _mat_to_quat(r: Array) -> Array:
    import mujoco

    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(r, np.float64).ravel())
    return q


class SceneRenderer:
    """Compiles a scene once and renders grayscale images from OpenCV-convention camera poses."""

    def __init__(self, spec: SceneSpec, camera: CameraIntrinsics) -> None:
        import mujoco

        if camera.distortion_model != "none" and any(camera.distortion):
            raise ValueError("MuJoCo renders undistorted pinhole images only")
        if (
            abs(camera.fx - camera.fy) > 1e-6
            or abs(camera.cx - (camera.width - 1) / 2) > 1e-6
            or abs(camera.cy - (camera.height - 1) / 2) > 1e-6
        ):
            raise ValueError("MuJoCo cameras need fx == fy and the principal point at the image centre")
        self.spec, self.camera = spec, camera
        with tempfile.TemporaryDirectory(prefix="splittag-scene-") as tmp:
            self.model = mujoco.MjModel.from_xml_string(build_mjcf(spec, camera, Path(tmp)))
        self.data = mujoco.MjData(self.model)
        self.renderer = mujoco.Renderer(self.model, camera.height, camera.width)
        self._cam_id = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_CAMERA, "cam")
        self._mujoco: Any = mujoco

    def render(self, world_from_camera: Array) -> NDArray[np.uint8]:
        """Grayscale uint8 image seen from `world_from_camera` (OpenCV camera convention)."""
        mj = self._mujoco
        r_mj = world_from_camera[:3, :3] @ _CV_FROM_MJ
        self.model.cam_pos[self._cam_id] = world_from_camera[:3, 3]
        self.model.cam_quat[self._cam_id] = _mat_to_quat(r_mj)
        mj.mj_forward(self.model, self.data)
        self.renderer.update_scene(self.data, camera=self._cam_id)
        rgb = self.renderer.render()
        return np.asarray(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), np.uint8)

    def close(self) -> None:
        """Free the GL context."""
        self.renderer.close()


def look_at(eye: Array, target: Array, *, roll_rad: float = 0.0) -> Array:
    """world_from_camera (OpenCV convention) at `eye` looking at `target`, world z up, rolled."""
    z = np.asarray(target, np.float64) - np.asarray(eye, np.float64)
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    if np.linalg.norm(x) < 1e-6:
        x = np.array([1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    r = np.column_stack([x, y, z])
    c, s = math.cos(roll_rad), math.sin(roll_rad)
    roll = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    return make_pose(r @ roll, eye)
