"""The recorder's faster paths against the code they replaced, kept here as references.

- ``to_json`` (a generated function per record) against the closures of ``_plan`` and
  ``json.dumps`` it replaced: the same bytes for every message type, NaN and infinities
  included.
- ``peek_envelope``, which reads the codec's usual head from the bytes, against
  msgpack's ``Unpacker``: the same envelope or None for any head.
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
import random
import typing

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bench import fuzz
from deploy.record import recorder
from deploy.record.recorder import JSON_OMITTED, to_json

from protocol import codec
from protocol.codec import MalformedMessage, decode, encode, message_class
from protocol.messages import AgentReport, ChannelStats, Command, ControlMsg, ObjectMap, Pose, WorldTruth

# A fuzzed float32 array may hold a signalling NaN: widening it to float64 raises numpy's
# "invalid value" flag, in the old code as in the new; the bytes are what is compared
pytestmark = pytest.mark.filterwarnings("ignore:invalid value encountered in cast:RuntimeWarning")

# ------------------------------------------------------------------ to_json as it was


def _ref_finite(x: float) -> float | None:
    return x if math.isfinite(x) else None


def _ref_array_to_json(a: np.ndarray) -> list:
    if a.dtype == np.float32:
        return np.round(a.astype(np.float64), 6).tolist()
    return a.tolist()


def _ref_plan(hint: typing.Any, owner: type | None = None, name: str = "") -> tuple[str, typing.Callable]:
    if hint is np.ndarray:
        if (owner, name) in JSON_OMITTED:
            return f"{name}_shape", lambda a: list(a.shape)
        return name, _ref_array_to_json
    if hint is bytes:
        return f"{name}_size_bytes", len
    if hint is float:
        return name, _ref_finite
    if hint is bool:
        return name, bool
    if hint is int:
        return name, int
    if hint is str:
        return name, str
    origin = typing.get_origin(hint)
    if origin is list:
        (inner,) = typing.get_args(hint)
        inner_name, conv = _ref_plan(inner, owner, name)
        return inner_name, (lambda v: [conv(x) for x in v])
    if origin is dict:
        return name, (lambda v: v)
    if dataclasses.is_dataclass(hint):
        return name, _ref_record(hint)
    if hint is typing.Any:
        return name, (lambda v: v)
    raise TypeError(f"{name}: no JSON mirror for {hint!r}")


def _ref_record(cls: type) -> typing.Callable:
    hints = typing.get_type_hints(cls)
    plans = [(f.name, *_ref_plan(hints[f.name], cls, f.name)) for f in dataclasses.fields(cls)]
    return lambda value: {out: conv(getattr(value, name)) for name, out, conv in plans}


def _ref_no_nan(v: typing.Any) -> typing.Any:
    if isinstance(v, float):
        return _ref_finite(v)
    if isinstance(v, dict):
        return {k: _ref_no_nan(x) for k, x in v.items()}
    if isinstance(v, list):
        return [_ref_no_nan(x) for x in v]
    return v


def ref_to_json(msg: typing.Any) -> bytes:
    obj = _ref_record(type(msg))(msg)
    try:
        return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()
    except ValueError:
        return json.dumps(_ref_no_nan(obj), separators=(",", ":"), allow_nan=False).encode()


# ------------------------------------------------------------------ to_json


@given(bits=st.lists(st.integers(0, 2**32 - 1), max_size=40), rows=st.integers(1, 4))
def test_a_float32_array_rounds_to_the_bits_np_round_gave(bits, rows):
    """Any float32 (NaN, infinities, -0.0, subnormals, the largest) in any shape."""
    flat = np.array(bits, np.uint32).view(np.float32)
    for a in (flat, flat[: len(flat) // rows * rows].reshape(rows, -1), flat.astype(">f4")):
        got, want = recorder._array_to_json(a), _ref_array_to_json(a)
        assert np.array_equal(np.array(got, np.float64).view(np.uint64), np.array(want, np.float64).view(np.uint64))
        assert repr(got) == repr(want)


def test_float32_rounding_by_hand():
    a = np.array([[37.805, 0.1], [-2.25, 1e-7]], np.float32)
    assert recorder._array_to_json(a) == [[37.805, 0.1], [-2.25, 0.0]]
    assert recorder._array_to_json(np.array([1, 2], np.int64)) == [1, 2]


@settings(max_examples=60, deadline=None)
@pytest.mark.parametrize("cls", fuzz.MESSAGE_TYPES, ids=lambda c: c.__name__)
@given(seed=st.integers(0, 2**64 - 1))
def test_to_json_gives_the_bytes_the_field_closures_gave(cls, seed):
    rnd = random.Random(seed)
    payload = fuzz.valid_payload(cls.__name__, rnd) if seed % 2 else fuzz.fuzz_input(cls.__name__, rnd)
    try:
        msg = decode(payload, cls)
    except MalformedMessage:
        return
    assert to_json(msg) == ref_to_json(msg)


NAN, INF = float("nan"), float("inf")


@pytest.mark.parametrize("msg", [
    Command(3, NAN, 1, INF, -INF),
    WorldTruth(1, 0.1, np.array([4, 5]), np.array([[1.5, NAN, 0.25], [INF, 2.0, -INF]], np.float32),
               np.array([NAN, 3.0], np.float32), np.zeros((2, 3), np.float32)),
    ChannelStats(2, 0.2, {"a": NAN, "b": [1.0, INF, {"c": -INF}], "d": "NaN"}),
    AgentReport(2, 0.2, 0, np.array([[0.1, 37.805]], np.float32), 5, True),
], ids=["float fields", "float32 arrays", "free-form", "plain"])
def test_non_finite_numbers_become_null_wherever_they_are(msg):
    assert to_json(msg) == ref_to_json(msg)
    doc = json.loads(to_json(msg))
    assert "NaN" not in json.dumps(doc).replace('"NaN"', "")


def test_a_control_message_by_hand():
    objects = ObjectMap(np.array([7]), np.array([120]), np.array([[1.5, -2.25]], np.float32), np.array([3, 4]),
                        np.ones((1, 2), np.float32), np.zeros((1, 2), np.float32))
    msg = ControlMsg(4, 0.4, 2, Pose(1.0, -2.5, 0.125), 3.0, np.array([[0.1, 0.2, 0.5]], np.float32), objects,
                     np.array([1, 3]))
    assert to_json(msg) == (
        b'{"tick":4,"t_sim_s":0.4,"vid":2,"pose":{"x_m":1.0,"y_m":-2.5,"yaw_rad":0.125},"speed_mps":3.0,'
        b'"trajectory":[[0.1,0.2,0.5]],"objects":{"object_id":[7],"size_bytes":[120],"centroid_xy":[[1.5,-2.25]],'
        b'"receivers":[3,4],"visibility_shape":[1,2],"relevance_shape":[1,2]},"heard":[1,3],"unscheduled":[],'
        b'"digests":[],"domains":[]}')


# ------------------------------------------------------------------ peek_envelope


def ref_peek_envelope(payload: bytes):
    """peek_envelope as it was: msgpack's Unpacker over the head."""
    unpacker = msgpack.Unpacker(io.BytesIO(payload), read_size=64, raw=False, strict_map_key=False)
    try:
        n = unpacker.read_array_header()
        type_id, version, tick, t_sim_s = (unpacker.unpack() for _ in range(4))
    except Exception:
        return None
    cls = message_class(type_id) if isinstance(type_id, int) and not isinstance(type_id, bool) else None
    if cls is None or version != cls.VERSION or n != 2 + len(dataclasses.fields(cls)):
        return None
    if not isinstance(tick, int) or isinstance(t_sim_s, bool) or not isinstance(t_sim_s, (int, float)):
        return None
    return codec.Envelope(cls, tick, float(t_sim_s))


