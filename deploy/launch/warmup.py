"""Every numba kernel of a run compiled (or loaded from the cache) once, before its processes start.

The launcher, a sweep and a host of ``autocast deploy`` warm once, so the N processes
of a run load the kernels from the cache instead of compiling them each.

On a machine's first run nothing is cached yet: ~120 kernels compile, a minute or two.
That first compile runs in worker processes, one per usable core (up to ``PARTS``): the
kernels are independent, and numba reads its disk cache before every compile, so a
worker finds what the other has already written. The launcher reports what is
compiling, how many of the missing kernels are done and roughly how long is left.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import time
from collections.abc import Callable

from protocol.codec import decode, encode
from protocol.messages import MapMsg, Mission, Scan
from world_server.scenarios import ScenarioParams

log = logging.getLogger(__name__)


# ``warm_numba_caches`` as a command of its own (the test suite's first step, and its check
# that nothing is left to compile): the kernels are the same for every scenario
WARM_ARGV = (sys.executable, "-c", "import logging; logging.basicConfig(level='INFO', format='%(message)s'); "
             "from deploy.launch.warmup import warm_numba_caches; "
             "from world_server.scenarios import params_from_dict; "
             "warm_numba_caches(params_from_dict({'scenario': 'left_turn', 'vehicles': 5}))")


KERNEL_PACKAGES = ("world_server", "vehicle_agent", "channel_proxy", "protocol")
PROGRESS_EVERY_S = 5.0


def warm_numba_caches(params: ScenarioParams) -> None:
    """Compile (or load) every numba kernel once here, so N processes load them from the cache.

    The agent's kernels are reached through ``vehicle_agent.warm_up()`` when the agent
    provides it, otherwise through one pass of the agent's stages (perceive, reason,
    fuse, plan, control) on the scenario's first scans and every built-in scheduler's
    warm-up. A failure only costs the agents compile time. Kernels missing from the
    cache compile first in parallel workers (module docstring), with progress reported.
    """
    t0 = time.perf_counter()
    missing = missing_kernels()
    progress = Progress(len(missing), t0) if missing else None
    if missing:
        workers = min(len(PARTS), _usable_cores())
        log.info("compiling %d numba kernels on %d core%s: the first run only, later runs load them from the "
                 "cache", len(missing), workers, "" if workers == 1 else "s")
        if workers > 1:
            _compile_in_workers(params, progress)
    with _reporting(progress):  # loads what the workers wrote; compiles anything they left
        for part in PARTS.values():
            part(params)
    if progress is not None:
        loaded = max(progress.total - progress.done, 0)  # compiled meanwhile by another process, then loaded
        log.info("compiled %d numba kernels in %.1f s%s; later runs load them from the cache", progress.done,
                 time.perf_counter() - t0, f" (the other {loaded} of the {progress.total} missing were in the cache "
                 "by then: another process compiled them)" if loaded else "")
    else:
        log.info("numba caches warm in %.1f s", time.perf_counter() - t0)


def _warm_world(params: ScenarioParams) -> None:
    """The world's kernels (the LiDAR, the judge's distance), every scheduler's, the agent's
    kernels that synthetic calls reach, then the agent's own synthetic interval
    (``vehicle_agent.warmup``): beside ``_warm_agent`` on a cold cache, mostly in another
    order, so the two workers compile different kernels and then load each other's."""
    from world_server import geometry, lidar
    from world_server.sim import Simulation

    sim = Simulation(params)
    lidar.warm_up(sim.lidar_cfg)
    geometry.warm_up()  # the judge's distance, at every physics step
    try:
        from channel_proxy.profiles import get_profile
        from vehicle_agent.agent import Agent
        from vehicle_agent.agreement import AgreementConfig
        from vehicle_agent.fusion import warm_kernels as warm_fusion
        from vehicle_agent.payload import warm_kernels as warm_payload
        from vehicle_agent.scheduler.warmup import warm_up as warm_schedulers
        from vehicle_agent.tracking import warm_kernels as warm_tracking
        from vehicle_agent.warmup import warm_up as warm_agent

        warm_schedulers()
        warm_tracking()
        warm_fusion()
        warm_payload()
        # decoded, read-only arrays (numba types them apart): the map and mission as an agent gets them
        vid = sim.connected_vids[0]
        agent = Agent(decode(encode(sim.mission(vid)), Mission), decode(encode(sim.scenario.roadmap.to_msg()), MapMsg))
        warm_agent(agent, AgreementConfig.from_profile(get_profile("lte-direct"), scheduler="autocast"))
    except Exception:  # warming is an optimisation; the agents compile what is missing
        log.warning("agent kernels not warmed; each agent compiles its own", exc_info=True)


