"""Scheduler bench: the paper's "Optimality" and "Computation Time" figures on generated
intersection instances (autocast bench scheduler [--quick] [--out DIR]).

Two series:
- scale: 5..40 connected vehicles at a four-way intersection, each reporting up to 30
  objects, T_n = 10 ms, N = 10 frames of 9000 B (B = 7.2 Mbps). Total expected reward
  and computation time of every scheduler; exact optima are refused at this size.
- small: 3-6 vehicles with up to 3 objects each and N = 2-3 congested frames, where
  the exact open-loop optimum (and, when it fits, the MDP value) can be computed;
  every scheduler's reward relative to the optimum.
"""

from __future__ import annotations

import argparse
import logging
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vehicle_agent.scheduler import (
    Instance,
    InstanceTooLarge,
    SchedulerState,
    check_schedule,
    expected_reward,
    get,
    instance_from_arrays,
    link_probabilities,
    mdp_optimal,
)

log = logging.getLogger(__name__)

ARM_LENGTH_M = 90.0
LANE_OFFSET_M = (1.75, 5.25)  # right-hand lanes' centre offsets from the road axis
BLOCK_CORNER_M = 12.0  # buildings fill every quadrant beyond |x|, |y| > 12 m
SENSOR_RANGE_M = 80.0
RELEVANCE_RANGE_M = 35.0
BYTES_PER_POINT = 16  # x, y, z, intensity as float32
HEADER_BYTES = 64

SCALE_VEHICLES = (5, 10, 20, 30, 40)
ALGORITHMS = ("greedy", "fptas", "knapsack", "agnostic", "optimal")


# ------------------------------------------------------------------------- instances


@dataclass(frozen=True, slots=True)
class Scene:
    xy: np.ndarray  # (A, 2) actor positions, world frame, metres
    arm: np.ndarray  # (A,) approach 0..3 (E, N, W, S), -1 for pedestrians
    along_m: np.ndarray  # (A,) distance to the intersection centre along the arm
    radius_m: np.ndarray  # (A,) occluding disc radius
    n_connected: int  # actors 0..n_connected-1 are the connected vehicles


def intersection_scene(rng: np.random.Generator, n_connected: int, n_others: int, n_pedestrians: int) -> Scene:
    """Cars on the four approaches (two lanes each way), pedestrians at the corners."""
    n_cars = n_connected + n_others
    arm = rng.integers(0, 4, n_cars)
    along = rng.uniform(-20.0, ARM_LENGTH_M, n_cars)  # negative: already through the box
    lateral = rng.choice(LANE_OFFSET_M, n_cars) * rng.choice((-1.0, 1.0), n_cars)
    angle = arm * (np.pi / 2)
    ux, uy = np.cos(angle), np.sin(angle)
    car_xy = np.stack([ux * along - uy * lateral, uy * along + ux * lateral], axis=1)
    corner = rng.integers(0, 4, n_pedestrians) * (np.pi / 2) + np.pi / 4
    ped_r = rng.uniform(13.0, 18.0, n_pedestrians)
    ped_xy = np.stack([ped_r * np.cos(corner), ped_r * np.sin(corner)], axis=1)
    return Scene(
        xy=np.concatenate([car_xy, ped_xy]),
        arm=np.concatenate([arm, -np.ones(n_pedestrians, dtype=np.int64)]),
        along_m=np.concatenate([along, ped_r]),
        radius_m=np.concatenate([np.full(n_cars, 2.2), np.full(n_pedestrians, 0.4)]),
        n_connected=n_connected,
    )


