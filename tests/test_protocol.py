import typing

import msgpack
import numpy as np
import pytest

from protocol import codec, keys
from protocol.codec import MalformedMessage, decode, decode_fields, encode
from protocol.messages import Command, ControlMsg, LidarConfig, MapMsg, Mission, ObjectMap, Outcome, Pose, Scan, Tick, \
    VehicleSpec, Lane, LightState, TrafficLight


def _examples():
    spec = VehicleSpec(4.5, 1.8, 1.5, 2.7, 3.0, 7.5, 0.6)
    lane = Lane("S.in.0", np.array([[0.0, 0.0], [0.0, 10.0]]), 3.5, 13.9, 0, 10.0)
    return [
        Scan(3, 0.3, 7, Pose(1.0, -2.0, 0.5), 4.0, np.arange(30, dtype=np.uint16).reshape(10, 3)),
        Command(3, 0.3, 7, -2.5, 0.1),
        Tick(3, 0.3, [0, 1, 4], [LightState(0, "green")]),
        Mission(0, 0.0, 2, "background", np.zeros((2, 2)), 12.0, spec, LidarConfig(), 0.1),
        MapMsg(0, 0.0, "x", [lane], [np.zeros((4, 2))], [TrafficLight(0, 1.0, 2.0)], np.zeros((1, 6))),
        Outcome(5, 0.5, {"outcome": "safe", "closest_distance_m": 3.2}),
    ]


@pytest.mark.parametrize("msg", _examples(), ids=lambda m: type(m).__name__)
def test_round_trip(msg):
    back = decode(encode(msg), type(msg))
    for name in msg.__dataclass_fields__:
        a, b = getattr(msg, name), getattr(back, name)
        if isinstance(a, np.ndarray):
            assert a.dtype == b.dtype and np.array_equal(a, b)
        elif name in ("lanes", "drivable"):
            assert len(a) == len(b)
        else:
            assert a == b


def test_empty_arrays_round_trip():
    msg = Scan(0, 0.0, 0, Pose(0, 0, 0), 0.0, np.zeros((0, 3), np.uint16))
    assert decode(encode(msg), Scan).range_cm.shape == (0, 3)


def test_scan_ranges_travel_without_tolist():
    ranges = np.random.default_rng(0).integers(0, 10000, (1800, 64), dtype=np.uint16)
    payload = encode(Scan(0, 0.0, 0, Pose(0, 0, 0), 0.0, ranges))
    assert len(payload) < ranges.nbytes + 200  # raw bytes, not a list of numbers


def test_scan_points_from_a_hand_made_range_image():
    """Four azimuths (-180, -90, 0, 90 deg) by two beams (+10, -10 deg): each return is at
    horizontal distance d along its azimuth and d * tan(elevation) above the sensor."""
    lidar = LidarConfig(beams=2, fov_up_deg=10.0, fov_down_deg=-10.0, azimuth_steps=4)
    ranges = np.zeros((4, 2), np.uint16)
    ranges[2, 0] = 1000  # 10 m straight ahead, upper beam
    ranges[3, 1] = 550  # 5.5 m to the left, lower beam
    pts = Scan(0, 0.0, 0, Pose(0, 0, 0), 0.0, ranges).points(lidar)
    t = np.tan(np.deg2rad(10.0))
    np.testing.assert_allclose(pts, [[10.0, 0.0, 10.0 * t], [0.0, 5.5, -5.5 * t]], atol=1e-5)
    with pytest.raises(ValueError, match="does not fit"):
        Scan(0, 0.0, 0, Pose(0, 0, 0), 0.0, ranges).points(LidarConfig())


def _envelope(*fields):
    return msgpack.packb(list(fields), use_bin_type=True)


@pytest.mark.parametrize("payload, why", [
    (b"\xc1garbage", "not msgpack"),
    (_envelope(99, 1), "unknown message type"),
    (_envelope(5, 2, 0, 0.0, 1, 0.0, 0.0), "version"),
    (_envelope(5, 1, 0, 0.0, 1, 0.0), "needs 5 fields"),
    (_envelope(5, 1, "zero", 0.0, 1, 0.0, 0.0), "expected an int"),
    (_envelope(4, 1, 0, 0.0, 1, [0.0, 0.0, 0.0], 0.0, ["<u2", [10, 3], b"\x00" * 60]), "version"),
    (_envelope(4, 2, 0, 0.0, 1, [0.0, 0.0, 0.0], 0.0, ["<u2", [10, 3], b"\x00" * 12]), "do not fill"),
    (_envelope(4, 2, 0, 0.0, 1, [0.0, 0.0, 0.0], 0.0, ["O", [1], b"\x00"]), "bad array dtype"),
    (_envelope(4, 2, 0, 0.0, 1, [0.0, 0.0, 0.0], 0.0, [["<u2"], [1], b"\x00\x00"]), "bad array dtype"),
    (_envelope(4, 2, 0, 0.0, 1, [0.0, 0.0, 0.0], 0.0, ["<u2", [-1, -2], b"\x00\x00"]), "bad array shape"),
    (_envelope(4, 2, 0, 0.0, 1, [0.0, 0.0, 0.0], 0.0, ["<u2", [1.0], b"\x00\x00"]), "bad array shape"),
    (_envelope(4, 2, 0, 0.0, 1, [0.0, 0.0, 0.0], 0.0, ["<u2", 1, b"\x00\x00"]), "bad array shape"),
    (msgpack.packb({"tick": 1}), "not a message envelope"),
])
def test_malformed_payloads_raise_one_named_error(payload, why):
    with pytest.raises(MalformedMessage, match=why):
        decode(payload)


