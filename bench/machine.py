"""Which CPU a benchmark ran on: every benchmark prints this first, and README figures quote it.

The project meets at least three CPU kinds (Intel Sapphire Rapids with AMX; AMD EPYC Zen 4 with AVX-512
bf16 + VNNI; AMD EPYC Zen 3 with AVX2 only), and the network's speed at one precision differs up to
20x between them, so a figure without its CPU says little.
"""

from __future__ import annotations

import os
from pathlib import Path

# Instruction-set features that decide the network's speed here, in the order we quote them.
FEATURES = (
    ("amx_bf16", "AMX"),
    ("avx512_bf16", "AVX-512 bf16"),
    ("avx512_vnni", "VNNI"),
    ("avx512f", "AVX-512"),
    ("avx_vnni", "AVX-VNNI"),
    ("avx2", "AVX2"),
)


def cpu_label(cpuinfo: str | None = None) -> str:
    """e.g. 'AMD EPYC (family 25 model 17), 2 cores, AVX-512 bf16 + VNNI + AVX-512, no AMX'."""
    text = cpuinfo if cpuinfo is not None else _read_cpuinfo()
    fields: dict[str, str] = {}
    for line in text.splitlines():
        key, _, value = line.partition(":")
        fields.setdefault(key.strip(), value.strip())
    flags = set(fields.get("flags", "").split())
    model = fields.get("model name", "unknown CPU")
    family = f"family {fields.get('cpu family', '?')} model {fields.get('model', '?')}"
    has = [name for flag, name in FEATURES if flag in flags and name != "AMX"]
    amx = "AMX" if "amx_bf16" in flags else "no AMX"
    cores = os.cpu_count() or 0
    return f"{model} ({family}), {cores} cores, {' + '.join(has) or 'no AVX2'}, {amx}"


def _read_cpuinfo() -> str:
    path = Path("/proc/cpuinfo")
    return path.read_text() if path.exists() else ""


if __name__ == "__main__":
    print(cpu_label())
