"""The agreement rule against hand-derived cases, and its promise: whatever each vehicle
heard, the vehicles that transmit laid out the same plan, so nothing collides."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from channel_proxy import loss, medium
from protocol.codec import MalformedMessage, _packed_to_wire, encode
from protocol.messages import ControlMsg, ObjectMap, Pose
from vehicle_agent.agreement import (AgreementConfig, HeardControl, agreed_p, agreed_state, decide, frames_of,
                                     group_of, group_schedule, members, n_groups, plan, unscheduled_after)
from vehicle_agent.scheduler import get, make_instance

GROUPED = AgreementConfig()


def msg(vid: int, tick: int, heard, objects=(), xy=(0.0, 0.0), unscheduled=None) -> ControlMsg:
    """``objects``: (object id, size, {receiver: y}), with v = 0 and r = y;
    ``unscheduled``: {object id: m} the sender reports (0 for the others)."""
    receivers = sorted({j for _, _, ys in objects for j in ys})
    n, m = len(objects), len(receivers)
    rel = np.zeros((n, m), dtype=np.float32)
    for t, (_, _, ys) in enumerate(objects):
        for j, y in ys.items():
            rel[t, receivers.index(j)] = y
    om = ObjectMap(np.array([o for o, _, _ in objects], dtype=np.int64), np.array([s for _, s, _ in objects], dtype=np.int64),
                   np.zeros((n, 2), np.float32), np.array(receivers, dtype=np.int64), np.zeros((n, m), np.float32), rel)
    m = np.array([(unscheduled or {}).get(o, 0) for o, _, _ in objects], dtype=np.int64)
    return ControlMsg(tick, tick * 0.1, vid, Pose(xy[0], xy[1], 0.0), 0.0, np.zeros((2, 3), np.float32), om,
                      np.array(sorted(heard), dtype=np.int64), m)


# ------------------------------------------------------------------ the steps


def test_members_are_those_enough_ballots_list():
    # votes: 1 by ballots 2 and 3; 2 by ballot 1 (its own listing does not count); 3 by 1 and 2; 9 by 3
    ballots = {1: [2, 3], 2: [1, 2, 3], 3: [1, 9]}
    assert members(ballots, 0.5).tolist() == [1, 3]  # need ceil(1.5) = 2 votes
    assert members(ballots, 0.3).tolist() == [1, 2, 3, 9]  # need 1
    assert members({1: [], 2: []}, 0.25).tolist() == []  # first interval: nobody was heard yet
    assert members({1: [2, 2], 3: np.array([], dtype=np.int64)}, 1.0).tolist() == []  # listing twice: one vote
    assert members({1: {2}, 3: (2,)}, 1.0).tolist() == [2]


def test_membership_agrees_under_heavy_loss():
    # 40 vehicles, 30% independent loss: every vehicle holds different ballots, all agree on M
    rng = np.random.default_rng(0)
    vids = np.arange(40)
    heard_last = {v: [u for u in vids if u != v and rng.random() > 0.3] for v in vids}
    views = []
    for v in vids:
        ballots = {v: heard_last[v]} | {u: heard_last[u] for u in vids if u != v and rng.random() > 0.3}
        views.append(tuple(members(ballots, GROUPED.quorum).tolist()))
    assert set(views) == {tuple(vids.tolist())}


def test_group_count_and_frames():
    assert [n_groups(m, 4, 10) for m in (0, 3, 4, 5, 20, 40, 100)] == [0, 1, 1, 2, 5, 10, 10]
    assert n_groups(40, None, 10) == 1
    assert frames_of(1, 3, 10) == (1, 4, 7)
    assert sorted(f for g in range(3) for f in frames_of(g, 3, 10)) == list(range(10))


def test_groups_are_balanced_rotate_and_ignore_input_order():
    vids = np.arange(100, 140)
    g = group_of(vids, 7, 10)
    assert np.bincount(g).tolist() == [4] * 10
    shuffled = np.random.default_rng(1).permutation(vids)
    assert dict(zip(shuffled.tolist(), group_of(shuffled, 7, 10).tolist())) == dict(zip(vids.tolist(), g.tolist()))
    assert not np.array_equal(g, group_of(vids, 8, 10))  # a new grouping every tick


# ------------------------------------------------------------------ hand-derived plans

# two vehicles 10 m apart (p = 1): 1 offers object 5 (900 B, worth 1.0 to 2), 2 offers
# object 6 (900 B, worth 0.5 to 1). Greedy puts both in frame 0; the TDMA layout sends
# the larger reward first: 1 in [0, 1 ms), 2 in [1, 2 ms).
A = msg(1, 3, [2], [(5, 900, {2: 1.0})], xy=(0.0, 0.0))
B = msg(2, 3, [1], [(6, 900, {1: 0.5})], xy=(10.0, 0.0))


def test_complete_vehicles_share_one_plan():
    da, db = decide(1, 3, A, [B], GROUPED), decide(2, 3, B, [A], GROUPED)
    assert da.members.tolist() == [1, 2] and da.frames == tuple(range(10)) and da.transmits
    assert [(t.object_id, t.start_s, t.size_bytes, t.frame) for t in plan(da, GROUPED)] == [(5, 0.0, 900, 0)]
    assert [(t.object_id, round(t.start_s, 9), t.frame) for t in plan(db, GROUPED)] == [(6, 0.001, 0)]


def test_the_paper_rule_collides_when_one_vehicle_missed_the_other():
    heard = AgreementConfig(rule="heard")
    pa = plan(decide(1, 3, A, [B], heard), heard)
    pb = plan(decide(2, 3, B, [], heard), heard)  # 2 did not hear 1: it schedules itself first
    assert pa[0].start_s == 0.0 and pb[0].start_s == 0.0  # both claim [0, 1 ms)


def test_a_vehicle_that_missed_a_group_member_stays_silent():
    # three vehicles, one group; all heard each other last interval; now 2 misses 1's message
    a = msg(1, 3, [2, 4], [(5, 900, {2: 1.0})], xy=(0.0, 0.0))
    b = msg(2, 3, [1, 4], [(6, 900, {1: 0.5})], xy=(10.0, 0.0))
    c = msg(4, 3, [1, 2], [], xy=(20.0, 0.0))
    db = decide(2, 3, b, [c], GROUPED)
    assert db.members.tolist() == [1, 2, 4] and db.missing.tolist() == [1] and not db.transmits
    assert plan(db, GROUPED) == ()
    assert plan(decide(1, 3, a, [b, c], GROUPED), GROUPED)[0].start_s == 0.0  # 1 heard everyone: sends as planned
    assert not decide(2, 3, b, [], GROUPED).transmits  # heard nobody: not even a member in its own view


def test_a_newcomer_is_not_a_member_and_does_not_transmit():
    C = msg(3, 3, [1, 2], [(7, 900, {1: 1.0})])
    d = decide(3, 3, C, [A, B], GROUPED)  # nobody listed 3 last interval
    assert d.members.tolist() == [1, 2] and not d.is_member and plan(d, GROUPED) == ()


def test_missing_a_member_of_another_group_does_not_matter():
    # 8 vehicles in 2 groups of 4; vehicle v misses exactly one vehicle of the other group
    vids = list(range(8))
    msgs = {v: msg(v, 5, [u for u in vids if u != v], [(v * 10, 900, {(v + 1) % 8: 1.0})]) for v in vids}
    g = dict(zip(vids, group_of(np.array(vids), 5, 2).tolist()))
    for v in vids:
        other = next(u for u in vids if g[u] != g[v])
        d = decide(v, 5, msgs[v], [msgs[u] for u in vids if u not in (v, other)], GROUPED)
        assert d.transmits and d.frames == frames_of(g[v], 2, 10)
        assert all(t.frame in d.frames for t in plan(d, GROUPED))


def test_round_robin_starts_at_the_member_the_tick_picks():
    # one group [1, 2], each offering six 8000 B objects: agnostic fills one 9000 B frame
    # each, ten frames for twelve objects, starting at member group[tick mod 2]: that
    # member sends all six, the other its first four
    agn = AgreementConfig(scheduler="agnostic")
    for tick, first in ((3, 2), (4, 1)):
        a = msg(1, tick, [2], [(k, 8000, {2: 1.0}) for k in range(6)], xy=(0.0, 0.0))
        b = msg(2, tick, [1], [(k, 8000, {1: 1.0}) for k in range(6)], xy=(10.0, 0.0))
        sent = {1: plan(decide(1, tick, a, [b], agn), agn), 2: plan(decide(2, tick, b, [a], agn), agn)}
        assert len(sent[first]) == 6 and [t.object_id for t in sent[3 - first]] == [0, 1, 2, 3]


def test_heard_order_does_not_change_the_plan():
    vids = list(range(6))
    msgs = [msg(v, 2, [u for u in vids if u != v], [(v, 500 + 100 * v, {(v + 1) % 6: 0.5, (v + 2) % 6: 1.0})],
                xy=(5.0 * v, 0.0)) for v in vids]
    a = plan(decide(0, 2, msgs[0], msgs[1:], GROUPED), GROUPED)
    b = plan(decide(0, 2, msgs[0], msgs[:0:-1], GROUPED), GROUPED)
    assert a == b


# ------------------------------------------------------------------ the promise


def transmissions_under_loss(n: int, q: float, seed: int, config: AgreementConfig):
    """Every vehicle's plan when each control message reaches each receiver w.p. 1 - q."""
    rng = np.random.default_rng(seed)
    vids = list(range(100, 100 + n))
    heard_last = {v: [u for u in vids if u != v and rng.random() > q] for v in vids}
    msgs = {}
    for v in vids:
        objs = [(v * 100 + k, int(rng.integers(1000, 5000)), {int(j): float(rng.random())
                for j in rng.choice([u for u in vids if u != v], 3, replace=False)}) for k in range(4)]
        msgs[v] = msg(v, 9, heard_last[v], objs, xy=tuple(rng.uniform(-40, 40, 2)))
    sender, start, size, item = [], [], [], []
    for c, v in enumerate(vids):
        heard_now = [msgs[u] for u in vids if u != v and rng.random() > q]
        for t in plan(decide(v, 9, msgs[v], heard_now, config), config):
            sender.append(c), start.append(t.start_s), size.append(t.size_bytes), item.append(t.object_id)
    return np.array(vids), np.array(sender, int), np.array(start), np.array(size, int), np.array(item, int)


