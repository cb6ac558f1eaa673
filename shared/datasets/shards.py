"""Dataset on disk: safetensors shards of fixed size plus a versioned info.json.

A data set folder holds `info.json` and `shard_00000.safetensors`, ... Each shard stores, per
sample: `roi` uint8 (N,256,256), `keypoints` float32 (N,16,2) normalised ROI coordinates,
`roi_to_image` float64 (N,3,3), `camera_from_tag` float64 (N,4,4), `corners_px` float64 (N,4,2)
(detected, bias-corrected, unperturbed), `keypoints_px` float64 (N,16,2) exact image keypoints,
`tag_id` int32, `tag_size_m` float32, `distance_m` float32, `tilt_deg` float32, `is_test` uint8,
`index` int32. Shards are written atomically (tmp + rename), so an interrupted run resumes by
skipping finished shards; safetensors output is byte-identical for identical arrays.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray
from safetensors.numpy import load_file, save_file

INFO_VERSION: Final[str] = "splittag/dataset-info/v1"
FIELDS: Final[dict[str, tuple[str, tuple[int, ...]]]] = {
    "roi": ("uint8", (256, 256)),
    "keypoints": ("float32", (16, 2)),
    "roi_to_image": ("float64", (3, 3)),
    "camera_from_tag": ("float64", (4, 4)),
    "corners_px": ("float64", (4, 2)),
    "keypoints_px": ("float64", (16, 2)),
    "tag_id": ("int32", ()),
    "tag_size_m": ("float32", ()),
    "distance_m": ("float32", ()),
    "tilt_deg": ("float32", ()),
    "is_test": ("uint8", ()),
    "index": ("int32", ()),
}


class DatasetError(ValueError):
    """A data set folder that is missing, incomplete or of another version."""


def shard_path(root: Path, shard: int) -> Path:
    """Path of shard number `shard`."""
    return root / f"shard_{shard:05d}.safetensors"


def write_shard(path: Path, samples: Sequence[dict[str, Any]]) -> None:
    """Stack per-sample dicts into arrays and write them atomically."""
    arrays = {}
    for name, (dtype, shape) in FIELDS.items():
        arr = np.stack([np.asarray(s[name], dtype=dtype) for s in samples]) if samples else np.zeros((0, *shape), dtype)
        arrays[name] = np.ascontiguousarray(arr)
    tmp = path.with_suffix(".tmp")
    save_file(arrays, str(tmp))
    tmp.replace(path)


@dataclass(frozen=True)
class Dataset:
    """All samples of a data set folder in memory (a few hundred MB for 10k samples)."""

    root: Path
    info: dict[str, Any]
    arrays: dict[str, NDArray[Any]]

    def __len__(self) -> int:
        return int(self.arrays["index"].shape[0])

    def split(self, name: str) -> NDArray[np.int64]:
        """Row indices of the 'train' or 'test' split."""
        if name not in ("train", "test", "all"):
            raise ValueError(f"split must be train, test or all, got {name!r}")
        if name == "all":
            return np.arange(len(self), dtype=np.int64)
        mask = self.arrays["is_test"].astype(bool)
        return np.flatnonzero(mask if name == "test" else ~mask)


def read_info(root: Path) -> dict[str, Any]:
    """Read and check info.json."""
    path = Path(root) / "info.json"
    if not path.is_file():
        raise DatasetError(f"{root} is not a splittag data set (no info.json)")
    info: dict[str, Any] = json.loads(path.read_text())
    if info.get("version") != INFO_VERSION:
        raise DatasetError(f"{path}: version {info.get('version')!r}, expected {INFO_VERSION}")
    return info


def load_dataset(root: Path, *, limit: int | None = None) -> Dataset:
    """Load every shard listed in info.json (optionally only the first `limit` samples)."""
    root = Path(root)
    info = read_info(root)
    parts: dict[str, list[NDArray[Any]]] = {k: [] for k in FIELDS}
    count = 0
    for shard in range(int(info["num_shards"])):
        path = shard_path(root, shard)
        if not path.is_file():
            raise DatasetError(f"{root}: shard {path.name} is missing (generation not finished?)")
        data = load_file(str(path))
        for k in FIELDS:
            parts[k].append(data[k])
        count += len(data["index"])
        if limit is not None and count >= limit:
            break
    arrays = {k: np.concatenate(v)[:limit] for k, v in parts.items()}
    return Dataset(root, info, arrays)
