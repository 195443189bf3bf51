"""What an agent carries from one decision interval to the next.

The state is a pure function of the instances and schedules seen so far, so every
vehicle that heard the same control messages holds the same state: starvation
counters m for the greedy scheduler and the round-robin cursor for agnostic.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vehicle_agent.scheduler.instance import Instance, ObjectKey, Schedule


@dataclass(frozen=True, slots=True)
class SchedulerState:
    """``starved``: (object key, m) for every object skipped for m >= 1 intervals while
    still occluded and relevant to someone, sorted by key. ``cursor``: the key of the
    last object sent, from which round robin continues."""

    starved: tuple[tuple[ObjectKey, int], ...] = ()
    cursor: ObjectKey | None = None

    def starvation(self, instance: Instance) -> np.ndarray:
        """int64 (K,): m for each object of ``instance`` (0 if never skipped)."""
        m = dict(self.starved)
        return np.array([m.get(key, 0) for key in instance.keys()], dtype=np.int64)

    def advance(self, instance: Instance, schedule: Schedule) -> SchedulerState:
        """The state after ``schedule`` was played on ``instance``: a wanted object that
        was not sent gets m + 1, a sent or no longer wanted one is forgotten; the cursor
        moves to the last object sent in round-robin order."""
        m_prev = dict(self.starved)
        sent = schedule.sent()
        keys = instance.keys()
        wanted = instance.wanted()
        starved = tuple(
            (key, m_prev.get(key, 0) + 1) for k, key in enumerate(keys) if wanted[k] and k not in sent
        )
        return SchedulerState(starved=starved, cursor=_last_in_rotation(keys, sent, self.cursor))


def _last_in_rotation(keys: list[ObjectKey], sent: frozenset[int], cursor: ObjectKey | None) -> ObjectKey | None:
    """Among the sent objects, the one furthest along the cyclic key order that starts
    just after ``cursor``; the old cursor if nothing was sent."""
    if not sent:
        return cursor
    sent_keys = sorted(keys[k] for k in sent)
    if cursor is None:
        return sent_keys[-1]
    before = [key for key in sent_keys if key <= cursor]
    return before[-1] if before else sent_keys[-1]
