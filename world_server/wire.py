"""A message encoded in parts, for the world's scans: ``protocol.codec.encode``'s exact
bytes as the encoded head (everything up to its last field's raw array bytes) and those
raw bytes, a view of the array itself, so that ``protocol.shm.ShmPublisher.put_parts``
copies the array once, straight into shared memory, instead of msgpack copying it into
its buffer and then into a fresh ``bytes`` that is copied again.

msgpack packs a list as its header and then each element's packing in turn, so a
message whose last field is an array ends in that array's ``bin`` (its header, then its
bytes): the head is the message packed with an empty ``bin`` there (``c4 00``), those
two bytes replaced by the real ``bin`` header. ``tests/test_world_wire.py`` holds it to
``encode`` byte for byte.
"""

from __future__ import annotations

import msgpack
import numpy as np

from protocol.codec import _fields_to_wire, encode

_EMPTY_BIN = b"\xc4\x00"  # msgpack (use_bin_type) of b""


def bin_header(n: int) -> bytes:
    """msgpack's header of a ``bin`` of ``n`` bytes (bin 8, 16 or 32)."""
    if n < 1 << 8:
        return b"\xc4" + n.to_bytes(1, "big")
    if n < 1 << 16:
        return b"\xc5" + n.to_bytes(2, "big")
    return b"\xc6" + n.to_bytes(4, "big")


def encode_parts(msg) -> tuple[bytes, memoryview | bytes]:
    """``(head, raw)`` with ``head + raw == encode(msg)``: ``raw`` the bytes of ``msg``'s
    last field when that is an array (a view of it, if C-contiguous: use it before the
    array changes); for any other message, ``(encode(msg), b"")``."""
    cls = type(msg)
    names = list(getattr(cls, "__dataclass_fields__", ()))
    if not names or not isinstance(getattr(msg, names[-1]), np.ndarray):
        return encode(msg), b""
    fields = _fields_to_wire(cls)(msg)  # encode's own conversion (and checks)
    dtype_str, shape, raw = fields[-1]
    fields[-1] = [dtype_str, shape, b""]
    head = msgpack.packb([cls.TYPE_ID, cls.VERSION, *fields], use_bin_type=True)
    assert head.endswith(_EMPTY_BIN)  # msgpack packs a list's last element last
    return head[:-len(_EMPTY_BIN)] + bin_header(len(raw)), raw
