"""The paper's three scenarios, as validated parameters plus a builder per scenario.

Every scenario has an *ego* (connected, vid 0), an *occluder* truck (connected,
vid 1), a passive *collider* (no V2V, driven by the world, vid N) and background
connected vehicles (vids 2..N-1) placed on lanes within R/2 of the scene centre. The
ego and the collider drive routes that cross at a *conflict point*; the collider
reaches it ``delta_s`` seconds after the ego (negative: before) if neither reacts.
A scenario may add more unconnected actors after the collider (vids N+1...): parked
trucks (``parked``) and the traffic that follows the collider (``traffic``), as the
paper's authors built their scenarios (docs/scenarios.md):

- overtaking: a box truck parked in the ego's lane, shifted 0.8 m toward the centre
  line; cars follow the collider in the oncoming lane (a car enters whenever the last
  is 40 m on); the collider and its followers brake fully for a vehicle within three
  of their lengths ahead.
- left_turn: the box truck waits inside the junction, 3.5 m past its stop line and
  yawed 30 degrees toward its turn; cars follow the collider (a car enters whenever the
  last is 20 m on); the collider and its followers do not brake for others.
- red_light: the connected box truck waits at the junction's entry in the ego's left
  lane, behind it a row of parked, unconnected box trucks one every 6 m back to 3 m
  past the ego's start; the collider runs the red from the ego's left and holds its
  speed.

Background vehicles are queued (stationary) on approach lanes and parking strips, or
drive away from the centre on exit lanes; a candidate is kept only if, driven at its
speed along its lane, it never comes near an actor or another kept vehicle within the
scenario's duration, so the background adds occlusion and channel load, not crashes.
They are placed within R/2 of a junction first and, when those places are full, further
out along the arms. A map holds ``MAX_VEHICLES_PER_DOMAIN`` connected vehicles per
scheduler domain: no domain gets more members than that at t = 0, and a run asks for at
most that many times the map's domains.

A scenario is a builder ``(ScenarioParams) -> Scenario`` that places the ego, the
occluder and the collider; ``build`` adds the background. A scenario may hold several
occlusion events (``Event``: an ego, its occluder, a collider, a conflict point and a
time window each), built each by its event builder as if alone and joined by
``several_events``; ``corridor3x`` has two (docs/domains.md). Builders are found by name
(``register_scenario``) or by import path (``--scenario mypkg.scenes:merge``), so a
user's scenario runs in the world process without editing this file
(docs/extending.md).
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from protocol import plugins
from protocol.messages import MAX_DOMAINS, VehicleSpec
from world_server.geometry import arc_lengths, first_crossing, point_at, project_s
from world_server.roadmap import DOMAIN_RADIUS_M, LEFT_OF, OPPOSITE, RoadMap, corridor, grid, intersection, \
    straight_road

SCENARIOS = ("overtaking", "left_turn", "red_light")  # the paper's, registered below
NETWORK_SCENARIOS = ("corridor3", "grid4", "corridor3x", "grid4_handover")  # several domains (docs/domains.md)
EGO_LEAD_TIME_S = 7.0  # the ego reaches the conflict point this long after t = 0
OVERTAKE_LEAD_TIME_S = 5.0  # starts closer behind the truck, as a driver about to pull out
GRID4_HANDOVER_LEAD_S = 9.5  # grid4_handover: the ego starts in the J0-J1 overlap and leaves it
LEFT_TURNER_INTO_BOX_M = 3.5  # the waiting left-turn truck's centre, past its stop line on its lane's line
LEFT_TURNER_YAW_DEG = 30.0  # ... yawed this much toward its turn (the authors: 5 m in, 30 deg; 5 m would
# touch the ego's turn in our 16 m box, 3.5 m clears it by 0.7 m)
TRUCK_OFFSET_M = 0.8  # the parked truck stands this far toward the centre line "for more occlusion"
RED_LIGHT_TRUCK_INTO_BOX_M = 0.5  # the connected truck's front, past the ego's left lane's stop line
PARKED_ROW_PITCH_M = 6.0  # the red-light row: one parked truck every 6 m ...
PARKED_ROW_FROM_M = 3.0  # ... from 3 m past the ego's start up to the junction
OVERTAKE_TRAFFIC_GAP_M = 40.0  # a car enters behind the overtaking collider when the last one is this far on
LEFT_TURN_TRAFFIC_GAP_M = 20.0  # ... behind the left-turn collider
OVERTAKE_EGO_KMH, LEFT_TURN_EGO_KMH, RED_LIGHT_EGO_KMH = 20.0, 30.0, 40.0  # the authors' evaluation speeds
OVERTAKE_BRAKE_LENGTHS = 3.0  # the oncoming traffic brakes fully for a vehicle this many own lengths ahead
OVERTAKE_RAMP_M = (12.0, 4.0)  # the ego's route leaves its lane this far behind the truck's centre, is
# in the oncoming lane this far behind it (and mirrored past it)
MAX_VEHICLES_PER_DOMAIN = 64  # connected vehicles of one scheduler domain; a map of D domains holds D times that
BACKGROUND_SPEED_MPS = 12.0
BACKGROUND_SPACING_M = 9.5
TRUCK_SHARE = 0.15

CAR = VehicleSpec(4.5, 1.8, 1.5, 2.7, 3.0, 7.5, 0.6)
TRUCK = VehicleSpec(9.0, 2.5, 3.5, 5.5, 2.0, 6.5, 0.6)
BOX_TRUCK = VehicleSpec(5.2, 2.5, 2.6, 3.4, 2.0, 6.5, 0.6)  # the scenarios' occluders: a 5.2 m box truck
SPECS = {"car": CAR, "truck": TRUCK, "box_truck": BOX_TRUCK}
MOUNT_HEIGHT_M = {"car": 1.9, "truck": 3.8, "box_truck": 2.9}


class ScenarioError(ValueError):
    """A scenario definition that cannot be run; the message names the field."""


@dataclass(frozen=True, slots=True)
class ScenarioParams:
    """The named knobs of a run (paper section 6.2)."""

    scenario: str = "left_turn"
    vehicles: int = 10  # connected vehicles in range, ego and occluder included
    collider_speed_kmh: float = 30.0
    delta_s: float = 0.0  # collider's arrival at the conflict point minus the ego's
    seed: int = 0
    duration_s: float = 0.0  # sim-time limit; 0: the scenario's own (``time_limit_s``)
    ego_speed_kmh: float = 0.0  # 0: the scenario's default

    def __post_init__(self) -> None:
        builder_of(self.scenario)  # raises ScenarioError naming the field
        if self.duration_s == 0:
            object.__setattr__(self, "duration_s", time_limit_s(self.scenario))
        # the scenario's map bounds it further (``build``: MAX_VEHICLES_PER_DOMAIN a domain)
        _check_range("vehicles", self.vehicles, 2, MAX_VEHICLES_PER_DOMAIN * MAX_DOMAINS, int)
        _check_range("collider_speed_kmh", self.collider_speed_kmh, 5.0, 80.0, float)
        _check_range("delta_s", self.delta_s, -5.0, 5.0, float)
        _check_range("seed", self.seed, 0, 2**31 - 1, int)
        _check_range("duration_s", self.duration_s, 0.5, 600.0, float)
        _check_range("ego_speed_kmh", self.ego_speed_kmh, 0.0, 80.0, float)


def _check(ok: bool, name: str, value: Any, expect: str) -> None:
    if not ok:
        raise ScenarioError(f"{name}: {value!r} is not {expect}")


def _check_range(name: str, value: Any, lo: float, hi: float, kind: type) -> None:
    is_num = isinstance(value, (int, float)) and not isinstance(value, bool)
    if kind is int:
        _check(isinstance(value, int) and not isinstance(value, bool), name, value, "an integer")
    else:
        _check(is_num and math.isfinite(value), name, value, "a number")
    _check(lo <= value <= hi, name, value, f"in [{lo}, {hi}]")


def params_from_dict(values: dict[str, Any]) -> ScenarioParams:
    """Validate a mapping (from TOML or CLI flags) into parameters; errors name the field."""
    known = {f.name: f for f in dataclasses.fields(ScenarioParams)}
    for key in values:
        if key not in known:
            raise ScenarioError(f"{key}: unknown field (known: {', '.join(known)})")
    coerced = {}
    for key, value in values.items():
        if known[key].type in ("float", float) and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        coerced[key] = value
    return ScenarioParams(**coerced)


def load_scenario_file(path: str | Path) -> ScenarioParams:
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except tomllib.TOMLDecodeError as exc:
        raise ScenarioError(f"{path}: not valid TOML: {exc}") from None
    return params_from_dict(data)


@dataclass(slots=True)
class Actor:
    """A vehicle at t = 0: its route starts at its position; speed 0 means it waits.

    ``brake_lengths`` is for the world-driven (unconnected) movers: they brake fully
    while a vehicle is within that many of their own lengths ahead; 0 never brakes.
    """

    vid: int
    role: str  # ego | occluder | collider | background | parked | traffic
    kind: str  # car | truck | box_truck
    route: np.ndarray
    speed_mps: float
    connected: bool
    brake_lengths: float = 0.0

    @property
    def spec(self) -> VehicleSpec:
        return SPECS[self.kind]

    @property
    def mount_height_m(self) -> float:
        return MOUNT_HEIGHT_M[self.kind]

    def start_pose(self) -> tuple[float, float, float]:
        d = self.route[1] - self.route[0]
        return float(self.route[0, 0]), float(self.route[0, 1]), math.atan2(d[1], d[0])


@dataclass(frozen=True, slots=True, eq=False)
class Event:
    """One occlusion event of a scenario, judged on its own (``world_server.judge``): its
    ego (connected, role ``ego``), the truck that hides the collider from it (``occluder``),
    the passive collider (``collider``), the point where the ego's and the collider's routes
    cross, and its time window: from t = 0 to ``time_limit_s`` of sim time (the run's
    duration, if shorter), by which it is judged a deadlock (or a near miss) if nothing
    else was decided."""

    name: str  # unique within its scenario: "red_light@J0"; a scenario of one event: the scenario's name
    junction: str  # where it happens ("J0"); "" on a map of one junction
    ego: int  # vids
    occluder: int
    collider: int
    conflict_xy: np.ndarray
    time_limit_s: float


@dataclass(slots=True)
class Scenario:
    """The actors at t = 0, the map, the lights and the events. ``conflict_xy``, ``ego``
    and ``collider`` are the first event's (vids 0 and ``params.vehicles``); a builder
    that names no ``events`` has that one event (``build`` adds it)."""

    params: ScenarioParams
    roadmap: RoadMap
    actors: list[Actor]
    conflict_xy: np.ndarray
    lights: dict[int, str] = field(default_factory=dict)
    events: list[Event] = field(default_factory=list)

    @property
    def ego(self) -> Actor:
        return self._role("ego")

    @property
    def collider(self) -> Actor:
        return self._role("collider")

    def _role(self, role: str) -> Actor:
        """The lowest-numbered actor of ``role``: the first event's."""
        return min((a for a in self.actors if a.role == role), key=lambda a: a.vid)

    def actor(self, vid: int) -> Actor:
        return next(a for a in self.actors if a.vid == vid)

    def connected(self) -> list[Actor]:
        return [a for a in self.actors if a.connected]

    def passive(self) -> list[Actor]:
        """The world-driven vehicles: the collider, parked trucks, traffic."""
        return [a for a in self.actors if not a.connected]

    def arrival_s(self, actor: Actor, conflict_xy: np.ndarray | None = None) -> float:
        """When ``actor`` reaches the conflict point (the first event's, or ``conflict_xy``)
        driving its route at its speed."""
        s = project_s(actor.route, self.conflict_xy if conflict_xy is None else conflict_xy)
        return s / actor.speed_mps if actor.speed_mps > 0 else math.inf