@pytest.mark.parametrize("q", [0.1, 0.3])
def test_grouped_plans_never_overlap_whatever_each_vehicle_heard(q):
    for seed in range(3):
        vids, sender, start, size, item = transmissions_under_loss(40, q, seed, GROUPED)
        assert len(sender) > 0
        ones = np.ones((40, 40))
        out = medium.play_data(vids, sender, item, start, size, ones, ones.astype(bool), bandwidth_bps=7.2e6,
                               interval_s=0.1, seed=0, tick=0)
        assert not out.collided.any() and not out.overflow.any()


def test_the_paper_rule_collides_under_the_same_loss():
    vids, sender, start, size, item = transmissions_under_loss(40, 0.1, 0, AgreementConfig(rule="heard"))
    ones = np.ones((40, 40))
    out = medium.play_data(vids, sender, item, start, size, ones, ones.astype(bool), bandwidth_bps=7.2e6,
                           interval_s=0.1, seed=0, tick=0)
    assert out.collided.any(axis=1).mean() > 0.2


# ------------------------------------------------------------------ starvation, agreed


# one 9000 B frame per interval (T_n = 10 ms, N = 1); 1 and 2 are 10 m apart (p = 1).
# 1 offers object 5 (8000 B, y = 1.0 to 2), 2 offers object 6 (8000 B, y = 0.9 to 1):
# one fits a frame. Plain H/s always picks 5. With m reported by the senders: interval
# 3, m = (0, 0): 5; 2 counts m = 1 for 6. Interval 4: m = (0, 1), mean 0.5, var 0.25 ->
# max(var, 1) = 1, boost 1 + m = 2 for 6: 1.8 / 8000 > 1.0 / 8000, so 6; 1 counts m = 1
# for 5. Interval 5: 5 again (2.0 > 0.9), and so on.
ONE_FRAME = AgreementConfig(n_frames=1)


