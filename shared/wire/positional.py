"""Framing 3: a positional msgpack header whose wire types are compiled from the message models, so
one C call (msgspec) parses the header and checks every field of it.

    0xC1 | version 3 | 2 zero bytes | u32 LE header length H | H bytes msgpack header | 0-7 zero bytes |
    array data, each array starting 8-byte aligned (relative to the data section), in header order

The header is `[schema id, field 1, field 2, ...]` in the model's field order, nested models are
arrays of their fields the same way: no field names travel (a one-tag Features header is 62 % of its
framing-2 size). Arrays travel two ways:

- small fixed-shape float arrays whose values must be finite (corners, homographies, poses,
  covariances, TagPoses' 16 keypoints): inline, as flat msgpack number arrays of exactly the right
  length, their bounds (the dtype's largest finite value) checked by the parser, so NaN and inf are
  refused there;
- every other array (images, split tensors): a reference `[dtype code, [sizes], offset]` into the data
  section, which is viewed without a copy and then checked by the field's own `ArraySpec` (dtype,
  shape, finiteness), in header order, 8-byte aligned, without overlap, inside the payload, the
  payload ending with the last one.

Models compile only if they are strict, forbid extra fields and use no config or constraint the
parser does not know (a lax field, `str_strip_whitespace`, `model_post_init`, a field validator, a
before-validator...): the parser must refuse exactly what pydantic refuses.

Why: inside a Zenoh callback each Python call runs cold, and framing 2's per-array hooks and pydantic's
validation of a small Features message cost ~0.1 ms per round trip, more than Zenoh itself. Here the
parser does the scalar checks natively and the models are assembled without a second validation; the
models' own `model_validator(mode="after")` checks then run on the result, so nothing pydantic would
refuse gets through (tests/test_wire.py decodes every example and thousands of mutated payloads both
ways and requires the same verdicts and values).

The wire types are derived from the pydantic models when a codec is built (`PositionalCodec`); a field
whose type or constraint the compiler does not know is an error at that moment, never a silently
unchecked field.

Readers of a few fields (the link probe's echo and its ack, robot_infer's TagPoses bookkeeping on
Zenoh's thread) can skip the model: `unpack_wire` makes every check `unpack` makes on the parsed wire
struct itself (references' bounds and shapes without making an ndarray, the models' after-validators
run on the struct: each is marked `@wire_safe`, written for either form) and `build` assembles the
model later if it is wanted (`shared.wire.messages.decode_view`). Encoders are generated per model (one
function, no loop over a field plan).
"""

from __future__ import annotations

import math
import re
import types
import typing
from collections.abc import Callable, Iterable, Sequence
from typing import Annotated, Any, Final, Literal, Union

import annotated_types as at
import msgspec
import numpy as np
from pydantic import BaseModel
from pydantic.fields import FieldInfo
from pydantic.types import AllowInfNan, Strict

from shared.wire.codec import (
    ALIGN,
    CODE_DTYPES,
    DTYPE_CODES,
    MAX_DIM,
    MAX_NDIM,
    WIRE_DTYPES,
    ArrayError,
    DataSection,
    DataWriter,
    MalformedFrame,
    SchemaError,
    open_frame,
    wire_dtype_name,
)

FRAMING3: Final[int] = 3
MAX_INLINE: Final[int] = 64  # elements: larger arrays travel in the data section
MAX_ERROR_CHARS: Final[int] = 300  # an error quotes the received value: never a megabyte of it
_FINITE_MAX: Final[dict[str, float]] = {
    "float64": float(np.finfo(np.float64).max),
    "float32": float(np.finfo(np.float32).max),
    "float16": float(np.finfo(np.float16).max),
}
_Dims = Annotated[list[Annotated[int, msgspec.Meta(ge=0, le=MAX_DIM)]], msgspec.Meta(max_length=MAX_NDIM)]
_Offset = Annotated[int, msgspec.Meta(ge=0, multiple_of=ALIGN)]


class CompileError(TypeError):
    """A model field whose type or constraint has no positional wire type (a programming error)."""


