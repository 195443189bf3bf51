"""Starting, watching and stopping the processes of a run (openpilot manager style).

A run is a table of ``ProcSpec`` rows (``deploy/table.py``); the manager only starts
what the table says, notices a process that died (the watchdog), and stops everything
the same way every time: SIGINT, a grace period, then SIGKILL. Each child gets its own
session (process group), so a Ctrl-C in the terminal reaches the launcher only, which
then stops children in order instead of all of them at once.

Where a warm process factory is active (``deploy/factory.py``: the launcher makes one
before it opens its Zenoh hub), a process is forked from it instead of started with
``Popen``: the same command line, log, session and exit code, without importing the
stack and loading the numba kernels again. ``AUTOCAST_FACTORY=popen`` forces Popen.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from deploy import factory as process_factory

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class ProcSpec:
    """One process of a run: ``python -m <module> <args>``."""

    name: str
    module: str
    args: tuple[str, ...] = ()
    critical: bool = False  # the run cannot reach a judged outcome without it

    def argv(self) -> list[str]:
        return [sys.executable, "-m", self.module, *self.args]


Proc = subprocess.Popen | process_factory.ForkedProcess


class ProcessManager:
    def __init__(self, log_dir: Path | None = None, factory: process_factory.Factory | None = None) -> None:
        """``factory``: fork processes from it; default the process's active factory, if any."""
        self.log_dir = log_dir
        self.factory = factory if factory is not None else process_factory.current()
        self.procs: dict[str, tuple[ProcSpec, Proc]] = {}
        self._reported: set[str] = set()

    def start(self, spec: ProcSpec) -> Proc:
        """Start ``spec``; its stdout and stderr go to ``<log_dir>/<name>.log``."""
        if spec.name in self.procs:
            raise ValueError(f"process {spec.name!r} started twice")
        out = subprocess.DEVNULL
        if self.log_dir is not None:
            self.log_dir.mkdir(parents=True, exist_ok=True)
            out = open(self.log_dir / f"{spec.name}.log", "wb")
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        try:
            proc = self._fork(spec, out, env) if self.factory is not None else None
            if proc is None:
                proc = subprocess.Popen(spec.argv(), stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                        start_new_session=True, env=env)
        finally:
            if out is not subprocess.DEVNULL:
                out.close()  # the child holds its own descriptor
        self.procs[spec.name] = (spec, proc)
        log.debug("started %s (pid %d%s): %s", spec.name, proc.pid, ", forked" if self.factory else "",
                  " ".join(spec.argv()))
        return proc

    def _fork(self, spec: ProcSpec, out, env: dict[str, str]) -> process_factory.ForkedProcess | None:
        """``spec`` forked from the factory; None (and Popen from now on) if the factory failed."""
        try:
            return self.factory.spawn(spec.module, spec.args, stdout=None if out is subprocess.DEVNULL else out.fileno(),
                                      env=env)
        except process_factory.FactoryError as exc:
            log.warning("process factory failed (%s); starting processes with Popen", exc)
            self.factory = None
            return None

    def pids(self) -> dict[str, int]:
        return {name: proc.pid for name, (_, proc) in self.procs.items()}

    def running(self) -> list[str]:
        return [name for name, (_, proc) in self.procs.items() if proc.poll() is None]

    def died(self) -> list[tuple[ProcSpec, int]]:
        """Processes that exited since the last call (watchdog); each reported once."""
        out = []
        for name, (spec, proc) in self.procs.items():
            rc = proc.poll()
            if rc is not None and name not in self._reported:
                self._reported.add(name)
                out.append((spec, rc))
        return out

    def wait(self, names: Iterable[str], timeout_s: float) -> list[str]:
        """Wait up to ``timeout_s`` for ``names`` to exit on their own; return those still running."""
        deadline = time.monotonic() + timeout_s
        left = [n for n in names if n in self.procs]
        while left:
            left = [n for n in left if self.procs[n][1].poll() is None]
            if not left or time.monotonic() >= deadline:
                break
            time.sleep(0.05)
        return left

    def stop(self, names: Iterable[str], grace_s: float = 3.0) -> None:
        """SIGINT ``names`` together, wait up to ``grace_s``, SIGKILL what is left; reap all."""
        running = [self.procs[n][1] for n in names if n in self.procs and self.procs[n][1].poll() is None]
        for p in running:
            _signal(p, signal.SIGINT)
        deadline = time.monotonic() + grace_s
        for p in running:
            try:
                p.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("pid %d ignored SIGINT for %.1f s; killing", p.pid, grace_s)
                _signal(p, signal.SIGKILL)
                p.wait()

    def stop_all(self, grace_s: float = 3.0) -> None:
        self.stop(list(self.procs), grace_s)

    def __enter__(self) -> "ProcessManager":
        return self

    def __exit__(self, *exc) -> None:
        self.stop_all()


