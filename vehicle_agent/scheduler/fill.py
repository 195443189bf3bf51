"""Work-conserving AutoCast: spare airtime of the interval carries the remaining objects.

Algorithm 1 sends only objects of positive weight H, so once every wanted object is
delivered (p_ij = 1 at short range) the channel idles, while a relevance estimate that
missed an object (a receiver's plan unknown, a tracker's cold start) gets nothing. The
paper's AutoCast "does transmit objects with less relevance when possible". Here the
reward-weighted schedule is kept exactly as it is (the *primary*) and, frame by frame,
the room each frame leaves is filled first-fit with objects the primary does not send,
each at most once per interval, in a secondary order every vehicle computes alike:

1. decreasing unseen / s: the receivers' expected number of vehicles that do not see
   the object themselves, sum_j (1 - v_(i,k),j), per byte (``Instance.unseen``);
2. ties (e.g. objects nobody reports) in agnostic's round-robin order from the state's
   cursor, so a congested channel still rotates through them.

The filled objects only take room the primary left, and the TDMA layout puts them after
every primary transmission of their frame (``tdma.py``), so no object of the primary is
delayed: the primary's schedule and airtimes are unchanged.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from vehicle_agent.scheduler.instance import Instance, ObjectKey, Schedule


@njit(cache=True)
def _fill_frames(order, size_bytes, room, taken):
    """First fit of the objects in ``order`` (skipping ``taken``) into each frame's
    ``room`` in turn; returns the frame of each object, -1 if none."""
    n_frames = room.shape[0]
    at = np.full(size_bytes.shape[0], -1, dtype=np.int64)
    left = room.copy()
    for n in range(n_frames):
        smallest = np.int64(1) << 62
        for t in range(order.shape[0]):
            k = order[t]
            if not taken[k] and size_bytes[k] < smallest:
                smallest = size_bytes[k]
        if smallest > left[n]:
            continue
        for t in range(order.shape[0]):
            k = order[t]
            if taken[k] or size_bytes[k] > left[n]:
                continue
            at[k] = n
            taken[k] = True
            left[n] -= size_bytes[k]
            if left[n] < smallest:
                break
    return at


def fill_order(instance: Instance, cursor: ObjectKey | None = None) -> np.ndarray:
    """Object indices by decreasing unseen / s, ties in round-robin order after ``cursor``."""
    K = instance.n_objects
    if cursor is None or K == 0:
        rotation = np.arange(K)
    else:  # round_robin_order's rank of each object: (k - start) mod K, without its roll and scatter
        v, o = instance.vids[instance.owner], instance.object_id
        start = int(np.count_nonzero((v < cursor[0]) | ((v == cursor[0]) & (o <= cursor[1]))))
        rotation = (np.arange(K) - start) % K
    return np.lexsort((rotation, -(instance.unseen / instance.size_bytes)))


def work_conserving(instance: Instance, primary: Schedule, cursor: ObjectKey | None = None) -> Schedule:
    """``primary`` plus, in each frame's spare room, objects it does not send (module docstring)."""
    if instance.n_objects == 0 or instance.n_frames == 0:
        return primary
    frames = [list(f) for f in primary.frames] + [[] for _ in range(instance.n_frames - len(primary.frames))]
    sizes = instance.size_bytes.tolist()
    room = np.array([instance.frame_bytes - sum(sizes[k] for k in f) for f in frames], dtype=np.int64)
    taken = instance.size_bytes > instance.frame_bytes
    taken[list(primary.sent())] = True
    at = _fill_frames(fill_order(instance, cursor), instance.size_bytes, room, taken)
    fill = [[] for _ in frames]
    for k, n in enumerate(at.tolist()):
        if n >= 0:
            fill[n].append(k)
    return Schedule(tuple(tuple(sorted(f + g)) for f, g in zip(frames, fill)), tuple(tuple(g) for g in fill))
