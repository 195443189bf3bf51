"""A hostile peer: ``python -m bench.hostile --run-id R --connect HUB --vids 0 1 2``.

Joins a run's hub and, once the run is live, publishes on every data key the run uses
(every ``protocol.keys`` key but the liveliness tokens, for each given vehicle, and the
twins that carry the shared-memory notices of a one-host run) a
known number of payloads that no subscriber of that key may accept: generated and
mutated garbage (``bench/fuzz.py``'s generators, seeded by key) and well-formed
messages of another type. Nothing it sends is a valid message of the key's own type:
impersonating a peer is not what this tests, surviving garbage is.

Deterministic: the payloads are a function of ``--seed``, the run id and the key;
"live" is an event (the world's first tick reached us, and the channel proxy's
liveliness token is up with ``--proxy``), never a sleep. Once its payloads are built
and its subscriptions are up, it holds the liveliness token
``keys.participant_alive(run, --name)``: a world told ``--wait-for hostile`` plays no
tick before that, so the first tick the peer sees is tick 0 on any machine.
``--late-s S`` (fault injection: a slow peer) holds that token back until every
agent's token and the proxy's are up, the moment a world that did not wait would
start, and S seconds more. The last payload goes on the
world's tick key, and a second session of ours subscribed to that key through the hub
sees it come back: the hub has then routed every payload we sent (it forwards one
link's messages in order). The first real tick seen after it is reported as
``confirmed_before_tick``: every process that handled that tick's traffic had every
payload we sent queued before it.

With ``--forge --insider FILE``, it also impersonates, in a signed run (``--sign``):
it holds one vehicle's own credentials (``FILE``: a compromised vehicle, the
``insider``) and, every interval of its first ``--forge-ticks``, sends what that
vehicle and a stranger could send to make others act on a lie (``Forger``): commands
and reports for another vehicle (``--victim``), unsigned, under a certificate no
authority issued, under the insider's key, with the victim's certificate and a wrong
signature, and replays of the victim's own earlier ones; control messages in the
victim's name that add a phantom object of the highest reward, sent in the insider's
slot; object payloads with phantom points, in another's name, and replays of the
insider's earlier ones; replays of the victim's earlier control messages on its own
key. Each forged control message and payload is reported by its SHA-256, with the
reason a receiver must reject it for.

Ends with one line on stdout, ``hostile_peer {json}``: ``sent`` (per key),
``bad_envelope`` (per key, the payloads whose envelope the recorder cannot read, so
it records them on a schemaless channel), ``signed_envelope`` (per key, the payloads
that are ``Signed`` envelopes: a verifier rejects them, by certificate, rather than
count them malformed), ``first_tick`` and ``confirmed_before_tick``; with ``--forge``
also ``forged`` (per key and reason, what went out) and ``frames`` (SHA-256 of each
forged control message and payload -> the reason). Exit 0 once confirmed, 1 if the run
ended (or ``--timeout-s`` passed) first.
"""

from __future__ import annotations

import argparse
import hashlib
import inspect
import json
import logging
import queue
import random
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import zenoh

from bench import fuzz
from protocol.codec import peek_envelope
from protocol import keys
from protocol.codec import MalformedMessage, decode, encode
from protocol.messages import (AgentReport, ChannelStats, Command, ControlMsg, CtrlBundle, DataBundle, DataTx,
                               EmpBundle, EmpUpload, InShm, MapMsg, Mission, ObjectMap, Outcome, Pose, Rejected,
                               Scan, Signed, Tick, Transmission, WorldTruth)
from protocol.security import Authority, Credentials, Signer, Verifier
from protocol.session import add_zenoh_args, session_scope, zenoh_args_from
from vehicle_agent.payload import ObjectPayload, encode_object, header_of

log = logging.getLogger("bench.hostile")

