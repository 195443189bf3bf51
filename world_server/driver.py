"""The built-in driver of passive participants (the collider).

It follows its route at its speed and brakes only for what its own LiDAR shows in the
corridor in front of it: no V2V, no map of others, no traffic lights (the red-light
runner ignores them by definition).
"""

from __future__ import annotations

import numpy as np

from protocol.messages import VehicleSpec
from world_server.geometry import point_at, project_s, wrap_angle

LOOKAHEAD_MIN_M = 4.0
LOOKAHEAD_S = 0.8  # look-ahead distance grows with speed
SPEED_GAIN = 1.0  # 1/s, proportional speed control
COMFORT_BRAKE_MPS2 = 4.0
STANDOFF_M = 3.0
OBSTACLE_MIN_HEIGHT_M = 0.3


def pure_pursuit_steer(x: float, y: float, yaw: float, speed_mps: float, route: np.ndarray,
                       wheelbase_m: float) -> float:
    """Front-wheel angle that steers toward the route point one look-ahead ahead."""
    s = project_s(route, np.array([x, y]))
    lookahead = max(LOOKAHEAD_MIN_M, LOOKAHEAD_S * speed_mps)
    (tx, ty), _ = point_at(route, s + lookahead)
    alpha = wrap_angle(np.arctan2(ty - y, tx - x) - yaw)
    return float(np.arctan2(2.0 * wheelbase_m * np.sin(alpha), lookahead))


def free_distance_ahead(points: np.ndarray, spec: VehicleSpec, mount_height_m: float,
                        horizon_m: float) -> float:
    """Distance from the front bumper to the nearest obstacle point in the lane ahead."""
    above = points[:, 2] > OBSTACLE_MIN_HEIGHT_M - mount_height_m
    front = spec.length_m / 2.0
    ahead = (points[:, 0] > front) & (points[:, 0] < front + horizon_m)
    in_lane = np.abs(points[:, 1]) < spec.width_m / 2.0 + 0.5
    hits = points[above & ahead & in_lane, 0]
    return float(hits.min() - front) if hits.size else np.inf


def passive_command(x: float, y: float, yaw: float, speed_mps: float, cruise_mps: float, route: np.ndarray,
                    spec: VehicleSpec, points: np.ndarray, mount_height_m: float) -> tuple[float, float]:
    """(accel, steer) for one decision interval."""
    steer = pure_pursuit_steer(x, y, yaw, speed_mps, route, spec.wheelbase_m)
    stopping_m = speed_mps**2 / (2.0 * COMFORT_BRAKE_MPS2) + STANDOFF_M
    gap = free_distance_ahead(points, spec, mount_height_m, horizon_m=stopping_m + 10.0)
    if gap < stopping_m:
        return -spec.max_brake_mps2, steer
    accel = float(np.clip(SPEED_GAIN * (cruise_mps - speed_mps), -spec.max_brake_mps2, spec.max_accel_mps2))
    return accel, steer
