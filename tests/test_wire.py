"""Wire format: round trips, golden bytes, typed errors for every kind of bad input, fuzzing."""

from __future__ import annotations

import struct
from collections.abc import Callable
from pathlib import Path

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import Field

from shared.wire.codec import (
    WIRE_DTYPES,
    ArrayError,
    MalformedFrame,
    PayloadTooLarge,
    SchemaError,
    WireError,
    pack,
    pack_framing1,
    unpack,
)
from shared.wire.messages import (
    LEGACY_SCHEMAS,
    SCHEMAS,
    WRITE_FRAMING,
    Features,
    Frame,
    MapTagV1,
    MapTagV2,
    Message,
    SplitConfig,
    TagFeature,
    TagFeatureV1,
    TagFeatureV2,
    TagFeatureV3,
    TagMap,
    TagPoses,
    TagPoseV2,
    TagPoseV3,
    View,
    decode,
    decode_view,
    encode,
    framing_of,
)
from tests.examples import INTRINSICS, assert_messages_equal, example_messages, golden_name, golden_names

GOLDEN = Path(__file__).parent / "golden"
# The per-tag model each legacy version's tags had.
LEGACY_TAG_TYPES: dict[str, type[TagFeatureV1] | type[TagPoseV2] | type[MapTagV1] | type[MapTagV2]] = {
    "splittag/Features/v1": TagFeatureV1,
    "splittag/Features/v2": TagFeatureV2,
    "splittag/Features/v3": TagFeatureV3,
    "splittag/TagPoses/v1": TagPoseV2,
    "splittag/TagPoses/v2": TagPoseV2,
    "splittag/TagPoses/v3": TagPoseV3,
    "splittag/TagMap/v1": MapTagV1,
    "splittag/TagMap/v2": MapTagV2,
}
EXAMPLES = example_messages()
# Legacy versions with the current fields but fewer allowed values (CameraPose/v1: no "bridged").
NARROWER_LEGACY_SCHEMAS = frozenset({"splittag/CameraPose/v1"})


def test_every_schema_has_an_example() -> None:
    assert set(EXAMPLES) == set(SCHEMAS)


@pytest.mark.parametrize("schema", sorted(EXAMPLES))
def test_round_trip(schema: str) -> None:
    msg = EXAMPLES[schema]
    out = decode(encode(msg), type(msg))
    assert_messages_equal(msg, out)


@pytest.mark.parametrize("schema", sorted(EXAMPLES))
def test_golden_bytes(schema: str) -> None:
    """Encoding is stable: a change here breaks every deployed peer (bump the version instead)."""
    golden = (GOLDEN / golden_name(schema)).read_bytes()
    assert encode(EXAMPLES[schema]) == golden
    assert_messages_equal(decode(golden), EXAMPLES[schema])


def test_every_golden_file_names_a_current_or_legacy_schema() -> None:
    """Each golden file is one the tests read: a current schema's (every framing) or a legacy version's
    (framing1/). A file of a version that no longer exists, or left in framing2/ or framing3/ when its
    version was superseded, is stale: nothing tests it, and it passed unnoticed."""
    on_disk = {path.relative_to(GOLDEN).as_posix() for path in GOLDEN.glob("framing*/*")}
    stale = sorted(on_disk - golden_names())
    assert not stale, f"golden files of no current or legacy schema (delete them; docs/wire.md): {stale}"


@pytest.mark.parametrize("schema", sorted(EXAMPLES))
def test_framing1_bytes_of_older_peers_still_decode_and_can_still_be_written(schema: str) -> None:
    """Framing 1 (plain msgpack, before the tensors went out of band): frozen bytes decode to the same
    message, and `encode(framing=1)` still writes them byte for byte (for a peer that has not upgraded)."""
    golden = (GOLDEN / golden_name(schema, framing=1)).read_bytes()
    assert_messages_equal(decode(golden), EXAMPLES[schema])
    assert encode(EXAMPLES[schema], framing=1) == golden


@pytest.mark.parametrize("schema", sorted(EXAMPLES))
def test_a_reply_goes_in_the_askers_framing_and_garbage_gets_ours(schema: str) -> None:
    """framing_of (the echo's and the split queryable's reply framing): each framing's frozen bytes are
    recognised; a payload that is no framing at all gets the current one, not the oldest peer's (a
    trial's garbage probes were answered in framing 1)."""
    for framing in (1, 2, 3):
        assert framing_of((GOLDEN / golden_name(schema, framing=framing)).read_bytes()) == framing
    assert framing_of(encode(EXAMPLES[schema])) == WRITE_FRAMING
    for garbage in (b"x", b"\x00" * 64, b"GET / HTTP/1.1\r\n", b"\x81\xa1a\x01", b"\x92\x01\x02", b""):
        assert framing_of(garbage) == WRITE_FRAMING, garbage