# A field's (wire type, encoder of a model value -> wire value, decoder of a wire value -> model value,
# checker of a wire value that the parser could not judge). None for any of them: nothing to do (the
# value is the same on both sides: scalars, strings, literals, lists of those, inline arrays' checks).
Enc = Callable[[Any, DataWriter], Any] | None
Dec = Callable[[Any, DataSection], Any] | None
Chk = Callable[[Any, DataSection], None] | None
Compiled = tuple[Any, Enc, Dec, Chk]


def _rust_anchor(pattern: str) -> str:
    """pydantic matches patterns with Rust's regex, where `$` is the end of the text; Python's `$` also
    matches before a final newline ("abc\\n"). The same pattern with Python's `\\Z` instead."""
    if pattern.endswith("$") and not pattern.endswith("\\$"):
        return pattern[:-1] + r"\Z"
    return pattern


_BOUNDS: Final[dict[type, str]] = {
    at.Ge: "ge",
    at.Gt: "gt",
    at.Le: "le",
    at.Lt: "lt",
    at.MinLen: "min_length",
    at.MaxLen: "max_length",
}


def _meta_of(metadata: Iterable[Any], where: str) -> tuple[dict[str, Any], Any, bool | None]:
    """msgspec.Meta keywords, an ArraySpec (or None) and allow_inf_nan from pydantic field metadata."""
    from shared.wire.messages import ArraySpec  # the array checks live with the messages

    kw: dict[str, Any] = {}
    spec = None
    allow_inf_nan: bool | None = None
    for m in metadata:
        if isinstance(m, ArraySpec):
            spec = m
        elif type(m) in _BOUNDS:  # annotated_types' names are msgspec.Meta's
            name = _BOUNDS[type(m)]
            kw[name] = getattr(m, name)
        elif isinstance(m, FieldInfo):
            inner, inner_spec, inner_nan = _meta_of(m.metadata, where)
            kw.update(inner)
            spec = inner_spec or spec
            allow_inf_nan = inner_nan if inner_nan is not None else allow_inf_nan
        elif isinstance(m, AllowInfNan):
            allow_inf_nan = m.allow_inf_nan
        elif isinstance(m, Strict):
            if not m.strict:
                raise CompileError(f"{where}: a lax (strict=False) field has no positional wire type")
        elif type(m).__name__ == "_PydanticGeneralMetadata":
            extra = dict(vars(m))
            if "pattern" in extra:
                kw["pattern"] = _rust_anchor(extra.pop("pattern"))
            if "allow_inf_nan" in extra:
                allow_inf_nan = bool(extra.pop("allow_inf_nan"))
            if extra.pop("strict", True) is not True:
                raise CompileError(f"{where}: a lax (strict=False) field has no positional wire type")
            if extra:
                raise CompileError(f"{where}: constraints {sorted(extra)} have no positional wire type")
        else:
            raise CompileError(f"{where}: metadata {m!r} has no positional wire type")
    return kw, spec, allow_inf_nan


def inline_array(spec: Any) -> bool:
    """An array field that travels inline in the header (a flat number array): fixed shape, one float
    dtype, finite, at most MAX_INLINE elements; every other array is a reference into the data section."""
    shape = spec.shape
    fixed = shape is not None and all(d is not None for d in shape)
    return bool(
        fixed
        and spec.finite
        and len(spec.dtypes) == 1
        and spec.dtypes[0] in _FINITE_MAX
        and math.prod(shape) <= MAX_INLINE
    )


def _meta(tp: Any, kw: dict[str, Any]) -> Any:
    return Annotated[tp, msgspec.Meta(**kw)] if kw else tp


