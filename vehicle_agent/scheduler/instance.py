"""The scheduling problem of one decision interval, and what a schedule is worth.

Notation follows the paper's scheduler section: vehicles C (ids ``vids``), objects
(i,k) owned by sender i, sizes s_ik, rewards y_(i,k),j = (1 - v) * r, delivery
probabilities p_ij, N PHY frames of S_f bytes each, history h_(i,k),j.

Every array is canonical: vehicles ascending by id, objects ascending by (owner id,
object id). Two agents that heard the same control messages therefore build
bit-identical instances whatever order the messages arrived in, and every scheduler
breaks ties by this index order.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numba import njit

ObjectKey = tuple[int, int]  # (sender vid i, object id k)

DEFAULT_BANDWIDTH_BPS = 7.2e6  # LTE-Direct QPSK, 10 MHz
DEFAULT_FRAME_DURATION_S = 0.01  # T_n; the paper allows 10-100 ms
DEFAULT_DECISION_INTERVAL_S = 0.1  # T_d


class OfferLike(Protocol):
    """What a control message says about one object of its sender."""

    object_id: int
    size_bytes: int
    visibility: Mapping[int, float]  # v_(i,k),j per receiver j, 1 = j sees it itself
    relevance: Mapping[int, float]  # r_(i,k),j per receiver j, in [0, 1]


@dataclass(frozen=True, slots=True)
class ObjectOffer:
    """One object a sender offers; receivers missing from ``relevance`` get no reward."""

    object_id: int
    size_bytes: int
    visibility: Mapping[int, float]
    relevance: Mapping[int, float]


@dataclass(frozen=True, slots=True, eq=False)
class Instance:
    """One decision interval's scheduling problem, canonically ordered, read-only."""

    vids: np.ndarray  # int64 (C,), ascending
    owner: np.ndarray  # int64 (K,), index into vids of the sender i of each object
    object_id: np.ndarray  # int64 (K,), ascending within each owner
    size_bytes: np.ndarray  # int64 (K,), s_ik
    reward: np.ndarray  # float64 (K, C), y_(i,k),j; zero in the owner's own column
    p_deliver: np.ndarray  # float64 (C, C), p_ij
    history: np.ndarray  # bool (K, C), h_(i,k),j at the start of the interval
    frame_bytes: int  # S_f
    n_frames: int  # N
    frame_duration_s: float  # T_n
    bandwidth_bps: float  # B
    unseen: np.ndarray | None = None  # float64 (K,), sum_j (1 - v_(i,k),j) over the receivers i named; zeros if None

    def __post_init__(self) -> None:
        C, K = len(self.vids), len(self.object_id)
        if self.unseen is None:
            object.__setattr__(self, "unseen", np.zeros(K))
        _check(self.unseen.dtype == np.float64 and self.unseen.shape == (K,), "unseen must be float64 (K,)")
        _check(self.vids.dtype == np.int64 and self.vids.shape == (C,), "vids must be int64 (C,)")
        for name in ("owner", "object_id", "size_bytes"):
            a = getattr(self, name)
            _check(a.dtype == np.int64 and a.shape == (K,), f"{name} must be int64 (K,)")
        _check(self.reward.dtype == np.float64 and self.reward.shape == (K, C), "reward must be float64 (K, C)")
        _check(self.p_deliver.dtype == np.float64 and self.p_deliver.shape == (C, C), "p_deliver must be float64 (C, C)")
        _check(self.history.dtype == np.bool_ and self.history.shape == (K, C), "history must be bool (K, C)")
        bad = _first_bad_value(self.vids, self.owner, self.object_id, self.size_bytes, self.reward, self.p_deliver,
                               self.unseen)
        _check(bad == 0, _BAD_VALUE[bad])
        _check(self.frame_bytes >= 0 and self.n_frames >= 0, "frame_bytes and n_frames must be >= 0")
        for name in ("vids", "owner", "object_id", "size_bytes", "reward", "p_deliver", "history", "unseen"):
            getattr(self, name).setflags(write=False)

    @property
    def n_objects(self) -> int:
        return len(self.object_id)

    @property
    def n_vehicles(self) -> int:
        return len(self.vids)

    def keys(self) -> list[ObjectKey]:
        """(sender vid, object id) of every object, in index order."""
        return list(zip(self.vids[self.owner].tolist(), self.object_id.tolist()))

    def p_object(self) -> np.ndarray:
        """float64 (K, C): p_(owner of k), j, the delivery probability of each object to each j."""
        return self.p_deliver[self.owner]

    def wanted(self) -> np.ndarray:
        """bool (K,): objects that still carry reward for someone (some y > 0 with h = 0)."""
        return np.any((self.reward > 0.0) & ~self.history, axis=1)