def test_expected_type_is_enforced():
    with pytest.raises(MalformedMessage, match="expected Scan, got Command"):
        decode(encode(Command(0, 0.0, 1, 0.0, 0.0)), Scan)


def test_keys_follow_the_schema_and_refuse_bad_parts():
    assert keys.scan("r1", 7) == "ac/r1/v/7/scan"
    assert keys.cmd("r1", "*") == "ac/r1/v/*/cmd"
    assert keys.world_tick("r1") == "ac/r1/world/tick"
    assert keys.vid_of(keys.alive("r1", 12)) == 12
    with pytest.raises(ValueError):
        keys.scan("bad/run", 1)
    with pytest.raises(ValueError):
        keys.scan("r", -1)


def test_a_bundle_gives_each_receiver_its_row_and_refuses_a_mask_that_does_not_fit():
    from protocol.messages import CtrlBundle, DataBundle, Reception

    heard = np.array([[False, True, True], [True, False, False]])  # receivers 2 and 5; senders 1, 2, 5
    b = decode(encode(CtrlBundle(4, 0.4, np.array([1, 2, 5]), np.array([2, 5]), heard, [b"a", b"b", b"c"])), CtrlBundle)
    assert b.heard_by(2) == [b"b", b"c"] and b.heard_by(5) == [b"a"] and b.heard_by(1) is None
    rx = [Reception(1, 7, 0.01, b"x"), Reception(5, 3, 0.02, b"y")]
    d = decode(encode(DataBundle(4, 0.4, np.array([2, 5]), np.array([[True, True], [False, False]]), rx)), DataBundle)
    assert d.received_by(2) == rx and d.received_by(5) == [] and d.received_by(3) is None
    with pytest.raises(MalformedMessage, match="heard must be bool"):
        decode(_bundle_bytes(heard[:, :2]), CtrlBundle)
    with pytest.raises(MalformedMessage, match=r"CtrlBundle.heard: expected bool \(n, n\), got uint8"):
        decode(_bundle_bytes(heard.astype(np.uint8)), CtrlBundle)
    with pytest.raises(MalformedMessage, match="receivers must be ascending"):
        decode(_bundle_bytes(heard, receivers=[5, 2]), CtrlBundle)


def _bundle_bytes(heard, receivers=(2, 5)):
    """A CtrlBundle's wire bytes built by hand, bypassing the constructor's checks."""
    arr = lambda a: [a.dtype.str, list(a.shape), a.tobytes()]  # noqa: E731
    return msgpack.packb([8, 2, 4, 0.4, arr(np.array([1, 2, 5])), arr(np.array(receivers)), arr(np.asarray(heard)),
                          [b"a", b"b", b"c"]], use_bin_type=True)


def test_decode_fields_reads_the_named_fields_as_decode_does_and_no_others():
    """The named fields of a message, equal to ``decode``'s, checked as it checks them;
    the fields not named are not read, so a fault there goes unnoticed (by design)."""
    scan = Scan(7, 0.7, 3, Pose(1.0, 2.0, 0.5), 4.0, np.arange(6, dtype=np.uint16).reshape(2, 3))
    assert decode_fields(encode(scan), Scan, ()) == ()
    tick, pose, ranges = decode_fields(encode(scan), Scan, ("tick", "pose", "range_cm"))
    whole = decode(encode(scan), Scan)
    assert (tick, pose) == (whole.tick, whole.pose) and np.array_equal(ranges, whole.range_cm)
    body = msgpack.unpackb(encode(scan))
    body[2 + 5][2] = b"\x00"  # range_cm: one byte for six uint16
    broken = msgpack.packb(body)
    assert decode_fields(broken, Scan, ("tick", "pose"))[0] == 7
    with pytest.raises(MalformedMessage, match=r"Scan\.range_cm"):
        decode_fields(broken, Scan, ("range_cm",))
    with pytest.raises(MalformedMessage, match="expected Pose"):
        decode_fields(encode(scan), Pose, ("x_m",))
    with pytest.raises(MalformedMessage, match="Scan needs"):
        decode_fields(msgpack.packb(body[:-1]), Scan, ("tick",))


