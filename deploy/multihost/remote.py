"""What ``autocast deploy`` runs on a host, through that host's command prefix.

``python -m deploy.multihost.remote exec MODULE ARGS...``: makes this process lead its own
process group, prints ``autocast-remote: pid N on HOST`` as its first line, then
becomes ``python -m MODULE ARGS...`` (same pid). The launcher reads that line from
the log it collects (the prefix forwards stdout) and stops the process with
``kill -s INT -- -N`` through the same prefix: a remote process is stopped where it
runs, whatever the prefix is (ssh, ip netns exec, a local shell).

``python -m deploy.multihost.remote warm SCENARIO_JSON``: compiles or loads the numba caches
for that scenario on this host, so its agents start from the cache.
"""

from __future__ import annotations

import json
import os
import socket
import sys

PID_LINE = "autocast-remote: pid"


def exec_module(argv: list[str]) -> None:
    if os.getpgid(0) != os.getpid():
        os.setsid()  # not a group leader: lead a new session, so the group is only ours
    print(f"{PID_LINE} {os.getpid()} on {socket.gethostname()}", flush=True)
    os.execv(sys.executable, [sys.executable, "-m", *argv])


def warm(params_json: str) -> int:
    import logging

    from deploy.launch.warmup import warm_numba_caches
    from world_server.scenarios import params_from_dict

    logging.basicConfig(level="INFO", format="%(asctime)s warm %(message)s")
    warm_numba_caches(params_from_dict(json.loads(params_json)))
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) >= 2 and argv[0] == "exec":
        exec_module(argv[1:])  # does not return
    if len(argv) == 2 and argv[0] == "warm":
        return warm(argv[1])
    print(__doc__, file=sys.stderr)
    return 2


if __name__ == "__main__":
    raise SystemExit(main())