def _ascending_pairs(d_major: np.ndarray, d_minor: np.ndarray) -> bool:
    """Pairs in lexicographic order (ties allowed), from their consecutive differences:
    what a stable ``np.lexsort`` leaves in place."""
    return bool(np.all((d_major > 0) | ((d_major == 0) & (d_minor >= 0))))


_BAD_VALUE = ("", "unseen must be >= 0", "vids must be strictly ascending", "owner out of range",
              "objects must be sorted by (owner, object_id)", "duplicate (owner, object_id)",
              "size_bytes must be positive", "reward to the owner itself must be 0", "reward must lie in [0, 1]",
              "p_deliver must lie in [0, 1]")


@njit(cache=True)
def _first_bad_value(vids, owner, object_id, size_bytes, reward, p_deliver, unseen) -> int:
    """The first of the instance's value checks that fails (its index in ``_BAD_VALUE``),
    0 if none does: one pass each, where a dozen numpy reductions took ~45 us an
    interval. NaN fails every range check, as ``np.all(x >= 0)`` fails it."""
    for k in range(len(unseen)):
        if not unseen[k] >= 0.0:
            return 1
    for c in range(1, len(vids)):
        if not vids[c] > vids[c - 1]:
            return 2
    C, K = len(vids), len(object_id)
    for k in range(K):
        if owner[k] < 0 or owner[k] >= C:
            return 3
    for k in range(1, K):
        if owner[k] < owner[k - 1] or (owner[k] == owner[k - 1] and object_id[k] < object_id[k - 1]):
            return 4
    for k in range(1, K):
        if owner[k] == owner[k - 1] and object_id[k] == object_id[k - 1]:
            return 5
    for k in range(K):
        if size_bytes[k] <= 0:
            return 6
    for k in range(K):
        if reward[k, owner[k]] != 0.0:
            return 7
    for k in range(K):
        for c in range(C):
            if not (reward[k, c] >= 0.0 and reward[k, c] <= 1.0):
                return 8
    for i in range(C):
        for j in range(C):
            if not (p_deliver[i, j] >= 0.0 and p_deliver[i, j] <= 1.0):
                return 9
    return 0


def _check(ok: bool, what: str) -> None:
    if not ok:
        raise ValueError(f"invalid scheduling instance: {what}")


@dataclass(frozen=True, slots=True)
class Schedule:
    """x^n_(i,k): for each of the N frames, the object indices sent in it (ascending).

    ``fill`` (empty, or one tuple per frame) marks the objects of ``frames`` that only
    take the frame's spare airtime (work-conserving AutoCast, ``fill.py``): the TDMA
    layout puts them after every other transmission of their frame."""

    frames: tuple[tuple[int, ...], ...]
    fill: tuple[tuple[int, ...], ...] = ()

    @staticmethod
    def from_sets(frames: Iterable[Iterable[int]]) -> Schedule:
        return Schedule(tuple(tuple(sorted(int(k) for k in f)) for f in frames))

    def filled(self, n: int) -> tuple[int, ...]:
        """The spare-airtime objects of frame ``n`` (ascending)."""
        return self.fill[n] if self.fill else ()

    def primary(self) -> Schedule:
        """The schedule without its spare-airtime objects."""
        if not self.fill:
            return self
        return Schedule(tuple(tuple(k for k in f if k not in set(g)) for f, g in zip(self.frames, self.fill)))

    def matrix(self, n_objects: int) -> np.ndarray:
        """bool (N, K): x^n_(i,k)."""
        x = np.zeros((len(self.frames), n_objects), dtype=bool)
        for n, frame in enumerate(self.frames):
            x[n, list(frame)] = True
        return x

    def sent(self) -> frozenset[int]:
        return frozenset(k for frame in self.frames for k in frame)

    def keyed(self, instance: Instance) -> tuple[tuple[ObjectKey, ...], ...]:
        """The schedule by (vid, object id), comparable across differently built instances."""
        keys = instance.keys()
        return tuple(tuple(keys[k] for k in frame) for frame in self.frames)


