"""Perception's sub-stages (grid, components, tracking) in a replay of a logged run.

    python -m bench.perception_stages runs/r40 [--vids 0,7]

Replays every agent as ``python -m vehicle_agent.replay`` does (byte for byte, the
same count of different agents), and prints the mean thread CPU per tick of each of
the data plane's perception timers, over all agents and ticks but each agent's first.
"""

from __future__ import annotations

import argparse
import collections
import sys
import time
from pathlib import Path

from vehicle_agent import dataplane, replay


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.perception_stages")
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("--vids", default=None)
    args = ap.parse_args(argv)
    path = args.run_dir if args.run_dir.suffix == ".mcap" else args.run_dir / "run.mcap"
    log = replay.Log.read(path)
    vids = [int(v) for v in args.vids.split(",")] if args.vids else log.vids_with_scans()
    totals: collections.Counter = collections.Counter()
    counts: collections.Counter = collections.Counter()
    original = dataplane.DataPlane.perceive

    def perceive(self, scan, extra_world=None):
        view = original(self, scan, extra_world)
        if scan.tick > 0:
            for k, v in self.timings_ms.items():
                if k.endswith("_cpu"):
                    totals[k[:-4]] += v
                    counts[k[:-4]] += 1
        return view

    class ThreadTimed(dataplane._Timed):  # thread CPU time, not wall time
        __slots__ = ()

        def __enter__(self) -> None:
            self.t0 = time.thread_time()

        def __exit__(self, exc_type, exc, tb) -> None:
            if exc_type is None:
                self.timings_ms[self.stage + "_cpu"] = (time.thread_time() - self.t0) * 1e3

    timed, snap = dataplane._Timed, dataplane.LaneDirections.snap

    def timed_snap(self, tracks):
        t0 = time.thread_time()
        snap(self, tracks)
        totals["snap"] += (time.thread_time() - t0) * 1e3

    dataplane.LaneDirections.snap = timed_snap
    dataplane.DataPlane.perceive, dataplane._Timed = perceive, ThreadTimed
    bad = 0
    for vid in vids:
        bad += bool(replay.replay(log, vid).mismatches)
    dataplane.DataPlane.perceive, dataplane._Timed, dataplane.LaneDirections.snap = original, timed, snap
    n = max(counts.values()) if counts else 1
    print(" ".join(f"{k}={totals[k] / n:.3f}" for k in sorted(totals)), f"| agents={len(vids)} different={bad}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
