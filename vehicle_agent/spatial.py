"""Spatial reasoning (paper 5.1): visibility v_(i,k),j and relevance r_(i,k),j.

Visibility: vehicle i traces rays from vehicle j's reported position toward each of
its objects o_(i,k). A ray is blocked when it enters another object of i's view (i's
own body and the map's static buildings included, j's own body excluded) before it
reaches o_(i,k). ``visible_share`` is the fraction of rays across o_(i,k)'s angular
extent that get through; an object beyond j's LiDAR range has share 0. The paper's
boolean v is ``share >= VISIBLE_SHARE``.

Relevance (the paper: "an object is relevant to another vehicle if the trajectories
of those two objects could potentially collide at some point in the future"): j's
shared trajectory (waypoints with times) and o_(i,k)'s extrapolated trajectory
(constant velocity) are sampled over the planner's horizon; each body is three circles
along its heading. They could collide when j's body comes within ``safety_m`` of
where o_(i,k) is within +-``window_s`` of the same moment: neither j's plan (it may
brake or wait) nor o_(i,k)'s tracked velocity is exact. r = 1 then (boolean, as in
the paper's evaluation), or 1 / (1 + time to that moment) in the TTC form.
"""

from __future__ import annotations

import numpy as np
from numba import njit

VISIBLE_SHARE = 0.5
RAYS_PER_OBJECT = 9
HORIZON_S = 8.0  # the planner's horizon (PlannerConfig.horizon_s): what it would brake for
STEP_S = 0.25
SAFETY_M = 1.0
WINDOW_S = 2.0  # "could collide": k's timing may be off by this much either way (the paper's delta spans +-2 s)
_MARGIN_RAD = 1e-9  # angles here are exact to ~1e-15 rad: intervals this far apart share no ray
_COVER_RAD = 1e-7  # _hides: rays this far inside an occluder's extent and from its corners
_UNKNOWN, _SKIP, _KNOWN = 0, 1, 2  # an occluder for the viewer at hand (_visible_share)


@njit(cache=True)
def _ray_rect(px, py, dx, dy, corners):
    """Distance along the ray (p, d) to where it enters a convex quad; inf if it misses."""
    best = np.inf
    for e in range(4):
        ax, ay = corners[e, 0], corners[e, 1]
        bx, by = corners[(e + 1) % 4, 0], corners[(e + 1) % 4, 1]
        ex, ey = bx - ax, by - ay
        den = dx * ey - dy * ex
        if abs(den) < 1e-12:
            continue
        wx, wy = ax - px, ay - py
        t = (wx * ey - wy * ex) / den
        u = (wx * dy - wy * dx) / den
        if t >= 0.0 and 0.0 <= u <= 1.0 and t < best:
            best = t
    return best


@njit(cache=True)
def _inside(px, py, corners):
    sign = 0
    for e in range(4):
        ax, ay = corners[e, 0], corners[e, 1]
        bx, by = corners[(e + 1) % 4, 0], corners[(e + 1) % 4, 1]
        cross = (bx - ax) * (py - ay) - (by - ay) * (px - ax)
        s = 1 if cross > 0 else -1
        if sign == 0:
            sign = s
        elif s != sign:
            return False
    return True


@njit(cache=True)
def _quad_distance(px, py, quad):
    """Distance from (px, py) to the nearest point of ``quad``'s edges, a little less
    (1e-9 relative and absolute, far above rounding): a lower bound of where any ray
    from (px, py) can enter the quad by ``_ray_rect``.

    The nearest of the edges' points by their squared distances, and ``np.hypot`` of it
    only (of every edge within 1e-12 of it): the squares are exact to a few ulps, so an
    edge clear of the nearest by that margin has the larger hypot too. Distances outside
    [1e-50, 1e50], or NaN, take ``np.hypot`` of every edge."""
    near2, plain = np.inf, False
    for e in range(4):
        gx, gy = _edge_offset(px, py, quad, e)
        d2 = gx * gx + gy * gy
        if not (1e-100 <= d2 <= 1e100):
            plain = True
        near2 = min(near2, d2)
    best = np.inf
    for e in range(4):
        gx, gy = _edge_offset(px, py, quad, e)
        if not plain and gx * gx + gy * gy > near2 * (1.0 + 1e-12):
            continue
        best = min(best, np.hypot(gx, gy))
    return best * (1.0 - 1e-9) - 1e-9


