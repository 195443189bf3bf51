"""Low-level control: a longitudinal PID and a lateral pure-pursuit controller.

Like CARLA's ``VehiclePIDController``: each is a small class with its own gains, and
``VehicleController.run_step`` combines them into the world's command
(acceleration, front-wheel angle).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from protocol.messages import Pose, VehicleSpec
from vehicle_agent.paths import point_at, progress_along


def clip(x: float, lo: float, hi: float) -> float:
    """``float(np.clip(x, lo, hi))`` of one number, the same value (NaN stays NaN),
    without the ~5 us of array machinery np.clip spends on a scalar."""
    return float(min(max(x, lo), hi))


@dataclass
class LongitudinalPID:
    """Acceleration command that tracks a target speed."""

    kp: float = 1.2
    ki: float = 0.05
    kd: float = 0.0
    dt_s: float = 0.1
    _integral: float = 0.0
    _last_error: float = 0.0

    def run_step(self, target_mps: float, speed_mps: float) -> float:
        error = target_mps - speed_mps
        self._integral = clip(self._integral + error * self.dt_s, -5.0, 5.0)
        derivative = (error - self._last_error) / self.dt_s
        self._last_error = error
        return self.kp * error + self.ki * self._integral + self.kd * derivative


@dataclass
class PurePursuit:
    """Front-wheel angle toward the path point one look-ahead distance ahead."""

    wheelbase_m: float
    lookahead_min_m: float = 4.0
    lookahead_gain_s: float = 0.8

    def run_step(self, pose: Pose, speed_mps: float, path: np.ndarray, s_along_m: float) -> float:
        lookahead = max(self.lookahead_min_m, self.lookahead_gain_s * speed_mps)
        target = point_at(path, s_along_m + lookahead)
        alpha = np.arctan2(target[1] - pose.y_m, target[0] - pose.x_m) - pose.yaw_rad
        alpha = (alpha + np.pi) % (2 * np.pi) - np.pi
        return float(np.arctan2(2.0 * self.wheelbase_m * np.sin(alpha), lookahead))


@dataclass
class VehicleController:
    """Tracks a path (world frame polyline) at a target speed within the vehicle's limits."""

    spec: VehicleSpec
    dt_s: float = 0.1
    lon: LongitudinalPID = field(init=False)
    lat: PurePursuit = field(init=False)

    def __post_init__(self) -> None:
        self.lon = LongitudinalPID(dt_s=self.dt_s)
        self.lat = PurePursuit(self.spec.wheelbase_m)

    def run_step(self, pose: Pose, speed_mps: float, path: np.ndarray, target_mps: float) -> tuple[float, float]:
        s = progress_along(path, np.array([pose.x_m, pose.y_m]))
        steer = self.lat.run_step(pose, speed_mps, path, s)
        if target_mps <= 0.0:
            accel = -self.spec.max_brake_mps2  # hold still
        else:
            accel = self.lon.run_step(target_mps, speed_mps)
        accel = clip(accel, -self.spec.max_brake_mps2, self.spec.max_accel_mps2)
        steer = clip(steer, -self.spec.max_steer_rad, self.spec.max_steer_rad)
        return accel, steer
