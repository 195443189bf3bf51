"""``autocast sweep``: the paper's experiments as a matrix of ``autocast run``s.

A sweep is the product scenarios x collider speeds x intersection deltas x vehicle
counts x schemes x seeds, from a preset (``paper``, ``smoke``) or a TOML/JSON file,
narrowed by flags. Each run is ``python -m deploy.cli run ... --json`` in its own
process group, so a run that crashes is one failed record, not a failed sweep; the
launchers are forked from one warm parent kept for the whole sweep (``processes/factory.py``:
no run imports the stack or loads a kernel again). Every
finished run, judged or failed, is appended to ``<sweep dir>/results.jsonl`` as one
JSON line (flushed and fsynced): the same command again skips every run already
recorded, so a sweep stopped at any point resumes where it stopped.

Outputs in the sweep directory: ``plan.json`` (the matrix, settings, estimate),
``results.jsonl``, ``runs/<run id>/`` (each run's own outputs, see docs/running.md;
``--runs-dir`` puts them elsewhere), ``logs/<run id>.out|.err`` (each launcher's stdout
and stderr). Exit code: 0 every planned run judged, 1 some run failed (recorded with
its error), 2 bad input, 3 the cluster's scheduler was lost (``--cluster``), 4 the
disk nearly full (``--min-free-mb``: no run started below it, those running finished), 130
interrupted (Ctrl-C: the running launchers stop their processes; nothing is left).
With ``--cluster`` each run is a task on a Dask worker instead (``deploy/experiments/cluster.py``).
"""

from __future__ import annotations

import argparse
import fcntl
import json
import logging
import signal
import statistics
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any, NoReturn

from deploy.experiments.plan import (AXES, AXIS_LABEL, EXIT_BAD_INPUT, EXIT_INTERRUPTED, EXIT_OK, LOCK,
                                      MIN_CALIBRATION_RUNS, PLAN, PRESETS, RESULTS, RunKey, SweepError, SweepSpec, _duration,
                                      calibration, check_scenarios, estimate_run_s, estimate_wall_s, expand, latest, load_file,
                                      model_suffix, narrowed, preset_values, read_results, spec_from, sweep_cost_s,
                                      time_limit_s)
