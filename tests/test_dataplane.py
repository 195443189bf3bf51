"""The agent's data plane: hand-derived unit cases, then real scans from the world."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from numba import njit
from hypothesis import strategies as st

from protocol.codec import MalformedMessage, decode, encode
from protocol.messages import LidarConfig, Pose, Scan
from vehicle_agent.frames import ray_tables, scan_to_world, sensor_to_world, world_to_sensor
from vehicle_agent.payload import MAX_ERROR_M, ObjectPayload, decode_object, encode_object, payload_size
from vehicle_agent.perception import (ABOVE, EMPTY, GROUND, DrivableRaster, Grid, GridSpec, _cells_by_label,
                                      _labels, _merge_shadowed, _object_stats, build_grid, extract_objects,
                                      scan_grid, scan_objects)
from vehicle_agent.spatial import _inside, _ray_rect, relevance, sample_trajectory, visibility, visible_share
from vehicle_agent.tracking import Tracker
from world_server import lidar
from world_server.geometry import box_corners

from tests.fusion_scenes import received_intervals

OPEN_FIELD = [np.array([[-200.0, -200.0], [200.0, -200.0], [200.0, 200.0], [-200.0, 200.0]])]
SENSOR = Pose(0.0, 0.0, 0.0)


def perceive(boxes, pose=SENSOR, mount=1.9, drivable=OPEN_FIELD):
    """Scan ``boxes`` (world frame) from ``pose`` and extract objects."""
    pts, _ = lidar.scan(np.asarray(boxes, dtype=float), np.array([pose.x_m, pose.y_m, pose.yaw_rad]), mount,
                        LidarConfig())
    world = sensor_to_world(pts, pose, mount)
    grid, cell_idx = build_grid(world, (pose.x_m, pose.y_m), GridSpec(), DrivableRaster(drivable, 0.5))
    return grid, extract_objects(world, grid, cell_idx, (pose.x_m, pose.y_m))


def test_scan_to_world_places_the_range_image_like_sensor_to_world():
    """The agent's one-pass decoding of a scan equals decoding to sensor points and then
    transforming them, for a rotated, shifted vehicle."""
    cfg = LidarConfig()
    pose = Pose(12.0, -7.0, 2.1)
    sweep = lidar.scan_many(np.array([[20.0, -3.0, 0.4, 4.5, 1.8, 1.5]]), np.array([[12.0, -7.0, 2.1]]),
                            np.array([1.9]), cfg, np.array([-1]))[0]
    scan = Scan(0, 0.0, 0, pose, 0.0, sweep.range_cm)
    expected = sensor_to_world(scan.points(cfg), pose, cfg.mount_height_m)
    np.testing.assert_allclose(scan_to_world(scan, cfg), expected, atol=1e-4)
    assert np.abs(expected[sweep.labels == lidar.GROUND, 2]).max() < 0.01  # ground comes back at z = 0


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_perceiving_from_the_range_image_equals_perceiving_the_scans_world_points(seed):
    """scan_grid + scan_objects (straight from the range image) against scan_to_world +
    build_grid + extract_objects: the same grid and the same objects, bit for bit, in a
    scene of random boxes seen from a random pose, with a drivable area that cuts some."""
    rng = np.random.default_rng(seed)
    cfg = LidarConfig(mount_height_m=float(rng.choice([1.9, 3.8])))
    pose = Pose(*rng.uniform(-30, 30, 2), float(rng.uniform(-np.pi, np.pi)))
    n = int(rng.integers(0, 12))
    boxes = np.column_stack([pose.x_m + rng.uniform(-60, 60, n), pose.y_m + rng.uniform(-60, 60, n),
                             rng.uniform(-np.pi, np.pi, n), rng.uniform(1, 12, n), rng.uniform(1, 3, n),
                             rng.uniform(0.2, 4, n)])
    sweep = lidar.scan_many(boxes.reshape(-1, 6), np.array([[pose.x_m, pose.y_m, pose.yaw_rad]]),
                            np.array([cfg.mount_height_m]), cfg, np.array([-1]))[0]
    scan = decode(encode(Scan(0, 0.0, 0, pose, 0.0, sweep.range_cm)), Scan)  # read-only, as received
    drivable = DrivableRaster([OPEN_FIELD[0], np.array([[0.0, -90.0], [90.0, -90.0], [90.0, 90.0]])]
                              if seed % 2 else [np.array([[-200.0, -10.0], [200.0, -10.0], [200.0, 10.0],
                                                          [-200.0, 10.0]])], 0.5)
    world = scan_to_world(scan, cfg)
    want_grid, cell_idx = build_grid(world, (pose.x_m, pose.y_m), GridSpec(), drivable)
    want = extract_objects(world, want_grid, cell_idx, (pose.x_m, pose.y_m))
    xyyaw = (pose.x_m, pose.y_m, pose.yaw_rad)
    grid, binned = scan_grid(scan.range_cm, ray_tables(cfg), xyyaw, cfg.mount_height_m, GridSpec(), drivable)
    got = scan_objects(scan.range_cm, ray_tables(cfg), xyyaw, cfg.mount_height_m, grid, binned)
    assert (grid.i0, grid.j0) == (want_grid.i0, want_grid.j0)
    np.testing.assert_array_equal(grid.state, want_grid.state)
    np.testing.assert_array_equal(grid.drivable, want_grid.drivable)
    assert len(got) == len(want)
    for a, b in zip(got, want):
        assert (a.yaw_rad, a.length_m, a.width_m) == (b.yaw_rad, b.length_m, b.width_m)
        for name in ("points_world", "cells", "centroid"):
            x, y = getattr(a, name), getattr(b, name)
            assert x.dtype == y.dtype
            np.testing.assert_array_equal(x, y)


def test_a_wall_is_one_object_with_its_extent():
    # a 10 m x 0.4 m wall, 2 m tall, 15 m ahead, facing the sensor: its near face spans y in [-5, 5]
    _, objs = perceive([[15.2, 0.0, np.pi / 2, 10.0, 0.4, 2.0]])
    assert len(objs) == 1
    wall = objs[0]
    assert wall.length_m == pytest.approx(10.0, abs=0.3)  # the visible face, minus ray spacing
    assert abs(np.cos(wall.yaw_rad)) < 0.05  # its long side runs along y
    assert wall.centroid[0] == pytest.approx(15.0, abs=0.05)  # points on the near face x = 15.0
    assert wall.centroid[1] == pytest.approx(0.0, abs=0.2)


def test_two_cars_3_m_apart_are_two_objects():
    # side by side, centres 4.8 m apart: a 3 m gap between their flanks
    _, objs = perceive([[12.0, 2.4, 0.0, 4.5, 1.8, 1.5], [12.0, -2.4, 0.0, 4.5, 1.8, 1.5]])
    assert len(objs) == 2
    assert sorted(round(o.centroid[1]) for o in objs) == [-2, 2]


def test_cells_off_the_drivable_area_are_ignored():
    road = [np.array([[-100.0, -4.0], [100.0, -4.0], [100.0, 4.0], [-100.0, 4.0]])]
    _, objs = perceive([[15.0, 0.0, 0.0, 4.5, 1.8, 1.5], [15.0, 10.0, 0.0, 4.5, 1.8, 1.5]], drivable=road)
    assert len(objs) == 1 and objs[0].centroid[1] == pytest.approx(0.0, abs=0.5)


def test_empty_cells_behind_an_object_are_occluded_area():
    grid, _ = perceive([[10.0, 0.0, 0.0, 4.5, 3.0, 3.0]])
    occ = grid.occluded()
    rows, cols = grid.cell_of(np.array([[20.0, 0.0], [-10.0, 0.0]])).T
    assert occ[rows[0], cols[0]]  # behind the box
    assert not occ[rows[1], cols[1]]  # open ground behind the sensor


def test_tracking_keeps_ids_and_estimates_velocity():
    tracker = Tracker()
    ids, vel = [], None
    for k in range(15):
        x = 20.0 + 1.0 * k  # 10 m/s along x, 0.1 s per tick
        _, objs = perceive([[x, 3.5, 0.0, 4.5, 1.8, 1.5], [15.0, -6.0, 0.0, 4.5, 1.8, 1.5]])
        tracks = tracker.update(objs, 0.1 * k)
        ids.append([t.track_id for t in tracks])
        vel = {t.track_id: t.velocity for t in tracks}
    assert all(i == ids[0] for i in ids) and len(ids[0]) == 2
    moving = max(vel.values(), key=lambda v: np.hypot(*v))
    assert moving == pytest.approx([10.0, 0.0], abs=1.0)
    assert min(np.hypot(*v) for v in vel.values()) == 0.0  # the parked car does not drift


def test_object_stats_of_a_rotated_rectangle():
    """Points on the outline of a 4 x 2 m rectangle turned 30 degrees, centred at (5, -3),
    1 m high; an empty label in between gets zeros."""
    u = np.concatenate([np.linspace(-2, 2, 41), np.linspace(-2, 2, 41), np.full(21, -2.0), np.full(21, 2.0)])
    v = np.concatenate([np.full(41, -1.0), np.full(41, 1.0), np.linspace(-1, 1, 21), np.linspace(-1, 1, 21)])
    th = np.radians(30.0)
    pts = np.stack([5 + u * np.cos(th) - v * np.sin(th), -3 + u * np.sin(th) + v * np.cos(th), np.ones_like(u)], 1)
    mean, yaw, u_lo, u_hi, v_lo, v_hi, z = _object_stats(pts, np.array([0, 0, len(pts)]))
    assert mean[0].tolist() == [0.0, 0.0] and u_lo[0] == u_hi[0] == 0.0
    assert mean[1] == pytest.approx([5.0, -3.0]) and z[1] == pytest.approx(1.0)
    assert yaw[1] == pytest.approx(th)
    assert (u_hi[1] - u_lo[1], v_hi[1] - v_lo[1]) == pytest.approx((4.0, 2.0))


def _two_parts(between: int) -> Grid:
    """Seen from the origin along +x: a car's rear face (x 10-11 m) and, 2 m behind it,
    its roof (x 13-14 m), |y| <= 1 m; the cells in between set to ``between``."""
    spec = GridSpec(half_extent_m=20.0)
    n = spec.cells
    i0 = j0 = -n // 2
    state = np.full((n, n), EMPTY, dtype=np.uint8)
    cols = lambda x0, x1: slice(int(x0 / spec.cell_m) - i0, int(x1 / spec.cell_m) - i0)  # noqa: E731
    rows = slice(int(-1 / spec.cell_m) - j0, int(1 / spec.cell_m) - j0)
    state[rows, cols(11, 13)] = between
    state[rows, cols(10, 11)] = state[rows, cols(13, 14)] = ABOVE
    return Grid(spec, i0, j0, state, np.ones((n, n), dtype=bool))


@njit
def label_components(mask, reach):
    """The slower reference for ``perception._components``: components of a boolean
    grid where cells up to ``reach`` cells apart (Chebyshev) connect, seeded by a scan
    of every cell. Labels 1..k, and k."""
    ny, nx = mask.shape
    labels = np.zeros((ny, nx), dtype=np.int32)
    stack = np.empty(ny * nx, dtype=np.int64)
    k = 0
    for y in range(ny):
        for x in range(nx):
            if not mask[y, x] or labels[y, x] != 0:
                continue
            k += 1
            labels[y, x] = k
            stack[0] = y * nx + x
            top = 1
            while top > 0:
                top -= 1
                cy, cx = divmod(stack[top], nx)
                for dy in range(-reach, reach + 1):
                    for dx in range(-reach, reach + 1):
                        yy, xx = cy + dy, cx + dx
                        if 0 <= yy < ny and 0 <= xx < nx and mask[yy, xx] and labels[yy, xx] == 0:
                            labels[yy, xx] = k
                            stack[top] = yy * nx + xx
                            top += 1
    return labels, k


@pytest.mark.parametrize("between, parts", [(EMPTY, 1), (GROUND, 2)])
def test_a_part_in_anothers_shadow_merges_only_across_unseen_cells(between, parts):
    grid = _two_parts(between)
    labels, k = label_components(grid.state == ABOVE, 1)
    assert k == 2
    merged, k = _merge_shadowed(labels, k, grid, (0.0, 0.0))
    assert k == parts and sorted(np.unique(merged).tolist()) == list(range(parts + 1))
    assert np.array_equal(merged > 0, labels > 0)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_labels_equal_labelling_the_mask_then_merging_shadows(seed):
    """``_labels`` (one kernel over the grid's ABOVE and drivable cells, then the shadow
    merge on the labelled cells only) against the whole-grid reference: numpy's mask,
    ``label_components``, ``_merge_shadowed``; and the cells grouped by label against a
    stable sort by label."""
    rng = np.random.default_rng(seed)
    spec = GridSpec(half_extent_m=float(rng.choice([6.0, 12.0])), reach_cells=int(rng.integers(1, 4)))
    n = spec.cells
    state = rng.choice(np.array([EMPTY, GROUND, ABOVE], dtype=np.uint8), size=(n, n), p=[0.5, 0.3, 0.2])
    drivable = rng.random((n, n)) < 0.8
    grid = Grid(spec, int(rng.integers(-50, 50)), int(rng.integers(-50, 50)), state, drivable)
    sensor = tuple(((np.array([grid.i0, grid.j0]) + rng.uniform(0, n, 2)) * spec.cell_m).tolist())
    labels, k, cells = _labels(grid, sensor)
    want, want_k = label_components((state == ABOVE) & drivable, spec.reach_cells)
    if want_k > 1:
        want, want_k = _merge_shadowed(want, want_k, grid, sensor)
    assert k == want_k
    np.testing.assert_array_equal(labels, want)
    np.testing.assert_array_equal(cells, np.flatnonzero((state == ABOVE) & drivable))
    got_cells, bounds = _cells_by_label(cells, labels.ravel(), k, n, grid.i0, grid.j0)
    order = np.flatnonzero(labels.ravel())
    order = order[np.argsort(labels.ravel()[order], kind="stable")]
    np.testing.assert_array_equal(got_cells, np.stack([order % n + grid.i0, order // n + grid.j0], axis=1))
    counts = np.bincount(labels.ravel(), minlength=k + 1)[1:]
    np.testing.assert_array_equal(bounds, np.concatenate([[0], np.cumsum(counts)]))


def _quad(cx, cy, yaw, length, width):
    return box_corners(cx, cy, yaw, length, width)


def test_a_box_behind_a_truck_is_hidden_from_j_and_seen_from_a_clear_line():
    truck, car = _quad(0.0, 10.0, 0.0, 9.0, 2.5), _quad(0.0, 20.0, 0.0, 4.5, 1.8)
    quads = np.stack([truck, car])
    # j at the origin looks along +y: the truck (|x| <= 4.5) covers the car (|x| <= 2.25) entirely
    # j2 at (20, 20) looks along -x at the car: nothing in between
    share = visible_share(np.array([[0.0, 0.0], [20.0, 20.0]]), np.array([100.0, 100.0]), quads, quads,
                          np.array([0, 1]))
    assert share[0].tolist() == [1.0, 0.0]
    assert share[1].tolist() == [1.0, 1.0]
    assert visibility(share)[:, 1].tolist() == [0.0, 1.0]


def test_a_long_wall_beside_the_viewer_hides_what_is_behind_it():
    """A 100 m wall 10 m from j, its corners 50 m away; a car 20 m behind its middle.
    Every ray from j to the car crosses the wall 10 m out, nearer than the car (~19 m):
    share 0. (Tested by its nearest corner, 51 m off, the wall was passed over and the
    car seen through it: share 1.) Moved along the wall past its end, j sees the car."""
    wall, car = _quad(0.0, 10.0, 0.0, 100.0, 0.2), _quad(0.0, 20.0, 0.0, 4.5, 1.8)
    quads = np.stack([car, wall])
    share = visible_share(np.array([[0.0, 0.0], [60.0, 20.0]]), np.array([100.0, 100.0]), car[None], quads,
                          np.array([0]))
    assert share[:, 0].tolist() == [0.0, 1.0]


def test_an_object_beyond_js_range_is_invisible():
    car = _quad(0.0, 0.0, 0.0, 4.5, 1.8)[None]
    share = visible_share(np.array([[0.0, 99.0], [0.0, 101.0]]), np.array([100.0, 100.0]), car, car, np.array([0]))
    assert share[:, 0].tolist() == [1.0, 0.0]


def test_half_hidden_object_has_half_share():
    # occluder covers exactly the left half of the target's angular extent
    target = _quad(0.0, 20.0, 0.0, 4.0, 1.0)
    blocker = _quad(-1.0, 10.0, 0.0, 1.0, 0.5)  # spans x in [-1.5, -0.5] at y = 10: angles of x in [-3, -1] at y=20
    share = visible_share(np.array([[0.0, 0.0]]), np.array([100.0]), target[None], np.stack([target, blocker]),
                          np.array([0]), n_rays=100)
    # target spans x in [-2, 2] at y = 19.5..20.5; the blocker shadows x in [-2, -0.98] of it: ~25% hidden
    assert share[0, 0] == pytest.approx(0.75, abs=0.03)


def test_crossing_trajectories_are_relevant_parallel_ones_are_not():
    t = np.arange(0.0, 7.0, 1.0)
    # j drives north along x = 0 at 5 m/s from y = -20: at the origin at t = 4 s
    j_traj = np.stack([np.zeros_like(t), -20.0 + 5.0 * t, t], axis=1)
    # an object driving west along y = 0 at 5 m/s from x = 20: also at the origin at t = 4 s
    crossing = relevance([j_traj], np.array([[4.5, 1.8]]), np.array([[20.0, 0.0]]), np.array([[-5.0, 0.0]]),
                         np.array([[4.5, 1.8]]), 0.0)
    # an object in the next lane (3.5 m to the east) at the same speed and direction
    parallel = relevance([j_traj], np.array([[4.5, 1.8]]), np.array([[3.5, -20.0]]), np.array([[0.0, 5.0]]),
                         np.array([[4.5, 1.8]]), 0.0)
    assert crossing[0, 0] == 1.0 and parallel[0, 0] == 0.0
    # TTC form: bodies (three circles, r = 0.9) come within 1 m of each other before t = 4 s
    ttc = relevance([j_traj], np.array([[4.5, 1.8]]), np.array([[20.0, 0.0]]), np.array([[-5.0, 0.0]]),
                    np.array([[4.5, 1.8]]), 0.0, mode="ttc")
    assert 1 / (1 + 4.0) < ttc[0, 0] < 1 / (1 + 3.0)


@pytest.mark.parametrize("late_s, relevant", [(0.0, 1.0), (1.5, 1.0), (-1.5, 1.0), (3.5, 0.0), (-3.5, 0.0)])
def test_an_object_that_could_collide_within_the_timing_window_is_relevant(late_s, relevant):
    """j drives north through the origin at t = 4 s; the object crosses it westwards
    ``late_s`` later. Bodies within 1 m while the object is within +-2 s of that moment
    count: by hand, the object is 5 m per s x 2 s = 10 m along its lane from the
    crossing at the window's edge, far more than the bodies' 2.8 m plus 1.35 m reach."""
    t = np.arange(0.0, 9.0, 1.0)
    j_traj = np.stack([np.zeros_like(t), -20.0 + 5.0 * t, t], axis=1)
    x0 = 5.0 * (4.0 + late_s)  # at the origin at 4 + late_s
    r = relevance([j_traj], np.array([[4.5, 1.8]]), np.array([[x0, 0.0]]), np.array([[-5.0, 0.0]]),
                  np.array([[4.5, 1.8]]), 0.0)
    assert r[0, 0] == relevant


def test_relevance_matches_a_dense_reference_on_random_traffic():
    """The kernel against a direct evaluation: j's three circles at each sample time
    against k's three circles at every time of the window, sampled every 0.01 s."""
    rng = np.random.default_rng(7)
    t = np.arange(0.0, 9.0, 1.0)
    trajs = []
    for _ in range(4):
        p0, v = rng.uniform(-30, 30, 2), rng.uniform(-8, 8, 2)
        trajs.append(np.column_stack([p0[0] + v[0] * t, p0[1] + v[1] * t, t]))
    xy, vel = rng.uniform(-30, 30, (12, 2)), rng.uniform(-8, 8, (12, 2))
    dims = np.tile([4.5, 1.8], (12, 1))
    got = relevance(trajs, np.tile([4.5, 1.8], (4, 1)), xy, vel, dims, 0.0)
    times = np.arange(0.0, 8.0 + 1e-9, 0.25)
    off = np.array([-1.0, 0.0, 1.0]) * 1.35
    checked = 0
    for j, wp in enumerate(trajs):
        pos, head = sample_trajectory(wp, times)
        cj = pos[:, None, :] + off[None, :, None] * np.stack([np.cos(head), np.sin(head)], axis=1)[:, None, :]
        for k in range(12):
            hk = np.arctan2(vel[k, 1], vel[k, 0])
            d_min = np.inf
            for ti, tt in enumerate(times):
                tau = np.arange(max(tt - 2.0, 0.0), tt + 2.0 + 1e-9, 0.01)
                ck = (xy[k] + tau[:, None] * vel[k])[:, None, :] + off[None, :, None] * [np.cos(hk), np.sin(hk)]
                d_min = min(d_min, np.linalg.norm(cj[ti][:, None, None, :] - ck[None], axis=-1).min())
            reach = 0.9 + 0.9 + 1.0
            if d_min < reach - 0.1:  # the dense samples are 0.08 m apart at most: well inside the slack
                assert got[j, k] == 1.0, (j, k, d_min)
                checked += 1
            elif d_min > reach + 0.1:
                assert got[j, k] == 0.0, (j, k, d_min)
    assert checked > 0


