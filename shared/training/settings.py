"""What defines a training run (saved as `config.json` beside the checkpoints); `splittag train`'s
options are generated from it (shared.tools.options). No torch here: the CLI imports it to parse."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class TrainSettings(BaseModel):
    """Everything that defines a training run."""

    model_config = ConfigDict(extra="forbid")

    data: list[Path] = Field(description="data set folder (repeat the option for several)")
    out: Path = Field(description="run folder: checkpoints, best weights, curve (resumes from OUT/last.pt)")
    init: Path | None = Field(default=None, description="weights folder to start from (fine-tuning)")
    epochs: int = Field(default=70, ge=1, description="epochs")
    batch_size: int = Field(default=32, ge=1, description="batch size")
    lr: float = Field(default=3e-4, gt=0, description="peak learning rate (Adam, cosine decay)")
    warmup_steps: int = Field(default=500, ge=0, description="linear warm-up steps")
    weight_decay: float = Field(default=0.0, description="Adam weight decay")
    augment_dihedral: bool = Field(default=True, description="random flips and 90-degree turns")
    device: Literal["cpu", "cuda"] = Field(default="cpu", description="where to train")
    bf16: bool = Field(default=True, description="bf16 autocast")
    channels_last: bool = Field(default=True, description="channels_last memory format")
    threads: int | None = Field(default=None, description="torch threads (default: torch's choice)")
    seed: int = Field(default=0, description="random seed")
    eval_samples: int = Field(default=1000, ge=1, description="test samples evaluated after each epoch")
    limit_train: int | None = Field(default=None, description="use at most this many training samples")
    time_budget_secs: float | None = Field(
        default=None,
        gt=0,
        description="cut the epoch count after epoch 1 so the run fits (the cosine schedule is re-planned)",
    )


class QuantizeSettings(BaseModel):
    """Quantisation-aware fine-tuning of fp32 weights into the int8 variant (OpenVINO IR)."""

    model_config = ConfigDict(extra="forbid")

    weights: Path = Field(description="fp32 weights folder to quantise (its int8/ variant is written with --install)")
    data: list[Path] = Field(description="data set folder (repeat the option for several): calibration + fine-tuning")
    out: Path = Field(description="run folder: checkpoints, curve, best IR (resumes from OUT/last.pt)")
    calibration_samples: int = Field(default=300, ge=1, description="training ROIs that set the initial int8 ranges")
    steps: int = Field(default=300, ge=0, description="fine-tuning steps with the quantisers in the graph")
    batch_size: int = Field(default=32, ge=1, description="batch size")
    lr: float = Field(default=2e-5, gt=0, description="peak learning rate (Adam, cosine decay)")
    eval_every: int = Field(default=50, ge=1, description="steps between validations of the exported int8 graph")
    val_samples: int = Field(default=400, ge=1, description="held-out training ROIs that select the best step")
    threads: int | None = Field(default=None, description="torch threads (default: torch's choice)")
    seed: int = Field(default=0, description="random seed")
    time_budget_secs: float | None = Field(default=None, gt=0, description="stop fine-tuning after this long")
    install: bool = Field(default=False, description="copy the best IR into WEIGHTS/int8 and record it in config.json")
    exact_first_conv: bool = Field(
        default=True,
        description="run the first convolution int8 on an exactly quantised input (shared.model.int8_graph)",
    )
    fc_int8_weights: bool = Field(
        default=True, description="int8 weights (fp32 activations) for the fully connected layers"
    )
