"""docker compose: the file ``autocast deploy --compose`` writes, checked by docker compose
itself, and the end-to-end run in containers (``deploy.multihost.compose_run``).

The end-to-end run builds an image and starts 17 containers; it takes minutes (the
figures are in docs/multihost.md), so it runs only with ``AUTOCAST_COMPOSE_TEST=1``.
Without it CI checks the generated file with ``docker compose config`` (or
``docker-compose config``), and skips that where neither is installed.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from deploy.multihost import compose_launcher, compose_run, hosts
from deploy.launch import run, table
from protocol.messages import Outcome

REPO = Path(__file__).resolve().parents[1]
FLAGS = ["--scenario", "left_turn", "--vehicles", "10", "--scheme", "autocast", "--seed", "0"]


def write_compose(tmp_path: Path, hosts_text: str, *flags: str) -> Path:
    hosts_file = tmp_path / "hosts.toml"
    hosts_file.write_text(hosts_text)
    out = tmp_path / "docker-compose.yml"
    assert hosts.main(["--hosts", str(hosts_file), *FLAGS, "--out", str(tmp_path / "runs"), "--run-id", "c",
                       *flags, "--compose", str(out)]) == 0
    return out


def local_compose(tmp_path: Path, *flags: str) -> Path:
    return write_compose(tmp_path, compose_run.local_hosts(tuple(range(10))), *flags)


@pytest.mark.parametrize("example", [False, True], ids=["one-engine", "hosts-example"])
def test_docker_compose_takes_the_generated_file(tmp_path, example):
    cmd = compose_run.compose_command()
    if cmd is None:
        pytest.skip("neither `docker compose` nor `docker-compose` is installed")
    out = (write_compose(tmp_path, (REPO / "deploy" / "hosts.example.toml").read_text()) if example
           else local_compose(tmp_path))
    res = subprocess.run([*cmd, "-p", "autocast-c", "-f", str(out), "config", "-q"], capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 0, res.stderr


def test_each_container_gets_only_its_own_credentials(tmp_path):
    yaml = pytest.importorskip("yaml")
    project = yaml.safe_load(local_compose(tmp_path).read_text())
    services, secrets = project["services"], project["secrets"]
    assert set(services) == {"router-alpha", "router-beta", "router-gamma", "launcher", "recorder", "world", "proxy",
                             *(f"agent{v}" for v in range(10))}
    creds = tmp_path / "runs" / "c" / "credentials"
    for name, s in secrets.items():  # relative to the compose file, on the host
        assert (tmp_path / s["file"]).resolve() == creds / name and (creds / name).exists()
    for name, s in services.items():
        if name.startswith("router-"):
            assert s["secrets"] == ["zenoh-users.txt", f"{name}.zenoh.json5", "ca.pem", f"{name}.tls.pem",
                                    f"{name}.tls.key"]
            assert "ports" not in s  # one engine: the routers meet on the compose network
        else:
            assert s["secrets"] == [f"{name}.zenoh.json5"]
    router = json.loads((creds / "router-gamma.zenoh.json5").read_text())
    assert router["transport"]["link"]["tls"]["enable_mtls"] is True
    assert router["transport"]["link"]["tls"]["listen_private_key"] == "/run/secrets/router-gamma.tls.key"
    cmd = services["router-gamma"]["command"]
    assert [cmd[i + 1] for i, w in enumerate(cmd) if w == "--connect"] == ["tls/router-alpha:7448",
                                                                             "tls/router-beta:7448"]
    for name in ("recorder", "launcher"):  # they write the run's outputs; the credentials beside them stay hidden
        assert services[name]["volumes"] == ["./runs/c:/app/runs/c"]
        assert services[name]["tmpfs"] == ["/app/runs/c/credentials"]
    assert not any("volumes" in s for n, s in services.items() if n not in ("recorder", "launcher"))


def test_the_credentials_are_not_in_the_image_context():
    """The build context is what git would commit; runs/ (outputs and credentials) is ignored."""
    res = subprocess.run(["git", "-C", str(REPO), "check-ignore", "-q", "runs/x/credentials/agent0.zenoh.json5"])
    assert res.returncode == 0


def test_the_launcher_records_as_autocast_run(tmp_path):
    base = {"scheme": "single", "scenario": "left_turn", "vehicles": 10, "seed": 0, "hosts": {"recorder": "alpha"}}
    judged = Outcome(152, 15.2, {"outcome": "near_miss", "closest_distance_m": 0.33, "ticks": 120})
    code, record = compose_launcher.record_of(judged, None, base, tmp_path, stopped=False)
    assert code == run.EXIT_JUDGED and record["outcome"] == "near_miss" and record["scheme"] == "single"
    assert record["mcap"] == f"alpha:{tmp_path / 'run.mcap'}"  # not on the launcher's host (yet)
    code, record = compose_launcher.record_of(Outcome(1, 0.1, {"outcome": "safe"}), None, base, tmp_path, False)
    assert code == run.EXIT_SAFE
    code, record = compose_launcher.record_of(judged, "a host's router is gone", base, tmp_path, stopped=False)
    assert code == run.EXIT_FAILED and record["outcome"] is None and record["failure"] == "a host's router is gone"
    code, record = compose_launcher.record_of(Outcome(9, 0.9, {"outcome": None, "failure": "stopped at tick 9"}),
                                              None, base, tmp_path, stopped=False)
    assert code == run.EXIT_FAILED and record["failure"] == "stopped at tick 9"  # nothing judged
    code, record = compose_launcher.record_of(None, "stopped", base, tmp_path, stopped=True)
    assert code == run.EXIT_INTERRUPTED and record["interrupted"] is True


def test_the_local_hosts_place_every_process(tmp_path):
    hf = hosts.parse_hosts(__import__("tomllib").loads(compose_run.local_hosts(tuple(range(10)))))
    cfg = run.options_from(run.build_parser().parse_args([*FLAGS, "--out", str(tmp_path)]), hub="").run
    placed = {spec.name: h.name for spec, h in hosts.place(cfg, hf)}
    assert placed[table.WORLD] == placed[table.RECORDER] == placed["agent0"] == "alpha"
    assert sorted(placed.values()).count("beta") == 1 + 4 and sorted(placed.values()).count("gamma") == 5


@pytest.mark.heavy
@pytest.mark.skipif(os.environ.get("AUTOCAST_COMPOSE_TEST") != "1",
                    reason="the run in containers takes minutes (docs/multihost.md); set AUTOCAST_COMPOSE_TEST=1")
@pytest.mark.parametrize("scheme", ["single", "autocast"])
def test_a_run_in_containers_is_judged_as_on_one_host(tmp_path, scheme):
    flags = ["--scenario", "left_turn", "--vehicles", "10", "--seed", "0", "--scheme", scheme]
    res = subprocess.run([sys.executable, "-m", "deploy.multihost.compose_run", *flags, "--out", str(tmp_path)],
                         capture_output=True, text=True, cwd=REPO, timeout=3600)
    summary = json.loads(res.stdout.strip().splitlines()[-1])
    assert summary["problems"] == [] and summary["same_as_one_host"] is True, res.stdout
    assert res.returncode == (0 if summary["outcome"]["outcome"] == "safe" else 1)