@njit(cache=True)
def _edge_offset(px, py, quad, e):
    """From (px, py) to the nearest point of ``quad``'s edge ``e``."""
    ax, ay = quad[e, 0], quad[e, 1]
    ex, ey = quad[(e + 1) % 4, 0] - ax, quad[(e + 1) % 4, 1] - ay
    len2 = ex * ex + ey * ey
    t = 0.0 if len2 == 0.0 else min(max(((px - ax) * ex + (py - ay) * ey) / len2, 0.0), 1.0)
    return ax + t * ex - px, ay + t * ey - py


@njit(cache=True)
def _farthest_corner(px, py, quad):
    """``max`` of ``np.hypot`` from (px, py) to ``quad``'s corners, taken of the corners
    within 1e-12 of the farthest by their squared distances only (as ``_quad_distance``)."""
    far2, plain = 0.0, False
    for c in range(4):
        dx, dy = quad[c, 0] - px, quad[c, 1] - py
        d2 = dx * dx + dy * dy
        if not (1e-100 <= d2 <= 1e100):
            plain = True
        far2 = max(far2, d2)
    far = 0.0
    for c in range(4):
        dx, dy = quad[c, 0] - px, quad[c, 1] - py
        if not plain and dx * dx + dy * dy < far2 * (1.0 - 1e-12):
            continue
        far = max(far, np.hypot(dx, dy))
    return far


@njit(cache=True)
def _wrap(a):
    """``(a + np.pi) % (2 * np.pi) - np.pi``, the same value: where a + pi lies in
    [0, 2 pi) the remainder is a + pi itself (fmod is exact; -0.0 and 0.0 give the same
    -pi), and is not taken (it cost more than an arctangent)."""
    x = a + np.pi
    if 0.0 <= x < 2 * np.pi:
        return x - np.pi
    return x % (2 * np.pi) - np.pi


@njit(cache=True)
def _occluder_extent(px, py, quad):
    """The angular extent [lo, hi] (rad, world) of ``quad`` seen from (px, py)."""
    base, lo, hi = _extent(px, py, quad)
    return lo + base, hi + base


@njit(cache=True)
def _extent(px, py, quad):
    """The direction (rad, world) from (px, py) to ``quad``'s centre, and the lowest and
    highest of its corners' directions relative to it."""
    cx = 0.25 * (quad[0, 0] + quad[1, 0] + quad[2, 0] + quad[3, 0])
    cy = 0.25 * (quad[0, 1] + quad[1, 1] + quad[2, 1] + quad[3, 1])
    base = np.arctan2(cy - py, cx - px)
    lo, hi = np.inf, -np.inf
    for c in range(4):
        a = _wrap(np.arctan2(quad[c, 1] - py, quad[c, 0] - px) - base)
        lo, hi = min(lo, a), max(hi, a)
    return base, lo, hi


@njit(cache=True)
def _same_quads(targets, occluders, target_as_occluder):
    """For each occluder, the target it is (``target_as_occluder``, with the same corners
    bit for bit), or -1: their angular extents are then one computation."""
    occ_target = np.full(occluders.shape[0], -1, dtype=np.int64)
    for k in range(targets.shape[0]):
        o = target_as_occluder[k]
        if o < 0 or o >= occluders.shape[0]:
            continue
        same = True
        for c in range(4):
            for d in range(2):
                if not targets[k, c, d] == occluders[o, c, d]:
                    same = False
        if same:
            occ_target[o] = k
    return occ_target


