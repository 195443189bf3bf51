"""Work-conserving AutoCast (``fill.py``): a hand-derived case, and properties over
random instances: the reward-weighted schedule and its airtimes are untouched, no
spare room is left that an unsent object would fit, and when the interval has room
for everything AutoCast carries every object, so never less than Agnostic."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from vehicle_agent.scheduler import (
    Instance,
    ObjectOffer,
    SchedulerState,
    check_schedule,
    expected_reward,
    get,
    greedy_schedule,
    instance_from_arrays,
    make_instance,
    tdma_plan,
    work_conserving,
)

FRESH = SchedulerState()


def test_spare_room_goes_to_the_most_unseen_bytes_after_the_rewarded_object():
    # one 100 B frame (B = 8000 b/s, T_n = 100 ms). A (1,1): 60 B, hidden from 2 and
    # relevant (y = 1): the primary. Spare 40 B. Unseen per byte: D (2,2) 1/10, B (1,2)
    # 1/30, C (2,1) 0 (1 sees it): D then B fill the 40 B, C is left out.
    offers = {
        1: [ObjectOffer(1, 60, {2: 0.0}, {2: 1.0}), ObjectOffer(2, 30, {2: 0.0}, {2: 0.0})],
        2: [ObjectOffer(1, 30, {1: 1.0}, {1: 0.0}), ObjectOffer(2, 10, {1: 0.0}, {1: 0.0})],
    }
    inst = make_instance(offers, lambda i, j: 1.0, bandwidth_bps=8000.0, frame_duration_s=0.1, decision_interval_s=0.1)
    assert inst.unseen.tolist() == [1.0, 1.0, 0.0, 1.0]
    assert get("greedy")(inst, FRESH).keyed(inst) == (((1, 1),),)
    s = get("autocast")(inst, FRESH)
    assert s.keyed(inst) == (((1, 1), (1, 2), (2, 2)),) and s.fill == ((1, 3),)
    # the rewarded object first, then the fill by sender: A [0, 60 ms), B [60, 90), D [90, 100)
    got = [(t.vid, t.object_id, round(t.start_s * 1e3, 6)) for t in tdma_plan(inst, s).transmissions]
    assert got == [(1, 1, 0.0), (1, 2, 60.0), (2, 2, 90.0)]
    # nothing unseen: the round robin from the cursor decides (after (1, 2): (2, 1) first)
    blind = make_instance({1: [ObjectOffer(k, 50, {}, {}) for k in (1, 2)], 2: [ObjectOffer(1, 50, {}, {})]},
                          lambda i, j: 1.0, bandwidth_bps=8000.0, frame_duration_s=0.1, decision_interval_s=0.1)
    assert get("autocast")(blind, SchedulerState(cursor=(1, 2))).keyed(blind) == (((1, 1), (2, 1)),)


def test_not_delaying_the_rewarded_objects_can_cost_a_frame_of_packing():
    # why "when capacity allows" is needed: two 100 B frames; 40 B objects B and D carry
    # the reward and share frame 0; the 60 B objects A and C then fit only frame 1 and
    # one of them is left out. Agnostic, blind to reward, packs [A, B], [C, D]: all four,
    # but D goes out a frame later than AutoCast sends it.
    offers = {1: [ObjectOffer(1, 60, {}, {}), ObjectOffer(2, 40, {2: 0.0}, {2: 1.0})],
              2: [ObjectOffer(1, 60, {}, {}), ObjectOffer(2, 40, {1: 0.0}, {1: 1.0})]}
    inst = make_instance(offers, lambda i, j: 1.0, bandwidth_bps=8000.0, frame_duration_s=0.1, decision_interval_s=0.2)
    assert get("autocast")(inst, FRESH).keyed(inst) == (((1, 2), (2, 2)), ((1, 1),))
    assert get("agnostic")(inst, FRESH).keyed(inst) == (((1, 1), (1, 2)), ((2, 1), (2, 2)))


# ------------------------------------------------------------------ properties


@st.composite
def instances(draw, lossless: bool = False, roomy: bool = False) -> Instance:
    """2-6 vehicles with 0-6 objects each, N = 1-4 frames; ``lossless``: every p_ij = 1
    (the primary sends a wanted object once); ``roomy``: S_f leaves room for every
    object plus the largest, N (S_f - s_max) >= sum s."""
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    C = int(rng.integers(2, 7))
    vids = rng.choice(500, C, replace=False)
    per = rng.integers(0, 7, C)
    owner = np.repeat(vids, per)
    K = len(owner)
    oid = rng.choice(1000, K, replace=False)
    size = rng.integers(1, 40, K) * 10
    N = int(rng.integers(1, 5))
    reward = np.where(rng.random((K, C)) < 0.3, rng.integers(1, 5, (K, C)) / 4, 0.0)
    unseen = np.where(rng.random(K) < 0.7, rng.integers(0, 5, K) / 2, 0.0)
    p = np.ones((C, C)) if lossless else rng.choice([0.5, 0.9, 1.0], (C, C))
    if roomy:
        frame_bytes = int(np.ceil(size.sum() / N)) + int(size.max(initial=0)) + int(rng.integers(0, 50))
    else:
        frame_bytes = int(rng.integers(10, 600))
    return instance_from_arrays(vids, owner, oid, size, reward, p, frame_bytes=frame_bytes, n_frames=N,
                                unseen=unseen, bandwidth_bps=8000.0)


def _starvation(inst: Instance, seed: int) -> SchedulerState:
    """A state with some starvation counters and a cursor, as a running agent holds."""
    rng = np.random.default_rng(seed)
    keys = np.array(inst.keys(), dtype=np.int64).reshape(-1, 2)
    pick = rng.random(len(keys)) < 0.4
    cursor = tuple(int(x) for x in keys[rng.integers(len(keys))]) if len(keys) else None
    return SchedulerState(keys[pick], rng.integers(1, 6, int(pick.sum())), cursor)


def _bytes(inst: Instance, schedule) -> int:
    return int(sum(int(inst.size_bytes[list(f)].sum()) for f in schedule.frames if f))


@settings(max_examples=150, deadline=None)
@given(instances(), st.integers(0, 1000))
def test_the_reward_weighted_schedule_and_its_airtimes_are_untouched(inst, seed):
    state = _starvation(inst, seed)
    pure = get("greedy")(inst, state)
    wc = get("autocast")(inst, state)
    check_schedule(inst, wc)
    assert wc.primary() == pure
    assert expected_reward(inst, wc) >= expected_reward(inst, pure) - 1e-12
    fill = [k for f in wc.fill for k in f]
    assert len(fill) == len(set(fill)) and not set(fill) & pure.sent()  # each filler once, none of the primary's
    before = {(t.frame, t.index): t.start_s for t in tdma_plan(inst, pure).transmissions}
    after = {(t.frame, t.index): t.start_s for t in tdma_plan(inst, wc).transmissions}
    assert {key: after[key] for key in before} == before  # no rewarded transmission moves
    last_primary = {}
    for (n, k), t in before.items():
        last_primary[n] = max(last_primary.get(n, 0.0), t)
    assert all(after[(n, k)] > last_primary.get(n, -1.0) for n, f in enumerate(wc.fill) for k in f)


@settings(max_examples=150, deadline=None)
@given(instances())
def test_no_frame_keeps_room_an_unsent_object_would_fit(inst):
    wc = get("autocast")(inst, FRESH)
    room = [inst.frame_bytes - int(inst.size_bytes[list(f)].sum()) for f in wc.frames]
    unsent = sorted(set(range(inst.n_objects)) - wc.sent())
    assert all(int(inst.size_bytes[k]) > max(room, default=0) for k in unsent)


@settings(max_examples=150, deadline=None)
@given(instances(lossless=True, roomy=True))
def test_with_room_for_everything_autocast_carries_everything_so_never_less_than_agnostic(inst):
    wc = get("autocast")(inst, FRESH)
    agn = get("agnostic")(inst, FRESH)
    assert wc.sent() == set(range(inst.n_objects))
    assert len(wc.sent()) >= len(agn.sent()) and _bytes(inst, wc) >= _bytes(inst, agn)


@settings(max_examples=150, deadline=None)
@given(instances(), st.integers(0, 1000))
def test_when_the_primary_leaves_room_for_the_rest_autocast_never_carries_less_than_agnostic(inst, seed):
    # the sufficient condition, for any p: the primary's bytes plus every other object's
    # fit N (S_f - s_max); first fit then cannot leave an object out (each frame would
    # have to be fuller than S_f - s_max)
    state = _starvation(inst, seed)
    pure = get("greedy")(inst, state)
    rest = sorted(set(range(inst.n_objects)) - pure.sent())
    s_max = int(inst.size_bytes.max(initial=0))
    if _bytes(inst, pure) + int(inst.size_bytes[rest].sum()) > inst.n_frames * (inst.frame_bytes - s_max):
        return
    wc = get("autocast")(inst, state)
    agn = get("agnostic")(inst, state)
    assert wc.sent() == set(range(inst.n_objects))
    assert len(wc.sent()) >= len(agn.sent()) and _bytes(inst, wc) >= _bytes(inst, agn)


@settings(max_examples=60, deadline=None)
@given(instances(), st.integers(0, 1000), st.integers(0, 2**32 - 1))
def test_every_vehicle_fills_alike_whatever_order_it_built_the_instance_in(inst, seed, perm_seed):
    rng = np.random.default_rng(perm_seed)
    vp, kp = rng.permutation(inst.n_vehicles), rng.permutation(inst.n_objects)
    other = instance_from_arrays(inst.vids[vp], inst.vids[inst.owner][kp], inst.object_id[kp], inst.size_bytes[kp],
                                 inst.reward[kp][:, vp], inst.p_deliver[vp][:, vp], frame_bytes=inst.frame_bytes,
                                 n_frames=inst.n_frames, history=inst.history[kp][:, vp], unseen=inst.unseen[kp],
                                 bandwidth_bps=inst.bandwidth_bps)
    state = _starvation(inst, seed)
    for name in ("autocast", "autocast-fptas"):
        a, b = get(name)(inst, state), get(name)(other, state)
        assert a.keyed(inst) == b.keyed(other)
        keys_a, keys_b = inst.keys(), other.keys()
        assert [[keys_a[k] for k in f] for f in a.fill] == [[keys_b[k] for k in f] for f in b.fill]


def test_fill_of_an_empty_or_full_schedule():
    inst = instance_from_arrays([1, 2], [1, 1], [1, 2], [50, 500], np.zeros((2, 2)), np.ones((2, 2)),
                                frame_bytes=100, n_frames=2)
    s = work_conserving(inst, greedy_schedule(inst))
    assert s.keyed(inst) == (((1, 1),), ()) and s.fill == ((0,), ())  # 500 B > S_f: never sent
