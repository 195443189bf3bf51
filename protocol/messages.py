"""Every message that crosses a process boundary, in one place.

Each top-level message carries ``tick`` (decision interval number) and ``t_sim_s``
(simulation time at the start of that tick). Units are in the field names. Poses are
in the world frame (x east, y north, yaw counter-clockwise from +x); scans are in the
sensor frame (origin at the LiDAR, x forward, y left, z up). An array field declares
its dtype and shape (``Array``: ``"<f4", (None, 3)`` is float32 of three columns, any
number of rows); a message whose arrays are otherwise is refused whole. Each message
and record declares in ``INVARIANTS`` what its values must be besides (``protocol.codec``:
finite, within the map's bound and a margin, ids unique, lengths that agree, counts and
sizes within limits, times that do not go back); the decoder refuses a message that
breaks one, naming the field.
"""

from __future__ import annotations

from dataclasses import field
from typing import Annotated, Any

import numpy as np

from protocol.codec import (MAP_BOUND_M, MAX_TICK, MAX_VID, STAMPED, Array, Invariant, ascending, at_most, byte_length, each,
                            finite, in_map, message, nondecreasing, record, same_rows, unique, vid, waypoints, within)

MAX_OBJECTS = 4096  # objects in one vehicle's map
MAX_OBJECT_BYTES = 1 << 24  # one object's payload on air (a 40-vehicle run's largest is ~0.3 MB)
MAX_POINTS = 1 << 22  # points of one point cloud (a full 64 x 1800 scan is 115,200)
MAX_SPEED_MPS = 100.0
MAX_ACCEL_MPS2 = 100.0
MAX_WAYPOINTS = 1024
MAX_ITEMS = 1 << 16  # transmissions, receptions, segments, lanes: far beyond any run's
MAX_RANGE_IMAGE = (1 << 14, 1 << 10)  # azimuth steps, beams
PUBLIC_KEY_BYTES, SIGNATURE_BYTES = 32, 64
MAX_DOMAINS = 256  # scheduler domains of one map, and radio channels

# ---------------------------------------------------------------------------- records


@record
class Pose:
    x_m: float
    y_m: float
    yaw_rad: float

    INVARIANTS = (in_map("x_m"), in_map("y_m"), *finite("yaw_rad"))


@record
class LidarConfig:
    """A spinning LiDAR: ``beams`` elevations evenly spread over the vertical FOV."""

    beams: int = 64
    fov_up_deg: float = 2.0
    fov_down_deg: float = -24.8
    azimuth_steps: int = 1800
    range_m: float = 100.0
    mount_height_m: float = 1.9

    INVARIANTS = (within("beams", 1, MAX_RANGE_IMAGE[1]), within("azimuth_steps", 1, MAX_RANGE_IMAGE[0]),
                  within("fov_up_deg", -90.0, 90.0), within("fov_down_deg", -90.0, 90.0),
                  within("range_m", 0.0, 10_000.0), *finite("mount_height_m"))

    def elevations_rad(self) -> np.ndarray:
        return np.deg2rad(np.linspace(self.fov_up_deg, self.fov_down_deg, self.beams))

    def azimuths_rad(self) -> np.ndarray:
        return np.arange(self.azimuth_steps) * (2.0 * np.pi / self.azimuth_steps) - np.pi


@record
class Lane:
    """A directed lane: its centreline runs in the direction of travel."""

    lane_id: str
    centerline: Annotated[np.ndarray, Array("<f8", (None, 2))]  # metres, world frame
    width_m: float
    speed_limit_mps: float
    light_id: int  # traffic light governing the lane's end, -1 if none
    stop_s_m: float  # arc length of the stop line along the centreline, -1 if none

    INVARIANTS = (within("centerline", -MAP_BOUND_M, MAP_BOUND_M), *finite("width_m", "speed_limit_mps", "stop_s_m"),
                  within("light_id", -1, MAX_ITEMS))


@record
class TrafficLight:
    light_id: int
    x_m: float
    y_m: float

    INVARIANTS = (within("light_id", 0, MAX_ITEMS), within("x_m", -MAP_BOUND_M, MAP_BOUND_M),
                  within("y_m", -MAP_BOUND_M, MAP_BOUND_M))


