"""An agent's whole-process CPU per tick in a live run, measured from outside, so that
any two versions of the code compare the same way (back to back).

The agents' own exit figures (``proc_cpu``, what ``autocast bench pipeline`` reports)
exist only in versions that print them. This bench reads every agent process's user +
system CPU (its CPU-time clock: ``processes.manager.process_cpu_s``) twice, ``--window`` seconds apart, starting
``--settle`` seconds after the world's first tick (its log line ``N of N agents up;
starting``), and divides by the ticks in that window (the window times the run's
lock-step real-time factor over 0.1 s). The run: ``autocast run --scenario left_turn
--scheme autocast --delta 3 --scans none``, long enough for the window.

``--against DIR`` runs the same measurement in another checkout (``git worktree add
DIR REV``; warm its numba caches with one run first) alternately with this one, A B A
B, and prints each round's ratio (this over that): the machine's speed drifts, pairs
do not.

    python -m bench.agent_cpu --vehicles 40 --rounds 2 --against ../base

Linux only (``/proc``).
"""

from __future__ import annotations

import argparse
import json
import os
import secrets
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from processes.manager import has_argument, process_cpu_s

HERE = Path(__file__).resolve().parent.parent  # this checkout
UP_LINE = "agents up; starting"


@dataclass(frozen=True, slots=True)
class Sample:
    tree: str
    vehicles: int
    agents: int  # agent processes seen in both snapshots
    rtf: float  # the run's real-time factor (lock-step, whole run)
    ticks: float  # ticks in the window
    agent_ms: float  # whole-process CPU per agent and tick


def _agent_cpu_s(run_id: str) -> dict[int, float]:
    """user + system CPU seconds of every agent process of ``run_id``, by pid."""
    out = {}
    for pid in map(int, filter(str.isdigit, os.listdir("/proc"))):
        if has_argument(pid, "vehicle_agent") and has_argument(pid, run_id):
            cpu = process_cpu_s(pid)
            if cpu is not None:  # not gone meanwhile
                out[pid] = cpu
    return out


def measure(tree: Path, vehicles: int, out: Path, settle_s: float, window_s: float, duration_s: float) -> Sample:
    run_id = f"agentcpu-{vehicles}-{secrets.token_hex(3)}"
    env = dict(os.environ, PYTHONPATH=str(tree))
    argv = [sys.executable, "-m", "deploy.cli", "run", "--scenario", "left_turn", "--vehicles", str(vehicles),
            "--scheme", "autocast", "--duration", str(duration_s), "--delta", "3", "--json", "--out", str(out),
            "--run-id", run_id, "--scans", "none", "--log-level", "INFO"]
    proc = subprocess.Popen(argv, cwd=tree, env=env, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    world_log = out / run_id / "logs" / "world.log"
    try:
        while proc.poll() is None:
            if world_log.exists() and UP_LINE in world_log.read_text(errors="replace"):
                break
            time.sleep(0.1)
        time.sleep(settle_s)
        before, t0 = _agent_cpu_s(run_id), time.monotonic()
        time.sleep(window_s)
        after, t1 = _agent_cpu_s(run_id), time.monotonic()
        stdout, _ = proc.communicate(timeout=1800)
    finally:
        if proc.poll() is None:
            proc.terminate()
            proc.wait()
    lines = stdout.strip().splitlines()
    if not lines or not lines[-1].startswith("{"):
        raise RuntimeError(f"the run {run_id} in {tree} failed (exit {proc.returncode}); see {out / run_id}")
    result = json.loads(lines[-1])
    both = [pid for pid in before if pid in after]
    if len(both) != vehicles or settle_s + window_s > result["wall_s"]:
        raise RuntimeError(f"the run {run_id}: {len(both)} of {vehicles} agents through the window, "
                           f"{result['wall_s']:.1f} s of ticks; raise --duration")
    ticks = (t1 - t0) * result["realtime_factor"] / 0.1
    cpu_s = sum(after[pid] - before[pid] for pid in both)
    return Sample(str(tree), vehicles, len(both), result["realtime_factor"], ticks, cpu_s / len(both) / ticks * 1e3)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.agent_cpu", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--vehicles", type=int, default=40)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--against", type=Path, default=None, metavar="DIR", help="another checkout, measured alternately")
    ap.add_argument("--settle", type=float, default=2.0, help="seconds after the first tick before the window")
    ap.add_argument("--window", type=float, default=5.0, help="seconds between the two snapshots")
    ap.add_argument("--duration", type=float, default=30.0, help="the runs' sim-time limit (they end once judged)")
    ap.add_argument("--out", type=Path, default=Path("runs/bench_agent_cpu"))
    args = ap.parse_args(argv)
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    trees = [HERE] + ([args.against.resolve()] if args.against else [])
    got: dict[str, list[Sample]] = {str(t): [] for t in trees}
    for r in range(args.rounds):
        for tree in trees:
            s = measure(tree, args.vehicles, out, args.settle, args.window, args.duration)
            got[str(tree)].append(s)
            print(f"round {r + 1}: {tree}: {s.agent_ms:.2f} ms per agent and tick ({s.agents} agents, "
                  f"{s.ticks:.0f} ticks, RTF {s.rtf:.3f})", flush=True)
    mine = [s.agent_ms for s in got[str(HERE)]]
    line = f"agent_cpu: vehicles={args.vehicles} agent_ms={statistics.median(mine):.2f}"
    if args.against:
        theirs = [s.agent_ms for s in got[str(trees[1])]]
        ratios = [a / b for a, b in zip(mine, theirs)]
        print("ratios this / that, round by round: " + ", ".join(f"{x:.2f}" for x in ratios))
        line += f" against_ms={statistics.median(theirs):.2f} ratio={statistics.median(ratios):.2f}"
    print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
