"""The simulation core of the world server, with no I/O: sense, then step.

One decision interval: ``sense`` casts every live vehicle's LiDAR (and the collider's,
when its built-in driver brakes for what it sees); ``step`` applies the agents'
commands, drives the passive vehicles (the collider and the traffic behind it; parked
ones hold still), and advances physics by the decision interval in fixed physics steps
while the judge watches. Deterministic for a scenario and seed.

A scenario of several events has a judge per event (``judges``): each watches its event
until it is judged, then keeps its record as it was; the run is done when every event is
judged, each at the latest when its time window closes.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass

import numpy as np

from protocol.messages import LidarConfig, LightState, Mission, Pose, WorldTruth
from world_server import driver, lidar
from world_server.judge import SEVERITY, Judge
from world_server.physics import Physics
from world_server.scenarios import Scenario, ScenarioParams, build

log = logging.getLogger(__name__)

DECISION_INTERVAL_S = 0.1  # T_d
PHYSICS_DT_S = 0.01


@dataclass(frozen=True, slots=True)
class Sensed:
    """One vehicle's view for a tick: what its Scan carries."""

    vid: int
    pose: Pose
    speed_mps: float
    range_cm: np.ndarray  # uint16 (steps, beams)


class Simulation:
    def __init__(self, params: ScenarioParams, lidar_cfg: LidarConfig | None = None,
                 decision_interval_s: float = DECISION_INTERVAL_S, physics_dt_s: float = PHYSICS_DT_S) -> None:
        self.params = params
        self.scenario: Scenario = build(params)
        self.lidar_cfg = lidar_cfg or LidarConfig()
        self.decision_interval_s = decision_interval_s
        self.physics_dt_s = physics_dt_s
        self.substeps = int(round(decision_interval_s / physics_dt_s))
        actors = self.scenario.actors
        assert [a.vid for a in actors] == list(range(len(actors))), "vids index the physics arrays"
        self.physics = Physics([a.spec for a in actors], np.array([a.start_pose() for a in actors]),
                               np.array([a.speed_mps for a in actors]))
        self.heights_m = np.array([a.spec.height_m for a in actors])
        self.mount_m = np.array([a.mount_height_m for a in actors])
        events = self.scenario.events
        self.judges = [Judge(self.scenario, ev) for ev in events]
        self.judge = self.judges[0]  # the first event's
        self._windows_s = [min(ev.time_limit_s, params.duration_s) for ev in events]
        self._judges_of: dict[int, list[int]] = {}  # an event's ego -> its judges' indices
        for i, ev in enumerate(events):
            self._judges_of.setdefault(ev.ego, []).append(i)
        self._braking = [ev.collider for ev in events if self.scenario.actor(ev.collider).brake_lengths > 0]
        self._collider_points: dict[int, np.ndarray] = {}  # a braking collider's LiDAR points this tick, for its driver
        self._collider_in_view = [0] * len(events)  # per event: the collider's returns in its ego's own scan
        self.tick = 0
        self._passive = self.scenario.passive()
        self._connected = np.array(self.connected_vids, dtype=np.int64)

    @property
    def t_sim_s(self) -> float:
        return self.tick * self.decision_interval_s

    @property
    def connected_vids(self) -> list[int]:
        return [a.vid for a in self.scenario.connected()]

    def mission(self, vid: int) -> Mission:
        """What connected vehicle ``vid`` knows about itself: role, route, body, sensor."""
        a = self.scenario.actors[vid]
        lidar_cfg = dataclasses.replace(self.lidar_cfg, mount_height_m=a.mount_height_m)
        route = np.asarray(a.route, dtype=np.float64).reshape(-1, 2)  # as Mission declares it, whatever the scenario built
        return Mission(0, 0.0, vid, a.role, route, a.speed_mps, a.spec, lidar_cfg, self.decision_interval_s)

    def lights(self) -> list[LightState]:
        return [LightState(i, s) for i, s in sorted(self.scenario.lights.items())]

    def sense(self, vids: Iterable[int]) -> dict[int, Sensed]:
        """LiDAR scans of ``vids`` plus the colliders', when their driver needs them."""
        return {v.vid: v for v in self.sense_each(vids)}

    def sense_each(self, vids: Iterable[int]) -> Iterator[Sensed]:
        """``sense``, one vehicle at a time as each scan is cast, in the order of ``vids``
        (the world publishes each scan at once, so agents start while it casts the rest).
        The colliders' scans, for their driver (only of those that brake for anything),
        are cast last; consume the whole iterator."""
        braking = set(self._braking)
        wanted = [v for v in dict.fromkeys(vids) if v not in braking] + self._braking
        boxes = np.vstack([self.physics.boxes(self.heights_m), self.scenario.roadmap.buildings])
        poses = self.physics.poses()
        prepared = lidar.prepare_boxes(boxes)
        self._collider_in_view = [0] * len(self.judges)
        for vid in wanted:
            x, y, yaw = poses[vid]
            mount_m = float(self.mount_m[vid])
            if vid in braking:
                self._collider_points[vid] = lidar.scan_prepared(prepared, poses[vid], mount_m, self.lidar_cfg,
                                                                 vid).points
                continue
            image = lidar.range_image_prepared(prepared, poses[vid], mount_m, self.lidar_cfg, vid)
            for i in self._judges_of.get(vid, ()):
                self._collider_in_view[i] = int(image.box_hits[self.judges[i].col_i])
            yield Sensed(vid, Pose(float(x), float(y), float(yaw)), float(self.physics.v[vid]), image.range_cm)

    def truth(self) -> WorldTruth:
        """Every vehicle's true pose, speed and size now."""
        boxes = self.physics.boxes(self.heights_m)
        return WorldTruth(self.tick, self.t_sim_s, np.arange(len(boxes), dtype=np.int64),
                          boxes[:, :3].astype(np.float32), np.asarray(self.physics.v, dtype=np.float32),
                          boxes[:, 3:6].astype(np.float32))

    def step(self, commands: Mapping[int, tuple[float, float]], dead: Iterable[int] = (),
             fused_xy: Mapping[int, np.ndarray] | None = None) -> None:
        """Apply commands for this tick and advance physics by one decision interval.

        A connected vehicle without a command (its agent is dead) gets the failsafe:
        full brake, wheels straight. ``fused_xy`` holds, by ego vid, each event's ego
        agent's reported fused view for this tick (world points), for its judge's
        visibility metrics; an ego that reported nothing is judged on its own scan.
        """
        phys = self.physics
        ids = self._connected
        accel = np.empty(len(ids))
        steer = np.empty(len(ids))
        for j, vid in enumerate(ids.tolist()):
            if vid in commands:
                accel[j], steer[j] = commands[vid]
            else:
                accel[j], steer[j] = -phys.max_brake[vid], 0.0
        phys.command_many(ids, accel, steer)
        self._drive_passive()
        fused_xy = fused_xy or {}
        watching = [(i, judge) for i, judge in enumerate(self.judges) if judge.verdict is None]
        for i, judge in watching:
            xy = fused_xy.get(judge.ego_i)
            fused = None if xy is None else judge.collider_points_in(phys, xy)
            judge.observe_tick(phys, self._collider_in_view[i], fused)
        for _ in range(self.substeps):
            phys.step(self.physics_dt_s)
            for _, judge in watching:
                judge.observe_step(phys)
        self.tick += 1
        self._collider_points = {}

    def _drive_passive(self) -> None:
        """Commands for the world-driven vehicles (driver.py)."""
        phys = self.physics
        if any(v not in self._collider_points for v in self._braking):
            self.sense([])
        outline = owner = None
        for a in self._passive:
            i = a.vid
            horizon = max(a.brake_lengths * a.spec.length_m, 1.0)
            if a.speed_mps <= 0.0 or a.brake_lengths <= 0.0:
                gap = np.inf
            elif i in self._collider_points:
                gap = driver.free_distance_ahead(self._collider_points[i], a.spec, a.mount_height_m, horizon)
            else:
                if outline is None:
                    outline, owner = driver.outline_points(phys.boxes(self.heights_m))
                gap = driver.free_distance_to_boxes(phys.x[i], phys.y[i], phys.yaw[i], a.spec, outline, owner, i,
                                                    horizon)
            phys.command(i, *driver.passive_command(phys.x[i], phys.y[i], phys.yaw[i], phys.v[i], a.speed_mps,
                                                    a.route, a.spec, gap, a.brake_lengths))

    @property
    def done(self) -> bool:
        """Every event judged; an event whose time window has closed is judged now."""
        for judge, window_s in zip(self.judges, self._windows_s):
            if judge.verdict is None and self.t_sim_s >= window_s - 1e-9:
                judge.time_out(self.t_sim_s)
        return all(judge.verdict is not None for judge in self.judges)

    def result(self) -> dict:
        """The judged outcome. One event: its judge's record. Several: the worst event's
        record (``judge.SEVERITY``: crash, near miss, deadlock, safe; an event not judged
        yet counts worse than a crash; the earlier event on a tie), ``event`` naming it,
        and ``events``: every event's own record (``Judge.event_result``), in order."""
        if len(self.judges) == 1:
            return self.judge.result()
        worst = max(self.judges, key=lambda j: SEVERITY.index(j.verdict) if j.verdict in SEVERITY else len(SEVERITY))
        record = worst.result()
        return {"outcome": record["outcome"], "event": worst.event.name, **record,
                "events": [judge.event_result() for judge in self.judges]}
