"""Slow, obviously correct references for the tests: plain enumeration, no pruning."""

from __future__ import annotations

from functools import lru_cache
from itertools import combinations, product

from vehicle_agent.scheduler.instance import Instance


def _feasible_subsets(sizes: list[int], capacity: int) -> list[tuple[int, ...]]:
    return [
        subset
        for r in range(len(sizes) + 1)
        for subset in combinations(range(len(sizes)), r)
        if sum(sizes[k] for k in subset) <= capacity
    ]


def brute_knapsack(profit: list[float], sizes: list[int], capacity: int) -> float:
    """max sum of profit over every subset that fits."""
    return max(sum(profit[k] for k in s) for s in _feasible_subsets(list(sizes), capacity))


def brute_open_loop(instance: Instance) -> float:
    """max expected reward over every sequence of N feasible frame loads, h simulated frame by frame."""
    y = instance.reward.tolist()
    p = instance.p_object().tolist()
    h0 = instance.history.astype(float).tolist()
    subsets = _feasible_subsets(instance.size_bytes.tolist(), instance.frame_bytes)
    best = 0.0
    for plan in product(subsets, repeat=instance.n_frames):
        h = [row[:] for row in h0]
        total = 0.0
        for frame in plan:
            for k in frame:
                for j in range(instance.n_vehicles):
                    total += y[k][j] * (1.0 - h[k][j]) * p[k][j]
                    h[k][j] = 1.0 - (1.0 - h[k][j]) * (1.0 - p[k][j])
        best = max(best, total)
    return best


def brute_mdp(instance: Instance) -> float:
    """The MDP's optimal value by expectimax over every feasible action and every
    delivery outcome of every pair with reward (memoised on the exact state)."""
    K, C, N = instance.n_objects, instance.n_vehicles, instance.n_frames
    y = instance.reward.tolist()
    p = instance.p_object().tolist()
    subsets = _feasible_subsets(instance.size_bytes.tolist(), instance.frame_bytes)
    start = frozenset((k, j) for k in range(K) for j in range(C) if instance.history[k, j])

    @lru_cache(maxsize=None)
    def value(n: int, have: frozenset) -> float:
        if n == N:
            return 0.0
        best = 0.0
        for action in subsets:
            pending = [(k, j) for k in action for j in range(C) if y[k][j] > 0 and (k, j) not in have]
            q = 0.0
            for outcome in product((False, True), repeat=len(pending)):
                prob, gained, got = 1.0, 0.0, set(have)
                for (k, j), ok in zip(pending, outcome):
                    prob *= p[k][j] if ok else 1.0 - p[k][j]
                    if ok:
                        gained += y[k][j]
                        got.add((k, j))
                if prob > 0.0:
                    q += prob * (gained + value(n + 1, frozenset(got)))
            best = max(best, q)
        return best

    return value(0, start)


def reference_greedy(instance: Instance, starvation: list[int] | None = None) -> list[list[int]]:
    """Algorithm 1 written plainly: every frame, recompute H, sort everything, fill."""
    K, C = instance.n_objects, instance.n_vehicles
    y = instance.reward.tolist()
    p = instance.p_object().tolist()
    size = instance.size_bytes.tolist()
    h = instance.history.astype(float).tolist()
    m = [0] * K if starvation is None else list(starvation)

    def weight(k: int) -> float:
        total = 0.0
        for j in range(C):
            total += y[k][j] * (1.0 - h[k][j])
        return total

    cands = [k for k in range(K) if weight(k) > 0.0 and size[k] <= instance.frame_bytes]
    if cands:
        mean = sum(m[k] for k in cands) / len(cands)
        var = max(sum((m[k] - mean) ** 2 for k in cands) / len(cands), 1.0)
    boost = {k: 1.0 + m[k] / var for k in cands}
    frames = []
    for _ in range(instance.n_frames):
        keyed = sorted((-(weight(k) / size[k]) * boost[k], k) for k in cands if weight(k) > 0.0)
        room, frame = instance.frame_bytes, []
        for _, k in keyed:
            if size[k] <= room:
                frame.append(k)
                room -= size[k]
        for k in frame:
            for j in range(C):
                h[k][j] = 1.0 - (1.0 - h[k][j]) * (1.0 - p[k][j])
        frames.append(sorted(frame))
    return frames
