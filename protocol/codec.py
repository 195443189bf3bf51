"""msgpack codec for the versioned message dataclasses.

A message travels as one msgpack array: ``[type_id, version, field_1, ..., field_n]``
in the dataclass's field order. numpy arrays travel as ``[dtype_str, shape, bytes]``
with the bytes packed from a ``memoryview`` (no ``tobytes`` copy, no ``tolist``);
nested dataclasses travel as plain arrays of their fields. Decoding checks the type,
the version, the field count and every field's type, and raises ``MalformedMessage``
on any mismatch, so a receiver can count and drop a bad payload without crashing.
"""

from __future__ import annotations

import dataclasses
import types
import typing
from typing import Any

import msgpack
import numpy as np


class MalformedMessage(ValueError):
    """A payload that is not a valid message of the expected type and version."""


# dtypes an array field may carry on the wire; anything else is refused on decode.
_WIRE_DTYPES = frozenset(["<f4", "<f8", "<i2", "<i4", "<i8", "|u1", "|i1", "<u2", "<u4", "|b1"])

_REGISTRY: dict[int, type] = {}
_HINTS: dict[type, list[tuple[str, Any]]] = {}


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


def message_class(type_id: int) -> type | None:
    """The registered message dataclass of a wire type id (None if unknown)."""
    return _REGISTRY.get(type_id)


def _hints(cls) -> list[tuple[str, Any]]:
    got = _HINTS.get(cls)
    if got is None:
        resolved = typing.get_type_hints(cls)
        got = [(f.name, resolved[f.name]) for f in dataclasses.fields(cls)]
        _HINTS[cls] = got
    return got


def _to_wire(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        arr = np.ascontiguousarray(value)
        if arr.dtype.str not in _WIRE_DTYPES:
            raise TypeError(f"dtype {arr.dtype} cannot go on the wire")
        raw = memoryview(arr).cast("B") if arr.size else b""  # a view with a 0 in its shape cannot be cast
        return [arr.dtype.str, list(arr.shape), raw]
    if dataclasses.is_dataclass(value):
        return [_to_wire(getattr(value, name)) for name, _ in _hints(type(value))]
    if isinstance(value, (list, tuple)):
        return [_to_wire(v) for v in value]
    if isinstance(value, dict):
        return {k: _to_wire(v) for k, v in value.items()}
    if isinstance(value, np.generic):
        return value.item()
    return value


def encode(msg: Any) -> bytes:
    """Serialize a registered message dataclass to bytes."""
    cls = type(msg)
    if getattr(cls, "TYPE_ID", None) not in _REGISTRY:
        raise TypeError(f"{cls.__name__} is not a registered message")
    body = [cls.TYPE_ID, cls.VERSION]
    body.extend(_to_wire(getattr(msg, name)) for name, _ in _hints(cls))
    return msgpack.packb(body, use_bin_type=True)


def _array_from_wire(value: Any, where: str) -> np.ndarray:
    if not (isinstance(value, list) and len(value) == 3):
        raise MalformedMessage(f"{where}: expected an array triple [dtype, shape, bytes]")
    dtype_str, shape, raw = value
    if dtype_str not in _WIRE_DTYPES or not isinstance(raw, bytes):
        raise MalformedMessage(f"{where}: bad array dtype {dtype_str!r}")
    if not isinstance(shape, list) or not all(isinstance(d, int) and d >= 0 for d in shape):
        raise MalformedMessage(f"{where}: bad array shape {shape!r}")
    dtype = np.dtype(dtype_str)
    if int(np.prod(shape, dtype=np.int64)) * dtype.itemsize != len(raw):
        raise MalformedMessage(f"{where}: {len(raw)} bytes do not fill shape {shape} of {dtype}")
    return np.frombuffer(raw, dtype=dtype).reshape(shape)


def _from_wire(value: Any, hint: Any, where: str) -> Any:
    origin = typing.get_origin(hint)
    if hint is np.ndarray:
        return _array_from_wire(value, where)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(hint)
        if value is None and type(None) in args:
            return None
        (inner,) = [a for a in args if a is not type(None)]
        return _from_wire(value, inner, where)
    if origin is list:
        (inner,) = typing.get_args(hint)
        if not isinstance(value, list):
            raise MalformedMessage(f"{where}: expected a list")
        return [_from_wire(v, inner, f"{where}[{i}]") for i, v in enumerate(value)]
    if origin is tuple:
        args = typing.get_args(hint)
        if not isinstance(value, list):
            raise MalformedMessage(f"{where}: expected a tuple")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_from_wire(v, args[0], f"{where}[{i}]") for i, v in enumerate(value))
        if len(args) != len(value):
            raise MalformedMessage(f"{where}: expected {len(args)} items, got {len(value)}")
        return tuple(_from_wire(v, a, f"{where}[{i}]") for i, (v, a) in enumerate(zip(args, value)))
    if origin is dict:
        kt, vt = typing.get_args(hint)
        if not isinstance(value, dict):
            raise MalformedMessage(f"{where}: expected a map")
        return {_from_wire(k, kt, where): _from_wire(v, vt, f"{where}.{k}") for k, v in value.items()}
    if dataclasses.is_dataclass(hint):
        return _record_from_wire(hint, value, where)
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise MalformedMessage(f"{where}: expected a number, got {type(value).__name__}")
        return float(value)
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise MalformedMessage(f"{where}: expected an int, got {type(value).__name__}")
        return value
    if hint in (str, bool, bytes):
        if not isinstance(value, hint):
            raise MalformedMessage(f"{where}: expected {hint.__name__}, got {type(value).__name__}")
        return value
    if hint is Any:
        return value
    raise TypeError(f"{where}: unsupported field type {hint!r}")


def _record_from_wire(cls, values: Any, where: str):
    fields = _hints(cls)
    if not isinstance(values, list) or len(values) != len(fields):
        raise MalformedMessage(f"{where}: {cls.__name__} needs {len(fields)} fields")
    kwargs = {name: _from_wire(v, hint, f"{where}.{name}") for (name, hint), v in zip(fields, values)}
    return cls(**kwargs)


def decode(payload: bytes | bytearray | memoryview, expected: type | None = None) -> Any:
    """Parse bytes into a message; ``expected`` narrows the accepted type.

    Raises ``MalformedMessage`` for anything that is not a well-formed message of a
    known type and the current version (or not of ``expected``).
    """
    try:
        body = msgpack.unpackb(payload, raw=False, use_list=True, strict_map_key=False)
    except Exception as exc:  # msgpack raises several unrelated exception types
        raise MalformedMessage(f"not msgpack: {exc}") from None
    if not isinstance(body, list) or len(body) < 2:
        raise MalformedMessage("not a message envelope")
    type_id, version = body[0], body[1]
    cls = _REGISTRY.get(type_id) if isinstance(type_id, int) else None
    if cls is None:
        raise MalformedMessage(f"unknown message type {type_id!r}")
    if expected is not None and cls is not expected:
        raise MalformedMessage(f"expected {expected.__name__}, got {cls.__name__}")
    if version != cls.VERSION:
        raise MalformedMessage(f"{cls.__name__} version {version!r}, this build speaks {cls.VERSION}")
    try:
        return _record_from_wire(cls, body[2:], cls.__name__)
    except MalformedMessage:
        raise
    except (TypeError, ValueError) as exc:
        raise MalformedMessage(f"{cls.__name__}: {exc}") from None

