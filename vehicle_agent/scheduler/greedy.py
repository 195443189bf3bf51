"""Greedy max-weight scheduler (paper Algorithm 1) with starvation compensation."""

from __future__ import annotations

import numpy as np
from numba import njit

from vehicle_agent.scheduler.instance import Instance, Schedule
from vehicle_agent.scheduler.registry import register
from vehicle_agent.scheduler.state import SchedulerState


def starvation_boost(starvation: np.ndarray, candidates: np.ndarray) -> np.ndarray:
    """Factor on H/s for starved objects: 1 + m / max(var_m, 1), var_m over the candidates.

    The paper's key is H / (s / var_s) * m / var_m. var_s is common to every object of
    an interval, so it scales all keys alike and is dropped; m / var_m alone would give
    every never-skipped object (m = 0) a key of 0 and divide by zero when all m are
    equal, hence 1 + m / max(var_m, 1): plain H/s for m = 0, growing with m.
    """
    m = starvation.astype(np.float64)
    var_m = float(np.var(m[candidates])) if np.any(candidates) else 0.0
    return 1.0 + m / max(var_m, 1.0)


@njit(cache=True)
def _greedy_frames(reward, p_deliver, owner, size_bytes, h, boost, cand, frame_bytes, n_frames):
    """x (N, K): per frame, objects by decreasing boost * H/s, ties by index, each
    taken if it still fits (first fit down the order); h updated with p_ij after
    each frame. ``h`` (float64 (K, C)) is updated in place."""
    K, C = reward.shape
    n_cand = cand.shape[0]
    x = np.zeros((n_frames, K), dtype=np.bool_)
    weight = np.zeros(n_cand)
    for c in range(n_cand):
        k = cand[c]
        w = 0.0
        for j in range(C):
            w += reward[k, j] * (1.0 - h[k, j])  # eq. GreedyMetric
        weight[c] = w
    neg_key = np.empty(n_cand)
    sent = np.empty(n_cand, dtype=np.int64)
    for n in range(n_frames):
        min_size = frame_bytes + 1
        for c in range(n_cand):
            k = cand[c]
            if weight[c] > 0.0:
                neg_key[c] = -(weight[c] / size_bytes[k]) * boost[k]
                if size_bytes[k] < min_size:
                    min_size = size_bytes[k]
            else:
                neg_key[c] = np.inf
        if min_size > frame_bytes:
            break
        order = np.argsort(neg_key, kind="mergesort")  # stable: equal keys stay in index order
        room = frame_bytes
        n_sent = 0
        for t in range(n_cand):
            c = order[t]
            if neg_key[c] == np.inf or room < min_size:
                break
            k = cand[c]
            if size_bytes[k] <= room:
                x[n, k] = True
                room -= size_bytes[k]
                sent[n_sent] = c
                n_sent += 1
        for t in range(n_sent):
            c = sent[t]
            k = cand[c]
            i = owner[k]
            w = 0.0
            for j in range(C):
                h[k, j] = 1.0 - (1.0 - h[k, j]) * (1.0 - p_deliver[i, j])  # expected delivery
                w += reward[k, j] * (1.0 - h[k, j])
            weight[c] = w
    return x


def greedy_schedule(instance: Instance, starvation: np.ndarray | None = None) -> Schedule:
    """Algorithm 1: per frame, fill S_f by decreasing H/s (times the starvation boost)."""
    K = instance.n_objects
    if K == 0 or instance.n_frames == 0:
        return Schedule(tuple(() for _ in range(instance.n_frames)))
    fits = instance.size_bytes <= instance.frame_bytes
    candidates = instance.wanted() & fits
    m = np.zeros(K, dtype=np.int64) if starvation is None else np.asarray(starvation, dtype=np.int64)
    boost = starvation_boost(m, candidates)
    x = _greedy_frames(
        instance.reward,
        instance.p_deliver,
        instance.owner,
        instance.size_bytes,
        instance.history.astype(np.float64),
        boost,
        np.flatnonzero(candidates).astype(np.int64),
        np.int64(instance.frame_bytes),
        np.int64(instance.n_frames),
    )
    return Schedule(tuple(tuple(np.flatnonzero(row).tolist()) for row in x))


@register("greedy", "autocast")
def greedy(instance: Instance, state: SchedulerState) -> Schedule:
    """AutoCast's scheduler: greedy max-weight with starvation compensation."""
    return greedy_schedule(instance, state.starvation(instance))


@register("greedy-plain")
def greedy_plain(instance: Instance, state: SchedulerState) -> Schedule:
    """Algorithm 1 without starvation compensation."""
    return greedy_schedule(instance)
