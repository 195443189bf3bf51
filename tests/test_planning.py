"""Planning helpers against hand-derived geometry."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numba import njit

from tests.test_paths import numpy_arc_lengths, numpy_point_at
from vehicle_agent.paths import arc_lengths
from vehicle_agent.planning import path_until


def test_a_path_is_cut_at_the_stop_point():
    # 10 m east, then north-east: the cut at 12 m lies 2 m along the diagonal
    path = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 10.0]])
    s = arc_lengths(path)
    np.testing.assert_allclose(path_until(path, s, 5.0), [[0, 0], [5, 0]])
    np.testing.assert_allclose(path_until(path, s, 12.0), [[0, 0], [10, 0], [10 + np.sqrt(2), np.sqrt(2)]])
    # a stop point at the car still leaves a 0.5 m stub to steer along
    np.testing.assert_allclose(path_until(path, s, 0.0), [[0, 0], [0.5, 0]])
    assert path_until(path, s, 100.0) is path


def test_a_braking_vehicle_shares_where_it_means_to_go_not_its_stop():
    """A car crossing 10 m ahead, timed to meet the ego: the ego brakes, and its shared
    trajectory still runs through the crossing (senders judge relevance against it)."""
    from protocol.messages import Pose
    from vehicle_agent.paths import point_at, progress_along
    from vehicle_agent.perception import GROUND, Grid, GridSpec
    from vehicle_agent.planning import Obstacle, Planner
    from world_server.scenarios import ScenarioParams
    from world_server.sim import Simulation

    mission = Simulation(ScenarioParams(scenario="red_light", vehicles=5, delta_s=0.0, seed=0)).mission(0)
    route = np.asarray(mission.route, dtype=float)
    x, y = point_at(route, 5.0)
    ahead = point_at(route, 6.0) - point_at(route, 5.0)
    yaw = float(np.arctan2(ahead[1], ahead[0]))
    speed = 8.0
    cx, cy = point_at(route, 15.0)
    normal = np.array([-np.sin(yaw), np.cos(yaw)])
    crossing = Obstacle(np.array([cx, cy]) + 7.5 * normal, -6.0 * normal, 4.5, 1.8, 0.0,
                        float(np.arctan2(-normal[1], -normal[0])))
    spec = GridSpec()
    n = spec.cells
    i0, j0 = int(np.floor(x / spec.cell_m)) - n // 2, int(np.floor(y / spec.cell_m)) - n // 2
    grid = Grid(spec, i0, j0, np.full((n, n), GROUND, dtype=np.uint8), np.ones((n, n), dtype=bool))
    plan = Planner(mission).run_step(grid, grid.state, np.zeros((n, n), dtype=bool), [crossing], Pose(x, y, yaw),
                                     speed, 0.0)
    assert plan.braking and plan.accel_mps2 < 0 and plan.conflict_s_m is not None
    along = np.array([progress_along(route, p) for p in plan.trajectory[:, :2].astype(float)]) - 5.0
    assert along[0] == pytest.approx(0.0, abs=0.5)
    assert along[-1] > plan.conflict_s_m + 5.0  # past the crossing, not stopped before it


# ------------------------------------------------------------------ first_conflict

SPEC = dict(length_m=4.5, width_m=1.8, height_m=1.5, wheelbase_m=2.7, max_accel_mps2=3.0, max_brake_mps2=8.0,
            max_steer_rad=0.6)


def _straight(n_m: float = 60.0) -> np.ndarray:
    x = np.arange(0.0, n_m + 1e-9, 0.5)
    return np.column_stack([x, np.zeros_like(x)])


def test_a_car_crossing_when_the_ego_gets_there_stops_it_before_its_swept_lane():
    """Ego east along y=0 at 10 m/s; a 4.5 x 1.8 car drives north along x=30 and is at
    the crossing at t=3 s, when the ego is. The ego's body is three circles of radius
    0.9 at -1.35, 0, +1.35 m; it waits 2.0 m clear of the car's swept lane: reach 2.9 m.
    The car's side (its box's x half 0.9) is within reach of the front circle once
    30 - (s + 1.35) - 0.9 < 2.9, i.e. s > 24.85: the first waypoint is 25.0 m."""
    from protocol.messages import VehicleSpec
    from vehicle_agent.planning import Obstacle, PlannerConfig, first_conflict

    path = _straight()
    t_path = arc_lengths(path) / 10.0
    car = Obstacle(np.array([30.0, -30.0]), np.array([0.0, 10.0]), 4.5, 1.8, 0.0, np.pi / 2)
    spec, cfg = VehicleSpec(**SPEC), PlannerConfig()
    assert first_conflict(path, t_path, spec, [car], 0.0, cfg) == pytest.approx(25.0)
    # seen 1 s ago 10 m further back: the same car now
    older = Obstacle(np.array([30.0, -40.0]), np.array([0.0, 10.0]), 4.5, 1.8, -1.0, np.pi / 2)
    assert first_conflict(path, t_path, spec, [older], 0.0, cfg) == pytest.approx(25.0)
    # 5 s later: when the ego is at the crossing (t = 3 +- 1.5 s) the car is 20 m or more short of it
    late = Obstacle(np.array([30.0, -80.0]), np.array([0.0, 10.0]), 4.5, 1.8, 0.0, np.pi / 2)
    assert first_conflict(path, t_path, spec, [late], 0.0, cfg) is None


def _overtaking_path() -> np.ndarray:
    """East along y = -2 (the ego's lane of a 4 m two-lane road), over to y = +2 from
    x = 10 to 14 m to pass a parked truck, back from x = 30 to 34 m."""
    x = np.arange(0.0, 60.0 + 1e-9, 0.5)
    y = np.interp(x, [0.0, 10.0, 14.0, 30.0, 34.0, 60.0], [-2.0, -2.0, 2.0, 2.0, -2.0, -2.0])
    return np.column_stack([x, y])


def test_an_oncoming_car_in_its_own_lane_needs_no_stop_but_one_in_the_way_of_a_pass_does():
    """A car comes west along y = +2 at 8 m/s. An ego keeping its lane (y = -2) passes
    it 4 - 1.8 = 2.2 m apart: within the 2.3 m it plans with, but outside the 2.0 m it
    must wait clear of, so no stop. An ego about to pass a truck in the car's lane must
    wait before its body comes within 2.9 m of y = +2 - 0.9 = 1.1, i.e. before a
    circle's centre reaches y > -1.8. The path bends at x = 10 to y = -2 + (x - 10);
    from the waypoint at s = 9.0 the front circle, 1.35 m further along, is at
    s = 10.35, x = 10 + 0.35 / sqrt(2) = 10.247, y = -1.753: the zone starts there (at
    s = 8.5 the front circle is still on the straight, y = -2)."""
    from protocol.messages import VehicleSpec
    from vehicle_agent.planning import Obstacle, PlannerConfig, first_conflict

    spec, cfg = VehicleSpec(**SPEC), PlannerConfig()
    car = Obstacle(np.array([70.0, 2.0]), np.array([-8.0, 0.0]), 4.5, 1.8, 0.0, np.pi)
    lane = np.column_stack([np.arange(0.0, 60.0 + 1e-9, 0.5), np.full(121, -2.0)])
    assert first_conflict(lane, arc_lengths(lane) / 6.0, spec, [car], 0.0, cfg) is None
    path = _overtaking_path()
    stop = first_conflict(path, arc_lengths(path) / 6.0, spec, [car], 0.0, cfg)
    assert stop == pytest.approx(9.0)
    # the same car 150 m away: by the time it arrives the pass is over, no stop
    far = Obstacle(np.array([150.0, 2.0]), np.array([-8.0, 0.0]), 4.5, 1.8, 0.0, np.pi)
    assert first_conflict(path, arc_lengths(path) / 6.0, spec, [far], 0.0, cfg) is None


def _first_conflict_reference(path, t_path, spec, obstacles, t_now_s, cfg):
    """The dense numpy formulation (every waypoint x time x obstacle), slower: the
    kernel must give the same answer."""
    from vehicle_agent.paths import point_at

    def near(path, pos, half, cos_h, sin_h, clear):
        full = arc_lengths(path)
        body_half = max(spec.length_m - spec.width_m, 0.0) / 2
        radius = spec.width_m / 2
        out = np.zeros(pos.shape[:-1], dtype=bool)
        extra = (None,) * (pos.ndim - 2)
        for shift in (-body_half, 0.0, body_half):
            point = point_at(path, full + shift)
            d = point[(slice(None), *extra)] - pos
            u = np.abs(d[..., 0] * cos_h + d[..., 1] * sin_h) - half[:, 0]
            v = np.abs(-d[..., 0] * sin_h + d[..., 1] * cos_h) - half[:, 1]
            out |= np.hypot(np.maximum(u, 0.0), np.maximum(v, 0.0)) < radius + clear
        return out

    s = arc_lengths(path)
    within = t_path <= cfg.horizon_s
    if not obstacles or not within.any():
        return None
    path, s, t_path = path[within], s[within], t_path[within]
    xy = np.array([o.xy for o in obstacles])
    vel = np.array([o.velocity for o in obstacles])
    dt_obs = np.array([t_now_s - o.t_sim_s for o in obstacles])
    half = np.array([[o.length_m / 2, o.width_m / 2] for o in obstacles])
    cos_h, sin_h = np.cos([o.heading_rad for o in obstacles]), np.sin([o.heading_rad for o in obstacles])
    offsets = np.linspace(-cfg.time_window_s, cfg.time_window_s, 7)
    when = np.maximum(t_path[:, None] + offsets[None, :], 0.0)
    pos = xy[None, None] + vel[None, None] * (when[..., None, None] + dt_obs[None, None, :, None])
    timed = near(path, pos, half, cos_h, sin_h, cfg.safety_m).any(axis=1)
    timed[s < 0.5] = False
    conflicting = timed.any(axis=0)
    if not conflicting.any():
        return None
    sweep_t = np.arange(0.0, cfg.horizon_s + 1e-9, 0.25)
    swept = xy[None] + vel[None] * (sweep_t[:, None, None] + dt_obs[None, :, None])
    zone = near(path, np.broadcast_to(swept, (len(path), *swept.shape)), half, cos_h, sin_h,
                cfg.wait_clear_m).any(axis=1)
    zone = zone[:, conflicting]
    first = zone.any(axis=1)
    if first[0]:  # inside a zone: out of it unless the conflict falls before
        leave = next((i for i in range(len(first)) if not first[i]), len(first))
        if timed[:leave, conflicting].any():
            return float(s[min(1, len(s) - 1)])
        first[:leave] = False
    first[s < 0.5] = False
    return float(s[np.argmax(first)]) if first.any() else None


def test_first_conflict_matches_the_dense_reference_on_random_traffic():
    from protocol.messages import VehicleSpec
    from vehicle_agent.planning import Obstacle, PlannerConfig, first_conflict

    rng = np.random.default_rng(7)
    spec, cfg = VehicleSpec(**SPEC), PlannerConfig()
    found = 0
    for _ in range(200):
        # a curving path, 40-80 m, waypoints ~0.5 m apart
        n = int(rng.integers(80, 160))
        heading = np.cumsum(rng.normal(0.0, 0.03, n))
        path = np.cumsum(np.column_stack([np.cos(heading), np.sin(heading)]) * 0.5, axis=0)
        v0 = float(rng.uniform(0.0, 12.0))
        t_path = arc_lengths(path) / max(v0, 2.0)
        obstacles = []
        for _ in range(int(rng.integers(1, 40))):
            xy = path[rng.integers(0, n)] + rng.normal(0.0, 25.0, 2)
            vel = rng.normal(0.0, 6.0, 2) * (rng.random() < 0.8)
            obstacles.append(Obstacle(xy, vel, float(rng.uniform(1.0, 5.0)), float(rng.uniform(1.0, 2.0)),
                                      float(-rng.uniform(0.0, 1.0)), float(rng.uniform(-np.pi, np.pi))))
        got = first_conflict(path, t_path, spec, obstacles, 0.0, cfg)
        want = _first_conflict_reference(path, t_path, spec, obstacles, 0.0, cfg)
        assert got == want
        found += want is not None
    assert 40 < found < 190  # both answers are exercised


def test_smoothing_keeps_clear_of_the_obstacle_margin_the_grid_path_avoided():
    """A grid path that steps round a blocked block at a right angle: the moving average
    would cut the corner into the block; the kept path does not touch a blocked cell."""
    from vehicle_agent.perception import Grid, GridSpec
    from vehicle_agent.planning import _smooth, _smooth_clear

    spec = GridSpec(half_extent_m=10.0)
    n = spec.cells
    grid = Grid(spec, -n // 2, -n // 2, np.zeros((n, n), np.uint8), np.ones((n, n), bool))
    blocked = np.zeros((n, n), bool)
    rows, cols = grid.cell_of(np.array([[0.25, 0.25]]))[0]
    blocked[rows - 8:rows, cols:cols + 8] = True  # x in [0, 4), y in [-4, 0)
    # north along the block's west side (cell centres x = -0.25), then east along its north side (y = 0.25)
    path = np.vstack([np.column_stack([np.full(10, -0.25), np.arange(-4.75, 0.0, 0.5)]),
                      np.column_stack([np.arange(-0.25, 4.5, 0.5), np.full(10, 0.25)])])
    rc = grid.cell_of(_smooth(path))
    assert blocked[rc[:, 0], rc[:, 1]].any()  # the plain average cuts into the block
    kept = _smooth_clear(path, grid, blocked)
    s = np.linspace(0.0, 1.0, 400)
    seg = np.diff(kept, axis=0)
    pts = (kept[:-1, None, :] + s[None, :, None] * seg[:, None, :]).reshape(-1, 2)
    rc = grid.cell_of(pts)
    assert not blocked[rc[:, 0], rc[:, 1]].any()


def test_a_reused_path_is_measured_from_where_the_vehicle_is_now():
    from vehicle_agent.planning import path_from

    path = _straight(20.0)
    rest = path_from(path, np.array([7.3, 0.4]))
    assert rest[0].tolist() == [7.3, 0.4] and rest[1].tolist() == [7.5, 0.0]
    assert arc_lengths(rest)[-1] == pytest.approx(np.hypot(0.2, 0.4) + 12.5)
    assert path_from(path, np.array([25.0, 0.0])).tolist() == [[25.0, 0.0], [20.0, 0.0]]


def test_an_ego_already_out_in_the_oncoming_lane_drives_on_unless_the_car_is_upon_it():
    """The pass of ``_overtaking_path`` seen from x = 16, out in the oncoming lane (y = +2)
    until x = 30, back in its lane (y = -2) from x = 34. A car coming west along y = +2
    at 8 m/s from x = 102: the ego, at 6 m/s, is back in its lane at x = 50 at 5.94 s
    (s = 14 + 4 sqrt(2) + 16), when the car is at 54.5 m, 3.1 m across (< 0.9 + 2.3):
    a conflict, but outside the zone it waits out of (0.9 + 2.0). On the pass (until
    3.3 s, +1.5 s) the car is beyond x = 63: drive on, nothing to stop for. From x = 70
    the car is at x = 31.8 at 3.28 + 1.5 s, on the ramp back: upon the ego while it is
    still out there, stop at once (the first waypoint, 0.5 m)."""
    from protocol.messages import VehicleSpec
    from vehicle_agent.planning import Obstacle, PlannerConfig, first_conflict

    spec, cfg = VehicleSpec(**SPEC), PlannerConfig(horizon_s=30.0)
    path = _overtaking_path()[32:]  # from x = 16
    t_path = arc_lengths(path) / 6.0
    far = Obstacle(np.array([102.0, 2.0]), np.array([-8.0, 0.0]), 4.5, 1.8, 0.0, np.pi)
    near = Obstacle(np.array([70.0, 2.0]), np.array([-8.0, 0.0]), 4.5, 1.8, 0.0, np.pi)
    assert first_conflict(path, t_path, spec, [far], 0.0, cfg) is None
    assert first_conflict(path, t_path, spec, [near], 0.0, cfg) == pytest.approx(0.5)


# ------------------------------------------------------------------ kernels against the numpy they replace


def test_cell_values_are_cell_of_and_the_lookup():
    """``_cell_value``: 1 / 0 for a point in a set / unset cell, -1 outside, as
    ``Grid.cell_of`` with the inside test and the lookup; NaN and inf fall outside."""
    from vehicle_agent.perception import Grid, GridSpec
    from vehicle_agent.planning import _cell_value

    rng = np.random.default_rng(3)
    spec = GridSpec(half_extent_m=10.0)
    n = spec.cells
    grid = Grid(spec, 17, -63, np.zeros((n, n), np.uint8), np.ones((n, n), bool))
    mask = rng.random((n, n)) < 0.3
    xy = np.column_stack([rng.uniform(5.0, 20.0, 4000), rng.uniform(-35.0, -18.0, 4000)])  # the grid and around
    xy[:4] = [[np.nan, -25.0], [np.inf, -25.0], [10.0, -np.inf], [1e300, 1e300]]
    rc = grid.cell_of(xy[4:])
    inside = (rc[:, 0] >= 0) & (rc[:, 0] < n) & (rc[:, 1] >= 0) & (rc[:, 1] < n)
    want = np.full(len(rc), -1)
    want[inside] = mask[rc[inside, 0], rc[inside, 1]]
    got = np.array([_cell_value(mask, x, y, grid.i0, grid.j0, spec.cell_m) for x, y in xy.tolist()])
    assert got[:4].tolist() == [-1, -1, -1, -1]
    assert got[4:].tolist() == want.tolist()
    assert {-1, 0, 1} <= set(got.tolist())


def test_blocked_and_passable_in_one_kernel_are_the_inflation_and_the_masks():
    from vehicle_agent.planning import _blocked_passable, _inflate

    rng = np.random.default_rng(5)
    static = rng.random((60, 70)) < 0.02
    drivable, corridor = rng.random((60, 70)) < 0.8, rng.random((60, 70)) < 0.7
    blocked, passable = _blocked_passable(static, drivable, corridor, 3)
    assert np.array_equal(blocked, _inflate(static, 3))
    assert np.array_equal(passable, drivable & ~_inflate(static, 3) & corridor)
    assert passable.any() and (drivable & corridor & ~passable).any()


def test_one_leg_rejects_exactly_where_the_hypot_would():
    """``_below(dx, dy, r)`` is ``np.hypot(dx, dy) < r``, at and around the boundary."""
    from vehicle_agent.planning import _below

    rng = np.random.default_rng(11)
    r = 3.2
    legs = np.concatenate([rng.uniform(-5.0, 5.0, 3000), [0.0, -0.0, r, -r, np.nextafter(r, 0.0), np.nan, np.inf],
                           r * rng.uniform(0.999999, 1.000001, 500)])
    dx, dy = rng.choice(legs, 20000), rng.choice(legs, 20000)
    want = np.hypot(dx, dy) < r
    got = np.array([_below(a, b, r) for a, b in zip(dx.tolist(), dy.tolist())])
    assert np.array_equal(got, want) and want.any() and not want.all()


def numpy_received_movers(points, counts, velocity, static_mps, i0, j0, cell, inv, mask):
    """What ``Agent._obstacles`` did for the received movers before ``_received_movers``:
    the movers' points gathered, their boxes by ``np.minimum/maximum.reduceat`` (as the
    ``_boxes`` kernel it had, a NaN coordinate propagating), their cells by ``_mark_cells``."""
    from vehicle_agent.agent import _mark_cells

    movers = (counts > 0) & (np.hypot(velocity[:, 0], velocity[:, 1]) > static_mps)
    if not movers.any():
        return movers, np.zeros((0, 2)), np.zeros(0), np.zeros(0)
    gathered = points[np.repeat(movers, counts)]
    run_starts = np.cumsum(counts[movers]) - counts[movers]
    lo = np.minimum.reduceat(gathered[:, :2], run_starts, axis=0)
    hi = np.maximum.reduceat(gathered[:, :2], run_starts, axis=0)
    center, extent = (lo + hi) / 2, hi - lo
    _mark_cells(np.ascontiguousarray(gathered), i0, j0, cell, inv, mask)
    return movers, center, np.maximum(extent.max(axis=1), 1.0), np.maximum(extent.min(axis=1), 1.0)


def test_a_received_mover_by_hand():
    """Two objects: a parked one (no box) and a car-sized mover of three points."""
    from vehicle_agent.agent import _received_movers

    points = np.array([[0.2, 0.2, 1.0], [10.1, 3.1, 1.0], [14.1, 3.4, 1.0], [12.0, 4.6, 0.5]])
    counts, velocity = np.array([1, 3]), np.array([[0.3, 0.3], [5.0, 0.0]])  # 0.42 m/s: not moving
    mask = np.zeros((40, 40), dtype=bool)  # square, as the grid
    movers, center, length, width = _received_movers(points, counts, velocity, 0.5, 0, 0, 0.5, 2.0, mask)
    assert movers.tolist() == [False, True]
    np.testing.assert_allclose(center, [[12.1, 3.85]])
    np.testing.assert_allclose(length, [4.0])
    np.testing.assert_allclose(width, [1.5])
    assert sorted(zip(*np.nonzero(mask))) == [(6, 20), (6, 28), (9, 24)]  # rows y / 0.5, columns x / 0.5


@settings(max_examples=300, deadline=None)
@given(st.lists(st.integers(0, 12), max_size=12), st.data())
def test_received_movers_match_the_numpy_steps_to_the_bit(counts, data):
    from vehicle_agent.agent import _received_movers

    counts = np.array(counts, dtype=np.int64)
    coord = st.one_of(st.floats(-30.0, 30.0), st.just(np.nan))
    points = np.array(data.draw(st.lists(st.tuples(coord, coord, st.floats(0, 2)), min_size=int(counts.sum()),
                                         max_size=int(counts.sum()))), dtype=np.float64).reshape(-1, 3)
    speed = st.one_of(st.floats(-3.0, 3.0), st.sampled_from([0.5, -0.5, 0.0]))
    velocity = np.array(data.draw(st.lists(st.tuples(speed, speed), min_size=len(counts), max_size=len(counts))),
                        dtype=np.float64).reshape(-1, 2)
    got_mask, want_mask = np.zeros((60, 60), dtype=bool), np.zeros((60, 60), dtype=bool)
    got = _received_movers(points, counts, velocity, 0.5, -30, -30, 1.0, 1.0, got_mask)
    want = numpy_received_movers(points, counts, velocity, 0.5, -30, -30, 1.0, 1.0, want_mask)
    for g, w in zip(got, want):
        assert g.dtype == w.dtype and g.shape == w.shape and g.tobytes() == w.tobytes()
    assert np.array_equal(got_mask, want_mask)


def test_inflation_is_every_cell_within_the_radius_of_an_obstacle_cell():
    """``_inflate`` against the disc's offsets one by one (shifted copies OR-ed)."""
    from vehicle_agent.planning import _inflate

    rng = np.random.default_rng(9)
    for radius in (0, 1, 2, 3, 5):
        obst = rng.random((40, 53)) < 0.03
        obst[0, 0] = obst[-1, 20] = obst[17, -1] = True  # at the edges
        want = np.zeros_like(obst)
        ny, nx = obst.shape
        for dy in range(-radius, radius + 1):
            for dx in range(-radius, radius + 1):
                if dx * dx + dy * dy <= radius * radius:
                    want[max(dy, 0):ny + min(dy, 0), max(dx, 0):nx + min(dx, 0)] |= \
                        obst[max(-dy, 0):ny + min(-dy, 0), max(-dx, 0):nx + min(-dx, 0)]
        assert np.array_equal(_inflate(obst, radius), want), radius


