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
its error), 2 bad input, 3 the cluster's scheduler was lost (``--cluster``), 130
interrupted (Ctrl-C: the running launchers stop their processes; nothing is left).
With ``--cluster`` each run is a task on a Dask worker instead (``deploy/experiments/cluster.py``).
"""

from __future__ import annotations

import argparse
import fcntl
import hashlib
import itertools
import json
import logging
import math
import os
import signal
import statistics
import subprocess
import sys
import time
from collections import Counter, deque
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, NoReturn, TextIO

from processes import factory as process_factory
from processes.manager import has_argument
from protocol import shm

log = logging.getLogger("deploy.experiments.sweep")

EXIT_OK, EXIT_SOME_FAILED, EXIT_BAD_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130
RESULTS, PLAN, LOCK = "results.jsonl", "plan.json", "sweep.lock"
LAUNCHER_GRACE_S = 30.0  # a launcher stops its processes within ~15 s of SIGINT (docs/running.md)
ORPHAN_GRACE_S = 10.0  # a killed launcher's factory stops its processes within ~3.5 s (processes/factory.py)
LAUNCHER_MODULES = ("deploy.cli", "deploy.launch.run", *process_factory.RUN_MODULES)  # what a launcher imports
LAUNCHER_SLACK_S = 120.0  # beyond the run's own --timeout-s: start-up and shutdown
STDERR_TAIL_CHARS = 2000
BIG_RESULT_CHARS = 1000  # outcome fields longer than this as JSON (the distance series) stay in outcome.json
ALWAYS_KEPT = ("dead_agents",)  # kept however long: 36 dead agents are 1.6 kB, and they matter

# ---------------------------------------------------------------------------- the matrix

AXES = ("scenarios", "collider_speeds_kmh", "deltas_s", "vehicles", "schemes", "seeds")
AXIS_PARAM = {"scenarios": "scenario", "collider_speeds_kmh": "collider_speed_kmh", "deltas_s": "delta_s",
              "vehicles": "vehicles", "seeds": "seed"}  # axis -> world_server.scenarios field that checks it
AXIS_LABEL = {"scenarios": "scenario", "collider_speeds_kmh": "collider speed", "deltas_s": "delta",
              "vehicles": "vehicle count", "schemes": "scheme", "seeds": "seed"}
SCANS = ("ego", "all", "none")


class SweepError(ValueError):
    """A bad preset, file or flag; the message starts with the field's name."""


@dataclass(frozen=True, slots=True)
class SweepSpec:
    """A sweep: its axes (the matrix is their product) and what every run shares."""

    name: str
    scenarios: tuple[str, ...]
    collider_speeds_kmh: tuple[float, ...]
    deltas_s: tuple[float, ...]
    vehicles: tuple[int, ...]
    schemes: tuple[str, ...]
    seeds: tuple[int, ...] = (0,)
    duration_s: float | None = None  # sim-time limit of each run; None: each scenario's own
    timeout_s: float = 900.0  # wall-clock limit of each run (autocast run --timeout-s)
    agent_timeout_s: float = 10.0  # wall time an agent may take for a tick before the world declares it dead
    scans: str = "none"  # LiDAR scans the recorder keeps; the report needs none of them
    mcap_limit_mb: float = 200.0  # a run's MCAP larger than this is deleted (EMP logs every point cloud)
    json_mirror: bool = False  # each run's recorder writes the JSON mirror too (half its CPU; the report reads none)
    model: str = "ours"  # the modelling profile of every run (protocol.model, docs/models.md)
    model_settings: tuple[tuple[str, Any], ...] = ()  # settings changed on top of it, (name, value) pairs

    def size(self) -> int:
        return math.prod(len(getattr(self, a)) for a in AXES)

    def resolved_model(self):
        from protocol.model import resolve

        return resolve(self.model, dict(self.model_settings))


PRESETS: dict[str, dict[str, Any]] = {
    # Paper section 6: 3 scenarios, 20/30/40 km/h, deltas -2..+2 s, 5..40 vehicles, four schemes.
    "paper": {"scenarios": ["overtaking", "left_turn", "red_light"], "collider_speeds_kmh": [20, 30, 40],
              "deltas_s": [-2, -1, 0, 1, 2], "vehicles": [5, 10, 20, 40],
              "schemes": ["single", "agnostic", "emp", "autocast"], "seeds": [0]},
    # Two short runs: enough for the tests and a first look at the report.
    "smoke": {"scenarios": ["left_turn"], "collider_speeds_kmh": [30], "deltas_s": [0], "vehicles": [5],
              "schemes": ["single", "autocast"], "seeds": [0]},
}