class PositionalCodec:
    """Encoder and decoder of framing 3 for a set of message models (current and older schemas)."""

    def __init__(self, models: Sequence[type[BaseModel]], *, legacy: Iterable[type[BaseModel]] = ()) -> None:
        self._structs: dict[type[BaseModel], type[msgspec.Struct]] = {}
        self._encoders: dict[type[BaseModel], Callable[[Any, DataWriter], list[Any]]] = {}
        self._tops: dict[type[BaseModel], Callable[[Any, DataWriter], list[Any]]] = {}  # with the schema id
        self._builders: dict[type[msgspec.Struct], Callable[[Any, DataSection], Any]] = {}
        self._checkers: dict[type[msgspec.Struct], Chk] = {}
        self._ref_types: dict[tuple[int, ...], type[msgspec.Struct]] = {}
        self.models = {m.SCHEMA: m for m in (*models, *legacy)}  # type: ignore[attr-defined]
        tops = []
        for schema, model in self.models.items():
            tops.append(self._struct_for(model, tag=schema))
        self._decoder = msgspec.msgpack.Decoder(Union[tuple(tops)])  # noqa: UP007
        self._encoder = msgspec.msgpack.Encoder()

    # -- compilation ------------------------------------------------------------------------------

    def _ref_type(self, codes: tuple[int, ...]) -> type[msgspec.Struct]:
        ref = self._ref_types.get(codes)
        if ref is None:
            ref = msgspec.defstruct(
                f"ArrayRef{'_'.join(map(str, codes))}",
                [("dtype", Literal[codes]), ("shape", _Dims), ("offset", _Offset)],
                array_like=True,
                forbid_unknown_fields=True,
                frozen=True,
            )
            self._ref_types[codes] = ref
        return ref

    def _array(self, spec: Any, where: str) -> Compiled:
        shape = spec.shape
        count = math.prod(shape) if inline_array(spec) else 0
        if inline_array(spec):
            name = spec.dtypes[0]
            dtype = WIRE_DTYPES[name]
            bound = _FINITE_MAX[name]
            item = Annotated[float, msgspec.Meta(ge=-bound, le=bound)]
            wire = Annotated[tuple[item, ...], msgspec.Meta(min_length=count, max_length=count)]

            def enc_inline(value: np.ndarray, out: DataWriter) -> list[float]:
                if type(value) is np.ndarray and value.dtype is dtype and value.shape == shape:
                    return value.ravel().tolist()  # what a validated message holds (builtin dtypes are singletons)
                if isinstance(value, np.ndarray) and value.dtype != dtype and value.dtype.newbyteorder("<") == dtype:
                    value = value.astype(dtype)  # the same values in the other byte order (as framing 2 writes it)
                if not isinstance(value, np.ndarray) or value.dtype != dtype or value.shape != shape:
                    got = f"{value.dtype} {value.shape}" if isinstance(value, np.ndarray) else type(value).__name__
                    raise ArrayError(f"{where}: expected a {name} array of shape {shape}, got {got}")
                return value.ravel().tolist()

            def dec_inline(value: tuple[float, ...], ctx: DataSection) -> np.ndarray:
                out = np.array(value, dtype).reshape(shape)
                out.flags.writeable = False  # as framing 2's views of the payload
                return out

            return wire, enc_inline, dec_inline, None  # the parser checked length and bounds
        codes = tuple(sorted(DTYPE_CODES[d] for d in spec.dtypes))
        validate = spec.validate
        wire_codes = {WIRE_DTYPES[d]: DTYPE_CODES[d] for d in spec.dtypes}  # the field's little-endian dtypes

        def enc_ref(value: np.ndarray, out: DataWriter) -> list[Any]:
            if not isinstance(value, np.ndarray):
                raise ArrayError(f"{where}: expected an ndarray, got {type(value).__name__}")
            code = wire_codes.get(value.dtype)
            if code is not None and value.flags.c_contiguous:  # what a validated message holds
                arr = value
            else:
                name = wire_dtype_name(value.dtype)
                arr = np.ascontiguousarray(value, dtype=WIRE_DTYPES[name])
                code = DTYPE_CODES[name]
            return [code, list(arr.shape), out.place(arr)]

        def dec_ref(ref: Any, ctx: DataSection) -> np.ndarray:
            arr = ctx.view(CODE_DTYPES[ref.dtype], ref.shape, ref.offset)
            try:
                return validate(arr)
            except ValueError as exc:
                raise _FieldError(f"{where}: {exc}") from None

        check_shape = spec.check_shape
        scan = spec.finite and any(WIRE_DTYPES[d].kind == "f" for d in spec.dtypes)

        def chk_ref(ref: Any, ctx: DataSection) -> None:
            if scan:  # finiteness needs the values: the array is viewed and scanned
                dec_ref(ref, ctx)
                return
            ctx.claim(CODE_DTYPES[ref.dtype], ref.shape, ref.offset)  # the bounds, without an ndarray
            try:
                check_shape(tuple(ref.shape))
            except ValueError as exc:
                raise _FieldError(f"{where}: {exc}") from None

        return self._ref_type(codes), enc_ref, dec_ref, chk_ref

    def _field(self, tp: Any, metadata: Sequence[Any], where: str) -> Compiled:
        """(wire type, encoder, decoder, checker) of one field type with its pydantic metadata."""
        if typing.get_origin(tp) is Annotated:
            base, *more = typing.get_args(tp)
            return self._field(base, [*more, *metadata], where)
        kw, spec, allow_inf_nan = _meta_of(metadata, where)
        if spec is not None:
            return self._array(spec, where)
        origin = typing.get_origin(tp)
        if origin in (Union, types.UnionType):
            args = typing.get_args(tp)
            others = [a for a in args if a is not type(None)]
            if len(others) != 1 or len(args) != 2:
                raise CompileError(f"{where}: only `X | None` unions have a positional wire type, not {tp}")
            wire, enc, dec, chk = self._field(others[0], metadata, where)  # the constraints are the value's
            enc_opt = None if enc is None else (lambda v, out, _e=enc: None if v is None else _e(v, out))
            dec_opt = None if dec is None else (lambda v, ctx, _d=dec: None if v is None else _d(v, ctx))
            chk_opt = None if chk is None else (lambda v, ctx, _c=chk: None if v is None else _c(v, ctx))
            return wire | None, enc_opt, dec_opt, chk_opt
        if origin is list:
            (item,) = typing.get_args(tp)
            wire, enc, dec, chk = self._field(item, [], where + "[]")
            enc_list = None if enc is None else (lambda v, out, _e=enc: [_e(x, out) for x in _as_list(v, where)])
            dec_list = None if dec is None else (lambda v, ctx, _d=dec: [_d(x, ctx) for x in v])
            chk_list = None if chk is None else _each(chk)
            return _meta(list[wire], kw), enc_list, dec_list, chk_list  # type: ignore[valid-type]
        if origin is Literal:
            if kw:
                raise CompileError(f"{where}: constraints on a Literal")
            return tp, None, None, None
        if isinstance(tp, type) and issubclass(tp, BaseModel):
            if kw:
                raise CompileError(f"{where}: constraints on a nested model")
            struct_type = self._struct_for(tp)
            return struct_type, self._encoders[tp], self._builders[struct_type], self._checkers[struct_type]
        if tp is bool or tp is str:
            return _meta(tp, kw), None, None, None
        if tp is int:
            return _meta(int, kw), None, None, None
        if tp is float:
            if allow_inf_nan is False:  # NaN fails any bound; a finite bound refuses +-inf
                big = _FINITE_MAX["float64"]
                kw.setdefault("ge", -big) if "gt" not in kw else None
                kw.setdefault("le", big) if "lt" not in kw else None
            return _meta(float, kw), None, None, None  # an int on the wire becomes a float, as in pydantic
        raise CompileError(f"{where}: type {tp!r} has no positional wire type")

    def _struct_for(self, model: type[BaseModel], *, tag: str | None = None) -> type[msgspec.Struct]:
        """The positional wire type of one model (compiled once; `tag`: a top-level message's schema id)."""
        existing = self._structs.get(model)
        if existing is not None and tag is None:
            return existing
        _check_config(model)
        fields: list[tuple[str, Any]] = []
        encoders: list[tuple[str, Enc]] = []
        decoders: list[tuple[str, Dec]] = []
        checkers: list[tuple[str, Chk]] = []
        for name, info in model.model_fields.items():
            where = f"{model.__name__}.{name}"
            wire, enc, dec, chk = self._field(info.annotation, info.metadata, where)
            fields.append((name, wire))
            encoders.append((name, enc))
            decoders.append((name, dec))
            checkers.append((name, chk))
        # frozen: a view's fields were checked once; they cannot be changed before `build` trusts them
        options: dict[str, Any] = {"array_like": True, "forbid_unknown_fields": True, "frozen": True}
        if tag is not None:
            options["tag"] = tag
        struct_type = msgspec.defstruct(f"Wire{model.__name__}", fields, **options)
        self._structs.setdefault(model, struct_type)
        self._builders[struct_type] = _builder(model, decoders)
        self._checkers[struct_type] = _checker(model, checkers)
        if model not in self._encoders:
            self._encoders[model] = _encoder(model, encoders, tag=None)
        if tag is not None:
            self._tops[model] = _encoder(model, encoders, tag=tag)
        return struct_type

    # -- encoding and decoding --------------------------------------------------------------------

    def pack(self, message: BaseModel) -> bytes:
        """Framing 3 bytes of a message (its model must be one this codec was built for)."""
        out = DataWriter()
        return out.frame(FRAMING3, self._encoder.encode(self._tops[type(message)](message, out)))

    def pack_values(self, model: type[BaseModel], values: Sequence[Any]) -> bytes:
        """Framing 3 bytes of a message given as its field values in declaration order (nested messages
        as sequences of theirs, small float arrays as flat sequences), checked by the same compiled wire
        type the receiver parses with; for a message built only to be sent at once. A model with
        out-of-band arrays or after-validators is refused (TypeError): their checks need the model (`pack`)."""
        struct_type = self._structs.get(model)
        if struct_type is None or self._checkers[struct_type] is not None:
            raise TypeError(f"{model.__name__}: pack_values takes messages of this codec without arrays or validators")
        if len(values) != len(model.model_fields):
            raise SchemaError(
                f"invalid {model.SCHEMA}: {len(values)} values for its {len(model.model_fields)} fields "  # type: ignore[attr-defined]
                f"({', '.join(model.model_fields)})"
            )
        try:
            wire = msgspec.convert([model.SCHEMA, *values], struct_type)  # type: ignore[attr-defined]
        except msgspec.ValidationError as exc:
            raise SchemaError(f"invalid {model.SCHEMA}: {_short(_named(str(exc), struct_type))}") from None  # type: ignore[attr-defined]
        return DataWriter().frame(FRAMING3, self._encoder.encode(wire))

    def unpack(self, mv: memoryview) -> tuple[str, BaseModel]:
        """(schema id, model of that schema) from a framing-3 payload; arrays view `mv`."""
        schema, wire, section = self._parse(mv)
        return schema, self._build(schema, wire, section)

    def unpack_wire(self, mv: memoryview) -> tuple[str, Any]:
        """(schema id, wire struct) from a framing-3 payload that passed every check `unpack` makes, without
        building the model (`build` does, later): the header's values by field name, nested messages as
        wire structs, inline arrays as flat tuples, the others as [dtype, shape, offset] references whose
        bounds and shapes were checked. The models' after-validators ran on the wire struct."""
        schema, wire, section = self._parse(mv)
        check = self._checkers[type(wire)]
        if check is not None:
            try:
                check(wire, section)
            except _FieldError as exc:
                raise SchemaError(f"invalid {schema}: {_short(str(exc))}") from None
        section.finish()
        return schema, wire

    def build(self, schema: str, wire: Any, mv: memoryview) -> BaseModel:
        """The model of a wire struct that `unpack_wire` returned for `mv` (arrays view `mv`)."""
        _, _, section = open_frame(mv)
        return self._build(schema, wire, section)

    def _parse(self, mv: memoryview) -> tuple[str, Any, DataSection]:
        _, header, section = open_frame(mv)  # the version was read by the caller's dispatch
        try:
            wire = self._decoder.decode(header)
        except msgspec.ValidationError as exc:
            raise self._header_error(header, exc) from None
        except (msgspec.DecodeError, ValueError) as exc:  # ValueError: a string that is not UTF-8
            raise MalformedFrame(f"malformed msgpack header: {_short(str(exc))}") from None
        return wire.__struct_config__.tag, wire, section

    def _build(self, schema: str, wire: Any, section: DataSection) -> BaseModel:
        try:
            model = self._builders[type(wire)](wire, section)
        except _FieldError as exc:
            raise SchemaError(f"invalid {schema}: {_short(str(exc))}") from None
        section.finish()
        return model

    def _header_error(self, header: memoryview, exc: msgspec.ValidationError) -> Exception:
        """The clearest error for a header the parser refused: an unknown schema id is said as such."""
        try:
            doc = msgspec.msgpack.decode(header)
        except (msgspec.DecodeError, ValueError, RecursionError):
            return MalformedFrame(f"malformed msgpack header: {_short(str(exc))}")
        if not isinstance(doc, list):
            return MalformedFrame(f"the header is a {type(doc).__name__}, not [schema id, fields...]")
        schema = doc[0] if doc else None
        if not isinstance(schema, str) or schema not in self.models:
            return UnknownSchema(schema)
        return SchemaError(f"invalid {schema}: {_short(_named(str(exc), self._structs[self.models[schema]]))}")