from deploy.experiments.runner import LAUNCHER_MODULES, Progress, Sweep, _exit_code, finish_sweep, git_revision, warm_up
from processes import factory as process_factory

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------- CLI


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        self.print_usage(sys.stderr)
        self.exit(EXIT_BAD_INPUT, f"error: {message}\n")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = _Parser(prog="autocast sweep", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    src = ap.add_mutually_exclusive_group()
    src.add_argument("--preset", help=f"one of {', '.join(PRESETS)}")
    src.add_argument("--file", type=Path, help="a TOML or JSON file of fields (docs/experiments.md)")
    nar = ap.add_argument_group("narrow the matrix (comma-separated; replaces the preset's axis)")
    nar.add_argument("--scenarios")
    nar.add_argument("--collider-speeds", metavar="KMH,...")
    nar.add_argument("--deltas", metavar="S,...", help="--deltas=-1,0,1: a list starting with a minus needs the =")
    nar.add_argument("--vehicles", metavar="N,...")
    nar.add_argument("--schemes")
    nar.add_argument("--seeds", metavar="N,...")
    nar.add_argument("--duration", metavar="S",
                     help="sim seconds per run (default: each scenario's own; overtaking 40, left_turn 30, red_light 40)")
    nar.add_argument("--timeout-s", metavar="S", help="wall-clock limit per run (default 900)")
    nar.add_argument("--agent-timeout-s", metavar="S", help="wall time an agent may take for one tick before the "
                     "world declares it dead (default 10; raise it on a loaded machine)")
    nar.add_argument("--scans", help="LiDAR scans each run's recorder keeps: none (default) | ego | all")
    nar.add_argument("--json-mirror", action="store_true",
                     help="each run's MCAP gets the JSON mirror too, for Foxglove (default: without; "
                          "`autocast export --foxglove` writes it for one run later)")
    nar.add_argument("--mcap-limit-mb", metavar="MB", help="delete a run's MCAP beyond this size (default 200)")
    nar.add_argument("--model", help="the modelling profile of every run: ours (default) | paper (docs/models.md)")
    nar.add_argument("--model-set", action="append", default=[], metavar="KEY=VALUE",
                     help="change one setting of the model (repeatable)")
    ap.add_argument("--out", type=Path, help="the sweep directory (default runs/sweeps/<preset or file name>); "
                    "the same directory again resumes")
    ap.add_argument("--jobs", type=int, default=1, help="runs at once (default 1, see docs/experiments.md)")
    ap.add_argument("--vehicle-budget", type=int, default=20,
                    help="with --jobs > 1: connected vehicles of all running runs together (default 20)")
    ap.add_argument("--min-free-mb", type=float, default=1000.0, metavar="MB",
                    help="start no run while the runs' file system has less free (default 1000; exit 4, "
                    "the same command resumes)")
    ap.add_argument("--retry-failed", action="store_true", help="run again the keys whose last record failed")
    ap.add_argument("--runs-dir", type=Path, help="where the runs write their outputs (default <out>/runs; with "
                    "--cluster a directory every worker can reach at the same path)")
    ap.add_argument("--cluster", metavar="tcp://HOST:8786", help="submit each run to this Dask scheduler (an "
                    "address, or a scheduler file) instead of running it here (pip install 'autocast-py[cluster]'; "
                    "docs/experiments.md); the workers' resources replace --jobs and --vehicle-budget")
    ap.add_argument("--dry-run", action="store_true", help="print the plan and the estimated wall time; run nothing")
    ap.add_argument("--log-level", default="INFO")
    return ap.parse_args(argv)


def _sim_limits(spec: SweepSpec) -> str:
    if spec.duration_s is not None:
        return f"{spec.duration_s:g} s of sim time"
    return "sim time " + ", ".join(f"{sc} {time_limit_s(sc):g} s" for sc in spec.scenarios)


def plan_text(spec: SweepSpec, keys: list[RunKey], todo: list[RunKey], records: dict[str, dict[str, Any]], out: Path,
              jobs: int, vehicle_budget: int) -> str:
    dims = " x ".join(f"{len(getattr(spec, a))} {AXIS_LABEL[a]}{'s' if len(getattr(spec, a)) != 1 else ''}"
                      for a in AXES)
    lines = [f"plan {spec.name!r}: {len(keys)} runs = {dims}",
             f"  scenarios {', '.join(spec.scenarios)}; collider speeds {', '.join(f'{v:g}' for v in spec.collider_speeds_kmh)} km/h;"
             f" deltas {', '.join(f'{v:g}' for v in spec.deltas_s)} s; vehicles {', '.join(map(str, spec.vehicles))};"
             f" schemes {', '.join(spec.schemes)}; seeds {', '.join(map(str, spec.seeds))}; {_sim_limits(spec)};"
             f" model {spec.resolved_model().label()}",
             f"  {'vehicles':>8} {'runs':>6} {'to run':>7} {'est. per run':>13} {'est. to run':>12}"]
    scale, measured = calibration(records.values())
    for n in sorted(spec.vehicles):
        mine = [k for k in todo if k.vehicles == n]
        per = scale * statistics.fmean(estimate_run_s(k) for k in keys if k.vehicles == n)
        lines.append(f"  {n:>8} {sum(k.vehicles == n for k in keys):>6} {len(mine):>7} {per:>11.0f} s"
                     f" {_duration(scale * sum(sweep_cost_s(k, jobs, vehicle_budget) for k in mine)):>12}")
    wall = estimate_wall_s(todo, jobs, scale, vehicle_budget)
    how = f"--jobs {jobs}, vehicle budget {vehicle_budget}" if jobs > 1 else "--jobs 1"
    hours = f"{wall / 3600:.1f} h, " if wall >= 3600 else ""
    basis = (f"the model x {scale:.2f}, the median measured/modelled of the {measured} runs recorded here"
             if measured >= MIN_CALIBRATION_RUNS else "model: start-up + ticks x s/tick by vehicle count and scheme")
    recorded = sum(k.name in records for k in keys)
    lines += [f"  already recorded in {out / RESULTS}: {recorded}; to run: {len(todo)}",
              f"  estimated wall time: {_duration(wall)} ({hours}{how}; {basis}; docs/experiments.md)"]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    level = args.log_level.upper() if args.log_level.upper() in logging.getLevelNamesMapping() else "INFO"
    logging.basicConfig(level=level, format="autocast sweep: %(message)s")
    try:
        if args.file is not None:
            values, name = load_file(args.file)
        elif args.preset is not None:
            values, name = preset_values(args.preset), args.preset
        else:
            raise SweepError("preset: give --preset NAME or --file PATH")
        spec = spec_from(narrowed(values, args), name)
        if args.jobs < 1:
            raise SweepError(f"jobs: {args.jobs} is not >= 1")
        if args.vehicle_budget < 1:
            raise SweepError(f"vehicle_budget: {args.vehicle_budget} is not >= 1")
        if not args.min_free_mb >= 0:
            raise SweepError(f"min_free_mb: {args.min_free_mb:g} is not >= 0")
        keys = expand(spec)
        check_scenarios(keys)
    except SweepError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    suffix = model_suffix(spec.resolved_model().label())
    out = args.out or Path("runs") / "sweeps" / (f"{spec.name}-{suffix[1:]}" if suffix else spec.name)
    records = latest(read_results(out / RESULTS))
    todo = [k for k in keys if k.name not in records
            or (args.retry_failed and records[k.name]["status"] == "failed")]
    text = plan_text(spec, keys, todo, records, out, args.jobs, args.vehicle_budget)
    if args.cluster:
        text += (f"\n  on the cluster at {args.cluster}: as many runs at once as the workers' vehicles resources "
                 "hold; the estimate above is for this machine")
    if args.dry_run:
        print(text)
        return EXIT_OK
    return run_sweep(spec, keys, todo, out, args, text, calibration(records.values())[0])


def run_sweep(spec: SweepSpec, keys: list[RunKey], todo: list[RunKey], out: Path, args: argparse.Namespace,
              text: str, scale: float) -> int:
    out.mkdir(parents=True, exist_ok=True)
    lock = open(out / LOCK, "w")
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        print(f"error: out: another sweep is running in {out}", file=sys.stderr)
        return EXIT_BAD_INPUT
    with lock:
        sweep = Sweep(spec, out, args.jobs, args.vehicle_budget, (args.runs_dir or out / "runs").resolve(),
                      args.min_free_mb)
        sweep.runs_dir.mkdir(parents=True, exist_ok=True)
        sweep.logs_dir.mkdir(exist_ok=True)
        plan = {"spec": asdict(spec), "runs": [{"run_key": k.name, **asdict(k)} for k in keys],
                "jobs": args.jobs, "vehicle_budget": args.vehicle_budget, "to_run": len(todo),
                "runs_dir": str(sweep.runs_dir), "cluster": args.cluster,
                "estimated_wall_s": round(estimate_wall_s(todo, args.jobs, scale, args.vehicle_budget)), "git_revision": git_revision(),
                "written_at": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "argv": sys.argv[1:]}
        (out / PLAN).write_text(json.dumps(plan, indent=1) + "\n")
        print(text, file=sys.stderr)
        if not todo:
            log.info("nothing to run: every run of the plan is recorded in %s", out / RESULTS)
            return _exit_code(spec, keys, out)
        if args.cluster:  # the same runs and records, each run a task on a Dask worker
            from deploy.experiments.cluster import run_on_cluster

            return run_on_cluster(sweep, keys, todo, args.cluster)
        t0 = time.monotonic()
        if (low := sweep.disk_low_reason()) is not None:  # before warming anything
            return finish_sweep(spec, keys, out, t0, False, low)
        try:
            warm_up(todo[0])
            sweep.warm = True
        except KeyboardInterrupt:
            return EXIT_INTERRUPTED
        except Exception:  # an optimisation: each run then warms its own
            log.warning("warming the numba caches failed; every run warms its own", exc_info=True)
        signal.signal(signal.SIGINT, sweep.on_signal)
        signal.signal(signal.SIGTERM, sweep.on_signal)
        progress = Progress(len(todo))
        try:  # every launcher forked from one warm parent, kept for the whole sweep
            with process_factory.activated(LAUNCHER_MODULES):
                failed, interrupted = sweep.execute(todo, progress)
        finally:
            progress.close()
        return finish_sweep(spec, keys, out, t0, interrupted, sweep.disk_low)


if __name__ == "__main__":
    sys.exit(main())