# ------------------------------------------------------------------------- builders


def _ints(a: Iterable[int]) -> np.ndarray:
    return np.asarray(a if isinstance(a, np.ndarray) else list(a), dtype=np.int64)


def instance_from_arrays(
    vids: Iterable[int],
    owner_vid: Iterable[int],
    object_id: Iterable[int],
    size_bytes: Iterable[int],
    reward: np.ndarray,
    p_deliver: np.ndarray,
    *,
    frame_bytes: int,
    n_frames: int,
    history: np.ndarray | None = None,
    bandwidth_bps: float = DEFAULT_BANDWIDTH_BPS,
    frame_duration_s: float | None = None,
    unseen: np.ndarray | None = None,
) -> Instance:
    """Canonicalise arrays given in any order: ``reward``/``history`` are (K, C) and
    ``p_deliver`` (C, C), their vehicle axes in the order of ``vids``; ``unseen`` (K,)."""
    vids, owner_vid, object_id, size_bytes = (_ints(a) for a in (vids, owner_vid, object_id, size_bytes))
    reward = np.asarray(reward, dtype=np.float64).reshape(len(object_id), len(vids))
    p_deliver = np.asarray(p_deliver, dtype=np.float64).reshape(len(vids), len(vids))
    if history is None:
        history = np.zeros(reward.shape, dtype=bool)
    history = np.asarray(history, dtype=bool).reshape(reward.shape)
    ascending = len(vids) < 2 or bool(np.all(vids[1:] > vids[:-1]))  # as make_instance gives them: no reordering
    if not ascending and len(np.unique(vids)) != len(vids):
        raise ValueError("invalid scheduling instance: duplicate vehicle id")
    vorder = np.arange(len(vids)) if ascending else np.argsort(vids, kind="stable")
    sorted_vids = vids if ascending else vids[vorder]
    owner = np.searchsorted(sorted_vids, owner_vid)
    found = owner < len(sorted_vids)
    found[found] = sorted_vids[owner[found]] == owner_vid[found]
    if not found.all():  # np.isin(owner_vid, vids)
        raise ValueError("invalid scheduling instance: an object's owner is not among vids")
    if len(owner) < 2 or _ascending_pairs(np.diff(owner), np.diff(object_id)):  # np.lexsort's order already
        korder = np.arange(len(owner))
        reward, history = reward.copy(), history.copy()
        if not ascending:
            reward, history = reward[:, vorder], history[:, vorder]
    else:
        korder = np.lexsort((object_id, owner))
        reward = reward[korder][:, vorder].copy()
        history = history[korder][:, vorder].copy()
        owner = owner[korder]
    if len(owner):
        reward[np.arange(len(owner)), owner] = 0.0  # i does not need its own object
    if frame_duration_s is None:
        frame_duration_s = frame_bytes * 8.0 / bandwidth_bps
    return Instance(
        vids=sorted_vids.copy(),
        owner=owner.astype(np.int64),
        object_id=object_id[korder].copy(),
        size_bytes=size_bytes[korder].copy(),
        reward=reward,
        p_deliver=p_deliver.copy() if ascending else p_deliver[vorder][:, vorder].copy(),
        history=history,
        frame_bytes=int(frame_bytes),
        n_frames=int(n_frames),
        frame_duration_s=float(frame_duration_s),
        bandwidth_bps=float(bandwidth_bps),
        unseen=None if unseen is None else np.asarray(unseen, dtype=np.float64).reshape(len(object_id))[korder].copy(),
    )