@njit(cache=True)
def _visible_share(viewers, ranges, targets, occluders, target_as_occluder, self_target, n_rays, need=0):
    """``visible_share``'s arithmetic. With ``need`` > 0 a target's rays are cast only
    until ``seen >= need`` is settled either way, and its share is then 1.0 or 0.0.

    An occluder's angular extent and inside test are worked out for a viewer only once
    a target asks (``_UNKNOWN`` until then), and never for an occluder whose nearest
    point is beyond the target's farthest corner: the per-ray test skips an occluder
    whose nearest point is no nearer than the ray's hit (``occ_near >= t_target``), so
    it would skip that one on every ray. The nearest point of its edges, not its nearest
    corner: a long wall beside the viewer has its corners far away and its middle near,
    and was skipped so, the objects behind it counted as seen through it.

    A target's angular extent is worked out once per viewer, for its rays and for it as
    an occluder (``_same_quads``; at 40 vehicles a third of the arctangents). A target
    no occluder's extent meets sees every ray through: its rays are not cast. Of the
    candidate occluders the one that blocked the last ray is tried first (a ray is
    blocked by any of them, whatever the order)."""
    J, K, O = viewers.shape[0], targets.shape[0], occluders.shape[0]
    share = np.zeros((J, K))
    occ_lo = np.empty(O)
    occ_hi = np.empty(O)
    occ_near = np.empty(O)
    state = np.zeros(O, dtype=np.int8)  # _UNKNOWN, _SKIP or _KNOWN, per viewer
    cand = np.empty(O, dtype=np.int64)
    occ_target = _same_quads(targets, occluders, target_as_occluder)
    ext_known = np.zeros(K, dtype=np.bool_)  # per viewer: each target's _extent
    ext_base = np.empty(K)
    ext_lo = np.empty(K)
    ext_hi = np.empty(K)
    for j in range(J):
        px, py = viewers[j, 0], viewers[j, 1]
        own = target_as_occluder[self_target[j]] if self_target[j] >= 0 else -1
        for o in range(O):
            state[o] = _UNKNOWN
            occ_near[o] = _quad_distance(px, py, occluders[o])
        ext_known[:] = False
        for k in range(K):
            tk = targets[k]
            cx = 0.25 * (tk[0, 0] + tk[1, 0] + tk[2, 0] + tk[3, 0])
            cy = 0.25 * (tk[0, 1] + tk[1, 1] + tk[2, 1] + tk[3, 1])
            if k == self_target[j] or _inside(px, py, tk):
                share[j, k] = 1.0  # j itself: nothing to send it
                continue
            if _farther(cx - px, cy - py, ranges[j]):
                continue
            if not ext_known[k]:
                ext_base[k], ext_lo[k], ext_hi[k] = _extent(px, py, tk)
                ext_known[k] = True
            base, lo, hi = ext_base[k], ext_lo[k], ext_hi[k]
            far = _farthest_corner(px, py, tk)
            # a ray meets the target no farther than its farthest corner (a convex quad)
            reach = far * (1.0 + 1e-9) + 1e-9
            # the occluders whose angular extent meets the target's (with a margin far above
            # rounding): no ray of the target can enter another, so the per-ray test is not run
            n_cand = 0
            width = hi - lo
            for o in range(O):
                if o == target_as_occluder[k] or occ_near[o] > reach:
                    continue
                if state[o] == _UNKNOWN:
                    # j's own body (as i sees it) does not hide anything from j
                    if o == own or _inside(px, py, occluders[o]):
                        state[o] = _SKIP
                    else:
                        state[o] = _KNOWN
                        t = occ_target[o]
                        if t < 0:
                            occ_lo[o], occ_hi[o] = _occluder_extent(px, py, occluders[o])
                        else:
                            if not ext_known[t]:
                                ext_base[t], ext_lo[t], ext_hi[t] = _extent(px, py, targets[t])
                                ext_known[t] = True
                            occ_lo[o], occ_hi[o] = ext_lo[t] + ext_base[t], ext_hi[t] + ext_base[t]
                if state[o] == _SKIP:
                    continue
                span = occ_hi[o] - occ_lo[o]
                if width + _MARGIN_RAD < np.pi and span + _MARGIN_RAD < np.pi:
                    gap = _wrap(base + lo - occ_lo[o])
                    if gap < -width - _MARGIN_RAD or gap > span + _MARGIN_RAD:
                        continue
                cand[n_cand] = o
                n_cand += 1
            cast = n_cand > 0
            if not cast:  # every ray cast gets through
                seen = n_rays if need <= 0 else min(need, n_rays)
            else:
                seen = 0
                near2 = np.inf  # the target's nearest point, squared
                for e in range(4):
                    gx, gy = _edge_offset(px, py, tk, e)
                    near2 = min(near2, gx * gx + gy * gy)
                # with need > 0 the rays up to n_rays - need, all blocked, settle it
                rays = n_rays if need <= 0 else min(n_rays - need + 1, n_rays)
                for i in range(n_cand):
                    o = cand[i]
                    if _hides(px, py, occluders[o], occ_lo[o], occ_hi[o], occ_near[o], base + lo, width, n_rays,
                              rays, near2):
                        cast = False  # every ray blocked
                        break
            for r in range(n_rays if cast else 0):
                if need > 0 and (seen >= need or r - seen > n_rays - need):
                    break  # settled: enough rays seen, or too many blocked
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
                    rel = _wrap(ang - occ_lo[o])
                    if rel < 0.0 or rel > occ_hi[o] - occ_lo[o]:
                        continue
                    if _ray_rect(px, py, dx, dy, occluders[o]) < t_target:
                        blocked = True
                        cand[i], cand[0] = cand[0], o  # likely to block the next ray too
                        break
                if not blocked:
                    seen += 1
            if need > 0:
                share[j, k] = 1.0 if seen >= need else 0.0
            else:
                share[j, k] = seen / n_rays
    return share


