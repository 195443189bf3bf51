"""Every message type declares its invariants (``INVARIANTS``, protocol/messages.py) and
the codec refuses a message that breaks one, naming the field: a well-typed lie (the
right dtypes, the wrong shapes, lengths or values), crafted at the wire level as a
hostile sender would, never decodes."""

from __future__ import annotations

import math
import re
import struct

import msgpack
import numpy as np
import pytest

from protocol.codec import COORD_BOUND_M, MalformedMessage, _packed_to_wire, decode, encode, message_types
from protocol.messages import (MAX_SPEED_MPS, AgentReport, Certificate, ChannelStats, Command, ControlMsg,
                               CtrlBundle, DataBundle, DataTx, EmpBundle, EmpSegment, EmpUpload, InShm, Lane,
                               LidarConfig, LightState, MapMsg, Mission, ObjectMap, Outcome, Pose, Reception, Rejected,
                               Scan, Signed, Tick, TrafficLight, Transmission, VehicleSpec, WorldTruth)
from vehicle_agent.agreement import HeardControl
from vehicle_agent.payload import HEADER_BOUNDS, ObjectPayload, decode_object, decode_objects, encode_object

F4, I8 = np.float32, np.int64


def _control() -> ControlMsg:
    objects = ObjectMap(np.array([3, 5, 9], I8), np.array([700, 80, 1500], I8),
                        np.array([[10, 2], [12, -4], [30, 1]], F4), np.array([2, 4], I8),
                        np.array([[1, 0], [0.5, 1], [0, 0]], F4), np.array([[0.2, 0], [0, 1], [0, 0.7]], F4))
    return ControlMsg(7, 0.7, 1, Pose(3.0, -2.0, 0.1), 8.0, np.array([[3, -2, 0.8], [5, -2, 1.0], [9, -2, 1.5]], F4),
                      objects, np.array([0, 2, 4], I8), np.array([0, 3, 1], I8), np.zeros((3, 16), np.uint8))


HONEST = {
    MapMsg: MapMsg(0, 0.0, "cross", [Lane("S.in.0", np.array([[0.0, -100], [0, -10]]), 3.5, 13.9, 0, 88.0)],
                   [np.array([[-10.0, -10], [10, -10], [10, 10]])], [TrafficLight(0, 5.0, -10.0)],
                   np.array([[40.0, 40, 0, 60, 60, 12]])),
    Mission: Mission(0, 0.0, 1, "occluder", np.array([[0.0, -50], [0, 50]]), 8.0,
                     VehicleSpec(8.0, 2.5, 3.5, 5.0, 2.0, 6.5, 0.6), LidarConfig(), 0.1),
    Tick: Tick(4, 0.4, [0, 1, 2], [LightState(0, "red"), LightState(1, "green")]),
    Scan: Scan(4, 0.4, 1, Pose(3.0, -2.0, 0.1), 8.0, np.zeros((1800, 64), np.uint16)),
    Command: Command(4, 0.4, 1, -2.0, 0.1),
    Outcome: Outcome(40, 4.0, {"outcome": "safe"}),
    ControlMsg: _control(),
    CtrlBundle: CtrlBundle(7, 0.7, np.array([0, 1, 1], I8), np.array([0, 1], I8), np.ones((2, 3), bool),
                           [b"a", b"b", b"c"]),
    DataTx: DataTx(7, 0.7, 1, [Transmission(3, 0.01, b"pts")]),
    DataBundle: DataBundle(7, 0.7, np.array([0, 2], I8), np.ones((2, 1), bool), [Reception(1, 3, 0.02, b"pts")]),
    ChannelStats: ChannelStats(7, 0.7, {"offered_bytes": 10}),
    EmpUpload: EmpUpload(7, 0.7, 1, Pose(3.0, -2.0, 0.1), np.array([[4, -2, 0.5]], F4)),
    EmpBundle: EmpBundle(7, 0.7, 0, [EmpSegment(1, Pose(3.0, -2.0, 0.1), 0.02, np.array([[4, -2, 0.5]], F4))],
                         np.array([0, 1], I8), np.array([[0.0, 0], [3, -2]])),
    AgentReport: AgentReport(7, 0.7, 0, np.array([[4, -2], [5, -3]], F4), 1, False),
    WorldTruth: WorldTruth(7, 0.7, np.array([0, 1], I8), np.array([[0, 0, 0], [3, -2, 0.1]], F4),
                           np.array([5, 8], F4), np.array([[4.5, 1.8, 1.5], [8, 2.5, 3.5]], F4)),
    Signed: Signed(7, 0.7, Certificate("run", 1, 0.0, 60.0, b"k" * 32, b"s" * 64), b"body", b"x" * 64),
    InShm: InShm(7, 0.7, 230_000),
    Rejected: Rejected(7, 0.7, 1, {"total": 0}),
}


