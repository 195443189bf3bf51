"""The agent's per-interval step, one line per stage (CARLA BasicAgent style).

perceive -> control message -> [schedule -> share] -> fuse -> plan -> control. The
bracketed stages need the V2V channel; the process loop (``__main__``) runs them
through the channel proxy, a test can run them through a perfect in-process channel.
Every stage's wall time goes into ``timings_ms[stage]`` and the CPU time its thread
spent into ``timings_ms[stage + "_cpu"]``: with more agent processes than cores the
wall time counts the waits for a core, the CPU time is the stage's own cost.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numba import njit

from protocol.messages import Command, ControlMsg, MapMsg, Mission, Scan
from protocol.model import OURS, Model
from vehicle_agent.control import VehicleController, clip
from vehicle_agent.dataplane import DataPlane, View
from vehicle_agent.fusion import FusedGrid
from vehicle_agent.payload import DATA_STREAM
from vehicle_agent.perception import exact_inverse
from vehicle_agent.planning import STATIC_MPS, Obstacles, Plan, Planner

if TYPE_CHECKING:
    from protocol.session import DropCounter


@dataclass
class Agent:
    mission: Mission
    mapmsg: MapMsg
    model: Model = OURS
    dataplane: DataPlane = field(init=False)
    planner: Planner = field(init=False)
    controller: VehicleController = field(init=False)
    last_plan: Plan | None = None
    timings_ms: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.dataplane = DataPlane(self.mission, self.mapmsg, model=self.model)
        self.planner = Planner(self.mission)
        self.controller = VehicleController(self.mission.spec, self.mission.decision_interval_s)

    # ------------------------------------------------------------------ stages

    def perceive(self, scan: Scan, extra_world: np.ndarray | None = None) -> View:
        self.timings_ms = {}
        with timed(self.timings_ms, "perception"):
            return self.dataplane.perceive(scan, extra_world)

    def control_message(self, view: View, scan: Scan, heard: list[int],
                        unscheduled: Mapping[int, int] | None = None) -> ControlMsg:
        """What this vehicle broadcasts: pose, planned trajectory, object map, and the
        starvation counter of each of its objects."""
        with timed(self.timings_ms, "spatial_reasoning"):
            return self.dataplane.control_message(view, scan, self._trajectory(scan), heard, unscheduled)

    def control_messages(self, view: View, scan: Scan, heard: Mapping[int, list[int]],
                         unscheduled: Mapping[int, Mapping[int, int]], domains: tuple[int, ...]) -> dict[int, ControlMsg]:
        """``control_message`` in each scheduler domain the vehicle takes part in (docs/domains.md)."""
        with timed(self.timings_ms, "spatial_reasoning"):
            return self.dataplane.control_messages(view, scan, self._trajectory(scan), heard, unscheduled, domains)

    def _trajectory(self, scan: Scan) -> np.ndarray:
        traj = self.last_plan.trajectory if self.last_plan is not None else \
            self.planner.intended(scan.pose, scan.speed_mps, scan.t_sim_s)
        return _retimed(traj, scan.t_sim_s)

    def fuse(self, view: View, payloads: list[bytes], drops: DropCounter | None = None) -> FusedGrid:
        """``drops``: where a payload that is not one is counted (on ``DATA_STREAM``)."""
        with timed(self.timings_ms, "fusion"):
            fused, refused = self.dataplane.fuse(view, payloads)
        if drops is not None:
            for err in refused:
                drops.add(DATA_STREAM, err)
        return fused

    def plan(self, view: View, fused: FusedGrid | None, scan: Scan) -> Plan:
        """``fused`` may be None for a vehicle that ``holds_still``: its plan does not read it."""
        with timed(self.timings_ms, "planning"):
            if self.planner.holds_still:  # what it sees changes nothing: no obstacles to gather
                self.last_plan = self.planner.hold(scan.pose, scan.t_sim_s)
                return self.last_plan
            obstacles, moving = self._obstacles(view, fused)
            plan = self.planner.run_step(view.grid, fused.state, moving, obstacles, scan.pose, scan.speed_mps,
                                         scan.t_sim_s)
            self.last_plan = plan
            return plan

    def control(self, plan: Plan, scan: Scan) -> Command:
        with timed(self.timings_ms, "control"):
            steer = 0.0
            if len(plan.path) >= 2:
                _, steer = self.controller.run_step(scan.pose, scan.speed_mps, plan.path, self.mission.cruise_speed_mps)
            accel = clip(plan.accel_mps2, -self.mission.spec.max_brake_mps2, self.mission.spec.max_accel_mps2)
            return Command(scan.tick, scan.t_sim_s, self.mission.vid, accel, steer)

    def drive(self, view: View, fused: FusedGrid, scan: Scan) -> Command:
        """plan -> control."""
        return self.control(self.plan(view, fused, scan), scan)

    # ------------------------------------------------------------------ helpers

    def _obstacles(self, view: View, fused: FusedGrid) -> tuple[Obstacles, np.ndarray]:
        """The moving tracks and received objects as obstacles, and their cells."""
        grid = view.grid
        n = grid.state.shape[0]
        moving = np.zeros((n, n), dtype=bool)
        # what stands still is an obstacle only through the grid: the planner takes moving
        # obstacles alone (Planner.run_step, the same speed test)
        xy, vel, length, width, heading, cells = [], [], [], [], [], []
        tracks = view.tracks
        velocity = np.array([tr.velocity for tr in tracks], dtype=np.float64).reshape(-1, 2)
        speed = np.hypot(velocity[:, 0], velocity[:, 1])  # Track.speed_mps
        for k in np.flatnonzero(speed > STATIC_MPS).tolist():  # the moving few: one step each
            tr = tracks[k]
            det = tr.detection
            xy.append(tr.xy)
            vel.append(tr.velocity)
            length.append(max(det.length_m, 1.0))
            width.append(max(det.width_m, 1.0))
            heading.append(tr.heading_rad)
            cells.append(det.cells)
        if cells:  # every mover's cells at once
            _mark(moving, grid, np.concatenate(cells) * grid.spec.cell_m + grid.spec.cell_m / 2)
        own = Obstacles(np.array(xy, dtype=np.float64).reshape(-1, 2), np.array(vel, dtype=np.float64).reshape(-1, 2),
                        np.array(length, dtype=np.float64), np.array(width, dtype=np.float64),
                        np.full(len(xy), view.t_sim_s), np.array(heading, dtype=np.float64)) if xy else _NO_OBSTACLES
        shared = self.dataplane.shared_batch
        if not len(shared):
            return own, moving
        points = np.ascontiguousarray(shared.points, dtype=np.float64)
        movers, center, length, width = _received_movers(points, shared.counts, shared.velocity, STATIC_MPS, grid.i0,
                                                         grid.j0, grid.spec.cell_m, exact_inverse(grid.spec.cell_m),
                                                         moving)
        if not len(center):
            return own, moving
        vel = shared.velocity[movers]
        received = Obstacles(center, vel, length, width, np.full(len(vel), view.t_sim_s),
                             np.arctan2(vel[:, 1], vel[:, 0]))
        if not len(own):
            return received, moving
        return Obstacles(*(np.concatenate([a, b]) for a, b in zip(own.columns(), received.columns()))), moving


def _no_obstacles() -> Obstacles:
    """No obstacle, read-only arrays (one for every tick a vehicle tracks no mover)."""
    out = Obstacles(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0))
    for column in out.columns():
        column.setflags(write=False)
    return out


_NO_OBSTACLES = _no_obstacles()


class timed:
    """``with timed(timings_ms, stage):`` adds the block's wall time to ``stage`` and its
    thread's CPU time to ``stage_cpu``, in ms (a stage timed twice in a tick counts both;
    an exception records nothing). A class, not a generator context manager: an agent
    times ~18 blocks a tick, and the generator's machinery cost 1.6 us a block."""

    __slots__ = ("timings_ms", "stage", "t0", "c0")

    def __init__(self, timings_ms: dict[str, float], stage: str) -> None:
        self.timings_ms, self.stage = timings_ms, stage

    def __enter__(self) -> None:
        self.t0, self.c0 = time.perf_counter(), time.thread_time()

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            return
        timings_ms, stage = self.timings_ms, self.stage
        cpu_key = stage + "_cpu"
        timings_ms[cpu_key] = timings_ms.get(cpu_key, 0.0) + (time.thread_time() - self.c0) * 1e3
        timings_ms[stage] = timings_ms.get(stage, 0.0) + (time.perf_counter() - self.t0) * 1e3