@njit(cache=True)
def _hides(px, py, quad, occ_lo, occ_hi, occ_near, fan_lo, width, n_rays, rays, near2):
    """``quad``, an occluder of angular extent [occ_lo, occ_hi] from (px, py), blocks
    each of a target's first ``rays`` rays (ray r at fan_lo + width (r + 0.5) / n_rays,
    rad, world) in ``_visible_share``'s per-ray test, for a target whose nearest point is
    sqrt(``near2``) away. It does when those rays lie within its extent by
    ``_COVER_RAD``, none passes that near one of its corners, and where they enter it is
    nearer than the target by 5e-6 (relative, in distance; the viewer at least 1 mm
    from it): each ray then crosses two of its edges away from their ends and not
    along them, so ``_ray_rect`` finds the entry (rounding ~1e-16 relative, far below
    the margins). Where the rays enter, at most: the entry along the first and the last
    ray and along the direction of each corner between them (the edges' distance is
    convex along each edge). NaN anywhere: False."""
    span = occ_hi - occ_lo
    if rays <= 0 or not (width + _MARGIN_RAD < np.pi and span + _MARGIN_RAD < np.pi and occ_near > 1e-3):
        return False
    if not occ_near * occ_near * (1.0 + 1e-5) < near2:  # it enters no nearer than its nearest point
        return False
    first = fan_lo + width * 0.5 / n_rays
    last = fan_lo + width * (rays - 0.5) / n_rays
    gap = _wrap(first - occ_lo)
    if not (gap >= _COVER_RAD and gap + (last - first) <= span - _COVER_RAD):
        return False
    cos_first, sin_first = np.cos(first), np.sin(first)
    cos_last, sin_last = np.cos(last), np.sin(last)
    enter = _ray_rect(px, py, cos_first, sin_first, quad)
    bound2 = enter * enter
    enter = _ray_rect(px, py, cos_last, sin_last, quad)
    bound2 = max(bound2, enter * enter)
    if not bound2 * (1.0 + 1e-5) < near2:
        return False
    for c in range(4):
        wx, wy = quad[c, 0] - px, quad[c, 1] - py
        margin2 = _COVER_RAD * _COVER_RAD * (wx * wx + wy * wy)
        below = cos_first * wy - sin_first * wx  # < 0: clockwise of the first ray
        above = cos_last * wy - sin_last * wx  # > 0: counter-clockwise of the last
        if (below < 0.0 and below * below > margin2) or (above > 0.0 and above * above > margin2):
            continue  # beside every ray (the extent spans less than pi: the signs order them)
        phi = np.arctan2(below, cos_first * wx + sin_first * wy)  # from the first ray
        if not (phi == phi):
            return False
        for r in range(rays):
            if abs(phi - width * r / n_rays) <= _COVER_RAD:
                return False  # a ray through (or near) the corner
        enter = _ray_rect(px, py, wx, wy, quad)  # in units of the corner's distance
        if not enter < np.inf:
            return False
        bound2 = max(bound2, enter * enter * (wx * wx + wy * wy))
    return bound2 * (1.0 + 1e-5) < near2


