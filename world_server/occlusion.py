"""How long each scenario's occlusion hides the collider, from the ego and from the sharers.

Every vehicle drives its route at its speed and nobody reacts (the *nominal* motion:
the ego and the collider would meet at the conflict point ``delta_s`` apart). Each
decision interval the world's own LiDAR model is cast from the ego and from every
connected vehicle, in the scene the scenario builder made; a vehicle *sees* the
collider when at least ``AWARE_MIN_POINTS`` (5) of its returns hit the collider's body,
the judge's awareness threshold.

Against that, the ego's stopping budget: braking at its maximum deceleration (the
judge's braking model, v^2 / 2a with the vehicle's ``max_brake_mps2``), when could it
last start braking and still stop

- before its body enters the collider's path (``entry``: the first point of its route
  where its body comes within the collider's half width of the collider's route), and
- before the conflict point (``conflict``: the judge's reaction-time reference).

The ego sees the collider too late when its first sight comes after the last moment
to brake for the entry. Run ``python -m world_server.occlusion`` for the table in
docs/scenarios.md.
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass

import numpy as np

from protocol.messages import LidarConfig
from world_server import lidar
from world_server.driver import outline_points
from world_server.geometry import point_at, project_s
from world_server.judge import AWARE_MIN_POINTS
from world_server.scenarios import SCENARIOS, Scenario, ScenarioParams, build

DT_S = 0.1  # the decision interval: one scan per vehicle per interval
ENTRY_STEP_M = 0.05  # resolution of the entry point along the ego's route
AUTHORS_LIDAR = LidarConfig(range_m=50.0, fov_up_deg=4.0, fov_down_deg=-20.0)  # for comparison only


@dataclass(frozen=True, slots=True)
class Occlusion:
    """First sights of the collider (s after start, None: never before the ego's entry)."""

    scenario: str
    collider_speed_kmh: float
    delta_s: float
    ego_speed_kmh: float
    ego_first_s: float | None  # the ego's own LiDAR
    sharer_first_s: float | None  # the first connected vehicle other than the ego
    sharer_vid: int | None
    occluder_first_s: float | None  # the occluder truck (vid 1)
    last_brake_entry_s: float  # last moment full braking stops the ego before the collider's path
    last_brake_conflict_s: float  # ... before the conflict point (the judge's reference)
    entry_s: float  # when the ego's body enters the collider's path

    @property
    def ego_budget_s(self) -> float | None:
        """Time the ego's own view leaves it to start braking for the entry (< 0: too late)."""
        return None if self.ego_first_s is None else round(self.last_brake_entry_s - self.ego_first_s, 3)

    @property
    def sharer_budget_s(self) -> float | None:
        return None if self.sharer_first_s is None else round(self.last_brake_entry_s - self.sharer_first_s, 3)

    @property
    def sharer_lead_s(self) -> float | None:
        """How much earlier than the ego a sharer sees the collider (the ego never: up to its entry)."""
        if self.sharer_first_s is None:
            return None
        ego = self.ego_first_s if self.ego_first_s is not None else self.entry_s
        return round(ego - self.sharer_first_s, 3)


def nominal_boxes(sc: Scenario, t_s: float) -> np.ndarray:
    """Every actor's box ``[cx, cy, yaw, l, w, h]`` at ``t_s``, driving its route at its speed."""
    rows = []
    for a in sc.actors:
        if a.speed_mps > 0:
            xy, yaw = point_at(a.route, a.speed_mps * t_s)
            x, y, yaw = float(xy[0]), float(xy[1]), float(yaw)
        else:
            x, y, yaw = a.start_pose()
        rows.append([x, y, yaw, a.spec.length_m, a.spec.width_m, a.spec.height_m])
    return np.array(rows)


def entry_s_m(sc: Scenario) -> float:
    """Arc length of the ego's route where its body first comes within the collider's half
    width of the collider's route (ego body sampled on its outline, the route exactly)."""
    ego, col = sc.ego, sc.collider
    s_conflict = project_s(ego.route, sc.conflict_xy)
    s = np.arange(0.0, s_conflict + ENTRY_STEP_M, ENTRY_STEP_M)
    xy, yaw = point_at(ego.route, s)
    spec = ego.spec
    boxes = np.column_stack([xy, yaw, np.full(len(s), spec.length_m), np.full(len(s), spec.width_m)])
    outline, owner = outline_points(boxes)
    a, ab = col.route[:-1], np.diff(col.route, axis=0)
    rel = outline[:, None, :] - a[None]  # (points, segments, 2)
    t = np.clip((rel * ab[None]).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-12)[None], 0.0, 1.0)
    dist = np.linalg.norm(a[None] + t[..., None] * ab[None] - outline[:, None, :], axis=-1).min(axis=1)
    per_s = np.full(len(s), np.inf)
    np.minimum.at(per_s, owner, dist)
    inside = np.nonzero(per_s < col.spec.width_m / 2)[0]
    return float(s[inside[0]]) if inside.size else s_conflict