def _pair(tick, m1, m2, heard=(1, 2, 3)):
    a = msg(1, tick, [v for v in heard if v != 1], [(5, 8000, {2: 1.0})], xy=(0.0, 0.0), unscheduled=m1)
    b = msg(2, tick, [v for v in heard if v != 2], [(6, 8000, {1: 0.9})], xy=(10.0, 0.0), unscheduled=m2)
    return a, b


def test_reported_starvation_alternates_two_objects_that_do_not_fit_together():
    m1, m2, sent = {}, {}, []
    for tick in (3, 4, 5, 6):
        a, b = _pair(tick, m1, m2, heard=(1, 2))
        pa, pb = plan(decide(1, tick, a, [b], ONE_FRAME), ONE_FRAME), plan(decide(2, tick, b, [a], ONE_FRAME), ONE_FRAME)
        sent.append([(t.object_id, t.start_s) for t in pa + pb])
        m1, m2 = unscheduled_after(a, [t.object_id for t in pa]), unscheduled_after(b, [t.object_id for t in pb])
    assert sent == [[(5, 0.0)], [(6, 0.0)], [(5, 0.0)], [(6, 0.0)]]
    assert (m1, m2) == ({5: 1}, {})
    plain = AgreementConfig(n_frames=1, scheduler="greedy-plain")
    a, b = _pair(4, {}, {6: 1}, heard=(1, 2))
    assert [t.object_id for t in plan(decide(1, 4, a, [b], plain), plain)] == [5]  # without compensation: 5 again