def _start_before(route: np.ndarray, conflict_xy: np.ndarray, distance_m: float, what: str) -> np.ndarray:
    """The part of ``route`` that starts ``distance_m`` before its conflict point."""
    s_conflict = project_s(route, conflict_xy)
    s0 = s_conflict - distance_m
    if s0 < 0:
        raise ScenarioError(f"{what}: needs {distance_m:.0f} m of approach, the map has {s_conflict:.0f} m")
    return _trim(route, s0)


def _trim(route: np.ndarray, s0: float) -> np.ndarray:
    cum = arc_lengths(route)
    start, _ = point_at(route, s0)
    return np.vstack([start[None], route[cum > s0 + 1e-9]])


Builder = Callable[[ScenarioParams], Scenario]
_BUILDERS: dict[str, Builder] = {}
_TIME_LIMITS_S: dict[str, float] = {}
# A scenario's sim-time limit unless a run gives one (--duration). The paper's three take
# their authors' scenario timeouts (overtaking 40 s, left turn 30 s, red-light violation
# 40 s): the ego that rightly waits for the cars following the collider needs that long.
# With 20 s for all, overtaking at 20 km/h was judged a deadlock for every scheme at
# 20 s while the AutoCast ego waited for the third oncoming car; with 40 s it passed
# safely at 29.4 s (overtaking, 5 vehicles, delta 0, seed 0).
DEFAULT_TIME_LIMIT_S = 20.0


