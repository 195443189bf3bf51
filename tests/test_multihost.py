"""Multi-host deployment: the hosts file, placement, the compose file, stopping through a
prefix, and one real run over network namespaces compared with the same run on one host.

The namespace test builds a private network (``deploy.multihost.netns.Lab``: a bridge namespace and
four host namespaces with their own 10.77.0.x addresses, nothing in the root namespace),
runs ``autocast deploy`` inside the first namespace with world and recorder there, the
channel proxy in the second and the agents in the third and fourth, each namespace with
its own Zenoh router, and checks that it is judged exactly as ``autocast run`` judges the
same scenario and seed on one host. A second does the same for a corridor of three
scheduler domains over three namespaces, each domain's agents on a host of their own. They
skip, saying why, where namespaces are unavailable.
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import pytest
from mcap.reader import make_reader

from deploy.launch import credentials, table
from deploy.multihost import hosts, netns
from deploy.multihost.hosts import Host, HostProcessManager, HostsFile, load_hosts, parse_hosts, place
from processes.manager import ProcSpec
from deploy.launch.run import InputError, LaunchOptions, options_from, build_parser
from protocol import keys
from tests.conftest import wait_until

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "deploy" / "hosts.example.toml"
COMPOSE = REPO / "deploy" / "docker-compose.yml"
RUN_FLAGS = ["--scenario", "left_turn", "--vehicles", "5", "--scheme", "autocast", "--seed", "0"]
COMPARED = ("outcome", "closest_distance_m", "ticks", "reaction_time_s", "collider_visible_share",
            "collider_points_mean", "distance_series_m", "dead_agents")


def options(tmp_path: Path, *flags: str) -> LaunchOptions:
    return options_from(build_parser().parse_args([*RUN_FLAGS, "--out", str(tmp_path), *flags]), hub="")


def host(name: str, address: str, **kw) -> dict:
    return {"name": name, "address": address, **kw}


# ---------------------------------------------------------------------------- hosts file and placement


def test_the_example_hosts_file_places_every_process_once(tmp_path):
    hf = load_hosts(EXAMPLE)
    placed = {spec.name: h.name for spec, h in place(options(tmp_path).run, hf)}
    assert placed == {"recorder": "alpha", "world": "alpha", "proxy": "beta", "agent0": "alpha",
                      "agent1": "beta", "agent2": "beta", "agent3": "gamma", "agent4": "gamma"}
    assert [h.prefix for h in hf.hosts] == [("ssh", "-o", "BatchMode=yes", f"autocast@10.0.0.{i}") for i in (1, 2, 3)]


def test_each_process_connects_to_its_own_hosts_router(tmp_path):
    hf = load_hosts(EXAMPLE)
    for spec, h in place(options(tmp_path).run, hf):
        assert spec.args[spec.args.index("--connect") + 1] == f"tcp/{h.address}:7447"
    routers = [hosts.router_spec(h, hf) for h in hf.hosts]
    assert [r.args for r in routers] == [
        ("--name", "alpha", "--listen", "tcp/10.0.0.1:7447"),
        ("--name", "beta", "--listen", "tcp/10.0.0.2:7447", "--connect", "tcp/10.0.0.1:7447"),
        ("--name", "gamma", "--listen", "tcp/10.0.0.3:7447", "--connect", "tcp/10.0.0.1:7447",
         "--connect", "tcp/10.0.0.2:7447")]


def test_a_command_runs_the_process_in_the_hosts_checkout_through_its_prefix():
    h = Host("b", "10.0.0.2", prefix=("ssh", "u@b"), workdir="/opt/a c", python="/opt/py", env=(("K", "v w"),))
    argv = hosts.command(h, ProcSpec("proxy", "channel_proxy", ("--seed", "3")))
    assert argv == ["ssh", "u@b", "cd '/opt/a c' && exec env PYTHONUNBUFFERED=1 'K=v w' /opt/py -m deploy.multihost.remote exec "
                                  "channel_proxy --seed 3"]


@pytest.mark.parametrize("data, field", [
    ({"host": []}, "no [[host]]"),
    ({"host": [host("a", "10.0.0.1", run=["world", "recorder", "proxy"], agents="rest", colour="red")]}, "colour"),
    ({"host": [host("a", "10.0.0.1", run=["world", "recorder"], agents="rest"), host("a", "10.0.0.2")]}, "used twice"),
    ({"host": [host("a", "10.0.0.1", run=["world", "recorder", "proxy"], agents="rest", port=0)]}, "port"),
    ({"host": [host("a", "10.0.0.1", run=["world", "recorder"], agents="rest"),
               host("b", "10.0.0.1", run=["proxy"])]}, "two hosts' routers"),
    ({"host": [host("a", "10.0.0.1", run=["world", "lidar"])]}, "run"),
    ({"host": [host("a", "10.0.0.1", run=["world", "recorder"], agents="some")]}, "agents"),
    ({"host": [{"name": "a", "run": ["world"]}]}, "address"),
])
def test_a_bad_hosts_file_is_refused_naming_the_field(data, field):
    with pytest.raises(InputError, match=re.escape(field)):
        parse_hosts(data)


@pytest.mark.parametrize("entries, field", [
    ([host("a", "1", run=["world", "recorder", "proxy"], agents=3)], "vehicles 3, 4 are on no host"),
    ([host("a", "1", run=["world", "recorder", "proxy"], agents=6)], "6 asked, 5 left"),
    ([host("a", "1", run=["world", "recorder", "proxy"], agents=[0, 9])], "vehicle 9 is not a connected vehicle"),
    ([host("a", "1", run=["world", "recorder", "proxy"], agents=[0]), host("b", "2", agents=[0, 1])],
     "vehicle 0 is on a and b"),
    ([host("a", "1", run=["world", "recorder", "proxy"], agents="rest"), host("b", "2", agents="rest")],
     "one host at most"),
    ([host("a", "1", run=["world", "recorder"], agents="rest")], "proxy: no host runs it"),
    ([host("a", "1", run=["world", "recorder", "proxy"], agents="rest"), host("b", "2", run=["world"])],
     "world: on a, b"),
])
def test_a_placement_that_misses_or_repeats_a_process_is_refused(tmp_path, entries, field):
    with pytest.raises(InputError, match=re.escape(field)):
        place(options(tmp_path).run, parse_hosts({"host": entries}))


def test_no_proxy_host_is_needed_when_the_scheme_shares_nothing(tmp_path):
    hf = parse_hosts({"host": [host("a", "1", run=["world", "recorder"], agents="rest")]})
    names = [spec.name for spec, _ in place(options(tmp_path, "--scheme", "single").run, hf)]
    assert table.PROXY not in names and len(names) == 7


CORRIDOR_FLAGS = ["--scenario", "corridor3x", "--vehicles", "5", "--seed", "1"]
# corridor3x, 5 vehicles, seed 1: the left turn's ego (0) and truck (1) start at J1 (domain
# 1), the red light's ego (2) and truck (3) at J0 (domain 0), background car 4 at J2 (domain 2)
START_DOMAIN = {0: 1, 1: 1, 2: 0, 3: 0, 4: 2}  # vehicle id -> the domain it starts in


def test_a_map_of_several_domains_puts_each_domains_vehicles_on_a_host_of_its_own(tmp_path):
    """No host names agents: domain d's vehicles, by where they start, go on the d-th host."""
    hf = parse_hosts({"host": [host("a", "1", run=["world", "recorder"]), host("b", "2", run=["proxy"]),
                               host("c", "3"), host("d", "4")]})
    cfg = options(tmp_path, *CORRIDOR_FLAGS).run
    placed = {spec.name: h.name for spec, h in place(cfg, hf)}
    assert {n: h for n, h in placed.items() if n.startswith("agent")} == {f"agent{v}": "abc"[d]
                                                                         for v, d in START_DOMAIN.items()}
    plan = hosts.plan(hf, place(cfg, hf)).splitlines()  # what --dry-run prints
    assert [line.split("; ")[1] for line in plan[:4]] == [
        "runs recorder world agent2 agent3", "runs proxy agent0 agent1", "runs agent4", "runs nothing else"]
    start = hosts.start_domains(cfg.params)
    assert start == hosts.StartDomains(3, tuple(START_DOMAIN.items()))


