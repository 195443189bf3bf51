"""The proxy's faster paths against the code they replaced, kept here as the reference:
the same draws, collisions, link probabilities, statistics bytes and data bundles, to
the bit; and the collector woken by the last message it waits for."""

from __future__ import annotations

import math
import threading
import time

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from channel_proxy import loss, medium
from channel_proxy.profiles import get_profile
from channel_proxy.proxy import ChannelProxy, ProxyConfig, encode_stats
from protocol import keys
from protocol.codec import encode
from protocol.messages import ChannelStats, ControlMsg, DataBundle, DataTx, ObjectMap, Pose, Reception, Tick, \
    Transmission
from tests.conftest import wait_until

# ------------------------------------------------------------------ the references (the code before)


def old_keyed_uniform(seed, *keys):
    arrays = [np.atleast_1d(np.asarray(k)).astype(np.int64).view(np.uint64) for k in keys]
    shape = np.broadcast_shapes(*(a.shape for a in arrays)) if arrays else (1,)
    with np.errstate(over="ignore"):
        h = loss._mix(np.full(shape, np.uint64(seed & 0xFFFFFFFFFFFFFFFF)) + loss._GOLDEN)
        for a in arrays:
            h = loss._mix(h ^ (a + loss._GOLDEN))
    return (h >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)


def old_collided_at(ov, sender, reach):
    return (ov.astype(np.float32) @ reach[sender].astype(np.float32)) > 0.0


def old_link_probabilities(xy, model, extra_loss=0.0):
    d = loss.distances(xy)
    known = ~np.isnan(d)
    p = np.where(known, model.prr(np.where(known, d, np.inf)), 0.0) * (1.0 - extra_loss)
    np.fill_diagonal(p, 1.0)
    return p


def old_in_range(xy, model):
    d = loss.distances(xy)
    r = np.where(np.isnan(d), False, d <= model.max_range_m)
    np.fill_diagonal(r, True)
    return r


def old_deliver_data(self, tick, live, xy, reach, data):
    k, profile, run = tick.tick, self.cfg.profile, self.cfg.run_id
    txs = []
    for vid in sorted(data):
        for t in data[vid][0].transmissions:
            if math.isfinite(t.start_s) and t.start_s >= 0.0:
                txs.append((vid, t))
            else:
                self.counters.invalid_tx += 1
    sender = np.searchsorted(live, np.array([v for v, _ in txs], dtype=np.int64))
    item = np.array([t.object_id for _, t in txs], dtype=np.int64)
    size = np.array([len(t.payload) for _, t in txs], dtype=np.int64)
    start = np.array([t.start_s for _, t in txs], dtype=np.float64)
    out = medium.play_data(live, sender, item, start, size,
                           old_link_probabilities(xy, profile.prr, self.cfg.data_loss), reach,
                           bandwidth_bps=profile.bandwidth_bps, interval_s=profile.decision_interval_s,
                           seed=self.cfg.seed, tick=k)
    rx_s = out.end_ns / medium.NS
    order = np.lexsort((item, live[sender] if len(txs) else sender, out.end_ns))
    order = order[out.delivered[order].any(axis=1)]
    receptions = [Reception(int(live[sender[t]]), int(item[t]), float(rx_s[t]), txs[t][1].payload)
                  for t in order.tolist()]
    twins, extra = self._extra_receptions(txs, self._extras, out.delivered.any(axis=1), rx_s)
    decoded = out.delivered[np.concatenate([order, np.array(twins, dtype=np.int64)])]
    bundle = encode(DataBundle(k, tick.t_sim_s, live, np.ascontiguousarray(decoded.T), receptions + extra))
    self._bundles[keys.net_data_rx(run)].put(k, tick.t_sim_s, bundle)
    size_col = size[:, None]
    sent = ~out.overflow
    return {
        "transmissions": len(txs),
        "extra_receptions": len(extra),
        "offered_bytes": int(size.sum()),
        "overflow_tx": int(out.overflow.sum()),
        "overflow_bytes": int(size[out.overflow].sum()),
        "collided_tx": int(np.any(out.collided, axis=1).sum()),
        "delivered_pairs": int(out.delivered.sum()),
        "delivered_bytes": int((out.delivered * size_col).sum()),
        "lost_collision_bytes": int((out.collided * size_col).sum()),
        "lost_channel_bytes": int((out.lost_channel * size_col).sum()),
        "in_range_bytes": int((out.in_range * size_col).sum()),
        "utilization": round(out.busy_ns / (profile.decision_interval_s * medium.NS), 4),
        "objects": [[int(live[sender[t]]), int(item[t]), round(float(out.start_ns[t] / medium.NS), 6),
                     round(float(rx_s[t]), 6), int(out.delivered[t].sum()), int(out.in_range[t].sum())]
                    for t in np.flatnonzero(sent).tolist()],
    }


