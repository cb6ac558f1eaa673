"""The positional layout of every current schema, for a reader who decodes framing 3 without this package
(any language with msgpack): each message's header fields in order, with their wire form. Generated from
the message models, as the codec compiles them (`shared.wire.positional`), into docs/wire.md's *Field
order of every schema* (written by `python -m shared.tools.docgen`; tests/test_docs.py fails when they differ).
"""

from __future__ import annotations

import types
import typing
from typing import Annotated, Any, Final, Literal, Union

import annotated_types as at
from pydantic import BaseModel
from pydantic.fields import FieldInfo
from pydantic.types import AllowInfNan

from shared.wire.codec import DTYPE_CODES
from shared.wire.cuts import CUTS, N_CUTS
from shared.wire.messages import MESSAGE_TYPES, ArraySpec
from shared.wire.positional import inline_array

_BOUNDS: Final[dict[type, tuple[str, str]]] = {
    at.Ge: (">=", "ge"),
    at.Gt: (">", "gt"),
    at.Le: ("<=", "le"),
    at.Lt: ("<", "lt"),
    at.MinLen: ("length >=", "min_length"),
    at.MaxLen: ("length <=", "max_length"),
}


def _constraints(metadata: list[Any]) -> tuple[list[str], ArraySpec | None]:
    out: list[str] = []
    spec = None
    for m in metadata:
        if isinstance(m, ArraySpec):
            spec = m
        elif type(m) in _BOUNDS:
            symbol, attr = _BOUNDS[type(m)]
            out.append(f"{symbol} {getattr(m, attr)}")
        elif isinstance(m, FieldInfo):
            more, inner = _constraints(list(m.metadata))
            out += more
            spec = inner or spec
        elif isinstance(m, AllowInfNan) and not m.allow_inf_nan:
            out.append("finite")
        elif hasattr(m, "pattern") and getattr(m, "pattern", None):
            out.append(f"matches {m.pattern}")
    return out, spec


def _array(spec: ArraySpec) -> str:
    shape = " x ".join("any" if d is None else str(d) for d in spec.shape) if spec.shape else None
    if inline_array(spec):
        count = 1
        for d in spec.shape or ():
            count *= int(d or 0)
        return f"{count} numbers inline ({spec.dtypes[0]} {shape}, row-major), finite"
    codes = ", ".join(f"{d} = {DTYPE_CODES[d]}" for d in spec.dtypes)
    dims = f"shape {shape}" if shape else f"{'/'.join(map(str, spec.ndims or ()))} dimensions"
    finite = ", finite" if spec.finite and any(d.startswith("float") for d in spec.dtypes) else ""
    return f"array reference [dtype code, [sizes], offset] into the data section ({codes}; {dims}{finite})"


def _describe(tp: Any, metadata: list[Any], depth: int) -> tuple[str, list[str]]:
    """(one-line wire form, nested lines) of a field type."""
    if typing.get_origin(tp) is Annotated:
        base, *more = typing.get_args(tp)
        return _describe(base, [*more, *metadata], depth)
    bounds, spec = _constraints(metadata)
    if spec is not None:
        return _array(spec), []
    extra = f" ({', '.join(bounds)})" if bounds else ""
    origin = typing.get_origin(tp)
    if origin in (Union, types.UnionType):
        (other,) = [a for a in typing.get_args(tp) if a is not type(None)]
        text, nested = _describe(other, metadata, depth)
        return f"{text} or nil", nested
    if origin is list:
        (item,) = typing.get_args(tp)
        text, nested = _describe(item, [], depth)
        return f"array of {text}{extra}", nested
    if origin is Literal:
        return "one of " + " | ".join(repr(v) for v in typing.get_args(tp)), []
    if isinstance(tp, type) and issubclass(tp, BaseModel):
        return f"[{tp.__name__}: the {len(tp.model_fields)} fields below, in order]", _fields(tp, depth + 1)
    names = {bool: "bool", str: "str", int: "int", float: "float"}
    if tp in names:
        return f"{names[tp]}{extra}", []
    raise TypeError(f"no wire form for {tp!r}")


def _fields(model: type[BaseModel], depth: int) -> list[str]:
    lines = []
    pad = "   " * depth  # three spaces: a nested item under "1. " in markdown
    for i, (name, info) in enumerate(model.model_fields.items(), start=1):
        text, nested = _describe(info.annotation, list(info.metadata), depth)
        lines.append(f"{pad}{i}. `{name}`: {text}")
        lines += nested
    return lines


def layout_markdown() -> str:
    """docs/wire.md's generated section: each current schema's header, field by field (shared.tools.docgen
    puts it between its markers)."""
    out = [
        "Each header is a msgpack array `[schema id, field 1, field 2, ...]`; a nested message is an array",
        "of its fields the same way; nil is an absent optional value. Numbers: msgpack ints and floats",
        '("float" accepts an int). An inline array is a flat msgpack array of numbers, row-major; an array',
        "reference `[dtype code, [sizes], offset]` points into the data section: `offset` counts from the",
        "data section's first byte (the 8-byte boundary after the header; no padding when the message has",
        "no such array), each array starts 8-byte aligned, little-endian, C order, in header order, and the",
        "payload ends with the last one. dtype codes: "
        + ", ".join(f"{d} = {c}" for d, c in DTYPE_CODES.items())
        + ". The two bytes after the version are zero (reserved: a message where they are not is refused).",
        "",
        "Checks beyond each field's type (a message failing one is refused whole): `distortion` has 0, 4, 5,",
        "8, 12 or 14 coefficients (OpenCV's), all zero when `distortion_model` is none (a camera file's",
        "rational_polynomial arrives as plumb_bob with its 8: OpenCV's model); a Frame's `image` is (height,",
        "width) of its intrinsics;",
        "`roi_to_image` is invertible; where `proposer` is given, `tracked` is true exactly when it is `tracker`;",
        "`covariance_world` is symmetric with no negative variance.",
        "",
        "A Features tag's `tensor` at cut k, per tag (no batch dimension; the export manifest's shapes without",
        "theirs): "
        + f"k = 0 ({CUTS[0].name}) uint8 {CUTS[0].shape}; k = 1..{N_CUTS - 2} ("
        + ", ".join(c.name for c in CUTS[1:-1])
        + ") "
        + ", ".join(str(c.shape) for c in CUTS[1:-1])
        + f", float16 or float32 as `codec` says; k = {N_CUTS - 1} ({CUTS[-1].name}) float32 {CUTS[-1].shape}"
        + ". An int8 network's cut travels as its values (scale * (code - zero point)) in that dtype, not as",
        "its uint8 codes. `edge_width_px` (optional) is how wide the tag's border edge is in the image: the",
        "median over 36 profiles across the black square's edges of (outer - inner level) / steepest",
        "gradient, times the ROI's zoom (about 1 px sharp, more with blur); None and the edge uses its nominal width.",
        "",
    ]
    for model in MESSAGE_TYPES:
        schema = model.SCHEMA
        out.append(f'**`{schema}`**: `["{schema}", ...]`')
        out.append("")
        out += _fields(model, 0)
        out.append("")
    return "\n".join(out) + "\n"
