"""The agent's spatial-reasoning and fusion kernels against the code they replaced
(kept here as the reference, as it stood at ec93cfa): the same values, bit for bit,
in random scenes, and hand-derived cases."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from numba import njit

from vehicle_agent import spatial
from vehicle_agent.spatial import _inside, _ray_rect, rays_needed
from world_server.geometry import box_corners

from tests.fusion_scenes import received_intervals


@njit
def _quad_distance_ec93cfa(px, py, quad):
    best = np.inf
    for e in range(4):
        ax, ay = quad[e, 0], quad[e, 1]
        ex, ey = quad[(e + 1) % 4, 0] - ax, quad[(e + 1) % 4, 1] - ay
        len2 = ex * ex + ey * ey
        t = 0.0 if len2 == 0.0 else min(max(((px - ax) * ex + (py - ay) * ey) / len2, 0.0), 1.0)
        best = min(best, np.hypot(ax + t * ex - px, ay + t * ey - py))
    return best * (1.0 - 1e-9) - 1e-9


@njit
def _occluder_extent_ec93cfa(px, py, quad):
    cx = 0.25 * (quad[0, 0] + quad[1, 0] + quad[2, 0] + quad[3, 0])
    cy = 0.25 * (quad[0, 1] + quad[1, 1] + quad[2, 1] + quad[3, 1])
    base = np.arctan2(cy - py, cx - px)
    lo, hi = np.inf, -np.inf
    for c in range(4):
        a = np.arctan2(quad[c, 1] - py, quad[c, 0] - px) - base
        a = (a + np.pi) % (2 * np.pi) - np.pi
        lo, hi = min(lo, a), max(hi, a)
    return lo + base, hi + base


@njit
def _visible_share_ec93cfa(viewers, ranges, targets, occluders, target_as_occluder, self_target, n_rays, need=0):
    """``spatial._visible_share`` as it stood at ec93cfa."""
    J, K, O = viewers.shape[0], targets.shape[0], occluders.shape[0]
    share = np.zeros((J, K))
    occ_lo = np.empty(O)
    occ_hi = np.empty(O)
    occ_near = np.empty(O)
    state = np.zeros(O, dtype=np.int8)
    cand = np.empty(O, dtype=np.int64)
    for j in range(J):
        px, py = viewers[j, 0], viewers[j, 1]
        own = target_as_occluder[self_target[j]] if self_target[j] >= 0 else -1
        for o in range(O):
            state[o] = 0
            occ_near[o] = _quad_distance_ec93cfa(px, py, occluders[o])
        for k in range(K):
            tk = targets[k]
            cx = 0.25 * (tk[0, 0] + tk[1, 0] + tk[2, 0] + tk[3, 0])
            cy = 0.25 * (tk[0, 1] + tk[1, 1] + tk[2, 1] + tk[3, 1])
            if k == self_target[j] or _inside(px, py, tk):
                share[j, k] = 1.0
                continue
            if np.hypot(cx - px, cy - py) > ranges[j]:
                continue
            base = np.arctan2(cy - py, cx - px)
            lo, hi, far = np.inf, -np.inf, 0.0
            for c in range(4):
                a = np.arctan2(tk[c, 1] - py, tk[c, 0] - px) - base
                a = (a + np.pi) % (2 * np.pi) - np.pi
                lo, hi = min(lo, a), max(hi, a)
                far = max(far, np.hypot(tk[c, 0] - px, tk[c, 1] - py))
            reach = far * (1.0 + 1e-9) + 1e-9
            n_cand = 0
            width = hi - lo
            for o in range(O):
                if o == target_as_occluder[k] or occ_near[o] > reach:
                    continue
                if state[o] == 0:
                    if o == own or _inside(px, py, occluders[o]):
                        state[o] = 1
                    else:
                        state[o] = 2
                        occ_lo[o], occ_hi[o] = _occluder_extent_ec93cfa(px, py, occluders[o])
                if state[o] == 1:
                    continue
                span = occ_hi[o] - occ_lo[o]
                if width + 1e-9 < np.pi and span + 1e-9 < np.pi:
                    gap = (base + lo - occ_lo[o] + np.pi) % (2 * np.pi) - np.pi
                    if gap < -width - 1e-9 or gap > span + 1e-9:
                        continue
                cand[n_cand] = o
                n_cand += 1
            seen = 0
            for r in range(n_rays):
                if need > 0 and (seen >= need or r - seen > n_rays - need):
                    break
                ang = base + lo + (hi - lo) * (r + 0.5) / n_rays
                dx, dy = np.cos(ang), np.sin(ang)
                t_target = _ray_rect(px, py, dx, dy, tk)
                if not np.isfinite(t_target):
                    t_target = np.hypot(cx - px, cy - py)
                blocked = False
                for i in range(n_cand):
                    o = cand[i]
                    if occ_near[o] >= t_target:
                        continue
                    rel = (ang - occ_lo[o] + np.pi) % (2 * np.pi) - np.pi
                    if rel < 0.0 or rel > occ_hi[o] - occ_lo[o]:
                        continue
                    if _ray_rect(px, py, dx, dy, occluders[o]) < t_target:
                        blocked = True
                        break
                if not blocked:
                    seen += 1
            if need > 0:
                share[j, k] = 1.0 if seen >= need else 0.0
            else:
                share[j, k] = seen / n_rays
    return share


def _scene(rng: np.random.Generator, extent_m: float):
    """Targets (cars, trucks, thin or tiny boxes) packed into a square of ``extent_m``,
    a few buildings, viewers anywhere (some inside a target or on its corner, some on a
    building's corner or the diagonal of a target): a crowd where most targets are
    hidden by one another."""
    n_t, n_b, n_v = int(rng.integers(0, 30)), int(rng.integers(0, 6)), int(rng.integers(1, 30))
    n = n_t + n_b
    half = extent_m / 2
    boxes = np.column_stack([rng.uniform(-half, half, n), rng.uniform(-half, half, n),
                             np.where(rng.random(n) < 0.3, rng.choice([0.0, np.pi / 2, np.pi / 4], n),
                                      rng.uniform(-np.pi, np.pi, n)),
                             np.r_[rng.choice([4.5, 12.0, 0.3, 1e-6, 8.0], n_t) * rng.uniform(0.5, 1.5, n_t),
                                   rng.uniform(10, 60, n_b)],
                             np.r_[rng.choice([1.8, 2.5, 0.3, 1e-6], n_t) * rng.uniform(0.5, 1.5, n_t),
                                   rng.uniform(10, 60, n_b)]])
    corners = np.array([box_corners(*b) for b in boxes]).reshape(-1, 4, 2)
    viewers = [rng.uniform(-half - 20, half + 20, (n_v, 2))]
    if n:
        pick = rng.integers(0, n, 4)
        viewers.append(corners[pick, rng.integers(0, 4, 4)])  # on corners
        a, c = corners[pick, 0], corners[pick, 2]
        viewers.append(a + (a - c) * rng.uniform(0.1, 3.0, (4, 1)))  # on a diagonal, outside
    viewers = np.concatenate(viewers)
    ranges = rng.uniform(20, 150, len(viewers))
    self_target = np.where(rng.random(len(viewers)) < 0.2, rng.integers(-1, max(n_t, 1), len(viewers)), -1)
    self_target[self_target >= n_t] = -1
    return (viewers, ranges, corners[:n_t], corners, np.arange(n_t, dtype=np.int64), self_target.astype(np.int64))


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n_rays=st.integers(1, 12), extent_m=st.sampled_from([15.0, 40.0, 120.0]))
def test_visible_share_equals_the_kernel_it_replaced(seed, n_rays, extent_m):
    """Shared target extents, no rays for a target no occluder's extent meets, and
    ``_hides`` deciding a wholly hidden target without its rays: the same shares and v
    as ec93cfa's kernel, bit for bit, with every ray (need 0) and stopping once settled."""
    args = _scene(np.random.default_rng(seed), extent_m)
    for need in (0, rays_needed(n_rays), 1, n_rays, n_rays + 1):
        np.testing.assert_array_equal(spatial._visible_share(*args, n_rays, need),
                                      _visible_share_ec93cfa(*args, n_rays, need))


def test_a_target_behind_a_wall_is_decided_without_its_rays_and_one_beside_it_is_seen():
    """A 4.5 x 1.8 m car 20 m straight ahead behind a 10 m wide wall at 10 m is hidden
    (``_hides``: the wall covers its fan and is nearer); the same car 20 m to the side,
    with nothing between, is seen."""
    wall = box_corners(10.0, 0.0, 0.0, 0.5, 10.0)
    hidden, open_ = box_corners(20.0, 0.0, 0.0, 4.5, 1.8), box_corners(0.0, 20.0, 0.0, 4.5, 1.8)
    targets = np.stack([hidden, open_])
    occluders = np.stack([hidden, open_, wall])
    args = (np.zeros((1, 2)), np.array([100.0]), targets, occluders, np.arange(2, dtype=np.int64),
            np.full(1, -1, dtype=np.int64))
    np.testing.assert_array_equal(spatial._visible_share(*args, 9, 5), [[0.0, 1.0]])
    np.testing.assert_array_equal(spatial._visible_share(*args, 9, 0), [[0.0, 1.0]])
    base, lo, hi = spatial._extent(0.0, 0.0, hidden)
    occ_lo, occ_hi = spatial._occluder_extent(0.0, 0.0, wall)
    near2 = (20.0 - 2.25) ** 2
    assert spatial._hides(0.0, 0.0, wall, occ_lo, occ_hi, 9.75, base + lo, hi - lo, 9, 5, near2)
    # the car's near face is 17.75 m away; a wall at 18 m does not hide it
    far_wall = box_corners(18.5, 0.0, 0.0, 0.5, 10.0)
    occ_lo, occ_hi = spatial._occluder_extent(0.0, 0.0, far_wall)
    assert not spatial._hides(0.0, 0.0, far_wall, occ_lo, occ_hi, 18.25, base + lo, hi - lo, 9, 5, near2)


def test_a_corner_on_a_ray_leaves_the_rays_to_be_cast():
    """A square occluder turned 45 degrees, its near and far corners straight ahead: the
    middle ray of a target behind it runs through both corners, where ``_ray_rect``'s
    rounding decides; ``_hides`` leaves that to the rays."""
    diamond = box_corners(10.0, 0.0, np.pi / 4, 4.0, 4.0)
    target = box_corners(30.0, 0.0, 0.0, 0.5, 1.0)
    base, lo, hi = spatial._extent(0.0, 0.0, target)
    occ_lo, occ_hi = spatial._occluder_extent(0.0, 0.0, diamond)
    assert not spatial._hides(0.0, 0.0, diamond, occ_lo, occ_hi, 8.0, base + lo, hi - lo, 9, 9, 29.75 ** 2)
    assert spatial._hides(0.0, 0.0, diamond, occ_lo, occ_hi, 8.0, base + lo, hi - lo, 8, 8, 29.75 ** 2)


@given(a=st.floats(allow_nan=True, allow_infinity=True))
def test_wrap_is_the_remainder_formula(a):
    """``_wrap`` against ``(a + pi) % (2 pi) - pi`` (in numba, as the kernel had it): the
    same float, sign of zero included, NaN for NaN."""
    got, want = spatial._wrap(a), _wrap_formula(a)
    assert (np.isnan(got) and np.isnan(want)) or (got == want and np.signbit(got) == np.signbit(want))


@njit
def _wrap_formula(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def test_wrap_at_the_ends_of_its_fast_range():
    for a in (-np.pi, np.nextafter(-np.pi, 0.0), np.nextafter(-np.pi, -4.0), np.pi, np.nextafter(np.pi, 0.0),
              np.nextafter(np.pi, 4.0), 0.0, -0.0, 3 * np.pi, -3 * np.pi):
        assert spatial._wrap(a) == _wrap_formula(a)
    assert spatial._wrap(0.0) == 0.0 and spatial._wrap(np.pi) == -np.pi  # 2 pi wraps to -pi


coord = st.floats(-1e4, 1e4, allow_nan=False) | st.sampled_from([0.0, 1e-30, -1e-30, 1e60, np.nan, np.inf])


@given(px=coord, py=coord, quad=st.lists(coord, min_size=8, max_size=8))
def test_quad_distance_and_farthest_corner_equal_hypot_of_every_edge_and_corner(px, py, quad):
    """``_quad_distance`` and ``_farthest_corner``, which take np.hypot of the nearest
    (farthest) by squares only, against hypot of all four, in any quad (degenerate,
    huge, tiny, NaN)."""
    q = np.array(quad, dtype=np.float64).reshape(4, 2)
    np.testing.assert_array_equal(spatial._quad_distance(px, py, q), _quad_distance_ec93cfa(px, py, q))
    np.testing.assert_array_equal(spatial._farthest_corner(px, py, q), _farthest_ec93cfa(px, py, q))


@njit
def _farthest_ec93cfa(px, py, quad):
    far = 0.0
    for c in range(4):
        far = max(far, np.hypot(quad[c, 0] - px, quad[c, 1] - py))
    return far


def test_quad_distance_of_a_square_by_hand():
    """A 2 m square centred at (10, 0): its nearest edge is 9 m from the origin, its
    farthest corner sqrt(11^2 + 1) m."""
    sq = box_corners(10.0, 0.0, 0.0, 2.0, 2.0)
    assert spatial._quad_distance(0.0, 0.0, sq) == 9.0 * (1.0 - 1e-9) - 1e-9
    assert spatial._farthest_corner(0.0, 0.0, sq) == np.hypot(11.0, 1.0)


@njit
def _first_close_ec93cfa(pos_j, head_j, dims_j, obj_xy, obj_vel, head_k, dims_k, dt, safety, window):
    """``spatial._first_close`` as it stood at ec93cfa."""
    J, T = pos_j.shape[0], pos_j.shape[1]
    K = obj_xy.shape[0]
    first = np.full((J, K), -1, dtype=np.int64)
    for j in range(J):
        off_j = max(dims_j[j, 0] - dims_j[j, 1], 0.0) / 2
        for k in range(K):
            off_k = max(dims_k[k, 0] - dims_k[k, 1], 0.0) / 2
            reach = dims_j[j, 1] / 2 + dims_k[k, 1] / 2 + safety
            ck, sk = np.cos(head_k[k]), np.sin(head_k[k])
            vx, vy = obj_vel[k, 0], obj_vel[k, 1]
            for t in range(T):
                t_lo = max(dt[t] - window, 0.0)
                t_hi = dt[t] + window
                ax, ay = obj_xy[k, 0] + vx * t_lo, obj_xy[k, 1] + vy * t_lo
                ex, ey = vx * (t_hi - t_lo), vy * (t_hi - t_lo)
                len2 = ex * ex + ey * ey
                jx, jy = pos_j[j, t, 0], pos_j[j, t, 1]
                f = 0.0 if len2 <= 0.0 else min(max(((jx - ax) * ex + (jy - ay) * ey) / len2, 0.0), 1.0)
                if spatial._farther(jx - ax - f * ex, jy - ay - f * ey, off_j + off_k + reach):
                    continue
                cj, sj = np.cos(head_j[j, t]), np.sin(head_j[j, t])
                close = False
                for a in (-1.0, 0.0, 1.0):
                    px, py = jx + a * off_j * cj, jy + a * off_j * sj
                    for b in (-1.0, 0.0, 1.0):
                        bx, by = ax + b * off_k * ck, ay + b * off_k * sk
                        f = 0.0 if len2 <= 0.0 else min(max(((px - bx) * ex + (py - by) * ey) / len2, 0.0), 1.0)
                        dx, dy = px - bx - f * ex, py - by - f * ey
                        if dx * dx + dy * dy < reach * reach:
                            close = True
                if close:
                    first[j, k] = t
                    break
    return first


@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), spread_m=st.sampled_from([5.0, 30.0, 150.0]),
       window_s=st.sampled_from([0.0, 2.0, 11.0]), odd=st.booleans())
