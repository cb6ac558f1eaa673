"""TUM trajectory files: `t tx ty tz qx qy qz qw` per line, world_from_camera poses."""

from __future__ import annotations

from pathlib import Path

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