def time_limit_s(name: str) -> float:
    """The sim-time limit of scenario ``name`` when a run gives none."""
    return _TIME_LIMITS_S.get(name, DEFAULT_TIME_LIMIT_S)


def register_scenario(name: str, time_limit_s: float = DEFAULT_TIME_LIMIT_S) -> Callable[[Builder], Builder]:
    """Decorator: make a builder runnable as ``--scenario NAME``, run for
    ``time_limit_s`` of sim time unless the run says otherwise.

    A builder returns a ``Scenario`` with the ego (vid 0, connected), the occluder
    (vid 1, connected), the collider (vid ``params.vehicles``, not connected, its route
    crossing the ego's at ``conflict_xy``), optionally more unconnected actors (vids
    ``params.vehicles + 1`` on, in order) and the lights; ``build`` adds
    ``params.vehicles - 2`` background vehicles around ``conflict_xy``. A scenario of
    several events (``events``) places each further event's ego and occluder as the next
    connected vids (2, 3, ...; ``several_events``) and its collider among the unconnected
    ones; the background then fills the connected vids after them.
    """
    def add(builder: Builder) -> Builder:
        if name in _BUILDERS:
            raise ValueError(f"scenario {name!r} registered twice")
        _BUILDERS[name] = builder
        _TIME_LIMITS_S[name] = float(time_limit_s)
        return builder
    return add


