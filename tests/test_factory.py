"""The warm process factory (processes/factory.py) with real processes: what a forked child
is (its own pid, group, session, log, command line), the exit codes its owner sees
(Popen's, compared with Popen itself), killing one child alone, a child's own Zenoh
session, and nothing left behind when the owner dies.

This test process has had Zenoh sessions (their runtime threads stay), so it cannot
fork a zygote itself: the fixture's zygote is a fresh interpreter (``start="exec"``),
whose children are forked exactly as a forked zygote's are. The owner test runs a
clean owner process that forks its zygote, as the launcher does."""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh

from processes import factory as process_factory
from processes import manager as procs
from processes.factory import Factory, FactoryError, ForkedProcess
from processes.manager import ProcessManager, has_argument
from deploy.experiments.runner import kill_run_processes
from protocol import keys
from protocol.codec import decode
from protocol.messages import Command
from protocol.session import ZenohArgs, session_scope
from tests.conftest import batch_allowed, reports_slices, wait_until

TESTS = Path(__file__).resolve().parent


@pytest.fixture
def probe_env(monkeypatch) -> dict[str, str]:
    """The environment in which ``python -m factory_probe`` is found."""
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(p for p in (str(TESTS), os.environ.get("PYTHONPATH")) if p))
    return dict(os.environ)


@pytest.fixture
def factory(probe_env):
    f = Factory(preload=("factory_probe",), start="exec")
    yield f
    f.close()


def spawn_logged(factory: Factory, log: Path, *args: str, **kw) -> ForkedProcess:
    with open(log, "wb") as out:
        return factory.spawn("factory_probe", args, stdout=out.fileno(), **kw)


def gone(pid: int) -> bool:
    """Not running any more (exited and reaped, or a zombie nobody has reaped yet)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] == "Z"
    except FileNotFoundError:
        return True


def test_a_forked_child_is_its_own_process_with_its_own_log(factory, tmp_path):
    log = tmp_path / "ids.log"
    proc = spawn_logged(factory, log, "ids", env=dict(os.environ, PROBE="mine"), cwd=str(tmp_path))
    assert proc.wait(timeout=60) == 0
    stdout, stderr = log.read_text().splitlines()
    ids = json.loads(stdout)
    assert ids["pid"] == proc.pid != os.getpid()
    assert ids["pgid"] == ids["sid"] == proc.pid  # its own session and process group, as start_new_session
    assert ids["ppid"] == factory.pid  # the zygote reaps it
    assert ids["argv"] == ["ids"] and ids["env"] == "mine" and ids["cwd"] == str(tmp_path)
    assert f"{sys.executable} -m factory_probe ids" in ids["cmdline"]  # what Popen's child would show
    assert stderr == "probe stderr line"  # stdout and stderr in the one log
    assert proc.cpu_s is not None and proc.cpu_s >= 0.0


def test_a_child_that_exits_before_its_spawn_is_answered_is_still_reaped(factory):
    """The zygote reports a child's exit right after the reply that names it; a child that
    exits at once can have both read in one go, before the owner knows the pid. Here the
    owner reads the exit before it registers the child, every time: it waits (on the
    socket, not the clock) for the zygote's report between reading the reply and using it."""
    read_reply = factory._reply

    def reply_read_after_the_exit_is_reported() -> dict:
        reply = read_reply()
        deadline = time.monotonic() + 60.0  # a safety net: the exit report is the next message
        while reply["pid"] not in factory._unclaimed and time.monotonic() < deadline:
            select.select([factory._sock], [], [], deadline - time.monotonic())  # (read with the reply, or later)
            factory.pump(0.0)
        assert reply["pid"] in factory._unclaimed  # the exit is known before the child is registered
        return reply

    factory._reply = reply_read_after_the_exit_is_reported
    proc = factory.spawn("factory_probe", ["exit", "5"])
    assert proc.wait(timeout=60) == 5