def test_a_vehicle_that_missed_last_interval_still_weighs_alike():
    # 3 heard nothing in interval 3 and kept no counters of the others; in interval 4 it
    # hears 1 and 2, whose messages carry m: its group schedule is theirs
    a, b = _pair(4, {}, {6: 1})
    c = msg(3, 4, [1, 2], [], xy=(20.0, 0.0))
    views = [decide(1, 4, a, [b, c], ONE_FRAME), decide(2, 4, b, [c, a], ONE_FRAME), decide(3, 4, c, [a, b], ONE_FRAME)]
    assert all(d.transmits for d in views)
    schedules = [group_schedule(d, ONE_FRAME) for d in views]
    assert {s.keyed(i) for i, _, s in schedules} == {(((2, 6),),)}
    assert all(st.starved() == {(2, 6): 1} for _, st, _ in schedules)
    # a vehicle that missed 2's message now does not transmit at all
    assert not decide(3, 4, c, [a], ONE_FRAME).transmits
    assert agreed_state(decide(1, 4, a, [b, c], ONE_FRAME)).starved() == {(2, 6): 1}


def test_unscheduled_counts_only_wanted_objects_left_out():
    own = msg(1, 3, [2], [(5, 900, {2: 1.0}), (6, 900, {2: 0.0}), (7, 900, {2: 0.5})], unscheduled={7: 2, 6: 4})
    assert unscheduled_after(own, [5]) == {7: 3}  # 5 sent, 6 wanted by nobody: m = 0
    assert unscheduled_after(own, []) == {5: 1, 7: 3}  # a silent vehicle skipped them all


def test_starvation_agrees_and_never_collides_over_intervals_under_loss():
    """20 vehicles, 20% control loss, 6 intervals; each sender counts its own objects'
    m from its own plan and reports them. Every interval: no two transmissions
    overlap, and all complete members of a group hold the same compensated state and
    schedule, whatever else each of them heard or missed."""
    rng = np.random.default_rng(21)
    vids = list(range(200, 220))
    q = 0.2
    objects = {v: [(v * 100 + k, int(rng.integers(2000, 6000)),
                    {int(j): float(rng.uniform(0.2, 1.0)) for j in rng.choice([u for u in vids if u != v], 2, replace=False)})
                   for k in range(4)] for v in vids}
    xy = {v: tuple(rng.uniform(-40, 40, 2)) for v in vids}
    heard_last = {v: [u for u in vids if u != v] for v in vids}
    counters = {v: {} for v in vids}
    reported, differs, agreed_groups = 0, 0, 0
    for tick in range(10, 16):
        msgs = {v: msg(v, tick, heard_last[v], objects[v], xy=xy[v], unscheduled=counters[v]) for v in vids}
        reported += sum(int((m.unscheduled > 0).sum()) for m in msgs.values())
        sender, start, size, item, by_group = [], [], [], [], {}
        for c, v in enumerate(vids):
            heard_now = [msgs[u] for u in vids if u != v and rng.random() > q]
            heard_last[v] = sorted(m.vid for m in heard_now)
            d = decide(v, tick, msgs[v], heard_now, GROUPED)
            mine = plan(d, GROUPED)
            counters[v] = unscheduled_after(msgs[v], [t.object_id for t in mine])
            for t in mine:
                sender.append(c), start.append(t.start_s), size.append(t.size_bytes), item.append(t.object_id)
            if d.transmits:
                inst, state, s = group_schedule(d, GROUPED)
                by_group.setdefault(tuple(d.group.tolist()), set()).add(
                    (s.keyed(inst), tuple(state.starvation(inst).tolist())))
                differs += s.primary().keyed(inst) != get("greedy-plain")(inst, state).keyed(inst)
        assert all(len(views) == 1 for views in by_group.values())  # one compensated schedule per group
        agreed_groups += len(by_group)
        n = len(vids)
        out = medium.play_data(np.array(vids), np.array(sender, int), np.array(item, int), np.array(start),
                               np.array(size, int), np.ones((n, n)), np.ones((n, n), bool), bandwidth_bps=7.2e6,
                               interval_s=0.1, seed=0, tick=tick)
        assert not out.collided.any() and not out.overflow.any()
    assert reported > 20 and differs > 0 and agreed_groups > 20  # compensation was in play and changed schedules