# ------------------------------------------------------------------ the draws


_KEY = st.integers(-(2 ** 63), 2 ** 63 - 1)


@st.composite
def key_sets(draw):
    """A seed and keys of shapes that broadcast together: scalars, (T, 1), (1, C), (T, C), (C,)."""
    T, C = draw(st.integers(0, 6)), draw(st.integers(1, 6))
    shapes = st.sampled_from([(), (T, 1), (1, C), (T, C), (C,), (1,)])
    keys_ = []
    for shape in draw(st.lists(shapes, min_size=0, max_size=6)):
        n = math.prod(shape)
        values = draw(st.lists(_KEY, min_size=n, max_size=n))
        keys_.append(values[0] if shape == () else np.array(values, dtype=np.int64).reshape(shape))
    return draw(st.integers(0, 2 ** 64 - 1)), keys_


@settings(max_examples=200)
@given(key_sets())
def test_keyed_uniform_is_the_full_shape_hash_to_the_bit(case):
    seed, keys_ = case
    new, old = loss.keyed_uniform(seed, *keys_), old_keyed_uniform(seed, *keys_)
    assert new.shape == old.shape and new.dtype == old.dtype
    assert np.array_equal(new.view(np.uint64), old.view(np.uint64))


def test_keyed_uniform_by_hand():
    """splitmix64's finaliser on Python integers: seed 5, keys (3, [1, 2]) for two draws."""
    mask, golden = (1 << 64) - 1, 0x9E3779B97F4A7C15

    def mix(x):
        x ^= x >> 30
        x = (x * 0xBF58476D1CE4E5B9) & mask
        x ^= x >> 27
        x = (x * 0x94D049BB133111EB) & mask
        return x ^ (x >> 31)

    head = mix(mix((5 + golden) & mask) ^ ((3 + golden) & mask))
    want = [(mix(head ^ ((k + golden) & mask)) >> 11) / 2 ** 53 for k in (1, 2)]
    assert loss.keyed_uniform(5, 3, np.array([1, 2])).tolist() == want
    assert loss.keyed_uniform(5, np.array([[3]]), np.array([[1, 2]])).tolist() == [want]


# ------------------------------------------------------------------ collisions


@st.composite
def overlap_cases(draw):
    T, C = draw(st.integers(0, 8)), draw(st.integers(1, 6))
    ov = np.array(draw(st.lists(st.booleans(), min_size=T * T, max_size=T * T)), dtype=bool).reshape(T, T)
    if draw(st.booleans()):
        ov = ov & ov.T  # as ``overlaps`` gives it
    sender = np.array(draw(st.lists(st.integers(0, C - 1), min_size=T, max_size=T)), dtype=np.int64)
    reach = np.array(draw(st.lists(st.booleans(), min_size=C * C, max_size=C * C)), dtype=bool).reshape(C, C)
    return ov, sender, reach


@settings(max_examples=200)
@given(overlap_cases())
def test_collided_at_is_the_full_product(case):
    ov, sender, reach = case
    new = medium.collided_at(ov, sender, reach)
    assert new.dtype == bool and np.array_equal(new, old_collided_at(ov, sender, reach))