@pytest.mark.parametrize("args, sig, expected", [
    (("exit", "3"), None, 3),
    (("exit", "0"), None, 0),
    (("raise",), None, 1),
    (("wait",), signal.SIGINT, -signal.SIGINT),  # KeyboardInterrupt, uncaught: Python dies of the signal
    (("wait",), signal.SIGTERM, -signal.SIGTERM),
    (("wait",), signal.SIGKILL, -signal.SIGKILL),
])
def test_exit_codes_are_the_ones_popen_reports(factory, probe_env, tmp_path, args, sig, expected):
    forked_log, popen_log = tmp_path / "forked.log", tmp_path / "popen.log"
    forked = spawn_logged(factory, forked_log, *args)
    with open(popen_log, "wb") as out:
        popen = subprocess.Popen([sys.executable, "-m", "factory_probe", *args], stdout=out, stderr=subprocess.STDOUT,
                                 start_new_session=True, env=probe_env)
    try:
        if sig is not None:
            for log in (forked_log, popen_log):
                wait_until(lambda: "waiting" in log.read_text(), f"{log.name} is waiting")
            for pid in (forked.pid, popen.pid):
                os.killpg(pid, sig)
        assert (forked.wait(timeout=60), popen.wait(timeout=60)) == (expected, expected)
    finally:
        for p in (forked, popen):
            if p.poll() is None:
                p.kill()
                p.wait(timeout=60)
    if args == ("raise",):
        for log in (forked_log, popen_log):
            assert "RuntimeError: the probe fails on purpose" in log.read_text()


def test_a_child_is_killed_alone(factory, tmp_path):
    procs = [spawn_logged(factory, tmp_path / f"w{i}.log", "wait") for i in range(3)]
    for i in range(3):
        wait_until(lambda: "waiting" in (tmp_path / f"w{i}.log").read_text(), f"child {i} is waiting")
    os.killpg(procs[1].pid, signal.SIGKILL)
    assert procs[1].wait(timeout=60) == -signal.SIGKILL
    assert procs[0].poll() is None and procs[2].poll() is None
    assert not gone(procs[0].pid) and not gone(procs[2].pid)
    for p in (procs[0], procs[2]):
        os.killpg(p.pid, signal.SIGINT)
        assert p.wait(timeout=60) == -signal.SIGINT


def test_a_child_whose_arguments_outgrow_its_parents_still_names_its_run(factory, tmp_path):
    """Its title is then one space-joined string (``_set_title``): the sweep must still
    find a killed launcher's leftovers by their run id."""
    run_id = "sweep-run-0042"
    proc = spawn_logged(factory, tmp_path / "w.log", "wait", "--run-id", run_id, "--shm-dir", "/dev/shm/" + "x" * 400)
    wait_until(lambda: "waiting" in (tmp_path / "w.log").read_text(), "the child is waiting")
    cmdline = Path(f"/proc/{proc.pid}/cmdline").read_bytes().rstrip(b"\0")
    assert b"\0" not in cmdline and cmdline.endswith(b"x" * 40)  # the long form, whole
    assert has_argument(proc.pid, run_id) and has_argument(proc.pid, "factory_probe")
    assert not has_argument(proc.pid, run_id[:-1]) and not has_argument(proc.pid, "sweep")
    (tmp_path / "pids.json").write_text(json.dumps({"w": proc.pid}))
    kill_run_processes(tmp_path, "another-run")
    assert proc.poll() is None
    kill_run_processes(tmp_path, run_id)
    assert proc.wait(timeout=60) == -signal.SIGKILL