def builder_of(name: Any) -> Builder:
    """The builder of a registered name or of an import path ``package.module:function``."""
    if isinstance(name, str) and name in _BUILDERS:
        return _BUILDERS[name]
    if plugins.is_import_path(name):
        try:
            builder = plugins.load(name)
        except plugins.PluginError as exc:
            raise ScenarioError(f"scenario: {exc}") from None
        if not callable(builder):
            raise ScenarioError(f"scenario: {name!r} is not a function")
        return builder
    raise ScenarioError(f"scenario: {name!r} is not one of {', '.join(_BUILDERS)} "
                        "nor an import path package.module:function")


def build(params: ScenarioParams) -> Scenario:
    """Place every actor for ``params``; deterministic in ``params.seed``."""
    scenario = builder_of(params.scenario)(params)
    bound, m = vehicle_bound(scenario.roadmap), scenario.roadmap
    _check(params.vehicles <= bound, "vehicles", params.vehicles,
           f"in [2, {bound}] ({MAX_VEHICLES_PER_DOMAIN} a scheduler domain; {params.scenario}'s map has "
           f"{len(m.domain_centers())})")
    _check_roles(scenario, params)
    _check_events(scenario, params)
    _add_background(scenario, np.random.default_rng(params.seed))
    return scenario


def vehicle_bound(m: RoadMap) -> int:
    """The connected vehicles a run on map ``m`` may ask for: ``MAX_VEHICLES_PER_DOMAIN``
    for each of its scheduler domains (64 on a map of one, 192 on a corridor of three)."""
    return MAX_VEHICLES_PER_DOMAIN * len(m.domain_centers())


def _check_roles(scenario: Scenario, p: ScenarioParams) -> None:
    """A builder's actors fit what the world, the judge and the launcher rely on."""
    roles: dict[str, Actor] = {}
    for a in sorted(scenario.actors, key=lambda a: a.vid):
        roles.setdefault(a.role, a)  # the first event's
    want = {"ego": (0, True), "occluder": (1, True), "collider": (p.vehicles, False)}
    for role, (vid, connected) in want.items():
        actor = roles.get(role)
        if actor is None or actor.vid != vid or actor.connected != connected:
            raise ScenarioError(f"scenario: {p.scenario!r} must place the {role} as vid {vid}"
                                f"{'' if connected else ', not connected'}")
    connected = sorted(a.vid for a in scenario.actors if a.connected)
    if connected != list(range(len(connected))) or \
            any(a.role not in ("ego", "occluder") for a in scenario.actors if a.connected):
        raise ScenarioError(f"scenario: {p.scenario!r} must place its connected actors, each event's ego and "
                            f"occluder, as vids 0 to {len(connected) - 1}")
    if len(connected) > p.vehicles:
        raise ScenarioError(f"vehicles: {p.scenario} places {len(connected)} connected vehicles (an ego and an "
                            f"occluder for each event), asked for {p.vehicles}")
    passive = sorted(a.vid for a in scenario.actors if not a.connected)
    if passive != list(range(p.vehicles, p.vehicles + len(passive))) or \
            any(a.role in ("ego", "occluder") for a in scenario.actors if not a.connected):
        raise ScenarioError(f"scenario: {p.scenario!r} must place its other actors unconnected, "
                            f"as vids {p.vehicles + 1} on")


def _check_events(scenario: Scenario, p: ScenarioParams) -> None:
    """Each event names its own ego, occluder and collider by their roles; a builder that
    names none has one: the first ego's, the first occluder's and the first collider's."""
    if not scenario.events:
        scenario.events = [Event(p.scenario, "", scenario.ego.vid, scenario._role("occluder").vid,
                                 scenario.collider.vid, scenario.conflict_xy, p.duration_s)]
    by_vid = {a.vid: a for a in scenario.actors}
    for ev in scenario.events:
        for role in ("ego", "occluder", "collider"):
            vid = getattr(ev, role)
            if vid not in by_vid or by_vid[vid].role != role:
                raise ScenarioError(f"scenario: {p.scenario!r}: event {ev.name!r}'s {role} (vid {vid}) is no {role}")
    first = scenario.events[0]
    if (first.ego, first.collider) != (scenario.ego.vid, scenario.collider.vid) or \
            not np.array_equal(first.conflict_xy, scenario.conflict_xy):
        raise ScenarioError(f"scenario: {p.scenario!r}: the first event must be the scenario's ego, collider "
                            "and conflict point")
    for what in ("name", "ego", "collider"):
        values = [getattr(ev, what) for ev in scenario.events]
        if len(set(values)) != len(values):
            raise ScenarioError(f"scenario: {p.scenario!r}: two events share their {what}")


def _speeds(p: ScenarioParams, ego_default_kmh: float) -> tuple[float, float]:
    ego_kmh = p.ego_speed_kmh or ego_default_kmh
    return ego_kmh / 3.6, p.collider_speed_kmh / 3.6


