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

from vehicle_agent.frames import sensor_to_world
from vehicle_agent.payload import ObjectPayload
from vehicle_agent.perception import ABOVE, GROUND, Grid

MAX_AGE_S = 1.0
SELF_SHARE = 0.3  # a received object with this share of its points on our own body is ourselves
BODY_MARGIN_M = 0.5  # a point this close to our body's box is on it

ObjectKey = tuple[int, int]  # (sender vid, object id)


@dataclass(frozen=True, slots=True)
class SharedObject:
    key: ObjectKey
    points_world: np.ndarray  # float64 (n, 3), placed at the current time
    velocity_xy: np.ndarray  # float64 (2,), world frame
    age_s: float  # now minus the capture time
    fresh: bool  # received this interval (False: carried forward)


@dataclass
class ReceivedStore:
    """The last reception of every shared object, for extrapolation."""

    max_age_s: float = MAX_AGE_S
    _last: dict[ObjectKey, tuple[ObjectPayload, np.ndarray]] = field(default_factory=dict)

    def add(self, obj: ObjectPayload) -> None:
        key = (obj.sender, obj.object_id)
        prev = self._last.get(key)
        if prev is None or obj.t_sim_s >= prev[0].t_sim_s:
            self._last[key] = (obj, sensor_to_world(obj.points_sensor, obj.sender_pose, obj.mount_height_m))

    def current(self, t_now_s: float, fresh_keys: set[ObjectKey] = frozenset()) -> list[SharedObject]:
        out = []
        for key in sorted(self._last):
            obj, world = self._last[key]
            age = t_now_s - obj.t_sim_s
            if age > self.max_age_s:
                del self._last[key]
                continue
            placed = world.copy()
            placed[:, :2] += obj.velocity_xy.astype(np.float64) * age
            out.append(SharedObject(key, placed, obj.velocity_xy.astype(np.float64), age, key in fresh_keys))
        return out


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


def stack_points(shared: list[SharedObject]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All objects' points stacked, each object's start row (for reduceat) and its count."""
    counts = np.array([len(o.points_world) for o in shared], dtype=np.int64)
    return np.concatenate([o.points_world for o in shared]), np.cumsum(counts) - counts, counts


def not_me(shared: list[SharedObject], poses: list, length_m: float, width_m: float) -> list[SharedObject]:
    """Drop what other vehicles saw of this vehicle itself: the objects that are mostly
    our body, and our body's points from the rest (an object may have merged us with a
    neighbour). ``poses`` are our current and recent poses: an older reception of us
    sits where we were a moment ago."""
    shared = [o for o in shared if len(o.points_world)]
    if not shared:
        return []
    pts, starts, _ = stack_points(shared)
    mine = np.zeros(len(pts), dtype=bool)
    if poses:
        # only points within the box around all the poses, widened by the body's half
        # diagonal (a point on the body at one of them lies inside it), are tested
        reach = np.hypot(length_m / 2 + BODY_MARGIN_M, width_m / 2 + BODY_MARGIN_M)
        px, py = np.array([p.x_m for p in poses]), np.array([p.y_m for p in poses])
        x, y = pts[:, 0], pts[:, 1]
        near = np.flatnonzero((x >= px.min() - reach) & (x <= px.max() + reach)
                              & (y >= py.min() - reach) & (y <= py.max() + reach))
        xy = pts[near, :2]
        hit = np.zeros(len(near), dtype=bool)
        for pose in poses:  # a handful of poses, each test vectorized over the nearby points
            hit |= on_body(xy, pose, length_m, width_m, BODY_MARGIN_M)
        mine[near] = hit
    share = np.add.reduceat(mine.astype(np.float64), starts) / np.diff(np.append(starts, len(pts)))
    out = []
    for o, start, frac in zip(shared, starts, share):
        if frac >= SELF_SHARE:
            continue
        if frac > 0:
            keep = ~mine[start:start + len(o.points_world)]
            o = SharedObject(o.key, o.points_world[keep], o.velocity_xy, o.age_s, o.fresh)
        out.append(o)
    return out


def not_contradicted(shared: list[SharedObject], grid: Grid, free_share: float = 0.5) -> list[SharedObject]:
    """Drop carried-forward (not fresh) objects where our own LiDAR now sees bare ground:
    we can see that they are no longer there."""
    stale = [o for o in shared if not o.fresh and len(o.points_world)]
    if not stale:
        return shared
    pts, starts, _ = stack_points(stale)
    n = grid.state.shape[0]
    rc = grid.cell_of(pts[:, :2])
    inside = (rc[:, 0] >= 0) & (rc[:, 0] < n) & (rc[:, 1] >= 0) & (rc[:, 1] < n)
    ground = np.zeros(len(pts), dtype=bool)
    ground[inside] = grid.state[rc[inside, 0], rc[inside, 1]] == GROUND
    n_inside = np.add.reduceat(inside.astype(np.int64), starts)
    n_ground = np.add.reduceat(ground.astype(np.int64), starts)
    gone = {o.key for o, ni, ng in zip(stale, n_inside, n_ground) if ni > 0 and ng >= free_share * ni}
    return [o for o in shared if o.key not in gone]


def fuse(grid: Grid, shared: list[SharedObject]) -> FusedGrid:
    """Merge placed shared objects into the grid (points outside the grid are ignored)."""
    state = grid.state.copy()
    received = np.zeros_like(grid.drivable)
    if not shared:
        return FusedGrid(grid, state, received, {})
    pts, _, counts = stack_points(shared)
    on_own = np.zeros(len(shared), dtype=np.bool_)
    _fuse_points(pts, counts, grid.i0, grid.j0, grid.spec.cell_m, grid.spec.ground_clear_m, grid.state, state,
                 received, on_own)
    return FusedGrid(grid, state, received, {o.key: hit for o, hit in zip(shared, on_own.tolist())})


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