def visible_share(viewers_xy: np.ndarray, ranges_m: np.ndarray, targets: np.ndarray, occluders: np.ndarray,
                  target_as_occluder: np.ndarray, self_target: np.ndarray | None = None,
                  n_rays: int = RAYS_PER_OBJECT) -> np.ndarray:
    """(J, K) share of each target's angular extent that viewer j sees unobstructed.

    ``targets`` (K, 4, 2) and ``occluders`` (O, 4, 2) are footprints (quads);
    ``target_as_occluder[k]`` is the occluder index of target k itself (-1 if none);
    ``self_target[j]`` is the target that is vehicle j's own body (-1 if none): j
    "sees" it (share 1) and it hides nothing from j.
    """
    if self_target is None:
        self_target = np.full(len(viewers_xy), -1)
    return _visible_share(*_kernel_args(viewers_xy, ranges_m, targets, occluders, target_as_occluder, self_target),
                          n_rays)


def match_vehicles(viewers_xy: np.ndarray, centroids: np.ndarray, gate_m: float = 3.0) -> np.ndarray:
    """For each viewer j, the target whose centroid is nearest its reported position
    within ``gate_m`` (that object is j itself), or -1."""
    if len(viewers_xy) == 0 or len(centroids) == 0:
        return np.full(len(viewers_xy), -1, dtype=np.int64)
    return _nearest_within(np.ascontiguousarray(viewers_xy, dtype=np.float64),
                           np.ascontiguousarray(centroids, dtype=np.float64), float(gate_m))


@njit(cache=True)
def _nearest_within(viewers, centroids, gate):
    """``match_vehicles``' numpy statements in one pass: the distances as np.linalg.norm
    takes them (the root of the sum of the two squares), the first nearest (or the first
    NaN, as np.argmin), kept if within ``gate``."""
    out = np.empty(viewers.shape[0], dtype=np.int64)
    for j in range(viewers.shape[0]):
        best, at = np.inf, 0
        for k in range(centroids.shape[0]):
            dx, dy = viewers[j, 0] - centroids[k, 0], viewers[j, 1] - centroids[k, 1]
            d = np.sqrt(dx * dx + dy * dy)
            if k == 0 or d < best or (d != d and best == best):
                best, at = d, k
        out[j] = at if best <= gate else -1
    return out


def visibility(share: np.ndarray) -> np.ndarray:
    """The paper's boolean v from the visible share."""
    return (share >= VISIBLE_SHARE).astype(np.float32)