# ------------------------------------------------------------------ packed arrays


def _packed_msg(vis: np.ndarray, rel: np.ndarray) -> ControlMsg:
    n, m = vis.shape
    om = ObjectMap(np.arange(n, dtype=np.int64), np.full(n, 70, np.int64), np.zeros((n, 2), np.float32),
                   np.arange(m, dtype=np.int64), vis, rel)
    return ControlMsg(3, 0.3, 1, Pose(0.0, 1.0, 2.0), 4.0, np.zeros((2, 3), np.float32), om, np.array([2]))


def test_a_packed_table_is_two_masks_and_the_other_values_on_the_wire():
    """Worked by hand: entries (C order) 0, 1, 0.5 / -0.0, 0, 1: ones at 1 and 5 (bits
    0b01000100), others at 2 and 3 (0b00110000, -0.0 is not +0.0's bits), their values
    in order; the decoded table has every entry's bits."""
    vis = np.array([[0.0, 1.0, 0.5], [-0.0, 0.0, 1.0]], np.float32)
    body = msgpack.unpackb(encode(_packed_msg(vis, np.zeros((2, 3), np.float32))), raw=False)
    assert body[8][4] == ["<f4", [2, 3], b"\x44", b"\x30", np.array([0.5, -0.0], "<f4").tobytes()]
    assert body[8][5] == ["<f4", [2, 3], b"\x00", b"\x00", b""]  # relevance, all +0.0
    got = decode(encode(_packed_msg(vis, vis)), ControlMsg)
    assert got.objects.visibility.tobytes() == vis.tobytes() and got.objects.relevance.dtype == np.float32


def test_a_packed_table_keeps_every_bit_pattern():
    """NaNs with payloads, -0.0, denormals, infinities, 1.0 and its neighbours."""
    bits = np.array([0, 0x80000000, 0x3F800000, 0x3F800001, 0x3F7FFFFF, 0x7FC00001, 0xFFFFFFFF, 1, 0x7F800000,
                     0xFF800000, 0x00000000, 0x3F800000], np.uint32)
    vis = bits.view(np.float32).reshape(3, 4)
    rel = bits[::-1].copy().view(np.float32).reshape(3, 4)
    table = codec._converter(typing.get_type_hints(ObjectMap, include_extras=True)["visibility"])
    for t in (vis, rel):
        assert table(codec._packed_to_wire(t)).view(np.uint32).tolist() == t.view(np.uint32).tolist()
    # a share outside [0, 1] (NaN, infinities, 1.0's neighbour above) is no share: the message is refused
    with pytest.raises(MalformedMessage, match=r"^ControlMsg\.objects\.visibility: holds a value not in \[0, 1\]"):
        decode(encode(_packed_msg(vis, rel)), ControlMsg)


@pytest.mark.parametrize("table, why", [
    (["<f4", [1, 1], b"\x00"], "expected a packed array"),  # the dense form
    (["<f8", [1, 1], b"\x00", b"\x00", b""], "expected a packed float32 .n, n., got dtype '<f8'"),
    (["<f4", [1], b"\x00", b"\x00", b""], "got shape"),
    (["<f4", [1, 1], b"", b"", b""], "masks of 0 and 0 bytes for 1 entries"),
    (["<f4", [3, 3], b"\x00", b"\x00\x00", b""], "masks of 1 and 2 bytes for 9 entries"),
    (["<f4", [1, 1], b"\x40", b"\x00", b""], "mask padding bits set"),
    (["<f4", [1, 1], b"\x80", b"\x80", b"\x00\x00\x00\x00"], "marked both 1 and other"),
    (["<f4", [1, 2], b"\x00", b"\xc0", b"\x00\x00\x00\x00"], "4 bytes of values for 2 entries"),
    (["<f4", [1, 2], b"\x00", b"\x00", b"\x00"], "1 bytes of values for 0 entries"),
    (["<f4", [1, 1], b"\x00", "\x00", b""], "masks and values are bytes"),
    (["<f4", [1, 1], b"\x00", b"\x80", np.ones(1, "<f4").tobytes()], "a value of 1.0 or \\+0.0 among the others"),
    (["<f4", [1, 1], b"\x00", b"\x80", np.zeros(1, "<f4").tobytes()], "a value of 1.0 or \\+0.0 among the others"),
])
def test_a_bad_packed_table_is_refused_naming_its_field(table, why):
    msg = _packed_msg(np.zeros((1, 1), np.float32), np.zeros((1, 1), np.float32))
    body = msgpack.unpackb(encode(msg), raw=False)
    body[8][4] = table
    with pytest.raises(MalformedMessage, match=r"^ControlMsg\.objects\.visibility: .*" + why):
        decode(msgpack.packb(body, use_bin_type=True), ControlMsg)