@pytest.mark.parametrize("entries, placed", [
    ([host("a", "1", run=["world", "recorder", "proxy"], domains=[1]), host("b", "2", domains=[0, 2])],
     {"agent0": "a", "agent1": "a", "agent2": "b", "agent3": "b", "agent4": "b"}),
    ([host("a", "1", run=["world", "recorder", "proxy"], domains=[1], agents=[3]), host("b", "2", agents="rest")],
     {"agent0": "a", "agent1": "a", "agent2": "b", "agent3": "a", "agent4": "b"}),  # a vehicle list comes first
])
def test_a_hosts_file_may_place_the_agents_by_domain(tmp_path, entries, placed):
    hf = parse_hosts({"host": entries})
    got = {spec.name: h.name for spec, h in place(options(tmp_path, *CORRIDOR_FLAGS).run, hf)}
    assert {n: h for n, h in got.items() if n.startswith("agent")} == placed


@pytest.mark.parametrize("flags, entries, field", [
    (CORRIDOR_FLAGS, [host("a", "1", run=["world", "recorder", "proxy"]), host("b", "2")],
     "the map has 3 scheduler domains and the file 2 hosts"),
    (CORRIDOR_FLAGS, [host("a", "1", run=["world", "recorder", "proxy"], domains=[0, 3], agents="rest")],
     "domains: 3 is not a scheduler domain of this run's map (0-2)"),
    (CORRIDOR_FLAGS, [host("a", "1", run=["world", "recorder", "proxy"], domains=[0, 1]),
                      host("b", "2", domains=[1, 2])], "domain 1 is on a and b"),
    ([], [host("a", "1", run=["world", "recorder", "proxy"], domains=[1], agents="rest")],
     "domains: 1 is not a scheduler domain of this run's map (0-0)"),
    ([], [host("a", "1", run=["world", "recorder", "proxy"]), host("b", "2")], "vehicles 0, 1, 2, 3, 4 are on no host"),
])
def test_a_placement_by_domain_that_cannot_be_is_refused(tmp_path, flags, entries, field):
    with pytest.raises(InputError, match=re.escape(field)):
        place(options(tmp_path, *flags).run, parse_hosts({"host": entries}))


