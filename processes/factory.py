"""A warm process factory: a run's processes forked from a parent that is already warm.

Started the usual way, every process of a run (``python -m world_server ...``) imports
numpy, numba, zenoh, msgpack and pymunk and loads its numba kernels from the cache
again: ~0.7 s of CPU each, 40+ times per run. A ``Factory`` forks, once, a *zygote*
from the process that owns it (the launcher, or a sweep), after that process has
imported the stack and loaded every kernel and before it opens any Zenoh session.
The zygote imports the process modules it will run and then only forks: each child
it forks on request starts with everything loaded, becomes its own session and
process group (as ``start_new_session=True`` does), points its stdin, stdout and stderr
where the owner says (the owner passes the descriptors over the socket), resets what
it inherited (signal handlers, standard streams, the root logger, environment, working
directory), names itself after the command line ``Popen`` would have run, and runs
the module as ``python -m`` does (``runpy``). It opens its own Zenoh session itself:
no session exists in the zygote or its owner when the zygote is forked (``import
zenoh`` starts no thread; a session starts Zenoh's runtime threads, which a fork would
not carry over), and a factory refuses to be made in a process with any thread
besides the main one and numpy's BLAS workers (whose at-fork handlers make them safe).

Exits. The zygote is the children's parent: it reaps each one (``wait4``) and reports
its exit code (Popen's convention: -N for a signal), CPU time and peak RSS to the
owner over the same socket. ``ForkedProcess`` gives the owner Popen's interface
(``pid``, ``poll``, ``wait``, ``returncode``) over those reports, so the launcher's
watchdog, its staged stop (SIGINT to the child's group, grace, SIGKILL) and the tests
see the same codes as with Popen. The zygote leads its own process group, so a
Ctrl-C in the terminal or a SIGKILL of the owner's group does not reach it; when the
owner dies or closes the factory, its end of the socket closes, and the zygote
stops every child still running (SIGINT, a grace period, SIGKILL) and exits.

``AUTOCAST_FACTORY=popen`` (or ``off``/``0``) forces ``subprocess.Popen`` (A/B
comparisons); a factory that cannot be made or used falls back to it too.
(docs/architecture.md, "The process factory")
"""

from __future__ import annotations

import contextlib
import ctypes
import gc
import importlib
import io
import json
import logging
import os
import runpy
import select
import signal
import socket
import subprocess
import sys
import threading
import time
import traceback
from collections.abc import Iterable, Iterator, Mapping, Sequence
from typing import NoReturn

log = logging.getLogger(__name__)

ENV = "AUTOCAST_FACTORY"
OFF_VALUES = ("0", "off", "popen", "no", "false")
# The modules a run's processes are (deploy/launch/table.py): imported once in the zygote.
RUN_MODULES = ("world_server.__main__", "channel_proxy.__main__", "vehicle_agent.__main__", "deploy.record.recorder")
STOP_GRACE_S = 3.0  # the owner is gone: children get this long after SIGINT before SIGKILL
_MAX_MSG = 1 << 20
_MAX_FDS = 3

_current: Factory | None = None  # the factory ProcessManager uses in this process, if any


class FactoryError(RuntimeError):
    """The factory cannot be made here, or stopped answering."""


def disabled() -> bool:
    """``AUTOCAST_FACTORY=popen`` (``off``, ``0``, ``no``, ``false``): start processes with Popen."""
    return os.environ.get(ENV, "").strip().lower() in OFF_VALUES


def fork_unsafe_reason() -> str | None:
    """Why forking a zygote here would hand it a broken runtime; None if it is safe.

    Python threads (other than the main one) and named native threads (Zenoh's runtime
    workers are ``app-0``, ``net-0``, ``acc-0``...; they stay after a session closes)
    would not exist in a forked child while their locks and state would. numpy's BLAS
    workers share the main thread's name and shut down and restart across a fork."""
    if not hasattr(os, "fork"):
        return "this platform cannot fork"
    if threading.active_count() > 1:
        return f"{threading.active_count() - 1} Python threads are running"
    try:
        main = _comm("self")
        others = sorted({_comm(f"self/task/{t}") for t in os.listdir("/proc/self/task")} - {main})
    except OSError:
        return "cannot list this process's threads"
    if others:
        return f"native threads are running ({', '.join(others)}): a Zenoh session was opened in this process?"
    return None