def test_transform_round_trip_is_exact():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-50, 50, (1000, 3))
    a, b = Pose(12.5, -3.0, 0.7), Pose(-40.0, 8.0, -2.9)
    back = world_to_sensor(sensor_to_world(pts, a, 1.9), a, 1.9)
    assert np.allclose(back, pts, atol=1e-9)
    # V_r = T_r^-1 T_s V_s then back again
    v_r = world_to_sensor(sensor_to_world(pts, a, 1.9), b, 3.8)
    assert np.allclose(world_to_sensor(sensor_to_world(v_r, b, 3.8), a, 1.9), pts, atol=1e-9)


def test_payload_encoding_error_is_within_the_stated_bound():
    rng = np.random.default_rng(1)
    pts = rng.uniform(-3, 3, (500, 3)).astype(np.float32) + np.float32([20, -5, -1])
    centroid = pts.mean(axis=0)
    obj = ObjectPayload(3, 17, 42, 4.2, Pose(1.0, 2.0, 0.3), 1.9, centroid, np.float32([4.0, -1.0]), pts)
    raw = encode_object(obj)
    assert len(raw) == payload_size(500) == 64 + 6 * 500
    back = decode_object(raw)
    assert (back.sender, back.object_id, back.tick) == (3, 17, 42)
    err = np.linalg.norm(back.points_sensor - pts, axis=1).max()
    assert err <= MAX_ERROR_M + 1e-6  # 0.5 cm per axis
    with pytest.raises(MalformedMessage):
        decode_object(raw[:-1])
    with pytest.raises(MalformedMessage):
        decode_object(b"XXXX" + raw[4:])


