"""Deterministic fault injection: a process of a run dies or hangs at a tick it is told.

``AUTOCAST_FAULTS="world:kill@20,agent2:hang@5"`` (in the environment of ``autocast
run``, which its processes inherit) makes the world SIGKILL itself when it is about to
play tick 20 and agent 2 stop answering from its scan of tick 5 on. A fault is tied
to a tick, not to the wall clock, so a test or a resilience experiment causes the same
failure at the same point of the run on a fast machine and on a loaded one.

Actions:
- ``kill``: SIGKILL itself (no clean-up, no outcome, no goodbye: a crashed process);
- ``hang``: block that thread forever (a process that is alive and silent);
- ``stop``: SIGSTOP itself (the whole process frozen, every thread: a process the OS
  stopped, or a machine that froze); whoever stops it later continues it first.

Processes name themselves as the launcher's table does: ``world``, ``proxy``,
``agent<vid>``, ``recorder`` (at the first message it writes of that tick or later: the
world's outcome carries the tick after the last played, so ``recorder:kill@N`` of a run
of N ticks kills it as the outcome arrives), and ``hub``: the launcher, whose Zenoh
router every process of a one-host run talks through (at the world's tick). A bad
specification is an error at start-up, naming the entry.

With ``AUTOCAST_FAULTS_LOG=FILE`` each fault appends one JSON line to FILE just before
it acts (process, action, tick, ``t_unix``: the wall time), so whoever caused it can
measure what followed (``bench/soak.py``: the time from the fault to the run's verdict).
"""

from __future__ import annotations

import json
import logging
import os
import signal
import threading
import time
from dataclasses import dataclass

log = logging.getLogger(__name__)

ENV = "AUTOCAST_FAULTS"
LOG_ENV = "AUTOCAST_FAULTS_LOG"
ACTIONS = ("kill", "hang", "stop")


@dataclass(frozen=True, slots=True)
class Fault:
    process: str
    action: str
    tick: int


def parse(spec: str) -> list[Fault]:
    """``"world:kill@20,agent2:hang@5"`` -> faults; raises ValueError naming the bad entry."""
    faults = []
    for entry in filter(None, (e.strip() for e in spec.split(","))):
        process, sep, rest = entry.partition(":")
        action, at, tick = rest.partition("@")
        if not (sep and at and process) or action not in ACTIONS or not tick.isdigit():
            raise ValueError(f"{ENV}: {entry!r} is not <process>:<{'|'.join(ACTIONS)}>@<tick>")
        faults.append(Fault(process, action, int(tick)))
    return faults


class Injector:
    """A process's own faults; ``at(tick)`` is called where the process starts a tick."""

    def __init__(self, process: str, spec: str | None = None) -> None:
        spec = os.environ.get(ENV, "") if spec is None else spec
        self.faults = [f for f in parse(spec) if f.process == process]
        if self.faults:
            log.warning("fault injection: %s", ", ".join(f"{f.action} at tick {f.tick}" for f in self.faults))

    def at(self, tick: int) -> None:
        for f in self.faults:
            if tick >= f.tick:
                log.warning("fault injection: %s at tick %d", f.action, tick)
                for handler in logging.getLogger().handlers:  # the line reaches the log before we go
                    handler.flush()
                _note(f, tick)
                if f.action == "kill":
                    os.kill(os.getpid(), signal.SIGKILL)
                if f.action == "stop":
                    self.faults = []  # continued (to be stopped for good), it goes on as if nothing happened
                    os.kill(os.getpid(), signal.SIGSTOP)
                    return
                threading.Event().wait()  # hang


def _note(fault: Fault, tick: int) -> None:
    """One JSON line in ``AUTOCAST_FAULTS_LOG``, if set: what acts, when (wall time)."""
    path = os.environ.get(LOG_ENV)
    if path:
        with open(path, "a") as f:
            f.write(json.dumps({"process": fault.process, "action": fault.action, "tick": tick,
                                "t_unix": time.time()}) + "\n")
