"""The agent's side of the V2V channel: it talks only to the channel proxy.

Per interval: publish the control message, wait for the ``CtrlBundle`` (one for all
receivers: this vehicle takes the messages it heard), publish the ``DataTx`` (its
scheduled objects, possibly none), wait for the ``DataBundle`` (likewise, what it
decoded). A bundle that does not come within the timeout, or that does not list this
vehicle as a receiver, counts as hearing nothing, so a dead proxy degrades sharing,
never the run.
In the EMP scheme the same two-step shape carries the Voronoi-segment upload to the
edge relay and the relay's forwarded segments.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import zenoh

from protocol import keys, phases, shm
from protocol.codec import MalformedMessage, encode
from protocol.messages import ControlMsg, CtrlBundle, DataBundle, DataTx, EmpBundle, EmpUpload, Pose, Reception, \
    Transmission
from protocol.session import DropCounter, big_publisher, reliable_publisher, typed_handler
from vehicle_agent.agreement import HeardControl

log = logging.getLogger(__name__)


class _Mailbox:
    """The latest bundle per tick, with a wait for a given tick."""

    def __init__(self) -> None:
        self._cv = threading.Condition()
        self._by_tick: dict[int, object] = {}

    def put(self, tick: int, item: object) -> None:
        with self._cv:
            self._by_tick[tick] = item
            for old in [t for t in self._by_tick if t < tick - 5]:
                del self._by_tick[old]
            self._cv.notify_all()

    def take(self, tick: int, timeout_s: float, stop: threading.Event) -> object | None:
        """The bundle of ``tick``; None after ``timeout_s`` or once ``stop`` is set."""
        deadline = time.monotonic() + timeout_s
        with self._cv:
            while tick not in self._by_tick and not stop.is_set():
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._cv.wait(min(left, 0.1))  # a signal handler cannot notify: poll the stop event
            return self._by_tick.pop(tick, None)


class V2VLink:
    def __init__(self, session: zenoh.Session, run: str, vid: int, drops: DropCounter, stop: threading.Event,
                 timeout_s: float = 10.0, receives_data: bool = True, shm_dir: str | None = None,
                 missed: DropCounter | None = None, channels: Sequence[int] = (0,)) -> None:
        """``shm_dir``: the bundles come through the run's shared memory (``protocol.shm``;
        ``missed`` counts the notices whose bundle was no longer there).

        ``channels[d]``: the radio channel of scheduler domain d (the map's domains,
        docs/domains.md). The link listens to every domain's bundles, each of which
        lists as receivers only the vehicles that took part in that domain; domain 0 on
        channel 0 has the run's plain keys.

        ``receives_data`` False: a vehicle that uses nothing it could decode (one that
        fuses nothing, ``__main__.fuses``) does not subscribe to the data bundle, which
        its Zenoh threads would receive, its callback decode and the hub send every
        interval. What the medium delivers does not change: the proxy plays the channel
        alone."""
        self.vid, self.stop, self.timeout_s = vid, stop, timeout_s
        self.drops = drops
        self.receives_data = receives_data
        domains = list(enumerate(channels))
        self._ctrl = {d: _Mailbox() for d, _ in domains}
        self._data = {d: _Mailbox() for d, _ in domains}
        self._emp = _Mailbox()
        self.missed_bundles = 0
        self.wait_s = 0.0  # time spent waiting for bundles (the channel's phases), reset by the caller
        self._subs = [shm.subscribe(session, keys.net_ctrl_rx(run, c, d), shm_dir, CtrlBundle, _into(self._ctrl[d]),
                                    drops, missed) for d, c in domains]
        self._subs.append(session.declare_subscriber(keys.net_emp_down(run, vid),
                                                     typed_handler(EmpBundle, _into(self._emp), drops)))
        if receives_data:
            self._subs += [shm.subscribe(session, keys.net_data_rx(run, c, d), shm_dir, DataBundle,
                                         _into(self._data[d]), drops, missed) for d, c in domains]
        self._ctrl_pubs = {d: reliable_publisher(session, keys.net_ctrl_tx(run, vid, c, d)) for d, c in domains}
        self._data_pubs = {d: big_publisher(session, keys.net_data_tx(run, vid, c, d)) for d, c in domains}
        self._emp_pub = big_publisher(session, keys.net_emp_up(run, vid))

    def close(self) -> None:
        for entity in (*self._subs, *self._ctrl_pubs.values(), *self._data_pubs.values(), self._emp_pub):
            entity.undeclare()

    def _take(self, box: _Mailbox, tick: int):
        t0 = time.perf_counter()
        try:
            return box.take(tick, self.timeout_s, self.stop)
        finally:
            self.wait_s += time.perf_counter() - t0

    def exchange_control(self, msg: ControlMsg) -> list[HeardControl]:
        """Broadcast our control message; return the ones we heard this interval."""
        return self.exchange_controls({0: msg})[0]

    def exchange_controls(self, msgs: Mapping[int, ControlMsg]) -> dict[int, list[HeardControl]]:
        """Broadcast our control message in each domain (``msgs[d]``), then return, per
        domain, the ones we heard there this interval."""
        tick = next(iter(msgs.values())).tick
        bundles = self.exchange_control_raws({d: encode(m) for d, m in msgs.items()}, tick)
        out = {}
        for d, bundle in bundles.items():
            heard = heard_in(bundle, self.vid, self.drops)
            if heard is None:
                self.missed_bundles += 1
            out[d] = heard or []
        return out

    def exchange_control_raw(self, raw: bytes, tick: int) -> CtrlBundle | None:
        """Broadcast our encoded (or sealed) control message of ``tick``; return the
        interval's bundle (None if none came: the caller counts it missed)."""
        return self.exchange_control_raws({0: raw}, tick)[0]

    def exchange_control_raws(self, raws: Mapping[int, bytes], tick: int) -> dict[int, CtrlBundle | None]:
        """``exchange_control_raw`` in each domain of ``raws``: every message is sent
        before any bundle is waited for (the proxy closes the phase once a vehicle has
        sent in each of its domains)."""
        phases.mark("agent.ctrl_sent", tick)
        for d, raw in raws.items():
            self._ctrl_pubs[d].put(raw)
        bundles = {d: self._take(self._ctrl[d], tick) for d in raws}
        if any(b is not None for b in bundles.values()):
            phases.mark("agent.ctrl_bundle", tick)
        return bundles

    def exchange_data(self, tick: int, t_sim_s: float, transmissions: list[Transmission],
                      receive: bool = True) -> list[Reception]:
        """Transmit our scheduled objects; return what we decoded this interval, or, with
        ``receive`` False (the vehicle fuses nothing), nothing at once, without waiting
        for the data phase to close. ``ValueError`` if the link does not take the bundle
        (``receives_data``) and ``receive`` asks for it."""
        return self.exchange_datas(tick, t_sim_s, {0: transmissions}, receive)

    def exchange_datas(self, tick: int, t_sim_s: float, transmissions: Mapping[int, list[Transmission]],
                       receive: bool = True) -> list[Reception]:
        """``exchange_data`` in each domain of ``transmissions``: what we decoded in all
        of them, an object heard in two domains once (the first domain's)."""
        if receive and not self.receives_data:
            raise ValueError("this link does not take the data bundle (receives_data=False)")
        phases.mark("agent.data_sent", tick)
        for d, txs in transmissions.items():
            self._data_pubs[d].put(encode(DataTx(tick, t_sim_s, self.vid, txs)))
        if not receive:
            return []
        out: list[Reception] = []
        seen: set[tuple[int, int]] = set()
        for d in transmissions:
            bundle = self._take(self._data[d], tick)
            if bundle is not None:
                phases.mark("agent.data_bundle", tick)
            mine = received_in(bundle, self.vid)
            if mine is None:
                self.missed_bundles += 1
                continue
            if len(transmissions) == 1:
                return mine
            for r in mine:
                if (r.sender, r.object_id) not in seen:
                    seen.add((r.sender, r.object_id))
                    out.append(r)
        return out

    def exchange_emp(self, tick: int, t_sim_s: float, pose: Pose, segment_world: np.ndarray) -> EmpBundle | None:
        """Upload our Voronoi segment to the edge relay; return what it forwarded to us."""
        self._emp_pub.put(encode(EmpUpload(tick, t_sim_s, self.vid, pose, segment_world.astype(np.float32))))
        bundle = self._take(self._emp, tick)
        if bundle is None:
            self.missed_bundles += 1
        return bundle


def heard_in(bundle: CtrlBundle | None, vid: int, drops: DropCounter) -> list[HeardControl] | None:
    """The control messages ``vid`` heard in ``bundle``, read as far as every vehicle
    needs them (``HeardControl``: the object map is opened by the sender's group only; a
    message whose envelope, ballot or motion is malformed is counted in ``drops`` and
    left out); None if there is no bundle or ``vid`` is not one of its receivers."""
    mine = bundle.heard_by(vid) if bundle is not None else None
    if mine is None:
        return None
    heard = []
    for raw in mine:
        try:
            heard.append(HeardControl.read(raw))
        except MalformedMessage as err:
            drops.add("ctrl bundle item", err)
    return heard


def received_in(bundle: DataBundle | None, vid: int) -> list[Reception] | None:
    """What ``vid`` decoded in ``bundle``; None if there is no bundle or ``vid`` is not
    one of its receivers."""
    return bundle.received_by(vid) if bundle is not None else None


def _into(box: _Mailbox) -> Callable[[str, Any], None]:
    return lambda key, msg: box.put(msg.tick, msg)
