"""msgpack codec for the versioned message dataclasses.

A message travels as one msgpack array: ``[type_id, version, field_1, ..., field_n]``
in the dataclass's field order. numpy arrays travel as ``[dtype_str, shape, bytes]``
with the bytes packed from a ``memoryview`` (no ``tobytes`` copy, no ``tolist``); a
field declared ``Array(..., packed=True)`` (a table of shares, mostly exactly 0 or 1)
as ``[dtype_str, shape, ones, others, values]``: two bit masks and the other entries'
values, every entry's bits as they were (``_packed_to_wire``); nested dataclasses
travel as plain arrays of their fields. Decoding checks the type,
the version, the field count and every field's type, an array field's dtype and shape
as the message declares them (``Array``), and raises ``MalformedMessage`` on any
mismatch, so a receiver can count and drop a bad payload without crashing: a
trajectory of two columns, say, would otherwise have reached a planner that indexes
three, and its vehicle's fail-safe brake.

Hostile input allocates no more than the bytes it brings: msgpack refuses a container
or byte string whose declared length exceeds the payload, an array's declared shape
must be filled by the bytes present before anything is built from them, nesting
deeper than msgpack's stack (1024 levels) is refused, and a free-form (``Any``) value
may hold only msgpack's plain types, at most ``MAX_ANY_DEPTH`` levels deep. The
remaining cost is msgpack's: a payload of n bytes builds at most ~80 n bytes of
Python objects (one empty list per byte; ``autocast bench fuzz`` measures it). A
packed array's masks hold a bit per entry, so each mask byte brought builds 8 entries:
32 bytes of float32 or 64 of float64 per byte.
"""

from __future__ import annotations

import dataclasses
import functools
import io
import math
import struct
import threading
import types
import typing
from collections.abc import Sequence
from typing import Any

import msgpack
import numpy as np


class MalformedMessage(ValueError):
    """A payload that is not a valid message of the expected type and version."""


# dtypes an array field may carry on the wire; anything else is refused on decode.
WIRE_DTYPES = frozenset(["<f4", "<f8", "<i2", "<i4", "<i8", "|u1", "|i1", "<u2", "<u4", "|b1"])
_DTYPE_OF = {name: np.dtype(name) for name in WIRE_DTYPES}
MAX_ARRAY_DIMS = 8  # no field has more than 2; numpy's own limit is 64
# a packed array's float dtypes: the unsigned integer of the same width, and 1.0's bits in it
_BITS_OF = {"<f4": (np.dtype("<u4"), 0x3F800000), "<f8": (np.dtype("<u8"), 0x3FF0000000000000)}
MAX_ANY_DEPTH = 16  # containers within a free-form value (an outcome, channel statistics)
_PLAIN = (type(None), bool, int, float, str, bytes)

_REGISTRY: dict[int, type] = {}
_HINTS: dict[type, list[tuple[str, Any]]] = {}


@dataclasses.dataclass(frozen=True, slots=True)
class Array:
    """What an array field holds, declared with the field:
    ``trajectory: Annotated[np.ndarray, Array("<f4", (None, 3))]`` is float32 with three
    columns and any number of rows (``None``: a free dimension). The decoder refuses any
    other dtype or shape; the encoder raises ``TypeError`` at the sender."""

    dtype: str  # one of WIRE_DTYPES
    shape: tuple[int | None, ...]
    packed: bool = False  # a float table of shares, mostly exactly 0 or 1: on the wire as two masks and the rest

    def __post_init__(self) -> None:
        if self.dtype not in WIRE_DTYPES:
            raise ValueError(f"dtype {self.dtype!r} cannot go on the wire")
        if self.packed and self.dtype not in _BITS_OF:
            raise ValueError(f"a packed array is of {' or '.join(sorted(_BITS_OF))}, not {self.dtype!r}")
        if len(self.shape) > MAX_ARRAY_DIMS:
            raise ValueError(f"{len(self.shape)} dimensions: the decoder refuses more than {MAX_ARRAY_DIMS}")

    def fits(self, arr: np.ndarray) -> bool:
        shape = arr.shape
        return arr.dtype.str == self.dtype and len(shape) == len(self.shape) and \
            all(d is None or d == n for d, n in zip(self.shape, shape))

    def __str__(self) -> str:
        return f"{np.dtype(self.dtype)} ({', '.join('n' if d is None else str(d) for d in self.shape)})"


def array_spec(hint: Any) -> Array | None:
    """The ``Array`` of a field type ``Annotated[np.ndarray, Array(...)]``, else None."""
    if typing.get_origin(hint) is typing.Annotated:
        base, *extras = typing.get_args(hint)
        if base is np.ndarray:
            return next((e for e in extras if isinstance(e, Array)), None)
    return None


# ----------------------------------------------------------------------- invariants

MAP_BOUND_M = 1000.0  # every map lies within this of the origin on both axes (MapMsg checks it)
# beyond the map: a vehicle driving off its end (a 40 s scenario at 40 m/s: 1.6 km), a LiDAR
# return (100 m) and a trajectory's horizon (3 s) farther
MAP_MARGIN_M = 2000.0
COORD_BOUND_M = MAP_BOUND_M + MAP_MARGIN_M  # what a world-frame coordinate may be: the map's bound plus the margin
MAX_VID = 1 << 16  # vehicle ids are in [0, MAX_VID) (the agreement's members kernel counts them so)
MAX_TICK = 1 << 31
MAX_T_SIM_S = 1e6


@dataclasses.dataclass(frozen=True, slots=True)
class Invariant:
    """A property the values of a message's (or record's) ``fields`` must have, declared
    with the message in its ``INVARIANTS`` and checked by the codec as it decodes them
    (``decode``, and ``decode_fields`` for the invariants whose fields it reads): ``test``
    takes the fields' decoded values and returns None, or what is wrong; the decoder then
    raises ``MalformedMessage`` naming the first field. Build them with the functions
    below (``finite``, ``within``, ``in_map``, ``same_rows``, ...)."""

    fields: tuple[str, ...]
    test: typing.Callable[..., str | None]


