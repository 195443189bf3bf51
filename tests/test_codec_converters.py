"""The codec's generated record converters against the per-field loop they replaced.

``reference_decode`` is the decoder as it was before the record converters were
generated: a loop over a record's fields with one converter call each. On valid and
fuzzed payloads of every message type, both must give the same message (the same wire
bytes again) or refuse the payload with the same error message.
"""

from __future__ import annotations

import dataclasses
import random
import types
import typing
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from bench import fuzz
from protocol import codec
from protocol.codec import MalformedMessage, decode, encode
from protocol.messages import ControlMsg, DataBundle, ObjectMap, Pose, Reception

_REF: dict[Any, Any] = {}


def _ref_converter(hint: Any):
    got = _REF.get(hint)
    if got is None:
        got = _REF[hint] = _ref_build(hint)
    return got


def _ref_build(hint: Any):
    """codec._build_converter as it was, over reference converters."""
    origin = typing.get_origin(hint)
    if hint is np.ndarray:
        return codec._array_from_wire
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(hint)
        (inner,) = [a for a in args if a is not type(None)]
        conv = _ref_converter(inner)
        optional = type(None) in args
        return lambda value: None if value is None and optional else conv(value)
    if origin is list or (origin is tuple and typing.get_args(hint)[1:] == (Ellipsis,)):
        conv = _ref_converter(typing.get_args(hint)[0])
        kind = list if origin is list else tuple
        return lambda value: kind(codec._items(value, [conv] * len(value) if isinstance(value, list) else None))
    if origin is tuple:
        convs = [_ref_converter(a) for a in typing.get_args(hint)]
        return lambda value: tuple(codec._items(value, convs))
    if origin is dict:
        kconv, vconv = (_ref_converter(a) for a in typing.get_args(hint))
        return lambda value: codec._mapping(value, kconv, vconv)
    if hasattr(hint, "__dataclass_fields__"):
        return _ref_record(hint)
    return codec._build_converter(hint)  # scalars and Any: unchanged


def _ref_record(cls: type):
    names = [name for name, _ in codec._hints(cls)]
    convs: list = []

    def convert(values: Any) -> Any:
        if not isinstance(values, list) or len(values) != len(names):
            codec._bad(f"{cls.__name__} needs {len(names)} fields")
        args = []
        for name, conv, v in zip(names, convs, values):
            try:
                args.append(conv(v))
            except codec._FieldError as err:
                err.path.insert(0, f".{name}")
                raise
        for inv in codec.invariants(cls):  # its declared invariants, in order, the first field named
            problem = inv.test(*(args[names.index(f)] for f in inv.fields))
            if problem is not None:
                err = codec._FieldError(problem)
                err.path.insert(0, f".{inv.fields[0]}")
                raise err
        try:
            return cls(*args)
        except ValueError as exc:  # a record's own check (__post_init__): named by where it sits, as codec words it
            raise codec._FieldError(str(exc)) from None

    _REF[cls] = convert
    convs.extend(_ref_converter(hint) for _, hint in codec._hints(cls))
    return convert


def reference_decode(payload: bytes, expected: type) -> Any:
    """``decode`` with the reference converters (the envelope checks are the same)."""
    body = msgpack.unpackb(payload, raw=False, use_list=True, strict_map_key=False)
    try:
        return _ref_converter(expected)(body[2:])
    except codec._FieldError as err:
        raise MalformedMessage(f"{expected.__name__}{''.join(err.path)}: {err.text}") from None
    except (TypeError, ValueError) as exc:
        raise MalformedMessage(f"{expected.__name__}: {exc}") from None


def _outcome(fn, payload: bytes, cls: type) -> tuple[str, Any]:
    try:
        return "valid", encode(fn(payload, cls))
    except MalformedMessage as err:
        return "malformed", str(err)


def _envelope_ok(payload: bytes, cls: type) -> bool:
    """The payload passes decode's envelope checks (type id and version), so the
    difference can only lie in the converters."""
    try:
        body = msgpack.unpackb(payload, raw=False, use_list=True, strict_map_key=False)
    except Exception:
        return False
    return isinstance(body, list) and len(body) >= 2 and body[0] == cls.TYPE_ID and body[1] == cls.VERSION \
        and type(body[0]) is int and type(body[1]) is int