def test_the_agreed_link_table_equals_asking_pair_by_pair():
    """p_ij as one matrix (what make_instance uses) equals the per-pair answers, also
    for a vehicle without a control message (the domain-radius model)."""
    heard = [msg(v, 4, [1, 2, 3], [(7, 900, {1: 1.0})] if v == 2 else (), xy=(30.0 * v, 5.0 * v)) for v in (2, 3)]
    decision = decide(1, 4, msg(1, 4, [2, 3], xy=(0.0, 0.0)), heard, AgreementConfig(rule="heard"))
    links = agreed_p(decision, GROUPED)
    vids = [1, 2, 3, 9]
    pairwise = np.array([[links(i, j) for j in vids] for i in vids])
    assert links.matrix(vids) == pytest.approx(pairwise)
    assert links(1, 9) == links.outside and 0.0 < links(1, 3) < links(1, 2) <= 1.0
    offers = {v: m.objects for v, m in decision.messages.items()}
    by_table = make_instance(offers, links, vids=vids)
    by_pair = make_instance(offers, lambda i, j: links(i, j), vids=vids)
    assert np.array_equal(by_table.p_deliver, by_pair.p_deliver) and by_table.p_deliver[0, 0] == 1.0


def test_config_checks_and_profile():
    with pytest.raises(ValueError):
        AgreementConfig(rule="vote")
    with pytest.raises(ValueError):
        AgreementConfig(group_size=0)
    from channel_proxy.profiles import get_profile
    cfg = AgreementConfig.from_profile(get_profile("dsrc"))
    assert cfg.n_frames == 1 and cfg.bandwidth_bps == 6e6 and cfg.prr == loss.PrrModel(range_m=150.0)


@given(tick=st.integers(0, 2**31), vids=st.lists(st.integers(0, 2**40), max_size=50, unique=True),
       salt=st.integers(0, 2**64 - 1))
def test_the_grouping_draws_are_the_channels_keyed_draws(tick, vids, salt):
    """The one-pass draws against channel_proxy.loss.keyed_uniform, bit for bit."""
    from channel_proxy.loss import keyed_uniform, keyed_uniform_1d

    got = keyed_uniform_1d(salt, tick, np.array(vids, dtype=np.int64))
    np.testing.assert_array_equal(got, keyed_uniform(salt, tick, np.array(vids, dtype=np.int64)))


@given(ballots=st.dictionaries(st.integers(0, 60), st.lists(st.integers(0, 60), max_size=40), max_size=40)
       | st.dictionaries(st.integers(-5, 70_000), st.lists(st.sampled_from([-2, 0, 3, 65_535, 65_536, 69_999]),
                                                             max_size=8), max_size=8),
       sort=st.booleans(), quorum=st.sampled_from([0.0, 0.1, 0.5, 1.0]))
def test_members_equal_counting_each_ballots_distinct_others(ballots, sort, quorum):
    """members against its definition, ballot by ballot: ascending heard lists (as
    control messages carry them, the fast path) and unsorted ones with repeats."""
    import math

    from vehicle_agent.agreement import members

    if sort:
        ballots = {a: sorted(set(h)) for a, h in ballots.items()}
    votes: dict[int, int] = {}
    for author, heard in ballots.items():
        for v in set(heard) - {author}:
            votes[v] = votes.get(v, 0) + 1
    need = max(1, math.ceil(quorum * len(ballots) - 1e-9))
    want = sorted(v for v, n in votes.items() if n >= need)
    got = members({a: np.array(h, dtype=np.int64) for a, h in ballots.items()}, quorum)
    assert got.dtype == np.int64 and got.tolist() == want


