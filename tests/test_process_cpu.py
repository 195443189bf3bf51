"""The agent's own CPU accounting (``vehicle_agent.__main__.ProcessCpu``)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import pytest

from vehicle_agent.__main__ import ProcessCpu


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
    after = _burn(0.1)  # the teardown: not counted
    summary = proc.summary()
    threads = {k: v for k, v in summary.items() if k.startswith("thread_")}
    assert threads, summary
    n = summary["proc_ticks"]
    assert n == 1
    main_ms = sum(threads.values()) * n  # the main thread carries the process's name, like any of ours
    assert between * 1e3 <= main_ms < (between + after) * 1e3