# ------------------------------------------------------------------ kernels against the numpy they replaced


def numpy_trajectory_of(path, v0, v_cruise, accel, t_now_s, horizon_s=8.0, step_s=1.0):
    """``trajectory_of`` as it was in numpy (the reference for its kernel)."""
    def distance_with(t):
        if v0 >= v_cruise:
            return v0 * t
        t_acc = (v_cruise - v0) / accel
        if t <= t_acc:
            return v0 * t + 0.5 * accel * t * t
        return (v0 + v_cruise) / 2 * t_acc + v_cruise * (t - t_acc)

    t = np.arange(0.0, horizon_s + 1e-9, step_s)
    if len(path) < 2:
        return np.column_stack([np.repeat(path[:1], len(t), axis=0), t_now_s + t]).astype(np.float32)
    s = np.array([distance_with(x) for x in t])
    cum = numpy_arc_lengths(path)
    s = np.minimum(s, cum[-1])
    return np.column_stack([numpy_point_at(path, s, cum), t_now_s + t]).astype(np.float32)


def test_the_shared_trajectory_by_hand():
    from vehicle_agent.planning import trajectory_of

    # from rest at 2 m/s^2 towards 4 m/s: 1 m after 1 s, 4 m after 2 s, then 4 m/s; the path ends at 10 m
    path = np.array([[0.0, 0.0], [10.0, 0.0]])
    traj = trajectory_of(path, 0.0, 4.0, 2.0, 100.0, horizon_s=4.0)
    np.testing.assert_array_equal(traj, np.array([[0, 0, 100], [1, 0, 101], [4, 0, 102], [8, 0, 103], [10, 0, 104]],
                                                 dtype=np.float32))
    standing = trajectory_of(np.array([[3.0, 4.0]]), 0.0, 0.0, 2.0, 7.5)
    assert standing.dtype == np.float32 and standing.shape == (9, 3)
    np.testing.assert_array_equal(standing[:, :2], np.tile([3.0, 4.0], (9, 1)))
    np.testing.assert_array_equal(standing[:, 2], 7.5 + np.arange(9.0))


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.floats(-500, 500), st.floats(-500, 500)), min_size=1, max_size=40),
       st.floats(0.0, 20.0), st.floats(0.0, 20.0), st.sampled_from([2.0, 4.0, 0.7]), st.floats(0.0, 1e4),
       st.sampled_from([8.0, 3.0]), st.sampled_from([1.0, 0.5]))
