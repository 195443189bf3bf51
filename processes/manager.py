"""Starting, watching and stopping the processes of a run (openpilot manager style).

A run is a table of ``ProcSpec`` rows (``deploy/launch/table.py``); the manager only starts
what the table says, notices a process that died (the watchdog), and stops everything
the same way every time: SIGINT, a grace period, then SIGKILL. Each child gets its own
session (process group), so a Ctrl-C in the terminal reaches the launcher only, which
then stops children in order instead of all of them at once.

Where a warm process factory is active (``processes/factory.py``: the launcher makes one
before it opens its Zenoh hub), a process is forked from it instead of started with
``Popen``: the same command line, log, session and exit code, without importing the
stack and loading the numba kernels again. ``AUTOCAST_FACTORY=popen`` forces Popen.
"""

from __future__ import annotations

import ctypes
import errno
import functools
import json
import logging
import os
import platform
import signal
import struct
import subprocess
import sys
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from processes import factory as process_factory

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
        """SIGINT ``names`` together (SIGCONT too: a stopped one finishes as the others do),
        wait up to ``grace_s``, SIGKILL what is left; reap all."""
        running = [self.procs[n][1] for n in names if n in self.procs and self.procs[n][1].poll() is None]
        for p in running:
            _signal(p, signal.SIGINT)
            _signal(p, signal.SIGCONT)  # a stopped process (SIGSTOP) acts on it only once continued
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


def process_cpu_s(pid: int, reaped_children: bool = False) -> float | None:
    """User + system CPU seconds of process ``pid`` so far, every thread of it, the ended
    ones included (its CPU-time clock, nanoseconds; Linux: clock id ``~pid << 3 | 2``),
    and with ``reaped_children`` those of the children it has waited for (``/proc``'s
    cutime and cstime, in clock ticks); None where there is no such clock or process."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        total = time.clock_gettime((~pid << 3) | 2)
        if reaped_children:
            with open(f"/proc/{pid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
            total += (int(fields[13]) + int(fields[14])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):  # gone, or not ours to read
        return None
    return total


def usable_cores() -> int:
    """The cores this process may run on (its affinity), else the machine's."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


class RunCpu:
    """What each process of a run spends while the run ticks: its CPU at the world's
    first tick (``first_tick``, from its CPU-time clock) and at its exit (the factory's
    ``wait4``), and the launcher's own at the first tick and at the outcome. Reported per
    tick and by role (``per_tick_ms``) where every process was forked from the factory
    on this host; ``None`` otherwise (``Popen``, whose exit CPU nobody collects)."""

    def __init__(self, procs: "ProcessManager") -> None:
        self.procs = procs
        self._at_tick: dict[str, float] | None = None
        self._launcher: list[float] = []

    @property
    def ticking(self) -> bool:
        return self._at_tick is not None

    def first_tick(self) -> None:
        """At the world's first tick (once; later calls do nothing)."""
        if self._at_tick is not None:
            return
        launcher = time.process_time()  # every thread of the launcher, its Zenoh hub's too
        at = {name: process_cpu_s(pid) for name, pid in self.procs.pids().items()}
        self._launcher = [launcher]
        self._at_tick = {name: cpu for name, cpu in at.items() if cpu is not None}

    def outcome(self) -> None:
        if len(self._launcher) == 1:
            self._launcher.append(time.process_time())

    def per_tick_ms(self, ticks: int) -> dict[str, float] | None:
        """ms of CPU per tick by role (``agents``: every ``agent<vid>`` together; the
        launcher: its Zenoh hub and itself) and ``all``, from the first tick to each
        process's exit (the launcher: to the outcome); after every process has exited."""
        if self._at_tick is None or len(self._launcher) != 2 or ticks < 1:
            return None
        by_role: dict[str, float] = {}
        for name, (_, proc) in self.procs.procs.items():
            end = getattr(proc, "cpu_s", None)
            if end is None or name not in self._at_tick:
                return None
            role = "agents" if name.startswith("agent") else name
            by_role[role] = by_role.get(role, 0.0) + end - self._at_tick[name]
        by_role["launcher"] = self._launcher[1] - self._launcher[0]
        by_role["all"] = sum(by_role.values())
        return {role: round(cpu_s * 1e3 / ticks, 2) for role, cpu_s in by_role.items()}


def has_argument(pid: int, word: str) -> bool:
    """Whether ``word`` is one of process ``pid``'s arguments as ``/proc/<pid>/cmdline``
    shows them: one string per argument, or, for a forked child whose arguments do not
    fit its parent's (``processes.factory``), one string with spaces between them."""
    try:
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:  # gone
        return False
    return word.encode() in cmdline.replace(b"\0", b" ").split()


# sched_setattr(2)'s and sched_getattr(2)'s numbers, for a 64-bit process on these machines
# (the generic table's 274 on the newer ones); elsewhere, a 32-bit Python on a 64-bit kernel
# included, only the policy is set
_SCHED_SETATTR = {"x86_64": 314, "aarch64": 274, "riscv64": 274, "loongarch64": 274, "ppc64le": 355,
                  "ppc64": 355, "s390x": 345}.get(platform.machine()) if struct.calcsize("P") == 8 else None
_SCHED_GETATTR = {314: 315, 274: 275, 355: 356, 345: 346}.get(_SCHED_SETATTR)
_SCHED_ATTR = struct.Struct("=IIQiIQQQ")  # struct sched_attr as of Linux 3.14 (SCHED_ATTR_SIZE_VER0)
_FAIR = frozenset(getattr(os, name) for name in ("SCHED_OTHER", "SCHED_BATCH", "SCHED_IDLE") if hasattr(os, name))
BATCH_SLICE_MS = 20.0  # longer than any stage of a lock-step tick: a stage runs on to its end
SLICE_RANGE_MS = (0.1, 100.0)  # what Linux takes (it clamps the rest)