@dataclass(frozen=True, slots=True)
class RunKey:
    """One point of the matrix: everything that decides a run's outcome."""

    scenario: str
    vehicles: int
    collider_speed_kmh: float
    delta_s: float
    scheme: str
    seed: int
    duration_s: float
    model: str = "ours"  # the model's label (``Model.label``): ``paper``, ``paper+hold_s=1.0``

    @property
    def name(self) -> str:
        """Readable and a valid run id: ``left_turn-v10-c30-d-1-autocast-s0-t20`` (0.5 -> 0p5);
        under another model than ours ``...-t20-mpaper`` (settings changed on top of a
        profile: a short hash of the label, ``-mpaper-a4efd27e`` for ``paper+hold_s=1.0``)."""
        base = (f"{self.scenario}-v{self.vehicles}-c{_num(self.collider_speed_kmh)}-d{_num(self.delta_s)}"
                f"-{self.scheme}-s{self.seed}-t{_num(self.duration_s)}")
        suffix = model_suffix(self.model)
        return f"{base}-{suffix}" if suffix else base

    def run_flags(self) -> list[str]:
        return ["--scenario", self.scenario, "--vehicles", str(self.vehicles),
                "--collider-speed", repr(self.collider_speed_kmh), "--delta", repr(self.delta_s),
                "--scheme", self.scheme, "--seed", str(self.seed), "--duration", repr(self.duration_s)]


def model_suffix(label: str) -> str:
    """What a model's label adds to a run key and a sweep's directory: nothing for ours,
    ``mpaper`` for a profile, ``mpaper-a4efd27e`` for settings changed on top of one (a
    hash of them, here ``hold_s=1.0``)."""
    if label == "ours":
        return ""
    name, _, extra = label.partition("+")
    return f"m{name}" + (f"-{hashlib.sha256(extra.encode()).hexdigest()[:8]}" if extra else "")


def time_limit_s(scenario: str) -> float:
    """The scenario's own sim-time limit (``world_server.scenarios.time_limit_s``)."""
    from world_server.scenarios import time_limit_s as limit

    return limit(scenario)


def _num(x: float) -> str:
    return f"{x:g}".replace(".", "p")


def expand(spec: SweepSpec) -> list[RunKey]:
    """The runs, seed by seed, densities ascending, every scheme of a configuration
    together: a sweep stopped early holds comparable schemes, the slow 40-vehicle
    runs last within a seed."""
    model = spec.resolved_model().label()
    return [RunKey(sc, n, v, d, scheme, seed, spec.duration_s or time_limit_s(sc), model)
            for seed, n, sc, v, d, scheme in itertools.product(
                spec.seeds, sorted(spec.vehicles), spec.scenarios, spec.collider_speeds_kmh, spec.deltas_s,
                spec.schemes)]


# ---------------------------------------------------------------------------- reading a spec


def spec_from(values: Mapping[str, Any], name: str) -> SweepSpec:
    """A validated spec from a mapping (preset, file, flags); errors name the field."""
    from vehicle_agent.__main__ import SCHEMES
    from world_server.scenarios import ScenarioError, params_from_dict

    known = [f.name for f in fields(SweepSpec) if f.name != "name"]
    for key in values:
        if key not in known:
            raise SweepError(f"{key}: unknown field (known: {', '.join(known)})")
    for axis in AXES:
        if axis not in values:
            raise SweepError(f"{axis}: missing")
    out: dict[str, Any] = {"name": name}
    for axis in AXES:
        raw = values[axis]
        if isinstance(raw, (str, int, float)):
            raw = [raw]
        if not isinstance(raw, (list, tuple)) or not raw:
            raise SweepError(f"{axis}: {raw!r} is not a non-empty list")
        vals = []
        for v in raw:
            if axis == "schemes":
                if v not in SCHEMES:
                    raise SweepError(f"schemes: {v!r} is not one of {', '.join(SCHEMES)}")
            else:
                param = AXIS_PARAM[axis]
                try:
                    v = getattr(params_from_dict({param: v}), param)
                except ScenarioError as exc:
                    raise SweepError(f"{axis}: {str(exc).removeprefix(param + ': ')}") from None
            if v not in vals:
                vals.append(v)
        out[axis] = tuple(vals)
    try:
        if values.get("duration_s") is not None:
            out["duration_s"] = params_from_dict({"duration_s": values["duration_s"]}).duration_s
    except ScenarioError as exc:
        raise SweepError(str(exc)) from None
    for key in ("timeout_s", "agent_timeout_s", "mcap_limit_mb"):
        if key in values:
            v = values[key]
            ok = isinstance(v, (int, float)) and not isinstance(v, bool) and v == v
            positive = key != "mcap_limit_mb"
            if not ok or v < 0 or (positive and v == 0):
                raise SweepError(f"{key}: {v!r} is not a number {'> 0' if positive else '>= 0'}")
            out[key] = float(v)
    if "json_mirror" in values:
        if not isinstance(values["json_mirror"], bool):
            raise SweepError(f"json_mirror: {values['json_mirror']!r} is not true or false")
        out["json_mirror"] = values["json_mirror"]
    if "scans" in values:
        if values["scans"] not in SCANS:
            raise SweepError(f"scans: {values['scans']!r} is not one of {', '.join(SCANS)}")
        out["scans"] = values["scans"]
    if "model" in values or "model_settings" in values:
        from protocol.model import ModelError, resolve

        from channel_proxy.profiles import get_profile

        model, settings = values.get("model", "ours"), values.get("model_settings", {})
        if not isinstance(settings, Mapping):
            raise SweepError(f"model_settings: {settings!r} is not a table of settings")
        try:
            get_profile(resolve(model, settings).channel_profile)
        except ModelError as exc:
            raise SweepError(str(exc)) from None
        except KeyError as exc:
            raise SweepError(f"channel_profile: {exc.args[0]}") from None
        out["model"], out["model_settings"] = model, tuple(sorted(settings.items()))
    return SweepSpec(**out)


