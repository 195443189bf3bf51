"""Rigid transforms between a vehicle's sensor frame and the world (the 3-D map).

Sensor frame: origin at the LiDAR, x forward, y left, z up. World: x east, y north,
z = height above the (flat) ground. The paper's V_r = T_r^-1 T_s V_s is
``world_to_sensor(sensor_to_world(V_s, pose_s, h_s), pose_r, h_r)``.
"""

from __future__ import annotations

import functools

import numpy as np
from numba import njit

from protocol.messages import LidarConfig, Pose, Scan


def sensor_to_world(points: np.ndarray, pose: Pose, mount_height_m: float) -> np.ndarray:
    """T_s: sensor frame -> world x, y and height above ground."""
    return placed_in_world(points, pose.x_m, pose.y_m, np.cos(pose.yaw_rad), np.sin(pose.yaw_rad), mount_height_m)


def placed_in_world(points, x, y, cos_yaw, sin_yaw, mount_height_m) -> np.ndarray:
    """``sensor_to_world`` with the pose (x, y, cos and sin of the yaw) and the mount
    height given per point (arrays) or for all (scalars): many senders' points in one
    pass. The height is added in the points' dtype, as a Python float would be."""
    out = np.empty((len(points), 3), dtype=np.float64)
    out[:, 0] = x + cos_yaw * points[:, 0] - sin_yaw * points[:, 1]
    out[:, 1] = y + sin_yaw * points[:, 0] + cos_yaw * points[:, 1]
    out[:, 2] = points[:, 2] + mount_height_m
    return out


def world_to_sensor(world: np.ndarray, pose: Pose, mount_height_m: float) -> np.ndarray:
    """T_r^-1: world x, y, height above ground -> a receiver's sensor frame."""
    c, s = np.cos(pose.yaw_rad), np.sin(pose.yaw_rad)
    dx, dy = world[:, 0] - pose.x_m, world[:, 1] - pose.y_m
    out = np.empty((len(world), 3), dtype=np.float64)
    out[:, 0] = c * dx + s * dy
    out[:, 1] = -s * dx + c * dy
    out[:, 2] = world[:, 2] - mount_height_m
    return out


def scan_to_world(scan: Scan, lidar: LidarConfig) -> np.ndarray:
    """A scan's returns in the world: float64 (n, 3) x, y, height above ground, azimuth-major.

    The same points as ``sensor_to_world(scan.points(lidar), scan.pose, lidar.mount_height_m)``
    in one numba pass over the range image.
    """
    check_fits(scan, lidar)
    cos_az, sin_az, tan_el = ray_tables(lidar)
    return _ranges_to_world(scan.range_cm, cos_az, sin_az, tan_el, scan.pose.x_m, scan.pose.y_m,
                            scan.pose.yaw_rad, lidar.mount_height_m)


def check_fits(scan: Scan, lidar: LidarConfig) -> None:
    """ValueError unless the scan's range image has the LiDAR's azimuths x beams."""
    if scan.range_cm.shape != (lidar.azimuth_steps, lidar.beams):
        raise ValueError(f"range image {scan.range_cm.shape} does not fit a "
                         f"{lidar.azimuth_steps} x {lidar.beams} LiDAR")


@functools.lru_cache(maxsize=4)
def ray_tables(lidar: LidarConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """cos and sin of each azimuth and tan of each elevation of the LiDAR."""
    az, el = lidar.azimuths_rad(), lidar.elevations_rad()
    return np.cos(az), np.sin(az), np.tan(el)


@njit(cache=True)
def _ranges_to_world(range_cm: np.ndarray, cos_az: np.ndarray, sin_az: np.ndarray, tan_el: np.ndarray,
                     x: float, y: float, yaw: float, mount_m: float) -> np.ndarray:
    n_az, n_beams = range_cm.shape
    n = 0
    for i in range(n_az):
        for b in range(n_beams):
            if range_cm[i, b] != 0:
                n += 1
    out = np.empty((n, 3), dtype=np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    j = 0
    for i in range(n_az):
        # the ray's horizontal direction in the world
        wx = c * cos_az[i] - s * sin_az[i]
        wy = s * cos_az[i] + c * sin_az[i]
        for b in range(n_beams):
            r = range_cm[i, b]
            if r == 0:
                continue
            d = r * 0.01
            out[j, 0] = x + d * wx
            out[j, 1] = y + d * wy
            out[j, 2] = mount_m + d * tan_el[b]
            j += 1
    return out