def test_first_close_equals_the_kernel_it_replaced(seed, spread_m, window_s, odd):
    """``_first_close``, which passes over a pair whose boxes (j's centres over the
    horizon, k's over every window) lie farther apart than any sample could be close,
    against ec93cfa's: the same first index for every pair; with ``odd``, NaN and inf
    velocities and positions, negative and zero dims, unsorted and negative times."""
    rng = np.random.default_rng(seed)
    J, K, T = int(rng.integers(0, 12)), int(rng.integers(0, 12)), int(rng.integers(0, 34))
    dt = np.arange(T) * 0.25
    pos_j = rng.uniform(-spread_m, spread_m, (J, 1, 2)) + rng.normal(0, 3, (J, 1, 2)) * dt[None, :, None]
    head_j = rng.uniform(-np.pi, np.pi, (J, T))
    dims_j = np.tile([4.5, 1.8], (J, 1))
    obj_xy = rng.uniform(-spread_m, spread_m, (K, 2))
    obj_vel = rng.normal(0, 5, (K, 2)) * (rng.random((K, 1)) < 0.7)
    head_k = rng.uniform(-np.pi, np.pi, K)
    dims_k = rng.uniform(0.3, 12, (K, 2))
    if odd:
        dt = rng.permutation(dt) - rng.uniform(0, 3)
        for a in (pos_j.reshape(-1), obj_vel.reshape(-1), obj_xy.reshape(-1)):
            if len(a):
                a[rng.integers(0, len(a), 2)] = rng.choice([np.nan, np.inf, -np.inf], 2)
        dims_k[:, 1] *= rng.choice([-1.0, 0.0, 1.0], K)
    args = (pos_j, head_j, dims_j, obj_xy, obj_vel, head_k, dims_k, dt, 1.0, window_s)
    np.testing.assert_array_equal(spatial._first_close(*args), _first_close_ec93cfa(*args))


