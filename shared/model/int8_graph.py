"""Two rewrites of the int8 IR that NNCF does not make: the layers it leaves in fp32, made cheap without
costing the keypoints.

1. **The first convolution on an exact int8 input.** The graph's input is an 8-bit image, normalised
   as x = u / 127.5 - 1: 256 values, but not on a symmetric int8 grid (x = 0 falls between two codes),
   so a calibrated quantiser rounds the image itself (what made NNCF's int8 first convolution cost
   +0.08 px). Rewritten exactly: x = a x' + c with x' = (u - 128) / 128 (an int8 code times 1/128,
   zero point 0) and a = 128 / 127.5, c = 0.5 / 127.5, so conv(x, W) + b = conv(x', a W) + b + c sum(W).
   The graph computes x' from x, quantises it on the grid [-1, 127/128] of 256 levels (lossless: every
   input lands on a code), and the weights a W get per-output-channel symmetric int8 scales; c sum(W)
   joins the bias that follows. Rounding each weight to the nearest code cost +0.012 px on the synth2
   validation ROIs (9 taps per channel: every rounding error shows); instead each channel's 9 codes are
   the floor/ceil combination (all 512 are tried) that minimises the layer's output error on 3x3
   patches of calibration images, E[(p . (q s - w))^2] = d^T G d with G the patches' second moments
   (AdaRound's objective, solved exactly): 13x lower output error, and the keypoints no worse than
   with the layer in fp32. Only the one-pixel border differs from the fp32 layer: there the
   zero padding stands for u = 128 instead of u = 127.5 (a 0.4 % grey step under one tap ring of the
   ROI's margin).
2. **Int8 weights for the fully connected layers** (weight-only, NNCF's `compress_weights`,
   asymmetric per output channel): the 4096 -> 512 layer's 8 MB of fp32 weights are read once per ROI
   and dominate its time; as int8 they are a quarter of the traffic. Activations stay fp32.

Both act on an OpenVINO `Model` in place of nothing else: the cuts (one output per cut) are unchanged,
so head(k) + tail(k) still equal the whole graph.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

INPUT_SCALE: Final[float] = 128 / 127.5  # x = INPUT_SCALE * x' + INPUT_SHIFT
INPUT_SHIFT: Final[float] = 0.5 / 127.5


class GraphRewriteError(RuntimeError):
    """The graph does not have the shape a rewrite expects (it is left unchanged)."""


def _constant_array(node: Any) -> np.ndarray:
    if node.get_type_name() != "Constant":
        raise GraphRewriteError(f"expected a Constant, found {node.get_type_name()} {node.get_friendly_name()}")
    return np.asarray(node.get_data(), dtype=np.float64)


def patch_moments(rois_u8: NDArray[np.uint8], size: tuple[int, int], *, samples: int = 50_000) -> NDArray[np.float64]:
    """Second moments G = E[p p^T] of zero-padded (kh, kw) patches of x' = (u - 128) / 128 over the
    ROIs (`samples` random positions, fixed seed)."""
    kh, kw = size
    x = (np.asarray(rois_u8, np.float64).reshape(-1, *np.shape(rois_u8)[-2:]) - 128) / 128
    x = np.pad(x, ((0, 0), (kh // 2, kh // 2), (kw // 2, kw // 2)))
    rng = np.random.default_rng(0)
    n, h, w = len(x), x.shape[1] - 2 * (kh // 2), x.shape[2] - 2 * (kw // 2)
    i, r, c = rng.integers(0, n, samples), rng.integers(0, h, samples), rng.integers(0, w, samples)
    patches = np.stack([x[i, r + dy, c + dx] for dy in range(kh) for dx in range(kw)], axis=1)
    moments: NDArray[np.float64] = patches.T @ patches / samples
    return moments


def round_codes(
    weights: NDArray[np.float64], step: NDArray[np.float64], moments: NDArray[np.float64] | None
) -> NDArray[np.int8]:
    """int8 codes q of per-channel weights (C, ...) at steps (C,): nearest rounding without `moments`;
    with them, per channel the floor/ceil combination minimising d^T G d, d = q s - w (<= 9 taps)."""
    channels = len(weights)
    flat = weights.reshape(channels, -1)
    taps = flat.shape[1]
    s = step.reshape(channels, 1)
    if moments is None or taps > 9:
        return np.clip(np.round(flat / s), -127, 127).astype(np.int8).reshape(weights.shape)
    combos = ((np.arange(1 << taps)[:, None] >> np.arange(taps)) & 1).astype(np.float64)
    codes = np.empty_like(flat)
    for ch in range(channels):
        candidates = np.clip(np.floor(flat[ch] / s[ch]) + combos, -127, 127)
        d = candidates * s[ch] - flat[ch]
        codes[ch] = candidates[np.argmin(np.einsum("ni,ij,nj->n", d, moments, d))]
    return codes.astype(np.int8).reshape(weights.shape)


def first_convolution_exact_int8(model: Any, calibration_rois: NDArray[np.uint8] | None = None) -> Any:
    """Rewrite 1 (module docstring) on `model` (modified and returned). The first convolution must read
    the graph's input directly and have float weights (C, 1, kh, kw). Without `calibration_rois` the
    weights are rounded to the nearest code."""
    import openvino as ov
    import openvino.opset13 as ops

    (param,) = model.get_parameters()
    convs = [t.get_node() for t in param.output(0).get_target_inputs()]
    if len(convs) != 1 or convs[0].get_type_name() != "Convolution":
        raise GraphRewriteError(f"the input feeds {[c.get_type_name() for c in convs]}, not one Convolution")
    conv = convs[0]
    weights = _constant_array(conv.input_value(1).get_node())
    if weights.ndim != 4 or weights.shape[1] != 1:
        raise GraphRewriteError(f"first convolution weights {weights.shape}, expected (C, 1, kh, kw)")
    channels = weights.shape[0]
    users = [t.get_node() for t in conv.output(0).get_target_inputs()]
    bias_add = None
    if len(users) == 1 and users[0].get_type_name() == "Add":
        other = users[0].input_value(1).get_node()
        if other.get_type_name() == "Constant" and int(np.prod(other.get_output_shape(0))) == channels:
            bias_add = users[0]

    x_int = ops.add(
        ops.multiply(param.output(0), ops.constant(np.float32(1 / INPUT_SCALE))),
        ops.constant(np.float32(-INPUT_SHIFT / INPUT_SCALE)),
    )
    low, high = ops.constant(np.float32(-1.0)), ops.constant(np.float32(127 / 128))
    x_q = ops.fake_quantize(x_int, low, high, low, high, 256)

    scaled = INPUT_SCALE * weights
    step = np.abs(scaled).reshape(channels, -1).max(axis=1) / 127
    step[step == 0] = 1.0
    moments = None if calibration_rois is None else patch_moments(calibration_rois, weights.shape[2:])
    codes = round_codes(scaled, step, moments)
    step = step.reshape(channels, 1, 1, 1)
    w_q = ops.multiply(ops.convert(ops.constant(codes), ov.Type.f32), ops.constant(step.astype(np.float32)))

    shift = INPUT_SHIFT * weights.reshape(channels, -1).sum(axis=1)
    targets = list(conv.output(0).get_target_inputs())
    conv.input(0).replace_source_output(x_q.output(0))
    conv.input(1).replace_source_output(w_q.output(0))
    if bias_add is not None:  # fold the shift into the bias that follows (BatchNorm's)
        bias_node = bias_add.input_value(1).get_node()
        bias = _constant_array(bias_node).reshape(-1) + shift
        bias_add.input(1).replace_source_output(
            ops.constant(bias.reshape(bias_node.get_output_shape(0)).astype(np.float32)).output(0)
        )
    else:  # no bias (e.g. untrained BatchNorm folded away): add one
        shifted = ops.add(conv.output(0), ops.constant(shift.reshape(1, channels, 1, 1).astype(np.float32)))
        for target in targets:
            target.replace_source_output(shifted.output(0))
    model.validate_nodes_and_infer_types()
    return model


def fully_connected_int8_weights(model: Any, *, min_weights: int = 1 << 20) -> Any:
    """Rewrite 2 (module docstring): int8 weights for the MatMuls with at least `min_weights` float
    weights (the 4096 -> 512 layer; the 512 -> 32 output layer is 64 kB and stays fp32). Convolutions
    are left alone (NNCF would compress a float convolution's weights too)."""
    import nncf  # the quantize extra

    small = []
    for op in model.get_ordered_ops():
        if op.get_type_name() != "MatMul":
            continue
        weights = op.input_value(1).get_node()
        if weights.get_type_name() != "Constant" or int(np.prod(weights.get_output_shape(0))) < min_weights:
            small.append(op.get_friendly_name())
    scope = nncf.IgnoredScope(names=small, types=["Convolution"])
    compressed: Any = nncf.compress_weights(model, mode=nncf.CompressWeightsMode.INT8_ASYM, ignored_scope=scope)
    return compressed


def int8_rewrite(
    *,
    exact_first_conv: bool = True,
    fc_int8_weights: bool = True,
    calibration_rois: NDArray[np.uint8] | None = None,
) -> Callable[[Any], Any]:
    """The rewrites `splittag quantize` applies to the exported int8 graph (both by default), in order."""

    def rewrite(model: Any) -> Any:
        if exact_first_conv:
            model = first_convolution_exact_int8(model, calibration_rois)
        if fc_int8_weights:
            model = fully_connected_int8_weights(model)
        return model

    return rewrite