def _array(triple: list, change) -> list:
    """An array on the wire (``[dtype, shape, bytes]``) with ``change`` applied to a copy."""
    a = np.frombuffer(triple[2], triple[0]).reshape(triple[1]).copy()
    a = change(a)
    return [a.dtype.str, list(a.shape), a.tobytes()]


def _set(body: list, path: tuple, value) -> list:
    """``body`` (the message's wire list) with the item at ``path`` replaced (``value(old)``)."""
    node = body
    for i in path[:-1]:
        node = node[i]
    node[path[-1]] = value(node[path[-1]])
    return body


def _at(value):
    def change(a):
        a[(0,) * a.ndim] = value
        return a
    return change


# (type, what the lie is, field index path into [type_id, version, *fields], new value, the field the error names)
NAN, BIG = math.nan, 1e30
LIES = [
    (MapMsg, "a building at 1e30", (8,), lambda t: _array(t, _at(BIG)), "MapMsg.buildings"),
    (MapMsg, "a NaN polygon", (6, 0), lambda t: _array(t, _at(NAN)), "MapMsg.drivable"),
    (MapMsg, "a lane centreline off the map", (5, 0, 1), lambda t: _array(t, _at(5e3)), "MapMsg.lanes[0].centerline"),
    (Mission, "a NaN route", (6,), lambda t: _array(t, _at(NAN)), "Mission.route"),
    (Mission, "a negative cruise speed", (7,), lambda v: -5.0, "Mission.cruise_speed_mps"),
    (Mission, "a LiDAR of 0 beams", (9, 0), lambda v: 0, "Mission.lidar.beams"),
    (Tick, "live vehicles out of order", (4,), lambda v: [2, 0, 1], "Tick.live"),
    (Tick, "a tick before the first", (2,), lambda v: -1, "Tick.tick"),
    (Tick, "a light twice", (5,), lambda v: [v[0], v[0]], "Tick.lights"),
    (Scan, "a NaN pose", (5, 0), lambda v: NAN, "Scan.pose.x_m"),
    (Scan, "an infinite speed", (6,), lambda v: math.inf, "Scan.speed_mps"),
    (Scan, "a range image of 2^20 azimuths", (7,), lambda t: ["<u2", [1 << 20, 0], b""], "Scan.range_cm"),
    (Command, "a NaN acceleration", (5,), lambda v: NAN, "Command.accel_mps2"),
    (Command, "steering past half a turn", (6,), lambda v: 10.0, "Command.steer_rad"),
    (Command, "a vehicle id out of range", (4,), lambda v: 1 << 40, "Command.vid"),
    (Outcome, "a NaN time", (3,), lambda v: NAN, "Outcome.t_sim_s"),
    # the control message: the kinds of lie, each at the wire level
    (ControlMsg, "a NaN pose", (5, 0), lambda v: NAN, "ControlMsg.pose.x_m"),
    (ControlMsg, "a 1e30 pose", (5, 1), lambda v: BIG, "ControlMsg.pose.y_m"),
    (ControlMsg, "an infinite speed", (6,), lambda v: math.inf, "ControlMsg.speed_mps"),
    (ControlMsg, "a NaN trajectory", (7,), lambda t: _array(t, _at(NAN)), "ControlMsg.trajectory"),
    (ControlMsg, "a trajectory back in time", (7,), lambda t: _array(t, lambda a: a[::-1].copy()),
     "ControlMsg.trajectory"),
    (ControlMsg, "a trajectory of 10^4 waypoints", (7,), lambda t: _array(t, lambda a: np.repeat(a, 4000, axis=0)),
     "ControlMsg.trajectory"),
    (ControlMsg, "NaN centroids", (8, 2), lambda t: _array(t, _at(NAN)), "ControlMsg.objects.centroid_xy"),
    (ControlMsg, "a negative size", (8, 1), lambda t: _array(t, _at(-70)), "ControlMsg.objects.size_bytes"),
    (ControlMsg, "a 2^62-byte object", (8, 1), lambda t: _array(t, _at(1 << 62)), "ControlMsg.objects.size_bytes"),
    (ControlMsg, "an object id twice", (8, 0), lambda t: _array(t, lambda a: np.array([3, 3, 9], I8)),
     "ControlMsg.objects.object_id"),
    (ControlMsg, "sizes of fewer objects", (8, 1), lambda t: _array(t, lambda a: a[:2]),
     "ControlMsg.objects.size_bytes"),
    (ControlMsg, "a visibility of 2", (8, 4), lambda t: _packed_to_wire(np.full((3, 2), 2.0, F4)),
     "ControlMsg.objects.visibility"),
    (ControlMsg, "a NaN relevance", (8, 5), lambda t: _packed_to_wire(np.full((3, 2), NAN, F4)),
     "ControlMsg.objects.relevance"),
    (ControlMsg, "receivers twice", (8, 3), lambda t: _array(t, lambda a: np.array([2, 2], I8)),
     "ControlMsg.objects.receivers"),
    (ControlMsg, "a starvation list longer than the objects", (10,), lambda t: _array(t, lambda a: np.arange(5)),
     "ControlMsg.unscheduled"),
    (ControlMsg, "a negative starvation count", (10,), lambda t: _array(t, _at(-4)), "ControlMsg.unscheduled"),
    (ControlMsg, "digests of fewer objects", (11,), lambda t: _array(t, lambda a: a[:1]), "ControlMsg.digests"),
    (ControlMsg, "a heard list with a vehicle twice", (9,), lambda t: _array(t, lambda a: np.array([0, 2, 2], I8)),
     "ControlMsg.heard"),
    (ControlMsg, "a negative vehicle id", (4,), lambda v: -1, "ControlMsg.vid"),
    (CtrlBundle, "senders out of order", (4,), lambda t: _array(t, lambda a: a[::-1].copy()), "CtrlBundle.senders"),
    (CtrlBundle, "a receiver id out of range", (5,), lambda t: _array(t, _at(-3)), "CtrlBundle.receivers"),
    (DataTx, "a NaN start", (5, 0, 1), lambda v: NAN, "DataTx.transmissions[0].start_s"),
    (DataTx, "a negative object id", (5, 0, 0), lambda v: -1, "DataTx.transmissions[0].object_id"),
    (DataBundle, "a reception before the phase", (6, 0, 2), lambda v: -1.0, "DataBundle.receptions[0].rx_time_s"),
    (DataBundle, "a receiver id out of range", (4,), lambda t: _array(t, _at(1 << 20)), "DataBundle.receivers"),
    (ChannelStats, "a negative tick", (2,), lambda v: -5, "ChannelStats.tick"),
    (EmpUpload, "NaN points", (6,), lambda t: _array(t, _at(NAN)), "EmpUpload.points_world"),
    (EmpUpload, "points 1e30 away", (6,), lambda t: _array(t, _at(BIG)), "EmpUpload.points_world"),
    (EmpBundle, "sites of fewer vehicles", (7,), lambda t: _array(t, lambda a: a[:1]), "EmpBundle.site_xy"),
    (EmpBundle, "a site twice", (6,), lambda t: _array(t, lambda a: np.array([1, 1], I8)), "EmpBundle.site_vids"),
    (EmpBundle, "a segment's infinite point", (5, 0, 3), lambda t: _array(t, _at(math.inf)),
     "EmpBundle.segments[0].points_world"),
    (AgentReport, "more received points than points", (6,), lambda v: 3, "AgentReport.received_points"),
    (AgentReport, "a fused point off the map", (5,), lambda t: _array(t, _at(2 * COORD_BOUND_M)),
     "AgentReport.fused_xy"),
    (WorldTruth, "poses of fewer vehicles", (5,), lambda t: _array(t, lambda a: a[:1]), "WorldTruth.pose"),
    (WorldTruth, "a vehicle twice", (4,), lambda t: _array(t, lambda a: np.array([1, 1], I8)), "WorldTruth.vids"),
    (Signed, "a short signature", (6,), lambda v: v[:63], "Signed.signature"),
    (Signed, "a certificate's short key", (4, 4), lambda v: v[:31], "Signed.certificate.public_key"),
    (Signed, "a certificate that ends before it starts", (4, 3), lambda v: -1.0, "Signed.certificate.valid_until_s"),
    (InShm, "a negative size", (4,), lambda v: -1, "InShm.nbytes"),
    (Rejected, "a negative vehicle id", (4,), lambda v: -1, "Rejected.vid"),
]


