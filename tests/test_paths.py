"""The path kernels against hand-derived geometry and, to the bit, against the numpy
versions they replaced (kept here as the reference)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vehicle_agent.paths import arc_lengths, point_at, progress_along


def numpy_arc_lengths(path: np.ndarray) -> np.ndarray:
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])


def numpy_progress_along(path: np.ndarray, xy: np.ndarray, cum: np.ndarray | None = None) -> float:
    a, ab = path[:-1], np.diff(path, axis=0)
    len2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12)
    t = np.clip(np.einsum("ij,ij->i", xy - a, ab) / len2, 0.0, 1.0)
    i = int(np.argmin(np.linalg.norm(a + t[:, None] * ab - xy, axis=1)))
    return float((numpy_arc_lengths(path) if cum is None else cum)[i] + t[i] * np.sqrt(len2[i]))


def numpy_point_at(path: np.ndarray, s: float | np.ndarray, cum: np.ndarray | None = None) -> np.ndarray:
    cum = numpy_arc_lengths(path) if cum is None else cum
    s = np.clip(s, 0.0, cum[-1])
    return np.stack([np.interp(s, cum, path[:, 0]), np.interp(s, cum, path[:, 1])], axis=-1)


def test_a_path_measured_and_walked_by_hand():
    # 3-4-5: 5 m east-north-east, then 2 m north, then a repeated vertex
    path = np.array([[0.0, 0.0], [4.0, 3.0], [4.0, 5.0], [4.0, 5.0]])
    np.testing.assert_array_equal(arc_lengths(path), [0.0, 5.0, 7.0, 7.0])
    np.testing.assert_array_equal(point_at(path, 2.5), [2.0, 1.5])
    np.testing.assert_array_equal(point_at(path, np.array([-1.0, 6.0, 99.0])), [[0, 0], [4, 4], [4, 5]])
    assert point_at(path, np.zeros((2, 3))).shape == (2, 3, 2)
    assert progress_along(path, np.array([5.0, 4.0])) == 6.0  # beside the second segment, 1 m up it
    assert progress_along(path, np.array([-3.0, -4.0])) == 0.0  # behind the start
    assert arc_lengths(path[:1]).tolist() == [0.0] and arc_lengths(np.zeros((0, 2))).tolist() == [0.0]


coord = st.one_of(st.floats(-100, 100), st.sampled_from([0.0, -0.0, 1.0, 1e-7, 1e-13]))
paths = st.lists(st.tuples(coord, coord), min_size=1, max_size=30).map(lambda p: np.array(p, dtype=np.float64))


def _bits(a) -> bytes:
    return np.asarray(a, dtype=np.float64).tobytes()


@settings(max_examples=400, deadline=None)
@given(paths, st.lists(st.one_of(st.floats(-10, 300), st.just(np.nan)), max_size=20), st.booleans(),
       st.tuples(coord, coord), st.integers(0, 3))
def test_the_kernels_match_the_numpy_versions_to_the_bit(path, s, with_cum, xy, repeat):
    if repeat and len(path) > 1:  # repeated vertices: zero-length segments
        path = np.repeat(path, [repeat if k % 2 else 1 for k in range(len(path))], axis=0)
    cum = numpy_arc_lengths(path)
    assert _bits(arc_lengths(path)) == _bits(cum)
    given_cum = cum if with_cum else None
    s = np.array(s, dtype=np.float64)
    assert _bits(point_at(path, s, given_cum)) == _bits(numpy_point_at(path, s, given_cum))
    for one in s[:3]:
        assert _bits(point_at(path, float(one), given_cum)) == _bits(numpy_point_at(path, float(one), given_cum))
    assert _bits(point_at(path, cum)) == _bits(numpy_point_at(path, cum))  # at the vertices
    if len(path) >= 2:
        xy = np.array(xy)
        got, want = progress_along(path, xy, given_cum), numpy_progress_along(path, xy, given_cum)
        assert _bits(got) == _bits(want)
        on = path[len(path) // 2]  # a vertex: several segments equally near
        assert _bits(progress_along(path, on, given_cum)) == _bits(numpy_progress_along(path, on, given_cum))


def test_a_path_with_a_nan_vertex_answers_as_numpy():
    path = np.array([[0.0, 0.0], [np.nan, 1.0], [2.0, 2.0]])
    assert _bits(progress_along(path, np.array([1.0, 1.0]))) == _bits(numpy_progress_along(path, np.array([1.0, 1.0])))
    assert _bits(point_at(path, 1.0)) == _bits(numpy_point_at(path, 1.0))


def test_an_empty_path_is_refused():
    with pytest.raises(ValueError):
        progress_along(np.zeros((1, 2)), np.zeros(2))
    with pytest.raises(ValueError):
        point_at(np.zeros((0, 2)), 1.0)
