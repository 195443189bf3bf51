"""The schedule stage's kernels against the code they replaced (kept here as the
reference) and hand-derived cases: every array bit for bit, or the same error."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from vehicle_agent.scheduler import SenderOffers, instance_from_arrays, make_instance

FIELDS = ("vids", "owner", "object_id", "size_bytes", "reward", "p_deliver", "history", "unseen")


def make_instance_reference(offers, p_deliver, *, vids=(), bandwidth_bps=7.2e6, frame_duration_s=0.01,
                            decision_interval_s=0.1):
    """``make_instance`` for ``SenderOffers`` without history, as it was before the kernel
    (ec93cfa): one numpy block per sender, then ``instance_from_arrays``."""
    senders = [(int(i), objs) for i, objs in offers.items()]
    all_vids = {int(v) for v in vids} | {i for i, _ in senders}
    for _, b in senders:
        all_vids.update(np.asarray(b.receivers).tolist())
    vid_arr = np.array(sorted(all_vids), dtype=np.int64)
    C = len(vid_arr)
    blocks, unseen = [], []
    for i, b in senders:
        y = np.zeros((len(b.object_id), C))
        hidden = np.zeros((len(b.object_id), C))
        v, r = np.asarray(b.visibility, dtype=np.float64), np.asarray(b.relevance, dtype=np.float64)
        cols = np.searchsorted(vid_arr, b.receivers)
        y[:, cols] = (1.0 - v) * r
        hidden[:, cols] = np.minimum(np.maximum(1.0 - v, 0.0), 1.0)
        hidden[:, np.searchsorted(vid_arr, i)] = 0.0
        blocks.append(y)
        unseen.append(hidden.sum(axis=1))
    reward = np.concatenate(blocks) if blocks else np.zeros((0, C))
    owner_vid = np.repeat(np.array([i for i, _ in senders], dtype=np.int64), [len(b.object_id) for _, b in senders])
    object_id = np.concatenate([np.asarray(b.object_id, dtype=np.int64) for _, b in senders] or [np.zeros(0, np.int64)])
    size_bytes = np.concatenate([np.asarray(b.size_bytes, dtype=np.int64) for _, b in senders] or [np.zeros(0, np.int64)])
    ids = vid_arr.tolist()
    p = np.array(p_deliver.matrix(ids), dtype=np.float64).reshape(C, C)
    np.fill_diagonal(p, 1.0)
    return instance_from_arrays(vid_arr, owner_vid, object_id, size_bytes, reward, p,
                                frame_bytes=int(bandwidth_bps * frame_duration_s / 8.0),
                                n_frames=int(decision_interval_s / frame_duration_s + 1e-9),
                                history=np.zeros(reward.shape, dtype=bool), bandwidth_bps=bandwidth_bps,
                                frame_duration_s=frame_duration_s,
                                unseen=np.concatenate(unseen) if unseen else np.zeros(0))


class Links:
    """p_ij = a value per vehicle pair, through ``matrix`` as ``AgreedLinks`` gives it."""

    def __init__(self, seed: int) -> None:
        self.seed = seed

    def matrix(self, vids):
        v = np.asarray(vids, dtype=np.float64)
        return (np.sin(v[:, None] * 1.3 + v[None, :] * 0.7 + self.seed) + 1.0) / 2.0


def _outcome(build):
    try:
        return build()
    except Exception as exc:  # noqa: BLE001 - the same error is the expected outcome
        return f"{type(exc).__name__}: {exc}"


def assert_same_instance(a, b) -> None:
    if isinstance(a, str) or isinstance(b, str):
        assert a == b
        return
    for name in FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes(), name
    assert (a.frame_bytes, a.n_frames, a.frame_duration_s, a.bandwidth_bps) == \
        (b.frame_bytes, b.n_frames, b.frame_duration_s, b.bandwidth_bps)


SHARES = st.sampled_from([0.0, 1.0, 0.25, 0.5, 0.1, 0.9999, 1.5, -0.5, float("nan"), 0.3333])


@st.composite
def group_offers(draw):
    """A group's offers as control messages give them (float32 tables), sometimes out of
    order, with values a hostile sender could put there."""
    n_senders = draw(st.integers(1, 5))
    senders = draw(st.lists(st.integers(0, 60), min_size=n_senders, max_size=n_senders, unique=True))
    if draw(st.booleans()):
        senders = sorted(senders)
    wide = draw(st.booleans())  # over 128 receivers: numpy sums such rows pairwise in halves
    offers = {}
    for i in senders:
        pool = list(range(0, 300 if wide else 60))
        receivers = sorted(draw(st.lists(st.sampled_from(pool), max_size=200 if wide else 40, unique=True)))
        if receivers and draw(st.integers(0, 9)) == 0:
            receivers.append(receivers[0])  # a receiver named twice
        n = draw(st.integers(0, 12))
        ids = draw(st.lists(st.integers(0, 1000), min_size=n, max_size=n, unique=True))
        if draw(st.integers(0, 4)) > 0:
            ids = sorted(ids)
        dtype = np.float32 if draw(st.integers(0, 4)) > 0 else np.float64
        shape = (n, len(receivers))
        size = n * len(receivers)
        vis = np.array(draw(st.lists(SHARES, min_size=size, max_size=size)), dtype=dtype).reshape(shape)
        rel = np.array(draw(st.lists(SHARES, min_size=size, max_size=size)), dtype=dtype).reshape(shape)
        sizes = np.array(draw(st.lists(st.integers(1, 5000), min_size=n, max_size=n)), dtype=np.int64)
        offers[i] = SenderOffers(np.array(ids, dtype=np.int64), sizes, np.array(receivers, dtype=np.int64), vis, rel)
    extra = draw(st.lists(st.integers(0, 80), max_size=10))
    return offers, extra, draw(st.integers(0, 3))


@given(group_offers(), st.booleans())
def test_make_instance_builds_the_instance_the_numpy_blocks_built(case, as_array):
    offers, extra, seed = case
    links = Links(seed)
    kw = dict(vids=np.array(extra, dtype=np.int64) if as_array else extra, decision_interval_s=0.04)
    assert_same_instance(_outcome(lambda: make_instance(offers, links, **kw)),
                         _outcome(lambda: make_instance_reference(offers, links, **kw)))


def test_offer_tables_by_hand():
    # sender 3 offers object 7 to 1 and 5; sender 5 offers objects 2 and 4 to 3 and to itself
    offers = {
        3: SenderOffers(np.array([7]), np.array([100]), np.array([1, 5]), np.array([[0.0, 1.0]], np.float32),
                        np.array([[0.5, 1.0]], np.float32)),
        5: SenderOffers(np.array([2, 4]), np.array([10, 20]), np.array([3, 5]),
                        np.array([[0.25, 0.0], [1.0, 0.0]], np.float32), np.array([[1.0, 1.0], [1.0, 0.0]], np.float32)),
    }
    inst = make_instance(offers, Links(0), vids=[9])
    assert inst.vids.tolist() == [1, 3, 5, 9]
    assert inst.owner.tolist() == [1, 2, 2] and inst.object_id.tolist() == [7, 2, 4]
    # y = (1 - v) r: object 7 -> 1: 1 * 0.5, -> 5: 0 * 1; object 2 -> 3: 0.75 * 1; its owner's column 0
    assert inst.reward.tolist() == [[0.5, 0.0, 0.0, 0.0], [0.0, 0.75, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]]
    # unseen: sum of 1 - v over the named receivers but the owner: 1 + 0; 0.75; 0
    assert inst.unseen.tolist() == [1.0, 0.75, 0.0]
    assert np.all(np.diag(inst.p_deliver) == 1.0)


def test_objects_out_of_order_are_put_in_order():
    offers = {4: SenderOffers(np.array([9, 3]), np.array([1, 2]), np.array([1]), np.zeros((2, 1), np.float32),
                              np.ones((2, 1), np.float32)),
              2: SenderOffers(np.array([5]), np.array([3]), np.array([4]), np.zeros((1, 1), np.float32),
                              np.full((1, 1), 0.5, np.float32))}
    inst = make_instance(offers, Links(1))
    assert inst.keys() == [(2, 5), (4, 3), (4, 9)]
    assert_same_instance(inst, make_instance_reference(offers, Links(1)))


@pytest.mark.parametrize("value", [float("nan"), 2.0])
def test_a_reward_out_of_range_is_refused_as_before(value):
    offers = {1: SenderOffers(np.array([1]), np.array([5]), np.array([2]), np.zeros((1, 1), np.float32),
                              np.full((1, 1), value, np.float32))}
    with pytest.raises(ValueError, match="reward must lie in"):
        make_instance(offers, Links(0))


def fill_order_reference(instance, cursor=None):
    """``fill_order`` as it was (ec93cfa): the rank of each object in round_robin_order."""
    from vehicle_agent.scheduler.agnostic import round_robin_order

    rotation = np.empty(instance.n_objects, dtype=np.int64)
    rotation[round_robin_order(instance, cursor)] = np.arange(instance.n_objects)
    return np.lexsort((rotation, -(instance.unseen / instance.size_bytes)))


@given(group_offers(), st.none() | st.tuples(st.integers(-1, 62), st.integers(-1, 1001)))
def test_fill_order_is_the_round_robin_ranks_order(case, cursor):
    from vehicle_agent.scheduler import fill_order

    offers, extra, seed = case
    try:
        inst = make_instance(offers, Links(seed), vids=extra)
    except ValueError:
        return  # NaN or out-of-range shares: no instance
    got, want = fill_order(inst, cursor), fill_order_reference(inst, cursor)
    assert got.dtype == want.dtype and got.tolist() == want.tolist()


def test_fill_order_by_hand():
    from vehicle_agent.scheduler import fill_order

    # three objects of 1 unseen vehicle each and equal size: round-robin order after (2, 5)
    offers = {2: SenderOffers(np.array([5, 6]), np.array([10, 10]), np.array([3]), np.zeros((2, 1), np.float32),
                              np.ones((2, 1), np.float32)),
              3: SenderOffers(np.array([1]), np.array([10]), np.array([2]), np.zeros((1, 1), np.float32),
                              np.ones((1, 1), np.float32))}
    inst = make_instance(offers, Links(0))
    assert fill_order(inst, (2, 5)).tolist() == [1, 2, 0]  # (2, 6), (3, 1), then (2, 5)
    assert fill_order(inst).tolist() == [0, 1, 2]


@given(st.lists(st.integers(0, 70) | st.sampled_from([-3, 65_535, 65_536, 2**40]), max_size=60))
def test_vehicle_ids_once_each_ascending_are_np_unique(ids):
    from vehicle_agent.scheduler.instance import _ascending_once

    arr = np.array(ids, dtype=np.int64)
    got, want = _ascending_once(arr), np.unique(arr)
    assert got.dtype == want.dtype and got.tolist() == want.tolist()


def test_vehicle_ids_once_each_by_hand():
    from vehicle_agent.scheduler.instance import _ascending_once

    assert _ascending_once(np.array([7, 3, 7, 0, 3], dtype=np.int64)).tolist() == [0, 3, 7]
    assert _ascending_once(np.zeros(0, dtype=np.int64)).tolist() == []
    assert _ascending_once(np.array([1 << 20, 2, 2], dtype=np.int64)).tolist() == [2, 1 << 20]


@given(group_offers(), st.none() | st.tuples(st.integers(-1, 62), st.integers(-(1 << 62), 1001)), st.data(),
       st.sampled_from([(7.2e6, 0.01, 0.1), (8000.0, 0.1, 0.3), (400_000.0, 0.01, 0.05)]))
def test_autocast_is_work_conserving_greedy(case, cursor, data, link):
    """The fused kernel against what it fuses, ``work_conserving(greedy(...))``: the
    same frames and fill, for any starvation counts and cursor, roomy or tight frames."""
    from vehicle_agent.scheduler import SchedulerState, Schedule
    from vehicle_agent.scheduler.fill import work_conserving
    from vehicle_agent.scheduler.greedy import autocast, greedy

    offers, extra, seed = case
    bandwidth_bps, frame_duration_s, decision_interval_s = link
    try:
        inst = make_instance(offers, Links(seed), vids=extra, bandwidth_bps=bandwidth_bps,
                             frame_duration_s=frame_duration_s, decision_interval_s=decision_interval_s)
    except ValueError:
        return  # NaN or out-of-range shares: no instance
    keys = inst.keys()
    starved = sorted(set(data.draw(st.lists(st.sampled_from(keys), max_size=5)))) if keys else []
    counts = data.draw(st.lists(st.integers(1, 6), min_size=len(starved), max_size=len(starved)))
    state = SchedulerState(np.array(starved, dtype=np.int64).reshape(-1, 2), np.array(counts, dtype=np.int64), cursor)
    got, want = autocast(inst, state), work_conserving(inst, greedy(inst, state), cursor)
    assert isinstance(got, Schedule) and got == want


def test_autocast_by_hand():
    """One 100-byte frame: X (60 B, reward 0.6 -> 0.01/B) goes first, Y (50 B, 0.4) no
    longer fits; the spare 40 B carry Z (30 B, no reward but unseen by one vehicle)."""
    from vehicle_agent.scheduler import SchedulerState
    from vehicle_agent.scheduler.greedy import autocast

    offers = {1: SenderOffers(np.array([1, 2, 3]), np.array([60, 50, 30]), np.array([2]),
                              np.zeros((3, 1), np.float32), np.array([[0.6], [0.4], [0.0]], np.float32))}
    inst = make_instance(offers, Links(0), bandwidth_bps=8000.0, frame_duration_s=0.1, decision_interval_s=0.1)
    schedule = autocast(inst, SchedulerState())
    assert schedule.frames == ((0, 2),) and schedule.fill == ((2,),)


def test_vids_given_once_as_an_iterator_reach_the_general_path_too():
    """Objects out of order take the general path after the kernel declined them: an
    iterator of vids is read once, yet both see all of it."""
    offers = {4: SenderOffers(np.array([9, 3]), np.array([1, 2]), np.array([1]), np.zeros((2, 1), np.float32),
                              np.ones((2, 1), np.float32))}
    inst = make_instance(offers, Links(0), vids=iter([7, 8]))
    assert inst.vids.tolist() == [1, 4, 7, 8]