def load_file(path: Path) -> tuple[dict[str, Any], str]:
    """A sweep file's fields (``preset = "paper"`` in it starts from that preset) and its name."""
    import tomllib

    try:
        text = path.read_text()
    except OSError as exc:
        raise SweepError(f"file: cannot read {path}: {exc.strerror}") from None
    try:
        values = json.loads(text) if path.suffix == ".json" else tomllib.loads(text)
    except (ValueError, tomllib.TOMLDecodeError) as exc:
        raise SweepError(f"file: {path} is not valid {'JSON' if path.suffix == '.json' else 'TOML'}: {exc}") from None
    if not isinstance(values, dict):
        raise SweepError(f"file: {path} must hold a table of fields")
    base = values.pop("preset", None)
    if base is not None:
        values = {**preset_values(base), **values}
    return values, path.stem


def preset_values(name: str) -> dict[str, Any]:
    if name not in PRESETS:
        raise SweepError(f"preset: {name!r} is not one of {', '.join(PRESETS)}")
    return dict(PRESETS[name])


FLAG_AXES = {"scenarios": str, "collider_speeds": float, "deltas": float, "vehicles": int, "schemes": str,
             "seeds": int}  # flag -> element type; --collider-speeds and --deltas fill the _kmh/_s axes


def narrowed(values: dict[str, Any], args: argparse.Namespace) -> dict[str, Any]:
    """Flags override the preset's or file's fields (``--vehicles 5,10 --seeds 0``)."""
    out = dict(values)
    for flag, kind in FLAG_AXES.items():
        text = getattr(args, flag)
        if text is None:
            continue
        axis = {"collider_speeds": "collider_speeds_kmh", "deltas": "deltas_s"}.get(flag, flag)
        items = [t.strip() for t in text.split(",") if t.strip()]
        try:
            out[axis] = [kind(t) for t in items]
        except ValueError:
            raise SweepError(f"{axis}: {text!r} is not a comma-separated list of "
                             f"{'integers' if kind is int else 'numbers' if kind is float else 'names'}") from None
    for flag, key, kind in (("duration", "duration_s", float), ("timeout_s", "timeout_s", float),
                            ("agent_timeout_s", "agent_timeout_s", float), ("mcap_limit_mb", "mcap_limit_mb", float)):
        text = getattr(args, flag)
        if text is not None:
            try:
                out[key] = kind(text)
            except ValueError:
                raise SweepError(f"{key}: {text!r} is not a number") from None
    if args.scans is not None:
        out["scans"] = args.scans
    if args.model is not None:
        out["model"] = args.model
    if args.model_set:
        if not isinstance(out.get("model_settings") or {}, Mapping):
            raise SweepError(f"model_settings: {out['model_settings']!r} is not a table of settings")
        settings = dict(out.get("model_settings") or {})
        for text in args.model_set:
            key, sep, value = text.partition("=")
            if not sep:
                raise SweepError(f"model_set: {text!r} is not KEY=VALUE")
            settings[key.strip()] = value.strip()
        out["model_settings"] = settings
    if args.json_mirror:
        out["json_mirror"] = True
    return out


def check_scenarios(keys: Iterable[RunKey]) -> None:
    """Build every distinct scenario of the matrix once (~30 ms each, 0.3 s at 40 vehicles):
    a combination the world cannot set up is refused before hours of runs, naming it."""
    from deploy.launch.table import connected_vids
    from world_server.scenarios import ScenarioError, params_from_dict

    seen = set()
    for k in keys:
        p = (k.scenario, k.vehicles, k.collider_speed_kmh, k.delta_s, k.seed, k.duration_s)
        if p in seen:
            continue
        seen.add(p)
        try:
            connected_vids(params_from_dict(dict(zip(("scenario", "vehicles", "collider_speed_kmh", "delta_s", "seed",
                                                        "duration_s"), p))))
        except ScenarioError as exc:
            raise SweepError(f"{exc} (run {k.name})") from None