def test_the_trajectory_kernel_matches_the_numpy_version_to_the_bit(points, v0, v_cruise, accel, t_now_s, horizon_s,
                                                                     step_s):
    from vehicle_agent.planning import trajectory_of

    path = np.array(points, dtype=np.float64)
    got = trajectory_of(path, v0, v_cruise, accel, t_now_s, horizon_s, step_s)
    want = numpy_trajectory_of(path, v0, v_cruise, accel, t_now_s, horizon_s, step_s)
    assert got.dtype == want.dtype and got.tobytes() == want.tobytes()


def test_the_static_cells_mask_in_the_kernel_is_the_numpy_one():
    """``_static_blocked_passable`` is ``_blocked_passable`` of ``(state == ABOVE) &
    drivable & ~moving``: a hand-made grid, then random ones."""
    from vehicle_agent.perception import ABOVE, GROUND
    from vehicle_agent.planning import _blocked_passable, _static_blocked_passable

    state = np.full((9, 9), GROUND, dtype=np.uint8)
    state[4, 4] = state[0, 8] = state[8, 0] = ABOVE
    drivable, moving, corridor = np.ones((9, 9), bool), np.zeros((9, 9), bool), np.ones((9, 9), bool)
    drivable[0, 8] = False  # off the road: no obstacle to the planner
    moving[8, 0] = True  # a mover's cell: the speed planner's business
    blocked, passable = _static_blocked_passable(state, drivable, moving, corridor, 1, ABOVE)
    want = np.zeros((9, 9), bool)
    want[3:6, 4] = want[4, 3:6] = True  # the radius-1 disc round (4, 4)
    assert np.array_equal(blocked, want) and np.array_equal(passable, drivable & ~want)
    rng = np.random.default_rng(3)
    for _ in range(20):
        state = rng.integers(0, 4, (50, 61)).astype(np.uint8)
        drivable, moving, corridor = rng.random((3, 50, 61)) < [[[0.8]], [[0.1]], [[0.7]]]
        drivable.setflags(write=False)  # as the grid's
        got = _static_blocked_passable(state, drivable, moving, corridor, 3, ABOVE)
        want = _blocked_passable((state == ABOVE) & drivable & ~moving, drivable, corridor, 3)
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])


