"""A hostile peer: ``python -m deploy.hostile --run-id R --connect HUB --vids 0 1 2``.

Joins a run's hub and, once the run is live, publishes on every data key the run uses
(every ``protocol.keys`` key but the liveliness tokens, for each given vehicle) a
known number of payloads that no subscriber of that key may accept: generated and
mutated garbage (``bench/fuzz.py``'s generators, seeded by key) and well-formed
messages of another type. Nothing it sends is a valid message of the key's own type:
impersonating a peer is not what this tests, surviving garbage is.

Deterministic: the payloads are a function of ``--seed``, the run id and the key;
"live" is an event (the world's first tick reached us, and the channel proxy's
liveliness token is up with ``--proxy``), never a sleep. The last payload goes on the
world's tick key, and a second session of ours subscribed to that key through the hub
sees it come back: the hub has then routed every payload we sent (it forwards one
link's messages in order). The first real tick seen after it is reported as
``confirmed_before_tick``: every process that handled that tick's traffic had every
payload we sent queued before it.

Ends with one line on stdout, ``hostile_peer {json}``: ``sent`` (per key),
``bad_envelope`` (per key, the payloads whose envelope the recorder cannot read, so
it records them on a schemaless channel), ``first_tick`` and ``confirmed_before_tick``.
Exit 0 once confirmed, 1 if the run ended (or ``--timeout-s`` passed) first.
"""

from __future__ import annotations

import argparse
import inspect
import json
import logging
import random
import sys
import threading
from collections.abc import Callable

import zenoh

from bench import fuzz
from deploy.recorder import peek_envelope
from protocol import keys
from protocol.codec import MalformedMessage, decode
from protocol.messages import (AgentReport, ChannelStats, Command, ControlMsg, CtrlBundle, DataBundle, DataTx,
                               EmpBundle, EmpUpload, MapMsg, Mission, Outcome, Scan, Tick, WorldTruth)
from protocol.session import add_zenoh_args, session_scope, zenoh_args_from

log = logging.getLogger("deploy.hostile")

# the message type each data key carries (its subscribers decode that type only)
KEY_TYPES: dict[Callable[..., str], type] = {
    keys.world_tick: Tick, keys.world_map: MapMsg, keys.world_truth: WorldTruth, keys.world_outcome: Outcome,
    keys.mission: Mission, keys.scan: Scan, keys.cmd: Command, keys.report: AgentReport,
    keys.net_ctrl_tx: ControlMsg, keys.net_ctrl_rx: CtrlBundle, keys.net_data_tx: DataTx,
    keys.net_data_rx: DataBundle, keys.net_stats: ChannelStats, keys.net_emp_up: EmpUpload,
    keys.net_emp_down: EmpBundle,
}
NOT_DATA = (keys.alive, keys.proxy_alive, keys.everything)  # liveliness tokens and the run's wildcard
MAX_PAYLOAD_BYTES = 4096  # garbage, not load: keep the hub's work small
MARKER = b"\xc1hostile-peer: last payload"  # 0xc1 is never used by msgpack: garbage like the rest


def key_functions() -> list[Callable[..., str]]:
    """Every ``protocol.keys`` function that builds a key of a run."""
    return [fn for name, fn in inspect.getmembers(keys, inspect.isfunction)
            if fn.__module__ == keys.__name__ and not name.startswith("_")
            and list(inspect.signature(fn).parameters)[:1] == ["run"]]


def data_keys(run: str, vids: list[int]) -> dict[str, type]:
    """``{key: message type}`` for every data key of a run with vehicles ``vids``."""
    out: dict[str, type] = {}
    for fn in key_functions():
        if fn in NOT_DATA:
            continue
        if len(inspect.signature(fn).parameters) == 1:
            out[fn(run)] = KEY_TYPES[fn]
        else:
            out.update({fn(run, vid): KEY_TYPES[fn] for vid in vids})
    return out


