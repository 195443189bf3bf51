"""Perception bench: the per-tick cost of each data-plane stage for one agent (the ego)
in a 40-vehicle ``left_turn`` scene, on real scans, median over ticks.

Every other vehicle's control message is what it would send (its pose and its route
ahead at its speed); the ego encodes the payloads of all its tracked objects (an upper
bound on what it is scheduled to send) and fuses all of the occluder truck's objects.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from protocol.messages import ControlMsg, ObjectMap, Scan
from vehicle_agent.control import VehicleController
from vehicle_agent.dataplane import DataPlane, lane_trajectory
from world_server.scenarios import ScenarioParams
from world_server.sim import Simulation

STAGES = ("grid", "components", "tracking", "visibility", "relevance", "encoding", "fusion")
EGO, TRUCK = 0, 1


def _empty_map() -> ObjectMap:
    z = np.zeros(0, dtype=np.int64)
    return ObjectMap(z, z, np.zeros((0, 2), np.float32), z, np.zeros((0, 0), np.float32), np.zeros((0, 0), np.float32))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="autocast bench perception", description=__doc__)
    ap.add_argument("--quick", action="store_true", help="fewer ticks")
    ap.add_argument("--ticks", type=int, default=None, help="ticks to time (default 60, quick 20)")
    ap.add_argument("--vehicles", type=int, default=40)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    ticks = args.ticks if args.ticks is not None else (20 if args.quick else 60)

    sim = Simulation(ScenarioParams(scenario="left_turn", vehicles=args.vehicles, seed=args.seed, delta_s=0.0,
                                    duration_s=60.0))
    mapmsg = sim.scenario.roadmap.to_msg()
    planes = {vid: DataPlane(sim.mission(vid), mapmsg) for vid in (EGO, TRUCK)}
    ctl = {a.vid: VehicleController(a.spec) for a in sim.scenario.connected()}
    rows: dict[str, list[float]] = {s: [] for s in STAGES}
    n_tracks, n_receivers, n_fused = [], [], []
    for k in range(ticks + 5):  # the first ticks compile / load the numba cache
        views = sim.sense(sim.connected_vids)
        t = sim.t_sim_s
        scans = {vid: Scan(sim.tick, t, vid, v.pose, v.speed_mps, v.range_cm) for vid, v in views.items()}
        msgs = [ControlMsg(sim.tick, t, vid, v.pose, v.speed_mps,
                           lane_trajectory(sim.scenario.actors[vid].route, v.pose, sim.scenario.actors[vid].speed_mps, t),
                           _empty_map(), np.zeros(0, np.int64)) for vid, v in views.items()]
        truck = planes[TRUCK]
        truck_view = truck.perceive(scans[TRUCK])
        shared = truck.payloads(truck_view, [tr.track_id for tr in truck_view.tracks])
        ego = planes[EGO]
        t0 = time.perf_counter()
        view = ego.perceive(scans[EGO])
        ego.neighbors.update(msgs)
        msg = ego.control_message(view, scans[EGO], msgs[EGO].trajectory, heard=[m.vid for m in msgs])
        ego.payloads(view, [int(i) for i in msg.objects.object_id])
        ego.fuse(view, list(shared.values()))
        total_ms = (time.perf_counter() - t0) * 1e3
        if k >= 5:
            for s in STAGES:
                rows[s].append(ego.timings_ms.get(s, 0.0))
            rows.setdefault("total", []).append(total_ms)
            n_tracks.append(len(view.tracks))
            n_receivers.append(len(msg.objects.receivers))
            n_fused.append(len(shared))
        sim.step({vid: ctl[vid].run_step(v.pose, v.speed_mps, sim.scenario.actors[vid].route,
                                         sim.scenario.actors[vid].speed_mps) for vid, v in views.items()})

    print(f"left_turn, {args.vehicles} vehicles, seed {args.seed}: the ego's data plane, {ticks} ticks")
    print(f"objects tracked (median) {np.median(n_tracks):.0f}, receivers in domain {np.median(n_receivers):.0f}, "
          f"objects fused per tick {np.median(n_fused):.0f}")
    print(f"{'stage':<12} {'median ms':>10} {'p90 ms':>8}")
    for s in (*STAGES, "total"):
        print(f"{s:<12} {np.median(rows[s]):>10.2f} {np.percentile(rows[s], 90):>8.2f}")
    print(f"perception: dataplane_ms={np.median(rows['total']):.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