@record
class Domain:
    """A scheduler domain declared in the map (paper 4.1): the vehicles within
    ``radius_m`` of its centre schedule together on radio channel ``channel``;
    neighbouring domains use different channels (docs/domains.md)."""

    domain_id: int
    x_m: float
    y_m: float
    radius_m: float
    channel: int

    INVARIANTS = (within("domain_id", 0, MAX_DOMAINS - 1), within("x_m", -MAP_BOUND_M, MAP_BOUND_M),
                  within("y_m", -MAP_BOUND_M, MAP_BOUND_M), within("radius_m", 0.0, MAP_BOUND_M),
                  within("channel", 0, MAX_DOMAINS - 1))


DEFAULT_DOMAIN = Domain(0, 0.0, 0.0, 85.0, 0)  # R/2 with R ~ 170 m (urban LTE-Direct), paper 4.1


@record
class LightState:
    light_id: int
    state: str  # "red" | "yellow" | "green"


@record
class VehicleSpec:
    length_m: float
    width_m: float
    height_m: float
    wheelbase_m: float
    max_accel_mps2: float
    max_brake_mps2: float
    max_steer_rad: float

    INVARIANTS = tuple(within(f, 0.0, 1000.0) for f in ("length_m", "width_m", "height_m", "wheelbase_m",
                                                        "max_accel_mps2", "max_brake_mps2", "max_steer_rad"))


# ---------------------------------------------------------------------------- messages


def _no_domains() -> list:
    return []


@message(1, version=2)
class MapMsg:
    """The road map, served once to each agent (the paper assumes a shared 3-D map).

    ``domains``: the scheduler domains the map declares (version 2 added them); none
    means the one domain of R/2 around the origin on channel 0 (``scheduler_domains``)."""

    tick: int
    t_sim_s: float
    name: str
    lanes: list[Lane]
    drivable: list[Annotated[np.ndarray, Array("<f8", (None, 2))]]  # polygons; their union is drivable
    lights: list[TrafficLight]
    buildings: Annotated[np.ndarray, Array("<f8", (None, 6))]  # static prisms [cx, cy, yaw, length, width, height]
    domains: list[Domain] = field(default_factory=_no_domains)

    INVARIANTS = (*STAMPED, at_most("lanes", MAX_ITEMS), at_most("drivable", MAX_ITEMS),
                  each("drivable", within("polygon", -MAP_BOUND_M, MAP_BOUND_M)), Invariant(
                      ("lights",), lambda v: None if len({x.light_id for x in v}) == len(v) else "a light id twice"),
                  within("buildings", -MAP_BOUND_M, MAP_BOUND_M, slice(0, 2)), *finite("buildings"),
                  at_most("domains", MAX_DOMAINS), Invariant(
                      ("domains",), lambda v: None if [d.domain_id for d in v] == list(range(len(v)))
                      else "domain ids not 0, 1, ... in order"))

    def scheduler_domains(self) -> list[Domain]:
        """The declared domains, or the one default domain (R/2 around the origin, channel 0)."""
        return list(self.domains) or [DEFAULT_DOMAIN]


@message(2)
class Mission:
    """What one connected vehicle is and where it is going: its own knowledge only."""

    tick: int
    t_sim_s: float
    vid: int
    role: str  # "ego" | "occluder" | "background"
    route: Annotated[np.ndarray, Array("<f8", (None, 2))]  # waypoints of the intended path, world frame
    cruise_speed_mps: float
    spec: VehicleSpec
    lidar: LidarConfig
    decision_interval_s: float

    INVARIANTS = (*STAMPED, *vid("vid"), within("route", -MAP_BOUND_M, MAP_BOUND_M), at_most("route", MAX_ITEMS),
                  within("cruise_speed_mps", 0.0, MAX_SPEED_MPS), within("decision_interval_s", 1e-3, 10.0))


