"""Every decoder under generated and mutated payloads (hypothesis; profiles in conftest).

Each decoder of a payload that crosses a process boundary (``decode`` per message
type and for any type, the object payload codec, the recorder's envelope reader) must
return a valid message or raise ``MalformedMessage`` (the envelope reader: ``None``),
never another exception, and never allocate out of proportion to the payload. The
generators live in ``bench/fuzz.py``, whose ``autocast bench fuzz`` runs 10,000 inputs
per decoder; ``AUTOCAST_HYPOTHESIS=fuzz pytest tests/test_fuzz.py`` runs as many here.
"""

from __future__ import annotations

import random
import tracemalloc

import msgpack
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from bench import fuzz
from protocol.codec import MAX_ANY_DEPTH, MalformedMessage, decode, encode
from protocol.messages import Outcome, Pose, Scan, Tick

SMALL_PEAK_BYTES = 64 * 1024  # far below what a declared 10^12-element array would take


@pytest.fixture
def traced():
    tracemalloc.start()
    yield
    tracemalloc.stop()


@pytest.mark.parametrize("name", fuzz.DECODERS)
@given(seed=st.integers(0, 2**64 - 1))
def test_a_mutated_payload_decodes_to_a_valid_message_or_is_refused(name, seed):
    """The bench's generator, seeded by hypothesis (a failure names its seed)."""
    payload = fuzz.fuzz_input(name, random.Random(seed))
    assert fuzz.check(name, payload) in ("valid", "malformed")
    tracemalloc.start()
    try:
        peak = fuzz.decode_peak(fuzz.decoder(name), payload)
    finally:
        tracemalloc.stop()
    assert peak <= fuzz.alloc_bound(len(payload)), f"{peak} bytes traced decoding {len(payload)}"


_plain = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.floats() | st.text(max_size=8)
    | st.binary(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=4) | st.integers(-(2**63), 2**63 - 1), inner, max_size=4),
    max_leaves=20)


@pytest.mark.parametrize("cls", fuzz.MESSAGE_TYPES, ids=lambda c: c.__name__)
@given(data=st.data())
def test_any_values_in_the_fields_give_a_valid_message_or_malformed(cls, data):
    """Right type id and version, fields of any type and number (each field may also
    keep a valid value, so errors deep inside a message are reached)."""
    n = len(cls.__dataclass_fields__)
    valid = fuzz.message_body(cls, random.Random(data.draw(st.integers(0, 2**32), label="seed")))[2:]
    fields = data.draw(st.lists(st.one_of(_plain, st.sampled_from(valid)), min_size=max(n - 1, 0), max_size=n + 1))
    payload = msgpack.packb([cls.TYPE_ID, cls.VERSION, *fields], use_bin_type=True)
    assert fuzz.check(cls.__name__, payload) in ("valid", "malformed")


def _scan_with(dtype, shape, raw) -> bytes:
    return msgpack.packb([Scan.TYPE_ID, Scan.VERSION, 0, 0.0, 1, [0.0, 0.0, 0.0], 0.0, [dtype, shape, raw]],
                         use_bin_type=True)


@pytest.mark.parametrize("shape", [[10**6, 10**6], [10**12], [2**63, 2], [2**64 - 1], [2**32] * 8])
def test_an_array_declaring_enormous_shape_is_refused_before_any_allocation(traced, shape):
    """10^12 uint16 would be 2 TB; the 16 bytes present are all there is."""
    payload = _scan_with("<u2", shape, b"\x00" * 16)
    with pytest.raises(MalformedMessage, match="do not fill"):
        decode(payload, Scan)
    assert fuzz.decode_peak(lambda p: decode(p, Scan), payload) < SMALL_PEAK_BYTES


@pytest.mark.parametrize("shape, why", [([0, 2**64 - 1], "Maximum allowed dimension"),
                                        ([1] * 9, "bad array shape"), ([-1], "bad array shape"),
                                        ([True], "bad array shape")])
def test_an_empty_or_odd_shape_is_refused_cleanly(shape, why):
    with pytest.raises(MalformedMessage, match=why):
        decode(_scan_with("<u2", shape, b""), Scan)


@pytest.mark.parametrize("header", [b"\xdd", b"\xdf", b"\xc6", b"\xdb", b"\xc9"],
                         ids=["array32", "map32", "bin32", "str32", "ext32"])
