"""msgpack framing of splittag messages: arrays as {dtype, shape, data}, decoded without copying.

Encoding uses the msgpack library. Decoding uses a small msgpack reader of our own because the
library always copies `bin` values into new `bytes` objects; ours returns them as memoryview
slices of the received buffer, so a tensor crosses from Zenoh into numpy with only the one copy
that Zenoh's `to_bytes()` forces. The reader is also where every byte-level check lives: size
limit, truncation, trailing bytes, nesting depth, array dtype/shape/length.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping
from typing import Any, Final

import msgpack
import numpy as np

# Wire dtype name -> numpy dtype (always little-endian on the wire).
WIRE_DTYPES: Final[dict[str, np.dtype[Any]]] = {
    "float64": np.dtype("<f8"),
    "float32": np.dtype("<f4"),
    "float16": np.dtype("<f2"),
    "uint8": np.dtype("u1"),
    "int8": np.dtype("i1"),
}
_NUMPY_TO_WIRE: Final[dict[str, str]] = {dt.str.lstrip("<>|="): name for name, dt in WIRE_DTYPES.items()}

ARRAY_KEYS: Final[frozenset[str]] = frozenset({"dtype", "shape", "data"})
MAX_NDIM: Final[int] = 8
MAX_DIM: Final[int] = 2**31 - 1  # per dimension
MAX_DEPTH: Final[int] = 32
DEFAULT_MAX_BYTES: Final[int] = 64 * 1024 * 1024


class WireError(ValueError):
    """Base of every error raised while turning bytes into messages (or messages into bytes)."""


class PayloadTooLarge(WireError):
    """The payload exceeds the configured size limit."""


class MalformedFrame(WireError):
    """The bytes are not a well-formed msgpack document of the kind we accept."""


class ArrayError(WireError):
    """An array's dtype, shape or byte length is inconsistent or not allowed."""


class SchemaError(WireError):
    """Unknown schema id, unsupported version, or a body that does not validate."""


# ----------------------------------------------------------------------------------------------
# Encoding
# ----------------------------------------------------------------------------------------------


def wire_dtype_name(dtype: np.dtype[Any]) -> str:
    """The wire name of a numpy dtype, or ArrayError if it may not travel (object, complex...)."""
    key = dtype.str.lstrip("<>|=")
    name = _NUMPY_TO_WIRE.get(key)
    if name is None:
        allowed = ", ".join(WIRE_DTYPES)
        raise ArrayError(f"dtype {dtype!s} cannot be sent; allowed dtypes: {allowed}")
    return name


