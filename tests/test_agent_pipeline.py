"""The agent's per-interval pipeline (``vehicle_agent.__main__.Pipeline``) in one process,
on a scenario's real scans."""

from __future__ import annotations

from protocol.codec import encode
from protocol.messages import Scan
from vehicle_agent.__main__ import Pipeline
from vehicle_agent.control import VehicleController
from world_server.scenarios import ScenarioParams
from world_server.sim import Simulation


def test_a_vehicle_that_holds_still_shares_without_fusing_and_commands_as_if_it_fused():
    sim = Simulation(ScenarioParams(scenario="red_light", vehicles=10, seed=0))
    mapmsg = sim.scenario.roadmap.to_msg()
    waiting = [a.vid for a in sim.scenario.connected() if a.speed_mps <= 0.0]
    assert waiting, "the scenario has no connected vehicle that holds still"
    vid = waiting[0]
    lean = Pipeline(sim.mission(vid), mapmsg, "single", "lte-direct")
    full = Pipeline(sim.mission(vid), mapmsg, "single", "lte-direct")
    full.fuses = True  # what every vehicle did before
    assert not lean.fuses
    reporting = Pipeline(sim.mission(vid), mapmsg, "single", "lte-direct", report=lambda raw: None)
    assert reporting.fuses, "a vehicle that reports its fused view must fuse"
    ctl = {a.vid: VehicleController(a.spec) for a in sim.scenario.connected()}
    for _ in range(5):
        views = sim.sense(sim.connected_vids)
        v = views[vid]
        scan = Scan(sim.tick, sim.t_sim_s, vid, v.pose, v.speed_mps, v.range_cm)
        assert encode(lean.run(scan)) == encode(full.run(scan))
        assert "fusion" not in lean.agent.timings_ms and "fusion" in full.agent.timings_ms
        sim.step({u: ctl[u].run_step(w.pose, w.speed_mps, sim.scenario.actors[u].route, sim.scenario.actors[u].speed_mps)
                  for u, w in views.items()})