# the message type each data key carries (its subscribers decode that type only)
KEY_TYPES: dict[Callable[..., str], type] = {
    keys.world_tick: Tick, keys.world_map: MapMsg, keys.world_truth: WorldTruth, keys.world_outcome: Outcome,
    keys.mission: Mission, keys.scan: Scan, keys.cmd: Command, keys.report: AgentReport,
    keys.net_ctrl_tx: ControlMsg, keys.net_ctrl_rx: CtrlBundle, keys.net_data_tx: DataTx,
    keys.net_data_rx: DataBundle, keys.net_stats: ChannelStats, keys.net_emp_up: EmpUpload,
    keys.net_emp_down: EmpBundle, keys.rejected: Rejected,
}
# the keys whose payloads a one-host run puts in shared memory (protocol.shm): the
# notices on their twins (keys.in_shm) are data keys too
SHM_KEYS = (keys.scan, keys.net_ctrl_rx, keys.net_data_rx)
# liveliness tokens and the run's wildcard
NOT_DATA = (keys.alive, keys.proxy_alive, keys.participant_alive, keys.alive_any, keys.everything)
MAX_PAYLOAD_BYTES = 4096  # garbage, not load: keep the hub's work small
MARKER = b"\xc1hostile-peer: last payload"  # 0xc1 is never used by msgpack: garbage like the rest


def key_functions() -> list[Callable[..., str]]:
    """Every ``protocol.keys`` function that builds a key of a run."""
    return [fn for name, fn in inspect.getmembers(keys, inspect.isfunction)
            if fn.__module__ == keys.__name__ and not name.startswith("_")
            and list(inspect.signature(fn).parameters)[:1] == ["run"]]


def data_keys(run: str, vids: list[int]) -> dict[str, type | tuple[type, ...]]:
    """``{key: message type}`` for every data key of a run with vehicles ``vids``; a
    shared-memory twin key's are ``InShm`` and its key's own type (a payload its writer
    could not put in shared memory comes on the twin itself)."""
    out: dict[str, type] = {}
    for fn in key_functions():
        if fn in NOT_DATA:
            continue
        built = [fn(run)] if len(inspect.signature(fn).parameters) == 1 else [fn(run, vid) for vid in vids]
        out.update({key: KEY_TYPES[fn] for key in built})
        if fn in SHM_KEYS:
            out.update({keys.in_shm(key): (InShm, KEY_TYPES[fn]) for key in built})
    return out


def payloads_for(key: str, cls: type | tuple[type, ...], garbage: int, wrong_typed: int, seed: int) -> list[bytes]:
    """``garbage`` fuzzed payloads that ``cls`` (each of its types) refuses, then
    ``wrong_typed`` valid messages of the other types in turn; a function of (seed,
    key) only."""
    accepted = cls if isinstance(cls, tuple) else (cls,)
    rnd = random.Random(f"{seed}:{key}")
    out: list[bytes] = []
    while len(out) < garbage:
        payload = fuzz.fuzz_input(accepted[0].__name__, rnd)
        if len(payload) <= MAX_PAYLOAD_BYTES and not any(_decodes_as(payload, c) for c in accepted):
            out.append(payload)
    others = [c.__name__ for c in fuzz.MESSAGE_TYPES if c not in accepted]
    for i in range(wrong_typed):
        out.append(fuzz.valid_payload(others[i % len(others)], rnd))
    return out


def sha256(payload: bytes) -> str:
    return hashlib.sha256(payload).hexdigest()


