"""LiDAR sensor model against hand-derived geometry and a brute-force caster."""

from __future__ import annotations

import math

import numpy as np
import pytest

from protocol.messages import LidarConfig, Pose, Scan
from world_server.lidar import prepare_boxes, range_image_prepared, scan, scan_many, scan_prepared

CFG = LidarConfig()  # 64 beams, +2.0 .. -24.8 deg, 1800 azimuths, 100 m
H = 1.9  # car mount height
ELEV_DEG = np.linspace(2.0, -24.8, 64)  # beam i: 2.0 - 0.425397 i degrees
CAR = (4.5, 1.8, 1.5)
TRUCK = (9.0, 2.5, 3.5)


def box(cx: float, cy: float, yaw: float, size: tuple[float, float, float]) -> list[float]:
    return [cx, cy, yaw, *size]


def column(points: np.ndarray, az_index: int) -> np.ndarray:
    """Mask of the points on the ray column at azimuth -pi + az_index * 0.2 deg."""
    az = np.arctan2(points[:, 1], points[:, 0])
    want = -math.pi + az_index * 2.0 * math.pi / CFG.azimuth_steps
    diff = np.angle(np.exp(1j * (az - want)))
    return np.abs(diff) < 1e-4


def elevation_deg(points: np.ndarray) -> np.ndarray:
    return np.degrees(np.arctan2(points[:, 2], np.hypot(points[:, 0], points[:, 1])))


def beam_index(points: np.ndarray) -> np.ndarray:
    idx = np.rint((2.0 - elevation_deg(points)) / (26.8 / 63)).astype(int)
    return idx


def test_ground_rings_at_exact_radius_and_count() -> None:
    pts, lbl = scan(np.zeros((0, 6)), np.zeros(3), H, CFG)
    # beam i returns ground within 100 m iff 1.9 / sin(-theta_i) <= 100, i.e. theta <= -1.0887
    # deg: beams 8..63 (theta_8 = -1.403 deg, theta_7 = -0.978 deg), 56 beams x 1800 columns
    assert pts.dtype == np.float32 and lbl.dtype == np.int32
    assert pts.shape == (56 * 1800, 3)
    assert np.all(lbl == -1)
    np.testing.assert_allclose(pts[:, 2], -H, atol=1e-6)
    radius = np.hypot(pts[:, 0], pts[:, 1]).reshape(1800, 56)
    lowest = H / math.tan(math.radians(24.8))  # 4.1118 m
    np.testing.assert_allclose(radius[:, -1], lowest, atol=1e-3)
    beam8 = H / math.tan(math.radians(-(2.0 - 8 * 26.8 / 63)))  # 77.58 m
    np.testing.assert_allclose(radius[:, 0], beam8, atol=1e-2)


def test_box_straight_ahead_face_and_top() -> None:
    pts, lbl = scan(np.array([box(10.0, 0.0, 0.0, CAR)]), np.zeros(3), H, CFG)
    mine = pts[lbl == 0]
    # near face at x = 10 - 4.5/2 = 7.75 m, spanning y in +-0.9
    assert mine[:, 0].min() == pytest.approx(7.75, abs=1e-3)
    assert np.abs(mine[:, 1]).max() <= 0.9 + 1e-3
    # the azimuth-0 column (index 900): side hits where 0 <= 1.9 + 7.75 tan(theta) <= 1.5,
    # i.e. theta in [-13.78, -2.95] deg -> beams 12..37; each at 3-D range 7.75 / cos(theta)
    col = column(mine, 900)
    side = mine[col & (mine[:, 2] < -0.4 - 1e-4)]
    side_beams = sorted(beam_index(side).tolist())
    assert side_beams == list(range(12, 38))
    rng = np.linalg.norm(side, axis=1)
    expected = 7.75 / np.cos(np.radians(ELEV_DEG[side_beams]))
    np.testing.assert_allclose(np.sort(rng), np.sort(expected), atol=1e-3)
    # roof (z = 1.5 - 1.9 = -0.4) hit by beams 10 and 11 (they reach 1.5 m at 10.17 / 8.55 m,
    # inside the box's 7.75..12.25 m); beam 9 reaches it at 12.53 m, past the far side
    roof = mine[col & (np.abs(mine[:, 2] + 0.4) < 1e-4)]
    assert sorted(beam_index(roof).tolist()) == [10, 11]
    for p, i in zip(roof, beam_index(roof)):
        assert p[0] == pytest.approx(0.4 / math.tan(math.radians(-ELEV_DEG[i])), abs=1e-3)
    # ground beyond the box in that column: only beams 8 and 9, which pass over the roof
    ground_col = pts[column(pts, 900) & (lbl == -1)]
    past = ground_col[np.hypot(ground_col[:, 0], ground_col[:, 1]) > 7.75]
    assert sorted(beam_index(past).tolist()) == [8, 9]


