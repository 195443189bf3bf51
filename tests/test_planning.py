"""Planning helpers against hand-derived geometry."""

import numpy as np

from vehicle_agent.paths import arc_lengths
from vehicle_agent.planning import path_until


def test_a_path_is_cut_at_the_stop_point():
    # 10 m east, then north-east: the cut at 12 m lies 2 m along the diagonal
    path = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 10.0]])
    s = arc_lengths(path)
    np.testing.assert_allclose(path_until(path, s, 5.0), [[0, 0], [5, 0]])
    np.testing.assert_allclose(path_until(path, s, 12.0), [[0, 0], [10, 0], [10 + np.sqrt(2), np.sqrt(2)]])
    # a stop point at the car still leaves a 0.5 m stub to steer along
    np.testing.assert_allclose(path_until(path, s, 0.0), [[0, 0], [0.5, 0]])
    assert path_until(path, s, 100.0) is path