@pytest.mark.parametrize("schema", sorted(LEGACY_SCHEMAS))
def test_legacy_golden_bytes_still_decode_as_the_current_version(schema: str) -> None:
    """Bytes of an older version (frozen golden file, never regenerated) decode as the current message,
    with the fields that version lacked set to None, and pass an `expected` of the current type."""
    golden = (GOLDEN / golden_name(schema, framing=1)).read_bytes()
    msg = decode(golden)
    name = schema.rpartition("/")[0]
    [example] = [m for s, m in EXAMPLES.items() if s.rpartition("/")[0] == name]
    assert type(msg) is type(example) and schema != msg.SCHEMA
    lacking: dict[str, object] = {
        name: None for name in type(example).model_fields if name not in LEGACY_SCHEMAS[schema].model_fields
    }
    expected = example.model_copy(update=lacking)
    if isinstance(example, Features | TagPoses | TagMap):  # older tags lack fields (tracked, edge width, ...)
        tag_type = type(example.tags[0])
        legacy_tag_fields = LEGACY_TAG_TYPES[schema].model_fields
        tag_lacking: dict[str, object] = {
            name: (False if name in ("tracked", "bridged") else None)
            for name in tag_type.model_fields
            if name not in legacy_tag_fields
        }
        lacking |= {f"tags[].{name}": value for name, value in tag_lacking.items()}
        tags = [t.model_copy(update=tag_lacking) for t in example.tags]
        expected = expected.model_copy(update={"tags": tags})
    # A legacy schema lacks at least one field of the current one, or allows fewer values of one.
    assert lacking or schema in NARROWER_LEGACY_SCHEMAS
    assert_messages_equal(msg, expected)
    assert type(decode(golden, type(example))) is type(example)
    with pytest.raises(SchemaError, match="where"):
        decode(golden, Frame)


@pytest.mark.parametrize(
    ("tracked", "proposer", "reason"),
    [
        (False, "tracker", "tracked=False but proposer='tracker'"),
        (True, "aruco", "tracked=True but"),
        (False, "sift", "proposer"),
    ],
)
def test_a_tag_whose_proposer_is_unknown_or_contradicts_tracked_is_refused(
    tracked: bool, proposer: str, reason: str
) -> None:
    """Features/v4 and TagPoses/v4 carry who found each tag: a name outside the list, or one that
    disagrees with `tracked` (tracked exactly when the tracker), is refused with what was wrong."""
    for schema in ("splittag/Features/v4", "splittag/TagPoses/v4"):
        msg = EXAMPLES[schema]
        assert isinstance(msg, Features | TagPoses)
        bad_tag = msg.tags[0].model_copy(update={"tracked": tracked, "proposer": proposer})  # unvalidated
        payload = encode(msg.model_copy(update={"tags": [bad_tag]}))
        with pytest.raises(SchemaError, match=reason):
            decode(payload, type(msg))


def test_a_bridged_camera_pose_is_refused_by_the_v1_schema_and_kept_by_v2() -> None:
    """The version bump is needed: v1 peers' model cannot hold the new status."""
    from pydantic import ValidationError

    from shared.wire.messages import CameraPose, CameraPoseV1

    bridged = EXAMPLES[CameraPose.SCHEMA].model_copy(update={"status": "bridged"})
    assert decode(encode(bridged), CameraPose).status == "bridged"
    with pytest.raises(ValidationError):
        CameraPoseV1.model_validate({**bridged.model_dump(exclude={"covariance_world"}), "status": "bridged"})


@pytest.mark.parametrize(
    ("change", "reason"),
    [
        (lambda c: c + np.triu(np.full((6, 6), 1e-3), 1), "not symmetric"),
        (lambda c: c - np.diag(np.full(6, 1.0)), "negative variance"),
        (lambda c: np.where(np.eye(6, dtype=bool), np.nan, c), "non-finite"),
        (lambda c: c[:3, :3].copy(), "shape"),
    ],
)
def test_a_camera_pose_covariance_must_be_one(change: Callable[[np.ndarray], np.ndarray], reason: str) -> None:
    """CameraPose/v3's covariance_world: a finite symmetric 6x6 without negative variances, or refused."""
    from shared.wire.messages import CameraPose

    good = EXAMPLES[CameraPose.SCHEMA]
    assert isinstance(good, CameraPose) and good.covariance_world is not None
    body = {**good.model_dump(), "covariance_world": change(good.covariance_world)}
    with pytest.raises(SchemaError, match=reason):
        decode(pack({"schema": CameraPose.SCHEMA, "body": body}), CameraPose)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("position_sigma_m", 0.0),
        ("position_sigma_m", float("nan")),
        ("rotation_sigma_deg", -1.0),
        ("rotation_sigma_deg", 181.0),
    ],
)
def test_a_map_tags_uncertainty_must_be_a_real_one(field: str, value: float) -> None:
    """TagMap/v3's per-tag sigmas: finite, positive, rotation at most 180 deg, or the message is refused."""
    good = EXAMPLES[TagMap.SCHEMA]
    assert isinstance(good, TagMap)
    body = good.model_dump()
    body["tags"][1][field] = value
    with pytest.raises(SchemaError, match=field):
        decode(pack({"schema": TagMap.SCHEMA, "body": body}), TagMap)


@pytest.mark.parametrize("dtype", sorted(WIRE_DTYPES))
def test_array_round_trip_every_dtype(dtype: str) -> None:
    rng = np.random.default_rng(0)
    arr = (rng.standard_normal((3, 5, 7)) * 50).astype(WIRE_DTYPES[dtype])
    out = unpack(pack({"a": arr, "empty": np.zeros((0, 4), WIRE_DTYPES[dtype])}))
    assert out["a"].dtype == arr.dtype and out["a"].tobytes() == arr.tobytes()
    assert out["empty"].shape == (0, 4)


