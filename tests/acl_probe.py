"""Probes of a locked-down Zenoh network, run as processes inside network namespaces by
tests/test_multihost.py (``ip netns exec NS python -m tests.acl_probe MODE ...``).

``join ENDPOINT [CONFIG]``: open one client session (with the credentials in CONFIG, or
none) and print ``joined`` or ``refused: <why>``.

``listen ENDPOINT CONFIG KEYEXPR LAST``: subscribe, print ``subscribed``, then print
``got <key>`` for every sample until one arrives on LAST; then exit.

``put ENDPOINT CONFIG OTHER OWN``: wait until a subscriber matches OWN, put on OTHER
(a key the credentials do not allow), then on OWN (same session and link: if OTHER had
passed the router it would arrive first), print ``put``.
"""

from __future__ import annotations

import sys
import threading
import time

import zenoh

from protocol.session import ZenohArgs, open_session, session_scope

WAIT_S = 120.0  # safety net only


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
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