def test_received_points_land_in_the_receivers_grid():
    from vehicle_agent.fusion import ReceivedStore, fuse

    # the sender at (0, 0) sees a car at (10, 0); the receiver at (30, 30) fuses it
    pts, labels = lidar.scan(np.array([[10.0, 0.0, 0.0, 4.5, 1.8, 1.5]]), np.zeros(3), 1.9, LidarConfig())
    car = pts[labels == 0]
    obj = ObjectPayload(1, 0, 5, 0.5, SENSOR, 1.9, car.mean(axis=0), np.float32([2.0, 0.0]), car)
    store = ReceivedStore()
    store.add(decode_object(encode_object(obj)))
    receiver = Pose(30.0, 30.0, 1.0)
    world = sensor_to_world(np.zeros((1, 3), np.float32), receiver, 1.9)
    grid, _ = build_grid(world, (30.0, 30.0), GridSpec(), DrivableRaster(OPEN_FIELD, 0.5))
    fused = fuse(grid, store.current(1.0, {(1, 0)}))  # 0.5 s later: moved 1 m along +x
    rows, cols = np.nonzero(fused.received)
    centers = grid.cell_centers(rows, cols)
    assert fused.state[rows, cols].tolist() == [ABOVE] * len(rows)
    assert centers[:, 0].min() == pytest.approx(7.75 + 1.0, abs=0.5)  # near face x = 7.75, plus 1 m
    assert np.abs(centers[:, 1]).max() <= 0.9 + 0.5