def test_decoded_tensor_views_the_payload_without_copy() -> None:
    tensor = np.random.default_rng(1).standard_normal((64, 32, 32)).astype(np.float16)
    msg = Features(
        **{
            **EXAMPLES[Features.SCHEMA].model_dump(),
            "tags": [
                TagFeature(
                    tag_id=1,
                    decision_margin=1.0,
                    hamming=0,
                    corners_px=np.zeros((4, 2), np.float32),
                    roi_to_image=np.eye(3),
                    tensor=tensor,
                    edge_width_px=1.5,
                    tracked=False,
                )
            ],
        }
    )
    payload = encode(msg)
    out = decode(payload, Features)
    got = out.tags[0].tensor
    assert np.shares_memory(got, np.frombuffer(payload, np.uint8))
    assert not got.flags.writeable
    assert got.tobytes() == tensor.tobytes()


@pytest.mark.parametrize("dtype", [object, np.complex64, np.int64, np.bool_])
def test_disallowed_dtypes_are_refused_at_encode(dtype: type) -> None:
    with pytest.raises(ArrayError, match="cannot be sent"):
        pack({"a": np.zeros(3, dtype=dtype)})


def _body(schema: str) -> dict:
    return unpack(encode(EXAMPLES[schema], framing=2))["body"]


def _patched(schema: str, **changes: object) -> bytes:
    """Framing 1 (plain msgpack), so that array maps written by hand reach the framing-1 array checks."""
    body = {k: v for k, v in _body(schema).items()}
    body.update(changes)
    return pack_framing1({"schema": schema, "body": body})


@pytest.mark.parametrize(
    ("payload", "error", "match"),
    [
        (b"", MalformedFrame, "empty payload"),
        (encode(EXAMPLES[Frame.SCHEMA])[:-3], MalformedFrame, "truncated"),
        (encode(EXAMPLES[Frame.SCHEMA]) + b"\x00", MalformedFrame, "1 trailing bytes"),
        (b"\xc1", MalformedFrame, "0xc1"),
        # the two bytes after the version are reserved: an integrator's flag there was read as nothing
        (b"\xc1\x03\x01\x00" + encode(EXAMPLES[Frame.SCHEMA])[4:], MalformedFrame, "reserved and must be zero"),
        (b"\xc1\x02\x00\xff" + encode(EXAMPLES[Frame.SCHEMA], framing=2)[4:], MalformedFrame, "got 00 ff"),
        (b"\xc1\x09" + encode(EXAMPLES[Frame.SCHEMA])[2:], MalformedFrame, "framing version 9 is unknown"),
        (msgpack.packb([1, 2]), MalformedFrame, "envelope"),
        (
            pack({"schema": "splittag/Frame/v2", "body": {}}),
            SchemaError,
            "unsupported version 'v2'",
        ),
        (pack({"schema": "other/Thing/v1", "body": {}}), SchemaError, "unknown schema id"),
        (pack({"schema": 3, "body": {}}), SchemaError, "must be a string"),
        (pack({"schema": "splittag/Frame/v1", "body": {"seq": 1}}), SchemaError, "missing fields"),
        (_patched(Frame.SCHEMA, seq="3"), SchemaError, "seq"),
        (_patched(Frame.SCHEMA, extra=1), SchemaError, "extra"),
        (
            _patched(Frame.SCHEMA, image={"dtype": "uint8", "shape": [6, 8], "data": b"\x00" * 47}),
            ArrayError,
            "needs 48 bytes, data has 47",
        ),
        (
            _patched(Frame.SCHEMA, image={"dtype": "object", "shape": [1], "data": b"\x00"}),
            ArrayError,
            "'object'",
        ),
        (
            _patched(Frame.SCHEMA, image={"dtype": "uint8", "shape": [-1], "data": b""}),
            ArrayError,
            "shape",
        ),
        (_patched(Frame.SCHEMA, image=np.zeros((6, 9), np.uint8)), SchemaError, "image is 9x6"),
        (_patched(Frame.SCHEMA, image=np.zeros((6, 8), np.float32)), SchemaError, "not allowed"),
        (_patched(SplitConfig.SCHEMA, k=8), SchemaError, "less than or equal to 7"),
    ],
)
def test_bad_input_gives_typed_error_saying_what_was_received(
    payload: bytes, error: type[WireError], match: str
) -> None:
    with pytest.raises(error, match=match):
        decode(payload)


def test_non_finite_values_are_rejected() -> None:
    """In every small array and scalar; the split tensor is checked by the edge (its keypoints), not here."""
    body = _body(Features.SCHEMA)
    tags = [dict(t) for t in body["tags"]]
    bad = np.array(tags[0]["corners_px"], copy=True)
    bad.flat[3] = np.nan
    tags[0]["corners_px"] = bad
    with pytest.raises(SchemaError, match="1 non-finite"):
        decode(pack({"schema": Features.SCHEMA, "body": {**body, "tags": tags}}))
    with pytest.raises(SchemaError, match="finite"):
        decode(_patched(Features.SCHEMA, robot_compute_secs=float("inf")))


def test_size_limit() -> None:
    payload = encode(EXAMPLES[Frame.SCHEMA])
    with pytest.raises(PayloadTooLarge, match=f"payload of {len(payload)} bytes"):
        decode(payload, max_bytes=len(payload) - 1)
    decode(payload, max_bytes=len(payload))


def test_unexpected_type_is_refused() -> None:
    with pytest.raises(SchemaError, match="where splittag/Features/v4 was expected"):
        decode(encode(EXAMPLES[Frame.SCHEMA]), Features)