def payloads_for(key: str, cls: type, garbage: int, wrong_typed: int, seed: int) -> list[bytes]:
    """``garbage`` fuzzed payloads that ``cls`` refuses, then ``wrong_typed`` valid
    messages of the other types in turn; a function of (seed, key) only."""
    rnd = random.Random(f"{seed}:{key}")
    out: list[bytes] = []
    while len(out) < garbage:
        payload = fuzz.fuzz_input(cls.__name__, rnd)
        if len(payload) <= MAX_PAYLOAD_BYTES and not _decodes_as(payload, cls):
            out.append(payload)
    others = [name for name in fuzz.DECODERS if name in {c.__name__ for c in fuzz.MESSAGE_TYPES} and name != cls.__name__]
    for i in range(wrong_typed):
        out.append(fuzz.valid_payload(others[i % len(others)], rnd))
    return out


def _decodes_as(payload: bytes, cls: type) -> bool:
    try:
        decode(payload, cls)
    except MalformedMessage:
        return False
    return True


class Watch:
    """What our second session sees on the world's tick key, in the hub's order."""

    def __init__(self) -> None:
        self.first_tick: int | None = None
        self.confirmed_before_tick: int | None = None
        self.live = threading.Event()
        self.done = threading.Event()  # confirmed, or the run ended
        self._marker_seen = False
        self._lock = threading.Lock()

    def on_tick_key(self, sample: zenoh.Sample) -> None:
        payload = sample.payload.to_bytes()
        with self._lock:
            if payload == MARKER:
                self._marker_seen = True
                return
            try:
                tick = decode(payload, Tick)
            except MalformedMessage:
                return  # our own garbage coming back
            if self.first_tick is None:
                self.first_tick = tick.tick
                self.live.set()
            if self._marker_seen and self.confirmed_before_tick is None:
                self.confirmed_before_tick = tick.tick
                self.done.set()

    def on_outcome(self, sample: zenoh.Sample) -> None:
        if _decodes_as(sample.payload.to_bytes(), Outcome):
            self.live.set()
            self.done.set()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m deploy.hostile", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run-id", required=True)
    ap.add_argument("--vids", type=int, nargs="+", required=True, help="the run's connected vehicles")
    ap.add_argument("--garbage", type=int, default=80, help="malformed payloads per key")
    ap.add_argument("--wrong-typed", type=int, default=20, help="valid messages of another type per key")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--proxy", action="store_true", help="the run has a channel proxy: wait for it too")
    ap.add_argument("--timeout-s", type=float, default=120.0, help="safety net: give up waiting after this long")
    ap.add_argument("--log-level", default="INFO")
    add_zenoh_args(ap)
    args = ap.parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s hostile %(levelname)s %(message)s")
    run = args.run_id
    targets = data_keys(run, args.vids)
    tick_key = keys.world_tick(run)
    plan = {key: payloads_for(key, cls, args.garbage, args.wrong_typed, args.seed)
            for key, cls in targets.items() if key != tick_key}
    plan[tick_key] = payloads_for(tick_key, Tick, args.garbage, args.wrong_typed, args.seed) + [MARKER]  # last
    report = {"sent": {k: len(v) for k, v in plan.items()},
              "bad_envelope": {k: sum(peek_envelope(p) is None for p in v) for k, v in plan.items()}}
    watch = Watch()
    z = zenoh_args_from(args)
    with session_scope(z) as session, session_scope(z) as echo:
        subs = [echo.declare_subscriber(tick_key, watch.on_tick_key),
                echo.declare_subscriber(keys.world_outcome(run), watch.on_outcome)]
        proxy_up = threading.Event()
        if args.proxy:
            subs.append(session.liveliness().declare_subscriber(
                keys.proxy_alive(run), lambda s: proxy_up.set() if s.kind == zenoh.SampleKind.PUT else None,
                history=True))
        else:
            proxy_up.set()
        if not (watch.live.wait(args.timeout_s) and proxy_up.wait(args.timeout_s)):
            log.error("the run never became live")
            return 1
        log.info("run live at tick %s; sending %d payloads on %d keys", watch.first_tick,
                 sum(report["sent"].values()), len(plan))
        for key, payloads in plan.items():  # the tick key last: its last payload is the marker
            pub = session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
            for payload in payloads:
                pub.put(payload)
            pub.undeclare()
        watch.done.wait(args.timeout_s)
        for sub in subs:
            sub.undeclare()
    report.update(first_tick=watch.first_tick, confirmed_before_tick=watch.confirmed_before_tick)
    print("hostile_peer " + json.dumps(report), flush=True)
    if watch.confirmed_before_tick is None:
        log.error("the run ended before every payload was confirmed routed")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
