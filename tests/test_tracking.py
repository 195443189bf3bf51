"""The tracker: a constant-velocity Kalman filter with gating, and motion judged from
free space. Filter cases are derived by hand and against a full 4-state reference
filter; the motion cases run on the world's LiDAR."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol.messages import LidarConfig, Pose
from vehicle_agent.frames import sensor_to_world
from vehicle_agent.perception import (DetectedObject, DrivableRaster, GridSpec, build_grid, extract_objects,
                                      object_of_points)
from vehicle_agent.tracking import (_OFFSETS, ACCEL_SIGMA_MPS2, EVIDENCE_LAG_MIN, EVIDENCE_MARGIN,
                                   EVIDENCE_MIN_POINTS, EVIDENCE_MIN_SHARE, EVIDENCE_SHIFT_M, GATE_CHI2, GATE_MAX_M,
                                   GATE_MIN_M, INIT_SPEED_SIGMA_MPS, MEAS_SIGMA_M, REGISTERED_POINTS, VOXEL_M, Tracker,
                                   _nearest_owner, _persisting, associate, registered_velocity,
                                   split_merged)
from world_server import lidar

DT = 0.1
OPEN_FIELD = [np.array([[-200.0, -200.0], [200.0, -200.0], [200.0, 200.0], [-200.0, 200.0]])]


def _det(x: float, y: float) -> DetectedObject:
    """A 2 x 1 m detection centred at (x, y) (cells on the 0.5 m lattice)."""
    i, j = np.meshgrid(np.arange(4) + int(np.floor((x - 1) / 0.5)), np.arange(2) + int(np.floor((y - 0.5) / 0.5)))
    cells = np.stack([i.ravel(), j.ravel()], axis=1).astype(np.int64)
    return DetectedObject(np.zeros((0, 3), np.float32), cells, np.array([x, y, 0.7]), 0.0, 2.0, 1.0)


def _reference_kf(zs: np.ndarray, dt: float) -> np.ndarray:
    """The textbook 4-state filter [x, y, vx, vy] with full matrices: velocity after each frame."""
    f = np.eye(4)
    f[0, 2] = f[1, 3] = dt
    g = np.array([[dt**2 / 2, 0], [0, dt**2 / 2], [dt, 0], [0, dt]])
    q = ACCEL_SIGMA_MPS2**2 * g @ g.T
    h = np.hstack([np.eye(2), np.zeros((2, 2))])
    r = MEAS_SIGMA_M**2 * np.eye(2)
    x = np.array([zs[0, 0], zs[0, 1], 0.0, 0.0])
    p = np.diag([MEAS_SIGMA_M**2] * 2 + [INIT_SPEED_SIGMA_MPS**2] * 2)
    out = [x[2:].copy()]
    for z in zs[1:]:
        x, p = f @ x, f @ p @ f.T + q
        k = p @ h.T @ np.linalg.inv(h @ p @ h.T + r)
        x, p = x + k @ (z - h @ x), (np.eye(4) - k @ h) @ p
        out.append(x[2:].copy())
    return np.array(out)


def test_a_mover_at_1_m_per_tick_is_at_10_mps_by_its_third_frame():
    tracker = Tracker()
    zs = np.array([[20.0 + k, 3.0] for k in range(3)])
    for k, (x, y) in enumerate(zs):
        (tr,) = tracker.update([_det(x, y)], DT * k)
        if k == 1:
            # by hand: P00 = R + s_v^2 dt^2 + q dt^4 / 4 and P10 = s_v^2 dt + q dt^3 / 2 after the
            # prediction; the 1 m innovation times the gain P10 / (P00 + R)
            r, sv2, q = MEAS_SIGMA_M**2, INIT_SPEED_SIGMA_MPS**2, ACCEL_SIGMA_MPS2**2
            p00, p10 = r + sv2 * DT**2 + q * DT**4 / 4, sv2 * DT + q * DT**3 / 2
            assert tr.filtered_velocity[0] == pytest.approx(p10 / (p00 + r))
    assert tr.filtered_velocity == pytest.approx([10.0, 0.0], abs=1.0)
    assert tr.filtered_velocity == pytest.approx(_reference_kf(zs, DT)[-1], abs=1e-9)


def test_the_filter_matches_the_reference_on_a_noisy_turning_mover():
    rng = np.random.default_rng(3)
    t = np.arange(30) * DT
    truth = 30.0 * np.stack([np.cos(0.3 * t), np.sin(0.3 * t)], axis=1)  # 9 m/s, 2.7 m/s^2 inward
    zs = truth + rng.normal(0.0, 0.15, truth.shape)
    tracker = Tracker()
    got = []
    for k, z in enumerate(zs):
        (tr,) = tracker.update([_det(*z)], DT * k)
        got.append(tr.filtered_velocity.copy())
    np.testing.assert_allclose(np.array(got), _reference_kf(zs, DT), atol=1e-9)


def test_a_static_object_stays_static():
    tracker = Tracker()
    for k in range(20):
        (tr,) = tracker.update([_det(15.0, -2.0)], DT * k)
        assert tr.velocity.tolist() == [0.0, 0.0]
    assert np.hypot(*tr.filtered_velocity) < 1e-6


def test_gating_rejects_a_jump():
    """A track settled at 10 m/s; a detection 5 m off its prediction starts a new track."""
    tracker = Tracker()
    for k in range(6):
        (tr,) = tracker.update([_det(20.0 + k, 3.0)], DT * k)
    first = tr.track_id
    (tr,) = tracker.update([_det(26.0, 8.0)], DT * 6)
    assert tr.track_id != first and tr.hits == 1
    assert [t.missed for t in tracker.tracks if t.track_id == first] == [1]


def test_association_pairs_nearest_first_within_each_gate():
    predicted = np.array([[0.0, 0.0], [10.0, 0.0]])
    measured = np.array([[10.5, 0.0], [0.3, 0.0], [50.0, 0.0]])
    # variance 0.1 m^2: gate sqrt(9.21 * 0.1) ~ 0.96 m, clipped up to the 1.5 m floor
    assert sorted(associate(predicted, np.array([0.1, 0.1]), measured)) == [(0, 1), (1, 0)]
    assert associate(predicted, np.array([0.1, 0.1]), measured[2:]) == []


# ------------------------------------------------------------------------ on the LiDAR


def _scan(boxes, pose: Pose, mount: float = 1.9):
    pts, _ = lidar.scan(np.asarray(boxes, dtype=float), np.array([pose.x_m, pose.y_m, pose.yaw_rad]), mount,
                        LidarConfig())
    world = sensor_to_world(pts, pose, mount)
    grid, cell_idx = build_grid(world, (pose.x_m, pose.y_m), GridSpec(), DrivableRaster(OPEN_FIELD, 0.5))
    return grid, extract_objects(world, grid, cell_idx, (pose.x_m, pose.y_m))


@pytest.mark.parametrize("heading", [0.0, np.pi, np.pi / 2])
def test_a_car_seen_by_lidar_moves_at_its_speed_by_the_third_frame(heading):
    """Away from, towards and across the sensor's view, 1 m per tick."""
    tracker = Tracker()
    d = np.array([np.cos(heading), np.sin(heading)])
    start = np.array([25.0, -4.0]) - (10 * d if heading == np.pi / 2 else 0)
    for k in range(3):
        xy = start + k * d
        grid, objs = _scan([[xy[0], xy[1], heading, 4.5, 1.8, 1.5]], Pose(0.0, 0.0, 0.0))
        (tr,) = tracker.update(objs, DT * k)
    assert tr.velocity == pytest.approx(10.0 * d, abs=1.5)


