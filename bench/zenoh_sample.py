"""What one received Zenoh sample costs the receiving process, in CPU.

An agent receives three samples an interval (its scan, the ``CtrlBundle``, the
``DataBundle``) and publishes three (its control message, its ``DataTx``, its command),
all far apart at 40 vehicles: a lock-step tick then takes ~300 ms of wall time. In
this bench a subscriber process (a callback that takes the payload's bytes, as
``protocol.session.typed_handler`` does) receives ``--count`` samples from a publisher
process that puts one every ``--gaps`` ms. Both are Zenoh clients of a hub process in
router mode, as in a run (``protocol.session.make_config``). It prints the subscriber's
whole-process CPU per sample (user + system, every thread: Zenoh's and the
callback's), for each gap and payload size. That is a floor under an agent's CPU per
tick which no change in the agent's own work moves.

    python -m bench.zenoh_sample                       # gaps 1,5,20,100 ms; 4 KB and 230 KB
    python -m bench.zenoh_sample --gaps 20 --sizes 4000 --count 100 --rounds 3

Each figure is the median of ``--rounds`` runs.
"""

from __future__ import annotations

import argparse
import resource
import statistics
import subprocess
import sys
import threading
import time

import zenoh

from protocol.session import ZenohArgs, make_config, open_session

KEY = "bench/zenoh_sample"


def serve(endpoint: str, seconds: float) -> None:
    """The hub process: a router on ``endpoint`` for ``seconds``."""
    with zenoh.open(make_config(ZenohArgs(listen=(endpoint,)))):
        time.sleep(seconds)


def publish(endpoint: str, size: int, count: int, gap_s: float) -> None:
    """The publisher process: ``count`` puts of ``size`` bytes, ``gap_s`` apart, once the
    subscriber is matched."""
    with open_session(ZenohArgs(connect=(endpoint,))) as session:
        pub = session.declare_publisher(KEY, congestion_control=zenoh.CongestionControl.BLOCK)
        deadline = time.monotonic() + 30.0
        while not pub.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.01)
        data = bytes(size)
        for _ in range(count):
            pub.put(data)
            time.sleep(gap_s)
        time.sleep(0.5)  # let the last samples drain before the session closes


def receive(endpoint: str, size: int, count: int, gap_s: float) -> float:
    """This process subscribes and receives; returns its CPU seconds per sample, from the
    first sample to the last (the publisher's start-up left out)."""
    got: list[int] = []
    first, done = threading.Event(), threading.Event()
    marks: list[float] = []

    def on_sample(sample: zenoh.Sample) -> None:
        got.append(len(sample.payload.to_bytes()))
        if len(got) == 1:
            marks.append(_cpu_s())
            first.set()
        if len(got) == count:
            marks.append(_cpu_s())
            done.set()

    me = [sys.executable, "-m", "bench.zenoh_sample"]
    hub = subprocess.Popen([*me, "--serve", endpoint, str(120.0 + count * gap_s * 2)])
    try:
        with open_session(ZenohArgs(connect=(endpoint,))) as session:
            sub = session.declare_subscriber(KEY, on_sample)
            pub = subprocess.Popen([*me, "--publish", endpoint, str(size), str(count), str(gap_s)])
            try:
                if not (first.wait(60.0) and done.wait(60.0 + count * gap_s * 2)):
                    raise RuntimeError(f"received {len(got)} of {count} samples")
            finally:
                pub.wait(timeout=60.0)
                sub.undeclare()
    finally:
        hub.terminate()
        hub.wait(timeout=30.0)
    return (marks[1] - marks[0]) / (count - 1)


def _cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def main(argv: list[str] | None = None) -> int:
    if argv is None and len(sys.argv) > 1 and sys.argv[1] == "--publish":
        endpoint, size, count, gap_s = sys.argv[2:6]
        publish(endpoint, int(size), int(count), float(gap_s))
        return 0
    if argv is None and len(sys.argv) > 1 and sys.argv[1] == "--serve":
        serve(sys.argv[2], float(sys.argv[3]))
        return 0
    ap = argparse.ArgumentParser(prog="python -m bench.zenoh_sample", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gaps", default="1,5,20,100", help="ms between two samples (comma-separated)")
    ap.add_argument("--sizes", default="4000,230000", help="payload bytes (comma-separated)")
    ap.add_argument("--count", type=int, default=200, help="samples per measurement")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--port", type=int, default=7461, help="the loopback TCP port of the hub")
    args = ap.parse_args(argv)
    endpoint = f"tcp/127.0.0.1:{args.port}"
    rows = []
    for size in (int(s) for s in args.sizes.split(",")):
        for gap_ms in (float(g) for g in args.gaps.split(",")):
            per = [receive(endpoint, size, args.count, gap_ms / 1e3) for _ in range(args.rounds)]
            us = statistics.median(per) * 1e6
            rows.append((size, gap_ms, us))
            print(f"{size:>8} B every {gap_ms:>5g} ms: {us:6.1f} us of CPU per sample "
                  f"({', '.join(f'{p * 1e6:.0f}' for p in per)})", flush=True)
    worst = max(us for _, _, us in rows)
    print(f"zenoh_sample: samples={args.count} rounds={args.rounds} max_us={worst:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