def test_apart_by_hand():
    """Boxes 3 m apart along x and 4 m along y are 5 m apart: apart beyond 4.99 m, not
    beyond 5 m (the margin), nor beyond a NaN bound."""
    a, b = np.array([0.0, 1.0, 0.0, 1.0]), np.array([4.0, 6.0, 5.0, 7.0])
    assert spatial._apart(a, b, 4.99) and spatial._apart(b, a, 4.99)
    assert not spatial._apart(a, b, 5.0) and not spatial._apart(a, b, np.nan)
    assert not spatial._apart(a, a, 0.0)


def _match_vehicles_ec93cfa(viewers_xy, centroids, gate_m=3.0):
    if len(viewers_xy) == 0 or len(centroids) == 0:
        return np.full(len(viewers_xy), -1, dtype=np.int64)
    d = np.linalg.norm(viewers_xy[:, None, :] - centroids[None, :, :2], axis=2)
    nearest = np.argmin(d, axis=1)
    return np.where(d[np.arange(len(viewers_xy)), nearest] <= gate_m, nearest, -1).astype(np.int64)


@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), spread_m=st.sampled_from([2.0, 10.0, 100.0]), odd=st.booleans())
def test_match_vehicles_equals_the_numpy_statements_it_replaced(seed, spread_m, odd):
    """``match_vehicles`` (one kernel) against ec93cfa's numpy statements: the same
    matches, ties to the first, NaN as np.argmin takes it, with 2 or 3 centroid columns."""
    rng = np.random.default_rng(seed)
    J, K = int(rng.integers(0, 15)), int(rng.integers(0, 15))
    viewers = rng.uniform(-spread_m, spread_m, (J, 2))
    centroids = np.round(rng.uniform(-spread_m, spread_m, (K, int(rng.integers(2, 4)))), 1)
    if odd and K:
        centroids[rng.integers(0, K, 2), 0] = np.nan
        viewers = np.concatenate([viewers, centroids[:3, :2]])
    np.testing.assert_array_equal(spatial.match_vehicles(viewers, centroids),
                                  _match_vehicles_ec93cfa(viewers, centroids))