@dataclass(frozen=True, slots=True, eq=False)
class SenderOffers:
    """One sender's object map as arrays (the cheap form for a control message): row t
    is object ``object_id[t]``, column c refers to receiver ``receivers[c]``."""

    object_id: np.ndarray  # int (n,)
    size_bytes: np.ndarray  # int (n,)
    receivers: np.ndarray  # int (m,)
    visibility: np.ndarray  # float (n, m), v
    relevance: np.ndarray  # float (n, m), r


def _as_arrays(objs: SenderOffers | Iterable[OfferLike]) -> SenderOffers:
    if hasattr(objs, "receivers"):
        return objs  # type: ignore[return-value]
    objs = list(objs)
    receivers = sorted({int(j) for o in objs for j in o.relevance})
    col = {j: c for c, j in enumerate(receivers)}
    at = [(t, col[int(j)], rel, o.visibility.get(j, 0.0)) for t, o in enumerate(objs) for j, rel in o.relevance.items()]
    rows, cols, rel, vis = (list(x) for x in zip(*at)) if at else ([], [], [], [])
    v = np.zeros((len(objs), len(receivers)))
    r = np.zeros((len(objs), len(receivers)))
    v[rows, cols] = vis
    r[rows, cols] = rel
    return SenderOffers(
        np.array([int(o.object_id) for o in objs], dtype=np.int64),
        np.array([int(o.size_bytes) for o in objs], dtype=np.int64),
        np.array(receivers, dtype=np.int64),
        v,
        r,
    )


def make_instance(
    offers: Mapping[int, SenderOffers | Iterable[OfferLike]],
    p_deliver: Callable[[int, int], float] | Mapping[tuple[int, int], float],
    *,
    vids: Iterable[int] = (),
    history: Mapping[ObjectKey, Iterable[int]] | None = None,
    bandwidth_bps: float = DEFAULT_BANDWIDTH_BPS,
    frame_duration_s: float = DEFAULT_FRAME_DURATION_S,
    decision_interval_s: float = DEFAULT_DECISION_INTERVAL_S,
) -> Instance:
    """Build the instance from the control messages heard this interval.

    ``offers`` maps each sender vid to its objects, as ``SenderOffers`` arrays or as
    per-object records; ``p_deliver`` gives p_ij for a (sender, receiver) pair (a
    callable, a mapping, or an object whose ``matrix(vids)`` returns the whole table);
    ``vids`` adds receivers that offer nothing; ``history`` lists, per object, the
    receivers that already have it. S_f = B * T_n / 8 bytes and N = floor(T_d / T_n).
    """
    senders = [(int(i), _as_arrays(objs)) for i, objs in offers.items()]
    if type(vids) is not np.ndarray:
        vids = list(vids)  # read twice if the general path takes the instance after all
    if not history:
        # the senders' tables as they come in control messages: one kernel, which adds the senders and
        # receivers to an int64 array of vids itself (a set of a group's 40 receivers was 9 us)
        given = type(vids) is np.ndarray and vids.dtype == np.int64 and vids.ndim == 1
        tables = _offer_tables(senders, vids if given else np.array(sorted({int(v) for v in vids}), dtype=np.int64))
        if tables is not None:
            vid_arr, *arrays = tables
            return _canonical(vid_arr, *arrays, _p_table(p_deliver, vid_arr), bandwidth_bps, frame_duration_s,
                              decision_interval_s)
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
        y[:, cols] = (1.0 - v) * r  # y = (1 - v) * r
        hidden[:, cols] = np.minimum(np.maximum(1.0 - v, 0.0), 1.0)  # np.clip's values, a third of its time
        hidden[:, np.searchsorted(vid_arr, i)] = 0.0  # the sender sees its own object
        blocks.append(y)
        unseen.append(hidden.sum(axis=1))  # summed in vid order: bit-equal on every vehicle
    reward = np.concatenate(blocks) if blocks else np.zeros((0, C))
    owner_vid = np.repeat(np.array([i for i, _ in senders], dtype=np.int64), [len(b.object_id) for _, b in senders])
    object_id = np.concatenate([np.asarray(b.object_id, dtype=np.int64) for _, b in senders] or [np.zeros(0, np.int64)])
    size_bytes = np.concatenate([np.asarray(b.size_bytes, dtype=np.int64) for _, b in senders] or [np.zeros(0, np.int64)])
    hist = np.zeros(reward.shape, dtype=bool)
    if history:
        index = {key: row for row, key in enumerate(zip(owner_vid.tolist(), object_id.tolist()))}
        col = {v: c for c, v in enumerate(vid_arr.tolist())}
        for key, receivers in history.items():
            row = index.get((int(key[0]), int(key[1])))
            if row is not None:
                for j in receivers:
                    if int(j) in col:
                        hist[row, col[int(j)]] = True
    ids = vid_arr.tolist()
    if hasattr(p_deliver, "matrix"):  # vectorized: the whole (C, C) table at once
        p = np.array(p_deliver.matrix(ids), dtype=np.float64).reshape(C, C)
        np.fill_diagonal(p, 1.0)
    else:
        get_p = p_deliver if callable(p_deliver) else (lambda i, j: p_deliver[(i, j)])
        p = np.array([[1.0 if i == j else float(get_p(i, j)) for j in ids] for i in ids]).reshape(C, C)
    return instance_from_arrays(
        vid_arr,
        owner_vid,
        object_id,
        size_bytes,
        reward,
        p,
        frame_bytes=int(bandwidth_bps * frame_duration_s / 8.0),  # S_f = B * T_n
        n_frames=int(decision_interval_s / frame_duration_s + 1e-9),  # N = T_d / T_n
        history=hist,
        bandwidth_bps=bandwidth_bps,
        frame_duration_s=frame_duration_s,
        unseen=np.concatenate(unseen) if unseen else np.zeros(0),
    )


