"""One run in docker containers, end to end, checked against the same run on one host.

    python -m deploy.multihost.compose_run --scenario left_turn --vehicles 10 --scheme autocast
    python -m deploy.multihost.compose_run --vehicles 10 --scheme single --fault     # kill an agent and a router mid-run

It starts the Docker daemon if none answers, makes a base image if there is none (the
official ``python:3.11-slim`` if it is here, else a Debian root file system made with
``debootstrap`` and ``docker import``ed), builds ``deploy/Dockerfile``, writes a hosts file
with three "hosts" on this Docker engine and the compose file ``autocast deploy
--compose`` makes of it (locked down: each container gets its own credentials as compose
secrets, the routers link over mutual TLS), brings it up, waits for the compose
launcher's judged outcome (``runs/<id>/outcome.json``, the MCAP beside it), tears
everything down and checks that no container, network or volume of the project is left.
Unless ``--no-compare``, it then runs the same scenario with ``autocast run`` on one host
and compares the judged outcome, closest distance and ticks (lock-step: they are equal).

``--fault`` kills one agent's container and then one host's router container mid-run
(at ticks it sees in the launcher's log) and checks that the run ends within a bounded
time, failed or judged, with its MCAP finalized.

Exit codes as ``autocast run``'s: 0 safe, 1 another judged outcome, 2 bad input,
3 failed (also: the outcome differs from the one-host run's, the MCAP is not finalized,
or something was left behind), 130 interrupted. With ``--fault``: 0 if the run ended
within ``FAULT_BOUND_S`` of the router's kill (judged or failed) with its MCAP finalized
and nothing left behind, else 3.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import tarfile
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from deploy.launch import run

log = logging.getLogger("deploy.multihost.compose_run")

REPO = Path(__file__).resolve().parents[2]
IMAGE = "autocast-py"
OFFICIAL_BASE = "python:3.11-slim"
DEBIAN_BASE = "autocast-base:bookworm"
DEBIAN_SUITE = "bookworm"
DEBIAN_PACKAGES = ("python3", "python3-venv", "ca-certificates")
HOST_CA_BUNDLE = Path("/etc/ssl/certs/ca-certificates.crt")
DAEMON_WAIT_S = 60.0
BUILD_TIMEOUT_S = 3600.0
RUN_TIMEOUT_S = 1200.0  # the compose launcher's own --timeout-s is 900
RECORDER_EXIT_WAIT_S = 30.0  # after the outcome the recorder drains and exits on its own
FAULT_BOUND_S = 60.0  # after the router's container is killed, the run has ended within this
STOP_GRACE_S = 5


# ---------------------------------------------------------------------------- docker


def sh(*cmd: str, check: bool = True, timeout: float | None = 600.0, **kw) -> subprocess.CompletedProcess:
    """Run a command, its output captured as text."""
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, **kw)
    if check and res.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd[:4])}...: exit {res.returncode}: {res.stderr.strip()[-2000:]}")
    return res


def daemon_up() -> bool:
    return shutil.which("docker") is not None and sh("docker", "info", check=False, timeout=30).returncode == 0


def start_daemon(log_path: Path, storage_driver: str = "") -> subprocess.Popen:
    """``dockerd`` in the background (this script stops it at the end); returns once it answers."""
    if shutil.which("dockerd") is None:
        raise RuntimeError("no Docker daemon answers and there is no dockerd to start (Debian: apt-get install "
                           "docker.io)")
    cmd = ["dockerd", *(["--storage-driver", storage_driver] if storage_driver else [])]
    out = open(log_path, "ab")
    proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                            start_new_session=True)
    deadline = time.monotonic() + DAEMON_WAIT_S
    while not daemon_up():
        if proc.poll() is not None or time.monotonic() > deadline:
            stop_daemon(proc)
            tail = log_path.read_text(errors="replace").strip().splitlines()[-3:]
            raise RuntimeError(f"dockerd did not come up: {' '.join(tail)}")
        time.sleep(0.5)
    return proc


def stop_daemon(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def compose_command() -> list[str] | None:
    """``docker compose`` (v2 plugin) if it is there, else ``docker-compose`` (v1), else None."""
    if shutil.which("docker") and sh("docker", "compose", "version", check=False, timeout=30).returncode == 0:
        return ["docker", "compose"]
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    return None


def image_exists(name: str) -> bool:
    return sh("docker", "image", "inspect", name, check=False, timeout=30).returncode == 0


def make_debian_base(name: str = DEBIAN_BASE, mirror: str = "http://deb.debian.org/debian") -> None:
    """A Debian root file system (``debootstrap``, Debian's packages) with Python 3 and its
    venv module, imported as image ``name``. It carries this machine's CA bundle and pip's
    ``cert`` setting, so pip inside reaches the package index as pip on this machine does
    (through a proxy that re-signs TLS, where there is one)."""
    if shutil.which("debootstrap") is None:
        raise RuntimeError(f"no base image ({OFFICIAL_BASE} or {name}) and no debootstrap to make one "
                           "(Debian: apt-get install debootstrap)")
    with tempfile.TemporaryDirectory(prefix="autocast-base-") as tmp:
        root = Path(tmp) / "rootfs"
        t0 = time.monotonic()
        sh("debootstrap", "--variant=minbase", f"--include={','.join(DEBIAN_PACKAGES)}", DEBIAN_SUITE, str(root),
           mirror, timeout=1800)
        if HOST_CA_BUNDLE.exists():
            shutil.copyfile(HOST_CA_BUNDLE, root / "etc/ssl/certs/ca-certificates.crt")
        (root / "etc/pip.conf").write_text("[global]\ncert = /etc/ssl/certs/ca-certificates.crt\n")
        tarball = Path(tmp) / "rootfs.tar"
        sh("tar", "-C", str(root), "-cf", str(tarball), ".", timeout=600)
        sh("docker", "import", "--change", "ENV LANG=C.UTF-8", "--change", 'CMD ["python3"]', str(tarball), name,
           timeout=600)
        log.info("made base image %s (debootstrap %s + python3) in %.0f s", name, DEBIAN_SUITE, time.monotonic() - t0)


def base_image(wanted: str = "") -> str:
    """The image to build on: ``wanted``, else the official one if present, else the Debian one (made if missing)."""
    if wanted:
        if not image_exists(wanted):
            raise RuntimeError(f"base image {wanted} is not on this Docker engine")
        return wanted
    if image_exists(OFFICIAL_BASE):
        return OFFICIAL_BASE
    if not image_exists(DEBIAN_BASE):
        make_debian_base()
    return DEBIAN_BASE


def build_image(base: str, log_path: Path, tag: str = IMAGE) -> float:
    """``docker build`` of deploy/Dockerfile on ``base``; returns its wall time. The context
    is the files git would commit (tracked, or untracked and not ignored): the same with
    the legacy builder, which ignores ``deploy/Dockerfile.dockerignore``, as with BuildKit."""
    files = sh("git", "-C", str(REPO), "ls-files", "-z", "--cached", "--others", "--exclude-standard").stdout
    t0 = time.monotonic()
    with tempfile.TemporaryFile() as context, open(log_path, "ab") as out:
        with tarfile.open(fileobj=context, mode="w", format=tarfile.GNU_FORMAT) as tar:  # PAX: not taken for a tar
            for name in sorted(set(filter(None, files.split("\0")))):
                if (REPO / name).exists():
                    tar.add(REPO / name, arcname=name, recursive=False)
        context.seek(0)
        res = subprocess.run(["docker", "build", "-f", "deploy/Dockerfile", "--build-arg", f"BASE={base}", "--force-rm",
                              "-t", tag, "-"], stdin=context, stdout=out, stderr=subprocess.STDOUT,
                             timeout=BUILD_TIMEOUT_S)
    if res.returncode != 0:
        raise RuntimeError(f"docker build failed (exit {res.returncode}; see {log_path})")
    return time.monotonic() - t0


# ---------------------------------------------------------------------------- one compose run


def local_hosts(vids: tuple[int, ...]) -> str:
    """Three "hosts" on this Docker engine, placed as docs/multihost.md's example: world,
    recorder and the ego on alpha, the proxy and half the others on beta, the rest on
    gamma. Each address is its router's service name: the routers reach each other over
    the compose network, and no port is published."""
    return "\n".join([
        '[[host]]\nname = "alpha"\naddress = "router-alpha"\nrun = ["world", "recorder"]\nagents = [0]\n',
        f'[[host]]\nname = "beta"\naddress = "router-beta"\nrun = ["proxy"]\nagents = {(len(vids) - 1) // 2}\n',
        '[[host]]\nname = "gamma"\naddress = "router-gamma"\nagents = "rest"\n'])


@dataclass
class Compose:
    """One project: ``docker compose -p NAME -f FILE ...``."""

    cmd: list[str]
    project: str
    file: Path
    env: dict[str, str] = field(default_factory=dict)

    def __call__(self, *args: str, check: bool = True, timeout: float = 600.0) -> subprocess.CompletedProcess:
        return sh(*self.cmd, "-p", self.project, "-f", str(self.file), *args, check=check, timeout=timeout,
                  env={**os.environ, **self.env})

    def container(self, service: str) -> str:
        return self("ps", "-a", "-q", service).stdout.strip()

    def left_behind(self) -> list[str]:
        """Every container, network and volume of the project still on the engine."""
        label = f"label=com.docker.compose.project={self.project}"
        out = []
        for kind, ls in (("container", ["ps", "-a"]), ("network", ["network", "ls"]), ("volume", ["volume", "ls"])):
            ids = sh("docker", *ls, "-q", "--filter", label, timeout=60).stdout.split()
            out += [f"{kind} {i}" for i in ids]
        return out


class FaultInjector(threading.Thread):
    """Follows the launcher's log (``tick N`` lines) and kills one agent's container at
    ``agent_tick``, then a router's container at ``router_tick``."""

    def __init__(self, launcher: str, agent: tuple[str, str], router: tuple[str, str], agent_tick: int,
                 router_tick: int) -> None:
        super().__init__(daemon=True)
        self.launcher, self.agent, self.router = launcher, agent, router
        self.agent_tick, self.router_tick = agent_tick, router_tick
        self.events: list[tuple[str, int, float]] = []  # (service, tick, monotonic time of the kill)

    def run(self) -> None:
        follow = subprocess.Popen(["docker", "logs", "-f", self.launcher], stdout=subprocess.PIPE,
                                  stderr=subprocess.STDOUT, text=True)
        try:
            todo = [(self.agent_tick, self.agent), (self.router_tick, self.router)]
            for line in follow.stdout:
                words = line.split()
                if len(words) >= 2 and words[-2] == "tick" and words[-1].isdigit():
                    while todo and int(words[-1]) >= todo[0][0]:
                        _, (service, container) = todo.pop(0)
                        sh("docker", "kill", container, check=False, timeout=60)
                        self.events.append((service, int(words[-1]), time.monotonic()))
                        log.info("killed %s's container at tick %s", service, words[-1])
                if not todo:
                    break
        finally:
            follow.kill()
            follow.wait()


def mcap_finalized(path: Path) -> dict | None:
    """The MCAP's message count if it has its summary (finalized), else None."""
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
    except Exception:  # a cut-off file raises in many ways; what matters is that it is not whole
        return None
    if summary is None or summary.statistics is None:
        return None
    return {"messages": summary.statistics.message_count, "channels": len(summary.channels)}


COMPARED = ("outcome", "closest_distance_m", "ticks", "reaction_time_s", "collider_visible_share",
            "collider_points_mean", "distance_series_m", "dead_agents")


@dataclass
class Report:
    figures: dict = field(default_factory=dict)
    problems: list[str] = field(default_factory=list)

    def say(self, text: str) -> None:
        print(f"compose run: {text}", flush=True)


def compose_run(args: argparse.Namespace, flags: list[str], report: Report) -> int:
    opts = run.options_from(run.build_parser(lock_down_default=True).parse_args(flags), hub="")
    cfg = opts.run
    cfg.log_dir.mkdir(parents=True)
    daemon = None
    if not daemon_up():
        daemon = start_daemon(cfg.log_dir / "dockerd.log", args.storage_driver)
        report.say(f"started dockerd (pid {daemon.pid}); it is stopped at the end")
    try:
        return _with_daemon(args, flags, cfg, report)
    finally:
        if daemon is not None:
            stop_daemon(daemon)


def _with_daemon(args: argparse.Namespace, flags: list[str], cfg, report: Report) -> int:
    from deploy.multihost import hosts
    from deploy.launch import table

    cmd = compose_command()
    if cmd is None:
        raise RuntimeError("neither `docker compose` nor `docker-compose` is installed (Debian: apt-get install "
                           "docker-compose)")
    base = base_image(args.base)
    build_s = build_image(base, cfg.log_dir / "build.log")
    report.figures.update(base=base, build_s=round(build_s, 1), compose=" ".join(cmd))
    report.say(f"image {IMAGE} built on {base} in {build_s:.0f} s ({' '.join(cmd)})")
    hosts_file = cfg.run_dir / "hosts.toml"
    hosts_file.write_text(local_hosts(table.connected_vids(cfg.params)))
    out = cfg.run_dir / "docker-compose.yml"
    deploy_argv = ["--hosts", str(hosts_file), *flags, "--compose", str(out)]
    if hosts.main(deploy_argv) != 0:
        raise RuntimeError(f"autocast deploy {' '.join(deploy_argv)} failed")
    dc = Compose(cmd, hosts.project_name(cfg), out, {"AUTOCAST_BASE_IMAGE": base})
    services = list(hosts.compose(cfg, hosts.load_hosts(hosts_file), out.parent)["services"])
    t0 = time.monotonic()
    try:
        dc("up", "-d", "--no-build", timeout=900)
        report.figures["up_s"] = round(time.monotonic() - t0, 1)
        report.say(f"{len(services)} containers up in {report.figures['up_s']:.1f} s: {' '.join(services)}")
        launcher = dc.container(hosts.LAUNCHER)
        injector = None
        if args.fault:
            vids = table.connected_vids(cfg.params)
            agent = table.agent_name(vids[1])  # on beta; gamma's router goes down with its agents
            router = ("router-gamma", dc.container("router-gamma"))
            injector = FaultInjector(launcher, (agent, dc.container(agent)), router, *args.fault_ticks)
            injector.start()
        code = int(sh("docker", "wait", launcher, timeout=RUN_TIMEOUT_S).stdout.strip())
        ended = time.monotonic()
        report.figures["run_s"] = round(ended - t0, 1)
        recorder = dc.container(table.RECORDER)
        finished = sh("timeout", str(RECORDER_EXIT_WAIT_S), "docker", "wait", recorder, check=False,
                      timeout=RECORDER_EXIT_WAIT_S + 30)
        report.figures["recorder_exit"] = finished.stdout.strip() or "stopped"
        dc("stop", "-t", str(STOP_GRACE_S), timeout=300)  # the recorder, if still up, finalizes on SIGTERM
        for service in services:
            logs = sh("docker", "logs", dc.container(service), check=False, timeout=120)
            (cfg.log_dir / f"{service}.log").write_text(logs.stdout + logs.stderr)
    finally:
        t1 = time.monotonic()
        dc("down", "--volumes", "--remove-orphans", "-t", str(STOP_GRACE_S), check=False, timeout=300)
        left = dc.left_behind()
        report.figures["down_s"] = round(time.monotonic() - t1, 1)
        if left:
            report.problems.append(f"left behind: {' '.join(left)}")
        gone = f"LEFT BEHIND {' '.join(left)}" if left else f"no container, network or volume of {dc.project} left"
        report.say(f"torn down in {report.figures['down_s']:.1f} s: {gone}")
    record = json.loads((cfg.run_dir / "outcome.json").read_text())
    report.figures["outcome"] = {k: record.get(k) for k in ("outcome", "failure", "closest_distance_m", "ticks",
                                                             "dead_agents", "wall_s")}
    mcap = mcap_finalized(cfg.mcap_path)
    report.figures["mcap"] = mcap
    report.say(f"launcher exit {code}; outcome.json: {json.dumps(report.figures['outcome'])}")
    report.say(f"{cfg.mcap_path}: " + (f"finalized, {mcap['messages']} messages on {mcap['channels']} channels"
                                        if mcap else "NOT finalized"))
    if mcap is None:
        report.problems.append(f"{cfg.mcap_path} is not finalized")
    if args.fault:
        return _check_fault(injector, code, ended, record, report)
    if not args.no_compare:
        _compare(flags, cfg, record, report)
    return run.EXIT_FAILED if report.problems else code


def _check_fault(injector: FaultInjector | None, code: int, ended: float, record: dict, report: Report) -> int:
    events = injector.events if injector is not None else []
    report.figures["faults"] = [{"killed": s, "tick": t} for s, t, _ in events]
    if len(events) < 2:
        report.problems.append(f"the run ended before both faults were injected ({report.figures['faults']})")
        return run.EXIT_FAILED
    after_s = ended - events[-1][2]
    report.figures["ended_after_router_s"] = round(after_s, 1)
    report.say(f"killed {events[0][0]} at tick {events[0][1]} and {events[1][0]} at tick {events[1][1]}; the run "
               f"ended {after_s:.1f} s later (exit {code}: {record.get('outcome') or record.get('failure')})")
    if after_s > FAULT_BOUND_S:
        report.problems.append(f"the run took {after_s:.0f} s after the router was killed "
                               f"(bound {FAULT_BOUND_S:.0f} s)")
    if code not in (run.EXIT_SAFE, run.EXIT_JUDGED, run.EXIT_FAILED):
        report.problems.append(f"exit {code}")
    report.figures["launcher_exit"] = code
    return run.EXIT_FAILED if report.problems else 0  # the fault case passed, whatever the run's judgement


def _compare(flags: list[str], cfg, record: dict, report: Report) -> None:
    """The same run with ``autocast run`` on this host: lock-step, so the same judgement."""
    one_id = f"{cfg.run_id}-onehost"
    res = sh(sys.executable, "-m", "deploy.cli", "run", *flags, "--run-id", one_id, "--out", str(cfg.run_dir.parent),
             "--json", check=False, timeout=RUN_TIMEOUT_S, cwd=str(REPO))
    lines = res.stdout.strip().splitlines()
    try:
        one = json.loads(lines[-1])
    except (IndexError, ValueError):
        report.problems.append(f"the one-host run printed no outcome (exit {res.returncode}): {res.stderr[-500:]}")
        return
    report.say(f"one host (autocast run, exit {res.returncode}): {lines[-2] if len(lines) > 1 else ''}")
    diff = {k: (record.get(k), one.get(k)) for k in COMPARED if record.get(k) != one.get(k)}
    report.figures["one_host"] = {k: one.get(k) for k in ("outcome", "closest_distance_m", "ticks", "wall_s")}
    report.figures["same_as_one_host"] = not diff
    if diff:
        report.problems.append(f"differs from the one-host run (compose, one host): {diff}")
        report.say(f"DIFFERENT from the one-host run: {diff}")
    else:
        report.say(f"same as the one-host run: {record['outcome']}, closest distance "
                   f"{record['closest_distance_m']:.3f} m, "
                   f"{record['ticks']} ticks ({', '.join(COMPARED[3:])} equal too)")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m deploy.multihost.compose_run", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="Every other flag is autocast deploy's (autocast run --help); locked down by "
                                        "default.")
    ap.add_argument("--fault", action="store_true", help="kill an agent's and then a router's container mid-run")
    ap.add_argument("--fault-ticks", type=int, nargs=2, default=(20, 40), metavar=("AGENT", "ROUTER"),
                    help="the ticks at which they are killed (default 20 40)")
    ap.add_argument("--no-compare", action="store_true", help="skip the one-host run")
    ap.add_argument("--base", default="", metavar="IMAGE",
                    help=f"the base image (default: {OFFICIAL_BASE} if present, else {DEBIAN_BASE}, made if missing)")
    ap.add_argument("--storage-driver", default="", help="for a dockerd this script starts (e.g. vfs)")
    args, flags = ap.parse_known_args(argv)
    logging.basicConfig(level="INFO", format="compose run: %(message)s")
    try:
        parsed = run.build_parser(lock_down_default=True).parse_args(flags)
        if parsed.run_id is None:
            flags += ["--run-id", time.strftime("compose-%Y%m%d-%H%M%S")]
        if parsed.sign:
            raise run.InputError("--sign: compose files do not carry the vehicles' V2X credentials")
        run.options_from(run.build_parser(lock_down_default=True).parse_args(flags), hub="")
    except run.InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return run.EXIT_BAD_INPUT
    signal.signal(signal.SIGTERM, signal.default_int_handler)  # tear down as on Ctrl-C
    report = Report()
    t0 = time.monotonic()
    try:
        code = compose_run(args, flags, report)
    except KeyboardInterrupt:
        report.say("interrupted; torn down")
        code = run.EXIT_INTERRUPTED
    except (RuntimeError, subprocess.TimeoutExpired, OSError) as exc:
        report.problems.append(str(exc))
        code = run.EXIT_FAILED
    report.figures["total_s"] = round(time.monotonic() - t0, 1)
    for problem in report.problems:
        report.say(f"FAILED: {problem}")
    print(json.dumps({"exit": code, **report.figures, "problems": report.problems}), flush=True)
    return code


if __name__ == "__main__":
    sys.exit(main())