def rays_needed(n_rays: int = RAYS_PER_OBJECT, threshold: float = VISIBLE_SHARE) -> int:
    """The fewest of ``n_rays`` rays seen with ``seen / n_rays >= threshold`` (``visibility``'s
    test, in its arithmetic); n_rays + 1 if none is enough."""
    return next((seen for seen in range(n_rays + 1) if seen / n_rays >= threshold), n_rays + 1)


def visible(viewers_xy: np.ndarray, ranges_m: np.ndarray, targets: np.ndarray, occluders: np.ndarray,
            target_as_occluder: np.ndarray, self_target: np.ndarray | None = None,
            n_rays: int = RAYS_PER_OBJECT) -> np.ndarray:
    """``visibility(visible_share(...))``, float32 (J, K), casting a target's rays only
    until its v is settled (at 40 vehicles about half of them)."""
    need = rays_needed(n_rays)
    if need == 0:  # a threshold every target passes unseen
        return visibility(visible_share(viewers_xy, ranges_m, targets, occluders, target_as_occluder, self_target,
                                        n_rays))
    if self_target is None:
        self_target = np.full(len(viewers_xy), -1)
    share = _visible_share(*_kernel_args(viewers_xy, ranges_m, targets, occluders, target_as_occluder, self_target),
                           n_rays, need)
    return share.astype(np.float32)


def _kernel_args(viewers_xy, ranges_m, targets, occluders, target_as_occluder, self_target) -> tuple:
    return (np.ascontiguousarray(viewers_xy, dtype=np.float64), np.ascontiguousarray(ranges_m, dtype=np.float64),
            np.ascontiguousarray(targets, dtype=np.float64).reshape(-1, 4, 2),
            np.ascontiguousarray(occluders, dtype=np.float64).reshape(-1, 4, 2),
            np.ascontiguousarray(target_as_occluder, dtype=np.int64), np.ascontiguousarray(self_target, dtype=np.int64))


@njit(cache=True)
def _farther(dx, dy, bound):
    """``np.hypot(dx, dy) > bound``, deciding from the squares where they are clear by a
    margin far above rounding (1e-12 relative) and asking hypot only in between."""
    if not bound >= 0.0:
        return np.hypot(dx, dy) > bound
    d2, b2 = dx * dx + dy * dy, bound * bound
    if d2 > b2 * (1.0 + 1e-12):
        return True
    if d2 < b2 * (1.0 - 1e-12):
        return False
    return np.hypot(dx, dy) > bound


