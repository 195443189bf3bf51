"""The soak of faulted runs (``bench/soak.py``), bounded: one run each of a killed hub
(the launcher), a SIGKILLed recorder and a SIGSTOPped agent, side by side. Every run gets
a verdict, nothing is left behind and every log reads to its end; ``python -m
bench.soak --runs 200`` is the full soak (docs/running.md)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest


@pytest.mark.heavy
def test_faulted_runs_each_get_a_verdict_and_leave_nothing_behind(tmp_path):
    """As its own process: the soak makes itself the subreaper of what its launchers leave."""
    faults = ["hub:kill", "recorder:kill", "agent:stop"]
    done = subprocess.run([sys.executable, "-m", "bench.soak", "--runs", str(len(faults)), "--jobs", str(len(faults)),
                           "--out", str(tmp_path), "--timeout-s", "120", "--no-warm-up",  # the suite warmed them
                           *(a for f in faults for a in ("--fault", f))],
                          capture_output=True, text=True, timeout=900)
    last = done.stdout.strip().splitlines()[-1] if done.stdout.strip() else done.stderr[-2000:]
    assert last.startswith("soak: "), last
    figures = dict(item.split("=") for item in last.removeprefix("soak: ").split())
    assert done.returncode == 0, last
    assert figures["runs"] == "3" and int(figures["judged"]) + int(figures["failed"]) == 3, last
    assert (figures["lost"], figures["procs_left"], figures["shm_left"], figures["mcap_unreadable"]) == \
        ("0", "0", "0", "0"), last
    records = {r["fault"].split(":")[0].rstrip("0123456789"): r for r in map(json.loads,
                                                                          (tmp_path / "results.jsonl").open())}
    assert all(r["fault_fired"] for r in records.values()), records
    # the launcher killed: no record of its own; the soak, as a sweep, says why
    assert records["hub"]["status"] == "failed" and "exited with code -9" in records["hub"]["failure"]
    # a stopped agent is declared dead after the agent timeout, and the run plays out
    assert records["agent"]["status"] == "judged" and records["agent"]["dead_agents"], records["agent"]
    # a recorder killed mid-run leaves a log of whole records, unfinalized
    assert records["recorder"]["mcap_readable"] is True