class Forger:
    """What a compromised vehicle (``insider``, with its own credentials) and a stranger
    send each interval to make others act on a lie; see the module's docstring.

    Fed the run's traffic (``on_*``: the victim's genuine commands and control
    messages, the insider's genuine payloads), it forges, for world tick k, commands
    and a report of tick k for the victim, control messages and object payloads of tick
    k + 1 in the insider's slot (they wait there for the next control and data phases:
    the medium files them under k + 1 as soon as they come, whoever else sends), and
    replays of the victim's control message of tick k - 1 on the victim's own key.
    """

    PHANTOM_ID = 9_999_999

    def __init__(self, pubs: dict[str, zenoh.Publisher], run: str, insider: Credentials, victim: int) -> None:
        self.pubs, self.run, self.victim = pubs, run, victim
        self.insider = Signer(insider)
        self.genuine = Verifier(insider.authority, run)  # to tell the victim's own messages from ours
        self.stranger = Signer(Authority(run).issue(victim, 0.0, 1e9))  # a certificate no run's authority issued
        self.forged: dict[str, dict[str, int]] = {}
        self.frames: dict[str, str] = {}  # "<tick>:<sha256>" of a forged control message or payload -> the reason
        self._lock = threading.Lock()
        self._cmds: dict[int, bytes] = {}  # the victim's genuine commands by tick
        self._victim_cert = None
        self._ctrl: tuple[ControlMsg, bytes] | None = None  # the victim's newest genuine control message, raw
        self._payloads: list[bytes] = []  # the insider's genuine payloads, oldest first
        self._ours: set[bytes] = set()  # the payloads we forged

    # -- what the run shows everybody

    def on_cmd(self, sample: zenoh.Sample) -> None:
        raw = sample.payload.to_bytes()
        try:
            cmd = self.genuine.open(raw, Command, self.victim, "cmd")
        except MalformedMessage:
            return
        if cmd is not None:
            with self._lock:
                self._cmds.setdefault(cmd.tick, raw)
                self._victim_cert = decode(raw, Signed).certificate

    def on_ctrl_bundle(self, sample: zenoh.Sample) -> None:
        try:
            bundle = decode(sample.payload.to_bytes(), CtrlBundle)
            frames = bundle.frames_of(self.victim)
            msg = self.genuine.open(frames[0], ControlMsg, self.victim, "ctrl") if frames else None
        except MalformedMessage:
            return
        if msg is not None:
            with self._lock:
                self._ctrl = (msg, frames[0])

    def on_data_bundle(self, sample: zenoh.Sample, insider_vid: int) -> None:
        try:
            bundle = decode(sample.payload.to_bytes(), DataBundle)
        except MalformedMessage:
            return
        with self._lock:  # the insider's own, not ours relayed in its slot
            mine = [r.payload for r in bundle.receptions if r.sender == insider_vid and r.payload not in self._ours
                    and (header_of(r.payload) or (None,))[0] == insider_vid]
            self._payloads = (self._payloads + mine)[-8:]

    # -- forging

    def _put(self, key: str, raw: bytes, reason: str, tick: int | None = None) -> None:
        """Send ``raw``; ``tick``: it is a control message the medium will relay in that
        interval's bundle, recorded as ``"<tick>:<sha256>"`` with its reason."""
        self.pubs[key].put(raw)
        per = self.forged.setdefault(key, {})
        per[reason] = per.get(reason, 0) + 1
        if tick is not None:
            self.frames[f"{tick}:{sha256(raw)}"] = reason

    def _bad_signature(self, msg) -> bytes:
        """``msg`` under the victim's own certificate, signed by somebody else."""
        body = encode(msg)
        return encode(Signed(msg.tick, msg.t_sim_s, self._victim_cert, body, self.insider.signature(body)))

    def forge(self, tick: Tick) -> None:
        k, t, v, run = tick.tick, tick.t_sim_s, self.victim, self.run
        insider = self.insider.credentials.vid
        with self._lock:
            old_cmds = [raw for kk, raw in sorted(self._cmds.items()) if kk < k]
            ctrl, payloads, cert = self._ctrl, list(self._payloads), self._victim_cert
        # the world: commands and the ego's report in the victim's name
        cmd = Command(k, t, v, 3.0, 0.5)  # full throttle, hard left
        self._put(keys.cmd(run, v), encode(cmd), "unsigned")
        self._put(keys.cmd(run, v), self.stranger.seal(cmd), "bad_certificate")
        self._put(keys.cmd(run, v), self.insider.seal(cmd), "wrong_key")
        if cert is not None:
            self._put(keys.cmd(run, v), self._bad_signature(cmd), "bad_signature")
        if old_cmds:
            self._put(keys.cmd(run, v), old_cmds[-1], "replayed")
        report = AgentReport(k, t, v, np.zeros((0, 2), np.float32), 0, False)  # "I see nothing"
        self._put(keys.report(run, v), self.stranger.seal(report), "bad_certificate")
        # the medium: control messages in the victim's name with a phantom object, in the insider's slot
        if ctrl is not None:
            msg, raw = ctrl
            phantom = self._phantom(msg, k + 1, t + 0.1)
            for reason, frame in (("unsigned", encode(phantom)), ("bad_certificate", self.stranger.seal(phantom)),
                                  ("wrong_key", self.insider.seal(phantom))):
                self._put(keys.net_ctrl_tx(run, insider), frame, reason, k + 1)
            self._put(keys.net_ctrl_tx(run, v), raw, "late")  # the victim's own, replayed: a past interval
        # object payloads in the insider's slot, in a frame naming the victim
        if payloads:
            last = payloads[-1]
            sender, oid, _ = header_of(last)
            fake = self._payload(insider, oid, k + 1, t + 0.1)
            other = self._payload(v, oid, k + 1, t + 0.1)
            with self._lock:
                self._ours.update((fake, other))
            txs = [(fake, "bad_signature"), (other, "wrong_key"), (payloads[0], "replayed")]
            frame = encode(DataTx(k + 1, t + 0.1, v, [Transmission(oid, 0.0, p) for p, _ in txs]))
            self._put(keys.net_data_tx(run, insider), frame, "payloads")
            for p, reason in txs:
                self.frames[f"{k + 1}:{sha256(p)}"] = reason

    def _phantom(self, msg: ControlMsg, tick: int, t_sim_s: float) -> ControlMsg:
        """``msg`` as of ``tick`` with one more object: unseen by and relevant to everyone."""
        om = msg.objects
        m = len(om.receivers)
        objects = ObjectMap(np.append(om.object_id, self.PHANTOM_ID), np.append(om.size_bytes, 64),
                            np.vstack([om.centroid_xy, np.array([[0.0, 0.0]], np.float32)]).astype(np.float32),
                            om.receivers, np.vstack([om.visibility, np.zeros((1, m), np.float32)]),
                            np.vstack([om.relevance, np.ones((1, m), np.float32)]))
        n = len(objects.object_id)
        return replace(msg, tick=tick, t_sim_s=t_sim_s, objects=objects,
                       unscheduled=np.append(msg.starvation(), 1000),
                       digests=np.zeros((n, msg.digests.shape[1]), np.uint8))

    @staticmethod
    def _payload(sender: int, oid: int, tick: int, t_sim_s: float) -> bytes:
        """A car-sized block of points where the intersection's conflict point is."""
        g = np.mgrid[-2.0:2.0:0.25, -1.0:1.0:0.25, 0.0:1.5:0.25].reshape(3, -1).T.astype(np.float32)
        return encode_object(ObjectPayload(sender, oid, tick, t_sim_s, Pose(0.0, 0.0, 0.0), 1.9,
                                           np.zeros(3, np.float32), np.zeros(2, np.float32), g))