def line_of_sight(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """bool (C, A) twice: connected vehicle c ``detects`` actor a (in range, not behind a
    building corner; partly hidden objects are still segmented and can be shared) and
    ``sees`` it fully (no other actor's disc on the line of sight either)."""
    viewers = scene.xy[: scene.n_connected]
    d = scene.xy[None, :, :] - viewers[:, None, :]  # (C, A, 2)
    dist = np.hypot(d[..., 0], d[..., 1])
    t = np.linspace(0.05, 0.95, 19)
    pts = viewers[:, None, None, :] + d[:, :, None, :] * t[None, None, :, None]  # (C, A, T, 2)
    behind_building = np.any((np.abs(pts[..., 0]) > BLOCK_CORNER_M) & (np.abs(pts[..., 1]) > BLOCK_CORNER_M), axis=2)
    rel = scene.xy[None, None, :, :] - viewers[:, None, None, :]  # (C, 1, B, 2): blocker b from viewer c
    seg = d[:, :, None, :]  # (C, A, 1, 2)
    along = np.clip(np.sum(rel * seg, axis=-1) / np.maximum(np.sum(seg * seg, axis=-1), 1e-9), 0.0, 1.0)
    gap = np.hypot(*(rel - along[..., None] * seg).transpose(3, 0, 1, 2))  # blocker b to segment c -> a
    A = len(scene.xy)
    blocker = (gap < scene.radius_m[None, None, :]) & (along > 0.0) & (along < 1.0)
    blocker[:, np.arange(A), np.arange(A)] = False  # the target does not hide itself
    blocker[np.arange(scene.n_connected), :, np.arange(scene.n_connected)] = False  # nor the viewer
    own = np.zeros(dist.shape, dtype=bool)
    own[np.arange(scene.n_connected), np.arange(scene.n_connected)] = True
    detects = (dist < SENSOR_RANGE_M) & ~behind_building & ~own
    return detects, detects & ~np.any(blocker, axis=2)


def relevance(scene: Scene) -> np.ndarray:
    """float (A, C): r of actor a to connected vehicle c; an actor matters to c when it
    is close, on a crossing or oncoming approach, or ahead of c in its own approach."""
    C = scene.n_connected
    d = np.hypot(*(scene.xy[:, None, :] - scene.xy[None, :C, :]).transpose(2, 0, 1))  # (A, C)
    same_arm = scene.arm[:, None] == scene.arm[None, :C]
    ahead = scene.along_m[:, None] < scene.along_m[None, :C]
    approaching = scene.along_m[None, :C] > -5.0  # c has not left the box yet
    conflict = (~same_arm | ahead) & approaching
    r = np.clip(1.0 - d / RELEVANCE_RANGE_M, 0.0, 1.0) * conflict
    r[np.arange(C), np.arange(C)] = 0.0
    return np.round(r, 3)


def intersection_instance(
    rng: np.random.Generator,
    n_vehicles: int,
    *,
    objects_per_vehicle: int = 30,
    others: int | None = None,
    pedestrians: int | None = None,
    frame_duration_s: float = 0.01,
    n_frames: int = 10,
    bandwidth_bps: float = 7.2e6,
) -> Instance:
    """A scheduling instance as AutoCast would meet it at a busy intersection."""
    others = n_vehicles if others is None else others
    pedestrians = 4 + n_vehicles // 2 if pedestrians is None else pedestrians
    scene = intersection_scene(rng, n_vehicles, others, pedestrians)
    detects, seen = line_of_sight(scene)  # (C, A)
    r = relevance(scene)  # (A, C)
    C = n_vehicles
    vids = rng.permutation(np.arange(100, 100 + 3 * C))[:C]
    owner, oid, size, rows = [], [], [], []
    for i in range(C):
        visible = np.flatnonzero(detects[i])
        dist = np.hypot(*(scene.xy[visible] - scene.xy[i]).T)
        for a in visible[np.argsort(dist, kind="stable")][:objects_per_vehicle]:
            d_ia = float(np.hypot(*(scene.xy[a] - scene.xy[i])))
            points = int(np.clip(5000.0 / max(d_ia, 5.0), 60, 300) * rng.uniform(0.8, 1.2))
            owner.append(int(vids[i]))
            oid.append(int(a))
            size.append(points * BYTES_PER_POINT + HEADER_BYTES)
            visible_to_j = seen[:, a].astype(np.float64)
            y = (1.0 - visible_to_j) * r[a]  # y_(i,k),j = (1 - v) * r
            if a < C:
                y[a] = 0.0  # a connected vehicle needs no point cloud of itself
            rows.append(y)
    reward = np.array(rows).reshape(len(rows), C)
    p = link_probabilities(scene.xy[:C])
    frame_bytes = int(bandwidth_bps * frame_duration_s / 8.0)  # S_f = B * T_n
    return instance_from_arrays(
        vids, owner, oid, size, reward, p,
        frame_bytes=frame_bytes, n_frames=n_frames, bandwidth_bps=bandwidth_bps, frame_duration_s=frame_duration_s,
    )
