"""The agent's own bookkeeping around its ticks (``vehicle_agent.__main__``): its CPU
accounting (``ProcessCpu``) and its stall dump (``StallDump``)."""

from __future__ import annotations

import gc
import signal
import sys
import threading
import time
from pathlib import Path

import pytest

from conftest import wait_until
from vehicle_agent.__main__ import ProcessCpu, StallDump


def _burn(cpu_s: float) -> float:
    """Spend at least ``cpu_s`` of this thread's CPU; returns what it spent."""
    t0 = time.thread_time()
    while time.thread_time() - t0 < cpu_s:
        sum(range(1000))
    return time.thread_time() - t0


@pytest.mark.skipif(not sys.platform.startswith("linux") or not Path("/proc/self/task").exists(),
                    reason="per-thread clocks by thread id: Linux")
def test_the_threads_are_read_at_the_first_tick_and_once_the_loop_ends():
    proc = ProcessCpu()
    proc.tick_done()
    between = _burn(0.02)
    proc.tick_done()
    assert not any(k.startswith("thread_") for k in proc.summary()), "read before the loop ended"
    proc.loop_done()
    assert proc._on_gc not in gc.callbacks, "its garbage-collector hook goes with the loop"
    after = _burn(0.1)  # the teardown: not counted
    summary = proc.summary()
    threads = {k: v for k, v in summary.items() if k.startswith("thread_")}
    assert threads, summary
    n = summary["proc_ticks"]
    assert n == 1
    main_ms = sum(threads.values()) * n  # the main thread carries the process's name, like any of ours
    assert between * 1e3 <= main_ms < (between + after) * 1e3


@pytest.mark.skipif(not sys.platform.startswith("linux") or not Path("/proc/self/task").exists(),
                    reason="per-thread clocks by thread id: Linux")
def test_a_thread_that_ends_mid_run_takes_none_of_the_others_cpu():
    """A thread of the process's name (as Python's threads are) that burned CPU before
    the first tick and ends before the loop does: the name's figure is what the threads
    spent meanwhile, not less by what the ended one had spent (it was, once in a while,
    in a test worker whose threads come and go)."""
    burned, end = threading.Event(), threading.Event()

    def helper() -> None:
        _burn(0.05)
        burned.set()
        end.wait()

    t = threading.Thread(target=helper)
    t.start()
    burned.wait()
    proc = ProcessCpu()
    proc.tick_done()  # the helper's 0.05 s on its clock, read
    end.set()
    t.join()
    between = _burn(0.02)
    proc.tick_done()
    proc.loop_done()
    main_ms = sum(v for k, v in proc.summary().items() if k.startswith("thread_"))
    assert between * 1e3 <= main_ms < (between + 0.05) * 1e3


@pytest.mark.skipif(not hasattr(signal, "SIGALRM"), reason="SIGALRM: POSIX")
def test_a_tick_that_overruns_dumps_every_stack_and_goes_on(tmp_path):
    with open(tmp_path / "log", "w+") as log:
        stall = StallDump(0.05, file=log)
        try:
            with stall:  # the timer goes off inside the block; the block is not interrupted
                wait_until(lambda: "most recent call first" in (tmp_path / "log").read_text(), "a stack dump")
            assert signal.getitimer(signal.ITIMER_REAL) == (0.0, 0.0), "disarmed as the block ended"
            assert "test_a_tick_that_overruns" in (tmp_path / "log").read_text()
        finally:
            stall.close()


@pytest.mark.skipif(not hasattr(signal, "SIGALRM"), reason="SIGALRM: POSIX")
def test_a_tick_within_its_limit_leaves_nothing_armed(tmp_path):
    with open(tmp_path / "log", "w+") as log:
        stall = StallDump(600.0, file=log)
        try:
            with stall:
                remaining, _ = signal.getitimer(signal.ITIMER_REAL)
                assert 0.0 < remaining <= 600.0, "armed as the block started"
            assert signal.getitimer(signal.ITIMER_REAL) == (0.0, 0.0)
            with pytest.raises(RuntimeError), stall:  # an exception disarms it too
                raise RuntimeError
            assert signal.getitimer(signal.ITIMER_REAL) == (0.0, 0.0)
        finally:
            stall.close()
        assert (tmp_path / "log").read_text() == ""
