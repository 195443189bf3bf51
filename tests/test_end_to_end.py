"""The paper's headline, end to end: real processes (world, channel proxy, one agent per
vehicle, recorder) through ``autocast run``. In the red-light violation at delta 0 the
parked row and the truck at the junction hide the red-light runner: on its own LiDAR
alone the ego is unsafe; with AutoCast's sharing it passes safely (docs/scenarios.md)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest


def autocast_run(tmp_path, scheme: str) -> dict:
    proc = subprocess.run([sys.executable, "-m", "deploy.cli", "run", "--scenario", "red_light", "--vehicles", "5",
                           "--delta", "0", "--seed", "0", "--scheme", scheme, "--duration", "16", "--json",
                           "--out", str(tmp_path), "--scans", "none", "--log-level", "WARNING"],
                          capture_output=True, text=True, timeout=300)
    lines = proc.stdout.strip().splitlines()
    assert lines and lines[-1].startswith("{"), proc.stderr[-3000:]
    return json.loads(lines[-1]) | {"exit_code": proc.returncode}


@pytest.mark.heavy
def test_hidden_collider_single_is_unsafe_and_autocast_is_safe(tmp_path):
    single = autocast_run(tmp_path, "single")
    assert single["outcome"] in ("crash", "near_miss"), single
    assert single["exit_code"] == 1
    shared = autocast_run(tmp_path, "autocast")
    assert shared["outcome"] == "safe", shared
    assert shared["exit_code"] == 0 and shared["dead_agents"] == {}
    assert shared["closest_distance_m"] >= 2.0
    # sharing is what made the difference: the ego saw the collider in more ticks, earlier
    assert shared["visibility_source"] == "fused"
    assert shared["collider_visible_share"] > single["collider_visible_share"]
