"""Fusing received objects into the agent's own occupancy grid (paper 5.1-5.2).

A received object's points go through V_r = T_r^-1 T_s V_s (here: to the world, the
frame the grid lives in) and are moved along the object's velocity to the current
time. An object that was not received this interval (lost, or not scheduled) is
carried forward from its last reception the same way, for up to ``max_age_s``: the
paper's loss compensation. Received cells that the agent already sees as occupied
are the same object (same world cells); the rest are what sharing added.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit

from vehicle_agent.payload import ObjectBatch, ObjectPayload
from vehicle_agent.perception import ABOVE, GROUND, Grid, exact_inverse

MAX_AGE_S = 1.0
SAME_INTERVAL_S = 1e-3  # an age below this is this interval's: the header's float32 time is off by ~1e-6 s
SELF_SHARE = 0.3  # a received object with this share of its points on our own body is ourselves
MERGED_SHARE = 0.05  # ... with this share, it merged us with something else: its velocity is ours
BODY_MARGIN_M = 0.5  # a point this close to our body's box is on it

ObjectKey = tuple[int, int]  # (sender vid, object id)


@dataclass(frozen=True, slots=True)
class SharedObject:
    key: ObjectKey
    points_world: np.ndarray  # float64 (n, 3), placed at the current time
    velocity_xy: np.ndarray  # float64 (2,), world frame
    age_s: float  # now minus the capture time
    fresh: bool  # received this interval (False: carried forward)


@dataclass(frozen=True, slots=True)
class SharedBatch:
    """Received objects as one stack of points, object after object: the per-object
    work of fusion is done in whole-array passes, not one small numpy call per object
    (at 40 vehicles an agent holds ~30 objects of a few hundred points)."""

    sender: np.ndarray  # int64 (K,): the keys (sender, object id), as two arrays
    object_id: np.ndarray  # int64 (K,)
    points: np.ndarray  # float64 (N, 3), placed at the current time
    counts: np.ndarray  # int64 (K,): object k's points follow object k-1's
    velocity: np.ndarray  # float64 (K, 2), world frame
    age_s: np.ndarray  # float64 (K,)
    fresh: np.ndarray  # bool (K,)

    def __len__(self) -> int:
        return len(self.counts)

    @property
    def keys(self) -> list[ObjectKey]:
        """(sender, object id) of each object: built on demand, as only tests and
        ``FusedGrid.same_as_own`` read them (a Python tuple per object every tick)."""
        return list(zip(self.sender.tolist(), self.object_id.tolist()))

    @property
    def starts(self) -> np.ndarray:
        return np.cumsum(self.counts) - self.counts

    @property
    def owner(self) -> np.ndarray:
        """(N,) the object of each point."""
        return np.repeat(np.arange(len(self)), self.counts)

    @staticmethod
    def of(objects: list[SharedObject]) -> SharedBatch:
        pts = [o.points_world for o in objects]
        return SharedBatch(np.array([o.key[0] for o in objects], dtype=np.int64),
                           np.array([o.key[1] for o in objects], dtype=np.int64),
                           np.concatenate(pts) if pts else np.zeros((0, 3)),
                           np.array([len(p) for p in pts], dtype=np.int64),
                           np.array([o.velocity_xy for o in objects], dtype=np.float64).reshape(-1, 2),
                           np.array([o.age_s for o in objects], dtype=np.float64),
                           np.array([o.fresh for o in objects], dtype=bool))

    def objects(self) -> list[SharedObject]:
        """One SharedObject per object, its points a view into the stack."""
        ends = np.cumsum(self.counts).tolist()
        keys = self.keys
        out, start = [], 0
        for k, end in enumerate(ends):
            out.append(SharedObject(keys[k], self.points[start:end], self.velocity[k], float(self.age_s[k]),
                                    bool(self.fresh[k])))
            start = end
        return out

    def keep(self, objects: np.ndarray, points: np.ndarray | None = None) -> SharedBatch:
        """The objects where ``objects`` (K,) is set, with their points where ``points``
        (N,) is set (all if None)."""
        if objects.all() and (points is None or points.all()):
            return self
        kept_points, counts = _compact(self.points, self.counts, objects,
                                       np.ones(0, dtype=np.bool_) if points is None else points)
        return SharedBatch(self.sender[objects], self.object_id[objects], kept_points, counts[objects],
                           self.velocity[objects], self.age_s[objects], self.fresh[objects])


@dataclass
class ReceivedStore:
    """The last reception of every shared object, taken to the world, for extrapolation.

    Held as arrays, ascending by key (sender, object id): at 40 vehicles an agent decodes
    ~160 receptions and holds ~300 objects per interval, and a Python step per object
    was most of fusion's cost. The objects' world points lie in ``pool``, object k's at
    rows ``starts[k]:starts[k] + counts[k]``: a reception is placed once, after the
    rows written so far, and the held rows are compacted only when the pool is full
    (restacking all ~30 000 points in key order at every reception and again at every
    expiry was a third of fusion's time). ``bounds`` lets ``shared_now`` pass over the
    objects far from our body without testing their points."""

    max_age_s: float = MAX_AGE_S
    key: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # _key(sender, object id)
    t_sim_s: np.ndarray = field(default_factory=lambda: np.zeros(0))  # capture time
    velocity_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # float64
    counts: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    bounds: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))  # each object's min x, max x, min y, max y
    starts: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # rows in pool
    pool: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # float64, world, at capture time
    used: int = 0  # rows of pool written since it was last compacted

    def __len__(self) -> int:
        return len(self.key)

    @property
    def sender(self) -> np.ndarray:
        return self.key >> 32

    @property
    def object_id(self) -> np.ndarray:
        return self.key & _ID_MASK

    @property
    def points_world(self) -> np.ndarray:
        """(N, 3) every object's points, object after object."""
        return _gather(self.pool, self.starts, self.counts, int(self.counts.sum()))

    def add(self, obj: ObjectPayload) -> None:
        self.add_many([obj])

    def add_many(self, objs: list[ObjectPayload]) -> None:
        self.add_batch(ObjectBatch.of(objs))

    def add_batch(self, batch: ObjectBatch) -> None:
        """Keep each object's newest reception: of the batch's receptions of an object the
        last with the latest capture time, if not older than the one held; taken to the
        world (``sensor_to_world``, all of them in one pass)."""
        if not len(batch):
            return
        for ids in (batch.sender, batch.object_id):
            if ids.min() < 0 or ids.max() >= 1 << 32:
                raise ValueError("sender and object ids must lie in [0, 2**32)")
        key = _key(batch.sender, batch.object_id)
        win = _newest(self.key, self.t_sim_s, key, batch.t_sim_s)  # ascending by key
        if not len(win):
            return
        counts = batch.counts[win]
        need = int(counts.sum())
        order = _merge_rows(self.key, key[win])  # rows of [held, won], ascending by key
        starts = self.starts
        if self.used + need > len(self.pool):
            stay = order[order < len(self)]  # the held rows not replaced
            live = int(self.counts[stay].sum())
            self.pool = _gather(self.pool, starts[stay], self.counts[stay], max(POOL_GROWTH * (live + need), 1024))
            starts = np.zeros(len(self), dtype=np.int64)
            starts[stay] = _starts(self.counts[stay])
            self.used = live
        pose = batch.sender_pose[win]
        bounds = _place(self.pool, self.used, batch.points_sensor, _starts(batch.counts)[win], counts,
                        np.ascontiguousarray(pose), np.cos(pose[:, 2]), np.sin(pose[:, 2]),
                        batch.mount_height_m[win].astype(batch.points_sensor.dtype))
        self.bounds = np.concatenate([self.bounds, bounds])[order]
        self.starts = np.concatenate([starts, self.used + _starts(counts)])[order]
        self.used += need
        self.key = np.concatenate([self.key, key[win]])[order]
        self.t_sim_s = np.concatenate([self.t_sim_s, batch.t_sim_s[win]])[order]
        self.velocity_xy = np.concatenate([self.velocity_xy, batch.velocity_xy[win]])[order]
        self.counts = np.concatenate([self.counts, counts])[order]

    def expire(self, t_now_s: float) -> np.ndarray:
        """Forget the objects older than ``max_age_s`` at ``t_now_s``; the age of each
        object held."""
        age = t_now_s - self.t_sim_s
        # this interval's receptions stay whatever the float32 capture time's rounding says
        # (a held time of 0 keeps exactly them: the paper's model, protocol.model)
        alive = ~(age > self.max_age_s) | (age < SAME_INTERVAL_S)
        if not alive.all():  # their points stay in the pool until it is compacted
            self.key, self.t_sim_s, self.velocity_xy = self.key[alive], self.t_sim_s[alive], self.velocity_xy[alive]
            self.counts, self.starts, self.bounds = self.counts[alive], self.starts[alive], self.bounds[alive]
            age = age[alive]
        return age

    def current(self, t_now_s: float, fresh_keys: set[ObjectKey] = frozenset()) -> SharedBatch:
        """Every object not older than ``max_age_s``, placed at ``t_now_s`` along its
        velocity; older ones are forgotten."""
        age = self.expire(t_now_s)
        velocity = self.velocity_xy.copy()
        points = _moved(self.points_world, self.counts, velocity * age[:, None], 1.0)
        sender, object_id = self.sender, self.object_id
        fresh = [k in fresh_keys for k in zip(sender.tolist(), object_id.tolist())]
        return SharedBatch(sender, object_id, points, self.counts.copy(), velocity, age, np.array(fresh, dtype=bool))


POOL_GROWTH = 3  # a compacted pool holds this many times the live rows: compacted every few intervals
_ID_MASK = (1 << 32) - 1


def _key(sender: np.ndarray, object_id: np.ndarray) -> np.ndarray:
    """One sortable int64 per (sender, object id): vids and object ids fit in 32 bits each
    (the payload carries them as uint16 and uint32)."""
    return (sender.astype(np.int64) << 32) | object_id.astype(np.int64)


def _member(held: np.ndarray, keys: np.ndarray) -> np.ndarray:
    """``np.isin(held, keys)`` for ``held`` ascending (the store's keys), by binary search."""
    out = np.zeros(len(held), dtype=bool)
    if len(held) and len(keys):
        at = np.minimum(np.searchsorted(held, keys), len(held) - 1)
        out[at[held[at] == keys]] = True
    return out


def _starts(counts: np.ndarray) -> np.ndarray:
    return np.cumsum(counts) - counts


@njit(cache=True)
def _gather(points, starts, counts, rows):
    """The rows ``starts[k]:starts[k] + counts[k]`` of ``points``, segment after segment,
    at the head of a new array of ``rows`` rows (at least ``counts.sum()``)."""
    out = np.empty((rows, points.shape[1]), dtype=points.dtype)
    q = 0
    for k in range(len(counts)):
        for i in range(starts[k], starts[k] + counts[k]):
            for c in range(points.shape[1]):  # element by element: a row slice copy took 3x as long
                out[q, c] = points[i, c]
            q += 1
    return out


@njit(cache=True)
def _newest(held_key, held_t, key, t):
    """The rows of a batch of receptions (``key``, capture time ``t``) to keep, ascending
    by key: per key the last reception with the latest time (a NaN time is the latest, as
    ``np.lexsort`` orders it), if its time is not older than the held one's (``held_key``
    ascending). Replaces a ``np.lexsort`` of the batch and a binary search of the held
    keys, a dozen numpy calls per interval."""
    order = np.argsort(key, kind="mergesort")  # stable: a key's receptions in batch order
    out = np.empty(len(key), dtype=np.int64)
    n = h = i = 0
    while i < len(order):
        best, j = order[i], i + 1
        while j < len(order) and key[order[j]] == key[best]:
            r = order[j]
            if np.isnan(t[r]) or (not np.isnan(t[best]) and t[r] >= t[best]):
                best = r
            j += 1
        while h < len(held_key) and held_key[h] < key[best]:
            h += 1
        if h == len(held_key) or held_key[h] != key[best] or t[best] >= held_t[h]:
            out[n] = best
            n += 1
        i = j
    return out[:n]


@njit(cache=True)
def _merge_rows(held, won):
    """Merge two ascending key arrays (``won`` replaces ``held``'s equal keys): each row
    of the result as a row of ``held`` then ``won`` stacked. Replaces a ``np.lexsort``
    of the stacked keys."""
    out = np.empty(len(held) + len(won), dtype=np.int64)
    n = i = j = 0
    while i < len(held) or j < len(won):
        if j == len(won) or (i < len(held) and held[i] < won[j]):
            out[n] = i
            i += 1
        else:
            if i < len(held) and held[i] == won[j]:
                i += 1  # replaced
            out[n] = len(held) + j
            j += 1
        n += 1
    return out[:n]


@njit(cache=True)
def _place(out, at, points, starts, counts, pose, cos_yaw, sin_yaw, mount):
    """``placed_in_world`` of the segments ``starts[k]:starts[k] + counts[k]`` of the
    sensor-frame ``points``, each with its sender's pose (x, y, yaw), cos and sin of its
    yaw and mount height (in the points' dtype), one after the other into the rows of
    ``out`` from ``at``: the same sums. Returns each segment's bounds in x and y (min x,
    max x, min y, max y; NaNs left out, an empty or all-NaN segment inf, -inf)."""
    bounds = np.empty((len(counts), 4))
    q = at
    for k in range(len(counts)):
        x, y, c, s, h = pose[k, 0], pose[k, 1], cos_yaw[k], sin_yaw[k], mount[k]
        x_lo, x_hi, y_lo, y_hi = np.inf, -np.inf, np.inf, -np.inf
        for i in range(starts[k], starts[k] + counts[k]):
            wx = x + c * points[i, 0] - s * points[i, 1]
            wy = y + s * points[i, 0] + c * points[i, 1]
            out[q, 0], out[q, 1], out[q, 2] = wx, wy, points[i, 2] + h
            if wx < x_lo:  # a NaN compares false: left out
                x_lo = wx
            if wx > x_hi:
                x_hi = wx
            if wy < y_lo:
                y_lo = wy
            if wy > y_hi:
                y_hi = wy
            q += 1
        bounds[k, 0], bounds[k, 1], bounds[k, 2], bounds[k, 3] = x_lo, x_hi, y_lo, y_hi
    return bounds


@njit(cache=True)
def _moved(points, counts, shift, sign):
    """Each object's points with x, y plus ``sign`` times its ``shift`` (K, 2); the same
    sums as adding ``np.repeat(sign * shift, counts)`` (``sign`` is +1 or -1)."""
    out = np.empty_like(points)
    p = 0
    for k in range(len(counts)):
        dx, dy = shift[k, 0], shift[k, 1]
        for _ in range(counts[k]):
            if sign > 0:
                out[p, 0], out[p, 1] = points[p, 0] + dx, points[p, 1] + dy
            else:
                out[p, 0], out[p, 1] = points[p, 0] - dx, points[p, 1] - dy
            out[p, 2] = points[p, 2]
            p += 1
    return out


@njit(cache=True)
def _compact(points, counts, objects, keep_point):
    """The points of the objects set in ``objects`` that are set in ``keep_point``
    (every one if it is empty), and the kept count of every object."""
    out = np.empty_like(points)
    kept = np.zeros(len(counts), dtype=np.int64)
    all_points = len(keep_point) == 0
    q = start = 0
    for k in range(len(counts)):
        end = start + counts[k]
        if objects[k]:
            q0 = q
            for p in range(start, end):
                if all_points or keep_point[p]:
                    for c in range(points.shape[1]):
                        out[q, c] = points[p, c]
                    q += 1
            kept[k] = q - q0
        start = end
    return out[:q], kept


@dataclass(frozen=True, slots=True)
class FusedGrid:
    grid: Grid  # the agent's own grid
    state: np.ndarray  # uint8 (n, n): own state with received objects' cells set ABOVE
    received: np.ndarray  # bool (n, n): cells occupied only because of received objects
    shared: SharedBatch  # the received objects fused
    on_own: np.ndarray  # bool (K,): each of them overlaps something the agent sees itself

    @property
    def same_as_own(self) -> dict[ObjectKey, bool]:
        """``on_own`` by key (built on demand: the agent does not read it)."""
        return dict(zip(self.shared.keys, self.on_own.tolist()))


def on_body(xy: np.ndarray, pose, length_m: float, width_m: float, margin_m: float = BODY_MARGIN_M) -> np.ndarray:
    """Which world points fall on a vehicle's body at ``pose`` (plus a margin)."""
    c, s = np.cos(pose.yaw_rad), np.sin(pose.yaw_rad)
    dx, dy = xy[:, 0] - pose.x_m, xy[:, 1] - pose.y_m
    return (np.abs(c * dx + s * dy) <= length_m / 2 + margin_m) & (np.abs(-s * dx + c * dy) <= width_m / 2 + margin_m)


def not_me(shared: SharedBatch, poses: list, length_m: float, width_m: float) -> SharedBatch:
    """Drop what other vehicles saw of this vehicle itself: the objects that are mostly
    our body, and our body's points from the rest (an object may have merged us with a
    neighbour). ``poses`` are our current and recent poses: an older reception of us
    sits where we were a moment ago. Each point is tested where it is placed now and
    where it was captured (placed minus the sender's velocity times its age): a sender
    that tracked us extrapolates us along the velocity we had, so once we brake our
    ghost runs on ahead of us, and we braked for it (measured: overtaking, autocast,
    the ego stopped beside the truck for received points of itself 4 m ahead). Objects
    without points are dropped too."""
    pts = shared.points
    counts = shared.counts
    mine = np.zeros(len(pts), dtype=bool)
    hits = np.zeros(len(shared))
    shift = shared.velocity * shared.age_s[:, None]
    if poses and len(pts):
        yaw = np.array([p.yaw_rad for p in poses])
        px, py = np.array([p.x_m for p in poses]), np.array([p.y_m for p in poses])
        reach = np.hypot(length_m / 2 + BODY_MARGIN_M, width_m / 2 + BODY_MARGIN_M)
        box = np.array([px.min() - reach, px.max() + reach, py.min() - reach, py.max() + reach])
        _mark_mine(pts, counts, shift, px, py, np.cos(yaw), np.sin(yaw), length_m / 2 + BODY_MARGIN_M,
                   width_m / 2 + BODY_MARGIN_M, box, mine, hits)
    share = hits / np.maximum(counts, 1)
    merged = (share >= MERGED_SHARE) & (share < SELF_SHARE)
    if merged.any():
        # merged with us: its motion is ours, the rest of it is taken as standing where it
        # was captured (measured: a parked car's view merged the truck with the passing
        # ego; the truck, "moving" at the ego's speed, blocked the ego's way back)
        points = _moved(pts, counts, np.where(merged[:, None], shift, 0.0), -1.0)
        shared = SharedBatch(shared.sender, shared.object_id, points, counts,
                             np.where(merged[:, None], 0.0, shared.velocity), shared.age_s, shared.fresh)
    return shared.keep((counts > 0) & (share < SELF_SHARE), ~mine)


@njit(cache=True)
def _on_a_body(x, y, px, py, cos_yaw, sin_yaw, half_length, half_width, x_lo, x_hi, y_lo, y_hi):
    """(x, y) inside the bodies' bounding box and on one of the bodies: the per-point
    test of ``_mark_mine`` and ``_mark_mine_placed``. The box comes as four floats: as
    an array, indexing it in this called function made the two kernels 15x slower (1.7
    ms for 35 000 points, the agent's largest kernel at 40 vehicles, against 0.11)."""
    if not (x >= x_lo and x <= x_hi and y >= y_lo and y <= y_hi):
        return False
    for i in range(len(px)):
        dx, dy = x - px[i], y - py[i]
        c, s = cos_yaw[i], sin_yaw[i]
        if abs(c * dx + s * dy) <= half_length and abs(-s * dx + c * dy) <= half_width:
            return True
    return False


@njit(cache=True)
def _clear(lo_x, hi_x, lo_y, hi_y, x_lo, x_hi, y_lo, y_hi):
    """The box [lo_x, hi_x] x [lo_y, hi_y] lies wholly on one side of [x_lo, x_hi] x
    [y_lo, y_hi] (False where a bound is NaN)."""
    return hi_x < x_lo or lo_x > x_hi or hi_y < y_lo or lo_y > y_hi


@njit(cache=True)
def _mark_mine(pts, counts, shift, px, py, cos_yaw, sin_yaw, half_length, half_width, box, mine, hits):
    """``_on_bodies`` of every point where it is placed and where it was captured (its
    object's ``shift`` back), in one pass: sets ``mine`` and counts each object's
    ``hits``. The same tests in the same arithmetic as ``on_body``."""
    p = 0
    x_lo, x_hi, y_lo, y_hi = box[0], box[1], box[2], box[3]
    for k in range(len(counts)):
        for _ in range(counts[k]):
            x, y = pts[p, 0], pts[p, 1]
            x0, y0 = x - shift[k, 0], y - shift[k, 1]  # where it was captured
            if _on_a_body(x, y, px, py, cos_yaw, sin_yaw, half_length, half_width, x_lo, x_hi, y_lo, y_hi) or \
                    _on_a_body(x0, y0, px, py, cos_yaw, sin_yaw, half_length, half_width, x_lo, x_hi, y_lo, y_hi):
                mine[p] = True
                hits[k] += 1.0
            p += 1


def not_contradicted(shared: SharedBatch, grid: Grid, free_share: float = 0.5) -> SharedBatch:
    """Drop carried-forward (not fresh) objects where our own LiDAR now sees bare ground:
    we can see that they are no longer there."""
    stale = ~shared.fresh & (shared.counts > 0)
    if not stale.any():
        return shared
    n_inside, n_ground = _on_ground(shared.points, shared.counts, stale, grid.spec.cell_m, grid.i0, grid.j0,
                                   grid.state, GROUND)
    gone = stale & (n_inside > 0) & (n_ground >= free_share * n_inside)
    return shared.keep(~gone)


def shared_now(store: ReceivedStore, t_now_s: float, fresh: tuple[np.ndarray, np.ndarray], poses: list,
               length_m: float, width_m: float, grid: Grid, free_share: float = 0.5) -> SharedBatch:
    return _shared_now_of(store, t_now_s, fresh, poses, length_m, width_m, grid, free_share, False)[0]


def fused_now(store: ReceivedStore, t_now_s: float, fresh: tuple[np.ndarray, np.ndarray], poses: list,
              length_m: float, width_m: float, grid: Grid, free_share: float = 0.5) -> FusedGrid:
    """``fuse(grid, shared_now(...))``: the same grid, the same batch, its points fused
    as ``_shared_now`` writes them."""
    return _shared_now_of(store, t_now_s, fresh, poses, length_m, width_m, grid, free_share, True)[1]


def _shared_now_of(store: ReceivedStore, t_now_s: float, fresh: tuple[np.ndarray, np.ndarray], poses: list,
                   length_m: float, width_m: float, grid: Grid, free_share: float,
                   mark: bool) -> tuple[SharedBatch, FusedGrid | None]:
    """``not_contradicted(not_me(store.current(t_now_s, fresh_keys), poses, length_m,
    width_m), grid, free_share)`` in one pass over the held objects (``_shared_now``):
    the same objects, the same points, the same values. ``fresh``: the (sender, object
    id) arrays of this interval's receptions.

    Placing every held object (~30 000 points at 40 vehicles), dropping our body's
    points and compacting, then dropping what our LiDAR contradicts and compacting again
    copied the stack three times and paid a Python step per object to rebuild its keys."""
    age = store.expire(t_now_s)
    velocity = store.velocity_xy
    shift = velocity * age[:, None]  # the same product as current's and not_me's
    half_length, half_width = length_m / 2 + BODY_MARGIN_M, width_m / 2 + BODY_MARGIN_M
    if poses:
        yaw = np.array([p.yaw_rad for p in poses])
        px, py = np.array([p.x_m for p in poses]), np.array([p.y_m for p in poses])
        reach = np.hypot(half_length, half_width)
        box = (px.min() - reach, px.max() + reach, py.min() - reach, py.max() + reach)
    else:  # an empty box: nothing is on our body
        yaw = px = py = np.zeros(0)
        box = (np.inf, -np.inf, np.inf, -np.inf)
    is_fresh = _member(store.key, _key(*fresh))
    state = grid.state.copy() if mark else np.zeros((0, 0), dtype=grid.state.dtype)
    received = np.zeros_like(grid.drivable) if mark else np.zeros((0, 0), dtype=np.bool_)
    on_own = np.zeros(len(store.counts), dtype=np.bool_)
    points, kept, kept_counts, merged = _shared_now(
        store.pool, store.starts, store.counts, store.bounds, shift, is_fresh, px, py, np.cos(yaw), np.sin(yaw),
        half_length, half_width, *box, grid.spec.cell_m, exact_inverse(grid.spec.cell_m), grid.i0, grid.j0,
        grid.state, GROUND, free_share, MERGED_SHARE, SELF_SHARE, mark, grid.spec.ground_clear_m, state, received,
        on_own)
    if merged.any():
        velocity = np.where(merged[:, None], 0.0, velocity)
    key = store.key[kept]
    shared = SharedBatch(key >> 32, key & _ID_MASK, points, kept_counts[kept], velocity[kept], age[kept],
                         is_fresh[kept])
    return shared, FusedGrid(grid, state, received, shared, on_own[:len(shared)]) if mark else None


@njit(cache=True)
def _shared_now(pool, starts, counts, bounds, shift, fresh, px, py, cos_yaw, sin_yaw, half_length, half_width,
                x_lo, x_hi, y_lo, y_hi, cell_m, inv, i0, j0, state, ground, free_share, merged_share, self_share,
                mark, clear_m, fused, received, on_own):
    """Object by object, the held points (``starts``/``counts`` rows of ``pool``)
    placed at their object's ``shift``: ``not_me``'s test of each point where it is
    placed and where it was captured against our bodies (``_on_a_body``, the box as four
    floats), the object's share of points on us (merged: moved back by its shift, kept:
    a small share); for a kept stale (not ``fresh``) object, ``not_contradicted``'s count
    of its other points in the grid and on ``ground`` (``inv``: ``exact_inverse(cell_m)``);
    the kept objects' other points, placed, one object after the other. The same sums
    and tests as ``_moved``, ``_mark_mine``, ``_compact`` and ``_on_ground`` in turn.

    An object whose ``bounds`` (min x, max x, min y, max y of its held points), placed
    and taken back the same way, lie clear of the box has no point on us and is not
    tested point by point: rounding is monotonic, so no point lies beyond its bounds
    after the same sums (NaN bounds are never clear). Most objects are far from us.

    Returns the points, which objects are kept, each object's points not on us, and
    which objects merged us with something. Replaces three passes over the whole stack
    (marking, counting, writing): an object's points are read three times while they
    are in cache.

    With ``mark``, each kept point is also fused into the grid as it is written
    (``_fuse_points``' step, one kept object after the other, into ``fused``,
    ``received`` and ``on_own``, the kept object's row; ``clear_m``: the grid's
    ``ground_clear_m``): the points are not read a second time."""
    n = state.shape[0]
    out = np.empty((counts.sum(), 3))
    kept = np.zeros(len(counts), dtype=np.bool_)
    kept_counts = np.zeros(len(counts), dtype=np.int64)
    merged = np.zeros(len(counts), dtype=np.bool_)
    mine = np.zeros(counts.max() if len(counts) else 0, dtype=np.bool_)  # the object's points on our body
    q = n_kept = 0
    for k in range(len(counts)):
        start, count = starts[k], counts[k]
        sx, sy = shift[k, 0], shift[k, 1]
        hits = 0
        lo_x, hi_x, lo_y, hi_y = bounds[k, 0] + sx, bounds[k, 1] + sx, bounds[k, 2] + sy, bounds[k, 3] + sy
        tested = not (_clear(lo_x, hi_x, lo_y, hi_y, x_lo, x_hi, y_lo, y_hi) and
                      _clear(lo_x - sx, hi_x - sx, lo_y - sy, hi_y - sy, x_lo, x_hi, y_lo, y_hi))
        for i in range(count if tested else 0):
            x, y = pool[start + i, 0] + sx, pool[start + i, 1] + sy
            x0, y0 = x - sx, y - sy  # where it was captured
            mine[i] = _on_a_body(x, y, px, py, cos_yaw, sin_yaw, half_length, half_width, x_lo, x_hi, y_lo, y_hi) or \
                _on_a_body(x0, y0, px, py, cos_yaw, sin_yaw, half_length, half_width, x_lo, x_hi, y_lo, y_hi)
            hits += mine[i]
        share = np.float64(hits) / max(count, 1)
        back = share >= merged_share and share < self_share
        keep = count > 0 and share < self_share
        if keep and not fresh[k] and count - hits > 0:  # stale: gone where our LiDAR sees bare ground
            inside = on_ground = 0
            for i in range(count):
                if tested and mine[i]:
                    continue
                x, y = _placed_xy(pool, start + i, sx, sy, back)
                if inv > 0.0:
                    fx, fy = np.floor(x * inv), np.floor(y * inv)
                else:
                    fx, fy = np.floor(x / cell_m), np.floor(y / cell_m)
                if not (abs(fx) < 4e18 and abs(fy) < 4e18):  # NaN, inf, out of int64: outside
                    continue
                row, col = np.int64(fy) - j0, np.int64(fx) - i0
                if 0 <= row < n and 0 <= col < n:
                    inside += 1
                    if state[row, col] == ground:
                        on_ground += 1
            keep = not (inside > 0 and on_ground >= free_share * inside)
        if keep:
            last_r = last_c = -1
            for i in range(count):
                if tested and mine[i]:
                    continue
                x, y = _placed_xy(pool, start + i, sx, sy, back)
                z = pool[start + i, 2]
                out[q, 0], out[q, 1], out[q, 2] = x, y, z
                q += 1
                if not (mark and z > clear_m):  # _fuse_points' step, into the kept object's row n_kept
                    continue
                r, c = _cell_of(x, y, i0, j0, cell_m, inv, n)
                if r < 0 or (r == last_r and c == last_c):
                    continue
                last_r, last_c = r, c
                if state[r, c] == ABOVE:
                    on_own[n_kept] = True
                else:
                    received[r, c] = True
                fused[r, c] = ABOVE
            n_kept += 1
        kept[k], kept_counts[k], merged[k] = keep, count - hits, back
    return out[:q], kept, kept_counts, merged


@njit(cache=True)
def _cell_of(x, y, i0, j0, cell_m, inv, n):
    """The cell (row, col) of the n x n grid a point at (x, y) falls in, or (-1, -1)
    outside it (NaN included); ``inv``: ``exact_inverse(cell_m)``, used when positive."""
    if inv > 0.0:
        col, row = np.floor(x * inv) - i0, np.floor(y * inv) - j0
    else:
        col, row = np.floor(x / cell_m) - i0, np.floor(y / cell_m) - j0
    if not (0 <= row < n and 0 <= col < n):  # also refuses NaN
        return -1, -1
    return int(row), int(col)


@njit(cache=True)
def _placed_xy(pool, p, sx, sy, back):
    """Where ``_shared_now`` places pool point ``p``: shifted by (sx, sy), or where it
    was captured when its object is merged back (the shift added, then taken off)."""
    x, y = pool[p, 0] + sx, pool[p, 1] + sy
    if back:
        x, y = x - sx, y - sy
    return x, y


@njit(cache=True)
def _on_ground(points, counts, objects, cell_m, i0, j0, state, ground):
    """Per object set in ``objects``: how many of its points fall in the grid, and how
    many of those on a ``ground`` cell (``Grid.cell_of``'s cells)."""
    n = state.shape[0]
    n_inside = np.zeros(len(counts), dtype=np.int64)
    n_ground = np.zeros(len(counts), dtype=np.int64)
    p = 0
    for k in range(len(counts)):
        if not objects[k]:
            p += counts[k]
            continue
        for _ in range(counts[k]):
            fx, fy = np.floor(points[p, 0] / cell_m), np.floor(points[p, 1] / cell_m)
            p += 1
            if not (abs(fx) < 4e18 and abs(fy) < 4e18):  # NaN, inf, out of int64: outside
                continue
            row, col = np.int64(fy) - j0, np.int64(fx) - i0
            if 0 <= row < n and 0 <= col < n:
                n_inside[k] += 1
                if state[row, col] == ground:
                    n_ground[k] += 1
    return n_inside, n_ground


def fuse(grid: Grid, shared: SharedBatch) -> FusedGrid:
    """Merge placed shared objects into the grid (points outside the grid are ignored):
    the tests' reference for ``fused_now``, which the agents fuse with."""
    state = grid.state.copy()
    received = np.zeros_like(grid.drivable)
    on_own = np.zeros(len(shared), dtype=np.bool_)
    if not len(shared):
        return FusedGrid(grid, state, received, shared, on_own)
    _fuse_points(shared.points, shared.counts, grid.i0, grid.j0, grid.spec.cell_m, exact_inverse(grid.spec.cell_m),
                 grid.spec.ground_clear_m, grid.state, state, received, on_own)
    return FusedGrid(grid, state, received, shared, on_own)


@njit  # fuse()'s, a reference for the tests (agents fuse with fused_now): not cached
def _fuse_points(pts, counts, i0, j0, cell_m, inv, clear_m, own, state, received, on_own):
    """One pass over the stacked points (``counts[o]`` of object o in turn): a point
    above the ground in a grid cell sets it ABOVE in ``state``; it is ``received`` when
    our own grid did not have it ABOVE, and its object is ``on_own`` when it did.
    ``inv``: ``exact_inverse(cell_m)``. A point in the cell its object's previous point
    set changes nothing and is passed over (an object's consecutive points mostly share
    a cell: a quarter of the kernel's time)."""
    n = own.shape[0]
    p = 0
    for o in range(len(counts)):
        last_r = last_c = -1
        for _ in range(counts[o]):
            x, y, z = pts[p, 0], pts[p, 1], pts[p, 2]
            p += 1
            if not z > clear_m:
                continue
            r, c = _cell_of(x, y, i0, j0, cell_m, inv, n)
            if r < 0 or (r == last_r and c == last_c):
                continue
            last_r, last_c = r, c
            if own[r, c] == ABOVE:
                on_own[o] = True
            else:
                received[r, c] = True
            state[r, c] = ABOVE


def warm_kernels() -> None:
    """Load every kernel of this module with the argument types fusion passes (the
    synthetic warm-up interval takes only some of the paths)."""
    pts, pts32 = np.zeros((2, 3)), np.zeros((2, 3), dtype=np.float32)
    counts, flags = np.array([1, 1], dtype=np.int64), np.array([True, False])
    keys, times = np.array([0, 1], dtype=np.int64), np.zeros(2)
    _gather(pts, counts - 1, counts, 2)
    _newest(keys, times, keys, times)
    _merge_rows(keys, keys)
    for p in (pts, pts32):
        _place(np.zeros((2, 3)), 0, p, counts - 1, counts, np.zeros((2, 3)), np.ones(2), np.zeros(2),
               np.zeros(2, dtype=p.dtype))
    _moved(pts, counts, np.zeros((2, 2)), -1.0)
    _compact(pts, counts, flags, flags)
    _compact(pts, counts, flags, np.ones(0, dtype=np.bool_))
    _mark_mine(pts, counts, np.zeros((2, 2)), np.zeros(1), np.zeros(1), np.ones(1), np.zeros(1), 1.0, 1.0,
               np.zeros(4), np.zeros(2, dtype=np.bool_), np.zeros(2))
    _on_ground(pts, counts, flags, 0.5, 0, 0, np.zeros((2, 2), dtype=np.uint8), GROUND)
    x_lo = np.float64(0.0)  # the box's bounds come as numpy floats (from ``np.min``)
    for mark in (False, True):  # shared_now's and fused_now's
        _shared_now(pts, counts - 1, counts, np.zeros((2, 4)), np.zeros((2, 2)), flags, np.zeros(1), np.zeros(1),
                    np.ones(1), np.zeros(1), 1.0, 1.0, x_lo, x_lo, x_lo, x_lo, 0.5, 2.0, 0, 0,
                    np.zeros((2, 2), dtype=np.uint8), GROUND, 0.5, MERGED_SHARE, SELF_SHARE, mark, 0.25,
                    np.zeros((2, 2), dtype=np.uint8), np.zeros((2, 2), dtype=np.bool_), np.zeros(2, dtype=np.bool_))