@message(3)
class Tick:
    """Start of decision interval ``tick``; ``live`` lists the connected vehicles in play."""

    tick: int
    t_sim_s: float
    live: list[int]
    lights: list[LightState]

    INVARIANTS = (*STAMPED, at_most("live", MAX_VID), each("live", within("vid", 0, MAX_VID - 1)),
                  Invariant(("live",), lambda v: None if all(a < b for a, b in zip(v, v[1:])) else
                            "is not strictly ascending"),
                  Invariant(("lights",), lambda v: None if len({x.light_id for x in v}) == len(v) else "a light twice"))


@message(4, version=2)
class Scan:
    """One vehicle's LiDAR sweep for a tick, as a range image, with its exact pose.

    ``range_cm[i, b]`` is the horizontal distance (cm) of the return of the ray at
    azimuth ``i`` and beam ``b`` of the vehicle's ``LidarConfig`` (in its ``Mission``),
    0 for no return: 2 bytes per ray instead of 12 per point (version 1 sent float32
    points; at 40 vehicles that was ~50 MB per tick through the hub). ``points`` turns
    it back into sensor-frame points, to within 0.5 cm horizontally.
    """

    tick: int
    t_sim_s: float
    vid: int
    pose: Pose
    speed_mps: float
    range_cm: Annotated[np.ndarray, Array("<u2", (None, None))]  # (azimuth_steps, beams)

    INVARIANTS = (*STAMPED, *vid("vid"), within("speed_mps", -MAX_SPEED_MPS, MAX_SPEED_MPS),
                  Invariant(("range_cm",), lambda a: None if a.shape[0] <= MAX_RANGE_IMAGE[0] and
                            a.shape[1] <= MAX_RANGE_IMAGE[1] else f"a {a.shape} range image: at most {MAX_RANGE_IMAGE}"))

    def points(self, lidar: LidarConfig) -> np.ndarray:
        """float32 (n, 3) sensor-frame points, azimuth-major, rays without a return left out."""
        if self.range_cm.shape != (lidar.azimuth_steps, lidar.beams):
            raise ValueError(f"range image {self.range_cm.shape} does not fit a "
                             f"{lidar.azimuth_steps} x {lidar.beams} LiDAR")
        col, beam = np.nonzero(self.range_cm)
        d = self.range_cm[col, beam].astype(np.float64) * 0.01
        az, el = lidar.azimuths_rad(), lidar.elevations_rad()
        return np.column_stack([d * np.cos(az[col]), d * np.sin(az[col]), d * np.tan(el[beam])]).astype(np.float32)


@message(13)
class WorldTruth:
    """Ground truth of a tick, for the log and the viewer only (no agent subscribes):
    where every vehicle, the passive collider included, really is."""

    tick: int
    t_sim_s: float
    vids: Annotated[np.ndarray, Array("<i8", (None,))]
    pose: Annotated[np.ndarray, Array("<f4", (None, 3))]  # x_m, y_m, yaw_rad
    speed_mps: Annotated[np.ndarray, Array("<f4", (None,))]
    size_m: Annotated[np.ndarray, Array("<f4", (None, 3))]  # length, width, height

    INVARIANTS = (*STAMPED, *vid("vids"), unique("vids"), same_rows("pose", "vids"), same_rows("speed_mps", "vids"),
                  same_rows("size_m", "vids"), in_map("pose"), *finite("pose"),
                  within("speed_mps", -MAX_SPEED_MPS, MAX_SPEED_MPS), within("size_m", 0.0, 1000.0))


@message(5)
class Command:
    """An agent's actuation for the interval that starts at ``tick``."""

    tick: int
    t_sim_s: float
    vid: int
    accel_mps2: float  # negative brakes
    steer_rad: float  # front-wheel angle, positive turns left

    INVARIANTS = (*STAMPED, *vid("vid"), within("accel_mps2", -MAX_ACCEL_MPS2, MAX_ACCEL_MPS2),
                  within("steer_rad", -np.pi, np.pi))


@message(6)
class Outcome:
    """The judged result of a run; ``result`` is the JSON-ready dict the CLI prints."""

    tick: int
    t_sim_s: float
    result: dict[str, Any]

    INVARIANTS = STAMPED


