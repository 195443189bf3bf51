"""An object's point cloud as it leaves on the data channel.

Layout (little-endian): a 64-byte header, then the points relative to the object's
centroid in the sender's sensor frame, in one of two codings the header's version
names: int16 centimetres (version 1, 6 bytes per point; our model's) or three float64
(version 2, 24 bytes per point; the paper's model, its authors' point format).
Rounding to the centimetre bounds the error at 0.5 cm per axis (0.87 cm in 3-D); int16
spans +-327 m, far beyond the LiDAR range. The header carries the sender's pose (T_s)
and mount height so the receiver can apply V_r = T_r^-1 T_s V_s, and the object's
velocity so it can extrapolate a late or lost update (paper 5.1, loss compensation).
``payload_size`` is exactly what the scheduler budgets. ``decode_objects`` decodes
an interval's receptions (~160 per agent at 40 vehicles) into one ``ObjectBatch`` of
arrays, with the same checks and the same values as ``decode_object`` one by one.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np
from numba import njit

from protocol.codec import COORD_BOUND_M, MAX_T_SIM_S, MalformedMessage
from protocol.messages import MAX_SPEED_MPS, Pose

MAGIC = b"ACOB"
VERSION = 1  # int16 centimetres
VERSION_F64 = 2  # float64 metres
_HEADER = struct.Struct("<4sBxHIiffffffffff8x")  # 64 bytes
HEADER_BYTES = _HEADER.size
BYTES_PER_POINT = 6
BYTES_PER_POINT_F64 = 24
VERSION_OF = {BYTES_PER_POINT: VERSION, BYTES_PER_POINT_F64: VERSION_F64}  # by bytes per point
MAX_ERROR_M = 0.005 * np.sqrt(3)
DATA_STREAM = "data bundle item"  # where a receiver counts an object payload it drops or rejects

# What each of the header's floats may be, in its order (``_HEADER``): the codec's bounds
# for the same quantities (``protocol.codec``: a time as STAMPED, a coordinate as
# ``in_map``, a heading ``finite``; a speed as ``protocol.messages``' speeds), the
# centroid and the mount height taken as coordinates; NaN is never within them
_FINITE = float(np.finfo(np.float32).max)
HEADER_BOUNDS = {
    "t_sim_s": (0.0, MAX_T_SIM_S),
    "sender_pose.x_m": (-COORD_BOUND_M, COORD_BOUND_M),
    "sender_pose.y_m": (-COORD_BOUND_M, COORD_BOUND_M),
    "sender_pose.yaw_rad": (-_FINITE, _FINITE),
    "mount_height_m": (-COORD_BOUND_M, COORD_BOUND_M),
    **{f"centroid_sensor[{i}]": (-COORD_BOUND_M, COORD_BOUND_M) for i in range(3)},
    **{f"velocity_xy[{i}]": (-MAX_SPEED_MPS, MAX_SPEED_MPS) for i in range(2)},
}
_LO, _HI = (np.array(bounds, dtype=np.float64) for bounds in zip(*HEADER_BOUNDS.values()))


@dataclass(frozen=True, slots=True)
class ObjectPayload:
    sender: int
    object_id: int
    tick: int
    t_sim_s: float
    sender_pose: Pose
    mount_height_m: float
    centroid_sensor: np.ndarray  # float32 (3,), sender's sensor frame
    velocity_xy: np.ndarray  # float32 (2,), world frame, m/s
    points_sensor: np.ndarray  # float32 (n, 3), sender's sensor frame


def payload_size(n_points, bytes_per_point: int = BYTES_PER_POINT):
    """The payload's length in bytes for ``n_points`` (an int or an int array)."""
    return HEADER_BYTES + bytes_per_point * n_points