def _offer_tables(senders: list[tuple[int, SenderOffers]], vids: np.ndarray) -> tuple | None:
    """``make_instance``'s vehicles and objects from arrays of senders given ascending,
    each sender's objects ascending by id (how a group's control messages give them):
    the vids (those of ``vids``, the senders and their receivers, ascending), owner,
    object id, size, reward and unseen, as ``make_instance``'s per-sender numpy blocks and
    ``instance_from_arrays`` compute them, in one kernel over the concatenated tables
    (~15 numpy calls per sender were most of the schedule stage). None for anything
    else (no sender, tables not (n, m) numeric arrays, senders or objects out of
    order): the general path takes it."""
    if not senders:
        return None
    meta = [[], [], []]  # each sender's vid, number of objects and of receivers
    ndarray = np.ndarray
    for i, b in senders:
        ids, sizes, receivers, v, r = b.object_id, b.size_bytes, b.receivers, b.visibility, b.relevance
        if type(ids) is not ndarray or type(sizes) is not ndarray or type(receivers) is not ndarray or \
                type(v) is not ndarray or type(r) is not ndarray or ids.ndim != 1 or sizes.ndim != 1 or \
                receivers.ndim != 1:
            return None
        n, m = len(ids), len(receivers)
        if v.shape != (n, m) or r.shape != (n, m):
            return None
        meta[0].append(i)
        meta[1].append(n)
        meta[2].append(m)
    # two concatenations, not one per field: the ids, sizes and receivers; then every table, flattened
    ints = np.concatenate([b.object_id for _, b in senders] + [b.size_bytes for _, b in senders] +
                          [b.receivers for _, b in senders])
    shares = np.concatenate([b.visibility.ravel() for _, b in senders] + [b.relevance.ravel() for _, b in senders])
    if ints.dtype != np.int64 or shares.dtype.kind != "f":  # values as np.asarray(..., np.float64) gives them
        return None
    vid_arr, owner, reward, hidden, canonical = _offer_kernel(vids, np.array(meta, dtype=np.int64), ints, shares)
    if not canonical:
        return None
    K = len(owner)
    object_id, size_bytes = ints[:K], ints[K:2 * K]
    return vid_arr, owner, object_id, size_bytes, reward, hidden.sum(axis=1)  # summed in vid order, row by row


