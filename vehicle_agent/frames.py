"""Rigid transforms between a vehicle's sensor frame and the world (the 3-D map).

Sensor frame: origin at the LiDAR, x forward, y left, z up. World: x east, y north,
z = height above the (flat) ground. The paper's V_r = T_r^-1 T_s V_s is
``world_to_sensor(sensor_to_world(V_s, pose_s, h_s), pose_r, h_r)``.
"""

from __future__ import annotations

import numpy as np

from protocol.messages import Pose


def sensor_to_world(points: np.ndarray, pose: Pose, mount_height_m: float) -> np.ndarray:
    """T_s: sensor frame -> world x, y and height above ground."""
    c, s = np.cos(pose.yaw_rad), np.sin(pose.yaw_rad)
    out = np.empty((len(points), 3), dtype=np.float64)
    out[:, 0] = pose.x_m + c * points[:, 0] - s * points[:, 1]
    out[:, 1] = pose.y_m + s * points[:, 0] + c * points[:, 1]
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