def test_a_map_of_several_domains_is_deployed_unsigned(tmp_path, capsys):
    """The agents refuse to sign there (docs/domains.md): unsigned by default with a note,
    and an explicit --sign is refused before anything starts."""
    flags = ["--hosts", str(EXAMPLE), *CORRIDOR_FLAGS, "--out", str(tmp_path), "--dry-run"]
    assert hosts.main(flags) == 0
    out, err = capsys.readouterr()
    assert "note: a map of several scheduler domains runs unsigned" in err
    assert "  agent0: " in out and "--credentials" not in out and "--authority" not in out
    assert hosts.main([*flags, "--sign"]) == 2
    assert "error: sign: a map of several scheduler domains runs unsigned" in capsys.readouterr().err
    assert hosts.main(["--hosts", str(EXAMPLE), *RUN_FLAGS, "--out", str(tmp_path), "--dry-run"]) == 0
    assert "--credentials" in capsys.readouterr().out  # one domain: signed, as before


def test_the_cli_refuses_a_bad_hosts_file_before_starting_anything(tmp_path):
    bad = tmp_path / "hosts.toml"
    bad.write_text('[[host]]\nname = "a"\naddress = "10.0.0.1"\nrun = ["world"]\n')
    out = subprocess.run([sys.executable, "-m", "deploy.cli", "deploy", "--hosts", str(bad), *RUN_FLAGS,
                          "--out", str(tmp_path / "runs")], capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "error: hosts: proxy: no host runs it" in out.stderr
    assert not (tmp_path / "runs").exists()


def test_dry_run_prints_every_hosts_router_and_command(tmp_path, capsys):
    assert hosts.main(["--hosts", str(EXAMPLE), *RUN_FLAGS, "--out", str(tmp_path), "--dry-run"]) == 0
    out = capsys.readouterr().out
    assert "host beta: router tcp/10.0.0.2:7447 and tls/10.0.0.2:7448 (connects to tls/10.0.0.1:7448); " \
           "runs proxy agent1 agent2" in out  # locked down: routers link over mutual TLS
    assert "  world: ssh -o BatchMode=yes autocast@10.0.0.1 'cd /opt/autocast-py && exec env" in out
    assert not list(tmp_path.iterdir())


# ---------------------------------------------------------------------------- docker compose (run: tests/test_compose.py)


def test_compose_refuses_to_sign_and_is_locked_down(tmp_path, capsys):
    """A signed run asked for is refused, not run unsigned; the file is locked down by
    default, its credentials beside the run's outputs on the host, not in the image."""
    out = tmp_path / "compose.yml"
    flags = ["--hosts", str(EXAMPLE), *RUN_FLAGS, "--out", str(tmp_path), "--run-id", "c", "--compose", str(out)]
    assert hosts.main([*flags, "--sign"]) == 2 and not out.exists()
    assert "--sign" in capsys.readouterr().err
    assert hosts.main(flags) == 0 and out.exists()
    assert (tmp_path / "c" / "credentials" / "router-beta.zenoh.json5").exists()
    assert "/run/secrets/zenoh-users.txt" in (tmp_path / "c" / "credentials" / "router-beta.zenoh.json5").read_text()
    assert hosts.main(flags) == 0  # made again: a compose file only describes the run


def test_the_compose_file_has_a_service_per_process_and_a_router_per_host(tmp_path):
    yaml = pytest.importorskip("yaml")
    checked_in = yaml.safe_load(COMPOSE.read_text())
    hf = load_hosts(EXAMPLE)
    cfg = options(tmp_path, "--run-id", "compose", "--lock-down").run
    generated = yaml.safe_load(hosts.compose_text(cfg, hf, "test"))
    assert generated == hosts.compose(cfg, hf)  # the emitter is YAML
    services = checked_in["services"]
    assert services.keys() == generated["services"].keys()
    for name, s in generated["services"].items():  # the checked-in file is what the launcher makes today
        assert services[name]["command"] == s["command"], name
    routers = {f"router-{h.name}": h for h in hf.hosts}
    procs = [n for n in services if n not in routers]
    assert sorted(procs) == sorted(["launcher", "recorder", "world", "proxy"] + [f"agent{v}" for v in range(5)])
    for name, h in routers.items():
        cmd = services[name]["command"]
        assert cmd[:3] == ["python", "-m", "deploy.multihost.router"] and f"tcp/0.0.0.0:{h.port}" in cmd
        earlier = [o for o in hf.hosts[:hf.hosts.index(h)]]
        assert [cmd[i + 1] for i, w in enumerate(cmd) if w == "--connect"] == [o.tls_endpoint for o in earlier]
        assert services[name]["ports"] == [f"{h.port}:{h.port}", f"{h.port + 1}:{h.port + 1}"]
    for name in procs:
        s = services[name]
        (router,) = s["depends_on"]
        assert router == f"router-{s['labels']['autocast.host']}"
        assert s["command"][s["command"].index("--connect") + 1] == f"tcp/{router}:7447"
        assert s["command"][s["command"].index("--zenoh-config") + 1] == f"/run/secrets/{name}.zenoh.json5"
        assert s["secrets"] == [f"{name}.zenoh.json5"]  # its own credentials only
        assert s["build"]["context"] == ".." and s["build"]["dockerfile"] == "deploy/Dockerfile"
    assert "launcher" in services["world"]["command"][services["world"]["command"].index("--wait-for") + 1:]
    assert services["launcher"]["labels"]["autocast.host"] == "alpha"  # the recorder's host: outputs together
    assert (REPO / "deploy" / "Dockerfile").exists()


# ---------------------------------------------------------------------------- stopping through a prefix


def test_a_process_is_stopped_through_its_hosts_prefix(tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    here = Host("here", "127.0.0.1", port=port)  # prefix "sh -c": this machine
    hf = HostsFile((here,))
    procs = HostProcessManager(tmp_path, {here.router: here})
    proc = procs.start(hosts.router_spec(here, hf))
    try:
        assert procs.remote_pid(here.router) == proc.pid  # sh, env and the wrapper all exec: one pid
        deadline = time.monotonic() + 30
        while "listening on" not in (tmp_path / f"{here.router}.log").read_text():
            assert time.monotonic() < deadline and proc.poll() is None, (tmp_path / f"{here.router}.log").read_text()
            time.sleep(0.05)
        procs.stop([here.router], grace_s=60)
        assert proc.returncode == 0  # SIGINT through the prefix: a SIGKILL would be -9
    finally:
        procs.stop_all(0.5)


# ---------------------------------------------------------------------------- the real thing, over namespaces


def _launch(argv: list[str], log: Path) -> subprocess.Popen:
    with open(log, "w") as err:
        return subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=err, text=True, start_new_session=True)


def _result(proc: subprocess.Popen, log: Path, timeout: float) -> dict:
    try:
        stdout, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()
        pytest.fail(f"{proc.args[:6]} did not finish in {timeout} s:\n{log.read_text()[-3000:]}")
    assert proc.returncode in (0, 1), log.read_text()[-3000:]
    return json.loads(stdout.strip().splitlines()[-1])


def _processes_in(ns: str) -> set[tuple[str, str, str]]:
    """(module, vid, --connect endpoint) of every ``python -m`` process in the namespace."""
    out = set()
    for pid in subprocess.run(["ip", "netns", "pids", ns], capture_output=True, text=True).stdout.split():
        try:
            argv = Path(f"/proc/{pid}/cmdline").read_bytes().decode().split("\0")
        except OSError:
            continue
        if "-m" in argv and argv[argv.index("-m") + 1] != "deploy.multihost.remote":
            def flag(name: str) -> str:
                return argv[argv.index(name) + 1] if name in argv else ""
            out.add((argv[argv.index("-m") + 1], flag("--vid"), flag("--listen") or flag("--connect")))
    return out


def _deploy_beside_one_host(tmp_path: Path, lab: netns.Lab, hosts_toml: str, flags: list[str]
                            ) -> tuple[dict, dict, dict[str, set]]:
    """``autocast deploy`` over the lab and ``autocast run`` on this host, the same flags:
    their records, and who ran in each host's namespace while the deploy ran."""
    hosts_file = tmp_path / "hosts.toml"
    hosts_file.write_text(hosts_toml)
    seen: dict[str, set] = {}
    # Both at once (the same code, less wall time); the second starts once the first has
    # warmed the numba caches (the namespaces share this machine's files) and skips that.
    deadline = time.monotonic() + 600  # a safety net: measured 34-125 s (left_turn), 21-28 s (corridor3x) a test
    single = _launch([sys.executable, "-m", "deploy.cli", "run", *flags, "--run-id", "single"], tmp_path / "single.err")
    while "caches warm" not in (tmp_path / "single.err").read_text() and single.poll() is None:
        assert time.monotonic() < deadline, "the single-host run never warmed its caches"
        time.sleep(0.1)
    multi = _launch(netns.deploy_argv(lab, hosts_file, [*flags, "--run-id", "multi", "--no-warm-up"]),
                    tmp_path / "multi.err")
    while multi.poll() is None and time.monotonic() < deadline:  # who runs where, while it runs
        for h in lab.hosts:
            seen.setdefault(h.name, set()).update(_processes_in(h.ns))
        time.sleep(0.5)
    many = _result(multi, tmp_path / "multi.err", 10)
    one = _result(single, tmp_path / "single.err", max(10.0, deadline - time.monotonic()))
    return many, one, seen


def _check_lab_run(lab_names: list[str], left: dict, placed: dict[str, str], addresses: dict[str, str],
                   seen: dict[str, set], logs: Path) -> None:
    """The lab is gone and nothing was left in it; each process ran in its host's
    namespace, connected to that namespace's own router; the routers formed a full mesh."""
    listed = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    assert not any(ns in listed for ns in lab_names), "the lab's namespaces were not deleted"
    assert left == {}, f"processes left in the namespaces after autocast deploy exited: {left}"
    expected = {h: {("deploy.multihost.router", "", f"tcp/{a}:7447")} for h, a in addresses.items()}
    expected["h0"].add(("deploy.cli", "", ""))  # the launcher
    module = {"recorder": "deploy.record.recorder", "world": "world_server", "proxy": "channel_proxy"}
    for name, h in placed.items():
        vid = name[len("agent"):] if name.startswith("agent") else ""
        expected[h].add((module.get(name, "vehicle_agent"), vid, f"tcp/{addresses[h]}:7447"))
    assert seen == expected
    for h in addresses:  # every router was linked to the others
        assert f"linked to {len(addresses) - 1} other router(s)" in (logs / f"router-{h}.log").read_text()


@pytest.mark.heavy
def test_deploy_over_network_namespaces_is_judged_as_the_single_host_run(tmp_path):
    reason = netns.unavailable()
    if reason:
        pytest.skip(f"network namespaces unavailable: {reason}")
    out = tmp_path / "runs"
    with netns.Lab(4) as lab:
        many, one, seen = _deploy_beside_one_host(tmp_path, lab, lab.hosts_toml(), [*RUN_FLAGS, "--json", "--out",
                                                                                     str(out)])
        left = lab.leftovers()
        names = [h.ns for h in lab.hosts] + [lab.switch]
        addresses = {h.name: h.address for h in lab.hosts}
    placed = {"recorder": "h0", "world": "h0", "proxy": "h1", "agent0": "h2", "agent1": "h2",
              "agent2": "h3", "agent3": "h3", "agent4": "h3"}
    _check_lab_run(names, left, placed, addresses, seen, out / "multi" / "logs")
    assert {k: many[k] for k in COMPARED} == {k: one[k] for k in COMPARED}
    assert many["hosts"] == placed


@pytest.mark.heavy
def test_a_corridor_of_three_domains_over_three_namespaces_is_judged_as_on_one_host(tmp_path):
    """corridor3x (three junctions, each a scheduler domain; the left turn's event at J1,
    the red light's at J0), 5 vehicles for 3 s: the hosts file places no agent, so each
    domain's vehicles run in a namespace of their own (domain 0's with the world and
    recorder on h0, domain 1's with the proxy on h1, domain 2's on h2). Lock-step, the
    run and each event are judged as the same run on one host."""
    reason = netns.unavailable()
    if reason:
        pytest.skip(f"network namespaces unavailable: {reason}")
    out = tmp_path / "runs"
    flags = [*CORRIDOR_FLAGS, "--scheme", "autocast", "--duration", "3", "--json", "--out", str(out)]
    with netns.Lab(3) as lab:
        many, one, seen = _deploy_beside_one_host(tmp_path, lab, lab.hosts_toml(by_domain=True), flags)
        left = lab.leftovers()
        names = [h.ns for h in lab.hosts] + [lab.switch]
        addresses = {h.name: h.address for h in lab.hosts}
    placed = {"recorder": "h0", "world": "h0", "proxy": "h1"} | {f"agent{v}": f"h{d}" for v, d in START_DOMAIN.items()}
    _check_lab_run(names, left, placed, addresses, seen, out / "multi" / "logs")
    assert many["hosts"] == placed
    assert one["mode"] == many["mode"] == "lockstep" and one["ticks"] == 30
    assert [e["event"] for e in one["events"]] == ["left_turn@J1", "red_light@J0"]
    assert {k: many[k] for k in (*COMPARED, "events")} == {k: one[k] for k in (*COMPARED, "events")}


def test_a_router_that_cannot_start_fails_the_run_at_once(tmp_path):
    """Host b's address is not on this machine (TEST-NET-1): its router cannot listen."""
    ports = []
    for _ in range(3):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            ports.append(s.getsockname()[1])
    hosts_file = tmp_path / "hosts.toml"  # locked down (the default): a's routers' TLS port is a free one too
    hosts_file.write_text(f'[defaults]\nwarm_up = false\n'
                          f'[[host]]\nname = "a"\naddress = "127.0.0.1"\nport = {ports[0]}\ntls_port = {ports[2]}\n'
                          f'run = ["world", "recorder", "proxy"]\nagents = "rest"\n'
                          f'[[host]]\nname = "b"\naddress = "192.0.2.1"\nport = {ports[1]}\n')
    out = subprocess.run([sys.executable, "-m", "deploy.cli", "deploy", "--hosts", str(hosts_file), *RUN_FLAGS,
                          "--no-warm-up", "--json", "--out", str(tmp_path / "runs"), "--run-id", "r"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 3, out.stderr
    record = json.loads(out.stdout.strip().splitlines()[-1])
    # at once: the router's exit, not the mesh check's timeout ("not linked after ...")
    assert record["outcome"] is None and record["failure"].startswith("router-b exited")
    left = subprocess.run(["pgrep", "-f", f"--listen tcp/127.0.0.1:{ports[0]}"], capture_output=True, text=True)
    assert left.stdout == "", "host a's router was left running"


def _pid_in(ns: str, module: str) -> int:
    for pid in subprocess.run(["ip", "netns", "pids", ns], capture_output=True, text=True).stdout.split():
        try:
            argv = Path(f"/proc/{pid}/cmdline").read_bytes().decode().split("\0")
        except OSError:
            continue
        if "-m" in argv and argv[argv.index("-m") + 1] == module:
            return int(pid)
    raise AssertionError(f"no {module} process in {ns}")


@pytest.mark.heavy
def test_a_hosts_router_killed_mid_run_fails_the_run_and_leaves_nothing(tmp_path):
    """h1's router (the proxy's host) is SIGKILLed while the run is under way: agent 2
    hangs at tick 10 and may take 600 s to be declared dead, so the run cannot end on its
    own first. The launcher fails the run (exit 3) for the dead router, not after its
    wall-clock limit; the MCAP on h0 is finalized; nothing is left in any namespace."""
    reason = netns.unavailable()
    if reason:
        pytest.skip(f"network namespaces unavailable: {reason}")
    out = tmp_path / "runs"
    with netns.Lab(4) as lab:
        hosts_file = tmp_path / "hosts.toml"
        hosts_file.write_text(lab.hosts_toml())
        err = tmp_path / "deploy.err"
        with open(err, "w") as f:
            proc = subprocess.Popen(netns.deploy_argv(lab, hosts_file, [*RUN_FLAGS, "--json", "--out", str(out),
                                                                        "--run-id", "cut", "--agent-timeout-s", "600"]),
                                    stdout=subprocess.PIPE, stderr=f, text=True, start_new_session=True,
                                    env=dict(os.environ, AUTOCAST_FAULTS="agent2:hang@10"))
        try:
            world_log = out / "cut" / "logs" / "world.log"
            wait_until(lambda: world_log.exists() and "agents up" in world_log.read_text() or proc.poll() is not None,
                       "the world started ticking", timeout_s=240)
            assert proc.poll() is None, err.read_text()[-3000:]
            os.kill(_pid_in(lab.hosts[1].ns, "deploy.multihost.router"), signal.SIGKILL)
            stdout, _ = proc.communicate(timeout=240)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
        left = lab.leftovers()
    assert proc.returncode == 3, err.read_text()[-3000:]
    record = json.loads(stdout.strip().splitlines()[-1])
    assert record["outcome"] is None and record["failure"].startswith("router-h1 exited (code -9)"), record
    with open(out / "cut" / "run.mcap", "rb") as f:
        assert make_reader(f).get_summary() is not None
    assert left == {}, f"processes left in the namespaces: {left}"


# ---------------------------------------------------------------------------- the lock-down, over namespaces


def _in_ns(ns: str, *args: str) -> subprocess.Popen:
    return subprocess.Popen(["ip", "netns", "exec", ns, sys.executable, "-m", "tests.acl_probe", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
                            start_new_session=True)


def _lines(proc: subprocess.Popen, timeout: float = 120.0) -> list[str]:
    out, err = proc.communicate(timeout=timeout)  # a safety net: each probe ends on an event
    assert proc.returncode == 0, err[-3000:]
    return out.splitlines()


def test_a_locked_down_network_admits_only_the_runs_processes_each_on_its_own_keys(tmp_path):
    """Two hosts (namespaces), each with its router as ``autocast deploy --lock-down``
    configures it (the run's passwords, its ACL). A session with no password, or a wrong
    one, cannot join either router. Agent 2's own session, on h1, puts a command on
    vehicle 1's key and then on its own: the world's session on h0 gets its own and
    never vehicle 1's (the same link carried both, the forged one first)."""
    reason = netns.unavailable()
    if reason:
        pytest.skip(f"network namespaces unavailable: {reason}")
    cfg = options(tmp_path, "--lock-down", "--run-id", "acl").run
    with netns.Lab(2) as lab:
        hf = parse_hosts(tomllib.loads(lab.hosts_toml()))
        written = credentials.lock_down(cfg, {h.router: h.address for h in hf.hosts})
        procs = HostProcessManager(tmp_path / "logs", {h.router: h for h in hf.hosts})
        try:
            for h in hf.hosts:
                procs.start(hosts.router_spec(h, hf, written[h.router]))
            logs = [tmp_path / "logs" / f"{h.router}.log" for h in hf.hosts]
            wait_until(lambda: all("linked to 1 other router(s)" in p.read_text() for p in logs if p.exists())
                       and all(p.exists() for p in logs), "the two routers authenticated each other", 120)
            h0, h1 = hf.hosts
            wrong = tmp_path / "wrong.json5"
            wrong.write_text(json.dumps({"transport": {"auth": {"usrpwd": {"user": "agent2", "password": "guess"}}}}))
            strangers = [_in_ns(lab.hosts[1].ns, "join", h1.endpoint), _in_ns(lab.hosts[1].ns, "join", h0.endpoint),
                         _in_ns(lab.hosts[0].ns, "join", h0.endpoint, str(wrong))]
            member = _in_ns(lab.hosts[1].ns, "join", h1.endpoint, str(written["agent2"]))
            world = _in_ns(lab.hosts[0].ns, "listen", h0.endpoint, str(written["world"]), keys.cmd("acl", "*"),
                           keys.cmd("acl", 2))
            assert world.stdout.readline().strip() == "subscribed"
            agent = _in_ns(lab.hosts[1].ns, "put", h1.endpoint, str(written["agent2"]), keys.cmd("acl", 1),
                           keys.cmd("acl", 2))
            assert _lines(agent) == ["put"]
            assert _lines(world) == [f"got {keys.cmd('acl', 2)}"]
            assert _lines(member) == ["joined"]
            for s in strangers:
                (line,) = _lines(s)
                assert line.startswith("refused"), line
        finally:
            procs.stop_all(3.0)
