"""Exact solutions for small instances.

Two optima, because vehicles get no acknowledgements inside a decision interval:

- ``mdp_optimal``: the paper's finite-horizon MDP over the N frames, solved by the
  Bellman recursion (eq. Bellman) over delivery outcomes. Its policy may react to
  which receivers got which object, information no vehicle has while the interval
  runs, so its value is an upper bound on what any schedule can earn.
- ``optimal_open_loop`` (registered as ``optimal``): the best schedule the vehicles
  can actually play, the same kind of object every other scheduler returns. Without
  feedback the state evolves deterministically in expectation, and an object sent c
  times reaches j with probability 1 - (1 - p_ij)^c whichever frames carry it, so
  the optimum is the best multiset of N frame loads; it is found exactly by
  enumerating multisets of maximal frame loads. With N = 1 it is a plain knapsack on
  the expected gain, solved by the exact DP over bytes at any realistic size.

Both only ever need maximal actions (no further wanted object fits): sending more
never lowers the expected reward, now or later. Both refuse instances whose search
would not finish, raising ``InstanceTooLarge``.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations_with_replacement
from math import comb

import numpy as np

from vehicle_agent.scheduler.instance import Instance, Schedule
from vehicle_agent.scheduler.knapsack import InstanceTooLarge, knapsack_exact
from vehicle_agent.scheduler.registry import register
from vehicle_agent.scheduler.state import SchedulerState

MAX_OPEN_LOOP_OBJECTS = 16  # wanted objects that fit a frame
MAX_OPEN_LOOP_CELLS = 30_000_000  # frame-load multisets x frames x objects
MAX_MDP_OBJECTS = 12
MAX_MDP_PAIRS = 24  # (object, receiver) pairs with reward still to earn
MAX_MDP_EVALUATIONS = 2_000_000  # successor states visited by the Bellman recursion


def _subsets(size_bytes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All subsets of the objects as bool rows (ascending bitmask order) and their bytes."""
    u = len(size_bytes)
    bits = ((np.arange(1 << u)[:, None] >> np.arange(u)) & 1).astype(bool)
    return bits, bits @ size_bytes


def maximal_loads(size_bytes: np.ndarray, capacity: int) -> np.ndarray:
    """bool (F, u): every frame load that fits ``capacity`` and admits no further object."""
    bits, used = _subsets(np.asarray(size_bytes, dtype=np.int64))
    fits = used <= capacity
    smallest_out = np.where(bits, np.iinfo(np.int64).max, size_bytes[None, :]).min(axis=1)
    return bits[fits & (smallest_out > capacity - used)]


def _empty(instance: Instance) -> Schedule:
    return Schedule(tuple(() for _ in range(instance.n_frames)))


def optimal_open_loop(instance: Instance) -> Schedule:
    """The schedule of maximum expected reward (eq. reward_func) among all schedules."""
    N = instance.n_frames
    objects = np.flatnonzero(instance.wanted() & (instance.size_bytes <= instance.frame_bytes))
    u = len(objects)
    if u == 0 or N == 0:
        return _empty(instance)
    if u > MAX_OPEN_LOOP_OBJECTS and N > 1:
        raise InstanceTooLarge(
            f"optimal: {u} wanted objects exceed the limit of {MAX_OPEN_LOOP_OBJECTS} for exact search; "
            "use 'greedy' or 'fptas'"
        )
    if N == 1:  # a single frame is a knapsack on the expected gain sum_j y (1 - h) p_ij
        gain = np.sum(instance.reward * ~instance.history * instance.p_object(), axis=1)
        return Schedule((tuple(np.flatnonzero(knapsack_exact(gain, instance.size_bytes, instance.frame_bytes)).tolist()),))
    loads = maximal_loads(instance.size_bytes[objects], instance.frame_bytes)
    F = len(loads)
    n_multisets = comb(F + N - 1, N)
    if n_multisets * N * u > MAX_OPEN_LOOP_CELLS:
        raise InstanceTooLarge(
            f"optimal: {n_multisets:.3g} multisets of {F} maximal frame loads over N={N} frames "
            f"x {u} objects exceed {MAX_OPEN_LOOP_CELLS:.0e}; use 'greedy' or 'fptas'"
        )
    gain = instance.reward[objects] * ~instance.history[objects]
    miss = 1.0 - instance.p_object()[objects]
    # value[t, c]: expected reward of object t when sent c times
    value = np.stack([np.sum(gain * (1.0 - miss**c), axis=1) for c in range(N + 1)], axis=1)
    multisets = np.array(list(combinations_with_replacement(range(F), N)), dtype=np.int64)
    counts = loads[multisets].sum(axis=1)
    total = value[np.arange(u)[None, :], counts].sum(axis=1)
    best = multisets[int(np.argmax(total))]  # ties: first multiset in lexicographic order
    return Schedule(tuple(tuple(objects[loads[f]].tolist()) for f in _order_frames(best, loads, value)))


