"""Per-frame 0/1 knapsack (paper eq. DP): exact DP over bytes, and a profit-scaling FPTAS.

Each frame n is the knapsack max sum H^n_(i,k) x_(i,k) s.t. sum s_(i,k) x_(i,k) <= S_f.
The frame-by-frame schedulers ``knapsack`` (exact) and ``fptas`` solve it for frame 1,
update h with the expected delivery, and go on to the next frame, as greedy does.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numba import njit

from vehicle_agent.scheduler.fill import work_conserving
from vehicle_agent.scheduler.instance import Instance, Schedule, deliver_expected, weight_H
from vehicle_agent.scheduler.registry import register
from vehicle_agent.scheduler.state import SchedulerState

DEFAULT_EPSILON = 0.1
MAX_EXACT_CELLS = 100_000_000  # items x bytes in the exact DP's choice table (1 byte each)
MAX_FPTAS_CELLS = 200_000_000  # items x profit levels in the FPTAS's choice table


class InstanceTooLarge(ValueError):
    """An exact or approximate solver refused an instance it cannot finish in memory/time."""


@njit(cache=True)
def _knapsack_by_bytes(profit, size, capacity):
    """Exact 0/1 knapsack: best[w] = max profit within w bytes; an item is taken only
    when strictly better, so ties keep the lower-index solution."""
    n = profit.shape[0]
    best = np.zeros(capacity + 1)
    take = np.zeros((n, capacity + 1), dtype=np.bool_)
    for t in range(n):
        s = size[t]
        for w in range(capacity, s - 1, -1):
            cand = best[w - s] + profit[t]
            if cand > best[w]:
                best[w] = cand
                take[t, w] = True
    chosen = np.zeros(n, dtype=np.bool_)
    w = capacity
    for t in range(n - 1, -1, -1):
        if take[t, w]:
            chosen[t] = True
            w -= size[t]
    return chosen


@njit(cache=True)
def _knapsack_by_profit(scaled, size, capacity, levels):
    """min_bytes[P] = fewest bytes reaching scaled profit exactly P; returns the items
    of the largest P that fits ``capacity``."""
    n = scaled.shape[0]
    big = np.iinfo(np.int64).max
    min_bytes = np.full(levels, big, dtype=np.int64)
    min_bytes[0] = 0
    take = np.zeros((n, levels), dtype=np.bool_)
    top = 0
    for t in range(n):
        q = scaled[t]
        if q == 0:
            continue
        hi = min(top + q, levels - 1)
        for P in range(hi, q - 1, -1):
            prev = min_bytes[P - q]
            if prev != big and prev + size[t] < min_bytes[P]:
                min_bytes[P] = prev + size[t]
                take[t, P] = True
        top = hi
    P = top
    while min_bytes[P] > capacity:
        P -= 1
    chosen = np.zeros(n, dtype=np.bool_)
    for t in range(n - 1, -1, -1):
        if take[t, P]:
            chosen[t] = True
            P -= scaled[t]
    return chosen


def knapsack_exact(profit: np.ndarray, size_bytes: np.ndarray, capacity: int) -> np.ndarray:
    """bool (n,): an optimal 0/1 knapsack selection (DP over bytes, O(n * capacity)).

    Sizes and capacity are first divided by the sizes' greatest common divisor (point
    clouds are whole points of equal byte size), which changes no solution."""
    profit = np.asarray(profit, dtype=np.float64)
    size_bytes = np.asarray(size_bytes, dtype=np.int64)
    live = np.flatnonzero((profit > 0) & (size_bytes <= capacity))
    chosen = np.zeros(len(profit), dtype=bool)
    if len(live) == 0:
        return chosen
    unit = int(np.gcd.reduce(size_bytes[live]))
    cells = len(live) * (capacity // unit + 1)
    if cells > MAX_EXACT_CELLS:
        raise InstanceTooLarge(
            f"exact knapsack: {len(live)} items x {capacity // unit + 1} capacity steps = {cells:.2g} cells "
            f"exceeds {MAX_EXACT_CELLS:.0e}; use 'fptas' or 'greedy'"
        )
    chosen[live] = _knapsack_by_bytes(profit[live], size_bytes[live] // unit, np.int64(capacity // unit))
    return chosen


def knapsack_fptas(profit: np.ndarray, size_bytes: np.ndarray, capacity: int, epsilon: float = DEFAULT_EPSILON) -> np.ndarray:
    """bool (n,): a selection worth >= (1 - epsilon) * optimum.

    Profits are scaled by K = epsilon * LB / n and floored, LB <= OPT being the better
    of the density-greedy prefix and the best single item; the scaled problem is
    solved exactly by a DP over profit. Each item loses < K, so the loss is < n * K =
    epsilon * LB <= epsilon * OPT. The DP needs profit levels only up to UB / K, UB the
    fractional (LP) bound <= 2 LB, so at most 2n/epsilon levels: O(n^2 / epsilon).
    Leftover room is then filled by density, which can only add profit.
    """
    if not 0.0 < epsilon < 1.0:
        raise ValueError(f"epsilon must lie in (0, 1), got {epsilon}")
    profit = np.asarray(profit, dtype=np.float64)
    size_bytes = np.asarray(size_bytes, dtype=np.int64)
    live = np.flatnonzero((profit > 0) & (size_bytes <= capacity))
    chosen = np.zeros(len(profit), dtype=bool)
    if len(live) == 0:
        return chosen
    v, s = profit[live], size_bytes[live]
    density_order = np.lexsort((np.arange(len(v)), -(v / s)))
    cum = np.cumsum(s[density_order])
    fit = int(np.searchsorted(cum, capacity, side="right"))  # items of the greedy prefix
    prefix = float(v[density_order[:fit]].sum())
    lower = max(prefix, float(v.max()))
    upper = prefix
    if fit < len(v):
        nxt = density_order[fit]
        room = capacity - (int(cum[fit - 1]) if fit else 0)
        upper += v[nxt] * room / s[nxt]
    scale = epsilon * lower / len(v)
    scaled = np.floor(v / scale).astype(np.int64)
    levels = int(min(np.floor(upper / scale) + 1, scaled.sum())) + 1  # +1: slack for rounding in upper / scale
    if len(v) * levels > MAX_FPTAS_CELLS:
        raise InstanceTooLarge(
            f"fptas: {len(v)} items x {levels} profit levels exceeds {MAX_FPTAS_CELLS:.0e}; raise epsilon or use 'greedy'"
        )
    pick = _knapsack_by_profit(scaled, s, np.int64(capacity), np.int64(levels))
    room = capacity - int(s[pick].sum())
    for t in density_order:
        if not pick[t] and s[t] <= room:
            pick[t] = True
            room -= int(s[t])
    chosen[live] = pick
    return chosen


FrameSolver = Callable[[np.ndarray, np.ndarray, int], np.ndarray]  # (H, sizes, S_f) -> chosen


def frame_by_frame(instance: Instance, solve_frame: FrameSolver) -> Schedule:
    """Solve each frame's knapsack on H^n, then update h with p_ij, N times."""
    h = instance.history.astype(np.float64)
    p = instance.p_object()
    frames = []
    for _ in range(instance.n_frames):
        sent = solve_frame(weight_H(instance.reward, h), instance.size_bytes, instance.frame_bytes)
        frames.append(tuple(np.flatnonzero(sent).tolist()))
        h = deliver_expected(h, p, sent)
    return Schedule(tuple(frames))


@register("fptas")
def fptas(instance: Instance, state: SchedulerState, epsilon: float = DEFAULT_EPSILON) -> Schedule:
    """Per-frame FPTAS knapsack on H (paper's FPTAS-based scheduler)."""
    return frame_by_frame(instance, lambda H, s, cap: knapsack_fptas(H, s, cap, epsilon))


@register("autocast-fptas")
def autocast_fptas(instance: Instance, state: SchedulerState) -> Schedule:
    """The FPTAS scheduler, its frames' spare airtime filled as AutoCast's (``fill.py``)."""
    return work_conserving(instance, fptas(instance, state), state.cursor)


@register("knapsack")
def knapsack(instance: Instance, state: SchedulerState) -> Schedule:
    """Per-frame exact knapsack DP on H: each frame optimal given the state before it."""
    return frame_by_frame(instance, knapsack_exact)