def _comm(path: str) -> str:
    with open(f"/proc/{path}/comm") as f:
        return f.read().strip()


def current() -> Factory | None:
    """The factory ``ProcessManager`` starts processes with in this process (None: Popen)."""
    return _current if _current is not None and _current.alive else None


@contextlib.contextmanager
def activated(preload: Sequence[str] = RUN_MODULES) -> Iterator[Factory | None]:
    """Make a factory the current one for the block (None if disabled or impossible here:
    processes then start with Popen); stop it, and whatever it still runs, at the end."""
    global _current
    if disabled() or _current is not None:
        yield _current
        return
    try:
        factory = Factory(preload)
    except FactoryError as exc:
        log.warning("process factory unavailable (%s); starting processes with Popen", exc)
        yield None
        return
    _current = factory
    try:
        yield factory
    finally:
        _current = None
        factory.close()


# ---------------------------------------------------------------------------- the owner's side


class ForkedProcess:
    """One child of the zygote, with ``subprocess.Popen``'s interface."""

    def __init__(self, factory: Factory, pid: int, args: list[str]) -> None:
        self._factory = factory
        self.pid = pid
        self.args = args
        self.returncode: int | None = None
        self.cpu_s: float | None = None  # user + system, from the zygote's wait4
        self.maxrss_kib: int | None = None

    def poll(self) -> int | None:
        if self.returncode is None:
            self._factory.pump(0.0)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.returncode is None:
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                raise subprocess.TimeoutExpired(self.args, timeout)
            self._factory.pump(0.5 if left is None else min(left, 0.5))
        return self.returncode

    def send_signal(self, sig: int) -> None:
        if self.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, sig)

    def terminate(self) -> None:
        self.send_signal(signal.SIGTERM)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)

    def _exited(self, rc: int, cpu_s: float, maxrss_kib: int) -> None:
        self.returncode, self.cpu_s, self.maxrss_kib = rc, cpu_s, maxrss_kib

    def __repr__(self) -> str:
        return f"ForkedProcess(pid={self.pid}, returncode={self.returncode})"


