"""`splittag link probe` and `splittag link cost`: the paper's link-model and split-cost figures.

probe: time round trips of real Features messages at every split point's payload size against the
edge's echo queryable (tiny replies, so only the uplink carries the payload), fit RTT = t0 + beta S.
cost: T(k) = gamma C(k) + t0 + beta S(k) + E(k) per split point from the measured compute profile
and a fitted link, for several gamma, optimum starred; or the paper's Eq. 4 exactly (`paper`):
T(k) = gamma C(k) + t0 + beta S(k) over k = 1..7, without the raw-ROI cut k = 0 and without E(k).
"""

from __future__ import annotations

import json
import random
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from shared.control.linkmodel import FLOOR_BELOW_KB, LinkFit, fit_link, split_costs
from shared.transport.probe import Prober
from shared.wire.cuts import CUTS, tensor_bytes
from shared.wire.messages import encode
from shared.wire.sizing import probe_features

KB = 1024.0


def probe_payloads(tags: int = 1) -> list[bytes]:
    """One probe message per split point, as large as `tags` tags' tensors at that cut."""
    return [encode(probe_features(tags * tensor_bytes(c.k, "fp16"), seq=c.k)) for c in CUTS]


def run_probes(prober: Prober, payloads: Sequence[bytes], *, repetitions: int, warmup: int = 3) -> list[list[float]]:
    """[payload bytes, RTT ms] samples; sizes shuffled in every round so drift cannot bias the slope."""
    rng = random.Random(0)
    for _ in range(warmup):  # open the TCP window and warm the path; not recorded
        for p in payloads:
            prober.round_trip(p)
    samples = []
    for _ in range(repetitions):
        order = list(payloads)
        rng.shuffle(order)
        for p in order:
            r = prober.round_trip(p)
            samples.append([float(r.payload_bytes), r.rtt_secs * 1e3])
    return samples


def report(
    samples: Sequence[Sequence[float]],
    *,
    profile: str | None,
    profile_config: dict[str, Any] | None = None,
    repetitions: int | None = None,
    tags: int | None = None,
) -> dict[str, Any]:
    """JSON-ready result: the fit, the floor and the per-size medians; `profile_config`: the emulated
    link's configured rate and floor (what the fit should find)."""
    s = np.asarray(samples, np.float64)
    fit = fit_link((s[:, 0] / KB).tolist(), s[:, 1].tolist())
    sizes = sorted(set(s[:, 0].tolist()))
    return {
        "units": "kB = 1024 bytes; ms; samples are [payload bytes, round-trip ms]",
        "profile": profile,
        "profile_config": profile_config,
        "repetitions": repetitions,
        "tags": tags,
        "t0_ms": fit.t0_ms,
        "floor_ms": fit.floor_ms,
        "beta_ms_per_kB": fit.beta_ms_per_kB,
        "rmse_ms": fit.rmse_ms,
        "n": fit.n,
        "floor_below_kB": FLOOR_BELOW_KB,
        "per_size": [
            {
                "payload_kB": size / KB,
                "rtt_ms_median": float(np.median(s[s[:, 0] == size, 1])),
                "rtt_ms_p90": float(np.percentile(s[s[:, 0] == size, 1], 90)),
            }
            for size in sizes
        ],
        "samples": [[float(a), float(b)] for a, b in s],
    }


def link_fit_of(doc: dict[str, Any]) -> LinkFit:
    """The LinkFit inside a probe JSON document."""
    return LinkFit(doc["t0_ms"], doc["beta_ms_per_kB"], doc["floor_ms"], doc.get("rmse_ms", 0.0), doc.get("n", 0))


