"""Shared fixtures: free loopback ports and process cleanup; hypothesis profiles."""

from __future__ import annotations

import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from hypothesis import HealthCheck, Phase, settings

from deploy.launch.warmup import WARM_ARGV

# Property tests run the bounded, derandomized "ci" profile (the same examples every
# run, no per-example deadline on a loaded machine); AUTOCAST_HYPOTHESIS=fuzz runs
# 10,000 random examples per property instead (AUTOCAST_HYPOTHESIS_EXAMPLES=N: N).
settings.register_profile("ci", max_examples=25, derandomize=True, deadline=None, database=None,
                          phases=[Phase.explicit, Phase.generate, Phase.shrink],
                          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
settings.register_profile("fuzz", max_examples=int(os.environ.get("AUTOCAST_HYPOTHESIS_EXAMPLES", "10000")),
                          deadline=None,
                          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
settings.load_profile(os.environ.get("AUTOCAST_HYPOTHESIS", "ci"))


def pytest_sessionstart(session: pytest.Session) -> None:
    """Fill the numba caches before any test starts, once for the session (in the xdist
    controller, before its workers exist). On a fresh clone every kernel compiles
    otherwise inside whichever test first starts a run, with the other workers compiling
    the same kernels at the same time: on CI that took 86 s, and the run's 90 s safety net
    went off. Warm, a launcher loads them in under a second.

    From an empty cache (a fresh clone, CI) the warm-up's own output is kept apart for
    ``tests/test_warmup.py``, which checks that runs compile nothing it left out: its
    files alone, before any test adds to the cache (``AUTOCAST_WARMED_CACHE``)."""
    if hasattr(session.config, "workerinput"):
        return
    from deploy.launch.warmup import cached_kernels, missing_kernels

    cold = len(missing_kernels()) == len(cached_kernels())
    t0 = time.monotonic()
    try:  # the timeout only a safety net: a cold warm-up takes 20 s here, 86 s on CI
        done = subprocess.run(WARM_ARGV, capture_output=True, text=True, timeout=900)
        failure = f"exit {done.returncode}:\n{done.stderr[-2000:]}" if done.returncode != 0 else ""
    except subprocess.TimeoutExpired:
        failure = "no end in 900 s"
    if cold and not failure:
        kept = Path(tempfile.mkdtemp(prefix="autocast-warmed-"))
        copy_as_cache_dir(cached_kernels(), kept)
        (kept / "warm-up.log").write_text(done.stderr)
        os.environ["AUTOCAST_WARMED_CACHE"] = str(kept)  # the workers inherit it
    reporter = session.config.pluginmanager.get_plugin("terminalreporter")
    if reporter is None:
        return
    if failure:  # not fatal: each test then compiles what it needs
        reporter.write_line(f"numba caches not warmed ({failure})", red=True)
    elif time.monotonic() - t0 > 5:
        reporter.write_line(f"numba caches compiled in {time.monotonic() - t0:.0f} s")


def pytest_sessionfinish(session: pytest.Session) -> None:
    kept = os.environ.get("AUTOCAST_WARMED_CACHE")
    if kept and not hasattr(session.config, "workerinput"):
        shutil.rmtree(kept, ignore_errors=True)


def copy_as_cache_dir(kernels: list, dest: Path) -> None:
    """The kernels' cache files (index and compiled signatures) as they would lie under
    ``NUMBA_CACHE_DIR=dest``: the same file names, in numba's directory for each source
    file instead of the source's ``__pycache__``."""
    from numba.core.caching import UserProvidedCacheLocator

    for kernel in kernels:
        index = Path(kernel._cache._cache_file._index_path)
        stem = index.name.removesuffix(".nbi")
        into = dest / UserProvidedCacheLocator.get_suitable_cache_subpath(kernel.py_func.__code__.co_filename)
        into.mkdir(parents=True, exist_ok=True)
        for f in [index, *index.parent.glob(f"{stem}.*.nbc")]:
            shutil.copy2(f, into / f.name)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Longest first: the ``heavy`` tests lead the queue (a stable sort keeps the rest in
    file order), so under ``--dist load`` no worker picks up a half-minute test when the
    other is nearly done. An ``xdist_group`` with a heavy test leads whole, in file
    order: its worker then runs its tests back to back and its module's fixtures start
    once. (Split, the heavy test first and the rest at the tail with other modules'
    tests between, the hostile peer's module started its two runs four times, 47 s each.)"""
    heavy_groups = {_xdist_group(item) for item in items if item.get_closest_marker("heavy")} - {None}
    items.sort(key=lambda item: not (item.get_closest_marker("heavy") or _xdist_group(item) in heavy_groups))


def _xdist_group(item: pytest.Item) -> str | None:
    mark = item.get_closest_marker("xdist_group")
    if mark is None:
        return None
    return mark.args[0] if mark.args else mark.kwargs.get("name")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until(condition: Callable[[], bool], what: str, timeout_s: float = 60.0) -> None:
    """Poll ``condition`` until it holds; the timeout is only a safety net (a test that
    reaches it has failed, whatever the machine's speed)."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"never happened: {what}")
        time.sleep(0.02)


@pytest.fixture
def hub() -> str:
    """A free loopback endpoint for a test's Zenoh hub."""
    return f"tcp/127.0.0.1:{free_port()}"


@pytest.fixture(scope="session")
def run_factory():
    """A warm process factory (``processes.factory``) for the tests that launch a run from
    this process: ``Launcher(..., procs=ProcessManager(log_dir, run_factory))`` forks the
    run's processes from it, as ``autocast run`` forks them from its own, instead of
    starting an interpreter for each that imports the stack anew (~0.7 s of CPU a
    process). This process has had Zenoh sessions, so the zygote is a fresh interpreter
    (``start="exec"``); one per worker, made when first asked for."""
    from processes.factory import RUN_MODULES, Factory

    factory = Factory(RUN_MODULES, start="exec")
    yield factory
    factory.close()


@pytest.fixture
def procs():
    """Start ``python -m ...`` processes; every one is killed and reaped at teardown."""
    started: list[subprocess.Popen] = []

    def start(*args: str, **kw) -> subprocess.Popen:
        p = subprocess.Popen([sys.executable, "-m", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True, start_new_session=True, **kw)
        started.append(p)
        return p

    yield start
    for p in started:
        if p.poll() is None:
            p.kill()
        p.communicate()


def reports_slices() -> bool:
    """Whether this kernel gives a thread a time slice of its own and reports it (Linux
    6.12 and later), through ``processes.manager``' ``sched_getattr`` for this machine."""
    from processes import manager as procs

    release = re.match(r"(\d+)\.(\d+)", os.uname().release) if hasattr(os, "uname") else None
    return procs._SCHED_GETATTR is not None and release is not None and \
        (int(release[1]), int(release[2])) >= (6, 12)


def batch_allowed() -> bool:
    """Whether this system lets a process under the default policy take SCHED_BATCH (Linux
    does, unprivileged; a sandbox may refuse), tried in a child of the default policy."""
    if not hasattr(os, "SCHED_BATCH") or not Path("/proc/self/task").is_dir():
        return False
    probe = "import os; os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))"
    return os.sched_getscheduler(0) == os.SCHED_OTHER and subprocess.run([sys.executable, "-c", probe]).returncode == 0
