"""What an agent carries from one decision interval to the next.

The state is a pure function of the instances and schedules seen so far, so every
vehicle that heard the same control messages holds the same state: starvation
counters m for the greedy scheduler and the round-robin cursor for agnostic.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit

from vehicle_agent.scheduler.instance import Instance, ObjectKey, Schedule


def _no_keys() -> np.ndarray:
    return np.zeros((0, 2), dtype=np.int64)


def _no_counts() -> np.ndarray:
    return np.zeros(0, dtype=np.int64)


@dataclass(frozen=True, slots=True, eq=False)
class SchedulerState:
    """``starved_key`` (S, 2) (vid, object id), ascending, with ``starved_m`` (S,): the
    objects skipped for m >= 1 intervals while still occluded and relevant to someone.
    ``cursor``: the key of the last object sent, from which round robin continues.
    ``order_key``: what a shuffled order is drawn from (the tick, agreed by the group),
    so that every vehicle that schedules the same instance draws the same order."""

    starved_key: np.ndarray = field(default_factory=_no_keys)
    starved_m: np.ndarray = field(default_factory=_no_counts)
    cursor: ObjectKey | None = None
    order_key: int = 0

    def __post_init__(self) -> None:
        self.starved_key.setflags(write=False)
        self.starved_m.setflags(write=False)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, SchedulerState):
            return NotImplemented
        return (
            self.cursor == other.cursor
            and self.order_key == other.order_key
            and np.array_equal(self.starved_key, other.starved_key)
            and np.array_equal(self.starved_m, other.starved_m)
        )

    def starved(self) -> dict[ObjectKey, int]:
        """m by object key, for logs and tests."""
        return {(int(v), int(o)): int(m) for (v, o), m in zip(self.starved_key, self.starved_m)}

    def starvation(self, instance: Instance) -> np.ndarray:
        """int64 (K,): m for each object of ``instance`` (0 if never skipped)."""
        m = np.zeros(instance.n_objects, dtype=np.int64)
        if len(self.starved_m):
            at = _merge_join(instance.vids[instance.owner], instance.object_id, self.starved_key[:, 0], self.starved_key[:, 1])
            found = at >= 0
            m[at[found]] = self.starved_m[found]
        return m

    def advance(self, instance: Instance, schedule: Schedule) -> SchedulerState:
        """The state after ``schedule`` was played on ``instance``: a wanted object that
        was not sent gets m + 1, a sent or no longer wanted one is forgotten; the cursor
        moves to the last object sent in round-robin order."""
        sent = np.zeros(instance.n_objects, dtype=bool)
        sent[list(schedule.sent())] = True
        starving = instance.wanted() & ~sent
        keys = np.stack([instance.vids[instance.owner], instance.object_id], axis=1)
        return SchedulerState(
            starved_key=keys[starving],
            starved_m=self.starvation(instance)[starving] + 1,
            cursor=_last_in_rotation(keys, np.flatnonzero(sent), self.cursor),
        )


@njit(cache=True)
def _merge_join(a_vid, a_oid, b_vid, b_oid):
    """For each key of b, its position in a, or -1; both lists ascending by (vid, oid)."""
    at = np.full(b_vid.shape[0], -1, dtype=np.int64)
    i = 0
    for t in range(b_vid.shape[0]):
        while i < a_vid.shape[0] and (a_vid[i] < b_vid[t] or (a_vid[i] == b_vid[t] and a_oid[i] < b_oid[t])):
            i += 1
        if i < a_vid.shape[0] and a_vid[i] == b_vid[t] and a_oid[i] == b_oid[t]:
            at[t] = i
    return at


def _last_in_rotation(keys: np.ndarray, sent: np.ndarray, cursor: ObjectKey | None) -> ObjectKey | None:
    """Among the sent objects (indices, ascending = key order), the one furthest along
    the cyclic key order that starts just after ``cursor``; the old cursor if none."""
    if len(sent) == 0:
        return cursor
    last = sent[-1]
    if cursor is not None:
        v, o = keys[sent, 0], keys[sent, 1]
        wrapped = sent[(v < cursor[0]) | ((v == cursor[0]) & (o <= cursor[1]))]
        if len(wrapped):
            last = wrapped[-1]
    return int(keys[last, 0]), int(keys[last, 1])
