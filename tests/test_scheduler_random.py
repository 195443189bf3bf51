"""Scheduler against brute force on hundreds of seeded random instances."""

from __future__ import annotations


import numpy as np
import pytest

from bench.scheduler import intersection_instance
from vehicle_agent.scheduler import (
    Instance,
    SchedulerState,
    check_schedule,
    expected_reward,
    frame_weights,
    get,
    greedy_schedule,
    instance_from_arrays,
    knapsack_exact,
    knapsack_fptas,
    mdp_optimal,
    optimal_open_loop,
    weight_H,
)
from vehicle_agent.scheduler.brute import brute_knapsack, brute_mdp, brute_open_loop, reference_greedy
from vehicle_agent.scheduler.instance import deliver_expected

FRESH = SchedulerState()
TOL = 1e-9


def tiny_instance(rng: np.random.Generator, binary_p: bool = False, coarse: bool = False) -> Instance:
    """2-3 vehicles with 1-2 objects each, N = 1-3 frames: small enough to enumerate."""
    C = int(rng.integers(2, 4))
    per = rng.integers(1, 3, C)
    N = int(rng.integers(1, 4))
    vids = rng.choice(1000, C, replace=False)
    owner = np.repeat(vids, per)
    K = len(owner)
    oid = rng.choice(50, K, replace=False)
    size = rng.integers(1, 6, K) * 10
    values = rng.integers(1, 4, (K, C)) / 4 if coarse else rng.random((K, C)).round(3)
    reward = np.where(rng.random((K, C)) < 0.5, values, 0.0)
    history = rng.random((K, C)) < 0.1
    p = rng.choice([0.0, 1.0], (C, C)) if binary_p else rng.uniform(0.2, 1.0, (C, C)).round(2)
    cap = int(rng.integers(10, 80))
    return instance_from_arrays(vids, owner, oid, size, reward, p, frame_bytes=cap, n_frames=N, history=history)


def tiny_instances(seed: int, n: int, **kw) -> list[Instance]:
    rng = np.random.default_rng(seed)
    return [tiny_instance(rng, **kw) for _ in range(n)]


def permuted(inst: Instance, rng: np.random.Generator) -> Instance:
    """The same instance with vehicles and objects given in a random order."""
    vp = rng.permutation(inst.n_vehicles)
    kp = rng.permutation(inst.n_objects)
    return instance_from_arrays(
        inst.vids[vp],
        inst.vids[inst.owner][kp],
        inst.object_id[kp],
        inst.size_bytes[kp],
        inst.reward[kp][:, vp],
        inst.p_deliver[vp][:, vp],
        frame_bytes=inst.frame_bytes,
        n_frames=inst.n_frames,
        history=inst.history[kp][:, vp],
        bandwidth_bps=inst.bandwidth_bps,
    )


# ------------------------------------------------------------------------- per frame


def test_exact_knapsack_equals_brute_force():
    rng = np.random.default_rng(1)
    for _ in range(300):
        n = int(rng.integers(1, 9))
        profit = np.where(rng.random(n) < 0.8, rng.random(n), 0.0)
        size = rng.integers(1, 40, n)
        cap = int(rng.integers(0, 100))
        chosen = knapsack_exact(profit, size, cap)
        assert size[chosen].sum() <= cap
        assert profit[chosen].sum() == pytest.approx(brute_knapsack(profit.tolist(), size.tolist(), cap), abs=TOL)


@pytest.mark.parametrize("epsilon", [0.5, 0.25, 0.1, 0.02])
def test_fptas_is_within_epsilon_of_the_optimum(epsilon):
    rng = np.random.default_rng(2)
    for _ in range(200):
        n = int(rng.integers(1, 11))
        profit = rng.random(n) ** 3  # skewed profits make the scaling matter
        size = rng.integers(1, 40, n)
        cap = int(rng.integers(1, 120))
        chosen = knapsack_fptas(profit, size, cap, epsilon)
        best = brute_knapsack(profit.tolist(), size.tolist(), cap)
        assert size[chosen].sum() <= cap
        assert profit[chosen].sum() >= (1.0 - epsilon) * best - TOL