# ------------------------------------------------------------------ V2V (channel proxy)


@record
class ObjectMap:
    """A sender's object map (paper 4.1) as arrays: row t is object ``object_id[t]``,
    column c is receiver ``receivers[c]`` (the other vehicles of the domain)."""

    object_id: Annotated[np.ndarray, Array("<i8", (None,))]  # (n,)
    size_bytes: Annotated[np.ndarray, Array("<i8", (None,))]  # (n,), what the object's payload will occupy on air
    centroid_xy: Annotated[np.ndarray, Array("<f4", (None, 2))]  # (n, 2), world frame
    receivers: Annotated[np.ndarray, Array("<i8", (None,))]  # (m,)
    # the two tables travel packed (protocol.codec: two bit masks and the entries neither 0 nor 1): most
    # entries are 0 or 1, and a vehicle hears 39 such maps an interval at 40 vehicles
    visibility: Annotated[np.ndarray, Array("<f4", (None, None), packed=True)]  # (n, m), v_(i,k),j: 1 = j sees it itself
    relevance: Annotated[np.ndarray, Array("<f4", (None, None), packed=True)]  # (n, m), r_(i,k),j in [0, 1]

    INVARIANTS = (at_most("object_id", MAX_OBJECTS), within("object_id", 0, 1 << 53), unique("object_id"),
                  same_rows("size_bytes", "object_id"), same_rows("centroid_xy", "object_id"),
                  within("size_bytes", 0, MAX_OBJECT_BYTES), in_map("centroid_xy"),
                  ascending("receivers"),
                  Invariant(("visibility", "object_id", "receivers"), lambda t, o, r: _table(t, o, r)),
                  Invariant(("relevance", "object_id", "receivers"), lambda t, o, r: _table(t, o, r)))

    def __post_init__(self) -> None:
        n, m = len(self.object_id), len(self.receivers)
        rows = {"size_bytes": len(self.size_bytes), "centroid_xy": len(self.centroid_xy)}
        tables = {"visibility": self.visibility.shape, "relevance": self.relevance.shape}
        if any(k != n for k in rows.values()) or any(shape != (n, m) for shape in tables.values()):
            raise ValueError(f"{n} objects and {m} receivers, but rows {rows} and tables {tables}")


def _table(table: np.ndarray, objects: np.ndarray, receivers: np.ndarray) -> str | None:
    """An object map's table of shares: each in [0, 1] (its shape is the record's own check)."""
    if table.shape != (len(objects), len(receivers)):
        return None  # ObjectMap.__post_init__ refuses it, naming the map's dimensions
    if table.size and not (float(table.min()) >= 0.0 and float(table.max()) <= 1.0):  # NaN fails both
        return "holds a value not in [0, 1]"
    return None


def _no_counts() -> np.ndarray:
    return np.zeros(0, dtype=np.int64)


DIGEST_BYTES = 16  # SHA-256 of an object's payload, its first 128 bits (protocol.security.payload_digest)


def _no_digests() -> np.ndarray:
    return np.zeros((0, DIGEST_BYTES), dtype=np.uint8)