def test_box_behind_truck_is_fully_occluded() -> None:
    boxes = np.array([box(20.0, 0.0, 0.0, TRUCK), box(30.0, 0.0, 0.0, CAR)])
    _, lbl = scan(boxes, np.zeros(3), H, CFG)
    assert np.count_nonzero(lbl == 0) > 500
    assert np.count_nonzero(lbl == 1) == 0


def test_low_box_seen_over_a_lower_obstacle_only_where_geometry_allows() -> None:
    # sensor at 3.8 m; obstacle A: x 9..11, 2.0 m tall; target B: x 20..24, 1.5 m tall.
    # On the azimuth-0 column a beam reaches B iff it clears A (3.8 + 11 tan > 2.0, theta >
    # -9.29 deg) and hits B's side (0 <= 3.8 + 20 tan <= 1.5) or B's roof before x = 24
    # (theta <= -5.47 deg): beams 18..26.
    boxes = np.array([box(10.0, 0.0, 0.0, (2.0, 4.0, 2.0)), box(22.0, 0.0, 0.0, (4.0, 1.8, 1.5))])
    pts, lbl = scan(boxes, np.zeros(3), 3.8, CFG)
    col = column(pts, 900)
    assert sorted(beam_index(pts[col & (lbl == 1)]).tolist()) == list(range(18, 27))


def test_box_beyond_range_gets_no_points() -> None:
    far = np.array([box(105.0, 0.0, 0.0, CAR)])  # near face at 102.75 m
    _, lbl = scan(far, np.zeros(3), H, CFG)
    assert np.count_nonzero(lbl == 0) == 0
    # near face at 98 m: beams with theta in [-1.11, -0.23] deg hit it (beams 6 and 7)
    near = np.array([box(100.25, 0.0, 0.0, CAR)])
    pts, lbl = scan(near, np.zeros(3), H, CFG)
    assert set(beam_index(pts[lbl == 0]).tolist()) == {6, 7}
    assert np.linalg.norm(pts[lbl == 0], axis=1).max() <= CFG.range_m


def test_rotated_box_points_lie_on_its_surface() -> None:
    cx, cy, yaw = 15.0, 5.0, math.pi / 4
    sx, sy, syaw = 2.0, -3.0, 0.3
    pts, lbl = scan(np.array([box(cx, cy, yaw, CAR)]), np.array([sx, sy, syaw]), H, CFG)
    mine = pts[lbl == 0].astype(np.float64)
    assert len(mine) > 200
    # sensor frame -> world -> box frame
    wx = sx + math.cos(syaw) * mine[:, 0] - math.sin(syaw) * mine[:, 1]
    wy = sy + math.sin(syaw) * mine[:, 0] + math.cos(syaw) * mine[:, 1]
    wz = mine[:, 2] + H
    u = (wx - cx) * math.cos(yaw) + (wy - cy) * math.sin(yaw)
    v = -(wx - cx) * math.sin(yaw) + (wy - cy) * math.cos(yaw)
    hl, hw, height = CAR[0] / 2, CAR[1] / 2, CAR[2]
    assert np.all(np.abs(u) <= hl + 0.01)
    assert np.all(np.abs(v) <= hw + 0.01)
    assert np.all((wz >= -0.01) & (wz <= height + 0.01))
    to_surface = np.minimum.reduce([hl - np.abs(u), hw - np.abs(v), height - wz])
    assert np.all(to_surface <= 0.01)


def test_box_straddling_the_azimuth_wrap_is_hit_on_both_sides() -> None:
    # near face 7.75 m away, half-width 0.9 m: half-angle atan(0.9 / 7.75) = 6.624 deg,
    # so columns within 33 steps of 0.2 deg either side: 67 columns, behind as in front
    behind, lbl_b = scan(np.array([box(-10.0, 0.0, 0.0, CAR)]), np.zeros(3), H, CFG)
    front, lbl_f = scan(np.array([box(10.0, 0.0, 0.0, CAR)]), np.zeros(3), H, CFG)
    mine = behind[lbl_b == 0]
    assert np.count_nonzero(mine[:, 1] > 0.01) > 0
    assert np.count_nonzero(mine[:, 1] < -0.01) > 0
    ahead = front[lbl_f == 0]
    az_b = np.unique(np.rint(np.degrees(np.arctan2(mine[:, 1], mine[:, 0])) * 5) % 1800)
    az_f = np.unique(np.rint(np.degrees(np.arctan2(ahead[:, 1], ahead[:, 0])) * 5))
    assert len(az_b) == 67
    assert len(az_f) == 67
    assert np.count_nonzero(lbl_b == 0) == np.count_nonzero(lbl_f == 0)


