"""world_server.wire: a message in parts is ``protocol.codec.encode``'s bytes, to the byte."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol.codec import encode
from protocol.messages import Command, Pose, Scan
from world_server.wire import bin_header, encode_parts


def test_bin_headers_by_hand():
    assert bin_header(0) == b"\xc4\x00"
    assert bin_header(255) == b"\xc4\xff"
    assert bin_header(256) == b"\xc5\x01\x00"
    assert bin_header(65535) == b"\xc5\xff\xff"
    assert bin_header(65536) == b"\xc6\x00\x01\x00\x00"
    assert bin_header(230400) == b"\xc6\x00\x03\x84\x00"


def test_a_scan_by_hand():
    rc = np.array([[1, 2], [515, 0]], dtype=np.uint16)
    head, raw = encode_parts(Scan(3, 0.5, 7, Pose(1.0, 2.0, 0.25), 4.0, rc))
    assert bytes(raw) == b"\x01\x00\x02\x00\x03\x02\x00\x00"  # little-endian uint16, row-major
    assert head.endswith(b"\xa3<u2\x92\x02\x02\xc4\x08")  # "<u2", [2, 2], bin 8 of 8 bytes
    assert head + bytes(raw) == encode(Scan(3, 0.5, 7, Pose(1.0, 2.0, 0.25), 4.0, rc))


def test_a_message_without_a_last_array_is_encoded_whole():
    cmd = Command(3, 0.3, 1, 0.5, -0.1)
    assert encode_parts(cmd) == (encode(cmd), b"")


finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


@settings(max_examples=200, deadline=None)
@given(tick=st.integers(0, 2**40), t=finite, vid=st.integers(0, 2**31), x=finite, y=finite, yaw=finite, v=finite,
       rows=st.integers(0, 300), cols=st.integers(0, 300), seed=st.integers(0, 2**32 - 1), step=st.sampled_from([1, 2]))
def test_a_scan_in_parts_is_its_encoding(tick, t, vid, x, y, yaw, v, rows, cols, seed, step):
    rc = np.random.default_rng(seed).integers(0, 65536, (rows, cols * step), dtype=np.uint16)[:, ::step]
    scan = Scan(tick, t, vid, Pose(x, y, yaw), v, rc)  # a strided range image too: encode copies it
    head, raw = encode_parts(scan)
    assert head + bytes(raw) == encode(scan)
