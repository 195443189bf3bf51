"""LiDAR bench: one 64 x 1800 scan, and the scans of all connected vehicles of a tick,
in the real 40-vehicle ``left_turn`` scene (corner buildings included) while every
vehicle drives its route, so the boxes move every tick.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from vehicle_agent.control import VehicleController
from world_server import lidar
from world_server.scenarios import ScenarioParams
from world_server.sim import Simulation


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="autocast bench lidar", description=__doc__)
    parser.add_argument("--quick", action="store_true", help="fewer repetitions (a few seconds)")
    parser.add_argument("--ticks", type=int, default=None, help="ticks to time (default 60, quick 20)")
    parser.add_argument("--vehicles", type=int, default=40)
    parser.add_argument("--scenario", default="left_turn")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    ticks = args.ticks if args.ticks is not None else (20 if args.quick else 60)
    reps = 100 if args.quick else 1000

    sim = Simulation(ScenarioParams(scenario=args.scenario, vehicles=args.vehicles, seed=args.seed,
                                    delta_s=3.0, duration_s=60.0))
    cfg = sim.lidar_cfg
    vids = np.array(sim.connected_vids)
    ctl = {int(v): VehicleController(sim.scenario.actors[v].spec) for v in vids}

    def scene():
        boxes = np.vstack([sim.physics.boxes(sim.heights_m), sim.scenario.roadmap.buildings])
        return boxes, sim.physics.poses()[vids], sim.mount_m[vids]

    boxes, poses, heights = scene()
    t0 = time.perf_counter()
    lidar.scan(boxes, poses[0], heights[0], cfg, int(vids[0]))  # compiles or loads the numba cache
    first_call_ms = (time.perf_counter() - t0) * 1e3
    lidar.scan_many(boxes, poses, heights, cfg, vids)  # builds the ground table of every mount height

    scan_ms = []
    for _ in range(reps):
        t0 = time.perf_counter()
        lidar.scan(boxes, poses[0], heights[0], cfg, int(vids[0]))
        scan_ms.append((time.perf_counter() - t0) * 1e3)

    tick_ms, n_points, n_object_points = [], [], []
    for _ in range(ticks):
        boxes, poses, heights = scene()
        t0 = time.perf_counter()
        out = lidar.scan_many(boxes, poses, heights, cfg, vids)
        tick_ms.append((time.perf_counter() - t0) * 1e3)
        n_points += [len(sweep.labels) for sweep in out]
        n_object_points += [int(np.count_nonzero(sweep.labels >= 0)) for sweep in out]
        views = sim.sense(vids.tolist())  # untimed: drive on so the scene changes
        sim.step({v: ctl[v].run_step(views[v].pose, views[v].speed_mps, sim.scenario.actors[v].route,
                                     sim.scenario.actors[v].speed_mps) for v in views})

    scan_med, tick_med = float(np.median(scan_ms)), float(np.median(tick_ms))
    n_trucks = sum(a.kind == "truck" for a in sim.scenario.connected())
    rows = [
        ("scene", f"{args.scenario}, {len(vids)} connected vehicles ({n_trucks} trucks), "
                  f"{len(sim.scenario.roadmap.buildings)} buildings, seed {args.seed}"),
        ("lidar", f"{cfg.beams} x {cfg.azimuth_steps} rays, range {cfg.range_m:g} m"),
        ("first call (numba start-up + cache load)", f"{first_call_ms:9.1f} ms"),
        ("one scan, median", f"{scan_med:9.3f} ms  (p90 {np.percentile(scan_ms, 90):.3f}, n={reps})"),
        (f"tick of {len(vids)} scans, median", f"{tick_med:9.2f} ms  (p90 {np.percentile(tick_ms, 90):.2f}, "
                                               f"n={ticks})"),
        ("per scan within a tick", f"{tick_med / len(vids):9.3f} ms"),
        ("points per scan, median", f"{np.median(n_points):9.0f}  (min {min(n_points)}, max {max(n_points)})"),
        ("object points per scan, median", f"{np.median(n_object_points):9.0f}"),
    ]
    width = max(len(name) for name, _ in rows)
    for name, value in rows:
        print(f"{name:<{width}}  {value}")
    print(f"lidar: scan_ms={scan_med:.2f} tick{len(vids)}_ms={tick_med:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
