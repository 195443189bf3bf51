"""Pipeline bench: whole runs through ``autocast run`` (real processes, real Zenoh) at
5, 10, 20 and 40 vehicles, scheme ``autocast``, scenario ``left_turn``.

Per run it reads each agent's own stage timings (the agent prints the median of every
stage when it exits) and the world's real-time factor (sim seconds per wall second,
lock-step). Reported per density: the median over agents of their median per-tick
compute time (without the waits for the channel's phases), the ego's (the vehicle
that plans a path every tick) and the RTF.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np

STAGES = ("perception", "spatial_reasoning", "schedule", "fusion", "planning", "control", "compute", "channel_wait",
          "cpu")
_TIMINGS = re.compile(r"^agent_timings (\{.*\})$", re.M)


def run_once(vehicles: int, duration_s: float, out: Path, scheme: str) -> tuple[dict, list[dict], dict]:
    cmd = [sys.executable, "-m", "deploy.cli", "run", "--scenario", "left_turn", "--vehicles", str(vehicles),
           "--scheme", scheme, "--duration", str(duration_s), "--delta", "3", "--json", "--out", str(out),
           "--scans", "none", "--log-level", "WARNING"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=1800)
    lines = proc.stdout.strip().splitlines()
    if not lines or not lines[-1].startswith("{"):
        raise RuntimeError(f"run with {vehicles} vehicles failed (exit {proc.returncode}):\n{proc.stderr[-2000:]}")
    outcome = json.loads(lines[-1])
    logs = Path(outcome["run_dir"]) / "logs"
    per_agent, ego = [], {}
    for log_file in sorted(logs.glob("agent*.log")):
        found = _TIMINGS.findall(log_file.read_text(errors="replace"))
        if found:
            t = json.loads(found[-1])
            per_agent.append(t)
            if log_file.stem == "agent0":
                ego = t
    return outcome, per_agent, ego


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="autocast bench pipeline", description=__doc__)
    ap.add_argument("--quick", action="store_true", help="5 and 10 vehicles, 3 s of sim time each")
    ap.add_argument("--vehicles", default=None, help="comma-separated densities (default 5,10,20,40)")
    ap.add_argument("--duration", type=float, default=None, help="sim seconds per run (default 8, quick 3)")
    ap.add_argument("--scheme", default="autocast")
    ap.add_argument("--out", default="runs/bench_pipeline")
    args = ap.parse_args(argv)
    densities = [int(v) for v in (args.vehicles or ("5,10" if args.quick else "5,10,20,40")).split(",")]
    duration = args.duration or (3.0 if args.quick else 8.0)

    rows, rtf, agent_ms, plan_ms = [], {}, [], []
    for n in densities:
        outcome, per_agent, ego = run_once(n, duration, Path(args.out), args.scheme)
        med = {s: float(np.median([a.get(s, 0.0) for a in per_agent])) for s in STAGES}
        rtf[n] = outcome["realtime_factor"]
        rows.append((n, len(per_agent), med, ego, outcome))
        agent_ms.append(med["cpu"])
        plan_ms.append(ego.get("planning", 0.0))

    print(f"left_turn, scheme {args.scheme}, {duration:g} s of sim time per run, lock-step; "
          "per-agent median per-tick ms (median over agents) | the ego's")
    print(f"{'vehicles':>8} {'agents':>6} " + " ".join(f"{s[:10]:>10}" for s in STAGES) + f" {'ego cpu':>9} "
          f"{'ego plan':>8} {'dead':>5} {'RTF':>6}")
    for n, k, med, ego, outcome in rows:
        print(f"{n:>8} {k:>6} " + " ".join(f"{med[s]:>10.2f}" for s in STAGES)
              + f" {ego.get('cpu', 0):>9.2f} {ego.get('planning', 0):>8.2f} {len(outcome['dead_agents']):>5} "
              f"{outcome['realtime_factor']:>6.3f}")
    print("stages, compute (wall time outside the channel's phases) and channel_wait are wall clock, inflated when "
          "more agents than cores run at once; cpu is the agent's main-thread CPU time per tick, its own cost: "
          "agent_ms below is its median over agents")
    rtf_keys = " ".join(f"rtf{n}={rtf[n]:.3f}" for n in densities)
    print(f"pipeline: agent_ms={np.median(agent_ms):.2f} plan_ms={np.median(plan_ms):.2f} {rtf_keys}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