def test_collided_at_by_hand():
    # transmissions 0 (sender 0) and 2 (sender 2) overlap; 1 overlaps nothing; sender 2 reaches 1 and 2, 0 reaches 0, 1
    ov = np.array([[0, 0, 1], [0, 0, 0], [1, 0, 0]], dtype=bool)
    reach = np.array([[1, 1, 0], [1, 1, 1], [0, 1, 1]], dtype=bool)
    got = medium.collided_at(ov, np.array([0, 1, 2]), reach)
    assert got.tolist() == [[False, True, True], [False, False, False], [True, True, False]]
    assert medium.collided_at(np.zeros((2, 2), bool), np.array([0, 1]), reach).tolist() == [[False] * 3] * 2


# ------------------------------------------------------------------ link probabilities


@settings(max_examples=100)
@given(st.lists(st.tuples(st.floats(-800, 800), st.floats(-800, 800), st.booleans()), min_size=0, max_size=12),
       st.sampled_from(["lte-direct", "dsrc", "ideal"]), st.sampled_from([0.0, 0.1, 0.5]))
def test_probabilities_and_range_from_distances_are_the_positions_ones(points, profile, extra):
    xy = np.array([(x, y) if known else (np.nan, np.nan) for x, y, known in points], dtype=np.float64).reshape(-1, 2)
    model = get_profile(profile).prr
    d = loss.distances(xy)
    for new, old in ((loss.probabilities_at(d, model, extra), old_link_probabilities(xy, model, extra)),
                     (loss.link_probabilities(xy, model, extra), old_link_probabilities(xy, model, extra)),
                     (loss.within_cutoff(d, model), old_in_range(xy, model)),
                     (loss.in_range(xy, model), old_in_range(xy, model))):
        assert new.dtype == old.dtype and np.array_equal(new, old, equal_nan=True)


# ------------------------------------------------------------------ statistics


_plain = st.recursive(
    st.none() | st.booleans() | st.integers(-(2 ** 63), 2 ** 64 - 1) | st.floats(allow_nan=True) | st.text(max_size=5)
    | st.integers(-(2 ** 31), 2 ** 31).map(np.int64) | st.floats(width=32).map(np.float32)
    | st.floats().map(np.float64) | st.booleans().map(np.bool_),
    lambda inner: st.lists(inner, max_size=4) | st.tuples(inner, inner)
    | st.dictionaries(st.text(max_size=4), inner, max_size=4),
    max_leaves=30)


@settings(max_examples=300)
@given(st.integers(0, 10 ** 6), st.floats(0, 1e5), st.dictionaries(st.text(max_size=6), _plain, max_size=6))
def test_stats_bytes_are_the_codecs(tick, t_sim_s, stats):
    assert encode_stats(tick, t_sim_s, stats) == encode(ChannelStats(tick, t_sim_s, stats))


def test_stats_bytes_by_hand():
    stats = {"tick": 3, "objects": [[1, 7, 0.25, 0.5, 2, 3]], "dead": []}
    want = msgpack.packb([ChannelStats.TYPE_ID, ChannelStats.VERSION, 3, 0.3, stats], use_bin_type=True)
    assert encode_stats(3, 0.3, stats) == want == encode(ChannelStats(3, 0.3, stats))
    odd = {"n": np.int64(4), "a": (1, 2)}  # a numpy integer: through the codec, which packs its value
    assert encode_stats(3, 0.3, odd) == encode(ChannelStats(3, 0.3, {"n": 4, "a": [1, 2]}))


# ------------------------------------------------------------------ the data phase


class _Pub:
    def __init__(self):
        self.sent = []

    def put(self, tick, t_sim_s, payload):
        self.sent.append(payload)


def _proxy(profile: str, seed: int, data_loss: float) -> ChannelProxy:
    p = ChannelProxy(ProxyConfig(run_id="t", profile=get_profile(profile), seed=seed, data_loss=data_loss), None)
    p._bundles = {keys.net_data_rx("t"): _Pub()}
    return p


@st.composite
def data_phases(draw):
    C = draw(st.sampled_from([1, 2, 2, 3, 5, 8]))  # two or three: a collision lost at one receiver only
    live = np.array(sorted(draw(st.sets(st.integers(0, 50), min_size=C, max_size=C))), dtype=np.int64)
    spread = draw(st.sampled_from([50.0, 300.0]))  # all in range of each other, or not
    xy = np.array([(draw(st.floats(-spread, spread)), draw(st.floats(-spread, spread))) if draw(st.integers(0, 6))
                   else (math.nan, math.nan) for _ in range(C)])  # a vehicle never heard of: no position
    data, extras = {}, {}
    for vid in live.tolist():
        if draw(st.integers(0, 9)) == 9:
            continue  # absent
        txs = [Transmission(draw(st.integers(0, 6)),
                            draw(st.sampled_from([0.0, 0.001, 0.002, 0.01, 0.05, 0.099, 0.2, -0.01, math.nan]))
                            + draw(st.sampled_from([0.0, 1e-7, 3e-4])),
                            bytes(draw(st.sampled_from([50, 900, 4000, 30000]))))
               for _ in range(draw(st.integers(0, 4).map(lambda n: 4 - n)))]  # mostly several
        msg = DataTx(1, 0.1, vid, txs)
        data[vid] = (msg, encode(msg))
        if txs and draw(st.integers(0, 3)) == 0:  # a signed run's extra frame in the slot
            other = DataTx(1, 0.1, vid, [Transmission(draw(st.integers(0, 8)), 0.0, b"x" * 10)])
            extras[vid] = [(other, encode(other))]
    return (live, xy, data, extras, draw(st.sampled_from(["lte-direct", "dsrc", "ideal"])),
            draw(st.integers(0, 2 ** 32)), draw(st.sampled_from([0.0, 0.3])))


@settings(max_examples=100)
@given(case=data_phases())
def test_the_data_phase_publishes_what_it_did_before(case, monkeypatch_module):
    live, xy, data, extras, profile, seed, data_loss = case
    outs = []
    for new in (True, False):
        p = _proxy(profile, seed, data_loss)
        p._extras = extras
        model = p.cfg.profile.prr
        tick = _tick(1, live)
        if new:
            reach = loss.within_cutoff(loss.distances(xy), model)
            p_data = loss.probabilities_at(loss.distances(xy), model, data_loss)
            stats = p._deliver_data(tick, live, p_data, reach, data)
        else:
            with monkeypatch_module.context() as m:  # the draws and collisions as they were, too
                m.setattr(loss, "keyed_uniform", old_keyed_uniform)
                m.setattr(medium, "collided_at", old_collided_at)
                stats = old_deliver_data(p, tick, live, xy, old_in_range(xy, model), data)
        outs.append((p._bundles[keys.net_data_rx("t")].sent, stats, p.counters.invalid_tx))
    assert outs[0] == outs[1]


