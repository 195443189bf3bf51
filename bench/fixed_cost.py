"""The fixed cost of a run: its start-up and teardown, wall and CPU.

A run of 0.5 s of sim time (5 lock-step ticks, ``left_turn``, scheme ``autocast``) is
almost all fixed cost. Start-up is from the launch to the world's first tick (its log
line ``N of N agents up; starting``); teardown from the world's outcome (the first
tick plus the ticks' wall time the world reports) to the launcher's exit; CPU is the
whole run's (the launcher and every process it started, reaped: ``wait4``), and the
part of it spent before the first tick and after the world printed its outcome
(each of the run's processes' CPU-time clock and its reaped children's, sampled at
those two log lines: ``processes.manager.process_cpu_s``). Two ways to launch:

- ``cold``: ``autocast run`` as a user types it, a new interpreter that imports the
  stack and warms the numba caches before it starts anything;
- ``warm``: the launcher forked from a parent that has done both already, as
  ``autocast sweep`` starts each of its runs (``processes/factory.py``).

``AUTOCAST_FACTORY=popen`` in the environment starts every process with Popen instead
(and makes ``warm`` the same as ``cold`` without the warm-up): the A/B comparison.

    python -m bench.fixed_cost --vehicles 10,40 --repeat 3 [--pss]

``--pss`` also sums the proportional set size (``/proc/<pid>/smaps_rollup``) of the
run's processes (the launcher and all its descendants) at its first tick.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import re
import secrets
import statistics
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

from processes.manager import process_cpu_s

SIM_S = 0.5
_UP = re.compile(r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}) world INFO \d+ of \d+ agents up; starting$", re.M)


@dataclass(frozen=True, slots=True)
class FixedCost:
    vehicles: int
    mode: str  # cold | warm
    startup_s: float  # launch -> first tick
    teardown_s: float  # outcome -> the launcher's exit
    startup_cpu_s: float  # every process of the run, up to the first tick
    teardown_cpu_s: float  # ... after the world printed its outcome
    cpu_s: float  # the whole run, every process, 5 ticks included
    ticks_wall_s: float
    pss_mib: float | None = None  # the run's processes, summed, at the first tick

    @property
    def fixed_s(self) -> float:
        return self.startup_s + self.teardown_s

    @property
    def fixed_cpu_s(self) -> float:
        return self.startup_cpu_s + self.teardown_cpu_s


def run_argv(vehicles: int, out: Path, run_id: str, warm: bool) -> list[str]:
    return ["run", "--scenario", "left_turn", "--vehicles", str(vehicles), "--scheme", "autocast",
            "--duration", str(SIM_S), "--json", "--out", str(out), "--run-id", run_id, "--scans", "none",
            "--log-level", "INFO", *(["--no-warm-up"] if warm else [])]


def measure(vehicles: int, out: Path, mode: str, pss: bool = False) -> FixedCost:
    """One run; ``warm`` needs an active factory (``warm_parent``) in this process."""
    from processes import factory as process_factory

    run_id = f"fixed-{vehicles}-{mode}-{secrets.token_hex(3)}"
    argv = run_argv(vehicles, out, run_id, warm=mode == "warm")
    log_dir = out / run_id / "logs"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    factory = process_factory.current() if mode == "warm" else None
    stdout = open(out / f"{run_id}.out", "wb+")
    t0_wall, t0 = time.time(), time.monotonic()
    if factory is not None:
        proc = factory.spawn("deploy.cli", argv, stdout=stdout.fileno(), env=env)
    else:
        proc = subprocess.Popen([sys.executable, "-m", "deploy.cli", *argv], stdout=stdout,
                                stderr=subprocess.STDOUT, env=env, start_new_session=True)
    sampler = _Sampler(proc.pid, log_dir / "world.log", pss)
    sampler.start()
    if factory is not None:
        proc.wait()
        cpu_s = proc.cpu_s
    else:
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        cpu_s = usage.ru_utime + usage.ru_stime
    t_exit = time.monotonic()
    sampler.done.set()
    sampler.join()
    stdout.seek(0)
    lines = stdout.read().decode(errors="replace").strip().splitlines()
    stdout.close()
    if not lines or not lines[-1].startswith("{"):
        raise RuntimeError(f"the {vehicles}-vehicle run {run_id} failed (exit {proc.returncode}); see {log_dir}")
    result = json.loads(lines[-1])
    up = _UP.findall((log_dir / "world.log").read_text(errors="replace"))
    if not up:
        raise RuntimeError(f"the {vehicles}-vehicle run {run_id} never ticked; see {log_dir}")
    t_up = datetime.strptime(up[-1], "%Y-%m-%d %H:%M:%S,%f").timestamp() - t0_wall + t0  # on the monotonic clock
    startup_s = t_up - t0
    teardown_s = t_exit - (t_up + result["wall_s"])
    if sampler.cpu_up_s is None or sampler.cpu_outcome_s is None:
        raise RuntimeError(f"the {vehicles}-vehicle run {run_id}: no CPU sample at its first tick or outcome")
    return FixedCost(vehicles, mode, startup_s, teardown_s, sampler.cpu_up_s, cpu_s - sampler.cpu_outcome_s, cpu_s,
                     result["wall_s"], sampler.pss_mib)


class _Sampler(threading.Thread):
    """Watches the world's log: at its first tick, the CPU time (and PSS) of the run's
    processes so far; at its outcome line, their CPU time again."""

    def __init__(self, root: int, world_log: Path, pss: bool) -> None:
        super().__init__(daemon=True)
        self.root, self.world_log, self.pss = root, world_log, pss
        self.cpu_up_s = self.cpu_outcome_s = self.pss_mib = None
        self.done = threading.Event()

    def run(self) -> None:
        deadline = time.monotonic() + 900.0
        while time.monotonic() < deadline and not self.done.is_set():
            try:
                text = self.world_log.read_text(errors="replace")
            except FileNotFoundError:
                text = ""
            if self.cpu_up_s is None and "agents up; starting" in text:
                pids = _tree(self.root)
                self.cpu_up_s = sum(process_cpu_s(p, reaped_children=True) or 0.0 for p in pids)
                if self.pss:
                    self.pss_mib = sum(_pss_kib(p) for p in pids) / 1024
            if self.cpu_up_s is not None and re.search(r"^outcome: ", text, re.M):
                self.cpu_outcome_s = sum(process_cpu_s(p, reaped_children=True) or 0.0 for p in _tree(self.root))
                return
            time.sleep(0.01)


def _tree(root: int) -> list[int]:
    children: dict[int, list[int]] = {}
    for name in os.listdir("/proc"):
        if name.isdigit():
            try:
                with open(f"/proc/{name}/stat") as f:
                    ppid = int(f.read().rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(name))
    out, todo = [], [root]
    while todo:
        pid = todo.pop()
        out.append(pid)
        todo += children.get(pid, [])
    return out


def _pss_kib(pid: int) -> int:
    try:
        with open(f"/proc/{pid}/smaps_rollup") as f:
            return sum(int(line.split()[1]) for line in f if line.startswith("Pss:"))
    except OSError:
        return 0


def warm_parent():
    """A context in which ``measure(..., "warm")`` forks its launchers: this process
    imports the stack and warms the numba caches, then makes the factory (as a sweep does)."""
    from processes import factory as process_factory
    from deploy.launch.warmup import warm_numba_caches
    from deploy.experiments.runner import LAUNCHER_MODULES
    from world_server.scenarios import params_from_dict

    warm_numba_caches(params_from_dict({"scenario": "left_turn", "vehicles": 10}))
    return process_factory.activated(LAUNCHER_MODULES)


def table(costs: list[FixedCost]) -> list[str]:
    """One row per density and mode: medians over the repeats."""
    rows = [f"{'vehicles':>8} {'launch':>6} {'runs':>4} {'start-up':>9} {'teardown':>9} {'fixed':>7} "
            f"{'CPU up':>7} {'CPU down':>8} {'CPU run':>8} {'PSS MiB':>8}"]
    for key in sorted({(c.vehicles, c.mode) for c in costs}):
        mine = [c for c in costs if (c.vehicles, c.mode) == key]
        pss = [c.pss_mib for c in mine if c.pss_mib is not None]
        rows.append(f"{key[0]:>8} {key[1]:>6} {len(mine):>4} {_med(mine, 'startup_s'):>8.2f}s "
                    f"{_med(mine, 'teardown_s'):>8.2f}s {_med(mine, 'fixed_s'):>6.2f}s "
                    f"{_med(mine, 'startup_cpu_s'):>6.2f}s {_med(mine, 'teardown_cpu_s'):>7.2f}s "
                    f"{_med(mine, 'cpu_s'):>7.2f}s " + (f"{statistics.median(pss):>8.0f}" if pss else f"{'-':>8}"))
    return rows


def _med(costs: list[FixedCost], attr: str) -> float:
    return statistics.median(getattr(c, attr) for c in costs)


def run_all(densities: list[int], out: Path, modes: tuple[str, ...] = ("cold", "warm"), repeat: int = 1,
            pss: bool = False) -> list[FixedCost]:
    """Each density, each mode, ``repeat`` times (interleaved: the machine's drift
    spreads over all); one JSON line per run on stderr."""
    out.mkdir(parents=True, exist_ok=True)
    costs = []
    with warm_parent() if "warm" in modes else contextlib.nullcontext():
        for _ in range(repeat):
            for n in densities:
                for mode in modes:
                    costs.append(measure(n, out, mode, pss))
                    print(json.dumps(dataclasses.asdict(costs[-1])), file=sys.stderr, flush=True)
    return costs


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.fixed_cost", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--vehicles", default="5,10,20,40")
    ap.add_argument("--modes", default="cold,warm", help="cold | warm | cold,warm")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--pss", action="store_true", help="sum the run's PSS at its first tick")
    ap.add_argument("--out", default="runs/bench_fixed_cost")
    args = ap.parse_args(argv)
    costs = run_all([int(v) for v in args.vehicles.split(",")], Path(args.out), tuple(args.modes.split(",")),
                    args.repeat, args.pss)
    print("\n".join(table(costs)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
