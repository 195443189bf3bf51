"""Path and trajectory planning on the fused occupancy grid (paper 5.2).

Path: A* over the grid's 8-connected cells from the vehicle to the route point
``lookahead_m`` ahead. Passable cells are drivable, not within the car's half width
(plus a margin) of a *static* obstacle (moving ones are the trajectory planner's
business), and within ``corridor_m`` of the route (the lane and its neighbour, so a
blocked lane can be passed, as in overtaking). Costs add the distance from the route
(stay in lane when you can) and a turn penalty that grows with speed (no heading
change the current speed cannot take). The path is reused while a fast check finds
its cells still passable.

Trajectory: the path with arrival times from the speed profile (accelerate to the
cruise speed at the comfort rate). Every moving object, own or received, is
extrapolated at constant velocity; a waypoint conflicts when an object's body comes
within ``safety_m`` of the ego's around the time the ego is there. Static obstacles
are the path's business; where no path avoids them, the first blocked cell on the
path is a conflict too. Bodies: the ego is three
circles of its half width along the path (rear, middle, front), each object its
oriented box. The vehicle
follows the plan until it is within stopping distance of the first conflict, then
brakes to stop short of it (``approach_accel``: at the stop point, moving up to it
while the conflict moves on), and stays stopping while any conflict remains; it
resumes when the conflict is gone.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from protocol.messages import Mission, Pose, VehicleSpec
from vehicle_agent.paths import (_arc_lengths, _clip, _interp, _interp_index, _point_at, _segment_foot, arc_lengths,
                                 point_at, progress_along)
from vehicle_agent.perception import ABOVE, Grid, LatticeRaster, lattice_centers

STATIC_MPS = 0.5
BEHIND_M = 1.0  # a path may run this far behind the vehicle's centre (it starts there), no farther: it does not reverse
MOVER_MIN_DIMS_M = (4.0, 1.8)  # a moving object is at least car-sized: LiDAR sees only part of it


@dataclass(frozen=True, slots=True)
class PlannerConfig:
    lookahead_m: float = 40.0
    corridor_m: float = 6.0
    margin_m: float = 0.3  # obstacle inflation beyond the half width
    route_weight: float = 0.4  # cost per cell per metre off the route
    turn_weight: float = 0.05  # cost per 45 degrees of heading change, per m/s of speed
    comfort_brake_mps2: float = 4.0
    comfort_accel_mps2: float = 2.0
    safety_m: float = 2.3  # body clearance to keep from a moving object (a near miss is < 2 m)
    wait_clear_m: float = 2.0  # where to wait for it: out of its swept zone by the near-miss distance
    time_window_s: float = 1.5  # +- uncertainty on when an object is where
    horizon_s: float = 8.0
    stop_buffer_m: float = 3.0


@dataclass(frozen=True, slots=True)
class Obstacle:
    """An object to avoid: where it is at ``t_sim_s``, how it moves, how big it is."""

    xy: np.ndarray
    velocity: np.ndarray
    length_m: float
    width_m: float
    t_sim_s: float
    heading_rad: float


@dataclass(frozen=True, slots=True)
class Obstacles:
    """Obstacles as arrays, one row per ``Obstacle``: the planner's per-obstacle work runs
    in whole-array passes (at 40 vehicles an agent avoids 30-70 moving objects, and one
    small Python step per object was most of the planning stage's cost)."""

    xy: np.ndarray  # float64 (O, 2)
    velocity: np.ndarray  # float64 (O, 2)
    length_m: np.ndarray  # float64 (O,)
    width_m: np.ndarray  # float64 (O,)
    t_sim_s: np.ndarray  # float64 (O,)
    heading_rad: np.ndarray  # float64 (O,)

    def __len__(self) -> int:
        return len(self.length_m)

    @staticmethod
    def of(obstacles: Sequence[Obstacle]) -> Obstacles:
        def column(values: list) -> np.ndarray:
            return np.array(values, dtype=np.float64)

        return Obstacles(column([o.xy for o in obstacles]).reshape(-1, 2),
                         column([o.velocity for o in obstacles]).reshape(-1, 2),
                         column([o.length_m for o in obstacles]), column([o.width_m for o in obstacles]),
                         column([o.t_sim_s for o in obstacles]), column([o.heading_rad for o in obstacles]))

    def columns(self) -> tuple[np.ndarray, ...]:
        return self.xy, self.velocity, self.length_m, self.width_m, self.t_sim_s, self.heading_rad

    def keep(self, rows: np.ndarray) -> Obstacles:
        """The obstacles where ``rows`` (O,) is set."""
        if rows.all():
            return self
        return Obstacles(self.xy[rows], self.velocity[rows], self.length_m[rows], self.width_m[rows],
                         self.t_sim_s[rows], self.heading_rad[rows])


@dataclass(frozen=True, slots=True)
class Plan:
    path: np.ndarray  # (m, 2) world frame
    accel_mps2: float
    trajectory: np.ndarray  # float32 (p, 3) [x, y, t] every second, for the control message
    conflict_s_m: float | None  # distance along the path to the first predicted conflict
    braking: bool


# ------------------------------------------------------------------------ A* path


@njit(cache=True)
def _disc_half_widths(radius):
    """(2 radius + 1,): the half width of the disc's row run at each row offset dy, the
    largest w with w^2 + dy^2 <= radius^2."""
    half = np.empty(2 * radius + 1, dtype=np.int64)
    for dy in range(-radius, radius + 1):
        w = 0
        while (w + 1) * (w + 1) + dy * dy <= radius * radius:
            w += 1
        half[dy + radius] = w
    return half


@njit(cache=True)
def _paint_disc(out, y, x, half, radius):
    """Set the cells of ``out`` within ``radius`` cells (Euclidean) of cell (y, x)."""
    ny, nx = out.shape
    for dy in range(-radius, radius + 1):
        yy = y + dy
        if 0 <= yy < ny:
            w = half[dy + radius]
            out[yy, max(x - w, 0):min(x + w + 1, nx)] = True


@njit  # a reference for the tests (the planner paints discs in _static_blocked_passable): not cached
def _inflate(obst, radius):
    """Cells within ``radius`` cells (Euclidean) of an obstacle cell: the disc painted
    round each one a row run at a time, not a test per cell of its square."""
    ny, nx = obst.shape
    out = np.zeros_like(obst)
    half = _disc_half_widths(radius)
    for y in range(ny):
        for x in range(nx):
            if obst[y, x]:
                _paint_disc(out, y, x, half, radius)
    return out


@njit(cache=True)
def _passable(blocked, drivable, corridor):
    """``drivable & ~blocked & corridor``."""
    passable = np.empty_like(blocked)
    ny, nx = blocked.shape
    for y in range(ny):
        for x in range(nx):
            passable[y, x] = drivable[y, x] & ~blocked[y, x] & corridor[y, x]
    return passable


@njit  # a reference for the tests, as _inflate
def _blocked_passable(static, drivable, corridor, radius):
    """``_inflate(static, radius)`` (the blocked cells) and the passable cells,
    ``drivable & ~blocked & corridor``, in one kernel: replaces the inflation and three
    whole-grid numpy passes (and their temporaries) of every tick."""
    blocked = _inflate(static, radius)
    return blocked, _passable(blocked, drivable, corridor)


@njit(cache=True)
def _static_blocked_passable(state, drivable, moving, corridor, radius, above):
    """``_blocked_passable`` of the static obstacles, ``(state == above) & drivable &
    ~moving``, tested cell by cell as the discs are painted: no mask of them, and not
    the three whole-grid numpy passes and their temporaries that made it every tick."""
    ny, nx = state.shape
    blocked = np.zeros((ny, nx), dtype=np.bool_)
    half = _disc_half_widths(radius)
    for y in range(ny):
        for x in range(nx):
            if state[y, x] == above and drivable[y, x] and not moving[y, x]:
                _paint_disc(blocked, y, x, half, radius)
    return blocked, _passable(blocked, drivable, corridor)


_DY = np.array([0, 1, 1, 1, 0, -1, -1, -1])
_DX = np.array([1, 1, 0, -1, -1, -1, 0, 1])


def _next_headings() -> np.ndarray:
    """(8, 5): the headings a move may take after one in heading d (at most 90 degrees
    in one cell), ascending, as ``_astar`` tries them."""
    out = np.empty((8, 5), dtype=np.int64)
    for d in range(8):
        out[d] = [nd for nd in range(8) if min(abs(nd - d), 8 - abs(nd - d)) <= 2]
    return out


_NEXT = _next_headings()


@njit(cache=True)
def _astar(passable, extra, start_r, start_c, start_dir, goal_r, goal_c, turn_cost):
    """A* over (cell, heading of the last move); returns the path cells (m, 2) or (0, 2).

    A state is closed by setting its cost to -inf (no cost is below it: a closed state
    is never reopened), which spares a closed flag per state; parents are read only
    along the path found, so they are not filled beforehand, and they and the heap's
    states are int32 (a window has at most 280 x 280 x 8 states): less memory
    touched per search."""
    ny, nx = passable.shape
    n_states = ny * nx * 8
    g = np.full(n_states, np.inf)
    parent = np.empty(n_states, dtype=np.int32)
    capacity = 4 * n_states  # lazy deletion pushes a state once per improvement (at most its in-degree, 5)
    heap_f = np.empty(capacity)
    heap_s = np.empty(capacity, dtype=np.int32)
    s0 = (start_r * nx + start_c) * 8 + start_dir
    g[s0] = 0.0
    parent[s0] = -1
    heap_f[0] = 0.0
    heap_s[0] = s0
    size = 1
    goal_state = -1
    while size > 0:
        s = heap_s[0]
        size -= 1
        # sift down the last element from the root
        lf, ls = heap_f[size], heap_s[size]
        i = 0
        while True:
            c = 2 * i + 1
            if c >= size:
                break
            if c + 1 < size and heap_f[c + 1] < heap_f[c]:
                c += 1
            if heap_f[c] < lf:
                heap_f[i], heap_s[i] = heap_f[c], heap_s[c]
                i = c
            else:
                break
        heap_f[i], heap_s[i] = lf, ls
        g_s = g[s]
        if g_s == -np.inf:  # closed
            continue
        g[s] = -np.inf
        cell, d = s // 8, s % 8
        r, cc = cell // nx, cell % nx
        if r == goal_r and cc == goal_c:
            goal_state = s
            break
        for k in range(5):
            nd = _NEXT[d, k]
            turn = abs(nd - d)
            turn = min(turn, 8 - turn)
            rr, c2 = r + _DY[nd], cc + _DX[nd]
            if rr < 0 or rr >= ny or c2 < 0 or c2 >= nx or not passable[rr, c2]:
                continue
            step = 1.4142135 if nd % 2 == 1 else 1.0
            ns = (rr * nx + c2) * 8 + nd
            cost = g_s + step * (1.0 + extra[rr, c2]) + turn_cost * turn
            if cost < g[ns]:
                if size == capacity:  # cannot happen within the in-degree bound; fail rather than overflow
                    return np.zeros((0, 2), dtype=np.int64)
                g[ns] = cost
                parent[ns] = s
                h = np.hypot(rr - goal_r, c2 - goal_c)
                # sift up
                j = size
                size += 1
                while j > 0:
                    p = (j - 1) // 2
                    if heap_f[p] <= cost + h:
                        break
                    heap_f[j], heap_s[j] = heap_f[p], heap_s[p]
                    j = p
                heap_f[j], heap_s[j] = cost + h, ns
    if goal_state < 0:
        return np.zeros((0, 2), dtype=np.int64)
    n = 0
    s = goal_state
    while s >= 0:
        n += 1
        s = parent[s]
    out = np.empty((n, 2), dtype=np.int64)
    s = goal_state
    for k in range(n - 1, -1, -1):
        cell = s // 8
        out[k, 0], out[k, 1] = cell // nx, cell % nx
        s = parent[s]
    return out

@njit(cache=True)
def _distance_to_polyline(xs, ys, route):
    """Distance from every lattice centre (ys x xs) to the polyline."""
    out = np.full((len(ys), len(xs)), np.inf)
    for k in range(route.shape[0] - 1):
        ax, ay = route[k, 0], route[k, 1]
        ex, ey = route[k + 1, 0] - ax, route[k + 1, 1] - ay
        len2 = max(ex * ex + ey * ey, 1e-12)
        for r in range(len(ys)):
            for c in range(len(xs)):
                t = min(max(((xs[c] - ax) * ex + (ys[r] - ay) * ey) / len2, 0.0), 1.0)
                d = np.hypot(xs[c] - ax - t * ex, ys[r] - ay - t * ey)
                if d < out[r, c]:
                    out[r, c] = d
    return out


class RouteRaster(LatticeRaster):
    """Distance to the route on the world lattice, computed once per mission."""

    def __init__(self, route: np.ndarray, cell_m: float, margin_m: float) -> None:
        i0, j0, xs, ys = lattice_centers(route, cell_m, margin_m)
        super().__init__(_distance_to_polyline(xs, ys, np.ascontiguousarray(route, dtype=np.float64)), i0, j0, np.inf)


def path_from(path: np.ndarray, xy: np.ndarray, s: np.ndarray | None = None, s0: float | None = None) -> np.ndarray:
    """The rest of ``path`` from the point nearest ``xy``, starting at ``xy`` itself;
    ``s`` and ``s0``: the path's ``arc_lengths`` and ``progress_along(path, xy)`` if the
    caller has them."""
    if len(path) < 2:
        return path
    s = arc_lengths(path) if s is None else s
    s0 = progress_along(path, xy, s) if s0 is None else s0
    rest = path[s > s0 + 1e-6]
    return np.vstack([xy[None, :], rest]) if len(rest) else np.vstack([xy[None, :], path[-1:]])


def path_until(path: np.ndarray, s: np.ndarray, s_end: float) -> np.ndarray:
    """``path`` (with arc lengths ``s``) cut at arc length ``s_end``; at least two points
    (a stub along the first segment when ``s_end`` is about 0)."""
    s_end = max(s_end, 0.5)
    if s_end >= s[-1] or len(path) < 2:
        return path
    keep = int(np.searchsorted(s, s_end, side="right"))
    return np.vstack([path[:keep], point_at(path, float(s_end), s).reshape(1, 2)])


@dataclass
class PathPlanner:
    route: np.ndarray
    spec: VehicleSpec
    config: PlannerConfig = field(default_factory=PlannerConfig)
    path: np.ndarray | None = None
    replans: int = 0
    blocked: np.ndarray | None = None
    static: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # what ``blocked`` was inflated from
    _route_raster: RouteRaster | None = None
    _corridor_raster: LatticeRaster | None = None  # the route raster's cells within corridor_m
    _route_cum: np.ndarray | None = None
    _path_end: tuple[np.ndarray, float] | None = None  # a path and progress_along(path, its last point)
    _path_cum: tuple[np.ndarray, np.ndarray] | None = None  # a path and its arc_lengths
    _progress: tuple[np.ndarray, tuple[float, float], float] | None = None  # a path, a point, progress_along

    def along(self, path: np.ndarray) -> np.ndarray:
        """``arc_lengths(path)``, computed once for the path it keeps while it stays good."""
        if self._path_cum is None or self._path_cum[0] is not path:
            self._path_cum = (path, arc_lengths(path))
        return self._path_cum[1]

    def progress(self, path: np.ndarray, xy: np.ndarray) -> float:
        """``progress_along(path, xy)``, computed once per path and point (the fast check
        and ``path_from`` both ask where the vehicle is along the kept path)."""
        key = (float(xy[0]), float(xy[1]))
        if self._progress is None or self._progress[0] is not path or self._progress[1] != key:
            self._progress = (path, key, progress_along(path, xy, self.along(path)))
        return self._progress[2]

    @property
    def route_cum(self) -> np.ndarray:
        """``arc_lengths(route)``, computed once (the route never changes)."""
        if self._route_cum is None:
            self._route_cum = arc_lengths(self.route)
        return self._route_cum

    def plan(self, grid: Grid, fused_state: np.ndarray, moving_cells: np.ndarray, pose: Pose,
             speed_mps: float) -> np.ndarray:
        """A world-frame path (m, 2) from the vehicle toward the route ahead, round the
        static obstacles: ``fused_state``'s ABOVE cells that are drivable and not
        ``moving_cells``.

        ``self.blocked`` keeps the inflated static obstacles the path had to avoid.
        """
        cfg = self.config
        radius = int(np.ceil((self.spec.width_m / 2 + cfg.margin_m) / grid.spec.cell_m))
        if self._route_raster is None:
            self._route_raster = RouteRaster(self.route, grid.spec.cell_m, cfg.corridor_m + 2.0)
            raster = self._route_raster
            self._corridor_raster = LatticeRaster(raster.values <= cfg.corridor_m, raster.i0, raster.j0, False)
        corridor = self._corridor_raster.window(grid.i0, grid.j0, grid.state.shape[0])  # dist <= corridor_m
        blocked, passable = _static_blocked_passable(fused_state, grid.drivable, moving_cells, corridor, radius, ABOVE)
        self.blocked = blocked
        self.static = (fused_state, grid.drivable, moving_cells)
        s_now = progress_along(self.route, np.array([pose.x_m, pose.y_m]), self.route_cum)
        route_ahead = point_at(self.route, s_now + np.arange(0.0, cfg.lookahead_m + 1e-9, 1.0), self.route_cum)
        if self.path is not None and self._still_good(grid, passable, pose, route_ahead):
            return self.path
        start = grid.cell_of(np.array([pose.x_m, pose.y_m]))
        n = grid.state.shape[0]
        goal = None
        for xy in route_ahead[::-1]:  # the farthest passable route point ahead, inside the grid
            rc = grid.cell_of(xy)
            if 0 <= rc[0] < n and 0 <= rc[1] < n and passable[rc[0], rc[1]]:
                goal = rc
                break
        self.replans += 1
        if goal is None or not (0 <= start[0] < n and 0 <= start[1] < n):
            self.path = route_ahead
            return self.path
        passable[start[0], start[1]] = True
        heading = int(np.round(pose.yaw_rad / (np.pi / 4))) % 8
        # search only the bounding box of the corridor: a band, not the whole 140 m grid
        rows, cols = np.flatnonzero(passable.any(axis=1)), np.flatnonzero(passable.any(axis=0))
        r0, r1 = max(min(rows[0], start[0], goal[0]) - 1, 0), min(max(rows[-1], start[0], goal[0]) + 2, n)
        c0, c1 = max(min(cols[0], start[1], goal[1]) - 1, 0), min(max(cols[-1], start[1], goal[1]) + 2, n)
        dist = self._route_raster.window(grid.i0, grid.j0, n)
        extra = (cfg.route_weight * dist[r0:r1, c0:c1]).astype(np.float64)
        ahead = _ahead_of(pose, grid.i0 + c0, grid.j0 + r0, r1 - r0, c1 - c0, grid.spec.cell_m, BEHIND_M)
        cells = _astar(np.ascontiguousarray(passable[r0:r1, c0:c1] & ahead), extra, int(start[0] - r0), int(start[1] - c0),
                       heading, int(goal[0] - r0), int(goal[1] - c0), cfg.turn_weight * max(speed_mps, 1.0))
        cells = cells + np.array([r0, c0])
        if len(cells) < 2:
            self.path = route_ahead  # no way through: the speed planner stops short of the block
        else:
            raw = _snap_to_route(grid.cell_centers(cells[:, 0], cells[:, 1]), self.route, grid.spec.cell_m)
            self.path = _smooth_clear(raw, grid, blocked)
            self.path[0] = [pose.x_m, pose.y_m]
        return self.path

    def _still_good(self, grid: Grid, passable: np.ndarray, pose: Pose, route_ahead: np.ndarray) -> bool:
        """The fast check: the old path's remaining cells are passable and it still leads ahead."""
        path = self.path
        cum = self.along(path)
        s = self.progress(path, np.array([pose.x_m, pose.y_m]))
        if self._path_end is None or self._path_end[0] is not path:  # the path is kept while it stays good
            self._path_end = (path, progress_along(path, path[-1], cum))
        end = self._path_end[1]
        if np.linalg.norm(path[-1] - route_ahead[-1]) > 10.0 or end - s < 15.0:
            return False
        ahead = s + np.arange(0.0, end - s, 0.5)
        return _first_along(passable, 0, path, ahead, cum, grid.i0, grid.j0, grid.spec.cell_m) < 0


def _ahead_of(pose: Pose, i0: int, j0: int, rows: int, cols: int, cell_m: float, behind_m: float) -> np.ndarray:
    """(rows, cols) bool: the cells of the window at lattice (i0, j0) whose centres lie
    ahead of the vehicle, or at most ``behind_m`` behind it, along its heading."""
    c, s = np.cos(pose.yaw_rad), np.sin(pose.yaw_rad)
    x = (i0 + np.arange(cols) + 0.5) * cell_m - pose.x_m
    y = (j0 + np.arange(rows) + 0.5) * cell_m - pose.y_m
    return (y[:, None] * s + x[None, :] * c) >= -behind_m


def _snap_to_route(path: np.ndarray, route: np.ndarray, cell_m: float) -> np.ndarray:
    """Where the grid path runs along the route (within a cell), put it on the route
    itself: a lane centre need not fall on a cell centre."""
    return _snapped(np.ascontiguousarray(path, dtype=np.float64), np.asarray(route, dtype=np.float64), cell_m * 0.75)


@njit(cache=True)
def _snapped(path, route, within_m):
    """Each path point moved to its foot on the nearest route segment (the first nearest;
    a NaN distance wins, as ``np.argmin``) where that is within ``within_m``: the
    (points x segments) numpy passes and their temporaries of ``_snap_to_route``, one
    point at a time, with their float operations in the same order."""
    out = path.copy()
    for p in range(path.shape[0]):
        x, y = path[p, 0], path[p, 1]
        best_d, best_x, best_y = np.inf, 0.0, 0.0
        for k in range(route.shape[0] - 1):
            _, _, fx, fy = _segment_foot(route, k, x, y)
            dx, dy = fx - x, fy - y
            d = np.sqrt(dx * dx + dy * dy)
            if k == 0 or d < best_d or (np.isnan(d) and not np.isnan(best_d)):
                best_d, best_x, best_y = d, fx, fy
            if np.isnan(d):
                break
        if best_d <= within_m:
            out[p, 0], out[p, 1] = best_x, best_y
    return out


def _smooth_clear(raw: np.ndarray, grid: Grid, blocked: np.ndarray) -> np.ndarray:
    """``_smooth`` where the smoothed path keeps clear of ``blocked`` cells (sampled every
    quarter cell); near a point where it does not, the raw (snapped) points are kept: a
    moving average cuts the corner round a parked truck into the truck's margin, and the
    speed planner would then stop for a block the path never had."""
    smooth = _smooth(raw)
    out = smooth
    keep_raw = np.zeros(len(raw), dtype=bool)
    for _ in range(8):
        bad = _uncleared(out, blocked, grid.i0, grid.j0, grid.spec.cell_m, grid.spec.cell_m / 4) & ~keep_raw
        if not bad.any():
            break
        keep_raw |= np.convolve(bad, np.ones(5), mode="same") > 0  # the window the average mixed in
        out = np.where(keep_raw[:, None], raw, smooth)
    return out


@njit(cache=True)
def _uncleared(path, blocked, i0, j0, cell, step_m):
    """(P,) bool: both ends of every segment of ``path`` that crosses a set cell of
    ``blocked`` (the grid with cell (0, 0) at lattice (i0, j0)), sampled ``step_m`` apart
    from its start (the segment's length over ``step_m`` points, rounded up, at least
    one): the dozen numpy passes over every sample that ``_smooth_clear`` made per
    round, with their float operations, and a segment left at its first blocked sample."""
    n = blocked.shape[0]
    bad = np.zeros(path.shape[0], dtype=np.bool_)
    for i in range(path.shape[0] - 1):
        sx, sy = path[i + 1, 0] - path[i, 0], path[i + 1, 1] - path[i, 1]
        steps = np.ceil(np.hypot(sx, sy) / step_m)
        if np.isnan(steps):
            raise ValueError("a path point is not finite")  # as np.repeat of the NaN's count
        steps = np.int64(max(steps, 1.0))
        for j in range(steps):
            f = j / steps
            row = np.int64(np.floor((path[i, 1] + f * sy) / cell)) - j0
            col = np.int64(np.floor((path[i, 0] + f * sx) / cell)) - i0
            if 0 <= row < n and 0 <= col < n and blocked[row, col]:
                bad[i] = bad[i + 1] = True
                break
    return bad


def _smooth(path: np.ndarray, window: int = 5) -> np.ndarray:
    """Moving average of the grid path (end points kept): removes the 45-degree stair steps."""
    if len(path) <= window:
        return path.copy()
    kernel = np.ones(window) / window
    out = path.copy()
    half = window // 2
    for d in range(2):
        out[half:-half, d] = np.convolve(path[:, d], kernel, mode="valid")
    return out


# ------------------------------------------------------------------------ speed / conflicts


@njit(cache=True)
def _cell_value(mask, x, y, i0, j0, cell):
    """1 where the point (x, y) falls in a set cell of ``mask`` (the grid with cell (0, 0)
    at lattice (i0, j0)), 0 in an unset one, -1 outside the grid: ``grid.cell_of``, the
    inside test and the lookup (about ten numpy calls on arrays of points)."""
    fx, fy = np.floor(x / cell), np.floor(y / cell)
    if not (abs(fx) < 4e18 and abs(fy) < 4e18):  # NaN, inf, out of int64: outside
        return -1
    row, col = np.int64(fy) - j0, np.int64(fx) - i0
    if 0 <= row < mask.shape[0] and 0 <= col < mask.shape[1]:
        return 1 if mask[row, col] else 0
    return -1


@njit(cache=True)
def _first_along(mask, value, path, s, cum, i0, j0, cell):
    """The first k whose point ``s[k]`` along the path (``point_at``) has ``_cell_value``
    ``value``, or -1: the points one at a time, up to the first found (the fast check and
    the blocked-cell test sampled every point of the path ahead, then looked)."""
    xs, ys = np.ascontiguousarray(path[:, 0]), np.ascontiguousarray(path[:, 1])
    end = cum[cum.shape[0] - 1]
    for k in range(s.shape[0]):
        key = _clip(s[k], 0.0, end)
        j = _interp_index(key, cum) if not np.isnan(key) else 0
        if _cell_value(mask, _interp(key, j, cum, xs), _interp(key, j, cum, ys), i0, j0, cell) == value:
            return k
    return -1


def first_blocked(path: np.ndarray, grid: Grid, blocked: np.ndarray, step_m: float = 0.5,
                  s_path: np.ndarray | None = None, static: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
                  body_radius: int = 0) -> float | None:
    """Distance along the path of its first cell inside an (inflated) static obstacle;
    ``s_path``: the path's ``arc_lengths`` if the caller has them.

    ``static`` = (state, drivable, moving), the grids ``blocked`` was inflated from (its
    static obstacles are the ABOVE cells that are drivable and not moving): then a
    vehicle that already stands inside the inflation (the path's first point, where it
    is, lies in a blocked cell) may drive on out of it. The inflation is the body's half
    width plus a margin, measured from cell centres, so pure pursuit trailing a path
    that runs along its edge puts the vehicle inside it without anything near its body:
    until the path first leaves the blocked cells, a blocked point counts only where
    the body itself would reach a static obstacle (one within ``body_radius`` cells).
    Without that, the first point ahead was "blocked" at 0.5 m whatever the path, and a
    vehicle that stopped there could never start again (overtaking, 40 vehicles, seed
    9: the ego stopped beside the parked truck in the oncoming lane and timed out)."""
    if len(path) < 2:
        return None
    cum = arc_lengths(path) if s_path is None else s_path
    s = np.arange(0.5, cum[-1], step_m)
    path = np.asarray(path, dtype=np.float64)
    if static is None:
        hit = _first_along(blocked, 1, path, s, cum, grid.i0, grid.j0, grid.spec.cell_m)
    else:
        state, drivable, moving = static
        hit = _first_blocked_leaving(blocked, state, drivable, moving, ABOVE, body_radius, path, s, cum, grid.i0,
                                     grid.j0, grid.spec.cell_m)
    return float(s[hit]) if hit >= 0 else None


@njit(cache=True)
def _near_static(state, drivable, moving, above, row, col, radius):
    """Whether a static obstacle cell (``state == above``, drivable, not moving) lies
    within ``radius`` cells (Euclidean, as ``_paint_disc`` paints) of cell (row, col)."""
    ny, nx = state.shape
    for dy in range(-radius, radius + 1):
        yy = row + dy
        if yy < 0 or yy >= ny:
            continue
        w = 0
        while (w + 1) * (w + 1) + dy * dy <= radius * radius:
            w += 1
        for xx in range(max(col - w, 0), min(col + w + 1, nx)):
            if state[yy, xx] == above and drivable[yy, xx] and not moving[yy, xx]:
                return True
    return False


@njit(cache=True)
def _first_blocked_leaving(blocked, state, drivable, moving, above, body_radius, path, s, cum, i0, j0, cell):
    """``first_blocked`` with its ``static`` grids: the first k whose point ``s[k]`` is in
    a blocked cell, except that while the vehicle is inside the inflation it stands in
    (the path's first point blocked, and no unblocked point passed yet) a blocked point
    counts only if a static obstacle lies within ``body_radius`` cells of it; -1 if none."""
    xs, ys = np.ascontiguousarray(path[:, 0]), np.ascontiguousarray(path[:, 1])
    leaving = _cell_value(blocked, xs[0], ys[0], i0, j0, cell) == 1
    end = cum[cum.shape[0] - 1]
    for k in range(s.shape[0]):
        key = _clip(s[k], 0.0, end)
        j = _interp_index(key, cum) if not np.isnan(key) else 0
        x, y = _interp(key, j, cum, xs), _interp(key, j, cum, ys)
        if _cell_value(blocked, x, y, i0, j0, cell) != 1:
            leaving = False
            continue
        if leaving:
            row, col = np.int64(np.floor(y / cell)) - j0, np.int64(np.floor(x / cell)) - i0
            if not _near_static(state, drivable, moving, above, row, col, body_radius):
                continue
        return k
    return -1


def arrival_times(s: np.ndarray, v0: float, v_cruise: float, accel: float) -> np.ndarray:
    """Time to cover distance ``s`` starting at v0, accelerating at ``accel`` up to v_cruise."""
    v_cruise = max(v_cruise, 1e-3)
    v0 = min(v0, v_cruise)
    t_acc = (v_cruise - v0) / accel
    s_acc = (v0 + v_cruise) / 2 * t_acc
    return _arrival_times(np.asarray(s, dtype=np.float64).reshape(-1), v0, v_cruise, accel, t_acc,
                          s_acc).reshape(np.shape(s))


@njit(cache=True)
def _arrival_times(s, v0, v_cruise, accel, t_acc, s_acc):
    """``arrival_times``' two branches, the one each distance takes only: the numpy
    version's expressions (both branches for every point, then ``np.where``) in one pass."""
    out = np.empty(s.shape[0])
    for k in range(s.shape[0]):
        x = s[k]
        if x <= s_acc:
            m = x if (x >= 0.0 or np.isnan(x)) else 0.0  # np.maximum(x, 0.0)
            out[k] = (-v0 + np.sqrt(v0 * v0 + 2 * accel * m)) / accel
        else:
            out[k] = t_acc + (x - s_acc) / v_cruise
    return out


def _body_centers(path: np.ndarray, spec: VehicleSpec, full: np.ndarray) -> tuple[np.ndarray, float]:
    """(3, M, 2) the ego's rear, middle and front circle centres at each path point, and
    their radius, the half width: exact across the body (a car in the next lane is
    as far as it is), short of the corners by 0.37 m diagonally at most. ``full``: the
    path's ``arc_lengths``."""
    body_half = max(spec.length_m - spec.width_m, 0.0) / 2
    return _body_circles(np.asarray(path, dtype=np.float64), full, body_half), float(spec.width_m / 2)


@njit(cache=True)
def _body_circles(path, full, body_half):
    """``_body_centers``' circles: the rear and front ones ``body_half`` behind and ahead
    along the path, in one ``_point_at`` (np.interp's value at a point does not depend
    on the others), the middle one the path point."""
    m = path.shape[0]
    s = np.empty(2 * m)
    for k in range(m):
        s[k], s[m + k] = full[k] - body_half, full[k] + body_half
    ends = _point_at(path, s, full)
    centers = np.empty((3, m, 2))
    for k in range(m):
        centers[0, k, 0], centers[0, k, 1] = ends[k, 0], ends[k, 1]
        centers[1, k, 0], centers[1, k, 1] = path[k, 0], path[k, 1]
        centers[2, k, 0], centers[2, k, 1] = ends[m + k, 0], ends[m + k, 1]
    return centers


@njit(cache=True)
def _below(dx, dy, reach):
    """``np.hypot(dx, dy) < reach``, without the hypot where one leg alone reaches: a
    (faithfully rounded) hypot is never below its longer leg, so the answer is the same."""
    if abs(dx) >= reach or abs(dy) >= reach:
        return False
    return np.hypot(dx, dy) < reach


@njit(cache=True)
def _near(centers, times, xy, vel, dt_obs, length, width, cos_h, sin_h, reach_m, tested):
    """(M, O'): at some time ``times[m, k]`` (row 0 for all m when ``times`` has one
    row) the obstacle's oriented box (``length`` x ``width``), at ``xy`` ``dt_obs`` ago
    and moving at ``vel``, comes within ``reach_m`` of one of the ego's body circles
    ``centers[:, m]``; a column for each of the O' obstacles where ``tested`` is set (a
    column mask, not the caller's copies of every obstacle array).

    A (path point,
    obstacle) pair is skipped when the point is farther than ``reach_m`` plus the box's
    half diagonal from the whole segment the box centre sweeps over those times (a
    lower bound on every tested distance), which most pairs are."""
    n_c, m_pts = centers.shape[0], centers.shape[1]
    n_obs, n_k = xy.shape[0], times.shape[1]
    out = np.zeros((m_pts, tested.sum()), dtype=np.bool_)
    t_min, t_max = np.empty(times.shape[0]), np.empty(times.shape[0])  # each row's time span
    for row in range(times.shape[0]):
        t_lo, t_hi = times[row, 0], times[row, 0]
        for k in range(1, n_k):
            t_lo = min(t_lo, times[row, k])
            t_hi = max(t_hi, times[row, k])
        t_min[row], t_max[row] = t_lo, t_hi
    q = -1  # the output column
    for o in range(n_obs):
        if not tested[o]:
            continue
        q += 1
        half_l, half_w = length[o] / 2, width[o] / 2
        bound = reach_m + np.hypot(half_l, half_w) + 1e-6
        for m in range(m_pts):
            row = m if times.shape[0] > 1 else 0
            t_lo, t_hi = t_min[row] + dt_obs[o], t_max[row] + dt_obs[o]
            ax, ay = xy[o, 0] + vel[o, 0] * t_lo, xy[o, 1] + vel[o, 1] * t_lo
            bx, by = xy[o, 0] + vel[o, 0] * t_hi - ax, xy[o, 1] + vel[o, 1] * t_hi - ay
            len2 = bx * bx + by * by
            far = True
            for c in range(n_c):
                px, py = centers[c, m, 0] - ax, centers[c, m, 1] - ay
                f = 0.0 if len2 <= 0.0 else min(max((px * bx + py * by) / len2, 0.0), 1.0)
                if _below(px - f * bx, py - f * by, bound):
                    far = False
                    break
            if far:
                continue
            for k in range(n_k):
                t = times[row, k] + dt_obs[o]
                ox, oy = xy[o, 0] + vel[o, 0] * t, xy[o, 1] + vel[o, 1] * t
                for c in range(n_c):
                    dx, dy = centers[c, m, 0] - ox, centers[c, m, 1] - oy
                    u = abs(dx * cos_h[o] + dy * sin_h[o]) - half_l  # along the obstacle
                    v = abs(-dx * sin_h[o] + dy * cos_h[o]) - half_w  # across it
                    if _below(max(u, 0.0), max(v, 0.0), reach_m):
                        out[m, q] = True
                        break
                if out[m, q]:
                    break
    return out


@functools.cache
def _time_offsets(window_s: float) -> np.ndarray:
    """The 7 times around a waypoint's arrival time that ``first_conflict`` tests (one
    array for every call, read-only)."""
    out = np.linspace(-window_s, window_s, 7)
    out.setflags(write=False)
    return out


@functools.cache
def _sweep_times(horizon_s: float) -> np.ndarray:
    """(1, T) the times over which ``first_conflict`` sweeps an obstacle's zone (one
    array for every call, read-only)."""
    out = np.arange(0.0, horizon_s + 1e-9, 0.25)[None, :]
    out.setflags(write=False)
    return out


def first_conflict(path: np.ndarray, t_path: np.ndarray, spec: VehicleSpec, obstacles: Obstacles | Sequence[Obstacle],
                   t_now_s: float, cfg: PlannerConfig, s_path: np.ndarray | None = None) -> float | None:
    """Where the vehicle must stop for the moving obstacles, or None.

    An obstacle conflicts when it will come within ``safety_m`` of the vehicle's body
    at some waypoint around the time the vehicle gets there (+-``time_window_s``):
    the vehicle cannot drive the path as planned. It must then wait out of that
    obstacle's whole swept zone: the answer is the first waypoint at which the body
    comes within ``wait_clear_m`` of where any conflicting obstacle passes at any time
    within the horizon. For a crossing that is before the crossing; for an oncoming car
    in the lane the vehicle would pull into to pass a parked truck, it is where the
    vehicle would leave its own lane, so it waits behind the truck until the oncoming
    lane is clear for the whole manoeuvre. A conflict with no such waypoint (a car
    passing in the next lane) needs no stop. A vehicle already inside a zone (it
    learnt of the car only once out in its lane) drives on out of it unless the
    conflict itself falls before it is out: stopping there would wait in the car's way.

    ``s_path``: the path's ``arc_lengths`` if the caller has them.
    """
    if not isinstance(obstacles, Obstacles):
        obstacles = Obstacles.of(obstacles)
    if not len(obstacles) or len(path) < 2:
        return None
    s = arc_lengths(path) if s_path is None else s_path
    within = t_path <= cfg.horizon_s
    if not within.any():
        return None
    path, s, t_path = path[within], s[within], t_path[within]
    xy, vel = obstacles.xy, obstacles.velocity  # (O, 2)
    dt_obs = t_now_s - obstacles.t_sim_s
    length, width = obstacles.length_m, obstacles.width_m
    cos_h, sin_h = np.cos(obstacles.heading_rad), np.sin(obstacles.heading_rad)
    centers, radius = _body_centers(path, spec, s)
    offsets = _time_offsets(cfg.time_window_s)
    when = np.maximum(t_path[:, None] + offsets[None, :], 0.0)  # (M, W) seconds from now
    timed = _near(centers, when, xy, vel, dt_obs, length, width, cos_h, sin_h, radius + cfg.safety_m,
                  np.ones(len(obstacles), dtype=np.bool_))  # (M, O)
    timed[s < 0.5] = False  # where the vehicle already is
    conflicting = timed.any(axis=0)  # (O,)
    if not conflicting.any():
        return None
    sweep_t = _sweep_times(cfg.horizon_s)  # the same times at every waypoint
    zone = _near(centers, sweep_t, xy, vel, dt_obs, length, width, cos_h, sin_h, radius + cfg.wait_clear_m,
                 conflicting)  # (M, O')
    first = zone.any(axis=1)
    if first[0]:
        # already inside the zone (out in the oncoming lane when the car came into view):
        # stopping here waits in its way. Drive on out of this stretch of the zone unless
        # the conflict falls inside it: then there is no clearing it, stop.
        ahead = np.flatnonzero(~first)
        leave = int(ahead[0]) if len(ahead) else len(first)
        if timed[:leave, conflicting].any():
            return float(s[min(1, len(s) - 1)])
        first[:leave] = False
    first[s < 0.5] = False
    return float(s[np.argmax(first)]) if first.any() else None


TICK_S = 0.1  # the decision interval: a plan's acceleration holds for one tick
AT_STOP_M = 0.5  # this close to the stop point the vehicle is there: full brake, hold


def approach_accel(speed_mps: float, stop_at_m: float, cfg: PlannerConfig, max_brake_mps2: float) -> float:
    """The acceleration of a vehicle stopping for a conflict ``stop_at_m`` ahead.

    It brakes at the constant rate that stops it at the stop point, ``v^2 / 2d``, and,
    rolling slower than the speed from which half the comfort braking rate stops it
    there (or standing), drives up to that speed: a vehicle stops where it may wait, not
    wherever it happened to begin braking, so a vehicle that learns of a conflict early
    is not the worse for it (braking at a fixed rate, a left-turning ego that saw the
    oncoming stream early stopped well short of where it could wait, held there, and
    crossed later than one that saw it late). Moving up stays safe: the stop point is
    out of the conflict's swept zone, and from the creep speed half the comfort rate
    stops the vehicle before it.
    """
    if stop_at_m < AT_STOP_M:
        return -max_brake_mps2
    creep_mps = math.sqrt(cfg.comfort_brake_mps2 * stop_at_m)  # sqrt(2 (b / 2) d)
    if speed_mps > creep_mps:
        return -min(speed_mps**2 / (2 * stop_at_m), max_brake_mps2)
    return min(cfg.comfort_accel_mps2, (creep_mps - speed_mps) / TICK_S)


SHARED_HORIZON_S = 8.0  # the shared trajectory covers what others judge relevance over (spatial.HORIZON_S)


def trajectory_of(path: np.ndarray, v0: float, v_cruise: float, accel: float, t_now_s: float,
                  horizon_s: float = SHARED_HORIZON_S, step_s: float = 1.0) -> np.ndarray:
    """Waypoints [x, y, t] every ``step_s`` along ``path``, from ``v0`` towards the cruise
    speed at ``accel``: what the control message shares (``Planner.run_step``)."""
    t = _waypoint_times(horizon_s, step_s)
    if len(path) < 2:  # standing at its one point
        out = np.empty((len(t), 3), dtype=np.float32)
        out[:, :2] = path[:1]
        out[:, 2] = t_now_s + t
        return out
    return _trajectory(np.asarray(path, dtype=np.float64), t, float(v0), float(v_cruise), float(accel),
                       float(t_now_s))


@functools.cache
def _waypoint_times(horizon_s: float, step_s: float) -> np.ndarray:
    """``trajectory_of``'s times from now (one array for every call, read-only)."""
    out = np.arange(0.0, horizon_s + 1e-9, step_s)
    out.setflags(write=False)
    return out


@njit(cache=True)
def _trajectory(path, t, v0, v_cruise, accel, t_now_s):
    """``trajectory_of`` of a path of two or more points, in one pass: each time's
    distance (``_distance_with``, capped at the path's end), its point, the time, as
    float32."""
    cum = _arc_lengths(path)
    s = np.empty(t.shape[0])
    for k in range(t.shape[0]):
        d = _distance_with(v0, v_cruise, accel, t[k])
        s[k] = d if (np.isnan(d) or d < cum[-1]) else cum[-1]  # np.minimum: NaN propagates
    xy = _point_at(path, s, cum)
    out = np.empty((t.shape[0], 3), dtype=np.float32)
    for k in range(t.shape[0]):
        out[k, 0], out[k, 1], out[k, 2] = xy[k, 0], xy[k, 1], t_now_s + t[k]
    return out


@njit(cache=True)
def _distance_with(v0, v_cruise, accel, t):
    if v0 >= v_cruise:
        return v0 * t
    t_acc = (v_cruise - v0) / accel
    if t <= t_acc:
        return v0 * t + 0.5 * accel * t * t
    return (v0 + v_cruise) / 2 * t_acc + v_cruise * (t - t_acc)


def holds_still(mission: Mission) -> bool:
    """Whether the vehicle waits (no cruise speed): its plan is to hold still, whatever it sees."""
    return mission.cruise_speed_mps <= 0.0


@dataclass
class Planner:
    """Path + speed planning for one vehicle; ``run_step`` once per decision interval."""

    mission: Mission
    config: PlannerConfig = field(default_factory=PlannerConfig)
    path_planner: PathPlanner = field(init=False)
    last: Plan | None = None
    _onward_from: tuple[tuple[float, float], float] | None = None  # a path's end and its progress along the route

    def __post_init__(self) -> None:
        self.path_planner = PathPlanner(np.asarray(self.mission.route, dtype=float), self.mission.spec, self.config)

    def intended(self, pose: Pose, speed_mps: float, t_now_s: float) -> np.ndarray:
        """The trajectory to share before the first plan: the route ahead, at the comfort
        acceleration towards the cruise speed."""
        cruise = self.mission.cruise_speed_mps
        here = np.array([[pose.x_m, pose.y_m]])
        return trajectory_of(self._onward(here, cruise), speed_mps, cruise, self.config.comfort_accel_mps2, t_now_s)

    def _onward(self, path: np.ndarray, cruise: float) -> np.ndarray:
        """``path`` continued along the route for as far as the shared horizon reaches at
        the cruise speed (the planned path ends ``lookahead_m`` ahead)."""
        route, cum = self.path_planner.route, self.path_planner.route_cum
        end = (float(path[-1, 0]), float(path[-1, 1]))
        if self._onward_from is None or self._onward_from[0] != end:  # a kept path keeps its end
            self._onward_from = (end, progress_along(route, path[-1], cum))
        s_end = self._onward_from[1]
        extra = min(cruise * SHARED_HORIZON_S, cum[-1] - s_end)
        if extra < 1.0:
            return path
        return np.vstack([path, point_at(route, s_end + np.arange(1.0, extra + 1e-9, 1.0), cum)])

    @property
    def holds_still(self) -> bool:
        """``holds_still`` of the vehicle's mission."""
        return holds_still(self.mission)

    def hold(self, pose: Pose, t_now_s: float) -> Plan:
        """The plan of a vehicle that ``holds_still``: full brake where it is."""
        here = np.array([[pose.x_m, pose.y_m]])
        traj = trajectory_of(here, 0.0, 0.0, self.config.comfort_accel_mps2, t_now_s)
        return Plan(here, -self.mission.spec.max_brake_mps2, traj, None, True)

    def run_step(self, grid: Grid, fused_state: np.ndarray, moving_cells: np.ndarray,
                 obstacles: Obstacles | Sequence[Obstacle], pose: Pose, speed_mps: float, t_now_s: float) -> Plan:
        cfg, spec = self.config, self.mission.spec
        cruise = self.mission.cruise_speed_mps
        if self.holds_still:
            return self.hold(pose, t_now_s)
        # a reused path starts where the vehicle was when it was planned: distances and
        # arrival times count from where the vehicle is now
        planner, here = self.path_planner, np.array([pose.x_m, pose.y_m])
        planned = planner.plan(grid, fused_state, moving_cells, pose, speed_mps)
        path = path_from(planned, here, planner.along(planned), planner.progress(planned, here)) \
            if len(planned) >= 2 else planned
        s = arc_lengths(path)
        t_path = arrival_times(s, speed_mps, cruise, cfg.comfort_accel_mps2)
        if not isinstance(obstacles, Obstacles):
            obstacles = Obstacles.of(obstacles)
        vel = obstacles.velocity
        moving = obstacles.keep(np.hypot(vel[:, 0], vel[:, 1]) > STATIC_MPS)
        moving = Obstacles(moving.xy, moving.velocity, np.maximum(moving.length_m, MOVER_MIN_DIMS_M[0]),
                           np.maximum(moving.width_m, MOVER_MIN_DIMS_M[1]), moving.t_sim_s, moving.heading_rad)
        conflicts = [c for c in (first_conflict(path, t_path, spec, moving, t_now_s, cfg, s),
                                 first_blocked(path, grid, self.path_planner.blocked, s_path=s,
                                               static=self.path_planner.static,
                                               body_radius=int(np.ceil(spec.width_m / 2 / grid.spec.cell_m))))
                     if c is not None]
        conflict = min(conflicts) if conflicts else None
        braking, accel, stop_at = False, cfg.comfort_accel_mps2 * np.sign(cruise - speed_mps), None
        if abs(cruise - speed_mps) < 0.2:
            accel = 0.0
        if conflict is not None:
            stop_at = max(conflict - cfg.stop_buffer_m, 0.0)
            stopping = speed_mps**2 / (2 * cfg.comfort_brake_mps2)
            was_braking = self.last is not None and self.last.braking and self.last.conflict_s_m is not None
            # within stopping distance (plus one tick); once braking for a conflict, keep at it
            if was_braking or stop_at <= stopping + speed_mps * TICK_S + 1.0:
                braking = True
                accel = approach_accel(speed_mps, stop_at, cfg, spec.max_brake_mps2)
        # The shared trajectory is where the vehicle means to go: while it brakes or waits
        # for a conflict, the drive it resumes once the conflict is gone. Senders judge an
        # object's relevance against it; a trajectory that stops short of the conflict made
        # the very object the ego waited for irrelevant, so nobody sent it again, the ego's
        # copy aged out after MAX_AGE_S and it drove on into it (measured: red_light, 20
        # km/h, delta 1 s, autocast crashed where single was safe).
        traj = trajectory_of(self._onward(path, cruise), speed_mps, cruise, cfg.comfort_accel_mps2, t_now_s)
        if stop_at is not None:
            # steer only along the path up to the stop point: pure pursuit looking past it
            # cuts the corner into what we may stop for (measured: an overtaking ego that
            # knew of the oncoming car drifted 0.7 m into its lane before it braked, and the
            # two blocked each other)
            path = path_until(path, s, stop_at + cfg.stop_buffer_m)
        self.last = Plan(path, float(accel), traj, conflict, braking)
        return self.last
