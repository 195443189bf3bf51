"""Every built-in scheduler's numba kernels compiled (or loaded from the cache) on one small instance.

An agent runs one scheduler, but a run's scheme picks which: the launcher warms them
all once, so no agent compiles its scheduler in its first interval.
"""

from __future__ import annotations

import numpy as np

from vehicle_agent.scheduler.instance import instance_from_arrays, link_probabilities
from vehicle_agent.scheduler.knapsack import InstanceTooLarge
from vehicle_agent.scheduler.registry import get
from vehicle_agent.scheduler.state import SchedulerState

BUILT_IN = ("greedy", "fptas", "knapsack", "agnostic", "optimal")


def warm_up() -> None:
    """Three vehicles, each offering two objects, over two frames too small for them all:
    two intervals through each scheduler, the second with the objects the first starved,
    from no history and from one starved object (numba types a column of one row apart)."""
    vids = np.array([100, 101, 102])
    xy = np.array([[0.0, 0.0], [30.0, 5.0], [-20.0, 40.0]])
    owner = np.repeat(vids, 2)
    reward = np.array([[0.0, 0.4, 0.7], [0.0, 0.2, 0.0], [0.5, 0.0, 0.3],
                       [0.1, 0.0, 0.6], [0.8, 0.3, 0.0], [0.2, 0.9, 0.0]])
    inst = instance_from_arrays(vids, owner, np.arange(6), np.array([2000, 3200, 1500, 4800, 2600, 900]), reward,
                                link_probabilities(xy), frame_bytes=4000, n_frames=2, bandwidth_bps=7.2e6,
                                frame_duration_s=0.01, unseen=np.array([2.0, 1.0, 1.0, 2.0, 1.0, 1.0]))
    one_starved = SchedulerState(np.array([[100, 1]], dtype=np.int64), np.array([1], dtype=np.int64))
    for name in BUILT_IN:
        for start in (SchedulerState(), one_starved):
            _two_intervals(name, inst, start)


def _two_intervals(name: str, inst, state: SchedulerState) -> None:
    for _ in range(2):
        try:
            state = state.advance(inst, get(name)(inst, state))
        except InstanceTooLarge:
            return