def exit_records(log_dir: Path, tag: str) -> dict[str, dict]:
    """``{process: record}`` from the last ``<tag> {json}`` line of each ``<name>.log``
    (e.g. the ``malformed_dropped`` line every process prints as it exits); a process
    without one (it did not exit normally, or runs on another host) is left out."""
    out: dict[str, dict] = {}
    prefix = tag + " "
    for path in sorted(log_dir.glob("*.log")) if log_dir.is_dir() else []:
        for line in path.read_text(errors="replace").splitlines():
            if line.startswith(prefix):
                try:
                    out[path.stem] = json.loads(line[len(prefix):])
                except ValueError:
                    log.warning("%s: unreadable %s line", path, tag)
    return out


def has_argument(pid: int, word: str) -> bool:
    """Whether ``word`` is one of process ``pid``'s arguments as ``/proc/<pid>/cmdline``
    shows them: one string per argument, or, for a forked child whose arguments do not
    fit its parent's (``deploy.factory``), one string with spaces between them."""
    try:
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:  # gone
        return False
    return word.encode() in cmdline.replace(b"\0", b" ").split()


def batch_scheduling(batch: bool = True) -> bool:
    """Put every thread of this process under Linux's ``SCHED_BATCH`` policy (``batch``),
    or take those under it back to the default ``SCHED_OTHER`` (not ``batch``; other
    policies are left alone), and so every thread and process it starts from now on
    (fork, threads and exec inherit the policy). Returns whether every thread is now so
    (False on other systems, or where the kernel refuses).

    A lock-step run is tens of CPU-bound processes on a few cores that wake together at
    each phase of an interval. Under the default policy a process that wakes preempts the
    one running, which then finishes its stage later on cold caches; under ``SCHED_BATCH``
    it waits for the running one to block or use up its slice. At 40 vehicles on 2 cores
    the real-time factor rose 2% (docs/architecture.md). No privilege is needed: it lowers
    no priority, it only gives up preempting on wake-up. A real-time run wants the
    opposite: a late wake-up is a late command."""
    if not hasattr(os, "SCHED_BATCH"):
        return False
    want = os.SCHED_BATCH if batch else os.SCHED_OTHER
    try:
        tids = [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:  # no /proc: the calling thread, whose later threads and children inherit it
        tids = [0]
    done = True
    for tid in tids:
        try:
            if batch or os.sched_getscheduler(tid) == os.SCHED_BATCH:
                os.sched_setscheduler(tid, want, os.sched_param(0))
        except ProcessLookupError:  # a thread that ended meanwhile
            continue
        except OSError as exc:  # a kernel or sandbox that refuses
            log.debug("scheduling policy %d for thread %d: %s", want, tid, exc)
            done = False
    return done


def _signal(proc: Proc, sig: int) -> None:
    try:
        os.killpg(proc.pid, sig)  # the child leads its own process group
    except ProcessLookupError:
        pass