_AT = re.compile(r"^(?P<what>.*) - at `\$(?P<path>(?:\[\d+\])*)`$", re.DOTALL)


def _named(message: str, top: type[msgspec.Struct]) -> str:
    """msgspec's "... - at `$[9][0][9]`" with field names: "tags[0].proposer: ..." (the positional
    header has no names; the wire types do)."""
    m = _AT.match(message)
    if m is None:
        return message
    indices = [int(i) for i in re.findall(r"\d+", m["path"])]
    names: list[str] = []
    tp: Any = top
    first = True
    for i in indices:
        while typing.get_origin(tp) is Annotated or typing.get_origin(tp) in (Union, types.UnionType):
            args = [a for a in typing.get_args(tp) if a is not type(None)]
            tp = args[0]
        if isinstance(tp, type) and issubclass(tp, msgspec.Struct):
            fields = msgspec.structs.fields(tp)
            j = i - 1 if first else i  # a top-level header starts with the schema id
            if not 0 <= j < len(fields):
                names.append(f"[{i}]")
                break
            names.append(("." if names else "") + fields[j].name)
            tp = fields[j].type
        elif typing.get_origin(tp) in (list, tuple):
            names.append(f"[{i}]")
            tp = typing.get_args(tp)[0]
        else:
            names.append(f"[{i}]")
        first = False
    where = "".join(names) or "<body>"
    return f"{where}: {m['what']}"