def _mark(mask: np.ndarray, grid, xy: np.ndarray) -> None:
    """Set the cells of ``mask`` (the grid's) that the points ``xy`` (world, x and y
    first, (m, 2) or (m, 3)) fall in:
    ``grid.cell_of``'s cells, in one pass (its numpy statements took ~0.4 ms per tick
    for the ~10 000 points of the received movers at 40 vehicles)."""
    _mark_cells(np.ascontiguousarray(xy, dtype=np.float64), grid.i0, grid.j0, grid.spec.cell_m,
                exact_inverse(grid.spec.cell_m), mask)


@njit(cache=True)
def _mark_cells(xy, i0, j0, cell, inv, mask):
    """``grid.cell_of`` (floor of x / cell, y / cell, minus the grid's origin) of every
    point (columns 0 and 1 of ``xy``), and its cell set where it lies in the grid;
    ``inv``: ``exact_inverse(cell)``."""
    n = mask.shape[0]
    for p in range(xy.shape[0]):
        if inv > 0.0:
            fx, fy = np.floor(xy[p, 0] * inv), np.floor(xy[p, 1] * inv)
        else:
            fx, fy = np.floor(xy[p, 0] / cell), np.floor(xy[p, 1] / cell)
        if not (abs(fx) < 4e18 and abs(fy) < 4e18):  # NaN, inf, out of int64: outside
            continue
        row, col = np.int64(fy) - j0, np.int64(fx) - i0
        if 0 <= row < n and 0 <= col < n:
            mask[row, col] = True


