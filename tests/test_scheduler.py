"""Scheduler: hand-derived cases, the instance builder, state, TDMA and the registry."""

from __future__ import annotations

import re

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from vehicle_agent.scheduler import (
    Instance,
    InstanceTooLarge,
    ObjectOffer,
    Schedule,
    SchedulerState,
    SenderOffers,
    UnknownSchedulerError,
    check_schedule,
    expected_reward,
    frame_weights,
    get,
    greedy_schedule,
    instance_from_arrays,
    knapsack_exact,
    knapsack_fptas,
    link_probability,
    make_instance,
    mdp_optimal,
    names,
    optimal_open_loop,
    register,
    tdma_plan,
)
from vehicle_agent.scheduler import registry

FRESH = SchedulerState()


def _offer(oid: int, size: int, rewards: dict[int, float]) -> ObjectOffer:
    """An object occluded from (v = 0) and relevant (r) to each listed receiver."""
    return ObjectOffer(oid, size, visibility={j: 0.0 for j in rewards}, relevance=rewards)


def _one_frame_of_100_bytes() -> dict:
    # S_f = B * T_n / 8 = 8000 b/s * 0.1 s / 8 = 100 bytes; N = T_d / T_n = 1
    return dict(bandwidth_bps=8000.0, frame_duration_s=0.1, decision_interval_s=0.1)


def _xyz_instance():
    # X: 51 B, H = 0.6 -> H/s = 0.01176;  Y, Z: 50 B, H = 0.5 -> H/s = 0.01
    offers = {1: [_offer(1, 51, {2: 0.6}), _offer(2, 50, {3: 0.5})], 2: [_offer(1, 50, {1: 0.5})]}
    return make_instance(offers, lambda i, j: 1.0, **_one_frame_of_100_bytes())


# ------------------------------------------------------------------------- instance


def test_reward_is_one_minus_visibility_times_relevance():
    offers = {
        7: [ObjectOffer(3, 1000, visibility={5: 1.0, 9: 0.0}, relevance={5: 0.8, 9: 0.25})],
        5: [ObjectOffer(1, 2000, visibility={7: 0.0}, relevance={7: 1.0})],
    }
    inst = make_instance(offers, lambda i, j: 0.9, vids=[11])
    assert inst.vids.tolist() == [5, 7, 9, 11]
    assert inst.keys() == [(5, 1), (7, 3)]
    # (7,3) -> 5: (1 - 1) * 0.8 = 0;  -> 9: (1 - 0) * 0.25 = 0.25
    assert inst.reward.tolist() == [[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.25, 0.0]]
    # S_f = 7.2e6 b/s * 10 ms / 8 = 9000 B, N = 100 ms / 10 ms = 10
    assert (inst.frame_bytes, inst.n_frames) == (9000, 10)
    assert np.all(np.diag(inst.p_deliver) == 1.0) and inst.p_deliver[0, 1] == 0.9


def test_instance_is_canonical_whatever_the_message_order():
    a = {1: [_offer(4, 100, {2: 0.5}), _offer(2, 300, {3: 1.0})], 3: [_offer(9, 50, {1: 0.2})], 2: []}
    b = {2: [], 3: [_offer(9, 50, {1: 0.2})], 1: [_offer(2, 300, {3: 1.0}), _offer(4, 100, {2: 0.5})]}
    p = {(i, j): 0.1 * i + 0.01 * j for i in (1, 2, 3) for j in (1, 2, 3)}
    ia, ib = make_instance(a, p), make_instance(b, p)
    for name in ("vids", "owner", "object_id", "size_bytes", "reward", "p_deliver", "history"):
        assert np.array_equal(getattr(ia, name), getattr(ib, name)), name
    with pytest.raises(ValueError):
        ia.reward[0, 0] = 1.0  # read-only


