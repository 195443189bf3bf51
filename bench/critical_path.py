"""Where a lock-step interval's wall time goes: one run with phase marks
(``protocol/phases.py``), and per event the medians over ticks of when the first and
the last process passed it, in ms after the world's ``Tick``; then what the agents'
main threads spent between their marks (CPU: the stage's own cost, free of the waits
for a core).

    python -m bench.critical_path --vehicles 40
    python -m bench.critical_path --vehicles 10 --scheme agnostic --duration 4

The run: ``autocast run --scenario SCENARIO --vehicles N --scheme SCHEME --duration D
--delta 3 --scans none``. A phase of the interval is as long as the CPU every process
spends in it over the machine's cores, plus what runs in no phase: compare the sums with the tick (docs/
performance.md, "Where a tick's wall time goes"). Linux or any system with one
monotonic clock for all processes; one host only.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from protocol import phases

EVENTS = ("world.tick", "agent.scan", "world.scans_sent", "agent.ctrl_sent", "proxy.ctrl_closed",
          "proxy.ctrl_bundle_sent", "agent.ctrl_bundle", "agent.data_sent", "proxy.data_closed",
          "proxy.data_bundle_sent", "agent.data_bundle", "agent.cmd_sent", "world.commands_in", "world.stepped")
# an agent's main thread between two of its marks: (label, from, to, only the agents that take the data bundle)
SPANS = (("scan -> control message out (perception, spatial reasoning)", "agent.scan", "agent.ctrl_sent", None),
         ("control bundle in -> data out (reading it, the schedule, payloads)", "agent.ctrl_bundle", "agent.data_sent",
          None),
         ("data bundle in -> command out (fusion, planning), fusing agents", "agent.data_bundle", "agent.cmd_sent", True),
         ("data out -> command out (planning), the others", "agent.data_sent", "agent.cmd_sent", False))

Marks = dict[int, dict[str, dict[str, tuple[float, float]]]]  # tick -> process file -> event -> (time, thread CPU)


def run_marked(vehicles: int, scheme: str, scenario: str, duration_s: float, out: Path, marks: Path) -> dict:
    """One ``autocast run`` with its phase marks in ``marks``; its outcome record."""
    cmd = [sys.executable, "-m", "deploy.cli", "run", "--scenario", scenario, "--vehicles", str(vehicles),
           "--scheme", scheme, "--duration", str(duration_s), "--delta", "3", "--json", "--out", str(out),
           "--scans", "none", "--log-level", "WARNING"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=1800, env=dict(os.environ, **{phases.ENV: str(marks)}))
    lines = proc.stdout.strip().splitlines()
    if not lines or not lines[-1].startswith("{"):
        raise RuntimeError(f"the run failed (exit {proc.returncode}):\n{proc.stderr[-2000:]}")
    return json.loads(lines[-1])


def read_marks(marks: Path) -> Marks:
    out: Marks = collections.defaultdict(lambda: collections.defaultdict(dict))
    for path in sorted(marks.glob("*.txt")):
        for line in path.read_text().splitlines():
            event, tick, t, cpu = line.split()
            out[int(tick)][path.stem][event] = (float(t), float(cpu))
    return out


def summarize(marks: Marks, skip: int) -> dict:
    """Medians over the ticks from ``skip`` on that the world stepped (and the next
    tick began): each event's first and last time after ``world.tick``, the tick, and
    each span's per-agent CPU (median over agents and ticks) and sum over agents."""
    starts = {k: e["world.tick"][0] for k, procs in marks.items() for e in procs.values() if "world.tick" in e}
    ticks = [k for k in sorted(starts) if k >= skip and k + 1 in starts]
    if not ticks:
        raise ValueError(f"no complete tick from tick {skip} on")
    first, last = collections.defaultdict(list), collections.defaultdict(list)
    span_cpu = collections.defaultdict(list)
    span_sum = collections.defaultdict(list)
    for k in ticks:
        t0 = starts[k]
        seen = collections.defaultdict(list)
        sums = collections.Counter()
        for e in marks[k].values():
            for event, (t, _) in e.items():
                seen[event].append((t - t0) * 1e3)
            for label, a, b, fusing in SPANS:
                if a in e and b in e and (fusing is None or fusing == ("agent.data_bundle" in e)):
                    cpu = (e[b][1] - e[a][1]) * 1e3
                    span_cpu[label].append(cpu)
                    sums[label] += cpu
        for event, times in seen.items():
            first[event].append(min(times))
            last[event].append(max(times))
        for label, _, _, _ in SPANS:
            span_sum[label].append(sums[label])
    return {"ticks": (ticks[0], ticks[-1]), "tick_ms": statistics.median((starts[k + 1] - starts[k]) * 1e3 for k in ticks),
            "events": {e: (statistics.median(first[e]), statistics.median(last[e])) for e in EVENTS if e in first},
            "spans": {label: (statistics.median(span_cpu[label]) if span_cpu[label] else 0.0,
                              len(span_cpu[label]) / len(ticks), statistics.median(span_sum[label]))
                      for label, _, _, _ in SPANS}}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.critical_path", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--vehicles", type=int, default=40)
    ap.add_argument("--scheme", default="autocast", choices=("autocast", "agnostic"),
                    help="a scheme with both channel phases")
    ap.add_argument("--scenario", default="left_turn")
    ap.add_argument("--duration", type=float, default=8.0, help="sim seconds")
    ap.add_argument("--skip", type=int, default=5, help="ticks left out at the start")
    ap.add_argument("--out", default="runs/bench_critical_path")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="autocast-phases-") as tmp:
        outcome = run_marked(args.vehicles, args.scheme, args.scenario, args.duration, Path(args.out), Path(tmp))
        s = summarize(read_marks(Path(tmp)), args.skip)
    print(f"{args.scenario}, {args.vehicles} vehicles, scheme {args.scheme}, lock-step, RTF "
          f"{outcome['realtime_factor']}; medians over ticks {s['ticks'][0]}-{s['ticks'][1]}, ms after the world's Tick")
    print(f"{'event':<24} {'first':>8} {'last':>8}")
    for event, (lo, hi) in s["events"].items():
        print(f"{event:<24} {lo:8.1f} {hi:8.1f}")
    print(f"{'tick':<24} {'':>8} {s['tick_ms']:8.1f}")
    print("an agent's main thread between its marks, CPU ms: per agent (median), agents a tick (mean), all agents a tick")
    for label, (each, per_tick, total) in s["spans"].items():
        print(f"  {label:<66} {each:6.2f} {per_tick:5.1f} {total:7.1f}")
    agents = sum(total for _, _, total in s["spans"].values())
    print(f"critical_path: vehicles={args.vehicles} tick_ms={s['tick_ms']:.1f} agents_main_ms={agents:.1f} "
          f"ctrl_closed_ms={s['events']['proxy.ctrl_closed'][0]:.1f} data_closed_ms={s['events']['proxy.data_closed'][0]:.1f} "
          f"commands_in_ms={s['events']['world.commands_in'][0]:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