@message(7, version=5)
class ControlMsg:
    """One vehicle's control message for a decision interval (paper 4.1).

    ``unscheduled[t]`` is m of object ``objects.object_id[t]``: the intervals in a row it
    has gone unscheduled while still occluded from and relevant to some receiver, as its
    sender counted them (the starvation compensation's state, so every vehicle that
    hears the message weighs the object alike); empty means 0 for every object.
    Version 2 added it.

    ``digests[t]`` is the digest of the payload object ``objects.object_id[t]`` will
    have if it is scheduled this interval: a signed control message vouches for its
    sender's object payloads too, so a receiver checks a payload with one signature per
    sender and interval (docs/security.md). Empty when the run does not sign. Version 3
    added it; it is not on air (``medium.control_onair_bytes`` counts the map only).
    Version 4 packs the object map's two tables (``ObjectMap``): the same values, ~3x
    fewer bytes; what is on air is counted from the map's dimensions, as before.

    ``domains``: every scheduler domain its sender takes part in this interval, ascending
    (it sends one control message in each, on that domain's keys); empty in a map of
    one domain. The channel proxy closes a vehicle's control phase once it has all of
    them (docs/domains.md). Version 5 added it; it is not on air."""

    tick: int
    t_sim_s: float
    vid: int
    pose: Pose
    speed_mps: float
    trajectory: Annotated[np.ndarray, Array("<f4", (None, 3))]  # waypoints [x_m, y_m, t_sim_s], down-sampled
    objects: ObjectMap
    heard: Annotated[np.ndarray, Array("<i8", (None,))]  # the senders whose control messages this vehicle heard last interval
    unscheduled: Annotated[np.ndarray, Array("<i8", (None,))] = field(default_factory=_no_counts)  # (n,) or (0,): m per object
    digests: Annotated[np.ndarray, Array("|u1", (None, DIGEST_BYTES))] = field(default_factory=_no_digests)  # (n or 0, 16)
    domains: Annotated[np.ndarray, Array("<i8", (None,))] = field(default_factory=_no_counts)  # domain ids, or (0,)

    INVARIANTS = (*STAMPED, *vid("vid"), within("speed_mps", -MAX_SPEED_MPS, MAX_SPEED_MPS),
                  at_most("trajectory", MAX_WAYPOINTS), waypoints("trajectory"), ascending("heard"),
                  same_rows("unscheduled", "objects", lambda o: o.object_id, or_none=True),
                  within("unscheduled", 0, MAX_TICK),
                  same_rows("digests", "objects", lambda o: o.object_id, or_none=True),
                  ascending("domains", 0, MAX_DOMAINS - 1))

    def starvation(self) -> np.ndarray:
        """int64 (n,): m of every object of the map; zeros if none was reported or the
        counts do not match the map row for row (every receiver reads the same zeros)."""
        n = len(self.objects.object_id)
        m = np.asarray(self.unscheduled).reshape(-1)
        if len(m) != n or not np.issubdtype(m.dtype, np.integer):
            return np.zeros(n, dtype=np.int64)
        return np.maximum(m.astype(np.int64), 0)


@message(8, version=2)
class CtrlBundle:
    """The control phase's outcome for all receivers at once: the raw ``ControlMsg`` of
    every sender, and which receiver heard which. One radio broadcast is heard by many,
    so the proxy publishes one bundle per interval rather than a copy of the same
    messages per receiver; a receiver takes its row (``heard_by``). Its arrival closes
    the control phase. A sender's slot normally holds one message; any other frame
    that came on its key follows it, heard by the same receivers (the medium judges
    nobody's identity: channel_proxy/proxy.py)."""

    tick: int
    t_sim_s: float
    senders: Annotated[np.ndarray, Array("<i8", (None,))]  # (S,), non-decreasing: the slot (vehicle) each message came in
    receivers: Annotated[np.ndarray, Array("<i8", (None,))]  # (C,), ascending: the interval's live vehicles
    heard: Annotated[np.ndarray, Array("|b1", (None, None))]  # (C, S): receiver c heard message s
    messages: list[bytes]  # (S,) the raw messages (a ControlMsg, or one in a Signed envelope)

    INVARIANTS = (*STAMPED, *vid("senders", "receivers"), nondecreasing("senders"), at_most("senders", MAX_ITEMS))

    def __post_init__(self) -> None:
        _check_mask("heard", self.heard, self.receivers, len(self.senders))
        if len(self.messages) != len(self.senders):
            raise ValueError(f"{len(self.messages)} messages for {len(self.senders)} senders")

    def heard_by(self, vid: int) -> list[bytes] | None:
        """The raw control messages ``vid`` heard; None if it is not a receiver."""
        frames = self.frames_heard_by(vid)
        return None if frames is None else [raw for _, raw in frames]

    def frames_heard_by(self, vid: int) -> list[tuple[int, bytes]] | None:
        """(sender, raw control message) of each message ``vid`` heard; None if it is not a receiver."""
        row = _row_of(self.receivers, vid)
        if row is None:
            return None
        return [(int(self.senders[s]), self.messages[s]) for s in np.flatnonzero(self.heard[row]).tolist()]

    def frames_of(self, sender: int) -> list[bytes]:
        """Every raw control message in ``sender``'s slot, heard by anybody or not."""
        return [self.messages[s] for s in np.flatnonzero(self.senders == sender).tolist()]


