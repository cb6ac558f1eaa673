"""Which CPUs a process runs on: robot and edge processes that share a host each on their own cores.

On one host the robot's and the edge's processes otherwise take turns on every core, and each wakes
to caches the other filled: a small message's codec work (cold Python) then costs several times what
it costs warm (README *Wire format*, CPU placement). `pin_cpus` moves every thread the process already
has (Zenoh's runtimes, torch's pool) and, through inheritance, every thread it starts later.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable
from pathlib import Path

log = logging.getLogger(__name__)


class CpuPlacementError(ValueError):
    """CPUs this process may not use (not in its allowed set, or none at all)."""


def allowed_cpus() -> frozenset[int]:
    """The CPUs this process may run on now."""
    return frozenset(os.sched_getaffinity(0))


def pin_cpus(cpus: Iterable[int]) -> frozenset[int]:
    """Run this process, all its threads and every thread they start on `cpus` only; returns the set
    it ran on before (to restore with `pin_cpus` again). Raises CpuPlacementError for an empty set or a
    CPU outside the allowed set (a container's cpuset, an earlier pin: restore before re-pinning)."""
    wanted = frozenset(cpus)
    before = allowed_cpus()
    online = frozenset(range(os.cpu_count() or 1))
    if not wanted:
        raise CpuPlacementError("an empty CPU set: give at least one CPU (or none at all to leave placement alone)")
    outside = sorted(wanted - online)
    if outside:
        raise CpuPlacementError(f"CPUs {outside} are not on this host (CPUs here: {sorted(online)})")
    for tid in _thread_ids():
        try:
            os.sched_setaffinity(tid, wanted)
        except ProcessLookupError:  # a thread that ended meanwhile
            continue
        except OSError as exc:
            raise CpuPlacementError(f"cannot place thread {tid} on CPUs {sorted(wanted)}: {exc}") from None
    log.info("running on CPUs %s (before: %s)", sorted(wanted), sorted(before))
    return before


def _thread_ids() -> list[int]:
    """Every thread of this process (Linux: /proc/self/task; elsewhere the calling thread)."""
    tasks = Path("/proc/self/task")
    return [int(p.name) for p in tasks.iterdir()] if tasks.is_dir() else [0]