def _order_frames(chosen: np.ndarray, loads: np.ndarray, value: np.ndarray) -> list[int]:
    """Play the chosen loads highest marginal gain first (lower delay for what matters)."""
    counts = np.zeros(loads.shape[1], dtype=np.int64)
    left = sorted(int(f) for f in chosen)
    order = []
    rows = np.arange(loads.shape[1])
    while left:
        gains = [float(np.sum(value[rows, counts + loads[f]] - value[rows, counts])) for f in left]
        f = left.pop(int(np.argmax(gains)))
        order.append(f)
        counts += loads[f]
    return order


@register("optimal")
def optimal(instance: Instance, state: SchedulerState) -> Schedule:
    """Exact best open-loop schedule; raises InstanceTooLarge beyond small instances."""
    return optimal_open_loop(instance)


@dataclass(frozen=True, slots=True)
class MdpSolution:
    value: float  # U^{pi*}(S^1): optimal expected reward with per-frame feedback
    first_frame: tuple[int, ...]  # pi*(S^1): object indices of the optimal first action
    evaluations: int  # successor states the recursion visited


def mdp_optimal(instance: Instance, max_evaluations: int = MAX_MDP_EVALUATIONS) -> MdpSolution:
    """Solve the paper's MDP exactly: U(S^n) = max_A sum_S' P(S'|S,A) (R^n + U(S^(n+1))).

    The state is the set of (object, receiver) pairs delivered so far, as a bitmask
    over the pairs that can still earn reward; outcomes branch only on pairs with
    0 < p_ij < 1.
    """
    N, cap = instance.n_frames, instance.frame_bytes
    live = (instance.reward > 0.0) & ~instance.history & (instance.size_bytes <= cap)[:, None]
    objects = np.flatnonzero(live.any(axis=1))
    pair_k, pair_j = np.nonzero(live[objects])
    u, L = len(objects), len(pair_k)
    if u == 0 or N == 0:
        return MdpSolution(0.0, (), 0)
    if u > MAX_MDP_OBJECTS or L > MAX_MDP_PAIRS:
        raise InstanceTooLarge(
            f"optimal MDP: {u} objects / {L} receiver pairs exceed the limits "
            f"{MAX_MDP_OBJECTS} / {MAX_MDP_PAIRS}; use optimal_open_loop or 'greedy'"
        )
    p_pair = instance.p_deliver[instance.owner[objects[pair_k]], pair_j].tolist()
    y_pair = instance.reward[objects[pair_k], pair_j].tolist()
    pairs_of = [0] * u
    for e, t in enumerate(pair_k.tolist()):
        pairs_of[t] |= 1 << e
    sizes = instance.size_bytes[objects].tolist()
    bits, used = _subsets(instance.size_bytes[objects])
    feasible = [(int(b @ (1 << np.arange(u))), int(s)) for b, s in zip(bits, used) if s <= cap]

    actions_for: dict[int, list[int]] = {}

    def actions(pending: int) -> list[int]:
        """Maximal feasible loads among the pending objects, ascending bitmask."""
        got = actions_for.get(pending)
        if got is None:
            got = []
            for a, s in feasible:
                if a & ~pending:
                    continue
                room = cap - s
                if all(sizes[t] > room for t in range(u) if pending >> t & 1 and not a >> t & 1):
                    got.append(a)
            actions_for[pending] = got
        return got

    memo: dict[tuple[int, int], tuple[float, int]] = {}
    evaluations = 0

    def bellman(n: int, delivered: int) -> tuple[float, int]:
        nonlocal evaluations
        if n == N:
            return 0.0, 0
        hit = memo.get((n, delivered))
        if hit is not None:
            return hit
        pending = 0
        for t in range(u):
            if pairs_of[t] & ~delivered:
                pending |= 1 << t
        best = (0.0, 0)
        for a in actions(pending):
            todo = 0
            for t in range(u):
                if a >> t & 1:
                    todo |= pairs_of[t] & ~delivered
            q = 0.0
            sure = 0
            outcomes = [(0, 1.0)]
            for e in range(L):
                if todo >> e & 1:
                    q += p_pair[e] * y_pair[e]  # E[R^n] = sum over sent pairs of p * y
                    if p_pair[e] >= 1.0:
                        sure |= 1 << e
                    elif p_pair[e] > 0.0:
                        pe = p_pair[e]
                        outcomes = [(m, pr * (1.0 - pe)) for m, pr in outcomes] + [(m | 1 << e, pr * pe) for m, pr in outcomes]
            evaluations += len(outcomes)
            if evaluations > max_evaluations:
                raise InstanceTooLarge(
                    f"optimal MDP: more than {max_evaluations:.0e} successor states "
                    f"({u} objects, {L} receiver pairs, N={N}); use optimal_open_loop or 'greedy'"
                )
            for m, pr in outcomes:
                q += pr * bellman(n + 1, delivered | sure | m)[0]
            if q > best[0]:
                best = (q, a)
        memo[(n, delivered)] = best
        return best

    value, first = bellman(0, 0)
    return MdpSolution(value, tuple(int(objects[t]) for t in range(u) if first >> t & 1), evaluations)