# ------------------------------------------------------------------ A* against the kernel it replaced

REF_DY = np.array([0, 1, 1, 1, 0, -1, -1, -1])
REF_DX = np.array([1, 1, 0, -1, -1, -1, 0, 1])


@njit  # not cached: a test module is imported under more than one name
def reference_astar(passable, extra, start_r, start_c, start_dir, goal_r, goal_c, turn_cost):
    """``planning._astar`` as it was before its states were closed by cost (the reference)."""
    ny, nx = passable.shape
    n_states = ny * nx * 8
    g = np.full(n_states, np.inf)
    parent = np.full(n_states, -1, dtype=np.int64)
    closed = np.zeros(n_states, dtype=np.bool_)
    capacity = 4 * n_states  # lazy deletion pushes a state once per improvement (at most its in-degree, 5)
    heap_f = np.empty(capacity)
    heap_s = np.empty(capacity, dtype=np.int64)
    size = 0
    s0 = (start_r * nx + start_c) * 8 + start_dir
    g[s0] = 0.0
    heap_f[0] = 0.0
    heap_s[0] = s0
    size = 1
    goal_state = -1
    while size > 0:
        f, s = heap_f[0], heap_s[0]
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
        if closed[s]:
            continue
        closed[s] = True
        cell, d = s // 8, s % 8
        r, cc = cell // nx, cell % nx
        if r == goal_r and cc == goal_c:
            goal_state = s
            break
        for nd in range(8):
            turn = abs(nd - d)
            turn = min(turn, 8 - turn)
            if turn > 2:  # no more than 90 degrees in one cell
                continue
            rr, c2 = r + REF_DY[nd], cc + REF_DX[nd]
            if rr < 0 or rr >= ny or c2 < 0 or c2 >= nx or not passable[rr, c2]:
                continue
            step = 1.4142135 if nd % 2 == 1 else 1.0
            ns = (rr * nx + c2) * 8 + nd
            cost = g[s] + step * (1.0 + extra[rr, c2]) + turn_cost * turn
            if cost < g[ns] and not closed[ns]:
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



