"""The paper's Agnostic baseline: every object alike, blind to v and r.

``agnostic``: round robin over all objects, rotating from interval to interval (our
model). ``agnostic-shuffle``: a fresh random order every interval, as its authors'
code shuffles the candidate list (the paper's model, ``docs/models.md``); the order
is drawn from the state's ``order_key`` and each object's key, so every vehicle that
schedules the same instance in the same interval draws the same order.
"""

from __future__ import annotations

import numpy as np

from channel_proxy.loss import keyed_uniform
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


SHUFFLE_SALT = 0x73687566  # keys the shuffle's draws apart from the channel's and the grouping's


def shuffled_order(instance: Instance, order_key: int) -> np.ndarray:
    """Object indices in a random order drawn from (``order_key``, vid, object id): a
    pure function of them, so equal on every vehicle (ties, which need equal 53-bit
    draws, broken by the key order)."""
    v, o = instance.vids[instance.owner].astype(np.int64), instance.object_id.astype(np.int64)
    draw = keyed_uniform(SHUFFLE_SALT, order_key, v, o) if instance.n_objects else np.zeros(0)
    return np.lexsort((o, v, draw))


def agnostic_schedule(instance: Instance, cursor: tuple[int, int] | None = None,
                      order: np.ndarray | None = None) -> Schedule:
    """Send objects in round-robin order (or ``order``), each at most once per interval:
    an object that does not fit the rest of a frame opens the next frame; one larger
    than S_f is skipped."""
    frames: list[list[int]] = [[] for _ in range(instance.n_frames)]
    n, room = 0, instance.frame_bytes
    sizes = instance.size_bytes.tolist()
    for k in (round_robin_order(instance, cursor) if order is None else order).tolist():
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


@register("agnostic-shuffle")
def agnostic_shuffle(instance: Instance, state: SchedulerState) -> Schedule:
    """A fresh random order every interval, drawn from the state's ``order_key``."""
    return agnostic_schedule(instance, order=shuffled_order(instance, state.order_key))
