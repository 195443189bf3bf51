"""Each scenario's occlusion, on the world's own scenario builder and LiDAR, without agents:
every vehicle drives its route at its speed and nobody reacts (world_server/occlusion.py)."""

import numpy as np
import pytest

from world_server.occlusion import entry_s_m, first_sights
from world_server.scenarios import ScenarioParams, build

SHARER_LEAD_S = 2.0  # "a vehicle that shares sees it seconds earlier"


@pytest.mark.parametrize("name, kmh", [
    ("red_light", 20.0), ("red_light", 40.0),  # the paper: no time to react whatsoever, at any speed
    ("overtaking", 30.0), ("overtaking", 40.0),  # the paper: 0.31 s at 20 km/h, none above
    ("left_turn", 40.0),  # the paper: benign, but crashes when the collider is fast
])
def test_the_ego_sees_the_collider_too_late_and_the_truck_seconds_earlier(name, kmh):
    """delta 0: ego and collider would reach the conflict point together. The ego's own
    LiDAR first has 5 points on the collider only after the last moment at which full
    braking (the judge's v^2 / 2a) would stop it short of the collider's path; the
    connected truck had it in view at least two seconds before that moment."""
    o = first_sights(ScenarioParams(scenario=name, vehicles=2, collider_speed_kmh=kmh, delta_s=0.0))
    assert o.ego_first_s is None or o.ego_first_s > o.last_brake_entry_s, o
    assert o.occluder_first_s is not None, o
    assert o.last_brake_entry_s - o.occluder_first_s >= SHARER_LEAD_S, o
    assert o.sharer_lead_s >= SHARER_LEAD_S, o


def test_the_row_of_parked_trucks_is_what_hides_the_red_light_runner():
    """Without the parked row, behind the truck at the junction and the corner building
    alone, the ego sees the collider in time: the row makes the occlusion wide."""
    p = ScenarioParams(scenario="red_light", vehicles=2, collider_speed_kmh=30.0, delta_s=0.0)
    with_row = first_sights(p)
    bare = first_sights(p, scenario=_without(build(p), {"parked"}))
    assert with_row.ego_first_s > with_row.last_brake_entry_s
    assert bare.ego_first_s is not None and bare.ego_first_s < bare.last_brake_entry_s - 1.0


def _without(sc, roles):
    """The scene with the actors of ``roles`` moved far away (vids keep indexing the boxes)."""
    for a in sc.actors:
        if a.role in roles:
            a.route = a.route - np.array([1000.0, 1000.0])
    return sc


def test_entry_points_by_hand():
    # red_light: ego straight north on x = 5.25 at 40 km/h, 7 s (77.8 m) before the conflict point
    # on the collider's line y = -5.25; its front bumper (2.25 m ahead) meets the collider's
    # near edge (0.9 m before the line) 3.15 m before the ego's centre gets there
    sc = build(ScenarioParams(scenario="red_light", vehicles=2))
    assert entry_s_m(sc) == pytest.approx(40 / 3.6 * 7.0 - 2.25 - 0.9, abs=0.051)
    # overtaking: the ramp leaves y = -2 at x = -12 for y = 2 at x = -4 (heading atan(1/2)); the
    # front-left corner is (2.25 * 1 + 0.9 * 2) / sqrt(5) above the centre and meets the collider's
    # edge y = 1.1 after u = (1.1 + 2 - 4.05 / sqrt(5)) * sqrt(5) m of ramp; the ego starts 5 s at
    # 20 km/h before the conflict point (0, 2), i.e. sqrt(80) + 4 m of route before the ramp's end
    sc = build(ScenarioParams(scenario="overtaking", vehicles=2))
    ramp_start_s = 20 / 3.6 * 5.0 - 4.0 - np.sqrt(80.0)
    u = (1.1 + 2.0 - 4.05 / np.sqrt(5.0)) * np.sqrt(5.0)
    assert entry_s_m(sc) == pytest.approx(ramp_start_s + u, abs=0.051)