def test_the_quorum_kernel_by_hand():
    """Ballots of 1: [2, 3], 2: [1, 2, 3] (its own listing does not count), 3: [2, 2]
    (one vote): 2 has the votes of 1 and 3, 3 of 1 and 2, 1 of 2 alone."""
    from vehicle_agent.agreement import _listed_by_quorum

    author = np.array([1, 2, 3], dtype=np.int64)
    vid = np.array([2, 3, 1, 2, 3, 2, 2], dtype=np.int64)
    lengths = np.array([2, 3, 2], dtype=np.int64)
    assert _listed_by_quorum(author, vid, lengths, 2).tolist() == [2, 3]
    assert _listed_by_quorum(author, vid, lengths, 1).tolist() == [1, 2, 3]
    assert _listed_by_quorum(author, vid, lengths, 3).tolist() == []
    assert _listed_by_quorum(author, np.array([2, 3, 1, 2, 1 << 16, 2, 2]), lengths, 1) is None  # numpy's to count


def _broken_map(m: ControlMsg) -> bytes:
    """``m`` encoded, its object map's visibility bytes cut short (the rest intact)."""
    body = msgpack.unpackb(encode(m))
    objects = body[2 + 6]  # the envelope's type and version, then tick .. trajectory
    objects[4][2] = objects[4][2][:-1]
    return msgpack.packb(body)


def test_heard_controls_decide_as_whole_messages_and_open_only_the_groups_maps():
    """``decide`` on ``HeardControl`` (ballot and motion read, object map not) gives the
    decision and plan the whole messages give; it opens the object maps of its group's
    members only: with every heard map broken, only those members are malformed, and
    missing, and the vehicle stays silent."""
    vids = list(range(12))
    msgs = {v: msg(v, 5, [u for u in vids if u != v], [(100 + v, 900, {(v + 1) % 12: 1.0})], xy=(3.0 * v, 0.0))
            for v in vids}
    for v in vids:
        others = [msgs[u] for u in vids if u != v]
        whole = decide(v, 5, msgs[v], others, GROUPED)
        lazy = decide(v, 5, msgs[v], [HeardControl.read(encode(m)) for m in others], GROUPED)
        assert whole.members.tolist() == lazy.members.tolist() and whole.group.tolist() == lazy.group.tolist()
        assert list(lazy.messages) == list(whole.messages) and not lazy.malformed and whole.transmits
        assert plan(lazy, GROUPED) == plan(whole, GROUPED)
        broken = decide(v, 5, msgs[v], [HeardControl.read(_broken_map(m)) for m in others], GROUPED)
        assert broken.members.tolist() == whole.members.tolist()  # the ballots were still read
        peers = sorted(set(whole.group.tolist()) - {v})
        assert sorted(broken.malformed) == peers and broken.missing.tolist() == peers
        assert not broken.transmits and plan(broken, GROUPED) == ()
        assert "visibility" in str(broken.malformed[peers[0]])


def test_a_heard_control_whose_ballot_is_malformed_is_refused():
    body = msgpack.unpackb(encode(msg(2, 5, [1, 3])))
    body[2 + 7] = ["<i8", [2], b"\x00"]  # heard: one byte for two int64
    with pytest.raises(MalformedMessage, match=r"ControlMsg\.heard"):
        HeardControl.read(msgpack.packb(body))


def _with_field(m: ControlMsg, at: int, value) -> bytes:
    """``m`` encoded with field ``at`` (0: tick) replaced on the wire by ``value``."""
    body = msgpack.unpackb(encode(m))
    body[2 + at] = value
    return msgpack.packb(body)


def _wire(a: np.ndarray) -> list:
    return [a.dtype.str, list(a.shape), a.tobytes()]


@pytest.mark.parametrize("at, value, field", [
    (5, _wire(np.zeros((4, 2), np.float32)), "trajectory"),  # two columns: a planner indexes the third
    (5, _wire(np.zeros(12, np.float32)), "trajectory"),
    (5, _wire(np.zeros((4, 3), np.float64)), "trajectory"),
    (7, _wire(np.zeros((2, 1), np.int64)), "heard"),
    (7, _wire(np.zeros(2, np.int32)), "heard"),
], ids=["two-columns", "flat", "float64", "column", "int32"])
def test_a_heard_control_of_another_shape_or_dtype_than_declared_is_dropped_and_counted(at, value, field):
    """Well-formed arrays, but not what ``ControlMsg`` declares: before, such a message
    was read and its trajectory went on to the neighbour table and the planner, which
    index three columns; now it is refused and counted, and the rest of the bundle is read."""
    from protocol.messages import CtrlBundle
    from protocol.session import DropCounter
    from vehicle_agent.link import heard_in

    good, bad = msg(1, 5, [2, 3]), _with_field(msg(2, 5, [1, 3]), at, value)
    with pytest.raises(MalformedMessage, match=rf"ControlMsg\.{field}: expected"):
        HeardControl.read(bad)
    bundle = CtrlBundle(5, 0.5, np.array([1, 2]), np.array([3]), np.ones((1, 2), bool), [encode(good), bad])
    drops = DropCounter()
    heard = heard_in(bundle, 3, drops)
    assert [h.vid for h in heard] == [1] and drops.total == 1


