"""Training of the split keypoint network (paper section IV-A3), resumable, CPU or CUDA.

Recipe: spatially weighted Wing loss (w = 10, epsilon = 2) on errors in ROI pixels (on normalised
errors, |delta| < 1 << epsilon and the Wing loss degenerates to a scaled L1), per-keypoint weight
omega = clamp(d_edge / 0.5, 0.3, 1); Adam, linear warm-up then cosine annealing, batch 32.
What makes it converge fast: data pre-generated into memory, the zero-initialised lattice-offset
output (shared.model.net), warm-up, and the 8 dihedral symmetries of the ROI as free augmentation
(an ROI flipped or rotated with its keypoints relabelled is another valid sample: the net never
decodes the tag's bits). bf16 autocast + channels_last on CPU (AMX) and CUDA.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from shared.datasets.shards import Dataset, load_dataset
from shared.model.infer import forward_train, keypoints
from shared.model.net import SplitKeypointNet, canonical_keypoints
from shared.model.weights import load_model, save_weights
from shared.training.settings import TrainSettings
from shared.vision.geometry import ROI_MARGIN, ROI_SIZE
from shared.vision.metrics import e_px, e_rel

log = logging.getLogger(__name__)

WING_W = 10.0
WING_EPS = 2.0
WING_C = WING_W - WING_W * math.log(1 + WING_W / WING_EPS)


def wing_loss(pred_norm: Tensor, gt_norm: Tensor) -> Tensor:
    """Spatially weighted Wing loss; errors in ROI pixels, omega from the ground truth."""
    delta = (pred_norm.float() - gt_norm) * ROI_SIZE
    a = delta.abs()
    per_coord = torch.where(a < WING_W, WING_W * torch.log1p(a / WING_EPS), a - WING_C)
    d_edge = torch.minimum(gt_norm, 1 - gt_norm).amin(dim=-1)
    omega = (d_edge / 0.5).clamp(0.3, 1.0)
    return (omega * per_coord.sum(dim=-1)).mean()


# ----------------------------------------------------------------------------------------------
# Dihedral augmentation: 8 transforms of the square ROI, keypoints relabelled to the lattice order
# ----------------------------------------------------------------------------------------------


def _transform_points(pts: Tensor, t: int) -> Tensor:
    x, y = pts[..., 0], pts[..., 1]
    if t & 4:  # transpose
        x, y = y, x
    if t & 1:  # flip x
        x = 1 - x
    if t & 2:  # flip y
        y = 1 - y
    return torch.stack([x, y], dim=-1)


def _transform_images(img: Tensor, t: int) -> Tensor:
    if t & 4:
        img = img.transpose(-1, -2)
    if t & 1:
        img = img.flip(-1)
    if t & 2:
        img = img.flip(-2)
    return img


@lru_cache(maxsize=8)
def _relabel(t: int, margin: float) -> tuple[int, ...]:
    """perm such that new[perm[j]] = T(old[j]) keeps keypoints in canonical lattice order."""
    lattice = torch.from_numpy(canonical_keypoints(margin)).double()
    moved = _transform_points(lattice, t)
    d = torch.cdist(moved, lattice)
    perm = d.argmin(dim=1)
    assert sorted(perm.tolist()) == list(range(16)) and float(d.min(dim=1).values.max()) < 1e-5
    return tuple(perm.tolist())


def dihedral(img: Tensor, kp: Tensor, t: int, margin: float = ROI_MARGIN) -> tuple[Tensor, Tensor]:
    """Apply dihedral transform t (0..7) to ROIs (B,1,S,S) and keypoints (B,16,2)."""
    if t == 0:
        return img, kp
    perm = torch.tensor(_relabel(t, margin), device=kp.device)
    out = torch.empty_like(kp)
    out[:, perm] = _transform_points(kp, t)
    return _transform_images(img, t), out


# ----------------------------------------------------------------------------------------------
# Loop
# ----------------------------------------------------------------------------------------------


def _lr_factor(step: int, total: int, warmup: int) -> float:
    if step < warmup:
        return (step + 1) / warmup
    progress = (step - warmup) / max(1, total - warmup)
    return 0.5 * (1 + math.cos(math.pi * min(1.0, progress)))


def _to_device(ds: Dataset, rows: np.ndarray, device: torch.device) -> tuple[Tensor, Tensor]:
    roi = torch.from_numpy(np.ascontiguousarray(ds.arrays["roi"][rows])).unsqueeze(1).to(device)
    kp = torch.from_numpy(np.ascontiguousarray(ds.arrays["keypoints"][rows])).to(device)
    return roi, kp


@torch.no_grad()
def predict(model: SplitKeypointNet, rois_u8: Tensor, *, bf16: bool, channels_last: bool, batch: int = 128) -> Tensor:
    """Keypoints (N,16,2) for uint8 ROIs (N,1,S,S) already on the model's device."""
    return keypoints(model, rois_u8, bf16=bf16, channels_last=channels_last, batch=batch)


