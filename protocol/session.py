"""Opening a Zenoh session the way every AutoCast process needs it.

Topology. On one host, one process is the hub: it *listens* on a loopback endpoint
and runs in Zenoh ``router`` mode; every other process is a ``client`` that
*connects* to it. Measured here (zenoh 1.10): peers that only connect to a common
peer do not get each other's data (peer-to-peer routing does not relay), and a full
peer mesh at 40 processes costs thousands of sockets; clients of one in-process hub
need no external ``zenohd``. Across hosts, each host's hub also connects to the other
hubs (``--connect``), which is how Zenoh routers federate.

Defaults that hurt and are switched off: multicast scouting and gossip (explicit
endpoints instead), shared memory (a 16 MB pool per sender mapped by every
receiver), and the 500 ms scouting delay on open.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import zenoh

from protocol.codec import MalformedMessage, decode, encode

log = logging.getLogger(__name__)

DEFAULT_HUB = "tcp/127.0.0.1:7447"


@dataclass(frozen=True, slots=True)
class ZenohArgs:
    """Where a process's session listens and connects; empty lists mean the default."""

    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    config_file: str | None = None


def add_zenoh_args(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("zenoh")
    group.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                       help="be the hub: listen on this endpoint (router mode), e.g. tcp/127.0.0.1:7447")
    group.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                       help=f"connect to a hub (client mode unless --listen too); default {DEFAULT_HUB}")
    group.add_argument("--zenoh-config", default=None, metavar="FILE",
                       help="a Zenoh JSON5 config file; --listen/--connect override its endpoints")


def zenoh_args_from(ns: argparse.Namespace) -> ZenohArgs:
    return ZenohArgs(tuple(ns.listen), tuple(ns.connect), ns.zenoh_config)


def zenoh_cli_flags(z: ZenohArgs) -> list[str]:
    """The command-line flags that reproduce ``z`` in a child process."""
    flags: list[str] = []
    for ep in z.listen:
        flags += ["--listen", ep]
    for ep in z.connect:
        flags += ["--connect", ep]
    if z.config_file:
        flags += ["--zenoh-config", z.config_file]
    return flags


def make_config(z: ZenohArgs) -> zenoh.Config:
    conf = zenoh.Config.from_file(z.config_file) if z.config_file else zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    conf.insert_json5("scouting/delay", "0")
    conf.insert_json5("transport/shared_memory/enabled", "false")
    listen = list(z.listen)
    connect = list(z.connect)
    if not listen and not connect and not z.config_file:
        connect = [DEFAULT_HUB]
    if listen:
        conf.insert_json5("mode", json.dumps("router"))
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    elif connect or not z.config_file:
        conf.insert_json5("mode", json.dumps("client"))
        conf.insert_json5("listen/endpoints", "[]")
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(connect))
        conf.insert_json5("connect/timeout_ms", str(CONNECT_ATTEMPT_MS))
    return conf


CONNECT_ATTEMPT_MS = 2000


def open_session(z: ZenohArgs, wait_s: float = 60.0) -> zenoh.Session:
    """Open a session; the caller must close it (``with`` or ``finally``).

    A client whose hub is not up yet (processes start in any order) retries for up to
    ``wait_s`` seconds, then raises ``ConnectionError``.
    """
    conf = make_config(z)
    deadline = time.monotonic() + wait_s
    while True:
        try:
            return zenoh.open(conf)
        except zenoh.ZError as exc:
            if time.monotonic() >= deadline:
                raise ConnectionError(f"no Zenoh hub at {', '.join(z.connect) or 'the configured endpoints'}: "
                                      f"{exc}") from None
            log.info("hub not reachable yet, retrying")
            conf = make_config(z)


@contextlib.contextmanager
def session_scope(z: ZenohArgs, wait_s: float = 60.0) -> Iterator[zenoh.Session]:
    """``with session_scope(z) as session:`` opens, and always closes, a session.

    A close that times out (a peer that is stopped but still connected does not answer
    the graceful close) is logged, not raised: the process's work is done by then.
    """
    session = open_session(z, wait_s)
    try:
        yield session
    finally:
        try:
            session.close()
        except zenoh.ZError as exc:
            log.warning("closing the Zenoh session: %s", exc)


