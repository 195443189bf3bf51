"""The judge on whole simulated runs, in process (no I/O): lane followers everywhere."""

import numpy as np
import pytest

from vehicle_agent.control import VehicleController
from world_server.scenarios import ScenarioParams
from world_server.sim import Simulation


def run(params: ScenarioParams, override=None) -> Simulation:
    """Every connected vehicle follows its route; ``override(sim, vid)`` may replace a command."""
    sim = Simulation(params)
    ctl = {a.vid: VehicleController(a.spec) for a in sim.scenario.connected()}
    while not sim.done:
        views = sim.sense(sim.connected_vids)
        cmds = {}
        for vid, v in views.items():
            actor = sim.scenario.actors[vid]
            cmds[vid] = ctl[vid].run_step(v.pose, v.speed_mps, actor.route, actor.speed_mps)
            if override is not None:
                cmds[vid] = override(sim, vid) or cmds[vid]
        sim.step(cmds)
    return sim


@pytest.mark.parametrize("name", ["left_turn", "red_light", "overtaking"])
def test_blind_drivers_crash_at_delta_zero(name):
    sim = run(ScenarioParams(scenario=name, vehicles=5, delta_s=0.0))
    r = sim.result()
    assert r["outcome"] == "crash" and r["crash_with"] == sim.scenario.collider.vid
    assert r["closest_distance_m"] == 0.0
    # they meet where and roughly when the scenario says: 7 s (5 s overtaking) minus half a car
    assert 4.0 < r["t_end_s"] < 7.2


@pytest.mark.parametrize("name", ["left_turn", "red_light"])
def test_a_late_collider_means_safe_passage(name):
    r = run(ScenarioParams(scenario=name, vehicles=5, delta_s=3.0)).result()
    assert r["outcome"] == "safe" and r["closest_distance_m"] >= 2.0


def test_both_stopped_in_front_of_each_other_is_a_deadlock():
    # the ego pulls into the oncoming lane and stops there; the collider sees it and stops too
    def ego_stops_when_out(sim, vid):
        if vid == 0 and sim.physics.y[0] > 0.5:
            return (-7.5, 0.0)
        return None

    sim = run(ScenarioParams(scenario="overtaking", vehicles=5, delta_s=2.0), ego_stops_when_out)
    r = sim.result()
    assert r["outcome"] == "deadlock", r
    assert r["closest_distance_m"] > 2.0


def test_closest_distance_is_the_body_gap_over_the_run():
    sim = run(ScenarioParams(scenario="left_turn", vehicles=5, delta_s=3.0))
    series = np.array(sim.result()["distance_series_m"])
    assert sim.result()["closest_distance_m"] <= series[:, 1].min() + 1e-9
    assert series[0, 1] > 50.0  # they start far apart


def test_same_seed_same_outcome():
    a = run(ScenarioParams(scenario="red_light", vehicles=10, delta_s=0.5, seed=4)).result()
    b = run(ScenarioParams(scenario="red_light", vehicles=10, delta_s=0.5, seed=4)).result()
    assert a == b