def test_every_message_type_has_honest_example_and_lies():
    assert set(HONEST) == set(message_types())
    assert {cls for cls, *_ in LIES} == set(message_types())
    for cls, msg in HONEST.items():
        assert decode(encode(msg), cls) is not None  # the honest example is valid


@pytest.mark.parametrize("cls, what, path, value, field", LIES, ids=[f"{c.__name__}: {w}" for c, w, *_ in LIES])
def test_a_well_typed_lie_is_refused_naming_its_field(cls, what, path, value, field):
    body = _set(msgpack.unpackb(encode(HONEST[cls]), raw=False), path, value)
    with pytest.raises(MalformedMessage, match="^" + re.escape(field) + r"(:| )"):
        decode(msgpack.packb(body, use_bin_type=True), cls)


@pytest.mark.parametrize("path, value, field", [
    ((5, 0), lambda v: NAN, "ControlMsg.pose"), ((7,), lambda t: _array(t, lambda a: a[::-1].copy()),
                                                 "ControlMsg.trajectory"),
    ((9,), lambda t: _array(t, lambda a: np.array([2, 0], I8)), "ControlMsg.heard")])
def test_a_vehicle_reads_the_ballot_and_motion_of_a_heard_message_under_the_same_invariants(path, value, field):
    """An agent reads every heard control message's ballot and motion alone
    (``decode_fields``) and opens the object map only for its group: each read checks
    the invariants of the fields it reads, and opening the rest checks the others."""
    raw = msgpack.packb(_set(msgpack.unpackb(encode(HONEST[ControlMsg]), raw=False), path, value), use_bin_type=True)
    with pytest.raises(MalformedMessage, match="^" + re.escape(field)):
        HeardControl.read(raw)
    lie = _set(msgpack.unpackb(encode(HONEST[ControlMsg]), raw=False), (10,), lambda t: _array(t, lambda a: a[:2]))
    heard = HeardControl.read(msgpack.packb(lie, use_bin_type=True))  # its ballot and motion are honest
    with pytest.raises(MalformedMessage, match=r"^ControlMsg\.unscheduled"):
        heard.message()