def encode_object(obj: ObjectPayload) -> bytes:
    rel_cm = np.rint((obj.points_sensor - obj.centroid_sensor) * 100.0)
    if rel_cm.size and np.abs(rel_cm).max() > 32767:
        raise ValueError("object spans more than 327 m")
    p = obj.sender_pose
    header = _HEADER.pack(MAGIC, VERSION, obj.sender, obj.object_id, obj.tick, obj.t_sim_s, p.x_m, p.y_m, p.yaw_rad,
                          obj.mount_height_m, *map(float, obj.centroid_sensor), *map(float, obj.velocity_xy))
    return header + rel_cm.astype("<i2").tobytes()


def encode_objects(sender: int, tick: int, t_sim_s: float, pose: Pose, mount_height_m: float,
                   object_ids: list[int], centroids: np.ndarray, velocities: np.ndarray, points: np.ndarray,
                   counts: np.ndarray, bytes_per_point: int = BYTES_PER_POINT) -> list[bytes]:
    """``encode_object`` of each object of one sender and tick, its points the next
    ``counts[k]`` rows of ``points`` (float32, sensor frame), with its ``centroids[k]``
    (float32) and ``velocities[k]`` (float32): the same bytes, the points' arithmetic
    done for all objects at once (one numpy call per step, not per step and object).
    ``bytes_per_point=24``: the points as float64 offsets from the centroid (version 2)."""
    starts = np.cumsum(counts) - counts
    if bytes_per_point == BYTES_PER_POINT_F64:
        version = VERSION_F64
        body = (points.astype(np.float64) - np.repeat(centroids, counts, axis=0).astype(np.float64)).astype("<f8")
    elif bytes_per_point == BYTES_PER_POINT:
        version = VERSION
        rel_cm = np.rint((points - np.repeat(centroids, counts, axis=0)) * 100.0)
        offsets = np.abs(rel_cm)
        # every offset within range: one flat max (a max along the rows' three columns
        # took ~180 us for 6000 points); else, or with a NaN somewhere (which would hide
        # another object's), each object's largest offset, NaN if it has one, as np.max gives it
        if rel_cm.size and not offsets.max() <= 32767:
            widest = np.maximum.reduceat(offsets.max(axis=1), starts[counts > 0])
            if (widest > 32767).any():
                raise ValueError("object spans more than 327 m")
        body = rel_cm.astype("<i2")
    else:
        raise ValueError(f"bytes_per_point: {bytes_per_point} is not {BYTES_PER_POINT} or {BYTES_PER_POINT_F64}")
    out = []
    for oid, start, n, c, v in zip(object_ids, starts.tolist(), counts.tolist(), centroids.tolist(),
                                   velocities.tolist()):
        header = _HEADER.pack(MAGIC, version, sender, oid, tick, t_sim_s, pose.x_m, pose.y_m, pose.yaw_rad,
                              mount_height_m, *c, *v)
        out.append(header + body[start:start + n].tobytes())
    return out


