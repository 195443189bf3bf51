"""Phase marks: where a lock-step interval's wall time goes, process by process.

With ``AUTOCAST_PHASES`` naming a directory, each process of a run writes a line per
mark into a file of its own there (``<pid>.txt``): the event, the tick, the time on
``CLOCK_MONOTONIC`` (one clock for every process of a host) and the marking thread's
CPU clock. The world marks the tick's start, its last scan sent, every command in and
its step done; the proxy each phase's close and bundle out; an agent its scan in, its
control message and data out, each bundle in and its command out. A mark before a send
and one after the matching receive are ordered as the messages were.
``python -m bench.critical_path`` runs a run so and prints the medians. Give an
absolute path: each process opens its file from its own working directory; one that
cannot says so on stderr and marks nothing. Unset (the default), a mark is one test of
a module global."""

from __future__ import annotations

import os
import sys
import threading
import time

ENV = "AUTOCAST_PHASES"
_DIR = os.environ.get(ENV) or None  # read once, at import: a forked child keeps its parent's
_lock = threading.Lock()
_file = None
_pid = 0


def mark(event: str, tick: int) -> None:
    """Record that this process passed ``event`` of interval ``tick`` (if marks are on)."""
    global _DIR, _file, _pid
    if _DIR is None:
        return
    with _lock:
        if _file is None or _pid != os.getpid():  # never a file opened before a fork
            _pid = os.getpid()
            try:
                _file = open(os.path.join(_DIR, f"{_pid}.txt"), "a", buffering=1)  # noqa: SIM115 - for the process's life
            except OSError as exc:  # marks are a measurement: never what stops a run
                print(f"{ENV}={_DIR}: {exc}; no phase marks", file=sys.stderr, flush=True)
                _DIR = None
                return
        _file.write(f"{event} {tick} {time.monotonic():.6f} {time.thread_time():.6f}\n")