def plot_link(doc: dict[str, Any], out: Path) -> None:
    """RTT against payload with the fitted line (the paper's link-model figure)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = np.asarray(doc["samples"], np.float64)
    fig, ax = plt.subplots(figsize=(7, 4.2))
    ax.scatter(s[:, 0] / KB, s[:, 1], s=6, alpha=0.35, label="probe RTT")
    med = doc["per_size"]
    ax.plot([m["payload_kB"] for m in med], [m["rtt_ms_median"] for m in med], "o", color="k", label="median")
    xs = np.linspace(0, s[:, 0].max() / KB * 1.02, 100)
    ax.plot(
        xs,
        doc["t0_ms"] + doc["beta_ms_per_kB"] * xs,
        "r-",
        label=f"fit: {doc['t0_ms']:.1f} ms + {doc['beta_ms_per_kB']:.3f} ms/kB x S",
    )
    ax.axhline(
        doc["floor_ms"], color="gray", ls=":", label=f"floor (S < {FLOOR_BELOW_KB:.0f} kB): {doc['floor_ms']:.1f} ms"
    )
    ax.set_xlabel("payload S (kB)")
    ax.set_ylabel("round-trip time (ms)")
    ax.set_title(f"link model, profile {doc.get('profile') or 'as measured'}")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)


# The two cost models `link cost` prints, said in its output and its JSON ("model").
FULL_MODEL = "T(k) = gamma C(k) + t0 + beta S(k) + E(k), k = 0..7"
PAPER_MODEL = "T(k) = gamma C(k) + t0 + beta S(k), k = 1..7 (the paper's Eq. 4)"


def cost_table(
    *,
    compute_ms: Sequence[float],
    edge_ms: Sequence[float] | None,
    payload_kB: Sequence[float],
    fit: LinkFit,
    gammas: Sequence[float],
    paper: bool = False,
) -> dict[str, Any]:
    """T(k) for every gamma with the argmin (`best_k`, a k). `compute_ms`, `edge_ms` and `payload_kB`
    have a value per cut (k = 0..7). `paper`: the paper's Eq. 4, T(k) = gamma C(k) + t0 + beta S(k) over
    k = 1..7 (it has no raw-ROI cut, and no edge compute term: `edge_ms` is not used and may be None);
    else splittag's model, with E(k), over every cut."""
    if not paper and edge_ms is None:
        raise ValueError("the full model needs edge_ms (E(k)); only the paper's has none")
    ks = [c.k for c in CUTS if c.k >= 1] if paper else [c.k for c in CUTS]
    edge = [0.0] * len(ks) if paper or edge_ms is None else [float(edge_ms[k]) for k in ks]
    rows = []
    for g in gammas:
        t = split_costs(
            compute_ms=[compute_ms[k] for k in ks],
            edge_ms=edge,
            payload_kB=[payload_kB[k] for k in ks],
            t0_ms=fit.t0_ms,
            beta_ms_per_kB=fit.beta_ms_per_kB,
            gamma=g,
        )
        rows.append({"gamma": g, "T_ms": [float(v) for v in t], "best_k": ks[int(np.argmin(t))]})
    return {
        "model": PAPER_MODEL if paper else FULL_MODEL,
        "link": asdict(fit),
        "k": ks,
        "split_point": [CUTS[k].name for k in ks],
        "C_ms": [float(compute_ms[k]) for k in ks],
        "E_ms": None if paper else edge,
        "S_kB": [float(payload_kB[k]) for k in ks],
        "gammas": rows,
    }


def plot_costs(table: dict[str, Any], out: Path) -> None:
    """T(k) per split point for every gamma, optimum starred (the paper's split-cost figure)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.2))
    ks = table["k"]
    for row in table["gammas"]:
        (line,) = ax.plot(ks, row["T_ms"], "o-", label=f"gamma = {row['gamma']:g}")
        b = ks.index(row["best_k"])
        ax.plot([ks[b]], [row["T_ms"][b]], "*", ms=16, color=line.get_color(), markeredgecolor="k")
    ax.set_xticks(ks, [f"{k}\n{n}" for k, n in zip(ks, table["split_point"], strict=True)], fontsize=7)
    ax.set_xlabel("split point k")
    ax.set_ylabel("predicted latency T(k) (ms)")
    link = table["link"]
    edge = "" if table.get("E_ms") is None else " + E(k)"
    ax.set_title(f"T(k) = gamma C(k) + {link['t0_ms']:.1f} ms + {link['beta_ms_per_kB']:.3f} ms/kB S(k){edge}")
    ax.set_yscale("log")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)


def write_json(doc: dict[str, Any], path: Path) -> None:
    """Write a result document (creating the folder)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=2))