@njit(cache=True)
def _first_close(pos_j, head_j, dims_j, obj_xy, obj_vel, head_k, dims_k, dt, safety, window):
    """(J, K) index of the first sample time t at which j's body comes within ``safety``
    of k's body anywhere k is between t - ``window`` and t + ``window`` (from now on);
    -1 if never. Each body is three circles of radius width/2 along its heading; k's
    circles sweep a segment over the window (constant velocity)."""
    J, T = pos_j.shape[0], pos_j.shape[1]
    K = obj_xy.shape[0]
    first = np.full((J, K), -1, dtype=np.int64)
    box_j = np.empty((J, 4))  # j's centres over the horizon: min x, max x, min y, max y
    for j in range(J):
        box_j[j, 0] = box_j[j, 2] = np.inf
        box_j[j, 1] = box_j[j, 3] = -np.inf
        for t in range(T):
            x, y = pos_j[j, t, 0], pos_j[j, t, 1]
            if not (x == x and y == y):  # NaN: no box, every pair sampled
                box_j[j, 0], box_j[j, 1], box_j[j, 2], box_j[j, 3] = -np.inf, np.inf, -np.inf, np.inf
                break
            box_j[j, 0], box_j[j, 1] = min(box_j[j, 0], x), max(box_j[j, 1], x)
            box_j[j, 2], box_j[j, 3] = min(box_j[j, 2], y), max(box_j[j, 3], y)
    tau_lo, tau_hi = np.inf, -np.inf  # the times k's segments span
    for t in range(T):
        t_lo = max(dt[t] - window, 0.0)
        tau_lo, tau_hi = min(tau_lo, t_lo, dt[t] + window), max(tau_hi, t_lo, dt[t] + window)
    box_k = np.empty((K, 4))  # k's centre over those times
    for k in range(K):
        x0, y0 = obj_xy[k, 0] + obj_vel[k, 0] * tau_lo, obj_xy[k, 1] + obj_vel[k, 1] * tau_lo
        x1, y1 = obj_xy[k, 0] + obj_vel[k, 0] * tau_hi, obj_xy[k, 1] + obj_vel[k, 1] * tau_hi
        if x0 == x0 and y0 == y0 and x1 == x1 and y1 == y1:
            box_k[k, 0], box_k[k, 1], box_k[k, 2], box_k[k, 3] = min(x0, x1), max(x0, x1), min(y0, y1), max(y0, y1)
        else:  # NaN (or no samples): no box, every pair sampled
            box_k[k, 0], box_k[k, 1], box_k[k, 2], box_k[k, 3] = -np.inf, np.inf, -np.inf, np.inf
    for j in range(J):
        off_j = max(dims_j[j, 0] - dims_j[j, 1], 0.0) / 2
        for k in range(K):
            off_k = max(dims_k[k, 0] - dims_k[k, 1], 0.0) / 2
            reach = dims_j[j, 1] / 2 + dims_k[k, 1] / 2 + safety
            if _apart(box_j[j], box_k[k], off_j + off_k + reach):
                continue  # the cheap reject below would reject every sample
            ck, sk = np.cos(head_k[k]), np.sin(head_k[k])
            vx, vy = obj_vel[k, 0], obj_vel[k, 1]
            for t in range(T):
                t_lo = max(dt[t] - window, 0.0)
                t_hi = dt[t] + window
                ax, ay = obj_xy[k, 0] + vx * t_lo, obj_xy[k, 1] + vy * t_lo
                ex, ey = vx * (t_hi - t_lo), vy * (t_hi - t_lo)
                len2 = ex * ex + ey * ey
                jx, jy = pos_j[j, t, 0], pos_j[j, t, 1]
                # cheap reject: j's centre far from the whole segment k's centre sweeps
                f = 0.0 if len2 <= 0.0 else min(max(((jx - ax) * ex + (jy - ay) * ey) / len2, 0.0), 1.0)
                if _farther(jx - ax - f * ex, jy - ay - f * ey, off_j + off_k + reach):
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


@njit(cache=True)
def _apart(a, b, bound):
    """The boxes ``a`` and ``b`` (min x, max x, min y, max y) are farther apart than
    ``bound`` (>= 0) by a margin far above rounding (1e-9 relative and absolute): every
    point of one is farther than ``bound`` from every point of the other. False where a
    bound is NaN."""
    if not bound >= 0.0:
        return False
    gx = max(b[0] - a[1], a[0] - b[1], 0.0)
    gy = max(b[2] - a[3], a[2] - b[3], 0.0)
    limit = bound * (1.0 + 1e-9) + 1e-9
    return gx * gx + gy * gy > limit * limit