def test_match_vehicles_by_hand():
    """Viewers at (0, 0) and (10, 0), centroids 1 m and 2 m from the first and 5 m from
    the second: the first matches the nearer, the second none (gate 3 m)."""
    got = spatial.match_vehicles(np.array([[0.0, 0.0], [10.0, 0.0]]), np.array([[2.0, 0.0], [0.0, 1.0], [5.0, 0.0]]))
    np.testing.assert_array_equal(got, [1, -1])


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_object_map_footprints_dims_and_headings_equal_the_per_track_ones(seed):
    """``dataplane._footprints``, ``_object_dims``, ``_body_corners`` and the headings
    of ``DataPlane.object_map`` against ``corners_of``, the per-track ``max``es,
    ``_box_corners`` and ``Track.heading_rad``: the same floats."""
    from vehicle_agent.dataplane import _body_corners, _box_corners, _footprints, _object_dims
    from vehicle_agent.perception import DetectedObject, corners_of
    from vehicle_agent.tracking import STILL_MPS, Track

    rng = np.random.default_rng(seed)
    K = int(rng.integers(0, 25))
    objs = [DetectedObject(np.zeros((1, 3), np.float32), np.zeros((1, 2), np.int64), rng.normal(0, 80, 3),
                           float(rng.uniform(-np.pi, np.pi)), float(rng.choice([rng.uniform(0.0, 12), 0.5, 1.0])),
                           float(rng.choice([rng.uniform(0.0, 3), 1.0, 0.2]))) for _ in range(K)]
    yaw = np.array([o.yaw_rad for o in objs], dtype=np.float64)
    extent = np.array([(o.length_m, o.width_m) for o in objs], dtype=np.float64).reshape(-1, 2)
    centroid = np.array([o.centroid[:2] for o in objs], dtype=np.float64).reshape(-1, 2)
    got = _footprints(yaw, extent, centroid)
    want = corners_of(objs)
    assert got.shape == want.shape and got.dtype == want.dtype
    np.testing.assert_array_equal(got, want)
    dims = np.array([[max(o.length_m, o.width_m, 1.0), max(o.width_m, 1.0)] for o in objs]).reshape(-1, 2)
    np.testing.assert_array_equal(_object_dims(extent), dims)
    vel = rng.normal(0, 3, (K, 2)) * rng.choice([0.0, 0.3, 1.0], (K, 1))
    tracks = [Track(k, centroid[k], vel[k], 0.0, objs[k]) for k in range(K)]
    heading = np.where(np.hypot(vel[:, 0], vel[:, 1]) > STILL_MPS, np.arctan2(vel[:, 1], vel[:, 0]), yaw)
    np.testing.assert_array_equal(heading, np.array([t.heading_rad for t in tracks], dtype=np.float64))
    x, y = (float(v) for v in rng.uniform(-100, 100, 2))
    yaw1, length, width = float(rng.uniform(-7, 7)), float(rng.uniform(0.5, 20)), float(rng.uniform(0.5, 5))
    np.testing.assert_array_equal(_body_corners(x, y, yaw1, length, width),
                                  _box_corners(np.array([[x, y, yaw1, length, width, 0.0]])))


