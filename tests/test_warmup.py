"""The agent's warm-up loads every numba kernel a real interval uses, with the types a
real interval gives them, so the first tick compiles and loads nothing."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from numba.core.dispatcher import Dispatcher

from channel_proxy.emp import voronoi_segment
from conftest import copy_as_cache_dir
from channel_proxy.profiles import get_profile
from protocol.codec import decode, encode
from protocol.messages import ControlMsg, Scan
from vehicle_agent.agent import Agent
from vehicle_agent.agreement import AgreementConfig, decide
from vehicle_agent.agreement import plan as plan_transmissions
from vehicle_agent.frames import scan_to_world
from vehicle_agent.paths import arc_lengths
from vehicle_agent.planning import Obstacle, first_conflict
from vehicle_agent.tracking import registered_velocity
from vehicle_agent.warmup import warm_up
from world_server.scenarios import ScenarioParams
from world_server.sim import Simulation


def kernel_signatures() -> dict[str, int]:
    """How many compiled signatures each numba kernel of the agent's modules has."""
    out = {}
    for name, module in list(sys.modules.items()):
        if not name.startswith(("vehicle_agent", "channel_proxy.emp")):  # EMP's segment is cut in the agent
            continue
        for attr, value in vars(module).items():
            if isinstance(value, Dispatcher):
                out[f"{name}.{attr}"] = len(value.signatures)
    return out


def test_a_real_interval_after_the_warm_up_adds_no_kernel_signature():
    sim = Simulation(ScenarioParams(scenario="left_turn", vehicles=5, delta_s=0.0, seed=0))
    mapmsg = sim.scenario.roadmap.to_msg()
    agreement = AgreementConfig.from_profile(get_profile("lte-direct"), scheduler="autocast")
    ego, truck = (Agent(sim.mission(vid), mapmsg) for vid in (0, 1))
    warm_up(ego, agreement)
    warm_up(truck, agreement)
    before = kernel_signatures()
    assert before, "no numba kernel found in the agent's modules"

    views = sim.sense(sim.connected_vids)
    scans = {vid: decode(encode(Scan(sim.tick, sim.t_sim_s, vid, views[vid].pose, views[vid].speed_mps,
                                     views[vid].range_cm)), Scan) for vid in (0, 1)}
    ego_view, truck_view = ego.perceive(scans[0]), truck.perceive(scans[1])
    again = views[1]  # the truck's next frame: its tracker pairs this frame's objects with its tracks
    truck.perceive(decode(encode(Scan(sim.tick + 1, sim.t_sim_s + 0.1, 1, again.pose, again.speed_mps,
                                      again.range_cm)), Scan))
    seen = max((t.detection.points_world for t in truck_view.tracks), key=len)  # a mover's third frame registers
    registered_velocity([(0.0, seen), (0.1, seen), (0.2, seen)], seen, 0.3, np.array([10.0, 0.0]))
    truck_msg = decode(encode(truck.control_message(truck_view, scans[1], heard=[0])), ControlMsg)
    ego.dataplane.neighbors.update([truck_msg])
    own = ego.control_message(ego_view, scans[0], heard=[1])
    plan_transmissions(decide(0, sim.tick, own, [truck_msg], agreement), agreement)
    payloads = truck.dataplane.payloads(truck_view, [t.track_id for t in truck_view.tracks])
    assert payloads, "the truck should see something to share"
    ego.drive(ego_view, ego.fuse(ego_view, list(payloads.values())), scans[0])
    world = scan_to_world(scans[0], ego.mission.lidar)  # EMP's segment of the scan
    truck_xy = np.array([[scans[1].pose.x_m, scans[1].pose.y_m]])
    voronoi_segment(world[:, :2], np.array([scans[0].pose.x_m, scans[0].pose.y_m]), truck_xy)
    # nothing moves at the start: a car that crosses the ego's planned path when it gets there
    path = ego.last_plan.path
    t_path = arc_lengths(path) / 10.0
    ahead = int(np.searchsorted(arc_lengths(path), 10.0))
    d = path[ahead + 1] - path[ahead]
    normal = np.array([-d[1], d[0]]) / np.hypot(*d)
    crossing = Obstacle(path[ahead] - 10.0 * normal, 10.0 * normal, 4.5, 1.8, 0.0, float(np.arctan2(*normal[::-1])))
    assert first_conflict(path, t_path, ego.mission.spec, [crossing], 0.0, ego.planner.config) is not None

    after = kernel_signatures()
    grown = {k: (before.get(k, 0), n) for k, n in after.items() if n > before.get(k, 0)}
    assert not grown, f"kernels compiled or loaded at the first real tick (before, after): {grown}"


