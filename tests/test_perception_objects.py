"""Object extraction's fused kernels against the numpy and numba code they replaced
(kept here as the references), plus hand-derived cases."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numba import njit

from vehicle_agent.perception import (ABOVE, EMPTY, DetectedObject, Grid, GridSpec, _above_cells, _cells_by_label,
                                      _label_sums, _labels, _object_stats, _objects, _rays_by_label)


def reference_objects(pts, pts32, bounds, grid, labels, k, cells):
    """``_objects`` as it was: two kernels, then the boxes in numpy."""
    cells_ij, cell_bounds = _cells_by_label(cells, labels.ravel(), k, grid.state.shape[0], grid.i0, grid.j0)
    mean, yaw, u_lo, u_hi, v_lo, v_hi, z_mean = _object_stats(pts, bounds)
    nonempty = bounds[1:] > bounds[:-1]
    kept = np.flatnonzero(nonempty).tolist()
    if len(kept) < k:
        mean, yaw, z_mean = mean[nonempty], yaw[nonempty], z_mean[nonempty]
        u_lo, u_hi, v_lo, v_hi = u_lo[nonempty], u_hi[nonempty], v_lo[nonempty], v_hi[nonempty]
    cy, sy = np.cos(yaw), np.sin(yaw)
    half_u, half_v = (u_hi + u_lo) / 2, (v_hi + v_lo) / 2
    centroid = np.empty((len(kept), 3))
    centroid[:, 0] = mean[:, 0] + cy * half_u + -sy * half_v
    centroid[:, 1] = mean[:, 1] + sy * half_u + cy * half_v
    centroid[:, 2] = z_mean
    length, width = (u_hi - u_lo).tolist(), (v_hi - v_lo).tolist()
    yaws = yaw.tolist()
    return [DetectedObject(pts32[bounds[lab]:bounds[lab + 1]], cells_ij[cell_bounds[lab]:cell_bounds[lab + 1]],
                           centroid[o], yaws[o], length[o], width[o]) for o, lab in enumerate(kept)]


@njit(cache=True)
def reference_rays_by_label(range_cm, cos_az, sin_az, tan_el, x, y, yaw, mount_m, rays, flat_labels, k):
    """``_rays_by_label`` as it was: the rays counted per label in memory, one by one."""
    counts = np.zeros(k + 1, dtype=np.int64)
    for t in range(rays.shape[0]):
        counts[flat_labels[rays[t, 2]]] += 1
    bounds = np.zeros(k + 1, dtype=np.int64)
    for lab in range(1, k + 1):
        bounds[lab] = bounds[lab - 1] + counts[lab]
    fill = bounds[:-1].copy()
    out = np.empty((bounds[k], 3))
    c, s = np.cos(yaw), np.sin(yaw)
    for t in range(rays.shape[0]):
        lab = flat_labels[rays[t, 2]]
        if lab == 0:
            continue
        i, b = rays[t, 0], rays[t, 1]
        wx = c * cos_az[i] - s * sin_az[i]
        wy = s * cos_az[i] + c * sin_az[i]
        d = range_cm[i, b] * 0.01
        p = fill[lab - 1]
        out[p, 0] = x + d * wx
        out[p, 1] = y + d * wy
        out[p, 2] = mount_m + d * tan_el[b]
        fill[lab - 1] += 1
    return out, out.astype(np.float32), bounds


def _assert_same_objects(got, want):
    assert len(got) == len(want)
    for g, w in zip(got, want):
        assert type(g) is DetectedObject
        for name in ("points_world", "cells", "centroid"):
            a, b = getattr(g, name), getattr(w, name)
            assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), name
        for name in ("yaw_rad", "length_m", "width_m"):
            a, b = getattr(g, name), getattr(w, name)
            assert type(a) is type(b) is float and np.float64(a).tobytes() == np.float64(b).tobytes(), name


def _labelled_grid(rng, n):
    """A grid of random ABOVE cells, labelled (shadows merged from a random sensor)."""
    spec = GridSpec(half_extent_m=n * 0.25, reach_cells=int(rng.integers(1, 4)))
    state = rng.choice(np.array([EMPTY, ABOVE], dtype=np.uint8), size=(n, n), p=[0.85, 0.15])
    grid = Grid(spec, int(rng.integers(-60, 60)), int(rng.integers(-60, 60)), state, rng.random((n, n)) < 0.9)
    sensor = tuple(((np.array([grid.i0, grid.j0]) + rng.uniform(0, n, 2)) * spec.cell_m).tolist())
    return grid, _labels(grid, sensor)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.sampled_from([8, 24, 40]), empty_share=st.sampled_from([0.0, 0.3, 1.0]))
def test_objects_equal_the_numpy_boxes_bit_for_bit(seed, n, empty_share):
    """Random points per label (some labels without any, on a lattice so that ties in
    the extent and points on the mean occur), against the reference."""
    rng = np.random.default_rng(seed)
    grid, (labels, k, cells) = _labelled_grid(rng, n)
    counts = rng.integers(1, 40, k) * (rng.random(k) >= empty_share)
    bounds = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    pts = np.round(rng.normal(0.0, 3.0, (int(bounds[-1]), 3)) * rng.choice([1.0, 4.0])) / 4.0
    pts[:, :2] += rng.uniform(-100, 100, 2)
    if rng.random() < 0.5:
        pts += rng.normal(0.0, 1e-3, pts.shape)
    pts32 = pts.astype(np.float32)
    want = reference_objects(pts, pts32, bounds, grid, labels, k, cells)
    _assert_same_objects(_objects(pts, pts32, bounds, grid, labels, k, cells), want)
    _assert_same_objects(_objects(pts, pts32, bounds, grid, labels, k, cells, _label_sums(pts, bounds)), want)
    xy = np.ascontiguousarray(pts[:, :2])  # as _rays_by_label gives them, the heights in the sums only
    _assert_same_objects(_objects(xy, pts32, bounds, grid, labels, k, cells, _label_sums(pts, bounds)), want)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.sampled_from([8, 24, 40]))
def test_labels_from_known_cells_equal_the_whole_grids_on_those_cells(seed, n):
    """``_labels`` with the ABOVE cells given (as ``scan_grid`` finds them) leaves the
    other cells' labels unset: on the given cells, the labels and k of the whole grid's."""
    rng = np.random.default_rng(seed)
    grid, _ = _labelled_grid(rng, n)
    np.empty((n, n), dtype=np.int32).fill(-7)  # garbage in memory the labels below may reuse
    sensor = tuple(((np.array([grid.i0, grid.j0]) + rng.uniform(0, n, 2)) * grid.spec.cell_m).tolist())
    want, want_k, cells = _labels(grid, sensor)
    labels, k, same = _labels(grid, sensor, _above_cells(grid.state, grid.drivable))
    assert k == want_k and np.array_equal(same, cells)
    assert labels.ravel()[cells].tolist() == want.ravel()[cells].tolist()


def test_a_rotated_rectangle_becomes_one_box_and_an_empty_label_none():
    """Label 1 has no points; label 2 the outline of a 4 x 2 m rectangle turned 30 degrees,
    centred at (5, -3), 1 m high: one object, its box the rectangle."""
    u = np.concatenate([np.linspace(-2, 2, 41), np.linspace(-2, 2, 41), np.full(21, -2.0), np.full(21, 2.0)])
    v = np.concatenate([np.full(41, -1.0), np.full(41, 1.0), np.linspace(-1, 1, 21), np.linspace(-1, 1, 21)])
    th = np.radians(30.0)
    pts = np.stack([5 + u * np.cos(th) - v * np.sin(th), -3 + u * np.sin(th) + v * np.cos(th), np.ones_like(u)], 1)
    spec = GridSpec(half_extent_m=2.0)
    state = np.zeros((8, 8), dtype=np.uint8)
    labels = np.zeros((8, 8), dtype=np.int32)
    labels[1, 1], labels[5, 6] = 1, 2
    grid = Grid(spec, 10, -20, state, np.ones((8, 8), dtype=bool))
    (obj,) = _objects(pts, pts.astype(np.float32), np.array([0, 0, len(pts)]), grid, labels, 2, np.array([9, 46]))
    assert obj.centroid == pytest.approx([5.0, -3.0, 1.0])
    assert (obj.yaw_rad, obj.length_m, obj.width_m) == pytest.approx((th, 4.0, 2.0))
    assert obj.cells.tolist() == [[16, -15]]  # cell 46: row 5, column 6 of a grid at lattice (10, -20)
    assert len(obj.points_world) == len(pts) and obj.points_world.dtype == np.float32


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), run=st.sampled_from([1, 5, 60]))
def test_rays_by_label_equals_the_per_ray_count(seed, run):
    """Rays in random cells (in runs of one cell, as a LiDAR's columns give them), some
    unlabelled, against the reference; the same points and bounds."""
    rng = np.random.default_rng(seed)
    n_az, n_beams, n = 50, 16, 12
    range_cm = rng.integers(0, 6000, (n_az, n_beams)).astype(np.uint16)
    range_cm.setflags(write=False)
    az = np.sort(rng.uniform(-np.pi, np.pi, n_az))
    tan_el = np.tan(rng.uniform(-0.4, 0.05, n_beams))
    m = int(rng.integers(0, 300))
    rays = np.empty((m, 3), dtype=np.uint32)  # as scan_grid gives them
    rays[:, 0] = np.sort(rng.integers(0, n_az, m))
    rays[:, 1] = rng.integers(0, n_beams, m)
    rays[:, 2] = np.repeat(rng.integers(0, n * n, m // run + 1), run)[:m]
    k = int(rng.integers(1, 6))
    flat_labels = rng.integers(0, k + 1, n * n).astype(np.int32)
    args = (range_cm, np.cos(az), np.sin(az), tan_el, float(rng.uniform(-50, 50)), float(rng.uniform(-50, 50)),
            float(rng.uniform(-np.pi, np.pi)), 1.9, rays, flat_labels, k)
    *got, sums = _rays_by_label(*args)
    want = list(reference_rays_by_label(*args))
    want[0] = np.ascontiguousarray(want[0][:, :2])  # float64: x and y only
    for a, b in zip(got, want, strict=True):
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
    assert sums.tobytes() == _label_sums(reference_rays_by_label(*args)[0], want[2]).tobytes()  # as placed


def test_rays_by_label_groups_by_label_in_ray_order():
    """Three rays straight ahead (azimuth 0, level beam) at 10, 20 and 30 m, in cells
    labelled 2, 1, 2: label 1 gets the 20 m ray, label 2 the 10 and 30 m ones."""
    range_cm = np.array([[1000, 2000, 3000]], dtype=np.uint16)
    rays = np.array([[0, 0, 5], [0, 1, 6], [0, 2, 7]], dtype=np.uint32)
    flat_labels = np.array([0, 0, 0, 0, 0, 2, 1, 2], dtype=np.int32)
    pts, pts32, bounds, sums = _rays_by_label(range_cm, np.ones(1), np.zeros(1), np.zeros(3), 0.0, 0.0, 0.0, 1.9,
                                              rays, flat_labels, 2)
    assert bounds.tolist() == [0, 1, 3] and sums.tolist() == [[20.0, 0.0, 1.9], [40.0, 0.0, 3.8]]
    assert pts.tolist() == [[20.0, 0.0], [10.0, 0.0], [30.0, 0.0]]
    assert pts32.dtype == np.float32 and pts32.tolist() == np.float32([[20, 0, 1.9], [10, 0, 1.9], [30, 0, 1.9]]).tolist()