def crossing_actors(p: ScenarioParams, m: RoadMap, ego_route: np.ndarray, collider_route: np.ndarray,
                     ego_kmh: float, conflict: np.ndarray | None = None,
                     lead_s: float = EGO_LEAD_TIME_S) -> tuple[Actor, Actor, np.ndarray]:
    v_ego, v_col = _speeds(p, ego_kmh)
    if conflict is None:
        hit = first_crossing(ego_route, collider_route)
        assert hit is not None, "scenario routes must cross"
        conflict = hit[0]
    ego_route = _start_before(ego_route, conflict, v_ego * lead_s, "ego_speed_kmh")
    collider_time = lead_s + p.delta_s
    collider_route = _start_before(collider_route, conflict, v_col * collider_time, "collider_speed_kmh")
    ego = Actor(0, "ego", "car", ego_route, v_ego, True)
    collider = Actor(p.vehicles, "collider", "car", collider_route, v_col, False)
    return ego, collider, conflict


def waiting_truck(route: np.ndarray, front_s: float, spec: VehicleSpec = BOX_TRUCK) -> Actor:
    """A stationary connected truck whose front bumper is at arc length ``front_s`` of ``route``."""
    kind = next(k for k, v in SPECS.items() if v == spec)
    return Actor(1, "occluder", kind, _trim(route, front_s - spec.length_m / 2), 0.0, True)


def left_turner(m: RoadMap, lane_id: str, turn_route: np.ndarray) -> Actor:
    """The connected truck waiting inside the junction to turn left: on its lane's line,
    ``LEFT_TURNER_INTO_BOX_M`` past the stop line, yawed toward its turn."""
    lane = m.lanes[lane_id]
    centre, yaw = point_at(lane.centerline, lane.stop_s_m)
    centre = centre + LEFT_TURNER_INTO_BOX_M * np.array([np.cos(yaw), np.sin(yaw)])
    yaw = float(yaw) + np.radians(LEFT_TURNER_YAW_DEG)  # left is counter-clockwise
    ahead = centre + 2.0 * np.array([np.cos(yaw), np.sin(yaw)])
    rest = _trim(turn_route, project_s(turn_route, ahead) + 2.0)
    return Actor(1, "occluder", "box_truck", np.vstack([centre, ahead, rest]), 0.0, True)


def followers(p: ScenarioParams, collider: Actor, full_route: np.ndarray, gap_m: float, first_vid: int,
              brake_lengths: float) -> list[Actor]:
    """Cars behind the collider on its route, at its speed, back to the road's start.

    The authors' code spawns a car, at rest, at the collider's start whenever no car is
    within ``gap_m`` of it, and drives it up to the collider's speed. Once at speed, each
    car of that stream is ``gap_m + v^2 / 2a`` behind the one before (the distance it lost
    accelerating at a car's ``max_accel_mps2``); we place the stream at that spacing at
    t = 0, so each car is where the stream puts it from the moment it is up to speed.
    """
    v = collider.speed_mps
    spacing = gap_m + v * v / (2.0 * CAR.max_accel_mps2)
    s_col = project_s(full_route, collider.route[0])
    out = []
    for k, s in enumerate(np.arange(s_col - spacing, 0.0, -spacing)):
        out.append(Actor(first_vid + k, "traffic", "car", _trim(full_route, float(s)), v, False, brake_lengths))
    return out


def left_turn_event(p: ScenarioParams, m: RoadMap, ego_arm: str, prefix: str = "",
                    lead_s: float = EGO_LEAD_TIME_S) -> tuple[list[Actor], np.ndarray]:
    """The left-turn event at a junction (lane ids ``prefix`` + ...): the ego turns left
    from ``ego_arm``, the opposite left-turning truck, waiting inside the junction, hides
    the collider coming straight from the opposite arm and the cars that follow it; they
    drive on straight ahead (``through_route``: on a grid, through the next junction).
    The ego reaches the conflict point ``lead_s`` after t = 0, the collider ``--delta``
    later. Returns the actors and the conflict point."""
    a, o = ego_arm, OPPOSITE[ego_arm]
    collider_route = m.through_route(f"{prefix}{o}.in.1")
    ego, collider, conflict = crossing_actors(
        p, m, m.route(f"{prefix}{a}.in.0", f"{prefix}{a}.in.0>{LEFT_OF[a]}", f"{prefix}{LEFT_OF[a]}.out.0"),
        collider_route, LEFT_TURN_EGO_KMH, lead_s=lead_s)
    truck = left_turner(m, f"{prefix}{o}.in.0",
                        m.route(f"{prefix}{o}.in.0", f"{prefix}{o}.in.0>{LEFT_OF[o]}", f"{prefix}{LEFT_OF[o]}.out.0"))
    traffic = followers(p, collider, collider_route, LEFT_TURN_TRAFFIC_GAP_M, p.vehicles + 1, 0.0)
    return [ego, truck, collider, *traffic], conflict


@register_scenario("left_turn", time_limit_s=30.0)
def _left_turn(p: ScenarioParams) -> Scenario:
    """Ego turns left from the south; the opposite left-turning truck, waiting inside the
    junction, hides the oncoming collider and the cars that follow it."""
    m = intersection()
    actors, conflict = left_turn_event(p, m, "S")
    lights = {0: "green", 2: "green", 1: "red", 3: "red"}
    return Scenario(p, m, actors, conflict, lights)