def test_skip_box_suppresses_own_body() -> None:
    own = box(0.0, 0.0, 0.0, CAR)
    other = box(10.0, 3.0, 0.5, CAR)
    pts_skip, lbl_skip = scan(np.array([own, other]), np.zeros(3), H, CFG, skip_box=0)
    pts_alone, lbl_alone = scan(np.array([other]), np.zeros(3), H, CFG)
    assert np.count_nonzero(lbl_skip == 0) == 0
    np.testing.assert_array_equal(pts_skip, pts_alone)
    np.testing.assert_array_equal(lbl_skip, np.where(lbl_alone == 0, 1, lbl_alone))
    # not skipped, a roof-mounted sensor (1.9 m over a 1.5 m body) sees its own roof:
    # a beam reaches z = 1.5 at 0.4 / tan(-theta) <= 0.9 m sideways for theta <= -23.96 deg
    pts_own, lbl_own = scan(np.array([own, other]), np.zeros(3), H, CFG)
    roof = pts_own[lbl_own == 0]
    assert len(roof) > 0
    np.testing.assert_allclose(roof[:, 2], -0.4, atol=1e-4)
    assert np.all(np.abs(roof[:, 0]) <= 2.25 + 1e-3) and np.all(np.abs(roof[:, 1]) <= 0.9 + 1e-3)


def test_sensor_pose_transform() -> None:
    # sensor at the origin facing world +y (yaw pi/2): its x axis is world +y, its y axis
    # (left) is world -x. A box at world (10, 0) lies to its right: near face at y = -7.75.
    pts, lbl = scan(np.array([box(10.0, 0.0, 0.0, CAR)]), np.array([0.0, 0.0, math.pi / 2]), H, CFG)
    mine = pts[lbl == 0]
    assert mine[:, 1].max() == pytest.approx(-7.75, abs=1e-3)
    assert np.abs(mine[:, 0]).max() <= 0.9 + 1e-3
    # sensor at (20, 5) facing world -x (yaw pi); a box at (10, 5) turned by pi/2 shows its
    # 1.8 m width along the view: near face at world x = 10.9, i.e. 9.1 m straight ahead
    pts, lbl = scan(
        np.array([box(10.0, 5.0, math.pi / 2, CAR)]), np.array([20.0, 5.0, math.pi]), H, CFG
    )
    mine = pts[lbl == 0]
    assert mine[:, 0].min() == pytest.approx(9.1, abs=1e-3)
    assert np.abs(mine[:, 1]).max() <= 2.25 + 1e-3


def random_scene(rng: np.random.Generator, m: int) -> np.ndarray:
    """m boxes with non-overlapping circumcircles, none over the origin."""
    out: list[list[float]] = []
    while len(out) < m:
        size = CAR if rng.random() < 0.7 else TRUCK
        c = rng.uniform(-60, 60, 2)
        r = math.hypot(size[0], size[1]) / 2
        if any(math.hypot(*(c - b[:2])) < r + math.hypot(b[3], b[4]) / 2 for b in out):
            continue
        out.append(box(c[0], c[1], rng.uniform(-math.pi, math.pi), size))
    return np.array(out)


def test_scan_many_equals_repeated_scan() -> None:
    rng = np.random.default_rng(7)
    boxes = random_scene(rng, 30)
    k = 6
    sensors = np.column_stack([boxes[:k, 0], boxes[:k, 1], boxes[:k, 2]])
    heights = np.where(boxes[:k, 5] > 2.0, 3.8, 1.9)
    skips = np.arange(k)
    many = scan_many(boxes, sensors, heights, CFG, skips)
    assert len(many) == k
    for i, (pts, lbl, _) in enumerate(many):
        ref_pts, ref_lbl = scan(boxes, sensors[i], heights[i], CFG, skip_box=i)
        np.testing.assert_array_equal(pts, ref_pts)
        np.testing.assert_array_equal(lbl, ref_lbl)
        assert np.count_nonzero(lbl == i) == 0


