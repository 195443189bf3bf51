"""Planning helpers against hand-derived geometry."""

import numpy as np
import pytest

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
