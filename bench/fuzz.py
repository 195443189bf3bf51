"""Fuzzing the decoders: generated and mutated payloads, per decoder
(autocast bench fuzz [--quick] [--inputs N] [--seed S]).

Every decoder of a payload that crosses a process boundary gets ``--inputs`` inputs
(10,000 by default): ``protocol.codec.decode`` once per message type (expecting that
type) and once expecting any type, the object payload codec
(``vehicle_agent.payload``) and the recorder's envelope reader. An input is a valid
message built from the type's hints, then usually mutated: truncated, bits flipped,
bytes overwritten, inserted or cut, two payloads spliced, a node of the message
replaced by a value of another type, a wrong type id or version, an array whose
declared shape does not match its bytes or is enormous (10^12 elements and more), a
well-formed array of another shape or dtype than its field declares (``Array``),
containers and byte strings declaring 2^32 - 1 items the payload does not hold, or
nesting 1,000 to 100,000 levels deep, or 20,000 empty containers side by side.

The contract: a decoder returns a valid message (every field of its declared type,
and the message encodes back to the same bytes' meaning) or raises
``MalformedMessage``; the envelope reader returns an envelope or ``None``. Any other
exception is a bug, and so is an allocation out of proportion to the payload: the
table shows the peak traced allocation of one decode (tracemalloc) and its largest
size beyond a fixed slack per payload byte, and how many inputs broke the bound
``alloc_bound`` (256 KiB + 100 bytes per payload byte). The last line is the headline:
``fuzz: inputs=... other_exceptions=0 over_alloc_bound=0 peak_kib=... peak_per_byte=...``.

The same generators drive the property tests (``tests/test_fuzz.py``) through
hypothesis, so a failure found here can be replayed there and shrunk.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import random
import time
import tracemalloc
import types
import typing
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np

from protocol import messages  # noqa: F401  (registers every message type)
from protocol.codec import (WIRE_DTYPES, MalformedMessage, _packed_to_wire, array_spec, decode, encode, message_types,
                            peek_envelope)
from protocol.messages import PUBLIC_KEY_BYTES, SIGNATURE_BYTES, Pose
from vehicle_agent.payload import ObjectPayload, decode_object, encode_object

MESSAGE_TYPES: tuple[type, ...] = message_types()
ANY = "any"  # decode() without an expected type
OBJECT = "object_payload"  # vehicle_agent.payload.decode_object
ENVELOPE = "envelope"  # the recorder's peek_envelope: an envelope or None, never raises
DECODERS: tuple[str, ...] = (*(cls.__name__ for cls in MESSAGE_TYPES), ANY, OBJECT, ENVELOPE)
_CLASS_OF = {cls.__name__: cls for cls in MESSAGE_TYPES}
_SENTINEL = msgpack.ExtType(99, b"FUZZ-SENTINEL-7f3a")  # replaced by raw bytes after packing
_SENTINEL_BYTES = msgpack.packb(_SENTINEL)
# "No large allocation": one decode's traced peak stays within a fixed slack (an
# exception and its message, the recorder's streaming reader: ~120 KB) plus a multiple of the
# payload's size (msgpack builds one ~72-byte empty list from one byte).
ALLOC_SLACK_BYTES = 256 * 1024
ALLOC_PER_BYTE = 100


def alloc_bound(payload_bytes: int) -> int:
    return ALLOC_SLACK_BYTES + ALLOC_PER_BYTE * payload_bytes


HUGE_DECLARED = (0xdd, 0xdf, 0xc6, 0xdb, 0xc9)  # array32, map32, bin32, str32, ext32 headers


# ------------------------------------------------------------------ valid messages


def wire_value(hint: Any, rnd: random.Random, depth: int = 0) -> Any:
    """A random valid wire value (what ``encode`` would produce) of a field type."""
    origin = typing.get_origin(hint)
    spec = array_spec(hint)
    if spec is not None:  # as declared: its dtype, its fixed dimensions, 0 to 4 along a free one
        shape = [rnd.randint(0, 4) if d is None else d for d in spec.shape]
        return _packed(spec.dtype, shape, rnd) if spec.packed else _array(spec.dtype, shape, rnd)
    if hint is np.ndarray:
        return _array(rnd.choice(sorted(WIRE_DTYPES)), [rnd.randint(0, 4) for _ in range(rnd.randint(1, 2))], rnd)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        optional = len(args) < len(typing.get_args(hint))
        return None if optional and rnd.random() < 0.3 else wire_value(args[0], rnd, depth)
    if origin in (list, tuple) and (origin is list or typing.get_args(hint)[1:] == (Ellipsis,)):
        return [wire_value(typing.get_args(hint)[0], rnd, depth + 1) for _ in range(rnd.randint(0, 3))]
    if origin is tuple:
        return [wire_value(a, rnd, depth + 1) for a in typing.get_args(hint)]
    if origin is dict:
        k, v = typing.get_args(hint)
        return {wire_value(k, rnd, depth + 1): wire_value(v, rnd, depth + 1) for _ in range(rnd.randint(0, 3))}
    if dataclasses.is_dataclass(hint):
        hints = typing.get_type_hints(hint, include_extras=True)
        fields = {f.name: wire_value(hints[f.name], rnd, depth + 1) for f in dataclasses.fields(hint)}
        _make_consistent(fields, rnd)
        return list(fields.values())
    if hint is float:  # within every float field's declared range (protocol.codec invariants)
        return rnd.choice([0.5, 1.5, 2.75, rnd.uniform(1e-3, 3.0)])
    if hint is int:
        return rnd.randint(0, 100)
    if hint is str:
        return rnd.choice(["", "ego", "S.in.0", "green"])
    if hint is bool:
        return rnd.random() < 0.5
    if hint is bytes:
        return bytes(rnd.getrandbits(8) for _ in range(rnd.randint(0, 8)))
    if hint is Any:
        return _plain_value(rnd, depth)
    raise TypeError(f"no generator for {hint!r}")


def _array(dtype_str: str, shape: list[int], rnd: random.Random) -> list:
    """A random array of ``dtype_str`` and ``shape`` on the wire, of values every field
    of its kind takes (``protocol.codec`` invariants): floats in [0, 1], integers a
    strictly ascending run of small ids (one-dimensional) or small counts, other bytes
    any."""
    dtype = np.dtype(dtype_str)
    count = math.prod(shape)
    if dtype.kind == "f":
        values = np.array([rnd.random() for _ in range(count)], dtype)
    elif dtype.kind == "i" and len(shape) == 1:
        values = np.array(sorted(rnd.sample(range(64), count)), dtype)
    elif dtype.kind == "i":
        values = np.array([rnd.randint(0, 100) for _ in range(count)], dtype)
    else:
        raw = bytes(rnd.getrandbits(8) for _ in range(count * dtype.itemsize))
        return [dtype.str, shape, bytes(b & 1 for b in raw) if dtype == np.bool_ else raw]
    return [dtype.str, shape, values.tobytes()]


def _packed(dtype_str: str, shape: list[int], rnd: random.Random) -> list:
    """A random packed array (``protocol.codec._packed_to_wire``) of ``dtype_str`` and
    ``shape``: entries 0, 1 or any bits (-0.0 and NaN included)."""
    dtype = np.dtype(dtype_str)
    uint = np.dtype(f"<u{dtype.itemsize}")
    one = np.ones(1, dtype).view(uint)[0]
    share = np.array([rnd.random()], dtype).view(uint)[0]  # a share (visibility, relevance) is in [0, 1]
    bits = [rnd.choice([0, int(one), int(share)]) for _ in range(math.prod(shape))]
    return _packed_to_wire(np.array(bits, uint).view(dtype).reshape(shape))


def _plain_value(rnd: random.Random, depth: int) -> Any:
    kind = rnd.randrange(7 if depth < 3 else 5)
    if kind == 5:
        return [_plain_value(rnd, depth + 1) for _ in range(rnd.randint(0, 3))]
    if kind == 6:
        return {f"k{i}": _plain_value(rnd, depth + 1) for i in range(rnd.randint(0, 3))}
    return [None, True, rnd.randint(-10, 10), rnd.uniform(-1, 1), "safe"][kind]


def message_body(cls: type, rnd: random.Random) -> list:
    """``[type_id, version, *fields]`` of a random valid message of ``cls``."""
    hints = typing.get_type_hints(cls, include_extras=True)
    fields = {f.name: wire_value(hints[f.name], rnd) for f in dataclasses.fields(cls)}
    _make_consistent(fields, rnd)
    return [cls.TYPE_ID, cls.VERSION, *fields.values()]


def _make_consistent(fields: dict[str, Any], rnd: random.Random) -> None:
    """Bundles check that their receiver masks fit, an object map that its rows and
    tables do (``__post_init__``), and every message its declared invariants (lengths
    that agree, ids once, times that do not go back, keys and signatures of their size):
    make them hold."""
    _keep_invariants(fields, rnd)
    if "object_id" in fields and "visibility" in fields:  # ObjectMap: n objects by m receivers
        n, m = rnd.randint(0, 4), rnd.randint(0, 4)
        shapes = {"object_id": [n], "size_bytes": [n], "centroid_xy": [n, 2], "receivers": [m],
                  "visibility": [n, m], "relevance": [n, m]}
        fields.update({name: (_packed if name in ("visibility", "relevance") else _array)(fields[name][0], shape, rnd)
                       for name, shape in shapes.items()})
        return
    if "receivers" in fields and ("heard" in fields or "decoded" in fields):
        receivers = sorted(rnd.sample(range(64), rnd.randint(0, 4)))
        fields["receivers"] = ["<i8", [len(receivers)], np.array(receivers, "<i8").tobytes()]
        if "heard" in fields:
            senders = sorted(rnd.sample(range(64), len(fields["messages"])))
            fields["senders"] = ["<i8", [len(senders)], np.array(senders, "<i8").tobytes()]
            mask, columns = "heard", len(senders)
        else:
            mask, columns = "decoded", len(fields["receptions"])
        bits = np.array([rnd.random() < 0.5 for _ in range(len(receivers) * columns)], "|b1")
        fields[mask] = ["|b1", [len(receivers), columns], bits.tobytes()]


def _rows(n: int, triple: list, rnd: random.Random) -> list:
    """``triple`` (an array on the wire) with ``n`` rows."""
    return _array(triple[0], [n, *triple[1][1:]], rnd)


def _keep_invariants(fields: dict[str, Any], rnd: random.Random) -> None:
    for name, size in (("public_key", PUBLIC_KEY_BYTES), ("signature", SIGNATURE_BYTES)):
        if type(fields.get(name)) is bytes:
            fields[name] = bytes(rnd.getrandbits(8) for _ in range(size))
    for name in ("beams", "azimuth_steps"):  # a LiDAR has at least one of each
        if name in fields:
            fields[name] = max(1, fields[name])
    if "valid_until_s" in fields:
        fields["valid_from_s"], fields["valid_until_s"] = sorted((fields["valid_from_s"], fields["valid_until_s"]))
    if isinstance(fields.get("live"), list):
        fields["live"] = sorted(set(fields["live"]))
    if isinstance(fields.get("lights"), list):
        fields["lights"] = [light for i, light in enumerate(fields["lights"])
                            if all(light[0] != other[0] for other in fields["lights"][:i])]
    if "lanes" in fields:  # a map's domains are numbered 0, 1, ... in order
        fields["domains"] = [[i, *d[1:]] for i, d in enumerate(fields["domains"])]
    if "trajectory" in fields:  # its times do not go back
        traj = np.frombuffer(fields["trajectory"][2], "<f4").reshape(fields["trajectory"][1]).copy()
        traj[:, 2] = np.sort(traj[:, 2])
        fields["trajectory"] = ["<f4", list(traj.shape), traj.tobytes()]
    if "objects" in fields:  # per-object arrays: a row per object, or none
        n = fields["objects"][0][1][0]
        for name in ("unscheduled", "digests"):
            fields[name] = _rows(rnd.choice([0, n]), fields[name], rnd)
    if "vids" in fields:  # WorldTruth: a row per vehicle
        n = fields["vids"][1][0]
        for name in ("pose", "speed_mps", "size_m"):
            fields[name] = _rows(n, fields[name], rnd)
    if "site_vids" in fields:
        fields["site_xy"] = _rows(fields["site_vids"][1][0], fields["site_xy"], rnd)
    if "received_points" in fields:
        fields["received_points"] = rnd.randint(0, fields["fused_xy"][1][0])


def valid_payload(name: str, rnd: random.Random) -> bytes:
    """A valid payload for decoder ``name`` (any message type for ``any`` and ``envelope``)."""
    if name == OBJECT:
        n = rnd.randint(0, 20)
        pts = np.array([[rnd.uniform(-5, 5) for _ in range(3)] for _ in range(n)], np.float32).reshape(n, 3)
        return encode_object(ObjectPayload(rnd.randint(0, 63), rnd.randint(0, 10**6), rnd.randint(0, 10**4),
                                           rnd.uniform(0, 60), Pose(rnd.uniform(-50, 50), rnd.uniform(-50, 50), 0.3),
                                           1.9, np.zeros(3, np.float32), np.zeros(2, np.float32), pts))
    cls = _CLASS_OF.get(name) or rnd.choice(MESSAGE_TYPES)
    return msgpack.packb(message_body(cls, rnd), use_bin_type=True)


# ------------------------------------------------------------------ mutations


def _nodes(tree: Any, path: tuple = ()) -> list[tuple]:
    """Paths into a wire tree (list indices and dict keys): 32 levels, 64 items a level."""
    out = [path]
    if len(path) >= 32:
        return out
    if isinstance(tree, list):
        for i, v in enumerate(tree[:64]):
            out += _nodes(v, path + (i,))
    elif isinstance(tree, dict):
        for k, v in list(tree.items())[:64]:
            out += _nodes(v, path + (k,))
    return out


def _replace(tree: Any, path: tuple, value: Any) -> Any:
    if not path:
        return value
    head, rest = path[0], path[1:]
    if isinstance(tree, list):
        return [_replace(v, rest, value) if i == head else v for i, v in enumerate(tree)]
    return {k: _replace(v, rest, value) if k == head else v for k, v in tree.items()}


def _arrays(tree: Any) -> list[tuple]:
    """Paths of the ``[dtype, shape, bytes]`` triples in a wire tree."""
    return [p for p in _nodes(tree) if _is_array(_get(tree, p))]


def _get(tree: Any, path: tuple) -> Any:
    for p in path:
        tree = tree[p]
    return tree


def _is_array(v: Any) -> bool:
    return type(v) is list and len(v) == 3 and type(v[0]) is str and type(v[1]) is list and type(v[2]) is bytes


def wrong_value(rnd: random.Random) -> Any:
    """A value of a random msgpack type, including the awkward ones."""
    return rnd.choice([
        None, True, False, -1, 2**63 - 1, -(2**63), 2**64 - 1, math.nan, math.inf, -0.0, "", "x" * 300,
        b"", b"\x00" * 17, [], [[[]]], {}, {"a": 1}, {1: 2}, {b"k": None}, msgpack.ExtType(5, b"ext"),
        msgpack.Timestamp(1, 0), [1, "two", 3.0], rnd.randint(-1000, 1000), rnd.uniform(-1e9, 1e9),
    ])


def _pack_with(tree: Any, path: tuple, raw: bytes) -> bytes:
    """Pack ``tree`` with the node at ``path`` replaced by ``raw`` msgpack bytes."""
    packed = msgpack.packb(_replace(tree, path, _SENTINEL), use_bin_type=True)
    return packed.replace(_SENTINEL_BYTES, raw, 1)


def _nested(depth: int, rnd: random.Random) -> bytes:
    opener = rnd.choice([b"\x91", b"\x81\xa1k"])  # a 1-item array, or a 1-entry map {"k": ...}
    return opener * depth + b"\xc0"


def _declared_huge(rnd: random.Random) -> bytes:
    head = rnd.choice(HUGE_DECLARED)
    return bytes([head]) + b"\xff\xff\xff\xff" + (b"\x01" if head == 0xc9 else b"") + b"\x00" * rnd.randint(0, 16)


def _bad_array(triple: list, rnd: random.Random) -> list:
    dtype, shape, raw = triple
    kind = rnd.randrange(9)
    if kind == 0:  # enormous declared shape, few bytes
        huge = [[10**6, 10**6], [10**12], [2**63, 2], [2**64 - 1], [0, 2**64 - 1], [2**32] * 8]
        return [dtype, rnd.choice(huge), raw]
    if kind == 1:  # a shape that does not match the bytes
        return [dtype, [d + rnd.choice([-1, 1, 7]) for d in shape] or [1], raw]
    if kind == 2:  # too many or bad dimensions
        return [dtype, rnd.choice([[1] * rnd.randint(9, 100), [-1], [1.5], ["2"], [None], [True, 1], 3]), raw]
    if kind == 3:  # a dtype that is not allowed on the wire
        return [rnd.choice(["O", "<c16", "<U4", "V8", ">f8", "float64", "", "\x00", "<f8" * 50]), shape, raw]
    if kind == 4:  # bytes cut or grown
        return [dtype, shape, raw[:rnd.randint(0, max(len(raw) - 1, 0))] if raw else b"\x00"]
    if kind == 5:  # the bytes of another type
        return [dtype, shape, rnd.choice(["text", None, [1, 2], 3])]
    if kind == 6 and type(shape) is list:  # a well-formed array of another shape than declared: flat, or one more axis
        count = math.prod(shape) if all(type(d) is int for d in shape) else 0
        return [dtype, rnd.choice([[*shape, 1], [1, *shape]] + ([[count]] if len(shape) > 1 else [])), raw]
    if kind == 7 and type(raw) is bytes:  # a well-formed array of another wire dtype than declared
        other = np.dtype(rnd.choice(sorted(WIRE_DTYPES)))
        n = len(raw) // other.itemsize
        return [other.str, [n], raw[:n * other.itemsize]]
    return triple[:rnd.randint(0, 2)] + [raw] * rnd.randint(0, 2)  # wrong length of the triple


def mutate(payload: bytes, name: str, rnd: random.Random) -> bytes:
    """One mutation of a valid payload (or a fresh piece of garbage)."""
    kind = rnd.randrange(6 if name == OBJECT else 14)  # the object payload is no msgpack: bytes only
    if kind == 0:  # truncated
        return payload[:rnd.randint(0, max(len(payload) - 1, 0))]
    if kind == 1:  # bit flips
        b = bytearray(payload)
        for _ in range(rnd.randint(1, 8)):
            if b:
                b[rnd.randrange(len(b))] ^= 1 << rnd.randrange(8)
        return bytes(b)
    if kind == 2:  # bytes overwritten, inserted or cut
        b = bytearray(payload)
        i = rnd.randint(0, len(b))
        op = rnd.randrange(3)
        if op == 0 and b:
            b[min(i, len(b) - 1)] = rnd.getrandbits(8)
        elif op == 1:
            b[i:i] = bytes(rnd.getrandbits(8) for _ in range(rnd.randint(1, 8)))
        else:
            del b[i:i + rnd.randint(1, 8)]
        return bytes(b)
    if kind == 3:  # two payloads spliced
        other = valid_payload(name if rnd.random() < 0.5 else ANY, rnd)
        return payload[:rnd.randint(0, len(payload))] + other[rnd.randint(0, len(other)):]
    if kind == 4:  # random bytes
        return bytes(rnd.getrandbits(8) for _ in range(rnd.randint(0, 64)))
    if kind == 5:  # a whole payload declaring what it does not hold
        return _declared_huge(rnd)
    try:
        tree = msgpack.unpackb(payload, raw=False, strict_map_key=False)
    except Exception:
        return payload
    if not isinstance(tree, list) or len(tree) < 2:
        return payload
    try:
        return _mutate_tree(tree, kind, payload, rnd)
    except (OverflowError, ValueError, TypeError):  # a mutation msgpack cannot pack (an int beyond 64 bits)
        return payload


def _mutate_tree(tree: list, kind: int, payload: bytes, rnd: random.Random) -> bytes:
    if kind == 6:  # a node of the message replaced by a value of another type
        path = rnd.choice(_nodes(tree))
        return msgpack.packb(_replace(tree, path, wrong_value(rnd)), use_bin_type=True)
    if kind == 7:  # wrong type id or version
        i = rnd.randrange(2)
        was = tree[i] if type(tree[i]) is int and abs(tree[i]) < 2**62 else 1
        tree[i] = rnd.choice([was + 1, was - 1, -1, 0, 2**64 - 1, True, float(was), str(was), None,
                              rnd.choice(MESSAGE_TYPES).TYPE_ID])
        return msgpack.packb(tree, use_bin_type=True)
    if kind == 8:  # an array whose declared shape, dtype or bytes do not match
        arrays = _arrays(tree)
        if arrays:
            path = rnd.choice(arrays)
            return msgpack.packb(_replace(tree, path, _bad_array(_get(tree, path), rnd)), use_bin_type=True)
        return msgpack.packb(tree[:-1], use_bin_type=True)
    if kind == 9:  # a field too many or too few
        tree = tree + [wrong_value(rnd)] if rnd.random() < 0.5 else tree[:-1]
        return msgpack.packb(tree, use_bin_type=True)
    if kind == 10:  # deep nesting in place of a node
        return _pack_with(tree, rnd.choice(_nodes(tree)[1:]), _nested(rnd.choice([20, 1000, 1100, 100_000]), rnd))
    if kind == 11:  # a container or string declaring 2^32 - 1 items in place of a node
        return _pack_with(tree, rnd.choice(_nodes(tree)[1:]), _declared_huge(rnd))
    if kind == 12:  # a wide container of empty ones (msgpack's worst bytes-to-objects ratio) in place of a node
        n = rnd.choice([1_000, 20_000])
        wide = b"\xdd" + n.to_bytes(4, "big") + rnd.choice([b"\x90", b"\x80"]) * n
        return _pack_with(tree, rnd.choice(_nodes(tree)[1:]), wide)
    return payload  # unmutated: the valid case must keep decoding


def fuzz_input(name: str, rnd: random.Random) -> bytes:
    """One input for decoder ``name``: a valid payload, mutated once or a few times."""
    payload = valid_payload(name, rnd)
    for _ in range(rnd.choice([1, 1, 1, 2, 3])):
        payload = mutate(payload, name, rnd)
    return payload


# ------------------------------------------------------------------ the contract


def decoder(name: str) -> Callable[[bytes], Any]:
    if name == ANY:
        return decode
    if name == OBJECT:
        return decode_object
    if name == ENVELOPE:
        return peek_envelope
    cls = _CLASS_OF[name]
    return lambda payload: decode(payload, cls)


def conforms(value: Any, hint: Any) -> bool:
    """Is ``value`` of field type ``hint`` (as ``decode`` promises)?"""
    origin = typing.get_origin(hint)
    spec = array_spec(hint)
    if spec is not None:
        return isinstance(value, np.ndarray) and spec.fits(value)
    if hint is np.ndarray:
        return isinstance(value, np.ndarray) and value.dtype.str in WIRE_DTYPES
    if origin in (typing.Union, types.UnionType):
        return any(conforms(value, a) for a in typing.get_args(hint))
    if hint is type(None):
        return value is None
    if origin is list or (origin is tuple and typing.get_args(hint)[1:] == (Ellipsis,)):
        return isinstance(value, origin) and all(conforms(v, typing.get_args(hint)[0]) for v in value)
    if origin is tuple:
        args = typing.get_args(hint)
        return isinstance(value, tuple) and len(value) == len(args) and all(map(conforms, value, args))
    if origin is dict:
        k, v = typing.get_args(hint)
        return isinstance(value, dict) and all(conforms(a, k) and conforms(b, v) for a, b in value.items())
    if dataclasses.is_dataclass(hint):
        hints = typing.get_type_hints(hint, include_extras=True)
        return type(value) is hint and all(conforms(getattr(value, f.name), hints[f.name])
                                           for f in dataclasses.fields(hint))
    if hint is float:
        return type(value) is float
    if hint is int:
        return type(value) is int
    if hint in (str, bytes, bool):
        return type(value) is hint
    if hint is Any:
        return True
    return False


def check(name: str, payload: bytes) -> str:
    """``"valid"`` or ``"malformed"``; raises AssertionError on a broken contract (and
    lets any other exception through: that is the bug the fuzzing looks for)."""
    try:
        got = decoder(name)(payload)
    except MalformedMessage:
        if name == ENVELOPE:
            raise AssertionError("the envelope reader raised instead of returning None") from None
        return "malformed"
    if name == ENVELOPE:
        return "malformed" if got is None else "valid"
    if name == OBJECT:
        assert isinstance(got, ObjectPayload) and got.points_sensor.shape == ((len(payload) - 64) // 6, 3)
        return "valid"
    cls = type(got)
    assert cls in MESSAGE_TYPES and (name == ANY or cls.__name__ == name), f"decoded a {cls.__name__}"
    assert conforms(got, cls), f"{got!r:.200} does not conform to {cls.__name__}"
    again = decode(encode(got), cls)  # a valid message survives its own round trip
    assert encode(again) == encode(got)
    return "valid"


# ------------------------------------------------------------------ the bench


def decode_peak(dec: Callable[[bytes], Any], payload: bytes) -> int:
    """The traced allocation peak (bytes) of one decode, whatever it raises; the caller
    has started tracemalloc."""
    base = tracemalloc.get_traced_memory()[0]
    tracemalloc.reset_peak()
    try:
        dec(payload)
    except Exception:  # noqa: BLE001  only the allocation is measured here
        pass
    return tracemalloc.get_traced_memory()[1] - base


@dataclass
class Tally:
    inputs: int = 0
    valid: int = 0
    malformed: int = 0
    other: int = 0
    peak_bytes: int = 0  # the largest traced peak of one decode
    peak_per_byte: float = 0.0  # the largest (peak - slack) / payload size
    over_bound: int = 0  # decodes whose peak broke alloc_bound
    max_payload_bytes: int = 0
    seconds: float = 0.0
    first_other: str = ""


def run_decoder(name: str, n: int, seed: int) -> Tally:
    """``n`` inputs through decoder ``name``: a timed pass, then a pass under tracemalloc."""
    rnd = random.Random(f"{seed}:{name}")
    inputs = [fuzz_input(name, rnd) for _ in range(n)]
    tally = Tally(inputs=n, max_payload_bytes=max(map(len, inputs)))
    outcomes = []
    t0 = time.perf_counter()
    for payload in inputs:
        try:
            outcomes.append(check(name, payload))
        except Exception as exc:  # noqa: BLE001  the bench counts what the tests forbid
            outcomes.append("other")
            if not tally.first_other:
                tally.first_other = f"{type(exc).__name__}: {exc!s:.120} on {payload[:48]!r}"
    tally.seconds = time.perf_counter() - t0
    tally.valid, tally.malformed, tally.other = (outcomes.count(k) for k in ("valid", "malformed", "other"))
    dec = decoder(name)
    tracemalloc.start()
    try:
        for payload in inputs:
            peak = decode_peak(dec, payload)
            tally.peak_bytes = max(tally.peak_bytes, peak)
            tally.peak_per_byte = max(tally.peak_per_byte, (peak - ALLOC_SLACK_BYTES) / max(len(payload), 1))
            tally.over_bound += peak > alloc_bound(len(payload))
    finally:
        tracemalloc.stop()
    return tally


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="autocast bench fuzz", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="100 inputs per decoder (a few seconds)")
    ap.add_argument("--inputs", type=int, default=None, help="inputs per decoder (default 10000, quick 100)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--decoders", nargs="+", default=list(DECODERS), choices=DECODERS, metavar="NAME")
    args = ap.parse_args(argv)
    n = args.inputs if args.inputs is not None else (100 if args.quick else 10_000)
    print(f"{'decoder':<14} {'inputs':>7} {'valid':>6} {'malformed':>9} {'other':>5} {'peak KiB':>9} "
          f"{'peak/byte':>9} {'>bound':>6} {'max input':>9} {'us/input':>8}")
    total = Tally()
    t0 = time.perf_counter()
    for name in args.decoders:
        t = run_decoder(name, n, args.seed)
        print(f"{name:<14} {t.inputs:>7} {t.valid:>6} {t.malformed:>9} {t.other:>5} {t.peak_bytes / 1024:>9.1f} "
              f"{max(t.peak_per_byte, 0.0):>9.1f} {t.over_bound:>6} {t.max_payload_bytes:>9} "
              f"{t.seconds / t.inputs * 1e6:>8.1f}")
        if t.first_other:
            print(f"  first other exception: {t.first_other}")
        total.inputs += t.inputs
        total.other += t.other
        total.over_bound += t.over_bound
        total.peak_bytes = max(total.peak_bytes, t.peak_bytes)
        total.peak_per_byte = max(total.peak_per_byte, t.peak_per_byte)
    print(f"({time.perf_counter() - t0:.1f} s; peak: the largest tracemalloc peak of one decode; peak/byte: the "
          f"largest (peak - {ALLOC_SLACK_BYTES // 1024} KiB) / input size; >bound: decodes above "
          f"{ALLOC_SLACK_BYTES // 1024} KiB + {ALLOC_PER_BYTE} x input size; us/input: decode and check, "
          f"without tracemalloc)")
    print(f"fuzz: inputs={total.inputs} other_exceptions={total.other} over_alloc_bound={total.over_bound} "
          f"peak_kib={total.peak_bytes / 1024:.1f} peak_per_byte={max(total.peak_per_byte, 0.0):.1f}")
    return 0 if total.other == 0 and total.over_bound == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