def test_an_agent_drives_its_first_ticks_as_if_it_had_never_been_warmed_up():
    """The warm-up's synthetic interval (a car ahead, a neighbour, a shared object) leaves
    nothing behind: the ego of grid4_handover, 60 vehicles, seed 3 (an oncoming car 23 m
    ahead in the next lane), warmed up and not, plans the same path and sends the same
    command in each of its first three ticks. Warmed in place, its planner kept the path
    round the synthetic obstacle, a swerve toward the centre line 10 m ahead."""
    sim = Simulation(ScenarioParams(scenario="grid4_handover", vehicles=60, delta_s=0.0, seed=3))
    mapmsg = sim.scenario.roadmap.to_msg()
    agreement = AgreementConfig.from_profile(get_profile("lte-direct"), scheduler="autocast")
    warmed, cold = Agent(sim.mission(0), mapmsg), Agent(sim.mission(0), mapmsg)
    warm_up(warmed, agreement)
    for _ in range(3):
        view = sim.sense([0])[0]
        scan = decode(encode(Scan(sim.tick, sim.t_sim_s, 0, view.pose, view.speed_mps, view.range_cm)), Scan)
        commands = []
        for agent in (warmed, cold):
            seen = agent.perceive(scan)
            commands.append(agent.drive(seen, agent.fuse(seen, []), scan))
        assert encode(commands[0]) == encode(commands[1]), sim.tick
        np.testing.assert_array_equal(warmed.last_plan.path, cold.last_plan.path)
        sim.step({0: (commands[1].accel_mps2, commands[1].steer_rad)})  # the others' agents are not run: they brake


@pytest.mark.heavy
def test_the_launchers_warm_up_leaves_no_kernel_for_a_run_to_compile(tmp_path):
    """From an empty numba cache (a fresh clone, CI): ``warm_numba_caches``, what the
    launcher and the suite run first, compiles every kernel that runs of every scenario
    and sharing scheme then load. A kernel it misses compiles inside a tick instead, in
    every agent at once; on CI one such compile outlasted a test's safety net.

    The suite's first step is that warm-up; when it started from an empty cache, its
    files are kept apart (``AUTOCAST_WARMED_CACHE``, tests/conftest.py) and the runs here
    start from a copy of them. From a warm cache (a developer's machine) the runs start
    from a copy of the whole cache instead: they must compile nothing, but a kernel the
    warm-up misses and an earlier run compiled is not caught there, only from an empty
    cache (``NUMBA_CACHE_DIR=<empty dir> python -m pytest tests/test_warmup.py``)."""
    from deploy.launch.warmup import cached_kernels

    cache = tmp_path / "numba"
    warmed = os.environ.get("AUTOCAST_WARMED_CACHE")
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache))
    if warmed:
        shutil.copytree(warmed, cache, ignore=shutil.ignore_patterns("warm-up.log"))
        said = (Path(warmed) / "warm-up.log").read_text().splitlines()
        # what a first run shows while it compiles: how many, and when it is done
        assert any(line.startswith("compiling ") and "numba kernels on" in line for line in said), said[-20:]
        assert any(line.startswith("compiled ") and "later runs load them from the cache" in line
                   for line in said), said[-20:]
    else:
        copy_as_cache_dir(cached_kernels(), cache)
    cached = {p.name for p in cache.rglob("*.nbc")}
    assert cached, "the warm-up wrote no numba cache"
    for scenario, scheme in (("overtaking", "autocast"), ("left_turn", "emp")):
        done = subprocess.run([sys.executable, "-m", "deploy.cli", "run", "--scenario", scenario, "--vehicles", "5",
                               "--scheme", scheme, "--duration", "2", "--out", str(tmp_path / "runs")],
                              env=env, capture_output=True, text=True, timeout=900)
        assert done.returncode in (0, 1), done.stderr[-2000:]  # judged (2 s of sim time: a deadlock)
    grown = {p.name for p in cache.rglob("*.nbc")} - cached
    assert not grown, f"compiled during the runs, not by the warm-up: {sorted(grown)}"


def test_compile_progress_counts_each_of_the_projects_kernels_once():
    from deploy.launch.warmup import Progress

    progress = Progress(total=2, t0=0.0)
    for name in ("vehicle_agent.perception.build_grid", "numba.cpython.unicode.unicode_len",
                 "vehicle_agent.perception.build_grid", "world_server.lidar._cm"):
        progress.started(name)
        progress.finished(name)
    assert progress.done == 2 and progress.now == "world_server.lidar._cm"


def test_the_warm_up_reaches_every_cached_kernel_of_the_stack():
    """After the suite's first step (``WARM_ARGV``), a launcher finds nothing to compile: a
    kernel the warm-up never reaches would be counted missing, and compiled in workers,
    at every run's start."""
    from deploy.launch.warmup import missing_kernels

    assert missing_kernels() == []
    done = subprocess.run([sys.executable, "-c", "import deploy.cli, deploy.launch.run, deploy.experiments.runner; "
                           "from deploy.launch.warmup import missing_kernels; print(missing_kernels())"],
                          capture_output=True, text=True, timeout=300)
    assert done.stdout.strip() == "[]", done.stdout + done.stderr[-2000:]