class Factory:
    """A zygote forked from this process, and the handles of the children it forked."""

    def __init__(self, preload: Sequence[str] = RUN_MODULES, start: str = "fork",
                 stop_grace_s: float = STOP_GRACE_S) -> None:
        """``start="fork"``: the zygote is a fork of this process, warm with all it has
        loaded (refused where that is unsafe, see ``fork_unsafe_reason``); ``"exec"``: a
        fresh interpreter (``python -m processes.factory``) that imports ``preload``, for an
        owner that cannot fork (it has a Zenoh session, or threads: a Dask worker); its
        children load their kernels, unless a ``"module:function"`` entry of ``preload``
        loaded them in the zygote (called after the import). ``stop_grace_s``: how long
        the children get after SIGINT when the owner goes, before SIGKILL."""
        if start not in ("fork", "exec"):
            raise ValueError(f"start: {start!r} is not fork or exec")
        reason = fork_unsafe_reason() if start == "fork" else None
        if reason is not None:
            raise FactoryError(reason)
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self._popen: subprocess.Popen | None = None
        if start == "exec":
            self._popen = subprocess.Popen([sys.executable, "-m", "processes.factory", str(theirs.fileno()),
                                            f"--stop-grace-s={stop_grace_s!r}", *preload],
                                           pass_fds=[theirs.fileno()], stdin=subprocess.DEVNULL,
                                           stdout=subprocess.DEVNULL)
            pid = self._popen.pid
        else:
            _flush_std_streams()  # nothing buffered here may be written twice
            pid = os.fork()
            if pid == 0:  # the zygote
                code = 1
                try:
                    ours.close()
                    code = _Zygote(theirs, tuple(preload), stop_grace_s).serve()
                except BaseException:
                    traceback.print_exc()
                finally:
                    os._exit(code)
        theirs.close()
        self.pid = pid
        self._sock = ours
        self._lock = threading.RLock()
        self._children: dict[int, ForkedProcess] = {}
        self._replies: list[dict] = []
        self._unclaimed: dict[int, dict] = {}  # exits reported before the spawn reply was read
        self.alive = True
        self.closed = False
        log.debug("process factory: zygote pid %d (%s)", pid, start)

    # -------------------------------------------------------------- requests

    def spawn(self, module: str, args: Sequence[str] = (), *, stdout: int | None = None, stderr: int | None = None,
              stdin: int | None = None, env: Mapping[str, str] | None = None, cwd: str | None = None) -> ForkedProcess:
        """Fork ``python -m module args`` from the zygote. ``stdout``/``stderr``/``stdin``:
        descriptors for the child (None: /dev/null; ``stderr`` None: where stdout goes)."""
        for fd in (stdin, stdout, stderr):
            if fd is not None:
                os.fstat(fd)  # a bad descriptor fails here (OSError), not the factory
        devnull = os.open(os.devnull, os.O_RDWR)
        try:
            fds = [devnull if stdin is None else stdin, devnull if stdout is None else stdout]
            fds.append(fds[1] if stderr is None else stderr)
            req = {"op": "spawn", "module": module, "args": list(args), "cwd": cwd or os.getcwd(),
                   "env": dict(os.environ if env is None else env), "python": sys.executable}
            with self._lock:
                self._send(req, fds)
                reply = self._reply()
                if "error" in reply:
                    raise FactoryError(f"the zygote could not start {module}: {reply['error']}")
                proc = ForkedProcess(self, reply["pid"], [sys.executable, "-m", module, *args])
                self._children[proc.pid] = proc
                early = self._unclaimed.pop(proc.pid, None)  # it exited before we knew it
                if early is not None:
                    proc._exited(early["rc"], early["cpu_s"], early["maxrss_kib"])
        finally:
            os.close(devnull)
        return proc

    def _send(self, msg: dict, fds: Sequence[int] = ()) -> None:
        if not self.alive:
            raise FactoryError("the zygote is gone")
        try:
            socket.send_fds(self._sock, [json.dumps(msg).encode()], list(fds))
        except OSError as exc:
            self._lost(f"cannot reach the zygote: {exc}")
            raise FactoryError("the zygote is gone") from exc

    def _reply(self) -> dict:
        while not self._replies:
            if not self.alive:
                raise FactoryError("the zygote exited before it answered")
            self.pump(1.0)
        return self._replies.pop(0)

    # -------------------------------------------------------------- reports

    def pump(self, timeout_s: float) -> None:
        """Read what the zygote reported (exits, replies), waiting up to ``timeout_s`` for the first."""
        with self._lock:
            wait = timeout_s
            while self.alive:
                ready, _, _ = select.select([self._sock], [], [], wait)
                if not ready:
                    return
                wait = 0.0
                try:
                    data = self._sock.recv(_MAX_MSG)
                except OSError as exc:
                    self._lost(f"lost the zygote: {exc}")
                    return
                if not data:
                    self._lost("the zygote exited")
                    return
                msg = json.loads(data)
                if msg.get("op") == "exit":
                    child = self._children.get(msg["pid"])
                    if child is None:  # a child that exited at once: its exit can come in the
                        self._unclaimed[msg["pid"]] = msg  # same read as the reply that names it
                        continue
                    child._exited(msg["rc"], msg["cpu_s"], msg["maxrss_kib"])
                    log.debug("pid %d (%s) exited: code %d, %.2f s CPU, peak RSS %d MiB", msg["pid"],
                              child.args[2], msg["rc"], msg["cpu_s"], msg["maxrss_kib"] // 1024)
                else:
                    self._replies.append(msg)

    def _lost(self, why: str) -> None:
        """The zygote is gone: its children are nobody's to reap any more; their exit
        codes cannot be known, so a child found gone reads as killed (-9)."""
        if self.alive and not self.closed:
            log.error("process factory: %s", why)
        self.alive = False
        for child in self._children.values():
            if child.returncode is None and not _pid_alive(child.pid):
                child._exited(-signal.SIGKILL, float("nan"), 0)

    def close(self, grace_s: float = STOP_GRACE_S) -> None:
        """Tell the zygote to stop (it stops what still runs) and reap it."""
        if self.closed:
            return
        self.closed = True
        with contextlib.suppress(OSError):
            self._sock.shutdown(socket.SHUT_WR)
        deadline = time.monotonic() + grace_s + 5.0
        while self.alive and time.monotonic() < deadline:
            self.pump(0.2)
        self._sock.close()
        self.alive = False
        if self._popen is not None:
            try:
                self._popen.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                self._popen.kill()
                self._popen.wait()
        else:
            _reap(self.pid, deadline)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _reap(pid: int, deadline: float) -> None:
    while True:
        try:
            done, _ = os.waitpid(pid, os.WNOHANG)
        except ChildProcessError:
            return
        if done:
            return
        if time.monotonic() > deadline:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            return
        time.sleep(0.01)


# ---------------------------------------------------------------------------- the zygote


class _Zygote:
    """Single-threaded: forks on request, reaps and reports, stops all when its owner goes."""

    def __init__(self, sock: socket.socket, preload: tuple[str, ...], stop_grace_s: float = STOP_GRACE_S) -> None:
        global _current
        _current = None
        self.sock = sock
        self.stop_grace_s = stop_grace_s
        self.children: set[int] = set()
        os.setpgid(0, 0)  # out of the owner's group: its Ctrl-C or SIGKILL of the group is not ours
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        self.term = False
        signal.signal(signal.SIGTERM, self._on_term)
        gc.collect()  # the owner's garbage goes now, before its descriptors are closed below
        gc.freeze()  # and what is left is never scanned again: its pages stay shared with the children
        devnull = os.open(os.devnull, os.O_RDWR)
        for fd in (0, 1):  # hold none of the owner's pipes (a reader waits for their end); stderr stays
            os.dup2(devnull, fd)
        _close_fds_from(3, keep=sock.fileno())
        self.wake_r, self.wake_w = os.pipe()
        os.set_blocking(self.wake_r, False)
        os.set_blocking(self.wake_w, False)
        signal.set_wakeup_fd(self.wake_w)
        signal.signal(signal.SIGCHLD, lambda *_: None)  # wakes the select through the wakeup fd
        for name in preload:  # "module", or "module:function" to call after the import (a warm-up)
            module, _, function = name.partition(":")
            try:
                loaded = importlib.import_module(module)
                if function:
                    getattr(loaded, function)()
            except Exception:  # the child will raise it where it can be seen, in its log
                log.debug("zygote: cannot preload %s", name, exc_info=True)
        gc.freeze()

    def _on_term(self, *_: object) -> None:
        self.term = True

    def serve(self) -> int:
        while not self.term:
            try:
                ready, _, _ = select.select([self.sock, self.wake_r], [], [])
            except InterruptedError:
                continue
            if self.wake_r in ready:
                with contextlib.suppress(BlockingIOError):
                    while os.read(self.wake_r, 512):
                        pass
            if not self._reap():
                break
            if self.sock in ready:
                try:
                    data, fds, _, _ = socket.recv_fds(self.sock, _MAX_MSG, _MAX_FDS)
                except OSError:
                    break
                if not data:  # the owner closed the factory or died
                    break
                try:
                    reply = self._spawn(json.loads(data), fds)
                finally:
                    for fd in fds:
                        os.close(fd)
                if not self._send(reply):
                    break
        self._stop_all()
        return 0

    def _send(self, msg: dict) -> bool:
        try:
            self.sock.send(json.dumps(msg).encode())
            return True
        except OSError:
            return False

    def _reap(self) -> bool:
        """Report every child that exited; False if the owner cannot hear it any more."""
        heard = True
        while self.children:
            try:
                pid, status, usage = os.wait4(-1, os.WNOHANG)
            except ChildProcessError:
                self.children.clear()
                break
            if pid == 0:
                break
            self.children.discard(pid)
            heard = self._send({"op": "exit", "pid": pid, "rc": os.waitstatus_to_exitcode(status),
                                "cpu_s": usage.ru_utime + usage.ru_stime, "maxrss_kib": usage.ru_maxrss}) and heard
        return heard

    def _spawn(self, req: dict, fds: list[int]) -> dict:
        if req.get("op") != "spawn" or len(fds) != 3:
            return {"error": f"bad request {req.get('op')!r} with {len(fds)} descriptors"}
        ready_r, ready_w = os.pipe()
        _flush_std_streams()
        try:
            pid = os.fork()
        except OSError as exc:
            os.close(ready_r)
            os.close(ready_w)
            return {"error": str(exc)}
        if pid == 0:
            os.close(ready_r)
            _child(req, fds, ready_w, (self.sock, self.wake_r, self.wake_w))
        os.close(ready_w)
        self.children.add(pid)
        with os.fdopen(ready_r, "rb") as r:
            ok = r.read(1)  # the child is in its own session and has its descriptors
        if ok != b"1":
            return {"error": "the child died while it set itself up", "pid": pid}
        return {"pid": pid}

    def _stop_all(self) -> None:
        """The owner is gone or closed the factory: stop every child still running, as the
        launcher would (SIGINT to its group, a grace period, SIGKILL); report what can be."""
        signal.set_wakeup_fd(-1)
        signal.signal(signal.SIGCHLD, signal.SIG_DFL)
        for pid in list(self.children):
            _killpg(pid, signal.SIGINT)
            _killpg(pid, signal.SIGCONT)  # a stopped child acts on it only once continued
        deadline = time.monotonic() + self.stop_grace_s
        while self.children and time.monotonic() < deadline:
            self._reap()
            time.sleep(0.02)
        for pid in list(self.children):
            _killpg(pid, signal.SIGKILL)
        while self.children:
            self._reap()
            time.sleep(0.01)


def _killpg(pid: int, sig: int) -> None:
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(pid, sig)


# ---------------------------------------------------------------------------- the child


def _child(req: dict, fds: list[int], ready_w: int, inherited: Iterable[object]) -> NoReturn:
    """In the forked child: become what ``python -m module args`` would be, run it, exit."""
    code = 1
    try:
        os.setsid()
        signal.set_wakeup_fd(-1)
        for sig in (signal.SIGCHLD, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT, signal.SIGUSR1, signal.SIGUSR2):
            signal.signal(sig, signal.SIG_DFL)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        for target, fd in enumerate(fds):
            os.dup2(fd, target)
        for obj in inherited:
            if isinstance(obj, socket.socket):
                obj.close()
        _close_fds_from(3, keep=ready_w)
        _fresh_std_streams()
        os.chdir(req["cwd"])
        os.environ.clear()
        os.environ.update(req["env"])
        _fresh_logging()
        module, args = req["module"], req["args"]
        loaded = sys.modules.get(module)  # preloaded, but runpy runs it afresh as __main__
        sys.modules.pop(f"{module}.__main__" if hasattr(loaded, "__path__") else module, None)
        sys.argv = [module, *args]
        _set_title(req["python"], module, args)
        os.write(ready_w, b"1")
        os.close(ready_w)
    except BaseException:
        traceback.print_exc()
        os._exit(code)
    code = _run(module)
    os._exit(code)


def _run(module: str) -> int:
    """``python -m module``'s exit code, with Python's own shutdown steps that matter here.

    At-exit functions do not run, as in a child of multiprocessing's fork start method:
    those registered before the fork are the owner's (``weakref.finalize`` would remove
    the owner's temporary directories); the project registers none of its own."""
    interrupted = False
    try:
        runpy.run_module(module, run_name="__main__", alter_sys=True)
        code = 0
    except SystemExit as exc:
        code = _exit_status(exc.code)
    except KeyboardInterrupt:
        traceback.print_exc()
        code, interrupted = 130, True
    except BaseException:
        traceback.print_exc()
        code = 1
    with contextlib.suppress(BaseException):
        threading._shutdown()  # joins non-daemon threads, as the interpreter does at exit
    with contextlib.suppress(BaseException):
        logging.shutdown()
    _flush_std_streams()
    if interrupted:  # as Python does: die of the SIGINT, so the parent sees -2
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        os.kill(os.getpid(), signal.SIGINT)
    return code


def _exit_status(code: object) -> int:
    """``sys.exit(code)``'s process exit status."""
    if code is None:
        return 0
    if isinstance(code, int):
        return code & 0xFF
    print(code, file=sys.stderr)
    return 1


def _close_fds_from(low: int, keep: int) -> None:
    for name in os.listdir("/proc/self/fd"):
        fd = int(name)
        if fd >= low and fd != keep:
            with contextlib.suppress(OSError):
                os.close(fd)


def _fresh_std_streams() -> None:
    """Text streams on the new descriptors, unbuffered as ``PYTHONUNBUFFERED`` makes them
    (the launcher sets it for Popen): the inherited objects are dropped unflushed."""
    sys.stdin = sys.__stdin__ = io.TextIOWrapper(io.BufferedReader(io.FileIO(0, "r", closefd=False)),
                                                 encoding="utf-8")
    sys.stdout = sys.__stdout__ = io.TextIOWrapper(io.FileIO(1, "w", closefd=False), encoding="utf-8",
                                                   write_through=True)
    sys.stderr = sys.__stderr__ = io.TextIOWrapper(io.FileIO(2, "w", closefd=False), encoding="utf-8",
                                                   errors="backslashreplace", write_through=True)


def _fresh_logging() -> None:
    """The root logger as a new interpreter has it, so the module's ``basicConfig`` takes effect."""
    root = logging.getLogger()
    for handler in list(root.handlers):
        root.removeHandler(handler)
    root.setLevel(logging.WARNING)
    logging.disable(logging.NOTSET)


def _set_title(python: str, module: str, args: Sequence[str]) -> None:
    """Show ``python -m module args`` in ``ps`` and ``/proc/<pid>/cmdline``, as Popen's
    child would, and name the process (``comm``) after the module. The title goes over
    the inherited command line, and on into the environment's strings (as
    setproctitle(3) does) once the environment has been copied elsewhere, so a long
    title still shows the run id. Cosmetic: a failure changes nothing else."""
    with contextlib.suppress(Exception):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(15, module[:15].encode(), 0, 0, 0)  # PR_SET_NAME
    with contextlib.suppress(Exception):
        with open("/proc/self/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
        arg_start, arg_end, env_start, env_end = (int(x) for x in fields[45:49])  # proc(5), fields 48-51
        argv = [python, "-m", module, *args]
        title = b"\0".join(a.encode() for a in argv) + b"\0"
        if len(title) <= arg_end - arg_start:
            end = arg_end  # as argv: one string per argument
        else:  # one string, spaces between: the kernel reads on past the arguments' end
            title = b" ".join(a.encode() for a in argv) + b"\0"
            end = env_end if env_start == arg_end and not _environ_points_into(env_start, env_end) else arg_end
        room = end - arg_start
        title = title[:room - 1] + b"\0" if len(title) > room else title
        ctypes.memmove(arg_start, title.ljust(room, b"\0"), room)


def _environ_points_into(start: int, end: int) -> bool:
    """Whether the C environment still uses strings in ``[start, end)`` (the original
    block; ``os.environ.update`` put copies in place of every key it knows)."""
    environ = ctypes.POINTER(ctypes.c_void_p).in_dll(ctypes.CDLL(None), "environ")
    i = 0
    while environ[i] is not None:
        if start <= environ[i] < end:
            return True
        i += 1
    return False


def _flush_std_streams() -> None:
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            if stream is not None:
                stream.flush()


def main(argv: list[str] | None = None) -> int:
    """``python -m processes.factory FD [--stop-grace-s=S] [MODULE ...]``: serve as a zygote
    on the socket FD, after importing the modules (``Factory(start="exec")`` starts it)."""
    argv = sys.argv[1:] if argv is None else argv
    if not argv or not argv[0].isdigit():
        print(main.__doc__, file=sys.stderr)
        return 2
    fd, rest, grace_s = int(argv[0]), argv[1:], STOP_GRACE_S
    if rest and rest[0].startswith("--stop-grace-s="):
        grace_s, rest = float(rest[0].partition("=")[2]), rest[1:]
    return _Zygote(socket.socket(fileno=fd), tuple(rest), grace_s).serve()


if __name__ == "__main__":
    sys.exit(main())