# ---------------------------------------------------------------------------- the estimate


# Wall seconds of one run alone on the 2-core development machine, by connected vehicles
# (scheme autocast, caches warm, --scans none): the fixed cost of a run, start-up and
# teardown (its launcher and N + 3 processes forked from the sweep's warm factory) and
# seconds per 100 ms lock-step tick; the other schemes' ticks cost a multiple of
# autocast's. How they were measured: docs/experiments.md.
MODEL_STARTUP_S = {5: 0.5, 10: 0.6, 20: 0.75, 40: 2.15}
MODEL_TICK_S = {5: 0.0332, 10: 0.0530, 20: 0.0682, 40: 0.1582}
# A scheme's tick as a multiple of autocast's, by connected vehicles (the median ratio,
# scheme over autocast, in the same scenario; docs/experiments.md); agnostic: 1.
MODEL_SCHEME_TICK: dict[str, dict[int, float]] = {
    "single": {5: 0.44, 10: 0.52, 20: 0.45, 40: 0.44}, "lane": {5: 0.58, 40: 0.36},  # lane: not refit (no preset runs it)
    "emp": {5: 1.36, 10: 1.9, 20: 1.84, 40: 1.79}}
# With --jobs > 1, runs whose vehicles fit the budget twice run two at once; a pair takes
# less than the two runs alone (each leaves idle time in its lock-step phases): the
# sweep's wall time per such run is its time alone over this gain.
PAIR_GAIN = 1.25
# A run ends once its outcome is decided, rarely at its time limit. What a sweep's wall
# time sums is each run's ticks, so the model takes the mean sim time at which judged runs
# ended, by scenario and collider speed (a slower collider reaches the conflict later:
# the left turn ended at 17.7 s on average with the collider at 20 km/h, at 11.4 s at
# 40), from the paper preset at 5 and 10 vehicles (480 judged runs, all schemes;
# docs/experiments.md); linear in between, and the scenarios' mean for one it has not seen.
TYPICAL_END_S: dict[str, float | dict[int, float]] = {
    "left_turn": {20: 17.7, 30: 14.5, 40: 11.4},
    "overtaking": {20: 28.9, 30: 20.7, 40: 16.0},
    "red_light": {20: 10.0, 30: 9.5, 40: 9.4}}
TYPICAL_END_OTHER_S = 15.3
MIN_CALIBRATION_RUNS = 3


def _interp(table: Mapping[int, float], n: float) -> float:
    """Piecewise linear in the key (a vehicle count, a speed), extended linearly beyond
    the measured ones."""
    xs = sorted(table)
    if n <= xs[0]:
        lo, hi = xs[0], xs[1]
    elif n >= xs[-1]:
        lo, hi = xs[-2], xs[-1]
    else:
        lo = max(x for x in xs if x <= n)
        hi = min(x for x in xs if x > n) if n != lo else lo
        if hi == lo:
            return table[lo]
    t = (n - lo) / (hi - lo)
    return max(0.0, table[lo] + t * (table[hi] - table[lo]))


def typical_end_s(key: RunKey) -> float:
    """The sim time at which a run like ``key`` typically ends (``TYPICAL_END_S``)."""
    end = TYPICAL_END_S.get(key.scenario, TYPICAL_END_OTHER_S)
    return end if isinstance(end, (int, float)) else max(1.0, _interp(end, key.collider_speed_kmh))


def estimate_run_s(key: RunKey) -> float:
    """Wall seconds of one run alone: start-up + ticks x seconds per tick."""
    ticks = min(key.duration_s, typical_end_s(key)) / 0.1
    factor = MODEL_SCHEME_TICK.get(key.scheme)
    tick_s = _interp(MODEL_TICK_S, key.vehicles) * (_interp(factor, key.vehicles) if factor else 1.0)
    return _interp(MODEL_STARTUP_S, key.vehicles) + ticks * tick_s