def red_light_event(p: ScenarioParams, m: RoadMap, ego_arm: str, prefix: str = "") -> tuple[list[Actor], np.ndarray]:
    """The red-light event at a junction (lane ids ``prefix`` + ...): the ego goes straight
    on from ``ego_arm`` in its outer lane; the collider runs the red from the ego's left in
    that approach's outer lane (from the segment's start on a network map: ``lead_in``)
    and drives on straight ahead (``through_route``), hidden by
    the connected truck waiting to turn left in the ego's left lane and the row of parked
    trucks behind it. Returns the actors and the conflict point."""
    a, left = ego_arm, LEFT_OF[ego_arm]
    ego, collider, conflict = crossing_actors(
        p, m, m.route(f"{prefix}{a}.in.1", f"{prefix}{a}.in.1>{OPPOSITE[a]}", f"{prefix}{OPPOSITE[a]}.out.1"),
        m.through_route(m.lead_in(f"{prefix}{left}.in.1")), RED_LIGHT_EGO_KMH)
    truck_route = m.route(f"{prefix}{a}.in.0", f"{prefix}{a}.in.0>{left}", f"{prefix}{left}.out.0")
    stop = m.lanes[f"{prefix}{a}.in.0"].stop_s_m
    truck = waiting_truck(truck_route, stop + RED_LIGHT_TRUCK_INTO_BOX_M)
    lane = m.lanes[f"{prefix}{a}.in.0"].centerline
    s_truck = stop + RED_LIGHT_TRUCK_INTO_BOX_M - BOX_TRUCK.length_m / 2
    s_first = project_s(lane, ego.route[0]) + PARKED_ROW_FROM_M
    row = []
    for k, s in enumerate(np.arange(s_truck - PARKED_ROW_PITCH_M, s_first - 1e-9, -PARKED_ROW_PITCH_M)):
        row.append(Actor(p.vehicles + 1 + k, "parked", "box_truck", _trim(lane, float(s)), 0.0, False))
    return [ego, truck, collider, *row], conflict


def several_events(p: ScenarioParams, events: list[tuple[str, str, tuple[list[Actor], np.ndarray]]]
                   ) -> tuple[list[Actor], list[Event]]:
    """Join events, each ``(kind, junction, (actors, conflict point))`` as its event builder
    placed it alone (ego 0, occluder 1, collider ``p.vehicles``, the rest from
    ``p.vehicles + 1``), into one scenario's actors: event k's ego and occluder become vids
    2k and 2k + 1, its unconnected actors follow the earlier events' in order. Each event's
    time window is its own scenario's limit (``kind``'s, e.g. left_turn 30 s)."""
    actors: list[Actor] = []
    out: list[Event] = []
    next_passive = p.vehicles
    for k, (kind, junction, (placed, conflict)) in enumerate(events):
        vids = {0: 2 * k, 1: 2 * k + 1}
        for j, vid in enumerate(sorted(a.vid for a in placed if not a.connected)):
            vids[vid] = next_passive + j
        next_passive += len(vids) - 2
        actors += [dataclasses.replace(a, vid=vids[a.vid]) for a in placed]
        out.append(Event(f"{kind}@{junction}", junction, 2 * k, 2 * k + 1, vids[p.vehicles], conflict,
                         time_limit_s(kind)))
    return actors, out


@register_scenario("red_light", time_limit_s=40.0)
def _red_light(p: ScenarioParams) -> Scenario:
    """Ego goes straight north on green; a red-light runner comes from its left, hidden by a
    row of parked trucks in the ego's left lane and the truck waiting at the junction."""
    m = intersection()
    actors, conflict = red_light_event(p, m, "S")
    lights = {0: "green", 2: "green", 1: "red", 3: "red"}
    return Scenario(p, m, actors, conflict, lights)


@register_scenario("overtaking", time_limit_s=40.0)
def _overtaking(p: ScenarioParams) -> Scenario:
    """A truck parked in the ego's lane toward the centre line; the ego passes in the
    oncoming lane, where the collider comes with more cars behind it."""
    m = straight_road()
    y_e, y_w = m.lanes["E"].centerline[0, 1], m.lanes["W"].centerline[0, 1]
    L = m.lanes["E"].centerline[-1, 0]
    far, near = OVERTAKE_RAMP_M
    ego_route = np.array([[-L, y_e], [-far, y_e], [-near, y_w], [near, y_w], [far, y_e], [L, y_e]])
    # the head-on meeting point: the middle of the ego's stretch in the oncoming lane, beside the truck
    collider_route = m.lanes["W"].centerline
    ego, collider, conflict = crossing_actors(
        p, m, ego_route, collider_route, OVERTAKE_EGO_KMH, conflict=np.array([0.0, y_w]), lead_s=OVERTAKE_LEAD_TIME_S)
    collider.brake_lengths = OVERTAKE_BRAKE_LENGTHS
    truck_lane = m.lanes["E"].centerline + np.array([0.0, TRUCK_OFFSET_M])
    truck = waiting_truck(truck_lane, L + BOX_TRUCK.length_m / 2)
    traffic = followers(p, collider, collider_route, OVERTAKE_TRAFFIC_GAP_M, p.vehicles + 1,
                        OVERTAKE_BRAKE_LENGTHS)
    return Scenario(p, m, [ego, truck, collider, *traffic], conflict, {})