def evaluate_arrays(pred: np.ndarray, gt: np.ndarray) -> dict[str, float]:
    """The paper's e_px and e_rel (mean, std) for predicted vs ground-truth normalised keypoints."""
    px, rel = e_px(pred, gt), e_rel(pred, gt)
    return {
        "e_px_mean": float(px.mean()),
        "e_px_std": float(px.std()),
        "e_rel_mean": float(rel.mean()),
        "e_rel_std": float(rel.std()),
        "n": len(px),
    }


@dataclass
class _Loop:
    """A training run's mutable state: what a checkpoint holds."""

    model: SplitKeypointNet
    opt: torch.optim.Adam
    sched: torch.optim.lr_scheduler.LambdaLR
    steps_per_epoch: int
    epochs: int
    plan: dict[str, int]
    epoch: int = 0
    best: float = math.inf
    history: list[dict[str, Any]] = field(default_factory=list)

    def set_epochs(self, epochs: int) -> None:
        """Re-plan the cosine schedule for `epochs` in total."""
        self.epochs = epochs
        self.plan["total"] = self.steps_per_epoch * epochs

    def save(self, path: Path) -> None:
        torch.save(
            {
                "model": self.model.state_dict(),
                "opt": self.opt.state_dict(),
                "sched": self.sched.state_dict(),
                "epoch": self.epoch,
                "epochs": self.epochs,
                "best": self.best,
                "history": self.history,
            },
            path,
        )

    def resume(self, path: Path, device: torch.device, max_epochs: int) -> None:
        ckpt = torch.load(path, map_location=device, weights_only=False)
        self.model.load_state_dict(ckpt["model"])
        self.opt.load_state_dict(ckpt["opt"])
        self.sched.load_state_dict(ckpt["sched"])
        self.epoch, self.best, self.history = ckpt["epoch"], ckpt["best"], ckpt["history"]
        self.set_epochs(min(ckpt.get("epochs", max_epochs), max_epochs))  # a smaller --epochs shortens the plan
        log.info("resumed from %s at epoch %d (best e_px %.3f)", path, self.epoch, self.best)