def sample_trajectory(waypoints: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions and headings at ``times`` along waypoints [x, y, t]; holds the last point."""
    t = waypoints[:, 2]
    x = np.interp(times, t, waypoints[:, 0])
    y = np.interp(times, t, waypoints[:, 1])
    seg = np.clip(np.searchsorted(t, times, side="right") - 1, 0, max(len(t) - 2, 0))
    if len(waypoints) >= 2:
        d = waypoints[seg + 1, :2] - waypoints[seg, :2]
        heading = np.arctan2(d[:, 1], d[:, 0])
    else:
        heading = np.zeros(len(times))
    return np.stack([x, y], axis=1), heading


@njit(cache=True)
def _sample_all(waypoints: np.ndarray, starts: np.ndarray, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``sample_trajectory`` of every trajectory at once; trajectory j is
    ``waypoints[starts[j]:starts[j + 1]]`` (times ascending, at least one waypoint)."""
    J, T = starts.shape[0] - 1, times.shape[0]
    pos = np.empty((J, T, 2))
    head = np.zeros((J, T))
    for j in range(J):
        a, b = starts[j], starts[j + 1]
        n = b - a
        seg = 0
        heading, of = 0.0, -1  # the heading of segment ``of``: its arctangent once, not once per sample
        for i in range(T):
            t = times[i]
            while seg < n - 1 and waypoints[a + seg + 1, 2] <= t:  # last waypoint at or before t
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
                if p != of:
                    heading, of = np.arctan2(waypoints[p + 1, 1] - waypoints[p, 1],
                                             waypoints[p + 1, 0] - waypoints[p, 0]), p
                head[j, i] = heading
    return pos, head


@njit(cache=True)
def _sampled_first_close(waypoints, starts, times, dims_j, obj_xy, obj_vel, head_k, dims_k, dt, safety, window):
    """``_first_close`` of the trajectories sampled at ``times`` (``_sample_all``): one
    call instead of two."""
    pos_j, head_j = _sample_all(waypoints, starts, times)
    return _first_close(pos_j, head_j, dims_j, obj_xy, obj_vel, head_k, dims_k, dt, safety, window)


def relevance(trajectories: list[np.ndarray] | np.ndarray, dims_j: np.ndarray, obj_xy: np.ndarray,
              obj_vel: np.ndarray, obj_dims: np.ndarray, t_now_s: float, mode: str = "bool",
              horizon_s: float = HORIZON_S, step_s: float = STEP_S, safety_m: float = SAFETY_M,
              obj_heading: np.ndarray | None = None, window_s: float = WINDOW_S,
              starts: np.ndarray | None = None) -> np.ndarray:
    """(J, K) relevance of each object to each vehicle's trajectory.

    ``trajectories[j]``: waypoints (p, 3) [x, y, t_sim_s]; or, with ``starts`` (int64
    (J + 1,)), all of them packed in one float64 (P, 3) array, trajectory j
    ``trajectories[starts[j]:starts[j + 1]]``; ``dims_j`` (J, 2) length,
    width; objects: centroid (K, 2), velocity (K, 2), dims (K, 2) length, width, and
    heading (K,) (default: the direction of motion).
    """
    if starts is not None:
        waypoints = trajectories
    else:
        starts = np.zeros(len(trajectories) + 1, dtype=np.int64)
        starts[1:] = np.cumsum([len(wp) for wp in trajectories])
        waypoints = np.concatenate(trajectories).astype(np.float64) if trajectories else np.zeros((0, 3))
    J, K = len(starts) - 1, len(obj_xy)
    if J == 0 or K == 0:
        return np.zeros((J, K), dtype=np.float32)
    times = t_now_s + np.arange(0.0, horizon_s + 1e-9, step_s)
    if obj_heading is None:
        speed = np.hypot(obj_vel[:, 0], obj_vel[:, 1])
        obj_heading = np.where(speed > 0.1, np.arctan2(obj_vel[:, 1], obj_vel[:, 0]), 0.0)
    first = _sampled_first_close(waypoints, starts, times,
                                 *(np.ascontiguousarray(a, dtype=np.float64)
                                   for a in (dims_j, obj_xy, obj_vel, obj_heading, obj_dims)),
                                 times - t_now_s, safety_m, window_s)
    hit = first >= 0
    if mode == "bool":
        return hit.astype(np.float32)
    if mode == "ttc":
        ttc = (times - t_now_s)[np.maximum(first, 0)]
        return np.where(hit, 1.0 / (1.0 + ttc), 0.0).astype(np.float32)
    raise ValueError(f"relevance mode {mode!r}: 'bool' or 'ttc'")