# ------------------------------------------------------------------ object payloads
# Not a message of the codec: a payload's header is a struct (vehicle_agent.payload), its
# floats checked against HEADER_BOUNDS, the codec's bounds for the same quantities.

def _object_payload(**header) -> bytes:
    pts = np.array([[10.0, 2.0, 0.5], [10.5, 2.5, 1.0]], F4)
    fields = dict(sender_pose=Pose(3.0, -2.0, 0.1), centroid_sensor=pts.mean(axis=0),
                  velocity_xy=np.array([8.0, 0.0], F4), tick=7, t_sim_s=0.7, mount_height_m=1.9)
    fields.update(header)
    return encode_object(ObjectPayload(1, 3, points_sensor=pts, **fields))


def _header_float(raw: bytes, field: str, value: float) -> bytes:
    """``raw`` with the header float ``field`` (a key of ``HEADER_BOUNDS``) set to ``value``."""
    out = bytearray(raw)
    struct.pack_into("<f", out, 16 + 4 * list(HEADER_BOUNDS).index(field), value)  # the floats start at byte 16
    return bytes(out)


PAYLOAD_LIES = [(field, value) for field in HEADER_BOUNDS for value in (NAN, math.inf, -math.inf)] + [
    ("t_sim_s", -0.1), ("t_sim_s", 2e6), ("sender_pose.x_m", 2 * COORD_BOUND_M), ("sender_pose.y_m", -BIG),
    ("mount_height_m", BIG), ("centroid_sensor[0]", BIG), ("centroid_sensor[2]", -2 * COORD_BOUND_M),
    ("velocity_xy[0]", 2 * MAX_SPEED_MPS), ("velocity_xy[1]", -BIG)]


@pytest.mark.parametrize("field, value", PAYLOAD_LIES, ids=[f"{f}={v:g}" for f, v in PAYLOAD_LIES])
def test_an_object_payload_whose_header_lies_is_refused_naming_its_field(field, value):
    honest = _object_payload()
    lie = _header_float(honest, field, value)
    with pytest.raises(MalformedMessage, match="^" + re.escape(f"ObjectPayload.{field}: ")) as refused:
        decode_object(lie)
    batch, dropped = decode_objects([honest, lie, honest])  # the batch: the same check, the same reason
    assert len(batch) == 2 and [str(e) for e in dropped] == [str(refused.value)]


def test_an_object_payload_with_a_negative_tick_is_refused_and_one_at_the_bounds_is_not():
    with pytest.raises(MalformedMessage, match=r"^ObjectPayload\.tick: "):
        decode_object(_object_payload(tick=-1))
    assert len(decode_objects([_object_payload(tick=-1)])[1]) == 1
    edge = _object_payload(sender_pose=Pose(COORD_BOUND_M, -COORD_BOUND_M, 1e30), t_sim_s=0.0,
                           velocity_xy=np.array([MAX_SPEED_MPS, -MAX_SPEED_MPS], F4))
    assert decode_object(edge).sender_pose.x_m == COORD_BOUND_M
    assert len(decode_objects([edge])[0]) == 1
