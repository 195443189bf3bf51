"""Probes of a locked-down Zenoh network, run as processes inside network namespaces by
tests/test_multihost.py (``ip netns exec NS python -m tests.acl_probe MODE ...``).

``join ENDPOINT [CONFIG]``: open one client session (with the credentials in CONFIG, or
none) and print ``joined`` or ``refused: <why>``.

``listen ENDPOINT CONFIG KEYEXPR LAST``: subscribe, print ``subscribed``, then print
``got <key>`` for every sample until one arrives on LAST; then exit.

``put ENDPOINT CONFIG OTHER OWN``: wait until a subscriber matches OWN, put on OTHER
(a key the credentials do not allow), then on OWN (same session and link: if OTHER had
passed the router it would arrive first), print ``put``.

``participant ENDPOINT CONFIG RUN NAME VID ...``: a participant the world waits for
(``--wait-for NAME``): declare its token ``ac/RUN/alive/p/NAME``, then at the run's first
tick put a ``Command`` (steering ``FORGED_STEER_RAD``) and a control message in each
VID's name on each of its keys, and a report and a rejected count; print ``forged N``
and exit at the outcome.
"""

from __future__ import annotations

import sys
import threading
import time

import zenoh

from protocol import keys
from protocol.codec import MalformedMessage, decode, encode
from protocol.messages import Command, Tick
from protocol.session import ZenohArgs, open_session, session_scope

WAIT_S = 120.0  # safety net only
FORGED_STEER_RAD = 0.0123  # no honest command steers exactly so at tick 0


def main(argv: list[str]) -> int:
    mode, endpoint, *rest = argv
    config = rest[0] if rest and rest[0] != "-" else None
    z = ZenohArgs(connect=(endpoint,), config_file=config)
    if mode == "join":
        try:
            session = open_session(z, wait_s=0.0)  # one attempt: a refusal is an answer, not a timeout
        except ConnectionError as exc:
            print(f"refused: {exc}", flush=True)
            return 0
        session.close()
        print("joined", flush=True)
        return 0
    with session_scope(z, wait_s=WAIT_S) as session:
        if mode == "listen":
            expr, last = rest[1], rest[2]
            done = threading.Event()

            def on(sample: zenoh.Sample) -> None:
                print(f"got {sample.key_expr}", flush=True)
                if str(sample.key_expr) == last:
                    done.set()

            sub = session.declare_subscriber(expr, on)
            print("subscribed", flush=True)
            ok = done.wait(WAIT_S)
            sub.undeclare()
            return 0 if ok else 1
        if mode == "put":
            other, own = rest[1], rest[2]
            pub = session.declare_publisher(own, congestion_control=zenoh.CongestionControl.BLOCK)
            deadline = time.monotonic() + WAIT_S
            while not pub.matching_status.matching:  # the listener's subscription reached our router
                if time.monotonic() > deadline:
                    return 1
                time.sleep(0.02)
            session.put(other, b"forged", congestion_control=zenoh.CongestionControl.BLOCK)
            pub.put(b"own")
            pub.undeclare()
            print("put", flush=True)
            return 0
        if mode == "participant":
            return _participant(session, *rest[1:])
    return 2


def _participant(session: zenoh.Session, run: str, name: str, *vids: str) -> int:
    """Forge on every vehicle's keys at the first tick, from a session whose credentials
    grant its own token only; exit at the outcome."""
    first, done = threading.Event(), threading.Event()
    ticks: list[Tick] = []

    def on_tick(sample: zenoh.Sample) -> None:
        try:
            ticks.append(decode(sample.payload.to_bytes(), Tick))
        except MalformedMessage:
            return
        first.set()

    subs = [session.declare_subscriber(keys.world_tick(run), on_tick),
            session.declare_subscriber(keys.world_outcome(run), lambda _: done.set())]
    token = session.liveliness().declare_token(keys.participant_alive(run, name))
    print("ready", flush=True)
    if not first.wait(WAIT_S):
        return 1
    tick = ticks[0]
    forged = 0
    for vid in map(int, vids):
        cmd = encode(Command(tick.tick, tick.t_sim_s, vid, -1.0, FORGED_STEER_RAD))
        for key in (keys.cmd(run, vid), keys.report(run, vid), keys.rejected(run, vid), keys.net_ctrl_tx(run, vid),
                    keys.net_data_tx(run, vid), keys.alive(run, vid)):
            session.put(key, cmd, congestion_control=zenoh.CongestionControl.BLOCK)
            forged += 1
    print(f"forged {forged}", flush=True)
    ok = done.wait(WAIT_S)
    token.undeclare()
    for sub in subs:
        sub.undeclare()
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
