"""The one tag-map format: a default size plus per-tag sizes and optional world poses, in YAML or
JSON. Read by edge_infer (sizes), slam (known poses), the launcher and `splittag detect`; slam writes
its map in the same format (`map.json`), so a map it built can be fed back as a known map."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from shared.vision.files import atomic_write_text
from shared.vision.geometry import Array, GeometryError, check_rigid


class TagSpec(BaseModel):
    """One tag: its size and (optionally) its pose in the world. The one shape of "a tag with a size
    and a pose": tag maps, slam's map.json and the simulated scenes' placements all use it."""

    model_config = ConfigDict(extra="forbid")
    id: int = Field(ge=0)
    size_m: float = Field(gt=0, le=100)
    world_from_tag: list[list[float]] | None = None
    # How well world_from_tag is known (1 sigma per axis, in the tag's frame): slam takes the pose as a
    # prior with these; None = slam's `known_tag_sigma` (1 mm / 1 mrad: a surveyed map). slam writes
    # its own map's marginals here, so a map it built and fed back is believed only as far as it holds.
    position_sigma_m: float | None = Field(default=None, gt=0, le=100)
    rotation_sigma_deg: float | None = Field(default=None, gt=0, le=180)

    @field_validator("world_from_tag")
    @classmethod
    def _rigid(cls, value: list[list[float]] | None) -> list[list[float]] | None:
        if value is not None:
            check_rigid(np.asarray(value, np.float64), "world_from_tag")
        return value

    def pose(self) -> Array | None:
        """4x4 world_from_tag, or None when the map gives only the size."""
        return None if self.world_from_tag is None else np.asarray(self.world_from_tag, np.float64)

    def stated_sigmas(self) -> tuple[float | None, float | None]:
        """(rotation sigma in rad, position sigma in m) as the map states them (None: not stated)."""
        rot = None if self.rotation_sigma_deg is None else float(np.radians(self.rotation_sigma_deg))
        return rot, self.position_sigma_m


class TagMapFile(BaseModel):
    """A tag-map file (YAML or JSON): a default size plus per-tag sizes and optional world poses."""

    model_config = ConfigDict(extra="forbid")
    default_size_m: float = Field(default=0.16, gt=0)
    anchor_tag_id: int | None = None
    tags: list[TagSpec] = Field(default_factory=list)

    @model_validator(mode="after")
    def _one_entry_per_tag_and_a_listed_anchor(self) -> TagMapFile:
        # A repeated id was accepted: edge_infer solved the tag at its first size, slam at its last, and
        # a trial's ATE went from 0.62 to 17.5 cm with only a misleading warning. An anchor the map does
        # not list left slam lost on every frame without a word.
        counts = Counter(t.id for t in self.tags)
        repeated = sorted(i for i, n in counts.items() if n > 1)
        if repeated:
            raise ValueError(f"tag ids listed more than once: {repeated} (one entry per tag: its size and pose)")
        if self.anchor_tag_id is not None and self.anchor_tag_id not in counts:
            raise ValueError(
                f"anchor_tag_id {self.anchor_tag_id} is not one of the map's tags: list it (its size, and with a "
                "known map its world pose), or leave anchor_tag_id out"
            )
        return self

    def size_of(self, tag_id: int) -> float:
        """Tag size in metres (the default for unknown ids)."""
        for t in self.tags:
            if t.id == tag_id:
                return t.size_m
        return self.default_size_m


class TagMapError(GeometryError):
    """A tag-map file that is not there or not a tag map (a user's file, not maths)."""


def load_tag_map(path: Path) -> TagMapFile:
    """Read a tag-map YAML/JSON file, with a clear error for a malformed one."""
    try:
        doc = yaml.safe_load(Path(path).read_text())
        return TagMapFile.model_validate(doc)
    except ValidationError as exc:  # each refused field by its place, without pydantic's links
        why = "; ".join(
            f"{'.'.join(str(p) for p in e['loc']) or 'the map'}: {e['msg']}" for e in exc.errors(include_url=False)
        )
        raise TagMapError(f"tag map {path}: {why}") from exc
    except (OSError, yaml.YAMLError) as exc:
        raise TagMapError(f"tag map {path}: {exc}") from exc


def write_tag_map(path: Path, tag_map: TagMapFile) -> None:
    """Write a tag map as JSON (loadable by `load_tag_map`)."""
    atomic_write_text(Path(path), json.dumps(tag_map.model_dump(exclude_none=True), indent=2))


def tag_map_from_poses(
    poses: dict[int, tuple[float, np.ndarray]],
    *,
    anchor_tag_id: int | None,
    default_size_m: float = 0.16,
    sigmas: dict[int, tuple[float, float]] | None = None,
) -> TagMapFile:
    """A tag map from {id: (size_m, world_from_tag 4x4)}; `sigmas` {id: (rotation rad, position m)}
    states how well each pose is known."""
    sigmas = sigmas or {}
    return TagMapFile(
        default_size_m=default_size_m,
        anchor_tag_id=anchor_tag_id,
        tags=[
            TagSpec(
                id=t,
                size_m=size,
                world_from_tag=np.asarray(pose, np.float64).tolist(),
                position_sigma_m=sigmas[t][1] if t in sigmas else None,
                rotation_sigma_deg=float(np.degrees(sigmas[t][0])) if t in sigmas else None,
            )
            for t, (size, pose) in sorted(poses.items())
        ],
    )
