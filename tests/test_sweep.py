"""``autocast sweep`` and ``autocast report``: the matrix, the estimate and the tables by
hand; then real sweeps (real runs on loopback) into a temporary directory: smoke,
resume, a failed run, Ctrl-C."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from mcap.reader import make_reader

from deploy.experiments import plan, report, runner, sweep
from deploy.record.recorder import JSON_PREFIX
from deploy.experiments.plan import RunKey
from tests.conftest import wait_until

# ---------------------------------------------------------------------------- the matrix


def spec(**over) -> plan.SweepSpec:
    values = {**plan.PRESETS["smoke"], **over}
    return plan.spec_from(values, "t")


def test_expand_is_the_product_in_plan_order():
    s = spec(vehicles=[10, 5], schemes=["single", "autocast"], deltas_s=[-1, 1], seeds=[0, 1])
    keys = plan.expand(s)
    assert len(keys) == 2 * 2 * 2 * 2 == s.size()
    assert len({k.name for k in keys}) == len(keys)
    # seed outermost, densities ascending, the schemes of one configuration next to each other
    assert [(k.seed, k.vehicles, k.delta_s, k.scheme) for k in keys[:4]] == [
        (0, 5, -1.0, "single"), (0, 5, -1.0, "autocast"), (0, 5, 1.0, "single"), (0, 5, 1.0, "autocast")]
    assert keys[4].vehicles == 10 and keys[-1].seed == 1


def test_paper_preset_is_the_papers_matrix():
    s = plan.spec_from(plan.PRESETS["paper"], "paper")
    assert s.size() == 3 * 3 * 5 * 4 * 4 == 720
    assert s.schemes == ("single", "agnostic", "emp", "autocast")
    assert s.collider_speeds_kmh == (20.0, 30.0, 40.0) and s.vehicles == (5, 10, 20, 40)


def test_each_scenario_runs_for_its_own_time_limit_unless_the_sweep_gives_one():
    """The paper's scenarios keep their authors' timeouts (overtaking 40 s, left turn
    30 s, red light 40 s); ``duration_s`` in a sweep replaces them all."""
    own = plan.expand(plan.spec_from(plan.PRESETS["paper"], "paper"))
    assert {(k.scenario, k.duration_s) for k in own} == {("overtaking", 40.0), ("left_turn", 30.0),
                                                         ("red_light", 40.0)}
    given = plan.expand(plan.spec_from({**plan.PRESETS["smoke"], "duration_s": 12}, "smoke"))
    assert {k.duration_s for k in given} == {12.0} and given[0].name.endswith("-t12")


def test_run_key_name_is_a_valid_run_id():
    k = RunKey("left_turn", 10, 30.0, -0.5, "autocast-fptas", 3, 20.0)
    assert k.name == "left_turn-v10-c30-d-0p5-autocast-fptas-s3-t20"
    from protocol import keys

    keys.everything(k.name)  # raises on a character a Zenoh key of the run cannot hold
    assert k.run_flags()[k.run_flags().index("--delta") + 1] == "-0.5"


def test_a_model_other_than_ours_is_in_every_key_and_every_run_s_flags(tmp_path):
    from deploy.experiments.plan import spec_from
    from deploy.experiments.runner import launcher_args

    values = {**plan.preset_values("smoke"), "model": "paper", "model_settings": {"hold_s": 1.0}}
    spec = spec_from(values, "smoke")
    keys = plan.expand(spec)
    assert {k.model for k in keys} == {"paper+hold_s=1.0"}
    assert keys[0].name.startswith("left_turn-v5-c30-d0-single-s0-t30-mpaper-") and len(keys[0].name.split("-")[-1]) == 8
    argv = launcher_args(spec, keys[0], keys[0].name, tmp_path, warm=True)
    assert argv[argv.index("--model") + 1] == "paper" and argv[argv.index("--model-set") + 1] == "hold_s=1.0"
    plain = plan.expand(spec_from(plan.preset_values("smoke"), "smoke"))
    assert plain[0].name == "left_turn-v5-c30-d0-single-s0-t30" and "--model" in launcher_args(
        spec_from(plan.preset_values("smoke"), "smoke"), plain[0], "r", tmp_path, warm=True)
    with pytest.raises(plan.SweepError, match="^hold_s:"):
        spec_from({**values, "model_settings": {"hold_s": "x"}}, "smoke")
    with pytest.raises(plan.SweepError, match="^model:"):
        spec_from({**values, "model": ["paper"]}, "smoke")


@pytest.mark.parametrize("over, message", [
    ({"vehicles": [5, 20000]}, "vehicles: 20000 is not in [2, 16384]"),  # a scenario's map bounds it further
    ({"schemes": ["telepathy"]}, "schemes: 'telepathy' is not one of"),
    ({"scenarios": ["roundabout"]}, "scenarios: 'roundabout' is not one of"),
    ({"deltas_s": []}, "deltas_s: [] is not a non-empty list"),
    ({"vehicle": [5]}, "vehicle: unknown field"),
    ({"timeout_s": 0}, "timeout_s: 0 is not a number > 0"),
    ({"scans": "most"}, "scans: 'most' is not one of"),
    ({"json_mirror": "yes"}, "json_mirror: 'yes' is not true or false"),
])
def test_bad_fields_are_named(over, message):
    with pytest.raises(plan.SweepError) as err:
        spec(**over)
    assert str(err.value).startswith(message)


def test_a_sweeps_runs_record_without_the_json_mirror_unless_asked():
    key = plan.expand(spec())[0]
    assert "--no-json-mirror" in runner.launcher_args(spec(), key, "r", Path("runs"), warm=True)
    assert "--no-json-mirror" not in runner.launcher_args(spec(json_mirror=True), key, "r", Path("runs"), warm=True)
    args = sweep.parse_args(["--preset", "smoke", "--json-mirror"])
    assert plan.spec_from(plan.narrowed(plan.preset_values("smoke"), args), "smoke").json_mirror


def test_duplicates_collapse_and_numbers_coerce():
    s = spec(vehicles=[5, 5, 10], collider_speeds_kmh=[30, 30.0])
    assert s.vehicles == (5, 10) and s.collider_speeds_kmh == (30.0,)


def test_cli_refuses_bad_input_naming_the_field(tmp_path, capsys):
    assert sweep.main(["--preset", "nope"]) == 2
    assert "error: preset: 'nope' is not one of paper, smoke" in capsys.readouterr().err
    assert sweep.main(["--preset", "smoke", "--vehicles", "5,500", "--dry-run"]) == 2
    assert "error: vehicles: 500 is not in [2, 64] (64 a scheduler domain; left_turn's map has 1) " \
        "(run left_turn-v500-" in capsys.readouterr().err
    f = tmp_path / "s.toml"
    f.write_text('preset = "smoke"\nvehicle = [5]\n')
    assert sweep.main(["--file", str(f), "--dry-run"]) == 2
    assert "error: vehicle: unknown field" in capsys.readouterr().err
    f.write_text("vehicles = [5\n")
    assert sweep.main(["--file", str(f)]) == 2
    assert "is not valid TOML" in capsys.readouterr().err
    assert not (tmp_path / "runs").exists()


def test_dry_run_prints_the_plan_and_writes_nothing(tmp_path, capsys):
    out = tmp_path / "sw"
    assert sweep.main(["--preset", "paper", "--vehicles", "5,20", "--scenarios", "left_turn", "--out", str(out),
                       "--dry-run"]) == 0
    text = capsys.readouterr().out
    assert "120 runs = 1 scenario x 3 collider speeds x 5 deltas x 2 vehicle counts x 4 schemes x 1 seed" in text
    assert "to run: 120" in text and "estimated wall time" in text
    assert not out.exists()


def test_estimate_interpolates_the_measured_model(monkeypatch):
    monkeypatch.setattr(plan, "MODEL_STARTUP_S", {10: 10.0, 20: 20.0})
    monkeypatch.setattr(plan, "MODEL_TICK_S", {10: 0.1, 20: 0.3})
    monkeypatch.setattr(plan, "TYPICAL_END_S", {"left_turn": 10.0})
    key = RunKey("left_turn", 15, 30.0, 0.0, "autocast", 0, 20.0)
    assert plan.estimate_run_s(key) == pytest.approx(15.0 + 100 * 0.2)  # 10 s of sim = 100 ticks
    short = RunKey("left_turn", 30, 30.0, 0.0, "autocast", 0, 5.0)  # beyond the table: linear; 50 ticks
    assert plan.estimate_run_s(short) == pytest.approx(30.0 + 50 * 0.5)


def test_estimate_takes_each_scenarios_typical_end(monkeypatch):
    monkeypatch.setattr(plan, "MODEL_STARTUP_S", {10: 0.0, 20: 0.0})
    monkeypatch.setattr(plan, "MODEL_TICK_S", {10: 0.1, 20: 0.1})
    monkeypatch.setattr(plan, "TYPICAL_END_S", {"overtaking": 20.0, "red_light": 8.0})
    monkeypatch.setattr(plan, "TYPICAL_END_OTHER_S", 12.0)
    run = lambda scenario, limit: plan.estimate_run_s(RunKey(scenario, 10, 30.0, 0.0, "autocast", 0, limit))
    assert run("overtaking", 40.0) == pytest.approx(200 * 0.1)
    assert run("red_light", 40.0) == pytest.approx(80 * 0.1)
    assert run("overtaking", 5.0) == pytest.approx(50 * 0.1)  # never beyond the time limit
    assert run("my_scenario", 40.0) == pytest.approx(120 * 0.1)  # one the model has not seen


def test_the_typical_end_follows_the_collider_speed(monkeypatch):
    monkeypatch.setattr(plan, "TYPICAL_END_S", {"left_turn": {20: 18.0, 40: 12.0}, "red_light": 9.0})
    end = lambda scenario, kmh: plan.typical_end_s(RunKey(scenario, 10, kmh, 0.0, "autocast", 0, 30.0))  # noqa: E731
    assert end("left_turn", 20.0) == pytest.approx(18.0)
    assert end("left_turn", 30.0) == pytest.approx(15.0)  # halfway
    assert end("left_turn", 50.0) == pytest.approx(9.0)  # beyond: the same slope
    assert end("left_turn", 500.0) == pytest.approx(1.0)  # never below a second
    assert end("red_light", 20.0) == end("red_light", 40.0) == pytest.approx(9.0)  # one figure for every speed


def test_estimate_is_rescaled_by_the_runs_already_measured(monkeypatch):
    monkeypatch.setattr(plan, "MODEL_STARTUP_S", {5: 5.0, 10: 5.0})
    monkeypatch.setattr(plan, "MODEL_TICK_S", {5: 0.1, 10: 0.1})
    monkeypatch.setattr(plan, "TYPICAL_END_S", {"left_turn": 10.0})  # every autocast run: 5 + 100 x 0.1 = 15 s
    key = RunKey("left_turn", 5, 30.0, 0.0, "autocast", 0, 20.0)
    measured = [{"run_key": "x", "status": "judged", "scenario": "left_turn", "vehicles": 5, "collider_speed_kmh": 30.0, "delta_s": 0.0,
                 "scheme": "autocast", "seed": s, "duration_s": 20.0, "wall_total_s": w}
                for s, w in enumerate((30.0, 45.0, 60.0))]
    assert plan.calibration(measured) == (pytest.approx(3.0), 3)  # median of 2x, 3x, 4x
    assert plan.calibration(measured[:2]) == (1.0, 2)  # too few to trust
    paired = [dict(r, seed=r["seed"] + 3, wall_total_s=150.0, alone=False) for r in measured]
    assert plan.calibration(measured + paired) == (pytest.approx(3.0), 3)  # runs in pairs are not the model's
    assert plan.estimate_wall_s([key, key], jobs=1, scale=3.0) == pytest.approx(90.0)


def test_with_jobs_runs_that_fit_the_budget_twice_pair_up(monkeypatch):
    monkeypatch.setattr(plan, "MODEL_STARTUP_S", {5: 5.0, 40: 5.0})
    monkeypatch.setattr(plan, "MODEL_TICK_S", {5: 0.1, 40: 0.1})
    monkeypatch.setattr(plan, "TYPICAL_END_S", {"left_turn": 10.0})  # every autocast run: 15 s alone
    monkeypatch.setattr(plan, "PAIR_GAIN", 1.5)
    small, big = (RunKey("left_turn", n, 30.0, 0.0, "autocast", 0, 20.0) for n in (5, 40))
    assert plan.estimate_wall_s([small, big], jobs=1) == pytest.approx(30.0)
    assert plan.estimate_wall_s([small, big], jobs=2, vehicle_budget=20) == pytest.approx(10.0 + 15.0)
    assert plan.estimate_wall_s([small, big], jobs=2, vehicle_budget=9) == pytest.approx(30.0)  # 5 + 5 > 9


# ---------------------------------------------------------------------------- records


KEY = RunKey("red_light", 5, 20.0, 1.0, "autocast", 0, 20.0)


def test_record_of_a_judged_run_keeps_scalars_not_the_series():
    outcome = {"outcome": "near_miss", "closest_distance_m": 1.5, "reaction_time_s": None, "scenario": "red_light",
               "vehicles": 5, "distance_series_m": [[0.1 * i, 50.0] for i in range(200)],
               "dead_agents": {str(v): "no command for tick 80 within 10.0 s" for v in range(40)}}
    rec = plan.record_of(KEY, KEY.name, 1, "outcome: near_miss ...\n" + json.dumps(outcome) + "\n", "", 12.3)
    assert rec["status"] == "judged" and rec["outcome"] == "near_miss" and rec["exit_code"] == 1
    assert rec["run_key"] == KEY.name and rec["scheme"] == "autocast" and rec["closest_distance_m"] == 1.5
    assert "distance_series_m" not in rec and "error" not in rec
    assert len(rec["dead_agents"]) == 40  # long, but kept: dead agents change outcomes


def test_record_of_a_run_of_several_events_keeps_each_events_scalars():
    series = [[0.1 * i, 50.0] for i in range(200)]
    events = [{"event": name, "outcome": o, "closest_distance_m": d, "distance_series_m": series}
              for name, o, d in (("left_turn@J1", "safe", 3.7), ("red_light@J0", "crash", 0.0))]
    outcome = {"outcome": "crash", "event": "red_light@J0", "closest_distance_m": 0.0, "distance_series_m": series,
               "events": events}
    rec = plan.record_of(KEY, KEY.name, 1, json.dumps(outcome) + "\n", "", 30.0)
    assert rec["event"] == "red_light@J0" and "distance_series_m" not in rec
    assert rec["events"] == [{"event": "left_turn@J1", "outcome": "safe", "closest_distance_m": 3.7},
                             {"event": "red_light@J0", "outcome": "crash", "closest_distance_m": 0.0}]


def test_record_of_a_failed_run_keeps_its_error():
    rec = plan.record_of(KEY, KEY.name, 3, json.dumps({"outcome": None, "failure": "world exited"}) + "\n",
                          "lots\nof\nstderr", 4.0)
    assert rec["status"] == "failed" and rec["error"]["failure"] == "world exited"
    assert rec["error"]["exit_code"] == 3 and rec["error"]["stderr_tail"].endswith("stderr")
    crashed = plan.record_of(KEY, KEY.name, 1, "", "Traceback ...\nZeroDivisionError", 1.0)
    assert crashed["status"] == "failed" and crashed["outcome"] is None
    assert crashed["error"]["failure"] == "exit code 1 without an outcome"


def test_results_survive_a_torn_line_and_the_last_attempt_wins(tmp_path):
    path = tmp_path / "results.jsonl"
    plan.append_record(path, {"run_key": "a", "status": "failed"})
    plan.append_record(path, {"run_key": "b", "status": "judged"})
    plan.append_record(path, {"run_key": "a", "status": "judged"})
    with open(path, "a") as f:
        f.write('{"run_key": "c", "sta')  # killed mid-write
    recs = plan.read_results(path)
    assert [r["run_key"] for r in recs] == ["a", "b", "a"]
    assert {k: r["status"] for k, r in plan.latest(recs).items()} == {"a": "judged", "b": "judged"}
    # the resumed sweep's first record starts a line of its own, not the torn one's tail
    plan.append_record(path, {"run_key": "c", "status": "judged"})
    assert [r["run_key"] for r in plan.read_results(path)] == ["a", "b", "a", "c"]


# ---------------------------------------------------------------------------- report tables


def rec(scheme, vehicles, outcome, scenario="left_turn", share=None, points=None, reaction=None, closest=5.0):
    status = "judged" if outcome else "failed"
    return {"run_key": f"{scenario}-{scheme}-{vehicles}-{len(RECS)}", "run_id": f"r{len(RECS)}",
            "scheme": scheme, "vehicles": vehicles, "scenario": scenario, "status": status, "outcome": outcome,
            "collider_visible_share": share, "collider_points_mean": points, "reaction_time_s": reaction,
            "closest_distance_m": closest, "exit_code": 0 if outcome == "safe" else 1 if outcome else 3,
            **({} if outcome else {"error": {"failure": "no outcome within 1 s of wall time"}})}


RECS: list[dict] = []
for args in [("single", 5, "safe", "left_turn", 0.2, 100.0, None, 3.0),
             ("single", 5, "crash", "red_light", 0.0, 0.0, None, 0.0),
             ("single", 10, "near_miss", "red_light", 0.4, 300.0, 1.0, 1.2),
             ("single", 10, None),
             ("autocast", 5, "safe", "left_turn", 1.0, 900.0, 12.0, 6.0),
             ("autocast", 5, "safe", "red_light", 0.8, 500.0, 10.0, 4.0),
             ("autocast", 10, "deadlock", "red_light", 0.6, 700.0, 8.0, 9.0)]:
    RECS.append(rec(*args))


def test_outcome_counts_and_safe_by_density():
    counts = report.outcome_counts(RECS)
    assert list(counts) == ["single", "autocast"]  # the paper's order: baselines first
    assert counts["single"] == Counter(safe=1, crash=1, near_miss=1, failed=1)
    assert report.safe_by_density(RECS) == {("single", 5): (1, 2), ("single", 10): (0, 1),
                                            ("autocast", 5): (2, 2), ("autocast", 10): (0, 1)}
    md = "\n".join(report.safe_table_md(RECS))
    assert "| scheme | 5 vehicles | 10 vehicles | all |" in md
    assert "| single | 50% (1/2) | 0% (0/1) | 33% (1/3) |" in md
    assert "| autocast | 100% (2/2) | 0% (0/1) | 67% (2/3) |" in md


def test_visibility_uses_red_light_when_run():
    chosen, which = report.visibility_records(RECS)
    assert which == "red_light" and {r["scenario"] for r in chosen} == {"red_light"}
    vis = report.visibility_by_density(chosen)
    assert vis[("autocast", 5)].share_mean == pytest.approx(0.8)
    assert vis[("single", 10)].points_mean == pytest.approx(300.0)
    assert ("single", 10) in vis and vis[("single", 10)].runs == 1  # the failed run is not averaged


def test_per_scenario_counts_never_aware_as_zero_reaction():
    rows = report.per_scenario(RECS)
    red_single = rows[("red_light", "single")]
    assert red_single.runs == 2 and red_single.reaction_mean_s == pytest.approx(0.5)  # (0 + 1) / 2
    assert red_single.closest_min_m == 0.0 and red_single.closest_mean_m == pytest.approx(0.6)
    assert rows[("red_light", "autocast")].outcomes == Counter(safe=1, deadlock=1)


def several(scheme, outcome, *events, status="judged"):
    """A corridor3x record: ``events`` are (outcome, reaction_time_s, closest_distance_m)
    of left_turn@J1 then red_light@J0; the top level is ``outcome`` (the worst event's)."""
    names = ("left_turn@J1", "red_light@J0")
    r = rec(scheme, 10, outcome, "corridor3x")
    return {**r, "status": status, "events": [{"event": n, "outcome": o, "reaction_time_s": t, "closest_distance_m": d}
                                              for n, (o, t, d) in zip(names, events)]}


def test_per_event_tabulates_each_event_of_the_runs_that_carry_events():
    recs = RECS + [several("autocast", "crash", ("safe", 2.0, 5.0), ("crash", None, 0.0)),
                   several("autocast", "near_miss", ("near_miss", 1.0, 1.5), ("safe", 3.0, 6.0)),
                   several("single", "crash", ("crash", 0.5, 0.0), ("crash", None, 0.0)),
                   several("autocast", "crash", ("crash", 0.1, 0.0), ("crash", 0.1, 0.0), status="failed")]
    rows = report.per_event(recs)
    assert set(rows) == {("corridor3x", e, s) for e in ("left_turn@J1", "red_light@J0") for s in ("single", "autocast")}
    left = rows[("corridor3x", "left_turn@J1", "autocast")]
    assert left.runs == 2 and left.outcomes == Counter(safe=1, near_miss=1)  # the failed run is not counted
    assert (left.reaction_mean_s, left.closest_mean_m, left.closest_min_m) == (1.5, 3.25, 1.5)
    red = rows[("corridor3x", "red_light@J0", "autocast")]
    assert red.outcomes == Counter(crash=1, safe=1) and red.reaction_mean_s == 1.5  # never aware counts 0 s
    assert report.per_scenario(recs)[("corridor3x", "autocast")].outcomes == Counter(crash=1, near_miss=1)
    md = report.per_event_md(recs)
    assert md[0] == ("| scenario | event | scheme | judged | safe | near miss | crash | deadlock | reaction mean (s) "
                     "| closest mean (m) | closest min (m) |")
    assert md[2:] == ["| corridor3x | left_turn@J1 | single | 1 | 0 | 0 | 1 | 0 | 0.50 | 0.00 | 0.00 |",
                      "| corridor3x | left_turn@J1 | autocast | 2 | 1 | 1 | 0 | 0 | 1.50 | 3.25 | 1.50 |",
                      "| corridor3x | red_light@J0 | single | 1 | 0 | 0 | 1 | 0 | 0.00 | 0.00 | 0.00 |",
                      "| corridor3x | red_light@J0 | autocast | 2 | 1 | 0 | 1 | 0 | 1.50 | 3.00 | 0.00 |"]
    title = "## Per event: runs of several events"
    assert title in report.summary_md(Path("sweep"), recs, None, {}, None, "")
    assert title not in report.summary_md(Path("sweep"), RECS, None, {}, None, "")


def sent(rewards, delays_ms):
    return [report.Sent(1, 0, k, float(r), 100, d / 1e3, 1) for k, (r, d) in enumerate(zip(rewards, delays_ms))]


def test_spearman_and_delay_table():
    assert report.spearman([1, 2, 3, 4], [40, 30, 20, 10]) == pytest.approx(-1.0)
    assert report.spearman([0, 0, 0], [1, 2, 3]) is None
    # few distinct rewards: grouped by value; ranks with ties (1.5, 1.5, 3.5, 3.5) vs (3, 4, 1, 2): -4 / sqrt(4 * 5)
    row = report.delay_table({"autocast": (1, sent([1, 1, 2, 2], [30, 50, 10, 20]))})["autocast"]
    assert row.sent == 4 and row.spearman == pytest.approx(-4 / 20 ** 0.5)
    assert row.by_reward == (("1", pytest.approx(40.0), 2), ("2", pytest.approx(15.0), 2))
    # many distinct rewards: quartiles of 0..11 (edges 0, 2.75, 5.5, 8.25, 11), delay 100 - 5 k ms
    groups = report.reward_groups(sent(range(12), [100 - 5 * k for k in range(12)]))
    assert [g.label for g in groups] == ["0.00-2.75", "2.75-5.50", "5.50-8.25", "8.25-11.00"]
    assert [float(np.median(g.delays_ms)) for g in groups] == pytest.approx([95.0, 80.0, 65.0, 50.0])


def test_the_report_counts_runs_against_the_last_plan_by_key():
    rec = lambda key, status="judged": {"run_key": key, "status": status, "outcome": "safe" if status == "judged" else None}
    plan = {"git_revision": "abc", "runs": [{"run_key": k} for k in ("b", "c", "d")]}
    records = [rec("a"), rec("b"), rec("c", "failed")]  # "a" from an earlier plan; "d" not run yet
    assert report.coverage(records, plan) == ("3 runs recorded (2 judged, 1 failed); the last plan (`plan.json`, "
                                              "git revision abc) has 3 runs, 1 of them not run yet; 1 recorded "
                                              "runs are from earlier plans.")
    assert report.coverage(records, None) == "3 runs recorded (2 judged, 1 failed)."


def test_report_of_an_empty_sweep_says_no_data(tmp_path):
    (tmp_path / "results.jsonl").write_text("")
    assert report.main([str(tmp_path)]) == 0
    for name in report.FIGURES:
        assert (tmp_path / "report" / name).stat().st_size > 1000
    assert "No data" in (tmp_path / "report" / "summary.md").read_text()
    assert report.main([str(tmp_path / "nowhere")]) == 2


# ---------------------------------------------------------------------------- real sweeps


def autocast(*args: str, timeout: float = 240, faults: str = "") -> subprocess.CompletedProcess:
    """``autocast ARGS``; ``faults`` goes to every process of the runs (protocol/faults.py)."""
    return subprocess.run([sys.executable, "-m", "deploy.cli", *args], capture_output=True, text=True,
                          timeout=timeout, env=dict(os.environ, AUTOCAST_FAULTS=faults))


def leftovers(run_ids) -> list[str]:
    out = subprocess.run(["pgrep", "-af", "|".join(f"--run-id {r}( |$)" for r in run_ids)], capture_output=True,
                         text=True)
    return [line for line in out.stdout.splitlines() if "pgrep" not in line]


def lines(path: Path) -> list[dict]:
    return [json.loads(x) for x in path.read_text().splitlines()]


@pytest.mark.heavy
def test_smoke_sweep_resume_and_report(tmp_path):
    out = tmp_path / "smoke"
    first = autocast("sweep", "--preset", "smoke", "--out", str(out))
    assert first.returncode == 0, first.stderr
    results = lines(out / "results.jsonl")
    assert [r["run_key"] for r in results] == ["left_turn-v5-c30-d0-single-s0-t30",
                                               "left_turn-v5-c30-d0-autocast-s0-t30"]
    for r in results:
        assert r["status"] == "judged" and r["outcome"] in report.OUTCOMES
        assert (out / "runs" / r["run_id"] / "outcome.json").exists()
        assert "distance_series_m" not in r
        # the launcher's rusage includes every process of the run: at least what they all spent while it
        # ticked (cpu_ms_per_tick, read per process), whatever the machine's speed (cpu_s is rounded to 0.1 s)
        assert r["cpu_s"] + 0.05 >= r["cpu_ms_per_tick"]["all"] * r["ticks"] / 1e3 > 0
    assert "[2/2]" in first.stderr
    assert json.loads((out / "plan.json").read_text())["spec"]["name"] == "smoke"
    with open(out / "runs" / results[1]["run_id"] / "run.mcap", "rb") as f:  # no JSON mirror: half the recorder's CPU
        topics = {c.topic for c in make_reader(f).get_summary().channels.values()}
    assert any(t.endswith("/world/outcome") for t in topics) and not any(t.startswith(JSON_PREFIX) for t in topics)
    assert not leftovers(r["run_id"] for r in results)

    again = autocast("sweep", "--preset", "smoke", "--out", str(out))
    assert again.returncode == 0 and "nothing to run" in again.stderr
    assert len(lines(out / "results.jsonl")) == 2

    rep = autocast("report", str(out))
    assert rep.returncode == 0, rep.stderr
    for name in report.FIGURES:
        assert (out / "report" / name).stat().st_size > 5000
    summary = (out / "report" / "summary.md").read_text()
    assert "| scheme | 5 vehicles | all |" in summary
    assert "| single | " in summary and "| autocast | " in summary
    assert "2 runs recorded (2 judged, 0 failed); the last plan (`plan.json`, git revision" in summary
    assert "has 2 runs, 0 of them not run yet." in summary


@pytest.mark.heavy
def test_a_failed_run_is_recorded_with_its_error(tmp_path):
    """The world hangs at tick 3, so the run cannot reach an outcome however fast the
    machine is; the wall-clock limit only notices. The run is failed, never judged."""
    f = tmp_path / "fail.toml"
    f.write_text('preset = "smoke"\nschemes = ["single"]\nvehicles = [2]\ntimeout_s = 1\n')
    out = tmp_path / "fail"
    res = autocast("sweep", "--file", str(f), "--out", str(out), faults="world:hang@3")
    assert res.returncode == 1, res.stderr
    [r] = lines(out / "results.jsonl")
    assert r["status"] == "failed" and r["outcome"] is None and r["exit_code"] == 3
    assert "no outcome within 1 s" in r["error"]["failure"]
    assert "FAILED (exit 3)" in res.stderr
    assert not leftovers([r["run_id"]])
    assert report.main([str(out)]) == 0
    assert "| left_turn-v2-c30-d0-single-s0-t30 | 3 | no outcome within 1 s" in (out / "report" / "summary.md").read_text()


def test_a_nearly_full_disk_starts_no_run_and_the_same_command_resumes(tmp_path):
    """A floor above the file system's whole size: no machine has that much free."""
    out = tmp_path / "full"
    floor_mb = shutil.disk_usage(tmp_path).total / 1e6 + 1
    res = autocast("sweep", "--preset", "smoke", "--schemes", "single", "--vehicles", "2", "--out", str(out),
                   "--min-free-mb", f"{floor_mb:.0f}")
    assert res.returncode == 4, res.stderr
    assert f"free where the runs write, under --min-free-mb {floor_mb:.0f}" in res.stderr
    assert "run the same command again" in res.stderr
    assert not (out / "results.jsonl").exists() and not any((out / "runs").iterdir())
    assert autocast("sweep", "--preset", "smoke", "--out", str(out), "--min-free-mb", "-1").returncode == 2


def test_ctrl_c_stops_the_running_run_and_records_nothing(tmp_path):
    """Agent 1 hangs at tick 5 (and would be declared dead only after 600 s), so the run
    is still going whenever the SIGINT lands."""
    out = tmp_path / "stop"
    proc = subprocess.Popen([sys.executable, "-m", "deploy.cli", "sweep", "--preset", "smoke", "--vehicles", "2",
                             "--agent-timeout-s", "600", "--out", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            env=dict(os.environ, AUTOCAST_FAULTS="agent1:hang@5"))
    run_id = "left_turn-v2-c30-d0-single-s0-t30"
    pids = out / "runs" / run_id / "pids.json"
    try:
        wait_until(lambda: pids.exists() or proc.poll() is not None, "the run started", timeout_s=240)
        assert proc.poll() is None, proc.stderr.read()
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, err
    assert not leftovers([run_id])
    assert not (out / "results.jsonl").exists() or not lines(out / "results.jsonl")
    assert "the same command resumes" in err


def test_the_delay_table_names_the_control_messages_it_cannot_read(tmp_path, caplog):
    """A run's object joins its sender's control message of the interval. One this build
    cannot read (here an earlier message version) leaves its objects out, and the run
    says how many it left; the JSON mirror of a readable one is not counted as unreadable."""
    import msgpack

    from deploy.record.recorder import McapLog
    from protocol.codec import encode
    from protocol.messages import ChannelStats, ControlMsg, ObjectMap, Pose

    def ctrl(vid: int) -> ControlMsg:
        om = ObjectMap(np.array([7]), np.array([500]), np.zeros((1, 2), np.float32), np.array([9]),
                       np.zeros((1, 1), np.float32), np.ones((1, 1), np.float32))
        return ControlMsg(3, 0.3, vid, Pose(0.0, 0.0, 0.0), 1.0, np.zeros((2, 3), np.float32), om, np.array([9]))

    old = msgpack.unpackb(encode(ctrl(2)))
    old[1] = ControlMsg.VERSION - 1
    stats = ChannelStats(3, 0.3, {"data": {"objects": [[1, 7, 0.0, 0.004], [2, 7, 0.0, 0.008]]}})
    path = tmp_path / "run.mcap"
    with open(path, "wb") as f:
        log = McapLog(f, {}, json_mirror=True)
        log.write("ac/r/net/ctrl/tx/1", encode(ctrl(1)), 1)
        log.write("ac/r/net/ctrl/tx/2", msgpack.packb(old), 2)
        log.write("ac/r/net/stats", encode(stats), 3)
        log.finish()
    with caplog.at_level("WARNING", logger="deploy.experiments.report"):
        sent = report.schedule_of_run(path)
    assert [(s.sender, s.object_id) for s in sent] == [(1, 7)]  # vehicle 2's object: no readable offer
    assert sent[0].reward == 1.0  # (1 - v) r of its one receiver
    warnings = [r.getMessage() for r in caplog.records if r.name == "deploy.experiments.report"]
    assert len(warnings) == 1 and "1 control messages unreadable" in warnings[0] and "version" in warnings[0]
