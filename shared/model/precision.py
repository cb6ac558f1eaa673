"""Which arithmetic runs the network on one side of the split (no torch here: settings import it)."""

from __future__ import annotations

from typing import Literal, get_args

# fp32 and bf16: PyTorch eager on the safetensors weights; int8: OpenVINO on the folder's int8 variant.
Precision = Literal["fp32", "bf16", "int8"]
PRECISIONS: tuple[Precision, ...] = get_args(Precision)


class ModelFileError(ValueError):
    """A weights folder, variant or export request that cannot be served: the CLI prints the message."""
