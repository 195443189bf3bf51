"""A scenario written outside ``scenarios.py``, run by import path:

    autocast run --scenario world_server.example_scenarios:left_turn_from_east --vehicles 10

Copy this file into your own package to write a scenario (docs/extending.md). A builder
places the ego (vid 0), the occluder (vid 1), the collider (vid ``p.vehicles``) and,
if it likes, more unconnected actors (vids ``p.vehicles + 1`` on); ``scenarios.build``
checks those roles and adds the background traffic.
"""

from __future__ import annotations

from world_server.roadmap import intersection
from world_server.scenarios import (LEFT_TURN_EGO_KMH, LEFT_TURN_TRAFFIC_GAP_M, Scenario, ScenarioParams,
                                    crossing_actors, followers, left_turner)


def left_turn_from_east(p: ScenarioParams) -> Scenario:
    """``left_turn`` turned a quarter: the ego turns left from the east, the opposite
    left-turning truck (from the west) hides the collider coming straight from the west."""
    m = intersection()
    collider_route = m.route("W.in.1", "W.in.1>E", "E.out.1")
    ego, collider, conflict = crossing_actors(
        p, m, m.route("E.in.0", "E.in.0>S", "S.out.0"), collider_route, LEFT_TURN_EGO_KMH)
    truck = left_turner(m, "W.in.0", m.route("W.in.0", "W.in.0>N", "N.out.0"))
    traffic = followers(p, collider, collider_route, LEFT_TURN_TRAFFIC_GAP_M, p.vehicles + 1, 0.0)
    lights = {1: "green", 3: "green", 0: "red", 2: "red"}  # light ids: S 0, E 1, N 2, W 3
    return Scenario(p, m, [ego, truck, collider, *traffic], conflict, lights)