def test_fusion_marks_received_cells_and_which_objects_we_see_ourselves():
    """Own grid: one ABOVE cell at (10.25, 0.25). Object A covers it and the cell east of
    it, object B a cell of its own plus a ground-height point, object C lies off the grid."""
    from vehicle_agent.fusion import SharedBatch, SharedObject, fuse

    spec = GridSpec(half_extent_m=20.0)
    n = spec.cells
    state = np.full((n, n), GROUND, dtype=np.uint8)
    grid = Grid(spec, -n // 2, -n // 2, state, np.ones((n, n), dtype=bool))
    own = tuple(grid.cell_of(np.array([10.25, 0.25])))
    state[own] = ABOVE
    pts = {"A": [[10.25, 0.25, 1.0], [10.75, 0.25, 1.0]], "B": [[-5.25, 3.25, 1.0], [-8.0, 3.0, 0.1]],
           "C": [[60.0, 0.0, 1.0]]}
    shared = [SharedObject((i, 0), np.array(p), np.zeros(2), 0.0, True) for i, p in enumerate(pts.values())]
    fused = fuse(grid, SharedBatch.of(shared))
    cells = lambda *xy: [tuple(grid.cell_of(np.array(p))) for p in xy]  # noqa: E731
    assert sorted(zip(*np.nonzero(fused.received))) == sorted(cells([10.75, 0.25], [-5.25, 3.25]))
    assert sorted(zip(*np.nonzero(fused.state == ABOVE))) == sorted(cells([10.25, 0.25], [10.75, 0.25],
                                                                            [-5.25, 3.25]))
    assert fused.same_as_own == {(0, 0): True, (1, 0): False, (2, 0): False}
    none = fuse(grid, SharedBatch.of([]))
    assert none.same_as_own == {} and not none.received.any()


def test_batched_trajectory_sampling_equals_one_at_a_time():
    """relevance samples every receiver's trajectory in one numba pass; it must agree with
    the numpy reference (np.interp, holding both ends) on random trajectories."""
    from vehicle_agent.spatial import _sample_all, sample_trajectory

    rng = np.random.default_rng(0)
    trajs = []
    for _ in range(150):
        n = int(rng.integers(1, 8))
        trajs.append(np.column_stack([rng.uniform(-50, 50, (n, 2)), np.sort(rng.uniform(0, 5, n))]))
    times = np.arange(0.0, 6.0, 0.1) - 0.3  # before the first and after the last waypoint too
    starts = np.concatenate([[0], np.cumsum([len(w) for w in trajs])])
    pos, head = _sample_all(np.concatenate(trajs), starts, times)
    for j, w in enumerate(trajs):
        ref_pos, ref_head = sample_trajectory(w, times)
        np.testing.assert_allclose(pos[j], ref_pos, atol=1e-9)
        np.testing.assert_allclose(head[j], ref_head, atol=1e-12)


def test_not_me_drops_what_others_saw_of_us_where_we_are_and_were():
    """We (4.5 x 1.8 m, +0.5 m margin: |dx| <= 2.75, |dy| <= 1.4) are at (0, 0) heading
    east and were at (-1, 0) a tick ago. Object 1 is all on our body: dropped. Object 2
    merged us with a car 10 m ahead: our points go, the car's stay. Object 3 is 1.35 m
    behind our rear, on where we were a tick ago: dropped. Object 4 is just clear."""
    from vehicle_agent.fusion import SharedBatch, SharedObject, not_me

    def obj(k, pts):
        return SharedObject((k, 0), np.array(pts, dtype=float), np.zeros(2), 0.0, True)

    us = [[1.0, 0.5, 1.0], [-2.0, -1.0, 1.0], [2.7, 1.3, 0.5]]
    car = [[10.0, 0.0, 1.0], [11.0, 0.5, 1.0], [12.0, -0.5, 1.0], [10.5, 0.0, 1.0], [11.5, 0.0, 1.0]]
    out = not_me(SharedBatch.of([obj(1, us), obj(2, us[:1] + car), obj(3, [[-3.5, 0.0, 1.0]]),
                                 obj(4, [[-3.8, 0.0, 1.0]])]),
                 [Pose(0.0, 0.0, 0.0), Pose(-1.0, 0.0, 0.0)], 4.5, 1.8).objects()
    assert [o.key[0] for o in out] == [2, 4]
    np.testing.assert_array_equal(out[0].points_world, car)


def test_not_me_drops_our_ghost_that_a_sender_extrapolated_past_us():
    """A sender captured us 1 s ago at (-1, 0), tracked at 6 m/s east; we braked and are
    at (0, 0). Placed now its points are 5 m ahead, clear of our body (|dx| <= 2.75),
    but where it captured them they are on our body as we were: dropped. A car
    captured 1 s ago 10 m ahead of that, at the same velocity, stays."""
    from vehicle_agent.fusion import SharedBatch, SharedObject, not_me

    body = np.array([[-2.0, 0.5, 1.0], [0.0, -0.8, 1.0], [2.0, 0.0, 1.0]])
    ghost = SharedObject((1, 0), body + [5.0, 0.0, 0.0], np.array([6.0, 0.0]), 1.0, False)  # x 3, 5, 7
    car = SharedObject((1, 1), body + [15.0, 0.0, 0.0], np.array([6.0, 0.0]), 1.0, False)
    out = not_me(SharedBatch.of([ghost, car]), [Pose(0.0, 0.0, 0.0), Pose(-1.0, 0.0, 0.0)], 4.5, 1.8).objects()
    assert [o.key for o in out] == [(1, 1)]


def test_not_me_stills_an_object_that_merged_us_with_a_parked_truck():
    """A sender saw us pass a parked truck as one object moving at our speed (6 m/s east),
    captured 0.5 s ago. One point in ten is ours: it goes, and the truck's points stand
    where they were captured, not moved 3 m on, with no velocity."""
    from vehicle_agent.fusion import SharedBatch, SharedObject, not_me

    truck = np.column_stack([np.linspace(8.0, 12.0, 9), np.full(9, -2.0), np.full(9, 1.5)])
    placed = np.vstack([[[0.0, 0.0, 1.0]], truck + [3.0, 0.0, 0.0]])  # as the receiver placed them
    obj = SharedObject((3, 10), placed, np.array([6.0, 0.0]), 0.5, True)
    (out,) = not_me(SharedBatch.of([obj]), [Pose(0.0, 0.0, 0.0)], 4.5, 1.8).objects()
    np.testing.assert_allclose(out.points_world, truck)
    assert out.velocity_xy.tolist() == [0.0, 0.0]


def test_not_me_matches_testing_every_point_against_every_pose():
    from vehicle_agent.fusion import SharedBatch, SharedObject, not_me, on_body

    def reference(shared, poses, length_m, width_m):
        out = []
        for o in shared:
            mine = np.zeros(len(o.points_world), dtype=bool)
            for pose in poses:
                mine |= on_body(o.points_world, pose, length_m, width_m)
            if mine.mean() >= 0.3:
                continue
            out.append((o.key, o.points_world[~mine]))
        return out

    rng = np.random.default_rng(3)
    for _ in range(50):
        poses = [Pose(float(x), float(y), float(h)) for x, y, h in
                 np.cumsum(rng.normal(0.0, [1.0, 1.0, 0.1], (int(rng.integers(1, 12)), 3)), axis=0)]
        shared = [SharedObject((1, i), np.column_stack([rng.normal(rng.uniform(-8, 8), 1.5, n),
                                                       rng.normal(rng.uniform(-8, 8), 1.0, n), rng.uniform(0, 2, n)]),
                               np.zeros(2), 0.0, True) for i, n in enumerate(rng.integers(1, 60, 20))]
        got = [(o.key, o.points_world) for o in not_me(SharedBatch.of(shared), poses, 4.5, 1.8).objects()]
        want = reference(shared, poses, 4.5, 1.8)
        assert [k for k, _ in got] == [k for k, _ in want]
        for (_, a), (_, b) in zip(got, want):
            np.testing.assert_array_equal(a, b)


def test_neighbor_table_places_older_messages_along_their_trajectories_like_interp():
    """An older control message stands for where its trajectory puts the vehicle now
    (np.interp, clamped at both ends) and the rest of its trajectory from there."""
    from protocol.messages import ControlMsg, ObjectMap
    from vehicle_agent.dataplane import NeighborTable

    z = np.zeros(0, dtype=np.int64)
    empty = ObjectMap(z, z, np.zeros((0, 2), np.float32), z, np.zeros((0, 0), np.float32),
                      np.zeros((0, 0), np.float32))
    rng = np.random.default_rng(5)
    table = NeighborTable()
    for vid in range(1, 40):
        t_msg = float(rng.uniform(0.0, 2.0))
        times = t_msg + np.sort(rng.choice(np.arange(0.0, 7.0, 0.5), int(rng.integers(1, 8)), replace=False))
        traj = np.column_stack([rng.normal(0, 50, (len(times), 2)), times]).astype(np.float32)
        table.update([ControlMsg(0, t_msg, vid, Pose(*rng.normal(0, 50, 2), 0.0), 5.0, traj, empty, z)])
    for t_now in (0.0, 1.0, 2.0, 2.3, 3.5, 9.0):
        got = table.current(t_now, exclude=7)
        assert got.waypoints.dtype == np.float64 and list(got.vid) == sorted(got.vid)
        row = {int(vid): i for i, vid in enumerate(got.vid)}
        for vid, m in table.last.items():
            if vid == 7 or t_now - m.t_sim_s > table.max_age_s:
                assert vid not in row
                continue
            traj = np.asarray(m.trajectory, dtype=np.float64)
            i = row[vid]
            if m.t_sim_s >= t_now - 1e-9 or len(traj) < 2:
                np.testing.assert_array_equal(got.xy[i], [m.pose.x_m, m.pose.y_m])
                np.testing.assert_array_equal(got.trajectory(i), traj)
                continue
            xy = [np.interp(t_now, traj[:, 2], traj[:, 0]), np.interp(t_now, traj[:, 2], traj[:, 1])]
            ahead = traj[traj[:, 2] > t_now]
            want = np.vstack([[*xy, t_now], ahead]) if len(ahead) else traj[-1:]
            np.testing.assert_array_equal(got.xy[i], xy)
            np.testing.assert_array_equal(got.trajectory(i), want)
            assert not got.fresh[i]
        # a subset keeps each kept vehicle's row and trajectory
        keep = np.arange(len(got)) % 3 != 1
        sub = got.take(keep)
        for i_sub, i in enumerate(np.flatnonzero(keep)):
            assert sub.vid[i_sub] == got.vid[i] and sub.fresh[i_sub] == got.fresh[i]
            np.testing.assert_array_equal(sub.xy[i_sub], got.xy[i])
            np.testing.assert_array_equal(sub.trajectory(i_sub), got.trajectory(i))


def test_neighbor_table_places_hostile_trajectories_as_searchsorted_does():
    """Times out of order, repeated, NaN or infinite, none or one waypoint (a peer's
    control message is not ours to trust): an older message is placed after the
    waypoint np.searchsorted(side="right") finds, as the per-vehicle numpy formulation
    placed it; one of fewer than two waypoints stands at its pose."""
    from protocol.messages import ControlMsg, ObjectMap
    from vehicle_agent.dataplane import NeighborTable

    def reference(traj, t_now):
        t = traj[:, 2]
        k = int(np.searchsorted(t, t_now, side="right"))
        if k == len(t):
            return traj[-1, :2], traj[-1:]
        xy = traj[0, :2] if k == 0 else \
            (traj[k, :2] - traj[k - 1, :2]) / (t[k] - t[k - 1]) * (t_now - t[k - 1]) + traj[k - 1, :2]
        return xy, np.vstack([[*xy, t_now], traj[k:]])

    z = np.zeros(0, dtype=np.int64)
    empty = ObjectMap(z, z, np.zeros((0, 2), np.float32), z, np.zeros((0, 0), np.float32),
                      np.zeros((0, 0), np.float32))
    rng = np.random.default_rng(11)
    table = NeighborTable(max_age_s=10.0)
    for vid in range(1, 30):
        times = rng.choice([0.5, 1.0, 1.0, 2.0, 3.0, np.nan, -1.0, np.inf], int(rng.integers(0, 7)))
        traj = np.column_stack([rng.normal(0, 20, (len(times), 2)), times]).astype(np.float32)
        table.update([ControlMsg(0, 0.0, vid, Pose(0.0, 0.0, 0.0), 5.0, traj, empty, z)])
    for t_now in (0.2, 1.0, 1.5, 2.5, 4.0):
        got = table.current(t_now, exclude=-1)
        for i, vid in enumerate(got.vid.tolist()):
            traj = np.asarray(table.last[vid].trajectory, dtype=np.float64)
            if len(traj) < 2:  # none or one waypoint: as sent, at its pose
                np.testing.assert_array_equal(got.xy[i], [0.0, 0.0])
                np.testing.assert_array_equal(got.trajectory(i), traj)
                continue
            want_xy, want_traj = reference(traj, t_now)
            np.testing.assert_array_equal(got.xy[i], want_xy)
            np.testing.assert_array_equal(got.trajectory(i), want_traj)


def test_fuse_matches_the_numpy_formulation_on_random_objects():
    from vehicle_agent.fusion import SharedBatch, SharedObject, fuse

    def reference(grid, shared):
        state, received = grid.state.copy(), np.zeros_like(grid.drivable)
        pts = np.concatenate([o.points_world for o in shared])
        owner = np.repeat(np.arange(len(shared)), [len(o.points_world) for o in shared])
        n = state.shape[0]
        rc = grid.cell_of(pts[:, :2])
        use = (pts[:, 2] > grid.spec.ground_clear_m) & (rc >= 0).all(axis=1) & (rc < n).all(axis=1)
        r, c = rc[use, 0], rc[use, 1]
        own = grid.state[r, c] == ABOVE
        on_own = np.bincount(owner[use], weights=own, minlength=len(shared)) > 0
        received[r[~own], c[~own]] = True
        state[r, c] = ABOVE
        return state, received, {o.key: bool(h) for o, h in zip(shared, on_own)}

    rng = np.random.default_rng(11)
    spec = GridSpec(half_extent_m=20.0)
    n = spec.cells
    for _ in range(30):
        state = rng.choice([GROUND, ABOVE, EMPTY], size=(n, n), p=[0.6, 0.2, 0.2]).astype(np.uint8)
        grid = Grid(spec, int(rng.integers(-100, 100)), int(rng.integers(-100, 100)), state, np.ones((n, n), bool))
        cx, cy = grid.origin_xy
        shared = []
        for k in range(int(rng.integers(1, 12))):
            m = int(rng.integers(1, 200))
            pts = np.column_stack([cx + rng.uniform(-5, 45, m), cy + rng.uniform(-5, 45, m), rng.uniform(-0.5, 2, m)])
            if k % 3 == 1:  # points in a row close together, many in the cell of the one before
                pts = np.repeat(pts, 3, axis=0) + rng.normal(0.0, 0.1, (3 * m, 3))
            if k == 0:
                pts[0] = [np.nan, cy + 1.0, 1.0]  # a corrupt point is ignored, not placed
            if k % 3 == 2:  # one point, in an ABOVE cell where the object before ends: it is on_own
                r, c = np.argwhere(state == ABOVE)[k]
                pts = np.array([[(c + grid.i0 + 0.5) * spec.cell_m, (r + grid.j0 + 0.5) * spec.cell_m, 1.0]])
                shared[-1].points_world[-1] = pts[0]
            shared.append(SharedObject((k, 0), pts, np.zeros(2), 0.0, True))
        got = fuse(grid, SharedBatch.of(shared))
        state_ref, received_ref, same_ref = reference(grid, [o if o.key[0] else
                                                             SharedObject(o.key, o.points_world[1:], o.velocity_xy,
                                                                          o.age_s, o.fresh) for o in shared])
        np.testing.assert_array_equal(got.state, state_ref)
        np.testing.assert_array_equal(got.received, received_ref)
        assert got.same_as_own == same_ref


def test_the_store_places_each_objects_newest_reception_like_one_at_a_time():
    """add_many takes every object to the world in one pass: the points must equal
    sensor_to_world's, object by object, and a reception older than the one kept (in
    the same batch or before) is ignored."""
    from vehicle_agent.fusion import ReceivedStore

    rng = np.random.default_rng(2)

    def payload(sender, oid, t, n):
        pose = Pose(*rng.normal(0, 30, 2), float(rng.uniform(-np.pi, np.pi)))
        pts = rng.normal(0, 3, (n, 3)).astype(np.float32)
        return ObjectPayload(sender, oid, int(t * 10), t, pose, float(rng.uniform(1.5, 2.5)), pts.mean(axis=0),
                             rng.normal(0, 5, 2).astype(np.float32), pts)

    store = ReceivedStore()
    first = [payload(1, 0, 0.5, 40), payload(2, 3, 0.5, 7)]
    store.add_many(first)
    batch = [payload(1, 0, 0.6, 30), payload(1, 0, 0.4, 9), payload(3, 1, 0.6, 1), payload(3, 1, 0.65, 12),
             payload(2, 3, 0.3, 5)]
    store.add_many(batch)
    want = {(1, 0): batch[0], (2, 3): first[1], (3, 1): batch[3]}
    got = store.current(0.7, {(1, 0)})
    assert got.keys == sorted(want) and got.fresh.tolist() == [True, False, False]
    for o in got.objects():
        p = want[o.key]
        placed = sensor_to_world(p.points_sensor, p.sender_pose, p.mount_height_m)
        placed[:, :2] += p.velocity_xy.astype(np.float64) * (0.7 - p.t_sim_s)
        np.testing.assert_array_equal(o.points_world, placed)
        assert o.age_s == 0.7 - p.t_sim_s
    assert store.current(1.66).keys == []  # all older than 1 s now, and forgotten


def test_a_carried_object_where_we_now_see_bare_ground_is_dropped():
    """Own grid: ground everywhere except one unseen column. A stale object on ground is
    gone; the same points fresh are kept; a stale object over unseen cells or off the
    grid is kept (we cannot see that it left)."""
    from vehicle_agent.fusion import SharedBatch, SharedObject, not_contradicted

    spec = GridSpec(half_extent_m=20.0)
    n = spec.cells
    state = np.full((n, n), GROUND, dtype=np.uint8)
    grid = Grid(spec, -n // 2, -n // 2, state, np.ones((n, n), dtype=bool))
    unseen = grid.cell_of(np.array([5.25, 0.0]))[1]
    state[:, unseen] = EMPTY
    on_ground = [[1.0, 1.0, 1.0], [1.5, 1.0, 1.0]]

    def obj(k, pts, fresh):
        return SharedObject((k, 0), np.array(pts), np.zeros(2), 0.2, fresh)

    shared = SharedBatch.of([obj(1, on_ground, False), obj(2, on_ground, True), obj(3, [[5.25, 0.0, 1.0]], False),
                             obj(4, [[50.0, 0.0, 1.0]], False)])
    assert not_contradicted(shared, grid).keys == [(2, 0), (3, 0), (4, 0)]


def test_the_drivable_raster_equals_testing_every_cell_against_every_polygon():
    """The three scenarios' maps, plus both windings of a triangle: the bounding-box
    kernel marks the same cells as the meshgrid formulation."""
    from vehicle_agent.perception import lattice_centers
    from world_server.scenarios import ScenarioParams
    from world_server.sim import Simulation

    def reference(polygons, cell_m, margin_m=100.0):
        _, _, xs, ys = lattice_centers(np.vstack(polygons), cell_m, margin_m)
        px, py = np.meshgrid(xs, ys)
        mask = np.zeros(px.shape, dtype=bool)
        for poly in polygons:
            poly = np.asarray(poly, dtype=float)
            ccw, cw = np.ones(px.shape, dtype=bool), np.ones(px.shape, dtype=bool)
            for a, b in zip(poly, np.roll(poly, -1, axis=0)):
                cross = (b[0] - a[0]) * (py - a[1]) - (b[1] - a[1]) * (px - a[0])
                ccw &= cross >= 0
                cw &= cross <= 0
            mask |= ccw | cw
        return mask

    triangle = np.array([[0.25, 0.25], [10.25, 0.25], [0.25, 7.75]])  # vertices and edges on cell centres
    maps = [[triangle], [triangle[::-1]]]
    maps += [Simulation(ScenarioParams(scenario=s, vehicles=5, seed=0, delta_s=0.0)).scenario.roadmap.to_msg().drivable
             for s in ("left_turn", "overtaking", "red_light")]
    for polygons in maps:
        got = DrivableRaster(polygons, 0.5).values
        want = reference(polygons, 0.5)
        assert got.any() and np.array_equal(got, want)


def test_a_mover_on_a_lane_takes_the_lane_direction_and_keeps_its_speed():
    from protocol.messages import Lane
    from vehicle_agent.dataplane import LaneDirections
    from vehicle_agent.tracking import Track

    lanes = LaneDirections([Lane("W", np.array([[50.0, 2.0], [-50.0, 2.0]]), 4.0, 10.0, -1, -1.0)])
    det = None

    def track(xy, vel):
        return Track(0, np.array(xy, float), np.array(vel, float), 0.0, det)

    oncoming = track([10.0, 2.5], [-8.0, -0.4])  # 2.9 degrees off the lane: snapped, same speed
    crossing = track([0.0, 2.0], [0.0, -8.0])  # across the lane: kept
    elsewhere = track([0.0, 9.0], [-8.0, -0.4])  # off the lane: kept
    parked = track([5.0, 2.0], [0.0, 0.0])
    lanes.snap([oncoming, crossing, elsewhere, parked])
    assert oncoming.velocity == pytest.approx([-np.hypot(8.0, 0.4), 0.0])
    assert crossing.velocity.tolist() == [0.0, -8.0] and elsewhere.velocity.tolist() == [-8.0, -0.4]
    assert parked.velocity.tolist() == [0.0, 0.0]


def _lane_segment_reference(xy, vel, a, d, length, half, snap_deg):
    """``LaneDirections.snap``'s choice as it was written in numpy over (T, S) arrays:
    the segment each mover is on (along, across and heading), nearest across, first on a
    tie; -1 if none."""
    speed = np.hypot(vel[:, 0], vel[:, 1])
    rel = xy[:, None, :] - a[None]
    along = np.einsum("tsk,sk->ts", rel, d)
    across = np.abs(rel[..., 0] * d[None, :, 1] - rel[..., 1] * d[None, :, 0])
    cos = (vel @ d.T) / np.maximum(speed, 1e-9)[:, None]
    on = (along >= 0) & (along <= length[None]) & (across <= half[None]) & (cos >= np.cos(np.radians(snap_deg)))
    score = np.where(on, across, np.inf)
    best = np.argmin(score, axis=1)
    return np.where(np.isfinite(score[np.arange(len(best)), best]), best, -1)


@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), movers=st.integers(1, 12), segments=st.integers(1, 60),
       twins=st.booleans())