def _pack_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        name = wire_dtype_name(obj.dtype)
        arr = np.ascontiguousarray(obj, dtype=WIRE_DTYPES[name]).reshape(obj.shape)
        data = memoryview(arr).cast("B") if arr.size else b""  # type: ignore[arg-type]
        return {"dtype": name, "shape": list(arr.shape), "data": data}
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.floating):
        return float(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    raise MalformedFrame(f"cannot encode value of type {type(obj).__name__}")


def pack(document: Mapping[str, Any]) -> bytes:
    """Serialise a document (dicts, lists, scalars, numpy arrays) to msgpack bytes."""
    out = msgpack.packb(document, default=_pack_default, use_bin_type=True, strict_types=False)
    assert isinstance(out, bytes)
    return out


# ----------------------------------------------------------------------------------------------
# Decoding
# ----------------------------------------------------------------------------------------------

_U8 = struct.Struct(">B")
_U16 = struct.Struct(">H")
_U32 = struct.Struct(">I")
_U64 = struct.Struct(">Q")
_I8 = struct.Struct(">b")
_I16 = struct.Struct(">h")
_I32 = struct.Struct(">i")
_I64 = struct.Struct(">q")
_F32 = struct.Struct(">f")
_F64 = struct.Struct(">d")

_FIXED: Final[dict[int, struct.Struct]] = {
    0xCA: _F32,
    0xCB: _F64,
    0xCC: _U8,
    0xCD: _U16,
    0xCE: _U32,
    0xCF: _U64,
    0xD0: _I8,
    0xD1: _I16,
    0xD2: _I32,
    0xD3: _I64,
}


class _Reader:
    """A cursor over a read-only buffer that decodes one msgpack value at a time."""

    __slots__ = ("mv", "pos")

    def __init__(self, mv: memoryview) -> None:
        self.mv = mv
        self.pos = 0

    def _need(self, n: int) -> int:
        start = self.pos
        if start + n > len(self.mv):
            raise MalformedFrame(
                f"truncated payload: needed {n} more bytes at offset {start}, "
                f"only {len(self.mv) - start} left (total {len(self.mv)} bytes)"
            )
        self.pos = start + n
        return start

    def _fixed(self, s: struct.Struct) -> Any:
        start = self._need(s.size)
        return s.unpack_from(self.mv, start)[0]

    def _str(self, n: int) -> str:
        start = self._need(n)
        try:
            return str(self.mv[start : start + n], "utf-8")
        except UnicodeDecodeError as exc:
            raise MalformedFrame(f"invalid UTF-8 string at offset {start}") from exc

    def _bin(self, n: int) -> memoryview:
        start = self._need(n)
        return self.mv[start : start + n]

    def value(self, depth: int) -> Any:
        if depth > MAX_DEPTH:
            raise MalformedFrame(f"nesting deeper than {MAX_DEPTH} levels")
        at = self.pos
        b = self._fixed(_U8)
        if b <= 0x7F:
            return b
        if b >= 0xE0:
            return b - 0x100
        if 0xA0 <= b <= 0xBF:
            return self._str(b & 0x1F)
        if 0x90 <= b <= 0x9F:
            return self._array(b & 0x0F, depth)
        if 0x80 <= b <= 0x8F:
            return self._map(b & 0x0F, depth)
        if b == 0xC0:
            return None
        if b == 0xC2:
            return False
        if b == 0xC3:
            return True
        s = _FIXED.get(b)
        if s is not None:
            return self._fixed(s)
        if b == 0xC4:
            return self._bin(self._fixed(_U8))
        if b == 0xC5:
            return self._bin(self._fixed(_U16))
        if b == 0xC6:
            return self._bin(self._fixed(_U32))
        if b == 0xD9:
            return self._str(self._fixed(_U8))
        if b == 0xDA:
            return self._str(self._fixed(_U16))
        if b == 0xDB:
            return self._str(self._fixed(_U32))
        if b == 0xDC:
            return self._array(self._fixed(_U16), depth)
        if b == 0xDD:
            return self._array(self._fixed(_U32), depth)
        if b == 0xDE:
            return self._map(self._fixed(_U16), depth)
        if b == 0xDF:
            return self._map(self._fixed(_U32), depth)
        raise MalformedFrame(f"unsupported msgpack type byte 0x{b:02x} at offset {at}")

    def _array(self, n: int, depth: int) -> list[Any]:
        # Every element takes at least one byte: a huge declared length fails fast as truncation.
        if n > len(self.mv) - self.pos:
            raise MalformedFrame(f"array of {n} elements at offset {self.pos} exceeds the payload")
        return [self.value(depth + 1) for _ in range(n)]

    def _map(self, n: int, depth: int) -> Any:
        if 2 * n > len(self.mv) - self.pos:
            raise MalformedFrame(f"map of {n} entries at offset {self.pos} exceeds the payload")
        out: dict[str, Any] = {}
        for _ in range(n):
            at = self.pos
            key = self.value(depth + 1)
            if not isinstance(key, str):
                raise MalformedFrame(f"map key at offset {at} is {type(key).__name__}, not str")
            if key in out:
                raise MalformedFrame(f"duplicate map key {key!r} at offset {at}")
            out[key] = self.value(depth + 1)
        if out.keys() == ARRAY_KEYS:
            return array_from_wire(out)
        return out


def array_from_wire(doc: Mapping[str, Any]) -> np.ndarray:
    """Turn a decoded {dtype, shape, data} map into a read-only ndarray viewing `data`."""
    name, shape, data = doc["dtype"], doc["shape"], doc["data"]
    if not isinstance(name, str) or name not in WIRE_DTYPES:
        raise ArrayError(f"array dtype {name!r} is not one of {', '.join(WIRE_DTYPES)}")
    if (
        not isinstance(shape, list)
        or len(shape) > MAX_NDIM
        or not all(isinstance(d, int) and not isinstance(d, bool) and 0 <= d <= MAX_DIM for d in shape)
    ):
        # Bounded sizes: a zero-length array of shape (0, 2**63) has the right byte count (none) but
        # numpy cannot even describe it.
        text = repr(shape) if len(repr(shape)) <= 120 else repr(shape)[:120] + "..."
        raise ArrayError(f"array shape {text} is not a list of at most {MAX_NDIM} sizes in 0..{MAX_DIM}")
    if not isinstance(data, memoryview | bytes):
        raise ArrayError(f"array data is {type(data).__name__}, expected msgpack bin")
    dtype = WIRE_DTYPES[name]
    count = 1
    for d in shape:
        count *= d
    if count * dtype.itemsize != len(data):
        raise ArrayError(
            f"array of dtype {name} and shape {tuple(shape)} needs {count * dtype.itemsize} bytes, data has {len(data)}"
        )
    return np.frombuffer(data, dtype=dtype, count=count).reshape(shape)


def unpack(payload: bytes | bytearray | memoryview, *, max_bytes: int = DEFAULT_MAX_BYTES) -> Any:
    """Decode one msgpack document that must span the whole payload exactly.

    Arrays come back as read-only ndarrays that view `payload` (no copy).
    """
    size = len(payload)
    if size > max_bytes:
        raise PayloadTooLarge(f"payload of {size} bytes exceeds the limit of {max_bytes} bytes")
    if size == 0:
        raise MalformedFrame("empty payload")
    mv = memoryview(payload)
    if mv.format != "B" or mv.ndim != 1:
        mv = mv.cast("B")
    reader = _Reader(mv)
    doc = reader.value(0)
    if reader.pos != size:
        raise MalformedFrame(
            f"{size - reader.pos} trailing bytes after the document (document ends at byte {reader.pos} of {size})"
        )
    return doc