def _row_of(receivers: np.ndarray, vid: int) -> int | None:
    row = int(np.searchsorted(receivers, vid))
    return row if row < len(receivers) and receivers[row] == vid else None


def _check_mask(name: str, mask: np.ndarray, receivers: np.ndarray, columns: int) -> None:
    if mask.dtype != np.bool_ or mask.shape != (len(receivers), columns):
        raise ValueError(f"{name} must be bool ({len(receivers)}, {columns}), got {mask.dtype} {mask.shape}")
    if len(receivers) > 1 and not np.all(receivers[1:] > receivers[:-1]):
        raise ValueError("receivers must be ascending")


@record
class Transmission:
    """One object sent in the sender's slot: airtime starts ``start_s`` after the data
    phase opens and lasts ``len(payload) * 8 / B``."""

    object_id: int
    start_s: float
    payload: bytes

    INVARIANTS = (within("object_id", 0, 1 << 53), within("start_s", 0.0, 10.0))


@message(9)
class DataTx:
    """Everything a vehicle transmits on the data channel this interval (possibly nothing)."""

    tick: int
    t_sim_s: float
    vid: int
    transmissions: list[Transmission]

    INVARIANTS = (*STAMPED, *vid("vid"), at_most("transmissions", MAX_ITEMS))


@record
class Reception:
    sender: int
    object_id: int
    rx_time_s: float  # end of airtime, from the start of the data phase
    payload: bytes

    INVARIANTS = (*vid("sender"), within("object_id", 0, 1 << 53), within("rx_time_s", 0.0, 10.0))


@message(10, version=2)
class DataBundle:
    """The data phase's outcome for all receivers at once: every reception, ordered by
    reception time (then sender, object), and which receiver decoded which. Published
    once per interval (``received_by`` gives one receiver's); closes the data phase.
    Receptions of frames beyond a sender's own (channel_proxy/proxy.py) come last."""

    tick: int
    t_sim_s: float
    receivers: Annotated[np.ndarray, Array("<i8", (None,))]  # (C,), ascending: the interval's live vehicles
    decoded: Annotated[np.ndarray, Array("|b1", (None, None))]  # (C, T): receiver c decoded reception t
    receptions: list[Reception]  # (T,) the transmissions somebody decoded

    INVARIANTS = (*STAMPED, *vid("receivers"), at_most("receptions", MAX_ITEMS))

    def __post_init__(self) -> None:
        _check_mask("decoded", self.decoded, self.receivers, len(self.receptions))

    def received_by(self, vid: int) -> list[Reception] | None:
        """What ``vid`` decoded, by reception time; None if it is not a receiver."""
        row = _row_of(self.receivers, vid)
        return None if row is None else [self.receptions[t] for t in np.flatnonzero(self.decoded[row]).tolist()]


@message(11)
class ChannelStats:
    """The medium's statistics for one interval (bytes offered, delivered, lost, ...)."""

    tick: int
    t_sim_s: float
    stats: dict[str, Any]

    INVARIANTS = STAMPED


# ------------------------------------------------------- EMP edge relay (V2I baseline)


@message(20)
class EmpUpload:
    """A vehicle's Voronoi segment of its full scan (the points nearer to it than to any
    other participant), uploaded to the edge relay for the EMP baseline."""

    tick: int
    t_sim_s: float
    vid: int
    pose: Pose
    points_world: Annotated[np.ndarray, Array("<f4", (None, 3))]  # world frame

    INVARIANTS = (*STAMPED, *vid("vid"), at_most("points_world", MAX_POINTS), in_map("points_world"),
                  *finite("points_world"))


