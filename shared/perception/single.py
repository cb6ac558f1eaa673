"""The whole perception chain as pure functions: stage 1 -> ROIs -> split net -> keypoints -> PnP.

The services call the same pieces split across processes; `splittag detect` and `splittag eval`
call them in one process.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray

from shared.model.infer import keypoints
from shared.model.net import SplitKeypointNet
from shared.model.runtime import SplitNet
from shared.vision.camera import CameraIntrinsics
from shared.vision.detector import Detection, Stage1
from shared.vision.fusion import KeypointFusion, edge_width_px
from shared.vision.geometry import (
    Array,
    corners_in_tag,
    image_to_roi_homography,
    keypoints_to_image,
    lattice_in_tag,
    warp_roi,
)
from shared.vision.pnp import PoseCandidates, solve_planar_pnp
from shared.vision.tagmap import TagMapFile


def extract_rois(image: NDArray[np.uint8], detections: list[Detection]) -> tuple[NDArray[np.uint8], Array]:
    """ROIs (N,256,256) and their ROI->image homographies (N,3,3) for the detected quads."""
    rois, homs = [], []
    for d in detections:
        h = image_to_roi_homography(d.corners_px)
        rois.append(warp_roi(image, h))
        homs.append(np.linalg.inv(h))
    if not rois:
        return np.zeros((0, 256, 256), np.uint8), np.zeros((0, 3, 3))
    return np.stack(rois), np.stack(homs)


@torch.no_grad()
def run_network(
    model: SplitKeypointNet | SplitNet, rois: NDArray[np.uint8], *, bf16: bool = False, channels_last: bool = True
) -> NDArray[np.float32]:
    """Normalised keypoints (N,16,2) for uint8 ROIs (N,256,256): PyTorch weights (bf16 autocast with
    `bf16`), or a SplitNet at its own precision (the whole network, the tail from cut 0)."""
    if len(rois) == 0:
        return np.zeros((0, 16, 2), np.float32)
    if not isinstance(model, SplitKeypointNet):
        return model.tail(rois, 0)
    rois_u8 = torch.from_numpy(np.ascontiguousarray(rois)).unsqueeze(1)
    return np.asarray(keypoints(model, rois_u8, bf16=bf16, channels_last=channels_last).numpy(), np.float32)


@dataclass(frozen=True)
class TagResult:
    """Everything `splittag detect` reports for one tag."""

    detection: Detection
    tag_size_m: float
    keypoints_px: Array | None  # the network's 16, fused with stage 1's corners when a fusion is given
    pose: PoseCandidates | None  # from the 16 keypoints (or the corners when no network)
    corner_pose: PoseCandidates
    # The network's own 16, before any fusion, and the pose from them alone: fused keypoints carry
    # AprilTag's corners, so "network against AprilTag" compared AprilTag partly with itself (a researcher).
    network_keypoints_px: Array | None = None
    network_pose: PoseCandidates | None = None

    def to_json(self) -> dict[str, Any]:
        """JSON-friendly dict."""

        def pose_json(p: PoseCandidates) -> dict[str, Any]:
            return {
                "chosen": {
                    "R": p.camera_from_tag[:3, :3].tolist(),
                    "t_m": p.camera_from_tag[:3, 3].tolist(),
                    "reprojection_error_px": p.reprojection_error_px,
                },
                "alternative": {
                    "R": p.alt_camera_from_tag[:3, :3].tolist(),
                    "t_m": p.alt_camera_from_tag[:3, 3].tolist(),
                    "reprojection_error_px": p.alt_reprojection_error_px,
                },
            }

        d = self.detection
        return {
            "id": d.tag_id,
            "decision_margin": d.decision_margin,
            "hamming": d.hamming,
            "proposer": d.proposer,
            "tag_size_m": self.tag_size_m,
            # what stage 1 proposed, whoever did; AprilTag's own corners only when it found the tag (a trial
            # compared "AprilTag" corners that ArUco or the line quads had found)
            "stage1_corners_px": d.corners_px.tolist(),
            "apriltag_corners_px": d.corners_px.tolist() if d.proposer in ("apriltag", "fullres") else None,
            "keypoints_px": None if self.keypoints_px is None else self.keypoints_px.tolist(),
            "network_keypoints_px": None if self.network_keypoints_px is None else self.network_keypoints_px.tolist(),
            "camera_from_tag": None if self.pose is None else pose_json(self.pose),
            "camera_from_tag_network_only": None if self.network_pose is None else pose_json(self.network_pose),
            "camera_from_tag_corners_only": pose_json(self.corner_pose),
        }


def perceive(
    image: NDArray[np.uint8],
    *,
    camera: CameraIntrinsics,
    detector: Stage1,
    model: SplitKeypointNet | SplitNet | None,
    tag_map: TagMapFile,
    fusion: KeypointFusion | None = None,
    bf16: bool = False,
) -> list[TagResult]:
    """Stage 1, the network (if given) and PnP on one grayscale image; `fusion` as in `edge_step`,
    `bf16` as the services run the network (fp32 by default, as `splittag detect` and `eval`)."""
    detections = detector.detect(image)
    rois, homs = extract_rois(image, detections)
    kps = run_network(model, rois, bf16=bf16) if model is not None else None
    out = []
    for i, d in enumerate(detections):
        size = tag_map.size_of(d.tag_id)
        corner_pose = solve_planar_pnp(camera, corners_in_tag(size), d.corners_px)
        if kps is None:
            out.append(TagResult(d, size, None, None, corner_pose))
            continue
        network_px = keypoints_to_image(kps[i], homs[i])
        network_pose = solve_planar_pnp(camera, lattice_in_tag(size), network_px)
        if fusion is None:
            kp_px, pose = network_px, network_pose
        else:
            kp_px = fusion.apply(network_px, d.corners_px, homs[i], edge_width_px(rois[i], homs[i]))
            pose = solve_planar_pnp(camera, lattice_in_tag(size), kp_px)
        out.append(TagResult(d, size, kp_px, pose, corner_pose, network_px, network_pose))
    return out