def encode_world_objects(sender: int, tick: int, t_sim_s: float, pose: Pose, mount_height_m: float,
                         object_ids: list[int], centroids_world: np.ndarray, velocities: np.ndarray,
                         world: np.ndarray, counts: np.ndarray) -> list[bytes]:
    """``encode_objects`` (int16 centimetres) of objects given in the world: their points
    the next ``counts[k]`` rows of ``world`` (x, y, height above the ground), their
    centroids ``centroids_world[k]`` (float64), taken to the sender's sensor frame as
    ``frames.world_to_sensor`` takes them and rounded to float32 there. The same bytes as
    ``encode_objects`` of those, in one pass over the points (``_world_cm``) instead
    of a dozen numpy passes, and one buffer for every payload: a signed control message
    vouches for every object the vehicle tracks, so it encodes all of them each interval
    (~17 000 points at 40 vehicles). A point whose offset is not finite or beyond int16
    takes ``encode_objects``' own path (its refusal, or its values)."""
    counts = np.ascontiguousarray(counts, dtype=np.int64)
    c, s = np.cos(pose.yaw_rad), np.sin(pose.yaw_rad)  # as world_to_sensor takes them
    cxyz = np.ascontiguousarray(centroids_world, dtype=np.float64).reshape(-1, 3)
    sizes = HEADER_BYTES + BYTES_PER_POINT * counts
    ends = np.cumsum(sizes)
    buf = np.empty(int(ends[-1]) if len(ends) else 0, dtype=np.uint8)
    centroids = np.empty((len(counts), 3), dtype=np.float32)
    if not _world_cm(world, counts, float(c), float(s), pose.x_m, pose.y_m, float(mount_height_m), cxyz, centroids,
                     buf, HEADER_BYTES):
        from vehicle_agent.frames import world_to_sensor

        pts = world_to_sensor(np.asarray(world, dtype=np.float64), pose, mount_height_m).astype(np.float32)
        return encode_objects(sender, tick, t_sim_s, pose, mount_height_m, object_ids, centroids,
                              np.asarray(velocities).astype(np.float32), pts, counts)
    v32 = np.asarray(velocities).astype(np.float32).tolist()
    pack, x, y, yaw = _HEADER.pack_into, pose.x_m, pose.y_m, pose.yaw_rad
    starts = (ends - sizes).tolist()
    for oid, start, cen, vel in zip(object_ids, starts, centroids.tolist(), v32):
        pack(buf, start, MAGIC, VERSION, sender, oid, tick, t_sim_s, x, y, yaw, mount_height_m, *cen, *vel)
    raw = buf.tobytes()
    return [raw[a:b] for a, b in zip(starts, ends.tolist())]


@njit(cache=True)
def _world_cm(world, counts, c, s, x, y, mount, centroids_world, centroids, buf, header_bytes):
    """Of each object k (its points the next ``counts[k]`` rows of ``world``): its
    centroid in the sensor frame into ``centroids[k]`` (float32), and its points'
    offsets from it in int16 centimetres, little-endian, into ``buf`` after a gap of
    ``header_bytes`` for its header, object after object. ``frames.world_to_sensor``
    (float64, the same operations in the same order) rounded to float32, then
    ``encode_objects``' ``rint((points - centroid) * 100)`` in float32. False, and
    ``buf`` partly written, if an offset is not finite or beyond int16."""
    for k in range(counts.shape[0]):
        dx, dy = centroids_world[k, 0] - x, centroids_world[k, 1] - y
        centroids[k, 0] = np.float32(c * dx + s * dy)
        centroids[k, 1] = np.float32(-s * dx + c * dy)
        centroids[k, 2] = np.float32(centroids_world[k, 2] - mount)
    hundred = np.float32(100.0)
    p, o = 0, 0
    for k in range(counts.shape[0]):
        cx, cy, cz = centroids[k, 0], centroids[k, 1], centroids[k, 2]
        o += header_bytes
        for _ in range(counts[k]):
            dx, dy = np.float64(world[p, 0]) - x, np.float64(world[p, 1]) - y
            for axis in range(3):
                if axis == 0:
                    v = np.float32(c * dx + s * dy) - cx
                elif axis == 1:
                    v = np.float32(-s * dx + c * dy) - cy
                else:
                    v = np.float32(np.float64(world[p, 2]) - mount) - cz
                cm = np.rint(v * hundred)
                if not abs(cm) <= 32767.0:
                    return False
                u = np.uint16(np.int16(cm))
                buf[o] = u & 0xFF
                buf[o + 1] = u >> 8
                o += 2
            p += 1
    return True


def header_of(payload: bytes) -> tuple[int, int, int] | None:
    """(sender, object id, tick) from a payload's header; None if it has no valid one
    (``decode_object``'s checks but those of the floats)."""
    if len(payload) < HEADER_BYTES:
        return None
    head = _HEADER.unpack_from(payload)
    per_point = _BYTES_PER_POINT_OF.get(head[1])
    if head[0] != MAGIC or per_point is None or (len(payload) - HEADER_BYTES) % per_point or head[4] < 0:
        return None
    return head[2], head[3], head[4]