def test_a_parked_truck_passed_by_a_moving_observer_stays_static():
    """The observer drives by at 6 m/s from 25 m behind to alongside: the truck's visible
    faces change (its centroid moves) but it never enters or leaves free ground."""
    tracker = Tracker()
    truck = [[0.0, 0.4, 0.0, 8.0, 2.5, 3.5]]
    for k in range(45):
        pose = Pose(-25.0 + 0.6 * k, -3.5, 0.0)
        grid, objs = _scan(truck, pose)
        tracks = tracker.update(objs, DT * k)
        assert all(t.velocity.tolist() == [0.0, 0.0] for t in tracks), k


@pytest.mark.parametrize("seed", range(4))
def test_persisting_matches_a_brute_force_neighbour_search(seed):
    """A point persists when a point of the other frame lies in its voxel or one of the
    26 around it: checked against every pair of points."""
    rng = np.random.default_rng(seed)
    old = rng.uniform([-2, -1, 0], [2, 1, 1.5], (60, 3))
    now = rng.uniform([-1, -1, 0], [3, 1, 1.5], (80, 3))
    dx, dy, voxel = 0.7, -0.1, 0.2
    ov = np.floor((old + [dx, dy, 0.0]) / voxel)
    nv = np.floor(now / voxel)
    expected = (np.abs(ov[:, None, :] - nv[None, :, :]).max(axis=2) <= 1).any(axis=1).mean()
    shares = _persisting(old, now, np.array([[0.0, 0.0], [dx, dy]]), voxel)
    unshifted = (np.abs(np.floor(old / voxel)[:, None, :] - nv[None, :, :]).max(axis=2) <= 1).any(axis=1).mean()
    assert shares.tolist() == pytest.approx([unshifted, expected])
    assert _persisting(old[:0], now, np.array([[dx, dy]]), voxel).tolist() == [0.0]
    # float32 points, as detected, give the shares of the same points widened to float64
    old32, now32 = old.astype(np.float32), now.astype(np.float32)
    shifts = np.array([[0.0, 0.0], [dx, dy], [-dx, 0.3]])
    assert (_persisting(old32, now32, shifts, voxel).tolist()
            == _persisting(old32.astype(np.float64), now32.astype(np.float64), shifts, voxel).tolist())