def batch_scheduling(batch: bool = True, slice_ms: float = BATCH_SLICE_MS) -> bool:
    """Put every thread of this process under Linux's ``SCHED_BATCH`` policy (``batch``)
    with a time slice of ``slice_ms``, or take those under it back to the default
    ``SCHED_OTHER`` and its default slice (not ``batch``; other policies are left alone),
    and so every thread and process it starts from now on (fork, threads and exec inherit
    both). Each thread keeps its nice value. Returns whether every thread now has the
    policy (False on other systems, or where the kernel refuses); a slice the kernel does
    not take is logged once as a warning.

    A lock-step run is tens of CPU-bound processes on a few cores that wake together at
    each phase of an interval. Under the default policy a process that wakes preempts the
    one running, which then finishes its stage later on cold caches; under ``SCHED_BATCH``
    it waits for the running one to block or use up its slice. The slice: Linux 6.12 and
    later let a thread ask for its own (``sched_setattr``'s ``sched_runtime``); earlier
    kernels ignore it. The default (1.4 ms on this project's 2-core machines, with Linux
    6.18) is about one agent stage, so half the stages were cut in two, each half resumed
    on cold caches. At 40 vehicles on 2 cores the policy raised the real-time factor 2%,
    the slice 3% more (docs/performance.md). No privilege is needed: neither raises a
    priority, they only give up preempting on wake-up and being preempted at the end of
    the default slice. A real-time run wants the opposite: a late wake-up is a late
    command."""
    if not hasattr(os, "SCHED_BATCH"):
        return False
    if batch and not SLICE_RANGE_MS[0] <= slice_ms <= SLICE_RANGE_MS[1]:
        raise ValueError(f"slice_ms must lie in [{SLICE_RANGE_MS[0]}, {SLICE_RANGE_MS[1]}], not {slice_ms}")
    want = os.SCHED_BATCH if batch else os.SCHED_OTHER
    slice_ns = round(slice_ms * 1e6) if batch else 0  # 0: the kernel's default
    try:
        tids = [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:  # no /proc: the calling thread, whose later threads and children inherit it
        tids = [0]
    done, slice_refused = True, None
    # a thread started meanwhile by one not yet visited keeps its policy: a run calls this
    # before it starts any (deploy.launch.run)
    for tid in tids:
        try:
            if batch or os.sched_getscheduler(tid) == os.SCHED_BATCH:
                slice_refused = _set_scheduling(tid, want, slice_ns) or slice_refused
        except ProcessLookupError:  # a thread that ended meanwhile
            continue
        except OSError as exc:  # a kernel or sandbox that refuses
            log.debug("scheduling policy %d for thread %d: %s", want, tid, exc)
            done = False
    if slice_refused and slice_ns:
        log.warning("the kernel did not take a %g ms time slice (%s): the default applies", slice_ms, slice_refused)
    return done


def _set_scheduling(tid: int, policy: int, slice_ns: int) -> str | None:
    """``policy`` (a fair one) for thread ``tid``, its nice value kept, and, where the
    kernel has ``sched_setattr``, the slice ``slice_ns`` (0: the default). Returns why the
    slice was not set (None if it was, or where there is no ``sched_setattr``); raises
    ``OSError`` if the policy is refused."""
    refused = None
    if _SCHED_SETATTR is not None:
        nice = os.getpriority(os.PRIO_PROCESS, tid)  # per thread on Linux; sched_setattr sets it too
        attr = ctypes.create_string_buffer(_SCHED_ATTR.pack(_SCHED_ATTR.size, policy, 0, nice, 0, slice_ns, 0, 0),
                                           _SCHED_ATTR.size)
        if _syscall(_SCHED_SETATTR, tid, attr, 0) == 0:
            return None
        err = ctypes.get_errno()
        if err == errno.ESRCH:
            raise ProcessLookupError(err, os.strerror(err))
        refused = os.strerror(err)
    os.sched_setscheduler(tid, policy, os.sched_param(0))  # sched_setscheduler keeps a slice as it is
    return refused


def scheduling(tid: int = 0) -> tuple[int, int | None]:
    """Thread ``tid``'s policy and, for a fair policy, its time slice in ns (None where
    the kernel does not say: no ``sched_getattr``, or a kernel before 6.12, which reports
    0; None for other policies)."""
    policy = os.sched_getscheduler(tid)
    if _SCHED_GETATTR is None or policy not in _FAIR:
        return policy, None
    buf = ctypes.create_string_buffer(_SCHED_ATTR.size)
    if _syscall(_SCHED_GETATTR, tid, buf, _SCHED_ATTR.size, 0) != 0:
        return policy, None
    slice_ns = _SCHED_ATTR.unpack(buf.raw)[5]
    return policy, slice_ns or None


def _syscall(number: int, *args: int | ctypes.Array) -> int:
    """libc's ``syscall``, every integer argument as a long (it reads each as one)."""
    return _libc().syscall(ctypes.c_long(number), *(a if isinstance(a, ctypes.Array) else ctypes.c_long(a)
                                                   for a in args))


@functools.cache
def _libc() -> ctypes.CDLL:
    libc = ctypes.CDLL(None, use_errno=True)
    libc.syscall.restype = ctypes.c_long
    return libc


def _signal(proc: Proc, sig: int) -> None:
    try:
        os.killpg(proc.pid, sig)  # the child leads its own process group
    except ProcessLookupError:
        pass