def test_footprint_by_hand():
    """A 4 x 2 m box at (10, 5) turned 90 degrees spans x 9..11 and y 3..7."""
    from vehicle_agent.dataplane import _body_corners, _footprints

    got = _footprints(np.array([np.pi / 2]), np.array([[4.0, 2.0]]), np.array([[10.0, 5.0]]))[0]
    np.testing.assert_allclose(np.sort(got[:, 0]), [9, 9, 11, 11], atol=1e-12)
    np.testing.assert_allclose(np.sort(got[:, 1]), [3, 3, 7, 7], atol=1e-12)
    np.testing.assert_allclose(_body_corners(10.0, 5.0, np.pi / 2, 4.0, 2.0)[0], got, atol=1e-12)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_fused_now_equals_fusing_what_shared_now_places(seed):
    """``fused_now`` (the points fused as they are placed) against ``fuse(grid,
    shared_now(...))``, interval after interval on two stores fed alike: receptions
    around a short history of our poses, late and aged-out copies, points above and
    below the ground clearance, inside and outside the grid, a grid with ABOVE cells of
    its own. The same grid state, received cells, on_own flags and batch, bit for bit."""
    from vehicle_agent.fusion import ReceivedStore, fuse, fused_now, shared_now

    a, b = ReceivedStore(), ReceivedStore()
    for t_now, poses, batch, grid in received_intervals(np.random.default_rng(seed), 10, xy_half_m=11.0, z_low_m=-0.5):
        a.add_batch(batch)
        b.add_batch(batch)
        want = fuse(grid, shared_now(a, t_now, (batch.sender, batch.object_id), poses, 4.5, 1.8, grid))
        got = fused_now(b, t_now, (batch.sender, batch.object_id), poses, 4.5, 1.8, grid)
        assert got.grid is grid
        for name in ("state", "received", "on_own"):
            x, y = getattr(got, name), getattr(want, name)
            assert x.dtype == y.dtype and x.shape == y.shape, name
            np.testing.assert_array_equal(x, y, err_msg=name)
        for name in ("sender", "object_id", "points", "counts", "velocity", "age_s", "fresh"):
            x, y = getattr(got.shared, name), getattr(want.shared, name)
            assert x.dtype == y.dtype, name
            np.testing.assert_array_equal(x, y, err_msg=name)
        assert not np.shares_memory(got.state, grid.state)