def _associate_numpy(predicted, variance, measured):
    """The reference: ``associate`` in numpy, as it was written before its kernel."""
    if len(predicted) == 0 or len(measured) == 0:
        return []
    dist = np.linalg.norm(predicted[:, None, :] - measured[None, :, :], axis=2)
    radius = np.clip(np.sqrt(GATE_CHI2 * variance), GATE_MIN_M, GATE_MAX_M)
    d2 = dist**2 / np.maximum(variance, 1e-9)[:, None]
    ii, jj = np.nonzero(dist <= radius[:, None])
    used_a, used_b, pairs = set(), set(), []
    for k in np.lexsort((jj, ii, d2[ii, jj])):
        i, j = int(ii[k]), int(jj[k])
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            pairs.append((i, j))
    return pairs


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n_t=st.integers(0, 12), n_d=st.integers(0, 12), lattice=st.booleans())
def test_associate_matches_the_numpy_formulation(seed, n_t, n_d, lattice):
    """The same pairs in the same order, including ties (points on a 0.5 m lattice)."""
    rng = np.random.default_rng(seed)
    if lattice:
        predicted = rng.integers(0, 12, (n_t, 2)) * 0.5
        measured = rng.integers(0, 12, (n_d, 2)) * 0.5
        variance = rng.choice([0.1, 0.4, 2.0], n_t)
    else:
        predicted = rng.uniform(0, 10, (n_t, 2))
        measured = rng.uniform(0, 10, (n_d, 2))
        variance = rng.uniform(0.0, 3.0, n_t)
    assert associate(predicted, variance, measured) == _associate_numpy(predicted, variance, measured)