@njit(cache=True)
def _received_movers(points, counts, velocity, static_mps, i0, j0, cell, inv, mask):
    """The received objects that move (points, and faster than ``static_mps``; object
    k's points follow object k-1's): which they are (K,), and each one's box, as
    the box of its points (its centre (K', 2), its longer and shorter side, at least
    1 m; a NaN coordinate propagates) and their cells marked in ``mask`` (``_mark_cells``):
    one pass over the points, which are cold in the cache (a pass for the boxes and one
    for the cells took twice as long), and none of the dozen small numpy steps in
    between (``tests/test_planning.py`` keeps those as the reference)."""
    n_obj = counts.shape[0]
    movers = np.zeros(n_obj, dtype=np.bool_)
    for k in range(n_obj):
        movers[k] = counts[k] > 0 and np.hypot(velocity[k, 0], velocity[k, 1]) > static_mps
    n = movers.sum()
    center, length, width = np.empty((n, 2)), np.empty(n), np.empty(n)
    start, row = 0, 0
    for k in range(n_obj):
        if movers[k]:
            lo_x = hi_x = points[start, 0]
            lo_y = hi_y = points[start, 1]
            for p in range(start + 1, start + counts[k]):
                x, y = points[p, 0], points[p, 1]
                if x < lo_x or x != x:  # once NaN, stays NaN: no value compares below it
                    lo_x = x
                if x > hi_x or x != x:
                    hi_x = x
                if y < lo_y or y != y:
                    lo_y = y
                if y > hi_y or y != y:
                    hi_y = y
            _mark_cells(points[start:start + counts[k]], i0, j0, cell, inv, mask)
            center[row, 0], center[row, 1] = (lo_x + hi_x) / 2, (lo_y + hi_y) / 2
            ext_x, ext_y = hi_x - lo_x, hi_y - lo_y
            length[row] = _at_least_1(_nan_max(ext_x, ext_y))
            width[row] = _at_least_1(_nan_min(ext_x, ext_y))
            row += 1
        start += counts[k]
    return movers, center, length, width


@njit(cache=True)
def _nan_max(a, b):
    """``np.max`` of (a, b): NaN if either is."""
    if a != a:
        return a
    if b != b:
        return b
    return a if a >= b else b


@njit(cache=True)
def _nan_min(a, b):
    """``np.min`` of (a, b): NaN if either is."""
    if a != a:
        return a
    if b != b:
        return b
    return a if a <= b else b


@njit(cache=True)
def _at_least_1(v):
    """``np.maximum(v, 1.0)``: NaN stays."""
    return v if (v != v or v > 1.0) else 1.0


def _retimed(traj: np.ndarray, t_now_s: float) -> np.ndarray:
    """Last interval's plan from now on: waypoints already passed evicted, first one now."""
    ahead = traj[traj[:, 2] > t_now_s]
    if len(ahead) == 0:
        return traj[-1:].copy()
    return ahead


@dataclass
class LaneFollower:
    """The minimal agent: tracks its route at its cruise speed, blind to everything."""

    mission: Mission
    controller: VehicleController = field(init=False)

    def __post_init__(self) -> None:
        self.controller = VehicleController(self.mission.spec, self.mission.decision_interval_s)

    def run_step(self, scan: Scan) -> Command:
        accel, steer = self.controller.run_step(scan.pose, scan.speed_mps, self.mission.route,
                                                self.mission.cruise_speed_mps)
        return Command(scan.tick, scan.t_sim_s, self.mission.vid, accel, steer)