def test_deep_nesting_is_refused() -> None:
    doc: object = 1
    for _ in range(40):
        doc = [doc]
    with pytest.raises(MalformedFrame, match="nesting"):
        unpack(msgpack.packb(doc))


def test_huge_declared_container_fails_fast() -> None:
    with pytest.raises(MalformedFrame, match="exceeds the payload"):
        unpack(b"\xdd\xff\xff\xff\xff\x01")


def test_intrinsics_mismatch_at_construction() -> None:
    with pytest.raises(ValueError, match="image is 9x6"):
        Frame(
            robot_id="r",
            seq=0,
            capture_nanos=0,
            intrinsics=INTRINSICS,
            image=np.zeros((6, 9), np.uint8),
        )


_VALID = [encode(m, framing=f) for m in EXAMPLES.values() for f in (2, 3)]


def _decode_only_typed_errors(payload: bytes) -> None:
    """Bad bytes are a WireError, never another exception; decode_view refuses them the same way."""
    verdicts = []
    for read in (decode, decode_view):
        try:
            read(payload)
            verdicts.append("ok")
        except WireError as exc:
            verdicts.append(type(exc).__name__)
    assert verdicts[0] == verdicts[1], verdicts


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=512))
def test_fuzz_random_bytes(payload: bytes) -> None:
    _decode_only_typed_errors(payload)


@settings(max_examples=600, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.sampled_from(_VALID),
    st.lists(st.tuples(st.integers(0, 10_000), st.integers(0, 255)), min_size=1, max_size=6),
    st.integers(0, 10_000),
    st.binary(max_size=16),
)
def test_fuzz_mutated_valid_messages(payload: bytes, flips: list[tuple[int, int]], cut: int, insert: bytes) -> None:
    buf = bytearray(payload)
    for pos, val in flips:
        buf[pos % len(buf)] = val
    _decode_only_typed_errors(bytes(buf))
    _decode_only_typed_errors(bytes(buf[: cut % (len(buf) + 1)]))
    at = cut % (len(buf) + 1)
    _decode_only_typed_errors(bytes(buf[:at]) + insert + bytes(buf[at:]))


EVIL_ARRAY = {"dtype": "uint8", "shape": [0, 2**63], "data": b""}  # right byte count (none), impossible shape


@pytest.mark.parametrize(
    ("schema", "path"),
    [
        ("splittag/Frame/v1", ("image",)),
        ("splittag/Features/v4", ("tags", 0, "tensor")),
        ("splittag/TagPoses/v4", ("tags", 0, "keypoints_px")),
    ],
)
def test_an_impossible_shape_is_a_wire_error_not_a_crash(schema: str, path: tuple[str | int, ...]) -> None:
    """A 37-byte array {uint8, [0, 2**63], b""} used to escape the decoder as numpy's ValueError."""
    doc = msgpack.unpackb(encode(EXAMPLES[schema], framing=1), raw=False)
    node = doc["body"]
    for step in path[:-1]:
        node = node[step]
    node[path[-1]] = EVIL_ARRAY
    with pytest.raises(ArrayError, match="sizes in 0"):
        decode(msgpack.packb(doc, use_bin_type=True))


@pytest.mark.parametrize(
    ("schema", "field", "value"),
    [
        ("splittag/ComputeProfile/v2", "frame_interval_ms", float("nan")),
        ("splittag/ComputeProfile/v2", "frame_interval_ms", -33.3),
        ("splittag/ComputeProfile/v2", "frame_interval_ms", float("inf")),
        ("splittag/ComputeProfile/v2", "period_ms_by_k", [1.0] * 7),
        ("splittag/ComputeProfile/v2", "period_ms_by_k", [1.0] * 7 + [-1.0]),
        ("splittag/ControllerState/v2", "achieved_ms_by_k", [None] * 7 + [float("nan")]),
        ("splittag/ControllerState/v2", "frame_share_by_k", [0.5] * 9),
        ("splittag/ControllerState/v2", "min_frame_share", -0.1),
    ],
)
def test_impossible_throughput_fields_are_refused(schema: str, field: str, value: object) -> None:
    """The camera's interval and the per-cut periods, shares and intervals the controller decides on:
    finite, not negative, one per cut (what the controller would otherwise divide by or index)."""
    doc = msgpack.unpackb(encode(EXAMPLES[schema], framing=1), raw=False)
    doc["body"][field] = value
    with pytest.raises(WireError, match=field):
        decode(pack_framing1(doc))


@pytest.mark.parametrize("width", [float("nan"), float("inf"), -1.0, 1e9])
def test_an_impossible_edge_width_is_refused(width: float) -> None:
    """Features v2's per-tag edge width (the fusion's blur measure) must be finite and 0..1000 px."""
    doc = msgpack.unpackb(encode(EXAMPLES[Features.SCHEMA], framing=1), raw=False)
    doc["body"]["tags"][0]["edge_width_px"] = width
    with pytest.raises(WireError, match="edge_width_px"):
        decode(pack_framing1(doc), Features)


# ---- framing 2: the header is msgpack, the arrays follow it out of band --------------------------


def _frame(header: bytes, data: bytes = b"") -> bytes:
    """A framing-2 payload assembled by hand (frame head, header, padding to 8, data)."""
    head = struct.pack("<BBxxI", 0xC1, 2, len(header)) + header
    return head + bytes(-len(head) % 8 if data else 0) + data


