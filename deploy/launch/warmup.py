"""Every numba kernel of a run compiled (or loaded from the cache) once, before its processes start.

The launcher, a sweep and a host of ``autocast deploy`` warm once, so the N processes
of a run load the kernels from the cache instead of compiling them each.
"""

from __future__ import annotations

import logging
import sys
import time

from protocol.codec import decode, encode
from protocol.messages import MapMsg, Mission, Scan
from world_server.scenarios import ScenarioParams

log = logging.getLogger(__name__)


# ``warm_numba_caches`` as a command of its own (the test suite's first step, and its check
# that nothing is left to compile): the kernels are the same for every scenario
WARM_ARGV = (sys.executable, "-c", "from deploy.launch.warmup import warm_numba_caches; "
             "from world_server.scenarios import params_from_dict; "
             "warm_numba_caches(params_from_dict({'scenario': 'left_turn', 'vehicles': 5}))")


def warm_numba_caches(params: ScenarioParams) -> None:
    """Compile (or load) every numba kernel once here, so N processes load them from the cache.

    The agent's kernels are reached through ``vehicle_agent.warm_up()`` when the agent
    provides it, otherwise through one pass of the agent's stages (perceive, reason,
    fuse, plan, control) on the scenario's first scans and every built-in scheduler's
    warm-up. A failure only costs the agents compile time.
    """
    from world_server import geometry, lidar
    from world_server.sim import Simulation

    t0 = time.perf_counter()
    sim = Simulation(params)
    lidar.warm_up(sim.lidar_cfg)
    geometry.warm_up()  # the judge's distance, at every physics step
    try:
        _warm_agent_kernels(sim)
    except Exception:  # warming is an optimisation; the agents compile what is missing
        log.warning("agent kernels not warmed; each agent compiles its own", exc_info=True)
    log.info("numba caches warm in %.1f s", time.perf_counter() - t0)


def _warm_agent_kernels(sim) -> None:
    import vehicle_agent

    hook = getattr(vehicle_agent, "warm_up", None)
    if callable(hook):
        hook()
        return
    from vehicle_agent.agent import Agent

    # the map and missions as an agent gets them, through the wire format: decoded arrays
    # are read-only, which numba types apart (the rasters' kernels at the agent's start)
    mapmsg = decode(encode(sim.scenario.roadmap.to_msg()), MapMsg)
    vids = sim.connected_vids[:2]
    views = sim.sense(vids)
    agents = {vid: Agent(decode(encode(sim.mission(vid)), Mission), mapmsg) for vid in vids}
    heard: list[int] = []
    for vid, agent in agents.items():  # two vehicles, so each has a neighbour to reason about
        v = views[vid]
        scan = Scan(0, 0.0, vid, v.pose, v.speed_mps, v.range_cm)
        view = agent.perceive(scan)
        msg = agent.control_message(view, scan, heard)
        for other in agents.values():
            other.dataplane.neighbors.update([msg])
        agent.drive(view, agent.fuse(view, []), scan)
        heard.append(vid)
    # the agents' own warm-up (decoded, read-only arrays; a shared object; a predicted
    # conflict): what it loads, each agent would otherwise compile for itself
    from channel_proxy.profiles import get_profile
    from vehicle_agent.agreement import AgreementConfig
    from vehicle_agent.scheduler.warmup import warm_up as warm_scheduler
    from vehicle_agent.warmup import warm_up as warm_agent

    warm_agent(agents[vids[0]], AgreementConfig.from_profile(get_profile("lte-direct"), scheduler="autocast"))
    warm_scheduler()
