"""One pinned configuration per scenario where the ego alone fails and AutoCast passes
safely, end to end through ``autocast run`` (real processes; the red-light violation is
tests/test_end_to_end.py). Both wait out the oncoming traffic behind the collider, so
the runs get 25 s of sim time (AutoCast's safe passages in these two configurations end at
18.3 and 18.9 s: `autocast run --scenario overtaking --vehicles 5 --collider-speed 30 --delta 0`)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest


def autocast_run(tmp_path, scenario: str, scheme: str) -> dict:
    proc = subprocess.run([sys.executable, "-m", "deploy.cli", "run", "--scenario", scenario, "--vehicles", "5",
                           "--collider-speed", "30", "--delta", "0", "--seed", "0", "--scheme", scheme,
                           "--duration", "25", "--json", "--out", str(tmp_path), "--scans", "none",
                           "--log-level", "WARNING"], capture_output=True, text=True, timeout=600)
    lines = proc.stdout.strip().splitlines()
    assert lines and lines[-1].startswith("{"), proc.stderr[-3000:]
    return json.loads(lines[-1])


@pytest.mark.heavy
@pytest.mark.parametrize("scenario", ["overtaking", "left_turn"])
def test_single_fails_and_autocast_passes_safely(tmp_path, scenario):
    single = autocast_run(tmp_path, scenario, "single")
    assert single["outcome"] in ("crash", "near_miss"), single
    shared = autocast_run(tmp_path, scenario, "autocast")
    assert shared["outcome"] == "safe", shared
    assert shared["closest_distance_m"] >= 2.0 and shared["dead_agents"] == {}
