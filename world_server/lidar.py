"""The LiDAR sensor model: exact ray casting of a spinning LiDAR against a flat ground
and vertical box prisms, in numba.

The world is the ground plane z = 0 plus boxes ``[cx, cy, yaw, length, width, height]``
(world frame, length along ``yaw``). A sensor sits at ``(x, y, yaw)`` at height ``z``
above the ground. Every ray of the ``beams x azimuth_steps`` grid returns its first hit
(ground or box side or box top) if it lies within ``range_m`` (3-D distance). Points
come back in the sensor frame (x forward, y left, z up; the ground is at z = -height),
ordered azimuth-major (all beams of azimuth 0, then of azimuth 1, ...), with labels:
the index of the box hit, or -1 for the ground.

Why it is fast (DESIGN.md "Facts measured"): the ground return of every ray depends
only on the config and the sensor height, so it is precomputed once; a scan then only
casts each box against the azimuth columns its corners span (azimuth culling) and
copies the precomputed ground for every column no box touched. The world sends only
the range image (``Scan.range_cm``); ``range_image_prepared`` builds just that, for the
vehicles whose points it does not need.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np
from numba import njit

from protocol.messages import LidarConfig

GROUND = -1
_NO_RETURN = -2  # internal label of a ray that returns nothing
_MAX_CM = 65535  # uint16 range image: 655 m, far beyond any LidarConfig.range_m we use

# columns of a prepared box row (see prepare_boxes)
_CX, _CY, _COS, _SIN, _HALF_L, _HALF_W, _HEIGHT = range(7)


@functools.lru_cache(maxsize=4)
def _scratch(n_az: int, n_beams: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-ray work arrays reused by every scan: fresh ones would cost ~1.4 MB of page faults
    per scan. Safe without locks because the kernel holds the GIL (no ``nogil``)."""
    return (
        np.empty((n_az, n_beams), dtype=np.float64),
        np.empty((n_az, n_beams), dtype=np.int32),
        np.zeros(n_az, dtype=np.bool_),
    )


