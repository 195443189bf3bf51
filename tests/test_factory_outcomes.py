"""Forked or started afresh, a run ends the same way: the same sweep (every scenario x
every scheme, 2 vehicles, 1 s of sim time) once with the warm process factory (each
launcher forked from the sweep's zygote, each of its processes from its own) and once
with ``AUTOCAST_FACTORY=popen`` (every process a new interpreter), compared run by run
on everything the world judged and measured (lock-step runs are deterministic)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from deploy.sweep import RESULTS
from vehicle_agent.__main__ import SCHEMES
from world_server.scenarios import SCENARIOS

UNSTABLE = ("run_id", "wall_s", "realtime_factor", "run_dir", "mcap", "malformed")  # differ between identical runs


def sweep(out: Path, factory: str) -> dict[str, dict]:
    spec = out.parent / f"{out.name}.toml"
    spec.write_text(f"scenarios = {json.dumps(list(SCENARIOS))}\nschemes = {json.dumps(list(SCHEMES))}\n"
                    "collider_speeds_kmh = [30]\ndeltas_s = [0]\nvehicles = [2]\nseeds = [0]\nduration_s = 1.0\n"
                    "agent_timeout_s = 300\nscans = \"none\"\n")
    res = subprocess.run([sys.executable, "-m", "deploy.cli", "sweep", "--file", str(spec), "--out", str(out),
                          "--jobs", "2", "--vehicle-budget", "4"], capture_output=True, text=True, timeout=900,
                         env=dict(os.environ, AUTOCAST_FACTORY=factory))
    assert res.returncode == 0, res.stderr[-3000:]
    records = [json.loads(line) for line in (out / RESULTS).read_text().splitlines()]
    assert len(records) == len(SCENARIOS) * len(SCHEMES) and all(r["status"] == "judged" for r in records)
    return {r["run_key"]: json.loads((out / "runs" / r["run_id"] / "outcome.json").read_text()) for r in records}


def test_every_scenario_and_scheme_ends_the_same_forked_or_not(tmp_path):
    forked, fresh = sweep(tmp_path / "forked", "fork"), sweep(tmp_path / "popen", "popen")
    assert forked.keys() == fresh.keys()
    for key in forked:
        a = {k: v for k, v in forked[key].items() if k not in UNSTABLE}
        b = {k: v for k, v in fresh[key].items() if k not in UNSTABLE}
        assert a == b, key
        assert a["ticks"] == 10 and not a["dead_agents"], key
