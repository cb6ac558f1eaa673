"""Which arithmetic runs the network on one side of the split (no torch here: settings import it).

`auto` (the services' default) picks by what this CPU has and what the weights folder holds, because
the same choice differs up to 20x between the machines we meet (full network per ROI, one thread):

| CPU | fp32 | bf16 | int8 (OpenVINO) |
| --- | --- | --- | --- |
| AMD EPYC Zen 4 (AVX-512 bf16 + VNNI) | 77 ms | 43 ms | 20 ms |
| AMD EPYC Zen 3 (AVX2 only) | 106 ms | 910 ms (emulated) | 43 ms |
| Intel Sapphire Rapids (AMX) | - | 25 ms | not yet measured |

So: int8 when the folder lists the int8 variant (OpenVINO runs it on AVX2, VNNI or AMX); else bf16
when the CPU does bf16 in hardware (AMX or AVX-512 bf16); else fp32. Never bf16 without hardware
support: PyTorch emulates it, 9x slower than fp32.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path
from typing import Literal, get_args

# fp32 and bf16: PyTorch eager on the safetensors weights; int8: OpenVINO on the folder's int8 variant.
Precision = Literal["fp32", "bf16", "int8"]
PRECISIONS: tuple[Precision, ...] = get_args(Precision)
# What configuration and the CLI accept: a precision, or `auto` (resolve_precision).
PrecisionChoice = Literal["auto", "fp32", "bf16", "int8"]
PRECISION_CHOICES: tuple[PrecisionChoice, ...] = get_args(PrecisionChoice)

HARDWARE_BF16_FLAGS = frozenset({"amx_bf16", "avx512_bf16"})


class ModelFileError(ValueError):
    """A weights folder, variant or export request that cannot be served: the CLI prints the message."""


def cpu_flags(cpuinfo: str | None = None) -> frozenset[str]:
    """The instruction-set flags of the first CPU in /proc/cpuinfo (empty where there is none)."""
    if cpuinfo is None:
        path = Path("/proc/cpuinfo")
        cpuinfo = path.read_text() if path.exists() else ""
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        if key.strip() == "flags":
            return frozenset(value.split())
    return frozenset()


def folder_variants(weights: Path) -> frozenset[str]:
    """The variants a weights folder's config.json lists (besides fp32/bf16, which every folder has)."""
    folder = Path(weights)
    if folder.is_file():
        folder = folder.parent
    config = folder / "config.json"
    if not config.is_file():
        return frozenset()
    try:
        return frozenset(json.loads(config.read_text()).get("variants", {}))
    except (json.JSONDecodeError, AttributeError):
        return frozenset()


def resolve_precision(choice: PrecisionChoice, *, variants: Iterable[str], flags: Iterable[str]) -> Precision:
    """The precision `choice` stands for on a CPU with `flags` and a folder holding `variants`."""
    if choice != "auto":
        if choice not in PRECISIONS:
            raise ValueError(f"precision must be one of {', '.join(PRECISION_CHOICES)}, got {choice!r}")
        return choice
    flag_set = set(flags)
    if "int8" in set(variants) and "avx2" in flag_set:
        return "int8"
    if flag_set & HARDWARE_BF16_FLAGS:
        return "bf16"
    return "fp32"


def resolve_for_folder(choice: PrecisionChoice, weights: Path, cpuinfo: str | None = None) -> Precision:
    """resolve_precision for a weights folder on this machine (or on the CPU that `cpuinfo` describes)."""
    if choice != "auto":
        return resolve_precision(choice, variants=(), flags=())
    return resolve_precision(choice, variants=folder_variants(weights), flags=cpu_flags(cpuinfo))
