"""A scenario written outside ``scenarios.py``, run by import path:

    autocast run --scenario world_server.example_scenarios:left_turn_from_east --vehicles 10

Copy this file into your own package to write a scenario (docs/extending.md). A builder
places the ego (vid 0), the occluder (vid 1), the collider (vid ``p.vehicles``) and,
if it likes, more unconnected actors (vids ``p.vehicles + 1`` on); ``scenarios.build``
checks those roles and adds the background traffic.
"""

from __future__ import annotations

from world_server.roadmap import intersection
from world_server.scenarios import Scenario, ScenarioParams, left_turn_event


def left_turn_from_east(p: ScenarioParams) -> Scenario:
    """``left_turn`` turned a quarter: the ego turns left from the east, the opposite
    left-turning truck (from the west) hides the collider coming straight from the west."""
    m = intersection()
    actors, conflict = left_turn_event(p, m, "E")
    lights = {1: "green", 3: "green", 0: "red", 2: "red"}  # light ids: S 0, E 1, N 2, W 3
    return Scenario(p, m, actors, conflict, lights)