@pytest.mark.parametrize("cls", fuzz.MESSAGE_TYPES, ids=lambda c: c.__name__)
@given(seed=st.integers(0, 2**64 - 1))
def test_generated_converters_decode_and_refuse_as_the_field_loop_did(cls, seed):
    rnd = random.Random(seed)
    payload = fuzz.valid_payload(cls.__name__, rnd) if seed % 4 == 0 else fuzz.fuzz_input(cls.__name__, rnd)
    if not _envelope_ok(payload, cls):
        return
    assert _outcome(decode, payload, cls) == _outcome(reference_decode, payload, cls)


def test_a_bad_field_deep_inside_is_named_by_its_path():
    om = ObjectMap(np.array([1]), np.array([70]), np.zeros((1, 2), np.float32), np.array([2]),
                   np.zeros((1, 1), np.float32), np.zeros((1, 1), np.float32))
    msg = ControlMsg(3, 0.3, 1, Pose(0.0, 1.0, 2.0), 4.0, np.zeros((2, 3), np.float32), om, np.array([2]))
    body = msgpack.unpackb(encode(msg), raw=False)
    body[8][2] = ["<f4", [1, 2], b"\x00"]  # objects.centroid_xy: 1 byte for 8
    with pytest.raises(MalformedMessage, match=r"^ControlMsg\.objects\.centroid_xy: 1 bytes do not fill"):
        decode(msgpack.packb(body, use_bin_type=True), ControlMsg)
    body = msgpack.unpackb(encode(msg), raw=False)
    body[8][4] = ["<f4", [1, 1], b"\x01", b"\x00", b""]  # objects.visibility (packed): a padding bit set
    with pytest.raises(MalformedMessage, match=r"^ControlMsg\.objects\.visibility: mask padding bits set$"):
        decode(msgpack.packb(body, use_bin_type=True), ControlMsg)
    body = msgpack.unpackb(encode(DataBundle(1, 0.1, np.array([2]), np.ones((1, 2), bool),
                                             [Reception(1, 2, 0.01, b"a"), Reception(3, 4, 0.02, b"b")])), raw=False)
    body[6][1][3] = "text"  # receptions[1].payload
    with pytest.raises(MalformedMessage, match=r"^DataBundle\.receptions\[1\]\.payload: expected bytes, got str$"):
        decode(msgpack.packb(body, use_bin_type=True), DataBundle)
    body[6][1] = [3, 4, 0.02]
    with pytest.raises(MalformedMessage, match=r"^DataBundle\.receptions\[1\]: Reception needs 4 fields$"):
        decode(msgpack.packb(body, use_bin_type=True), DataBundle)


def test_an_int_where_a_float_goes_becomes_a_float_and_a_bool_is_no_int():
    bundle = DataBundle(1, 0.1, np.array([2]), np.ones((1, 1), bool), [Reception(1, 2, 0.5, b"a")])
    body = msgpack.unpackb(encode(bundle), raw=False)
    body[6][0][2] = 1  # rx_time_s as an int
    got = decode(msgpack.packb(body, use_bin_type=True), DataBundle)
    assert type(got.receptions[0].rx_time_s) is float and got.receptions[0].rx_time_s == 1.0
    body[6][0][0] = True  # sender as a bool
    with pytest.raises(MalformedMessage, match=r"receptions\[0\]\.sender: expected an int, got bool"):
        decode(msgpack.packb(body, use_bin_type=True), DataBundle)