def _array_ext(dtype_code: int, shape: tuple[int, ...], offset: int) -> msgpack.ExtType:
    return msgpack.ExtType(
        1, struct.pack("<BB6xQ", dtype_code, len(shape), offset) + struct.pack(f"<{len(shape)}Q", *shape)
    )


def test_framing2_arrays_are_8_byte_aligned_views_in_header_order() -> None:
    doc = {"a": np.arange(3, dtype=np.uint8), "b": np.arange(4, dtype=np.float64), "c": [np.zeros((0, 2), np.float32)]}
    payload = pack(doc)
    out = unpack(payload)
    base = np.frombuffer(payload, np.uint8)
    for name in ("a", "b"):
        assert np.shares_memory(out[name], base) and not out[name].flags.writeable
        assert (out[name].__array_interface__["data"][0] - base.__array_interface__["data"][0]) % 8 == 0
    assert out["b"].tolist() == [0.0, 1.0, 2.0, 3.0] and out["c"][0].shape == (0, 2)


U8 = 3  # dtype code of uint8 (position in WIRE_DTYPES)


@pytest.mark.parametrize(
    ("payload", "error", "match"),
    [
        (b"\xc1\x02\x00\x00", MalformedFrame, "0xc1 frame head needs 8"),
        (_frame(b"")[:1] + b"\x03" + _frame(b"")[2:], MalformedFrame, "framing version 3"),
        (struct.pack("<BBxxI", 0xC1, 2, 50) + msgpack.packb({"a": 1}), MalformedFrame, "truncated"),
        (_frame(msgpack.packb({"a": 1}) + b"\x01"), MalformedFrame, "ends before"),
        (_frame(b"\xc1"), MalformedFrame, "malformed msgpack header"),
        (_frame(msgpack.packb({"a": msgpack.ExtType(7, b"")})), MalformedFrame, "ext type 7"),
        (_frame(msgpack.packb({"a": _array_ext(99, (3,), 0)}), bytes(8)), ArrayError, "dtype code 99"),
        (_frame(msgpack.packb({"a": _array_ext(U8, (0, 2**63), 0)}), bytes(8)), ArrayError, "sizes in 0"),
        (_frame(msgpack.packb({"a": _array_ext(U8, (16,), 0)}), bytes(8)), MalformedFrame, "truncated"),
        (_frame(msgpack.packb({"a": _array_ext(U8, (8,), 4)}), bytes(16)), ArrayError, "aligned"),
        (
            _frame(msgpack.packb({"a": _array_ext(U8, (8,), 8), "b": _array_ext(U8, (8,), 0)}), bytes(16)),
            ArrayError,
            "previous one ends at 16",
        ),
        (_frame(msgpack.packb({"a": _array_ext(U8, (8,), 0)}), bytes(9)), MalformedFrame, "1 trailing bytes"),
        (_frame(msgpack.packb({"a": 1})) + b"\x00", MalformedFrame, "1 trailing bytes"),
    ],
)
def test_framing2_bad_input_gives_typed_errors(payload: bytes, error: type[WireError], match: str) -> None:
    with pytest.raises(error, match=match):
        unpack(payload)


@pytest.mark.parametrize("precision", ["fp32", "int8"])
def test_a_non_finite_split_tensor_is_refused_by_the_edge_not_the_wire(precision: str) -> None:
    """Decoding is O(header): a NaN in a megabyte feature map passes the wire; the edge refuses the frame
    with a message naming the tag and the cut. An fp32 tail turns the NaN into non-finite keypoints; an
    int8 tail quantises it into finite, plausible ones (a trial found it in the exported int8 tails; the
    services' int8 did the same), so at int8 the edge checks the cut tensor before the tail."""
    from shared.model.runtime import load_split_net
    from shared.perception.split import edge_step
    from shared.vision.tagmap import TagMapFile
    from shared.wire.cuts import FeatureShapeError

    features = EXAMPLES[Features.SCHEMA]
    assert isinstance(features, Features)
    tag = features.tags[0]
    from shared.wire.cuts import CUTS

    bad = np.zeros(CUTS[features.split_k].shape, np.float16)
    bad.flat[0] = np.nan
    msg = features.model_copy(update={"tags": [tag.model_copy(update={"tensor": bad})]})
    received = decode(encode(msg), Features)
    with pytest.raises(FeatureShapeError, match=rf"tag\(s\) \[{tag.tag_id}\].*cut-{msg.split_k}"):
        edge_step(
            received,
            net=load_split_net(Path(__file__).resolve().parent.parent / "models", precision),  # type: ignore[arg-type]
            tag_map=TagMapFile(default_size_m=0.2),
            receive_nanos=1,
            previous_receive_nanos=0,
            payload_bytes=1,
        )


@pytest.mark.parametrize("big", [1e200, -1e300, 1.7e308])
def test_a_homography_with_a_huge_entry_is_a_schema_error_not_an_overflow(big: float) -> None:
    """Found by the mutation fuzzer: a flipped exponent made one homography entry ~1e200 and the
    invertibility check cubed it (OverflowError escaped decode). Scaled first, it is a typed refusal."""
    features = EXAMPLES["splittag/Features/v4"]
    assert isinstance(features, Features)
    h = np.eye(3)
    h[0, 1] = big
    tag = features.tags[0].model_copy(update={"roi_to_image": h})
    payload = encode(features.model_copy(update={"tags": [tag]}))
    with pytest.raises(SchemaError, match="invertible"):
        decode(payload)


# ---- framing 3: a positional header whose wire types are compiled from the models ------------------