def _floats(value: Any) -> np.ndarray:
    return value if isinstance(value, np.ndarray) else np.asarray(value, dtype=np.float64)


def finite(*fields: str) -> tuple[Invariant, ...]:
    """Each field (a number or an array) is finite: no NaN, no infinity."""
    def test(v: Any) -> str | None:
        if isinstance(v, float):
            return None if math.isfinite(v) else f"{v!r} is not finite"
        return None if np.isfinite(v).all() else "holds a value that is not finite"
    return tuple(Invariant((f,), test) for f in fields)


def within(field: str, lo: float, hi: float, columns: slice | None = None) -> Invariant:
    """Every value of ``field`` (a number, an array, or the ``columns`` of a table) lies in
    [lo, hi]; NaN never does (an array's min and max are NaN if any entry is)."""
    def test(v: Any) -> str | None:
        if type(v) is float or type(v) is int:
            return None if lo <= v <= hi else f"{_brief(v)} is not in [{lo:g}, {hi:g}]"
        a = v if columns is None else v[:, columns]
        if not a.size or (lo <= a.min() and a.max() <= hi):
            return None
        return f"holds a value not in [{lo:g}, {hi:g}]"
    return Invariant((field,), test)


def in_map(field: str, columns: slice | None = slice(0, 2)) -> Invariant:
    """World-frame coordinates: finite and within ``COORD_BOUND_M`` of the origin (the
    ``columns`` of a table, x and y by default; a number: itself)."""
    return within(field, -COORD_BOUND_M, COORD_BOUND_M, columns)


def vid(*fields: str) -> tuple[Invariant, ...]:
    """Each field is a vehicle id, or an array of them: in [0, MAX_VID)."""
    return tuple(within(f, 0, MAX_VID - 1) for f in fields)


def ascending(field: str, lo: int = 0, hi: int = MAX_VID - 1) -> Invariant:
    """Ids strictly ascending (in order, none twice), in [lo, hi] (vehicle ids by default)."""
    def test(v: np.ndarray) -> str | None:
        if len(v) and not (lo <= v[0] and v[-1] <= hi):
            return f"holds an id not in [{lo}, {hi}]"
        return None if len(v) < 2 or (v[1:] > v[:-1]).all() else "is not strictly ascending"
    return Invariant((field,), test)


def unique(field: str) -> Invariant:
    """No value twice."""
    return Invariant((field,), lambda v: None if len(set(v.tolist())) == len(v) else "holds a value twice")


def waypoints(field: str) -> Invariant:
    """A trajectory ``[x_m, y_m, t_sim_s]`` per row: on the map (``in_map``), its times in
    [0, MAX_T_SIM_S] and never going back. One check, as a vehicle reads one trajectory
    of every control message it hears."""
    bound = COORD_BOUND_M

    def test(a: np.ndarray) -> str | None:  # a loop over a few rows: a quarter of numpy's calls' time
        last = 0.0
        for i, (x, y, t) in enumerate(a.tolist()):  # NaN fails every comparison
            if not (-bound <= x <= bound and -bound <= y <= bound):
                return f"waypoint {i} is not within {bound:g} m of the origin"
            if not last <= t <= MAX_T_SIM_S:
                return f"waypoint {i}'s time goes back (or is not in [0, {MAX_T_SIM_S:g}])"
            last = t
        return None
    return Invariant((field,), test)


def nondecreasing(field: str, column: int | None = None) -> Invariant:
    """Never goes back (a column of a table: times along a trajectory)."""
    def test(v: np.ndarray) -> str | None:
        a = v if column is None else v[:, column]
        return None if len(a) < 2 or bool((a[1:] >= a[:-1]).all()) else "goes back"
    return Invariant((field,), test)


def at_most(field: str, n: int) -> Invariant:
    """At most ``n`` items (rows)."""
    return Invariant((field,), lambda v: None if len(v) <= n else f"{len(v)} items, at most {n}")


def same_rows(field: str, like: str, of: typing.Callable[[Any], Any] = lambda v: v, or_none: bool = False) -> Invariant:
    """``field`` has a row per row of ``like`` (``of(like)``: a record's array); with
    ``or_none``, or none at all."""
    def test(v: Any, w: Any) -> str | None:
        n = len(of(w))
        return None if len(v) == n or (or_none and len(v) == 0) else \
            f"{len(v)} rows for {n}{' (or none)' if or_none else ''}"
    return Invariant((field, like), test)


def byte_length(field: str, n: int) -> Invariant:
    return Invariant((field,), lambda v: None if len(v) == n else f"{len(v)} bytes, not {n}")


def each(field: str, inner: Invariant) -> Invariant:
    """``inner`` (of one field) holds for every item of the list ``field``."""
    def test(items: list) -> str | None:
        for i, v in enumerate(items):
            if (problem := inner.test(v)) is not None:
                return f"[{i}] {problem}"
        return None
    return Invariant((field,), test)


# every message's envelope fields
STAMPED = (within("tick", 0, MAX_TICK), within("t_sim_s", 0.0, MAX_T_SIM_S))


def invariants(cls: type) -> tuple[Invariant, ...]:
    """What a message or record class declares (``INVARIANTS``), checked for its fields."""
    declared = tuple(getattr(cls, "INVARIANTS", ()))
    names = {f.name for f in dataclasses.fields(cls)}
    for inv in declared:
        if not set(inv.fields) <= names:
            raise TypeError(f"{cls.__name__}: an invariant of {inv.fields} names no field of it")
    return declared


def _invariant_lines(env: dict[str, Any], cls: type, names: Sequence[str], indent: str) -> list[str]:
    """Generated lines that run ``cls``'s invariants over the values read so far
    (``a<i>`` is ``names[i]``), those whose fields are all among ``names``: each failing
    one sets ``at`` to its first field's place and raises ``_FieldError``."""
    where = {name: i for i, name in enumerate(names)}
    lines = []
    for j, inv in enumerate(invariants(cls)):
        if not all(f in where for f in inv.fields):
            continue
        env[f"inv{j}"] = inv.test
        env["_bad"] = _bad
        lines += [f"{indent}problem = inv{j}({', '.join(f'a{where[f]}' for f in inv.fields)})",
                  f"{indent}if problem is not None:",
                  f"{indent}    at = {where[inv.fields[0]]}",
                  f"{indent}    _bad(problem)"]
    return lines


