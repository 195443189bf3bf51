"""Runs end exactly as the golden file recorded (tests/golden_outcomes.py has the whole
matrix and re-runs it with ``--check``): one short AutoCast run through ``autocast run``
(real processes) as every experiment runs it (unsigned, the default), and the same run
with V2X signing on and Zenoh locked down (the file was recorded with neither: they
must change no result); each one's outcome, ego-collider distance series and channel
totals compared with the file, then every agent replayed from the run's log in this
process (with its credentials when the run signed), sending byte for byte what it sent
in the run."""

from __future__ import annotations

from pathlib import Path

import pytest
from golden_outcomes import QUICK, differences, entry_name, load, run_entry

from vehicle_agent.replay import Log, replay


@pytest.mark.heavy
@pytest.mark.parametrize("flags", [(), ("--sign", "--lock-down")], ids=["plain", "signed-locked-down"])
def test_a_short_autocast_run_ends_as_recorded_and_every_agent_replays_identically(tmp_path, flags):
    scenario, scheme, duration_s = QUICK[0]
    assert scheme == "autocast"
    got = run_entry(scenario, scheme, duration_s, tmp_path, scans="all", extra=flags)
    assert differences(load()[entry_name(scenario, scheme, duration_s)], got) == []
    (run_dir,) = [p for p in tmp_path.iterdir() if (p / "run.mcap").exists()]
    log = Log.read(Path(run_dir) / "run.mcap")
    vids = log.vids_with_scans()
    assert len(vids) == 4
    for vid in vids:
        creds = Path(run_dir) / "credentials" / f"agent{vid}.v2x.json" if flags else None
        r = replay(log, vid, credentials=creds)
        assert r.ticks == got["ticks"] and r.mismatches == [], (vid, r.mismatches[:5])
