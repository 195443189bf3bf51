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

from vehicle_agent.frames import placed_in_world
from vehicle_agent.payload import ObjectPayload
from vehicle_agent.perception import ABOVE, GROUND, Grid

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
        point_kept = np.repeat(objects, self.counts)
        if points is not None:
            point_kept &= points
        counts = np.bincount(self.owner[point_kept], minlength=len(self.keys)).astype(np.int64)
        kept_points = np.compress(point_kept, self.points, axis=0)  # ~4x faster than points[point_kept]
        return SharedBatch([k for k, kept in zip(self.keys, objects.tolist()) if kept], kept_points,
                           counts[objects], self.velocity[objects], self.age_s[objects], self.fresh[objects])


@dataclass
class ReceivedStore:
    """The last reception of every shared object, for extrapolation."""

    max_age_s: float = MAX_AGE_S
    _last: dict[ObjectKey, tuple[ObjectPayload, np.ndarray]] = field(default_factory=dict)

    def add(self, obj: ObjectPayload) -> None:
        self.add_many([obj])

    def add_many(self, objs: list[ObjectPayload]) -> None:
        """Keep each object's newest reception, taken to the world (``sensor_to_world``,
        for all of them in one pass)."""
        newest: dict[ObjectKey, ObjectPayload] = {}
        for obj in objs:
            key = (obj.sender, obj.object_id)
            prev = newest.get(key) or (self._last[key][0] if key in self._last else None)
            if prev is None or obj.t_sim_s >= prev.t_sim_s:
                newest[key] = obj
        if not newest:
            return
        kept = list(newest.values())
        counts = np.array([len(o.points_sensor) for o in kept], dtype=np.int64)
        pts = np.concatenate([o.points_sensor for o in kept])
        yaw = np.array([o.sender_pose.yaw_rad for o in kept])
        c, s = np.repeat(np.cos(yaw), counts), np.repeat(np.sin(yaw), counts)
        x = np.repeat(np.array([o.sender_pose.x_m for o in kept]), counts)
        y = np.repeat(np.array([o.sender_pose.y_m for o in kept]), counts)
        mount = np.repeat(np.array([o.mount_height_m for o in kept], dtype=pts.dtype), counts)
        world = placed_in_world(pts, x, y, c, s, mount)
        start = 0
        for key, obj, n in zip(newest, kept, counts.tolist()):
            self._last[key] = (obj, world[start:start + n])
            start += n

    def current(self, t_now_s: float, fresh_keys: set[ObjectKey] = frozenset()) -> SharedBatch:
        """Every object not older than ``max_age_s``, placed at ``t_now_s`` along its
        velocity; older ones are forgotten."""
        keys, worlds, vel, age = [], [], [], []
        for key in sorted(self._last):
            obj, world = self._last[key]
            a = t_now_s - obj.t_sim_s
            if a > self.max_age_s:
                del self._last[key]
                continue
            keys.append(key)
            worlds.append(world)
            vel.append(obj.velocity_xy)
            age.append(a)
        counts = np.array([len(w) for w in worlds], dtype=np.int64)
        velocity = np.array(vel, dtype=np.float64).reshape(-1, 2)
        age_s = np.array(age, dtype=np.float64)
        points = np.concatenate(worlds) if worlds else np.zeros((0, 3))
        points[:, :2] += np.repeat(velocity * age_s[:, None], counts, axis=0)
        return SharedBatch(keys, points, counts, velocity, age_s, np.array([k in fresh_keys for k in keys], dtype=bool))


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
    if poses and len(pts):
        captured = pts[:, :2] - np.repeat(shared.velocity * shared.age_s[:, None], counts, axis=0)
        for xy in (pts[:, :2], captured):
            mine |= _on_bodies(xy, poses, length_m, width_m)
    share = np.bincount(shared.owner, weights=mine, minlength=len(shared)) / np.maximum(counts, 1)
    merged = (share >= MERGED_SHARE) & (share < SELF_SHARE)
    if merged.any():
        # merged with us: its motion is ours, the rest of it is taken as standing where it
        # was captured (measured: a parked car's view merged the truck with the passing
        # ego; the truck, "moving" at the ego's speed, blocked the ego's way back)
        back = np.repeat(np.where(merged[:, None], shared.velocity * shared.age_s[:, None], 0.0), counts, axis=0)
        points = pts.copy()
        points[:, :2] -= back
        shared = SharedBatch(shared.keys, points, counts, np.where(merged[:, None], 0.0, shared.velocity),
                             shared.age_s, shared.fresh)
    return shared.keep((counts > 0) & (share < SELF_SHARE), ~mine)