def test_fused_now_by_hand():
    """One fresh object of two points 0.6 m apart at 1 m height, on cells (row 10, col
    12) and (10, 13) of a 0.5 m grid whose first is ABOVE already: the second is
    received, both ABOVE, and the object is on our own (nothing of it on our body, 30 m
    away)."""
    from protocol.messages import Pose
    from vehicle_agent.frames import world_to_sensor
    from vehicle_agent.fusion import ReceivedStore, fused_now
    from vehicle_agent.payload import ObjectPayload, decode_objects, encode_object
    from vehicle_agent.perception import ABOVE, GROUND, Grid, GridSpec

    spec = GridSpec(half_extent_m=10.0)
    n = spec.cells
    state = np.full((n, n), GROUND, dtype=np.uint8)
    state[10, 12] = ABOVE
    grid = Grid(spec, -n // 2, -n // 2, state, np.ones((n, n), dtype=bool))
    # cell (row, col) spans x in [(col - n/2) * 0.5, ...), y likewise
    pts = np.array([[(12 - n // 2) * 0.5 + 0.2, (10 - n // 2) * 0.5 + 0.25, 1.0],
                    [(13 - n // 2) * 0.5 + 0.3, (10 - n // 2) * 0.5 + 0.25, 1.0]])
    pose = Pose(0.0, 0.0, 0.0)
    sensor = world_to_sensor(pts, pose, 1.9).astype(np.float32)
    obj = ObjectPayload(3, 7, 0, 0.0, pose, 1.9, sensor.mean(axis=0), np.zeros(2, np.float32), sensor)
    batch, _ = decode_objects([encode_object(obj)])
    store = ReceivedStore()
    store.add_batch(batch)
    fused = fused_now(store, 0.0, (batch.sender, batch.object_id), [Pose(30.0, 30.0, 0.0)], 4.5, 1.8, grid)
    assert fused.state[10, 12] == ABOVE and fused.state[10, 13] == ABOVE
    assert not fused.received[10, 12] and fused.received[10, 13] and fused.received.sum() == 1
    np.testing.assert_array_equal(fused.on_own, [True])


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_relevance_in_one_call_equals_sampling_then_first_close(seed):
    """``relevance``, which samples and tests in one kernel call
    (``_sampled_first_close``), against ``_sample_all`` then ec93cfa's ``_first_close``,
    in both modes, with packed float64 trajectories and with lists of float32 ones."""
    rng = np.random.default_rng(seed)
    J, K = int(rng.integers(0, 8)), int(rng.integers(0, 8))
    t_now = float(rng.uniform(0, 10))
    trajs = []
    for _ in range(J):
        p = int(rng.integers(1, 10))
        t = t_now + np.sort(rng.uniform(-1, 9, p))
        trajs.append(np.column_stack([np.cumsum(rng.normal(0, 5, p)), np.cumsum(rng.normal(0, 5, p)), t]))
    dims_j = np.tile([4.5, 1.8], (J, 1))
    obj_xy, obj_vel = rng.uniform(-20, 20, (K, 2)), rng.normal(0, 4, (K, 2))
    obj_dims, heading = rng.uniform(0.5, 8, (K, 2)), rng.uniform(-np.pi, np.pi, K)
    times = t_now + np.arange(0.0, spatial.HORIZON_S + 1e-9, spatial.STEP_S)
    for packed in (True, False):
        if packed:
            wp = np.concatenate(trajs) if trajs else np.zeros((0, 3))
            starts = np.zeros(J + 1, dtype=np.int64)
            starts[1:] = np.cumsum([len(t) for t in trajs])
            args = (wp, dims_j, obj_xy, obj_vel, obj_dims, t_now)
            kw = {"starts": starts, "obj_heading": heading}
        else:
            trajs32 = [t.astype(np.float32) for t in trajs]
            wp = np.concatenate(trajs32).astype(np.float64) if trajs else np.zeros((0, 3))
            starts = np.zeros(J + 1, dtype=np.int64)
            starts[1:] = np.cumsum([len(t) for t in trajs])
            args = (trajs32, dims_j, obj_xy, obj_vel, obj_dims, t_now)
            kw = {}
        for mode in ("bool", "ttc"):
            got = spatial.relevance(*args, mode=mode, **kw)
            if J == 0 or K == 0:
                assert got.shape == (J, K)
                continue
            pos, head = spatial._sample_all(wp, starts, times)
            head_k = heading if packed else np.where(np.hypot(obj_vel[:, 0], obj_vel[:, 1]) > 0.1,
                                                     np.arctan2(obj_vel[:, 1], obj_vel[:, 0]), 0.0)
            first = _first_close_ec93cfa(pos, head, dims_j, obj_xy, obj_vel, head_k, obj_dims, times - t_now,
                                         spatial.SAFETY_M, spatial.WINDOW_S)
            hit = first >= 0
            want = hit.astype(np.float32) if mode == "bool" else np.where(
                hit, 1.0 / (1.0 + (times - t_now)[np.maximum(first, 0)]), 0.0).astype(np.float32)
            np.testing.assert_array_equal(got, want)


@njit
def _sample_all_ec93cfa(waypoints, starts, times):
    """``spatial._sample_all`` as it stood at ec93cfa."""
    J, T = starts.shape[0] - 1, times.shape[0]
    pos = np.empty((J, T, 2))
    head = np.zeros((J, T))
    for j in range(J):
        a, b = starts[j], starts[j + 1]
        n = b - a
        seg = 0
        for i in range(T):
            t = times[i]
            while seg < n - 1 and waypoints[a + seg + 1, 2] <= t:
                seg += 1
            if n == 1 or t <= waypoints[a, 2]:
                pos[j, i, 0], pos[j, i, 1] = waypoints[a, 0], waypoints[a, 1]
            elif seg >= n - 1:
                pos[j, i, 0], pos[j, i, 1] = waypoints[b - 1, 0], waypoints[b - 1, 1]
            else:
                p, q = a + seg, a + seg + 1
                w = (t - waypoints[p, 2]) / (waypoints[q, 2] - waypoints[p, 2])
                pos[j, i, 0] = waypoints[p, 0] + w * (waypoints[q, 0] - waypoints[p, 0])
                pos[j, i, 1] = waypoints[p, 1] + w * (waypoints[q, 1] - waypoints[p, 1])
            if n >= 2:
                p = a + min(seg, n - 2)
                head[j, i] = np.arctan2(waypoints[p + 1, 1] - waypoints[p, 1], waypoints[p + 1, 0] - waypoints[p, 0])
    return pos, head


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_sample_all_equals_the_kernel_it_replaced(seed):
    """``_sample_all``, which takes a segment's arctangent once for all its samples,
    against ec93cfa's: the same positions and headings, with one-waypoint trajectories,
    repeated times, times before the first and after the last waypoint, and NaN."""
    rng = np.random.default_rng(seed)
    J = int(rng.integers(0, 8))
    trajs = []
    for _ in range(J):
        p = int(rng.integers(1, 10))
        t = np.sort(rng.choice([0.0, 0.5, 1.0, 2.0, 3.5, 8.0], p) + rng.choice([0.0, 0.1], p))
        xy = np.cumsum(rng.normal(0, 5, (p, 2)), axis=0)
        if rng.random() < 0.1:
            xy[rng.integers(0, p)] = np.nan
        trajs.append(np.column_stack([xy, t]))
    wp = np.concatenate(trajs) if trajs else np.zeros((0, 3))
    starts = np.zeros(J + 1, dtype=np.int64)
    starts[1:] = np.cumsum([len(t) for t in trajs])
    times = rng.uniform(-1, 1) + np.arange(0.0, 8.0 + 1e-9, 0.25)
    got, want = spatial._sample_all(wp, starts, times), _sample_all_ec93cfa(wp, starts, times)
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g, w)


def test_sample_all_by_hand():
    """A trajectory from (0, 0) at t=0 to (10, 10) at t=1 then (10, 20) at t=2: at 0.5 s
    it is at (5, 5) heading 45 degrees, at 1.5 s at (10, 15) heading 90 degrees."""
    wp = np.array([[0.0, 0.0, 0.0], [10.0, 10.0, 1.0], [10.0, 20.0, 2.0]])
    pos, head = spatial._sample_all(wp, np.array([0, 3]), np.array([0.5, 1.5]))
    np.testing.assert_allclose(pos[0], [[5.0, 5.0], [10.0, 15.0]])
    np.testing.assert_allclose(head[0], [np.pi / 4, np.pi / 2])


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_neighbors_in_domain_equals_take_of_in_domain(seed):
    """``Neighbors.in_domain`` (one kernel) against ``take(in_domain(xy))``: the same
    rows, arrays and dtypes, with vehicles on the domain's edge, NaN positions, all
    inside (the same object back) and none inside."""
    from vehicle_agent.dataplane import DOMAIN_RADIUS_M, GUARD_BAND_M, Neighbors, in_domain

    rng = np.random.default_rng(seed)
    n = int(rng.integers(0, 12))
    limit = DOMAIN_RADIUS_M + GUARD_BAND_M
    spread = float(rng.choice([50.0, 120.0, 300.0]))
    xy = rng.uniform(-spread, spread, (n, 2))
    edge = rng.random(n) < 0.2
    ang = rng.uniform(-np.pi, np.pi, n)
    xy[edge] = np.column_stack([limit * np.cos(ang), limit * np.sin(ang)])[edge]
    if n and rng.random() < 0.2:
        xy[rng.integers(0, n)] = np.nan
    lengths = rng.integers(1, 6, n)
    starts = np.zeros(n + 1, dtype=np.int64)
    starts[1:] = np.cumsum(lengths)
    nb = Neighbors(np.sort(rng.choice(1000, n, replace=False)).astype(np.int64), xy,
                   rng.normal(0, 10, (int(starts[-1]), 3)), starts, rng.random(n) < 0.5)
    got, want = nb.in_domain(), nb.take(in_domain(nb.xy))
    assert (got is nb) == (want is nb)
    for name in ("vid", "xy", "waypoints", "starts", "fresh"):
        x, y = getattr(got, name), getattr(want, name)
        assert x.dtype == y.dtype and x.shape == y.shape, name
        np.testing.assert_array_equal(x, y, err_msg=name)


def test_neighbors_in_domain_by_hand():
    """Of vehicles 80 m and 90 m from the centre, the first is in the domain (85 m +
    1.8 m guard band), with its two waypoints."""
    from vehicle_agent.dataplane import Neighbors

    nb = Neighbors(np.array([3, 5]), np.array([[80.0, 0.0], [0.0, 90.0]]), np.arange(15.0).reshape(5, 3),
                   np.array([0, 2, 5]), np.array([True, False]))
    got = nb.in_domain()
    np.testing.assert_array_equal(got.vid, [3])
    np.testing.assert_array_equal(got.waypoints, np.arange(6.0).reshape(2, 3))
    np.testing.assert_array_equal(got.starts, [0, 2])