def test_a_container_declaring_four_billion_items_allocates_nothing(traced, header):
    for payload in (header + b"\xff\xff\xff\xff" + b"\x01" * 8,  # the whole payload
                    msgpack.packb([Tick.TYPE_ID, Tick.VERSION, 0, 0.0], use_bin_type=True)[:-1]
                    + b"\x92\x00" + header + b"\xff\xff\xff\xff\x01"):  # inside a field
        with pytest.raises(MalformedMessage, match="not msgpack"):
            decode(payload)
        assert fuzz.decode_peak(decode, payload) < SMALL_PEAK_BYTES


_DEEP = b"\xee"  # a byte msgpack never produces (reserved), replaced by the nesting
_DEEP_AT = {
    "type id": [_DEEP, 1, 0, 0.0, [], []],
    "version": [Tick.TYPE_ID, _DEEP, 0, 0.0, [], []],
    "a field": [Tick.TYPE_ID, Tick.VERSION, 0, 0.0, _DEEP, []],
    "array shape": [Scan.TYPE_ID, Scan.VERSION, 0, 0.0, 1, [0.0, 0.0, 0.0], 0.0, ["<u2", _DEEP, b""]],
    "array dtype": [Scan.TYPE_ID, Scan.VERSION, 0, 0.0, 1, [0.0, 0.0, 0.0], 0.0, [_DEEP, [0], b""]],
    "free-form value": [Outcome.TYPE_ID, Outcome.VERSION, 0, 0.0, {"a": _DEEP}],
}


@pytest.mark.parametrize("where", _DEEP_AT)
@pytest.mark.parametrize("depth", [1_000, 100_000])
def test_deep_nesting_is_refused_without_a_recursion_error(where, depth):
    """1,000 levels unpack (msgpack's stack is 1,024) and must still be refused without
    a RecursionError (e.g. from the repr of the value in the error message); 100,000
    levels are refused by msgpack."""
    payload = msgpack.packb(_DEEP_AT[where], use_bin_type=True).replace(b"\xc4\x01\xee", b"\x91" * depth + b"\xc0")
    assert len(payload) > depth
    with pytest.raises(MalformedMessage):
        decode(payload)


def _nested(depth: int):
    value = None
    for _ in range(depth):
        value = [value]
    return value


def test_a_free_form_value_is_plain_and_at_most_max_depth_deep():
    ok = Outcome(0, 0.0, {"nested": _nested(MAX_ANY_DEPTH), "n": 1, "m": {2: b"x"}, "f": 1.5})
    assert decode(encode(ok), Outcome).result == ok.result
    deep = msgpack.packb([Outcome.TYPE_ID, Outcome.VERSION, 0, 0.0, {"a": _nested(MAX_ANY_DEPTH + 1)}])
    with pytest.raises(MalformedMessage, match=f"nested deeper than {MAX_ANY_DEPTH}"):
        decode(deep, Outcome)
    for odd in (msgpack.ExtType(5, b"x"), msgpack.Timestamp(1, 0), {1.5: 0}, {None: 0}):
        with pytest.raises(MalformedMessage, match="plain value|map keys"):
            decode(msgpack.packb([Outcome.TYPE_ID, Outcome.VERSION, 0, 0.0, {"a": [odd]}]), Outcome)


@pytest.mark.parametrize("type_id, version", [(True, Tick.VERSION), (Tick.TYPE_ID, True), (Tick.TYPE_ID, 1.0),
                                              (float(Tick.TYPE_ID), 1), (str(Tick.TYPE_ID), 1)])
def test_a_type_id_or_version_of_another_type_is_refused(type_id, version):
    """True == 1 and 1.0 == 1 in Python; on the wire they are other types."""
    payload = msgpack.packb([type_id, version, 0, 0.0, [], []])
    with pytest.raises(MalformedMessage, match="unknown message type|version"):
        decode(payload)


def test_the_generators_make_valid_payloads_for_every_decoder():
    """The seeds the mutations start from decode: the fuzzing reaches past the envelope."""
    rnd = random.Random(0)
    for name in fuzz.DECODERS:
        assert all(fuzz.check(name, fuzz.valid_payload(name, rnd)) == "valid" for _ in range(20)), name
    scan = Scan(1, 0.1, 2, Pose(0.0, 0.0, 0.0), 0.0, np.ones((3, 2), np.uint16))
    assert fuzz.check("Scan", encode(scan)) == "valid"
