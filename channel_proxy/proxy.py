"""The channel proxy's I/O: collect what vehicles transmit, play the medium, deliver
to each receiver what it hears, publish statistics.

One interval (tick k), lock-step:
1. the world's ``Tick`` opens tick k and names the live vehicles;
2. control phase: wait until every expected vehicle has sent its ``ControlMsg`` for k
   (or a wall-clock timeout, or the world's next tick); play the control channel;
   publish one ``CtrlBundle``: every message once, and who heard which (it closes the
   phase for every receiver);
3. data phase: wait likewise for a ``DataTx`` from every vehicle that took part in
   the control phase; play the data channel; publish one ``DataBundle`` (every
   decoded payload once, and who decoded which), then ``ChannelStats``.

Who sent what: a frame on vehicle v's key (``.../tx/<v>``) is in v's slot. The first
one that names v (its ``vid``) is v's message for the phase: the phase waits for it,
and the medium plays it (its position, its size, its airtime). In an unsigned run any
other frame is dropped (one naming another vehicle is counted malformed, a second one
naming v ``duplicate``). In a signed run (``relay_extra_frames``) the proxy judges
nobody's identity: any other frame in v's slot is relayed unplayed, after v's own, to
the receivers that heard v's (control) or with the fate of v's own transmission of the
same object, else of its first decoded one (data); the first eight per slot, the rest
counted ``flooded``. The proxy verifies nothing: a signed frame (``protocol.security``)
is read through its envelope, and the receivers check who really sent what. On an open
network a frame naming v that comes before v's own is played as v's, and v's own is
then a second frame: that can make the medium mis-place v or close a phase without it,
never make a receiver accept a forgery; ``--lock-down`` (docs/security.md) lets only
v's session put on v's keys.

Expected vehicles: the tick's live set minus the dead. A vehicle that misses a phase is
absent for that tick; after ``dead_after`` absences in a row it is dead and no longer
waited for, until it sends again; a liveliness token that disappears makes it dead at
once. Real-time mode closes the phases at wall-clock deadlines after the tick instead.

EMP mode replaces both phases by one upload phase (``EmpUpload``), played by the relay
(``emp.py``) and delivered as one ``EmpBundle`` per receiver.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any

import msgpack
import numpy as np
import zenoh

from channel_proxy import emp, loss, medium
from channel_proxy.profiles import ChannelProfile
from protocol import keys, phases
from protocol.codec import MalformedMessage, decode, encode, slots_constructor
from protocol.faults import Injector
from protocol.messages import (ChannelStats, ControlMsg, CtrlBundle, DataBundle, DataTx, EmpBundle, EmpSegment,
                               EmpUpload, Outcome, Reception, Signed, Tick)
from protocol.session import DropCounter, big_publisher, reliable_publisher
from protocol.shm import ShmPublisher

log = logging.getLogger(__name__)

MODES = ("v2v", "emp")
FUTURE_TICKS = 2  # messages may run ahead of the tick by this much (they race the world's Tick)
MAX_EXTRA_FRAMES = 8  # frames relayed unplayed per slot and phase


@dataclass(frozen=True, slots=True)
class ProxyConfig:
    run_id: str
    profile: ChannelProfile
    mode: str = "v2v"
    seed: int = 0
    ctrl_loss: float = 0.0  # fixed loss rate on every control link, on top of the distance model
    data_loss: float = 0.0  # likewise on the data channel (and both relay hops in EMP mode)
    realtime: bool = False
    phase_timeout_s: float = 5.0  # lock-step: wall time a phase waits for the missing
    dead_after: int = 3  # absences in a row before a vehicle is no longer waited for
    ctrl_deadline_s: float = 0.03  # real-time: the control phase closes this long after the tick
    data_deadline_s: float = 0.09  # real-time: the data phase closes this long after the tick
    relay_xy: tuple[float, float] = (0.0, 0.0)
    emp_bytes_per_point: float = 6.0
    exit_on_outcome: bool = True
    relay_extra_frames: bool = False  # a signed run: relay a slot's other frames too (module docstring)
    shm_dir: str | None = None  # the bundles go through the run's shared memory (protocol.shm)

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}")
        for name in ("ctrl_loss", "data_loss"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must lie in [0, 1]")
        if self.dead_after < 1 or self.phase_timeout_s <= 0:
            raise ValueError("dead_after >= 1 and phase_timeout_s > 0 required")


@dataclass
class Counters:
    """Cumulative counts over the run (the per-interval ones go into each stats message)."""

    intervals: int = 0
    late: int = 0  # messages for a phase already closed
    duplicate: int = 0
    not_live: int = 0  # from a vehicle the tick does not list
    foreign: int = 0  # frames naming another vehicle than their key's (dropped; relayed unplayed in a signed run)
    extra_frames: int = 0  # frames relayed unplayed (foreign, or a second one naming the key's vehicle)
    flooded: int = 0  # frames beyond MAX_EXTRA_FRAMES in a slot, dropped
    invalid_tx: int = 0  # transmissions with a negative or non-finite start
    skipped_ticks: int = 0
    dead: dict[int, str] = field(default_factory=dict)


class ChannelProxy:
    def __init__(self, config: ProxyConfig, session: zenoh.Session) -> None:
        self.cfg = config
        self.session = session
        self.drops = DropCounter()
        self.faults = Injector("proxy")
        self.counters = Counters()
        self.last_stats: dict[str, Any] | None = None
        self._cv = threading.Condition()
        self._stop = threading.Event()
        self._tick: Tick | None = None  # newest Tick heard
        self._done_tick = -1  # newest tick fully played
        self._closed = {"ctrl": -1, "data": -1, "emp": -1}  # newest tick whose phase closed
        self._inbox: dict[str, dict[int, dict[int, Any]]] = {p: defaultdict(dict) for p in self._closed}
        self._extra: dict[str, dict[int, dict[int, list]]] = {p: defaultdict(dict) for p in self._closed}
        self._absent: dict[int, int] = {}  # absences in a row
        self._dead: set[int] = set()
        self._token_gone: set[int] = set()
        self._last_xy: dict[int, tuple[float, float]] = {}
        self._pubs: dict[str, zenoh.Publisher | ShmPublisher] = {}
        self._bundles: dict[str, ShmPublisher] = {}
        self._extras: dict[int, list] = {}  # the closed phase's frames beyond each slot's own
        self._awaited: tuple[str, int, set[int]] | None = None  # the phase being collected, whom it waits for
        # several scheduler domains (docs/domains.md): phase -> tick -> vid -> domain -> (msg, raw, channel)
        self._dom_inbox: dict[str, dict[int, dict[int, dict[int, tuple]]]] = {p: defaultdict(dict) for p in self._closed}
        self._dom_want: dict[str, dict[int, dict[int, set[int]]]] = {p: defaultdict(dict) for p in self._closed}
        self._dom_got: dict[int, dict[int, tuple]] = {}  # the closed phase's frames by vid and domain
        self._entities: list = []
        self._cpu_mark = time.process_time()

    # ------------------------------------------------------------------ wiring

    def _declare(self) -> None:
        s, run = self.session, self.cfg.run_id
        self._entities += [
            s.declare_subscriber(keys.world_tick(run), self._on_tick),
            s.declare_subscriber(keys.world_outcome(run), self._on_outcome),
            s.liveliness().declare_subscriber(keys.alive(run, "*"), self._on_token, history=True),
        ]
        if self.cfg.mode == "v2v":
            self._entities += [
                s.declare_subscriber(keys.net_ctrl_tx(run, "*", "*", "*"), self._inbound("ctrl", ControlMsg)),
                s.declare_subscriber(keys.net_data_tx(run, "*", "*", "*"), self._inbound("data", DataTx)),
            ]
            self._bundles = {key: ShmPublisher(s, key, self.cfg.shm_dir)  # undeclared with _pubs
                             for key in (keys.net_ctrl_rx(run), keys.net_data_rx(run))}
            self._pubs.update(self._bundles)
        else:
            self._entities.append(s.declare_subscriber(keys.net_emp_up(run, "*"), self._inbound("emp", EmpUpload)))
        self._pubs["stats"] = reliable_publisher(s, keys.net_stats(run))  # the recorder and the bench count on every one
        self._entities.append(s.liveliness().declare_token(keys.proxy_alive(run)))  # declared last: all is set up

    def _pub(self, key: str) -> zenoh.Publisher:
        pub = self._pubs.get(key)
        if pub is None:
            pub = self._pubs[key] = big_publisher(self.session, key)
        return pub

    def _on_tick(self, sample: zenoh.Sample) -> None:
        try:
            tick = decode(sample.payload.to_bytes(), Tick)
        except MalformedMessage as err:
            self.drops.add(str(sample.key_expr), err)
            return
        with self._cv:
            if self._tick is None or tick.tick > self._tick.tick:
                self._tick = tick
                self._cv.notify_all()

    def _on_outcome(self, sample: zenoh.Sample) -> None:
        try:
            decode(sample.payload.to_bytes(), Outcome)
        except MalformedMessage as err:
            self.drops.add(str(sample.key_expr), err)
            return
        if self.cfg.exit_on_outcome:
            log.info("the world published its outcome; stopping")
            self.stop()

    def _on_token(self, sample: zenoh.Sample) -> None:
        try:
            vid = keys.vid_of(str(sample.key_expr))
        except ValueError:
            return
        with self._cv:
            if sample.kind == zenoh.SampleKind.PUT:
                self._token_gone.discard(vid)
            else:
                self._token_gone.add(vid)
                self._kill(vid, "liveliness token dropped")
            self._cv.notify_all()

    def _inbound(self, phase: str, expected: type):
        """Subscriber callback: decode, check, and file the message under (tick, vid)."""

        def handler(sample: zenoh.Sample) -> None:
            key = str(sample.key_expr)
            raw = sample.payload.to_bytes()
            try:
                msg = read_frame(raw, expected) if self.cfg.relay_extra_frames else decode(raw, expected)
                vid = keys.vid_of(key)
            except (MalformedMessage, ValueError) as err:
                self.drops.add(key, err)
                return
            relay = self.cfg.relay_extra_frames
            channel, domain = keys.channel_domain_of(key)
            with self._cv:
                if self._domain_frame(phase, msg, vid, channel, domain, raw, key):
                    return
                if msg.vid != vid and not relay:
                    self.counters.foreign += 1
                    self.drops.add(key, ValueError(f"vid {msg.vid} on vehicle {vid}'s key"))
                    return
                newest = self._tick.tick if self._tick is not None else -1
                if msg.tick <= self._closed[phase]:
                    self.counters.late += 1
                    return
                if msg.tick > newest + FUTURE_TICKS:
                    self.drops.add(key, ValueError(f"tick {msg.tick} is far ahead of the world's {newest}"))
                    return
                box = self._inbox[phase][msg.tick]
                if not relay:  # one frame per slot: the vehicle's own
                    if vid in box:
                        self.counters.duplicate += 1
                        return
                    box[vid] = (msg, raw)
                    self._filed(phase, msg.tick, vid)
                    return
                extra = self._extra[phase][msg.tick].setdefault(vid, [])
                if (vid in box and box[vid][1] == raw) or any(r == raw for _, r in extra):
                    self.counters.duplicate += 1
                    return
                if msg.vid == vid and vid not in box:
                    box[vid] = (msg, raw)  # the vehicle's own: played, and waited for
                    self._filed(phase, msg.tick, vid)
                elif len(extra) >= MAX_EXTRA_FRAMES:
                    self.counters.flooded += 1
                else:
                    self.counters.foreign += msg.vid != vid
                    extra.append((msg, raw))

        return handler

    def _domain_frame(self, phase: str, msg: Any, vid: int, channel: int, domain: int, raw: bytes, key: str) -> bool:
        """Caller holds ``_cv``. File a frame of a map with several domains (one on a
        domain's keys, or a control message naming its domains) under (tick, vid,
        domain); once a vehicle has sent in every domain it takes part in (those its
        control messages name; in the data phase, those it sent control in), its first
        frame goes into the phase's inbox, where the lock-step waits for it. Returns
        False for a frame of a map of one domain, which is filed as always."""
        named = getattr(msg, "domains", None)
        want_of = self._dom_want[phase].get(msg.tick, {})
        if (channel, domain) == (0, 0) and not (named is not None and len(named)) and vid not in want_of:
            return False
        if msg.vid != vid:
            self.counters.foreign += 1
            self.drops.add(key, ValueError(f"vid {msg.vid} on vehicle {vid}'s key"))
            return True
        newest = self._tick.tick if self._tick is not None else -1
        if msg.tick <= self._closed[phase]:
            self.counters.late += 1
            return True
        if msg.tick > newest + FUTURE_TICKS:
            self.drops.add(key, ValueError(f"tick {msg.tick} is far ahead of the world's {newest}"))
            return True
        frames = self._dom_inbox[phase][msg.tick].setdefault(vid, {})
        if domain in frames:
            self.counters.duplicate += 1
            return True
        frames[domain] = (msg, raw, channel)
        if phase == "ctrl":
            want = self._dom_want[phase][msg.tick].setdefault(vid, {int(d) for d in named} if named is not None else set())
        else:
            want = want_of.get(vid, {domain})
        box = self._inbox[phase][msg.tick]
        if want <= set(frames) and vid not in box:
            first = frames[min(frames)]
            box[vid] = (first[0], first[1])
            self._filed(phase, msg.tick, vid)
        return True

    def _filed(self, phase: str, k: int, vid: int) -> None:
        """Caller holds ``_cv``: ``vid``'s own message for ``phase`` of tick ``k`` is in.
        Wakes the collector only when it was the last one the collector waits for: woken
        by every message, the proxy's main thread spent ~80 wake-ups a tick at 40
        vehicles re-testing a condition that still held."""
        awaited = self._awaited
        if awaited is not None and awaited[0] == phase and awaited[1] == k:
            awaited[2].discard(vid)
            if not awaited[2]:
                self._cv.notify_all()

    def _kill(self, vid: int, why: str) -> None:
        """Caller holds ``_cv``."""
        if vid not in self._dead:
            self._dead.add(vid)
            self.counters.dead[vid] = why
            log.warning("vehicle %d is dead for the channel (%s)", vid, why)

    # ------------------------------------------------------------------ running

    def stop(self) -> None:
        self._stop.set()
        with self._cv:
            self._cv.notify_all()

    def serve(self) -> Counters:
        """Play intervals until stopped; returns the run's counters."""
        self._declare()
        try:
            while not self._stop.is_set():
                tick, t_open = self._next_tick()
                if tick is None:
                    break
                self.faults.at(tick.tick)
                if self.cfg.mode == "v2v":
                    self._play_v2v(tick, t_open)
                else:
                    self._play_emp(tick, t_open)
        finally:
            for entity in self._entities:
                entity.undeclare()
            for pub in self._pubs.values():
                pub.undeclare()
        return self.counters

    def _next_tick(self) -> tuple[Tick | None, float]:
        with self._cv:
            while not self._stop.is_set():
                if self._tick is not None and self._tick.tick > self._done_tick:
                    if self._done_tick >= 0 and self._tick.tick > self._done_tick + 1:
                        self.counters.skipped_ticks += self._tick.tick - self._done_tick - 1
                    return self._tick, time.monotonic()
                self._cv.wait(0.5)
        return None, 0.0

    def _collect(self, phase: str, k: int, expected: set[int], deadline: float) -> dict[int, tuple[Any, bytes]]:
        """Wait until every expected vehicle has filed its message for tick k, the
        deadline passes, the world moves past k, or we stop; then close the phase.
        Returns each vehicle's own message; the phase's other frames are left in
        ``self._extras`` (vid -> [(msg, raw)])."""
        with self._cv:
            while not self._stop.is_set():
                have = self._inbox[phase].get(k, {})
                waiting = expected - set(have) - self._dead - self._token_gone
                if not waiting:
                    break
                if self._tick is not None and self._tick.tick > k:
                    break
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._awaited = (phase, k, waiting)  # the inbound callbacks wake us when it empties
                self._cv.wait(left)
            self._awaited = None
            self._closed[phase] = max(self._closed[phase], k)
            got = self._inbox[phase].pop(k, {})
            self._dom_got = self._dom_inbox[phase].pop(k, {})
            for t in [t for t in self._dom_inbox[phase] if t <= k]:
                self.counters.late += sum(map(len, self._dom_inbox[phase].pop(t).values()))
            for t in [t for t in self._dom_want[phase] if t <= k]:
                del self._dom_want[phase][t]
            self._extras = {v: frames for v, frames in self._extra[phase].pop(k, {}).items() if frames}
            self.counters.extra_frames += sum(map(len, self._extras.values()))
            for t in [t for t in self._inbox[phase] if t <= k]:
                self.counters.late += len(self._inbox[phase].pop(t))
            for t in [t for t in self._extra[phase] if t <= k]:
                self.counters.late += sum(map(len, self._extra[phase].pop(t).values()))
            return got

    def _deadline(self, t_open: float, realtime_after_s: float) -> float:
        return t_open + (realtime_after_s if self.cfg.realtime else self.cfg.phase_timeout_s)

    def _account(self, expected: set[int], present: set[int]) -> list[int]:
        """Absences in a row; dead after ``dead_after``; a vehicle that sends is alive again."""
        absent = sorted(expected - present)
        with self._cv:
            for vid in present:
                self._absent[vid] = 0
                if vid in self._dead and vid not in self._token_gone:
                    self._dead.discard(vid)
                    self.counters.dead.pop(vid, None)
                    log.info("vehicle %d is back", vid)
            for vid in absent:
                self._absent[vid] = self._absent.get(vid, 0) + 1
                if self._absent[vid] >= self.cfg.dead_after:
                    self._kill(vid, f"absent {self._absent[vid]} phases in a row")
        return absent

    def _live(self, tick: Tick) -> tuple[np.ndarray, set[int]]:
        with self._cv:
            live = np.array(sorted(set(tick.live) - self._token_gone), dtype=np.int64)
            expected = set(live.tolist()) - self._dead
        return live, expected

    def _positions(self, vids: np.ndarray) -> np.ndarray:
        """(C, 2) latest known position of each vehicle; NaN if never heard of."""
        nan = (math.nan, math.nan)
        return np.array([self._last_xy.get(v, nan) for v in vids.tolist()], dtype=np.float64).reshape(-1, 2)

    def _publish_stats(self, tick: Tick, stats: dict[str, Any], t_work: float) -> None:
        cpu = time.process_time()
        stats.update({
            "tick": tick.tick,
            "mode": self.cfg.mode,
            "work_ms": round((time.perf_counter() - t_work) * 1e3, 3),
            "cpu_ms": round((cpu - self._cpu_mark) * 1e3, 3),
            "malformed_dropped": self.drops.total,
            "late": self.counters.late,
            "duplicate": self.counters.duplicate,
            "not_live": self.counters.not_live,
            "extra_frames": self.counters.extra_frames,
            "flooded": self.counters.flooded,
            "invalid_tx": self.counters.invalid_tx,
            "dead": sorted(self.counters.dead),
        })
        self._cpu_mark = cpu
        self.last_stats = stats
        self.counters.intervals += 1
        self._pubs["stats"].put(encode_stats(tick.tick, tick.t_sim_s, stats))
        log.debug("tick %d: %s", tick.tick, stats)

    # ------------------------------------------------------------------ V2V

    def _play_v2v(self, tick: Tick, t_open: float) -> None:
        k, profile, run = tick.tick, self.cfg.profile, self.cfg.run_id
        live, expected = self._live(tick)
        ctrl = self._collect("ctrl", k, expected, self._deadline(t_open, self.cfg.ctrl_deadline_s))
        t_work = time.perf_counter()
        phases.mark("proxy.ctrl_closed", k)
        ctrl = self._only_live(ctrl, live)
        absent_ctrl = self._account(expected, set(ctrl))
        for vid, (msg, _) in ctrl.items():
            self._last_xy[vid] = (msg.pose.x_m, msg.pose.y_m)
        if self._dom_got:
            self._play_domains(tick, t_open, live, absent_ctrl, t_work)
            return
        d = loss.distances(self._positions(live))  # once for the range and both channels' p
        reach = loss.within_cutoff(d, profile.prr)
        p_ctrl = loss.probabilities_at(d, profile.prr, self.cfg.ctrl_loss)
        senders = np.array(sorted(ctrl), dtype=np.int64)
        s_idx = np.searchsorted(live, senders)
        sizes = np.array([_ctrl_onair(ctrl[v][0]) for v in senders.tolist()], dtype=np.int64)
        out = medium.play_control(live, s_idx, sizes, p_ctrl, reach, capacity_bytes=profile.ctrl_capacity_bytes,
                                  seed=self.cfg.seed, tick=k)
        columns, frames = self._with_extras(senders, [ctrl[v][1] for v in senders.tolist()], self._extras)
        bundle = encode(CtrlBundle(k, tick.t_sim_s, senders[columns], live, np.ascontiguousarray(out.heard.T[:, columns]),
                                   frames))
        phases.mark("proxy.ctrl_bundle_sent", k)
        self._bundles[keys.net_ctrl_rx(run)].put(k, tick.t_sim_s, bundle)
        ctrl_stats = {
            "senders": len(senders),
            "offered_bytes": int(sizes.sum()),
            "overflow_msgs": int(out.overflow.sum()),
            "delivered_pairs": int(out.heard.sum()),
            "lost_channel_pairs": int(out.lost_channel.sum()),
            "in_range_pairs": int(out.in_range.sum()),
            "absent": absent_ctrl,
            "extra_frames": len(frames) - len(senders),
        }
        same_loss = self.cfg.data_loss == self.cfg.ctrl_loss  # then the data channel's p is the control's
        p_data = p_ctrl if same_loss else loss.probabilities_at(d, profile.prr, self.cfg.data_loss)
        ctrl_work_s = time.perf_counter() - t_work

        data = self._collect("data", k, set(ctrl), self._deadline(t_open, self.cfg.data_deadline_s))
        t_work = time.perf_counter() - ctrl_work_s  # so that work_ms counts both phases' work, not the wait
        data = self._only_live(data, live)
        absent_data = self._account(set(ctrl), set(data))
        stats = {"ctrl": ctrl_stats, "data": self._deliver_data(tick, live, p_data, reach, data)}
        stats["data"]["absent"] = absent_data
        self._publish_stats(tick, stats, t_work)
        self._done_tick = k

    def _with_extras(self, senders: np.ndarray, own: list[bytes], extras: dict[int, list]) -> tuple[np.ndarray, list[bytes]]:
        """The bundle's columns: each sender's own message, then the other frames of its
        slot (a column index into ``senders`` per frame, and the frames); a slot
        without a message of its own relays nothing (nobody heard that vehicle)."""
        columns, frames = [], []
        for s, vid in enumerate(senders.tolist()):
            columns.append(s)
            frames.append(own[s])
            for _, raw in extras.get(vid, []):
                columns.append(s)
                frames.append(raw)
        return np.array(columns, dtype=np.int64), frames

    def _only_live(self, got: dict[int, tuple[Any, bytes]], live: np.ndarray) -> dict[int, tuple[Any, bytes]]:
        live_set = set(live.tolist())
        out = {v: m for v, m in got.items() if v in live_set}
        self.counters.not_live += len(got) - len(out)
        return out

    def _deliver_data(self, tick: Tick, live: np.ndarray, p: np.ndarray, reach: np.ndarray,
                      data: dict[int, tuple[DataTx, bytes]]) -> dict[str, Any]:
        k, profile, run = tick.tick, self.cfg.profile, self.cfg.run_id
        phases.mark("proxy.data_closed", k)
        txs: list[tuple[int, Any]] = []
        for vid in sorted(data):
            for t in data[vid][0].transmissions:
                if math.isfinite(t.start_s) and t.start_s >= 0.0:
                    txs.append((vid, t))
                else:
                    self.counters.invalid_tx += 1
        sender = np.searchsorted(live, np.array([v for v, _ in txs], dtype=np.int64))
        item = np.array([t.object_id for _, t in txs], dtype=np.int64)
        size = np.array([len(t.payload) for _, t in txs], dtype=np.int64)
        start = np.array([t.start_s for _, t in txs], dtype=np.float64)
        out = medium.play_data(live, sender, item, start, size, p, reach, bandwidth_bps=profile.bandwidth_bps,
                               interval_s=profile.decision_interval_s, seed=self.cfg.seed, tick=k)
        rx_s = out.end_ns / medium.NS
        sender_vid = live[sender] if len(txs) else sender
        decoded_any = out.delivered.any(axis=1)
        order = np.lexsort((item, sender_vid, out.end_ns))  # by time, sender, object
        order = order[decoded_any[order]]  # what somebody decoded
        # each transmission's numbers as Python's, once (not a numpy scalar per field and reception)
        vid_of, item_of, rx_of = sender_vid.tolist(), item.tolist(), rx_s.tolist()
        receptions = [_reception(vid_of[t], item_of[t], rx_of[t], txs[t][1].payload) for t in order.tolist()]
        twins, extra = self._extra_receptions(txs, self._extras, decoded_any, rx_s)
        decoded = out.delivered[np.concatenate([order, np.array(twins, dtype=np.int64)])]
        bundle = encode(DataBundle(k, tick.t_sim_s, live, np.ascontiguousarray(decoded.T), receptions + extra))
        phases.mark("proxy.data_bundle_sent", k)
        self._bundles[keys.net_data_rx(run)].put(k, tick.t_sim_s, bundle)
        # counts per transmission first (receivers over a row), then the sums: the same integers
        n_delivered, n_in_range = out.delivered.sum(axis=1), out.in_range.sum(axis=1)
        n_collided, n_lost = out.collided.sum(axis=1), out.lost_channel.sum(axis=1)
        start_of, delivered_of, in_range_of = (out.start_ns / medium.NS).tolist(), n_delivered.tolist(), \
            n_in_range.tolist()
        return {
            "transmissions": len(txs),
            "extra_receptions": len(extra),
            "offered_bytes": int(size.sum()),
            "overflow_tx": int(out.overflow.sum()),
            "overflow_bytes": int(size[out.overflow].sum()),
            "collided_tx": int((n_collided > 0).sum()),
            "delivered_pairs": int(n_delivered.sum()),
            "delivered_bytes": int((n_delivered * size).sum()),
            "lost_collision_bytes": int((n_collided * size).sum()),
            "lost_channel_bytes": int((n_lost * size).sum()),
            "in_range_bytes": int((n_in_range * size).sum()),
            "utilization": round(out.busy_ns / (profile.decision_interval_s * medium.NS), 4),
            "objects": [[vid_of[t], item_of[t], round(start_of[t], 6), round(rx_of[t], 6), delivered_of[t],
                         in_range_of[t]] for t in np.flatnonzero(~out.overflow).tolist()],
        }

    def _extra_receptions(self, txs: list[tuple[int, Any]], extras: dict[int, list], decoded: np.ndarray,
                          rx_s: np.ndarray) -> tuple[list[int], list[Reception]]:
        """The transmissions of the frames beyond each sender's own, each relayed with
        the fate of a decoded transmission of the sender's own (its twin: who decoded
        it, when): the one of the same object, else the sender's first one; nothing is
        relayed from a sender none of whose own transmissions was decoded. Returns the
        twin of each (an index into ``txs``) and the receptions."""
        twin_of: dict[tuple[int, int], int] = {}
        first: dict[int, int] = {}
        for t, (vid, tx) in enumerate(txs):
            if decoded[t]:
                twin_of.setdefault((vid, tx.object_id), t)
                first.setdefault(vid, t)
        twins, out = [], []
        for vid in sorted(extras):
            for msg, _ in extras[vid]:
                for tx in msg.transmissions:
                    t = twin_of.get((vid, tx.object_id), first.get(vid))
                    if t is not None:
                        twins.append(t)
                        out.append(Reception(vid, tx.object_id, float(rx_s[t]), tx.payload))
        return twins, out

    # ------------------------------------------------------------------ several domains

    def _play_domains(self, tick: Tick, t_open: float, live: np.ndarray, absent_ctrl: list[int],
                      t_work: float) -> None:
        """One interval of a map with several scheduler domains (docs/domains.md): each
        radio channel is its own medium, shared by the domains on it. A vehicle hears a
        channel only if it takes part in a domain on it (it sent its control message
        there); collisions happen only within a channel, across its domains too; every
        domain gets its own bundles (its members as receivers) and statistics. A vehicle
        in two domains has a radio for each (paper 4.1)."""
        k, profile, run = tick.tick, self.cfg.profile, self.cfg.run_id
        live_set = set(live.tolist())
        ctrl = {v: f for v, f in self._dom_got.items() if v in live_set}
        for vid, frames in ctrl.items():
            msg = frames[min(frames)][0]
            self._last_xy[vid] = (msg.pose.x_m, msg.pose.y_m)
        d = loss.distances(self._positions(live))
        reach = loss.within_cutoff(d, profile.prr)
        p_ctrl = loss.probabilities_at(d, profile.prr, self.cfg.ctrl_loss)
        p_data = p_ctrl if self.cfg.data_loss == self.cfg.ctrl_loss else \
            loss.probabilities_at(d, profile.prr, self.cfg.data_loss)
        with self._cv:  # before any bundle goes out: a vehicle's data frames then wait for all of its domains
            self._dom_want["data"][k] = {v: set(f) for v, f in ctrl.items()}
        channel_of = {dom: f[2] for frames in ctrl.values() for dom, f in frames.items()}
        members = {dom: np.array(sorted(v for v, f in ctrl.items() if dom in f), dtype=np.int64) for dom in channel_of}
        stats: dict[str, Any] = {"domains": {}}
        for ch in sorted(set(channel_of.values())):
            doms = sorted(dom for dom, c in channel_of.items() if c == ch)
            slots = [(dom, int(v)) for dom in doms for v in members[dom]]
            sizes = np.array([_ctrl_onair(ctrl[v][dom][0]) for dom, v in slots], dtype=np.int64)
            s_idx = np.searchsorted(live, np.array([v for _, v in slots], dtype=np.int64))
            out = medium.play_control(live, s_idx, sizes, p_ctrl, reach, capacity_bytes=profile.ctrl_capacity_bytes,
                                      seed=self.cfg.seed, tick=k)
            for dom in doms:
                cols = np.array([i for i, (dd, _) in enumerate(slots) if dd == dom], dtype=np.int64)
                rows = np.searchsorted(live, members[dom])
                heard = np.ascontiguousarray(out.heard[cols][:, rows].T)
                frames = [ctrl[v][dom][1] for v in members[dom].tolist()]
                self._bundle(keys.net_ctrl_rx(run, ch, dom)).put(
                    k, tick.t_sim_s, encode(CtrlBundle(k, tick.t_sim_s, members[dom], members[dom], heard, frames)))
                stats["domains"][str(dom)] = {"channel": ch, "members": members[dom].tolist(), "ctrl": {
                    "senders": len(cols), "offered_bytes": int(sizes[cols].sum()),
                    "overflow_msgs": int(out.overflow[cols].sum()), "delivered_pairs": int(heard.sum())}}
        phases.mark("proxy.ctrl_bundle_sent", k)
        ctrl_work_s = time.perf_counter() - t_work
        data = self._collect("data", k, set(ctrl), self._deadline(t_open, self.cfg.data_deadline_s))
        t_work = time.perf_counter() - ctrl_work_s
        data = self._only_live(data, live)
        absent_data = self._account(set(ctrl), set(data))
        sent = {v: f for v, f in self._dom_got.items() if v in live_set}
        for ch in sorted(set(channel_of.values())):
            self._play_channel_data(tick, live, p_data, reach, ch, sorted(d for d, c in channel_of.items() if c == ch),
                                    members, sent, stats["domains"])
        stats["ctrl"] = {"senders": len(ctrl), "absent": absent_ctrl}
        stats["data"] = {"absent": absent_data,
                         **{key: sum(s["data"][key] for s in stats["domains"].values())
                            for key in ("transmissions", "offered_bytes", "collided_tx", "delivered_pairs",
                                        "delivered_bytes")},
                         "objects": [o for s in stats["domains"].values() for o in s["data"].pop("objects")]}
        self._publish_stats(tick, stats, t_work)
        self._done_tick = k

    def _play_channel_data(self, tick: Tick, live: np.ndarray, p: np.ndarray, reach: np.ndarray, ch: int,
                           doms: list[int], members: dict[int, np.ndarray], sent: dict[int, dict[int, tuple]],
                           stats: dict[str, Any]) -> None:
        """The data channel ``ch``: every transmission of its domains on one medium,
        heard by the vehicles tuned to it; each domain's receptions to its members."""
        k, profile, run = tick.tick, self.cfg.profile, self.cfg.run_id
        txs: list[tuple[int, int, Any]] = []
        for dom in doms:
            for vid in sorted(sent):
                if dom in sent[vid]:
                    for t in sent[vid][dom][0].transmissions:
                        if math.isfinite(t.start_s) and t.start_s >= 0.0:
                            txs.append((dom, vid, t))
                        else:
                            self.counters.invalid_tx += 1
        sender = np.searchsorted(live, np.array([v for _, v, _ in txs], dtype=np.int64))
        item = np.array([t.object_id for _, _, t in txs], dtype=np.int64)
        size = np.array([len(t.payload) for _, _, t in txs], dtype=np.int64)
        start = np.array([t.start_s for _, _, t in txs], dtype=np.float64)
        out = medium.play_data(live, sender, item, start, size, p, reach, bandwidth_bps=profile.bandwidth_bps,
                               interval_s=profile.decision_interval_s, seed=self.cfg.seed, tick=k)
        tuned = np.isin(live, np.concatenate([members[dom] for dom in doms]))
        delivered = out.delivered & tuned[None, :]
        rx_s = out.end_ns / medium.NS
        dom_of = np.array([dom for dom, _, _ in txs], dtype=np.int64)
        sender_vid = live[sender] if len(txs) else sender
        for dom in doms:
            rows = np.searchsorted(live, members[dom])
            mine = np.flatnonzero(dom_of == dom)
            decoded = delivered[mine][:, rows]
            order = np.lexsort((item[mine], sender_vid[mine], out.end_ns[mine]))
            order = order[decoded[order].any(axis=1)]
            receptions = [_reception(int(sender_vid[mine[t]]), int(item[mine[t]]), float(rx_s[mine[t]]),
                                     txs[mine[t]][2].payload) for t in order.tolist()]
            bundle = DataBundle(k, tick.t_sim_s, members[dom], np.ascontiguousarray(decoded[order].T), receptions)
            self._bundle(keys.net_data_rx(run, ch, dom)).put(k, tick.t_sim_s, encode(bundle))
            n_delivered = delivered[mine].sum(axis=1)
            stats[str(dom)]["data"] = {
                "transmissions": len(mine), "offered_bytes": int(size[mine].sum()),
                "overflow_tx": int(out.overflow[mine].sum()),
                "collided_tx": int((out.collided[mine].sum(axis=1) > 0).sum()),
                "delivered_pairs": int(n_delivered.sum()), "delivered_bytes": int((n_delivered * size[mine]).sum()),
                "channel_utilization": round(out.busy_ns / (profile.decision_interval_s * medium.NS), 4),
                "objects": [[int(sender_vid[t]), int(item[t]), round(float(out.start_ns[t] / medium.NS), 6),
                             round(float(rx_s[t]), 6), int(n_delivered[i]), int(out.in_range[t].sum())]
                            for i, t in enumerate(mine.tolist()) if not out.overflow[t]]}
        phases.mark("proxy.data_bundle_sent", k)

    def _bundle(self, key: str) -> ShmPublisher:
        """The bundle publisher of ``key``, declared at its first bundle (a domain's keys)."""
        pub = self._bundles.get(key)
        if pub is None:
            pub = self._bundles[key] = self._pubs[key] = ShmPublisher(self.session, key, self.cfg.shm_dir)
        return pub

    # ------------------------------------------------------------------ EMP

    def _play_emp(self, tick: Tick, t_open: float) -> None:
        k, profile, run = tick.tick, self.cfg.profile, self.cfg.run_id
        live, expected = self._live(tick)
        ups = self._collect("emp", k, expected, self._deadline(t_open, self.cfg.data_deadline_s))
        t_work = time.perf_counter()
        ups = self._only_live(ups, live)
        absent = self._account(expected, set(ups))
        for vid, (msg, _) in ups.items():
            self._last_xy[vid] = (msg.pose.x_m, msg.pose.y_m)
        xy = self._positions(live)
        d_relay = np.hypot(xy[:, 0] - self.cfg.relay_xy[0], xy[:, 1] - self.cfg.relay_xy[1])
        d_relay = np.where(np.isnan(d_relay), np.inf, d_relay)
        p = profile.prr.prr(d_relay) * (1.0 - self.cfg.data_loss)
        reach = d_relay <= profile.prr.max_range_m
        senders = np.array(sorted(ups), dtype=np.int64)
        s_idx = np.searchsorted(live, senders)
        msgs = [ups[v][0] for v in senders.tolist()]
        size = emp.segment_onair_bytes(np.array([len(m.points_world) for m in msgs]), self.cfg.emp_bytes_per_point)
        out = emp.play_relay(live, s_idx, size, p[s_idx], p, reach, bandwidth_bps=profile.bandwidth_bps,
                             interval_s=profile.decision_interval_s, seed=self.cfg.seed, tick=k)
        rx_s = out.fwd_end_ns / medium.NS
        site_vids = senders
        site_xy = xy[s_idx] if len(s_idx) else np.zeros((0, 2))
        order = np.argsort(out.fwd_end_ns, kind="stable")
        for c, receiver in enumerate(live.tolist()):
            got = order[out.delivered[order, c]]
            segs = [EmpSegment(int(senders[u]), msgs[u].pose, float(rx_s[u]), msgs[u].points_world) for u in got.tolist()]
            self._pub(keys.net_emp_down(run, receiver)).put(
                encode(EmpBundle(k, tick.t_sim_s, receiver, segs, site_vids, site_xy)))
        size_col = size[:, None]
        stats = {"emp": {
            "uploads": len(senders),
            "offered_bytes": int(size.sum()),
            "overflow_tx": int(out.overflow.sum()),
            "overflow_bytes": int(size[out.overflow].sum()),
            "lost_uplink": int((~out.overflow & ~out.uploaded).sum()),
            "delivered_pairs": int(out.delivered.sum()),
            "delivered_bytes": int((out.delivered * size_col).sum()),
            "in_range_bytes": int((out.in_range * size_col).sum()),
            "utilization": round(out.busy_ns / (profile.decision_interval_s * medium.NS), 4),
            "absent": absent,
        }}
        self._publish_stats(tick, stats, t_work)
        self._done_tick = k