class _FieldError(ValueError):
    """A field the header parser cannot judge was refused by the model's own check (array, validator)."""


class UnknownSchema(SchemaError):
    """The header's first element is not a schema id this peer knows (messages.py words the error)."""

    def __init__(self, schema: Any) -> None:
        super().__init__(f"unknown schema id {schema!r}")
        self.schema = schema


# Config keys that change what pydantic accepts or returns; the parser knows none of them.
_LAX_CONFIG: Final[frozenset[str]] = frozenset(
    {
        "str_strip_whitespace",
        "str_to_lower",
        "str_to_upper",
        "str_min_length",
        "str_max_length",
        "coerce_numbers_to_str",
        "use_enum_values",
        "validate_default",
        "regex_engine",
        "ser_json_inf_nan",
        "allow_inf_nan",
    }
)


def _check_config(model: type[BaseModel]) -> None:
    """The parser checks what a strict, extra-forbidding, plain model checks: nothing else compiles."""
    config = model.model_config
    if config.get("strict") is not True or config.get("extra") != "forbid":
        raise CompileError(f"{model.__name__}: only strict models that forbid extra fields compile")
    lax = sorted(k for k in _LAX_CONFIG if k in config)
    if lax:
        raise CompileError(f"{model.__name__}: config {lax} has no positional wire type")
    if model.__pydantic_post_init__ is not None:
        raise CompileError(f"{model.__name__}: model_post_init has no positional wire type")