def first_sights(p: ScenarioParams, cfg: LidarConfig | None = None, scenario: Scenario | None = None) -> Occlusion:
    """Replay the nominal motion of ``p``'s scene (or of ``scenario``, built from ``p``)
    and time each vehicle's first sight."""
    cfg = cfg or LidarConfig()
    sc = scenario if scenario is not None else build(p)
    ego, col = sc.ego, sc.collider
    v = ego.speed_mps
    a_max = ego.spec.max_brake_mps2
    stop_m = v * v / (2.0 * a_max)  # the judge's braking model
    s_entry = entry_s_m(sc)
    s_conflict = project_s(ego.route, sc.conflict_xy)
    entry_t = s_entry / v
    viewers = [a for a in sc.connected()]
    first: dict[int, float] = {}
    buildings = sc.roadmap.buildings
    for k in range(int(math.floor(entry_t / DT_S)) + 1):
        t = k * DT_S
        boxes = nominal_boxes(sc, t)
        prepared = lidar.prepare_boxes(np.vstack([boxes, buildings]))
        for a in viewers:
            if a.vid in first:
                continue
            sweep = lidar.scan_prepared(prepared, boxes[a.vid, :3], a.mount_height_m, cfg, a.vid)
            if np.count_nonzero(sweep.labels == col.vid) >= AWARE_MIN_POINTS:
                first[a.vid] = round(t, 3)
        if ego.vid in first:
            break
    sharers = {vid: t for vid, t in first.items() if vid != ego.vid}
    best = min(sharers, key=lambda vid: (sharers[vid], vid)) if sharers else None
    return Occlusion(p.scenario, p.collider_speed_kmh, p.delta_s, round(v * 3.6, 2), first.get(ego.vid),
                     sharers.get(best) if best is not None else None, best, first.get(1),
                     round((s_entry - stop_m) / v, 3), round((s_conflict - stop_m) / v, 3), round(entry_t, 3))


def _fmt(x: float | None) -> str:
    return "never" if x is None else f"{x:.1f}"


def table(rows: list[Occlusion]) -> str:
    head = ("| scenario | collider km/h | delta s | ego km/h | ego sees at s | last brake (entry) s | "
            "ego budget s | sharer sees at s (vid) | sharer lead s | sharer budget s | "
            "last brake (conflict point) s |")
    lines = [head, "|" + "---|" * head.count(" | ") + "---|"]
    for r in rows:
        lines.append(f"| {r.scenario} | {r.collider_speed_kmh:g} | {r.delta_s:g} | {r.ego_speed_kmh:g} | "
                     f"{_fmt(r.ego_first_s)} | {r.last_brake_entry_s:.1f} | {_fmt(r.ego_budget_s)} | "
                     f"{_fmt(r.sharer_first_s)} ({r.sharer_vid}) | {_fmt(r.sharer_lead_s)} | "
                     f"{_fmt(r.sharer_budget_s)} | {r.last_brake_conflict_s:.1f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m world_server.occlusion", description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenarios", default=",".join(SCENARIOS))
    ap.add_argument("--collider-speeds", default="20,30,40", metavar="KMH,...")
    ap.add_argument("--deltas", default="0", metavar="S,...")
    ap.add_argument("--vehicles", type=int, default=2, help="connected vehicles (2: the ego and the occluder)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--lidar", choices=("world", "authors"), default="world",
                    help="the world's LiDAR (default) or the authors' (50 m range, +4 to -20 degrees)")
    args = ap.parse_args(argv)
    cfg = LidarConfig() if args.lidar == "world" else AUTHORS_LIDAR
    rows = []
    for name in args.scenarios.split(","):
        for kmh in (float(x) for x in args.collider_speeds.split(",")):
            for delta in (float(x) for x in args.deltas.split(",")):
                p = ScenarioParams(scenario=name, vehicles=args.vehicles, collider_speed_kmh=kmh, delta_s=delta,
                                   seed=args.seed)
                rows.append(first_sights(p, cfg))
    sys.stdout.write(table(rows) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