def brute_force(boxes: np.ndarray, pose: np.ndarray, h: float, cfg: LidarConfig, skip: int):
    """Every ray against every box, no culling: (beams, steps) horizontal hit distance, label."""
    elev = cfg.elevations_rad()[:, None]
    az = cfg.azimuths_rad()[None, :]
    tan_t = np.tan(elev) * np.ones_like(az)
    dx, dy = np.cos(az + pose[2]) * np.ones_like(elev), np.sin(az + pose[2]) * np.ones_like(elev)
    best = np.where(elev < 0, h / np.tan(-np.minimum(elev, -1e-12)), np.inf) * np.ones_like(az)
    label = np.where(np.isfinite(best), -1, -2)
    for k, (cx, cy, yaw, length, width, height) in enumerate(boxes):
        if k == skip:
            continue
        ox, oy = pose[0] - cx, pose[1] - cy
        ou, ov = ox * math.cos(yaw) + oy * math.sin(yaw), -ox * math.sin(yaw) + oy * math.cos(yaw)
        du = dx * math.cos(yaw) + dy * math.sin(yaw)
        dv = -dx * math.sin(yaw) + dy * math.cos(yaw)
        with np.errstate(divide="ignore", invalid="ignore"):
            a1, a2 = (-length / 2 - ou) / du, (length / 2 - ou) / du
            b1, b2 = (-width / 2 - ov) / dv, (width / 2 - ov) / dv
        t_in = np.maximum(np.minimum(a1, a2), np.minimum(b1, b2))
        t_out = np.minimum(np.maximum(a1, a2), np.maximum(b1, b2))
        ok = (t_in <= t_out) & (t_in >= 0)
        z_in = h + t_in * tan_t
        side = ok & (z_in >= 0) & (z_in <= height)
        with np.errstate(divide="ignore", invalid="ignore"):
            d_top = (height - h) / tan_t
        top = ok & (z_in > height) & (tan_t < 0) & (d_top <= t_out)
        d = np.where(side, t_in, np.where(top, d_top, np.inf))
        better = d < best
        best = np.where(better, d, best)
        label = np.where(better, k, label)
    in_range = best / np.cos(elev) <= cfg.range_m
    label = np.where(in_range, label, -2)
    return best, label


def test_matches_brute_force_on_random_scenes() -> None:
    cfg = LidarConfig(beams=32, azimuth_steps=720)
    rng = np.random.default_rng(3)
    boxes = random_scene(rng, 25)
    for i in range(4):
        pose = np.array([boxes[i, 0], boxes[i, 1], rng.uniform(-math.pi, math.pi)])
        h = 3.8 if boxes[i, 5] > 2.0 else 1.9
        pts, lbl = scan(boxes, pose, h, cfg, skip_box=i)
        best, ref_label = brute_force(boxes, pose, h, cfg, i)
        order = ref_label.T  # the scan is azimuth-major
        keep = order != -2
        np.testing.assert_array_equal(lbl, order[keep])
        d_ref = best.T[keep]
        np.testing.assert_allclose(np.hypot(pts[:, 0], pts[:, 1]), d_ref, rtol=1e-5, atol=1e-4)


def test_range_image_carries_the_points() -> None:
    """The range image the world sends decodes to the sweep's points: same rays, same
    order, within the 0.5 cm rounding of the horizontal distance."""
    rng = np.random.default_rng(3)
    boxes = random_scene(rng, 25)
    sweep = scan_many(boxes, boxes[:1, :3], np.array([1.9]), CFG, np.array([0]))[0]
    assert sweep.range_cm.shape == (CFG.azimuth_steps, CFG.beams) and sweep.range_cm.dtype == np.uint16
    assert np.count_nonzero(sweep.range_cm) == len(sweep.points)
    back = Scan(0, 0.0, 0, Pose(0, 0, 0), 0.0, sweep.range_cm).points(CFG)
    horiz_err = np.abs(np.hypot(back[:, 0], back[:, 1]) - np.hypot(sweep.points[:, 0], sweep.points[:, 1]))
    assert horiz_err.max() <= 0.005 + 1e-4
    np.testing.assert_allclose(back, sweep.points, atol=0.006)


def test_range_image_alone_equals_the_sweeps() -> None:
    """``range_image_prepared`` (what the world casts for most vehicles) gives the very
    range image ``scan_prepared`` does, and counts each box's rays as its labels do."""
    rng = np.random.default_rng(5)
    boxes = random_scene(rng, 30)
    prepared = prepare_boxes(boxes)
    for i in range(6):
        pose = np.array([boxes[i, 0], boxes[i, 1], rng.uniform(-math.pi, math.pi)])
        h = 3.8 if boxes[i, 5] > 2.0 else 1.9
        sweep = scan_prepared(prepared, pose, h, CFG, i)
        image = range_image_prepared(prepared, pose, h, CFG, i)
        np.testing.assert_array_equal(image.range_cm, sweep.range_cm)
        hit = sweep.labels[sweep.labels >= 0]
        np.testing.assert_array_equal(image.box_hits, np.bincount(hit, minlength=len(boxes)))
        assert image.box_hits[i] == 0 and image.box_hits.sum() > 0