def _short(value: object) -> str:
    text = value if isinstance(value, str) else repr(value)
    return text if len(text) <= MAX_ERROR_CHARS else text[:MAX_ERROR_CHARS] + f"... ({len(text)} chars)"


def _as_list(value: Any, where: str) -> list[Any]:
    if not isinstance(value, list):
        raise MalformedFrame(f"{where}: cannot encode {type(value).__name__} where a list belongs")
    return value


_new = object.__new__
_set = object.__setattr__


def wire_safe(check: Callable[[Any], Any]) -> Callable[[Any], Any]:
    """Mark a model's after-validator as one that also judges the model's wire struct (`unpack_wire`
    runs it there): it may read fields by name and must take a small float array either as the
    model's ndarray or as the wire's flat tuple, and an out-of-band array's shape from `.shape` alone."""
    check.__wire_safe__ = True  # type: ignore[attr-defined]
    return check


def flat(value: Any) -> list[float] | tuple[float, ...]:
    """A small float array's values in C order: the model's ndarray or the wire struct's flat tuple."""
    return value.ravel().tolist() if isinstance(value, np.ndarray) else value


def _after_validators(model: type[BaseModel]) -> list[Callable[[Any], Any]]:
    decorators = model.__pydantic_decorators__
    if any(d.info.mode != "after" for d in decorators.model_validators.values()):
        raise CompileError(f"{model.__name__}: only after-validators are supported")
    if decorators.field_validators:
        raise CompileError(f"{model.__name__}: field validators have no positional wire check")
    after = [d.func for d in decorators.model_validators.values()]
    unsafe = [f.__name__ for f in after if not getattr(f, "__wire_safe__", False)]
    if unsafe:
        raise CompileError(f"{model.__name__}: after-validators {unsafe} are not marked @wire_safe")
    return after


