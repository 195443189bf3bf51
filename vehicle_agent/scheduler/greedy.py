"""Greedy max-weight scheduler (paper Algorithm 1) with starvation compensation, and
AutoCast's scheduler: the same, its frames' spare airtime filled (``fill.py``).

Starvation: the paper replaces H/s by H / (s / var_s) * m / var_m. var_s is common to
every object of an interval, so it scales all keys alike and is dropped; m / var_m
alone would give every never-skipped object (m = 0) a key of 0 and divide by zero when
all m are equal. We use boost * H/s with boost = 1 + m / max(var_m, 1), var_m the
variance of m over the candidates: plain H/s for m = 0, growing with m.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from vehicle_agent.scheduler.fill import _fill_frames, work_conserving
from vehicle_agent.scheduler.instance import Instance, Schedule
from vehicle_agent.scheduler.registry import register
from vehicle_agent.scheduler.state import SchedulerState


@njit(cache=True)
def _before(neg_key, a, b):
    """Strict order of the greedy: larger boost * H/s first, then lower index."""
    return neg_key[a] < neg_key[b] or (neg_key[a] == neg_key[b] and a < b)


@njit(cache=True)
def _greedy_frames(reward, p_deliver, owner, size_bytes, history, starvation, frame_bytes, n_frames):
    """x (N, K): Algorithm 1 with starvation compensation.

    Candidates are the objects with H > 0 that fit a frame. Per frame, objects go by
    decreasing boost * H/s (ties: lower index) and each is taken if it still fits, so
    the frame is filled first-fit down that order; then h is updated with p_ij for the
    objects sent and only their keys change, so the order is kept by one merge rather
    than a full sort per frame.
    """
    K, C = reward.shape
    x = np.zeros((n_frames, K), dtype=np.bool_)
    h = np.empty((K, C))
    weight = np.zeros(K)
    for k in range(K):
        w = 0.0
        for j in range(C):
            h[k, j] = 1.0 if history[k, j] else 0.0
            w += reward[k, j] * (1.0 - h[k, j])  # eq. GreedyMetric
        weight[k] = w
    n_cand = 0
    cand = np.empty(K, dtype=np.int64)
    for k in range(K):
        if weight[k] > 0.0 and size_bytes[k] <= frame_bytes:
            cand[n_cand] = k
            n_cand += 1
    cand = cand[:n_cand]
    if n_cand == 0:
        return x
    # starvation boost 1 + m / max(var_m, 1), var_m over the candidates (module docstring)
    mean_m = 0.0
    for c in range(n_cand):
        mean_m += starvation[cand[c]]
    mean_m /= n_cand
    var_m = 0.0
    for c in range(n_cand):
        var_m += (starvation[cand[c]] - mean_m) ** 2
    var_m = max(var_m / n_cand, 1.0)
    boost = np.empty(n_cand)
    neg_key = np.empty(n_cand)
    for c in range(n_cand):
        k = cand[c]
        boost[c] = 1.0 + starvation[k] / var_m
        neg_key[c] = -(weight[k] / size_bytes[k]) * boost[c]
    order = np.argsort(neg_key, kind="mergesort")  # stable: ties stay in index order
    merged = np.empty(n_cand, dtype=np.int64)
    sent = np.empty(n_cand, dtype=np.int64)
    is_sent = np.zeros(n_cand, dtype=np.bool_)
    for n in range(n_frames):
        min_size = frame_bytes + 1
        for c in range(n_cand):
            if neg_key[c] < 0.0 and size_bytes[cand[c]] < min_size:
                min_size = size_bytes[cand[c]]
        if min_size > frame_bytes:
            break
        room = frame_bytes
        n_sent = 0
        for t in range(n_cand):
            c = order[t]
            if neg_key[c] >= 0.0 or room < min_size:
                break
            k = cand[c]
            if size_bytes[k] <= room:
                x[n, k] = True
                room -= size_bytes[k]
                sent[n_sent] = c
                is_sent[c] = True
                n_sent += 1
        for t in range(n_sent):
            c = sent[t]
            k = cand[c]
            i = owner[k]
            w = 0.0
            for j in range(C):
                h[k, j] = 1.0 - (1.0 - h[k, j]) * (1.0 - p_deliver[i, j])  # expected delivery
                w += reward[k, j] * (1.0 - h[k, j])
            weight[k] = w
            neg_key[c] = -(w / size_bytes[k]) * boost[c] if w > 0.0 else 0.0
        for t in range(1, n_sent):  # insertion sort of the few re-keyed objects
            c = sent[t]
            u = t - 1
            while u >= 0 and _before(neg_key, c, sent[u]):
                sent[u + 1] = sent[u]
                u -= 1
            sent[u + 1] = c
        a, b, out = 0, 0, 0
        while out < n_cand:
            while a < n_cand and is_sent[order[a]]:
                a += 1
            if a < n_cand and (b >= n_sent or _before(neg_key, order[a], sent[b])):
                merged[out] = order[a]
                a += 1
            else:
                merged[out] = sent[b]
                b += 1
            out += 1
        order, merged = merged, order
        for t in range(n_sent):
            is_sent[sent[t]] = False
    return x


def greedy_schedule(instance: Instance, starvation: np.ndarray | None = None) -> Schedule:
    """Algorithm 1: per frame, fill S_f by decreasing H/s (times the starvation boost)."""
    if instance.n_objects == 0 or instance.n_frames == 0:
        return Schedule(tuple(() for _ in range(instance.n_frames)))
    m = np.zeros(instance.n_objects, dtype=np.int64) if starvation is None else np.asarray(starvation, dtype=np.int64)
    x = _greedy_frames(
        instance.reward,
        instance.p_deliver,
        instance.owner,
        instance.size_bytes,
        instance.history,
        m,
        np.int64(instance.frame_bytes),
        np.int64(instance.n_frames),
    )
    frames: list[list[int]] = [[] for _ in range(instance.n_frames)]
    for n, k in zip(*(a.tolist() for a in np.nonzero(x))):  # row by row, each row's objects ascending
        frames[n].append(k)
    return Schedule(tuple(tuple(f) for f in frames))


@register("greedy")
def greedy(instance: Instance, state: SchedulerState) -> Schedule:
    """Algorithm 1 with starvation compensation: only objects of positive weight."""
    return greedy_schedule(instance, state.starvation(instance))


@register("autocast")
def autocast(instance: Instance, state: SchedulerState) -> Schedule:
    """AutoCast's scheduler: Algorithm 1 with starvation compensation, then the frames'
    spare airtime filled with the remaining objects (work-conserving, ``fill.py``).

    ``work_conserving(instance, greedy(instance, state), state.cursor)``, in one kernel
    (``_autocast_frames``) where the instance has objects and frames and the cursor fits
    int64: the two schedulers' dozen numpy calls and three kernel calls were a tenth of
    the schedule stage."""
    cursor = state.cursor
    if instance.n_objects == 0 or instance.n_frames == 0 or \
            (cursor is not None and not all(-(1 << 63) <= int(c) < 1 << 63 for c in cursor)):
        return work_conserving(instance, greedy(instance, state), cursor)
    x, at = _autocast_frames(instance.reward, instance.p_deliver, instance.owner, instance.size_bytes,
                             instance.history, state.starvation(instance), np.int64(instance.frame_bytes),
                             np.int64(instance.n_frames), instance.unseen, instance.vids, instance.object_id,
                             np.int64(cursor[0] if cursor is not None else 0),
                             np.int64(cursor[1] if cursor is not None else 0), cursor is not None)
    frames: list[list[int]] = [[] for _ in range(instance.n_frames)]
    for n, k in zip(*(a.tolist() for a in np.nonzero(x))):  # row by row, each row's objects ascending
        frames[n].append(k)
    fill: list[list[int]] = [[] for _ in frames]
    for k, n in enumerate(at.tolist()):
        if n >= 0:
            fill[n].append(k)
    return Schedule(tuple(tuple(sorted(f + g)) for f, g in zip(frames, fill)), tuple(tuple(g) for g in fill))


@njit(cache=True)
def _autocast_frames(reward, p_deliver, owner, size_bytes, history, starvation, frame_bytes, n_frames, unseen, vids,
                     object_id, cursor_vid, cursor_oid, has_cursor):
    """(x, at): Algorithm 1's frames x (N, K) (``_greedy_frames``), then each object's
    spare-room frame (-1: none) as ``work_conserving`` fills them: by decreasing
    unseen / s, ties in round-robin order after the cursor (``fill_order``: a stable
    sort of the objects taken in that order), first fit (``_fill_frames``) of the
    objects x does not send and that fit a frame."""
    K = owner.shape[0]
    x = _greedy_frames(reward, p_deliver, owner, size_bytes, history, starvation, frame_bytes, n_frames)
    start = 0
    if has_cursor:  # round_robin_order's start: the objects at or before the cursor in (vid, id) order
        for k in range(K):
            v = vids[owner[k]]
            if v < cursor_vid or (v == cursor_vid and object_id[k] <= cursor_oid):
                start += 1
    rotated = np.empty(K, dtype=np.int64)
    for t in range(K):
        rotated[t] = (start + t) % K
    key = np.empty(K)
    for t in range(K):
        key[t] = -(unseen[rotated[t]] / size_bytes[rotated[t]])
    order = rotated[np.argsort(key, kind="mergesort")]  # stable: ties stay in round-robin order
    room = np.empty(n_frames, dtype=np.int64)
    taken = np.empty(K, dtype=np.bool_)
    for k in range(K):
        taken[k] = size_bytes[k] > frame_bytes
    for n in range(n_frames):
        used = 0
        for k in range(K):
            if x[n, k]:
                used += size_bytes[k]
                taken[k] = True
        room[n] = frame_bytes - used
    return x, _fill_frames(order, size_bytes, room, taken)


@register("greedy-plain")
def greedy_plain(instance: Instance, state: SchedulerState) -> Schedule:
    """Algorithm 1 without starvation compensation."""
    return greedy_schedule(instance)