def test_a_childs_zenoh_session_works(factory, hub, tmp_path):
    """Two forked children, each with its own session to the hub: their liveliness
    tokens and publications arrive; one stopped, its token goes and the other's stays."""
    run = "factorytest"
    tokens: set[str] = set()
    heard: dict[int, int] = {}
    lock = threading.Lock()

    def on_token(sample) -> None:
        with lock:
            key = str(sample.key_expr)
            (tokens.add if sample.kind == zenoh.SampleKind.PUT else tokens.discard)(key)

    def on_cmd(sample) -> None:
        cmd = decode(sample.payload.to_bytes(), Command)
        with lock:
            heard[cmd.vid] = heard.get(cmd.vid, 0) + 1

    with session_scope(ZenohArgs(listen=(hub,)), wait_s=0.0) as session:
        subs = [session.liveliness().declare_subscriber(keys.alive(run, "*"), on_token, history=True),
                session.declare_subscriber(keys.cmd(run, "*"), on_cmd)]
        procs = {vid: spawn_logged(factory, tmp_path / f"z{vid}.log", "zenoh", hub, run, str(vid)) for vid in (1, 2)}
        try:
            wait_until(lambda: tokens == {keys.alive(run, 1), keys.alive(run, 2)}, "both tokens")
            wait_until(lambda: heard.get(1, 0) >= 3 and heard.get(2, 0) >= 3, "commands from both")
            os.killpg(procs[1].pid, signal.SIGINT)
            assert procs[1].wait(timeout=60) == 0
            wait_until(lambda: tokens == {keys.alive(run, 2)}, "the stopped child's token gone")
            before = heard[2]
            wait_until(lambda: heard[2] > before, "the other child still publishing")
            assert procs[2].poll() is None
        finally:
            for p in procs.values():
                if p.poll() is None:
                    os.killpg(p.pid, signal.SIGINT)
                    p.wait(timeout=60)
            for s in subs:
                s.undeclare()
    assert "published" in (tmp_path / "z1.log").read_text()


def test_closing_the_factory_stops_what_still_runs(probe_env, tmp_path):
    f = Factory(preload=("factory_probe",), start="exec")
    proc = spawn_logged(f, tmp_path / "w.log", "wait")
    wait_until(lambda: "waiting" in (tmp_path / "w.log").read_text(), "the child is waiting")
    f.close()
    assert proc.returncode == -signal.SIGINT  # stopped as the launcher stops: SIGINT first
    assert gone(proc.pid) and gone(f.pid)


def test_the_factory_leaves_nothing_behind_when_its_owner_dies(probe_env):
    """A clean owner forks its zygote (as the launcher does) and starts three children
    through it; the owner is SIGKILLed: the zygote stops its children and exits."""
    owner = subprocess.Popen([sys.executable, "-m", "factory_probe", "owner", "3"], stdout=subprocess.PIPE,
                             text=True, start_new_session=True, env=probe_env)
    try:
        started = json.loads(owner.stdout.readline())
        pids = [started["zygote"], *started["children"]]
        assert len(set(pids)) == 4 and not any(gone(p) for p in pids)
        assert all(os.getpgid(c) == c for c in started["children"])
        assert os.getpgid(started["zygote"]) == started["zygote"] != os.getpgid(owner.pid)
    finally:
        owner.kill()
        owner.communicate(timeout=60)
    wait_until(lambda: all(gone(p) for p in pids), "the zygote and its children gone")


def test_no_zygote_is_forked_where_a_zenoh_session_ran(hub):
    """A Zenoh session leaves runtime threads that a fork would not carry: the factory
    refuses, and the launcher's processes start with Popen instead."""
    with session_scope(ZenohArgs(listen=(hub,)), wait_s=0.0):
        reason = process_factory.fork_unsafe_reason()
        assert reason is not None
        with pytest.raises(FactoryError):
            Factory()
        with process_factory.activated() as f:
            assert f is None and process_factory.current() is None
        assert ProcessManager().factory is None


def test_popen_is_forced_by_the_environment(monkeypatch):
    monkeypatch.setenv(process_factory.ENV, "popen")
    assert process_factory.disabled()
    with process_factory.activated() as f:
        assert f is None


