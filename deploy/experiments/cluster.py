"""``autocast sweep --cluster tcp://HOST:8786``: a sweep's runs as tasks on Dask workers.

The client (the machine that runs ``autocast sweep``) plans the sweep as usual
(``deploy/experiments/plan.py``) and submits each run still to do as one Dask task, asking for
as many units of the workers' ``vehicles`` resource as the run has connected
vehicles: a worker started with ``--resources "vehicles=40"`` holds runs of at most
40 vehicles at once. On the worker the task starts the same ``autocast run ... --json``
as a local sweep, in its own process group, forked (as a local sweep's launchers are
from the sweep) from the worker's warm zygote: a fresh interpreter made at the
worker's first run, which imports the stack and loads every numba kernel once
(``processes/factory.py``; a worker has threads, so it cannot fork itself). When the
worker dies, the zygote's socket closes and it stops every launcher (SIGINT, which
stops a run's processes as Ctrl-C does, then SIGKILL). Without a zygote
(``AUTOCAST_FACTORY=popen``) the launcher is a new interpreter under this module's
``launch`` wrapper, which asks the kernel for SIGINT when the worker dies
(``PR_SET_PDEATHSIG``). The task returns the run's record, built on the worker
(``plan.record_of``: the outcome's scalars, or the failure and stderr tail) with
the launcher's stdout and stderr; the client appends each record to
``results.jsonl`` as it arrives and writes the logs under ``logs/``, so resume,
``--retry-failed``, the progress line and ``autocast report`` see what a local sweep
leaves.

Faults. Each task counts its starts in the scheduler's task metadata. A worker that
dies (killed, node lost) while it runs a task makes the scheduler run the task again
elsewhere; that second start runs the run again under a fresh run id, a third start
records the run as failed naming the workers that died (a scheduler that gave up
first, ``KilledWorker``, gets the task resubmitted once by the client, with the same
count). Only the task's result is recorded, once. A scheduler that goes away cancels
every future: the sweep stops, says so, and exits with ``EXIT_CLUSTER_LOST``;
``results.jsonl`` holds every run finished so far and the same command resumes. Each
task also stops its run when it cannot reach the scheduler any more.

Ctrl-C: the client sets the sweep's stop flag in the scheduler's metadata, cancels
the tasks that have not started, and waits for the started ones: each sends SIGINT
to its launcher, which stops its processes; a second Ctrl-C (or 30 s) SIGKILLs them.
Nothing of an interrupted run is recorded.
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import queue
import secrets
import select
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from importlib import metadata as importlib_metadata
from pathlib import Path
from typing import TYPE_CHECKING, Any

from deploy.experiments.plan import (EXIT_BAD_INPUT, EXIT_INTERRUPTED, STDERR_TAIL_CHARS, RunKey, SweepError, SweepSpec,
                                      append_record, estimate_run_s, read_results, record_of)
from deploy.experiments.runner import (LAUNCHER_GRACE_S, LAUNCHER_MODULES, LAUNCHER_SLACK_S, Job, Progress, Sweep,
                                        _signal_group, finish_sweep, git_revision, kill_run_processes, launcher_args,
                                        limit_mcap)
from processes import factory as process_factory

if TYPE_CHECKING:
    from distributed import Client, Future

log = logging.getLogger("deploy.experiments.cluster")

EXIT_CLUSTER_LOST = 3  # the scheduler could not be reached, or went away during the sweep
RESOURCE = "vehicles"  # the worker resource a run asks for, one unit per connected vehicle
MAX_STARTS = 2  # a run whose worker died is run once more; a third start records it failed
TIMED_OUT = "timed out"
POLL_S = 1.0  # a task looks at the sweep's stop flag this often while its run goes on
CONNECT_TIMEOUT_S = 30.0
STOP_SLACK_S = 15.0  # after Ctrl-C the client waits LAUNCHER_GRACE_S plus this for the started tasks
LOG_KEEP_CHARS = 200_000  # of a launcher's stderr sent back to the client (its tail)
PR_SET_PDEATHSIG = 1  # prctl(2)
PACKAGE = "autocast-py"


@dataclass(frozen=True, slots=True)
class ClusterRun:
    """One run as a task: what the worker needs to start it and to build its record."""

    key: RunKey
    attempt: int  # the first free attempt number at the client (run id ``<key>-a<attempt>`` beyond 1)
    runs_dir: str  # absolute; a directory every worker reaches at this path (or each its own)
    spec: SweepSpec
    token: str  # this sweep's: names its stop flag and its start counts in the scheduler


def _meta(token: str, *path: str) -> list[str]:
    return ["autocast-sweep", token, *path]


# ---------------------------------------------------------------------------- on the worker


def execute_run(task: ClusterRun) -> dict[str, Any]:
    """Run one run on this worker; its record (and logs), or ``{"stopped": ...}`` when
    the sweep was stopped (nothing to record)."""
    from distributed import get_client, get_worker

    client, worker = get_client(), get_worker()
    count_key = _meta(task.token, "starts", task.key.name)
    starts = [*client.get_metadata(count_key, default=[]), worker.address]
    client.set_metadata(count_key, starts)  # before the stop flag is read: see ClusterSweep._stop
    if client.get_metadata(_meta(task.token, "stop"), default=None):
        return {"stopped": "before it started"}
    if len(starts) > MAX_STARTS:
        return {"record": lost_record(task.key, task.key.name, starts[:-1])}
    runs_dir = Path(task.runs_dir)
    run_id = free_run_id(runs_dir, task.key.name, task.attempt)
    with tempfile.TemporaryDirectory(prefix=f"autocast-{run_id}-") as tmp:
        job = _start(task, run_id, Path(tmp))
        why = _watch(job, task, client, runs_dir)
        stdout = job.out_path.read_text(errors="replace")
        stderr = job.err_path.read_text(errors="replace")
    if why not in (None, TIMED_OUT):
        return {"stopped": why, "run_id": run_id}
    timed_out = why == TIMED_OUT
    extra = {"cpu_s": None if job.cpu_s is None else round(job.cpu_s, 1),
             **limit_mcap(runs_dir / run_id, task.spec.mcap_limit_mb),
             "worker": worker.address, "host": socket.gethostname(), "attempt": len(starts)}
    if len(starts) > 1:
        extra["lost_workers"] = starts[:-1]
    rec = record_of(task.key, run_id, job.proc.returncode, stdout, stderr, time.monotonic() - job.t_start, extra)
    if timed_out:
        stderr += (f"\nautocast sweep: the launcher did not exit within {task.spec.timeout_s + LAUNCHER_SLACK_S:.0f} s;"
                   " killed it and its processes")
        rec["status"] = "failed"
        rec["error"] = {"exit_code": job.proc.returncode, "failure": "the launcher did not exit in time",
                        "stderr_tail": stderr[-STDERR_TAIL_CHARS:]}
    return {"record": rec, "stdout": stdout, "stderr": stderr[-LOG_KEEP_CHARS:]}


def free_run_id(runs_dir: Path, name: str, attempt: int) -> str:
    """The first run id from ``attempt`` on whose directory does not exist here (a
    retried or resumed run never writes into an earlier attempt's directory)."""
    while True:
        run_id = name if attempt == 1 else f"{name}-a{attempt}"
        if not (runs_dir / run_id).exists():
            return run_id
        attempt += 1


def _start(task: ClusterRun, run_id: str, tmp: Path) -> Job:
    """The launcher: forked from this worker's warm zygote, as a local sweep's launchers
    are from the sweep's; or (no zygote) ``python -m deploy.experiments.cluster launch WORKER_PID
    <autocast run args>``, which warms its own caches."""
    out_path, err_path = tmp / "launcher.out", tmp / "launcher.err"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc: subprocess.Popen | process_factory.ForkedProcess | None = None
    with open(out_path, "wb") as out, open(err_path, "wb") as err:
        factory = worker_factory()
        if factory is not None:
            args = launcher_args(task.spec, task.key, run_id, Path(task.runs_dir), warm=True)
            try:
                proc = factory.spawn("deploy.cli", args, stdout=out.fileno(), stderr=err.fileno(), env=env)
            except process_factory.FactoryError as exc:
                log.warning("the worker's process factory failed (%s); starting the launcher anew", exc)
        if proc is None:
            args = launcher_args(task.spec, task.key, run_id, Path(task.runs_dir), warm=False)
            proc = subprocess.Popen([sys.executable, "-m", "deploy.experiments.cluster", "launch", str(os.getpid()), *args[1:]],
                                    stdout=out, stderr=err, stdin=subprocess.DEVNULL, start_new_session=True, env=env)
    now = time.monotonic()
    log.debug("started %s (pid %d): %s", run_id, proc.pid, " ".join(args))
    return Job(task.key, run_id, proc, out_path, err_path, now, now + task.spec.timeout_s + LAUNCHER_SLACK_S)


_factory: process_factory.Factory | None = None
_factory_lock = threading.Lock()


def worker_factory() -> process_factory.Factory | None:
    """This worker process's warm zygote (made at its first run; ``None`` when
    ``AUTOCAST_FACTORY=popen`` or it cannot be made): a fresh interpreter, since a
    worker has threads, that imports what a launcher runs and loads every numba kernel
    (``zygote_warm_up``), then forks each launcher. It stops the launchers still
    running when the worker dies (its socket closes) as a sweep does: SIGINT, up to
    ``LAUNCHER_GRACE_S`` for the launcher to stop its processes, SIGKILL."""
    global _factory
    if process_factory.disabled():
        return None
    with _factory_lock:
        if _factory is None or not _factory.alive:
            try:
                _factory = process_factory.Factory((*LAUNCHER_MODULES, f"{__name__}:zygote_warm_up"), start="exec",
                                                   stop_grace_s=LAUNCHER_GRACE_S)
            except (process_factory.FactoryError, OSError) as exc:
                log.warning("no process factory on this worker (%s): each launcher starts anew", exc)
                return None
        return _factory


def zygote_warm_up() -> None:
    """In the worker's zygote: load (or, on a new host, compile) every numba kernel, as
    a local sweep does before its first run."""
    from deploy.launch.warmup import warm_numba_caches
    from world_server.scenarios import ScenarioParams

    warm_numba_caches(ScenarioParams())


def _watch(job: Job, task: ClusterRun, client: Client, runs_dir: Path) -> str | None:
    """Wait for the launcher to exit; stop it when the sweep is stopped, the scheduler
    cannot be reached, or the launcher outlives its deadline (``TIMED_OUT``). What
    stopped it, or None when it exited on its own."""
    try:
        pidfd: int | None = os.pidfd_open(job.proc.pid)
    except (AttributeError, OSError):  # not Linux >= 5.3: look every POLL_S
        pidfd = None
    try:
        while not job.exited():
            if time.monotonic() > job.deadline:
                _stop_launcher(job, runs_dir, lambda: False)
                return TIMED_OUT
            if pidfd is not None and select.select([pidfd], [], [], POLL_S)[0]:
                _reap(job)  # it exited
                break
            if pidfd is None:
                time.sleep(POLL_S)
            why = _stop_flag(client, task.token)
            if why is not None and not job.exited():
                _stop_launcher(job, runs_dir, lambda: why == "kill" or _stop_flag(client, task.token) == "kill")
                return why
        return None
    finally:
        if pidfd is not None:
            os.close(pidfd)


def _reap(job: Job) -> None:
    """The exit status (and CPU time) of a launcher known to have exited: the zygote's
    report of a forked one follows its exit."""
    if isinstance(job.proc, process_factory.ForkedProcess):
        try:
            job.proc.wait(timeout=LAUNCHER_GRACE_S)
        except subprocess.TimeoutExpired:  # the zygote is gone: nobody can tell its exit code
            job.proc.returncode = -signal.SIGKILL
        job.cpu_s = job.proc.cpu_s
    job.exited()


def _stop_flag(client: Client, token: str) -> str | None:
    """``"stop"`` (Ctrl-C), ``"kill"`` (a second one), ``"scheduler lost"``, or None."""
    try:
        return client.get_metadata(_meta(token, "stop"), default=None)
    except Exception as exc:  # the scheduler is gone: nobody will take this run's record
        log.warning("cannot reach the scheduler (%s); stopping the run", exc)
        return "scheduler lost"


def _stop_launcher(job: Job, runs_dir: Path, kill_now: Callable[[], bool]) -> None:
    """SIGINT to the launcher's group (it stops its processes in order), up to
    ``LAUNCHER_GRACE_S`` or until ``kill_now()``; then SIGKILL, and the processes it
    listed that still carry its run id (``runner.kill_run_processes``)."""
    _signal_group(job.proc.pid, signal.SIGINT)
    deadline = time.monotonic() + LAUNCHER_GRACE_S
    while not job.exited() and time.monotonic() < deadline:
        try:
            job.proc.wait(timeout=POLL_S)
        except subprocess.TimeoutExpired:
            if kill_now():
                break
    if not job.exited():
        _signal_group(job.proc.pid, signal.SIGKILL)
        job.proc.wait()
        kill_run_processes(runs_dir / job.run_id, job.run_id)


def lost_record(key: RunKey, run_id: str, workers: list[str]) -> dict[str, Any]:
    """A failed record for a run whose workers died during each of its attempts."""
    failure = (f"the worker died during each of its {len(workers)} attempts "
               f"({', '.join(workers) or 'the scheduler gave up on it'})")
    rec = record_of(key, run_id, -signal.SIGKILL, "", "", 0.0, {"lost_workers": workers, "attempt": len(workers)})
    rec["exit_code"] = None
    rec["wall_total_s"] = 0.0
    rec["error"] = {"exit_code": None, "failure": failure, "stderr_tail": ""}
    return rec


def worker_versions() -> dict[str, str]:
    """What the client compares on every worker: this package's version and revision."""
    return {"version": _version(), "git_revision": git_revision(), "python": sys.version.split()[0]}


def _version() -> str:
    try:
        return importlib_metadata.version(PACKAGE)
    except importlib_metadata.PackageNotFoundError:
        return "not installed"


# ---------------------------------------------------------------------------- the launch wrapper


def launch(argv: list[str]) -> int:
    """``python -m deploy.experiments.cluster launch WORKER_PID <autocast run args>``: ``autocast run``
    that gets SIGINT when the worker that started it dies, and so stops its processes."""
    parent = int(argv[0])
    with contextlib.suppress(OSError, AttributeError):
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(PR_SET_PDEATHSIG, signal.SIGINT, 0, 0, 0) != 0:
            log.warning("prctl(PR_SET_PDEATHSIG) failed: errno %d", ctypes.get_errno())
    if os.getppid() != parent:  # the worker died before the signal was armed
        print(f"autocast run: the worker (pid {parent}) is gone", file=sys.stderr)
        return EXIT_INTERRUPTED
    from deploy.launch.run import exit_now
    from deploy.launch.run import main as run_main

    exit_now(run_main(argv[1:]))
    return EXIT_INTERRUPTED  # not reached


# ---------------------------------------------------------------------------- the client


class ClusterLost(RuntimeError):
    """The scheduler could not be reached or went away."""


def connect(address: str) -> Client:
    """A client of the scheduler at ``address``, or named in the scheduler file at that
    path (``dask scheduler --scheduler-file``, as in a Slurm allocation)."""
    from distributed import Client

    where = {"scheduler_file": address} if Path(address).is_file() else {"address": address}
    try:
        return Client(**where, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
    except (OSError, TimeoutError, ValueError) as exc:
        raise ClusterLost(f"cannot reach the scheduler at {address}: {exc}") from None


def check_workers(client: Client, keys: list[RunKey]) -> None:
    """Refuse a cluster whose workers cannot run the plan: none offers enough ``vehicles``
    for its largest run, or one runs another version of this package."""
    workers = client.scheduler_info(n_workers=-1)["workers"]
    need = max(k.vehicles for k in keys)
    if not workers:
        log.warning("no worker is connected yet: the runs wait for workers with --resources \"%s=%d\" or more",
                    RESOURCE, need)
        return
    offers = {addr: w.get("resources", {}).get(RESOURCE, 0) for addr, w in workers.items()}
    if max(offers.values()) < need:
        raise SweepError(f"cluster: no worker offers {need} {RESOURCE} (the plan's largest run); they offer "
                         f"{', '.join(f'{a} {v:g}' for a, v in sorted(offers.items()))}; start workers with "
                         f"--resources \"{RESOURCE}={need}\" or more (docs/experiments.md)")
    try:
        found = client.run(worker_versions)
    except Exception as exc:
        raise SweepError(f"cluster: the workers cannot run this package's tasks ({type(exc).__name__}: {exc}); "
                         f"install {PACKAGE} {_version()} on every worker") from None
    mine = worker_versions()
    bad = {a: v["version"] for a, v in found.items() if v["version"] != mine["version"]}
    if bad:
        raise SweepError(f"cluster: workers run another version of {PACKAGE} than this client's {mine['version']}: "
                         + ", ".join(f"{a} {v}" for a, v in sorted(bad.items())))
    other = sorted(a for a, v in found.items() if v["git_revision"] != mine["git_revision"])
    if other:
        log.warning("workers at another git revision than this client's %s: %s", mine["git_revision"],
                    ", ".join(f"{a} {found[a]['git_revision']}" for a in other))
    log.info("cluster: %d workers, %s %s", len(workers), RESOURCE,
             ", ".join(f"{offers[a]:g}" for a in sorted(offers)))


class ClusterSweep:
    """Submits the runs, records each result as it arrives, stops them all on Ctrl-C."""

    def __init__(self, sweep: Sweep, client: Client) -> None:
        self.sweep, self.client = sweep, client
        self.token = secrets.token_hex(6)
        self.futures: dict[Future, RunKey] = {}
        self.done: queue.Queue[Future] = queue.Queue()
        self.model_done_s = self.model_left_s = 0.0
        self.stop_requested = False
        self.kill_requested = False

    def on_signal(self, signum: int, _frame: Any) -> None:
        if self.stop_requested:
            self.kill_requested = True
        self.stop_requested = True

    def execute(self, todo: list[RunKey], progress: Progress) -> tuple[int, bool]:
        """Run ``todo`` on the cluster; return (failed runs, interrupted). Raises
        ``ClusterLost`` when the scheduler goes away."""
        self.model_left_s = sum(estimate_run_s(k) for k in todo)
        for key in todo:  # in plan order: the scheduler starts equal-priority tasks first come, first served
            self._submit(key)
        failed = 0
        while self.futures:
            if self.stop_requested:
                self._stop(progress)
                return failed, True
            try:
                future = self.done.get(timeout=0.5)
            except queue.Empty:
                progress.draw([f"{len(self.futures)} runs on the cluster"], self._model())
                continue
            rec = self._collect(future)
            if rec is not None:
                failed += rec["status"] == "failed"
                progress.finished(rec, self._model())
        return failed, False

    def _submit(self, key: RunKey) -> None:
        task = ClusterRun(key, self._first_attempt(key), str(self.sweep.runs_dir), self.sweep.spec, self.token)
        future = self.client.submit(execute_run, task, key=f"autocast-{key.name}-{self.token}-{secrets.token_hex(3)}",
                                    resources={RESOURCE: key.vehicles}, pure=False)
        self.futures[future] = key
        future.add_done_callback(self.done.put)

    def _first_attempt(self, key: RunKey) -> int:
        """As ``Sweep._run_id``: past every attempt whose logs (or, on a shared
        filesystem, run directory) this client sees."""
        attempt = 1
        while True:
            run_id = key.name if attempt == 1 else f"{key.name}-a{attempt}"
            if not (self.sweep.logs_dir / f"{run_id}.out").exists() and not (self.sweep.runs_dir / run_id).exists():
                return attempt
            attempt += 1

    def _collect(self, future: Future) -> dict[str, Any] | None:
        """The finished task's record, appended to results.jsonl; None if there is none
        to record (the run goes on elsewhere, or the sweep is stopping)."""
        from distributed.scheduler import KilledWorker

        key = self.futures.pop(future)
        if future.cancelled():
            raise ClusterLost(f"the scheduler went away ({self._cancel_reason(future)})")
        try:
            result = future.result()
        except KilledWorker:  # the scheduler gave up before our second start: one more try
            starts = self.client.get_metadata(_meta(self.token, "starts", key.name), default=[])
            if len(starts) < MAX_STARTS:
                log.warning("%s: its worker died; running it again", key.name)
                self._submit(key)
                return None
            result = {"record": lost_record(key, key.name, starts)}
        except Exception as exc:  # the task itself failed (e.g. a worker without this package)
            if self.client.status != "running":
                raise ClusterLost(f"the scheduler went away ({exc})") from None
            rec = record_of(key, key.name, -1, "", "", 0.0)
            rec["error"] = {"exit_code": None, "failure": f"the task failed: {type(exc).__name__}: {exc}",
                            "stderr_tail": ""}
            result = {"record": rec}
        finally:
            future.release()
        if "stopped" in result:
            if self.stop_requested:
                return None
            log.warning("%s: stopped on its worker (%s); running it again", key.name, result["stopped"])
            self._submit(key)
            return None
        rec = result["record"]
        logs = self.sweep.logs_dir
        (logs / f"{rec['run_id']}.out").write_text(result.get("stdout", ""))
        err = result.get("stderr", "")
        if rec.get("lost_workers"):
            err = "".join(f"autocast sweep: attempt {i} on {w}: the worker died during the run\n"
                          for i, w in enumerate(rec["lost_workers"], 1)) + err
        (logs / f"{rec['run_id']}.err").write_text(err)
        append_record(self.sweep.results, rec)
        self.model_done_s += estimate_run_s(key)
        self.model_left_s -= estimate_run_s(key)
        return rec

    @staticmethod
    def _cancel_reason(future: Future) -> str:
        try:
            future.result(timeout=0)
        except Exception as exc:
            return str(exc) or type(exc).__name__
        return "cancelled"

    def _model(self) -> tuple[float, float]:
        return self.model_done_s, max(0.0, self.model_left_s)

    def _stop(self, progress: Progress) -> None:
        """Stop every run on the workers: the flag first, then read who started (a task
        sets its start before it reads the flag, so each either is seen started here or
        sees the flag); cancel the rest; wait for the started ones to stop their runs."""
        log.info("stopping: the started runs stop their processes (Ctrl-C again: kill them)")
        try:
            self.client.set_metadata(_meta(self.token, "stop"), "stop")
            started = set(self.client.get_metadata(_meta(self.token, "starts"), default={}))
        except Exception as exc:
            raise ClusterLost(f"the scheduler went away ({exc})") from None
        waiting = {f for f, k in self.futures.items() if k.name in started}
        self.client.cancel([f for f in self.futures if f not in waiting])
        deadline = time.monotonic() + LAUNCHER_GRACE_S + STOP_SLACK_S
        killed = False
        while waiting and time.monotonic() < deadline:
            if self.kill_requested and not killed:
                with contextlib.suppress(Exception):
                    self.client.set_metadata(_meta(self.token, "stop"), "kill")
                killed = True
            try:
                future = self.done.get(timeout=0.5)
            except queue.Empty:
                continue
            if future in waiting:
                waiting.discard(future)
                rec = self._collect(future)  # a run that ended on its own before the flag is recorded whole
                if rec is not None:
                    progress.finished(rec, self._model())
        if waiting:
            log.warning("%d tasks did not answer within %.0f s: %s", len(waiting), LAUNCHER_GRACE_S + STOP_SLACK_S,
                        ", ".join(sorted(self.futures[f].name for f in waiting)))
        self.client.cancel(list(self.futures))
        self.futures.clear()


def run_on_cluster(sweep: Sweep, keys: list[RunKey], todo: list[RunKey], address: str) -> int:
    """The cluster half of ``run_sweep``: connect, check the workers, run, summarise."""
    try:
        import distributed  # noqa: F401
    except ImportError:
        print(f"error: cluster: the Dask client is not installed: pip install '{PACKAGE}[cluster]'", file=sys.stderr)
        return EXIT_BAD_INPUT
    t0 = time.monotonic()
    try:
        client = connect(address)
    except ClusterLost as exc:
        print(f"error: cluster: {exc}", file=sys.stderr)
        return EXIT_CLUSTER_LOST
    interrupted = False
    try:
        try:
            check_workers(client, todo)
        except SweepError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return EXIT_BAD_INPUT
        runner = ClusterSweep(sweep, client)
        signal.signal(signal.SIGINT, runner.on_signal)
        signal.signal(signal.SIGTERM, runner.on_signal)
        progress = Progress(len(todo))
        try:
            _, interrupted = runner.execute(todo, progress)
        except ClusterLost as exc:
            progress.close()
            print(f"error: cluster: {exc}; {len(read_results(sweep.results))} records in {sweep.results}; the runs "
                  "still on the workers stop and are not recorded; the same command resumes the sweep", file=sys.stderr)
            return EXIT_CLUSTER_LOST
        finally:
            progress.close()
        with contextlib.suppress(Exception):
            client.set_metadata(_meta(runner.token), None)  # the sweep's flag and counts
    finally:
        with contextlib.suppress(Exception):
            client.close(timeout=10)
    return finish_sweep(sweep.spec, keys, sweep.out, t0, interrupted)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["launch"] and len(argv) > 1 and argv[1].isdigit():
        return launch(argv[1:])
    print("usage: python -m deploy.experiments.cluster launch WORKER_PID <autocast run arguments>  (started by the "
          "tasks of autocast sweep --cluster)", file=sys.stderr)
    return EXIT_BAD_INPUT


if __name__ == "__main__":
    sys.exit(main())