def test_the_lane_segment_kernel_chooses_as_the_numpy_arrays_did(seed, movers, segments, twins):
    """``_lane_segment`` against the numpy statements it replaced, on random movers and
    segments (half of them repeated, ``twins``, for ties; some movers standing still)."""
    from vehicle_agent.dataplane import LaneDirections, _lane_segment

    rng = np.random.default_rng(seed)
    xy = rng.normal(0.0, 30.0, (movers, 2))
    vel = rng.normal(0.0, 8.0, (movers, 2)) * (rng.random((movers, 1)) > 0.2)
    a = rng.normal(0.0, 30.0, (segments, 2))
    d = rng.normal(0.0, 1.0, (segments, 2))
    d /= np.hypot(d[:, 0], d[:, 1])[:, None]
    length, half = rng.uniform(1.0, 60.0, segments), rng.uniform(1.0, 40.0, segments)
    if twins:
        k = segments // 2
        for col in (a, d, length, half):
            col[segments - k:] = col[:k]
    speed = np.hypot(vel[:, 0], vel[:, 1])
    got = _lane_segment(xy, vel, speed, a, d, length, half, float(np.cos(np.radians(LaneDirections.SNAP_DEG))))
    assert got.tolist() == _lane_segment_reference(xy, vel, a, d, length, half, LaneDirections.SNAP_DEG).tolist()