def test_astar_by_hand():
    """A wall with one gap: the path goes through it, heading east first."""
    from vehicle_agent.planning import _astar

    passable = np.ones((7, 9), dtype=bool)
    passable[:, 4] = False
    passable[5, 4] = True
    cells = _astar(passable, np.zeros((7, 9)), 1, 0, 0, 1, 8, 0.05)
    assert cells[0].tolist() == [1, 0] and cells[-1].tolist() == [1, 8] and [5, 4] in cells.tolist()
    assert passable[cells[:, 0], cells[:, 1]].all()
    assert (np.abs(np.diff(cells, axis=0)).max(axis=1) == 1).all()  # one 8-connected step at a time
    passable[5, 4] = False
    assert _astar(passable, np.zeros((7, 9)), 1, 0, 0, 1, 8, 0.05).shape == (0, 2)


@settings(max_examples=200, deadline=None)
@given(st.integers(3, 40), st.integers(3, 40), st.floats(0.0, 0.45), st.integers(0, 2**32 - 1),
       st.sampled_from([0.05, 0.5, 0.0]), st.booleans())
def test_astar_matches_the_reference_kernel(ny, nx, density, seed, turn_cost, flat):
    from vehicle_agent.planning import _astar

    rng = np.random.default_rng(seed)
    passable = rng.random((ny, nx)) >= density
    extra = np.zeros((ny, nx)) if flat else 0.4 * rng.integers(0, 12, (ny, nx)) * 0.5  # ties, as on the grid
    (sr, sc), (gr, gc) = rng.integers(0, [ny, nx]), rng.integers(0, [ny, nx])
    passable[sr, sc] = True
    d = int(rng.integers(0, 8))
    got = _astar(passable, extra, sr, sc, d, gr, gc, turn_cost)
    want = reference_astar(passable, extra, sr, sc, d, gr, gc, turn_cost)
    assert got.shape == want.shape and np.array_equal(got, want)


def numpy_snap_to_route(path, route, cell_m):
    """``planning._snap_to_route`` as it was in numpy (the reference for its kernel)."""
    a, ab = route[:-1], np.diff(route, axis=0)
    len2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12)
    t = np.clip(np.einsum("pij,ij->pi", path[:, None, :] - a[None], ab) / len2, 0.0, 1.0)  # (P, S)
    foot = a[None] + t[..., None] * ab[None]  # (P, S, 2)
    dist = np.linalg.norm(foot - path[:, None, :], axis=2)
    best = np.argmin(dist, axis=1)
    nearest = foot[np.arange(len(path)), best]
    close = dist[np.arange(len(path)), best] <= cell_m * 0.75
    out = path.copy()
    out[close] = nearest[close]
    return out


def test_a_grid_path_snaps_onto_the_route_within_three_quarters_of_a_cell():
    from vehicle_agent.planning import _snap_to_route

    route = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])
    path = np.array([[1.25, 0.25], [5.0, -0.25], [9.75, 5.25], [6.0, 2.0], [12.0, 12.0]])
    want = np.array([[1.25, 0.0], [5.0, 0.0], [10.0, 5.25], [6.0, 2.0], [12.0, 12.0]])  # the last two: too far
    np.testing.assert_array_equal(_snap_to_route(path, route, 0.5), want)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.floats(-50, 50), st.floats(-50, 50)), min_size=2, max_size=25),
       st.lists(st.tuples(st.floats(-50, 50), st.floats(-50, 50)), max_size=30), st.sampled_from([0.5, 4.0, 30.0]),
       st.booleans())
def test_snapping_matches_the_numpy_version_to_the_bit(route, path, cell_m, on_cells):
    from vehicle_agent.planning import _snap_to_route

    route, path = np.array(route, dtype=np.float64), np.array(path, dtype=np.float64).reshape(-1, 2)
    if on_cells:  # grid cell centres, some of them near the route (ties between segments at its vertices)
        path = (np.floor(np.concatenate([path, route]) / 0.5) + 0.5) * 0.5
    route.setflags(write=False)  # as the mission's
    got, want = _snap_to_route(path, route, cell_m), numpy_snap_to_route(path, route, cell_m)
    assert got.tobytes() == want.tobytes()


# ------------------------------------------------------------------ the conflict test against the code it replaced

def reference_body_centers(path, spec, full):
    """``planning._body_centers`` as it was in numpy (the reference)."""
    body_half = max(spec.length_m - spec.width_m, 0.0) / 2
    m = len(path)
    centers = np.empty((3, m, 2))
    # rear and front in one point_at (np.interp's value at a point does not depend on the others)
    centers[0::2] = numpy_point_at(path, np.concatenate([full - body_half, full + body_half]), full).reshape(2, m, 2)
    centers[1] = path
    return centers, float(spec.width_m / 2)


@njit  # not cached: a test module is imported under more than one name
def reference_below(dx, dy, reach):
    """``np.hypot(dx, dy) < reach``, without the hypot where one leg alone reaches: a
    (faithfully rounded) hypot is never below its longer leg, so the answer is the same."""
    if abs(dx) >= reach or abs(dy) >= reach:
        return False
    return np.hypot(dx, dy) < reach


