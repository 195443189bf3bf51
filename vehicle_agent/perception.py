"""Object extraction (paper 5.1): a bird's-eye occupancy grid over one LiDAR scan.

The grid is axis-aligned with the world and snapped to a world lattice of ``cell_m``
cells, so the same world cell has the same global index in every vehicle's grid:
objects from different vehicles that fall in the same world cells are the same object.
Each cell is EMPTY (no return: unknown, possibly occluded), GROUND (only ground
returns) or ABOVE (a return above ``ground_clear_m``, using the LiDAR mount height).
Cells off the drivable area are ignored; contiguous ABOVE cells (8-connected) on the
drivable area form an object.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from protocol.codec import slots_constructor


EMPTY, GROUND, ABOVE = 0, 1, 2


def exact_inverse(cell_m: float) -> float:
    """1 / ``cell_m`` where dividing by ``cell_m`` and multiplying by it give the same
    result for every float (``cell_m`` a power of two, e.g. 0.5 m: both are exact
    scalings), else 0.0. The kernels that bin many points multiply then (division is
    about three times slower) and divide otherwise."""
    mantissa, _ = math.frexp(cell_m)
    return 1.0 / cell_m if cell_m > 0.0 and mantissa == 0.5 else 0.0


@dataclass(frozen=True, slots=True)
class GridSpec:
    cell_m: float = 0.5
    half_extent_m: float = 70.0  # the grid spans +-70 m around the vehicle (the paper's authors' choice)
    ground_clear_m: float = 0.25  # returns higher than this above the ground are obstacles
    reach_cells: int = 3  # above-ground cells this close (Chebyshev) belong to one object

    @property
    def cells(self) -> int:
        return int(round(2 * self.half_extent_m / self.cell_m))


@dataclass(frozen=True, slots=True)
class Grid:
    """One tick's occupancy grid; ``state[iy, ix]`` covers world cell (i0 + ix, j0 + iy)."""

    spec: GridSpec
    i0: int  # global lattice index of column 0 (x)
    j0: int  # global lattice index of row 0 (y)
    state: np.ndarray  # uint8 (n, n)
    drivable: np.ndarray  # bool (n, n)

    @property
    def origin_xy(self) -> tuple[float, float]:
        return self.i0 * self.spec.cell_m, self.j0 * self.spec.cell_m

    def cell_of(self, xy: np.ndarray) -> np.ndarray:
        """(…, 2) row/col indices in this grid of world points (may fall outside)."""
        ij = np.floor(np.asarray(xy) / self.spec.cell_m).astype(np.int64)
        return np.stack([ij[..., 1] - self.j0, ij[..., 0] - self.i0], axis=-1)

    def cell_centers(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        c = self.spec.cell_m
        return np.stack([(self.i0 + cols + 0.5) * c, (self.j0 + rows + 0.5) * c], axis=-1)

    def occluded(self) -> np.ndarray:
        """Drivable cells with no return at all: hidden from this vehicle (or beyond range)."""
        return (self.state == EMPTY) & self.drivable


@dataclass(frozen=True, slots=True)
class DetectedObject:
    """An object in one vehicle's view, in the world frame."""

    points_world: np.ndarray  # float32 (n, 3): x, y, height above ground
    cells: np.ndarray  # int64 (m, 2): global lattice (i, j) of its cells
    centroid: np.ndarray  # float64 (3,)
    yaw_rad: float  # orientation of the longer side
    length_m: float
    width_m: float

    def corners(self) -> np.ndarray:
        c, s = np.cos(self.yaw_rad), np.sin(self.yaw_rad)
        hl, hw = self.length_m / 2, self.width_m / 2
        local = np.array([[hl, hw], [-hl, hw], [-hl, -hw], [hl, -hw]])
        return self.centroid[:2] + local @ np.array([[c, s], [-s, c]])


def corners_of(objects: list[DetectedObject]) -> np.ndarray:
    """(K, 4, 2) ``corners()`` of every object in one pass: the same products (one 4 x 2
    by 2 x 2 matrix product per object), so the same values."""
    if not objects:
        return np.zeros((0, 4, 2))
    yaw = np.array([o.yaw_rad for o in objects], dtype=np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    hl = np.array([o.length_m for o in objects], dtype=np.float64) / 2
    hw = np.array([o.width_m for o in objects], dtype=np.float64) / 2
    local = np.stack([np.stack([hl, hw], 1), np.stack([-hl, hw], 1), np.stack([-hl, -hw], 1),
                      np.stack([hl, -hw], 1)], 1)
    rotation = np.stack([np.stack([c, s], 1), np.stack([-s, c], 1)], 1)
    centroid = np.array([o.centroid[:2] for o in objects], dtype=np.float64)
    return centroid[:, None, :] + local @ rotation


@njit(cache=True)
def _bin(world, i0, j0, cell, n, clear, state, cell_idx):
    """Classify cells and remember each point's flat cell index (-1 outside)."""
    for p in range(world.shape[0]):
        ix = int(np.floor(world[p, 0] / cell)) - i0
        iy = int(np.floor(world[p, 1] / cell)) - j0
        if ix < 0 or iy < 0 or ix >= n or iy >= n:
            cell_idx[p] = -1
            continue
        c = iy * n + ix
        cell_idx[p] = c
        if world[p, 2] > clear:
            state[c] = 2
        elif state[c] == 0:
            state[c] = 1


@njit(cache=True)
def _above_cells(state, drivable):
    """The flat indices, in grid order, of the ABOVE cells on the drivable area."""
    flat_state, flat_drivable = state.ravel(), drivable.ravel()
    m = 0
    cells = np.empty(len(flat_state), dtype=np.int64)
    for q in range(len(flat_state)):
        if flat_state[q] == ABOVE and flat_drivable[q]:
            cells[m] = q
            m += 1
    return cells[:m]


@njit(cache=True)
def _components(state, drivable, reach, cells, whole=True):
    """Components of the ABOVE cells on the drivable area, ``cells`` (their flat indices
    in grid order), where cells up to ``reach`` cells apart (Chebyshev) connect: reach 1
    is 8-connectivity; larger reaches bridge the gaps a LiDAR's rings and columns leave
    on surfaces seen at a grazing angle. Labels 1..k (numbered by lowest cell), and k;
    only the given cells are visited, no mask of the whole grid is built. Not ``whole``:
    the labels of other cells are left unset (only the labels of ``cells`` are read),
    rather than 300 kB of zeros written at 280 x 280 cells."""
    ny, nx = state.shape
    m = len(cells)
    if whole:
        labels = np.zeros((ny, nx), dtype=np.int32)
    else:
        labels = np.empty((ny, nx), dtype=np.int32)
        flat = labels.ravel()
        for t in range(m):
            flat[cells[t]] = 0
    stack = np.empty(m, dtype=np.int64)
    k = 0
    for t in range(m):
        y, x = divmod(cells[t], nx)
        if labels[y, x] != 0:
            continue
        k += 1
        labels[y, x] = k
        stack[0] = cells[t]
        top = 1
        while top > 0:
            top -= 1
            cy, cx = divmod(stack[top], nx)
            for dy in range(-reach, reach + 1):
                for dx in range(-reach, reach + 1):
                    yy, xx = cy + dy, cx + dx
                    if (0 <= yy < ny and 0 <= xx < nx and state[yy, xx] == ABOVE and drivable[yy, xx]
                            and labels[yy, xx] == 0):  # one of ``cells``: its label is set
                        labels[yy, xx] = k
                        stack[top] = yy * nx + xx
                        top += 1
    return labels, k


class LatticeRaster:
    """Values on a window of the world lattice, computed once, sliced per tick."""

    def __init__(self, values: np.ndarray, i0: int, j0: int, fill) -> None:
        self.values, self.i0, self.j0, self.fill = values, i0, j0, fill
        self._last: tuple[tuple[int, int, int], np.ndarray] | None = None

    def window(self, i0: int, j0: int, n: int) -> np.ndarray:
        """The (n, n) values of the grid whose cell (0, 0) is lattice (i0, j0), read-only:
        a vehicle that stands still asks for the same window every tick, and gets the
        same array."""
        if self._last is not None and self._last[0] == (i0, j0, n):
            return self._last[1]
        out = self._cut(i0, j0, n)
        out.setflags(write=False)
        self._last = ((i0, j0, n), out)
        return out

    def _cut(self, i0: int, j0: int, n: int) -> np.ndarray:
        ny, nx = self.values.shape
        x0, y0 = i0 - self.i0, j0 - self.j0
        if 0 <= x0 and x0 + n <= nx and 0 <= y0 and y0 + n <= ny:  # inside: a copy, no fill written first
            return self.values[y0:y0 + n, x0:x0 + n].copy()
        out = np.full((n, n), self.fill, dtype=self.values.dtype)
        sx0, sy0 = max(x0, 0), max(y0, 0)
        sx1, sy1 = min(x0 + n, nx), min(y0 + n, ny)
        if sx1 > sx0 and sy1 > sy0:
            out[sy0 - y0:sy1 - y0, sx0 - x0:sx1 - x0] = self.values[sy0:sy1, sx0:sx1]
        return out


def lattice_centers(points: np.ndarray, cell_m: float, margin_m: float) -> tuple[int, int, np.ndarray, np.ndarray]:
    """The lattice window covering ``points`` plus a margin: (i0, j0, x centres, y centres)."""
    lo = np.floor((points.min(axis=0) - margin_m) / cell_m).astype(int)
    hi = np.ceil((points.max(axis=0) + margin_m) / cell_m).astype(int)
    xs = (np.arange(hi[0] - lo[0]) + lo[0] + 0.5) * cell_m
    ys = (np.arange(hi[1] - lo[1]) + lo[1] + 0.5) * cell_m
    return int(lo[0]), int(lo[1]), xs, ys


class DrivableRaster(LatticeRaster):
    """The map's drivable area on the world lattice, rasterized once per agent."""

    def __init__(self, polygons: list[np.ndarray], cell_m: float, margin_m: float = 100.0) -> None:
        i0, j0, xs, ys = lattice_centers(np.vstack(polygons), cell_m, margin_m)
        mask = np.zeros((len(ys), len(xs)), dtype=bool)
        for poly in polygons:
            poly = np.ascontiguousarray(poly, dtype=np.float64)
            # only the cells whose centres lie in the polygon's bounding box can be inside it
            c0, c1 = np.searchsorted(xs, poly[:, 0].min()), np.searchsorted(xs, poly[:, 0].max(), side="right")
            r0, r1 = np.searchsorted(ys, poly[:, 1].min()), np.searchsorted(ys, poly[:, 1].max(), side="right")
            _fill_convex(mask, xs, ys, int(r0), int(r1), int(c0), int(c1), poly)
        super().__init__(mask, i0, j0, False)


@njit(cache=True)
def _fill_convex(mask, xs, ys, r0, r1, c0, c1, poly):
    """Set the cells of rows r0:r1, columns c0:c1 whose centre (xs[c], ys[r]) is inside
    the convex polygon (either winding; on an edge counts as inside). 40 agents do this
    for the whole map at startup: in numpy over a meshgrid it took ~0.2 s each."""
    m = poly.shape[0]
    for r in range(r0, r1):
        py = ys[r]
        for c in range(c0, c1):
            px = xs[c]
            ccw, cw = True, True
            for k in range(m):
                ax, ay = poly[k, 0], poly[k, 1]
                bx, by = poly[(k + 1) % m, 0], poly[(k + 1) % m, 1]
                cross = (bx - ax) * (py - ay) - (by - ay) * (px - ax)
                ccw = ccw and cross >= 0
                cw = cw and cross <= 0
                if not (ccw or cw):
                    break
            if ccw or cw:
                mask[r, c] = True


def build_grid(world: np.ndarray, center_xy: tuple[float, float], spec: GridSpec,
               drivable: DrivableRaster) -> tuple[Grid, np.ndarray]:
    """The grid around ``center_xy`` and each point's flat cell index (-1 outside)."""
    n = spec.cells
    i0 = int(np.floor(center_xy[0] / spec.cell_m)) - n // 2
    j0 = int(np.floor(center_xy[1] / spec.cell_m)) - n // 2
    state = np.zeros(n * n, dtype=np.uint8)
    cell_idx = np.empty(len(world), dtype=np.int64)
    _bin(world, i0, j0, spec.cell_m, n, spec.ground_clear_m, state, cell_idx)
    grid = Grid(spec, i0, j0, state.reshape(n, n), drivable.window(i0, j0, n))
    return grid, cell_idx


def extract_objects(world: np.ndarray, grid: Grid, cell_idx: np.ndarray,
                    sensor_xy: tuple[float, float] | None = None) -> list[DetectedObject]:
    """Connected ABOVE cells on the drivable area, each with its points and extent.

    With ``sensor_xy``, a component that lies in another's shadow just behind it, with
    nothing but unseen cells in between, is merged into it: a roof ring seen beyond a
    car's rear face is the same car.
    """
    labels, k, cells = _labels(grid, sensor_xy)
    if k == 0:
        return []
    order, bounds = _group_by_label(cell_idx, world[:, 2] > grid.spec.ground_clear_m, labels.ravel(), k)
    pts = world[order]
    return _objects(pts, pts.astype(np.float32), bounds, grid, labels, k, cells)


def _labels(grid: Grid, sensor_xy: tuple[float, float] | None,
            cells: np.ndarray | None = None) -> tuple[np.ndarray, int, np.ndarray]:
    """The grid's objects as labelled cells (``extract_objects``): labels 1..k, k, and
    the flat indices of the labelled cells in grid order (``cells``, if known:
    ``_above_cells``; then the labels of other cells are left unset, see ``_components``)."""
    whole = cells is None
    if whole:
        cells = _above_cells(grid.state, grid.drivable)
    sx, sy = (float(sensor_xy[0]), float(sensor_xy[1])) if sensor_xy is not None else (0.0, 0.0)
    labels, k = _merged_components(grid.state, grid.drivable, grid.spec.reach_cells, cells, whole, grid.i0, grid.j0,
                                   grid.spec.cell_m, sensor_xy is not None, sx, sy, SHADOW_MERGE_M)
    return labels, k, cells


@njit(cache=True)
def _merged_components(state, drivable, reach, cells, whole, i0, j0, cell, merge, sx, sy, merge_m):
    """``_components``, then (if ``merge``, the sensor at (sx, sy)) ``_shadow_relabel``
    applied to them: ``_labels``' labels and k in one call."""
    labels, k = _components(state, drivable, reach, cells, whole)
    if merge and k > 1:
        relabel, k = _shadow_relabel(labels, k, cells, i0, j0, cell, state, sx, sy, merge_m)
        _relabel_cells(labels.ravel(), cells, relabel)
    return labels, k


def _objects(pts: np.ndarray, pts32: np.ndarray, bounds: np.ndarray, grid: Grid, labels: np.ndarray, k: int,
             cells: np.ndarray, sums: np.ndarray | None = None) -> list[DetectedObject]:
    """The objects of ``k`` labels, label l's points (world) ``pts[bounds[l - 1]:bounds[l]]``
    (``pts32``: the same in float32); a label without points makes no object. ``cells``:
    the labelled cells' flat indices in grid order; ``sums``: ``_label_sums`` of the
    points, if known (then ``pts`` may hold their x and y only)."""
    if sums is None:
        sums = _label_sums(pts, bounds)
    cells_ij, cell_bounds, kept, box = _object_boxes(pts, bounds, sums, cells, labels.ravel(), k,
                                                     grid.state.shape[0], grid.i0, grid.j0)
    centroid = _box_centres(box, np.cos(box[2]), np.sin(box[2]))  # the cosine and sine as numpy takes them
    _, _, yaw, _, _, length, width, _ = box.tolist()
    bounds_l, cell_bounds_l = bounds.tolist(), cell_bounds.tolist()
    objects = []  # each object's points and cells are slices of pts32 and cells_ij
    for o, lab in enumerate(kept.tolist()):
        objects.append(_new_object(pts32[bounds_l[lab]:bounds_l[lab + 1]],
                                   cells_ij[cell_bounds_l[lab]:cell_bounds_l[lab + 1]],
                                   centroid[o], yaw[o], length[o], width[o]))
    return objects


_new_object = slots_constructor(DetectedObject)  # DetectedObject(...) without the frozen __init__'s cost


def object_of_points(points: np.ndarray, cell_m: float) -> DetectedObject:
    """One object of ``points`` (float32 (n, 3), n >= 1, world x, y and height), its box
    and cells worked out as ``extract_objects`` works out a component's: the tracker's
    parts of a detection that held two objects (``tracking.split_merged``)."""
    pts = np.ascontiguousarray(points, dtype=np.float64)
    bounds = np.array([0, len(pts)], dtype=np.int64)
    mean, yaw, u_lo, u_hi, v_lo, v_hi, z_mean = _stats_of(pts, bounds, _label_sums(pts, bounds))
    box = np.array([[mean[0, 0]], [mean[0, 1]], [yaw[0]], [(u_hi[0] + u_lo[0]) / 2], [(v_hi[0] + v_lo[0]) / 2],
                    [u_hi[0] - u_lo[0]], [v_hi[0] - v_lo[0]], [z_mean[0]]])
    centre = _box_centres(box, np.cos(box[2]), np.sin(box[2]))[0]
    cells = _cells_of(pts, cell_m)
    return _new_object(np.ascontiguousarray(points, dtype=np.float32), cells, centre, float(yaw[0]),
                       float(box[5, 0]), float(box[6, 0]))


@njit(cache=True)
def _cells_of(pts, cell_m):
    """The lattice cells (i, j) of points ``pts`` (n >= 1), each once, ordered by i then j:
    ``np.unique(np.floor(pts[:, :2] / cell_m).astype(np.int64), axis=0)`` without the
    sort (a cell window's marks, read in order)."""
    n = pts.shape[0]
    ij = np.empty((n, 2), dtype=np.int64)
    for p in range(n):
        ij[p, 0] = np.int64(np.floor(pts[p, 0] / cell_m))
        ij[p, 1] = np.int64(np.floor(pts[p, 1] / cell_m))
    i_lo, j_lo = ij[:, 0].min(), ij[:, 1].min()
    mark = np.zeros((ij[:, 0].max() - i_lo + 1, ij[:, 1].max() - j_lo + 1), dtype=np.bool_)
    for p in range(n):
        mark[ij[p, 0] - i_lo, ij[p, 1] - j_lo] = True
    out = np.empty((np.count_nonzero(mark), 2), dtype=np.int64)
    m = 0
    for a in range(mark.shape[0]):
        for b in range(mark.shape[1]):
            if mark[a, b]:
                out[m, 0], out[m, 1] = a + i_lo, b + j_lo
                m += 1
    return out


@njit(cache=True)
def _object_boxes(pts, bounds, sums, cells, flat_labels, k, n, i0, j0):
    """``_objects``' arithmetic before the cosine and sine of each yaw, in one kernel:
    ``_cells_by_label`` of the labelled cells, ``_object_stats`` of the points (their
    ``_label_sums`` given); then,
    for the labels with points (``kept``, 0-based, ascending), float64 (8, m) rows: xy
    mean, yaw, half the sum of the extent's ends along and across the axis (how far the
    box's centre lies from the mean), length, width and mean height. Replaces two
    kernels and some twenty numpy calls on arrays of a few objects each."""
    cells_ij, cell_bounds = _cells_by_label(cells, flat_labels, k, n, i0, j0)
    mean, yaw, u_lo, u_hi, v_lo, v_hi, z_mean = _stats_of(pts, bounds, sums)
    m = 0
    for lab in range(k):
        if bounds[lab + 1] > bounds[lab]:
            m += 1
    kept = np.empty(m, dtype=np.int64)
    box = np.empty((8, m))
    o = 0
    for lab in range(k):
        if bounds[lab + 1] > bounds[lab]:
            kept[o] = lab
            box[0, o], box[1, o], box[2, o] = mean[lab, 0], mean[lab, 1], yaw[lab]
            box[3, o], box[4, o] = (u_hi[lab] + u_lo[lab]) / 2, (v_hi[lab] + v_lo[lab]) / 2
            box[5, o], box[6, o], box[7, o] = u_hi[lab] - u_lo[lab], v_hi[lab] - v_lo[lab], z_mean[lab]
            o += 1
    return cells_ij, cell_bounds, kept, box


@njit(cache=True)
def _box_centres(box, cos_yaw, sin_yaw):
    """(m, 3) centre of each ``_object_boxes`` box: the mean moved along and across the
    axis (cosine and sine of each yaw given), and the mean height."""
    out = np.empty((box.shape[1], 3))
    for o in range(box.shape[1]):
        out[o, 0] = box[0, o] + cos_yaw[o] * box[3, o] + -sin_yaw[o] * box[4, o]
        out[o, 1] = box[1, o] + sin_yaw[o] * box[3, o] + cos_yaw[o] * box[4, o]
        out[o, 2] = box[7, o]
    return out


def scan_grid(range_cm: np.ndarray, tables: tuple[np.ndarray, np.ndarray, np.ndarray], pose_xyyaw: tuple,
              mount_m: float, spec: GridSpec, drivable: DrivableRaster) -> tuple[Grid, np.ndarray]:
    """``build_grid`` of a scan's points (``frames.scan_to_world``) straight from its
    range image: the same grid, without the world points of every ray in memory (at 40
    vehicles 110 000 rays of 24 bytes, read three times). ``tables``: the LiDAR's cos
    and sin of each azimuth and tan of each elevation (``frames.ray_tables``). Returns
    the grid and, for ``scan_objects``: the rays that can belong to an object, uint32
    (m, 3) rows (azimuth, beam, flat cell) of each return above the ground in a
    drivable cell of the grid, in ray order (about a fifth of the rays); and those
    cells (``_above_cells``), found as they turn ABOVE rather than by a scan of the grid."""
    x, y, yaw = pose_xyyaw
    n = spec.cells
    i0 = math.floor(x / spec.cell_m) - n // 2  # int(np.floor(...)) without numpy's scalar calls
    j0 = math.floor(y / spec.cell_m) - n // 2
    state = np.zeros(n * n, dtype=np.uint8)
    window = drivable.window(i0, j0, n)
    # pages past the m rows written are never touched; unsigned: an index read from it needs no test for
    # a negative value (``_rays_by_label``: 130 -> 95 us a 40-vehicle scan, hot)
    rays = np.empty((range_cm.size, 3), dtype=np.uint32)
    cells = np.empty(n * n, dtype=np.int64)  # likewise
    cos_az, sin_az, tan_el = tables
    m, m_cells = _bin_rays(range_cm, cos_az, sin_az, tan_el, x, y, yaw, mount_m, i0, j0, spec.cell_m,
                           exact_inverse(spec.cell_m), n, spec.ground_clear_m, window.ravel(), state, rays, cells)
    return _new_grid(spec, i0, j0, state.reshape(n, n), window), (rays[:m], np.sort(cells[:m_cells]))


_new_grid = slots_constructor(Grid)  # Grid(...) without the frozen __init__'s cost


def scan_objects(range_cm: np.ndarray, tables: tuple[np.ndarray, np.ndarray, np.ndarray], pose_xyyaw: tuple,
                 mount_m: float, grid: Grid, binned: tuple[np.ndarray, np.ndarray]) -> list[DetectedObject]:
    """``extract_objects`` of the scan ``scan_grid`` binned (the sensor at the pose): the
    same objects, only the rays of ``binned`` (``scan_grid``'s) placed in the world."""
    x, y, yaw = pose_xyyaw
    rays, cells = binned
    labels, k, cells = _labels(grid, (x, y), cells)
    if k == 0:
        return []
    cos_az, sin_az, tan_el = tables
    pts, pts32, bounds, sums = _rays_by_label(range_cm, cos_az, sin_az, tan_el, x, y, yaw, mount_m, rays,
                                              labels.ravel(), k)
    return _objects(pts, pts32, bounds, grid, labels, k, cells, sums)


@njit(cache=True)
def _bin_rays(range_cm, cos_az, sin_az, tan_el, x, y, yaw, mount_m, i0, j0, cell, inv, n, clear, drivable, state,
              rays, cells_above):
    """``_bin`` of the rays' world points (``frames._ranges_to_world``'s arithmetic):
    classify cells; ``rays[:m]`` gets (azimuth, beam, flat cell) of each ray with a
    return above the ground in a ``drivable`` cell of the grid, in ray order, and
    ``cells_above[:m_cells]`` each such cell once (unordered); returns (m, m_cells).
    ``inv``: ``exact_inverse(cell)``. Replaces a per-ray int32 cell (every ray written,
    then every ray read twice): only these rays can be in an object. Per azimuth, the
    cells and heights of its beams first, in a loop without branches (the compiler
    vectorises it), then the cells' updates: 0.29 -> 0.18 ms a 40-vehicle scan."""
    c, s = np.cos(yaw), np.sin(yaw)
    n_beams = range_cm.shape[1]
    cells = np.empty(n_beams, dtype=np.int64)  # -1: no return, or outside the grid
    above = np.empty(n_beams, dtype=np.bool_)
    m = m_cells = 0
    for i in range(range_cm.shape[0]):
        wx = c * cos_az[i] - s * sin_az[i]
        wy = s * cos_az[i] + c * sin_az[i]
        _beam_cells(range_cm[i], wx, wy, x, y, i0, j0, cell, inv, n, mount_m, tan_el, clear, cells, above)
        for b in range(n_beams):
            q = cells[b]
            if q < 0:
                continue
            if above[b]:
                if drivable[q]:
                    rays[m, 0], rays[m, 1], rays[m, 2] = i, b, q
                    m += 1
                    if state[q] != 2:
                        cells_above[m_cells] = q
                        m_cells += 1
                state[q] = 2
            elif state[q] == 0:
                state[q] = 1
    return m, m_cells


@njit(cache=True)
def _beam_cells(range_row, wx, wy, x, y, i0, j0, cell, inv, n, mount_m, tan_el, clear, cells, above):
    """``_bin_rays``' cells (-1: no return or outside the grid) and above-the-ground
    flags of one azimuth's beams, its horizontal direction (wx, wy). No branch inside a
    loop, so that the compiler vectorises it: the division's loop is a second copy. The
    column, row and flat cell are whole numbers in float64 (exact below 2^53), converted
    once to int64: one conversion and no 64-bit integer product per beam."""
    fn = float(n)
    if inv > 0.0:
        for b in range(len(range_row)):
            d = range_row[b] * 0.01
            ix = np.floor((x + d * wx) * inv) - i0
            iy = np.floor((y + d * wy) * inv) - j0
            inside = (range_row[b] != 0) & (ix >= 0.0) & (iy >= 0.0) & (ix < fn) & (iy < fn)
            cells[b] = np.int64(iy * fn + ix) if inside else -1
            above[b] = mount_m + d * tan_el[b] > clear
    else:
        for b in range(len(range_row)):
            d = range_row[b] * 0.01
            ix = np.floor((x + d * wx) / cell) - i0
            iy = np.floor((y + d * wy) / cell) - j0
            inside = (range_row[b] != 0) & (ix >= 0.0) & (iy >= 0.0) & (ix < fn) & (iy < fn)
            cells[b] = np.int64(iy * fn + ix) if inside else -1
            above[b] = mount_m + d * tan_el[b] > clear


@njit(cache=True)
def _rays_by_label(range_cm, cos_az, sin_az, tan_el, x, y, yaw, mount_m, rays, flat_labels, k):
    """``_group_by_label`` of ``rays`` (``_bin_rays``'), their world points placed as
    ``frames._ranges_to_world`` places them: (their x and y, float64 (m, 2); the points,
    float32 (m, 3); bounds; ``_label_sums`` of the points), label l's at
    ``bounds[l - 1]:bounds[l]``, in ray order. The sums add each point as it is placed,
    in the same order: a pass less over the points (latency-bound, 4 cycles a point);
    past them only x and y are read in float64 (``_stats_of``), and the heights are not
    written a second time (stores into memory not yet cached were half of this kernel's
    time)."""
    counts = np.zeros(k + 1, dtype=np.int64)
    cur, run = 0, 0  # a label's rays come in runs: counted in a register, not in memory per ray
    for t in range(rays.shape[0]):
        lab = flat_labels[rays[t, 2]]
        if lab != cur:
            counts[cur] += run
            cur, run = lab, 0
        run += 1
    counts[cur] += run
    bounds = np.zeros(k + 1, dtype=np.int64)
    for lab in range(1, k + 1):
        bounds[lab] = bounds[lab - 1] + counts[lab]
    fill = bounds[:-1].copy()
    out = np.empty((bounds[k], 2))
    out32 = np.empty((bounds[k], 3), dtype=np.float32)
    sums = np.zeros((k, 3))
    c, s = np.cos(yaw), np.sin(yaw)
    # consecutive rays mostly share a label and an azimuth: the label's next slot and sums
    # and the azimuth's direction are kept across them, not stored and loaded again per ray
    cur, p, last_i = 0, 0, -1
    wx = wy = sx = sy = sz = 0.0
    for t in range(rays.shape[0]):
        lab = flat_labels[rays[t, 2]]
        if lab == 0:
            continue
        if lab != cur:
            if cur > 0:
                fill[cur - 1] = p
                sums[cur - 1, 0], sums[cur - 1, 1], sums[cur - 1, 2] = sx, sy, sz
            cur, p = lab, fill[lab - 1]
            sx, sy, sz = sums[lab - 1, 0], sums[lab - 1, 1], sums[lab - 1, 2]
        i, b = rays[t, 0], rays[t, 1]
        if i != last_i:
            wx = c * cos_az[i] - s * sin_az[i]
            wy = s * cos_az[i] + c * sin_az[i]
            last_i = i
        d = range_cm[i, b] * 0.01
        px, py, pz = x + d * wx, y + d * wy, mount_m + d * tan_el[b]
        out[p, 0], out[p, 1] = px, py
        out32[p, 0], out32[p, 1], out32[p, 2] = px, py, pz  # as numpy's astype rounds
        sx += px
        sy += py
        sz += pz
        p += 1
    if cur > 0:
        sums[cur - 1, 0], sums[cur - 1, 1], sums[cur - 1, 2] = sx, sy, sz
    return out, out32, bounds, sums


@njit(cache=True)
def _cells_by_label(cells, flat_labels, k, n, i0, j0):
    """``_group_by_label`` of the labelled ``cells`` (flat indices in grid order, kept
    within a label), as global lattice (i, j): (int64 (m, 2), bounds). Replaces two
    passes over the whole grid and numpy's index arithmetic on the result."""
    counts = np.zeros(k + 1, dtype=np.int64)
    for t in range(len(cells)):
        counts[flat_labels[cells[t]]] += 1
    bounds = np.zeros(k + 1, dtype=np.int64)
    for lab in range(1, k + 1):
        bounds[lab] = bounds[lab - 1] + counts[lab]
    fill = bounds[:-1].copy()
    out = np.empty((bounds[k], 2), dtype=np.int64)
    for t in range(len(cells)):
        q = cells[t]
        lab = flat_labels[q]
        if lab > 0:
            out[fill[lab - 1], 0] = q % n + i0
            out[fill[lab - 1], 1] = q // n + j0
            fill[lab - 1] += 1
    return out, bounds


@njit(cache=True)
def _group_by_label(cell_of, valid, flat_labels, k):
    """Counting sort of the items (points or cells) in a labelled cell by label, item
    order kept within a label: (item indices, bounds) with label l's items at
    ``bounds[l - 1]:bounds[l]``. Items not ``valid``, outside the grid (cell -1) or in
    an unlabelled cell are left out."""
    counts = np.zeros(k + 1, dtype=np.int64)
    for p in range(len(cell_of)):
        if valid[p] and cell_of[p] >= 0:
            counts[flat_labels[cell_of[p]]] += 1
    bounds = np.zeros(k + 1, dtype=np.int64)
    for lab in range(1, k + 1):
        bounds[lab] = bounds[lab - 1] + counts[lab]
    fill = bounds[:-1].copy()
    order = np.empty(bounds[k], dtype=np.int64)
    for p in range(len(cell_of)):
        if valid[p] and cell_of[p] >= 0:
            lab = flat_labels[cell_of[p]]
            if lab > 0:
                order[fill[lab - 1]] = p
                fill[lab - 1] += 1
    return order, bounds


@njit  # a reference for the tests (objects take _label_sums and _stats_of apart): not cached
def _object_stats(pts, bounds):
    """Per label of points grouped by ``_group_by_label``: the xy mean, the yaw of the
    principal axis of the xy covariance, the extent along and across it (relative to
    the mean) and the mean height. A label without points gets zeros."""
    return _stats_of(pts, bounds, _label_sums(pts, bounds))


@njit(cache=True)
def _label_sums(pts, bounds):
    """(k, 3) sums of x, y and height of each label's points (``_object_stats``), added in
    point order."""
    k = len(bounds) - 1
    sums = np.zeros((k, 3))
    for o in range(k):
        sx = sy = sz = 0.0
        for p in range(bounds[o], bounds[o + 1]):
            sx += pts[p, 0]
            sy += pts[p, 1]
            sz += pts[p, 2]
        sums[o, 0], sums[o, 1], sums[o, 2] = sx, sy, sz
    return sums


@njit(cache=True)
def _stats_of(pts, bounds, sums):
    """``_object_stats`` of the points (x and y are read: the heights may be left out),
    their ``_label_sums`` given."""
    k = len(bounds) - 1
    mean = np.zeros((k, 2))
    yaw, z_mean = np.zeros(k), np.zeros(k)
    u_lo, u_hi, v_lo, v_hi = np.zeros(k), np.zeros(k), np.zeros(k), np.zeros(k)
    for o in range(k):
        a, b = bounds[o], bounds[o + 1]
        if b == a:
            continue
        sx, sy, sz = sums[o, 0], sums[o, 1], sums[o, 2]
        mx, my = sx / (b - a), sy / (b - a)
        sxx = syy = sxy = 0.0
        for p in range(a, b):
            dx, dy = pts[p, 0] - mx, pts[p, 1] - my
            sxx += dx * dx
            syy += dy * dy
            sxy += dx * dy
        th = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)
        c, s = np.cos(th), np.sin(th)
        ulo, uhi, vlo, vhi = np.inf, -np.inf, np.inf, -np.inf
        for p in range(a, b):
            dx, dy = pts[p, 0] - mx, pts[p, 1] - my
            u, v = dx * c + dy * s, -dx * s + dy * c
            ulo, uhi = min(ulo, u), max(uhi, u)
            vlo, vhi = min(vlo, v), max(vhi, v)
        mean[o, 0], mean[o, 1], yaw[o], z_mean[o] = mx, my, th, sz / (b - a)
        u_lo[o], u_hi[o], v_lo[o], v_hi[o] = ulo, uhi, vlo, vhi
    return mean, yaw, u_lo, u_hi, v_lo, v_hi, z_mean


SHADOW_MERGE_M = 5.0  # at most this far behind the nearer part


def _merge_shadowed(labels: np.ndarray, k: int, grid: Grid, sensor_xy: tuple[float, float]) -> tuple[np.ndarray, int]:
    """``labels`` (1..k) after merging the components in another's shadow (``_shadow_relabel``)."""
    cells = np.flatnonzero(labels.ravel())
    relabel, k = _shadow_relabel(labels, k, cells, grid.i0, grid.j0, grid.spec.cell_m, grid.state,
                                 float(sensor_xy[0]), float(sensor_xy[1]), SHADOW_MERGE_M)
    out = labels.copy()
    _relabel_cells(out.ravel(), cells, relabel)
    return out, k


@njit(cache=True)
def _relabel_cells(flat_labels, cells, relabel):
    """``flat_labels[cells] = relabel[flat_labels[cells]]`` in place: only the labelled
    cells change (numpy's fancy indexing of the whole grid took 0.1 ms at 280 x 280)."""
    for t in range(len(cells)):
        flat_labels[cells[t]] = relabel[flat_labels[cells[t]]]


@njit(cache=True)
def _shadow_relabel(labels, k, cells, i0, j0, cell, state, sx, sy, merge_m):
    """The new label of every old one (index 0 stays 0) after merging each component B
    that lies behind a component A, seen from the sensor at (sx, sy): B's centre
    direction within A's angular extent, B starting less than ``merge_m`` past A's far
    side, and only unseen (EMPTY) cells on the ray between them. Labels keep the order
    of their lowest member. ``cells``: the flat indices of the labelled cells, in grid
    order."""
    ny, nx = labels.shape
    lab = np.empty(len(cells), dtype=np.int64)
    ang = np.empty(len(cells))
    dir_x, dir_y = np.zeros(k), np.zeros(k)
    r_min, r_max = np.full(k, np.inf), np.zeros(k)
    for i in range(len(cells)):
        y, x = divmod(cells[i], nx)
        lab[i] = labels[y, x] - 1
        px, py = (i0 + x + 0.5) * cell - sx, (j0 + y + 0.5) * cell - sy
        ang[i] = np.arctan2(py, px)
        dir_x[lab[i]] += np.cos(ang[i])
        dir_y[lab[i]] += np.sin(ang[i])
        rng = np.hypot(px, py)
        r_min[lab[i]] = min(r_min[lab[i]], rng)
        r_max[lab[i]] = max(r_max[lab[i]], rng)
    center = np.arctan2(dir_y, dir_x)
    lo, hi = np.full(k, np.inf), np.full(k, -np.inf)
    for i in range(len(cells)):
        rel = (ang[i] - center[lab[i]] + np.pi) % (2 * np.pi) - np.pi
        lo[lab[i]] = min(lo[lab[i]], rel)
        hi[lab[i]] = max(hi[lab[i]], rel)
    parent = np.arange(k)
    for a in range(k):
        half_cell = cell / max(r_min[a], 1.0)
        for b in range(k):
            gap = r_min[b] - r_max[a]
            d_ang = (center[b] - center[a] + np.pi) % (2 * np.pi) - np.pi
            if not (gap > 0 and gap < merge_m and lo[a] - half_cell <= d_ang <= hi[a] + half_cell):
                continue
            start, stop, step = r_max[a] + cell, r_min[b] - cell / 2, cell / 2
            clear = True
            for i in range(max(int(np.ceil((stop - start) / step)), 0)):
                d = start + i * step
                cx = int(np.floor((sx + d * np.cos(center[b])) / cell)) - i0
                cy = int(np.floor((sy + d * np.sin(center[b])) / cell)) - j0
                if cx < 0 or cy < 0 or cx >= nx or cy >= ny or state[cy, cx] != EMPTY:
                    clear = False
                    break
            if clear:
                ra, rb = _root(parent, a), _root(parent, b)
                parent[max(ra, rb)] = min(ra, rb)
    relabel = np.zeros(k + 1, dtype=labels.dtype)
    rank = np.full(k, -1)
    m = 0
    for i in range(k):  # roots in index order: the lowest member's order
        r = _root(parent, i)
        if rank[r] < 0:
            rank[r] = m
            m += 1
        relabel[i + 1] = rank[r] + 1
    return relabel, m


@njit(cache=True)
def _root(parent, i):
    while parent[i] != i:
        i = parent[i]
    return i
