"""The outcome judge (paper section 6.2): crash, near miss, deadlock or safe passage.

The judge watches the ego and the collider at every physics step and reports, like a
ScenarioRunner criterion, each metric's actual value with its unit:

- ``crash``: the ego's body touched the collider's (or any vehicle's; ``crash_with``).
- ``near_miss``: no contact, but the bodies came closer than ``near_miss_m`` (2 m).
- ``deadlock``: the ego never got past the conflict point: it stood still for
  ``deadlock_s`` while the collider had not passed either, or the run timed out.
- ``safe``: the ego passed the conflict point with room to spare.

Reaction time is the time from the ego's first awareness of the collider (a tick in
which at least 5 of the collider's points were in its view: its fused view, own and
received points, when the ego agent reports it, else its own LiDAR's) to the last
moment at which braking at its maximum deceleration would still have stopped it
before the conflict point. Collider visibility (share of ticks, mean points) is
measured the same way, over the whole run (``collider_visible_share``, the paper's
"percentage of frames") and over the encounter (``collider_visible_share_encounter``):
the ticks before the ego or the collider had passed the conflict point, while the
collider could still matter to the ego. A scheme that stops sending the collider once it
is behind the ego scores lower on the first, not on the second.

A scenario of several events (``scenarios.Event``) has one judge per event, each watching
its own ego and collider about its own conflict point.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from world_server.geometry import box_corners, count_in_box, project_s, rect_distance
from world_server.physics import Physics
from world_server.scenarios import Event, Scenario

RUN_FIELDS = ("scenario", "vehicles", "collider_speed_kmh", "delta_s", "seed")  # ``result``'s that are the run's
SEVERITY = ("safe", "deadlock", "near_miss", "crash")  # mildest first: a run of several events is its worst event's
NEAR_MISS_M = 2.0
DEADLOCK_S = 5.0
STOPPED_MPS = 0.1
AWARE_MIN_POINTS = 5


@dataclass
class Judge:
    scenario: Scenario
    event: Event | None = None  # None: the scenario's first
    near_miss_m: float = NEAR_MISS_M
    deadlock_s: float = DEADLOCK_S
    closest_m: float = math.inf
    closest_t_s: float = 0.0
    distances: list[tuple[float, float]] = field(default_factory=list)  # (t_sim_s, m) per tick
    verdict: str | None = None
    crash_with: int | None = None
    t_end_s: float = 0.0
    _both_stopped_since: float | None = None
    _ego_aware_t: float | None = None
    _last_brake_t: float | None = None
    _visible_ticks: int = 0
    _ticks: int = 0
    _collider_points: list[int] = field(default_factory=list)
    _fused_points: list[int] = field(default_factory=list)
    _fused_ticks: list[int] = field(default_factory=list)  # the tick index of each _fused_points entry
    _in_encounter: list[bool] = field(default_factory=list)  # per tick: neither had passed the conflict point

    def __post_init__(self) -> None:
        sc = self.scenario
        ev = self.event = self.event or sc.events[0]  # ``scenarios.build`` gives every scenario its events
        self._ego, self._col, conflict = sc.actor(ev.ego), sc.actor(ev.collider), ev.conflict_xy
        self.ego_i, self.col_i = self._ego.vid, self._col.vid  # not looked up at every tick
        self._ego_conflict_s = project_s(self._ego.route, conflict)
        self._col_conflict_s = project_s(self._col.route, conflict)

    def _distance(self, phys: Physics) -> float:
        """Gap between the ego's and the collider's bodies."""
        e, c = self.ego_i, self.col_i
        boxes = box_corners(phys.x[[e, c]], phys.y[[e, c]], phys.yaw[[e, c]],
                            np.array([phys.specs[e].length_m, phys.specs[c].length_m]),
                            np.array([phys.specs[e].width_m, phys.specs[c].width_m]))
        return rect_distance(boxes[0], boxes[1])

    def observe_step(self, phys: Physics) -> None:
        """After every physics step: distance and contacts."""
        e, c = self.ego_i, self.col_i
        d = self._distance(phys)
        if d < self.closest_m:
            self.closest_m, self.closest_t_s = d, phys.t_sim_s
        for contact in phys.contacts:
            if self.verdict is None and e in (contact.a, contact.b):
                self.verdict = "crash"
                self.crash_with = contact.b if contact.a == e else contact.a
                self.closest_m = 0.0 if self.crash_with == c else self.closest_m
                self.t_end_s = contact.t_sim_s

    def collider_points_in(self, phys: Physics, xy: np.ndarray, margin_m: float = 0.25) -> int:
        """How many of the world points ``xy`` lie on the collider's body (plus a margin)."""
        c = self.col_i
        spec = phys.specs[c]
        return count_in_box(np.asarray(xy), float(phys.x[c]),
                            float(phys.y[c]), float(np.cos(phys.yaw[c])), float(np.sin(phys.yaw[c])),
                            spec.length_m / 2 + margin_m, spec.width_m / 2 + margin_m)

    def observe_tick(self, phys: Physics, collider_points_in_ego_view: int,
                     collider_points_fused: int | None = None) -> None:
        """Once per decision interval: awareness, braking margin, progress, deadlock.

        ``collider_points_fused`` is the count in the ego agent's fused view (own and
        received points), when the agent reported it; awareness then uses it.
        """
        t = phys.t_sim_s
        e, c = self.ego_i, self.col_i
        self._ticks += 1
        self._collider_points.append(collider_points_in_ego_view)
        if collider_points_in_ego_view >= AWARE_MIN_POINTS:
            self._visible_ticks += 1
        if collider_points_fused is not None:
            self._fused_points.append(collider_points_fused)
            self._fused_ticks.append(self._ticks - 1)
        aware_now = (collider_points_fused if collider_points_fused is not None
                     else collider_points_in_ego_view) >= AWARE_MIN_POINTS
        if aware_now and self._ego_aware_t is None:
            self._ego_aware_t = t
        d = self._distance(phys)
        if d < self.closest_m:
            self.closest_m, self.closest_t_s = d, t
        self.distances.append((round(t, 3), round(d, 3)))
        ego_s = self._progress(phys, e)
        col_s = self._progress(phys, c)
        to_go = self._ego_conflict_s - ego_s
        if to_go > 0 and to_go - phys.v[e] ** 2 / (2 * phys.max_brake[e]) >= 0:
            self._last_brake_t = t
        ego_past = ego_s > self._ego_conflict_s + phys.specs[e].length_m
        col_past = col_s > self._col_conflict_s + phys.specs[c].length_m
        self._in_encounter.append(not (ego_past or col_past) and (not self._in_encounter or self._in_encounter[-1]))
        if self.verdict is not None:
            return
        both_stopped = phys.v[e] < STOPPED_MPS and phys.v[c] < STOPPED_MPS
        if ego_past and (col_past or phys.v[c] < STOPPED_MPS):
            self.verdict = "near_miss" if self.closest_m < self.near_miss_m else "safe"
        elif both_stopped and not ego_past and not col_past:
            self._both_stopped_since = self._both_stopped_since if self._both_stopped_since is not None else t
            if t - self._both_stopped_since >= self.deadlock_s:
                self.verdict = "deadlock"
        else:
            self._both_stopped_since = None
        if self.verdict is not None:
            self.t_end_s = t

    def _progress(self, phys: Physics, i: int) -> float:
        actor = self._ego if i == self.ego_i else self._col
        return project_s(actor.route, np.array([phys.x[i], phys.y[i]]))

    def time_out(self, t_sim_s: float) -> None:
        if self.verdict is None:
            self.verdict = "near_miss" if self.closest_m < self.near_miss_m else "deadlock"
            self.t_end_s = t_sim_s

    def result(self) -> dict:
        p = self.scenario.params
        reaction = None
        if self._ego_aware_t is not None and self._last_brake_t is not None:
            reaction = round(self._last_brake_t - self._ego_aware_t, 3)
        pts = np.array(self._collider_points or [0])
        fused = np.array(self._fused_points) if self._fused_points else None
        own_share = self._visible_ticks / max(self._ticks, 1)
        during = np.array(self._in_encounter, dtype=bool)
        if fused is not None:
            seen, during = fused >= AWARE_MIN_POINTS, during[np.array(self._fused_ticks)]
        else:
            seen = np.array(self._collider_points, dtype=np.int64) >= AWARE_MIN_POINTS
        return {
            "outcome": self.verdict,
            "closest_distance_m": round(self.closest_m, 3) if math.isfinite(self.closest_m) else None,  # None: no step
            "closest_t_s": round(self.closest_t_s, 3),
            "reaction_time_s": reaction,
            "collider_visible_share": round(float((fused >= AWARE_MIN_POINTS).mean()), 4) if fused is not None
            else round(own_share, 4),
            "collider_points_mean": round(float(fused.mean()), 2) if fused is not None else round(float(pts.mean()), 2),
            "visibility_source": "fused" if fused is not None else "own_lidar",
            "collider_visible_share_encounter": round(float(seen[during].mean()), 4) if during.any() else None,
            "encounter_ticks": int(during.sum()),
            "collider_visible_share_own": round(own_share, 4),
            "collider_points_mean_own": round(float(pts.mean()), 2),
            "crash_with": self.crash_with,
            "t_end_s": round(self.t_end_s, 3),
            "scenario": p.scenario,
            "vehicles": p.vehicles,
            "collider_speed_kmh": p.collider_speed_kmh,
            "delta_s": p.delta_s,
            "seed": p.seed,
            "near_miss_m": self.near_miss_m,
            "distance_series_m": self.distances,
        }

    def event_result(self) -> dict:
        """``result`` of this judge's event alone: its name, junction, ego and collider,
        then the judge's fields without the run's parameters (``RUN_FIELDS``)."""
        ev = self.event
        return {"event": ev.name, "junction": ev.junction, "ego": ev.ego, "collider": ev.collider,
                **{k: v for k, v in self.result().items() if k not in RUN_FIELDS}}
