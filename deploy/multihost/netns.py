"""A private network of Linux network namespaces: "hosts" for ``autocast deploy`` on one machine.

``Lab(n)`` creates one namespace that holds a bridge (the switch) and ``n`` host
namespaces, each joined to the bridge by a veth pair and given its own address
(10.77.0.1, 10.77.0.2, ... /24) and a loopback. Both ends of every veth pair are
created inside namespaces: nothing is added to, or changed in, the root namespace,
and the lab's 10.77.0.0/24 is invisible outside it. Names carry a random tag
(``ac1f2e3d-h0``), so labs never collide; leaving the ``with`` block kills whatever
still runs in them and deletes them, also after a failure. Needs root.

    sudo python -m deploy.multihost.netns [--hosts 4] -- --scenario left_turn --vehicles 5 --scheme autocast
    sudo python -m deploy.multihost.netns --hosts 3 --by-domain -- --scenario corridor3 --vehicles 5 --scheme autocast

builds a lab, writes a hosts file that puts the world and the recorder on h0, the
channel proxy on h1 and the agents on the others, or with ``--by-domain`` each scheduler
domain's on a host of its own (prefix ``ip netns exec <ns> sh -c``,
one Zenoh router per namespace), runs ``autocast deploy`` with the given flags inside
h0, checks that no process of the run is left in any namespace, and deletes the lab.
"""

from __future__ import annotations

import argparse
import os
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

SUBNET = "10.77.0"  # private to the lab's namespaces
PORT = 7447  # each namespace has its own network stack: the same port everywhere


@dataclass(frozen=True, slots=True)
class NetnsHost:
    name: str  # the host's name in the hosts file
    ns: str  # its network namespace
    address: str

    @property
    def prefix(self) -> list[str]:
        """The hosts file's command prefix: run one shell command line in this namespace."""
        return ["ip", "netns", "exec", self.ns, "sh", "-c"]


def unavailable() -> str | None:
    """Why network namespaces cannot be used here, or None if they can."""
    if shutil.which("ip") is None:
        return "iproute2's ip is not installed"
    if os.geteuid() != 0:
        return "creating network namespaces needs root"
    probe = f"ac{secrets.token_hex(4)}-probe"
    out = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
    if out.returncode != 0:
        return f"ip netns add failed: {out.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", probe], capture_output=True)
    return None