@pytest.mark.parametrize("schema", sorted(EXAMPLES))
def test_framing2_bytes_of_older_peers_still_decode_and_can_still_be_written(schema: str) -> None:
    """Framing 2 (named msgpack header, tensors out of band): frozen bytes decode to the same message,
    and `encode(framing=2)` still writes them byte for byte (for a peer that has not upgraded)."""
    golden = (GOLDEN / golden_name(schema, framing=2)).read_bytes()
    assert_messages_equal(decode(golden), EXAMPLES[schema])
    assert encode(EXAMPLES[schema], framing=2) == golden


@pytest.mark.parametrize("schema", sorted(EXAMPLES))
def test_framing3_is_smaller_and_its_arrays_are_read_only(schema: str) -> None:
    """No field names travel: every message is smaller than in framing 2; decoded arrays (inline ones
    copied out of the header, the others viewing the payload) are read-only either way."""
    msg = EXAMPLES[schema]
    assert len(encode(msg)) < len(encode(msg, framing=2))
    out = decode(encode(msg))
    arrays = [v for v in _leaves(out.model_dump()) if isinstance(v, np.ndarray)]
    assert all(not a.flags.writeable for a in arrays)


def _leaves(x: object) -> list[object]:
    if isinstance(x, dict):
        return [leaf for v in x.values() for leaf in _leaves(v)]
    if isinstance(x, list):
        return [leaf for v in x for leaf in _leaves(v)]
    return [x]


def _paths(model: object, prefix: tuple[str | int, ...] = ()) -> list[tuple[str | int, ...]]:
    """Every field of a message, its nested models' and its first list entry's."""
    out: list[tuple[str | int, ...]] = []
    for name in type(model).model_fields:  # type: ignore[attr-defined]
        value = getattr(model, name)
        out.append((*prefix, name))
        if hasattr(type(value), "model_fields"):
            out += _paths(value, (*prefix, name))
        elif isinstance(value, list) and value and hasattr(type(value[0]), "model_fields"):
            out += _paths(value[0], (*prefix, name, 0))
    return out


def _replace(model: object, path: tuple[str | int, ...], value: object) -> object:
    """A copy of `model` with the field at `path` set to `value`, unvalidated (as a bad peer sends it)."""
    head, *rest = path
    if not rest:
        return model.model_copy(update={head: value})  # type: ignore[attr-defined]
    child = getattr(model, str(head))
    if isinstance(rest[0], int):
        items = list(child)
        items[rest[0]] = _replace(items[rest[0]], tuple(rest[1:]), value) if rest[1:] else value
        return model.model_copy(update={head: items})  # type: ignore[attr-defined]
    return model.model_copy(update={head: _replace(child, tuple(rest), value)})  # type: ignore[attr-defined]


_PATHS = [(schema, path) for schema, msg in EXAMPLES.items() for path in _paths(msg)]
_TRICKY = [
    -1, 0, 1, 7, 8, 2**40, 2**63 - 1, -(2**63), 1.5, -0.0, 3.5e38, 1e300, float("nan"), float("inf"),
    float("-inf"), True, None, "", "robot_1", "abc\n", "a" * 65, "fp16", "sift", "tracker", "lines",
    [], [1.0] * 8, [0.0, -1.0], np.zeros((4, 2), np.float32), np.full((4, 2), np.nan, np.float32),
    np.zeros((4, 2), np.float64), np.eye(3), np.zeros((3, 3)), np.full((3, 3), 1e200), np.eye(4),
    np.zeros((16, 2), np.float32), np.zeros((6, 9), np.uint8), np.zeros((2, 2, 2, 2), np.float16),
    np.zeros(5, np.int8), np.eye(6) * -1.0,
]  # fmt: skip


def _verdict(payload: bytes) -> tuple[str, object]:
    try:
        return "ok", decode(payload).model_dump()
    except WireError as exc:
        return "refused", type(exc).__name__


def _view_verdict(payload: bytes) -> tuple[str, object]:
    try:
        view: View[Message] = decode_view(payload)
    except WireError as exc:
        return "refused", type(exc).__name__
    return "ok", view.model().model_dump()


@settings(max_examples=1500, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.sampled_from(_PATHS), st.sampled_from(_TRICKY))
def test_framing3_refuses_and_accepts_exactly_what_framing2_does(where: tuple[str, tuple], value: object) -> None:
    """The compiled header checks against pydantic's: one field of a valid message set to a tricky value
    (out of range, NaN, wrong type, wrong shape or dtype, a pattern's trailing newline, an unknown
    literal, a singular homography...) is refused by both framings or decodes to the same message."""
    schema, path = where
    bad = _replace(EXAMPLES[schema], path, value)
    payloads = []
    for framing in (2, 3):
        try:
            payloads.append(encode(bad, framing=framing))  # type: ignore[arg-type]
        except (WireError, TypeError, ValueError, OverflowError):
            return  # a value the encoders cannot write at all is not a wire case
    two, three = (_verdict(p) for p in payloads)
    assert two[0] == three[0], (path, value, two, three)
    view = _view_verdict(payloads[1])  # the view's checks (on the wire struct) against the model's
    assert view[0] == three[0] and (view[0] == "ok" or view[1] == three[1]), (path, value, view, three)
    if two[0] == "ok":
        assert_messages_equal(decode(payloads[0]), decode(payloads[1]))
        assert_messages_equal(decode_view(payloads[1]).model(), decode(payloads[1]))


