"""``autocast report``'s offered-load table and plot: by model, scheme and density, from
each run's MCAP through ``deploy.experiments.load``, cached per run; and, for runs of
several domains, the per-domain and handover tables (``channel_proxy.domain_stats``,
``deploy.experiments.handover``), cached the same way. (The report's other tables are
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


# ---------------------------------------------------------------------------- several domains


def test_only_scenarios_of_several_domains_get_the_network_tables():
    assert report.several_domains("corridor3") and report.several_domains("grid4")
    assert not report.several_domains("red_light") and not report.several_domains("no_such_scenario")


def domains_run(domains: dict[str, tuple[int, list[int], list[int], int, int, int, int]]) -> dict:
    """A run's ``domain_stats.run_summary``: domain -> (channel, members and bytes on the
    air per interval, joined, left, transmissions, collided[, control messages sent,
    dropped]); capacity 90,000 bytes."""
    return {"intervals": 3, "capacity_bytes": 90_000, "in_two": 0,
            "domains": {d: {"channel": c, "members": m, "offered_bytes": b, "joined": j, "left": lf,
                            "transmissions": tx, "collided": col, "delivered_bytes": 0,
                            **({"ctrl_sent": ctrl[0], "ctrl_dropped": ctrl[1]} if ctrl else {})}
                        for d, (c, m, b, j, lf, tx, col, *ctrl) in domains.items()}}


def tally(ticks: int, visible: int, points: int) -> dict:
    return {"ticks": ticks, "visible": visible, "points": points}


def event(crossings: int, around: dict, away: dict) -> dict:
    return {"event": "left_turn@J1", "ego": 0, "collider": 20, "window": tally(0, 0, 0),
            "crossings": [{"tick": 10 * i} for i in range(crossings)], "crossings_outside": 0,
            "around": around, "away": away}


def test_domain_cells_pool_the_runs_intervals():
    a = domains_run({"0": (0, [2, 3, 3], [9_000, 45_000, 0], 1, 0, 10, 2, 8, 1),
                     "1": (1, [1, 1, 0], [90_000, 0, 0], 0, 1, 4, 0)})  # read before control drops were counted
    b = domains_run({"0": (0, [4, 4], [18_000, 18_000], 3, 2, 30, 4, 8, 0)})
    pairs = [(record(r, "autocast", 20, 0.8, scenario="corridor3"), {"domains": d, "handover": []})
             for r, d in (("a", a), ("b", b))]
    pairs.append((record("s", "single", 20, 0.2, scenario="corridor3"), {"domains": None, "handover": []}))
    cells = report.domain_cells(pairs)
    assert set(cells) == {("ours", "corridor3", "autocast", 20, 0), ("ours", "corridor3", "autocast", 20, 1)}
    c = cells[("ours", "corridor3", "autocast", 20, 0)]
    # members 2 3 3 4 4: median 3, max 4; load 0.1 0.5 0 0.2 0.2: median 0.2, max 0.5
    assert (c.runs, c.intervals, c.members_median, c.members_max) == (2, 5, 3, 4)
    assert (c.joined_per_run, c.left_per_run) == (2.0, 1.0)
    assert c.load_median == pytest.approx(0.2) and c.load_max == pytest.approx(0.5)
    md = report.domain_table_md(cells)
    assert md[0] == ("| scenario | scheme | vehicles | domain | channel | runs | members per interval, median (max) | "
                     "joined per run | left per run | load per interval, median (max) | collided (of transmissions) | "
                     "control dropped (of sent) |")
    assert "| corridor3 | autocast | 20 | 0 | 0 | 2 | 3 (4) | 2.0 | 1.0 | 0.20 (0.50) | 15% (6/40) | 6% (1/16) |" in md
    assert "| corridor3 | autocast | 20 | 1 | 1 | 1 | 1 (1) | 0.0 | 1.0 | 0.00 (1.00) | 0% (0/4) | - |" in md


def test_handover_cells_pool_the_ticks_around_and_away():
    pairs = [(record("a", "autocast", 20, 0.8, scenario="corridor3"),
              {"domains": None, "handover": [event(2, tally(10, 4, 400), tally(20, 18, 1800))]}),
             (record("b", "autocast", 20, 0.8, scenario="corridor3"),
              {"domains": None, "handover": [event(0, tally(0, 0, 0), tally(30, 30, 3000))]}),
             (record("s", "single", 20, 0.2, scenario="corridor3"),
              {"domains": None, "handover": [event(1, tally(10, 1, 50), tally(20, 2, 100))]})]
    cells = report.handover_cells(pairs)
    c = cells[("ours", "corridor3", "left_turn@J1", "autocast", 20)]
    assert (c.runs, c.crossed, c.crossings) == (2, 1, 2)
    assert c.cost == pytest.approx(48 / 50 - 4 / 10)
    md = report.handover_table_md(cells)
    assert ("| corridor3 | left_turn@J1 | autocast | 20 | 2 | 1 | 2 | 40% (4/10), 40 pts | 96% (48/50), 96 pts "
            "| +56 |") in md
    assert "| corridor3 | left_turn@J1 | single | 20 | 1 | 1 | 1 | 10% (1/10), 5 pts | 10% (2/20), 5 pts | +0 |" in md
    assert md.index(next(r for r in md if "| single |" in r)) < md.index(next(r for r in md if "| autocast |" in r))
    alone = report.handover_table_md({k: report.HandoverCell(1, 0, 0, tally(0, 0, 0), tally(5, 5, 50))
                                      for k in cells})
    assert alone[-1].endswith("| 1 | 0 | 0 | - | 100% (5/5), 10 pts | - |")  # no crossing, no cost


def network_messages() -> list:
    """tests/test_handover.py's run (ego 0 joins domain 1 at tick 12, leaves 0 at tick 19)
    with the proxy's statistics: domain 0 has vehicles 0 and 1 until tick 18, then 1;
    domain 1 has vehicle 0 from tick 12. Each interval domain 0 puts 9 kB on the air,
    domain 1 45 kB, every one of its transmissions collided."""
    from protocol import keys
    from protocol.messages import ChannelStats
    from tests.test_handover import RUN, hand_made_messages

    msgs = hand_made_messages()
    for k in range(30):
        doms = {"0": {"channel": 0, "members": [0, 1] if k < 19 else [1],
                      "data": {"transmissions": 1, "offered_bytes": 9_000, "collided_tx": 0}}}
        if k >= 12:
            doms["1"] = {"channel": 1, "members": [0],
                         "data": {"transmissions": 1, "offered_bytes": 45_000, "collided_tx": 1}}
        msgs.append((keys.net_stats(RUN), ChannelStats(k, k * 0.1, {"domains": doms})))
    return msgs


@pytest.fixture
def network_sweep(tmp_path):
    """A sweep of corridor3 with one autocast run (its MCAP the hand-made one above) and one
    single run whose MCAP is not here."""
    run = tmp_path / "runs" / "n1"
    run.mkdir(parents=True)
    write(run / "run.mcap", network_messages(), {"run_id": "handover", "vehicles": "2", "scheme": "autocast"})
    records = [record("n1", "autocast", 20, 0.84, scenario="corridor3"),
               record("n2", "single", 20, 0.2, scenario="corridor3")]
    (tmp_path / "results.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    return tmp_path


def test_a_network_sweeps_report_has_the_domain_and_handover_tables_and_caches_each_run(network_sweep, monkeypatch):
    from channel_proxy import domain_stats
    from deploy.experiments import handover

    assert report.main([str(network_sweep)]) == 0
    md = (network_sweep / "report" / "summary.md").read_text()
    section = md.split("## Per domain: members, handovers, load, collisions")[1]
    # domain 0: members 2 (19 intervals) then 1 (11): median 2; load 9/90 every interval
    assert "| corridor3 | autocast | 20 | 0 | 0 | 1 | 2 (2) | 0.0 | 1.0 | 0.10 (0.10) | 0% (0/30) |" in section
    # domain 1: no member in 12 intervals, 1 in 18: median 1; load 0 then 0.5: median 0.5
    assert "| corridor3 | autocast | 20 | 1 | 1 | 1 | 1 (1) | 1.0 | 0.0 | 0.50 (0.50) | 100% (18/18) |" in section
    # around ticks 12 and 19: 7..23 without 20, 12 of 16 visible, 128 points; away: 0, 1, 2
    assert "| corridor3 | hand | autocast | 20 | 1 | 1 | 2 | 75% (12/16), 8 pts | 100% (3/3), 10 pts | +25 |" in section
    assert "1 judged run of several domains left out, MCAP missing or unreadable: `n2`." in section
    assert json.loads((network_sweep / "report" / "network" / "n1.json").read_text())["summary"]["domains"]

    def unread(path):
        raise AssertionError("read again despite the cache")

    monkeypatch.setattr(domain_stats, "read_summary", unread)
    monkeypatch.setattr(handover, "run_costs", unread)
    assert report.main([str(network_sweep)]) == 0  # the second report reads the cache
    again = (network_sweep / "report" / "summary.md").read_text()
    assert again.split("## Per domain")[1] == md.split("## Per domain")[1]


def test_a_changed_network_mcap_is_read_again(network_sweep):
    mcap = network_sweep / "runs" / "n1" / "run.mcap"
    cache = network_sweep / "report" / "network" / "n1.json"
    assert report.run_network(mcap, cache)["domains"]["intervals"] == 30
    without_stats = [m for m in network_messages() if type(m[1]).__name__ != "ChannelStats"]
    write(mcap, without_stats, {"run_id": "handover", "vehicles": "2", "scheme": "single"})
    got = report.run_network(mcap, cache)
    assert got["domains"] is None and got["handover"][0]["around"]["ticks"] == 16


def test_a_one_domain_sweep_has_no_network_tables_and_reads_nothing_for_them(sweep):
    assert report.main([str(sweep)]) == 0
    md = (sweep / "report" / "summary.md").read_text()
    assert "## Per domain" not in md and "## Handover cost" not in md
    assert not (sweep / "report" / "network").exists()


@pytest.mark.heavy
def test_a_short_real_sweep_of_grid4_handover_through_domain_stats_into_the_report(tmp_path):
    """``autocast sweep`` of grid4_handover at 10 vehicles for 3 s, Single and AutoCast,
    then the report: a row per domain for AutoCast (Single has no channel), a handover row
    per scheme, and the handover figures' whole window gives the judge's own visibility."""
    import subprocess
    import sys

    (tmp_path / "spec.toml").write_text(
        'scenarios = ["grid4_handover"]\ncollider_speeds_kmh = [30]\ndeltas_s = [0]\nvehicles = [10]\n'
        'schemes = ["single", "autocast"]\nseeds = [0]\nduration_s = 3\n')
    sweep = tmp_path / "sweep"
    proc = subprocess.run([sys.executable, "-m", "deploy.cli", "sweep", "--file", str(tmp_path / "spec.toml"),
                           "--out", str(sweep)], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert report.main([str(sweep)]) == 0
    md = (sweep / "report" / "summary.md").read_text().split("## Per domain")[1]
    for d, ch in ((0, 0), (1, 1), (2, 1), (3, 0)):
        assert f"| grid4_handover | autocast | 10 | {d} | {ch} | 1 |" in md
    assert "| grid4_handover | single | 10 |" not in md.split("## Handover cost")[0]
    for scheme in ("single", "autocast"):
        assert f"| grid4_handover | grid4_handover | {scheme} | 10 | 1 |" in md
    for r in map(json.loads, (sweep / "results.jsonl").read_text().splitlines()):
        net = json.loads((sweep / "report" / "network" / f"{r['run_id']}.json").read_text())["summary"]
        window = net["handover"][0]["window"]
        assert window["ticks"] == r["ticks"] == 30
        assert round(window["visible"] / window["ticks"], 4) == r["collider_visible_share"]
        assert round(window["points"] / window["ticks"], 2) == r["collider_points_mean"]
        assert (net["domains"] is None) == (r["scheme"] == "single")