@record
class EmpSegment:
    """One uploader's segment as the relay forwarded it; received at ``rx_time_s`` after
    the interval opened."""

    sender: int
    pose: Pose
    rx_time_s: float
    points_world: Annotated[np.ndarray, Array("<f4", (None, 3))]

    INVARIANTS = (*vid("sender"), within("rx_time_s", 0.0, 10.0), at_most("points_world", MAX_POINTS),
                  in_map("points_world"), *finite("points_world"))


@message(21)
class EmpBundle:
    """What the relay forwarded to one receiver this interval (closes its interval), plus
    every uploader's position this interval: next interval's Voronoi sites."""

    tick: int
    t_sim_s: float
    receiver: int
    segments: list[EmpSegment]
    site_vids: Annotated[np.ndarray, Array("<i8", (None,))]  # (m,)
    site_xy: Annotated[np.ndarray, Array("<f8", (None, 2))]  # (m, 2)

    INVARIANTS = (*STAMPED, *vid("receiver", "site_vids"), unique("site_vids"), same_rows("site_xy", "site_vids"),
                  in_map("site_xy"), at_most("segments", MAX_ITEMS))


# ------------------------------------------------------------------ agent -> judge


@message(12)
class AgentReport:
    """What the ego's fused view held this tick, for the judge's collider-visibility
    metrics (the world counts the points that fall on the collider's true footprint)."""

    tick: int
    t_sim_s: float
    vid: int
    fused_xy: Annotated[np.ndarray, Array("<f4", (None, 2))]  # every above-ground point of the fused view, world frame
    received_points: int  # how many of them came from other vehicles
    braking: bool  # the planner is braking for a predicted conflict

    INVARIANTS = (*STAMPED, *vid("vid"), at_most("fused_xy", MAX_POINTS), in_map("fused_xy"),
                  Invariant(("received_points", "fused_xy"), lambda n, xy: None if 0 <= n <= len(xy) else
                            f"{n} of {len(xy)} points"))


# ------------------------------------------------------------ authenticated V2X messages


@record
class Certificate:
    """A vehicle's certificate (IEEE 1609.2's, reduced): the run's authority binds the
    Ed25519 ``public_key`` to vehicle ``vid`` of run ``run_id`` for sim times
    [``valid_from_s``, ``valid_until_s``]; ``signature`` is the authority's over the
    other fields (``protocol.security.certificate_tbs``)."""

    run_id: str
    vid: int
    valid_from_s: float
    valid_until_s: float
    public_key: bytes  # 32 bytes, raw Ed25519
    signature: bytes  # 64 bytes, the authority's

    INVARIANTS = (*vid("vid"), *finite("valid_from_s", "valid_until_s"),
                  Invariant(("valid_until_s", "valid_from_s"), lambda b, a: None if a <= b else "before valid_from_s"),
                  byte_length("public_key", PUBLIC_KEY_BYTES), byte_length("signature", SIGNATURE_BYTES))


@message(14)
class Signed:
    """A vehicle's message and its signature (1609.2's SignedData, reduced): ``body`` is
    the encoded message, ``signature`` the certificate key's Ed25519 signature over a
    context string and ``body``. ``tick`` and ``t_sim_s`` repeat the body's, for the
    recorder; a receiver checks them against the body it verified."""

    tick: int
    t_sim_s: float
    certificate: Certificate
    body: bytes
    signature: bytes  # 64 bytes

    INVARIANTS = (*STAMPED, byte_length("signature", SIGNATURE_BYTES))


@message(16)
class InShm:
    """The payload of ``tick`` on the key this notice's key twins is in shared memory,
    ``nbytes`` long (``protocol.shm``: on one host, scans and bundles skip the hub)."""

    tick: int
    t_sim_s: float
    nbytes: int

    INVARIANTS = (*STAMPED, within("nbytes", 0, 1 << 40))


@message(15)
class Rejected:
    """What a process has rejected as not authentic so far (``protocol.security``), by
    reason and by stream; published by an agent after a tick in which the counts grew."""

    tick: int
    t_sim_s: float
    vid: int
    counts: dict[str, Any]  # {"total": n, "by_reason": {reason: n}, "by_stream": {stream: {reason: n}}}

    INVARIANTS = (*STAMPED, *vid("vid"))