@njit(cache=True)
def _offer_kernel(extra, meta, ints, shares):
    """(vids, owner, reward, hidden, canonical) of the senders ``meta[0]`` with
    ``meta[1]`` objects and ``meta[2]`` receivers each, whose object ids, sizes and
    receivers are ``ints`` (all ids, all sizes, all receivers) and whose tables are
    ``shares`` (all visibilities, all relevances): the vehicles (``extra``, the senders
    and the receivers, ascending, once each); per object, the index of its sender in
    ``vids``; y = (1 - v) * r in the receivers' columns, 0 in the sender's own;
    min(max(1 - v, 0), 1) likewise (``unseen`` is its row sums); and whether the
    objects are in canonical order (senders strictly ascending, object ids ascending
    within a sender). Tables are (n, m) row-major, sender after sender; a receiver
    named twice keeps its last column, as numpy's ``y[:, cols] = ...`` does."""
    sender, counts = meta[0], meta[1:]
    K, T = counts[0].sum(), (counts[0] * counts[1]).sum()
    object_id, receivers = ints[:K], ints[2 * K:]
    visibility, relevance = shares[:T], shares[T:]
    vids = _ascending_once(np.concatenate((extra, sender, receivers)))
    C = vids.shape[0]
    owner = np.empty(K, dtype=np.int64)
    reward = np.zeros((K, C))
    hidden = np.zeros((K, C))
    canonical = True
    row, at_r, at_t = 0, 0, 0
    for s in range(sender.shape[0]):
        n, m = counts[0, s], counts[1, s]
        own = np.searchsorted(vids, sender[s])
        if s > 0 and sender[s] <= sender[s - 1]:
            canonical = False
        cols = np.searchsorted(vids, receivers[at_r:at_r + m])
        for t in range(n):
            k = row + t
            owner[k] = own
            if t > 0 and object_id[k] < object_id[k - 1]:
                canonical = False
            for c in range(m):
                v = np.float64(visibility[at_t + t * m + c])
                r = np.float64(relevance[at_t + t * m + c])
                reward[k, cols[c]] = (1.0 - v) * r  # y = (1 - v) * r
                a = 1.0 - v
                if a < 0.0:  # np.maximum, then np.minimum: NaN stays NaN
                    a = 0.0
                if a > 1.0:
                    a = 1.0
                hidden[k, cols[c]] = a
            hidden[k, own] = 0.0  # the sender sees its own object
            reward[k, own] = 0.0  # i does not need its own object
        row += n
        at_r += m
        at_t += n * m
    return vids, owner, reward, hidden, canonical


@njit(cache=True)
def _ascending_once(ids):
    """``np.unique(ids)``: ids ascending, once each; vehicle ids (small, non-negative)
    marked in a table rather than sorted."""
    if ids.shape[0] == 0 or ids.min() < 0 or ids.max() >= 1 << 16:
        return np.unique(ids)
    seen = np.zeros(ids.max() + 1, dtype=np.bool_)
    n = 0
    for v in ids:
        if not seen[v]:
            seen[v] = True
            n += 1
    out = np.empty(n, dtype=np.int64)
    n = 0
    for v in range(seen.shape[0]):
        if seen[v]:
            out[n] = v
            n += 1
    return out


def _p_table(p_deliver, vid_arr: np.ndarray) -> np.ndarray:
    """float64 (C, C) p_ij over ``vid_arr``, 1 on the diagonal (``make_instance``'s)."""
    ids = vid_arr.tolist()
    C = len(ids)
    if hasattr(p_deliver, "matrix"):
        p = np.array(p_deliver.matrix(ids), dtype=np.float64).reshape(C, C)
        np.fill_diagonal(p, 1.0)
        return p
    get_p = p_deliver if callable(p_deliver) else (lambda i, j: p_deliver[(i, j)])
    return np.array([[1.0 if i == j else float(get_p(i, j)) for j in ids] for i in ids]).reshape(C, C)