def test_framing3_names_the_field_it_refuses() -> None:
    """The header carries no names; the error still says which field and why."""
    msg = EXAMPLES[Features.SCHEMA]
    assert isinstance(msg, Features)
    bad = _replace(msg, ("tags", 0, "hamming"), -2)
    with pytest.raises(SchemaError, match=r"tags\[0\]\.hamming: Expected `int` >= 0"):
        decode(encode(bad))  # type: ignore[arg-type]
    with pytest.raises(SchemaError, match="robot_id"):
        decode(encode(msg.model_copy(update={"robot_id": "abc\n"})))
    with pytest.raises(SchemaError, match="unknown schema id"):
        decode(encode(msg).replace(b"splittag/Features/v4", b"splittag/Featurez/v4"))
    with pytest.raises(SchemaError, match="unsupported version"):
        decode(encode(msg).replace(b"splittag/Features/v4", b"splittag/Features/v9"))


def _odd_message(name: str, annotation: object, default: object = None, **config: object) -> type:
    """A Message subclass with one field (and model config) the positional compiler must refuse."""
    from pydantic import ConfigDict

    from shared.wire.messages import Message

    namespace: dict[str, object] = {"SCHEMA": f"splittag/{name}/v1", "__annotations__": {"x": annotation}}
    if default is not None:
        namespace["x"] = default
    if config:
        namespace["model_config"] = ConfigDict(**config)  # type: ignore[typeddict-item]
    return type(name, (Message,), namespace)


@pytest.mark.parametrize(
    ("make", "reason"),
    [
        (lambda: _odd_message("Odd", float, Field(multiple_of=0.5)), r"Odd\.x"),
        (lambda: _odd_message("Mapping", dict[str, int]), r"Mapping\.x"),
        (lambda: _odd_message("Lax", int, strict=False), "strict"),
        (lambda: _odd_message("Stripped", str, str_strip_whitespace=True), "str_strip_whitespace"),
    ],
)
def test_framing3_compiles_only_what_it_can_check(make: Callable[[], type], reason: str) -> None:
    """A model field or config the compiler has no checked wire type for fails when the codec is built,
    not later."""
    from shared.wire.positional import CompileError, PositionalCodec

    with pytest.raises(CompileError, match=reason):
        PositionalCodec([make()])


def _unmarked_validator() -> type:
    from pydantic import model_validator

    from shared.wire.messages import Message

    def positive(self: object) -> object:
        return self

    namespace: dict[str, object] = {
        "SCHEMA": "splittag/Unmarked/v1",
        "__annotations__": {"x": int},
        "_positive": model_validator(mode="after")(positive),
    }
    return type("Unmarked", (Message,), namespace)


def test_an_after_validator_must_say_it_also_judges_the_wire_struct() -> None:
    """decode_view runs the models' after-validators on wire structs (flat tuples, array references):
    a validator not marked @wire_safe may not be written for that, so the model does not compile."""
    from shared.wire.positional import CompileError, PositionalCodec

    with pytest.raises(CompileError, match="wire_safe"):
        PositionalCodec([_unmarked_validator()])


@pytest.mark.parametrize("schema", sorted(SCHEMAS))
def test_a_view_has_the_messages_fields_and_builds_it_once(schema: str) -> None:
    msg = EXAMPLES[schema]
    view = decode_view(encode(msg), type(msg))
    assert view.schema == schema
    for name, value in msg.__dict__.items():
        got = getattr(view.fields, name)
        if isinstance(value, np.ndarray) and value.size <= 64 and value.dtype.kind == "f" and value.ndim == 2:
            assert list(got) == value.ravel().tolist()  # a small float array: a flat tuple
        elif isinstance(value, (int, float, str, bool)) and not isinstance(value, np.ndarray):
            assert got == value
    model = view.model()
    assert view.model() is model
    assert_messages_equal(model, msg)
    with pytest.raises(AttributeError):  # checked once, then trusted by model(): frozen
        view.fields.robot_id = "bad id"
    with pytest.raises(SchemaError, match="where"):
        decode_view(encode(msg), SplitConfig if schema != SplitConfig.SCHEMA else Features)


def test_a_view_of_an_older_framing_or_schema_is_the_model() -> None:
    msg = EXAMPLES[Features.SCHEMA]
    for framing in (1, 2):
        view = decode_view(encode(msg, framing=framing), Features)
        assert isinstance(view.fields, Features) and view.model() is view.fields
    from shared.wire.messages import FeaturesV3, positional_codec

    assert isinstance(msg, Features)
    tags = [TagFeatureV3(**{k: getattr(t, k) for k in TagFeatureV3.model_fields}) for t in msg.tags]
    older = FeaturesV3(**{k: getattr(msg, k) for k in FeaturesV3.model_fields if k != "tags"}, tags=tags)
    view = decode_view(positional_codec().pack(older), Features)  # framing 3 bytes of an older schema
    assert isinstance(view.fields, Features) and view.schema == Features.SCHEMA
    assert view.fields.tags[0].proposer is None


