"""Writing ONNX files: the exporter kept quiet, and every file self-contained (for `shared/model/export.py`
and `shared/model/onnx_int8.py`)."""

from __future__ import annotations

import logging
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

_EXPORTER_LOGGERS = ("onnx_ir", "onnxscript", "torch.onnx", "torch.export", "torch._dynamo")


@contextmanager
def quiet_exporter() -> Iterator[None]:
    """The exporter's advice and INFO lines (dynamo's dynamic_axes note, torchvision not installed,
    onnxscript's rewrites) are not the user's business: a successful export prints one line. Warnings
    raised by our own code still show."""
    levels = {name: logging.getLogger(name).level for name in _EXPORTER_LOGGERS}
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", module=r"(torch|onnx|onnxscript|onnx_ir|onnxruntime)(\.|$)")
        warnings.filterwarnings("ignore", message=r".*'dynamic_axes' is not recommended")  # (said at our call)
        warnings.filterwarnings("ignore", category=FutureWarning)  # (torch's pytree, raised through copyreg)
        for name in _EXPORTER_LOGGERS:
            logging.getLogger(name).setLevel(logging.ERROR)
        try:
            yield
        finally:
            for name, level in levels.items():
                logging.getLogger(name).setLevel(level)


class DropAdvice(logging.Filter):
    """ONNX Runtime's quantiser advises pre-processing through the root logger on every call: the advice
    is for other models (ours was measured as it is), so that one message is dropped."""

    def filter(self, record: logging.LogRecord) -> bool:
        return "pre-process" not in record.getMessage()


def inline_weights(path: Path) -> None:
    """One self-contained .onnx per half: the exporter writes large weights beside it (`.onnx.data`),
    which the manifest did not name and a copy of the listed files left behind (a trial). Saved at the
    lowest IR version its opsets allow (`lowest_ir_version`)."""
    import onnx

    model = onnx.load(str(path))  # (reads the external data in)
    lowest_ir_version(model)
    onnx.save_model(model, str(path), save_as_external_data=False)
    for side_file in path.parent.glob(f"{path.name}.data"):
        side_file.unlink()


def lowest_ir_version(model: Any) -> None:
    """Mark an ONNX model with the lowest IR version its opsets allow (opset 20: IR 9), not the newest
    the exporter writes (IR 10), which ONNX Runtime before 1.18 refuses (a trial). ONNX Runtime 1.17.3,
    the oldest with opset 20, loads IR 9 and gives the same keypoints bit for bit as 1.32 (session 31).
    Nothing in the graphs needs IR 10 (its additions are 4-bit types)."""
    from onnx.helper import find_min_ir_version_for

    lowest = find_min_ir_version_for(list(model.opset_import), ignore_unknown=True)
    model.ir_version = min(model.ir_version, lowest)
