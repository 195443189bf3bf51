"""What a sweep is: its matrix of runs (from a preset or a file, narrowed by flags), the
time estimate, and its records (``plan.json``, ``results.jsonl``). ``deploy/experiments/sweep.py`` runs it."""

from __future__ import annotations

import argparse
import hashlib
import itertools
import json
import logging
import math
import os
import time
from collections.abc import Iterable, Mapping
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

EXIT_OK, EXIT_SOME_FAILED, EXIT_BAD_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130
EXIT_DISK_LOW = 4  # stopped starting runs: the disk is nearly full (autocast sweep --min-free-mb)
RESULTS, PLAN, LOCK = "results.jsonl", "plan.json", "sweep.lock"
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
    """One JSON line, on disk before this returns: a crash right after cannot lose it.
    After a torn last line (a writer killed, or a full disk) it starts a line of its own,
    so the torn line does not take this record with it."""
    line = json.dumps(record, allow_nan=False, separators=(",", ":")) + "\n"
    with open(path, "a+b") as f:  # "a": every write goes to the end, wherever it was read
        end = f.seek(0, os.SEEK_END)
        if end:
            f.seek(end - 1)
            if f.read(1) != b"\n":
                line = "\n" + line
        f.write(line.encode())
        f.flush()
        os.fsync(f.fileno())


def record_of(key: RunKey, run_id: str, exit_code: int, stdout: str, stderr: str, wall_s: float,
              extra: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The results line of a finished run: its key, status, and the outcome's scalar fields
    (of a scenario of several events also ``events``, each event's scalar fields); a run
    without a judged outcome keeps its exit code, failure and stderr tail."""
    result = _last_json(stdout)
    judged = result is not None and result.get("outcome") is not None and exit_code in (0, 1)
    rec: dict[str, Any] = {"run_key": key.name, **asdict(key), "run_id": run_id,
                           "status": "judged" if judged else "failed", "exit_code": exit_code,
                           "outcome": result.get("outcome") if result else None, "wall_total_s": round(wall_s, 2),
                           "finished_at": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    rec.update({k: v for k, v in _short(result or {}).items() if k not in rec})
    if isinstance((result or {}).get("events"), list):
        rec["events"] = [_short(e) for e in result["events"] if isinstance(e, dict)]
    rec.update(extra or {})
    if not judged:
        failure = (result or {}).get("failure") or (f"exit code {exit_code} without an outcome" if result is None
                                                     else f"exit code {exit_code}")
        rec["error"] = {"exit_code": exit_code, "failure": failure, "stderr_tail": stderr[-STDERR_TAIL_CHARS:]}
    return rec


def _short(fields: Mapping[str, Any]) -> dict[str, Any]:
    """The fields no longer than ``BIG_RESULT_CHARS`` as JSON, and ``ALWAYS_KEPT``."""
    return {k: v for k, v in fields.items() if k in ALWAYS_KEPT or len(json.dumps(v)) <= BIG_RESULT_CHARS}


def _last_json(stdout: str) -> dict[str, Any] | None:
    lines = stdout.strip().splitlines()
    if not lines:
        return None
    try:
        out = json.loads(lines[-1])
    except ValueError:
        return None
    return out if isinstance(out, dict) else None