@njit  # not cached: a test module is imported under more than one name
def reference_near(centers, times, xy, vel, dt_obs, half, cos_h, sin_h, reach_m):
    """``planning._near`` before its column mask (the reference). (M, O): at some time ``times[m, k]`` (row 0 for all m when ``times`` has one
    row) the obstacle's oriented box, at ``xy`` ``dt_obs`` ago and moving at ``vel``,
    comes within ``reach_m`` of one of the ego's body circles ``centers[:, m]``.

    A (path point,
    obstacle) pair is skipped when the point is farther than ``reach_m`` plus the box's
    half diagonal from the whole segment the box centre sweeps over those times (a
    lower bound on every tested distance), which most pairs are."""
    n_c, m_pts = centers.shape[0], centers.shape[1]
    n_obs, n_k = xy.shape[0], times.shape[1]
    out = np.zeros((m_pts, n_obs), dtype=np.bool_)
    t_min, t_max = np.empty(times.shape[0]), np.empty(times.shape[0])  # each row's time span
    for row in range(times.shape[0]):
        t_lo, t_hi = times[row, 0], times[row, 0]
        for k in range(1, n_k):
            t_lo = min(t_lo, times[row, k])
            t_hi = max(t_hi, times[row, k])
        t_min[row], t_max[row] = t_lo, t_hi
    for o in range(n_obs):
        bound = reach_m + np.hypot(half[o, 0], half[o, 1]) + 1e-6
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
                if reference_below(px - f * bx, py - f * by, bound):
                    far = False
                    break
            if far:
                continue
            for k in range(n_k):
                t = times[row, k] + dt_obs[o]
                ox, oy = xy[o, 0] + vel[o, 0] * t, xy[o, 1] + vel[o, 1] * t
                for c in range(n_c):
                    dx, dy = centers[c, m, 0] - ox, centers[c, m, 1] - oy
                    u = abs(dx * cos_h[o] + dy * sin_h[o]) - half[o, 0]  # along the obstacle
                    v = abs(-dx * sin_h[o] + dy * cos_h[o]) - half[o, 1]  # across it
                    if reference_below(max(u, 0.0), max(v, 0.0), reach_m):
                        out[m, o] = True
                        break
                if out[m, o]:
                    break
    return out


def reference_first_conflict(path, t_path, spec, obstacles, t_now_s, cfg, s_path=None):
    """``planning.first_conflict`` before ``_near`` took a column mask and the boxes'
    sides and ``_body_centers`` became a kernel (the reference)."""
    from vehicle_agent.planning import _sweep_times, _time_offsets

    if not len(obstacles) or len(path) < 2:
        return None
    s = numpy_arc_lengths(path) if s_path is None else s_path
    within = t_path <= cfg.horizon_s
    if not within.any():
        return None
    path, s, t_path = path[within], s[within], t_path[within]
    xy, vel = obstacles.xy, obstacles.velocity  # (O, 2)
    dt_obs = t_now_s - obstacles.t_sim_s
    half = np.column_stack([obstacles.length_m / 2, obstacles.width_m / 2])  # (O, 2)
    cos_h, sin_h = np.cos(obstacles.heading_rad), np.sin(obstacles.heading_rad)
    centers, radius = reference_body_centers(path, spec, s)
    offsets = _time_offsets(cfg.time_window_s)
    when = np.maximum(t_path[:, None] + offsets[None, :], 0.0)  # (M, W) seconds from now
    timed = reference_near(centers, when, xy, vel, dt_obs, half, cos_h, sin_h, radius + cfg.safety_m)  # (M, O)
    timed[s < 0.5] = False  # where the vehicle already is
    conflicting = timed.any(axis=0)  # (O,)
    if not conflicting.any():
        return None
    c = conflicting
    sweep_t = _sweep_times(cfg.horizon_s)  # the same times at every waypoint
    zone = reference_near(centers, sweep_t, xy[c], vel[c], dt_obs[c], half[c], cos_h[c], sin_h[c],
                          radius + cfg.wait_clear_m)  # (M, O')
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


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 12), st.floats(0.0, 15.0), st.booleans())
def test_first_conflict_matches_the_previous_kernels(seed, n_obs, speed, curved):
    """Random traffic round a straight or curved path: the same stop (or none) to the
    bit as the previous ``_near`` on the caller's copies and the numpy body circles."""
    from protocol.messages import VehicleSpec
    from vehicle_agent.planning import Obstacles, PlannerConfig, first_conflict

    rng = np.random.default_rng(seed)
    x = np.arange(0.0, 60.0, 0.5 + rng.random())
    path = np.column_stack([x, 0.02 * x**2 if curved else np.zeros_like(x)])
    t_path = arc_lengths(path) / max(speed, 1.0)
    xy = rng.uniform([-5.0, -30.0], [65.0, 30.0], (n_obs, 2))
    vel = rng.normal(0.0, 6.0, (n_obs, 2)) * (rng.random((n_obs, 1)) < 0.8)
    obstacles = Obstacles(xy, vel, np.maximum(rng.uniform(0.5, 12.0, n_obs), 4.0),
                          np.maximum(rng.uniform(0.5, 3.0, n_obs), 1.8), rng.uniform(-0.3, 0.0, n_obs),
                          np.arctan2(vel[:, 1], vel[:, 0]))
    spec = VehicleSpec(**SPEC)
    cfg = PlannerConfig()
    got = first_conflict(path, t_path, spec, obstacles, 0.0, cfg)
    want = reference_first_conflict(path, t_path, spec, obstacles, 0.0, cfg)
    assert got == want or (got is None and want is None)


def numpy_first_along(mask, value, path, s, cum, grid):
    """What the fast check and ``first_blocked`` did before ``_first_along``: every
    point's cell value, then the first that is ``value`` (the reference)."""
    values = np.array([[-1, 0, 1][1 + int(mask[r, c])] if 0 <= r < mask.shape[0] and 0 <= c < mask.shape[1] else -1
                       for r, c in grid.cell_of(numpy_point_at(path, s, cum)).tolist()], dtype=np.int64).reshape(-1)
    hit = np.flatnonzero(values == value)
    return int(hit[0]) if len(hit) else -1


def test_the_first_blocked_cell_along_a_path_by_hand():
    from vehicle_agent.perception import Grid, GridSpec
    from vehicle_agent.planning import first_blocked

    spec = GridSpec(half_extent_m=5.0)  # 20 x 20 cells of 0.5 m from (0, 0)
    grid = Grid(spec, 0, 0, np.zeros((20, 20), np.uint8), np.ones((20, 20), bool))
    blocked = np.zeros((20, 20), dtype=bool)
    blocked[2, 12] = True  # x 6-6.5 m, y 1-1.5 m
    path = np.array([[0.0, 1.2], [9.0, 1.2]])
    assert first_blocked(path, grid, blocked) == 6.0
    assert first_blocked(path + [0.0, 1.0], grid, blocked) is None


