"""The ego's report gathers its fused view's points straight into float32
(``vehicle_agent.__main__.Pipeline._report``); it must hold the bits the float64
gathering cast after gave, which the logged runs' reports hold."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

pieces = st.lists(hnp.arrays(np.float64, st.tuples(st.integers(0, 40), st.just(3)),
                             elements=st.floats(allow_nan=True, allow_infinity=True, width=64)),
                  min_size=1, max_size=6)


@settings(max_examples=200)
@given(pieces)
def test_points_gathered_into_float32_are_the_float64_gathering_cast(parts):
    views = [p[:, :2] for p in parts]  # the report takes x and y of (n, 3) points, as slices
    with np.errstate(over="ignore", invalid="ignore"):
        before = np.concatenate(views).astype(np.float32)
        now = np.concatenate(views, dtype=np.float32)
    assert now.dtype == np.float32 and now.shape == before.shape
    assert now.tobytes() == before.tobytes()


def test_by_hand():
    """1/3 rounds to float32's nearest; 1e300 overflows to inf; NaN stays NaN."""
    a = np.array([[1 / 3, 1e300, 0.0], [np.nan, -2.5, 1.0]])
    b = np.array([[7.0, -1e-50, 3.0]])
    with np.errstate(over="ignore"):
        got = np.concatenate([a[:, :2], b[:, :2]], dtype=np.float32)
    assert got[0, 0] == np.float32(0.33333334) and np.isinf(got[0, 1]) and np.isnan(got[1, 0])
    assert got[1, 1] == -2.5 and got[2, 0] == 7.0 and got[2, 1] == 0.0 and np.signbit(got[2, 1])
