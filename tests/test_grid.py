"""The 2 x 2 grid (docs/domains.md, "The grid"): its junctions, domains and channels, the
roads through it, and the scenario on it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from protocol.codec import decode, encode
from protocol.messages import MapMsg
from vehicle_agent.domains import DomainTable
from world_server.geometry import arc_lengths, point_at
from world_server.roadmap import corridor, grid

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