def _each(check: Callable[[Any, DataSection], None]) -> Callable[[Any, DataSection], None]:
    def check_all(values: Any, ctx: DataSection) -> None:
        for v in values:
            check(v, ctx)

    return check_all


def _run_after(model: type[BaseModel], after: list[Callable[[Any], Any]], target: Any) -> None:
    """The model's after-validators on `target` (the model, or its wire struct: each is @wire_safe)."""
    for validate in after:
        try:
            validate(target)
        except ValueError as exc:
            raise _FieldError(f"{model.__name__}: {exc}") from None


def _checker(model: type[BaseModel], checkers: list[tuple[str, Chk]]) -> Chk:
    """The checks of a wire struct that the parser could not make (arrays' bounds and shapes, nested
    models' checks, then the model's after-validators run on the wire struct), in the order the builder
    makes them; None when the parser checked everything."""
    special = [(name, chk) for name, chk in checkers if chk is not None]
    after = _after_validators(model)
    if not special and not after:
        return None
    get = getattr

    def check(wire: Any, ctx: DataSection) -> None:
        for name, chk in special:
            chk(get(wire, name), ctx)
        _run_after(model, after, wire)

    return check


def _builder(model: type[BaseModel], decoders: list[tuple[str, Dec]]) -> Callable[[Any, DataSection], Any]:
    """Wire struct -> model, without a second validation: the parser checked every scalar; arrays are
    checked by their decoders; then the model's own after-validators run, as model_validate would."""
    special = [(name, dec) for name, dec in decoders if dec is not None]
    after = _after_validators(model)
    asdict = msgspec.structs.asdict
    names = frozenset(model.model_fields)

    def build(wire: Any, ctx: DataSection) -> Any:
        values = asdict(wire)
        for name, dec in special:
            values[name] = dec(values[name], ctx)
        out = _new(model)
        _set(out, "__dict__", values)
        _set(out, "__pydantic_fields_set__", set(names))
        _set(out, "__pydantic_extra__", None)
        _set(out, "__pydantic_private__", None)
        _run_after(model, after, out)
        return out

    return build


def _encoder(model: type[BaseModel], encoders: list[tuple[str, Enc]], *, tag: str | None) -> Callable[..., list[Any]]:
    """Model -> positional wire list (`[tag, fields...]` for a top-level message), as one generated
    function per model: a field list walked by a loop costs twice as much on the hot path."""
    names = {name: f"_e{i}" for i, (name, enc) in enumerate(encoders) if enc is not None}
    items = [f"d[{name!r}]" if name not in names else f"{names[name]}(d[{name!r}], out)" for name, _ in encoders]
    if tag is not None:
        items.insert(0, "_tag")
    source = (
        "def encode(message, out):\n"
        "    if message.__class__ is not _model and not isinstance(message, _BaseModel):\n"
        "        raise _MalformedFrame(f'cannot encode {type(message).__name__} where a message part belongs')\n"
        "    d = message.__dict__\n"
        f"    return [{', '.join(items)}]\n"
    )
    scope: dict[str, Any] = {"_model": model, "_BaseModel": BaseModel, "_MalformedFrame": MalformedFrame, "_tag": tag}
    scope.update({names[name]: enc for name, enc in encoders if enc is not None})
    exec(compile(source, f"<positional encoder of {model.__name__}>", "exec"), scope)
    return scope["encode"]
