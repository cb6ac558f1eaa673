"""The split network on OpenVINO: one IR of the all-cuts graph (`AllCuts`), cut at any k at load time.

A weights folder may hold variants beside its fp32 `model.safetensors`; `config.json` lists them
under `variants` (name -> {format, path, metrics}). The int8 variant is `int8/model.xml` (+ .bin),
written by `splittag quantize`: every convolution int8 (per-channel weights, per-tensor activations;
the first one on an exactly quantised image, `shared.model.int8_graph`), the 4096 -> 512 layer with
int8 weights and fp32 activations, the output layer and the lattice add in fp32.

Cutting: output j of the IR is the tensor at cut j + 1. The head for cut k is the sub-graph from the
input to output k - 1; the tail for cut k is a clone of the graph in which a new input of the cut's
shape replaces what output k - 1 fed, ending at the keypoints. Both halves keep the quantisers of
their own side, so head(k) then tail(k) computes exactly what the whole int8 graph computes (test).
Cut 0 is the ROI itself: the head is the normalisation (u8 / 127.5 - 1) and the tail is the graph.

The compiled models run with inference precision f32 for the parts that are not int8: with the CPU's
default (bf16 where the CPU has it) the lattice add would be rounded to ~0.5 ROI px.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any, Final, Literal

import numpy as np
from numpy.typing import NDArray

from shared.model.precision import ModelFileError
from shared.wire.cuts import N_CUTS, check_cut, check_net_cut, check_net_rois

INT8_FOLDER: Final[str] = "int8"
IR_NAME: Final[str] = "model.xml"
INPUT_SHAPE: Final[tuple[int, int, int, int]] = (-1, 1, 256, 256)


class VariantError(ModelFileError):
    """A weights folder without the asked-for variant, or with a broken one."""


def _core() -> Any:
    import openvino as ov

    return ov.Core()


def export_ir(all_cuts: Any, folder: Path, *, rewrite: Callable[[Any], Any] | None = None) -> Path:
    """Convert an `AllCuts` module (plain or NNCF-quantised) to OpenVINO IR in `folder`; returns the xml.
    `rewrite` edits the converted graph before it is saved (shared.model.int8_graph)."""
    import openvino as ov
    import torch

    folder.mkdir(parents=True, exist_ok=True)
    with torch.no_grad():
        model = ov.convert_model(all_cuts, example_input=torch.zeros(1, 1, 256, 256), input=[INPUT_SHAPE])
    if len(model.outputs) != N_CUTS - 1:
        raise VariantError(f"exported graph has {len(model.outputs)} outputs, expected {N_CUTS - 1} (cuts 1..7)")
    if rewrite is not None:
        model = rewrite(model)
    path = folder / IR_NAME
    ov.save_model(model, str(path), compress_to_fp16=False)
    return path


def _config(folder: Path) -> dict[str, Any]:
    config: dict[str, Any] = json.loads((Path(folder) / "config.json").read_text())
    return config


def record_variant(folder: Path, name: str, metrics: dict[str, Any]) -> None:
    """List a variant in the folder's config.json (the rest of the file is kept)."""
    path = Path(folder) / "config.json"
    config = _config(folder)
    variants = config.setdefault("variants", {})
    variants[name] = {"format": "openvino-ir", "path": f"{INT8_FOLDER}/{IR_NAME}", **metrics}
    path.write_text(json.dumps(config, indent=2))


def variant_path(folder: Path, name: str) -> Path:
    """The IR of a variant listed in the folder's config.json, or VariantError naming what is there."""
    folder = Path(folder)
    if folder.is_file():
        folder = folder.parent
    variants = _config(folder).get("variants", {})
    if name not in variants:
        have = ", ".join(["fp32", "bf16", *variants]) or "none"
        raise VariantError(
            f"{folder}/config.json lists no {name!r} variant (this folder has: {have}); "
            f"make it with `splittag quantize --weights {folder} --data DATA --out RUN --install`"
        )
    path = folder / variants[name]["path"]
    if not path.is_file() or not path.with_suffix(".bin").is_file():
        raise VariantError(f"{path} (+ .bin) listed in {folder}/config.json is missing")
    return path


# Every graph compiles with these (`splittag export` writes them into its manifest): f32, because a CPU
# with bf16 otherwise runs the float parts, the int8 graph's included, in bf16 (keypoints up to ~1 px off).
COMPILE_CONFIG: dict[str, str] = {"PERFORMANCE_HINT": "LATENCY", "INFERENCE_PRECISION_HINT": "f32"}


def _compile(model: Any, threads: int | None) -> Any:
    config: dict[str, Any] = dict(COMPILE_CONFIG)
    if threads:
        config["INFERENCE_NUM_THREADS"] = threads
    return _core().compile_model(model, "CPU", config)