def decode_object(payload: bytes) -> ObjectPayload:
    if len(payload) < HEADER_BYTES:
        raise MalformedMessage(f"object payload of {len(payload)} bytes is shorter than its header")
    magic, version, sender, oid, tick, t, x, y, yaw, mount, cx, cy, cz, vx, vy = _HEADER.unpack_from(payload)
    per_point = _BYTES_PER_POINT_OF.get(version)
    if magic != MAGIC or per_point is None:
        raise MalformedMessage(f"not an object payload v{VERSION} or v{VERSION_F64} (magic {magic!r}, "
                               f"version {version})")
    body = len(payload) - HEADER_BYTES
    if body % per_point:
        raise MalformedMessage(f"object payload body of {body} bytes is not whole points")
    if tick < 0:
        raise MalformedMessage(f"ObjectPayload.tick: {tick} is negative")
    for field, v, (lo, hi) in zip(HEADER_BOUNDS, (t, x, y, yaw, mount, cx, cy, cz, vx, vy), HEADER_BOUNDS.values()):
        if not lo <= v <= hi:
            raise MalformedMessage(f"ObjectPayload.{field}: {v!r} is " +
                                   (f"not in [{lo:g}, {hi:g}]" if hi < _FINITE else "not finite"))
    centroid = np.array([cx, cy, cz], dtype=np.float32)
    if version == VERSION_F64:
        rel64 = np.frombuffer(payload, dtype="<f8", offset=HEADER_BYTES).reshape(-1, 3)
        with np.errstate(over="ignore", invalid="ignore"):  # a value beyond float32 becomes inf, as a sender's could
            points = (rel64 + centroid.astype(np.float64)).astype(np.float32)
    else:
        rel = np.frombuffer(payload, dtype="<i2", offset=HEADER_BYTES).reshape(-1, 3)
        points = rel.astype(np.float32) / 100.0 + centroid
    return ObjectPayload(sender, oid, tick, t, Pose(x, y, yaw), mount, centroid, np.array([vx, vy], np.float32), points)


@dataclass(frozen=True, slots=True)
class ObjectBatch:
    """Object payloads as arrays, in the order given: object k's points follow object
    k-1's in ``points_sensor``. The same fields as ``ObjectPayload``, one row each."""

    sender: np.ndarray  # int64 (K,)
    object_id: np.ndarray  # int64 (K,)
    t_sim_s: np.ndarray  # float64 (K,)
    sender_pose: np.ndarray  # float64 (K, 3): x_m, y_m, yaw_rad
    mount_height_m: np.ndarray  # float64 (K,)
    velocity_xy: np.ndarray  # float64 (K, 2)
    points_sensor: np.ndarray  # (N, 3), float32 when decoded
    counts: np.ndarray  # int64 (K,)

    def __len__(self) -> int:
        return len(self.sender)

    def keys(self) -> list[tuple[int, int]]:
        return list(zip(self.sender.tolist(), self.object_id.tolist()))

    @staticmethod
    def of(objs: list[ObjectPayload]) -> ObjectBatch:
        pts = [o.points_sensor for o in objs]
        return ObjectBatch(np.array([o.sender for o in objs], dtype=np.int64),
                           np.array([o.object_id for o in objs], dtype=np.int64),
                           np.array([o.t_sim_s for o in objs], dtype=np.float64),
                           np.array([[o.sender_pose.x_m, o.sender_pose.y_m, o.sender_pose.yaw_rad] for o in objs],
                                    dtype=np.float64).reshape(-1, 3),
                           np.array([o.mount_height_m for o in objs], dtype=np.float64),
                           np.array([o.velocity_xy for o in objs], dtype=np.float64).reshape(-1, 2),
                           np.concatenate(pts) if pts else np.zeros((0, 3), dtype=np.float32),
                           np.array([len(p) for p in pts], dtype=np.int64))