def test_decoding_a_batch_equals_decoding_each_payload_and_drops_the_malformed():
    from vehicle_agent.payload import decode_objects

    rng = np.random.default_rng(4)
    payloads, want = [], []
    for k in range(30):
        pts = rng.normal(0, 3, (int(rng.integers(0, 40)), 3)).astype(np.float32)
        obj = ObjectPayload(int(rng.integers(0, 64)), int(rng.integers(0, 1 << 31)), k, float(rng.uniform(0, 20)),
                            Pose(*rng.normal(0, 50, 3)), float(rng.uniform(1.5, 4)),
                            pts.mean(axis=0) if len(pts) else np.zeros(3, np.float32),
                            rng.normal(0, 5, 2).astype(np.float32), pts)
        raw = encode_object(obj)
        bad = (raw[:-1], b"XXXX" + raw[4:], raw[:10], raw[:4] + b"\x02" + raw[5:])[(k // 4) % 4] if k % 4 == 3 else None
        payloads.append(bad if bad is not None else raw)
        if bad is None:
            want.append(decode_object(raw))
    batch, refused = decode_objects(payloads)
    assert len(refused) == len(payloads) - len(want) > 0 and all(isinstance(e, MalformedMessage) for e in refused)
    assert batch.keys() == [(o.sender, o.object_id) for o in want]
    np.testing.assert_array_equal(batch.t_sim_s, [o.t_sim_s for o in want])
    np.testing.assert_array_equal(batch.sender_pose, [[o.sender_pose.x_m, o.sender_pose.y_m, o.sender_pose.yaw_rad]
                                                      for o in want])
    np.testing.assert_array_equal(batch.mount_height_m, [o.mount_height_m for o in want])
    np.testing.assert_array_equal(batch.velocity_xy, np.array([o.velocity_xy for o in want], dtype=np.float64))
    assert batch.points_sensor.dtype == np.float32
    np.testing.assert_array_equal(batch.points_sensor, np.concatenate([o.points_sensor for o in want]))
    assert batch.counts.tolist() == [len(o.points_sensor) for o in want]
    empty, refused = decode_objects([])
    assert len(empty) == 0 and refused == [] and empty.points_sensor.shape == (0, 3)


def test_encoding_a_senders_objects_at_once_equals_encoding_each():
    from vehicle_agent.payload import encode_objects

    rng = np.random.default_rng(12)
    pose = Pose(*rng.normal(0, 50, 2), float(rng.uniform(-np.pi, np.pi)))
    counts = np.array([5, 0, 1, 40, 17], dtype=np.int64)
    points = rng.normal(0, 4, (int(counts.sum()), 3)).astype(np.float32)
    centroids = rng.normal(0, 4, (len(counts), 3)).astype(np.float32)
    velocities = rng.normal(0, 5, (len(counts), 2)).astype(np.float32)
    ids = [int(i) for i in rng.integers(0, 1 << 31, len(counts))]
    got = encode_objects(9, 33, 3.3, pose, 1.9, ids, centroids, velocities, points, counts)
    ends = np.cumsum(counts)
    assert got == [encode_object(ObjectPayload(9, oid, 33, 3.3, pose, 1.9, centroids[k], velocities[k],
                                               points[ends[k] - counts[k]:ends[k]]))
                   for k, oid in enumerate(ids)]
    far = points.copy()
    far[ends[3] - 1, 0] = 400.0  # one object spans more than 327 m
    with pytest.raises(ValueError):
        encode_objects(9, 33, 3.3, pose, 1.9, ids, centroids, velocities, far, counts)


def _world_objects(rng, counts, spread_m):
    """A sender's pose and objects around it in the world: centroids (float64), points
    (float32, object after object), velocities."""
    pose = Pose(float(rng.normal(0, 300)), float(rng.normal(0, 300)), float(rng.uniform(-7, 7)))
    centroids = np.column_stack([pose.x_m + rng.normal(0, 60, len(counts)), pose.y_m + rng.normal(0, 60, len(counts)),
                                 rng.uniform(-1, 3, len(counts))])
    world = (np.repeat(centroids, counts, axis=0) + rng.normal(0, spread_m, (int(counts.sum()), 3))).astype(np.float32)
    return pose, centroids, world, rng.normal(0, 5, (len(counts), 2))


@pytest.mark.parametrize("seed", range(40))
def test_encoding_objects_from_the_world_in_one_pass_equals_taking_them_to_the_sensor_first(seed):
    """encode_world_objects gives encode_objects' bytes of the points world_to_sensor
    gives, rounded to float32: ties on the half centimetre, far objects, a point beyond
    int16 (refused alike) and a NaN (encode_objects' own values) among them."""
    from vehicle_agent.payload import encode_objects, encode_world_objects

    rng = np.random.default_rng(seed)
    counts = rng.integers(0, 300, int(rng.integers(1, 12))).astype(np.int64)
    pose, centroids, world, velocities = _world_objects(rng, counts, float(rng.uniform(0.1, 40)))
    if seed % 4 == 1:  # axes along the world's, everything on the half-centimetre grid: rint's ties
        pose, centroids = Pose(round(pose.x_m), round(pose.y_m), 0.0), np.round(centroids * 200) / 200
        world = (np.round(world * 200) / 200).astype(np.float32)
    ids = [int(i) for i in rng.integers(0, 1 << 31, len(counts))]
    if seed % 10 == 3 and counts.sum():
        world[int(rng.integers(counts.sum())), 0] += 400.0  # one object spans more than 327 m
    if seed % 10 == 7 and counts.sum():
        world[int(rng.integers(counts.sum())), 1] = np.nan

    def reference():
        sensor = world_to_sensor(world.astype(np.float64), pose, 1.9).astype(np.float32)
        return encode_objects(4, 21, 2.1, pose, 1.9, ids, world_to_sensor(centroids, pose, 1.9).astype(np.float32),
                              velocities.astype(np.float32), sensor, counts)

    with np.errstate(invalid="ignore"):  # a NaN cast to int16 (encode_objects casts it, either way)
        try:
            want = reference()
        except ValueError:
            with pytest.raises(ValueError):
                encode_world_objects(4, 21, 2.1, pose, 1.9, ids, centroids, velocities, world, counts)
            return
        assert encode_world_objects(4, 21, 2.1, pose, 1.9, ids, centroids, velocities, world, counts) == want


class _DictStore:
    """The received-object store one dict entry per object, as it was before the store
    became arrays: the slower reference."""

    def __init__(self, max_age_s: float = 1.0) -> None:
        self.max_age_s, self.last = max_age_s, {}

    def add_many(self, objs) -> None:
        newest = {}
        for obj in objs:
            key = (obj.sender, obj.object_id)
            prev = newest.get(key) or (self.last[key][0] if key in self.last else None)
            if prev is None or obj.t_sim_s >= prev.t_sim_s:
                newest[key] = obj
        for key, obj in newest.items():
            pts = obj.points_sensor
            mount = np.array(obj.mount_height_m, dtype=pts.dtype)
            c, s = np.cos(obj.sender_pose.yaw_rad), np.sin(obj.sender_pose.yaw_rad)
            self.last[key] = (obj, np.column_stack([obj.sender_pose.x_m + c * pts[:, 0] - s * pts[:, 1],
                                                    obj.sender_pose.y_m + s * pts[:, 0] + c * pts[:, 1],
                                                    (pts[:, 2] + mount).astype(np.float64)]))

    def current(self, t_now_s: float, fresh_keys):
        out = []
        for key in sorted(self.last):
            obj, world = self.last[key]
            age = t_now_s - obj.t_sim_s
            if age > self.max_age_s:
                del self.last[key]
                continue
            placed = world.copy()
            placed[:, :2] += obj.velocity_xy.astype(np.float64) * age
            out.append((key, placed, obj.velocity_xy.astype(np.float64), age, key in fresh_keys))
        return out


def test_the_store_keeps_the_same_objects_as_one_dict_entry_per_object():
    """Ticks of random receptions (repeated keys, late copies older than the one held,
    objects that age out): the array store holds and places exactly what the per-object
    reference does."""
    from vehicle_agent.fusion import ReceivedStore
    from vehicle_agent.payload import decode_objects

    rng = np.random.default_rng(5)
    store, ref = ReceivedStore(), _DictStore()
    for tick in range(40):
        t_now = 2.0 + tick * 0.1  # every time it draws after the run's start (a payload's t_sim_s >= 0)
        objs = []
        for _ in range(int(rng.integers(0, 25))):
            pts = rng.normal(0, 2, (int(rng.integers(0, 30)), 3)).astype(np.float32)
            objs.append(ObjectPayload(int(rng.integers(0, 6)), int(rng.integers(0, 8)), tick,
                                      float(np.float32(t_now - rng.choice([0.0, 0.0, 0.1, 0.3, 1.2]))),
                                      Pose(*rng.normal(0, 40, 3)), float(np.float32(rng.uniform(1.5, 4))),
                                      pts.mean(axis=0) if len(pts) else np.zeros(3, np.float32),
                                      rng.normal(0, 8, 2).astype(np.float32), pts))
        batch, refused = decode_objects([encode_object(o) for o in objs])
        decoded = [decode_object(encode_object(o)) for o in objs]
        store.add_batch(batch)
        ref.add_many(decoded)
        fresh = set(batch.keys())
        got, want = store.current(t_now, fresh), ref.current(t_now, fresh)
        assert got.keys == [w[0] for w in want] and refused == []
        assert got.fresh.tolist() == [w[4] for w in want]
        np.testing.assert_array_equal(got.age_s, [w[3] for w in want])
        np.testing.assert_array_equal(got.velocity, np.array([w[2] for w in want]).reshape(-1, 2))
        assert got.counts.tolist() == [len(w[1]) for w in want]
        np.testing.assert_array_equal(got.points, np.concatenate([w[1] for w in want]) if want else np.zeros((0, 3)))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_the_newest_receptions_and_the_merged_keys_equal_their_lexsort_formulations(seed):
    """_newest and _merge_rows against the numpy statements they replaced: repeated keys,
    equal and NaN capture times (np.lexsort puts NaN last), held copies newer, older and
    as old."""
    from vehicle_agent.fusion import _merge_rows, _newest

    rng = np.random.default_rng(seed)
    held_key = np.unique(rng.integers(0, 30, int(rng.integers(0, 20))))
    held_t = rng.choice([0.0, 0.1, 0.2, np.nan], len(held_key))
    key = rng.integers(0, 30, int(rng.integers(1, 40)))
    t = rng.choice([0.0, 0.1, 0.2, 0.3, np.nan], len(key))
    order = np.lexsort((np.arange(len(key)), t, key))
    last = np.ones(len(order), dtype=bool)
    last[:-1] = key[order][1:] != key[order][:-1]
    win = order[last]
    at = np.minimum(np.searchsorted(held_key, key[win]), max(len(held_key) - 1, 0))
    held = np.where(len(held_key) and (held_key[at] == key[win]), at, -1) if len(held_key) else np.full(len(win), -1)
    newer = held < 0
    newer[~newer] = t[win][~newer] >= held_t[held[~newer]]
    want = win[newer]
    got = _newest(held_key, held_t, key, t)
    assert got.tolist() == want.tolist()
    stacked = np.concatenate([held_key[~np.isin(held_key, key[got])], key[got]])
    rows = _merge_rows(held_key, key[got])
    assert np.concatenate([held_key, key[got]])[rows].tolist() == np.sort(stacked).tolist()


def test_not_me_and_not_contradicted_match_their_numpy_formulations():
    """The single-pass kernels against the whole-array numpy statements they replaced,
    on moving, aged objects near a short history of poses (so points are tested where
    they were captured too, and some objects merged us with something else)."""
    from vehicle_agent.fusion import MERGED_SHARE, SELF_SHARE, SharedBatch, SharedObject, not_contradicted, not_me
    from vehicle_agent.fusion import on_body

    def not_me_reference(shared, poses, length_m, width_m):
        pts, counts = shared.points, shared.counts
        shift = np.repeat(shared.velocity * shared.age_s[:, None], counts, axis=0)
        mine = np.zeros(len(pts), dtype=bool)
        for xy in (pts[:, :2], pts[:, :2] - shift):
            for pose in poses:
                mine |= on_body(xy, pose, length_m, width_m)
        share = np.bincount(shared.owner, weights=mine, minlength=len(shared)) / np.maximum(counts, 1)
        merged = (share >= MERGED_SHARE) & (share < SELF_SHARE)
        points = pts.copy()
        points[:, :2] -= np.repeat(np.where(merged[:, None], shared.velocity * shared.age_s[:, None], 0.0), counts,
                                   axis=0)
        keep = (counts > 0) & (share < SELF_SHARE)
        point_kept = np.repeat(keep, counts) & ~mine
        return ([k for k, ok in zip(shared.keys, keep) if ok], points[point_kept],
                np.where(merged[:, None], 0.0, shared.velocity)[keep])

    rng = np.random.default_rng(6)
    n_merged = 0
    for _ in range(30):
        poses = [Pose(float(x), float(y), float(h)) for x, y, h in
                 np.cumsum(rng.normal(0.0, [1.0, 1.0, 0.1], (int(rng.integers(1, 8)), 3)), axis=0)]
        shared = SharedBatch.of([SharedObject((1, i), np.column_stack([rng.normal(rng.uniform(-6, 6), 1.5, n),
                                                                      rng.normal(rng.uniform(-6, 6), 1.0, n),
                                                                      rng.uniform(0, 2, n)]),
                                              rng.normal(0, 4, 2), float(rng.uniform(0, 1)), bool(rng.random() < .5))
                                 for i, n in enumerate(rng.integers(1, 60, 20))])
        got = not_me(shared, poses, 4.5, 1.8)
        keys, points, velocity = not_me_reference(shared, poses, 4.5, 1.8)
        n_merged += int((velocity == 0.0).all(axis=1).sum())
        assert got.keys == keys
        np.testing.assert_array_equal(got.points, points)
        np.testing.assert_array_equal(got.velocity, velocity)
        # not_contradicted: a stale object is gone where half its in-grid points are on ground
        spec = GridSpec(half_extent_m=8.0)
        n = spec.cells
        state = rng.choice(np.array([EMPTY, GROUND, ABOVE], dtype=np.uint8), (n, n), p=[0.3, 0.5, 0.2])
        grid = Grid(spec, -n // 2, -n // 2, state, np.ones((n, n), dtype=bool))
        rc = grid.cell_of(got.points[:, :2])
        inside = (rc[:, 0] >= 0) & (rc[:, 0] < n) & (rc[:, 1] >= 0) & (rc[:, 1] < n)
        ground = np.zeros(len(rc), dtype=bool)
        ground[inside] = state[rc[inside, 0], rc[inside, 1]] == GROUND
        n_in = np.bincount(got.owner[inside], minlength=len(got))
        n_ground = np.bincount(got.owner[ground], minlength=len(got))
        gone = ~got.fresh & (got.counts > 0) & (n_in > 0) & (n_ground >= 0.5 * n_in)
        assert not_contradicted(got, grid).keys == [k for k, g in zip(got.keys, gone) if not g]
    assert n_merged > 0  # the merged branch ran


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_placing_the_received_objects_in_one_pass_equals_current_not_me_not_contradicted(seed):
    """shared_now against the three steps it fuses (each tested against its own
    reference above), interval after interval on one store: receptions of moving
    objects around a short history of our poses (some points ours, some objects merged
    us with something), late and aged-out copies, a grid that sees bare ground under
    some carried-forward objects. The same objects, points and values, bit for bit."""
    from vehicle_agent.fusion import ReceivedStore, not_contradicted, not_me, shared_now

    a, b = ReceivedStore(), ReceivedStore()
    for t_now, poses, batch, grid in received_intervals(np.random.default_rng(seed), 12, xy_half_m=8.0, z_low_m=0.0):
        a.add_batch(batch)
        b.add_batch(batch)
        want = not_contradicted(not_me(a.current(t_now, set(batch.keys())), poses, 4.5, 1.8), grid)
        got = shared_now(b, t_now, (batch.sender, batch.object_id), poses, 4.5, 1.8, grid)
        assert got.keys == want.keys
        for name in ("points", "counts", "velocity", "age_s", "fresh"):
            x, y = getattr(got, name), getattr(want, name)
            assert x.dtype == y.dtype, name
            np.testing.assert_array_equal(x, y, err_msg=name)


def test_corners_of_many_objects_equal_each_objects_corners():
    from vehicle_agent.perception import DetectedObject, corners_of

    rng = np.random.default_rng(7)
    objs = [DetectedObject(np.zeros((1, 3), np.float32), np.zeros((1, 2), np.int64), rng.normal(0, 80, 3),
                           float(rng.uniform(-np.pi, np.pi)), float(rng.uniform(0.2, 12)), float(rng.uniform(0.2, 3)))
            for _ in range(200)]
    np.testing.assert_array_equal(corners_of(objs), np.array([o.corners() for o in objs]))
    assert corners_of([]).shape == (0, 4, 2)


@njit
def _visible_share_reference(viewers, ranges, targets, occluders, target_as_occluder, self_target, n_rays):
    J, K, O = viewers.shape[0], targets.shape[0], occluders.shape[0]
    share = np.zeros((J, K))
    occ_lo = np.empty(O)
    occ_hi = np.empty(O)
    skip = np.zeros(O, dtype=np.bool_)
    for j in range(J):
        px, py = viewers[j, 0], viewers[j, 1]
        own = target_as_occluder[self_target[j]] if self_target[j] >= 0 else -1
        for o in range(O):
            # j's own body (as i sees it) does not hide anything from j
            skip[o] = o == own or _inside(px, py, occluders[o])
            cx = 0.25 * (occluders[o, 0, 0] + occluders[o, 1, 0] + occluders[o, 2, 0] + occluders[o, 3, 0])
            cy = 0.25 * (occluders[o, 0, 1] + occluders[o, 1, 1] + occluders[o, 2, 1] + occluders[o, 3, 1])
            base = np.arctan2(cy - py, cx - px)
            lo, hi = np.inf, -np.inf
            for c in range(4):
                a = np.arctan2(occluders[o, c, 1] - py, occluders[o, c, 0] - px) - base
                a = (a + np.pi) % (2 * np.pi) - np.pi
                lo, hi = min(lo, a), max(hi, a)
            occ_lo[o], occ_hi[o] = lo + base, hi + base
        for k in range(K):
            tk = targets[k]
            cx = 0.25 * (tk[0, 0] + tk[1, 0] + tk[2, 0] + tk[3, 0])
            cy = 0.25 * (tk[0, 1] + tk[1, 1] + tk[2, 1] + tk[3, 1])
            if k == self_target[j] or _inside(px, py, tk):
                share[j, k] = 1.0  # j itself: nothing to send it
                continue
            if np.hypot(cx - px, cy - py) > ranges[j]:
                continue
            base = np.arctan2(cy - py, cx - px)
            lo, hi = np.inf, -np.inf
            for c in range(4):
                a = np.arctan2(tk[c, 1] - py, tk[c, 0] - px) - base
                a = (a + np.pi) % (2 * np.pi) - np.pi
                lo, hi = min(lo, a), max(hi, a)
            seen = 0
            for r in range(n_rays):
                ang = base + lo + (hi - lo) * (r + 0.5) / n_rays
                dx, dy = np.cos(ang), np.sin(ang)
                t_target = _ray_rect(px, py, dx, dy, tk)
                if not np.isfinite(t_target):
                    t_target = np.hypot(cx - px, cy - py)
                blocked = False
                for o in range(O):
                    if skip[o] or o == target_as_occluder[k]:  # no test of distance: every occluder in the ray's way
                        continue
                    rel = (ang - occ_lo[o] + np.pi) % (2 * np.pi) - np.pi
                    if rel < 0.0 or rel > occ_hi[o] - occ_lo[o]:
                        continue
                    if _ray_rect(px, py, dx, dy, occluders[o]) < t_target:
                        blocked = True
                        break
                if not blocked:
                    seen += 1
            share[j, k] = seen / n_rays
    return share


def _crowded_footprints(rng: np.random.Generator, n_targets: int, n_buildings: int) -> np.ndarray:
    """(n_targets + n_buildings, 4, 2) random footprints in a 120 m square: targets of
    0.5-12 x 0.5-3 m, then buildings of 10-60 m a side."""
    n = n_targets + n_buildings
    boxes = np.column_stack([rng.uniform(-60, 60, n), rng.uniform(-60, 60, n), rng.uniform(-np.pi, np.pi, n),
                             np.r_[rng.uniform(0.5, 12, n_targets), rng.uniform(10, 60, n_buildings)],
                             np.r_[rng.uniform(0.5, 3, n_targets), rng.uniform(10, 60, n_buildings)]])
    return np.array([box_corners(*b) for b in boxes]).reshape(-1, 4, 2)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_visible_share_equals_testing_every_occluder_on_every_ray(seed):
    """The kernel, which runs the per-ray test only on occluders whose angular extent
    meets the target's and whose nearest point is nearer than the ray's hit, against
    one that tests every occluder in the ray's way, however far: the same shares, bit
    for bit, in crowded random scenes (viewers inside boxes, boxes touching, targets
    that are their own occluders, far buildings, long walls beside a viewer)."""
    from vehicle_agent import spatial

    rng = np.random.default_rng(seed)
    n_t, n_b, n_v = int(rng.integers(0, 25)), int(rng.integers(0, 6)), int(rng.integers(1, 30))
    corners = _crowded_footprints(rng, n_t, n_b)
    targets = corners[:n_t]
    viewers = np.concatenate([rng.uniform(-70, 70, (n_v, 2)), corners[:min(n_t, 3), 0] * 0.999]).reshape(-1, 2)
    ranges = rng.uniform(20, 120, len(viewers))
    target_as_occluder = np.arange(n_t)
    self_target = np.where(rng.random(len(viewers)) < 0.2, rng.integers(-1, max(n_t, 1), len(viewers)), -1)
    self_target[self_target >= n_t] = -1
    args = (viewers, ranges, targets, corners, target_as_occluder.astype(np.int64), self_target.astype(np.int64), 9)
    np.testing.assert_array_equal(spatial._visible_share(*args), _visible_share_reference(*args))


@given(dx=st.floats(-1e6, 1e6), dy=st.floats(-1e6, 1e6), bound=st.floats(-1.0, 2e6), nudge=st.integers(-3, 3))
def test_the_cheap_distance_test_decides_as_hypot(dx, dy, bound, nudge):
    """spatial._farther against np.hypot(dx, dy) > bound, also with the bound a few ulps
    from the distance itself (where only hypot can tell)."""
    from vehicle_agent.spatial import _farther

    assert _farther(dx, dy, bound) == (np.hypot(dx, dy) > bound)
    at = float(np.hypot(dx, dy))
    for _ in range(abs(nudge)):
        at = float(np.nextafter(at, np.inf if nudge > 0 else -np.inf))
    assert _farther(dx, dy, at) == (np.hypot(dx, dy) > at)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n_rays=st.integers(1, 12))
def test_visible_stops_casting_once_v_is_settled_and_agrees_with_the_share(seed, n_rays):
    """``spatial.visible``, which stops casting a target's rays once v is settled, against
    the paper's v from every ray's share (``visibility(visible_share(...))``), in crowded
    random scenes."""
    from vehicle_agent.spatial import visible

    rng = np.random.default_rng(seed)
    n_t, n_b, n_v = int(rng.integers(0, 20)), int(rng.integers(0, 5)), int(rng.integers(1, 25))
    corners = _crowded_footprints(rng, n_t, n_b)
    viewers = rng.uniform(-70, 70, (n_v, 2))
    ranges = rng.uniform(20, 120, n_v)
    args = (viewers, ranges, corners[:n_t], corners, np.arange(n_t))
    expected = visibility(visible_share(*args, n_rays=n_rays))
    np.testing.assert_array_equal(visible(*args, n_rays=n_rays), expected)
    assert expected.dtype == np.float32
