"""Pipeline bench: whole runs through ``autocast run`` (real processes, real Zenoh) at
5, 10, 20 and 40 vehicles, scheme ``autocast``, scenario ``left_turn``.

Per run it reads each agent's own stage timings (the agent prints the median of every
stage when it exits) and the world's real-time factor (sim seconds per wall second,
lock-step). Reported per density: each stage's CPU time per tick (the agent's mean,
median over agents), the agent's whole tick, the ego's (the vehicle that plans a
path every tick) and the RTF. ``proc`` is the agent's whole-process CPU per tick (user
+ system, every thread: also the Zenoh threads that receive and decode its scan and
bundles), measured with getrusage from the end of its first tick to the end of its last.
Then each run's CPU per tick by kind of process (agents, world, proxy, recorder,
launcher with its Zenoh hub: the outcome's ``cpu_ms_per_tick``) and how busy it kept
the cores.

Signing (docs/security.md): the largest density (``--sign-at``; 5 with ``--quick``)
runs once more with ``--sign``; the table compares the two runs' agents, and
``sign<N>_pct`` is what signing and verifying cost an agent, in per cent of its
whole-process CPU per tick without: how much more its ``security`` (sealing, checking
the heard control messages and the decoded payloads), ``encoding`` (a signed control
message vouches for every object's payload, so every one is encoded) and ``link``
stages (decoding the heard control messages moves from it to ``security``) take.
The agents of a run on one host share what they verified
(``protocol.security.Verdicts``): an agent's ``security`` stage holds its share of the
host's verifications, and the few that get a bundle first in an interval carry more of
it that interval (each agent's mean over ticks evens that out).
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np

from bench import fixed_cost

STAGES = ("perception", "spatial_reasoning", "schedule", "encoding", "link", "security", "fusion", "planning",
          "control")
_TIMINGS = re.compile(r"^agent_timings (\{.*\})$", re.M)


def run_once(vehicles: int, duration_s: float, out: Path, scheme: str,
             sign: bool = False) -> tuple[dict, list[dict], dict]:
    cmd = [sys.executable, "-m", "deploy.cli", "run", "--scenario", "left_turn", "--vehicles", str(vehicles),
           "--scheme", scheme, "--duration", str(duration_s), "--delta", "3", "--json", "--out", str(out),
           "--scans", "none", "--log-level", "WARNING", "--sign" if sign else "--no-sign"]
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


def _median_of(per_agent: list[dict], key: str) -> float:
    return float(np.median([a.get(key, 0.0) for a in per_agent])) if per_agent else 0.0


MACHINE_ROLES = ("agents", "world", "proxy", "recorder", "launcher")


def machine_table(rows: list[tuple]) -> list[str]:
    """Each run's CPU per tick by kind of process (the outcome's ``cpu_ms_per_tick``:
    from the first tick to each process's exit), the tick's wall time, and how busy
    that kept the machine's cores."""
    out = ["the whole machine: CPU ms per tick of each kind of process (first tick to its exit), the tick's wall "
           "time, and all of it over the cores' time",
           f"{'vehicles':>8} " + " ".join(f"{c:>8}" for c in (*MACHINE_ROLES, "all", "tick ms", "busy"))]
    for n, _, _, outcome in rows:
        cpu, ticks = outcome.get("cpu_ms_per_tick"), outcome.get("ticks") or 0
        if not cpu or not ticks:
            out.append(f"{n:>8} (no figures: the run's processes were not forked from its factory)")
            continue
        tick_ms = outcome["wall_s"] * 1e3 / ticks
        busy = cpu["all"] / (tick_ms * outcome.get("cores", 1))
        out.append(f"{n:>8} " + " ".join(f"{cpu.get(r, 0.0):>8.1f}" for r in (*MACHINE_ROLES, "all"))
                   + f" {tick_ms:>8.1f} {busy:>7.0%}")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="autocast bench pipeline", description=__doc__)
    ap.add_argument("--quick", action="store_true", help="5 and 10 vehicles, 3 s of sim time each")
    ap.add_argument("--vehicles", default=None, help="comma-separated densities (default 5,10,20,40)")
    ap.add_argument("--duration", type=float, default=None, help="sim seconds per run (default 8, quick 3)")
    ap.add_argument("--scheme", default="autocast")
    ap.add_argument("--out", default="runs/bench_pipeline")
    ap.add_argument("--sign-at", type=int, default=None,
                    help="the density run again with signing (default: the largest; 5 with --quick)")
    args = ap.parse_args(argv)
    densities = [int(v) for v in (args.vehicles or ("5,10" if args.quick else "5,10,20,40")).split(",")]
    duration = args.duration or (3.0 if args.quick else 8.0)
    sign_at = args.sign_at or (min(densities) if args.quick else max(densities))
    if sign_at not in densities:
        ap.error(f"--sign-at {sign_at} is not one of the densities {densities}")

    rows, rtf, agent_ms, plan_ms, proc = [], {}, [], [], {}
    for n in densities:
        outcome, per_agent, ego = run_once(n, duration, Path(args.out), args.scheme)
        rtf[n] = outcome["realtime_factor"]
        rows.append((n, per_agent, ego, outcome))
        agent_ms.append(_median_of(per_agent, "cpu"))
        plan_ms.append(ego.get("planning_cpu", 0.0))
        proc[n] = _median_of(per_agent, "proc_cpu")

    print(f"left_turn, scheme {args.scheme}, {duration:g} s of sim time per run, lock-step")
    print("per-agent CPU ms per tick by stage (each agent's mean over ticks; the median over agents), then the "
          "agent's whole tick (median and mean), the ego's, the channel wait (wall) and the run")
    cols = [s[:10] for s in STAGES] + ["cpu", "cpu mean", "ego cpu", "ego plan", "chan wait", "proc", "dead", "RTF"]
    print(f"{'vehicles':>8} {'agents':>6} " + " ".join(f"{c:>10}" for c in cols))
    signed = run_once(sign_at, duration, Path(args.out), args.scheme, sign=True)
    rows.append((f"{sign_at}+sign", signed[1], signed[2], signed[0]))
    for n, per_agent, ego, outcome in rows:
        vals = [_median_of(per_agent, f"{s}_cpu_mean") for s in STAGES]
        vals += [_median_of(per_agent, "cpu"), _median_of(per_agent, "cpu_mean"), ego.get("cpu", 0.0),
                 ego.get("planning_cpu", 0.0), _median_of(per_agent, "channel_wait"), _median_of(per_agent, "proc_cpu")]
        print(f"{n:>8} {len(per_agent):>6} " + " ".join(f"{v:>10.2f}" for v in vals)
              + f" {len(outcome['dead_agents']):>10} {outcome['realtime_factor']:>10.3f}")
    print("CPU is the agent's main-thread time (its own cost, free of the waits for a core when more agents than "
          "cores run); link is encoding, publishing and decoding the channel's messages; agent_ms below is the "
          "median over agents of their median tick, plan_ms the ego's median planning")
    print("\n".join(machine_table(rows)))
    costs = fixed_cost.run_all(densities, Path(args.out))
    print(f"the fixed cost of a run ({fixed_cost.SIM_S:g} s of sim time): start-up to the first tick, teardown from "
          "the outcome to the launcher's exit, wall; CPU of every process of the run before the first tick, after "
          "the outcome, in all; cold: autocast run typed in a shell, warm: forked from a warm parent, as a sweep "
          "runs it (bench/fixed_cost.py)")
    print("\n".join(fixed_cost.table(costs)))
    plain_row = next(r for r in rows if r[0] == sign_at)[1]
    touched = ("security", "encoding", "link")  # decoding the heard control messages moves from link to security
    extra = max(0.0, sum(_median_of(signed[1], f"{s}_cpu_mean") - _median_of(plain_row, f"{s}_cpu_mean")
                         for s in touched))
    sign_pct = 100.0 * extra / max(proc[sign_at], 1e-9)
    print(f"signing at {sign_at} vehicles: security + encoding + link stages {extra:.2f} ms more per agent and "
          f"tick = {sign_pct:.1f}% of the agent's whole-process CPU without ({proc[sign_at]:.2f} ms); whole "
          f"process {proc[sign_at]:.2f} -> {_median_of(signed[1], 'proc_cpu'):.2f} ms (the two runs ran one after "
          "the other: under load their difference is noisier than the stages')")
    warm = {c.vehicles: c.fixed_s for c in costs if c.mode == "warm"}
    rtf_keys = " ".join(f"rtf{n}={rtf[n]:.3f}" for n in densities)
    proc_keys = " ".join(f"proc{n}_ms={proc[n]:.2f}" for n in densities if n in (10, 40))
    print(f"pipeline: agent_ms={np.median(agent_ms):.2f} plan_ms={np.median(plan_ms):.2f} {rtf_keys} "
          f"startup{densities[-1]}_s={warm[densities[-1]]:.2f} {proc_keys} sign{sign_at}_pct={sign_pct:.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