def test_an_object_map_whose_rows_do_not_fit_is_refused_when_opened_and_never_sent():
    """An object map is n objects by m receivers in every array; one that is not
    (here a relevance table of one column for two receivers) is malformed for the group
    that opens it, and a sender cannot build one."""
    m = msg(1, 5, [2], [(100, 900, {2: 1.0, 3: 0.5})])
    body = msgpack.unpackb(encode(m))
    body[2 + 6][5] = _packed_to_wire(np.zeros((1, 1), np.float32))  # relevance (1, 1) for receivers [2, 3]
    heard = HeardControl.read(msgpack.packb(body))  # the ballot and the motion are fine
    with pytest.raises(MalformedMessage, match=r"ControlMsg\.objects: 1 objects and 2 receivers"):
        heard.message()
    om = m.objects
    with pytest.raises(ValueError, match="1 objects and 2 receivers"):
        ObjectMap(om.object_id, om.size_bytes, om.centroid_xy, om.receivers, om.visibility, om.relevance[:, :1])
    with pytest.raises(TypeError, match=r"ControlMsg\.trajectory: expected float32 \(n, 3\), got float64"):
        encode(ControlMsg(5, 0.5, 1, m.pose, 0.0, np.zeros((2, 3)), om, m.heard))


def agreed_state_reference(decision):
    """``agreed_state`` as it was (ec93cfa): numpy arrays per message, one lexsort."""
    from vehicle_agent.scheduler import SchedulerState

    if len(decision.group) == 0:
        return SchedulerState()
    first = int(decision.group[decision.tick % len(decision.group)])
    vid, oid, m = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for v, one in decision.messages.items():
        counts = one.starvation()
        starved = counts > 0
        vid.append(np.full(int(starved.sum()), v, dtype=np.int64))
        oid.append(np.asarray(one.objects.object_id, dtype=np.int64)[starved])
        m.append(counts[starved])
    vid, oid, m = np.concatenate(vid), np.concatenate(oid), np.concatenate(m)
    order = np.lexsort((oid, vid))
    return SchedulerState(np.stack([vid[order], oid[order]], axis=1), m[order], cursor=(first, -(1 << 62)))


@given(data=st.data(), n_senders=st.integers(1, 5), tick=st.integers(0, 50))
def test_agreed_state_is_the_numpy_one(data, n_senders, tick):
    """agreed_state against the per-message numpy version it replaced: the same keys and
    counts, bit for bit, for counts reported right, negative, of the wrong length or
    dtype, and object ids out of order or repeated."""
    from vehicle_agent.agreement import Decision

    vids = sorted(data.draw(st.lists(st.integers(0, 40), min_size=n_senders, max_size=n_senders, unique=True)))
    messages = {}
    for v in vids:
        n = data.draw(st.integers(0, 6))
        ids = data.draw(st.lists(st.integers(0, 9), min_size=n, max_size=n))
        one = msg(v, tick, [], [(k, 10, {}) for k in ids])
        kind = data.draw(st.sampled_from(["right", "empty", "short", "int32", "column"]))
        counts = np.array(data.draw(st.lists(st.integers(-2, 4), min_size=n, max_size=n)), dtype=np.int64)
        unscheduled = {"right": counts, "empty": counts[:0], "short": counts[:-1], "int32": counts.astype(np.int32),
                       "column": counts.reshape(-1, 1)}[kind]
        messages[v] = ControlMsg(one.tick, one.t_sim_s, v, one.pose, 0.0, one.trajectory, one.objects, one.heard,
                                 unscheduled)
    group = np.array(vids, dtype=np.int64)
    d = Decision(tick, vids[0], group, group, (0,), np.zeros(0, np.int64), messages)
    got, want = agreed_state(d), agreed_state_reference(d)
    assert got.cursor == want.cursor
    for a, b in ((got.starved_key, want.starved_key), (got.starved_m, want.starved_m)):
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
        assert a.flags.c_contiguous == b.flags.c_contiguous


