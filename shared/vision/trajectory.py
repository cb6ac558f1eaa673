"""TUM trajectory files: `t tx ty tz qx qy qz qw` per line, world_from_camera poses."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from shared.vision.files import atomic_write_text
from shared.vision.geometry import Array, GeometryError, make_pose


def read_tum(path: Path) -> list[tuple[float, Array]]:
    """TUM trajectory lines `t tx ty tz qx qy qz qw` -> [(t, world_from_camera)]."""
    from scipy.spatial.transform import Rotation

    out = []
    for n, line in enumerate(Path(path).read_text().splitlines(), start=1):
        if not line.strip() or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) != 8:
            raise GeometryError(f"{path}:{n}: expected 8 numbers, got {len(parts)}")
        v = [float(p) for p in parts]
        out.append((v[0], make_pose(Rotation.from_quat(v[4:8]).as_matrix(), v[1:4])))
    return out


def write_tum(path: Path, rows: list[tuple[float, Array]]) -> None:
    """Write `t tx ty tz qx qy qz qw` lines (world_from_camera)."""
    from scipy.spatial.transform import Rotation

    lines = []
    for t, pose in rows:
        q = Rotation.from_matrix(pose[:3, :3]).as_quat()
        lines.append(f"{t:.9f} " + " ".join(f"{v:.9f}" for v in (*pose[:3, 3], *q)))
    atomic_write_text(Path(path), "\n".join(lines) + "\n")


class PoseLog:
    """Stamped 4x4 poses in growable arrays: ~136 bytes a pose (a dict of arrays costs ~0.5 kB), for
    the histories a long run keeps (slam's finished frames, ground truth)."""

    def __init__(self) -> None:
        self._stamps = np.zeros(0, np.int64)
        self._poses = np.zeros((0, 4, 4))
        self._n = 0

    def __len__(self) -> int:
        return self._n

    def extend(self, stamps: list[int], poses: list[Array]) -> None:
        """Append poses (in any stamp order)."""
        need = self._n + len(stamps)
        if need > len(self._stamps):
            cap = max(need, 2 * len(self._stamps), 256)
            stamps_grown, poses_grown = np.zeros(cap, np.int64), np.zeros((cap, 4, 4))
            stamps_grown[: self._n], poses_grown[: self._n] = self._stamps[: self._n], self._poses[: self._n]
            self._stamps, self._poses = stamps_grown, poses_grown
        if stamps:
            self._stamps[self._n : need] = stamps
            self._poses[self._n : need] = np.asarray(poses, np.float64).reshape(-1, 4, 4)
        self._n = need

    def append(self, stamp: int, pose: Array) -> None:
        self.extend([stamp], [pose])

    def items(self) -> list[tuple[int, Array]]:
        """(stamp, pose) in stamp order (copies)."""
        order = np.argsort(self._stamps[: self._n], kind="stable")
        return [(int(self._stamps[i]), self._poses[i].copy()) for i in order]

    def positions(self) -> Array:
        """(n, 3) positions in stamp order."""
        order = np.argsort(self._stamps[: self._n], kind="stable")
        return np.asarray(self._poses[order, :3, 3])
