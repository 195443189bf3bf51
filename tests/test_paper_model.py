"""The paper's density result under its own model, end to end (``--model paper``,
docs/models.md): in the red-light violation at 40 vehicles the channel carries a small
share of what the vehicles offer, a receiver keeps nothing between intervals, and
Agnostic's random order gets the collider to the ego too rarely to stop in time, while
AutoCast, which sends what the ego needs first, passes safely."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from deploy.experiments.load import interval_load, load_summary


def paper_run(tmp_path, scheme: str) -> dict:
    proc = subprocess.run([sys.executable, "-m", "deploy.cli", "run", "--scenario", "red_light", "--vehicles", "40",
                           "--collider-speed", "40", "--delta", "1", "--seed", "0", "--scheme", scheme,
                           "--model", "paper", "--json", "--out", str(tmp_path), "--scans", "none",
                           "--no-json-mirror", "--log-level", "WARNING"],
                          capture_output=True, text=True, timeout=900)
    lines = proc.stdout.strip().splitlines()
    assert lines and lines[-1].startswith("{"), proc.stderr[-3000:]
    return json.loads(lines[-1])


@pytest.mark.heavy
def test_at_40_vehicles_agnostic_misses_the_collider_and_autocast_does_not(tmp_path):
    blind = paper_run(tmp_path, "agnostic")
    shared = paper_run(tmp_path, "autocast")
    assert blind["model"] == shared["model"] == "paper" and shared["model_settings"]["hold_s"] == 0.0
    assert blind["outcome"] == "crash", blind
    assert shared["outcome"] == "safe" and shared["closest_distance_m"] >= 2.0, shared
    assert shared["collider_visible_share"] >= 0.8 > blind["collider_visible_share"]
    # the channel binds: far more is offered than an interval carries
    load = load_summary(interval_load(shared["mcap"]))
    assert load["load_median"] > 1.0