def decode_objects(payloads: list[bytes]) -> tuple[ObjectBatch, list[MalformedMessage]]:
    """Every well-formed payload of ``payloads`` as one batch (in order), and why each
    malformed one was left out (``decode_object``'s refusal); the checks and values of
    ``decode_object``.

    At 40 vehicles an agent decodes ~160 payloads per interval: their headers are
    checked and copied out of the joined bytes in one pass (``_headers``), their floats
    checked in one comparison (``HEADER_BOUNDS``) and read as arrays of their fields,
    their points in a second pass (``_points_of``), not one ``struct`` call or a dozen
    numpy calls per field."""
    lengths = np.fromiter(map(len, payloads), dtype=np.int64, count=len(payloads))
    raw = np.frombuffer(b"".join(payloads), dtype=np.uint8)
    head, body_starts, counts, kept = _headers(raw, lengths, _MAGIC, VERSION, VERSION_F64)
    floats = head.view("<f4")[:, 4:14]  # from t_sim_s on, in HEADER_BOUNDS' order
    within = ((_LO <= floats) & (floats <= _HI)).all(axis=1) & (head.view("<i4")[:, 3] >= 0)  # and the tick
    if not within.all():
        head, body_starts, counts, kept = head[within], body_starts[within], counts[within], kept[within]
    refused = _refusals(payloads, kept) if len(kept) < len(payloads) else []
    # the header's float32 fields from t_sim_s on (_HEADER), one row per field:
    # t, x, y, yaw, mount, centroid (3), velocity (2)
    f32 = head.view("<f4")
    fields = f32[:, 4:14].T.astype(np.float64, order="C")
    wide = head[:, len(MAGIC)] == VERSION_F64
    centroid = np.ascontiguousarray(f32[:, 9:12])
    points = _points_of(raw, body_starts, counts, centroid, _METRES_OF, wide)
    if wide.any():  # float64 bodies (the paper's model): a few numpy calls per payload
        starts = np.cumsum(counts) - counts
        for k in np.flatnonzero(wide).tolist():
            rel = np.frombuffer(raw, dtype="<f8", count=3 * int(counts[k]), offset=int(body_starts[k]))
            with np.errstate(over="ignore", invalid="ignore"):  # beyond float32: inf, as decode_object gives it
                points[starts[k]:starts[k] + counts[k]] = rel.reshape(-1, 3) + centroid[k].astype(np.float64)
    batch = ObjectBatch(head.view("<u2")[:, 3].astype(np.int64), head.view("<u4")[:, 2].astype(np.int64),
                        fields[0], fields[1:4].T, fields[4], fields[8:10].T, points, counts)
    return batch, refused


def _refusals(payloads: list[bytes], kept: np.ndarray) -> list[MalformedMessage]:
    """``decode_object``'s refusal of each of ``payloads`` but those at ``kept``: why
    ``decode_objects`` left them out (only a malformed payload costs this call)."""
    refused = []
    for i in np.setdiff1d(np.arange(len(payloads)), kept).tolist():
        try:
            decode_object(payloads[i])
        except MalformedMessage as err:
            refused.append(err)
    return refused


_MAGIC = np.frombuffer(MAGIC, dtype=np.uint8)
_BYTES_PER_POINT_OF = {VERSION: BYTES_PER_POINT, VERSION_F64: BYTES_PER_POINT_F64}


@njit(cache=True)
def _headers(raw, lengths, magic, version, version_f64):
    """Of the payloads of ``lengths`` bytes joined in ``raw``: the ``HEADER_BYTES``
    header of each well-formed one (``magic``, ``version`` or ``version_f64``, whole
    points of its version's size, as ``decode_object`` checks them), one row each,
    where its points start, how many it has, and which payload it is."""
    head = np.empty((len(lengths), HEADER_BYTES), dtype=np.uint8)
    body_starts = np.empty(len(lengths), dtype=np.int64)
    counts = np.empty(len(lengths), dtype=np.int64)
    index = np.empty(len(lengths), dtype=np.int64)
    k = start = 0
    for i in range(len(lengths)):
        size = lengths[i]
        ok = size >= HEADER_BYTES
        per_point = BYTES_PER_POINT
        if ok:
            for b in range(len(magic)):
                ok = ok and raw[start + b] == magic[b]
            v = raw[start + len(magic)]
            if v == version_f64:
                per_point = BYTES_PER_POINT_F64
            ok = ok and (v == version or v == version_f64) and (size - HEADER_BYTES) % per_point == 0
        if ok:
            head[k] = raw[start:start + HEADER_BYTES]
            body_starts[k] = start + HEADER_BYTES
            counts[k] = (size - HEADER_BYTES) // per_point
            index[k] = i
            k += 1
        start += size
    return head[:k], body_starts[:k], counts[:k], index[:k]