def test_a_view_refuses_what_decode_refuses_with_the_same_error() -> None:
    msg = EXAMPLES[Features.SCHEMA]
    assert isinstance(msg, Features)
    singular = _replace(msg, ("tags", 0, "roi_to_image"), np.zeros((3, 3)))
    contradicting = _replace(msg, ("tags", 0, "proposer"), "tracker")
    header, _ = _features3_header()
    header[9][0][5] = [2, [0] + [2**31 - 1] * 7, 0]  # type: ignore[index]
    for payload in (encode(singular), encode(contradicting), _frame3(header, b""), encode(msg)[:-1]):  # type: ignore[arg-type]
        with pytest.raises(WireError) as want:
            decode(payload)
        with pytest.raises(type(want.value)) as got:
            decode_view(payload)
        assert str(got.value) == str(want.value)


def _features3_header() -> tuple[list[object], bytes]:
    """Framing 3's header of the Features example as a Python list, and its data section."""
    import msgspec

    payload = encode(EXAMPLES[Features.SCHEMA])
    (size,) = struct.unpack_from("<I", payload, 4)
    start = (8 + size + 7) & ~7
    return msgspec.msgpack.decode(payload[8 : 8 + size]), payload[start:]


def _frame3(header: list[object], data: bytes) -> bytes:
    import msgspec

    raw = msgspec.msgpack.encode(header)
    pad = bytes(-(8 + len(raw)) % 8) if data else b""
    return struct.pack("<BBxxI", 0xC1, 3, len(raw)) + raw + pad + data


def test_framing3_bad_input_is_a_wire_error_of_bounded_length() -> None:
    """Found in review: a zero-size tensor whose other sizes numpy cannot hold escaped as ValueError; a
    literal's error quoted a megabyte of input (a probe of X bytes got an X-byte error back)."""
    header, data = _features3_header()
    tag = header[9][0]  # type: ignore[index]
    tag[5] = [2, [0] + [2**31 - 1] * 7, 0]  # the tensor: float16, no bytes, impossible shape
    with pytest.raises(ArrayError, match="array shape"):
        decode(_frame3(header, b""))
    header, data = _features3_header()
    header[6] = "x" * 1_000_000  # codec
    with pytest.raises(SchemaError, match="codec") as info:
        decode(_frame3(header, data))
    assert len(str(info.value)) < 500
    with pytest.raises(MalformedFrame):  # the header parses as msgpack but is not a list
        decode(_frame3({"a": 1}, b""))  # type: ignore[arg-type]


def test_a_homography_scaled_below_the_smallest_normal_float_is_still_singular() -> None:
    """Found in review: 1 / a subnormal scale is inf, and an inf determinant passed the check."""
    msg = EXAMPLES[Features.SCHEMA]
    assert isinstance(msg, Features)
    singular = np.zeros((3, 3))
    singular[2, 2] = 5e-324
    bad = _replace(msg, ("tags", 0, "roi_to_image"), singular)
    for framing in (2, 3):
        with pytest.raises(SchemaError, match="invertible"):
            decode(encode(bad, framing=framing))  # type: ignore[arg-type]


def test_framing3_reads_any_view_and_writes_either_byte_order() -> None:
    """A memoryview of other items is read as its bytes; a big-endian array is written as its values."""
    msg = EXAMPLES[Features.SCHEMA]
    assert isinstance(msg, Features)
    payload = encode(msg)
    padded = payload + bytes(-len(payload) % 8)
    with pytest.raises(MalformedFrame, match="trailing"):  # the same bytes, seen as uint64 items
        decode(memoryview(bytearray(padded)).cast("Q"))
    assert_messages_equal(decode(memoryview(payload)), msg)
    strided = memoryview(bytes(b for pair in zip(payload, bytes(len(payload)), strict=True) for b in pair))[::2]
    assert_messages_equal(decode(strided), msg)  # a non-contiguous view is read as its bytes
    assert_messages_equal(decode_view(strided).model(), msg)
    for framing in (1, 2, 3):  # arrays viewing a mutable buffer are read-only too
        out = decode(bytearray(encode(msg, framing=framing)))
        assert not out.tags[0].tensor.flags.writeable
    swapped = _replace(msg, ("tags", 0, "roi_to_image"), msg.tags[0].roi_to_image.astype(">f8"))
    assert_messages_equal(decode(encode(swapped)), msg)  # type: ignore[arg-type]


def test_encode_values_writes_what_encode_writes_checked_as_the_receiver_parses() -> None:
    """The echo's ack is sent without building a ProbeAck model: the values are checked by the wire
    type the asker parses with, and the bytes are the model's."""
    from shared.wire.messages import LinkStamps, ProbeAck, encode_values

    link = LinkStamps(sent_nanos=5, received_nanos=9, previous_received_nanos=0)
    for stamps, values in ((link, [5, 9, 0]), (None, None)):
        want = encode(ProbeAck(received_bytes=376, decoded_ok=True, error="", link=stamps))
        assert encode_values(ProbeAck, 376, True, "", values) == want
    with pytest.raises(SchemaError, match=r"received_bytes: Expected `int` >= 0"):
        encode_values(ProbeAck, -1, True, "", None)
    with pytest.raises(SchemaError, match=r"link\.received_nanos"):
        encode_values(ProbeAck, 1, True, "", [5, -9, 0])
    with pytest.raises(SchemaError, match="decoded_ok"):
        encode_values(ProbeAck, 1, 1, "", None)  # strict: no int for a bool
    with pytest.raises(SchemaError, match=r"3 values for its 4 fields \(received_bytes, decoded_ok, error, link\)"):
        encode_values(ProbeAck, 1, True, "")
    for model in (Features, TagPoses, Frame):  # out-of-band arrays or validators need the model
        with pytest.raises(TypeError, match="without arrays or validators"):
            encode_values(model, 1)
