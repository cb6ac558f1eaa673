"""TUM trajectory files: `t tx ty tz qx qy qz qw` per line, world_from_camera poses."""

from __future__ import annotations

import io
from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import Final

import numpy as np
from numpy.typing import NDArray

from shared.vision.files import atomic_write_text
from shared.vision.geometry import Array, GeometryError, make_pose
from shared.vision.stamps import format_stamp_nanos


def _tum_rows(path: Path) -> list[list[str]]:
    """The 8 fields of each TUM line (comments and blank lines skipped)."""
    out = []
    for n, line in enumerate(Path(path).read_text().splitlines(), start=1):
        if not line.strip() or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) != 8:
            raise GeometryError(f"{path}:{n}: expected 8 numbers, got {len(parts)}")
        out.append(parts)
    return out


def _pose_of(fields: list[str]) -> Array:
    from scipy.spatial.transform import Rotation

    v = [float(p) for p in fields]
    return make_pose(Rotation.from_quat(v[3:7]).as_matrix(), v[0:3])


def read_tum(path: Path) -> list[tuple[float, Array]]:
    """TUM trajectory lines `t tx ty tz qx qy qz qw` -> [(t, world_from_camera)]."""
    return [(float(parts[0]), _pose_of(parts[1:])) for parts in _tum_rows(path)]


def write_tum(path: Path, rows: list[tuple[float, Array]]) -> None:
    """Write `t tx ty tz qx qy qz qw` lines (world_from_camera)."""
    stamps = np.array([t for t, _ in rows], np.float64)
    poses = np.array([p for _, p in rows], np.float64).reshape(-1, 4, 4)
    write_tum_arrays(path, stamps, poses)


def write_tum_arrays(path: Path, stamps: Array, poses: Array) -> None:
    """`write_tum` for arrays (n,) and (n, 4, 4): vectorised, no Python object per pose (a long run
    writes its whole trajectory every few seconds). Stamps in seconds (floats), or in nanoseconds
    (integers: written exactly, e.g. 1341847980.722988000 for a data set's 1341847980.722988, where a
    float second of that size is only good to ~0.2 us)."""
    from scipy.spatial.transform import Rotation

    n = len(stamps)
    if n == 0:
        atomic_write_text(Path(path), "")
        return
    quats = Rotation.from_matrix(poses[:, :3, :3]).as_quat()
    buf = io.StringIO()
    if np.issubdtype(np.asarray(stamps).dtype, np.integer):
        np.savetxt(buf, np.column_stack([poses[:, :3, 3], quats]), fmt="%.9f")
        lines = buf.getvalue().splitlines()
        text = "".join(f"{format_stamp_nanos(int(t))} {line}\n" for t, line in zip(stamps, lines, strict=True))
    else:
        np.savetxt(buf, np.column_stack([stamps, poses[:, :3, 3], quats]), fmt="%.9f")
        text = buf.getvalue()
    atomic_write_text(Path(path), text)


_MAX_STAMP_S: Final[Decimal] = Decimal(2**63).scaleb(-9)  # stamps travel as int64 nanoseconds


def parse_stamp_nanos(text: str) -> int:
    """Decimal seconds (a TUM or rgb.txt stamp) as nanoseconds, exact to the digits given; GeometryError
    for anything that is not a time in [0, 2**63 ns)."""
    try:
        stamp = Decimal(text)
    except InvalidOperation:
        raise GeometryError(f"timestamp {text!r} is not a number") from None
    if not stamp.is_finite() or not 0 <= stamp < _MAX_STAMP_S:
        raise GeometryError(f"timestamp {text!r} must be a finite time in [0, 2**63 ns) s")
    return int(stamp.scaleb(9).to_integral_value())


def read_tum_nanos(path: Path) -> tuple[NDArray[np.int64], Array]:
    """`read_tum` with exact stamps: ((n,) nanoseconds, (n, 4, 4) poses)."""
    rows = _tum_rows(path)
    stamps = np.array([parse_stamp_nanos(parts[0]) for parts in rows], np.int64)
    return stamps, np.array([_pose_of(parts[1:]) for parts in rows], np.float64).reshape(-1, 4, 4)