def _decodes_as(payload: bytes, cls: type) -> bool:
    try:
        decode(payload, cls)
    except MalformedMessage:
        return False
    return True


def _forge(forger: Forger, ticks: queue.SimpleQueue, n: int, watch: Watch, timeout_s: float) -> None:
    """Forge at each of the next ``n`` world ticks (or until the run ends)."""
    done = 0
    while done < n and not watch.done.is_set():
        try:
            tick = ticks.get(timeout=timeout_s)
        except queue.Empty:
            return
        while tick is not None and not ticks.empty():  # behind: forge at the newest tick only
            tick = ticks.get()
        if tick is None:
            return
        forger.forge(tick)
        done += 1


class Watch:
    """What our second session sees on the world's tick key, in the hub's order."""

    def __init__(self) -> None:
        self.on_tick: Callable[[Tick | None], None] = lambda tick: None
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
            self.on_tick(tick)
            if self._marker_seen and self.confirmed_before_tick is None:
                self.confirmed_before_tick = tick.tick
                self.done.set()

    def on_outcome(self, sample: zenoh.Sample) -> None:
        if _decodes_as(sample.payload.to_bytes(), Outcome):
            self.live.set()
            self.done.set()
            self.on_tick(None)


def _late(session: zenoh.Session, run: str, vids: list[int], proxy_up: threading.Event, late_s: float,
          timeout_s: float) -> bool:
    """Wait until every agent's liveliness token and the proxy's are up (a world that
    does not wait for us starts now), then ``late_s`` more: a slow peer, on purpose."""
    up: set[int] = set()
    all_up = threading.Event()

    def on_token(sample: zenoh.Sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            up.add(keys.vid_of(str(sample.key_expr)))
            if up >= set(vids):
                all_up.set()

    sub = session.liveliness().declare_subscriber(keys.alive(run, "*"), on_token, history=True)
    try:
        if not (all_up.wait(timeout_s) and proxy_up.wait(timeout_s)):
            return False
    finally:
        sub.undeclare()
    log.warning("fault injection: every agent and the proxy are up; declaring our token %.1f s late", late_s)
    time.sleep(late_s)  # the fault itself, not a synchronisation: the world's --wait-for is what is tested
    return True


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.hostile", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run-id", required=True)
    ap.add_argument("--vids", type=int, nargs="+", required=True, help="the run's connected vehicles")
    ap.add_argument("--garbage", type=int, default=80, help="malformed payloads per key")
    ap.add_argument("--wrong-typed", type=int, default=20, help="valid messages of another type per key")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--proxy", action="store_true", help="the run has a channel proxy: wait for it too")
    ap.add_argument("--timeout-s", type=float, default=120.0, help="safety net: give up waiting after this long")
    ap.add_argument("--forge", action="store_true", help="also impersonate (a signed run; needs --insider)")
    ap.add_argument("--insider", default=None, metavar="FILE", help="the compromised vehicle's credentials")
    ap.add_argument("--victim", type=int, default=0, help="the vehicle whose name the forgeries take")
    ap.add_argument("--forge-ticks", type=int, default=8, help="intervals to forge in, from the first one seen")
    ap.add_argument("--name", default="hostile", help="our participant token's name (the world's --wait-for NAME)")
    ap.add_argument("--late-s", type=float, default=0.0, metavar="S",
                    help="fault injection: declare our token only S s after every agent and the proxy are up")
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
              "bad_envelope": {k: sum(peek_envelope(p) is None for p in v) for k, v in plan.items()},
              "signed_envelope": {k: sum(_decodes_as(p, Signed) for p in v) for k, v in plan.items()}}
    if args.forge and not args.insider:
        ap.error("--forge needs --insider")
    watch = Watch()
    z = zenoh_args_from(args)
    with session_scope(z) as session, session_scope(z) as echo:
        # one publisher per key, shared by the garbage and the forger, all declared before we
        # are ready: a second publisher declared on a key while the first one was sending
        # lost the first one's payloads (100 of 100 on the insider's control key, once)
        pubs = {key: session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK) for key in plan}
        forger = Forger(pubs, run, Credentials.load(args.insider), args.victim) if args.forge else None
        if forger is not None and not {args.victim, forger.insider.credentials.vid} <= set(args.vids):
            log.error("--victim and the insider must be among --vids")
            return 2
        ticks: queue.SimpleQueue[Tick | None] = queue.SimpleQueue()
        watch.on_tick = ticks.put
        subs = [echo.declare_subscriber(tick_key, watch.on_tick_key),
                echo.declare_subscriber(keys.world_outcome(run), watch.on_outcome)]
        if forger is not None:
            insider = forger.insider.credentials.vid
            subs += [echo.declare_subscriber(keys.cmd(run, args.victim), forger.on_cmd),
                     echo.declare_subscriber(keys.net_ctrl_rx(run), forger.on_ctrl_bundle),
                     echo.declare_subscriber(keys.net_data_rx(run), lambda s: forger.on_data_bundle(s, insider))]
        proxy_up = threading.Event()
        if args.proxy:
            subs.append(session.liveliness().declare_subscriber(
                keys.proxy_alive(run), lambda s: proxy_up.set() if s.kind == zenoh.SampleKind.PUT else None,
                history=True))
        else:
            proxy_up.set()
        if args.late_s > 0 and not _late(session, run, args.vids, proxy_up, args.late_s, args.timeout_s):
            log.error("the run's agents never came up")
            return 1
        # last, on the session of our subscriptions: the hub has them before the world sees the token
        subs.append(echo.liveliness().declare_token(keys.participant_alive(run, args.name)))
        if not (watch.live.wait(args.timeout_s) and proxy_up.wait(args.timeout_s)):
            log.error("the run never became live")
            return 1
        log.info("run live at tick %s; sending %d payloads on %d keys", watch.first_tick,
                 sum(report["sent"].values()), len(plan))
        forging = threading.Thread(target=_forge, args=(forger, ticks, args.forge_ticks, watch, args.timeout_s),
                                   daemon=True) if forger is not None else None
        if forging is not None:
            forging.start()
        for key, payloads in plan.items():  # the tick key last: its last payload is the marker
            if key == tick_key and forging is not None:
                forging.join()  # every forgery out before the marker
            for payload in payloads:
                pubs[key].put(payload)
        watch.done.wait(args.timeout_s)
        for entity in (*subs, *pubs.values()):
            entity.undeclare()
        if forger is not None:
            report.update(forged=forger.forged, frames=forger.frames)
    report.update(first_tick=watch.first_tick, confirmed_before_tick=watch.confirmed_before_tick)
    print("hostile_peer " + json.dumps(report), flush=True)
    if watch.confirmed_before_tick is None:
        log.error("the run ended before every payload was confirmed routed")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