def _registered_velocity_numpy(history, now, t_sim_s, velocity):
    """The reference: ``registered_velocity`` as it was written, its shifts and choice in numpy."""
    speed = float(np.hypot(*velocity))
    for back in range(EVIDENCE_LAG_MIN, len(history) + 1):
        t_old, old = history[-back]
        age = t_sim_s - t_old
        if speed * age < EVIDENCE_SHIFT_M:
            continue
        if len(old) < EVIDENCE_MIN_POINTS:
            return None
        now = np.ascontiguousarray(now)
        old = np.ascontiguousarray(old[::max(len(old) // REGISTERED_POINTS, 1)])
        shifts = np.vstack([[0.0, 0.0], velocity * age + _OFFSETS])
        shares = _persisting(old, now, shifts, VOXEL_M)
        best = int(np.argmax(shares[1:])) + 1
        if shares[best] >= EVIDENCE_MIN_SHARE and shares[best] - shares[0] >= EVIDENCE_MARGIN:
            return shifts[best] / age
        return None
    return None


@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), frames=st.integers(1, 6), n=st.sampled_from([10, 40, 300, 1000]),
       lattice=st.booleans())
def test_registered_velocity_matches_the_numpy_formulation(seed, frames, n, lattice):
    """A block of float32 points that moves (or not, or jumps) frame to frame, the
    filter's velocity near or far from the truth: the same velocity, bit for bit, or None
    alike. On a 0.1 m lattice, points fall on voxel edges and shares tie."""
    rng = np.random.default_rng(seed)
    truth = rng.uniform(-12.0, 12.0, 2) * rng.choice([0.0, 1.0])
    block = rng.uniform([0.0, 0.0, 0.0], rng.uniform(0.5, 5.0, 3), (n, 3))
    if lattice:
        block = np.round(block * 10.0) / 10.0
    history = []
    for k in range(frames):
        pts = block + np.append(truth * DT * k, 0.0) + rng.normal(0.0, 0.02, block.shape) * rng.choice([0.0, 1.0])
        history.append((DT * k, pts[rng.random(n) < 0.9].astype(np.float32)))
    now = (block + np.append(truth * DT * frames, 0.0)).astype(np.float32)
    velocity = truth + rng.normal(0.0, 2.0, 2) * rng.choice([0.0, 1.0])
    got = registered_velocity(history, now, DT * frames, velocity)
    want = _registered_velocity_numpy(history, now, DT * frames, velocity)
    assert (got is None) == (want is None)
    if got is not None:
        assert got.dtype == want.dtype and got.tobytes() == want.tobytes()


def test_a_block_moved_1_m_in_0_1_s_registers_at_the_first_shift_that_keeps_it_all():
    """A 0.6 m block of points (off the voxel edges) moved 1 m along x in 0.1 s, the filter
    at 10 m/s: unmoved, none of its points persist; every moved hypothesis within one
    voxel of the truth keeps them all, and the first of those in the offsets' order,
    (-0.2, -0.2) m, wins: 8 m/s along x, -2 across."""
    g = np.arange(6) * 0.1 + 0.05
    block = np.stack(np.meshgrid(g, g, [0.55], indexing="ij"), axis=-1).reshape(-1, 3)
    old, now = block.astype(np.float32), (block + [1.0, 0.0, 0.0]).astype(np.float32)
    got = registered_velocity([(0.0, old), (0.05, old), (0.1, now)], now, 0.1, np.array([10.0, 0.0]))
    assert got == pytest.approx([8.0, -2.0])
    # a block that stays put is explained as well unmoved: no velocity
    assert registered_velocity([(0.0, old), (0.05, old), (0.1, old)], old, 0.1, np.array([10.0, 0.0])) is None


def test_the_filter_state_is_the_covariance_and_velocity_the_arrays_gave():
    """A new track's state: its centroid, no velocity, the initial covariance; after a
    second frame the filtered velocity is the one the state holds."""
    tracker = Tracker()
    (tr,) = tracker.update([_det(20.0, 3.0)], 0.0)
    assert tr.cov.tolist() == np.diag([MEAS_SIGMA_M**2, INIT_SPEED_SIGMA_MPS**2]).tolist()
    assert tr.filtered_velocity.tolist() == [0.0, 0.0] and tr.xy.tolist() == [20.0, 3.0]
    (tr,) = tracker.update([_det(21.0, 3.0)], DT)
    assert tr.filtered_velocity.tolist() == list(tr.kf[2:4]) and tr.xy.tolist() == list(tr.kf[:2])
    assert tr.cov.tolist() == [list(tr.kf[4:6]), list(tr.kf[6:8])]


def _block(x0: float, y0: float, size_x: float, size_y: float) -> np.ndarray:
    """Float32 (n, 3) points every 0.2 m over a box's footprint, at 0.6 and 1.2 m."""
    x, y, z = np.meshgrid(np.arange(x0, x0 + size_x + 1e-9, 0.2), np.arange(y0, y0 + size_y + 1e-9, 0.2), [0.6, 1.2])
    return np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1).astype(np.float32)