def message(type_id: int, version: int = 1):
    """Class decorator: a frozen, slotted dataclass registered as wire type ``type_id``."""

    def wrap(cls):
        cls = dataclasses.dataclass(frozen=True, slots=True)(cls)
        if type_id in _REGISTRY:
            raise ValueError(f"message type id {type_id} used twice")
        cls.TYPE_ID = type_id
        cls.VERSION = version
        _REGISTRY[type_id] = cls
        return cls

    return wrap


def record(cls):
    """Class decorator for a nested (non top-level) record: frozen, slotted dataclass."""
    return dataclasses.dataclass(frozen=True, slots=True)(cls)


def message_types() -> tuple[type, ...]:
    """Every registered message type, by type id."""
    return tuple(_REGISTRY[k] for k in sorted(_REGISTRY))


def message_class(type_id: int) -> type | None:
    """The registered message dataclass of a wire type id (None if unknown)."""
    return _REGISTRY.get(type_id)


@dataclasses.dataclass(frozen=True, slots=True)
class Envelope:
    """The head of a message: its class and timing, read without decoding the rest."""

    cls: type
    tick: int
    t_sim_s: float


def peek_envelope(payload: bytes) -> Envelope | None:
    """The type, tick and sim time at the head of a message; ``None`` if it is no valid envelope.

    Reads a few dozen bytes whatever the payload's size. The head as the codec packs it
    (an array of up to 65535 items, the type id and version as one byte each, the tick
    as an unsigned int, the time as a float64) is read straight from the bytes; any
    other form through msgpack.
    """
    head = _fast_head(payload)
    if head is not None:
        n, type_id, version, tick, t_sim_s = head
        cls = message_class(type_id)
        if cls is None or version != cls.VERSION or n != 2 + _field_count(cls):
            return None
        return Envelope(cls, tick, t_sim_s)
    unpacker = msgpack.Unpacker(io.BytesIO(payload), read_size=64, raw=False, strict_map_key=False)
    try:
        n = unpacker.read_array_header()
        type_id, version, tick, t_sim_s = (unpacker.unpack() for _ in range(4))
    except Exception:  # msgpack raises several unrelated exception types
        return None
    cls = message_class(type_id) if isinstance(type_id, int) and not isinstance(type_id, bool) else None
    if cls is None or version != cls.VERSION or n != 2 + len(dataclasses.fields(cls)):
        return None
    if not isinstance(tick, int) or isinstance(t_sim_s, bool) or not isinstance(t_sim_s, (int, float)):
        return None
    return Envelope(cls, tick, float(t_sim_s))


_UINT_AFTER = {0xcc: struct.Struct(">B"), 0xcd: struct.Struct(">H"), 0xce: struct.Struct(">I"),
               0xcf: struct.Struct(">Q")}  # msgpack's unsigned ints by their head byte
_FLOAT64 = struct.Struct(">d")


def _fast_head(payload: bytes) -> tuple[int, int, int, int, float] | None:
    """(item count, type id, version, tick, t_sim_s) of a payload whose head has the
    codec's usual form (``peek_envelope``), else None: the same values msgpack reads."""
    size = len(payload)
    if size < 12:
        return None
    first = payload[0]
    if 0x90 <= first <= 0x9f:  # fixarray
        n, at = first & 0x0f, 1
    elif first == 0xdc:  # array 16
        n, at = (payload[1] << 8) | payload[2], 3
    else:
        return None
    type_id, version, kind = payload[at], payload[at + 1], payload[at + 2]
    if type_id >= 0x80 or version >= 0x80:  # positive fixints only
        return None
    at += 3
    if kind < 0x80:
        tick = kind
    else:
        uint = _UINT_AFTER.get(kind)
        if uint is None or at + uint.size + 9 > size:
            return None
        (tick,) = uint.unpack_from(payload, at)
        at += uint.size
    if at + 9 > size or payload[at] != 0xcb:
        return None
    return n, type_id, version, tick, _FLOAT64.unpack_from(payload, at + 1)[0]


@functools.cache
def _field_count(cls: type) -> int:
    return len(dataclasses.fields(cls))


def _hints(cls) -> list[tuple[str, Any]]:
    got = _HINTS.get(cls)
    if got is None:
        resolved = typing.get_type_hints(cls, include_extras=True)  # an array's Array is an extra
        got = [(f.name, resolved[f.name]) for f in dataclasses.fields(cls)]
        _HINTS[cls] = got
    return got


def _checked_array_to_wire(spec: Array, value: Any, field: str) -> list:
    """An array field's value on the wire; raises ``TypeError`` naming the field if it
    is not the ``Array`` the message declares (a sender's bug, caught where it is)."""
    if not isinstance(value, np.ndarray) or not spec.fits(value):
        got = f"{value.dtype} {list(value.shape)}" if isinstance(value, np.ndarray) else type(value).__name__
        raise TypeError(f"{field}: expected {spec}, got {got}")
    return _packed_to_wire(value) if spec.packed else _array_to_wire(value)


def _packed_to_wire(value: np.ndarray, dtype_str: str | None = None) -> list:
    """A packed array on the wire: ``[dtype_str, shape, ones, others, values]``, where
    ``ones`` and ``others`` are bit masks over the entries in C order (``np.packbits``:
    a byte per 8 entries, the first entry in its top bit, the padding bits 0) of the
    entries whose bits are 1.0's and of those that are neither 1.0 nor +0.0; ``values``
    are the latter's bytes, in order. Every entry's bits come back as they were (-0.0
    and NaN are "others"). A vehicle's object map is such a table twice, with most
    entries 0 (relevance) or 0 and 1 (visibility): a control message shrank ~3x."""
    flat = np.ascontiguousarray(value).reshape(-1)
    if dtype_str is None:  # a generated encoder passes the declared dtype's, which is flat.dtype.str
        dtype_str = flat.dtype.str
    uint, one = _BITS_OF[dtype_str]
    bits = flat.view(uint)
    ones = bits == one
    others = (bits != 0) ^ ones  # neither 1.0 nor +0.0: ones are all nonzero
    return [dtype_str, list(value.shape), np.packbits(ones).tobytes(), np.packbits(others).tobytes(),
            flat[others].tobytes()]