def _canonical(vid_arr: np.ndarray, owner: np.ndarray, object_id: np.ndarray, size_bytes: np.ndarray,
               reward: np.ndarray, unseen: np.ndarray, p: np.ndarray, bandwidth_bps: float,
               frame_duration_s: float, decision_interval_s: float) -> Instance:
    """The instance of arrays already canonical (``_offer_tables``), as ``make_instance``
    would have ``instance_from_arrays`` build it."""
    return Instance(
        vids=vid_arr, owner=owner, object_id=object_id, size_bytes=size_bytes, reward=reward, p_deliver=p,
        history=np.zeros(reward.shape, dtype=bool),
        frame_bytes=int(bandwidth_bps * frame_duration_s / 8.0),  # S_f = B * T_n
        n_frames=int(decision_interval_s / frame_duration_s + 1e-9),  # N = T_d / T_n
        frame_duration_s=float(frame_duration_s), bandwidth_bps=float(bandwidth_bps), unseen=unseen,
    )


def link_probability(distance_m: np.ndarray | float, d50_m: float = 150.0, spread_m: float = 25.0) -> np.ndarray:
    """p_ij as a function of sender-receiver distance: a logistic packet-reception curve
    shaped like the 3GPP TR 36.885 highway/urban PRR curves (0.5 at ``d50_m``)."""
    d = np.asarray(distance_m, dtype=np.float64)
    return 1.0 / (1.0 + np.exp((d - d50_m) / spread_m))


def link_probabilities(positions_m: np.ndarray, **kw: float) -> np.ndarray:
    """(C, C) p_ij from (C, 2) vehicle positions, with p_ii = 1."""
    xy = np.asarray(positions_m, dtype=np.float64)
    d = np.hypot(xy[:, None, 0] - xy[None, :, 0], xy[:, None, 1] - xy[None, :, 1])
    p = link_probability(d, **kw)
    np.fill_diagonal(p, 1.0)
    return p


# ------------------------------------------------------------------------- evaluation


def weight_H(reward: np.ndarray, h_expected: np.ndarray) -> np.ndarray:
    """H^n_(i,k) = sum_j y_(i,k),j * (1 - h^(n-1)_(i,k),j)  (eq. GreedyMetric)."""
    return np.sum(reward * (1.0 - h_expected), axis=1)


def deliver_expected(h_expected: np.ndarray, p_object: np.ndarray, sent: np.ndarray) -> np.ndarray:
    """h after a frame: each sent object reaches j with probability p_ij, independently."""
    h = h_expected.copy()
    h[sent] = 1.0 - (1.0 - h[sent]) * (1.0 - p_object[sent])
    return h


def expected_reward(instance: Instance, schedule: Schedule) -> float:
    """E[sum_n R^n] (eq. reward_func) of an open-loop schedule: an object sent c times
    reaches j with probability 1 - (1 - p_ij)^c, independently of when."""
    counts = np.zeros(instance.n_objects, dtype=np.int64)
    for frame in schedule.frames:
        counts[list(frame)] += 1
    gain = instance.reward * ~instance.history
    miss = (1.0 - instance.p_object()) ** counts[:, None]
    return float(np.sum(gain * (1.0 - miss)))


def frame_weights(instance: Instance, schedule: Schedule) -> list[float]:
    """Per frame, sum of H^n over the objects sent in it, H taken at that frame's
    expected state (the knapsack objective each frame maximises)."""
    h = instance.history.astype(np.float64)
    p = instance.p_object()
    out = []
    for frame in schedule.frames:
        sent = np.zeros(instance.n_objects, dtype=bool)
        sent[list(frame)] = True
        out.append(float(np.sum(weight_H(instance.reward[sent], h[sent]))))
        h = deliver_expected(h, p, sent)
    return out


def check_schedule(instance: Instance, schedule: Schedule) -> None:
    """Raise ValueError if the schedule has more than N frames, an unknown or repeated
    object in a frame, or a frame whose objects exceed S_f."""
    if len(schedule.frames) > instance.n_frames:
        raise ValueError(f"schedule has {len(schedule.frames)} frames, instance has N={instance.n_frames}")
    for n, frame in enumerate(schedule.frames):
        if len(set(frame)) != len(frame) or any(k < 0 or k >= instance.n_objects for k in frame):
            raise ValueError(f"frame {n}: repeated or unknown object index in {frame}")
        used = int(instance.size_bytes[list(frame)].sum()) if frame else 0
        if used > instance.frame_bytes:
            raise ValueError(f"frame {n}: {used} bytes exceed S_f={instance.frame_bytes}")
