"""Polylines as paths: arc length, where a point is along one, the point at a distance.

Each is one numba kernel over the polyline's vertices: the planner and the controller
ask these a dozen times a tick of paths of 40-100 points, where the numpy versions'
five to eight calls each cost more than the arithmetic. The kernels do the numpy
versions' float operations in the same order (``tests/test_paths.py`` keeps those as
the reference): same values to the bit.
"""

from __future__ import annotations

import numpy as np
from numba import njit

# "the caller has no arc lengths": the kernels sum them themselves. Writable, like the
# arc lengths callers pass, so that a kernel has one signature for both (numba types a
# read-only array apart; each signature is one more for the warm-up to load)
_NO_CUM = np.zeros(0)


def arc_lengths(path: np.ndarray) -> np.ndarray:
    """Cumulative arc length at each vertex of a polyline (n, 2)."""
    return _arc_lengths(np.asarray(path, dtype=np.float64))


def progress_along(path: np.ndarray, xy: np.ndarray, cum: np.ndarray | None = None) -> float:
    """Arc length of the path point closest to ``xy``; ``cum``: the path's ``arc_lengths``
    if the caller has them."""
    path = np.asarray(path, dtype=np.float64)
    if len(path) < 2:
        raise ValueError("attempt to get argmin of an empty sequence")  # as the numpy version
    return _progress_along(path, float(xy[0]), float(xy[1]), _NO_CUM if cum is None else cum)


def point_at(path: np.ndarray, s: float | np.ndarray, cum: np.ndarray | None = None) -> np.ndarray:
    """The point(s) at arc length ``s`` along the path (clamped to its ends); ``cum``: the
    path's ``arc_lengths`` if the caller has them."""
    s = np.asarray(s, dtype=np.float64)
    if len(path) == 0:
        raise ValueError("array of sample points is empty")  # as np.interp
    out = _point_at(np.asarray(path, dtype=np.float64), s.reshape(-1), _NO_CUM if cum is None else cum)
    return out.reshape(s.shape + (2,))


@njit(cache=True)
def _segment_length(path, k):
    """``np.linalg.norm`` of the segment from vertex k to k + 1."""
    dx, dy = path[k + 1, 0] - path[k, 0], path[k + 1, 1] - path[k, 1]
    return np.sqrt(dx * dx + dy * dy)


@njit(cache=True)
def _arc_lengths(path):
    """``np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])``."""
    n = path.shape[0]
    out = np.empty(max(n, 1))
    out[0] = 0.0
    for k in range(n - 1):
        out[k + 1] = out[k] + _segment_length(path, k)  # 0.0 + d is d: cumsum's first term
    return out


@njit(cache=True)
def _clip(v, lo, hi):
    """``np.clip`` of one float64 (NaN in ``v`` or a bound propagates, as numpy's)."""
    if not np.isnan(v):
        v = v if v > lo else lo
    if not np.isnan(v):
        v = v if v < hi else hi
    return v


@njit(cache=True)
def _segment_foot(path, k, x, y):
    """The foot of (x, y) on segment k of ``path``: its parameter t in [0, 1], the
    segment's squared length (at least 1e-12, as ``np.maximum(., 1e-12)``; NaN stays),
    and the foot's x and y."""
    ax, ay = path[k, 0], path[k, 1]
    abx, aby = path[k + 1, 0] - ax, path[k + 1, 1] - ay
    len2 = abx * abx + aby * aby
    if len2 < 1e-12:
        len2 = 1e-12
    t = _clip(((x - ax) * abx + (y - ay) * aby) / len2, 0.0, 1.0)
    return t, len2, ax + t * abx, ay + t * aby


@njit(cache=True)
def _progress_along(path, x, y, cum):
    """The numpy ``progress_along``: each segment's foot of (x, y), the first nearest (a
    NaN distance wins, as ``np.argmin``), its arc length; ``cum`` empty: summed here."""
    best, best_d, best_t, best_len2 = 0, np.inf, 0.0, 0.0
    for k in range(path.shape[0] - 1):
        t, len2, fx, fy = _segment_foot(path, k, x, y)
        px, py = fx - x, fy - y
        d = np.sqrt(px * px + py * py)
        if k == 0 or d < best_d or (np.isnan(d) and not np.isnan(best_d)):
            best, best_d, best_t, best_len2 = k, d, t, len2
        if np.isnan(d):
            break
    if cum.shape[0] > 0:
        s = cum[best]
    else:
        s = 0.0
        for k in range(best):
            s = s + _segment_length(path, k)
    return s + best_t * np.sqrt(best_len2)


@njit(cache=True)
def _interp_index(key, xp):
    """``np.interp``'s segment of ``key`` (not NaN) in the ascending ``xp``: i with
    xp[i] <= key < xp[i + 1]; -1 below xp[0], len - 1 at xp[-1], len above it."""
    n = xp.shape[0]
    if key > xp[n - 1]:
        return n
    if key < xp[0]:
        return -1
    lo, hi = 0, n  # the number of xp at or below key, by bisection
    while lo < hi:
        mid = lo + ((hi - lo) >> 1)
        if key >= xp[mid]:
            lo = mid + 1
        else:
            hi = mid
    return lo - 1


@njit(cache=True)
def _interp(key, j, xp, fp):
    """``np.interp(key, xp, fp)`` (key clipped to xp's range or NaN, ``j`` its
    ``_interp_index``), with numpy's expression and its NaN fallbacks."""
    n = xp.shape[0]
    if n == 1:
        return fp[0]  # key is xp[0] or NaN: numpy's one-point case gives fp[0] for both
    if np.isnan(key):
        return key
    if j == -1:
        return fp[0]
    if j >= n - 1:
        return fp[n - 1]
    if xp[j] == key:
        return fp[j]
    slope = (fp[j + 1] - fp[j]) / (xp[j + 1] - xp[j])
    out = slope * (key - xp[j]) + fp[j]
    if np.isnan(out):
        out = slope * (key - xp[j + 1]) + fp[j + 1]
        if np.isnan(out) and fp[j] == fp[j + 1]:
            out = fp[j]
    return out


@njit(cache=True)
def _point_at(path, s, cum):
    """(K, 2): the numpy ``point_at`` of every ``s``, ``np.clip`` then ``np.interp`` of
    x and y; ``cum`` empty: ``_arc_lengths(path)``."""
    if cum.shape[0] == 0:
        cum = _arc_lengths(path)
    out = np.empty((s.shape[0], 2))
    xs, ys = np.ascontiguousarray(path[:, 0]), np.ascontiguousarray(path[:, 1])
    for k in range(s.shape[0]):
        key = _clip(s[k], 0.0, cum[cum.shape[0] - 1])
        j = _interp_index(key, cum) if not np.isnan(key) else 0
        out[k, 0] = _interp(key, j, cum, xs)
        out[k, 1] = _interp(key, j, cum, ys)
    return out