def prepare_boxes(boxes: np.ndarray) -> np.ndarray:
    """World boxes (m, 6) -> (m, 7) rows [cx, cy, cos yaw, sin yaw, L/2, W/2, H], once per tick."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 6)
    prepared = np.empty((b.shape[0], 7), dtype=np.float64)
    prepared[:, _CX] = b[:, 0]
    prepared[:, _CY] = b[:, 1]
    prepared[:, _COS] = np.cos(b[:, 2])
    prepared[:, _SIN] = np.sin(b[:, 2])
    prepared[:, _HALF_L] = 0.5 * b[:, 3]
    prepared[:, _HALF_W] = 0.5 * b[:, 4]
    prepared[:, _HEIGHT] = b[:, 5]
    return prepared


@njit(cache=True)
def _slab(du: float, cu: float, half: float) -> tuple[float, float]:
    """Interval of t where |t*du - cu| <= half (the ray inside one slab of a box)."""
    if abs(du) < 1e-12:
        if abs(cu) <= half:
            return -np.inf, np.inf
        return np.inf, -np.inf
    t1 = (cu - half) / du
    t2 = (cu + half) / du
    if t1 > t2:
        return t2, t1
    return t1, t2


@njit(cache=True)
def _cm(d: float) -> int:
    """A horizontal distance on the wire: cm, at least 1 (0 means no return)."""
    return max(1, min(_MAX_CM, int(d * 100.0 + 0.5)))


class _Tables(NamedTuple):
    """Per (config, sensor height) constants: ray directions, range limits, the ground return."""

    cos_phi: np.ndarray  # (steps,) cos of each azimuth
    sin_phi: np.ndarray  # (steps,)
    tan_theta: np.ndarray  # (beams,) tan of each elevation
    d_limit: np.ndarray  # (beams,) the largest horizontal distance within range
    ground_d: np.ndarray  # (beams,) horizontal distance to the ground, inf where out of range
    ground_pts: np.ndarray  # float32 (steps, beams, 3): the ground return of every ray
    ground_cm: np.ndarray  # uint16 (beams,): a column of the range image that no box touches
    first_ground: int  # the first beam that returns ground (a tail: elevations descend)


@functools.lru_cache(maxsize=32)
def _tables(cfg: LidarConfig, sensor_z_m: float) -> _Tables:
    if not cfg.fov_up_deg > cfg.fov_down_deg:
        raise ValueError("LidarConfig needs fov_up_deg > fov_down_deg")
    if sensor_z_m <= 0.0:
        raise ValueError(f"sensor height must be above the ground, got {sensor_z_m}")
    elev = cfg.elevations_rad()
    azim = cfg.azimuths_rad()
    cos_phi = np.cos(azim)
    sin_phi = np.sin(azim)
    tan_theta = np.tan(elev)
    d_limit = cfg.range_m * np.cos(elev)  # horizontal distance at 3-D range_m
    ground_d = np.full(cfg.beams, np.inf)
    down = elev < 0.0
    ground_d[down] = sensor_z_m / np.tan(-elev[down])
    ground_ok = ground_d <= d_limit  # ground hit within range (3-D: h / sin(-theta))
    first_ground = int(np.argmax(ground_ok)) if ground_ok.any() else cfg.beams
    ground_d[~ground_ok] = np.inf
    ground_pts = np.zeros((cfg.azimuth_steps, cfg.beams, 3), dtype=np.float32)
    d = np.where(ground_ok, ground_d, 0.0)
    ground_pts[:, :, 0] = cos_phi[:, None] * d[None, :]
    ground_pts[:, :, 1] = sin_phi[:, None] * d[None, :]
    ground_pts[:, :, 2] = -sensor_z_m
    ground_cm = np.zeros(cfg.beams, dtype=np.uint16)
    ground_cm[first_ground:] = [_cm(d) for d in ground_d[first_ground:]]
    for arr in (cos_phi, sin_phi, tan_theta, d_limit, ground_d, ground_pts, ground_cm):
        arr.setflags(write=False)
    return _Tables(cos_phi, sin_phi, tan_theta, d_limit, ground_d, ground_pts, ground_cm, first_ground)


@njit(cache=True)
def _cast(
    prepared: np.ndarray,
    sx: float,
    sy: float,
    syaw: float,
    h: float,
    skip: int,
    cos_phi: np.ndarray,
    sin_phi: np.ndarray,
    tan_theta: np.ndarray,
    d_limit: np.ndarray,
    ground_d: np.ndarray,
    best_d: np.ndarray,
    best_lbl: np.ndarray,
    touched: np.ndarray,
) -> None:
    """Cast one sweep: the nearest hit per ray over the boxes' azimuth spans.

    Fills ``touched`` (the columns some box's span covers) and, in those columns only,
    ``best_d`` (horizontal distance) and ``best_lbl`` (box, ``GROUND`` or ``_NO_RETURN``).
    """
    n_az = cos_phi.shape[0]
    n_beams = tan_theta.shape[0]
    step = 2.0 * math.pi / n_az
    d_limit_max = 0.0
    for b in range(n_beams):
        d_limit_max = max(d_limit_max, d_limit[b])
    touched[:] = False  # best_d / best_lbl rows are initialised when first touched
    cs = math.cos(syaw)
    ss = math.sin(syaw)

    for k in range(prepared.shape[0]):
        if k == skip:
            continue
        hl = prepared[k, _HALF_L]
        hw = prepared[k, _HALF_W]
        height = prepared[k, _HEIGHT]
        if hl <= 0.0 or hw <= 0.0 or height <= 0.0:
            continue
        # box centre and axes in the sensor frame
        dx = prepared[k, _CX] - sx
        dy = prepared[k, _CY] - sy
        bx = cs * dx + ss * dy
        by = -ss * dx + cs * dy
        ua = prepared[k, _COS] * cs + prepared[k, _SIN] * ss  # cos(yaw - syaw)
        va = prepared[k, _SIN] * cs - prepared[k, _COS] * ss  # sin(yaw - syaw)
        cu = bx * ua + by * va  # centre along the box's length axis
        cv = -bx * va + by * ua  # centre along the box's width axis
        gap_u = max(abs(cu) - hl, 0.0)
        gap_v = max(abs(cv) - hw, 0.0)
        inside = gap_u == 0.0 and gap_v == 0.0  # sensor above (or in) the footprint
        if inside:
            if h <= height:
                continue  # sensor inside the solid: the box is not seen
            i_lo = 0  # only its roof can be hit, in every direction
            i_hi = n_az - 1
        else:
            if gap_u * gap_u + gap_v * gap_v >= d_limit_max * d_limit_max:
                continue  # nearest point beyond range
            # azimuth span of the corners, relative to the centre's direction (< pi wide)
            ac = math.atan2(by, bx)
            rel_lo = np.inf
            rel_hi = -np.inf
            for su in (-1.0, 1.0):
                for sv in (-1.0, 1.0):
                    px = bx + su * hl * ua - sv * hw * va
                    py = by + su * hl * va + sv * hw * ua
                    rel = math.atan2(py, px) - ac
                    if rel > math.pi:
                        rel -= 2.0 * math.pi
                    elif rel < -math.pi:
                        rel += 2.0 * math.pi
                    rel_lo = min(rel_lo, rel)
                    rel_hi = max(rel_hi, rel)
            i_lo = int(math.ceil((ac + rel_lo + math.pi) / step - 1e-9))
            i_hi = int(math.floor((ac + rel_hi + math.pi) / step + 1e-9))
        for i in range(i_lo, i_hi + 1):
            col = i % n_az  # wraps across +-pi
            dir_x = cos_phi[col]
            dir_y = sin_phi[col]
            tu0, tu1 = _slab(dir_x * ua + dir_y * va, cu, hl)
            tv0, tv1 = _slab(-dir_x * va + dir_y * ua, cv, hw)
            d_in = max(tu0, tv0)
            d_out = min(tu1, tv1)
            if inside:
                d_in = 0.0  # z_in = h > height: only the roof branch below applies
            elif d_in > d_out or d_in < 0.0:
                continue
            if not touched[col]:
                touched[col] = True
                for b in range(n_beams):
                    if ground_d[b] < np.inf:
                        best_d[col, b] = ground_d[b]
                        best_lbl[col, b] = GROUND
                    else:
                        best_d[col, b] = d_limit[b]  # a box must be nearer to return
                        best_lbl[col, b] = _NO_RETURN
            for b in range(n_beams):
                t = tan_theta[b]
                z_in = h + d_in * t
                if z_in < 0.0:
                    break  # this and every lower beam reach the ground first
                if z_in <= height:
                    d = d_in  # side
                elif t < 0.0:
                    d = (height - h) / t  # top, if reached before the far side
                    if d > d_out:
                        continue
                else:
                    continue  # passes above
                if d < best_d[col, b]:
                    best_d[col, b] = d
                    best_lbl[col, b] = k


@njit(cache=True)
def _compact(
    cos_phi: np.ndarray,
    sin_phi: np.ndarray,
    tan_theta: np.ndarray,
    ground_d: np.ndarray,
    ground_pts: np.ndarray,
    first_ground: int,
    best_d: np.ndarray,
    best_lbl: np.ndarray,
    touched: np.ndarray,
    range_cm: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The cast sweep's points and labels, azimuth-major, and its range image.

    Fills ``range_cm`` (steps, beams): each ray's horizontal distance in cm, 0 for no
    return; the points are exactly what ``range_cm`` encodes, before rounding.
    """
    n_az = cos_phi.shape[0]
    n_beams = tan_theta.shape[0]
    n_ground = n_beams - first_ground
    n = 0
    for col in range(n_az):
        if touched[col]:
            for b in range(n_beams):
                if best_lbl[col, b] != _NO_RETURN:
                    n += 1
        else:
            n += n_ground
    points = np.empty((n, 3), dtype=np.float32)
    labels = np.empty(n, dtype=np.int32)
    j = 0
    for col in range(n_az):
        if touched[col]:
            for b in range(n_beams):
                lbl = best_lbl[col, b]
                if lbl == _NO_RETURN:
                    range_cm[col, b] = 0
                    continue
                if lbl == GROUND:
                    points[j, 0] = ground_pts[col, b, 0]
                    points[j, 1] = ground_pts[col, b, 1]
                    points[j, 2] = ground_pts[col, b, 2]
                    range_cm[col, b] = _cm(ground_d[b])
                else:
                    d = best_d[col, b]
                    points[j, 0] = d * cos_phi[col]
                    points[j, 1] = d * sin_phi[col]
                    points[j, 2] = d * tan_theta[b]
                    range_cm[col, b] = _cm(d)
                labels[j] = lbl
                j += 1
        else:
            for b in range(first_ground):
                range_cm[col, b] = 0
            for b in range(first_ground, n_beams):
                points[j, 0] = ground_pts[col, b, 0]
                points[j, 1] = ground_pts[col, b, 1]
                points[j, 2] = ground_pts[col, b, 2]
                labels[j] = GROUND
                range_cm[col, b] = _cm(ground_d[b])
                j += 1
    return points, labels


@njit(cache=True)
def _range_image(
    ground_cm: np.ndarray,
    best_d: np.ndarray,
    best_lbl: np.ndarray,
    touched: np.ndarray,
    range_cm: np.ndarray,
    box_hits: np.ndarray,
) -> None:
    """The cast sweep's range image only (what ``_compact`` fills, without the points),
    and ``box_hits[k]``: how many rays returned box ``k``."""
    n_az, n_beams = range_cm.shape
    for col in range(n_az):
        if not touched[col]:
            range_cm[col, :] = ground_cm
            continue
        for b in range(n_beams):
            lbl = best_lbl[col, b]
            if lbl == _NO_RETURN:
                range_cm[col, b] = 0
            elif lbl == GROUND:
                range_cm[col, b] = ground_cm[b]
            else:
                range_cm[col, b] = _cm(best_d[col, b])
                box_hits[lbl] += 1


class Sweep(NamedTuple):
    """One sweep: what the world keeps (points and ground-truth labels) and what it sends."""

    points: np.ndarray  # float32 (n, 3), sensor frame, azimuth-major
    labels: np.ndarray  # int32 (n,): box index hit, or GROUND
    range_cm: np.ndarray  # uint16 (steps, beams): horizontal distance per ray in cm, 0 = none


class RangeImage(NamedTuple):
    """One sweep as the world sends it, and how many of its rays returned each box."""

    range_cm: np.ndarray  # uint16 (steps, beams), as in Sweep
    box_hits: np.ndarray  # int64 (boxes,): rays that returned box k (box k's labels in the Sweep)


def scan_prepared(
    prepared: np.ndarray, pose: np.ndarray, sensor_z_m: float, cfg: LidarConfig, skip_box: int
) -> Sweep:
    t = _tables(cfg, float(sensor_z_m))
    best_d, best_lbl, touched = _cast_prepared(prepared, pose, sensor_z_m, cfg, skip_box, t)
    range_cm = np.empty((cfg.azimuth_steps, cfg.beams), dtype=np.uint16)
    points, labels = _compact(t.cos_phi, t.sin_phi, t.tan_theta, t.ground_d, t.ground_pts, t.first_ground,
                              best_d, best_lbl, touched, range_cm)
    return Sweep(points, labels, range_cm)


def range_image_prepared(
    prepared: np.ndarray, pose: np.ndarray, sensor_z_m: float, cfg: LidarConfig, skip_box: int
) -> RangeImage:
    """``scan_prepared``'s range image, without the points and labels it would build
    and the world does not need for most vehicles (~1.8 MB of fresh arrays a scan)."""
    t = _tables(cfg, float(sensor_z_m))
    best_d, best_lbl, touched = _cast_prepared(prepared, pose, sensor_z_m, cfg, skip_box, t)
    range_cm = np.empty((cfg.azimuth_steps, cfg.beams), dtype=np.uint16)
    box_hits = np.zeros(prepared.shape[0], dtype=np.int64)
    _range_image(t.ground_cm, best_d, best_lbl, touched, range_cm, box_hits)
    return RangeImage(range_cm, box_hits)


def _cast_prepared(
    prepared: np.ndarray, pose: np.ndarray, sensor_z_m: float, cfg: LidarConfig, skip_box: int, t: _Tables
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Casts into the shared scratch arrays and returns them: use them before the next cast."""
    best_d, best_lbl, touched = _scratch(cfg.azimuth_steps, cfg.beams)
    _cast(prepared, float(pose[0]), float(pose[1]), float(pose[2]), float(sensor_z_m), int(skip_box),
          t.cos_phi, t.sin_phi, t.tan_theta, t.d_limit, t.ground_d, best_d, best_lbl, touched)
    return best_d, best_lbl, touched


def scan(
    boxes: np.ndarray,
    sensor_xy_yaw: np.ndarray,
    sensor_z_m: float,
    cfg: LidarConfig,
    skip_box: int = -1,
) -> tuple[np.ndarray, np.ndarray]:
    """One sweep. Returns points float32 (n, 3) in the sensor frame and labels int32 (n,):
    the index of the box hit, or -1 for ground. ``skip_box`` is the sensor's own body (ignored).

    A box whose footprint contains the sensor and whose top is below it (a roof-mounted
    LiDAR over its own body, when not skipped) returns roof points only; one whose solid
    contains the sensor is ignored.
    """
    pose = np.asarray(sensor_xy_yaw, dtype=np.float64).reshape(3)
    points, labels, _ = scan_prepared(prepare_boxes(boxes), pose, sensor_z_m, cfg, skip_box)
    return points, labels


def scan_many(
    boxes: np.ndarray,
    sensors_xy_yaw: np.ndarray,
    sensors_z_m: np.ndarray,
    cfg: LidarConfig,
    skip_boxes: np.ndarray,
) -> list[Sweep]:
    """All sensors of a tick, sharing per-tick precomputation (e.g. box corners).

    ``sensors_xy_yaw`` is (k, 3), ``sensors_z_m`` (k,), ``skip_boxes`` (k,) int (-1: none).
    Sweep ``i``'s points and labels equal
    ``scan(boxes, sensors_xy_yaw[i], sensors_z_m[i], cfg, skip_boxes[i])``.
    """
    prepared = prepare_boxes(boxes)
    poses = np.asarray(sensors_xy_yaw, dtype=np.float64).reshape(-1, 3)
    heights = np.asarray(sensors_z_m, dtype=np.float64).reshape(-1)
    skips = np.asarray(skip_boxes).reshape(-1)
    if not poses.shape[0] == heights.shape[0] == skips.shape[0]:
        raise ValueError("sensors_xy_yaw, sensors_z_m and skip_boxes must have one row per sensor")
    return [
        scan_prepared(prepared, poses[i], heights[i], cfg, int(skips[i]))
        for i in range(poses.shape[0])
    ]


def warm_up(cfg: LidarConfig | None = None) -> None:
    """Compile (or load from the numba cache) the kernel; call once before spawning agents."""
    cfg = cfg or LidarConfig()
    boxes = np.array([[10.0, 0.0, 0.0, 4.5, 1.8, 1.5]])
    scan(boxes, np.zeros(3), cfg.mount_height_m, cfg)
    range_image_prepared(prepare_boxes(boxes), np.zeros(3), cfg.mount_height_m, cfg, -1)
