"""What a pause costs the work that follows it, in CPU.

A live agent stage costs ~1.4x the same stage in a replay of its log (docs/performance.md,
"Why live stages cost more than replayed ones"): live, each agent waits 50-150 ms between
its stages while the other processes run, or while the cores halt. This bench times a
fixed piece of Python and numpy work (about what an agent does in 0.3 ms: dict look-ups,
small-array sums, a sort of 5000 floats) by its thread's CPU clock, after sleeps of
``--sleeps`` ms, and prints the median for each sleep:

- ``--beside idle`` (the default): nothing else runs;
- ``--beside spin``: a busy loop of ours on each core at ``SCHED_IDLE`` priority, so no
  core ever halts, and ours takes the core back at once when it wakes;
- ``--beside thrash``: a process per core that rewrites 8 MB over and over (the other
  processes' data in the caches);
- ``--beside qos``: nothing else runs, but this process holds a PM QoS request of 0 us
  (``/dev/cpu_dma_latency``, root only), which keeps the cores from halting when idle.

    python -m bench.cold_wake                          # idle, sleeps 0, 5 and 50 ms
    python -m bench.cold_wake --beside spin --beside thrash

On this project's 2-core VM (after 0 / 5 / 50 ms): 308 / 320 / 483 us idle, 314 / 315 /
323 with the spinners, 309 / 369 / 473 with the thrashers, 311 / 316 / 323 with the QoS
request. A vCPU that halted comes back slow.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import statistics
import struct
import subprocess
import sys
import time
from collections.abc import Iterator

import numpy as np

_BESIDE = {
    "spin": "import os\nos.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))\nwhile True: pass\n",
    "thrash": "import numpy as np\na = np.ones(1 << 20)\nwhile True: a += 1.0\n",
}


def work(table: dict[int, int], a: np.ndarray) -> int:
    """The fixed piece of work: ~0.3 ms on this machine, back to back."""
    s = 0
    for i in range(300):
        s += table[i] + len(str(i))
        s += int(a[i:i + 50].sum() > 25.0)
    return s + int(np.sort(a[:5000])[0] > 1.0)


def timed_after(sleep_s: float, repeat: int) -> float:
    """Median thread CPU of ``work``, us, each run after a sleep of ``sleep_s``."""
    rng = np.random.default_rng(0)
    table, a = {i: 2 * i for i in range(2000)}, rng.random(20_000)
    out = []
    for _ in range(repeat):
        if sleep_s:
            time.sleep(sleep_s)
        c0 = time.thread_time()
        work(table, a)
        out.append(time.thread_time() - c0)
    return statistics.median(out) * 1e6


@contextlib.contextmanager
def beside(kind: str) -> Iterator[None]:
    """One process of ``kind`` per core for the duration (none for "idle"); for "qos", the
    PM QoS request held (``PermissionError`` if this user may not)."""
    if kind == "qos":
        fd = os.open("/dev/cpu_dma_latency", os.O_WRONLY)  # the request lasts while it is open
        try:
            os.write(fd, struct.pack("i", 0))
            yield
        finally:
            os.close(fd)
        return
    procs = []
    try:
        if kind != "idle":
            for _ in os.sched_getaffinity(0):  # one a core; each kept as soon as it exists
                procs.append(subprocess.Popen([sys.executable, "-c", _BESIDE[kind]]))
            time.sleep(0.3)  # let them start
        yield
    finally:
        for p in procs:
            p.kill()
            p.wait()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.cold_wake", description=__doc__.split("\n\n")[0])
    ap.add_argument("--sleeps", default="0,5,50", help="ms to sleep before each run of the work (default 0,5,50)")
    ap.add_argument("--beside", action="append", choices=["idle", "qos", *_BESIDE],
                    help="what runs on the cores meanwhile (repeatable; default idle)")
    ap.add_argument("--repeat", type=int, default=400, help="runs of the work per sleep (median)")
    args = ap.parse_args(argv)
    sleeps_ms = [float(x) for x in args.sleeps.split(",")]
    headline = []
    for kind in args.beside or ["idle"]:
        with beside(kind):
            figures = [timed_after(ms / 1e3, args.repeat) for ms in sleeps_ms]
        print(f"beside {kind:6s} " + "  ".join(f"after {ms:g} ms: {us:6.1f} us" for ms, us in zip(sleeps_ms, figures)),
              flush=True)
        headline += [f"{kind}_after{ms:g}ms_us={us:.1f}" for ms, us in zip(sleeps_ms, figures)]
    print("cold_wake: " + " ".join(headline))
    return 0


if __name__ == "__main__":
    sys.exit(main())
