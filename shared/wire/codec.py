"""Wire framing of splittag messages: a msgpack header with the tensors out of band, decoded without copying.

Framing 2 (what `pack` writes):

    0xC1 | version 2 | 2 zero bytes | u32 LE header length H | H bytes msgpack header | 0-7 zero bytes |
    array data, each array starting 8-byte aligned (relative to the data section), in header order

0xC1 is the one byte msgpack never uses, so a framed payload cannot be mistaken for plain msgpack. In the
header, each array is a msgpack ext (type 1): u8 dtype code, u8 ndim, 6 zero bytes, u64 LE offset into
the data section, then ndim u64 LE sizes. The header is decoded by the msgpack library's C unpacker,
and each array becomes a read-only ndarray viewing the received buffer: decoding costs O(header), not
O(tensor), and the tensor crosses from Zenoh into numpy with only the one copy that `to_bytes()` forces.
The checks: size limit, frame head, header well-formed and spanning exactly H bytes, array dtype/shape
bounds, arrays in order without overlap, inside the payload, and the payload ending with the last one.

Framing 1 (older peers; still decoded, and written by `pack_framing1`): the whole document is msgpack,
arrays are {dtype, shape, data} maps. It is read by a small msgpack reader of our own, because the
library copies `bin` values; ours returns memoryview slices of the buffer. That reader also bounds
nesting depth, refuses duplicate keys and fails fast on huge declared lengths.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping
from typing import Any, Final

import msgpack
import numpy as np
from pydantic import BaseModel

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
    if isinstance(obj, BaseModel):
        # A message's fields, in declaration order: what model_dump gives, without building a copy first
        # (msgpack's C packer walks the dict and calls back here for nested models and arrays).
        return obj.__dict__
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.floating):
        return float(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    raise MalformedFrame(f"cannot encode value of type {type(obj).__name__}")


def pack_framing1(document: Mapping[str, Any]) -> bytes:
    """Framing 1 (older peers): the document as one msgpack value, arrays as {dtype, shape, data} maps."""
    out = msgpack.packb(document, default=_pack_default, use_bin_type=True, strict_types=False)
    assert isinstance(out, bytes)
    return out


FRAME_MAGIC: Final[int] = 0xC1
FRAMING: Final[int] = 2
EXT_ARRAY: Final[int] = 1
ALIGN: Final[int] = 8
_FRAME_HEAD = struct.Struct("<BBxxI")  # magic, framing version, two reserved zero bytes, header length
_RESERVED = slice(2, 4)
_ARRAY_HEAD = struct.Struct("<BB6xQ")
DTYPE_CODES: Final[dict[str, int]] = {name: i for i, name in enumerate(WIRE_DTYPES)}
CODE_DTYPES: Final[dict[int, np.dtype[Any]]] = {i: WIRE_DTYPES[name] for name, i in DTYPE_CODES.items()}
_SHAPES: Final[list[struct.Struct]] = [struct.Struct(f"<{n}Q") for n in range(MAX_NDIM + 1)]
_ZEROS: Final[bytes] = bytes(ALIGN)


def _aligned(n: int) -> int:
    return (n + ALIGN - 1) & ~(ALIGN - 1)


class DataWriter:
    """The data section of a framed payload being written (framings 2 and 3): each array placed 8-byte
    aligned after the previous one, then the frame assembled with one copy of each array."""

    __slots__ = ("arrays", "end", "starts")

    def __init__(self) -> None:
        self.arrays: list[np.ndarray] = []
        self.starts: list[int] = []
        self.end = 0

    def place(self, arr: np.ndarray) -> int:
        """Append a C-contiguous array; its offset in the data section."""
        start = _aligned(self.end)
        self.arrays.append(arr)
        self.starts.append(start)
        self.end = start + arr.nbytes
        return start

    def frame(self, version: int, header: bytes) -> bytes:
        """Frame head, header, padding to 8, the arrays (no data section without arrays)."""
        if not self.arrays:
            return _FRAME_HEAD.pack(FRAME_MAGIC, version, len(header)) + header
        head_len = _FRAME_HEAD.size + len(header)
        parts: list[Any] = [
            _FRAME_HEAD.pack(FRAME_MAGIC, version, len(header)),
            header,
            _ZEROS[: _aligned(head_len) - head_len],
        ]
        pos = 0
        for start, arr in zip(self.starts, self.arrays, strict=True):
            parts.append(_ZEROS[: start - pos])
            if arr.nbytes:
                parts.append(memoryview(arr).cast("B"))  # type: ignore[arg-type]
            pos = start + arr.nbytes
        return b"".join(parts)


def pack(document: Mapping[str, Any]) -> bytes:
    """Serialise a document (dicts, lists, scalars, numpy arrays) in framing 2: one copy of each array."""
    data = DataWriter()

    def default(obj: Any) -> Any:
        if isinstance(obj, np.ndarray):
            name = wire_dtype_name(obj.dtype)
            arr = np.ascontiguousarray(obj, dtype=WIRE_DTYPES[name])
            if arr.ndim > MAX_NDIM:
                raise ArrayError(f"array of {arr.ndim} dimensions; at most {MAX_NDIM} travel")
            start = data.place(arr)
            head = _ARRAY_HEAD.pack(DTYPE_CODES[name], arr.ndim, start) + _SHAPES[arr.ndim].pack(*arr.shape)
            return msgpack.ExtType(EXT_ARRAY, head)
        return _pack_default(obj)

    header = msgpack.packb(document, default=default, use_bin_type=True, strict_types=False)
    return data.frame(FRAMING, header)


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


class DataSection:
    """The data section of one framed payload being read (framings 2 and 3): each array a view of it,
    in header order, 8-byte aligned, without overlap, inside the payload, which must end with the last
    one (`finish`)."""

    __slots__ = ("count", "data_size", "data_start", "end", "head_end", "mv", "size")

    def __init__(self, mv: memoryview, head_end: int) -> None:
        self.mv = mv
        self.size = size = len(mv)
        self.head_end = head_end
        self.data_start = min(_aligned(head_end), size)
        self.data_size = size - self.data_start
        self.end = 0
        self.count = 0

    def view(self, dtype: np.dtype[Any], shape: tuple[int, ...] | list[int], start: int) -> np.ndarray:
        """The next array: `shape` of `dtype` at `start`, a view of the payload."""
        count = self._claim(dtype, shape, start)
        try:
            arr = np.frombuffer(self.mv, dtype=dtype, count=count, offset=self.data_start + start).reshape(shape)
        except ValueError as exc:  # a zero-size shape whose other sizes numpy cannot hold
            raise ArrayError(f"array shape {repr(list(shape))[:120]}: {exc}") from None
        return arr

    def claim(self, dtype: np.dtype[Any], shape: tuple[int, ...] | list[int], start: int) -> None:
        """The checks of `view` without making the array (the same verdicts: an empty array is made)."""
        if not self._claim(dtype, shape, start):
            _reshape_empty(dtype, shape)

    def _claim(self, dtype: np.dtype[Any], shape: tuple[int, ...] | list[int], start: int) -> int:
        count = 1
        for d in shape:
            count *= d
        nbytes = count * dtype.itemsize
        if start < self.end or start % ALIGN:
            raise ArrayError(
                f"array of dtype {dtype.name} and shape {tuple(shape)} at offset {start}: arrays must follow each "
                f"other {ALIGN}-byte aligned (the previous one ends at {self.end})"
            )
        if start + nbytes > self.data_size:
            raise MalformedFrame(
                f"truncated payload: array of dtype {dtype.name} and shape {tuple(shape)} needs bytes "
                f"{start}..{start + nbytes} of the data section, which has {self.data_size}"
            )
        self.end = start + nbytes
        self.count += 1
        return count

    def finish(self) -> None:
        """The payload ends with the last array (or, without arrays, with the header: no padding)."""
        end = self.data_start + self.end if self.count else self.head_end
        if end != self.size:
            raise MalformedFrame(
                f"{self.size - end} trailing bytes after the document (document ends at byte {end} of {self.size})"
            )


def _reshape_empty(dtype: np.dtype[Any], shape: tuple[int, ...] | list[int]) -> None:
    """What numpy says of an empty array of this shape (sizes it cannot hold next to a zero are refused)."""
    try:
        np.empty(0, dtype).reshape(shape)
    except ValueError as exc:
        raise ArrayError(f"array shape {repr(list(shape))[:120]}: {exc}") from None


def open_frame(mv: memoryview) -> tuple[int, memoryview, DataSection]:
    """(framing version, header bytes, data section) of a 0xC1 frame whose head and header bounds hold."""
    size = len(mv)
    if size < _FRAME_HEAD.size:
        raise MalformedFrame(f"truncated payload: {size} bytes, a 0xc1 frame head needs {_FRAME_HEAD.size}")
    _, version, header_len = _FRAME_HEAD.unpack_from(mv)
    if mv[_RESERVED] != b"\0\0":  # kept zero, so that a later framing may use them (an integrator's note)
        raise MalformedFrame(
            f"bytes 2-3 of the frame head are reserved and must be zero, got {bytes(mv[_RESERVED]).hex(' ')}"
        )
    head_end = _FRAME_HEAD.size + header_len
    if head_end > size:
        raise MalformedFrame(
            f"truncated payload: the header needs {header_len} bytes, {size - 8} follow the frame head"
        )
    return version, mv[_FRAME_HEAD.size : head_end], DataSection(mv, head_end)


class _ArrayViews:
    """ext_hook of one framing-2 payload: each array ext becomes a view of the data section, in order."""

    __slots__ = ("section",)

    def __init__(self, section: DataSection) -> None:
        self.section = section

    def __call__(self, code: int, ext: bytes) -> np.ndarray:
        if code != EXT_ARRAY:
            raise MalformedFrame(f"unknown msgpack ext type {code} in the header (arrays are type {EXT_ARRAY})")
        if len(ext) < _ARRAY_HEAD.size:
            raise ArrayError(f"array header of {len(ext)} bytes, needs at least {_ARRAY_HEAD.size}")
        dcode, ndim, start = _ARRAY_HEAD.unpack_from(ext)
        dtype = CODE_DTYPES.get(dcode)
        if dtype is None:
            raise ArrayError(f"array dtype code {dcode} is not one of {DTYPE_CODES}")
        if ndim > MAX_NDIM or len(ext) != _ARRAY_HEAD.size + 8 * ndim:
            raise ArrayError(f"array header of {len(ext)} bytes for {ndim} dimensions (at most {MAX_NDIM})")
        shape = _SHAPES[ndim].unpack_from(ext, _ARRAY_HEAD.size)
        if any(d > MAX_DIM for d in shape):
            text = repr(list(shape))[:120]
            raise ArrayError(f"array shape {text} is not a list of at most {MAX_NDIM} sizes in 0..{MAX_DIM}")
        return self.section.view(dtype, shape, start)


def _unpack_framed(mv: memoryview) -> Any:
    version, header, section = open_frame(mv)
    if version != FRAMING:
        raise MalformedFrame(
            f"framing version {version} is not supported here (this untyped reader reads 1 and {FRAMING}; "
            "framing 3 is read with the message types, by shared.wire.messages.decode)"
        )
    try:
        doc = msgpack.unpackb(header, ext_hook=_ArrayViews(section), raw=False, strict_map_key=True)
    except WireError:
        raise
    except msgpack.ExtraData as exc:
        raise MalformedFrame(f"the msgpack header ends before its declared {len(header)} bytes") from exc
    except (ValueError, TypeError, msgpack.StackError, msgpack.FormatError) as exc:
        raise MalformedFrame(f"malformed msgpack header: {exc}") from exc
    section.finish()
    return doc


def unpack(payload: bytes | bytearray | memoryview, *, max_bytes: int = DEFAULT_MAX_BYTES) -> Any:
    """Decode one document that must span the whole payload exactly (framing 2, or framing 1 from
    older peers). Arrays come back as read-only ndarrays that view `payload` (no copy)."""
    size = len(payload)
    if size > max_bytes:
        raise PayloadTooLarge(f"payload of {size} bytes exceeds the limit of {max_bytes} bytes")
    if size == 0:
        raise MalformedFrame("empty payload")
    mv = memoryview(payload).toreadonly()  # arrays view it read-only, a bytearray payload included
    if mv.format != "B" or mv.ndim != 1:
        mv = mv.cast("B")
    if mv[0] == FRAME_MAGIC:
        return _unpack_framed(mv)
    reader = _Reader(mv)
    doc = reader.value(0)
    if reader.pos != size:
        raise MalformedFrame(
            f"{size - reader.pos} trailing bytes after the document (document ends at byte {reader.pos} of {size})"
        )
    return doc
