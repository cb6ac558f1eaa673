"""Which CPUs a process runs on: robot and edge processes that share a host each on their own cores;
and which CPU this is (`cpu_label`: every benchmark and `splittag profile` print it first).

On one host the robot's and the edge's processes otherwise take turns on every core, and each wakes
to caches the other filled: a small message's codec work (cold Python) then costs several times what
it costs warm (docs/wire.md, *Views and CPU placement*). `pin_cpus` moves every thread the process already
has (Zenoh's runtimes, torch's pool) and, through inheritance, every thread it starts later.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Iterable
from pathlib import Path

log = logging.getLogger(__name__)


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
    """e.g. 'AMD EPYC (family 25 model 17), 2 cores, AVX-512 bf16 + VNNI + AVX-512, no AMX'.

    The project meets several CPU kinds (Intel Sapphire Rapids with AMX; AMD EPYC Zen 4 with AVX-512
    bf16 + VNNI; Zen 3 with AVX2 only), and the network's speed at one precision differs up to 20x
    between them, so a figure without its CPU says little."""
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


class CpuPlacementError(ValueError):
    """CPUs this process may not use (not in its allowed set, or none at all)."""


def allowed_cpus() -> frozenset[int]:
    """The CPUs this process may run on now."""
    return frozenset(os.sched_getaffinity(0))


def online_cpus() -> frozenset[int]:
    """The CPUs the kernel has online (/sys/devices/system/cpu/online; elsewhere 0..cpu_count-1)."""
    path = Path("/sys/devices/system/cpu/online")
    if not path.is_file():
        return frozenset(range(os.cpu_count() or 1))
    out: set[int] = set()
    for part in path.read_text().strip().split(","):
        lo, _, hi = part.partition("-")
        out.update(range(int(lo), int(hi or lo) + 1))
    return frozenset(out)


def pin_cpus(cpus: Iterable[int]) -> frozenset[int]:
    """Run this process, all its threads and every thread they start on `cpus` only; returns the set
    it ran on before (`pin_cpus(before)` restores it). Raises CpuPlacementError, leaving the placement
    as it was, for an empty set, a CPU the host does not have online, or a set the process may not
    fully use (a container's cpuset would silently shrink it)."""
    wanted = frozenset(cpus)
    before = allowed_cpus()
    online = online_cpus()
    if not wanted:
        raise CpuPlacementError("an empty CPU set: give at least one CPU (or none at all to leave placement alone)")
    outside = sorted(wanted - online)
    if outside:
        raise CpuPlacementError(f"CPUs {outside} are not on this host (CPUs here: {sorted(online)})")
    moved: dict[int, frozenset[int]] = {}
    try:
        # Until a pass finds no thread it has not moved: a thread not yet moved may start another,
        # which inherits the old set.
        while True:
            new = [tid for tid in _thread_ids() if tid not in moved]
            if not new:
                break
            for tid in new:
                try:
                    old = frozenset(os.sched_getaffinity(tid))
                    os.sched_setaffinity(tid, wanted)
                    got = frozenset(os.sched_getaffinity(tid))
                except ProcessLookupError:  # a thread that ended meanwhile
                    moved[tid] = frozenset()
                    continue
                except OSError as exc:
                    raise CpuPlacementError(f"cannot place thread {tid} on CPUs {sorted(wanted)}: {exc}") from None
                moved[tid] = old
                if got != wanted:
                    limited = f"thread {tid} may use only CPUs {sorted(got)} of {sorted(wanted)}"
                    raise CpuPlacementError(f"{limited} (a cpuset limits this process)")
    except CpuPlacementError:
        for tid, old in moved.items():
            if old:
                with contextlib.suppress(OSError):
                    os.sched_setaffinity(tid, old)
        raise
    log.info("running on CPUs %s (before: %s)", sorted(wanted), sorted(before))
    return before


def _thread_ids() -> list[int]:
    """Every thread of this process (Linux: /proc/self/task; elsewhere the calling thread)."""
    tasks = Path("/proc/self/task")
    return [int(p.name) for p in tasks.iterdir()] if tasks.is_dir() else [0]