def test_agreed_state_by_hand():
    """3 reports m = 2 for its object 8 and 0 for 5; 1 reports m = 1 for 4: keys by (vid, id)."""
    from vehicle_agent.agreement import Decision

    a = msg(1, 6, [], [(4, 10, {3: 1.0})], unscheduled={4: 1})
    c = msg(3, 6, [], [(8, 10, {1: 1.0}), (5, 10, {1: 1.0})], unscheduled={8: 2})
    group = np.array([1, 3], dtype=np.int64)
    d = Decision(6, 1, group, group, (0,), np.zeros(0, np.int64), {3: c, 1: a})
    state = agreed_state(d)
    assert state.starved_key.tolist() == [[1, 4], [3, 8]] and state.starved_m.tolist() == [1, 2]
    assert state.cursor == (1, -(1 << 62))  # group[6 mod 2]


def unscheduled_after_reference(own, sent):
    """``unscheduled_after`` as it was (ec93cfa): numpy masks over the objects."""
    om = own.objects
    y = (1.0 - np.asarray(om.visibility, dtype=np.float64)) * np.asarray(om.relevance, dtype=np.float64)
    wanted = np.any(y > 0.0, axis=1) if y.size else np.zeros(len(om.object_id), dtype=bool)
    sent_ids = {int(k) for k in sent}
    skipped = wanted & np.array([k not in sent_ids for k in np.asarray(om.object_id).tolist()], dtype=bool)
    m = own.starvation() + 1
    return {int(k): int(c) for k, c in zip(np.asarray(om.object_id)[skipped].tolist(), m[skipped].tolist())}


@given(data=st.data(), n=st.integers(0, 8), m=st.integers(0, 4))
def test_unscheduled_after_is_the_numpy_one(data, n, m):
    """Against the version it replaced: shares that multiply to 0 (underflow, NaN, 1 - v
    = 0), counts right, negative, missing or of another dtype, ids repeated."""
    shares = st.sampled_from([0.0, 1.0, 0.5, 1e-30, float("nan"), 2.0, -1.0])
    vis = np.array(data.draw(st.lists(shares, min_size=n * m, max_size=n * m)), np.float32).reshape(n, m)
    rel = np.array(data.draw(st.lists(shares, min_size=n * m, max_size=n * m)), np.float32).reshape(n, m)
    ids = np.array(data.draw(st.lists(st.integers(0, 9), min_size=n, max_size=n)), np.int64)
    om = ObjectMap(ids, np.full(n, 10, np.int64), np.zeros((n, 2), np.float32), np.arange(m, dtype=np.int64), vis, rel)
    counts = np.array(data.draw(st.lists(st.integers(-2, 5), min_size=n, max_size=n)), np.int64)
    kind = data.draw(st.sampled_from(["right", "empty", "int32"]))
    unscheduled = {"right": counts, "empty": counts[:0], "int32": counts.astype(np.int32)}[kind]
    own = ControlMsg(3, 0.3, 1, Pose(0.0, 0.0, 0.0), 0.0, np.zeros((0, 3), np.float32), om, np.zeros(0, np.int64),
                     unscheduled)
    sent = data.draw(st.lists(st.integers(0, 9), max_size=4))
    assert unscheduled_after(own, sent) == unscheduled_after_reference(own, sent)


@given(seed=st.integers(0, 2**64 - 1))
def test_a_heard_messages_whole_message_is_decodes(seed):
    """``HeardControl.message`` (the fields ``read`` took, the rest read now) against
    ``decode``: the same message, or the same error text, on valid and fuzzed control
    messages that ``read`` accepts."""
    import random

    from bench import fuzz
    from protocol.codec import decode

    rnd = random.Random(seed)
    raw = fuzz.valid_payload("ControlMsg", rnd) if seed % 3 == 0 else fuzz.fuzz_input("ControlMsg", rnd)
    try:
        heard = HeardControl.read(raw)
    except MalformedMessage:
        return
    outcomes = []
    for whole in (heard.message, lambda: decode(raw, ControlMsg)):
        try:
            outcomes.append(("ok", encode(whole())))
        except MalformedMessage as err:
            outcomes.append(("malformed", str(err)))
    assert outcomes[0] == outcomes[1]
