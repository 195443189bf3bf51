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

    keys: list[ObjectKey]
    points: np.ndarray  # float64 (N, 3), placed at the current time
    counts: np.ndarray  # int64 (K,): object k's points follow object k-1's
    velocity: np.ndarray  # float64 (K, 2), world frame
    age_s: np.ndarray  # float64 (K,)
    fresh: np.ndarray  # bool (K,)

    def __len__(self) -> int:
        return len(self.keys)

    @property
    def starts(self) -> np.ndarray:
        return np.cumsum(self.counts) - self.counts

    @property
    def owner(self) -> np.ndarray:
        """(N,) the object of each point."""
        return np.repeat(np.arange(len(self.keys)), self.counts)

    @staticmethod
    def of(objects: list[SharedObject]) -> SharedBatch:
        pts = [o.points_world for o in objects]
        return SharedBatch([o.key for o in objects], np.concatenate(pts) if pts else np.zeros((0, 3)),
                           np.array([len(p) for p in pts], dtype=np.int64),
                           np.array([o.velocity_xy for o in objects], dtype=np.float64).reshape(-1, 2),
                           np.array([o.age_s for o in objects], dtype=np.float64),
                           np.array([o.fresh for o in objects], dtype=bool))

    def objects(self) -> list[SharedObject]:
        """One SharedObject per object, its points a view into the stack."""
        ends = np.cumsum(self.counts).tolist()
        out, start = [], 0
        for k, end in enumerate(ends):
            out.append(SharedObject(self.keys[k], self.points[start:end], self.velocity[k], float(self.age_s[k]),
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
        return SharedBatch([k for k, kept in zip(self.keys, objects.tolist()) if kept], kept_points,
                           counts[objects], self.velocity[objects], self.age_s[objects], self.fresh[objects])


@dataclass
class ReceivedStore:
    """The last reception of every shared object, taken to the world, for extrapolation.

    Held as arrays, ascending by key (sender, object id), with the objects' world points
    stacked in that order: at 40 vehicles an agent decodes ~160 receptions and holds
    ~300 objects per interval, and a Python step per object was most of fusion's cost."""

    max_age_s: float = MAX_AGE_S
    sender: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    object_id: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    t_sim_s: np.ndarray = field(default_factory=lambda: np.zeros(0))  # capture time
    velocity_xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # float64
    points_world: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # float64, at capture time
    counts: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def __len__(self) -> int:
        return len(self.sender)

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
        # per key, the batch's last reception with the latest time: the last row of its group
        order = np.lexsort((np.arange(len(batch)), batch.t_sim_s, batch.object_id, batch.sender))
        s, o = batch.sender[order], batch.object_id[order]
        last = np.ones(len(order), dtype=bool)
        last[:-1] = (s[1:] != s[:-1]) | (o[1:] != o[:-1])
        win = order[last]  # ascending by key
        held = self._find(batch.sender[win], batch.object_id[win])
        newer = held < 0
        newer[~newer] = batch.t_sim_s[win][~newer] >= self.t_sim_s[held[~newer]]
        win, held = win[newer], held[newer]
        if not len(win):
            return
        counts = batch.counts[win]
        pose = batch.sender_pose[win]
        world = _placed(batch.points_sensor, _starts(batch.counts)[win], counts, np.ascontiguousarray(pose),
                        np.cos(pose[:, 2]), np.sin(pose[:, 2]),
                        batch.mount_height_m[win].astype(batch.points_sensor.dtype))
        keep = np.ones(len(self), dtype=bool)
        keep[held[held >= 0]] = False  # replaced
        sender = np.concatenate([self.sender[keep], batch.sender[win]])
        object_id = np.concatenate([self.object_id[keep], batch.object_id[win]])
        order = np.lexsort((object_id, sender))
        from_batch = order >= int(keep.sum())
        starts = np.concatenate([_starts(self.counts)[keep], _starts(counts)])[order]
        self.sender, self.object_id = sender[order], object_id[order]
        self.t_sim_s = np.concatenate([self.t_sim_s[keep], batch.t_sim_s[win]])[order]
        self.velocity_xy = np.concatenate([self.velocity_xy[keep], batch.velocity_xy[win]])[order]
        self.counts = np.concatenate([self.counts[keep], counts])[order]
        self.points_world = _gather_two(self.points_world, world, starts, self.counts, from_batch)

    def _find(self, sender: np.ndarray, object_id: np.ndarray) -> np.ndarray:
        """The row of each (sender, object id) held, -1 where none."""
        if not len(self):
            return np.full(len(sender), -1, dtype=np.int64)
        held, want = _key(self.sender, self.object_id), _key(sender, object_id)
        at = np.minimum(np.searchsorted(held, want), len(held) - 1)
        return np.where(held[at] == want, at, -1)

    def _set(self, sender, object_id, t_sim_s, velocity_xy, counts, points) -> None:
        """Hold these rows, sorted by key."""
        order = np.lexsort((object_id, sender))
        self.sender, self.object_id = sender[order], object_id[order]
        self.t_sim_s, self.velocity_xy, self.counts = t_sim_s[order], velocity_xy[order], counts[order]
        self.points_world = _segments(points, _starts(counts)[order], self.counts)

    def expire(self, t_now_s: float) -> np.ndarray:
        """Forget the objects older than ``max_age_s`` at ``t_now_s``; the age of each
        object held."""
        age = t_now_s - self.t_sim_s
        alive = ~(age > self.max_age_s)
        if not alive.all():
            self._set(self.sender[alive], self.object_id[alive], self.t_sim_s[alive], self.velocity_xy[alive],
                      self.counts[alive], _segments(self.points_world, _starts(self.counts)[alive], self.counts[alive]))
            age = age[alive]
        return age

    def current(self, t_now_s: float, fresh_keys: set[ObjectKey] = frozenset()) -> SharedBatch:
        """Every object not older than ``max_age_s``, placed at ``t_now_s`` along its
        velocity; older ones are forgotten."""
        age = self.expire(t_now_s)
        keys = list(zip(self.sender.tolist(), self.object_id.tolist()))
        velocity = self.velocity_xy.copy()
        points = _moved(self.points_world, self.counts, velocity * age[:, None], 1.0)
        return SharedBatch(keys, points, self.counts.copy(), velocity, age,
                           np.array([k in fresh_keys for k in keys], dtype=bool))


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


def _segments(points: np.ndarray, starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """The rows ``starts[k]:starts[k] + counts[k]`` of ``points``, segment after segment."""
    total = int(counts.sum())
    if total == len(points) and np.array_equal(starts, _starts(counts)):
        return points
    return _gather(points, starts, counts, total)


@njit(cache=True)
def _gather(points, starts, counts, total):
    out = np.empty((total, points.shape[1]), dtype=points.dtype)
    q = 0
    for k in range(len(counts)):
        for i in range(starts[k], starts[k] + counts[k]):
            for c in range(points.shape[1]):  # element by element: a row slice copy took 3x as long
                out[q, c] = points[i, c]
            q += 1
    return out


@njit(cache=True)
def _placed(points, starts, counts, pose, cos_yaw, sin_yaw, mount):
    """``placed_in_world`` of the segments ``starts[k]:starts[k] + counts[k]`` of the
    sensor-frame ``points``, each with its sender's pose (x, y, yaw), cos and sin of its
    yaw and mount height (in the points' dtype), one after the other: the same sums."""
    out = np.empty((counts.sum(), 3))
    q = 0
    for k in range(len(counts)):
        x, y, c, s, h = pose[k, 0], pose[k, 1], cos_yaw[k], sin_yaw[k], mount[k]
        for i in range(starts[k], starts[k] + counts[k]):
            out[q, 0] = x + c * points[i, 0] - s * points[i, 1]
            out[q, 1] = y + s * points[i, 0] + c * points[i, 1]
            out[q, 2] = points[i, 2] + h
            q += 1
    return out


@njit(cache=True)
def _gather_two(a, b, starts, counts, from_b):
    """Segment k is ``counts[k]`` rows from ``starts[k]`` of ``b`` where ``from_b[k]``,
    else of ``a``; the segments one after the other."""
    out = np.empty((counts.sum(), a.shape[1]), dtype=a.dtype)
    q = 0
    for k in range(len(counts)):
        src = b if from_b[k] else a
        for i in range(starts[k], starts[k] + counts[k]):
            for c in range(a.shape[1]):
                out[q, c] = src[i, c]
            q += 1
    return out


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
    same_as_own: dict[ObjectKey, bool]  # received object overlaps something the agent sees itself


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
        shared = SharedBatch(shared.keys, points, counts, np.where(merged[:, None], 0.0, shared.velocity),
                             shared.age_s, shared.fresh)
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
    """``not_contradicted(not_me(store.current(t_now_s, fresh_keys), poses, length_m,
    width_m), grid, free_share)`` in three passes over the held points that write them
    once: the same objects, the same points, the same values. ``fresh``: the (sender,
    object id) arrays of this interval's receptions.

    Placing every held object (~34 000 points at 40 vehicles), dropping our body's
    points and compacting, then dropping what our LiDAR contradicts and compacting again
    copied the stack three times and paid a Python step per object to rebuild its keys."""
    age = store.expire(t_now_s)
    counts, velocity, pts = store.counts, store.velocity_xy, store.points_world
    shift = velocity * age[:, None]  # the same product as current's and not_me's
    mine = np.zeros(len(pts), dtype=bool)
    hits = np.zeros(len(counts))
    if poses and len(pts):
        yaw = np.array([p.yaw_rad for p in poses])
        px, py = np.array([p.x_m for p in poses]), np.array([p.y_m for p in poses])
        reach = np.hypot(length_m / 2 + BODY_MARGIN_M, width_m / 2 + BODY_MARGIN_M)
        box = np.array([px.min() - reach, px.max() + reach, py.min() - reach, py.max() + reach])
        _mark_mine_placed(pts, counts, shift, px, py, np.cos(yaw), np.sin(yaw), length_m / 2 + BODY_MARGIN_M,
                          width_m / 2 + BODY_MARGIN_M, box, mine, hits)
    share = hits / np.maximum(counts, 1)
    merged = (share >= MERGED_SHARE) & (share < SELF_SHARE)
    kept = (counts > 0) & (share < SELF_SHARE)
    kept_counts = counts - hits.astype(np.int64)  # each object's points that are not ours
    is_fresh = _member(_key(store.sender, store.object_id), _key(*fresh))
    stale = kept & ~is_fresh & (kept_counts > 0)
    if stale.any():
        n_inside, n_ground = _on_ground_placed(pts, counts, shift, merged, mine, stale, grid.spec.cell_m,
                                               exact_inverse(grid.spec.cell_m), grid.i0, grid.j0, grid.state, GROUND)
        kept &= ~(stale & (n_inside > 0) & (n_ground >= free_share * n_inside))
    points = _placed_kept(pts, counts, shift, merged, mine, kept, int(kept_counts[kept].sum()))
    if merged.any():
        velocity = np.where(merged[:, None], 0.0, velocity)
    keys = list(zip(store.sender[kept].tolist(), store.object_id[kept].tolist()))
    return SharedBatch(keys, points, kept_counts[kept], velocity[kept], age[kept], is_fresh[kept])


@njit(cache=True)
def _mark_mine_placed(pts, counts, shift, px, py, cos_yaw, sin_yaw, half_length, half_width, box, mine, hits):
    """``_mark_mine`` of the points placed at their objects' ``shift`` (``_moved``'s sums),
    placing them on the fly."""
    start = 0
    x_lo, x_hi, y_lo, y_hi = box[0], box[1], box[2], box[3]
    for k in range(len(counts)):
        sx, sy = shift[k, 0], shift[k, 1]
        n_hits = 0
        for p in range(start, start + counts[k]):
            x, y = pts[p, 0] + sx, pts[p, 1] + sy
            x0, y0 = x - sx, y - sy  # where it was captured
            if _on_a_body(x, y, px, py, cos_yaw, sin_yaw, half_length, half_width, x_lo, x_hi, y_lo, y_hi) or \
                    _on_a_body(x0, y0, px, py, cos_yaw, sin_yaw, half_length, half_width, x_lo, x_hi, y_lo, y_hi):
                mine[p] = True
                n_hits += 1
        hits[k] = n_hits
        start += counts[k]


@njit(cache=True)
def _on_ground_placed(pts, counts, shift, merged, mine, objects, cell_m, inv, i0, j0, state, ground):
    """``_on_ground`` of the points not ``mine``, placed at their objects' ``shift`` and,
    for the ``merged`` objects, moved back by it (``not_me``'s sums); ``inv``:
    ``exact_inverse(cell_m)``."""
    n = state.shape[0]
    n_inside = np.zeros(len(counts), dtype=np.int64)
    n_ground = np.zeros(len(counts), dtype=np.int64)
    start = 0
    for k in range(len(counts)):
        end = start + counts[k]
        if not objects[k]:
            start = end
            continue
        sx, sy, back = shift[k, 0], shift[k, 1], merged[k]
        inside = on_ground = 0
        for p in range(start, end):
            if mine[p]:
                continue
            x, y = pts[p, 0] + sx, pts[p, 1] + sy
            if back:
                x, y = x - sx, y - sy
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
        n_inside[k], n_ground[k] = inside, on_ground
        start = end
    return n_inside, n_ground


@njit(cache=True)
def _placed_kept(pts, counts, shift, merged, mine, objects, total):
    """The points not ``mine`` of the ``objects`` kept, placed as ``_on_ground_placed``
    places them, object after object."""
    out = np.empty((total, 3))
    q = start = 0
    for k in range(len(counts)):
        end = start + counts[k]
        if not objects[k]:
            start = end
            continue
        sx, sy, back = shift[k, 0], shift[k, 1], merged[k]
        for p in range(start, end):
            if mine[p]:
                continue
            x, y = pts[p, 0] + sx, pts[p, 1] + sy
            if back:
                x, y = x - sx, y - sy
            out[q, 0], out[q, 1], out[q, 2] = x, y, pts[p, 2]
            q += 1
        start = end
    return out


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
    """Merge placed shared objects into the grid (points outside the grid are ignored)."""
    state = grid.state.copy()
    received = np.zeros_like(grid.drivable)
    if not len(shared):
        return FusedGrid(grid, state, received, {})
    on_own = np.zeros(len(shared), dtype=np.bool_)
    _fuse_points(shared.points, shared.counts, grid.i0, grid.j0, grid.spec.cell_m, exact_inverse(grid.spec.cell_m),
                 grid.spec.ground_clear_m, grid.state, state, received, on_own)
    return FusedGrid(grid, state, received, dict(zip(shared.keys, on_own.tolist())))


@njit(cache=True)
def _fuse_points(pts, counts, i0, j0, cell_m, inv, clear_m, own, state, received, on_own):
    """One pass over the stacked points (``counts[o]`` of object o in turn): a point
    above the ground in a grid cell sets it ABOVE in ``state``; it is ``received`` when
    our own grid did not have it ABOVE, and its object is ``on_own`` when it did.
    ``inv``: ``exact_inverse(cell_m)``."""
    n = own.shape[0]
    p = 0
    for o in range(len(counts)):
        for _ in range(counts[o]):
            x, y, z = pts[p, 0], pts[p, 1], pts[p, 2]
            p += 1
            if not z > clear_m:
                continue
            if inv > 0.0:
                col = np.floor(x * inv) - i0
                row = np.floor(y * inv) - j0
            else:
                col = np.floor(x / cell_m) - i0
                row = np.floor(y / cell_m) - j0
            if not (0 <= row < n and 0 <= col < n):  # also refuses NaN
                continue
            r, c = int(row), int(col)
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
    _gather(pts, counts - 1, counts, 2)
    _gather(pts32, counts - 1, counts, 2)
    _gather_two(pts, pts, counts - 1, counts, flags)
    for p in (pts, pts32):
        _placed(p, counts - 1, counts, np.zeros((2, 3)), np.ones(2), np.zeros(2), np.zeros(2, dtype=p.dtype))
    _moved(pts, counts, np.zeros((2, 2)), -1.0)
    _compact(pts, counts, flags, flags)
    _compact(pts, counts, flags, np.ones(0, dtype=np.bool_))
    _mark_mine(pts, counts, np.zeros((2, 2)), np.zeros(1), np.zeros(1), np.ones(1), np.zeros(1), 1.0, 1.0,
               np.zeros(4), np.zeros(2, dtype=np.bool_), np.zeros(2))
    _on_ground(pts, counts, flags, 0.5, 0, 0, np.zeros((2, 2), dtype=np.uint8), GROUND)
    shift = np.zeros((2, 2))
    _mark_mine_placed(pts, counts, shift, np.zeros(1), np.zeros(1), np.ones(1), np.zeros(1), 1.0, 1.0, np.zeros(4),
                      np.zeros(2, dtype=np.bool_), np.zeros(2))
    _on_ground_placed(pts, counts, shift, flags, flags, flags, 0.5, 2.0, 0, 0, np.zeros((2, 2), dtype=np.uint8), GROUND)
    _placed_kept(pts, counts, shift, flags, flags, flags, 1)
