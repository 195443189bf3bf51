"""Scheduler domains (docs/domains.md): declared in the map, membership from a vehicle's
position, the agreement per domain, and the channel keys of each domain."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import keys
from protocol.codec import MalformedMessage, decode, encode
from protocol.messages import DEFAULT_DOMAIN, ControlMsg, Domain, MapMsg, ObjectMap, Pose
from vehicle_agent.agreement import AgreementConfig, group_schedule
from vehicle_agent.domains import GUARD_BAND_M, DomainTable, schedule_domains
from world_server.roadmap import CORRIDOR_SPACING_M, corridor, intersection
from world_server.scenarios import ScenarioParams, build

CFG = AgreementConfig()


def test_corridor_declares_three_domains_on_alternating_channels():
    m = corridor(3).to_msg()
    got = decode(encode(m), MapMsg).domains
    assert [(d.domain_id, d.x_m, d.y_m, d.radius_m, d.channel) for d in got] == [
        (0, -CORRIDOR_SPACING_M, 0.0, 85.0, 0), (1, 0.0, 0.0, 85.0, 1), (2, CORRIDOR_SPACING_M, 0.0, 85.0, 0)]
    for a, b in zip(got, got[1:]):  # neighbours overlap and never share a channel
        assert b.x_m - a.x_m < a.radius_m + b.radius_m and a.channel != b.channel


def test_a_map_without_domains_has_the_default_one():
    m = decode(encode(intersection().to_msg()), MapMsg)
    assert m.domains == [] and m.scheduler_domains() == [DEFAULT_DOMAIN]


@pytest.mark.parametrize("domains, error", [
    ([Domain(1, 0.0, 0.0, 85.0, 0)], "domain ids not 0, 1"),
    ([Domain(0, 0.0, 0.0, -1.0, 0)], "radius_m"),
    ([Domain(0, 5000.0, 0.0, 85.0, 0)], "x_m"),
    ([Domain(0, 0.0, 0.0, 85.0, -1)], "channel"),
])
def test_a_map_with_bad_domains_is_refused_naming_the_field(domains, error):
    m = intersection().to_msg()
    raw = encode(MapMsg(m.tick, m.t_sim_s, m.name, m.lanes, m.drivable, m.lights, m.buildings, domains))
    with pytest.raises(MalformedMessage, match=error):
        decode(raw, MapMsg)


def test_membership_by_position_both_in_the_overlap_nearest_outside():
    table = DomainTable.of(corridor(3).to_msg())
    assert table.membership(-150.0, 0.0) == (0,)
    assert table.membership(-75.0, 0.0) == (0, 1)  # 75 m from both centres: both
    assert table.membership(-150.0 + 85.0 + GUARD_BAND_M - 0.01, 0.0) == (0, 1)  # the guard band counts
    assert table.membership(-150.0 + 85.0 + GUARD_BAND_M + 0.01, 0.0) == (1,)
    assert table.membership(0.0, 200.0) == (1,)  # outside every circle: the nearest
    assert DomainTable.of(intersection().to_msg()).membership(500.0, 500.0) == (0,)  # one domain: always it


def test_domain_keys_keep_the_plain_keys_for_domain_zero_on_channel_zero():
    assert keys.net_ctrl_tx("r", 3) == keys.net_ctrl_tx("r", 3, 0, 0) == "ac/r/net/ctrl/tx/3"
    assert keys.net_data_rx("r", 1, 2) == "ac/r/net/c1/d2/data/rx"
    assert keys.net_ctrl_tx("r", "*", "*", "*") == "ac/r/net/**/ctrl/tx/*"
    assert keys.channel_domain_of(keys.net_data_tx("r", 4, 1, 2)) == (1, 2)
    assert keys.channel_domain_of(keys.net_data_tx("r", 4)) == (0, 0)
    assert keys.vid_of(keys.net_ctrl_tx("r", 7, 1, 1)) == 7
    assert keys.net_part(keys.net_ctrl_tx("r", 7, 1, 1)) == keys.net_part(keys.net_ctrl_tx("r", 7)) == "ctrl/tx/7"
    assert keys.net_part(keys.net_data_rx("r", 0, 2)) == "data/rx" and keys.net_part(keys.net_stats("r")) == "stats"
    assert keys.net_part(keys.report("r", 3)) == ""
    with pytest.raises(ValueError):
        keys.net_ctrl_tx("r", 1, -1, 0)


def test_corridor3_background_drives_across_domain_borders():
    s = build(ScenarioParams(scenario="corridor3", vehicles=40, duration_s=20.0))
    table = DomainTable.of(s.roadmap.to_msg())
    crossing = 0
    for a in s.actors:
        if a.role == "background" and a.speed_mps > 0:
            end = a.route[min(len(a.route) - 1, 1)]
            crossing += table.membership(*a.route[0]) != table.membership(*a.route[-1]) or \
                table.membership(*end) != table.membership(*a.route[0])
    assert crossing >= 5


# ------------------------------------------------------------------ agreement per domain


def _msg(vid: int, tick: int, heard, objects, xy, domains) -> ControlMsg:
    """``objects``: (object id, size, {receiver: relevance}) with visibility 0."""
    receivers = sorted({j for _, _, ys in objects for j in ys})
    rel = np.zeros((len(objects), len(receivers)), dtype=np.float32)
    for t, (_, _, ys) in enumerate(objects):
        for j, y in ys.items():
            rel[t, receivers.index(j)] = y
    om = ObjectMap(np.array([o for o, _, _ in objects], dtype=np.int64),
                   np.array([s for _, s, _ in objects], dtype=np.int64), np.zeros((len(objects), 2), np.float32),
                   np.array(receivers, dtype=np.int64), np.zeros(rel.shape, np.float32), rel)
    return ControlMsg(tick, tick * 0.1, vid, Pose(xy[0], xy[1], 0.0), 0.0, np.zeros((2, 3), np.float32), om,
                      np.array(sorted(heard), dtype=np.int64), domains=np.array(sorted(domains), dtype=np.int64))


@st.composite
def _domain(draw, vids, x0, domain):
    """Every vehicle's control message in one domain: random objects for the others."""
    out = {}
    for v in vids:
        n = draw(st.integers(0, 4))
        objects = [(100 * v + k, draw(st.integers(200, 4000)),
                    {j: draw(st.sampled_from([0.0, 0.5, 1.0])) for j in vids if j != v}) for k in range(n)]
        xy = (x0 + draw(st.floats(-60.0, 60.0)), draw(st.floats(-60.0, 60.0)))
        out[v] = (objects, xy)
    return out