class PoseLog:
    """Stamped poses, compact: stamp (int64), position (3 x float64) and rotation as a unit quaternion
    (4 x float32), 52 bytes a pose (a dict of 4x4 arrays costs ~0.5 kB), in growable arrays; for the
    histories a long run keeps (slam's finished frames, ground truth). Rotations come back to within
    ~1e-7 rad."""

    def __init__(self) -> None:
        self._stamps = np.zeros(0, np.int64)
        self._positions = np.zeros((0, 3))
        self._quats = np.zeros((0, 4), np.float32)
        self._n = 0

    def __len__(self) -> int:
        return self._n

    def extend(self, stamps: list[int], poses: list[Array]) -> None:
        """Append poses (in any stamp order)."""
        from scipy.spatial.transform import Rotation

        need = self._n + len(stamps)
        if need > len(self._stamps):
            cap = max(need, 2 * len(self._stamps), 256)
            grown = (np.zeros(cap, np.int64), np.zeros((cap, 3)), np.zeros((cap, 4), np.float32))
            grown[0][: self._n], grown[1][: self._n], grown[2][: self._n] = (
                self._stamps[: self._n],
                self._positions[: self._n],
                self._quats[: self._n],
            )
            self._stamps, self._positions, self._quats = grown
        if stamps:
            m = np.asarray(poses, np.float64).reshape(-1, 4, 4)
            self._stamps[self._n : need] = stamps
            self._positions[self._n : need] = m[:, :3, 3]
            self._quats[self._n : need] = Rotation.from_matrix(m[:, :3, :3]).as_quat()
        self._n = need

    def append(self, stamp: int, pose: Array) -> None:
        self.extend([stamp], [pose])

    def arrays(self) -> tuple[Array, Array]:
        """(stamps (n,), poses (n, 4, 4)) in stamp order."""
        from scipy.spatial.transform import Rotation

        order = np.argsort(self._stamps[: self._n], kind="stable")
        poses = np.tile(np.eye(4), (len(order), 1, 1))
        if len(order):
            poses[:, :3, :3] = Rotation.from_quat(self._quats[order].astype(np.float64)).as_matrix()
            poses[:, :3, 3] = self._positions[order]
        return self._stamps[order], poses

    def items(self) -> list[tuple[int, Array]]:
        """(stamp, pose) in stamp order."""
        stamps, poses = self.arrays()
        return [(int(t), p) for t, p in zip(stamps, poses, strict=True)]

    def positions(self) -> Array:
        """(n, 3) positions in stamp order."""
        order = np.argsort(self._stamps[: self._n], kind="stable")
        return np.asarray(self._positions[order])


class StampMap:
    """Live capture time -> a data set's own time, per frame, compact (two int64 per frame, growable):
    slam writes its trajectory in the data set's time when every pose has one."""

    def __init__(self) -> None:
        self._pairs = np.zeros((0, 2), np.int64)
        self._n = 0

    def __len__(self) -> int:
        return self._n

    def add(self, capture_nanos: int, source_nanos: int) -> None:
        """Record one frame's pair."""
        if self._n == len(self._pairs):
            grown = np.zeros((max(256, 2 * len(self._pairs)), 2), np.int64)
            grown[: self._n] = self._pairs[: self._n]
            self._pairs = grown
        self._pairs[self._n] = (capture_nanos, source_nanos)
        self._n += 1

    def lookup(self, capture_nanos: Array) -> tuple[Array, Array]:
        """(source nanos, found mask) for each capture time; not found: the capture time itself."""
        captures = np.asarray(capture_nanos, np.int64)
        pairs = self._pairs[: self._n]
        order = np.argsort(pairs[:, 0], kind="stable")
        keys, values = pairs[order, 0], pairs[order, 1]
        at = np.clip(np.searchsorted(keys, captures), 0, max(len(keys) - 1, 0))
        found = (keys[at] == captures) if len(keys) else np.zeros(len(captures), bool)
        out = np.where(found, values[at] if len(keys) else captures, captures)
        return out, found
