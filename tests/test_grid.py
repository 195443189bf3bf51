"""The 2 x 2 grid (docs/domains.md, "The grid"): its junctions, domains and channels, the
roads through it, and the scenarios on it (grid4, grid4_handover), built and run."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from collections import defaultdict

import numpy as np
import pytest

from channel_proxy.domain_stats import read_stats, summarise
from deploy.record.recorder import read_messages
from protocol import keys
from protocol.codec import decode, encode
from protocol.messages import MapMsg, WorldTruth
from vehicle_agent.domains import DomainTable
from world_server.geometry import arc_lengths, point_at
from world_server.roadmap import corridor, grid
from world_server.scenarios import ScenarioError, ScenarioParams, build

EDGE_M = 75.0 + 8.0 + 130.0  # a junction 75 m off the axis, its 8 m half box, an edge arm of 130 m
NEIGHBOURS = {(0, 1), (2, 3), (0, 2), (1, 3)}  # J0 south-west, J1 south-east, J2 north-west, J3 north-east
DIAGONALS = {(0, 3), (1, 2)}


def test_grid_declares_four_domains_in_a_checkerboard():
    got = decode(encode(grid(2, 2).to_msg()), MapMsg).domains
    assert [(d.domain_id, d.x_m, d.y_m, d.radius_m, d.channel) for d in got] == [
        (0, -75.0, -75.0, 85.0, 0), (1, 75.0, -75.0, 85.0, 1), (2, -75.0, 75.0, 85.0, 1), (3, 75.0, 75.0, 85.0, 0)]
    for a, b in NEIGHBOURS:  # 150 m apart: they overlap by 20 m, on different channels
        assert math.dist((got[a].x_m, got[a].y_m), (got[b].x_m, got[b].y_m)) == 150.0
        assert got[a].channel != got[b].channel
    for a, b in DIAGONALS:  # 212 m apart: no overlap, the same channel
        assert math.dist((got[a].x_m, got[a].y_m), (got[b].x_m, got[b].y_m)) == pytest.approx(150.0 * math.sqrt(2))
        assert got[a].channel == got[b].channel


def test_the_junctions_joined_by_road_are_the_four_neighbours():
    m = grid(2, 2)
    joined = {tuple(sorted((int(a[1]), int(b[1])))) for a, b in m.straight_on.items() if a[:3] != b[:3]}
    assert joined == NEIGHBOURS
    assert m.straight_on["J0:E.out.0"] == "J1:W.in.0" and m.straight_on["J1:W.out.1"] == "J0:E.in.1"
    assert m.straight_on["J1:N.out.0"] == "J3:S.in.0" and m.straight_on["J3:S.out.1"] == "J1:N.in.1"
    assert len(m.lights) == 16 and [t.light_id for t in m.lights] == list(range(16))


def test_a_segments_middle_is_in_both_of_its_junctions_domains():
    table = DomainTable.of(grid(2, 2).to_msg())
    assert table.membership(0.0, -75.0) == (0, 1)  # 75 m from J0 and J1
    assert table.membership(-75.0, 0.0) == (0, 2)
    assert table.membership(75.0, 0.0) == (1, 3)
    assert table.membership(0.0, 75.0) == (2, 3)
    assert table.membership(-75.0, -75.0) == (0,)


def test_the_corridor_is_the_one_row_grid():
    c, g = corridor(3), grid(1, 3)
    assert (c.name, g.name) == ("corridor3", "grid1x3")
    assert list(c.lanes) == list(g.lanes)
    assert all(np.array_equal(c.lanes[k].centerline, g.lanes[k].centerline) for k in c.lanes)
    assert c.straight_on == g.straight_on and c.domains == g.domains and c.lights == g.lights
    assert np.array_equal(c.buildings, g.buildings)


@pytest.mark.parametrize("lane, start, end, domains", [
    # east on the southern road's inner lane (3.5 / 2 right of its centre line): J0, then J1
    ("J0:W.in.0", (-EDGE_M, -76.75), (EDGE_M, -76.75), [(0,), (0, 1), (1,)]),
    # north on the eastern road's outer lane (3 * 3.5 / 2 right of it): J1, then J3
    ("J1:S.in.1", (80.25, -EDGE_M), (80.25, EDGE_M), [(1,), (1, 3), (3,)]),
    # west on the northern road: J3, then J2
    ("J3:E.in.0", (EDGE_M, 76.75), (-EDGE_M, 76.75), [(3,), (2, 3), (2,)]),
])
def test_through_route_from_an_edge_crosses_two_junctions_and_a_domain_border(lane, start, end, domains):
    m = grid(2, 2)
    route = m.through_route(lane)
    assert route[0] == pytest.approx(start) and route[-1] == pytest.approx(end)
    assert arc_lengths(route)[-1] == pytest.approx(2 * EDGE_M)  # straight across the map
    table = DomainTable.of(m.to_msg())
    visited = []
    for xy in point_at(route, np.arange(0.0, 2 * EDGE_M, 1.0))[0]:
        here = table.membership(*xy)
        if not visited or visited[-1] != here:
            visited.append(here)
    assert visited == domains


# ------------------------------------------------------------------------ grid4


def test_grid4_places_the_left_turn_at_the_south_west_junction():
    s = build(ScenarioParams(scenario="grid4", vehicles=20))
    # the ego comes west on J0:E's inner lane (1.75 m north of the road's centre line y = -75) ...
    x0, y0, yaw0 = s.ego.start_pose()
    assert y0 == pytest.approx(-73.25) and yaw0 == pytest.approx(math.pi) and -67.0 < x0 < 0.0
    # ... and turns left (south) on a quarter circle of radius 9.75 about J0's south-east corner
    # (-67, -67); the collider drives east on y = -80.25: left_turn's crossing turned a quarter
    assert s.conflict_xy == pytest.approx((-75.0 - (math.sqrt(9.75**2 - 2.75**2) - 8.0), -80.25), abs=0.02)
    assert s.arrival_s(s.ego) == pytest.approx(7.0) and s.arrival_s(s.collider) == pytest.approx(7.0)
    assert s.collider.route[0][1] == pytest.approx(-80.25) and s.collider.route[-1] == pytest.approx((EDGE_M, -80.25))
    truck = next(a for a in s.actors if a.role == "occluder")  # 3.5 m past J0:W's stop line, in its inner lane
    assert truck.route[0] == pytest.approx((-83.0 + 3.5, -76.75)) and truck.speed_mps == 0.0
    east_west, north_south = {0: "red", 1: "green", 2: "red", 3: "green"}, {0: "green", 1: "red", 2: "green", 3: "red"}
    assert s.lights == {4 * j + k: state for j, axis in enumerate((east_west, east_west, north_south, north_south))
                        for k, state in axis.items()}


def test_grid4_refuses_an_ego_too_fast_for_the_segment_it_comes_from():
    # the ego's approach: J0:E.in.0 (150 / 2 - 8 = 67 m), then 9.75 acos(2.75 / 9.75) = 12.5 m of its
    # turn: 79.5 m, 7 s of it at 40 km/h (77.8 m) but not at 45 km/h (87.5 m)
    build(ScenarioParams(scenario="grid4", vehicles=5, ego_speed_kmh=40.0))
    with pytest.raises(ScenarioError, match="ego_speed_kmh: needs 88 m of approach, the map has 80 m"):
        build(ScenarioParams(scenario="grid4", vehicles=5, ego_speed_kmh=45.0))


def test_grid4_background_drives_through_to_the_maps_edge():
    s = build(ScenarioParams(scenario="grid4", vehicles=40))
    moving = [a for a in s.actors if a.role == "background" and a.speed_mps > 0]
    assert moving
    for a in moving:  # through_route ends on an edge arm, whatever segment the vehicle starts on
        assert np.abs(a.route[-1]).max() == pytest.approx(EDGE_M)


def test_grid4_handover_starts_the_ego_in_the_overlap_so_it_hands_over_on_its_way():
    from deploy.experiments.handover import Crossing, crossings

    s = build(ScenarioParams(scenario="grid4_handover", vehicles=20))
    # 9.5 s at 30 km/h = 79.2 m of approach: the turn's 9.75 acos(2.75 / 9.75) = 12.5 m and 66.7 m of
    # J0:E.in.0 (x from 0 to -67)
    x0, y0, yaw0 = s.ego.start_pose()
    arc = 9.75 * math.acos(2.75 / 9.75)
    assert (x0, y0, yaw0) == pytest.approx((9.5 * 30 / 3.6 - arc - 67.0, -73.25, math.pi), abs=0.01)  # a polyline arc
    assert s.arrival_s(s.ego) == pytest.approx(9.5) and s.arrival_s(s.collider) == pytest.approx(9.5)
    assert s.conflict_xy == pytest.approx(build(ScenarioParams(scenario="grid4", vehicles=20)).conflict_xy)
    assert sum(a.role == "traffic" for a in s.actors) == 1  # the collider starts 79 m out: room for one more
    # J1's reach (85 + 1.8 m) ends at x = 75 - sqrt(86.8^2 - 1.75^2) = -11.78, J0's at 11.78: the ego starts
    # in both and, at 30 km/h from x0 = -0.36, leaves J1 at tick 14 (x = -12.0)
    table = DomainTable.of(s.roadmap.to_msg())
    assert table.membership(x0, y0) == (0, 1)
    ticks = range(96)
    xy = point_at(s.ego.route, s.ego.speed_mps * 0.1 * np.array(ticks))[0]
    assert crossings(ticks, [table.membership(*p) for p in xy]) == [Crossing(14, (), (1,))]
    build(ScenarioParams(scenario="grid4_handover", vehicles=5, collider_speed_kmh=50.0))
    with pytest.raises(ScenarioError, match="collider_speed_kmh: needs 145 m of approach, the map has 137 m"):
        build(ScenarioParams(scenario="grid4_handover", vehicles=5, collider_speed_kmh=55.0))


RUN_TICKS = 30  # 3 s of sim time at T_d = 0.1 s


@pytest.mark.heavy
def test_a_grid4_run_hands_vehicles_over_between_domains_and_is_judged(tmp_path):
    """``autocast run`` of grid4 for 3 s, lock-step. Each interval the proxy counts as a
    domain's members exactly the vehicles whose true position puts them in it (within
    85 + 1.8 m of its centre, else the nearest), at least one vehicle changes domains,
    and the judge times the run out: in 3 s the ego covers at most 25 m of the 58 m to
    the conflict point, so neither a crash nor a near miss can happen."""
    proc = subprocess.run([sys.executable, "-m", "deploy.cli", "run", "--scenario", "grid4", "--vehicles", "20",
                           "--scheme", "autocast", "--duration", "3", "--seed", "0", "--json", "--out", str(tmp_path),
                           "--run-id", "grid4", "--scans", "none", "--log-level", "WARNING"],
                          capture_output=True, text=True, timeout=300)
    lines = proc.stdout.strip().splitlines()
    assert lines and lines[-1].startswith("{"), proc.stderr[-3000:]
    r = json.loads(lines[-1])
    assert r["scenario"] == "grid4" and r["ticks"] == RUN_TICKS and r["dead_agents"] == {}
    assert r["outcome"] == "deadlock" and r["t_end_s"] == 3.0 and r["closest_distance_m"] > 2.0
    assert proc.returncode == 1  # not safe

    truth, table = {}, None
    with open(r["mcap"], "rb") as f:
        for _, channel, message in read_messages(f, [keys.world_truth("grid4"), keys.world_map("grid4")]):
            if channel.topic == keys.world_map("grid4"):
                table = DomainTable.of(decode(message.data, MapMsg))
            else:
                t = decode(message.data, WorldTruth)
                truth[t.tick] = t
    stats = [s for s in read_stats(tmp_path / "grid4" / "run.mcap") if "domains" in s]
    assert table is not None and len(truth) == len(stats) == RUN_TICKS
    for tick, s in enumerate(stats):
        want = defaultdict(list)
        for vid, pose in zip(truth[tick].vids.tolist(), truth[tick].pose.tolist()):
            if vid < 20:  # the connected ones; the collider and its followers are 20 on
                for d in table.membership(pose[0], pose[1]):
                    want[str(d)].append(vid)
        assert {d: ds["members"] for d, ds in s["domains"].items()} == want, f"interval {tick}"
    handovers = summarise(stats)
    assert sum(handovers.joins.values()) + sum(handovers.leaves.values()) >= 1
