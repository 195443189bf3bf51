"""Random scenes shared by the fusion tests (tests/test_dataplane.py,
tests/test_dataplane_kernels.py)."""

from __future__ import annotations

import numpy as np

from protocol.messages import Pose
from vehicle_agent.frames import world_to_sensor
from vehicle_agent.payload import ObjectPayload, decode_objects, encode_object
from vehicle_agent.perception import ABOVE, EMPTY, GROUND, Grid, GridSpec


def received_intervals(rng: np.random.Generator, ticks: int, xy_half_m: float, z_low_m: float):
    """Random intervals of receptions for the fusion tests: per tick, (t_now, the last
    five of our poses, the decoded batch, a random 20 m grid). Up to 11 objects of up
    to 39 points a tick, centred within ``xy_half_m`` of the origin, heights from
    ``z_low_m`` to 2 m, sent from random poses, some late or aged (up to 1.2 s)."""
    spec = GridSpec(half_extent_m=10.0)
    n = spec.cells
    poses: list[Pose] = []
    for tick in range(ticks):
        t_now = tick * 0.1
        poses = (poses + [Pose(float(rng.normal(0, 1)), float(rng.normal(0, 1)), float(rng.normal(0, 0.2)))])[-5:]
        objs = []
        for _ in range(int(rng.integers(0, 12))):
            m = int(rng.integers(0, 40))
            c = rng.uniform(-xy_half_m, xy_half_m, 3)
            pts = np.column_stack([rng.normal(c[0], 1.5, m), rng.normal(c[1], 1.0, m), rng.uniform(z_low_m, 2, m)])
            pose = Pose(*rng.normal(0, 20, 2), float(rng.uniform(-np.pi, np.pi)))
            sensor = world_to_sensor(pts, pose, 1.9).astype(np.float32)
            objs.append(ObjectPayload(int(rng.integers(0, 5)), int(rng.integers(0, 6)), tick,
                                      float(np.float32(t_now - rng.choice([0.0, 0.0, 0.1, 0.4, 1.2]))), pose, 1.9,
                                      sensor.mean(axis=0) if m else np.zeros(3, np.float32),
                                      rng.normal(0, 3, 2).astype(np.float32), sensor))
        batch, _ = decode_objects([encode_object(o) for o in objs])
        state = rng.choice(np.array([EMPTY, GROUND, ABOVE], dtype=np.uint8), (n, n), p=[0.2, 0.6, 0.2])
        yield t_now, poses, batch, Grid(spec, -n // 2, -n // 2, state, np.ones((n, n), dtype=bool))