def _array_to_wire(value: np.ndarray) -> list:
    arr = np.ascontiguousarray(value)
    if arr.dtype.str not in WIRE_DTYPES:
        raise TypeError(f"dtype {arr.dtype} cannot go on the wire")
    raw = memoryview(arr).cast("B") if arr.size else b""  # a view with a 0 in its shape cannot be cast
    return [arr.dtype.str, list(arr.shape), raw]


def _declared_array_to_wire(value: np.ndarray, dtype_str: str) -> list:
    """``_array_to_wire`` of an array of its field's declared dtype (``dtype_str``, which
    its ``dtype.str`` is): a generated encoder checks dtype and shape inline, where
    ``Array.fits`` and the dtype's string were ~1 us of each of a control message's ten
    arrays."""
    arr = np.ascontiguousarray(value)
    return [dtype_str, list(arr.shape), memoryview(arr).cast("B") if arr.size else b""]


def _to_wire(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return _array_to_wire(value)
    if dataclasses.is_dataclass(value):
        return _fields_to_wire(type(value))(value)
    if isinstance(value, (list, tuple)):
        return [_to_wire(v) for v in value]
    if isinstance(value, dict):
        return {k: _to_wire(v) for k, v in value.items()}
    if isinstance(value, np.generic):
        return value.item()
    return value


_ENCODERS: dict[type, typing.Callable[[Any], list]] = {}
# Encoders and converters are built on first use, in whichever thread needs one first (a
# process decodes in Zenoh's callback threads and its own). One builder at a time; a
# record's placeholder, which lets a record contain itself, waits for its builder if
# another thread calls it meanwhile (it raised IndexError: a recorder died so, mirroring
# a message while its fetcher thread built the same class's converter).
_BUILDING = threading.RLock()


def _built_once(cache: dict, key: Any, build: typing.Callable[[Any], Any]) -> Any:
    """``cache[key]``, built (under ``_BUILDING``) by the first thread that asks."""
    got = cache.get(key)
    if got is None:
        with _BUILDING:
            got = cache.get(key)
            if got is None:
                got = cache[key] = build(key)
    return got


def _placeholder(built: list) -> typing.Callable[[Any], Any]:
    """Calls ``built[0]`` once the builder holding ``_BUILDING`` has put it there."""

    def call(value: Any) -> Any:
        if not built:
            with _BUILDING:
                pass
        return built[0](value)

    return call


def _fields_to_wire(cls: type) -> typing.Callable[[Any], list]:
    """A record's fields on the wire, ``[_to_wire(getattr(value, name)) for each field]``,
    written out as one generated function per class: a field of its declared type
    (exactly an int, a float, an ndarray, a record, a list of records) is converted
    inline, anything else goes through ``_to_wire``. The same values, so the same bytes;
    but an array field takes only an array of its declared ``Array`` (``TypeError``)."""
    return _built_once(_ENCODERS, cls, _build_fields_to_wire)


def _build_fields_to_wire(cls: type) -> typing.Callable[[Any], list]:
    built: list[typing.Callable[[Any], list]] = []
    _ENCODERS[cls] = _placeholder(built)  # a record that (indirectly) contains itself
    env: dict[str, Any] = {"_to_wire": _to_wire, "_array_to_wire": _array_to_wire, "ndarray": np.ndarray,
                           "_checked_array_to_wire": _checked_array_to_wire, "_packed_to_wire": _packed_to_wire,
                           "_declared_array_to_wire": _declared_array_to_wire}
    items = []
    for i, (name, hint) in enumerate(_hints(cls)):
        v = f"value.{name}"
        inner = typing.get_args(hint)[0] if typing.get_origin(hint) is list else None
        spec, inner_spec = array_spec(hint), array_spec(inner)
        if spec is not None:
            env[f"a{i}"], env[f"d{i}"] = spec, np.dtype(spec.dtype)
            fits = "".join(f" and v.shape[{axis}] == {d}" for axis, d in enumerate(spec.shape) if d is not None)
            to_wire = f"{'_packed_to_wire' if spec.packed else '_declared_array_to_wire'}(v, {spec.dtype!r})"
            items.append(f"{to_wire} if type(v := {v}) is ndarray and v.dtype == d{i} and v.ndim == {len(spec.shape)}"
                         f"{fits} else _checked_array_to_wire(a{i}, v, '{cls.__name__}.{name}')")
        elif inner_spec is not None:
            env[f"a{i}"] = inner_spec
            items.append(f"[_checked_array_to_wire(a{i}, x, '{cls.__name__}.{name}[]') for x in {v}]")
        elif hint in (int, float, str, bool, bytes):
            items.append(f"v if type(v := {v}) is {hint.__name__} else _to_wire(v)")
        elif hint is np.ndarray:
            items.append(f"_array_to_wire(v) if type(v := {v}) is ndarray else _to_wire(v)")
        elif dataclasses.is_dataclass(hint):
            env[f"t{i}"], env[f"e{i}"] = hint, _fields_to_wire(hint)
            items.append(f"e{i}(v) if type(v := {v}) is t{i} else _to_wire(v)")
        elif inner is not None and dataclasses.is_dataclass(inner):
            env[f"t{i}"], env[f"e{i}"] = inner, _fields_to_wire(inner)
            items.append(f"[e{i}(x) if type(x) is t{i} else _to_wire(x) for x in v] if type(v := {v}) is list "
                         f"else _to_wire(v)")
        else:
            items.append(f"_to_wire({v})")
    source = "def fields(value):\n    return [" + ", ".join(f"({item})" for item in items) + "]"
    exec(source, env)  # noqa: S102 - the source is built from the class's own field list
    built.append(env["fields"])
    return env["fields"]


def encode(msg: Any) -> bytes:
    """Serialize a registered message dataclass to bytes."""
    cls = type(msg)
    if getattr(cls, "TYPE_ID", None) not in _REGISTRY:
        raise TypeError(f"{cls.__name__} is not a registered message")
    body = [cls.TYPE_ID, cls.VERSION]
    body.extend(_fields_to_wire(cls)(msg))
    return msgpack.packb(body, use_bin_type=True)


class _FieldError(Exception):
    """A bad value somewhere inside a message; ``path`` grows as it unwinds (".pose", "[3]")."""

    def __init__(self, text: str) -> None:
        super().__init__(text)
        self.text = text
        self.path: list[str] = []


Converter = typing.Callable[[Any], Any]
_CONVERTERS: dict[Any, Converter] = {}
_FIELD_READERS: dict[tuple[type, tuple[str, ...]], Converter] = {}


def _converter(hint: Any) -> Converter:
    """The checked wire -> Python conversion of a field type, built once per type.

    Decoding walks a message with these closures instead of inspecting type hints per
    value: a 40-vehicle control bundle (40 messages of 8 arrays each) decodes ~3x faster.
    """
    return _built_once(_CONVERTERS, hint, _build_converter)


def _build_converter(hint: Any) -> Converter:
    origin = typing.get_origin(hint)
    if hint is np.ndarray:
        return _array_from_wire
    spec = array_spec(hint)
    if spec is not None:
        return _packed_converter(spec) if spec.packed else _array_converter(spec)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(hint)
        (inner,) = [a for a in args if a is not type(None)]
        conv = _converter(inner)
        optional = type(None) in args
        return lambda value: None if value is None and optional else conv(value)
    if origin is list or (origin is tuple and typing.get_args(hint)[1:] == (Ellipsis,)):
        inner = typing.get_args(hint)[0]
        return _sequence_converter(_converter(inner), origin is list, inner if inner in (str, bytes) else None)
    if origin is tuple:
        convs = [_converter(a) for a in typing.get_args(hint)]
        return lambda value: tuple(_items(value, convs))
    if origin is dict:
        kconv, vconv = (_converter(a) for a in typing.get_args(hint))
        return lambda value: _mapping(value, kconv, vconv)
    if dataclasses.is_dataclass(hint):
        return _record_converter(hint)
    if hint is float:
        return _number
    if hint is int:
        return _integer
    if hint in (str, bool, bytes):
        return lambda value: value if isinstance(value, hint) else _bad(
            f"expected {hint.__name__}, got {type(value).__name__}")
    if hint is Any:
        return _plain
    raise TypeError(f"unsupported field type {hint!r}")


def _array_converter(spec: Array) -> Converter:
    """An array field of a declared dtype and shape: any other is refused."""

    dtype, ndim = np.dtype(spec.dtype), len(spec.shape)
    fixed = [(axis, d) for axis, d in enumerate(spec.shape) if d is not None]

    def convert(value: Any) -> np.ndarray:  # spec.fits, written out: a 40-vehicle bundle has ~100 arrays
        arr = _array_from_wire(value)
        shape = arr.shape
        if arr.dtype != dtype or len(shape) != ndim or any(shape[axis] != d for axis, d in fixed):
            _bad(f"expected {spec}, got {arr.dtype} {list(shape)}")
        return arr

    return convert


def _packed_converter(spec: Array) -> Converter:
    """A packed array field (``_packed_to_wire``) as the encoder writes it: its declared
    dtype and shape, masks of a bit per entry whose padding bits are 0 and that mark no
    entry twice, and a value for every entry the second marks that is neither 1.0 nor
    +0.0 (those have their own form: one array, one encoding); anything else is refused."""

    dtype, ndim = np.dtype(spec.dtype), len(spec.shape)
    fixed = [(axis, d) for axis, d in enumerate(spec.shape) if d is not None]
    uint, one_bits = _BITS_OF[spec.dtype]

    def convert(value: Any) -> np.ndarray:
        if type(value) is not list or len(value) != 5:
            _bad("expected a packed array [dtype, shape, ones, others, values]")
        dtype_str, shape, ones, others, raw = value
        if dtype_str != spec.dtype:
            _bad(f"expected a packed {spec}, got dtype {_brief(dtype_str)}")
        if type(ones) is not bytes or type(others) is not bytes or type(raw) is not bytes:
            _bad("a packed array's masks and values are bytes")
        fits = type(shape) is list and len(shape) == ndim
        if fits:  # loops, not any(<genexpr>): a vehicle reads two tables of each of its group's messages
            for d in shape:
                if type(d) is not int or d < 0:
                    fits = False
                    break
            for axis, d in fixed:
                if fits and shape[axis] != d:
                    fits = False
        if not fits:
            _bad(f"expected a packed {spec}, got shape {_brief(shape)}")
        count = math.prod(shape)
        if len(ones) != (count + 7) // 8 or len(others) != len(ones):  # checked before anything is built
            _bad(f"masks of {len(ones)} and {len(others)} bytes for {count} entries")
        # the checks on the masks as integers (a table has a few hundred entries): the
        # padding is the low bits of the last byte, the values one per bit of ``others``
        one, other = int.from_bytes(ones, "big"), int.from_bytes(others, "big")
        if (one | other) & ((1 << (8 * len(ones) - count)) - 1):
            _bad("mask padding bits set")
        if one & other:
            _bad("an entry marked both 1 and other")
        n_other = other.bit_count()
        if n_other * dtype.itemsize != len(raw):
            _bad(f"{len(raw)} bytes of values for {n_other} entries")
        if not other:  # the 0/1 entries straight from the unpacked mask (a table of relevance, mostly)
            return np.unpackbits(np.frombuffer(ones, np.uint8), count=count).astype(dtype).reshape(shape)
        bits = np.frombuffer(raw, uint)
        listed = bits.tolist()  # a few dozen values: two scans of a list, not four numpy calls
        if 0 in listed or one_bits in listed:
            _bad("a value of 1.0 or +0.0 among the others")
        both = np.unpackbits(np.frombuffer(ones + others, np.uint8)).reshape(2, -1)[:, :count]  # one call for both
        out = both[0].astype(dtype)
        out[both[1].view(np.bool_)] = bits.view(dtype)
        return out.reshape(shape)

    return convert


def _brief(value: Any) -> str:
    """A hostile value in an error message: its repr only if it is flat (a repr of a
    list nested 1,000 deep raises RecursionError), and cut short."""
    if type(value) is list and all(isinstance(v, _PLAIN) for v in value[:MAX_ARRAY_DIMS + 1]):
        text = repr(value[:MAX_ARRAY_DIMS + 1])
    elif isinstance(value, _PLAIN):
        text = repr(value)
    else:
        text = f"a {type(value).__name__}"
    return text if len(text) <= 80 else text[:77] + "..."


def _bad(text: str) -> typing.NoReturn:
    raise _FieldError(text)


def _number(value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        _bad(f"expected a number, got {type(value).__name__}")
    return float(value)


def _integer(value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        _bad(f"expected an int, got {type(value).__name__}")
    return value


def _plain(value: Any) -> Any:
    """A free-form value: msgpack's plain types only (no extension types such as its
    Timestamp), map keys str or int, at most ``MAX_ANY_DEPTH`` containers deep."""
    level = [value]
    for _ in range(MAX_ANY_DEPTH + 1):
        inner = []
        for v in level:
            if type(v) is list:
                inner.extend(v)
            elif type(v) is dict:
                if not all(type(k) in (str, int) for k in v):
                    _bad("map keys must be str or int")
                inner.extend(v.values())
            elif not isinstance(v, _PLAIN):
                _bad(f"{type(v).__name__} is not a plain value")
        if not inner:
            return value
        level = inner
    _bad(f"nested deeper than {MAX_ANY_DEPTH}")


def _items(value: Any, convs: list[Converter] | None) -> list:
    if not isinstance(value, list) or convs is None:
        _bad("expected a list")
    if len(convs) != len(value):
        _bad(f"expected {len(convs)} items, got {len(value)}")
    out = []
    for i, (conv, v) in enumerate(zip(convs, value)):
        try:
            out.append(conv(v))
        except _FieldError as err:
            err.path.insert(0, f"[{i}]")
            raise
    return out


def _mapping(value: Any, kconv: Converter, vconv: Converter) -> dict:
    if not isinstance(value, dict):
        _bad("expected a map")
    out = {}
    for k, v in value.items():
        try:
            out[kconv(k)] = vconv(v)
        except _FieldError as err:
            err.path.insert(0, f".{k}")
            raise
    return out


def _sequence_converter(conv: Converter, as_list: bool, plain: type | None = None) -> Converter:
    """``list[X]`` (or ``tuple[X, ...]``): each item through ``conv``; the index of a bad
    item goes into its error's path. ``plain``: X is this type (str, bytes), whose
    converter returns an item of exactly it as it is: such a list is taken at once (a
    control bundle's 40 messages: one pass over the items' types, not 40 calls)."""
    items_of = {plain}

    def convert(value: Any) -> Any:
        if not isinstance(value, list):
            _bad("expected a list")
        if plain is not None and set(map(type, value)) <= items_of:
            return list(value) if as_list else tuple(value)
        out = []
        append = out.append
        i = 0
        try:
            for v in value:
                append(conv(v))
                i += 1
        except _FieldError as err:
            err.path.insert(0, f"[{i}]")
            raise
        return out if as_list else tuple(out)

    return convert


def _inline(hint: Any, name: str) -> str | None:
    """A field's conversion as an expression of ``v`` where a plain check does it
    (the value as msgpack builds it: exactly an int, a float, ...), else None. Any
    other value goes through the field's converter ``name``, which accepts or refuses
    it as ever."""
    if hint is np.ndarray:
        return "_array_from_wire(v)"
    if hint in (int, float, str, bool, bytes):  # _integer/_number/the type check return such a value as it is
        return f"v if type(v) is {hint.__name__} else {name}(v)"
    spec = array_spec(hint)
    if spec is not None and not spec.packed:
        return _inline_array(spec, name)
    return None


def _inline_array(spec: Array, name: str) -> str:
    """A declared array's conversion as one expression of ``v``: the triple exactly as
    the encoder writes it (the declared dtype's wire name, a shape of plain ints that
    fits the declared one, the bytes that fill it) becomes the array at once, as
    ``_array_from_wire`` builds it (``_ndarray(shape, dtype, bytes)``); anything else
    goes through the converter ``name``, which accepts or refuses it as ever. A vehicle
    reads two such arrays of every control message it hears, the proxy all of every
    message it relays: two calls and a dozen lookups each."""
    shape = "shape_"  # v[1], bound once by the test (``:=``), not looked up again for every check
    test = ["type(v) is list", "len(v) == 3", "type(v[0]) is str", f"v[0] == {spec.dtype!r}", "type(v[2]) is bytes",
            f"type({shape} := v[1]) is list", f"len({shape}) == {len(spec.shape)}"]
    for axis, d in enumerate(spec.shape):
        test.append(f"type({shape}[{axis}]) is int")
        test.append(f"{shape}[{axis}] >= 0" if d is None else f"{shape}[{axis}] == {d}")
    count = " * ".join([f"{shape}[{axis}]" for axis, d in enumerate(spec.shape) if d is None] +
                       [str(math.prod(d for d in spec.shape if d is not None) * np.dtype(spec.dtype).itemsize)])
    test.append(f"{count} == len(v[2])")
    return f"_ndarray({shape}, _DTYPE_OF[{spec.dtype!r}], v[2]) if {' and '.join(test)} else {name}(v)"


def _field_lines(env: dict[str, Any], fields: list[tuple[int, Any]]) -> list[str]:
    """The body of a generated reader's ``try``: for the i-th of ``fields`` (its place in
    the wire list, its type), ``at = i``, then ``a<i>``, the value converted (``_inline``
    where a plain check does it, else the type's converter, bound in ``env`` as
    ``c<i>``)."""
    env.update({"_array_from_wire": _array_from_wire, "_ndarray": np.ndarray, "_DTYPE_OF": _DTYPE_OF})
    lines = []
    for i, (at, hint) in enumerate(fields):
        env[f"c{i}"] = _converter(hint)
        expr = _inline(hint, f"c{i}") or f"c{i}(v)"
        lines += [f"        at = {i}", f"        v = values[{at}]", f"        a{i} = {expr}"]
    return lines or ["        pass"]


def slots_constructor(cls: type) -> typing.Callable[..., Any]:
    """A function of a slotted dataclass's fields (all, in order, positional) that builds
    the instance as its ``__init__`` would, without the ``object.__setattr__`` call per
    field a frozen one's ``__init__`` makes: each slot's own descriptor sets it (as a
    record's converter does). For a class without ``__post_init__`` whose fields are all
    ``init`` fields in slots of its own (a subclass's inherited fields are not);
    ``TypeError`` otherwise.

    At 40 vehicles an agent reads 39 heard control messages a tick; their 8-field
    ``__init__`` was 0.7 of 4.7 us a message."""
    setters = _slot_setters(cls)
    if setters is None:
        raise TypeError(f"{cls.__name__}: not a dataclass of init fields in its own slots without __post_init__")
    env: dict[str, Any] = {"cls": cls}
    args = ", ".join(f"a{i}" for i in range(len(setters)))
    lines = [f"def construct({args}):", *_construct_lines(env, setters)]
    exec("\n".join(lines), env)  # noqa: S102 - the source is built from the class's own field list
    return env["construct"]


def _construct_lines(env: dict[str, Any], setters: list[typing.Callable[[Any, Any], None]]) -> list[str]:
    """Generated lines that build ``cls`` (in ``env``) from ``a0``, ``a1``, ... through
    ``setters`` (``_slot_setters``) and return it; ``env`` gets what they call."""
    env["new"] = object.__new__
    env.update({f"s{i}": setter for i, setter in enumerate(setters)})
    return ["    out = new(cls)", *(f"    s{i}(out, a{i})" for i in range(len(setters))), "    return out"]


def _slot_setters(cls: type) -> list[typing.Callable[[Any, Any], None]] | None:
    """The ``__set__`` of each field's slot, in field order, if setting them is all the
    dataclass's ``__init__`` does (no ``__post_init__``, every field an ``init`` field in
    a slot of the class's own); else None."""
    fields = dataclasses.fields(cls)
    slots = [cls.__dict__.get(f.name) for f in fields]
    if hasattr(cls, "__post_init__") or not all(f.init for f in fields) or \
            not all(isinstance(d, types.MemberDescriptorType) for d in slots):
        return None
    return [d.__set__ for d in slots]


def _record_converter(cls: type) -> Converter:
    """A record's conversion, written out as one function for its fields (generated
    once per class): the field count, then each field's converter in turn, the name of
    a bad field going into its error's path; then the record built from the values.

    Decoding a 40-vehicle interval's bundles runs this for every control message and
    every reception; a loop over the fields with a converter call each was most of the
    codec's time."""
    hints = _hints(cls)
    names = [name for name, _ in hints]
    # a record may (indirectly) contain itself: whoever is built meanwhile calls through this
    built: list[Converter] = []
    _CONVERTERS[cls] = _placeholder(built)
    env: dict[str, Any] = {"cls": cls, "names": names, "_bad": _bad, "_FieldError": _FieldError,
                           "needs": f"{cls.__name__} needs {len(names)} fields"}
    lines = ["def convert(values):",
             f"    if not isinstance(values, list) or len(values) != {len(names)}:",
             "        _bad(needs)",
             "    at = 0",
             "    try:"]
    lines += _field_lines(env, [(at, hint) for at, (_, hint) in enumerate(hints)])
    lines += _invariant_lines(env, cls, names, "        ")
    lines += ["    except _FieldError as err:",
              "        err.path.insert(0, '.' + names[at])",
              "        raise"]
    setters = _slot_setters(cls)
    if setters is not None:
        # what the frozen dataclass's __init__ does (object.__setattr__ of each field), through
        # each slot's own descriptor: ~40% less per record, ~180 receptions per data bundle
        lines += _construct_lines(env, setters)
    else:
        # a record's own check (__post_init__) refuses as a field does: the path names where it sits
        lines += ["    try:",
                  f"        return cls({', '.join(f'a{i}' for i in range(len(names)))})",
                  "    except ValueError as exc:",
                  "        raise _FieldError(str(exc)) from None"]
    exec("\n".join(lines), env)  # noqa: S102 - the source is built from the class's own field list
    convert = env["convert"]
    built.append(convert)
    _CONVERTERS[cls] = convert
    return convert


def _array_from_wire(value: Any) -> np.ndarray:
    if type(value) is not list or len(value) != 3:
        _bad("expected an array triple [dtype, shape, bytes]")
    dtype_str, shape, raw = value
    dtype = _DTYPE_OF.get(dtype_str) if type(dtype_str) is str else None
    if dtype is None or type(raw) is not bytes:
        _bad(f"bad array dtype {_brief(dtype_str)}")
    if type(shape) is not list or len(shape) > MAX_ARRAY_DIMS:
        _bad(f"bad array shape {_brief(shape)}")
    count = 1
    for d in shape:  # a loop, not all(<genexpr>): a control bundle decodes ~300 arrays
        if type(d) is not int or d < 0:
            _bad(f"bad array shape {_brief(shape)}")
        count *= d
    if count * dtype.itemsize != len(raw):  # checked before anything is built from the bytes
        _bad(f"{len(raw)} bytes do not fill shape {shape} of {dtype}")
    return np.ndarray(shape, dtype, raw)  # a read-only view of the bytes, as np.frombuffer gives


def decode(payload: bytes | bytearray | memoryview, expected: type | None = None) -> Any:
    """Parse bytes into a message; ``expected`` narrows the accepted type.

    Raises ``MalformedMessage`` for anything that is not a well-formed message of a
    known type and the current version (or not of ``expected``).
    """
    cls, values = _envelope(payload, expected)
    try:
        return _converter(cls)(values)
    except _FieldError as err:
        raise MalformedMessage(f"{cls.__name__}{''.join(err.path)}: {err.text}") from None
    except (TypeError, ValueError) as exc:  # e.g. a record's own __post_init__ check
        raise MalformedMessage(f"{cls.__name__}: {exc}") from None


def decode_fields(payload: bytes | bytearray | memoryview, expected: type, names: Sequence[str]) -> tuple:
    """The named fields of a message of type ``expected``, converted and checked as
    ``decode`` converts them; the other fields are left unread (not checked). For a
    reader that needs a few small fields of many messages: a vehicle reads every heard
    control message's ballot and motion, and only its group's object maps.

    Raises ``MalformedMessage`` as ``decode`` does, for the envelope and the named fields."""
    cls, values = _envelope(payload, expected)
    return _built_once(_FIELD_READERS, (cls, tuple(names)), _fields_reader)(values)


def _fields_reader(key: tuple[type, tuple[str, ...]]) -> Converter:
    """The conversion of a record's named fields, written out as one function (as
    ``_record_converter`` writes out a whole record's): at 40 vehicles a vehicle reads
    39 heard control messages' ballots and motion every interval, and a loop over the
    names with a converter call each was most of that time."""
    cls, names = key
    hints = dict(_hints(cls))
    index = {name: at for at, (name, _) in enumerate(_hints(cls))}
    env: dict[str, Any] = {"names": names, "_FieldError": _FieldError, "MalformedMessage": MalformedMessage,
                           "cls_name": cls.__name__, "needs": f"{cls.__name__} needs {len(index)} fields"}
    lines = ["def read(values):",
             f"    if not isinstance(values, list) or len(values) != {len(index)}:",
             "        raise MalformedMessage(needs)",
             "    at = 0",
             "    try:"]
    lines += _field_lines(env, [(index[name], hints[name]) for name in names])
    lines += _invariant_lines(env, cls, names, "        ")
    lines += ["    except _FieldError as err:",
              "        raise MalformedMessage(f\"{cls_name}.{names[at]}{''.join(err.path)}: {err.text}\") from None",
              "    except (TypeError, ValueError) as exc:",
              "        raise MalformedMessage(f\"{cls_name}.{names[at]}: {exc}\") from None",
              f"    return ({''.join(f'a{i}, ' for i in range(len(names)))})"]
    exec("\n".join(lines), env)  # noqa: S102 - the source is built from the class's own field list
    return env["read"]


def fields_decoder(expected: type, names: Sequence[str], into: type) -> typing.Callable[[bytes], Any]:
    """A function of a payload that returns ``into`` (a slotted dataclass whose fields are
    ``names`` followed by the payload itself; ``slots_constructor``'s kind) built of the
    named fields of a message of type ``expected``, read as ``decode_fields`` reads them,
    and raises ``MalformedMessage`` as it does (the same text).

    One generated function (msgpack, the envelope of a well-formed message of the type
    and version, the fields, the record): at 40 vehicles an agent reads 39 heard control
    messages an interval, and ``decode_fields``' four calls around them and its tuple
    were a third of a read. Any envelope that is not such a message's goes through
    ``decode_fields``, which refuses it."""
    setters = _slot_setters(into)
    if setters is None or len(setters) != len(names) + 1:
        raise TypeError(f"{into.__name__}: not a record of the {len(names)} named fields and the payload")
    hints = dict(_hints(expected))
    index = {name: at for at, (name, _) in enumerate(_hints(expected))}
    env: dict[str, Any] = {"names": tuple(names), "_FieldError": _FieldError, "MalformedMessage": MalformedMessage,
                           "cls_name": expected.__name__, "unpackb": msgpack.unpackb, "decode_fields": decode_fields,
                           "expected": expected, "cls": into}
    lines = ["def read(payload):",
             "    try:",
             "        values = unpackb(payload, raw=False, use_list=True, strict_map_key=False)",
             "    except Exception:  # not msgpack: decode_fields says so, in its words",
             "        values = None",
             f"    if type(values) is not list or len(values) != {len(index) + 2} or type(values[0]) is not int or "
             f"values[0] != {expected.TYPE_ID} or type(values[1]) is not int or values[1] != {expected.VERSION}:",
             "        decode_fields(payload, expected, names)  # raises MalformedMessage",
             "        raise AssertionError('decode_fields read an envelope the reader refused')",
             "    at = 0",
             "    try:"]
    lines += _field_lines(env, [(index[name] + 2, hints[name]) for name in names])
    lines += _invariant_lines(env, expected, names, "        ")
    lines += ["    except _FieldError as err:",
              "        raise MalformedMessage(f\"{cls_name}.{names[at]}{''.join(err.path)}: {err.text}\") from None",
              "    except (TypeError, ValueError) as exc:",
              "        raise MalformedMessage(f\"{cls_name}.{names[at]}: {exc}\") from None",
              f"    a{len(names)} = payload"]
    lines += _construct_lines(env, setters)
    exec("\n".join(lines), env)  # noqa: S102 - the source is built from the class's own field list
    return env["read"]


def _envelope(payload: bytes | bytearray | memoryview, expected: type | None) -> tuple[type, list]:
    """The message class and the field values of a payload, its envelope checked."""
    try:
        body = msgpack.unpackb(payload, raw=False, use_list=True, strict_map_key=False)
    except Exception as exc:  # msgpack raises several unrelated exception types
        raise MalformedMessage(f"not msgpack: {type(exc).__name__} {exc}") from None
    if not isinstance(body, list) or len(body) < 2:
        raise MalformedMessage("not a message envelope")
    type_id, version = body[0], body[1]
    cls = _REGISTRY.get(type_id) if type(type_id) is int else None  # not isinstance: True is no type id
    if cls is None:
        raise MalformedMessage(f"unknown message type {_brief(type_id)}")
    if expected is not None and cls is not expected:
        raise MalformedMessage(f"expected {expected.__name__}, got {cls.__name__}")
    if type(version) is not int or version != cls.VERSION:
        raise MalformedMessage(f"{cls.__name__} version {_brief(version)}, this build speaks {cls.VERSION}")
    return cls, body[2:]