@pytest.mark.skipif(not batch_allowed(), reason="Linux, under the default policy, where SCHED_BATCH may be taken")
def test_batch_scheduling_covers_every_thread_and_what_starts_later_and_is_undone():
    """In a fresh interpreter (this one has Zenoh's threads, and keeps its policy): a
    thread that ran before the call, one started after it and a child process all end
    up under SCHED_BATCH with the batch slice (where the kernel has slices of its own:
    Linux 6.12 and later), their nice value kept, as every process of a lock-step run
    does (``autocast run``); ``batch=False`` (a real-time run) takes every thread back to
    the default policy and the default slice."""
    script = """
import json, os, subprocess, sys, threading
from processes.manager import batch_scheduling, scheduling
os.nice(3)  # a niced launcher stays as nice
go, back, seen = threading.Event(), threading.Event(), {}
def early():
    go.wait()
    seen["early"] = scheduling()
    back.wait()
    seen["early_back"] = scheduling()
    seen["early_nice"] = os.getpriority(os.PRIO_PROCESS, 0)  # this thread's, on Linux
t = threading.Thread(target=early); t.start()
before = scheduling()
assert batch_scheduling(slice_ms=7.5)
late = threading.Thread(target=lambda: seen.__setitem__("late", scheduling())); late.start(); late.join()
go.set()
child = subprocess.run([sys.executable, "-c", "from processes.manager import scheduling; print(list(scheduling()))"],
                       capture_output=True, text=True, check=True).stdout
after = scheduling()
while "early" not in seen: go.wait(0.01)
assert batch_scheduling(batch=False)
back.set(); t.join()
print(json.dumps([before, after, seen["early"], seen["late"], json.loads(child), scheduling(), seen["early_back"]]))
print(os.getpriority(os.PRIO_PROCESS, 0), seen["early_nice"])
"""
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=TESTS.parent, timeout=120)
    assert out.returncode == 0, out.stderr
    policies, nices = out.stdout.splitlines()
    (before, default_slice), *batch, (main_back, main_slice), (early_back, early_slice) = json.loads(policies)
    assert before == os.SCHED_OTHER and [policy for policy, _ in batch] == [os.SCHED_BATCH] * 4
    assert main_back == early_back == os.SCHED_OTHER
    assert nices.split() == ["3", "3"]
    if reports_slices():
        assert default_slice is not None and default_slice != 7_500_000
        assert [slice_ns for _, slice_ns in batch] == [7_500_000] * 4
        assert main_slice == early_slice == default_slice


def test_a_batch_slice_out_of_the_kernels_range_is_refused_before_anything_is_set():
    with pytest.raises(ValueError, match="slice_ms"):
        procs.batch_scheduling(slice_ms=0.0)
    with pytest.raises(ValueError, match="slice_ms"):
        procs.batch_scheduling(slice_ms=250.0)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="a process's CPU-time clock by pid is Linux's")
def test_process_cpu_s_reads_another_processs_cpu_its_ended_threads_included():
    """A child burns CPU in a thread that ends, then in its main thread, prints its own
    process_time and sleeps: read from outside, its clock holds at least that much (the
    ended thread's share included) and not much more (it sleeps). Once it is reaped,
    there is no clock to read."""
    burn = ("import threading, time\n"
            "def spin(s):\n"
            "    t = time.thread_time()\n"
            "    while time.thread_time() - t < s: pass\n"
            "th = threading.Thread(target=spin, args=(0.15,)); th.start(); th.join()\n"
            "spin(0.1)\n"
            "print(time.process_time(), flush=True)\n"
            "time.sleep(120)\n")
    child = subprocess.Popen([sys.executable, "-c", burn], stdout=subprocess.PIPE, text=True)
    try:
        own = float(child.stdout.readline())
        got = procs.process_cpu_s(child.pid)
        assert own >= 0.25 and own <= got <= own + 0.5, (own, got)
    finally:
        child.kill()
        child.wait()
    assert procs.process_cpu_s(child.pid) is None
