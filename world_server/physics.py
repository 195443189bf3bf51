"""Vehicle dynamics and contacts.

Each vehicle follows a kinematic bicycle model (reference point at the body centre,
slip angle beta = atan(l_r / L * tan(steer)), l_r = L / 2), integrated exactly for
constant acceleration within a physics step, with speed clamped at zero (no reverse).
pymunk holds every body as a box-shaped *sensor* shape: it reports contacts through
``space.on_collision`` and applies no impulses, since a crash ends the interesting
part of a run and the crashed vehicles are frozen where they touched.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pymunk
import pymunk.batch

from protocol.messages import VehicleSpec

log = logging.getLogger(__name__)

_VEHICLE = 1  # pymunk collision type


@dataclass(frozen=True, slots=True)
class Contact:
    a: int
    b: int
    t_sim_s: float


class Physics:
    """Holds every vehicle's state as numpy arrays; ``step`` advances them together."""

    def __init__(self, specs: Sequence[VehicleSpec], poses: np.ndarray, speeds_mps: np.ndarray) -> None:
        n = len(specs)
        self.specs = list(specs)
        self.x = poses[:, 0].astype(float).copy()
        self.y = poses[:, 1].astype(float).copy()
        self.yaw = poses[:, 2].astype(float).copy()
        self.v = np.asarray(speeds_mps, dtype=float).copy()
        self.accel_cmd = np.zeros(n)
        self.steer_cmd = np.zeros(n)
        self.wheelbase = np.array([s.wheelbase_m for s in specs])
        self.max_accel = np.array([s.max_accel_mps2 for s in specs])
        self.max_brake = np.array([s.max_brake_mps2 for s in specs])
        self.max_steer = np.array([s.max_steer_rad for s in specs])
        self.frozen = np.zeros(n, dtype=bool)
        self.t_sim_s = 0.0
        self.contacts: list[Contact] = []
        self._touching: set[tuple[int, int]] = set()

        self.space = pymunk.Space()  # default BB-tree index; the spatial hash missed hits
        self.bodies: list[pymunk.Body] = []
        for i, spec in enumerate(specs):
            body = pymunk.Body(1.0, 1.0, body_type=pymunk.Body.DYNAMIC)
            shape = pymunk.Poly.create_box(body, (spec.length_m, spec.width_m))
            shape.sensor = True
            shape.collision_type = _VEHICLE
            body.vid = i
            self.space.add(body, shape)
            self.bodies.append(body)
        self.space.on_collision(_VEHICLE, _VEHICLE, begin=self._on_begin, separate=self._on_separate)
        self._synced_x = self._synced_y = self._synced_yaw = np.full(n, np.nan)  # where the bodies are: nowhere yet
        # the bodies are put in one call (pymunk.batch) when the space lists them in vid order, as it does
        self._poses_buf = np.empty((n, 3))  # x, y, angle per body, the batch's layout
        self._batch = pymunk.batch.Buffer()
        ids = pymunk.batch.Buffer()
        pymunk.batch.get_space_bodies(self.space, pymunk.batch.BodyFields.BODY_ID, ids)
        self._batched = np.frombuffer(ids.int_buf(), dtype=np.int64).tolist() == [b.id for b in self.bodies]
        self._sync_bodies()
        self.space.step(1e-6)  # register initial overlaps (spawned touching = a bad scenario)

    def _on_begin(self, arbiter: pymunk.Arbiter, space: pymunk.Space, data) -> None:
        a, b = sorted(s.body.vid for s in arbiter.shapes)
        if (a, b) not in self._touching:
            self._touching.add((a, b))
            self.contacts.append(Contact(a, b, self.t_sim_s))
            self.frozen[[a, b]] = True
            self.v[[a, b]] = 0.0
            log.info("contact between vehicles %d and %d at t=%.2f s", a, b, self.t_sim_s)

    def _on_separate(self, arbiter: pymunk.Arbiter, space: pymunk.Space, data) -> None:
        bodies = [s.body for s in arbiter.shapes]
        if all(b is not None for b in bodies):  # None while the space is torn down
            self._touching.discard(tuple(sorted(b.vid for b in bodies)))

    def _sync_bodies(self) -> None:
        """Put the pymunk bodies where the vehicles are. Only the ones that moved: pymunk
        leaves a body where it was put, at zero velocity (sensor shapes take no impulses,
        and the space has no gravity or forces)."""
        if self._batched:  # every body, moved or not: putting one where it is changes nothing
            buf = self._poses_buf
            buf[:, 0], buf[:, 1], buf[:, 2] = self.x, self.y, self.yaw
            self._batch.set_float_buf(buf.reshape(-1))
            pymunk.batch.set_space_bodies(self.space, pymunk.batch.BodyFields.POSITION | pymunk.batch.BodyFields.ANGLE,
                                          self._batch)
            return
        moved = (self.x != self._synced_x) | (self.y != self._synced_y) | (self.yaw != self._synced_yaw)
        for i in np.flatnonzero(moved):
            body = self.bodies[i]
            body.position = (self.x[i], self.y[i])
            body.angle = self.yaw[i]
        self._synced_x, self._synced_y, self._synced_yaw = self.x.copy(), self.y.copy(), self.yaw.copy()

    def command(self, i: int, accel_mps2: float, steer_rad: float) -> None:
        """Set vehicle ``i``'s actuation, clipped to its limits."""
        self.accel_cmd[i] = np.clip(accel_mps2, -self.max_brake[i], self.max_accel[i])
        self.steer_cmd[i] = np.clip(steer_rad, -self.max_steer[i], self.max_steer[i])

    def command_many(self, ids: np.ndarray, accel_mps2: np.ndarray, steer_rad: np.ndarray) -> None:
        """``command(i, accel_mps2[j], steer_rad[j])`` for each ``i = ids[j]`` (distinct), in one
        clip per array: the same elementwise min and max, for the same values."""
        self.accel_cmd[ids] = np.clip(accel_mps2, -self.max_brake[ids], self.max_accel[ids])
        self.steer_cmd[ids] = np.clip(steer_rad, -self.max_steer[ids], self.max_steer[ids])

    def step(self, dt_s: float) -> None:
        """Advance all vehicles by ``dt_s`` and collect contacts."""
        a = np.where(self.frozen, 0.0, self.accel_cmd)
        v0 = np.where(self.frozen, 0.0, self.v)
        v1 = v0 + a * dt_s
        stops = v1 < 0.0
        # distance under constant a; a vehicle that stops mid-step covers v0^2 / 2|a|
        dist = np.where(stops, v0 * v0 / np.maximum(-2.0 * a, 1e-12), 0.5 * (v0 + v1) * dt_s)
        v1 = np.maximum(v1, 0.0)
        beta = np.arctan(0.5 * np.tan(self.steer_cmd))
        dyaw = dist * np.cos(beta) * np.tan(self.steer_cmd) / self.wheelbase
        heading = self.yaw + 0.5 * dyaw + beta
        self.x += dist * np.cos(heading)
        self.y += dist * np.sin(heading)
        self.yaw = (self.yaw + dyaw + np.pi) % (2.0 * np.pi) - np.pi
        self.v = v1
        self.t_sim_s += dt_s
        self._sync_bodies()
        self.space.step(dt_s)

    def poses(self) -> np.ndarray:
        return np.stack([self.x, self.y, self.yaw], axis=1)

    def boxes(self, heights_m: np.ndarray) -> np.ndarray:
        """(n, 6) ``[cx, cy, yaw, length, width, height]`` for the LiDAR."""
        length = np.array([s.length_m for s in self.specs])
        width = np.array([s.width_m for s in self.specs])
        return np.stack([self.x, self.y, self.yaw, length, width, heights_m], axis=1)