def test_fptas_scheduler_is_within_epsilon_of_each_frames_optimum():
    """Each FPTAS frame, at the expected state it is played in, earns sum H >= (1-eps) x the
    exact knapsack optimum of that frame."""
    rng = np.random.default_rng(3)
    instances = tiny_instances(4, 100) + [intersection_instance(rng, 5, objects_per_vehicle=6) for _ in range(20)]
    for inst in instances:
        s = get("fptas")(inst, FRESH)
        h = inst.history.astype(np.float64)
        for frame, got in zip(s.frames, frame_weights(inst, s)):
            H = weight_H(inst.reward, h)
            best = H[knapsack_exact(H, inst.size_bytes, inst.frame_bytes)].sum()
            assert got >= 0.9 * best - TOL
            sent = np.zeros(inst.n_objects, dtype=bool)
            sent[list(frame)] = True
            h = deliver_expected(h, inst.p_object(), sent)


# ------------------------------------------------------------------------- optima


def test_open_loop_optimum_equals_brute_force():
    for inst in tiny_instances(5, 300):
        assert expected_reward(inst, optimal_open_loop(inst)) == pytest.approx(brute_open_loop(inst), abs=TOL)


def test_mdp_dynamic_program_equals_brute_force():
    for inst in tiny_instances(6, 300):
        assert mdp_optimal(inst).value == pytest.approx(brute_mdp(inst), abs=TOL)


def test_every_scheduler_is_below_the_optimum_below_the_mdp():
    for inst in tiny_instances(7, 300):
        best = expected_reward(inst, optimal_open_loop(inst))
        assert best <= mdp_optimal(inst).value + TOL
        for name in ("greedy", "greedy-plain", "fptas", "knapsack", "agnostic"):
            assert expected_reward(inst, get(name)(inst, FRESH)) <= best + TOL, name


def test_without_loss_feedback_is_worthless():
    """With every p_ij in {0, 1} the MDP is deterministic: open loop = closed loop."""
    for inst in tiny_instances(8, 200, binary_p=True):
        assert expected_reward(inst, optimal_open_loop(inst)) == pytest.approx(mdp_optimal(inst).value, abs=TOL)


# ------------------------------------------------------------------------- greedy


def test_greedy_equals_the_plain_reference_with_ties_and_starvation():
    rng = np.random.default_rng(9)
    instances = tiny_instances(10, 200, coarse=True) + [intersection_instance(rng, c, objects_per_vehicle=8) for c in (5, 10, 20)]
    for inst in instances:
        for m in (np.zeros(inst.n_objects, dtype=np.int64), rng.integers(0, 6, inst.n_objects)):
            assert [list(f) for f in greedy_schedule(inst, m).frames] == reference_greedy(inst, m.tolist())


# ------------------------------------------------------------------------- all schedulers


SCHEDULERS = ("greedy", "greedy-plain", "fptas", "knapsack", "agnostic", "optimal")


def _medium(seed: int) -> list[Instance]:
    rng = np.random.default_rng(seed)
    return [intersection_instance(rng, c, objects_per_vehicle=10) for c in (5, 10, 20)]


@pytest.mark.parametrize("name", SCHEDULERS)
def test_no_scheduler_overfills_a_frame(name):
    instances = tiny_instances(11, 100) + ([] if name == "optimal" else _medium(12))
    for inst in instances:
        check_schedule(inst, get(name)(inst, FRESH))


@pytest.mark.parametrize("name", SCHEDULERS)
def test_permuted_input_gives_the_identical_schedule(name):
    rng = np.random.default_rng(13)
    instances = tiny_instances(14, 100, coarse=True) + ([] if name == "optimal" else _medium(15))
    for inst in instances:
        state = FRESH
        for _ in range(2):  # a fresh state, then one carrying starvation counters and a cursor
            want = get(name)(inst, state).keyed(inst)
            for _ in range(2):
                other = permuted(inst, rng)
                assert get(name)(other, state).keyed(other) == want
            state = state.advance(inst, get(name)(inst, state))