def _on_bodies(xy: np.ndarray, poses: list, length_m: float, width_m: float) -> np.ndarray:
    """Which points fall on our body at any of ``poses``. Only the points within the box
    around all the poses, widened by the body's half diagonal (a point on the body at
    one of them lies inside it), are tested."""
    out = np.zeros(len(xy), dtype=bool)
    reach = np.hypot(length_m / 2 + BODY_MARGIN_M, width_m / 2 + BODY_MARGIN_M)
    px, py = np.array([p.x_m for p in poses]), np.array([p.y_m for p in poses])
    x, y = xy[:, 0], xy[:, 1]
    near = np.flatnonzero((x >= px.min() - reach) & (x <= px.max() + reach)
                          & (y >= py.min() - reach) & (y <= py.max() + reach))
    sub = xy.take(near, axis=0)
    hit = np.zeros(len(near), dtype=bool)
    for pose in poses:  # a handful of poses, each test vectorized over the nearby points
        hit |= on_body(sub, pose, length_m, width_m, BODY_MARGIN_M)
    out[near] = hit
    return out


def not_contradicted(shared: SharedBatch, grid: Grid, free_share: float = 0.5) -> SharedBatch:
    """Drop carried-forward (not fresh) objects where our own LiDAR now sees bare ground:
    we can see that they are no longer there."""
    stale = ~shared.fresh & (shared.counts > 0)
    if not stale.any():
        return shared
    on_stale = np.repeat(stale, shared.counts)
    pts, owner = np.compress(on_stale, shared.points, axis=0), shared.owner[on_stale]
    n = grid.state.shape[0]
    rc = grid.cell_of(pts[:, :2])
    inside = (rc[:, 0] >= 0) & (rc[:, 0] < n) & (rc[:, 1] >= 0) & (rc[:, 1] < n)
    ground = np.zeros(len(pts), dtype=bool)
    ground[inside] = grid.state[rc[inside, 0], rc[inside, 1]] == GROUND
    n_inside = np.bincount(owner[inside], minlength=len(shared))
    n_ground = np.bincount(owner[ground], minlength=len(shared))
    gone = stale & (n_inside > 0) & (n_ground >= free_share * n_inside)
    return shared.keep(~gone)


def fuse(grid: Grid, shared: SharedBatch) -> FusedGrid:
    """Merge placed shared objects into the grid (points outside the grid are ignored)."""
    state = grid.state.copy()
    received = np.zeros_like(grid.drivable)
    if not len(shared):
        return FusedGrid(grid, state, received, {})
    on_own = np.zeros(len(shared), dtype=np.bool_)
    _fuse_points(shared.points, shared.counts, grid.i0, grid.j0, grid.spec.cell_m, grid.spec.ground_clear_m,
                 grid.state, state, received, on_own)
    return FusedGrid(grid, state, received, dict(zip(shared.keys, on_own.tolist())))


@njit(cache=True)
def _fuse_points(pts, counts, i0, j0, cell_m, clear_m, own, state, received, on_own):
    """One pass over the stacked points (``counts[o]`` of object o in turn): a point
    above the ground in a grid cell sets it ABOVE in ``state``; it is ``received`` when
    our own grid did not have it ABOVE, and its object is ``on_own`` when it did."""
    n = own.shape[0]
    p = 0
    for o in range(len(counts)):
        for _ in range(counts[o]):
            x, y, z = pts[p, 0], pts[p, 1], pts[p, 2]
            p += 1
            if not z > clear_m:
                continue
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
