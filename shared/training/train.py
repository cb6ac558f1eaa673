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
from functools import lru_cache
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


def train(settings: TrainSettings) -> dict[str, Any]:
    """Train (resuming from out/last.pt if present); writes best weights to out/best/."""
    torch.manual_seed(settings.seed)
    if settings.threads:
        torch.set_num_threads(settings.threads)
    device = torch.device(settings.device)
    out = settings.out
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(settings.model_dump_json(indent=2))

    sets = [load_dataset(p) for p in settings.data]
    train_parts = [(ds, ds.split("train")) for ds in sets]
    test_parts = [(ds, ds.split("test")) for ds in sets]
    tr_roi, tr_kp = zip(*(_to_device(ds, rows, device) for ds, rows in train_parts), strict=True)
    train_roi, train_kp = torch.cat(tr_roi), torch.cat(tr_kp)
    if settings.limit_train:
        train_roi, train_kp = train_roi[: settings.limit_train], train_kp[: settings.limit_train]
    rng = np.random.default_rng(settings.seed)
    te_rows = [(ds, rng.permutation(rows)[: settings.eval_samples]) for ds, rows in test_parts]
    te_roi, te_kp = zip(*(_to_device(ds, rows, device) for ds, rows in te_rows), strict=True)
    test_roi, test_kp = torch.cat(te_roi), torch.cat(te_kp)
    log.info("train samples %d, eval samples %d, device %s", len(train_roi), len(test_roi), device)

    model = (load_model(settings.init) if settings.init else SplitKeypointNet(roi_margin=ROI_MARGIN)).to(device)
    if settings.channels_last:
        model = model.to(memory_format=torch.channels_last)  # type: ignore[call-overload]
    opt = torch.optim.Adam(model.parameters(), lr=settings.lr, weight_decay=settings.weight_decay)
    steps_per_epoch = len(train_roi) // settings.batch_size
    epochs = settings.epochs
    plan = {"total": steps_per_epoch * epochs}
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: _lr_factor(s, plan["total"], settings.warmup_steps))
    start_epoch, best = 0, math.inf
    history: list[dict[str, Any]] = []
    ckpt_path = out / "last.pt"
    if ckpt_path.is_file():
        ckpt = torch.load(ckpt_path, map_location=device, weights_only=False)
        model.load_state_dict(ckpt["model"])
        opt.load_state_dict(ckpt["opt"])
        sched.load_state_dict(ckpt["sched"])
        start_epoch, best, history = ckpt["epoch"], ckpt["best"], ckpt["history"]
        epochs = min(ckpt.get("epochs", epochs), settings.epochs)  # a smaller --epochs shortens the plan
        plan["total"] = steps_per_epoch * epochs
        log.info("resumed from %s at epoch %d (best e_px %.3f)", ckpt_path, start_epoch, best)

    gen = torch.Generator(device="cpu").manual_seed(settings.seed + start_epoch)
    started = time.monotonic()
    epoch = start_epoch
    while epoch < epochs:
        model.train()
        perm = torch.randperm(len(train_roi), generator=gen).to(device)
        running, n_loss = 0.0, 0
        bar = tqdm(range(steps_per_epoch), desc=f"epoch {epoch + 1}/{epochs}", leave=False)
        for step in bar:
            idx = perm[step * settings.batch_size : (step + 1) * settings.batch_size]
            roi, kp = train_roi[idx], train_kp[idx]
            if settings.augment_dihedral:
                roi, kp = dihedral(roi, kp, int(torch.randint(0, 8, (1,), generator=gen)))
            pred = forward_train(model, roi, bf16=settings.bf16, channels_last=settings.channels_last)
            loss = wing_loss(pred, kp)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            running += float(loss.detach())
            n_loss += 1
            if step % 20 == 0:
                bar.set_postfix(loss=f"{running / n_loss:.3f}", lr=f"{sched.get_last_lr()[0]:.2e}")
        pred = predict(model, test_roi, bf16=settings.bf16, channels_last=settings.channels_last)
        metrics = evaluate_arrays(pred.cpu().numpy(), test_kp.cpu().numpy())
        row = {
            "epoch": epoch + 1,
            "train_loss": running / max(1, n_loss),
            **metrics,
            "lr": sched.get_last_lr()[0],
            "elapsed_secs": round(time.monotonic() - started, 1),
        }
        history.append(row)
        with (out / "curve.jsonl").open("a") as f:
            f.write(json.dumps(row) + "\n")
        print(
            f"epoch {epoch + 1}/{epochs} loss {row['train_loss']:.4f} "
            f"test e_px {metrics['e_px_mean']:.3f} (sd {metrics['e_px_std']:.3f}) "
            f"e_rel {metrics['e_rel_mean']:.3f} % [{row['elapsed_secs']} s]",
            flush=True,
        )
        if metrics["e_px_mean"] < best:
            best = metrics["e_px_mean"]
            save_weights(
                model,
                out / "best",
                extra={"train": json.loads(settings.model_dump_json()), "epoch": epoch + 1, "eval": metrics},
            )
        if settings.time_budget_secs and epoch == start_epoch:
            per_epoch = time.monotonic() - started
            fits = start_epoch + max(1, int(settings.time_budget_secs // per_epoch))
            if fits < epochs:
                print(
                    f"time budget {settings.time_budget_secs:.0f} s: {per_epoch:.1f} s/epoch, "
                    f"cutting the schedule from {epochs} to {fits} epochs",
                    flush=True,
                )
                epochs = fits
                plan["total"] = steps_per_epoch * epochs
        epoch += 1
        torch.save(
            {
                "model": model.state_dict(),
                "opt": opt.state_dict(),
                "sched": sched.state_dict(),
                "epoch": epoch,
                "epochs": epochs,
                "best": best,
                "history": history,
            },
            ckpt_path,
        )
    save_weights(
        model,
        out / "final",
        extra={
            "train": json.loads(settings.model_dump_json()),
            "epoch": epochs,
            "eval": history[-1] if history else {},
        },
    )
    return {"best_e_px": best, "history": history, "epochs": epochs}
