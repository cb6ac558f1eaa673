"""The one tag-map format: a default size plus per-tag sizes and optional world poses, in YAML or
JSON. Read by edge_infer (sizes), slam (known poses), the launcher and `splittag detect`; slam writes
its map in the same format (`map.json`), so a map it built can be fed back as a known map."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from shared.vision.files import atomic_write_text
from shared.vision.geometry import Array, GeometryError, check_rigid


class TagSpec(BaseModel):
    """One tag: its size and (optionally) its pose in the world. The one shape of "a tag with a size
    and a pose": tag maps, slam's map.json and the simulated scenes' placements all use it."""

    model_config = ConfigDict(extra="forbid")
    id: int = Field(ge=0)
    size_m: float = Field(gt=0, le=100)
    world_from_tag: list[list[float]] | None = None

    @field_validator("world_from_tag")
    @classmethod
    def _rigid(cls, value: list[list[float]] | None) -> list[list[float]] | None:
        if value is not None:
            check_rigid(np.asarray(value, np.float64), "world_from_tag")
        return value

    def pose(self) -> Array | None:
        """4x4 world_from_tag, or None when the map gives only the size."""
        return None if self.world_from_tag is None else np.asarray(self.world_from_tag, np.float64)


class TagMapFile(BaseModel):
    """A tag-map file (YAML or JSON): a default size plus per-tag sizes and optional world poses."""

    model_config = ConfigDict(extra="forbid")
    default_size_m: float = Field(default=0.16, gt=0)
    anchor_tag_id: int | None = None
    tags: list[TagSpec] = Field(default_factory=list)

    def size_of(self, tag_id: int) -> float:
        """Tag size in metres (the default for unknown ids)."""
        for t in self.tags:
            if t.id == tag_id:
                return t.size_m
        return self.default_size_m


def load_tag_map(path: Path) -> TagMapFile:
    """Read a tag-map YAML/JSON file, with a clear error for a malformed one."""
    try:
        doc = yaml.safe_load(Path(path).read_text())
        return TagMapFile.model_validate(doc)
    except (OSError, yaml.YAMLError, ValidationError) as exc:
        raise GeometryError(f"tag map {path}: {exc}") from exc


def write_tag_map(path: Path, tag_map: TagMapFile) -> None:
    """Write a tag map as JSON (loadable by `load_tag_map`)."""
    atomic_write_text(Path(path), json.dumps(tag_map.model_dump(exclude_none=True), indent=2))


def tag_map_from_poses(
    poses: dict[int, tuple[float, np.ndarray]], *, anchor_tag_id: int | None, default_size_m: float = 0.16
) -> TagMapFile:
    """A tag map from {id: (size_m, world_from_tag 4x4)}."""
    return TagMapFile(
        default_size_m=default_size_m,
        anchor_tag_id=anchor_tag_id,
        tags=[
            TagSpec(id=t, size_m=size, world_from_tag=np.asarray(pose, np.float64).tolist())
            for t, (size, pose) in sorted(poses.items())
        ],
    )