def normalise(rois_u8: NDArray[Any]) -> NDArray[np.float32]:
    """uint8 ROIs (N,256,256) or (N,1,256,256) -> the graph's float input (N,1,256,256) in [-1, 1]."""
    x = np.asarray(rois_u8, np.float32).reshape(-1, 1, 256, 256)
    x *= 1 / 127.5
    x -= 1.0
    return x


def compile_full(path: Path, *, threads: int | None) -> Callable[[NDArray[np.uint8]], NDArray[np.float32]]:
    """The whole graph compiled once: uint8 ROIs -> normalised keypoints (N,16,2)."""
    compiled = _compile(_core().read_model(str(path)), threads)

    def run(rois_u8: NDArray[np.uint8]) -> NDArray[np.float32]:
        return np.asarray(compiled(normalise(rois_u8))[N_CUTS - 2], np.float32)

    return run


class OpenVINOSplitNet:
    """The split API on an IR: `head(rois_u8, k)` -> cut-k tensors, `tail(z, k)` -> keypoints.

    Each half is compiled on first use and kept (16 compiled halves at most); thread-safe per half.
    """

    def __init__(self, path: Path, *, threads: int | None = None) -> None:
        self.path = Path(path)
        self.threads = threads
        self.precision: Literal["int8"] = "int8"
        self._model = _core().read_model(str(self.path))
        if len(self._model.outputs) != N_CUTS - 1:
            raise VariantError(f"{path}: {len(self._model.outputs)} outputs, expected one per cut 1..{N_CUTS - 1}")
        self._heads: dict[int, Any] = {}
        self._tails: dict[int, Any] = {}
        self._lock = threading.Lock()

    def head_model(self, k: int) -> Any:
        import openvino as ov

        out = self._model.outputs[k - 1]
        return ov.Model([out.get_node()], self._model.get_parameters(), f"head{k}")

    def tail_model(self, k: int) -> Any:
        import openvino as ov
        import openvino.opset13 as ops

        if k == 0:
            return ov.Model([self._model.outputs[N_CUTS - 2].get_node()], self._model.get_parameters(), "tail0")
        clone = self._model.clone()
        result = clone.outputs[k - 1].get_node()  # the Result node of cut k
        cut = result.input_value(0)  # the tensor at cut k
        shape = ov.PartialShape([-1, *list(cut.get_partial_shape())[1:]])
        param = ops.parameter(shape, cut.get_element_type(), name=f"cut{k}")
        for target in list(cut.get_target_inputs()):
            if target.get_node().get_type_name() != "Result":  # the cut's own output stays out of the tail
                target.replace_source_output(param.output(0))
        last = clone.outputs[N_CUTS - 2].get_node()
        return ov.Model([last], [param], f"tail{k}")

    def _compiled(self, table: dict[int, Any], k: int, build: Callable[[int], Any]) -> Any:
        with self._lock:
            if k not in table:
                table[k] = _compile(build(k), self.threads)
            return table[k]

    def head(self, rois_u8: NDArray[np.uint8], k: int) -> NDArray[np.float32]:
        """Cut-k tensors (N, ...) float32 for uint8 ROIs; k = 0 is the normalised ROI."""
        check_cut(k)
        check_net_rois(np.asarray(rois_u8))
        x = normalise(rois_u8)
        if k == 0:
            return x
        return np.asarray(self._compiled(self._heads, k, self.head_model)(x)[0], np.float32)

    def tail(self, z: NDArray[np.floating[Any]], k: int) -> NDArray[np.float32]:
        """Normalised keypoints (N,16,2) from cut-k tensors (k = 0: uint8 ROIs or normalised floats)."""
        check_cut(k)
        check_net_cut(np.asarray(z), k)
        if k == N_CUTS - 1:
            return np.asarray(z, np.float32).reshape(-1, 16, 2)
        x = normalise(z) if (k == 0 and np.asarray(z).dtype == np.uint8) else np.asarray(z, np.float32)
        if k == 0:
            x = x.reshape(-1, 1, 256, 256)
        return np.asarray(self._compiled(self._tails, k, self.tail_model)(x)[0], np.float32)

    def warm_up(self, k: int, *, max_batch: int = 1) -> None:
        """Compile both halves at every cut (the split moves online; compiling takes ~0.1-0.5 s each),
        then run the halves at k once per batch size (shapes are specialised on first use)."""
        for cut in range(1, N_CUTS):
            self._compiled(self._heads, cut, self.head_model)
        for cut in range(N_CUTS - 1):
            self._compiled(self._tails, cut, self.tail_model)
        for n in range(1, max_batch + 1):
            self.tail(self.head(np.zeros((n, 256, 256), np.uint8), k), k)
