"""Small planar geometry shared by the map, the scenarios and the judge (numpy only)."""

from __future__ import annotations

import numpy as np


def arc_lengths(poly: np.ndarray) -> np.ndarray:
    """Cumulative arc length at each vertex of a polyline (n, 2)."""
    seg = np.linalg.norm(np.diff(poly, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(seg)])


def point_at(poly: np.ndarray, s: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position(s) and heading(s) at arc length ``s`` (clamped to the polyline)."""
    cum = arc_lengths(poly)
    s = np.clip(np.asarray(s, dtype=float), 0.0, cum[-1])
    i = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(poly) - 2)
    d = poly[i + 1] - poly[i]
    seg = np.maximum(cum[i + 1] - cum[i], 1e-12)
    frac = (s - cum[i]) / seg
    xy = poly[i] + d * frac[..., None]
    yaw = np.arctan2(d[..., 1], d[..., 0])
    return xy, yaw


def project_s(route: np.ndarray, xy: np.ndarray) -> float:
    """Arc length along ``route`` of its point closest to ``xy`` (exact projection)."""
    a, ab = route[:-1], np.diff(route, axis=0)
    seg_len2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12)
    t = np.clip(np.einsum("ij,ij->i", xy - a, ab) / seg_len2, 0.0, 1.0)
    dist = np.linalg.norm(a + t[:, None] * ab - xy, axis=1)
    i = int(np.argmin(dist))
    return float(arc_lengths(route)[i] + t[i] * np.sqrt(seg_len2[i]))


def resample(poly: np.ndarray, step_m: float) -> np.ndarray:
    """Points every ``step_m`` along the polyline, end point included."""
    total = arc_lengths(poly)[-1]
    s = np.append(np.arange(0.0, total, step_m), total)
    return point_at(poly, s)[0]


def arc(center: tuple[float, float], radius: float, a0: float, a1: float, step_m: float = 0.5) -> np.ndarray:
    """A circular arc from angle a0 to a1 (radians), as a polyline."""
    n = max(2, int(np.ceil(abs(a1 - a0) * radius / step_m)) + 1)
    a = np.linspace(a0, a1, n)
    return np.stack([center[0] + radius * np.cos(a), center[1] + radius * np.sin(a)], axis=1)


def join(*parts: np.ndarray) -> np.ndarray:
    """Concatenate polylines, dropping a vertex repeated at a joint."""
    out = [parts[0]]
    for p in parts[1:]:
        if np.allclose(out[-1][-1], p[0]):
            p = p[1:]
        out.append(p)
    return np.concatenate(out, axis=0)


def first_crossing(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, float, float] | None:
    """First intersection of polyline ``a`` with polyline ``b``, walking along ``a``.

    Returns (point, arc length along a, arc length along b), or None.
    """
    p, r = a[:-1], np.diff(a, axis=0)  # segments of a: p + t r
    q, s = b[:-1], np.diff(b, axis=0)  # segments of b: q + u s
    rxs = r[:, None, 0] * s[None, :, 1] - r[:, None, 1] * s[None, :, 0]
    qp = q[None, :, :] - p[:, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (qp[..., 0] * s[None, :, 1] - qp[..., 1] * s[None, :, 0]) / rxs
        u = (qp[..., 0] * r[:, None, 1] - qp[..., 1] * r[:, None, 0]) / rxs
    hit = (np.abs(rxs) > 1e-12) & (t >= 0) & (t <= 1) & (u >= 0) & (u <= 1)
    if not hit.any():
        return None
    ca, cb = arc_lengths(a), arc_lengths(b)
    ii, jj = np.nonzero(hit)
    sa = ca[ii] + t[ii, jj] * np.linalg.norm(r[ii], axis=1)
    k = int(np.argmin(sa))
    i, j = ii[k], jj[k]
    point = p[i] + t[i, j] * r[i]
    sb = cb[j] + u[i, j] * np.linalg.norm(s[j])
    return point, float(sa[k]), float(sb)


def box_corners(cx, cy, yaw, length, width) -> np.ndarray:
    """Corners (..., 4, 2) of oriented rectangles, counter-clockwise."""
    cx, cy, yaw, length, width = np.broadcast_arrays(*map(np.asarray, (cx, cy, yaw, length, width)))
    c, s = np.cos(yaw), np.sin(yaw)
    hl, hw = length / 2.0, width / 2.0
    local = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], dtype=float)  # (4, 2) in (l, w) units
    lx = local[:, 0] * hl[..., None]
    ly = local[:, 1] * hw[..., None]
    x = cx[..., None] + lx * c[..., None] - ly * s[..., None]
    y = cy[..., None] + lx * s[..., None] + ly * c[..., None]
    return np.stack([x, y], axis=-1)


def _point_segment_dist(pts: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from each point (n, 2) to each segment (m, 2)-(m, 2): (n, m)."""
    ab = b - a
    ap = pts[:, None, :] - a[None, :, :]
    t = np.clip(np.einsum("nmk,mk->nm", ap, ab) / np.maximum(np.einsum("mk,mk->m", ab, ab), 1e-12), 0, 1)
    closest = a[None] + t[..., None] * ab[None]
    return np.linalg.norm(pts[:, None, :] - closest, axis=2)


def _inside(pts: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Points inside a convex counter-clockwise polygon."""
    e = np.roll(poly, -1, axis=0) - poly
    rel = pts[:, None, :] - poly[None]
    cross = e[None, :, 0] * rel[..., 1] - e[None, :, 1] * rel[..., 0]
    return np.all(cross >= 0, axis=1)


def rect_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Distance between two convex quads (4, 2); 0 when they overlap."""
    if _inside(a, b).any() or _inside(b, a).any():
        return 0.0
    ea, eb = np.roll(a, -1, axis=0), np.roll(b, -1, axis=0)
    # edges crossing without a corner inside (a cross shape) overlap too
    if first_crossing(np.vstack([a, a[:1]]), np.vstack([b, b[:1]])) is not None:
        return 0.0
    return float(min(_point_segment_dist(a, b, eb).min(), _point_segment_dist(b, a, ea).min()))


def wrap_angle(a):
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi
