"""The medium's pure functions, against hand-derived answers: airtime, FIFO radios,
overflow, collisions (with half duplex), utilisation, the reception model, the draws."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
import pytest

from channel_proxy import emp, loss, medium
from channel_proxy.profiles import get_profile

MS = 1_000_000  # ns


def test_airtime_is_bytes_times_8_over_b():
    # 9000 B at 7.2 Mbps: 72000 bits / 7.2e6 = 10 ms; 1 B: 1.111 us
    assert medium.airtime_ns(np.array([9000, 1, 0]), 7.2e6).tolist() == [10 * MS, 1111, 0]


def test_a_sender_radio_serves_its_transmissions_first_come_first_served():
    sender = np.array([0, 0, 0, 1, 1])
    start = np.array([0, 0, 50, 5, 0]) * MS
    dur = np.array([10, 10, 10, 10, 10]) * MS
    # sender 0: [0, 10), queued to [10, 20), then its claim at 50 holds; sender 1: by claim, 0 then max(5, 10)
    assert (medium.serialize(sender, start, dur) // MS).tolist() == [0, 10, 50, 10, 0]


def play(sender, start_ms, size, *, p=None, reach=None, C=3, interval_s=0.1, seed=0, tick=0, item=None):
    sender = np.asarray(sender)
    p = np.ones((C, C)) if p is None else p
    reach = np.ones((C, C), dtype=bool) if reach is None else reach
    item = np.arange(len(sender)) if item is None else np.asarray(item)
    return medium.play_data(np.arange(C) + 10, sender, item, np.asarray(start_ms, dtype=float) / 1e3,
                            np.asarray(size), p, reach, bandwidth_bps=7.2e6, interval_s=interval_s, seed=seed,
                            tick=tick)


def test_back_to_back_slots_do_not_collide():
    # 900 B = 1 ms each: [0, 1) by 0, [1, 2) by 1, [2, 3) by 0
    out = play([0, 1, 0], [0.0, 1.0, 2.0], [900, 900, 900])
    assert not out.collided.any() and not out.overflow.any()
    assert out.delivered.sum() == 6  # each of three to the two others
    assert (out.end_ns // 1000).tolist() == [1000, 2000, 3000]


def test_overlapping_senders_both_lose_at_every_receiver_in_range_of_both():
    # 0: [0, 1) ms, 1: [0.5, 1.5) ms overlap; 2 hears both -> loses both; 0 and 1 are deaf while sending
    out = play([0, 1], [0.0, 0.5], [900, 900])
    assert out.collided[0].tolist() == [False, True, True]
    assert out.collided[1].tolist() == [True, False, True]
    assert out.delivered.sum() == 0


def test_a_collision_needs_the_interferer_in_range_of_the_receiver():
    # 0 and 1 overlap, 2 is in range of 0 only: 2 still decodes 0's transmission
    reach = np.array([[1, 1, 1], [1, 1, 0], [1, 0, 1]], dtype=bool)
    out = play([0, 1], [0.0, 0.5], [900, 900], reach=reach)
    assert out.delivered[0].tolist() == [False, False, True]
    assert not out.in_range[1, 2] and out.delivered[1].sum() == 0  # 0 is sending: half duplex


def test_a_burst_beyond_the_interval_is_cut_at_capacity():
    # 12 x 9000 B from one sender, all claiming t = 0: 10 ms each, queued; 10 fit in 100 ms
    out = play([0] * 12, [0.0] * 12, [9000] * 12)
    assert out.overflow.tolist() == [False] * 10 + [True] * 2
    assert out.delivered[:10, 1:].all() and not out.delivered[10:].any()
    assert out.busy_ns == 100 * MS


def test_overflowed_transmissions_do_not_interfere():
    # 1's transmission would end at 100.5 ms: not sent, so 0's [99, 100) survives
    out = play([0, 1], [99.0, 99.5], [900, 900])
    assert out.overflow.tolist() == [False, True]
    assert out.delivered[0].sum() == 2


def test_busy_time_is_the_union_of_airtimes():
    assert medium.busy_ns(np.array([0, 5, 30]) * MS, np.array([10, 12, 40]) * MS) == 22 * MS
    assert medium.busy_ns(np.zeros(0, np.int64), np.zeros(0, np.int64)) == 0


def test_a_resent_object_gets_its_own_loss_draw():
    assert medium.occurrence(np.array([0, 0, 1, 0]), np.array([5, 5, 5, 6])).tolist() == [0, 1, 0, 0]


def test_link_loss_follows_p_and_is_reproducible():
    p = np.full((2, 2), 0.3)
    out = play([0] * 100, np.arange(100) * 0.5, [450] * 100, p=p, C=2, seed=3)
    again = play([0] * 100, np.arange(100) * 0.5, [450] * 100, p=p, C=2, seed=3)
    rate = out.delivered[:, 1].mean()
    assert 0.15 < rate < 0.45
    assert np.array_equal(out.delivered, again.delivered)
    assert not np.array_equal(out.delivered, play([0] * 100, np.arange(100) * 0.5, [450] * 100, p=p, C=2,
                                                  seed=4).delivered)


def test_draws_do_not_depend_on_arrival_order():
    a = play([0, 1, 2], [0.0, 10.0, 20.0], [900, 900, 900], p=np.full((3, 3), 0.5), item=[7, 8, 9], seed=1)
    b = play([2, 0, 1], [20.0, 0.0, 10.0], [900, 900, 900], p=np.full((3, 3), 0.5), item=[9, 7, 8], seed=1)
    assert np.array_equal(a.delivered, b.delivered[[1, 2, 0]])


def test_control_pool_overflow_and_loss():
    vids = np.array([1, 2, 3])
    p = np.ones((3, 3))
    reach = np.ones((3, 3), dtype=bool)
    full = medium.play_control(vids, np.arange(3), np.array([100, 100, 100]), p, reach, capacity_bytes=250,
                               seed=0, tick=0)
    assert full.overflow.sum() == 1  # 300 B offered to a 250 B pool
    assert full.heard[~full.overflow].sum() == 4 and not full.heard[full.overflow].any()
    ok = medium.play_control(vids, np.arange(3), np.array([100, 100, 100]), p, reach, capacity_bytes=300, seed=0,
                             tick=0)
    assert ok.heard.tolist() == [[False, True, True], [True, False, True], [True, True, False]]


def test_control_onair_size():
    # 48 + 7 * 12 + 16 * 30 + 4 * 39 + 30 * 39 + 4 * 39
    assert medium.control_onair_bytes(30, 39, 7, 39) == 48 + 84 + 480 + 156 + 1170 + 156


def test_shadowed_prr_curve():
    m = loss.PrrModel()
    p = m.prr(np.array([0.0, 100.0, 170.0, 250.0, 1000.0]))
    assert p[0] == pytest.approx(1.0)
    assert p[1] > 0.999
    assert p[2] == pytest.approx(0.9, abs=1e-3)  # R is where the PRR is still 0.9
    assert p[3] == pytest.approx(0.347, abs=0.01)
    assert p[4] == 0.0 and 460 < m.max_range_m < 470  # cut off where the PRR falls below 0.001
    assert np.all(np.diff(m.prr(np.linspace(0, 400, 200))) <= 1e-12)


def test_fixed_and_logistic_curves():
    fixed = loss.PrrModel(curve="fixed", p_fixed=0.7, range_m=500.0)
    assert fixed.prr(np.array([1.0, 499.0, 501.0])).tolist() == [0.7, 0.7, 0.0]
    logistic = loss.PrrModel(curve="logistic", range_m=170.0, spread_m=20.0)
    assert float(logistic.prr(170.0)) == pytest.approx(0.9, abs=1e-3)
    with pytest.raises(ValueError):
        loss.PrrModel(curve="nonsense")


def test_link_probabilities_and_range():
    xy = np.array([[0.0, 0.0], [100.0, 0.0], [2000.0, 0.0], [np.nan, np.nan]])
    p = loss.link_probabilities(xy, loss.PrrModel(), extra_loss=0.5)
    assert np.diag(p).tolist() == [1.0] * 4
    assert p[0, 1] == pytest.approx(0.5 * float(loss.PrrModel().prr(100.0)))
    assert p[0, 2] == 0.0 and p[0, 3] == 0.0  # out of range; position unknown
    r = loss.in_range(xy, loss.PrrModel())
    assert r[0, 1] and not r[0, 2] and not r[0, 3] and r[3, 3]


def test_keyed_uniform_is_uniform_and_keyed():
    u = loss.keyed_uniform(7, 3, 1, np.arange(100_000))
    assert 0.0 <= u.min() and u.max() < 1.0
    assert u.mean() == pytest.approx(0.5, abs=0.01) and u.var() == pytest.approx(1 / 12, abs=0.005)
    assert loss.keyed_uniform(1, 2, 3)[0] == loss.keyed_uniform(1, 2, 3)[0] != loss.keyed_uniform(1, 2, 4)[0]


def test_profiles():
    lte = get_profile("lte-direct")
    assert lte.n_frames == 10 and lte.frame_bytes == 9000 and lte.ctrl_capacity_bytes == 90000
    with pytest.raises(KeyError):
        get_profile("5g-magic")


def test_voronoi_segment():
    pts = np.array([[1.0, 0.0], [4.0, 0.0], [6.0, 0.0], [5.0, 0.0]])
    mine = emp.voronoi_segment(pts, np.array([0.0, 0.0]), np.array([[10.0, 0.0]]))
    assert mine.tolist() == [True, True, False, True]  # the bisector at x = 5 is kept by both
    assert emp.voronoi_segment(pts, np.zeros(2), np.zeros((0, 2))).all()


def _voronoi_brute_force(pts, own, others):
    """The reference: every point against every site, as numpy arrays."""
    d_own = np.sum((pts - own) ** 2, axis=1)
    d_min = np.min(np.sum((pts[:, None, :] - others[None, :, :]) ** 2, axis=2), axis=1)
    return d_own <= d_min


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 40), st.integers(0, 400), st.booleans())
def test_voronoi_segment_is_the_brute_force_cell(seed, n_sites, n_pts, grid):
    """The pruned kernel against the brute force, bit for bit; ``grid`` puts sites and
    points on a 1 m lattice, so many points lie exactly on a bisector (ties: ours) and
    sites coincide."""
    rng = np.random.default_rng(seed)
    draw = (lambda n: rng.integers(-20, 21, (n, 2)).astype(np.float64)) if grid else \
        (lambda n: rng.uniform(-300, 300, (n, 2)))
    sites, pts = draw(n_sites + 1), draw(n_pts)
    own, others = sites[0], sites[1:]
    assert emp.voronoi_segment(pts, own, others).tolist() == _voronoi_brute_force(pts, own, others).tolist()


def test_relay_round_robin_store_and_forward_and_overflow():
    # 3 uploads of 1.25 MB-ish: at 50 Mbps, 62500 B = 10 ms up + 10 ms forward = 20 ms each
    vids = np.array([1, 2, 3])
    size = np.array([62500, 62500, 62500])
    out = emp.play_relay(vids, np.arange(3), size, np.ones(3), np.ones(3), np.ones(3, dtype=bool),
                         bandwidth_bps=50e6, interval_s=0.1, seed=0, tick=1)
    # tick 1 rotates the start by one: 2 first, then 3, then 1
    assert (out.fwd_end_ns // MS).tolist() == [60, 20, 40]
    assert out.delivered.tolist() == [[False, True, True], [True, False, True], [True, True, False]]
    big = emp.play_relay(vids, np.arange(3), size * 2, np.ones(3), np.ones(3), np.ones(3, dtype=bool),
                         bandwidth_bps=50e6, interval_s=0.1, seed=0, tick=0)
    assert big.overflow.tolist() == [False, False, True]  # 40 + 40 ms fit, the third would end at 120
