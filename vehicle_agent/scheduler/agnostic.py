"""The paper's Agnostic baseline: round robin over all objects, blind to v and r."""

from __future__ import annotations

import numpy as np

from vehicle_agent.scheduler.instance import Instance, Schedule
from vehicle_agent.scheduler.registry import register
from vehicle_agent.scheduler.state import SchedulerState


def round_robin_order(instance: Instance, cursor: tuple[int, int] | None) -> np.ndarray:
    """Object indices in (vid, object id) order, rotated to start just after ``cursor``."""
    start = 0
    if cursor is not None:
        v, o = instance.vids[instance.owner], instance.object_id
        start = int(np.count_nonzero((v < cursor[0]) | ((v == cursor[0]) & (o <= cursor[1]))))
    return np.roll(np.arange(instance.n_objects), -start)


def agnostic_schedule(instance: Instance, cursor: tuple[int, int] | None = None) -> Schedule:
    """Send objects in round-robin order, each at most once per interval: an object that
    does not fit the rest of a frame opens the next frame; one larger than S_f is skipped."""
    frames: list[list[int]] = [[] for _ in range(instance.n_frames)]
    n, room = 0, instance.frame_bytes
    sizes = instance.size_bytes.tolist()
    for k in round_robin_order(instance, cursor).tolist():
        if sizes[k] > instance.frame_bytes:
            continue
        if sizes[k] > room:
            n, room = n + 1, instance.frame_bytes
        if n >= instance.n_frames:
            break
        frames[n].append(k)
        room -= sizes[k]
    return Schedule.from_sets(frames)


@register("agnostic")
def agnostic(instance: Instance, state: SchedulerState) -> Schedule:
    """Round robin continuing from the cursor the agent keeps in its state."""
    return agnostic_schedule(instance, state.cursor)
