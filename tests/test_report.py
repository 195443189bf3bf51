"""``autocast report``'s offered-load table and plot: by model, scheme and density, from
each run's MCAP through ``deploy.experiments.load``, cached per run. (The report's other tables are
tested in tests/test_sweep.py.)"""

from __future__ import annotations

import json

import pytest

from deploy.experiments import load, report
from tests.test_load import three_intervals, write


def record(run_id: str, scheme: str, vehicles: int, share: float, model: str | None = None, **extra) -> dict:
    r = {"run_key": f"red_light-v{vehicles}-{scheme}-{run_id}", "run_id": run_id, "scheme": scheme,
         "vehicles": vehicles, "scenario": "red_light", "status": "judged", "outcome": "safe",
         "collider_visible_share": share, "collider_points_mean": 100.0, "reaction_time_s": 5.0,
         "closest_distance_m": 5.0, "exit_code": 0, **extra}
    return r if model is None else {**r, "model": model}


def summary(intervals: int, load_median: float | None, overloaded: float | None, offered: int, delivered: int,
            share_sent: float | None = 0.5) -> dict:
    return {"intervals": intervals, "load_median": load_median, "overloaded_share": overloaded,
            "share_sent_median": share_sent, "collider_offered_intervals": offered,
            "collider_delivered_intervals": delivered}


def test_cells_pool_the_intervals_and_keep_models_apart():
    pairs = [(record("a", "autocast", 10, 0.9), summary(100, 2.0, 1.0, 80, 40)),
             (record("b", "autocast", 10, 0.7), summary(300, 4.0, 0.5, 20, 20)),
             (record("c", "autocast", 10, 0.5, model="paper"), summary(10, 1.0, 0.0, 10, 5)),
             (record("d", "emp", 10, 0.4), summary(50, None, None, 10, 2, share_sent=None))]
    cells = report.load_by_density(pairs)
    ours = cells[("ours", "autocast", 10)]  # a record without "model" is ours
    assert ours.runs == 2
    assert ours.load_median == pytest.approx(3.0)  # median of the runs' medians
    assert ours.overloaded_share == pytest.approx((100 * 1.0 + 300 * 0.5) / 400)  # pooled over intervals
    assert ours.delivery_offered == pytest.approx(60 / 100)
    assert ours.delivery_all == pytest.approx(60 / 400)
    assert ours.visibility == pytest.approx(0.8)
    assert cells[("paper", "autocast", 10)].delivery_offered == pytest.approx(0.5)
    emp = cells[("ours", "emp", 10)]
    assert emp.load_median is None and emp.overloaded_share is None and emp.delivery_offered == pytest.approx(0.2)

    md = report.load_table_md(cells)
    assert md[0].startswith("| model | scheme | vehicles | runs | offered load / capacity (median) |")
    assert "| ours | emp | 10 | 1 | - | - | - | 20% | 4% | 40% |" in md
    assert "| ours | autocast | 10 | 2 | 3.00 | 62% | 0.50 | 60% | 15% | 80% |" in md
    alone = report.load_table_md({k: v for k, v in cells.items() if k[0] == "ours"})
    assert alone[0].startswith("| scheme | vehicles |")  # one model: no model column


@pytest.fixture
def sweep(tmp_path):
    """A sweep directory with one autocast run (the hand-made MCAP of tests/test_load.py,
    delivery 1 of 2 offered intervals, median load 0.8) and one single run."""
    run = tmp_path / "runs" / "r1"
    run.mkdir(parents=True)
    write(run / "run.mcap", three_intervals())
    records = [record("r1", "autocast", 3, 0.75), record("r2", "single", 3, 0.25)]
    (tmp_path / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    return tmp_path


def test_report_writes_the_load_table_and_plot_and_caches_each_run(sweep, monkeypatch):
    assert report.main([str(sweep)]) == 0
    assert (sweep / "report" / "load_vs_density.png").stat().st_size > 5000
    md = (sweep / "report" / "summary.md").read_text()
    assert "## Offered load and the collider's delivery by scheme x density" in md
    assert "| autocast | 3 | 1 | 0.80 | 33% | 0.62 | 50% | 33% | 75% |" in md
    assert "| single |" not in md.split("## Offered load")[1].split("##")[0]  # no channel, no row
    cached = json.loads((sweep / "report" / "load" / "r1.json").read_text())
    assert cached["summary"]["delivery_offered"] == 0.5

    def unread(path):
        raise AssertionError("read again despite the cache")

    monkeypatch.setattr(load, "interval_load", unread)
    assert report.main([str(sweep)]) == 0  # the second report reads the cache
    assert "| autocast | 3 | 1 | 0.80 |" in (sweep / "report" / "summary.md").read_text()


def test_a_changed_mcap_is_read_again_and_a_missing_one_is_named(sweep):
    mcap = sweep / "runs" / "r1" / "run.mcap"
    cache = sweep / "report" / "load" / "r1.json"
    first = report.run_load(mcap, cache)
    write(mcap, three_intervals()[:7])  # only its first interval now: delivered, 1 of 1
    assert report.run_load(mcap, cache)["delivery_offered"] == 1.0 != first["delivery_offered"]

    mcap.unlink()
    assert report.main([str(sweep)]) == 0
    md = (sweep / "report" / "summary.md").read_text()
    assert "No data" in md and "1 judged run with a channel left out, MCAP missing or unreadable: `r1`" in md


def test_visibility_over_the_encounter_is_the_mean_over_the_runs_that_have_it():
    records = [record("a", "autocast", 40, 0.9, collider_visible_share_encounter=1.0),
               record("b", "autocast", 40, 0.8, collider_visible_share_encounter=0.9),
               record("c", "autocast", 40, 0.7),  # recorded before the judge measured it
               record("d", "agnostic", 40, 0.98)]
    vis = report.visibility_by_density(records)
    assert vis[("autocast", 40)].share_mean == pytest.approx(0.8)
    assert vis[("autocast", 40)].encounter_mean == pytest.approx(0.95)
    assert vis[("agnostic", 40)].encounter_mean is None