def _load_tensors(settings: TrainSettings, device: torch.device) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(train ROIs, train keypoints, eval ROIs, eval keypoints) from every data set, on `device`."""
    sets = [load_dataset(p) for p in settings.data]
    tr_roi, tr_kp = zip(*(_to_device(ds, ds.split("train"), device) for ds in sets), strict=True)
    train_roi, train_kp = torch.cat(tr_roi), torch.cat(tr_kp)
    if settings.limit_train:
        train_roi, train_kp = train_roi[: settings.limit_train], train_kp[: settings.limit_train]
    rng = np.random.default_rng(settings.seed)
    te_rows = [(ds, rng.permutation(ds.split("test"))[: settings.eval_samples]) for ds in sets]
    te_roi, te_kp = zip(*(_to_device(ds, rows, device) for ds, rows in te_rows), strict=True)
    return train_roi, train_kp, torch.cat(te_roi), torch.cat(te_kp)


def _new_loop(settings: TrainSettings, device: torch.device, n_train: int) -> _Loop:
    model = (load_model(settings.init) if settings.init else SplitKeypointNet(roi_margin=ROI_MARGIN)).to(device)
    if settings.channels_last:
        model = model.to(memory_format=torch.channels_last)  # type: ignore[call-overload]
    opt = torch.optim.Adam(model.parameters(), lr=settings.lr, weight_decay=settings.weight_decay)
    steps_per_epoch = n_train // settings.batch_size
    plan = {"total": steps_per_epoch * settings.epochs}
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: _lr_factor(s, plan["total"], settings.warmup_steps))
    return _Loop(model, opt, sched, steps_per_epoch, settings.epochs, plan)


def _train_epoch(loop: _Loop, settings: TrainSettings, roi_all: Tensor, kp_all: Tensor, gen: torch.Generator) -> float:
    """One pass over the training tensors; returns the mean training loss."""
    loop.model.train()
    perm = torch.randperm(len(roi_all), generator=gen).to(roi_all.device)
    running, n_loss = 0.0, 0
    bar = tqdm(range(loop.steps_per_epoch), desc=f"epoch {loop.epoch + 1}/{loop.epochs}", leave=False)
    for step in bar:
        idx = perm[step * settings.batch_size : (step + 1) * settings.batch_size]
        roi, kp = roi_all[idx], kp_all[idx]
        if settings.augment_dihedral:
            roi, kp = dihedral(roi, kp, int(torch.randint(0, 8, (1,), generator=gen)))
        pred = forward_train(loop.model, roi, bf16=settings.bf16, channels_last=settings.channels_last)
        loss = wing_loss(pred, kp)
        loop.opt.zero_grad(set_to_none=True)
        loss.backward()
        loop.opt.step()
        loop.sched.step()
        running += float(loss.detach())
        n_loss += 1
        if step % 20 == 0:
            bar.set_postfix(loss=f"{running / n_loss:.3f}", lr=f"{loop.sched.get_last_lr()[0]:.2e}")
    return running / max(1, n_loss)


def _record_epoch(loop: _Loop, settings: TrainSettings, row: dict[str, Any]) -> None:
    """Append the epoch's row to the curve, print it, and keep the best weights."""
    loop.history.append(row)
    with (settings.out / "curve.jsonl").open("a") as f:
        f.write(json.dumps(row) + "\n")
    print(
        f"epoch {row['epoch']}/{loop.epochs} loss {row['train_loss']:.4f} "
        f"test e_px {row['e_px_mean']:.3f} (sd {row['e_px_std']:.3f}) "
        f"e_rel {row['e_rel_mean']:.3f} % [{row['elapsed_secs']} s]",
        flush=True,
    )
    if row["e_px_mean"] < loop.best:
        loop.best = row["e_px_mean"]
        metrics = {k: row[k] for k in ("e_px_mean", "e_px_std", "e_rel_mean", "e_rel_std", "n")}
        save_weights(
            loop.model,
            settings.out / "best",
            extra={"train": json.loads(settings.model_dump_json()), "epoch": row["epoch"], "eval": metrics},
        )


def train(settings: TrainSettings) -> dict[str, Any]:
    """Train (resuming from out/last.pt if present); writes best weights to out/best/."""
    torch.manual_seed(settings.seed)
    if settings.threads:
        torch.set_num_threads(settings.threads)
    device = torch.device(settings.device)
    settings.out.mkdir(parents=True, exist_ok=True)
    (settings.out / "config.json").write_text(settings.model_dump_json(indent=2))
    train_roi, train_kp, test_roi, test_kp = _load_tensors(settings, device)
    log.info("train samples %d, eval samples %d, device %s", len(train_roi), len(test_roi), device)
    loop = _new_loop(settings, device, len(train_roi))
    ckpt_path = settings.out / "last.pt"
    if ckpt_path.is_file():
        loop.resume(ckpt_path, device, settings.epochs)
    start_epoch = loop.epoch
    gen = torch.Generator(device="cpu").manual_seed(settings.seed + start_epoch)
    started = time.monotonic()
    while loop.epoch < loop.epochs:
        train_loss = _train_epoch(loop, settings, train_roi, train_kp, gen)
        pred = predict(loop.model, test_roi, bf16=settings.bf16, channels_last=settings.channels_last)
        metrics = evaluate_arrays(pred.cpu().numpy(), test_kp.cpu().numpy())
        row = {
            "epoch": loop.epoch + 1,
            "train_loss": train_loss,
            **metrics,
            "lr": loop.sched.get_last_lr()[0],
            "elapsed_secs": round(time.monotonic() - started, 1),
        }
        _record_epoch(loop, settings, row)
        if settings.time_budget_secs and loop.epoch == start_epoch:
            per_epoch = time.monotonic() - started
            fits = start_epoch + max(1, int(settings.time_budget_secs // per_epoch))
            if fits < loop.epochs:
                print(
                    f"time budget {settings.time_budget_secs:.0f} s: {per_epoch:.1f} s/epoch, "
                    f"cutting the schedule from {loop.epochs} to {fits} epochs",
                    flush=True,
                )
                loop.set_epochs(fits)
        loop.epoch += 1
        loop.save(ckpt_path)
    final_eval = loop.history[-1] if loop.history else {}
    save_weights(
        loop.model,
        settings.out / "final",
        extra={"train": json.loads(settings.model_dump_json()), "epoch": loop.epochs, "eval": final_eval},
    )
    return {"best_e_px": loop.best, "history": loop.history, "epochs": loop.epochs}
