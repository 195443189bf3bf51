"""Polylines as paths: arc length, where a point is along one, the point at a distance."""

from __future__ import annotations

import numpy as np


def arc_lengths(path: np.ndarray) -> np.ndarray:
    """Cumulative arc length at each vertex of a polyline (n, 2)."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])


def progress_along(path: np.ndarray, xy: np.ndarray, cum: np.ndarray | None = None) -> float:
    """Arc length of the path point closest to ``xy``; ``cum``: the path's ``arc_lengths``
    if the caller has them."""
    a, ab = path[:-1], np.diff(path, axis=0)
    len2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12)
    t = np.clip(np.einsum("ij,ij->i", xy - a, ab) / len2, 0.0, 1.0)
    i = int(np.argmin(np.linalg.norm(a + t[:, None] * ab - xy, axis=1)))
    return float((arc_lengths(path) if cum is None else cum)[i] + t[i] * np.sqrt(len2[i]))


def point_at(path: np.ndarray, s: float | np.ndarray, cum: np.ndarray | None = None) -> np.ndarray:
    """The point(s) at arc length ``s`` along the path (clamped to its ends); ``cum``: the
    path's ``arc_lengths`` if the caller has them."""
    cum = arc_lengths(path) if cum is None else cum
    s = np.clip(s, 0.0, cum[-1])
    return np.stack([np.interp(s, cum, path[:, 0]), np.interp(s, cum, path[:, 1])], axis=-1)
