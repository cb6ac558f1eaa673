"""The int8 variant of a weights folder: NNCF quantisation of the all-cuts graph, fine-tuned with the
quantisers in place (quantisation-aware training), exported as one OpenVINO IR.

Why fine-tune: post-training quantisation of this regression network (NNCF, 300 real ROIs, full
bias correction) raised the keypoint error from 0.236 to 0.557 ROI px on the synth2 test split; most
of it comes from the first convolution and the global pooling. A few hundred steps of the training
loss with the quantisers in the graph teach the weights to live with int8.

Recipe: NNCF `quantize` (PyTorch backend) on `AllCuts` with `calibration_samples` training ROIs
(ranges), every convolution but the first quantised (per-channel symmetric weights, per-tensor
activations); the first convolution, the global pooling and the two fully connected layers stay fp32
(21 M of 3.7 G multiply-adds). With every convolution int8, fine-tuning stalled at +0.03 px over fp32
(150 steps); NNCF's accuracy-aware ranking named the first convolution and the pooled features as the
costliest quantisers. The exported graph is then rewritten (`shared.model.int8_graph`, settings
`exact_first_conv`, `fc_int8_weights`): the first convolution runs int8 on an exactly quantised image
with output-error-optimal weight codes, and the 4096 -> 512 layer gets int8 weights. Then Adam on the Wing loss
with dihedral augmentation, BatchNorm statistics frozen, 20 warm-up steps then cosine decay over `steps`. Every
`eval_every` steps the model is exported to OpenVINO, compiled and validated on held-out *training*
ROIs (the test split stays untouched for the report), beside the fp32 weights on the same ROIs; the
best step's IR is kept. Resumable from OUT/last.pt (the quantisers are rebuilt from the same
calibration ROIs, then the checkpoint overwrites them).
"""

from __future__ import annotations

import json
import logging
import math
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from shared.datasets.shards import load_dataset
from shared.model.infer import keypoints as torch_keypoints
from shared.model.int8_graph import int8_rewrite
from shared.model.net import AllCuts, SplitKeypointNet
from shared.model.openvino_net import INT8_FOLDER, IR_NAME, compile_full, export_ir, record_variant
from shared.model.weights import load_model
from shared.training.settings import QuantizeSettings
from shared.training.train import dihedral, wing_loss
from shared.vision.metrics import e_px

log = logging.getLogger(__name__)

FIRST_CONV = "0/conv2d/0"  # NNCF's name of block 1's first convolution in AllCuts (nncf 3.4)


def _normalised(rois_u8: np.ndarray) -> Tensor:
    return torch.from_numpy(rois_u8.astype(np.float32) / 127.5 - 1.0).unsqueeze(1)


def _quantised(net: SplitKeypointNet, calibration: np.ndarray) -> nn.Module:
    import nncf  # the quantize extra: only this command needs it

    graph = AllCuts(net.to(memory_format=torch.contiguous_format)).eval()  # type: ignore[call-overload]
    dataset = nncf.Dataset([_normalised(calibration[i : i + 1]) for i in range(len(calibration))])
    # fp32 where int8 costs the keypoints most and saves least (NNCF's accuracy-aware ranking on this net):
    # the first convolution (the 8-bit image in, 9 taps per channel: 0.5 % of the multiply-adds) and the
    # pooled features that feed the fully connected regressor; those two layers are fp32 as well.
    scope = nncf.IgnoredScope(types=["linear", "adaptive_avg_pool2d"], names=[FIRST_CONV])
    quantised: nn.Module = nncf.quantize(graph, dataset, subset_size=len(calibration), ignored_scope=scope)
    return quantised


def _freeze_batchnorm(model: nn.Module) -> None:
    for m in model.modules():
        if isinstance(m, nn.BatchNorm2d):
            m.eval()


def _ir_error_px(ir_dir: Path, rois: np.ndarray, gt: np.ndarray) -> float:
    compiled = compile_full(ir_dir / IR_NAME, threads=None)
    preds = [compiled(rois[i : i + 64]) for i in range(0, len(rois), 64)]
    return float(e_px(np.concatenate(preds), gt).mean())


def quantize(settings: QuantizeSettings) -> dict[str, Any]:
    """Run (or resume) the fine-tuning; writes OUT/best/ (IR + metrics) and, with `install`, WEIGHTS/int8."""
    torch.manual_seed(settings.seed)
    if settings.threads:
        torch.set_num_threads(settings.threads)
    out = settings.out
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.json").write_text(settings.model_dump_json(indent=2))
    sets = [load_dataset(p) for p in settings.data]
    rng = np.random.default_rng(settings.seed)
    train_rows = [rng.permutation(ds.split("train")) for ds in sets]
    # Held-out training ROIs select the best step; calibration ROIs come from the rest.
    val_roi = np.concatenate(
        [ds.arrays["roi"][r[: settings.val_samples]] for ds, r in zip(sets, train_rows, strict=True)]
    )
    val_kp = np.concatenate(
        [ds.arrays["keypoints"][r[: settings.val_samples]] for ds, r in zip(sets, train_rows, strict=True)]
    )
    fit_roi = np.concatenate(
        [ds.arrays["roi"][r[settings.val_samples :]] for ds, r in zip(sets, train_rows, strict=True)]
    )
    fit_kp = np.concatenate(
        [ds.arrays["keypoints"][r[settings.val_samples :]] for ds, r in zip(sets, train_rows, strict=True)]
    )
    fp32 = load_model(settings.weights)
    fp32_val = float(
        e_px(torch_keypoints(fp32, torch.from_numpy(val_roi).unsqueeze(1), bf16=False).numpy(), val_kp).mean()
    )
    model = _quantised(load_model(settings.weights), fit_roi[: settings.calibration_samples])
    opt = torch.optim.Adam(model.parameters(), lr=settings.lr)
    total = max(1, settings.steps)
    warmup = min(20, total)

    def lr_factor(s: int) -> float:
        return min(1.0, (s + 1) / warmup) * 0.5 * (1 + math.cos(math.pi * min(1.0, s / total)))

    sched = torch.optim.lr_scheduler.LambdaLR(opt, lr_factor)
    step, best, history = 0, math.inf, []
    ckpt = out / "last.pt"
    if ckpt.is_file():
        state = torch.load(ckpt, map_location="cpu", weights_only=False)
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["opt"])
        sched.load_state_dict(state["sched"])
        step, best, history = state["step"], state["best"], state["history"]
        log.info("resumed from %s at step %d (best %.4f px)", ckpt, step, best)
    gen = torch.Generator().manual_seed(settings.seed + step)
    rewrite = int8_rewrite(
        exact_first_conv=settings.exact_first_conv,
        fc_int8_weights=settings.fc_int8_weights,
        calibration_rois=fit_roi[: settings.calibration_samples],
    )
    started = time.monotonic()

    def validate() -> None:
        nonlocal best
        model.eval()
        candidate = out / "candidate"
        export_ir(model, candidate, rewrite=rewrite)
        err = _ir_error_px(candidate, val_roi, val_kp)
        row = {
            "step": step,
            "val_e_px": err,
            "fp32_val_e_px": fp32_val,
            "elapsed_secs": round(time.monotonic() - started),
        }
        history.append(row)
        with (out / "curve.jsonl").open("a") as f:
            f.write(json.dumps(row) + "\n")
        print(
            f"step {step}/{settings.steps}: int8 val e_px {err:.4f} (fp32 {fp32_val:.4f}, {err - fp32_val:+.4f})",
            flush=True,
        )
        if err < best:
            best = err
            shutil.rmtree(out / "best", ignore_errors=True)
            candidate.rename(out / "best")
        else:
            shutil.rmtree(candidate)

    if not history:
        validate()  # step 0: plain post-training quantisation
    while step < settings.steps:
        if settings.time_budget_secs and time.monotonic() - started > settings.time_budget_secs:
            print(f"time budget of {settings.time_budget_secs:.0f} s reached at step {step}", flush=True)
            break
        model.train()
        _freeze_batchnorm(model)
        idx = torch.randint(0, len(fit_roi), (settings.batch_size,), generator=gen).numpy()
        roi = torch.from_numpy(fit_roi[idx]).unsqueeze(1)
        kp = torch.from_numpy(fit_kp[idx])
        roi, kp = dihedral(roi, kp, int(torch.randint(0, 8, (1,), generator=gen)))
        pred = model(roi.float().div(127.5).sub(1.0))[-1]
        loss = wing_loss(pred, kp)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        step += 1
        if step % 10 == 0:
            log.info("step %d loss %.4f lr %.2e", step, float(loss), sched.get_last_lr()[0])
        if step % settings.eval_every == 0 or step == settings.steps:
            validate()
            torch.save(
                {
                    "model": model.state_dict(),
                    "opt": opt.state_dict(),
                    "sched": sched.state_dict(),
                    "step": step,
                    "best": best,
                    "history": history,
                },
                ckpt,
            )
    # `steps`: how many ran; `best_step`: the one whose graph is kept (0 = calibration alone)
    best_step = min(history, key=lambda r: r["val_e_px"])["step"] if history else 0
    metrics = {
        "val_e_px": best,
        "fp32_val_e_px": fp32_val,
        "steps": step,
        "best_step": best_step,
        "val_samples": len(val_roi),
    }
    (out / "best" / "metrics.json").write_text(json.dumps(metrics, indent=2))
    shutil.copy(out / "curve.jsonl", out / "best" / "curve.jsonl")  # the curve travels with the weights
    if settings.install:
        target = Path(settings.weights) / INT8_FOLDER
        shutil.rmtree(target, ignore_errors=True)
        shutil.copytree(out / "best", target)
        record_variant(settings.weights, "int8", {**metrics, "recipe": json.loads(settings.model_dump_json())})
    return metrics
