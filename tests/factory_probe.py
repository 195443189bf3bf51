"""A process for tests/test_factory.py to start through the factory.

``python -m factory_probe WHAT ...`` (``tests/`` on the path):
- ``ids``: print its pid, process group, session, parent, argv, cwd, ``PROBE`` and
  command line as one JSON line on stdout, and a line on stderr;
- ``exit N``: exit with code N; ``raise``: die of an uncaught exception;
- ``wait``: print ``waiting`` and block until a signal ends it (SIGINT: KeyboardInterrupt);
- ``zenoh ENDPOINT RUN VID``: a client session to the hub at ENDPOINT holding the
  liveliness token of vehicle VID and publishing its ``Command`` every 50 ms until SIGINT;
- ``owner N``: make a factory (forked from this clean process, as the launcher does),
  start N ``wait`` children through it, print ``{"zygote": pid, "children": [pids]}``
  and block: a test kills this owner and checks nothing is left behind.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import threading


def ids() -> int:
    cmdline = open(f"/proc/{os.getpid()}/cmdline", "rb").read().replace(b"\0", b" ").decode().strip()
    print(json.dumps({"pid": os.getpid(), "pgid": os.getpgid(0), "sid": os.getsid(0), "ppid": os.getppid(),
                      "argv": sys.argv[1:], "cwd": os.getcwd(), "env": os.environ.get("PROBE"), "cmdline": cmdline}))
    print("probe stderr line", file=sys.stderr)
    return 0


def zenoh_client(endpoint: str, run: str, vid: int) -> int:
    from protocol import keys
    from protocol.codec import encode
    from protocol.messages import Command
    from protocol.session import ZenohArgs, reliable_publisher, session_scope

    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    with session_scope(ZenohArgs(connect=(endpoint,)), wait_s=60.0) as session:
        token = session.liveliness().declare_token(keys.alive(run, vid))
        pub = reliable_publisher(session, keys.cmd(run, vid))
        tick = 0
        while not stop.wait(0.05):
            pub.put(encode(Command(tick, 0.1 * tick, vid, 0.0, 0.0)))
            tick += 1
        pub.undeclare()
        token.undeclare()
    print(f"published {tick}", flush=True)
    return 0


def owner(n: int) -> int:
    from processes.factory import Factory

    factory = Factory(preload=("factory_probe",))
    children = [factory.spawn("factory_probe", ["wait"]) for _ in range(n)]
    print(json.dumps({"zygote": factory.pid, "children": [c.pid for c in children]}), flush=True)
    threading.Event().wait()
    return 0


def main(argv: list[str] | None = None) -> int:
    what, *rest = sys.argv[1:] if argv is None else argv
    if what == "ids":
        return ids()
    if what == "exit":
        return int(rest[0])
    if what == "raise":
        raise RuntimeError("the probe fails on purpose")
    if what == "wait":
        # Own SIGINT, as every process of ours does: a non-interactive shell that starts the
        # suite in the background ignores SIGINT, and a new interpreter would inherit that.
        signal.signal(signal.SIGINT, signal.default_int_handler)
        print("waiting", flush=True)
        threading.Event().wait()
    if what == "zenoh":
        return zenoh_client(rest[0], rest[1], int(rest[2]))
    if what == "owner":
        return owner(int(rest[0]))
    return 2


if __name__ == "__main__":
    sys.exit(main())
