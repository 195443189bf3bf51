"""Forked or started afresh, a run ends the same way: every scheme once and every
scenario twice (2 vehicles, 1 s of sim time), each run twice, once with the warm
process factory (the launcher forks its processes) and once with
``AUTOCAST_FACTORY=popen`` (every process a new interpreter), compared on everything
the world judged and measured (lock-step runs are deterministic). The sweep's tests
run their launchers forked from the sweep's own factory."""

from __future__ import annotations

import itertools
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from vehicle_agent.__main__ import SCHEMES
from world_server.scenarios import SCENARIOS

# differ between identical runs; the CPU figures come with forked runs only (processes.manager.RunCpu)
UNSTABLE = ("run_id", "wall_s", "realtime_factor", "run_dir", "mcap", "malformed", "cpu_ms_per_tick", "cores")
RUNS = list(zip(itertools.cycle(SCENARIOS), SCHEMES))  # every scheme, every scenario


def launch(out: Path, scenario: str, scheme: str, factory: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "deploy.cli", "run", "--scenario", scenario, "--scheme", scheme,
                             "--vehicles", "2", "--duration", "1", "--json", "--out", str(out), "--run-id",
                             f"{scenario}-{scheme}-{factory}", "--scans", "none", "--agent-timeout-s", "300"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            env=dict(os.environ, AUTOCAST_FACTORY=factory))


def test_the_runs_cover_every_scenario_and_scheme():
    assert {sc for sc, _ in RUNS} == set(SCENARIOS) and {s for _, s in RUNS} == set(SCHEMES)


@pytest.mark.heavy
@pytest.mark.parametrize(("scenario", "scheme"), RUNS)
def test_a_run_ends_the_same_forked_or_not(tmp_path, scenario, scheme):
    procs = {factory: launch(tmp_path, scenario, scheme, factory) for factory in ("fork", "popen")}  # both at once
    results = {}
    for factory, proc in procs.items():
        out, err = proc.communicate(timeout=600)
        assert proc.returncode in (0, 1), f"{scenario} {scheme} {factory}: {err[-3000:]}"
        results[factory] = json.loads(out.strip().splitlines()[-1])
    forked, fresh = ({k: v for k, v in results[f].items() if k not in UNSTABLE} for f in ("fork", "popen"))
    assert forked == fresh
    assert forked["ticks"] == 10 and not forked["dead_agents"]
