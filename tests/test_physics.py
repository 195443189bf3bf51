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


def test_command_many_clips_by_hand():
    phys = Physics([CAR, TRUCK, CAR], np.zeros((3, 3)), np.zeros(3))
    phys.command_many(np.array([2, 0]), np.array([100.0, -100.0]), np.array([-3.0, 0.1]))
    assert phys.accel_cmd.tolist() == [-CAR.max_brake_mps2, 0.0, CAR.max_accel_mps2]
    assert phys.steer_cmd.tolist() == [0.1, 0.0, -CAR.max_steer_rad]


def _one_by_one(phys: Physics, ids, accel, steer) -> None:  # what Simulation.step did before command_many
    for i, a, s in zip(ids, accel, steer):
        phys.command(int(i), a, s)


from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

_cmd = st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=64), st.sampled_from([0.0, -0.0]),
                 st.sampled_from([CAR.max_accel_mps2, -CAR.max_brake_mps2, TRUCK.max_steer_rad, -CAR.max_steer_rad]))


@settings(max_examples=300, deadline=None)
@given(data=st.data(), n=st.integers(1, 6))
def test_command_many_sets_what_command_one_by_one_sets(data, n):
    specs = [data.draw(st.sampled_from([CAR, TRUCK])) for _ in range(n)]
    ids = np.array(data.draw(st.permutations(range(n)))[:data.draw(st.integers(0, n))], dtype=np.int64)
    accel = np.array([data.draw(_cmd) for _ in ids], dtype=np.float64)
    steer = np.array([data.draw(_cmd) for _ in ids], dtype=np.float64)
    a, b = (Physics(specs, np.zeros((n, 3)), np.zeros(n)) for _ in range(2))
    _one_by_one(a, ids, accel.tolist(), steer.tolist())  # Python floats, as commands arrive
    b.command_many(ids, accel, steer)
    assert a.accel_cmd.view(np.int64).tolist() == b.accel_cmd.view(np.int64).tolist()  # to the bit (NaN, -0.0)
    assert a.steer_cmd.view(np.int64).tolist() == b.steer_cmd.view(np.int64).tolist()


def _body_state(phys: Physics) -> list:
    return [(b.position.x, b.position.y, b.angle, tuple(b.rotation_vector), *[tuple(s.bb) for s in b.shapes])
            for b in phys.bodies]


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(2, 12))
def test_bodies_put_in_one_batch_are_where_one_by_one_puts_them_and_touch_alike(seed, n):
    """``_sync_bodies`` puts every body through pymunk.batch; the reference puts only the
    moved ones one by one (as it did before): the same bodies, transforms, boxes and contacts."""
    rng = np.random.default_rng(seed)
    specs = [CAR if rng.random() < 0.7 else TRUCK for _ in range(n)]
    poses = np.column_stack([rng.uniform(-15, 15, n), rng.uniform(-15, 15, n), rng.uniform(-np.pi, np.pi, n)])
    speeds = rng.uniform(0, 12, n) * (rng.random(n) < 0.8)  # some parked
    fast, slow = Physics(specs, poses, speeds), Physics(specs, poses, speeds)
    assert fast._batched
    slow._batched = False
    for _ in range(30):
        accel, steer = rng.uniform(-8, 3, n), rng.uniform(-0.6, 0.6, n)
        for phys in (fast, slow):
            phys.command_many(np.arange(n), accel, steer)
            for _ in range(10):
                phys.step(0.01)
        assert _body_state(fast) == _body_state(slow)
    assert fast.contacts == slow.contacts
    assert fast.x.tolist() == slow.x.tolist() and fast.v.tolist() == slow.v.tolist()