def _lights(green_axis: dict[int, str]) -> dict[int, str]:
    """Every light of a corridor or grid, junction j's approaches on ``green_axis[j]`` ("NS" or
    "EW") green and the others red (per junction, light ids 4 j + S 0, E 1, N 2, W 3)."""
    return {4 * j + k: "green" if arm in axis else "red" for j, axis in green_axis.items()
            for k, arm in enumerate("SENW")}


@register_scenario("corridor3", time_limit_s=30.0)
def _corridor3(p: ScenarioParams) -> Scenario:
    """``left_turn`` at the middle junction ``J1`` of a corridor of three
    (``roadmap.corridor``: three domains on channels 0, 1, 0). The main road's lights are
    green at ``J0`` and ``J2`` and red at ``J1``, whose cross street has green; the
    background drives along the main road through the junctions, across the domains'
    borders."""
    m = corridor(3)
    actors, conflict = left_turn_event(p, m, "S", "J1:")
    return Scenario(p, m, actors, conflict, _lights({0: "EW", 1: "NS", 2: "EW"}))


@register_scenario("corridor3x", time_limit_s=max(time_limit_s("left_turn"), time_limit_s("red_light")))
def _corridor3x(p: ScenarioParams) -> Scenario:
    """Two of the paper's events on one corridor of three, each judged on its own:
    ``left_turn`` at ``J1`` as in ``corridor3`` (ego 0, truck 1, collider ``p.vehicles``)
    and ``red_light`` at ``J0`` (ego 2 going south from ``J0:N``, truck 3, the collider
    running the red from the ego's left, ``J0:E``, the segment from ``J1``, and on west
    off the map: a runner that obeys no light meets no other junction, where it would
    run that red too, into the left turn's ego waiting in ``J1``'s box). Lights:
    north-south green at ``J0`` (the red-light ego's) and ``J1`` (the left turn's), the
    main road green at ``J2``. The run lasts until both are judged, at most 40 s
    (red_light's limit; the left turn's window closes at 30 s)."""
    m = corridor(3)
    actors, events = several_events(p, [("left_turn", "J1", left_turn_event(p, m, "S", "J1:")),
                                        ("red_light", "J0", red_light_event(p, m, "N", "J0:"))])
    lights = _lights({0: "NS", 1: "NS", 2: "EW"})
    return Scenario(p, m, actors, events[0].conflict_xy, lights, events)


@register_scenario("grid4", time_limit_s=30.0)
def _grid4(p: ScenarioParams) -> Scenario:
    """``left_turn`` at the south-west junction ``J0`` of a 2 x 2 grid (``roadmap.grid``:
    four domains on channels 0, 1, 1, 0). The ego turns left from ``J0:E``, the segment
    from ``J1``, onto the southern edge arm; the collider comes straight from the western
    edge arm and drives on through ``J1``. (The collider and the cars that follow it need
    an edge arm's 130 m; the ego's 67 m segment holds its 7 s approach up to 40 km/h.) Lights: east-west green at ``J0`` (the ego's
    road, as at ``corridor3``'s ``J1``) and at ``J1`` (the collider's onward road),
    north-south green at ``J2`` and ``J3``; the background drives through the junctions
    where its light is green, across the domains' borders."""
    m = grid(2, 2)
    actors, conflict = left_turn_event(p, m, "E", "J0:")
    return Scenario(p, m, actors, conflict, _lights({0: "EW", 1: "EW", 2: "NS", 3: "NS"}))


@register_scenario("grid4_handover", time_limit_s=30.0)
def _grid4_handover(p: ScenarioParams) -> Scenario:
    """``grid4`` with an approach of ``GRID4_HANDOVER_LEAD_S`` (9.5 s) instead of 7: the
    ego starts at the eastern end of ``J0:E.in.0``, in the overlap of ``J0``'s and
    ``J1``'s domains, and leaves ``J1``'s 11.4 m on, so it hands over during its event
    (docs/domains.md, "What a handover costs"). The collider starts 9.5 s out too, and
    one car follows it on the edge arm instead of two."""
    m = grid(2, 2)
    actors, conflict = left_turn_event(p, m, "E", "J0:", lead_s=GRID4_HANDOVER_LEAD_S)
    return Scenario(p, m, actors, conflict, _lights({0: "EW", 1: "EW", 2: "NS", 3: "NS"}))


# ------------------------------------------------------------------------ background


