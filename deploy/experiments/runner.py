"""Running a sweep's runs on this machine: each an ``autocast run`` launcher forked from one
warm parent, as many at once as ``--jobs`` and ``--vehicle-budget`` allow, with a progress line.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from deploy.experiments.plan import (EXIT_DISK_LOW, EXIT_INTERRUPTED, EXIT_OK, EXIT_SOME_FAILED, RESULTS,
                                      STDERR_TAIL_CHARS, RunKey, SweepSpec, _duration, append_record, latest,
                                      read_results, record_of, sweep_cost_s)
from processes import factory as process_factory
from processes.manager import has_argument
from protocol import shm

log = logging.getLogger(__name__)

LAUNCHER_GRACE_S = 30.0  # a launcher stops its processes within ~15 s of SIGINT (docs/running.md)
ORPHAN_GRACE_S = 10.0  # a killed launcher's factory stops its processes within ~3.5 s (processes/factory.py)
LAUNCHER_MODULES = ("deploy.cli", "deploy.launch.run", *process_factory.RUN_MODULES)  # what a launcher imports
LAUNCHER_SLACK_S = 120.0  # beyond the run's own --timeout-s: start-up and shutdown


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
                 runs_dir: Path | None = None, min_free_mb: float = 0.0) -> None:
        self.spec, self.out = spec, out
        self.jobs, self.vehicle_budget = jobs, vehicle_budget
        self.min_free_mb = min_free_mb
        self.disk_low: str | None = None  # why the sweep stopped starting runs, if the disk filled
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
                if (low := self.disk_low_reason()) is not None:
                    self.disk_low = low  # the running runs finish; the rest wait for the same command again
                    log.warning("%s; starting no more runs", low)
                    pending.clear()
                    self.model_pending_s = 0.0
                    break
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

    def disk_low_reason(self) -> str | None:
        """Why no run may start (the outputs' file systems have less than ``min_free_mb``
        free), or None. A run on a full disk fails and can leave a torn MCAP."""
        free_mb = min(shutil.disk_usage(d).free for d in (self.runs_dir, self.out)) / 1e6
        if free_mb >= self.min_free_mb:
            return None
        return f"{free_mb:.1f} MB free where the runs write, under --min-free-mb {self.min_free_mb:g}"

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
    """Delete a run's MCAP beyond ``limit_mb`` (an EMP run at 40 vehicles logs every
    uploaded point cloud: up to ~500 MB); the record says so. The report's load and
    delivery figures of the run are kept first (``deploy.experiments.load.KEPT``)."""
    from deploy.experiments import load

    mcap = run_dir / "run.mcap"
    try:
        size_mb = mcap.stat().st_size / 1e6
    except OSError:
        return {}
    if size_mb <= limit_mb:
        return {}
    try:
        load.keep_summary(mcap, run_dir / load.KEPT)
    except Exception as exc:  # a torn log: deleted all the same, the report lists it as unread
        log.warning("%s: load figures not kept: %s", mcap, exc)
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


def finish_sweep(spec: SweepSpec, keys: list[RunKey], out: Path, t0: float, interrupted: bool,
                 disk_low: str | None = None) -> int:
    """Log the outcome counts and where the results are; the sweep's exit code."""
    counts = Counter((r["outcome"] or "failed") for r in latest(read_results(out / RESULTS)).values())
    log.info("%s after %s: %s; results %s; report: autocast report %s",
             "interrupted" if interrupted else "stopped" if disk_low else "done", _duration(time.monotonic() - t0),
             ", ".join(f"{k} {v}" for k, v in sorted(counts.items())) or "no runs", out / RESULTS, out)
    if interrupted:
        log.info("the same command resumes the sweep")
        return EXIT_INTERRUPTED
    if disk_low is not None:
        log.error("stopped: %s; free space (or lower the floor) and run the same command again: it resumes",
                  disk_low)
        return EXIT_DISK_LOW
    return _exit_code(spec, keys, out)


def _exit_code(spec: SweepSpec, keys: list[RunKey], out: Path) -> int:
    records = latest(read_results(out / RESULTS))
    return EXIT_SOME_FAILED if any(records[k.name]["status"] == "failed" for k in keys if k.name in records) else EXIT_OK
