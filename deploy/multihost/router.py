"""One host's Zenoh router in a multi-host run (``autocast deploy``).

``python -m deploy.multihost.router --listen tcp/10.0.0.2:7447 --connect tcp/10.0.0.1:7447``

Every process of the run on this host is a client of this router; the routers of the
run's hosts connect to each other with explicit endpoints (no multicast, no gossip)
and route between hosts. A router whose peer is not up yet keeps retrying, so hosts
may start in any order. The admin space is on so the launcher can check, by querying
``@/*/router``, that every router is linked to every other before the run starts.
Runs until SIGINT or SIGTERM.
"""

from __future__ import annotations

import argparse
import logging
import signal
import threading

import zenoh

from protocol.session import ZenohArgs, make_config

log = logging.getLogger("deploy.multihost.router")

# The same patience as the single-host hub (deploy.launch.run.HUB_CONFIG_JSON5): a DROP message
# waits up to 200 ms for a congested egress queue before it is dropped.
WAIT_BEFORE_DROP_US = 200_000
LINK_LOG_PERIOD_S = 2.0


def router_config(listen: list[str], connect: list[str], config_file: str | None = None) -> zenoh.Config:
    """``config_file``: the run's credentials and ACL for this router (deploy.launch.credentials)."""
    conf = make_config(ZenohArgs(tuple(listen), tuple(connect), config_file))
    conf.insert_json5("adminspace/enabled", "true")
    conf.insert_json5("transport/link/tx/queue/congestion_control/drop/wait_before_drop", str(WAIT_BEFORE_DROP_US))
    conf.insert_json5("connect/exit_on_failure", "false")  # a peer router that is not up yet is retried
    return conf


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m deploy.multihost.router", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--listen", action="append", required=True, metavar="ENDPOINT",
                    help="where this host's processes (and the other routers) reach this router")
    ap.add_argument("--connect", action="append", default=[], metavar="ENDPOINT", help="another host's router")
    ap.add_argument("--name", default="", help="the host's name, for the log")
    ap.add_argument("--zenoh-config", default=None, metavar="FILE",
                    help="the router's password, the run's password dictionary and ACL (autocast deploy's lock-down)")
    ap.add_argument("--log-level", default="INFO")
    args = ap.parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format=f"%(asctime)s router {args.name} %(levelname)s %(message)s")
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    session = zenoh.open(router_config(args.listen, args.connect, args.zenoh_config))
    try:
        log.info("router %s listening on %s, connecting to %s%s", session.zid(), ", ".join(args.listen),
                 ", ".join(args.connect) or "nobody", " (locked down)" if args.zenoh_config else "")
        linked: set[str] = set()
        while not stop.wait(LINK_LOG_PERIOD_S):
            now = {str(z) for z in session.info.routers_zid()}
            if now != linked:
                log.info("linked to %d other router(s): %s", len(now), " ".join(sorted(now)) or "-")
                linked = now
    finally:
        session.close()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
