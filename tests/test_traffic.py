"""The world-driven traffic (world_server/driver.py): who brakes for what."""

import numpy as np
import pytest

from world_server import driver
from world_server.scenarios import CAR, OVERTAKE_BRAKE_LENGTHS, ScenarioParams
from world_server.sim import Simulation


def test_free_distance_to_boxes_by_hand():
    """A car at the origin heading +x; its corridor is |y| < 0.9 + 0.5 ahead of its front bumper (2.25)."""
    boxes = np.array([
        [0.0, 0.0, 0.0, 4.5, 1.8],  # itself
        [10.0, 0.0, np.pi / 2, 4.5, 1.8],  # crossing its lane: near side at x = 10 - 0.9
        [6.0, 3.5, 0.0, 4.5, 1.8],  # in the next lane: y from 2.6, outside the corridor
        [-8.0, 0.0, 0.0, 4.5, 1.8],  # behind it
    ])
    outline, owner = driver.outline_points(boxes)
    gap = driver.free_distance_to_boxes(0.0, 0.0, 0.0, CAR, outline, owner, 0, horizon_m=50.0)
    assert gap == pytest.approx(10.0 - 0.9 - 2.25)
    outline, owner = driver.outline_points(boxes[[0, 2, 3]])
    assert driver.free_distance_to_boxes(0.0, 0.0, 0.0, CAR, outline, owner, 0, horizon_m=50.0) == np.inf


def test_brakes_fully_only_within_its_brake_lengths():
    route = np.array([[0.0, 0.0], [100.0, 0.0]])
    near = OVERTAKE_BRAKE_LENGTHS * CAR.length_m - 0.1
    assert driver.passive_command(0, 0, 0, 8.0, 8.0, route, CAR, near, OVERTAKE_BRAKE_LENGTHS)[0] == -CAR.max_brake_mps2
    assert driver.passive_command(0, 0, 0, 8.0, 8.0, route, CAR, near + 0.2, OVERTAKE_BRAKE_LENGTHS)[0] == 0.0
    assert driver.passive_command(0, 0, 0, 8.0, 8.0, route, CAR, 0.5, 0.0)[0] == 0.0  # never brakes


def test_oncoming_traffic_stops_in_a_queue_behind_a_car_in_its_lane():
    """Overtaking: the ego stands in the oncoming lane. The collider (its own LiDAR) stops
    short of it, the car 40 m behind (the world's boxes) short of the collider; nobody touches."""
    sim = Simulation(ScenarioParams(scenario="overtaking", vehicles=2, collider_speed_kmh=30.0, duration_s=12.0))
    col = sim.scenario.collider.vid
    follower = next(a.vid for a in sim.scenario.actors if a.role == "traffic")
    ph = sim.physics
    ph.x[0], ph.y[0], ph.yaw[0], ph.v[0] = 10.0, 2.0, 0.0, 0.0
    ph._sync_bodies()
    for _ in range(110):
        sim.sense([])
        sim.step({0: (-7.5, 0.0), 1: (-6.5, 0.0)})
    assert not ph.contacts
    assert ph.v[col] == 0.0 and ph.v[follower] == 0.0
    gap_col = ph.x[col] - ph.x[0] - CAR.length_m
    gap_follower = ph.x[follower] - ph.x[col] - CAR.length_m
    for gap in (gap_col, gap_follower):
        assert 0.0 < gap < OVERTAKE_BRAKE_LENGTHS * CAR.length_m