def _same_envelope(a, b) -> bool:
    if a is None or b is None:
        return a is b
    return (a.cls, a.tick, type(a.t_sim_s)) == (b.cls, b.tick, type(b.t_sim_s)) and \
        (a.t_sim_s == b.t_sim_s or (math.isnan(a.t_sim_s) and math.isnan(b.t_sim_s)))


@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 2**64 - 1))
def test_peek_envelope_reads_what_msgpack_read(seed):
    rnd = random.Random(seed)
    payload = fuzz.valid_payload(fuzz.ENVELOPE, rnd) if seed % 3 == 0 else fuzz.fuzz_input(fuzz.ENVELOPE, rnd)
    assert _same_envelope(codec.peek_envelope(payload), ref_peek_envelope(payload))


@given(type_id=st.one_of(st.integers(-2**63, 2**64 - 1), st.booleans(), st.floats(), st.none()),
       version=st.one_of(st.integers(-2**63, 2**64 - 1), st.booleans(), st.floats()),
       tick=st.one_of(st.integers(-2**63, 2**64 - 1), st.floats(), st.booleans(), st.text(max_size=3)),
       t_sim_s=st.one_of(st.floats(), st.integers(-2**63, 2**64 - 1), st.booleans(), st.none()),
       extra=st.integers(0, 20), single=st.booleans(), cut=st.integers(0, 40))
def test_any_head_peeks_as_msgpack_read_it(type_id, version, tick, t_sim_s, extra, single, cut):
    """Every form of each envelope value (ints of every width, float32 and float64 times,
    arrays of 16 items and more), whole or cut short."""
    body = [type_id, version, tick, t_sim_s] + [0] * extra
    try:
        payload = msgpack.packb(body, use_single_float=single)
    except OverflowError:  # a float64 beyond float32's range
        return
    for p in (payload, payload[:cut]):
        assert _same_envelope(codec.peek_envelope(p), ref_peek_envelope(p))


@pytest.mark.parametrize("tick", [0, 127, 128, 255, 256, 65535, 65536, 2**32, 2**64 - 1])
def test_a_tick_of_every_width_by_hand(tick):
    payload = encode(Command(tick, 0.5, 1, -2.0, 0.1))
    env = codec.peek_envelope(payload)
    assert (env.cls, env.tick, env.t_sim_s) == (Command, tick, 0.5)
    assert codec._fast_head(payload) == (7, Command.TYPE_ID, Command.VERSION, tick, 0.5)