def _reference_packed(arr: np.ndarray) -> list:
    """A packed array (``codec._packed_to_wire``) written out entry by entry."""
    flat = np.ascontiguousarray(arr).reshape(-1)
    width = 8 * flat.dtype.itemsize
    one = int(np.ones(1, flat.dtype).view(f"<u{flat.dtype.itemsize}")[0])
    bits = [int.from_bytes(flat[i:i + 1].tobytes(), "little") for i in range(len(flat))]
    assert all(0 <= b < 1 << width for b in bits)

    def mask(marked: list[bool]) -> bytes:
        out = bytearray((len(marked) + 7) // 8)
        for i, m in enumerate(marked):
            if m:
                out[i // 8] |= 0x80 >> (i % 8)
        return bytes(out)

    others = [b not in (0, one) for b in bits]
    values = b"".join(flat[i:i + 1].tobytes() for i in range(len(flat)) if others[i])
    return [flat.dtype.str, list(arr.shape), mask([b == one for b in bits]), mask(others), values]


def _reference_to_wire(value: Any) -> Any:
    """codec._to_wire as it was: every value through the chain of type tests; a field
    declared packed, entry by entry."""
    import dataclasses

    if isinstance(value, np.ndarray):
        arr = np.ascontiguousarray(value)
        return [arr.dtype.str, list(arr.shape), memoryview(arr).cast("B") if arr.size else b""]
    if dataclasses.is_dataclass(value):
        return [_reference_packed(getattr(value, name)) if (spec := codec.array_spec(hint)) is not None and spec.packed
                else _reference_to_wire(getattr(value, name)) for name, hint in codec._hints(type(value))]
    if isinstance(value, (list, tuple)):
        return [_reference_to_wire(v) for v in value]
    if isinstance(value, dict):
        return {k: _reference_to_wire(v) for k, v in value.items()}
    if isinstance(value, np.generic):
        return value.item()
    return value


def reference_encode(msg: Any) -> bytes:
    cls = type(msg)
    body = [cls.TYPE_ID, cls.VERSION] + [_reference_to_wire(getattr(msg, name)) for name, _ in codec._hints(cls)]
    return msgpack.packb(body, use_bin_type=True)


@pytest.mark.parametrize("cls", fuzz.MESSAGE_TYPES, ids=lambda c: c.__name__)
@given(seed=st.integers(0, 2**64 - 1))
def test_generated_encoders_write_the_bytes_the_type_tests_wrote(cls, seed):
    """Every message type, from valid payloads, re-encoded: the same bytes as the chain
    of type tests gave; and with fields holding other types than declared (a numpy
    scalar for a float, a tuple for a list, a read-only or strided array)."""
    msg = decode(fuzz.valid_payload(cls.__name__, random.Random(seed)), cls)
    assert encode(msg) == reference_encode(msg)
    odd = {}
    for name, value in ((f, getattr(msg, f)) for f, _ in codec._hints(cls)):
        if type(value) is float:
            odd[name] = np.float64(value)
        elif type(value) is int:
            odd[name] = np.int64(value)
        elif type(value) is list:
            odd[name] = tuple(value)
        elif type(value) is np.ndarray and value.ndim == 2:
            odd[name] = np.asfortranarray(value)
    if odd:
        other = cls.__new__(cls)
        for f, _ in codec._hints(cls):
            object.__setattr__(other, f, odd.get(f, getattr(msg, f)))
        assert encode(other) == reference_encode(other)


def test_a_converter_built_in_one_thread_is_waited_for_in_another(monkeypatch):
    """Converters are built on first use in whichever thread decodes first. Another
    thread that meets the record's placeholder mid-build waits for the builder instead of
    failing (it raised IndexError: a recorder died so). The builder is held mid-build
    until the other thread is at the build lock: no timing decides the verdict."""
    import threading
    from dataclasses import dataclass

    from protocol import codec

    @dataclass(frozen=True, slots=True)
    class Rec:
        a: int
        b: float

    builder_id: list[int] = []
    waiting = threading.Event()
    real_lock = codec._BUILDING

    class Watched:
        def __enter__(self):
            if threading.get_ident() not in builder_id:
                waiting.set()
            return real_lock.__enter__()

        def __exit__(self, *exc):
            return real_lock.__exit__(*exc)

    real_inline = codec._inline

    def held_inline(hint, name):
        assert waiting.wait(60), "the other thread never reached the build lock"
        return real_inline(hint, name)

    monkeypatch.setattr(codec, "_BUILDING", Watched())
    monkeypatch.setattr(codec, "_inline", held_inline)
    installed = threading.Event()
    real_placeholder = codec._placeholder

    def placeholder(built):
        out = real_placeholder(built)
        installed.set()
        return out

    monkeypatch.setattr(codec, "_placeholder", placeholder)

    def build():
        builder_id.append(threading.get_ident())
        codec._converter(Rec)

    builder = threading.Thread(target=build)
    builder.start()
    assert installed.wait(60)
    assert codec._CONVERTERS[Rec]([1, 2.0]) == Rec(1, 2.0)  # the placeholder, called mid-build
    builder.join(60)
    assert codec._CONVERTERS[Rec]([3, 4.0]) == Rec(3, 4.0)


_SPECS = [codec.Array("<f4", (None, 3)), codec.Array("<i8", (None,)), codec.Array("|u1", (None, 16)),
          codec.Array("<f4", (None, None)), codec.Array("|b1", (2, 2))]
_DECLINED = object()


def _fast(spec: codec.Array):
    """The inlined conversion of ``spec`` alone: the array, or ``_DECLINED`` where it hands
    the value to the converter."""
    env = {"_ndarray": np.ndarray, "_DTYPE_OF": codec._DTYPE_OF, "slow": lambda v: _DECLINED}
    return eval(f"lambda v: {codec._inline_array(spec, 'slow')}", env)  # noqa: S307 - the codec's own source


_odd_dims = st.one_of(st.integers(-2, 40), st.booleans(), st.floats(0, 4), st.none())


@given(spec=st.sampled_from(_SPECS), rows=st.integers(0, 5), data=st.data(),
       mutation=st.sampled_from(["none", "dtype", "dim", "ndim", "tuple", "bytes"]))
def test_an_inlined_array_is_the_converters_array_or_goes_to_it(spec, rows, data, mutation):
    """Where the inlined expression takes a value, the converter takes it too and builds
    the same array; everything else it hands to the converter. The value is a
    well-formed triple of the spec, or one with one thing changed: the dtype, a dim (to
    any int, a bool, a float, None), the number of dims, the shape a tuple, the bytes'
    length."""
    shape = [rows if d is None else d for d in spec.shape]
    dtype = spec.dtype
    if mutation == "dtype":
        dtype = data.draw(st.sampled_from(sorted(codec.WIRE_DTYPES - {spec.dtype}) + ["float32", 7, np.str_(spec.dtype)]))
    elif mutation == "dim":
        shape[data.draw(st.integers(0, len(shape) - 1))] = data.draw(_odd_dims)
    elif mutation == "ndim":
        shape = shape[:-1] if data.draw(st.booleans()) else shape + [1]
    count = 1
    for d in shape:
        count *= d if type(d) is int and d > 0 else 0
    item = codec._DTYPE_OF[dtype].itemsize if dtype in codec._DTYPE_OF else 4
    extra = data.draw(st.sampled_from([-1, 1, 8])) if mutation == "bytes" else 0
    raw = bytes(range(256)) * (max(count * item + extra, 0) // 256 + 1)
    value = [dtype, tuple(shape) if mutation == "tuple" else shape, raw[:max(count * item + extra, 0)]]
    got = _fast(spec)(value)
    if mutation == "none":
        assert got is not _DECLINED, "a well-formed array goes the fast way"
    if got is _DECLINED:
        return
    want = codec._array_converter(spec)(value)
    assert (got.dtype, got.shape, got.tobytes()) == (want.dtype, want.shape, want.tobytes())


@pytest.mark.parametrize("spec", _SPECS)
def test_a_well_formed_array_is_taken_inline(spec):
    rows = 4 if spec.shape[0] is None else spec.shape[0]
    arr = np.zeros([rows if d is None else d for d in spec.shape], dtype=spec.dtype)
    got = _fast(spec)([arr.dtype.str, list(arr.shape), arr.tobytes()])
    assert got is not _DECLINED and got.dtype == arr.dtype and got.shape == arr.shape


def test_a_slots_constructor_builds_what_init_builds_and_refuses_what_it_cannot():
    """``slots_constructor`` builds an instance equal field by field to the class's own
    ``__init__``'s, still frozen; a class with ``__post_init__``, without slots, with a
    non-init field or with inherited fields is refused (its ``__init__`` does more than
    set its own slots)."""
    import dataclasses

    from vehicle_agent.agreement import HeardControl

    build = codec.slots_constructor(Pose)
    got, want = build(1.5, -2.0, 0.25), Pose(1.5, -2.0, 0.25)
    assert type(got) is Pose and got == want
    with pytest.raises(dataclasses.FrozenInstanceError):
        got.x_m = 0.0
    traj, heard = np.zeros((3, 2), np.float32), np.array([1, 4], np.int64)
    args = (7, 0.7, 3, want, 9.5, traj, heard, b"raw")
    made = codec.slots_constructor(HeardControl)(*args)
    assert [getattr(made, f.name) for f in dataclasses.fields(HeardControl)] == list(args)

    @dataclasses.dataclass(frozen=True, slots=True)
    class Checked:
        a: int

        def __post_init__(self) -> None:
            if self.a < 0:
                raise ValueError("a")

    @dataclasses.dataclass(frozen=True)
    class NoSlots:
        a: int

    @dataclasses.dataclass(frozen=True, slots=True)
    class NotInit:
        a: int
        b: int = dataclasses.field(init=False, default=0)

    @dataclasses.dataclass(frozen=True, slots=True)
    class Inherits(Pose):  # Pose's fields sit in Pose's slots
        z_m: float = 0.0

    for cls in (Checked, NoSlots, NotInit, Inherits):
        with pytest.raises(TypeError, match=cls.__name__):
            codec.slots_constructor(cls)


def _read_outcome(read, payload: bytes) -> tuple[str, Any]:
    try:
        got = read(payload)
    except MalformedMessage as err:
        return "malformed", str(err)
    return "valid", got


@given(seed=st.integers(0, 2**64 - 1))
def test_a_fields_decoder_reads_and_refuses_as_decode_fields_does(seed):
    """``fields_decoder`` (one generated function) against ``decode_fields`` (the
    reference: envelope, then the fields' reader): the same fields, the same error text,
    on valid control messages, fuzzed ones and other messages' payloads."""
    from vehicle_agent.agreement import HeardControl

    rnd = random.Random(seed)
    name = "ControlMsg" if seed % 5 else rnd.choice([c.__name__ for c in fuzz.MESSAGE_TYPES])
    payload = fuzz.valid_payload(name, rnd) if seed % 3 == 0 else fuzz.fuzz_input(name, rnd)
    read = codec.fields_decoder(ControlMsg, HeardControl.FIELDS, HeardControl)
    got = _read_outcome(read, payload)
    want = _read_outcome(lambda raw: codec.decode_fields(raw, ControlMsg, HeardControl.FIELDS) + (raw,), payload)
    if got[0] == "valid":
        assert want[0] == "valid"
        fields = [getattr(got[1], f.name) for f in dataclasses.fields(HeardControl)]
        assert len(fields) == len(want[1])
        for a, b in zip(fields, want[1]):
            assert type(a) is type(b)
            if isinstance(a, np.ndarray):
                assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
                assert a.flags.writeable == b.flags.writeable
            else:
                assert repr(a) == repr(b)  # a float's repr is exact, and NaN's is NaN's
    else:
        assert got == want


def test_a_fields_decoder_by_hand():
    from vehicle_agent.agreement import HeardControl

    read = codec.fields_decoder(ControlMsg, HeardControl.FIELDS, HeardControl)
    om = ObjectMap(np.array([1]), np.array([70]), np.zeros((1, 2), np.float32), np.array([2]),
                   np.zeros((1, 1), np.float32), np.zeros((1, 1), np.float32))
    raw = encode(ControlMsg(4, 0.4, 3, Pose(1.0, 2.0, 0.5), 7.5, np.zeros((2, 3), np.float32), om,
                            np.array([1, 2], np.int64)))
    heard = read(raw)
    assert (heard.tick, heard.t_sim_s, heard.vid, heard.pose, heard.speed_mps) == (4, 0.4, 3, Pose(1.0, 2.0, 0.5), 7.5)
    assert heard.heard.tolist() == [1, 2] and heard.trajectory.shape == (2, 3) and heard.raw is raw
    body = msgpack.unpackb(raw)
    body[9] = ["<i4", [2], b"\0" * 8]  # heard of the wrong dtype
    with pytest.raises(MalformedMessage, match=r"^ControlMsg\.heard: expected int64"):
        read(msgpack.packb(body))
    with pytest.raises(MalformedMessage, match=r"^ControlMsg needs 11 fields"):
        read(msgpack.packb(body[:-1]))
    with pytest.raises(MalformedMessage, match=r"^not msgpack"):
        read(raw[:-3])
    with pytest.raises(MalformedMessage, match=r"^expected ControlMsg, got "):
        read(msgpack.packb([1, 1, 0.0]))


def _packed_reference(spec: codec.Array):
    """codec._packed_converter as it was (ec93cfa): zeros, then each mask's entries set."""
    import math

    dtype, ndim = np.dtype(spec.dtype), len(spec.shape)
    fixed = [(axis, d) for axis, d in enumerate(spec.shape) if d is not None]
    uint, one_bits = codec._BITS_OF[spec.dtype]

    def convert(value):
        if type(value) is not list or len(value) != 5:
            codec._bad("expected a packed array [dtype, shape, ones, others, values]")
        dtype_str, shape, ones, others, raw = value
        if dtype_str != spec.dtype:
            codec._bad(f"expected a packed {spec}, got dtype {codec._brief(dtype_str)}")
        if type(ones) is not bytes or type(others) is not bytes or type(raw) is not bytes:
            codec._bad("a packed array's masks and values are bytes")
        if type(shape) is not list or len(shape) != ndim or any(type(d) is not int or d < 0 for d in shape) \
                or any(shape[axis] != d for axis, d in fixed):
            codec._bad(f"expected a packed {spec}, got shape {codec._brief(shape)}")
        count = math.prod(shape)
        if len(ones) != (count + 7) // 8 or len(others) != len(ones):
            codec._bad(f"masks of {len(ones)} and {len(others)} bytes for {count} entries")
        one, other = int.from_bytes(ones, "big"), int.from_bytes(others, "big")
        if (one | other) & ((1 << (8 * len(ones) - count)) - 1):
            codec._bad("mask padding bits set")
        if one & other:
            codec._bad("an entry marked both 1 and other")
        n_other = other.bit_count()
        if n_other * dtype.itemsize != len(raw):
            codec._bad(f"{len(raw)} bytes of values for {n_other} entries")
        out = np.zeros(count, dtype)
        if one:
            out[np.unpackbits(np.frombuffer(ones, np.uint8), count=count).view(np.bool_)] = 1.0
        if other:
            bits = np.frombuffer(raw, uint)
            if ((bits == 0) | (bits == one_bits)).any():
                codec._bad("a value of 1.0 or +0.0 among the others")
            out[np.unpackbits(np.frombuffer(others, np.uint8), count=count).view(np.bool_)] = bits.view(dtype)
        return out.reshape(shape)

    return convert


_PACKED = [codec.Array("<f4", (None, None), packed=True), codec.Array("<f8", (None, 3), packed=True)]


def _packed_outcome(convert, value):
    try:
        arr = convert(value)
    except codec._FieldError as err:
        return "bad", err.text
    return "ok", (arr.dtype.str, arr.shape, arr.tobytes(), arr.flags.writeable, arr.flags.c_contiguous)


@given(spec=st.sampled_from(_PACKED), rows=st.integers(0, 6), cols=st.integers(0, 5), data=st.data(),
       mutation=st.sampled_from(["none", "none", "value", "padding", "overlap", "short", "shape"]))
def test_a_packed_table_decodes_and_is_refused_as_before(spec, rows, cols, data, mutation):
    """The packed converter (one unpack of both masks, the 0/1 table straight from its
    mask) against the one it replaced: the same array, bit for bit, or the same error."""
    cols = spec.shape[1] or cols
    pick = st.sampled_from([0.0, 1.0, -0.0, 0.5, float("nan"), 3.0, float("inf")])
    arr = np.array(data.draw(st.lists(pick, min_size=rows * cols, max_size=rows * cols)),
                   dtype=spec.dtype).reshape(rows, cols)
    value = codec._packed_to_wire(arr)
    n_bytes = len(value[2])
    if mutation == "value" and value[4]:
        one = codec._BITS_OF[spec.dtype][1].to_bytes(np.dtype(spec.dtype).itemsize, "little")
        value[4] = one + value[4][len(one):]
    elif mutation == "padding" and n_bytes and (rows * cols) % 8:
        value[3] = value[3][:-1] + bytes([value[3][-1] | 1])
    elif mutation == "overlap" and n_bytes:
        value[2] = bytes(b | o for b, o in zip(value[2], value[3])) if any(value[3]) else value[2]
        value[3] = bytes(255 for _ in value[3])
    elif mutation == "short" and value[4]:
        value[4] = value[4][:-1]
    elif mutation == "shape":
        value[1] = [rows, cols, 1]
    got = _packed_outcome(codec._packed_converter(spec), value)
    assert got == _packed_outcome(_packed_reference(spec), value)
    if mutation == "none":
        assert got[0] == "ok" and got[1][2] == arr.tobytes()


def test_a_packed_table_by_hand():
    convert = codec._packed_converter(codec.Array("<f4", (None, None), packed=True))
    # 2 x 3: ones at entries 0 and 4 (0b10001000), others at 2 (0b00100000) of value 0.5
    got = convert(["<f4", [2, 3], bytes([0b10001000]), bytes([0b00100000]), np.float32(0.5).tobytes()])
    assert got.tolist() == [[1.0, 0.0, 0.5], [0.0, 1.0, 0.0]] and got.dtype == np.float32
    assert convert(["<f4", [1, 2], bytes([0b01000000]), b"\0", b""]).tolist() == [[0.0, 1.0]]
    with pytest.raises(codec._FieldError, match="a value of 1.0 or"):
        convert(["<f4", [1, 1], b"\0", bytes([0b10000000]), np.float32(1.0).tobytes()])


@pytest.mark.parametrize("field, value, accepted", [
    ("trajectory", np.zeros((2, 3), np.float32), True),
    ("trajectory", np.zeros((4, 3), np.float32)[::2], True),  # strided: made contiguous
    ("trajectory", np.zeros((0, 3), np.float32), True),
    ("trajectory", np.zeros((2, 3), ">f4"), False),  # the declared dtype's other byte order
    ("trajectory", np.zeros((2, 2), np.float32), False),
    ("trajectory", np.zeros(6, np.float32), False),
    ("trajectory", np.zeros((2, 3), np.float64), False),
    ("trajectory", np.ma.zeros((2, 3), np.float32), False),  # a subclass takes the checked path: accepted there
    ("heard", np.array([1, 2], np.int32), False),
    ("heard", [1, 2], False),
])
def test_an_array_field_is_written_or_refused_as_the_checked_path_does(field, value, accepted):
    """The generated encoder's inline dtype and shape test against ``Array.fits``
    (``_checked_array_to_wire``): the same bytes, or the same ``TypeError``."""
    om = ObjectMap(np.array([1]), np.array([70]), np.zeros((1, 2), np.float32), np.array([2]),
                   np.zeros((1, 1), np.float32), np.zeros((1, 1), np.float32))
    msg = ControlMsg(1, 0.1, 3, Pose(0.0, 0.0, 0.0), 1.0, np.zeros((1, 3), np.float32), om, np.array([1], np.int64))
    object.__setattr__(msg, field, value)
    spec = codec.array_spec(dict(codec._hints(ControlMsg))[field])
    try:
        want = ("ok", msgpack.packb([7, ControlMsg.VERSION] + [codec._checked_array_to_wire(spec, value, f"ControlMsg.{field}")
                                              if name == field else codec._to_wire(getattr(msg, name))
                                              for name, _ in codec._hints(ControlMsg)], use_bin_type=True))
    except TypeError as exc:
        want = ("refused", str(exc))
    try:
        got = ("ok", encode(msg))
    except TypeError as exc:
        got = ("refused", str(exc))
    assert got == want
    assert (got[0] == "ok") == (accepted or isinstance(value, np.ma.MaskedArray))


def test_a_list_of_plain_items_is_taken_at_once_or_item_by_item():
    """``list[bytes]`` (a control bundle's messages): a list of bytes as it is (a new
    list); any other item still goes to the item's converter, its index in the path."""
    convert = codec._converter(list[bytes])
    items = [b"a", b"", b"c"]
    got = convert(items)
    assert got == items and got is not items
    with pytest.raises(codec._FieldError) as err:
        convert([b"a", "b"])
    assert err.value.path == ["[1]"] and err.value.text == "expected bytes, got str"
    assert codec._converter(tuple[str, ...])(["x", "y"]) == ("x", "y")
