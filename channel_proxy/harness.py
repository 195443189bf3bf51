"""Driving a running proxy from one Zenoh session: the world's ticks and any number of
vehicles' transmissions, and everything the proxy delivers, collected by tick.

For tests and the channel bench, which stand in for the world and the agents; the
proxy cannot tell them from real ones.
"""

from __future__ import annotations

import threading
import time
from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import zenoh

from protocol import keys
from protocol.codec import decode, encode
from protocol.messages import ChannelStats, CtrlBundle, DataBundle, EmpBundle, Reception, Tick
from protocol.session import big_publisher, reliable_publisher


@dataclass(frozen=True)
class Heard:
    """One receiver's row of a ``CtrlBundle``: the raw control messages it heard."""

    tick: int
    receiver: int
    messages: list[bytes]


@dataclass(frozen=True)
class Decoded:
    """One receiver's row of a ``DataBundle``: what it decoded, by reception time."""

    tick: int
    receiver: int
    receptions: list[Reception]


class Harness:
    """Publishes ticks and vehicles' messages; records bundles and stats by tick, the
    bundles also split per receiver (``ctrl[k][vid]``, ``data[k][vid]``)."""

    def __init__(self, session: zenoh.Session, run_id: str, vids: Iterable[int], *, emp: bool = False) -> None:
        self.session = session
        self.run = run_id
        self.vids = sorted(int(v) for v in vids)
        self._cv = threading.Condition()
        self.ctrl: dict[int, dict[int, Heard]] = defaultdict(dict)
        self.ctrl_raw: dict[int, bytes] = {}  # the bundle as published, by tick
        self.data: dict[int, dict[int, Decoded]] = defaultdict(dict)
        self.data_raw: dict[int, bytes] = {}
        self.emp: dict[int, dict[int, EmpBundle]] = defaultdict(dict)
        self.stats: dict[int, dict[str, Any]] = {}
        s, run = session, run_id
        self._subs = [s.declare_subscriber(keys.net_stats(run), self._on(ChannelStats, self._stats))]
        if emp:
            self._subs.append(s.declare_subscriber(keys.net_emp_down(run, "*"), self._on(EmpBundle, self._emp)))
        else:
            self._subs += [
                s.declare_subscriber(keys.net_ctrl_rx(run), self._on(CtrlBundle, self._ctrl)),
                s.declare_subscriber(keys.net_data_rx(run), self._on(DataBundle, self._data)),
            ]
        self._tick_pub = reliable_publisher(s, keys.world_tick(run))  # as the world's: a dropped tick stalls the proxy
        self._pubs: dict[str, zenoh.Publisher] = {}

    def _on(self, cls: type, store):
        def handler(sample: zenoh.Sample) -> None:
            raw = sample.payload.to_bytes()
            msg = decode(raw, cls)
            with self._cv:
                store(msg, raw)
                self._cv.notify_all()
        return handler

    def _stats(self, m: ChannelStats, raw: bytes) -> None:
        self.stats[m.tick] = m.stats

    def _ctrl(self, m: CtrlBundle, raw: bytes) -> None:
        self.ctrl_raw[m.tick] = raw  # before the bundle a waiter looks for
        self.ctrl[m.tick] = {v: Heard(m.tick, v, m.heard_by(v)) for v in m.receivers.tolist()}

    def _data(self, m: DataBundle, raw: bytes) -> None:
        self.data_raw[m.tick] = raw  # before the bundle a waiter looks for
        self.data[m.tick] = {v: Decoded(m.tick, v, m.received_by(v)) for v in m.receivers.tolist()}

    def _emp(self, m: EmpBundle, raw: bytes) -> None:
        self.emp[m.tick][m.receiver] = m

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
        self._tick_pub.undeclare()
        for pub in self._pubs.values():
            pub.undeclare()

    # ------------------------------------------------------------------ sending

    def tick(self, k: int, live: Iterable[int] | None = None, t_sim_s: float | None = None) -> None:
        live = self.vids if live is None else sorted(live)
        self._tick_pub.put(encode(Tick(k, k * 0.1 if t_sim_s is None else t_sim_s, list(live), [])))

    def put(self, key: str, payload: bytes) -> None:
        pub = self._pubs.get(key)
        if pub is None:
            pub = self._pubs[key] = big_publisher(self.session, key)
        pub.put(payload)

    def send_ctrl(self, msg: Any) -> None:
        self.put(keys.net_ctrl_tx(self.run, msg.vid), encode(msg))

    def send_data(self, msg: Any) -> None:
        self.put(keys.net_data_tx(self.run, msg.vid), encode(msg))

    def send_emp(self, msg: Any) -> None:
        self.put(keys.net_emp_up(self.run, msg.vid), encode(msg))

    # ------------------------------------------------------------------ waiting

    def wait_proxy(self, timeout_s: float = 30.0) -> None:
        """Block until the proxy's liveliness token is up (it declares it last, once subscribed)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            replies = list(self.session.liveliness().get(keys.proxy_alive(self.run), timeout=1.0))
            if any(r.ok is not None for r in replies):
                return
            time.sleep(0.05)
        raise TimeoutError("no channel proxy came up")

    def _wait(self, done, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        with self._cv:
            while not done():
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError("the proxy did not deliver in time")
                self._cv.wait(left)

    def wait_ctrl(self, k: int, receivers: Iterable[int] | None = None, timeout_s: float = 20.0) -> dict[int, Heard]:
        want = set(self.vids if receivers is None else receivers)
        self._wait(lambda: want <= set(self.ctrl.get(k, {})), timeout_s)
        with self._cv:
            return dict(self.ctrl[k])

    def wait_data(self, k: int, receivers: Iterable[int] | None = None, timeout_s: float = 20.0) -> dict[int, Decoded]:
        want = set(self.vids if receivers is None else receivers)
        self._wait(lambda: want <= set(self.data.get(k, {})), timeout_s)
        with self._cv:
            return dict(self.data[k])

    def wait_emp(self, k: int, receivers: Iterable[int] | None = None, timeout_s: float = 20.0) -> dict[int, EmpBundle]:
        want = set(self.vids if receivers is None else receivers)
        self._wait(lambda: want <= set(self.emp.get(k, {})), timeout_s)
        with self._cv:
            return dict(self.emp[k])

    def wait_stats(self, k: int, timeout_s: float = 20.0) -> dict[str, Any]:
        self._wait(lambda: k in self.stats, timeout_s)
        with self._cv:
            return self.stats[k]
