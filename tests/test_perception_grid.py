"""The grid's per-beam kernel against the integer arithmetic it replaced (kept here as
the reference), plus a hand-derived azimuth."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from numba import njit

from vehicle_agent.perception import LatticeRaster, _beam_cells


@njit(cache=True)
def reference_beam_cells(range_row, wx, wy, x, y, i0, j0, cell, inv, n, mount_m, tan_el, clear, cells, above):
    """``_beam_cells`` as it was: column and row converted to int64 each, the flat cell
    their integer product and sum."""
    for b in range(len(range_row)):
        d = range_row[b] * 0.01
        if inv > 0.0:
            ix = int(np.floor((x + d * wx) * inv)) - i0
            iy = int(np.floor((y + d * wy) * inv)) - j0
        else:
            ix = int(np.floor((x + d * wx) / cell)) - i0
            iy = int(np.floor((y + d * wy) / cell)) - j0
        inside = (range_row[b] != 0) & (ix >= 0) & (iy >= 0) & (ix < n) & (iy < n)
        cells[b] = iy * n + ix if inside else -1
        above[b] = mount_m + d * tan_el[b] > clear


def _both(range_row, wx, wy, x, y, i0, j0, cell, inv, n, tan_el):
    out = []
    for kernel in (_beam_cells, reference_beam_cells):
        cells, above = np.empty(len(range_row), dtype=np.int64), np.empty(len(range_row), dtype=np.bool_)
        kernel(range_row, wx, wy, x, y, i0, j0, cell, inv, n, 1.9, tan_el, 0.25, cells, above)
        out.append((cells.tolist(), above.tolist()))
    return out


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), cell=st.sampled_from([0.5, 0.25, 0.3, 1.0]), n=st.sampled_from([7, 40, 280]),
       snapped=st.booleans())
def test_beam_cells_equal_the_integer_arithmetic(seed, cell, n, snapped):
    """Random azimuths, poses and ranges (some zero, many off the grid); ``snapped``:
    the pose and ranges on the lattice, so that points fall on cell edges (-0.0 too)."""
    rng = np.random.default_rng(seed)
    range_row = rng.integers(0, 12000, 64).astype(np.uint16) * rng.choice([1, 0], 64, p=[0.9, 0.1]).astype(np.uint16)
    if snapped:
        range_row = (range_row // 50 * 50).astype(np.uint16)
    range_row.setflags(write=False)
    az = rng.choice([0.0, np.pi / 2, np.pi, -np.pi / 2]) if snapped else rng.uniform(-np.pi, np.pi)
    x, y = (rng.integers(-400, 400, 2) * cell).tolist() if snapped else rng.uniform(-300, 300, 2).tolist()
    if snapped and rng.random() < 0.3:
        x, y = -0.0, -0.0
    i0, j0 = (np.floor(np.array([x, y]) / cell).astype(int) - n // 2).tolist()
    i0, j0 = i0 + int(rng.integers(-3, 4)), j0 + int(rng.integers(-3, 4))
    inv = 1.0 / cell if cell in (0.5, 0.25, 1.0) else 0.0
    tan_el = np.tan(rng.uniform(-0.45, 0.05, 64))
    got, want = _both(range_row, float(np.cos(az)), float(np.sin(az)), x, y, i0, j0, cell, inv, n, tan_el)
    assert got == want


def test_an_azimuth_along_x_fills_the_cells_it_crosses():
    """From (0.2, 0.2) along +x on a 4 x 4 grid of 0.5 m cells at lattice (0, 0): returns at
    0.3, 0.8, 1.3 m fall in columns 1, 2, 3 of row 0 (cell 1, 2, 3); 1.8 m is past the
    grid and 0 is no return (-1 both); only the level beam is above the ground."""
    range_row = np.array([30, 80, 130, 180, 0], dtype=np.uint16)
    tan_el = np.array([0.0, -10.0, -10.0, -10.0, 0.0])
    cells, above = np.empty(5, dtype=np.int64), np.empty(5, dtype=np.bool_)
    _beam_cells(range_row, 1.0, 0.0, 0.2, 0.2, 0, 0, 0.5, 2.0, 4, 1.9, tan_el, 0.25, cells, above)
    assert cells.tolist() == [1, 2, 3, -1, -1]
    assert above.tolist() == [True, False, False, False, True]


def reference_cut(raster: LatticeRaster, i0: int, j0: int, n: int) -> np.ndarray:
    """``LatticeRaster._cut`` as it was: the fill everywhere, then the overlap copied in."""
    out = np.full((n, n), raster.fill, dtype=raster.values.dtype)
    ny, nx = raster.values.shape
    x0, y0 = i0 - raster.i0, j0 - raster.j0
    sx0, sy0, sx1, sy1 = max(x0, 0), max(y0, 0), min(x0 + n, nx), min(y0 + n, ny)
    if sx1 > sx0 and sy1 > sy0:
        out[sy0 - y0:sy1 - y0, sx0 - x0:sx1 - x0] = raster.values[sy0:sy1, sx0:sx1]
    return out


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), dtype=st.sampled_from([np.bool_, np.float64, np.uint8]))
def test_a_window_equals_the_filled_copy(seed, dtype):
    """Windows inside the raster, across its edges and outside it, of rasters of three
    dtypes: the same values, dtype and layout as filling then copying."""
    rng = np.random.default_rng(seed)
    values = rng.integers(0, 3, (int(rng.integers(1, 30)), int(rng.integers(1, 30)))).astype(dtype)
    raster = LatticeRaster(values, int(rng.integers(-20, 20)), int(rng.integers(-20, 20)), dtype(1))
    n = int(rng.integers(1, 35))
    ny, nx = values.shape
    edges_x, edges_y = [-1, 0, 1, nx - n - 1, nx - n, nx - n + 1], [-1, 0, 1, ny - n - 1, ny - n, ny - n + 1]
    x0 = int(rng.choice(edges_x)) if rng.random() < 0.7 else int(rng.integers(-n - 2, 32))  # at the edges, often
    y0 = int(rng.choice(edges_y)) if rng.random() < 0.7 else int(rng.integers(-n - 2, 32))
    i0, j0 = raster.i0 + x0, raster.j0 + y0
    got, want = raster.window(i0, j0, n), reference_cut(raster, i0, j0, n)
    assert got.dtype == want.dtype and got.flags.c_contiguous and not got.flags.writeable
    assert got.tobytes() == want.tobytes() and not np.shares_memory(got, values)


def test_a_window_inside_and_one_across_the_edge():
    """A 3 x 3 raster at lattice (10, 20), values 0..8: the 2 x 2 window at (11, 21) is its
    lower-right block; the one at (12, 22) has its corner value 8 and the fill elsewhere."""
    raster = LatticeRaster(np.arange(9.0).reshape(3, 3), 10, 20, -1.0)
    assert raster.window(11, 21, 2).tolist() == [[4.0, 5.0], [7.0, 8.0]]
    assert raster.window(12, 22, 2).tolist() == [[8.0, -1.0], [-1.0, -1.0]]
    assert raster.window(11, 20, 3).tolist() == [[1.0, 2.0, -1.0], [4.0, 5.0, -1.0], [7.0, 8.0, -1.0]]