def _warm_agent(params: ScenarioParams) -> None:
    """The agent's stages on the scenario's first scans (``_warm_agent_kernels``)."""
    from world_server.sim import Simulation

    try:
        _warm_agent_kernels(Simulation(params))
    except Exception:  # warming is an optimisation; the agents compile what is missing
        log.warning("agent kernels not warmed; each agent compiles its own", exc_info=True)


# the warm-up in independent parts, the longest first: a worker process each on a cold cache
PARTS: dict[str, Callable[[ScenarioParams], None]] = {"agent": _warm_agent, "world": _warm_world}


def _kernel_modules() -> None:
    """Import every module that holds a kernel the warm-up reaches."""
    import channel_proxy.__main__  # noqa: F401
    import channel_proxy.emp  # noqa: F401
    import vehicle_agent.__main__  # noqa: F401
    import vehicle_agent.scheduler.warmup  # noqa: F401
    import vehicle_agent.warmup  # noqa: F401
    import world_server.geometry  # noqa: F401
    import world_server.lidar  # noqa: F401


def cached_kernels() -> list:
    """This project's numba kernels compiled with ``cache=True`` (module-level ones)."""
    from numba.core.caching import FunctionCache
    from numba.core.dispatcher import Dispatcher

    _kernel_modules()
    kernels = {}
    for name, module in list(sys.modules.items()):
        if name.split(".")[0] not in KERNEL_PACKAGES or module is None:
            continue
        for obj in list(vars(module).values()):
            if isinstance(obj, Dispatcher) and isinstance(getattr(obj, "_cache", None), FunctionCache) \
                    and obj.py_func.__module__ == name:
                kernels[id(obj)] = obj
    return list(kernels.values())


def missing_kernels() -> list[str]:
    """The kernels with nothing in numba's cache yet (no index file): what a first run compiles."""
    return [_name(k) for k in cached_kernels() if not os.path.exists(k._cache._cache_file._index_path)]


def _name(dispatcher) -> str:
    return f"{dispatcher.py_func.__module__}.{dispatcher.py_func.__qualname__}"


class Progress:
    """Counts the project's kernels as they compile and logs how far it is, every few seconds."""

    def __init__(self, total: int, t0: float) -> None:
        self.total, self.t0 = total, t0
        self.done = 0
        self.seen: set[str] = set()
        self.now = ""
        self._last = t0

    def started(self, name: str) -> None:
        if name.split(".")[0] in KERNEL_PACKAGES:  # not numba's own helpers, which a kernel compiles with it
            self.now = name
        self._maybe_report()

    def finished(self, name: str) -> None:
        if name not in self.seen and name.split(".")[0] in KERNEL_PACKAGES:
            self.seen.add(name)
            self.done += 1
        self._maybe_report()

    def _maybe_report(self) -> None:
        t = time.perf_counter()
        if t - self._last < PROGRESS_EVERY_S:
            return
        self._last = t
        elapsed = t - self.t0
        left = elapsed / self.done * max(self.total - self.done, 0) if self.done else None
        log.info("compiling numba kernels: %d of %d done, now %s; %.0f s so far%s", min(self.done, self.total),
                 self.total, self.now or "-", elapsed, f", ~{left:.0f} s left" if left is not None else "")


