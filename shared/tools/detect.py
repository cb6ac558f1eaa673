"""`splittag detect`: the whole perception chain on image files, no services needed."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any, Final

import cv2
import numpy as np

from shared.model.runtime import TorchSplitNet
from shared.model.views import with_views
from shared.model.weights import load_keypoint_fusion, load_model
from shared.perception.single import perceive
from shared.runtime.sources import expand_paths
from shared.vision.camera import CameraIntrinsics
from shared.vision.detector import DetectorSettings
from shared.vision.geometry import GeometryError, camera_from_yaml
from shared.vision.linequads import LineQuadSettings
from shared.vision.proposals import ArucoSettings, FullResSettings, Stage1Detector, Stage1Settings
from shared.vision.tagmap import TagMapFile, load_tag_map

DEFAULT_WEIGHTS: Final[Path] = Path(__file__).resolve().parents[2] / "models"
DEFAULT_TAG_SIZE_M: Final[float] = 0.16  # without --tag-size or --tags (said on stderr)


def run_detect(
    paths: list[Path],
    *,
    camera_path: Path | None,
    tag_size_m: float | None,
    tags_path: Path | None,
    weights: Path | None,
    json_path: Path,
    quad_decimate: float = 1.0,
    aruco: bool = True,
    lines: bool = True,
    soft_decode: bool = True,
    views: int = 1,
) -> int:
    """Process every image; unreadable ones are reported in the JSON and on stderr. Exit 0 if any ran.
    Without a camera file each image gets an assumed pinhole camera (`assumed_camera`), said once."""
    camera = camera_from_yaml(camera_path) if camera_path is not None else None
    if camera is None:
        print(
            "splittag detect: no --camera: each image is solved with an assumed pinhole camera (fx = fy = the "
            "image's width, principal point at its centre, no distortion): the keypoints and corners do not "
            "depend on it, the poses' distance and tilt do (give the camera's ROS camera_info YAML for those)",
            file=sys.stderr,
        )
    if tags_path is None and tag_size_m is None:
        print(
            f"splittag detect: no --tag-size or --tags: every tag is solved at {DEFAULT_TAG_SIZE_M} m (the poses' "
            "translations scale with the true size)",
            file=sys.stderr,
        )
    tag_map = load_tag_map(tags_path) if tags_path else TagMapFile(default_size_m=tag_size_m or DEFAULT_TAG_SIZE_M)
    # fp32 PyTorch, as always; with views, each ROI's views averaged (shared.model.views)
    torch_model = load_model(weights or DEFAULT_WEIGHTS)
    model = torch_model if views == 1 else with_views(TorchSplitNet(torch_model, bf16=False), views)
    fusion = load_keypoint_fusion(weights or DEFAULT_WEIGHTS)
    detector = Stage1Detector(
        Stage1Settings(
            apriltag=DetectorSettings(quad_decimate=quad_decimate),
            aruco=ArucoSettings(enabled=aruco),
            lines=LineQuadSettings(enabled=lines, soft_decode=soft_decode),
            full_res=FullResSettings(enabled=False),  # unrelated images: no state from one to the next
        )
    )
    images: list[dict[str, Any]] = []
    errors = 0
    for path in expand_paths(paths):
        entry: dict[str, Any] = {"path": str(path)}
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) if path.is_file() else None
        if image is None:
            entry["error"] = "cannot read image (missing, not an image, or unsupported format)"
        elif camera is not None and image.shape != (camera.height, camera.width):
            entry["error"] = (
                f"image is {image.shape[1]}x{image.shape[0]} but the camera file says {camera.width}x{camera.height}"
            )
        else:
            this_camera = camera or assumed_camera(image.shape[1], image.shape[0])
            if camera is None:
                entry["assumed_camera"] = this_camera.model_dump()
            try:
                entry["tags"] = [
                    t.to_json()
                    for t in perceive(
                        np.ascontiguousarray(image),
                        camera=this_camera,
                        detector=detector,
                        model=model,
                        tag_map=tag_map,
                        fusion=fusion,
                    )
                ]
            except GeometryError as exc:
                entry["error"] = str(exc)
        if "error" in entry:
            errors += 1
            print(f"splittag detect: {path}: {entry['error']}", file=sys.stderr)
        else:
            print(f"{path}: {len(entry['tags'])} tags " + " ".join(str(t["id"]) for t in entry["tags"]))
        images.append(entry)
    json_path.parent.mkdir(parents=True, exist_ok=True)
    json_path.write_text(
        json.dumps(
            {
                "camera": camera.model_dump() if camera is not None else None,  # (None: each image's assumed_camera)
                "stage1": detector.settings.model_dump(),
                "images": images,
            },
            indent=2,
        )
    )
    detector.close()
    print(f"wrote {json_path} ({len(images) - errors} images processed, {errors} failed)")
    return 0 if len(images) > errors else 1


def assumed_camera(width: int, height: int) -> CameraIntrinsics:
    """A pinhole camera for an image without a camera file: fx = fy = its width (a 53 deg field of view,
    a phone's or a webcam's), the principal point at its centre, no distortion."""
    return CameraIntrinsics(
        width=width,
        height=height,
        fx=float(width),
        fy=float(width),
        cx=(width - 1) / 2,
        cy=(height - 1) / 2,
        distortion_model="none",
        distortion=[],
    )
