"""The grid's per-beam kernel against the integer arithmetic it replaced (kept here as
the reference), plus a hand-derived azimuth."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from numba import njit

from vehicle_agent.perception import _beam_cells


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
