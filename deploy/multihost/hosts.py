"""``autocast deploy``: one run's processes spread over several hosts.

    autocast deploy --hosts hosts.toml --scenario left_turn --vehicles 10 --scheme autocast --seed 0

The hosts file (``deploy/hosts.example.toml``, ``docs/multihost.md``) names each host:
its address, the command prefix that runs one shell command line there (``ssh
user@host``, ``ip netns exec NAME sh -c``; default ``sh -c``, this machine) and which
of the run's processes it takes (``run = ["world", "recorder", "proxy"]``,
``agents = 3``, ``agents = [0, 4]``, ``agents = "rest"`` or ``domains = [1]``: the
vehicles that start in scheduler domain 1). A map of several domains whose hosts file
places no agent gets each domain's vehicles on a host of its own, domain d on the d-th.

The run is the same table of processes as ``autocast run`` (``deploy.launch.table``). Each
host gets one Zenoh router (``deploy.multihost.router``) connected to the routers of the hosts
listed before it; every process connects to its own host's router. The launcher is a
client of the routers: it checks that they form a full mesh, then runs the same
``Launcher`` as ``autocast run`` (recorder first, the world's outcome, staged stop),
with every process started and stopped through its host's prefix (``deploy.multihost.remote``),
and prints the outcome as ``autocast run`` does. Same flags and exit codes as
``autocast run``, plus ``--hosts`` and ``--dry-run``.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import math
import os
import re
import shlex
import signal
import subprocess
import sys
import threading
import time
import tomllib
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path, PurePosixPath
from typing import Any

import zenoh

from deploy.launch import run, table, warmup
from deploy.multihost.remote import PID_LINE
from processes.manager import ProcessManager, ProcSpec
from protocol.session import ZenohArgs, session_scope
from vehicle_agent.domains import DomainTable
from world_server.scenarios import ScenarioParams, build

log = logging.getLogger("deploy.multihost.hosts")

REPO = Path(__file__).resolve().parents[2]
LOCAL_PREFIX = ("sh", "-c")  # this machine
DEFAULT_PORT = 7447
ROLES = (table.WORLD, table.PROXY, table.RECORDER)
REST = "rest"  # agents = "rest": every connected vehicle no other host takes
MESH_TIMEOUT_S = 60.0  # routers retry their links; a firewalled port shows up here
REMOTE_PID_WAIT_S = 5.0  # a process prints its pid line within this after it starts
PREFIX_TIMEOUT_S = 20.0  # one kill through a prefix (an ssh connection)
WARM_TIMEOUT_S = 900.0
_NAME = re.compile(r"^[A-Za-z0-9_\-]+$")


# ---------------------------------------------------------------------------- the hosts file


@dataclass(frozen=True, slots=True)
class Host:
    """One host of a run: where it is, how to run a command there, what it runs."""

    name: str
    address: str  # how the other hosts (and this host's processes) reach its router
    prefix: tuple[str, ...] = LOCAL_PREFIX  # runs its last argument, a shell command line, on the host
    port: int = DEFAULT_PORT  # the router's TCP port
    tls_port: int = 0  # locked down: where routers reach each other over mutual TLS; default port + 1
    listen: str = ""  # the address the router binds; default ``address`` (``0.0.0.0`` behind NAT)
    workdir: str = str(REPO)  # the repository's checkout on the host
    python: str = sys.executable  # a Python with the project installed, on the host
    env: tuple[tuple[str, str], ...] = ()
    warm_up: bool = True  # warm the host's numba caches before the run
    run: tuple[str, ...] = ()  # of world, proxy, recorder
    agents: int | tuple[int, ...] | str = 0  # a count, a list of vehicle ids, or "rest"
    domains: tuple[int, ...] = ()  # the agents of the vehicles that start in these scheduler domains

    @property
    def endpoint(self) -> str:
        return _endpoint(self.address, self.port)

    @property
    def listen_endpoint(self) -> str:
        return _endpoint(self.listen or self.address, self.port)

    @property
    def tls_endpoint(self) -> str:
        """Where the other routers reach this one when the run is locked down."""
        return _endpoint(self.address, self.tls_port or self.port + 1, "tls")

    @property
    def tls_listen_endpoint(self) -> str:
        return _endpoint(self.listen or self.address, self.tls_port or self.port + 1, "tls")

    @property
    def router(self) -> str:
        return f"router-{self.name}"


def _endpoint(address: str, port: int, protocol: str = "tcp") -> str:
    return f"{protocol}/[{address}]:{port}" if ":" in address else f"{protocol}/{address}:{port}"


@dataclass(frozen=True, slots=True)
class HostsFile:
    hosts: tuple[Host, ...]
    launcher_connect: tuple[str, ...] = ()  # the launcher's routers; default: every host's

    def router_endpoints(self) -> tuple[str, ...]:
        return tuple(h.endpoint for h in self.hosts)


_HOST_ONLY = ("name", "address", "run", "agents", "domains")
_SHARED = tuple(f.name for f in dataclasses.fields(Host) if f.name not in _HOST_ONLY)


def load_hosts(path: str | Path) -> HostsFile:
    """Read and check a hosts file; ``InputError`` names the field that is wrong."""
    try:
        with open(path, "rb") as f:
            data = tomllib.load(f)
    except OSError as exc:
        raise run.InputError(f"hosts: cannot read {path}: {exc.strerror}") from None
    except tomllib.TOMLDecodeError as exc:
        raise run.InputError(f"hosts: {path} is not valid TOML: {exc}") from None
    return parse_hosts(data)


def parse_hosts(data: dict[str, Any]) -> HostsFile:
    _known("hosts file", data, ("defaults", "launcher", "host"))
    defaults = data.get("defaults", {})
    _known("defaults", defaults, _SHARED)
    launcher = data.get("launcher", {})
    _known("launcher", launcher, ("connect",))
    entries = data.get("host", [])
    if not isinstance(entries, list) or not entries:
        raise run.InputError("hosts: no [[host]] entries")
    hosts = tuple(_host(i, {**defaults, **entry}) for i, entry in enumerate(entries))
    names = [h.name for h in hosts]
    for name in names:
        if names.count(name) > 1:
            raise run.InputError(f"hosts: host name {name!r} is used twice")
    endpoints = [h.endpoint for h in hosts] + [h.tls_endpoint.replace("tls/", "tcp/", 1) for h in hosts]
    for ep in endpoints:
        if endpoints.count(ep) > 1:
            raise run.InputError(f"hosts: two hosts' routers at {ep} (give them different addresses or ports; "
                                 "a locked-down router also listens on its tls_port, default port + 1)")
    connect = launcher.get("connect", [])
    if isinstance(connect, str):
        connect = [connect]
    if not all(isinstance(c, str) and c for c in connect):
        raise run.InputError("launcher.connect: a list of Zenoh endpoints, e.g. [\"tcp/10.0.0.1:7447\"]")
    return HostsFile(hosts, tuple(connect))


def _known(where: str, table_: Any, fields: Iterable[str]) -> None:
    if not isinstance(table_, dict):
        raise run.InputError(f"hosts: {where}: a table, not {type(table_).__name__}")
    fields = tuple(fields)
    for key in table_:
        if key not in fields:
            raise run.InputError(f"hosts: {where}: unknown field {key!r} (known: {', '.join(fields)})")


def _host(i: int, entry: dict[str, Any]) -> Host:
    if not isinstance(entry, dict):
        raise run.InputError(f"hosts: host #{i + 1}: a table")
    name = entry.get("name")
    where = f"host {name!r}" if isinstance(name, str) else f"host #{i + 1}"
    _known(where, entry, (*_HOST_ONLY, *_SHARED))

    def bad(field: str, want: str) -> run.InputError:
        return run.InputError(f"hosts: {where}: {field}: {entry.get(field)!r} is not {want}")

    if not isinstance(name, str) or not _NAME.match(name):
        raise bad("name", "a name of letters, digits, '-' and '_'")
    for field in ("address", "listen", "workdir", "python"):
        if field in entry and not (isinstance(entry[field], str) and (entry[field] or field == "listen")):
            raise bad(field, "a non-empty string")
    if "address" not in entry:
        raise run.InputError(f"hosts: {where}: address: missing")
    port = entry.get("port", DEFAULT_PORT)
    if not isinstance(port, int) or isinstance(port, bool) or not 1 <= port <= 65535:
        raise bad("port", "a TCP port (1..65535)")
    tls_port = entry.get("tls_port", 0)
    if not isinstance(tls_port, int) or isinstance(tls_port, bool) or not 0 <= tls_port <= 65535 or \
            (tls_port == 0 and port == 65535) or tls_port == port:
        raise bad("tls_port", "another TCP port (1..65535; default port + 1)")
    prefix = entry.get("prefix", "")
    if isinstance(prefix, str):
        prefix = shlex.split(prefix)
    if not isinstance(prefix, list) or not all(isinstance(p, str) for p in prefix):
        raise bad("prefix", "a command (string or list of strings)")
    env = entry.get("env", {})
    if not isinstance(env, dict) or not all(isinstance(v, str) and _NAME.match(k) for k, v in env.items()):
        raise bad("env", "a table of NAME = \"value\"")
    warm_up = entry.get("warm_up", True)
    if not isinstance(warm_up, bool):
        raise bad("warm_up", "true or false")
    roles = entry.get("run", [])
    if isinstance(roles, str):
        roles = [roles]
    if not isinstance(roles, list) or not all(r in ROLES for r in roles):
        raise bad("run", f"a list of {', '.join(ROLES)}")
    agents = entry.get("agents", 0)
    if isinstance(agents, list):
        if not all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in agents):
            raise bad("agents", "a list of vehicle ids")
        agents = tuple(agents)
    elif not (agents == REST or (isinstance(agents, int) and not isinstance(agents, bool) and agents >= 0)):
        raise bad("agents", f"a count, a list of vehicle ids or {REST!r}")
    domains = entry.get("domains", [])
    if not isinstance(domains, list) or not all(isinstance(d, int) and not isinstance(d, bool) and d >= 0
                                                for d in domains):
        raise bad("domains", "a list of scheduler domain ids")
    return Host(name=name, address=entry["address"], prefix=tuple(prefix) or LOCAL_PREFIX, port=port, tls_port=tls_port,
                listen=entry.get("listen", ""), workdir=entry.get("workdir", str(REPO)),
                python=entry.get("python", sys.executable), env=tuple(sorted(env.items())), warm_up=warm_up,
                run=tuple(roles), agents=agents, domains=tuple(domains))


# ---------------------------------------------------------------------------- placement


def place(cfg: table.RunConfig, hf: HostsFile, hub_of: Callable[[Host], str] = lambda h: h.endpoint
          ) -> list[tuple[ProcSpec, Host]]:
    """The run's table of processes, each on its host and connected to that host's router
    (``hub_of(host)``: its address by default, the router's service name under compose)."""
    host_of: dict[str, Host] = {}
    for role in ROLES:
        holders = [h for h in hf.hosts if role in h.run]
        if len(holders) > 1:
            raise run.InputError(f"hosts: {role}: on {', '.join(h.name for h in holders)}; exactly one host runs it")
        if holders:
            host_of[role] = holders[0]
        elif role != table.PROXY or table.needs_proxy(cfg.scheme):
            raise run.InputError(f"hosts: {role}: no host runs it (add it to one host's run = [...])")
    for vid, host in assign_agents(table.connected_vids(cfg.params), hf.hosts, start_domains(cfg.params)).items():
        host_of[table.agent_name(vid)] = host
    rows = {h.name: {s.name: s for s in table.processes(replace(cfg, hub=hub_of(h)))} for h in hf.hosts}
    return [(rows[host_of[spec.name].name][spec.name], host_of[spec.name]) for spec in table.processes(cfg)]


@dataclass(frozen=True, slots=True)
class StartDomains:
    """The scheduler domain each connected vehicle starts in, and how many the map has."""

    n_domains: int = 1
    domain_of: tuple[tuple[int, int], ...] = ()  # (vehicle id, domain)


@functools.lru_cache(maxsize=8)
def start_domains(params: ScenarioParams) -> StartDomains:
    """Each connected vehicle's domain: the one its start position is in
    (``DomainTable.membership``; in the overlap of two, the one whose centre is nearer).
    Its agent runs on that domain's host for the whole run, wherever it drives."""
    scene = build(params)
    domains = DomainTable.of(scene.roadmap.to_msg())
    pairs = []
    for actor in scene.connected():
        x, y, _ = actor.start_pose()
        pairs.append((actor.vid, min(domains.membership(x, y), key=lambda d: math.dist((x, y), domains.center[d]))))
    return StartDomains(len(domains), tuple(pairs))


def assign_agents(vids: Sequence[int], hosts: Sequence[Host], start: StartDomains = StartDomains()
                  ) -> dict[int, Host]:
    """Vehicle id -> host: lists first, then domains, then counts in host order, then
    "rest". For a map of several domains, a hosts file that places no agent puts domain
    d's vehicles on the d-th host."""
    domains_on = {h.name: h.domains for h in hosts}
    if start.n_domains > 1 and all(h.agents == 0 and not h.domains for h in hosts):
        if len(hosts) < start.n_domains:
            raise run.InputError(f"hosts: agents: the map has {start.n_domains} scheduler domains and the file "
                                 f"{len(hosts)} hosts; give each domain a host, or place the agents "
                                 "(agents = ..., domains = [...])")
        domains_on = {h.name: (d,) for d, h in enumerate(hosts[:start.n_domains])}
    out: dict[int, Host] = {}
    for h in hosts:
        if isinstance(h.agents, tuple):
            for vid in h.agents:
                if vid not in vids:
                    raise run.InputError(f"hosts: host {h.name!r}: agents: vehicle {vid} is not a connected "
                                         f"vehicle of this run ({', '.join(map(str, vids))})")
                if vid in out:
                    raise run.InputError(f"hosts: agents: vehicle {vid} is on {out[vid].name} and {h.name}")
                out[vid] = h
    host_of_domain: dict[int, Host] = {}
    for h in hosts:
        for d in domains_on.get(h.name, ()):
            if d >= start.n_domains:
                raise run.InputError(f"hosts: host {h.name!r}: domains: {d} is not a scheduler domain of this "
                                     f"run's map (0-{start.n_domains - 1})")
            if d in host_of_domain:
                raise run.InputError(f"hosts: domains: domain {d} is on {host_of_domain[d].name} and {h.name}")
            host_of_domain[d] = h
    for vid, d in start.domain_of:
        if vid in vids and vid not in out and d in host_of_domain:
            out[vid] = host_of_domain[d]
    free = [v for v in vids if v not in out]
    for h in hosts:
        if isinstance(h.agents, int):
            if h.agents > len(free):
                raise run.InputError(f"hosts: host {h.name!r}: agents: {h.agents} asked, {len(free)} left "
                                     f"of {len(vids)} connected vehicles")
            out.update({v: h for v in free[:h.agents]})
            free = free[h.agents:]
    rest = [h for h in hosts if h.agents == REST]
    if len(rest) > 1:
        raise run.InputError(f"hosts: agents = {REST!r} on {', '.join(h.name for h in rest)}; one host at most")
    if rest:
        out.update({v: rest[0] for v in free})
        free = []
    if free:
        raise run.InputError(f"hosts: agents: vehicles {', '.join(map(str, free))} are on no host "
                             f"(give one host agents = {REST!r})")
    return out


def router_spec(host: Host, hf: HostsFile, config: Path | None = None) -> ProcSpec:
    """The host's router connects to the routers of the hosts listed before it: one link
    per pair. ``config``: its credentials and the run's ACL (``--lock-down``); the routers
    then link over mutual TLS on their ``tls_port`` (deploy/launch/credentials.py says why)."""
    before = hf.hosts[:[h.name for h in hf.hosts].index(host.name)]
    args = ["--name", host.name, "--listen", host.listen_endpoint]
    if config is not None:
        args += ["--listen", host.tls_listen_endpoint]
    for other in before:
        args += ["--connect", other.tls_endpoint if config is not None else other.endpoint]
    if config is not None:
        args += ["--zenoh-config", str(config)]
    return ProcSpec(host.router, "deploy.multihost.router", tuple(args), critical=True)


# ---------------------------------------------------------------------------- commands on a host


def shell_line(host: Host, module: str, args: Sequence[str], action: str = "exec") -> str:
    """``cd WORKDIR && exec env ... PYTHON -m deploy.multihost.remote exec MODULE ARGS`` for the host's shell."""
    env = " ".join(shlex.quote(f"{k}={v}") for k, v in (("PYTHONUNBUFFERED", "1"), *host.env))
    words = [host.python, "-m", "deploy.multihost.remote", action, *([module] if module else []), *args]
    return f"cd {shlex.quote(host.workdir)} && exec env {env} {shlex.join(words)}"


def on_host(host: Host, line: str) -> list[str]:
    return [*host.prefix, line]


def put_files(host: Host, files: dict[Path, str]) -> None:
    """Write ``files`` on the host (paths relative to its workdir), readable by the owner
    only, through its prefix: the content goes over the prefix's stdin, never on a
    command line. Raises ``RuntimeError`` if the host refuses."""
    for path, text in files.items():
        line = f"cd {shlex.quote(host.workdir)} && umask 077 && mkdir -p {shlex.quote(str(path.parent))} && " \
               f"cat > {shlex.quote(str(path))}"
        res = subprocess.run(on_host(host, line), input=text, text=True, capture_output=True, timeout=PREFIX_TIMEOUT_S)
        if res.returncode != 0:
            raise RuntimeError(f"writing {path} on {host.name}: {res.stderr.strip() or f'exit {res.returncode}'}")


def credential_files(cfg: table.RunConfig, placed: list[tuple[ProcSpec, Host]], host: Host) -> dict[Path, str]:
    """What the host's router and processes need of the run's credentials (written on the
    launcher's machine by ``deploy.launch.credentials``)."""
    paths = []
    if cfg.lock_down:
        from deploy.launch.credentials import tls_files

        paths += [table.credentials_dir(cfg) / "zenoh-users.txt", table.zenoh_config_path(cfg, host.router),
                  *tls_files(cfg, host.router)]
        paths += [table.zenoh_config_path(cfg, spec.name) for spec, h in placed if h is host]
    if cfg.signing:
        paths += [table.v2x_credentials_path(cfg, int(spec.name[len("agent"):])) for spec, h in placed
                  if h is host and spec.name.startswith("agent")]
    return {p: p.read_text() for p in paths}


def command(host: Host, spec: ProcSpec) -> list[str]:
    return on_host(host, shell_line(host, spec.module, spec.args))


class HostProcessManager(ProcessManager):
    """``ProcessManager`` for processes that run through a host's command prefix.

    The local child is the prefix (an ssh client, ``ip netns exec``, a shell); its
    stdout, the remote process's, goes to ``logs/<name>.log``. Signals go to the remote
    process group through the same prefix (``kill -s SIG -- -PID``), so stopping works
    whether or not the prefix forwards signals.
    """

    def __init__(self, log_dir: Path, host_of: dict[str, Host]) -> None:
        super().__init__(log_dir)
        self.log_dir: Path = log_dir
        self.host_of = host_of
        self._remote_pids: dict[str, int] = {}

    def start(self, spec: ProcSpec) -> subprocess.Popen:
        if spec.name in self.procs:
            raise ValueError(f"process {spec.name!r} started twice")
        argv = command(self.host_of[spec.name], spec)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        with open(self.log_dir / f"{spec.name}.log", "wb") as out:
            proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                    start_new_session=True)
        self.procs[spec.name] = (spec, proc)
        log.debug("started %s on %s: %s", spec.name, self.host_of[spec.name].name, shlex.join(argv))
        return proc

    def remote_pid(self, name: str, wait_s: float = REMOTE_PID_WAIT_S) -> int | None:
        """The pid (and process group) on the host, from the log's first line; None if it never printed it."""
        if name in self._remote_pids:
            return self._remote_pids[name]
        path, proc = self.log_dir / f"{name}.log", self.procs[name][1]
        deadline = time.monotonic() + wait_s
        while True:
            with open(path, "rb") as f:
                first = f.readline().decode(errors="replace")
            if first.startswith(PID_LINE) and first.endswith("\n"):
                self._remote_pids[name] = int(first.split()[2])
                return self._remote_pids[name]
            if proc.poll() is not None or time.monotonic() > deadline:
                return None
            time.sleep(0.05)

    def pids(self) -> dict[str, int]:
        return {name: self.remote_pid(name) or proc.pid for name, (_, proc) in self.procs.items()}

    def signal(self, names: Iterable[str], sig: str) -> None:
        """Send ``sig`` (INT, KILL) to each process's group on its host, one prefix call per host."""
        by_host: dict[str, tuple[Host, list[int]]] = {}
        for name in names:
            pid = self.remote_pid(name)
            if pid is None:  # it never got to print its pid: the prefix itself is all there is
                _killpg(self.procs[name][1], getattr(signal, f"SIG{sig}"))
                continue
            host = self.host_of[name]
            by_host.setdefault(host.name, (host, []))[1].append(pid)
        calls = [subprocess.Popen(on_host(host, f"kill -s {sig} -- " + " ".join(f"-{p}" for p in pids)),
                                  stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                  start_new_session=True) for host, pids in by_host.values()]
        for call in calls:
            try:
                call.wait(timeout=PREFIX_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                log.warning("a kill through %s hung; giving up on it", shlex.join(call.args[:-1]))
                call.kill()
                call.wait()

    def stop(self, names: Iterable[str], grace_s: float = 3.0) -> None:
        """SIGINT on the hosts, wait up to ``grace_s``, SIGKILL what is left; then the prefixes."""
        running = [n for n in names if n in self.procs and self.procs[n][1].poll() is None]
        if not running:
            return
        self.signal(running, "INT")
        left = self.wait(running, grace_s)
        if left:
            log.warning("%s ignored SIGINT for %.1f s; killing", " ".join(left), grace_s)
            self.signal(left, "KILL")
            left = self.wait(left, grace_s)
        for name in left:  # the remote process is gone or unreachable: end the local prefix
            _killpg(self.procs[name][1], signal.SIGKILL)
        for name in running:
            self.procs[name][1].wait()


def _killpg(proc: subprocess.Popen, sig: int) -> None:
    try:
        os.killpg(proc.pid, sig)
    except ProcessLookupError:
        pass


# ---------------------------------------------------------------------------- the run


def warm_hosts(hosts: Iterable[Host], params, log_dir: Path, stop: threading.Event) -> None:
    """Warm the numba caches on every host that asks for it, all at once; a failure costs only time."""
    line = json.dumps(dataclasses.asdict(params))
    started = []
    for host in hosts:
        with open(log_dir / f"warm-{host.name}.log", "wb") as out:
            started.append((host, subprocess.Popen(on_host(host, shell_line(host, "", [line], action="warm")),
                                                   stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                                   start_new_session=True)))
    if not started:
        return
    t0 = time.monotonic()
    deadline = t0 + WARM_TIMEOUT_S
    for host, proc in started:
        while proc.poll() is None and not stop.is_set() and time.monotonic() < deadline:
            time.sleep(0.1)
        if proc.poll() is None:
            _killpg(proc, signal.SIGKILL)
            proc.wait()
        if proc.returncode:
            log.warning("warming %s failed (code %s, see logs/warm-%s.log); its agents compile their own",
                        host.name, proc.returncode, host.name)
    log.info("numba caches warm on %s in %.1f s", " ".join(h.name for h, _ in started), time.monotonic() - t0)


def routers_seen(session: zenoh.Session) -> list[dict]:
    """Every router's admin record reachable from the launcher (locators, linked sessions)."""
    out = []
    for reply in session.get("@/*/router", timeout=2.0):
        if reply.ok is not None:
            try:
                out.append(json.loads(reply.ok.payload.to_string()))
            except ValueError:
                pass
    return out


def router_links(session: zenoh.Session) -> dict[str, int]:
    """Each router the launcher reaches (by zid) and how many other routers it is linked to."""
    return {r.get("zid"): sum(s.get("whatami") == "router" for s in r.get("sessions", []))
            for r in routers_seen(session)}


def wait_for_mesh(session: zenoh.Session, hf: HostsFile, procs: HostProcessManager, timeout_s: float,
                  stop: threading.Event) -> str | None:
    """None once every router answers and is linked to every other; else why not."""
    n = len(hf.hosts)
    deadline = time.monotonic() + timeout_s
    while True:
        for spec, rc in procs.died():
            tail = (procs.log_dir / f"{spec.name}.log").read_text(errors="replace").strip().splitlines()[-1:]
            return f"{spec.name} exited (code {rc}) before the run: {' '.join(tail) or 'no output'}"
        links = router_links(session)
        if len(links) == n and all(k >= n - 1 for k in links.values()):
            return None
        if stop.is_set():
            return "interrupted"
        if time.monotonic() > deadline:
            ports = sorted({h.port for h in hf.hosts})
            return (f"the hosts' routers are not linked after {timeout_s:.0f} s: {len(links)} of {n} answered, "
                    f"with {sorted(links.values())} router links (want {n - 1} each); check that TCP port(s) "
                    f"{', '.join(map(str, ports))} are open between the hosts (logs/router-*.log)")
        time.sleep(0.2)


def deploy(opts: run.LaunchOptions, hf: HostsFile, placed: list[tuple[ProcSpec, Host]],
           stop: threading.Event) -> run.RunResult:
    """One run over the hosts: routers, mesh check, the launcher's run, then the routers stop."""
    cfg = opts.run
    cfg.log_dir.mkdir(parents=True, exist_ok=False)
    cfg = run.prepare(cfg)
    opts = replace(opts, run=cfg)
    placed = place(cfg, hf)  # again: the command lines now carry the credentials' flags
    routers = {h.name: None for h in hf.hosts}
    launcher_config = None
    if cfg.lock_down:
        from deploy.launch import credentials

        written = credentials.lock_down(cfg, {h.router: h.address for h in hf.hosts})
        routers = {h.name: written[h.router] for h in hf.hosts}
        launcher_config = str(written[credentials.LAUNCHER])
    if opts.warm_up:
        warmup.warm_numba_caches(cfg.params)  # the launcher's host, and any host sharing its files
        warm_hosts([h for h in hf.hosts if h.warm_up], cfg.params, cfg.log_dir, stop)
    host_of = {spec.name: host for spec, host in placed} | {h.router: h for h in hf.hosts}
    procs = HostProcessManager(cfg.log_dir, host_of)
    write_placement(cfg.run_dir / "hosts.json", hf, placed)
    try:
        for host in hf.hosts:
            files = credential_files(cfg, placed, host)
            if files:
                put_files(host, files)
        for host in hf.hosts:
            procs.start(router_spec(host, hf, routers[host.name]))
        connect = hf.launcher_connect or hf.router_endpoints()
        with session_scope(ZenohArgs(connect=connect, config_file=launcher_config), wait_s=MESH_TIMEOUT_S) as session:
            t0 = time.monotonic()
            failure = wait_for_mesh(session, hf, procs, MESH_TIMEOUT_S, stop)
            if failure == "interrupted":
                return run.RunResult(run.EXIT_INTERRUPTED, None, "interrupted before an outcome")
            if failure:
                return run.RunResult(run.EXIT_FAILED, None, failure)
            log.info("%d routers linked in %.1f s: %s", len(hf.hosts), time.monotonic() - t0,
                     " ".join(f"{h.name}={h.endpoint}" for h in hf.hosts))
            res = run.Launcher(opts, session, stop, procs, [spec for spec, _ in placed]).run()
    except ConnectionError as exc:
        return run.RunResult(run.EXIT_FAILED, None, f"the launcher reached no router: {exc}")
    except RuntimeError as exc:  # a host refused the credentials
        return run.RunResult(run.EXIT_FAILED, None, str(exc))
    finally:
        procs.stop_all(run.GRACE_S)  # the routers, and anything a failed start left behind
    return with_placement(res, cfg, placed)


def with_placement(res: run.RunResult, cfg: table.RunConfig, placed: list[tuple[ProcSpec, Host]]) -> run.RunResult:
    """The outcome record plus where each process ran; the MCAP named on the recorder's host."""
    if res.result is None:
        return res
    result = dict(res.result, hosts={spec.name: host.name for spec, host in placed})
    recorder = next(host for spec, host in placed if spec.name == table.RECORDER)
    if result.get("mcap") is None:
        path = cfg.mcap_path if cfg.mcap_path.is_absolute() else Path(recorder.workdir) / cfg.mcap_path
        result["mcap"] = f"{recorder.name}:{path}"
    return replace(res, result=result)


def write_placement(path: Path, hf: HostsFile, placed: list[tuple[ProcSpec, Host]]) -> None:
    record = {h.name: {"address": h.address, "router": h.endpoint, "prefix": shlex.join(h.prefix),
                       "processes": [s.name for s, host in placed if host is h]} for h in hf.hosts}
    path.write_text(json.dumps(record, indent=1) + "\n")


def plan(hf: HostsFile, placed: list[tuple[ProcSpec, Host]], cfg: table.RunConfig | None = None) -> str:
    """What ``--dry-run`` prints: each host's router and processes, then every command
    (``cfg`` locked down: the routers' links are mutual TLS, each has its credentials)."""
    locked = cfg is not None and cfg.lock_down
    lines = []
    for h in hf.hosts:
        links = ", ".join(o.tls_endpoint if locked else o.endpoint for o in hf.hosts[:hf.hosts.index(h)]) or "-"
        listens = f"{h.listen_endpoint} and {h.tls_listen_endpoint}" if locked else h.listen_endpoint
        lines.append(f"host {h.name}: router {listens} (connects to {links}); "
                     f"runs {' '.join(s.name for s, host in placed if host is h) or 'nothing else'}")
    lines.append(f"launcher connects to {', '.join(hf.launcher_connect or hf.router_endpoints())}")
    lines.append("commands:")
    for h in hf.hosts:
        config = table.zenoh_config_path(cfg, h.router) if locked else None
        lines.append(f"  {h.router}: {shlex.join(command(h, router_spec(h, hf, config)))}")
    for spec, h in placed:
        lines.append(f"  {spec.name}: {shlex.join(command(h, spec))}")
    return "\n".join(lines)


# ---------------------------------------------------------------------------- docker compose

IMAGE = "autocast-py"
LAUNCHER = "launcher"  # the compose file's launcher (deploy.multihost.compose_launcher), on the recorder's host
SECRETS = PurePosixPath("/run/secrets")  # where compose mounts each service's secrets
APP = PurePosixPath("/app")  # the image's checkout (deploy/Dockerfile)


def compose(cfg: table.RunConfig, hf: HostsFile, where: Path = REPO / "deploy") -> dict[str, Any]:
    """A compose file for this run and hosts (``where``: its directory; paths in it are
    relative to that): one service per process, a router per host, and the launcher.

    Processes reach their host's router by service name; routers reach each other at the
    hosts' addresses (published ports), or by service name where a host's address is its
    router's name (every "host" on one Docker engine). Locked down, each service gets
    only its own credentials, as compose secrets under /run/secrets. The recorder and
    the launcher write into the run's directory on their host (a bind mount).
    """
    cfg = replace(cfg, wait_for=(*cfg.wait_for, LAUNCHER))  # tick 0 waits for the launcher (the recorder is up)
    inside = replace(cfg, run_dir=Path("runs") / cfg.run_id)  # the run's directory in the container
    creds = str(table.credentials_dir(inside)) + "/"
    build = {"context": os.path.relpath(REPO, where), "dockerfile": "deploy/Dockerfile",
             "args": {"BASE": "${AUTOCAST_BASE_IMAGE:-python:3.11-slim}"}}
    run_dir = _relative(cfg.run_dir, where)
    outputs = {"volumes": [f"{run_dir}:{APP / inside.run_dir}"],  # the MCAP and outcome.json, on the host
               "tmpfs": [str(APP / table.credentials_dir(inside))]}  # the run's credentials stay out of sight

    def service(h: Host, module: str, args: Sequence[str], secrets: list[str]) -> dict[str, Any]:
        out = {"image": IMAGE, "build": build, "command": ["python", "-m", module, *(
            str(SECRETS) + "/" + a[len(creds):] if a.startswith(creds) else a for a in args)],
            "labels": {"autocast.host": h.name}}
        if secrets and cfg.lock_down:
            out["secrets"] = secrets
        return out

    services: dict[str, Any] = {}
    for h in hf.hosts:
        config = table.zenoh_config_path(inside, h.router) if cfg.lock_down else None
        spec = router_spec(replace(h, listen="0.0.0.0"), hf, config)
        services[h.router] = service(h, spec.module, spec.args, compose_secrets(cfg, h.router))
        if h.address != h.router:  # other machines reach it on this host's published port(s)
            tls = [f"{h.tls_port or h.port + 1}:{h.tls_port or h.port + 1}"] if cfg.lock_down else []
            services[h.router]["ports"] = [f"{h.port}:{h.port}", *tls]
    placed = place(inside, hf, hub_of=lambda h: f"tcp/{h.router}:{h.port}")
    recorder_host = next(h for spec, h in placed if spec.name == table.RECORDER)
    hosts_of = {spec.name: h.name for spec, h in placed} | {LAUNCHER: recorder_host.name}
    record = {"scenario": cfg.params.scenario, "vehicles": cfg.params.vehicles, "seed": cfg.params.seed,
              "scheme": cfg.scheme, "model": cfg.model.label(), "model_settings": cfg.model.settings(),
              "signed": cfg.signing, "lock_down": cfg.lock_down, "hosts": hosts_of}
    launcher_args = ["--run-id", cfg.run_id, "--connect", f"tcp/{recorder_host.router}:{recorder_host.port}",
                     "--routers", str(len(hf.hosts)), "--run-dir", str(inside.run_dir), "--record", json.dumps(record)]
    if cfg.lock_down:
        launcher_args += ["--zenoh-config", str(SECRETS / f"{LAUNCHER}.zenoh.json5")]
    services[LAUNCHER] = service(recorder_host, "deploy.multihost.compose_launcher", launcher_args,
                                 compose_secrets(cfg, LAUNCHER))
    services[LAUNCHER].update(depends_on=[recorder_host.router], **outputs)
    for spec, h in placed:
        services[spec.name] = service(h, spec.module, spec.args, compose_secrets(cfg, spec.name))
        services[spec.name]["depends_on"] = [h.router]
        if spec.name == table.RECORDER:
            services[spec.name].update(outputs)
    project: dict[str, Any] = {"services": services}
    if cfg.lock_down:
        names = sorted({s for service_ in services.values() for s in service_.get("secrets", [])})
        files = _relative(table.credentials_dir(cfg), where)
        project["secrets"] = {name: {"file": f"{files}/{name}"} for name in names}
    return project


def _relative(path: Path, where: Path) -> str:
    """``path`` relative to ``where``, as compose takes a host path (``./`` or ``../`` first)."""
    rel = os.path.relpath(path.resolve(), where.resolve())
    return rel if rel.startswith("..") else f"./{rel}"


def compose_secrets(cfg: table.RunConfig, name: str) -> list[str]:
    """The credential files service ``name`` gets (file names in the run's credentials directory)."""
    if not cfg.lock_down:
        return []
    if name.startswith("router-"):
        from deploy.launch.credentials import tls_files

        return ["zenoh-users.txt", table.zenoh_config_path(cfg, name).name, *(p.name for p in tls_files(cfg, name))]
    return [table.zenoh_config_path(cfg, name).name]


def project_name(cfg: table.RunConfig) -> str:
    return f"autocast-{cfg.run_id.lower()}"


def compose_text(cfg: table.RunConfig, hf: HostsFile, how: str, where: Path = REPO / "deploy",
                 path: str = "deploy/docker-compose.yml") -> str:
    project = compose(cfg, hf, where)
    by_host = {h.name: [n for n, s in project["services"].items() if s["labels"]["autocast.host"] == h.name]
               for h in hf.hosts}
    up = f"docker compose -p {project_name(cfg)} -f {path}"
    head = [f"# Generated by: {how}",
            "# One service per process of the run, a Zenoh router per host (explicit endpoints, no multicast) and",
            "# the launcher, which writes outcome.json beside the MCAP and exits with autocast run's exit code.",
            "# On each host: build the image (docker build -f deploy/Dockerfile -t autocast-py .)"
            + (f", copy {table.credentials_dir(cfg)}/ there" if cfg.lock_down else "")
            + ", then start that host's services:"]
    for name, services in by_host.items():
        head.append(f"#   {name}: {up} up -d {' '.join(services)}")
    head.append(f"# Wait: docker wait $({up} ps -q {LAUNCHER})  (its exit code is the run's); then on every host: "
                f"{up} down")
    return "\n".join(head) + "\n" + _yaml(project) + "\n"


def write_compose(cfg: table.RunConfig, hf: HostsFile, out: Path, how: str) -> None:
    """The compose file, and locked down the run's credentials (deploy.launch.credentials) with
    the routers' configs naming the files where the containers see them."""
    if cfg.lock_down:
        from deploy.launch import credentials

        written = credentials.lock_down(cfg, {h.router: h.address for h in hf.hosts})
        host_dir = str(table.credentials_dir(cfg)) + "/"
        for h in hf.hosts:
            path = written[h.router]
            path.write_text(path.read_text().replace(json.dumps(host_dir)[1:-1], f"{SECRETS}/"))
    out.write_text(compose_text(cfg, hf, how, out.parent, str(out)))


def _yaml(obj: dict[str, Any], depth: int = 0) -> str:
    """Block mappings, flow lists and JSON-quoted scalars: valid YAML without a YAML library."""
    pad, lines = "  " * depth, []
    for key, value in obj.items():
        if isinstance(value, dict):
            lines += [f"{pad}{json.dumps(key) if '.' in key else key}:", _yaml(value, depth + 1)]
        elif isinstance(value, list):
            lines.append(f"{pad}{key}: [{', '.join(json.dumps(v) for v in value)}]")
        else:
            lines.append(f"{pad}{key}: {json.dumps(value)}")
    return "\n".join(lines)


# ---------------------------------------------------------------------------- CLI


def main(argv: list[str] | None = None) -> int:
    ap = run.build_parser(prog="autocast deploy", description=__doc__, lock_down_default=True, sign_default=None)
    ap.add_argument("--hosts", required=True, metavar="FILE", help="the hosts file (deploy/hosts.example.toml)")
    ap.add_argument("--dry-run", action="store_true", help="print where each process runs and every command; "
                    "start nothing")
    ap.add_argument("--compose", metavar="FILE", help="write a docker compose file for this run and hosts "
                    "(one service per process, a router per host); start nothing")
    args = ap.parse_args(argv)
    sign_asked = args.sign
    if args.sign is None:  # signed by default; a compose file has no credentials to sign with
        args.sign = not args.compose
    level = args.log_level.upper()
    logging.basicConfig(level=level if level in logging.getLevelNamesMapping() else "INFO",
                        format="autocast deploy: %(message)s")
    try:
        opts = run.options_from(args, hub="", fresh=not args.compose)
        hf = load_hosts(args.hosts)
        if opts.run.signing and start_domains(opts.run.params).n_domains > 1:  # the agents refuse to sign there
            if sign_asked:
                raise run.InputError("sign: a map of several scheduler domains runs unsigned (docs/domains.md); "
                                     "drop --sign")
            print("note: a map of several scheduler domains runs unsigned (docs/domains.md)", file=sys.stderr)
            opts = replace(opts, run=replace(opts.run, signing=False))
            args.sign = False
        placed = place(opts.run, hf)
    except run.InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return run.EXIT_BAD_INPUT
    if args.dry_run:
        print(plan(hf, placed, opts.run))
        return 0
    if args.compose:
        if args.sign:  # asked for, and it would silently not be: the V2X credentials are not made into secrets
            print("error: --sign: compose files do not carry the vehicles' V2X credentials (docs/multihost.md)",
                  file=sys.stderr)
            return run.EXIT_BAD_INPUT
        print("note: the vehicles of a compose file do not sign (their V2X credentials are not made into secrets; "
              "docs/multihost.md)", file=sys.stderr)
        how = shlex.join(["autocast", "deploy", *(sys.argv[2:] if argv is None else argv)])
        write_compose(opts.run, hf, Path(args.compose), how)
        if args.lock_down:
            print(f"credentials in {table.credentials_dir(opts.run)}/ (each service gets its own as a compose secret)",
                  file=sys.stderr)
        print(f"wrote {args.compose}")
        return 0
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    t0 = time.monotonic()
    cfg = opts.run
    log.info("run %s: %s, %d vehicles, scheme %s, over %d hosts (%s) -> %s", cfg.run_id, cfg.params.scenario,
             cfg.params.vehicles, cfg.scheme, len(hf.hosts), " ".join(h.name for h in hf.hosts), cfg.run_dir)
    res = deploy(opts, hf, placed, stop)
    return run.report(res, cfg, args.json, time.monotonic() - t0)