def test_a_vehicle_inside_an_obstacle_margin_may_drive_on_out_of_it_by_hand():
    """The overtaking deadlock (40 vehicles, seed 9): the ego, trailing its pass path
    along the edge of the parked truck's inflated cells, stood inside them; the first
    point of its path, 0.5 m on, was "blocked" and it stopped there for good. By hand,
    on 0.5 m cells from (0, 0): a "truck side" in row 2 (y 1.0-1.5 m), columns 4-12
    (x 2.0-6.5 m). A 1.8 m wide car: blocked = within ceil((0.9 + 0.3) / 0.5) = 3 cells
    of it, so rows 3-5 right above it (row 5 = y 2.5-3.0 m, only in columns 4-12: at
    dy = 3 the disc is one cell wide); the body reaches ceil(0.9 / 0.5) = 2 cells, rows
    3-4 (y 1.5-2.5 m)."""
    from vehicle_agent.perception import ABOVE, Grid, GridSpec
    from vehicle_agent.planning import _blocked_passable, first_blocked

    spec = GridSpec(half_extent_m=5.0)  # 20 x 20 cells of 0.5 m from (0, 0)
    state = np.zeros((20, 20), np.uint8)
    state[2, 4:13] = ABOVE
    drivable, moving = np.ones((20, 20), bool), np.zeros((20, 20), bool)
    grid = Grid(spec, 0, 0, state, drivable)
    blocked, _ = _blocked_passable(state == ABOVE, drivable, np.ones((20, 20), bool), 3)
    assert blocked[5, 4:13].all() and not blocked[5, 3] and not blocked[5, 13] and not blocked[6].any()
    static = (state, drivable, moving)

    # alongside the truck at y = 2.9 m (row 5: in the margin, 1.4 m from its cells' centres)
    beside = np.array([[3.0, 2.9], [9.0, 2.9]])
    assert first_blocked(beside, grid, blocked) == 0.5  # before: blocked at the first point, for ever
    assert first_blocked(beside, grid, blocked, static=static, body_radius=2) is None
    # the same line from outside the margin (x = 0, column 0): entering it at x = 2.0 counts
    outside = np.array([[0.0, 2.9], [9.0, 2.9]])
    assert first_blocked(outside, grid, blocked, static=static, body_radius=2) == 2.0
    # from inside the margin straight at the truck: at s = 0.5, y = 2.4 m (row 4), the body's reach
    at_it = np.array([[3.0, 2.9], [3.0, 0.0]])
    assert first_blocked(at_it, grid, blocked, static=static, body_radius=2) == 0.5
    # out of the margin (s = 0.5 at y = 3.4 m, row 6), along it, then back in: (5.0, 2.9) at s = 3.0
    back_in = np.array([[3.0, 2.9], [3.0, 3.4], [5.0, 3.4], [5.0, 2.6]])
    assert first_blocked(back_in, grid, blocked, static=static, body_radius=2) == 3.0
    # a moving object's cells are not static obstacles (the speed planner's business): the body may reach them
    assert first_blocked(at_it, grid, blocked, static=(state, drivable, state == ABOVE), body_radius=2) is None


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(2, 30), st.sampled_from([0, 1]), st.floats(0.0, 0.6))
def test_first_along_matches_sampling_every_point_then_looking(seed, n_points, value, density):
    from vehicle_agent.perception import Grid, GridSpec
    from vehicle_agent.planning import _first_along

    rng = np.random.default_rng(seed)
    spec = GridSpec(half_extent_m=10.0)
    grid = Grid(spec, -20, -20, np.zeros((40, 40), np.uint8), np.ones((40, 40), bool))
    mask = rng.random((40, 40)) < density
    path = np.cumsum(rng.normal(0.0, 3.0, (n_points, 2)), axis=0)  # wanders in and out of the grid
    cum = numpy_arc_lengths(path)
    s = np.arange(rng.uniform(0.0, 1.0), cum[-1] + 2.0, 0.5)
    got = _first_along(mask, value, path, s, cum, grid.i0, grid.j0, spec.cell_m)
    assert got == numpy_first_along(mask, value, path, s, cum, grid)


def numpy_smooth_clear(raw, grid, blocked):
    """``planning._smooth_clear`` as it was in numpy (the reference for ``_uncleared``)."""
    from vehicle_agent.planning import _smooth

    out = _smooth(raw)
    keep_raw = np.zeros(len(raw), dtype=bool)
    n = blocked.shape[0]
    for _ in range(8):
        seg = np.diff(out, axis=0)
        steps = np.maximum(np.ceil(np.hypot(seg[:, 0], seg[:, 1]) / (grid.spec.cell_m / 4)), 1).astype(np.int64)
        owner = np.repeat(np.arange(len(seg)), steps)
        frac = (np.arange(steps.sum()) - np.repeat(np.cumsum(steps) - steps, steps)) / np.repeat(steps, steps)
        rc = grid.cell_of(out[owner] + frac[:, None] * seg[owner])
        inside = (rc[:, 0] >= 0) & (rc[:, 0] < n) & (rc[:, 1] >= 0) & (rc[:, 1] < n)
        hit = np.zeros(len(rc), dtype=bool)
        hit[inside] = blocked[rc[inside, 0], rc[inside, 1]]
        bad = np.zeros(len(out), dtype=bool)
        bad[owner[hit]] = True
        bad[owner[hit] + 1] = True
        bad &= ~keep_raw
        if not bad.any():
            break
        keep_raw |= np.convolve(bad, np.ones(5), mode="same") > 0
        out = np.where(keep_raw[:, None], raw, _smooth(raw))
    return out


def test_a_smoothed_corner_that_cuts_a_block_keeps_the_grid_points_by_hand():
    """An L-shaped grid path round a blocked cell at its inside corner: the moving
    average cuts the corner through the cell, so the points round it stay raw."""
    from vehicle_agent.perception import Grid, GridSpec
    from vehicle_agent.planning import _smooth, _smooth_clear, _uncleared

    spec = GridSpec(half_extent_m=5.0)
    grid = Grid(spec, 0, 0, np.zeros((20, 20), np.uint8), np.ones((20, 20), bool))
    raw = np.array([[x, 1.25] for x in np.arange(1.25, 6.0, 0.5)] + [[5.75, y] for y in np.arange(1.75, 6.5, 0.5)])
    blocked = np.zeros((20, 20), dtype=bool)
    blocked[3, 10] = True  # x 5-5.5 m, y 1.5-2 m: inside the corner at (5.75, 1.25)
    assert _uncleared(raw, blocked, 0, 0, 0.5, 0.125).sum() == 0  # the grid path itself is clear
    assert _uncleared(_smooth(raw), blocked, 0, 0, 0.5, 0.125).any()
    out = _smooth_clear(raw, grid, blocked)
    corner = int(np.flatnonzero((raw == [5.75, 1.25]).all(axis=1))[0])
    np.testing.assert_array_equal(out[corner - 2:corner + 3], raw[corner - 2:corner + 3])
    assert not _uncleared(out, blocked, 0, 0, 0.5, 0.125).any()


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(2, 40), st.floats(0.0, 0.3))
def test_smooth_clear_matches_the_numpy_version_to_the_bit(seed, n_points, density):
    from vehicle_agent.perception import Grid, GridSpec
    from vehicle_agent.planning import _smooth_clear

    rng = np.random.default_rng(seed)
    spec = GridSpec(half_extent_m=10.0)
    grid = Grid(spec, -20, -20, np.zeros((40, 40), np.uint8), np.ones((40, 40), bool))
    blocked = rng.random((40, 40)) < density
    moves = np.array([[1, 0], [1, 1], [0, 1], [-1, 1], [1, -1]])[rng.integers(0, 5, n_points - 1)]
    cells = np.cumsum(np.vstack([rng.integers(-15, 15, (1, 2)), moves]), axis=0)  # an 8-connected grid path
    raw = (cells + 0.5) * spec.cell_m + rng.normal(0.0, 0.1, (n_points, 2)) * (rng.random((n_points, 1)) < 0.3)
    outcomes = []
    for smooth_clear in (_smooth_clear, numpy_smooth_clear):
        try:
            outcomes.append(smooth_clear(raw, grid, blocked).tobytes())
        except ValueError as e:  # both: np.convolve's "same" of fewer than 5 points does not broadcast
            outcomes.append(str(e))
    assert outcomes[0] == outcomes[1]