class Lab:
    """``with Lab(4) as lab:`` -> ``lab.hosts`` (h0..h3), each in its own namespace."""

    def __init__(self, n_hosts: int, tag: str | None = None) -> None:
        if not 1 <= n_hosts <= 200:
            raise ValueError(f"n_hosts: {n_hosts} is not in [1, 200]")
        self.tag = tag or f"ac{secrets.token_hex(3)}"
        self.switch = f"{self.tag}-sw"
        self.hosts = [NetnsHost(f"h{i}", f"{self.tag}-h{i}", f"{SUBNET}.{i + 1}") for i in range(n_hosts)]
        self._made: list[str] = []

    def __enter__(self) -> "Lab":
        try:
            self.up()
        except BaseException:
            self.down()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.down()

    def up(self) -> None:
        self._netns_add(self.switch)
        _ip("-n", self.switch, "link", "add", "br0", "type", "bridge")
        _ip("-n", self.switch, "link", "set", "br0", "up")
        for i, h in enumerate(self.hosts):
            self._netns_add(h.ns)
            _ip("-n", self.switch, "link", "add", f"p{i}", "type", "veth", "peer", "name", "eth0", "netns", h.ns)
            _ip("-n", self.switch, "link", "set", f"p{i}", "master", "br0")
            _ip("-n", self.switch, "link", "set", f"p{i}", "up")
            _ip("-n", h.ns, "addr", "add", f"{h.address}/24", "dev", "eth0")
            _ip("-n", h.ns, "link", "set", "eth0", "up")
            _ip("-n", h.ns, "link", "set", "lo", "up")

    def _netns_add(self, ns: str) -> None:
        _ip("netns", "add", ns)
        self._made.append(ns)

    def leftovers(self) -> dict[str, list[int]]:
        """Processes still running in the lab's namespaces, per namespace."""
        out = {}
        for ns in self._made:
            res = subprocess.run(["ip", "netns", "pids", ns], capture_output=True, text=True)
            pids = [int(p) for p in res.stdout.split()]
            if pids:
                out[ns] = pids
        return out

    def down(self) -> None:
        """Kill what still runs in the namespaces (by pid), then delete them; never raises."""
        for pids in self.leftovers().values():
            for pid in pids:
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
        for ns in reversed(self._made):  # hosts first: their veth peers go with them
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)
        self._made.clear()

    def hosts_toml(self, port: int = PORT, by_domain: bool = False) -> str:
        """A hosts file: world and recorder on h0, the proxy on h1, the agents on the rest.

        With two hosts, h1 takes the agents too; with three, h2 takes them all; with four
        or more, h2 takes two and the last host the rest. ``by_domain``: no host names
        agents, so a map of several scheduler domains has domain d's vehicles on host d.
        The namespaces share this machine's files, whose numba caches the launcher warms:
        no per-host warm-up.
        """
        hosts = self.hosts
        if len(hosts) < 2:
            raise ValueError("a lab for deploy needs at least two hosts")
        if by_domain:
            agents: dict[str, object] = {}
        elif len(hosts) == 2:
            agents = {hosts[1].name: "rest"}
        elif len(hosts) == 3:
            agents = {hosts[2].name: "rest"}
        else:
            agents = {hosts[2].name: 2, hosts[-1].name: "rest"}
        lines = ["# written by deploy.multihost.netns: one host per network namespace", "",
                 "[defaults]", f"port = {port}", f"workdir = {_q(str(Path(__file__).resolve().parents[2]))}",
                 f"python = {_q(sys.executable)}", "warm_up = false", ""]
        roles = {hosts[0].name: ["world", "recorder"], hosts[1].name: ["proxy"]}
        for h in hosts:
            lines += ["[[host]]", f"name = {_q(h.name)}", f"address = {_q(h.address)}",
                      f"prefix = [{', '.join(_q(p) for p in h.prefix)}]"]
            if h.name in roles:
                lines.append(f"run = [{', '.join(_q(r) for r in roles[h.name])}]")
            if h.name in agents:
                a = agents[h.name]
                lines.append(f"agents = {_q(a) if isinstance(a, str) else a}")
            lines.append("")
        return "\n".join(lines)


def _q(s: str) -> str:
    return '"' + s.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _ip(*args: str) -> None:
    res = subprocess.run(["ip", *args], capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)}: {res.stderr.strip()}")


def deploy_argv(lab: Lab, hosts_file: Path, flags: list[str]) -> list[str]:
    """``autocast deploy`` run inside the first host's namespace (the launcher's host)."""
    return ["ip", "netns", "exec", lab.hosts[0].ns, sys.executable, "-m", "deploy.cli", "deploy",
            "--hosts", str(hosts_file), *flags]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m deploy.multihost.netns", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--hosts", type=int, default=4, help="host namespaces (default 4, at least 2)")
    ap.add_argument("--by-domain", action="store_true", help="place no agent in the hosts file: a map of several "
                    "scheduler domains has domain d's vehicles on host hd")
    ap.add_argument("flags", nargs=argparse.REMAINDER, help="-- then autocast deploy's flags")
    args = ap.parse_args(argv)
    flags = args.flags[1:] if args.flags[:1] == ["--"] else args.flags
    reason = unavailable()
    if reason:
        print(f"network namespaces unavailable: {reason}", file=sys.stderr)
        return 2
    with Lab(args.hosts) as lab, tempfile.TemporaryDirectory() as tmp:
        hosts_file = Path(tmp) / "hosts.toml"
        hosts_file.write_text(lab.hosts_toml(by_domain=args.by_domain))
        print(f"lab {lab.tag}: " + ", ".join(f"{h.name}={h.ns}@{h.address}" for h in lab.hosts), file=sys.stderr)
        code = subprocess.run(deploy_argv(lab, hosts_file, flags)).returncode
        left = lab.leftovers()
        if left:
            print(f"processes left in the lab after the run: {left}", file=sys.stderr)
            code = code or 3
    return code


if __name__ == "__main__":
    raise SystemExit(main())