def _footprint_circles(xy: np.ndarray, yaw: np.ndarray, spec: VehicleSpec) -> np.ndarray:
    """Three circles along the body cover the box: centres (..., 3, 2)."""
    off = np.array([-1.0, 0.0, 1.0]) * (spec.length_m / 2 - spec.width_m / 2)
    d = np.stack([np.cos(yaw), np.sin(yaw)], axis=-1)
    return xy[..., None, :] + off[:, None] * d[..., None, :]


def _sweep(actor: Actor, times: np.ndarray) -> np.ndarray:
    xy, yaw = point_at(actor.route, actor.speed_mps * times)
    return _footprint_circles(xy, yaw, actor.spec)


def _clash(a: np.ndarray, ra: float, b: np.ndarray, rb: float, margin_m: float) -> bool:
    d = np.linalg.norm(a[:, :, None, :] - b[:, None, :, :], axis=-1)
    return bool((d < ra + rb + margin_m).any())


def _candidates(scenario: Scenario) -> tuple[list[tuple[str, float, bool]], list[tuple[str, float, bool]]]:
    """Places for a background vehicle, ``(lane, arc length, moving)`` every
    ``BACKGROUND_SPACING_M`` along each lane outside the intersection boxes: those within
    R/2 of the nearest junction, and those further out (along the arms toward the map's
    edge). A vehicle moves if its lane leads away from that junction or, on a map of
    several domains, goes on through it (no light, or a green one); else it waits."""
    m = scenario.roadmap
    centers = m.domain_centers()
    network = len(centers) > 1  # several domains: the main road's traffic drives on through the junctions
    near, far = [], []
    for lane_id, lane in m.lanes.items():
        if ">" in lane_id:
            continue  # no one waits inside the intersection box
        cum = arc_lengths(lane.centerline)
        for s in np.arange(6.0, cum[-1] - 6.0, BACKGROUND_SPACING_M):
            xy, yaw = point_at(lane.centerline, s)
            rel = xy - centers[np.argmin(np.hypot(*(xy - centers).T))] if network else xy - m.center
            away = float(rel @ np.array([np.cos(yaw), np.sin(yaw)])) > 0
            light = m.lanes[lane_id].light_id
            through = network and lane_id in m.straight_on and (light < 0 or scenario.lights.get(light) == "green")
            moving = (away or through) and not lane_id.startswith("P_")
            if np.linalg.norm(rel) <= DOMAIN_RADIUS_M:
                near.append((lane_id, float(s), moving))
            else:
                far.append((lane_id, float(s), False))
    return near, far


def _add_background(scenario: Scenario, rng: np.random.Generator) -> None:
    """Fill the connected vids after the events' egos and occluders with background, in a
    seeded order: the places within R/2 of a junction first, then (only if those do not
    hold enough) the places further out, so a run that fits near the junctions is placed
    as if there were no others. A place is skipped if the vehicle would come near a kept
    one within the run, or join a domain that already has ``MAX_VEHICLES_PER_DOMAIN``
    members at t = 0."""
    from vehicle_agent.domains import DomainTable  # the agents' membership rule

    p, m = scenario.params, scenario.roadmap
    n_needed = p.vehicles - sum(a.connected for a in scenario.actors)
    times = np.arange(0.0, p.duration_s + 1e-9, 0.25)
    kept = [(a, _sweep(a, times)) for a in scenario.actors]
    table = DomainTable.of(m.to_msg())
    members = np.zeros(len(table), dtype=np.int64)
    for a in scenario.connected():
        members[list(table.membership(*a.route[0]))] += 1
    first = vid = p.vehicles - n_needed  # after the events' egos and occluders
    for candidates in _candidates(scenario):
        order = rng.permutation(len(candidates))
        kinds = rng.random(len(candidates)) < TRUCK_SHARE
        for idx in order:
            if vid - first >= n_needed:
                break
            lane_id, s, moving = candidates[idx]
            kind = "truck" if kinds[idx] else "car"
            route = _trim(m.through_route(lane_id), s)
            domains = list(table.membership(*route[0]))
            if (members[domains] >= MAX_VEHICLES_PER_DOMAIN).any():
                continue
            cand = Actor(vid, "background", kind, route, BACKGROUND_SPEED_MPS if moving else 0.0, True)
            sweep = _sweep(cand, times)
            r = cand.spec.width_m / 2
            if any(_clash(sweep, r, other, o.spec.width_m / 2, 0.8) for o, other in kept):
                continue
            kept.append((cand, sweep))
            scenario.actors.append(cand)
            members[domains] += 1
            vid += 1
        if vid - first >= n_needed:
            break
    if vid - first < n_needed:
        raise ScenarioError(f"vehicles: only {vid} connected vehicles fit the {p.scenario} scene, "
                            f"asked for {p.vehicles}")
    scenario.actors.sort(key=lambda a: a.vid)


assert set(_BUILDERS) == set(SCENARIOS) | set(NETWORK_SCENARIOS)

__all__ = ["ScenarioParams", "ScenarioError", "Scenario", "Event", "Actor", "build", "several_events", "builder_of",
           "register_scenario", "params_from_dict", "load_scenario_file", "SCENARIOS"]