def numpy_arrival_times(s, v0, v_cruise, accel):
    """``planning.arrival_times`` as it was in numpy (the reference)."""
    v_cruise = max(v_cruise, 1e-3)
    v0 = min(v0, v_cruise)
    t_acc = (v_cruise - v0) / accel
    s_acc = (v0 + v_cruise) / 2 * t_acc
    return np.where(s <= s_acc, (-v0 + np.sqrt(v0 * v0 + 2 * accel * np.maximum(s, 0.0))) / accel,
                    t_acc + (s - s_acc) / v_cruise)


def test_arrival_times_by_hand():
    from vehicle_agent.planning import arrival_times

    # from rest at 2 m/s^2 to 10 m/s: 25 m in 5 s, then 10 m/s; already at 10 m/s: s / 10
    np.testing.assert_allclose(arrival_times(np.array([0.0, 1.0, 25.0, 45.0]), 0.0, 10.0, 2.0), [0, 1, 5, 7])
    np.testing.assert_allclose(arrival_times(np.array([0.0, 30.0]), 12.0, 10.0, 2.0), [0.0, 3.0])


@settings(max_examples=300, deadline=None)
@given(st.lists(st.one_of(st.floats(-5.0, 500.0), st.sampled_from([0.0, -0.0, np.nan])), max_size=60),
       st.floats(0.0, 25.0), st.floats(-1.0, 25.0), st.sampled_from([2.0, 0.5, 4.0]))
def test_arrival_times_match_the_numpy_version_to_the_bit(s, v0, v_cruise, accel):
    from vehicle_agent.planning import arrival_times

    s = np.array(s, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        want = numpy_arrival_times(s, v0, v_cruise, accel)
    assert arrival_times(s, v0, v_cruise, accel).tobytes() == want.tobytes()


def test_a_lane_blocked_ahead_stops_the_vehicle_rather_than_a_path_back_round_the_block():
    """The lane is walled off 12 m ahead across the corridor but for its left 2 m, and a
    wall along the left side of the lane, from 25 m behind the vehicle to the wall ahead,
    keeps it from that gap: the only way through runs 25 m back, round the side wall's end
    and forward again. A vehicle does not reverse, so there is no path: it stops before
    the wall ahead (a parked row and a crossing car merged into one standing object led
    the path 47 m back down the lane while the car drove on toward the crossing)."""
    from protocol.messages import Pose
    from vehicle_agent.paths import point_at
    from vehicle_agent.perception import ABOVE, GROUND, Grid, GridSpec
    from vehicle_agent.planning import BEHIND_M, Planner
    from world_server.scenarios import ScenarioParams
    from world_server.sim import Simulation

    mission = Simulation(ScenarioParams(scenario="red_light", vehicles=5, delta_s=0.0, seed=0)).mission(0)
    route = np.asarray(mission.route, dtype=float)
    s0 = 40.0
    x, y = point_at(route, s0)
    d = point_at(route, s0 + 1.0) - point_at(route, s0)
    yaw = float(np.arctan2(d[1], d[0]))
    forward, left = np.array([np.cos(yaw), np.sin(yaw)]), np.array([-np.sin(yaw), np.cos(yaw)])
    spec = GridSpec()
    n = spec.cells
    i0, j0 = int(np.floor(x / spec.cell_m)) - n // 2, int(np.floor(y / spec.cell_m)) - n // 2
    grid = Grid(spec, i0, j0, np.full((n, n), GROUND, dtype=np.uint8), np.ones((n, n), dtype=bool))
    centres = grid.cell_centers(*np.meshgrid(np.arange(n), np.arange(n), indexing="ij"))
    along = (centres - [x, y]) @ forward
    across = (centres - [x, y]) @ left
    wall_ahead = (np.abs(along - 12.0) < 0.5) & (across < 4.0)
    side_wall = (along > -25.0) & (along < 12.5) & (np.abs(across - 3.0) < 0.5)
    grid.state[wall_ahead | side_wall] = ABOVE
    pose = Pose(float(x), float(y), yaw)
    planner = Planner(mission)
    path = planner.path_planner.plan(grid, grid.state, np.zeros((n, n), dtype=bool), pose, 5.0)
    assert ((path - [x, y]) @ forward >= -BEHIND_M - spec.cell_m).all()
    plan = planner.run_step(grid, grid.state, np.zeros((n, n), dtype=bool), [], pose, 5.0, 0.0)
    assert plan.conflict_s_m is not None and plan.conflict_s_m < 12.0  # it stops short of the wall


# ------------------------------------------------------------------ stopping for a conflict


def test_the_approach_to_a_stop_point_by_hand():
    """comfort brake 4 m/s^2: the creep speed at d metres is sqrt(4 d) (half the comfort
    rate stops the vehicle from it in d)."""
    from vehicle_agent.planning import PlannerConfig, approach_accel

    cfg = PlannerConfig(comfort_brake_mps2=4.0, comfort_accel_mps2=2.0)
    assert approach_accel(8.0, 8.0, cfg, 8.0) == pytest.approx(-4.0)  # 64 / 16: stops at 8 m
    assert approach_accel(12.0, 4.0, cfg, 8.0) == pytest.approx(-8.0)  # 144 / 8 = 18, capped
    assert approach_accel(0.0, 9.0, cfg, 8.0) == pytest.approx(2.0)  # standing 9 m short: creep 6 m/s
    assert approach_accel(5.9, 9.0, cfg, 8.0) == pytest.approx(1.0)  # 0.1 m/s below it, in one tick
    assert approach_accel(6.5, 9.0, cfg, 8.0) == pytest.approx(-6.5**2 / 18)  # above it: stop at 9 m
    assert approach_accel(0.0, 0.4, cfg, 8.0) == pytest.approx(-8.0)  # at the stop point: hold


def _drive_to(stop_x, v0: float, ticks: int, cfg) -> tuple[float, float, float]:
    """A point vehicle at 10 Hz under ``approach_accel``; ``stop_x(k)`` is the stop point at
    tick k. Returns where it ended, its speed, and the least gap to the stop point."""
    from vehicle_agent.planning import approach_accel

    x, v, least = 0.0, v0, float("inf")
    for k in range(ticks):
        a = approach_accel(v, max(stop_x(k) - x, 0.0), cfg, 8.0)
        v_next = max(v + a * 0.1, 0.0)
        x += (v + v_next) / 2 * 0.1
        v = v_next
        least = min(least, stop_x(k) - x)
    return x, v, least


def test_a_vehicle_braking_for_a_stop_point_that_moves_on_stops_at_the_new_one():
    """From 30 km/h the stop point is 10 m ahead; after 1 s it moves on to 17.6 m (the
    left turn's oncoming stream, seen whole): the vehicle ends within half a metre of it,
    never past it. (Braking at a fixed rate it stopped 7.6 m short and stayed there.)"""
    from vehicle_agent.planning import PlannerConfig

    x, v, least = _drive_to(lambda k: 10.0 if k < 10 else 17.6, 8.33, 200, PlannerConfig())
    assert v == 0.0 and 17.6 - 0.5 <= x <= 17.6 and least >= 0.0


def test_a_vehicle_standing_short_of_its_stop_point_moves_up_to_it():
    from vehicle_agent.planning import PlannerConfig

    x, v, least = _drive_to(lambda k: 12.0, 0.0, 200, PlannerConfig())
    assert v == 0.0 and 12.0 - 0.5 <= x <= 12.0 and least >= 0.0
    x, v, _ = _drive_to(lambda k: 0.3, 0.0, 50, PlannerConfig())  # already there: it holds
    assert x == 0.0 and v == 0.0
