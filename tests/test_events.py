"""Scenarios of several occlusion events (docs/domains.md, "Several events in one run"):
``corridor3x`` built, each event judged in process by its own judge, the outcome record
and its summary lines, and one short real run."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from tests.test_judge import run
from world_server.__main__ import summary
from world_server.geometry import point_at
from world_server.judge import RUN_FIELDS
from world_server.scenarios import ScenarioError, ScenarioParams, build
from world_server.sim import Simulation

LEFT_TURN_CONFLICT = (-5.25, math.sqrt(9.75**2 - 2.75**2) - 8.0)  # left_turn's (test_scenarios.py); J1 is the origin
# J0 (x = -150): the southbound ego's outer lane x = -5.25, the westbound collider's y = +5.25
RED_LIGHT_CONFLICT = (-150.0 - 5.25, 5.25)


def test_corridor3x_places_two_events_with_their_own_actors_and_conflict_points():
    s = build(ScenarioParams(scenario="corridor3x", vehicles=6, collider_speed_kmh=30.0, delta_s=1.25))
    left, red = s.events
    assert (left.name, left.junction, red.name, red.junction) == ("left_turn@J1", "J1", "red_light@J0", "J0")
    # the first event is the scenario's own (ego 0, truck 1, collider N); the second's ego and truck
    # are the next connected vids, its collider the first unconnected vid after the left turn's
    # collider and the 2 cars that follow it: the collider starts 8.25 s x 30 km/h = 68.8 m before
    # its conflict point, they 20 + 8.33^2 / 6 = 31.6 m apart behind it (100.3 and 131.9 m), on
    # the 136.6 m from the arm's start (130 m arm, 8 m half box, less the conflict point's 1.35 m)
    assert (left.ego, left.occluder, left.collider) == (0, 1, 6)
    assert [a.role for a in s.actors if a.vid in (7, 8)] == ["traffic", "traffic"]
    assert (red.ego, red.occluder, red.collider) == (2, 3, 9)
    assert (s.ego.vid, s.collider.vid) == (0, 6) and np.array_equal(s.conflict_xy, left.conflict_xy)
    assert left.conflict_xy == pytest.approx(LEFT_TURN_CONFLICT, abs=0.02)  # arc drawn as chords
    assert red.conflict_xy == pytest.approx(RED_LIGHT_CONFLICT)
    for ev, ego_kmh in ((left, 30.0), (red, 40.0)):
        ego, col = s.actor(ev.ego), s.actor(ev.collider)
        assert (ego.role, ego.connected, col.role, col.connected) == ("ego", True, "collider", False)
        assert s.actor(ev.occluder).role == "occluder" and s.actor(ev.occluder).connected
        assert ego.speed_mps == pytest.approx(ego_kmh / 3.6) and col.speed_mps == pytest.approx(30.0 / 3.6)
        for actor in (ego, col):  # both routes pass through the event's conflict point ...
            pts, _ = point_at(actor.route, np.arange(0.0, 400.0, 0.01))
            assert np.min(np.linalg.norm(pts - ev.conflict_xy, axis=1)) < 0.01
        # ... the ego 7 s from it, the collider delta later
        assert s.arrival_s(ego, ev.conflict_xy) == pytest.approx(7.0)
        assert s.arrival_s(col, ev.conflict_xy) - s.arrival_s(ego, ev.conflict_xy) == pytest.approx(1.25)
    assert (left.time_limit_s, red.time_limit_s, s.params.duration_s) == (30.0, 40.0, 40.0)
    # the red light's row of parked trucks (11 at the ego's 40 km/h, as in red_light) follows its collider
    assert [a.role for a in s.actors if a.vid > red.collider] == ["parked"] * 11
    assert [a.role for a in s.actors if a.connected] == ["ego", "occluder"] * 2 + ["background"] * 2
    # north-south green at J0 (the red-light ego's) and J1, east-west at J2 (light ids 4 j + S 0, E 1, N 2, W 3)
    assert [s.lights[k] for k in range(12)] == ["green", "red"] * 4 + ["red", "green"] * 2
    assert Simulation(ScenarioParams(scenario="corridor3x", vehicles=4)).mission(2).role == "ego"  # it reports


def test_corridor3x_needs_an_ego_and_a_truck_per_event():
    with pytest.raises(ScenarioError, match=r"^vehicles: corridor3x places 4 connected vehicles"):
        build(ScenarioParams(scenario="corridor3x", vehicles=3))


def ticks_to(t_s: float) -> int:
    """The ticks a judge watched up to a verdict at ``t_s``: the step of tick k covers
    (0.1 k, 0.1 (k + 1)] s."""
    return math.ceil(round(t_s * 10, 6))


def _stops(vid):
    """An override for ``tests.test_judge.run``: ``vid`` brakes fully from the start."""
    return lambda sim, v: (-7.5, 0.0) if v == vid else None


def test_blind_drivers_crash_in_both_events_and_the_run_ends_when_both_are_judged():
    """Lane followers, delta 0: in each event the ego meets its own collider about 7 s in
    (the left turn's and the red light's single-junction runs crash so too,
    tests/test_judge.py). The run stops once the later of the two is judged, not at 40 s;
    a tie goes to the first event."""
    sim = run(ScenarioParams(scenario="corridor3x", vehicles=5, delta_s=0.0))
    r = sim.result()
    left, red = r["events"]
    for e, ev in zip((left, red), sim.scenario.events):
        assert (e["event"], e["ego"], e["collider"]) == (ev.name, ev.ego, ev.collider)
        assert e["outcome"] == "crash" and e["crash_with"] == ev.collider and e["closest_distance_m"] == 0.0
        assert 4.0 < e["t_end_s"] < 7.2
        assert len(e["distance_series_m"]) == ticks_to(e["t_end_s"])
    assert sim.tick == ticks_to(max(left["t_end_s"], red["t_end_s"]))
    assert r["outcome"] == "crash" and r["event"] == "left_turn@J1" and r["crash_with"] == left["collider"]


def test_each_event_gets_its_own_verdict_and_window_and_the_run_its_worst():
    """The left turn's ego stands still from the start, 54 m short of its conflict point,
    while its collider passes 7 m to its left: no verdict until its window, left_turn's
    30 s (the run's 35 s do not reach), closes: a deadlock. The red light's blind ego crashes
    at about 7 s; its record stops there. The run is the crash, the red light's record."""
    sim = run(ScenarioParams(scenario="corridor3x", vehicles=5, delta_s=0.0, duration_s=35.0), _stops(0))
    r = sim.result()
    left, red = r["events"]
    assert left["outcome"] == "deadlock" and left["t_end_s"] == 30.0 and left["closest_distance_m"] > 2.0
    assert red["outcome"] == "crash" and red["crash_with"] == sim.scenario.events[1].collider
    assert sim.tick == 300  # ended at the left turn's window
    assert len(left["distance_series_m"]) == 300  # every tick
    assert len(red["distance_series_m"]) == ticks_to(red["t_end_s"]) < 80  # to its crash, none after
    assert r["outcome"] == "crash" and r["event"] == "red_light@J0"
    fields = set(red) - {"event", "junction", "ego", "collider"}
    assert {k: r[k] for k in fields} == {k: red[k] for k in fields}  # the worst event's
    assert r["scenario"] == "corridor3x" and r["vehicles"] == 5


def test_the_record_of_several_events_and_of_one():
    """Several events: the top level is a one-event record (``Judge.result``) plus ``event``
    and ``events``; an entry is the judge's fields without the run's parameters, plus the
    event's name, junction, ego and collider. One event: the judge's record, nothing more."""
    sim = Simulation(ScenarioParams(scenario="corridor3x", vehicles=4, duration_s=0.5))
    one = Simulation(ScenarioParams(scenario="corridor3", vehicles=4, duration_s=0.5))
    for s in (sim, one):
        while not s.done:
            s.sense(s.connected_vids)
            s.step({})
    judged = set(one.judge.result())
    assert set(one.result()) == judged and "events" not in one.result()
    r = sim.result()
    assert set(r) == judged | {"event", "events"}
    assert [set(e) for e in r["events"]] == [(judged - set(RUN_FIELDS)) | {"event", "junction", "ego", "collider"}] * 2
    assert [(e["event"], e["junction"], e["ego"], e["collider"]) for e in r["events"]] == \
        [("left_turn@J1", "J1", 0, 4), ("red_light@J0", "J0", 2, 7)]
    assert [e["outcome"] for e in r["events"]] == ["deadlock", "deadlock"]  # 0.5 s: both time out
    json.dumps(r, allow_nan=False)  # JSON as it is: no inf, no NaN


def test_a_run_of_several_events_prints_a_line_per_event_then_the_run():
    event = {"outcome": "safe", "closest_distance_m": 5.2, "reaction_time_s": 1.5, "collider_visible_share": 0.85,
             "collider_points_mean": 700.0, "visibility_source": "fused", "t_end_s": 9.31}
    record = {**event, "outcome": "crash", "closest_distance_m": 0.0, "event": "red_light@J0", "scenario": "corridor3x",
              "vehicles": 10, "seed": 0, "ticks": 94, "wall_s": 20.04,
              "events": [{"event": "left_turn@J1", "ego": 0, "collider": 10, **event},
                         {"event": "red_light@J0", "ego": 2, "collider": 13, **event, "outcome": "crash",
                          "closest_distance_m": 0.0, "reaction_time_s": None, "visibility_source": "own_lidar",
                          "t_end_s": 6.72}]}
    assert summary(record).splitlines() == [
        "left_turn@J1 (ego 0, collider 10): outcome: safe  closest distance 5.20 m  reaction time 1.50 s  "
        "collider in the ego's fused view 85% of ticks (700 points mean)  at 9.3 s",
        "red_light@J0 (ego 2, collider 13): outcome: crash  closest distance 0.00 m  reaction time n/a  "
        "collider in the ego's own view 85% of ticks (700 points mean)  at 6.7 s",
        "outcome: crash (the worst of 2 events: red_light@J0)  "
        "[corridor3x, 10 vehicles, seed 0, 94 ticks in 20.0 s wall]"]
    single = {k: v for k, v in record.items() if k not in ("event", "events")}
    assert summary(single) == ("outcome: crash  closest distance 0.00 m  reaction time 1.50 s  collider in the ego's "
                               "fused view 85% of ticks (700 points mean)  [corridor3x, 10 vehicles, seed 0, 94 ticks "
                               "in 20.0 s wall]")


RUN_TICKS = 20  # 2 s of sim time


@pytest.mark.heavy
def test_a_corridor3x_run_records_both_events(tmp_path):
    """``autocast run`` of corridor3x for 2 s, 6 vehicles, lock-step. In 2 s neither ego
    (30 and 40 km/h, 58 and 78 m from its conflict point) gets there, nor can a collider
    reach its ego, so both events time out as deadlocks at 2 s; each ego's agent reported
    its fused view (every scheme but lane does), so both are judged on it."""
    proc = subprocess.run([sys.executable, "-m", "deploy.cli", "run", "--scenario", "corridor3x", "--vehicles", "6",
                           "--scheme", "autocast", "--duration", "2", "--seed", "0", "--json", "--out", str(tmp_path),
                           "--run-id", "c3x", "--scans", "none", "--log-level", "WARNING"],
                          capture_output=True, text=True, timeout=300)
    lines = proc.stdout.strip().splitlines()
    assert lines and lines[-1].startswith("{"), proc.stderr[-3000:]
    r = json.loads(lines[-1])
    assert r["scenario"] == "corridor3x" and r["ticks"] == RUN_TICKS and r["dead_agents"] == {}
    assert [(e["event"], e["ego"], e["collider"]) for e in r["events"]] == [("left_turn@J1", 0, 6),
                                                                            ("red_light@J0", 2, 9)]
    for e in r["events"]:
        assert e["outcome"] == "deadlock" and e["t_end_s"] == 2.0 and e["closest_distance_m"] > 2.0
        assert e["visibility_source"] == "fused" and e["encounter_ticks"] == RUN_TICKS
    assert r["outcome"] == "deadlock" and r["event"] == "left_turn@J1"
    assert proc.returncode == 1  # not safe
    printed = lines[:-1]
    assert printed[-3].startswith("left_turn@J1 (ego 0, collider 6): outcome: deadlock")
    assert printed[-2].startswith("red_light@J0 (ego 2, collider 9): outcome: deadlock")
    assert printed[-1].startswith("outcome: deadlock (the worst of 2 events: left_turn@J1)  [corridor3x, 6 vehicles")
    assert json.loads((tmp_path / "c3x" / "outcome.json").read_text())["events"] == r["events"]
