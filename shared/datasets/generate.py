"""Parallel, resumable, deterministic data set generation into safetensors shards.

Shard s holds exactly `shard_size` samples: it tries sample indices s * STRIDE, s * STRIDE + 1, ...
until that many pass stage 1, so the content depends only on (seed, shard) and not on how many
processes ran. Within each shard exactly 30 % of the samples (a seeded permutation) are test.
Finished shards are skipped on restart; a per-shard stats file keeps the failure counts.
"""

from __future__ import annotations

import itertools
import json
import math
import multiprocessing as mp
import os
import time
from pathlib import Path
from typing import Any, Final, Protocol

import cv2
import numpy as np
from tqdm import tqdm

from shared.datasets.shards import INFO_VERSION, shard_path, write_shard

STRIDE: Final[int] = 1_000_000
TEST_FRACTION: Final[float] = 0.3
DISTANCE_BINS_M: Final[tuple[float, ...]] = (0.0, 0.75, 1.5, 3.0, 1e9)
TILT_BINS_DEG: Final[tuple[float, ...]] = (0.0, 20.0, 40.0, 55.0, 90.0)


class SampleMaker(Protocol):
    """Makes sample `index`: (sample dict or None when stage 1 missed, meta with distance/tilt)."""

    def __call__(self, index: int) -> tuple[dict[str, Any] | None, dict[str, float]]: ...


_MAKER: SampleMaker | None = None


def _init_worker(maker: SampleMaker) -> None:
    global _MAKER
    cv2.setNumThreads(1)
    _MAKER = maker


def _make_shard(job: tuple[Path, int, int, int]) -> dict[str, Any]:
    out, shard, size, seed = job
    assert _MAKER is not None
    samples: list[dict[str, Any]] = []
    attempts: list[dict[str, Any]] = []
    index = shard * STRIDE
    while len(samples) < size:
        sample, meta = _MAKER(index)
        attempts.append({**meta, "ok": sample is not None})
        if sample is not None:
            samples.append(sample)
        index += 1
        if index - shard * STRIDE > 20 * size + 100:
            raise RuntimeError(f"shard {shard}: stage 1 fails on almost every sample; check settings")
    order = np.random.default_rng([seed, shard, 0x5E5]).permutation(size)
    n_test = round(size * TEST_FRACTION)
    for rank, i in enumerate(order):
        samples[i]["is_test"] = int(rank < n_test)
    write_shard(shard_path(out, shard), samples)
    stats = {"shard": shard, "attempts": attempts}
    tmp = out / f"stats_{shard:05d}.json.tmp"
    tmp.write_text(json.dumps(stats))
    tmp.replace(out / f"stats_{shard:05d}.json")
    return stats


def _bin_table(attempts: list[dict[str, Any]], key: str, edges: tuple[float, ...]) -> list[dict[str, Any]]:
    rows = []
    for lo, hi in itertools.pairwise(edges):
        sel = [a for a in attempts if lo <= a[key] < hi]
        fails = sum(not a["ok"] for a in sel)
        rows.append(
            {
                "range": [lo, hi if hi < 1e8 else None],
                "attempts": len(sel),
                "failures": fails,
                "failure_rate": round(fails / len(sel), 4) if sel else None,
            }
        )
    return rows


def generate(
    out: Path,
    *,
    n: int,
    seed: int,
    kind: str,
    settings: dict[str, Any],
    maker: SampleMaker,
    shard_size: int = 250,
    workers: int | None = None,
) -> dict[str, Any]:
    """Generate (or finish) a data set of exactly `n` samples in `out`; returns info.json's content."""
    if n <= 0:
        raise ValueError(f"n must be positive, got {n}")
    shard_size = min(shard_size, n)
    num_shards = math.ceil(n / shard_size)
    sizes = [min(shard_size, n - s * shard_size) for s in range(num_shards)]
    out.mkdir(parents=True, exist_ok=True)
    header = {
        "version": INFO_VERSION,
        "kind": kind,
        "n": n,
        "seed": seed,
        "shard_size": shard_size,
        "num_shards": num_shards,
        "settings": settings,
    }
    info_path = out / "info.json"
    if info_path.is_file():
        old = json.loads(info_path.read_text())
        if {k: old.get(k) for k in header} != header:
            raise ValueError(
                f"{out} holds a different data set ({old.get('kind')}, n={old.get('n')}, "
                f"seed={old.get('seed')}); use another folder"
            )
    else:
        info_path.write_text(json.dumps(header, indent=2))
    todo = [
        (out, s, sizes[s], seed)
        for s in range(num_shards)
        if not (shard_path(out, s).is_file() and (out / f"stats_{s:05d}.json").is_file())
    ]
    started = time.monotonic()
    workers = workers or os.cpu_count() or 1
    if todo:
        # spawn, not fork: a parent that already runs OpenCV/OpenMP thread pools (tests, notebooks)
        # would leave forked workers deadlocked on those pools' locks. The maker is pickled.
        ctx = mp.get_context("spawn")
        with (
            ctx.Pool(workers, initializer=_init_worker, initargs=(maker,)) as pool,
            tqdm(total=sum(j[2] for j in todo), unit="sample", desc=f"data {kind}") as bar,
        ):
            for stats in pool.imap_unordered(_make_shard, todo):
                bar.update(sizes[stats["shard"]])
    wall = time.monotonic() - started
    attempts: list[dict[str, Any]] = []
    for s in range(num_shards):
        attempts += json.loads((out / f"stats_{s:05d}.json").read_text())["attempts"]
    fails = sum(not a["ok"] for a in attempts)
    n_test = sum(round(sz * TEST_FRACTION) for sz in sizes)
    info = {
        **header,
        "counts": {
            "samples": n,
            "train": n - n_test,
            "test": n_test,
            "attempts": len(attempts),
            "detector_failures": fails,
            "detector_failure_rate": round(fails / max(1, len(attempts)), 4),
        },
        "failure_by_distance_m": _bin_table(attempts, "distance_m", DISTANCE_BINS_M),
        "failure_by_tilt_deg": _bin_table(attempts, "tilt_deg", TILT_BINS_DEG),
    }
    info_path.write_text(json.dumps(info, indent=2))
    # Wall time goes beside info.json, not into it: same seed and n must give identical files.
    log = {"wall_secs": round(wall, 1), "workers": workers, "shards_made": len(todo)}
    (out / "generation_log.json").write_text(json.dumps(log, indent=2))
    return {**info, "last_run": log}
