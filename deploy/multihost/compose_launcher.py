"""The launcher of a docker compose run (``autocast deploy --compose``).

    python -m deploy.multihost.compose_launcher --run-id R --connect tcp/router-alpha:7447 --routers 3 \
        --run-dir runs/R --record '{"scheme": "autocast", "scenario": "left_turn", ...}'

Compose starts the processes; this service does the rest of what ``autocast run``'s
launcher does. It waits until every host's router answers and is linked to every other
(the routers' admin space), then until the recorder's subscriptions have reached its
router; then it declares the liveliness token ``ac/<run>/alive/p/launcher``, which the
world waits for before tick 0 (``--wait-for launcher``), so the MCAP starts at tick 0.
It logs every ``--progress-every``-th tick (``tick N``), waits for the world's judged
outcome and writes ``<run-dir>/outcome.json`` (the world's record plus ``--record``: the
scheme, model, placement), prints the outcome line and exits with ``autocast run``'s
code: 0 safe, 1 another judged outcome, 3 failed, 130 stopped (SIGINT, SIGTERM).

The run fails, as ``autocast deploy``'s does, when the proxy's liveliness token drops
before the outcome (it died), when a host's router is gone, or after ``--timeout-s``.
A dead agent is the world's business: its vehicle brakes, the outcome names it.
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

import zenoh

from deploy.launch import run
from deploy.multihost.hosts import router_links
from protocol import keys
from protocol.codec import MalformedMessage, decode
from protocol.messages import Outcome, Tick
from protocol.session import DropCounter, ZenohArgs, session_scope, typed_handler
from world_server.__main__ import summary

log = logging.getLogger("deploy.multihost.compose_launcher")

NAME = "launcher"  # its participant token: ac/<run>/alive/p/launcher
MESH_TIMEOUT_S = 120.0  # every router up and linked (containers start in any order)
ROUTER_CHECK_S = 1.0  # how often the routers are counted during the run


class Watch:
    """From the routers' mesh to the world's outcome, on one client session."""

    def __init__(self, session: zenoh.Session, args: argparse.Namespace, stop: threading.Event) -> None:
        self.session, self.args, self.stop = session, args, stop
        self.run_id = args.run_id
        self.outcome: Outcome | None = None
        self.got_outcome = threading.Event()
        self.proxy_gone = threading.Event()
        self.ticks = 0
        self._drops = DropCounter()

    def _on_outcome(self, _key: str, msg: Outcome) -> None:
        if self.outcome is None:
            self.outcome = msg
            self.got_outcome.set()

    def _on_tick(self, sample: zenoh.Sample) -> None:
        try:
            tick = decode(sample.payload.to_bytes(), Tick)
        except MalformedMessage:
            return
        self.ticks = max(self.ticks, tick.tick + 1)
        if tick.tick % self.args.progress_every == 0:
            log.info("tick %d", tick.tick)

    def _on_proxy_token(self, sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.DELETE:
            self.proxy_gone.set()

    def wait_for_mesh(self) -> str | None:
        deadline = time.monotonic() + MESH_TIMEOUT_S
        n = self.args.routers
        while True:
            links = router_links(self.session)
            if len(links) == n and all(k >= n - 1 for k in links.values()):
                log.info("%d routers linked", n)
                return None
            if self.stop.is_set():
                return "stopped"
            if time.monotonic() > deadline:
                return (f"the hosts' routers are not linked after {MESH_TIMEOUT_S:.0f} s: {len(links)} of {n} "
                        f"answered, with {sorted(links.values())} router links (want {n - 1} each)")
            time.sleep(0.2)

    def run(self) -> str | None:
        """None once the outcome is in; else why the run failed."""
        failure = self.wait_for_mesh()
        if failure:
            return failure
        if not run.wait_recorder_ready(self.session, self.run_id, None, MESH_TIMEOUT_S, self.stop):
            return "stopped" if self.stop.is_set() else "the recorder's subscriptions never reached the router"
        subs = [self.session.declare_subscriber(keys.world_outcome(self.run_id),
                                                typed_handler(Outcome, self._on_outcome, self._drops)),
                self.session.declare_subscriber(keys.world_tick(self.run_id), self._on_tick),
                self.session.liveliness().declare_subscriber(keys.proxy_alive(self.run_id), self._on_proxy_token)]
        token = self.session.liveliness().declare_token(keys.participant_alive(self.run_id, NAME))
        log.info("recorder subscribed; token %s declared: the world may start",
                 keys.participant_alive(self.run_id, NAME))
        try:
            return self._watch()
        finally:
            token.undeclare()
            for sub in subs:
                sub.undeclare()

    def _watch(self) -> str | None:
        deadline = time.monotonic() + self.args.timeout_s
        next_check = time.monotonic() + ROUTER_CHECK_S
        while not self.got_outcome.wait(0.1):
            if self.stop.is_set():
                return "stopped"
            if self.proxy_gone.is_set() and not self.got_outcome.wait(run.CRITICAL_EXIT_WAIT_S):
                return f"the proxy's liveliness token dropped at tick {self.ticks}, before the outcome (it died)"
            now = time.monotonic()
            if now >= next_check:
                next_check = now + ROUTER_CHECK_S
                routers = len(router_links(self.session))
                if routers < self.args.routers and not self.got_outcome.wait(run.CRITICAL_EXIT_WAIT_S):
                    return f"a host's router is gone at tick {self.ticks}: {routers} of {self.args.routers} answer"
            if now > deadline:
                return f"no outcome within {self.args.timeout_s:.0f} s of wall time"
        return None


def record_of(outcome: Outcome | None, failure: str | None, base: dict[str, Any], run_dir: Path,
              stopped: bool) -> tuple[int, dict[str, Any]]:
    """The exit code and outcome record, as ``autocast run`` makes them."""
    mcap = run_dir / "run.mcap"
    where = {"run_id": base.get("run_id"), "run_dir": str(run_dir),
             "mcap": str(mcap) if mcap.exists() else f"{base.get('hosts', {}).get('recorder', '?')}:{mcap}"}
    result = dict(outcome.result) if outcome is not None and failure is None else {}
    if result.get("outcome") is None:
        failure = failure or result.get("failure") or "the world judged nothing"
        code = run.EXIT_INTERRUPTED if stopped else run.EXIT_FAILED
        record = {"outcome": None, "failure": failure, **base, **where}
        if stopped:
            record["interrupted"] = True
        return code, record
    return (run.EXIT_SAFE if result["outcome"] == "safe" else run.EXIT_JUDGED), {**result, **base, **where}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m deploy.multihost.compose_launcher", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run-id", required=True)
    ap.add_argument("--connect", action="append", required=True, metavar="ENDPOINT", help="this host's router")
    ap.add_argument("--zenoh-config", default=None, metavar="FILE", help="the launcher's credentials (lock-down)")
    ap.add_argument("--routers", type=int, required=True, help="how many hosts' routers the run has")
    ap.add_argument("--run-dir", required=True, type=Path, help="where outcome.json goes (the MCAP's directory)")
    ap.add_argument("--record", default="{}", help="a JSON object added to the outcome record (scheme, model, hosts)")
    ap.add_argument("--timeout-s", type=float, default=900.0, help="wall-clock limit for the whole run")
    ap.add_argument("--progress-every", type=int, default=10, metavar="N", help="log every N-th tick")
    ap.add_argument("--log-level", default="INFO")
    args = ap.parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="compose launcher: %(message)s")
    base = json.loads(args.record)
    if not isinstance(base, dict):
        print("error: --record: a JSON object", file=sys.stderr)
        return run.EXIT_BAD_INPUT
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    t0 = time.monotonic()
    try:
        with session_scope(ZenohArgs(connect=tuple(args.connect), config_file=args.zenoh_config),
                           wait_s=MESH_TIMEOUT_S) as session:
            watch = Watch(session, args, stop)
            failure = watch.run()
            outcome = watch.outcome
    except ConnectionError as exc:
        failure, outcome = f"the launcher reached no router: {exc}", None
    code, record = record_of(outcome, failure, {"run_id": args.run_id, **base}, args.run_dir,
                             stopped=stop.is_set() and outcome is None)
    args.run_dir.mkdir(parents=True, exist_ok=True)
    record = run.write_record(args.run_dir, record)
    if record["outcome"] is not None:
        print(summary(record) + f"  [{record.get('scheme')}, {time.monotonic() - t0:.1f} s total]")
    else:
        print(f"run failed: {record['failure']}", file=sys.stderr)
    print(json.dumps(record, allow_nan=False), flush=True)
    return code


if __name__ == "__main__":
    sys.exit(main())