def test_a_car_passing_a_standing_truck_closer_than_the_segmentation_reach_keeps_its_track():
    # the truck stands at x 0-2.4 m, y 0-8 m; the car (1.8 x 4.5 m) drives down x 3.2-5.0 m
    # at 5 m/s, 0.8 m from the truck: closer than perception's 1.5 m, so while they are
    # side by side perception gives one detection of both. Split, the two parts are the
    # two objects' own points, so the tracks are those of a tracker given them apart.
    merged_tracker, apart_tracker, truck = Tracker(), Tracker(), _block(0.0, 0.0, 2.4, 8.0)
    merged_ticks = 0
    for k in range(41):
        y0 = 20.0 - 0.5 * k
        car = _block(3.2, y0, 1.8, 4.5)
        apart = [object_of_points(truck, 0.5), object_of_points(car, 0.5)]
        merged = y0 < 8.0 + 1.5
        merged_ticks += merged
        got = merged_tracker.update([object_of_points(np.concatenate([truck, car]), 0.5)] if merged else apart, DT * k)
        want = apart_tracker.update(apart, DT * k)
        assert [(tr.track_id, tr.moving) for tr in got] == [(tr.track_id, tr.moving) for tr in want] == \
            [(0, False), (1, k >= 2)], k
        for g, w in zip(got, want):
            assert g.xy.tolist() == w.xy.tolist() and g.velocity.tolist() == w.velocity.tolist(), k
    assert merged_ticks == 19
    assert got[1].velocity == pytest.approx([0.0, -5.0], abs=0.5)  # the tracker's own estimate of 5 m/s


def test_a_merged_detection_without_a_mover_in_it_is_left_whole():
    tracker = Tracker()
    a, b = _block(0.0, 0.0, 2.0, 4.5), _block(3.0, 0.0, 2.0, 4.5)  # two parked cars 1 m apart
    for k in range(3):
        tracker.update([object_of_points(a, 0.5), object_of_points(b, 0.5)], DT * k)
    whole = object_of_points(np.concatenate([a, b]), 0.5)
    assert split_merged(tracker.tracks, [whole], DT * 3, 0.5) == [whole]


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.floats(-5, 5), st.floats(-5, 5)), min_size=1, max_size=40),
       st.lists(st.tuples(st.floats(-6, 6), st.floats(-6, 6), st.integers(0, 2)), min_size=1, max_size=12))
def test_each_point_goes_to_an_owner_of_a_nearest_seed_on_the_lattice(points, seeds):
    xy = np.array(points, dtype=np.float64)
    seed_xy = np.array([s[:2] for s in seeds], dtype=np.float64)
    owner_of = np.array([s[2] for s in seeds], dtype=np.int64)
    voxel = 0.25
    owner = _nearest_owner(xy, seed_xy, owner_of, voxel)
    lo = xy.min(axis=0) - voxel
    size = np.floor((xy.max(axis=0) - lo) / voxel).astype(int) + 2
    cell = np.floor((xy - lo) / voxel).astype(int)
    seed_cell = np.floor((seed_xy - lo) / voxel).astype(int)
    inside = ((seed_cell >= 0) & (seed_cell < size)).all(axis=1)
    if not inside.any():
        assert (owner == -1).all()
        return
    # the slower reference: the Chebyshev distance on the lattice to every seed in the box
    dist = np.abs(cell[:, None, :] - seed_cell[None, inside, :]).max(axis=2)
    for p in range(len(xy)):
        nearest = dist[p].min()
        assert owner[p] in set(owner_of[inside][dist[p] == nearest].tolist())


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(st.floats(-300, 300), st.floats(-300, 300)), min_size=1, max_size=60))
def test_a_parts_cells_are_its_points_cells_each_once_in_order(points):
    pts = np.array([[x, y, 1.0] for x, y in points], dtype=np.float32)
    want = np.unique(np.floor(pts[:, :2].astype(np.float64) / 0.5).astype(np.int64), axis=0)
    assert object_of_points(pts, 0.5).cells.tolist() == want.tolist()