class _reporting:
    """A numba compile listener feeding ``progress`` while the block runs (no-op without one)."""

    def __init__(self, progress: Progress | None) -> None:
        self.progress = progress
        self.listener = None

    def __enter__(self) -> _reporting:
        if self.progress is not None:
            from numba.core import event

            progress = self.progress

            class Listener(event.Listener):
                def on_start(self, ev) -> None:
                    progress.started(_name(ev.data["dispatcher"]))

                def on_end(self, ev) -> None:
                    progress.finished(_name(ev.data["dispatcher"]))

            self.listener = Listener()
            event.register("numba:compile", self.listener)
        return self

    def __exit__(self, *exc) -> None:
        if self.listener is not None:
            from numba.core import event

            event.unregister("numba:compile", self.listener)


def _usable_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def _compile_in_workers(params: ScenarioParams, progress: Progress) -> None:
    """Each part of the warm-up in a worker process of its own, their compile events read
    from their stdout; a worker that fails costs only time (the in-process pass follows)."""
    import dataclasses
    import selectors

    argv = [sys.executable, "-m", "deploy.launch.warmup", "--params", json.dumps(dataclasses.asdict(params)), "--part"]
    workers = [subprocess.Popen([*argv, part], stdout=subprocess.PIPE, text=True) for part in PARTS]
    sel = selectors.DefaultSelector()
    for w in workers:
        sel.register(w.stdout, selectors.EVENT_READ, w)
    open_pipes = len(workers)
    try:
        while open_pipes:
            for key, _ in sel.select():
                line = key.fileobj.readline()
                if not line:
                    sel.unregister(key.fileobj)
                    open_pipes -= 1
                    continue
                what, _, name = line.strip().partition(" ")
                (progress.started if what == "start" else progress.finished)(name)
    finally:
        for w in workers:
            if w.wait() != 0:
                log.warning("a compile worker exited with %s; its kernels compile in the launcher", w.returncode)


def _warm_agent_kernels(sim) -> None:
    import vehicle_agent

    hook = getattr(vehicle_agent, "warm_up", None)
    if callable(hook):
        hook()
        return
    from vehicle_agent.agent import Agent

    # the map and missions as an agent gets them, through the wire format: decoded arrays
    # are read-only, which numba types apart (the rasters' kernels at the agent's start)
    mapmsg = decode(encode(sim.scenario.roadmap.to_msg()), MapMsg)
    vids = sim.connected_vids[:2]
    views = sim.sense(vids)
    agents = {vid: Agent(decode(encode(sim.mission(vid)), Mission), mapmsg) for vid in vids}
    heard: list[int] = []
    for vid, agent in agents.items():  # two vehicles, so each has a neighbour to reason about
        v = views[vid]
        scan = Scan(0, 0.0, vid, v.pose, v.speed_mps, v.range_cm)
        view = agent.perceive(scan)
        msg = agent.control_message(view, scan, heard)
        for other in agents.values():
            other.dataplane.neighbors.update([msg])
        agent.drive(view, agent.fuse(view, []), scan)
        heard.append(vid)


def main(argv: list[str] | None = None) -> int:
    """A compile worker: one part of the warm-up, each compile's start and end on stdout."""
    ap = argparse.ArgumentParser(prog="python -m deploy.launch.warmup", description=main.__doc__)
    ap.add_argument("--part", choices=tuple(PARTS), required=True)
    ap.add_argument("--params", required=True, help="the scenario's parameters as JSON")
    args = ap.parse_args(argv)
    from numba.core import event

    from world_server.scenarios import params_from_dict

    class Listener(event.Listener):
        def on_start(self, ev) -> None:
            print("start", _name(ev.data["dispatcher"]), flush=True)

        def on_end(self, ev) -> None:
            print("done", _name(ev.data["dispatcher"]), flush=True)

    event.register("numba:compile", Listener())
    PARTS[args.part](params_from_dict(json.loads(args.params)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