def reliable_publisher(session: zenoh.Session, key: str) -> zenoh.Publisher:
    """A publisher whose messages must arrive (commands, ticks, control messages, scans,
    point clouds): BLOCK. Zenoh's default, DROP, silently discards a message when the
    link's queue is congested, even a small command queued behind a large report."""
    return session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)


big_publisher = reliable_publisher


def put(session: zenoh.Session, key: str, msg: Any) -> None:
    session.put(key, encode(msg), congestion_control=zenoh.CongestionControl.BLOCK)


MALFORMED_LINE = "malformed_dropped"  # the tag of a process's exit line (DropCounter.exit_line)


@dataclass
class DropCounter:
    """Counts payloads that failed to decode, per key, and logs the first of each
    (``tag`` and ``what``: another kind of drop, e.g. ``protocol.shm``'s misses)."""

    counts: dict[str, int] = field(default_factory=dict)
    tag: str = MALFORMED_LINE
    what: str = "malformed payload"
    _lock: threading.Lock = field(default_factory=threading.Lock)

    @property
    def total(self) -> int:
        with self._lock:
            return sum(self.counts.values())

    def by_key(self) -> dict[str, int]:
        with self._lock:
            return dict(sorted(self.counts.items()))

    def exit_line(self, process: str) -> str:
        """What a process prints (stderr, so its log) as it exits:
        ``malformed_dropped {"process": ..., "total": n, "by_key": {key: n}}``; the
        launcher gathers these lines into the outcome record (``processes.manager.exit_records``)."""
        by_key = self.by_key()
        return f"{self.tag} " + json.dumps({"process": process, "total": sum(by_key.values()), "by_key": by_key})

    def add(self, key: str, err: Exception) -> None:
        with self._lock:
            n = self.counts.get(key, 0) + 1
            self.counts[key] = n
        if n == 1 or n % 100 == 0:  # the text, not the exception: a kept record must not hold its traceback's frames
            log.warning("dropped %s #%d on %s: %s", self.what, n, key, str(err))


def typed_handler(expected: type, on_msg: Callable[[str, Any], None], drops: DropCounter,
                  read: Callable[[bytes, str], Any] | None = None) -> Callable[[zenoh.Sample], None]:
    """A subscriber callback that decodes ``expected`` and drops (and counts) the rest.

    ``read(payload, key)`` replaces the plain decode (a signed run opens and verifies the
    envelope): it raises ``ValueError`` for a malformed payload, counted here, or returns
    None for one it refused and counted itself. Any exception in ``on_msg`` is logged,
    never propagated into Zenoh's thread.
    """

    def handler(sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        try:
            payload = sample.payload.to_bytes()
            msg = decode(payload, expected) if read is None else read(payload, key)
        except ValueError as err:  # MalformedMessage is one
            drops.add(key, err)
            return
        if msg is not None:
            deliver(on_msg, key, msg)

    return handler


def deliver(on_msg: Callable[[str, Any], None], key: str, msg: Any) -> None:
    """``on_msg(key, msg)`` in a Zenoh callback: what it raises is logged, never
    propagated into Zenoh's thread."""
    try:
        on_msg(key, msg)
    except Exception:
        log.exception("handler for %s failed", key)


def query_one(session: zenoh.Session, key: str, expected: type, timeout_s: float,
              drops: DropCounter | None = None) -> Any:
    """Ask a queryable for one message: the first reply that decodes as ``expected``;
    the others are dropped (and counted in ``drops``). Replies are not consolidated: a
    stranger's reply on the same key must not replace the real one. ``TimeoutError`` if
    no reply decodes."""
    for reply in session.get(key, timeout=timeout_s, consolidation=zenoh.ConsolidationMode.NONE):
        if reply.ok is not None:
            try:
                return decode(reply.ok.payload.to_bytes(), expected)
            except MalformedMessage as err:
                if drops is not None:
                    drops.add(key, err)
    raise TimeoutError(f"no valid reply on {key} within {timeout_s} s")