# every int16's metres, by its two bytes as a little-endian uint16: decode_object's
# ``rel.astype(np.float32) / 100.0``, looked up (a float32 division per coordinate was
# most of the decoding kernel's time)
_METRES_OF = np.arange(1 << 16, dtype=np.uint16).view(np.int16).astype(np.float32) / np.float32(100.0)


@njit(cache=True)
def _points_of(raw, body_starts, counts, centroid, metres_of, skip):
    """The points of the payloads whose bodies start at ``body_starts`` in the joined
    bytes ``raw``, one payload after the other: ``decode_object``'s
    ``rel.astype(np.float32) / 100.0 + centroid`` (float32 all through; ``metres_of``:
    ``_METRES_OF``). Replaces joining the bodies into a second buffer and repeating every
    centroid per point. The rows of a payload where ``skip`` (float64 bodies) are left
    for the caller."""
    out = np.empty((counts.sum(), 3), dtype=np.float32)
    q = 0
    for k in range(len(counts)):
        if skip[k]:
            q += counts[k]
            continue
        o = body_starts[k]
        for _ in range(counts[k]):
            for c in range(3):
                out[q, c] = metres_of[np.int64(raw[o]) | (np.int64(raw[o + 1]) << 8)] + centroid[k, c]
                o += 2
            q += 1
    return out


def warm_kernels() -> None:
    """Load this module's kernels with the argument types ``decode_objects`` passes (the
    joined bytes read-only, as ``np.frombuffer`` gives them)."""
    _headers(np.frombuffer(bytes(HEADER_BYTES), dtype=np.uint8), np.array([HEADER_BYTES]), _MAGIC, VERSION,
             VERSION_F64)
    _points_of(np.frombuffer(bytes(6), dtype=np.uint8), np.zeros(1, dtype=np.int64), np.ones(1, dtype=np.int64),
               np.zeros((1, 3), dtype=np.float32), _METRES_OF, np.zeros(1, dtype=np.bool_))


def column_thinned(points: np.ndarray, counts: np.ndarray, column_m: float, ground_cut_m: float) -> np.ndarray:
    """bool (N,): the points an object offers under the paper's model. Of each object's
    points (object k's the ``counts[k]`` rows after object k-1's; world frame, z the
    height above the ground) one point per column of ``column_m`` x ``column_m`` (the
    first in the object's own order), then those of them higher than ``ground_cut_m``:
    its authors thin first and cut the ground after (``docs/models.md``). A point with
    a non-finite coordinate is never kept."""
    n = len(points)
    keep = np.zeros(n, dtype=bool)
    if n == 0:
        return keep
    owner = np.repeat(np.arange(len(counts), dtype=np.int64), counts)
    with np.errstate(invalid="ignore"):
        ix, iy = np.floor(points[:, 0] / column_m), np.floor(points[:, 1] / column_m)
        finite = np.isfinite(ix) & np.isfinite(iy) & np.isfinite(points[:, 2])
    ix = np.where(finite, ix, 0.0).astype(np.int64)
    iy = np.where(finite, iy, 0.0).astype(np.int64)
    order = np.lexsort((iy, ix, owner))  # stable: within a column, the object's own order
    o, a, b = owner[order], ix[order], iy[order]
    first = np.ones(n, dtype=bool)
    first[1:] = (o[1:] != o[:-1]) | (a[1:] != a[:-1]) | (b[1:] != b[:-1])
    keep[order[first]] = True
    with np.errstate(invalid="ignore"):
        keep &= finite & (points[:, 2] > ground_cut_m)
    return keep
