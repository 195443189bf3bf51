"""Physics a reader can check by hand (HighwayEnv style)."""

import numpy as np
import pytest

from world_server.physics import Physics
from world_server.scenarios import CAR, TRUCK


def _drive(phys: Physics, seconds: float, dt: float = 0.01) -> None:
    for _ in range(int(round(seconds / dt))):
        phys.step(dt)


def test_two_seconds_at_20_mps_is_40_m():
    phys = Physics([CAR], np.array([[0.0, 0.0, 0.0]]), np.array([20.0]))
    _drive(phys, 2.0)
    assert phys.x[0] == pytest.approx(40.0, abs=1e-9)
    assert phys.y[0] == pytest.approx(0.0, abs=1e-9)


def test_heading_is_respected():
    phys = Physics([CAR], np.array([[5.0, 5.0, np.pi / 2]]), np.array([10.0]))
    _drive(phys, 1.5)
    assert (phys.x[0], phys.y[0]) == pytest.approx((5.0, 20.0), abs=1e-9)


@pytest.mark.parametrize("v, a", [(20.0, 7.5), (11.1, 6.0), (8.0, 3.3)])
def test_braking_distance_is_v2_over_2a(v, a):
    phys = Physics([CAR], np.array([[0.0, 0.0, 0.0]]), np.array([v]))
    phys.command(0, -a, 0.0)
    _drive(phys, 10.0)
    assert phys.v[0] == 0.0
    assert phys.x[0] == pytest.approx(v * v / (2 * a), abs=1e-9)


def test_commands_are_clipped_to_the_vehicle_limits():
    phys = Physics([CAR], np.array([[0.0, 0.0, 0.0]]), np.array([0.0]))
    phys.command(0, 100.0, 3.0)
    _drive(phys, 1.0)
    assert phys.v[0] == pytest.approx(CAR.max_accel_mps2 * 1.0)
    assert phys.steer_cmd[0] == CAR.max_steer_rad


def test_constant_steer_drives_a_circle_of_the_bicycle_radius():
    # centre-referenced bicycle: curvature = cos(beta) tan(delta) / L, beta = atan(tan(delta) / 2)
    delta, v = 0.3, 5.0
    beta = np.arctan(0.5 * np.tan(delta))
    radius = CAR.wheelbase_m / (np.cos(beta) * np.tan(delta))
    phys = Physics([CAR], np.array([[0.0, 0.0, 0.0]]), np.array([v]))
    phys.command(0, 0.0, delta)
    _drive(phys, 2 * np.pi * radius / v)  # one full lap returns to the start
    assert np.hypot(phys.x[0], phys.y[0]) < 0.05


def test_head_on_contact_is_reported_when_the_bodies_touch():
    # gap 30 - 4.5 = 25.5 m closed at 20 m/s: contact at 1.275 s, in the step ending at 1.28 s
    phys = Physics([CAR, CAR], np.array([[0.0, 0.0, 0.0], [30.0, 0.0, np.pi]]), np.array([20.0, 0.0]))
    _drive(phys, 1.27)
    assert phys.contacts == []
    _drive(phys, 0.05)
    assert [(c.a, c.b) for c in phys.contacts] == [(0, 1)]
    assert phys.contacts[0].t_sim_s == pytest.approx(1.28)
    assert phys.frozen.all() and (phys.v == 0).all()


def test_side_by_side_lanes_do_not_touch():
    phys = Physics([CAR, TRUCK], np.array([[0.0, 0.0, 0.0], [0.0, 3.5, 0.0]]), np.array([10.0, 9.0]))
    _drive(phys, 3.0)
    assert phys.contacts == []


def test_the_bodies_stay_where_the_vehicles_are():
    """pymunk's bodies follow the vehicles, moving or parked, and never move on their own."""
    phys = Physics([CAR, CAR, TRUCK], np.array([[0.0, 0.0, 0.0], [0.0, 10.0, 0.5], [20.0, -5.0, 1.0]]),
                   np.array([10.0, 0.0, 5.0]))
    phys.command(0, 0.0, 0.2)
    phys.command(2, -10.0, 0.0)  # stops within the second, then holds still
    _drive(phys, 1.5)
    for body, x, y, yaw in zip(phys.bodies, phys.x, phys.y, phys.yaw):
        assert tuple(body.position) == (x, y) and body.angle == yaw
        assert tuple(body.velocity) == (0.0, 0.0) and body.angular_velocity == 0.0
