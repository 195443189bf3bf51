"""The world server's own work per tick, without Zenoh: what its main thread does in
``WorldServer._one_tick`` besides Zenoh's puts and waiting (encode the tick, the truth and
every scan; put each scan into its shared-memory files, as ``protocol.shm.ShmPublisher``
does; cast the scans; step the simulation), in the 40-vehicle ``left_turn`` scene while
every connected vehicle follows its route (``VehicleController``), timed by phase.
``--joined``: each scan encoded whole and then written (as the world did before
``world_server.wire``).

    python -m bench.world_tick --vehicles 40 --ticks 100
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections import defaultdict

import numpy as np

from protocol.codec import encode
from protocol import keys
from protocol.messages import Scan, Tick
from protocol.shm import ShmWriter
from vehicle_agent.control import VehicleController
from world_server import geometry, lidar
from world_server.scenarios import ScenarioParams
from world_server.sim import Simulation
from world_server.wire import encode_parts


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.world_tick", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--vehicles", type=int, default=40)
    parser.add_argument("--scenario", default="left_turn")
    parser.add_argument("--ticks", type=int, default=100)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--joined", action="store_true", help="encode each scan whole, then write it")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(dir="/dev/shm", prefix="world-tick-") as shm_dir:
        return _run(args, shm_dir)


def _run(args, shm_dir: str) -> int:

    sim = Simulation(ScenarioParams(scenario=args.scenario, vehicles=args.vehicles, seed=args.seed,
                                    delta_s=3.0, duration_s=600.0))
    lidar.warm_up(sim.lidar_cfg)
    geometry.warm_up()
    vids = sim.connected_vids
    actors = sim.scenario.actors
    ctl = {v: VehicleController(actors[v].spec) for v in vids}
    writers = {v: ShmWriter(shm_dir, keys.scan("bench", v)) for v in vids}
    ms: dict[str, list[float]] = defaultdict(list)
    for _ in range(args.ticks):
        took: dict[str, float] = defaultdict(float)
        t = time.thread_time()
        encode(Tick(sim.tick, sim.t_sim_s, vids, sim.lights()))
        encode(sim.truth())
        took["tick + truth"] += time.thread_time() - t
        views = {}
        it = sim.sense_each(vids)
        while True:
            t = time.thread_time()
            v = next(it, None)
            took["sense"] += time.thread_time() - t
            if v is None:
                break
            t = time.thread_time()
            scan = Scan(sim.tick, sim.t_sim_s, v.vid, v.pose, v.speed_mps, v.range_cm)
            if args.joined:
                writers[v.vid].write(sim.tick, sim.t_sim_s, encode(scan))
            else:
                writers[v.vid].write_parts(sim.tick, sim.t_sim_s, encode_parts(scan))
            took["put scans"] += time.thread_time() - t
            views[v.vid] = v
        commands = {v: ctl[v].run_step(views[v].pose, views[v].speed_mps, actors[v].route, actors[v].speed_mps)
                    for v in views}
        t = time.thread_time()
        sim.step(commands, fused_xy={sim.scenario.ego.vid: np.zeros((2000, 2))})
        took["step"] += time.thread_time() - t
        for name, s in took.items():
            ms[name].append(s * 1e3)
        ms["total"].append(sum(took.values()) * 1e3)
        if sim.done:
            break
    for writer in writers.values():
        writer.close()
    print(f"{args.scenario}, {len(vids)} connected vehicles, {len(ms['total'])} ticks: median ms per tick")
    for name, values in ms.items():
        print(f"  {name:<14} {np.median(values):8.2f}  (p90 {np.percentile(values, 90):.2f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