@settings(max_examples=40, deadline=None)
@given(data=st.data(), n=st.integers(2, 9), n_other=st.integers(1, 6), tick=st.integers(1, 10_000),
       drop=st.lists(st.integers(0, 8), max_size=3))
def test_vehicles_that_heard_the_same_messages_of_a_domain_agree_on_its_schedule(data, n, n_other, tick, drop):
    """A is in domains 0 and 1, B in domain 0 only (or in 0 and 2); both heard the same
    messages of domain 0 (a few of them lost to both). Their schedules for domain 0 are
    the same, and so is A's whether or not it is also in domain 1."""
    vids = list(range(1, n + 1))
    a, b = vids[0], vids[-1]
    others = list(range(50, 50 + n_other))
    d0 = data.draw(_domain(vids, 0.0, 0))
    d1 = data.draw(_domain([a] + others, 150.0, 1))
    b_also = data.draw(st.booleans())  # B in a third domain of its own, or not
    lost = {vids[i % n] for i in drop} - {a, b}
    msgs0 = {v: _msg(v, tick, set(vids) - {v}, objs, xy, (0, 1) if v == a else (0, 2) if v == b and b_also else (0,))
             for v, (objs, xy) in d0.items()}
    msgs1 = {v: _msg(v, tick, set([a] + others) - {v}, objs, xy, (0, 1) if v == a else (1,))
             for v, (objs, xy) in d1.items()}
    heard0 = {me: [m for v, m in msgs0.items() if v != me and v not in lost] for me in (a, b)}
    got_a = schedule_domains(a, tick, {0: msgs0[a], 1: msgs1[a]}, {0: heard0[a], 1: list(msgs1.values())[1:]}, CFG)
    alone_a = schedule_domains(a, tick, {0: msgs0[a]}, {0: heard0[a]}, CFG)
    own_b = {0: msgs0[b]} | ({2: _msg(b, tick, [], [], (300.0, 0.0), (0, 2))} if b_also else {})
    got_b = schedule_domains(b, tick, own_b, {0: heard0[b]}, CFG)
    (dec_a, plan_a), (dec_b, _) = got_a[0], got_b[0]
    assert plan_a == alone_a[0][1]  # domain 1 changes nothing of A's domain-0 schedule
    np.testing.assert_array_equal(dec_a.members, dec_b.members)
    if dec_a.transmits and dec_b.transmits and np.array_equal(dec_a.group, dec_b.group):
        inst_a, _, sched_a = group_schedule(dec_a, CFG)
        inst_b, _, sched_b = group_schedule(dec_b, CFG)
        assert sched_a.frames == sched_b.frames
        np.testing.assert_array_equal(inst_a.reward, inst_b.reward)
        np.testing.assert_array_equal(inst_a.p_deliver, inst_b.p_deliver)