def test_the_data_phase_by_hand():
    """Two vehicles 100 m apart on an ideal channel: 1 sends 900 B at 0, 2 sends 900 B at
    0.5 ms (overlapping: both lost at each other, half duplex) and 450 B at 2 ms."""
    live = np.array([1, 2])
    p = _proxy("ideal", 0, 0.0)
    xy = np.array([[0.0, 0.0], [100.0, 0.0]])
    d = loss.distances(xy)
    data = {1: (DataTx(1, 0.1, 1, [Transmission(5, 0.0, bytes(900))]), b""),
            2: (DataTx(1, 0.1, 2, [Transmission(6, 0.0005, bytes(900)), Transmission(7, 0.002, bytes(450))]), b"")}
    stats = p._deliver_data(_tick(1, live), live, loss.probabilities_at(d, p.cfg.profile.prr),
                            loss.within_cutoff(d, p.cfg.profile.prr), data)
    air = 900 * 8 / 7.2e6  # 1 ms
    assert stats["collided_tx"] == 2 and stats["delivered_pairs"] == 1 and stats["delivered_bytes"] == 450
    assert stats["objects"] == [[1, 5, 0.0, round(air, 6), 0, 1], [2, 6, 0.0005, round(0.0005 + air, 6), 0, 1],
                                [2, 7, 0.002, round(0.002 + air / 2, 6), 1, 1]]
    from protocol.codec import decode
    bundle = decode(p._bundles[keys.net_data_rx("t")].sent[0], DataBundle)
    assert [(r.sender, r.object_id, r.rx_time_s) for r in bundle.receptions] == [(2, 7, 0.002 + air / 2)]
    assert bundle.decoded.tolist() == [[True], [False]]


def _tick(k: int, live: np.ndarray) -> Tick:
    return Tick(k, k * 0.1, [int(v) for v in live], [])


@pytest.fixture(scope="module")
def monkeypatch_module():
    with pytest.MonkeyPatch.context() as m:
        yield m


# ------------------------------------------------------------------ the collector's wake-up


class _Sample:
    def __init__(self, key: str, raw: bytes) -> None:
        self.key_expr, self.raw = key, raw
        self.payload = self

    def to_bytes(self) -> bytes:
        return self.raw


def _ctrl(vid: int, k: int) -> ControlMsg:
    empty = np.zeros(0, dtype=np.int64)
    objects = ObjectMap(empty, empty, np.zeros((0, 2), np.float32), empty, np.zeros((0, 0), np.float32),
                        np.zeros((0, 0), np.float32))
    return ControlMsg(k, k * 0.1, vid, Pose(0.0, 0.0, 0.0), 0.0, np.zeros((0, 3), np.float32), objects, empty)


class _CountingCondition(threading.Condition):
    """A condition that counts its ``notify_all`` calls (the collector's wake-ups)."""

    def __init__(self) -> None:
        super().__init__()
        self.notified = 0

    def notify_all(self) -> None:
        self.notified += 1
        super().notify_all()


def test_the_collector_wakes_when_the_last_message_it_waits_for_is_in():
    """Vehicle 1's message, and its message of the next tick, leave the collector
    asleep (no notify) and still awaiting vehicle 2; vehicle 2's message wakes it and
    the phase closes with both. The collector's own deadline is an hour: it can only
    return in time by being woken."""
    p = ChannelProxy(ProxyConfig(run_id="t", profile=get_profile("ideal"), phase_timeout_s=3600.0), None)
    p._cv = cv = _CountingCondition()
    p._tick = _tick(0, np.array([1, 2]))
    on_ctrl = p._inbound("ctrl", ControlMsg)
    got = {}
    collector = threading.Thread(target=lambda: got.update(p._collect("ctrl", 0, {1, 2}, time.monotonic() + 3600.0)))
    collector.start()
    try:
        wait_until(lambda: p._awaited is not None, "the collector waits")
        on_ctrl(_Sample(keys.net_ctrl_tx("t", 1), encode(_ctrl(1, 0))))
        on_ctrl(_Sample(keys.net_ctrl_tx("t", 1), encode(_ctrl(1, 1))))  # the next tick's: not awaited
        with cv:
            assert cv.notified == 0 and p._awaited == ("ctrl", 0, {2}), "woken, or no longer awaiting vehicle 2"
        on_ctrl(_Sample(keys.net_ctrl_tx("t", 2), encode(_ctrl(2, 0))))
        collector.join(60.0)  # a safety net: without the wake-up it sleeps for its hour
        assert not collector.is_alive(), "the last awaited message did not wake the collector"
        assert sorted(got) == [1, 2] and p._awaited is None and cv.notified == 1
    finally:
        p.stop()  # a failed test leaves no collector asleep
        collector.join(60.0)