def test_array_offers_build_the_same_instance_as_per_object_offers():
    per_object = {
        4: [ObjectOffer(2, 900, visibility={1: 1.0, 6: 0.0}, relevance={1: 0.5, 6: 0.75}), _offer(1, 300, {6: 0.2})],
        6: [_offer(8, 500, {4: 1.0})],
    }
    arrays = {
        6: SenderOffers(np.array([8]), np.array([500]), np.array([4]), np.zeros((1, 1)), np.ones((1, 1))),
        4: SenderOffers(
            np.array([2, 1]), np.array([900, 300]), np.array([6, 1]),
            visibility=np.array([[0.0, 1.0], [0.0, 0.0]]), relevance=np.array([[0.75, 0.5], [0.2, 0.0]]),
        ),
    }
    a, b = make_instance(per_object, lambda i, j: 0.8), make_instance(arrays, lambda i, j: 0.8)
    for name in ("vids", "owner", "object_id", "size_bytes", "reward", "p_deliver", "history"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    # (4,2) -> 6: (1 - 0) * 0.75;  -> 1: (1 - 1) * 0.5 = 0
    assert a.reward[a.keys().index((4, 2))].tolist() == [0.0, 0.0, 0.75]


def test_instance_rejects_bad_input():
    with pytest.raises(ValueError, match="duplicate"):
        instance_from_arrays([1, 2], [1, 1], [5, 5], [10, 10], np.zeros((2, 2)), np.ones((2, 2)), frame_bytes=100, n_frames=1)
    with pytest.raises(ValueError, match="owner"):
        instance_from_arrays([1, 2], [3], [5], [10], np.zeros((1, 2)), np.ones((2, 2)), frame_bytes=100, n_frames=1)
    with pytest.raises(ValueError, match="reward"):
        instance_from_arrays([1, 2], [1], [5], [10], [[0.0, 1.5]], np.ones((2, 2)), frame_bytes=100, n_frames=1)


@pytest.mark.parametrize("field, value, message", [
    ("unseen", [0.0, np.nan, 1.0], "unseen must be >= 0"),
    ("unseen", [0.0, -0.5, 1.0], "unseen must be >= 0"),
    ("vids", [1, 1, 3], "vids must be strictly ascending"),
    ("owner", [0, 1, 3], "owner out of range"),
    ("owner", [-1, 1, 2], "owner out of range"),
    ("object_id", [5, 5, 2], None),  # fine: object ids ascend within an owner only
    ("owner", [1, 0, 2], "objects must be sorted by (owner, object_id)"),
    ("object_id", [6, 6, 7], None),  # different owners: no duplicate
    ("object_id", [-(2**63) + 1, 2**62, 7], None),  # ids 2^63 apart: no int64 difference to overflow
    ("size_bytes", [10, 0, 10], "size_bytes must be positive"),
    ("reward", [[0.5, 0.0, 0.0], [0.0, 0.0, 0.5], [0.0, 0.2, 0.0]], "reward to the owner itself must be 0"),
    ("reward", [[0.0, np.nan, 0.0], [0.0, 0.0, 0.5], [0.5, 0.2, 0.0]], "reward must lie in [0, 1]"),
    ("p_deliver", [[1.0, 1.2, 0.5], [0.5, 1.0, 0.5], [0.5, 0.5, 1.0]], "p_deliver must lie in [0, 1]"),
])
def test_instance_names_the_first_bad_value(field, value, message):
    """Each value check on its own: an instance that breaks it is refused with its
    message, and the unbroken instance is accepted."""
    fields = dict(vids=np.array([1, 2, 3]), owner=np.array([0, 1, 2]), object_id=np.array([5, 6, 7]),
                  size_bytes=np.array([10, 10, 10]),
                  reward=np.array([[0.0, 0.5, 0.0], [0.0, 0.0, 0.5], [0.5, 0.2, 0.0]]),
                  p_deliver=np.full((3, 3), 0.5), history=np.zeros((3, 3), dtype=bool), frame_bytes=100, n_frames=1,
                  frame_duration_s=0.01, bandwidth_bps=6e6, unseen=np.zeros(3))
    Instance(**fields)
    broken = np.array(value, dtype=fields[field].dtype)
    if message is None:
        Instance(**{**fields, field: broken})
        return
    with pytest.raises(ValueError, match=re.escape(message)):
        Instance(**{**fields, field: broken})


def test_instance_names_a_duplicate_object_and_a_bad_dtype_before_any_value():
    fields = dict(vids=np.array([1, 2, 3]), owner=np.array([0, 0, 2]), object_id=np.array([5, 5, 7]),
                  size_bytes=np.array([10, 10, 10]), reward=np.zeros((3, 3)), p_deliver=np.full((3, 3), 0.5),
                  history=np.zeros((3, 3), dtype=bool), frame_bytes=100, n_frames=1, frame_duration_s=0.01,
                  bandwidth_bps=6e6, unseen=np.zeros(3))
    with pytest.raises(ValueError, match=re.escape("duplicate (owner, object_id)")):
        Instance(**fields)
    with pytest.raises(ValueError, match=re.escape("history must be bool (K, C)")):  # checked before the values
        Instance(**{**fields, "history": np.zeros((3, 3))})


def test_link_probability_falls_with_distance():
    p = link_probability(np.array([0.0, 50.0, 150.0, 300.0]))
    assert p[0] > p[1] > p[2] > p[3] and p[2] == pytest.approx(0.5) and p[1] > 0.95


# ------------------------------------------------------------------------- hand-derived


def test_greedy_by_density_versus_exact_knapsack():
    inst = _xyz_instance()
    # greedy takes X (51 B, best H/s); neither 50 B object fits the 49 B left: reward 0.6
    g = get("greedy")(inst, FRESH)
    assert g.keyed(inst) == (((1, 1),),)
    assert expected_reward(inst, g) == pytest.approx(0.6)
    # the exact per-frame knapsack and the optimum take Y + Z = 100 B: reward 1.0
    for name in ("knapsack", "optimal", "fptas"):
        s = get(name)(inst, FRESH)
        assert s.keyed(inst) == (((1, 2), (2, 1)),), name
        assert expected_reward(inst, s) == pytest.approx(1.0)


def test_knapsack_solvers_by_hand():
    profit, size = np.array([0.6, 0.5, 0.5, 0.0]), np.array([51, 50, 50, 10])
    assert knapsack_exact(profit, size, 100).tolist() == [False, True, True, False]
    assert knapsack_fptas(profit, size, 100, 0.1).tolist() == [False, True, True, False]
    with pytest.raises(ValueError):
        knapsack_fptas(profit, size, 100, 0.0)


def test_expected_delivery_resend_and_the_value_of_feedback():
    # one receiver, p = 0.5, N = 2 frames of 100 B; X: 60 B y = 1.0, Y: 60 B y = 0.4
    offers = {1: [_offer(1, 60, {2: 1.0}), _offer(2, 60, {2: 0.4})]}
    inst = make_instance(offers, lambda i, j: 0.5, bandwidth_bps=8000.0, frame_duration_s=0.1, decision_interval_s=0.2)
    # frame 1: H_X = 1.0 > H_Y = 0.4 -> X; h_X = 0.5. frame 2: H_X = 0.5 > H_Y = 0.4 -> X again
    g = get("greedy")(inst, FRESH)
    assert g.frames == ((0,), (0,))
    # E = 1.0 * (1 - 0.5^2) = 0.75; X then Y would give 0.5 + 0.2 = 0.7, Y twice 0.3
    assert expected_reward(inst, g) == pytest.approx(0.75)
    assert expected_reward(inst, optimal_open_loop(inst)) == pytest.approx(0.75)
    assert frame_weights(inst, g) == pytest.approx([1.0, 0.5])
    # with feedback: X first; delivered (0.5) -> Y earns 0.4 * 0.5, lost -> X again earns 0.5
    # U = 0.5 + 0.5 * 0.2 + 0.5 * 0.5 = 0.85
    mdp = mdp_optimal(inst)
    assert mdp.value == pytest.approx(0.85) and mdp.first_frame == (0,)


def test_exact_solvers_refuse_large_instances():
    rng = np.random.default_rng(0)
    K, C = 40, 6
    inst = instance_from_arrays(
        range(C), rng.integers(0, C, K), range(K), rng.integers(100, 400, K),
        rng.random((K, C)), np.full((C, C), 0.9), frame_bytes=1000, n_frames=3,
    )
    with pytest.raises(InstanceTooLarge, match="greedy"):
        get("optimal")(inst, FRESH)
    with pytest.raises(InstanceTooLarge, match="greedy"):
        mdp_optimal(inst)
    with pytest.raises(InstanceTooLarge, match="fptas"):
        knapsack_exact(np.ones(2000), np.ones(2000, dtype=np.int64), 100_000)


# ------------------------------------------------------------------------- starvation


def test_starvation_lifts_a_long_starved_object_over_a_fresh_one():
    # A (vid 1) and B (vid 2): both 60 B, y = 0.5, one fits a 100 B frame; equal H/s
    offers = {1: [_offer(1, 60, {3: 0.5})], 2: [_offer(1, 60, {3: 0.5})]}
    inst = make_instance(offers, lambda i, j: 1.0, **_one_frame_of_100_bytes())
    assert greedy_schedule(inst).keyed(inst) == (((1, 1),),)  # tie -> lower (vid, id)
    # m = [0, 5]: var_m = 6.25, boost_B = 1 + 5 / 6.25 = 1.8 > boost_A = 1
    assert greedy_schedule(inst, np.array([0, 5])).keyed(inst) == (((2, 1),),)


def test_starvation_does_not_beat_a_much_better_object():
    # A: H/s = 1.0 / 60, B: 0.5 / 60, B starved m = 5: 0.5 * 1.8 = 0.9 < 1.0 -> A
    offers = {1: [_offer(1, 60, {3: 1.0})], 2: [_offer(1, 60, {3: 0.5})]}
    inst = make_instance(offers, lambda i, j: 1.0, **_one_frame_of_100_bytes())
    assert greedy_schedule(inst, np.array([0, 5])).keyed(inst) == (((1, 1),),)


def test_state_counts_skipped_intervals_and_alternates_equal_objects():
    offers = {1: [_offer(1, 60, {3: 0.5})], 2: [_offer(1, 60, {3: 0.5})], 3: [_offer(1, 60, {1: 0.0})]}
    inst = make_instance(offers, lambda i, j: 1.0, **_one_frame_of_100_bytes())
    autocast, state, sent = get("autocast"), FRESH, []
    for _ in range(4):
        s = autocast(inst, state)
        sent.append(s.keyed(inst)[0])
        state = state.advance(inst, s)
    # interval 1: tie -> A, B starves (m = 1, var = 0.25 -> boost 2) -> interval 2: B, ...
    assert sent == [((1, 1),), ((2, 1),), ((1, 1),), ((2, 1),)]
    assert state.starved() == {(1, 1): 1}  # (3,1) carries no reward: never counted
    # a skipped object keeps counting while it stays wanted
    never = SchedulerState()
    for m in (1, 2, 3):
        never = never.advance(inst, Schedule(((0,),)))
        assert never.starved() == {(2, 1): m}


# ------------------------------------------------------------------------- agnostic


def test_agnostic_round_robin_ignores_reward_and_resumes_from_the_cursor():
    # four 40 B objects, two fit a 100 B frame; only (2,1) has any reward
    offers = {1: [_offer(1, 40, {}), _offer(2, 40, {})], 2: [_offer(1, 40, {3: 1.0})], 3: [_offer(1, 40, {})]}
    inst = make_instance(offers, lambda i, j: 1.0, **_one_frame_of_100_bytes())
    agnostic, state, sent = get("agnostic"), FRESH, []
    for _ in range(3):
        s = agnostic(inst, state)
        sent.append(s.keyed(inst)[0])
        state = state.advance(inst, s)
    assert sent == [((1, 1), (1, 2)), ((2, 1), (3, 1)), ((1, 1), (1, 2))]
    assert state.cursor == (1, 2)


# ------------------------------------------------------------------------- TDMA


def test_tdma_orders_senders_by_reward_and_times_by_size():
    # B = 7.2 Mbps, T_n = 10 ms: S_f = 9000 B
    offers = {5: [_offer(1, 900, {3: 0.3})], 3: [_offer(1, 1800, {5: 0.9}), _offer(2, 450, {5: 0.1})]}
    inst = make_instance(offers, lambda i, j: 1.0)
    plan = tdma_plan(inst, Schedule(((0, 1, 2), (2,))))
    got = [(t.frame, t.vid, t.object_id, round(t.start_s * 1e3, 6), round(t.duration_s * 1e3, 6)) for t in plan.transmissions]
    # frame 0: vid 3 (0.9 + 0.1) before vid 5 (0.3); 1800 B * 8 / 7.2 Mb/s = 2 ms, 450 B = 0.5 ms, 900 B = 1 ms
    # frame 1 starts at T_n = 10 ms
    assert got == [(0, 3, 1, 0.0, 2.0), (0, 3, 2, 2.0, 0.5), (0, 5, 1, 2.5, 1.0), (1, 5, 1, 10.0, 1.0)]
    assert [(s.frame, s.vid, round(s.start_s * 1e3, 6), round(s.duration_s * 1e3, 6)) for s in plan.slots()] == [
        (0, 3, 0.0, 2.5), (0, 5, 2.5, 1.0), (1, 5, 10.0, 1.0)
    ]
    assert plan.frame_duration_s == pytest.approx(0.01)
    assert [t.object_id for t in plan.sent_by(3)] == [1, 2]


def test_tdma_breaks_reward_ties_by_vid():
    offers = {9: [_offer(1, 100, {4: 0.5})], 4: [_offer(1, 100, {9: 0.5})]}
    inst = make_instance(offers, lambda i, j: 1.0)
    assert [s.vid for s in tdma_plan(inst, Schedule(((0, 1),))).slots()] == [4, 9]


# ------------------------------------------------------------------------- registry


def test_registry_names_and_aliases():
    for name in ("greedy", "autocast", "fptas", "autocast-fptas", "optimal", "agnostic", "knapsack"):
        assert name in names()
    inst = _xyz_instance()
    for wc, pure in (("autocast", "greedy"), ("autocast-fptas", "fptas")):  # the pure schedule, spare room filled
        assert get(wc)(inst, FRESH).primary() == get(pure)(inst, FRESH)


def test_unknown_scheduler_lists_the_known_ones():
    with pytest.raises(UnknownSchedulerError, match="known: .*agnostic.*greedy"):
        get("no-such-scheduler")
    with pytest.raises(UnknownSchedulerError, match="cannot load"):
        get("no_such_module:fn")


def test_user_scheduler_by_registration_and_by_import_path():
    @register("test-nothing")
    def nothing(instance, state):
        return Schedule(tuple(() for _ in range(instance.n_frames)))

    try:
        inst = _xyz_instance()
        assert get("test-nothing")(inst, FRESH) == Schedule(((),))
        assert get("vehicle_agent.scheduler.greedy:greedy_plain")(inst, FRESH) == get("greedy")(inst, FRESH)
        with pytest.raises(ValueError, match="already registered"):
            register("greedy")(nothing)
    finally:
        registry._SCHEDULERS.pop("test-nothing", None)


def test_check_schedule_catches_overfull_frames():
    inst = _xyz_instance()
    with pytest.raises(ValueError, match="exceed"):
        check_schedule(inst, Schedule(((0, 1),)))
    with pytest.raises(ValueError, match="frames"):
        check_schedule(inst, Schedule(((), ())))
    check_schedule(inst, Schedule(((1, 2),)))


@given(st.integers(0, 2**32 - 1), st.integers(1, 8), st.integers(0, 30))
def test_an_instance_is_the_same_whatever_order_its_arrays_came_in(seed, C, K):
    """instance_from_arrays of canonically ordered arrays (make_instance's, which skip
    reordering) and of the same arrays shuffled: every field equal, bit for bit."""
    rng = np.random.default_rng(seed)
    vids = np.sort(rng.choice(1000, C, replace=False))
    pairs = sorted({(int(rng.integers(0, C)), int(rng.integers(0, 50))) for _ in range(K)})
    owner = np.array([vids[o] for o, _ in pairs], dtype=np.int64)
    oid = np.array([k for _, k in pairs], dtype=np.int64)
    size = rng.integers(1, 500, len(pairs))
    reward, p = rng.random((len(pairs), C)), rng.random((C, C))
    history, unseen = rng.random((len(pairs), C)) < 0.3, rng.random(len(pairs)) * C
    kw = dict(frame_bytes=900, n_frames=10, bandwidth_bps=7.2e5)
    a = instance_from_arrays(vids, owner, oid, size, reward, p, history=history, unseen=unseen, **kw)
    vp, kp = rng.permutation(C), rng.permutation(len(pairs))
    b = instance_from_arrays(vids[vp], owner[kp], oid[kp], size[kp], reward[kp][:, vp], p[vp][:, vp],
                             history=history[kp][:, vp], unseen=unseen[kp], **kw)
    for name in ("vids", "owner", "object_id", "size_bytes", "reward", "p_deliver", "history", "unseen"):
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.flags.c_contiguous and y.flags.c_contiguous, name
        np.testing.assert_array_equal(x, y, err_msg=name)
    assert not a.reward.flags.writeable and reward.flags.writeable and history.flags.writeable  # copies frozen
