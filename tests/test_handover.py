"""``deploy.experiments.handover``: an event ego's border crossings and the collider's
visibility in its fused view around them and away from them, on hand-made per-tick
series and a hand-made MCAP, answers derived by hand."""

from __future__ import annotations

import numpy as np

from deploy.experiments import handover
from deploy.experiments.handover import Crossing
from protocol import keys
from protocol.messages import AgentReport, Domain, MapMsg, Outcome, WorldTruth
from tests.test_load import write

RUN = "handover"


def test_a_crossing_is_a_tick_whose_domains_differ_from_the_previous_ticks():
    got = handover.crossings([0, 1, 2, 3, 4, 5], [(0,), (0,), (0, 1), (0, 1), (1,), (0,)])
    assert got == [Crossing(2, (1,), ()), Crossing(4, (), (0,)), Crossing(5, (0,), (1,))]
    assert handover.crossings([0, 1], [(2,), (2,)]) == []


def test_around_is_the_second_centred_on_the_crossing_and_away_a_second_from_every_one():
    window = list(range(30))
    assert handover.around(window, 12) == [7, 8, 9, 10, 11, 12, 13, 14, 15, 16]  # k - 5 .. k + 4
    assert handover.around(window, 2) == [0, 1, 2, 3, 4, 5, 6]  # clipped at the window's start
    assert handover.around(window, 28) == [23, 24, 25, 26, 27, 28, 29]
    # at least 10 ticks from 12: up to 2 and from 22; ticks 3-6 and 17-21 are neither around nor away
    assert handover.away(window, [12]) == [0, 1, 2, *range(22, 30)]
    assert handover.away(window, [12, 35]) == [0, 1, 2, 22, 23, 24, 25]  # a crossing after the window counts
    assert handover.away(window, []) == window


def test_an_events_figures_from_a_hand_made_series():
    ticks = list(range(40))
    domains = [(0,)] * 12 + [(0, 1)] * 23 + [(1,)] * 5  # joins 1 at tick 12, leaves 0 at tick 35
    window = list(range(30))  # judged at tick 29: the crossing at 35 is after it
    points = {k: 0 if 10 <= k <= 13 else 10 for k in ticks if k != 14}  # no report at tick 14
    e = handover.event_cost("ev", 0, 9, ticks, domains, window, points)
    assert e["crossings"] == [{"tick": 12, "joined": [1], "left": [], "ticks": 9, "visible": 5, "points": 50}]
    assert e["crossings_outside"] == 1
    assert e["around"] == {"ticks": 9, "visible": 5, "points": 50}  # 7..16 without 14; 10..13 unseen
    assert e["away"] == {"ticks": 7, "visible": 7, "points": 70}  # 0, 1, 2 and 22..25 (10 from 35)
    assert e["window"] == {"ticks": 29, "visible": 25, "points": 250}
    assert handover.share(e["around"]) == 5 / 9 and handover.share({"ticks": 0, "visible": 0}) is None


def hand_made_run(path) -> None:
    write(path, hand_made_messages(), {"run_id": RUN, "vehicles": "2", "scheme": "autocast"})


def hand_made_messages() -> list[tuple[str, object]]:
    """Two domains overlapping between x = -6.8 and 6.8 (centres -30 and 30, radius 35, the
    1.8 m guard band); the ego drives east 2 m a tick from x = -30, so it joins domain 1 at
    tick 12 (x = -6) and leaves domain 0 at tick 19 (x = 8). The collider (vid 2) stands at
    (0, 20). The ego's fused view holds 10 of its points, 2 in ticks 10-13, and has no
    report at tick 20; the event is judged at 2.5 s, tick 25."""
    doms = [Domain(0, -30.0, 0.0, 35.0, 0), Domain(1, 30.0, 0.0, 35.0, 1)]
    msgs: list[tuple[str, object]] = [(keys.world_map(RUN), MapMsg(0, 0.0, "hand", [], [], [],
                                                                   np.zeros((0, 6)), doms))]
    for k in range(30):
        pose = np.array([[-30.0 + 2 * k, 0, 0], [0, -40, 0], [0, 20, 0]], np.float32)
        msgs.append((keys.world_truth(RUN), WorldTruth(k, k * 0.1, np.arange(3), pose, np.zeros(3, np.float32),
                                                       np.tile(np.array([4.5, 1.8, 1.5], np.float32), (3, 1)))))
        n = 2 if 10 <= k <= 13 else 10
        xy = np.array([[-1.0 + 0.2 * j, 20.0] for j in range(n)] + [[10.0, 10.0]], np.float32)  # one point elsewhere
        if k != 20:
            msgs.append((keys.report(RUN, 0), AgentReport(k, k * 0.1, 0, xy, 0, False)))
    msgs.append((keys.world_outcome(RUN), Outcome(25, 2.5, {"scenario": "hand", "vehicles": 2, "t_end_s": 2.5,
                                                            "outcome": "safe"})))
    return msgs


def test_a_runs_figures_from_its_log(tmp_path):
    hand_made_run(tmp_path / "run.mcap")
    [e] = handover.run_costs(tmp_path / "run.mcap")
    assert (e["event"], e["ego"], e["collider"]) == ("hand", 0, 2)
    assert [(c["tick"], c["joined"], c["left"]) for c in e["crossings"]] == [(12, [1], []), (19, [], [0])]
    assert e["crossings"][0] == {"tick": 12, "joined": [1], "left": [], "ticks": 10, "visible": 6,
                                "points": 6 * 10 + 4 * 2}  # ticks 7..16
    assert e["crossings"][1]["ticks"] == 9 and e["crossings"][1]["visible"] == 9  # 14..23 without 20
    assert e["around"] == {"ticks": 16, "visible": 12, "points": 12 * 10 + 4 * 2}  # 7..23 without 20
    assert e["away"] == {"ticks": 3, "visible": 3, "points": 30}  # 0, 1, 2: 10 ticks from 12 and 19
    assert e["window"] == {"ticks": 25, "visible": 21, "points": 21 * 10 + 4 * 2}  # 0..25 without 20


def test_the_cli_prints_each_event(tmp_path, capsys):
    hand_made_run(tmp_path / "run.mcap")
    assert handover.main([str(tmp_path / "run.mcap")]) == 0
    out = capsys.readouterr().out
    assert "hand (ego 0, collider 2): window 25 ticks, collider visible in 84%; 2 crossings in it" in out
    assert "  tick 12: joined [1], left -: visible in 6 of 10 ticks around it" in out
    assert "  around: 75% of 16 ticks; away: 100% of 3 ticks" in out