def encode_stats(tick: int, t_sim_s: float, stats: dict[str, Any]) -> bytes:
    """``encode(ChannelStats(tick, t_sim_s, stats))``, the same bytes in one msgpack call.

    The codec puts a free-form value on the wire as msgpack packs it, after walking it
    value by value (``codec._to_wire``: a list or tuple as a list, a numpy scalar as its
    Python number, an array or a record in its wire form); at 40 vehicles the data
    channel's ``objects`` are ~800 numbers, and that walk was ~0.6 ms an interval.
    msgpack packs the proxy's statistics (ints, floats, strings, lists and dicts of
    them) alike; a value it would pack otherwise it refuses (``TypeError``: a numpy
    integer, an array, a record; a numpy float64 is a float, packed as its value), and
    the codec then encodes the whole. The envelope is the codec's, with an empty dict
    last (its one byte, 0x80, replaced by the packed statistics)."""
    head = encode(ChannelStats(tick, t_sim_s, {}))
    try:
        body = msgpack.packb(stats, use_bin_type=True)
    except TypeError:
        return encode(ChannelStats(tick, t_sim_s, stats))
    return head[:-1] + body


_reception = slots_constructor(Reception)  # Reception(...) without its frozen __init__'s setattr per field


def read_frame(raw: bytes, expected: type) -> Any:
    """What the medium reads of a frame: a plain ``expected``, or the body of a ``Signed``
    one, unverified (the medium needs the tick, the sender's position and the sizes;
    receivers verify). Raises ``MalformedMessage`` for anything else."""
    msg = decode(raw)
    if isinstance(msg, Signed):
        return decode(msg.body, expected)
    if not isinstance(msg, expected):
        raise MalformedMessage(f"expected {expected.__name__} or Signed, got {type(msg).__name__}")
    return msg


def _ctrl_onair(msg: ControlMsg) -> int:
    om = msg.objects
    return medium.control_onair_bytes(len(om.object_id), len(om.receivers), len(msg.trajectory), len(msg.heard))
