"""One connected vehicle as its own process: ``python -m vehicle_agent --vid 3``."""

from __future__ import annotations

import argparse
import logging
import queue
import signal
import sys
import threading
import time

from protocol import keys
from protocol.codec import encode
from protocol.messages import MapMsg, Mission, Outcome, Scan
from protocol.session import DropCounter, add_zenoh_args, query_one, session_scope, typed_handler, zenoh_args_from
from vehicle_agent.agent import LaneFollower

log = logging.getLogger("vehicle_agent")

SCHEMES = ("single", "agnostic", "autocast", "autocast-fptas", "emp")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python -m vehicle_agent", description=__doc__)
    ap.add_argument("--run-id", required=True, help="the run's id (key prefix ac/<run>/)")
    ap.add_argument("--vid", type=int, required=True, help="this vehicle's id")
    ap.add_argument("--startup-timeout-s", type=float, default=120.0,
                    help="give up if the world does not answer within this long")
    ap.add_argument("--idle-exit-s", type=float, default=60.0,
                    help="exit if no scan arrives for this long (the world is gone)")
    ap.add_argument("--scheme", default="autocast", choices=SCHEMES,
                    help="sharing scheme: single (no V2V), agnostic, autocast, autocast-fptas, emp")
    ap.add_argument("--log-level", default="WARNING")
    add_zenoh_args(ap)
    return ap.parse_args(argv)


def _ask(session, key: str, expected: type, deadline: float):
    """Query until the world answers (it may start after us)."""
    while True:
        try:
            return query_one(session, key, expected, timeout_s=2.0)
        except TimeoutError:
            if time.monotonic() > deadline:
                raise


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format=f"%(asctime)s agent{args.vid} %(levelname)s %(message)s")
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        scope = session_scope(zenoh_args_from(args), wait_s=args.startup_timeout_s)
        with scope as session:
            return serve(session, args, stop)
    except ConnectionError as exc:  # no hub within the startup timeout
        log.error("%s", exc)
        return 2


def serve(session, args: argparse.Namespace, stop: threading.Event) -> int:
    """Fetch the map and mission, then answer every scan with a command until stopped."""
    run, vid = args.run_id, args.vid
    drops = DropCounter()
    scans: queue.Queue[Scan] = queue.Queue()
    deadline = time.monotonic() + args.startup_timeout_s
    try:
        _ask(session, keys.world_map(run), MapMsg, deadline)
        mission = _ask(session, keys.mission(run, vid), Mission, deadline)
    except TimeoutError as exc:
        log.error("world never answered: %s", exc)
        return 2
    agent = LaneFollower(mission)
    subs = [
        session.declare_subscriber(keys.scan(run, vid), typed_handler(Scan, lambda k, m: scans.put(m), drops)),
        session.declare_subscriber(keys.world_outcome(run), typed_handler(Outcome, lambda k, m: stop.set(), drops)),
    ]
    cmd_pub = session.declare_publisher(keys.cmd(run, vid))
    token = session.liveliness().declare_token(keys.alive(run, vid))
    last_scan = time.monotonic()
    try:
        while not stop.is_set():
            try:
                scan = scans.get(timeout=0.2)
            except queue.Empty:
                if time.monotonic() - last_scan > args.idle_exit_s:
                    log.warning("no scan for %.0f s; exiting", args.idle_exit_s)
                    break
                continue
            last_scan = time.monotonic()
            cmd_pub.put(encode(agent.run_step(scan)))
    finally:
        token.undeclare()
        for sub in subs:
            sub.undeclare()
    if drops.total:
        log.warning("dropped %d malformed messages", drops.total)
    return 0


if __name__ == "__main__":
    sys.exit(main())