def calibration(records: Iterable[dict[str, Any]]) -> tuple[float, int]:
    """How much slower than the model this machine ran the sweep's judged runs so far:
    the median of measured over modelled wall time (1.0 below ``MIN_CALIBRATION_RUNS``).
    Runs that ran beside another (``"alone": false``) are left out: the model is of a
    run alone, and a run in a pair takes ~1.5x that (the pair's gain is ``PAIR_GAIN``)."""
    ratios = []
    for r in records:
        if r.get("status") == "judged" and r.get("wall_total_s") and r.get("alone", True):
            key = RunKey(**{f.name: r.get(f.name, f.default) for f in fields(RunKey)})
            ratios.append(r["wall_total_s"] / estimate_run_s(key))
    if len(ratios) < MIN_CALIBRATION_RUNS:
        return 1.0, len(ratios)
    ratios.sort()
    return ratios[len(ratios) // 2], len(ratios)


def sweep_cost_s(key: RunKey, jobs: int, vehicle_budget: int) -> float:
    """What a run adds to its sweep's wall time: its time alone, over ``PAIR_GAIN`` if it
    can pair up (``jobs`` > 1 and twice its vehicles within ``vehicle_budget``)."""
    pairs = jobs > 1 and 2 * key.vehicles <= vehicle_budget
    return estimate_run_s(key) / (PAIR_GAIN if pairs else 1.0)


def estimate_wall_s(keys: Iterable[RunKey], jobs: int, scale: float = 1.0, vehicle_budget: int = 20) -> float:
    """The sweep's wall time: the sum of its runs' ``sweep_cost_s``."""
    return scale * sum(sweep_cost_s(k, jobs, vehicle_budget) for k in keys)


def _duration(s: float) -> str:
    s = max(0, int(round(s)))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"


# ---------------------------------------------------------------------------- results


def read_results(path: Path) -> list[dict[str, Any]]:
    """Every record of ``results.jsonl`` in order; a torn last line (killed mid-write) is skipped."""
    if not path.exists():
        return []
    out = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except ValueError:
            log.warning("%s:%d: not a JSON line; ignored", path, n)
            continue
        if isinstance(rec, dict) and "run_key" in rec:
            out.append(rec)
    return out


def latest(records: Iterable[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """The last record of each run key (a retried run's newest attempt)."""
    return {r["run_key"]: r for r in records}


def append_record(path: Path, record: dict[str, Any]) -> None:
    """One JSON line, on disk before this returns: a crash right after cannot lose it."""
    with open(path, "a") as f:
        f.write(json.dumps(record, allow_nan=False, separators=(",", ":")) + "\n")
        f.flush()
        os.fsync(f.fileno())


def record_of(key: RunKey, run_id: str, exit_code: int, stdout: str, stderr: str, wall_s: float,
              extra: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The results line of a finished run: its key, status, and the outcome's scalar fields;
    a run without a judged outcome keeps its exit code, failure and stderr tail."""
    result = _last_json(stdout)
    judged = result is not None and result.get("outcome") is not None and exit_code in (0, 1)
    rec: dict[str, Any] = {"run_key": key.name, **asdict(key), "run_id": run_id,
                           "status": "judged" if judged else "failed", "exit_code": exit_code,
                           "outcome": result.get("outcome") if result else None, "wall_total_s": round(wall_s, 2),
                           "finished_at": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    for k, v in (result or {}).items():
        if k not in rec and (k in ALWAYS_KEPT or len(json.dumps(v)) <= BIG_RESULT_CHARS):
            rec[k] = v
    rec.update(extra or {})
    if not judged:
        failure = (result or {}).get("failure") or (f"exit code {exit_code} without an outcome" if result is None
                                                     else f"exit code {exit_code}")
        rec["error"] = {"exit_code": exit_code, "failure": failure, "stderr_tail": stderr[-STDERR_TAIL_CHARS:]}
    return rec


def _last_json(stdout: str) -> dict[str, Any] | None:
    lines = stdout.strip().splitlines()
    if not lines:
        return None
    try:
        out = json.loads(lines[-1])
    except ValueError:
        return None
    return out if isinstance(out, dict) else None


# ---------------------------------------------------------------------------- running


@dataclass
class Job:
    key: RunKey
    run_id: str
    proc: subprocess.Popen | process_factory.ForkedProcess
    out_path: Path
    err_path: Path
    t_start: float
    deadline: float
    cpu_s: float | None = None  # user + system time of the launcher and every process it reaped
    alone: bool = True  # no other run of the sweep ran at the same time

    def exited(self) -> bool:
        """Reap the launcher if it has exited, keeping its rusage (which includes its children's)."""
        if self.proc.returncode is not None:
            return True
        if isinstance(self.proc, process_factory.ForkedProcess):  # the factory reaped it
            if self.proc.poll() is None:
                return False
            self.cpu_s = self.proc.cpu_s
            return True
        try:
            pid, status, usage = os.wait4(self.proc.pid, os.WNOHANG)
        except ChildProcessError:
            return self.proc.poll() is not None
        if pid == 0:
            return False
        self.proc.returncode = os.waitstatus_to_exitcode(status)
        self.cpu_s = usage.ru_utime + usage.ru_stime
        return True


@dataclass
class Progress:
    """A progress line on stderr: redrawn in place on a terminal; elsewhere each finished
    run prints one line with the counts and the ETA."""

    total: int
    stream: TextIO = sys.stderr
    done: int = 0
    outcomes: Counter = field(default_factory=Counter)
    t0: float = field(default_factory=time.monotonic)
    _drawn: bool = False

    def __post_init__(self) -> None:
        self.tty = self.stream.isatty()

    def eta_s(self, model_spent_s: float, model_left_s: float) -> float:
        """The model's time still to go, scaled by the pace so far (elapsed over the model's
        time of the work done): absorbs the model's error, parallel runs and other load."""
        pace = (time.monotonic() - self.t0) / model_spent_s if model_spent_s > 10.0 else 1.0
        return max(0.0, model_left_s * pace)

    def finished(self, rec: dict[str, Any], model: tuple[float, float]) -> None:
        self.done += 1
        self.outcomes[rec["outcome"] or "failed"] += 1
        if rec["status"] == "judged":
            closest = rec.get("closest_distance_m")
            what = f"{rec['outcome']}" + (f"  closest {closest:.2f} m" if isinstance(closest, (int, float)) else "")
            if rec.get("dead_agents"):
                what += f"  ({len(rec['dead_agents'])} agents declared dead: the machine is overloaded?)"
        else:
            what = f"FAILED (exit {rec['exit_code']}): {rec['error']['failure']}"
        line = f"[{self.done}/{self.total}] {rec['run_key']}: {what}  ({rec['wall_total_s']:.0f} s)"
        if not self.tty:
            line += f"  elapsed {_duration(time.monotonic() - self.t0)}  ETA {_duration(self.eta_s(*model))}"
        self._clear()
        print(line, file=self.stream, flush=True)

    def draw(self, running: list[str], model: tuple[float, float]) -> None:
        if not self.tty:
            return
        width = 24
        filled = int(width * self.done / max(self.total, 1))
        counts = " ".join(f"{k} {v}" for k, v in sorted(self.outcomes.items()))
        line = (f"[{'#' * filled}{'.' * (width - filled)}] {self.done}/{self.total}  {counts}  "
                f"elapsed {_duration(time.monotonic() - self.t0)}  ETA {_duration(self.eta_s(*model))}"
                f"  running: {', '.join(running)}")
        self.stream.write("\r\033[K" + line[:max(40, _terminal_columns() - 1)])
        self.stream.flush()
        self._drawn = True

    def _clear(self) -> None:
        if self.tty and self._drawn:
            self.stream.write("\r\033[K")
            self._drawn = False

    def close(self) -> None:
        self._clear()


def _terminal_columns() -> int:
    try:
        return os.get_terminal_size(sys.stderr.fileno()).columns
    except OSError:
        return 120


class Sweep:
    """Runs the planned keys that are not recorded yet, ``jobs`` at a time within the vehicle budget."""

    def __init__(self, spec: SweepSpec, out: Path, jobs: int, vehicle_budget: int,
                 runs_dir: Path | None = None) -> None:
        self.spec, self.out = spec, out
        self.jobs, self.vehicle_budget = jobs, vehicle_budget
        self.runs_dir, self.logs_dir, self.results = runs_dir or out / "runs", out / "logs", out / RESULTS
        self.running: list[Job] = []
        self.model_done_s = self.model_pending_s = 0.0
        self.warm = False  # the sweep warmed the numba caches: runs skip it
        self.stop_requested = False
        self.kill_requested = False

    # ------------------------------------------------------------------ signals

    def on_signal(self, signum: int, _frame: Any) -> None:
        if self.stop_requested:
            self.kill_requested = True  # second Ctrl-C: no more patience
        self.stop_requested = True

    # ------------------------------------------------------------------ the loop

    def execute(self, todo: list[RunKey], progress: Progress) -> tuple[int, bool]:
        """Run ``todo``; return (failed runs, interrupted)."""
        pending = deque(todo)
        self.model_pending_s = sum(self._cost(k) for k in todo)
        failed = 0
        while pending or self.running:
            if self.stop_requested:
                self._stop_running()
                return failed, True
            while pending and self._can_start(pending[0]):
                key = pending.popleft()
                self.model_pending_s -= self._cost(key)
                self._start(key)
            finished = [(j, False) for j in self.running if j.exited()]
            finished += [(j, True) for j in self.running if time.monotonic() > j.deadline and not j.exited()]
            for job, timed_out in finished:
                self.running.remove(job)
                if timed_out:
                    self._terminate(job)
                rec = self._finish(job, timed_out)
                failed += rec["status"] == "failed"
                self.model_done_s += self._cost(job.key)
                progress.finished(rec, self._model())
            progress.draw([j.run_id for j in self.running], self._model())
            time.sleep(0.2)
        return failed, False

    def _model(self) -> tuple[float, float]:
        """The model's seconds of work done (finished runs, and running ones up to their
        estimate) and still to do (pending runs, the rest of running ones)."""
        now = time.monotonic()
        est = [(self._cost(j.key), now - j.t_start) for j in self.running]
        return (self.model_done_s + sum(min(e, age) for e, age in est),
                self.model_pending_s + sum(max(0.0, e - age) for e, age in est))

    def _cost(self, key: RunKey) -> float:
        return sweep_cost_s(key, self.jobs, self.vehicle_budget)

    def _can_start(self, key: RunKey) -> bool:
        if not self.running:
            return True
        used = sum(j.key.vehicles for j in self.running)
        return len(self.running) < self.jobs and used + key.vehicles <= self.vehicle_budget

    def _run_id(self, key: RunKey) -> str:
        """The key's name; ``-a2``, ``-a3``, ... when an earlier attempt left its directory
        (interrupted, or failed and retried): nothing of an earlier attempt is overwritten."""
        run_id, attempt = key.name, 1
        while (self.runs_dir / run_id).exists() or (self.logs_dir / f"{run_id}.out").exists():
            attempt += 1
            run_id = f"{key.name}-a{attempt}"
        return run_id

    def _start(self, key: RunKey) -> None:
        run_id = self._run_id(key)
        out_path, err_path = self.logs_dir / f"{run_id}.out", self.logs_dir / f"{run_id}.err"
        argv = [sys.executable, "-m", "deploy.cli", *launcher_args(self.spec, key, run_id, self.runs_dir, self.warm)]
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        factory = process_factory.current()
        with open(out_path, "wb") as out, open(err_path, "wb") as err:
            proc: subprocess.Popen | process_factory.ForkedProcess | None = None
            if factory is not None:  # forked warm: no imports, kernels loaded (as start_new_session)
                try:
                    proc = factory.spawn(argv[2], argv[3:], stdout=out.fileno(), stderr=err.fileno(), env=env)
                except process_factory.FactoryError as exc:
                    log.warning("process factory failed (%s); starting runs with Popen", exc)
            if proc is None:
                proc = subprocess.Popen(argv, stdout=out, stderr=err, stdin=subprocess.DEVNULL,
                                        start_new_session=True, env=env)
        now = time.monotonic()
        for other in self.running:  # runs in pairs are slower each: calibration() leaves them out
            other.alone = False
        self.running.append(Job(key, run_id, proc, out_path, err_path, now, now + self.spec.timeout_s + LAUNCHER_SLACK_S,
                                alone=not self.running))
        log.debug("started %s (pid %d): %s", run_id, proc.pid, " ".join(argv))

    def _finish(self, job: Job, timed_out: bool = False) -> dict[str, Any]:
        wall_s = time.monotonic() - job.t_start
        stdout = job.out_path.read_text(errors="replace")
        stderr = job.err_path.read_text(errors="replace")
        rc = job.proc.returncode
        if rc is not None and rc < 0 and not timed_out:  # the launcher itself was killed
            clean_after_launcher(self.runs_dir / job.run_id, job.run_id, job.proc.pid)
        if timed_out:
            stderr += (f"\nautocast sweep: the launcher did not exit within {self.spec.timeout_s + LAUNCHER_SLACK_S:.0f} s;"
                       " killed it and its processes")
        extra = {"cpu_s": None if job.cpu_s is None else round(job.cpu_s, 1), "alone": job.alone,
                 **limit_mcap(self.runs_dir / job.run_id, self.spec.mcap_limit_mb)}
        rec = record_of(job.key, job.run_id, rc, stdout, stderr, wall_s, extra)
        if timed_out:
            rec["status"] = "failed"
            rec["error"] = {"exit_code": rc, "failure": "the launcher did not exit in time",
                            "stderr_tail": stderr[-STDERR_TAIL_CHARS:]}
        append_record(self.results, rec)
        return rec

    # ------------------------------------------------------------------ stopping

    def _stop_running(self) -> None:
        """SIGINT every launcher (each stops its own processes in order), wait, then SIGKILL."""
        for job in self.running:
            _signal_group(job.proc.pid, signal.SIGINT)
        deadline = time.monotonic() + LAUNCHER_GRACE_S
        for job in self.running:
            while job.proc.poll() is None and time.monotonic() < deadline and not self.kill_requested:
                time.sleep(0.1)
            if job.proc.poll() is None:
                self._terminate(job, grace_s=0.0)
        self.running.clear()

    def _terminate(self, job: Job, grace_s: float = LAUNCHER_GRACE_S) -> None:
        stop_launcher(job.proc, self.runs_dir / job.run_id, job.run_id, grace_s)


def launcher_args(spec: SweepSpec, key: RunKey, run_id: str, runs_dir: Path, warm: bool) -> list[str]:
    """``autocast run``'s arguments for one run of the sweep (after ``python -m deploy.cli``)."""
    return ["run", *key.run_flags(), "--json", "--out", str(runs_dir), "--run-id", run_id, "--scans", spec.scans,
            "--timeout-s", repr(spec.timeout_s), "--agent-timeout-s", repr(spec.agent_timeout_s),
            "--log-level", "WARNING", *(["--no-warm-up"] if warm else []),
            *([] if spec.json_mirror else ["--no-json-mirror"]), *spec.resolved_model().args()]


def limit_mcap(run_dir: Path, limit_mb: float) -> dict[str, Any]:
    """Delete a run's MCAP beyond ``limit_mb`` (an EMP run logs every uploaded point
    cloud: ~300 MB at 5 vehicles); the record says so."""
    mcap = run_dir / "run.mcap"
    try:
        size_mb = mcap.stat().st_size / 1e6
    except OSError:
        return {}
    if size_mb <= limit_mb:
        return {}
    mcap.unlink()
    return {"mcap": None, "mcap_deleted_mb": round(size_mb, 1)}


def _signal_group(pid: int, sig: int) -> None:
    try:
        os.killpg(pid, sig)  # the launcher leads its own process group
    except ProcessLookupError:
        pass


def stop_launcher(proc: subprocess.Popen | process_factory.ForkedProcess, run_dir: Path, run_id: str,
                  grace_s: float = LAUNCHER_GRACE_S) -> int:
    """Stop one launcher (SIGINT to its group, continued if it was stopped; SIGKILL after
    ``grace_s``); if it has to be killed, clean up after it (``clean_after_launcher``).
    Returns how many of its processes had to be killed."""
    if proc.poll() is None and grace_s > 0:
        _signal_group(proc.pid, signal.SIGINT)
        _signal_group(proc.pid, signal.SIGCONT)
        try:
            proc.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            pass
    if proc.poll() is None:
        _signal_group(proc.pid, signal.SIGKILL)
        proc.wait()
        return clean_after_launcher(run_dir, run_id, proc.pid, ORPHAN_GRACE_S if grace_s > 0 else 0.0)
    return 0


def clean_after_launcher(run_dir: Path, run_id: str, launcher_pid: int, grace_s: float = ORPHAN_GRACE_S) -> int:
    """What a launcher that died of a signal (killed, or by us after its time) could not
    stop or remove: the processes it started, which its process factory stops when it
    goes (SIGINT, 3 s, SIGKILL: the recorder finalizes its log) and which get
    ``grace_s`` for that before they are killed here, and its shared-memory directory.
    Returns how many processes had to be killed."""
    deadline = time.monotonic() + grace_s
    while run_processes(run_dir, run_id) and time.monotonic() < deadline:
        time.sleep(0.1)
    killed = kill_run_processes(run_dir, run_id)
    shm.remove_orphans(launcher=(launcher_pid, run_id))
    return killed


def run_processes(run_dir: Path, run_id: str) -> list[int]:
    """The pids in a run's ``pids.json`` that still run with its id on their command line
    (a reused pid is someone else's)."""
    try:
        pids = json.loads((run_dir / "pids.json").read_text()).values()
    except (OSError, ValueError):
        return []
    return [int(pid) for pid in pids if has_argument(int(pid), run_id)]


def kill_run_processes(run_dir: Path, run_id: str) -> int:
    """SIGKILL what a killed launcher left (``run_processes``); returns how many."""
    left = run_processes(run_dir, run_id)
    for pid in left:
        _signal_group(pid, signal.SIGKILL)
    return len(left)


def warm_up(key: RunKey) -> None:
    """Compile or load the numba caches once, so each run can skip it (``--no-warm-up``)."""
    from deploy.launch.warmup import warm_numba_caches
    from world_server.scenarios import params_from_dict

    warm_numba_caches(params_from_dict({"scenario": key.scenario, "vehicles": key.vehicles}))


def git_revision() -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5,
                             cwd=Path(__file__).resolve().parent)
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


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
        sweep = Sweep(spec, out, args.jobs, args.vehicle_budget, (args.runs_dir or out / "runs").resolve())
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
        return finish_sweep(spec, keys, out, t0, interrupted)


def finish_sweep(spec: SweepSpec, keys: list[RunKey], out: Path, t0: float, interrupted: bool) -> int:
    """Log the outcome counts and where the results are; the sweep's exit code."""
    counts = Counter((r["outcome"] or "failed") for r in latest(read_results(out / RESULTS)).values())
    log.info("%s after %s: %s; results %s; report: autocast report %s",
             "interrupted" if interrupted else "done", _duration(time.monotonic() - t0),
             ", ".join(f"{k} {v}" for k, v in sorted(counts.items())) or "no runs", out / RESULTS, out)
    if interrupted:
        log.info("the same command resumes the sweep")
        return EXIT_INTERRUPTED
    return _exit_code(spec, keys, out)


def _exit_code(spec: SweepSpec, keys: list[RunKey], out: Path) -> int:
    records = latest(read_results(out / RESULTS))
    return EXIT_SOME_FAILED if any(records[k.name]["status"] == "failed" for k in keys if k.name in records) else EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
