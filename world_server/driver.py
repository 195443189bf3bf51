"""The built-in driver of passive participants (the collider and the traffic around it).

It follows its route at its speed. Where the scenario says so (``Actor.brake_lengths``,
after the paper's authors' scenarios), it brakes fully while a vehicle is within that
many of its own lengths ahead in its lane; otherwise it holds its speed whatever comes
(the red-light runner, the left-turn scenario's oncoming traffic). The collider sees
what is ahead with its own LiDAR; the traffic that follows it keeps its distance from
the world's boxes (it has no sensors of its own here, and nobody judges its view). No
V2V, no map of others, no traffic lights.
"""

from __future__ import annotations

import numpy as np

from protocol.messages import VehicleSpec
from world_server.geometry import box_corners, point_at, project_s, wrap_angle

LOOKAHEAD_MIN_M = 4.0
LOOKAHEAD_S = 0.8  # look-ahead distance grows with speed
SPEED_GAIN = 1.0  # 1/s, proportional speed control
OBSTACLE_MIN_HEIGHT_M = 0.3
LANE_MARGIN_M = 0.5  # the corridor ahead: the body's half width plus this
OUTLINE_STEP_M = 0.5  # spacing of the points sampled on other bodies' outlines


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
    """Distance from the front bumper to the nearest obstacle point (sensor frame) in the lane ahead."""
    above = points[:, 2] > OBSTACLE_MIN_HEIGHT_M - mount_height_m
    front = spec.length_m / 2.0
    ahead = (points[:, 0] > front) & (points[:, 0] < front + horizon_m)
    in_lane = np.abs(points[:, 1]) < spec.width_m / 2.0 + LANE_MARGIN_M
    hits = points[above & ahead & in_lane, 0]
    return float(hits.min() - front) if hits.size else np.inf


def outline_points(boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points every ~0.5 m along each box's outline (world frame) and the box each lies on.

    ``boxes`` rows are ``[cx, cy, yaw, length, width, ...]``.
    """
    corners = box_corners(boxes[:, 0], boxes[:, 1], boxes[:, 2], boxes[:, 3], boxes[:, 4])  # (n, 4, 2)
    k = int(np.ceil(max(float(boxes[:, 3].max(initial=0.0)), 1.0) / OUTLINE_STEP_M))
    t = np.arange(k) / k
    a, b = corners, np.roll(corners, -1, axis=1)
    pts = a[:, :, None, :] + (b - a)[:, :, None, :] * t[None, None, :, None]  # (n, 4, k, 2)
    owner = np.repeat(np.arange(len(boxes)), 4 * k)
    return pts.reshape(-1, 2), owner


def free_distance_to_boxes(x: float, y: float, yaw: float, spec: VehicleSpec, outline: np.ndarray,
                           owner: np.ndarray, me: int, horizon_m: float) -> float:
    """``free_distance_ahead`` against other bodies' outlines (world frame) instead of a scan."""
    d = outline[owner != me] - np.array([x, y])
    c, s = np.cos(yaw), np.sin(yaw)
    u, v = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
    front = spec.length_m / 2.0
    hit = (u > front) & (u < front + horizon_m) & (np.abs(v) < spec.width_m / 2.0 + LANE_MARGIN_M)
    return float(u[hit].min() - front) if hit.any() else np.inf


def passive_command(x: float, y: float, yaw: float, speed_mps: float, cruise_mps: float, route: np.ndarray,
                    spec: VehicleSpec, gap_m: float, brake_lengths: float) -> tuple[float, float]:
    """(accel, steer) for one decision interval; ``gap_m`` is the free distance ahead."""
    steer = pure_pursuit_steer(x, y, yaw, speed_mps, route, spec.wheelbase_m)
    if cruise_mps <= 0.0:
        return -spec.max_brake_mps2, 0.0  # parked
    if brake_lengths > 0.0 and gap_m < brake_lengths * spec.length_m:
        return -spec.max_brake_mps2, steer
    accel = float(np.clip(SPEED_GAIN * (cruise_mps - speed_mps), -spec.max_brake_mps2, spec.max_accel_mps2))
    return accel, steer