def test_domain_stats_count_members_handovers_and_collisions():
    from channel_proxy.domain_stats import summarise

    def interval(members, collided=0, dropped=0):
        return {"domains": {d: {"channel": int(d) % 2, "members": m,
                                "ctrl": {"senders": len(m), "overflow_msgs": dropped if d == "0" else 0},
                                "data": {"transmissions": 4, "collided_tx": collided, "delivered_bytes": 1000}}
                            for d, m in members.items()}}

    s = summarise([interval({"0": [1, 2], "1": [3]}), interval({"0": [1, 2], "1": [2, 3]}, 1, dropped=1),
                   interval({"0": [1], "1": [2, 3]}), {"ctrl": {}}])
    assert s.intervals == 3 and s.members["0"] == [2, 2, 1] and s.members["1"] == [1, 2, 2]
    assert s.joins == {"1": 1} and s.leaves == {"0": 1} and s.in_two == 1  # vehicle 2 handed over from 0 to 1
    assert s.transmissions == {"0": 12, "1": 12} and s.collided == {"0": 1, "1": 1}
    assert s.ctrl_sent == {"0": 5, "1": 5} and s.ctrl_dropped == {"0": 1, "1": 0}  # one of domain 0's 2 + 2 + 1 messages


def test_domain_stats_count_an_empty_interval_as_zero_and_the_load_on_the_air():
    from channel_proxy.domain_stats import run_summary, summarise, table

    def dom(members, offered_bytes):
        return {"channel": 0, "members": members, "data": {"transmissions": 1, "offered_bytes": offered_bytes}}

    # domain 1 has no member in the first and the third interval: the proxy's stats leave it out
    s = summarise([{"domains": {"0": dom([1, 2], 45_000)}},
                   {"domains": {"0": dom([1, 2], 9_000), "1": dom([2], 90_000)}},
                   {"domains": {"0": dom([1, 2], 0)}}])
    assert s.members == {"0": [2, 2, 2], "1": [0, 1, 0]}
    assert s.offered_bytes == {"0": [45_000, 9_000, 0], "1": [0, 90_000, 0]}
    assert s.joins == {"1": 1} and s.leaves == {"1": 1}  # vehicle 2 went into domain 1 and back out
    summary = run_summary(s, 90_000)
    assert summary["domains"]["1"] == {"channel": 0, "members": [0, 1, 0], "offered_bytes": [0, 90_000, 0],
                                       "joined": 1, "left": 1, "transmissions": 1, "collided": 0,
                                       "delivered_bytes": 0, "ctrl_sent": 0, "ctrl_dropped": 0}
    # load per interval: 45000 / 90000 = 0.5, 0.1, 0: median 0.10, max 0.50; domain 1: 0, 1, 0
    assert "| 0 | 0 | 2.0 (2-2) | 0 | 0 | 0.10 (0.50) |" in table(s, 90_000)
    assert "| 1 | 0 | 0.3 (0-1) | 1 | 1 | 0.00 (1.00) |" in table(s, 90_000)
