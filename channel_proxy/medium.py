"""The shared medium of one decision interval, as plain functions over numpy arrays.

Times are integer nanoseconds from the start of the phase, so airtime arithmetic is
exact and two back-to-back transmissions never overlap by a rounding error; two
airtimes overlap only if they share more than ``TOLERANCE_NS``.

Data channel, per interval T_d:
1. each transmission lasts ``size_bytes * 8 / B``; a sender's radio sends one thing at a
   time, so its own transmissions are served first come first served from the start
   it claims (a burst queues behind itself);
2. a transmission that would not end by T_d is not sent at all (overflow);
3. airtimes of different senders that overlap collide: the transmission is lost at
   every receiver that the other sender reaches, and at the other sender itself, which
   cannot listen while it transmits (half duplex); no capture effect;
4. what survives reaches receiver j with probability p_ij, drawn from the keyed RNG.

Control channel: every vehicle owns its own resource in the control pool (semi-
persistent reservations), so control messages never collide; the pool carries
``capacity_bytes`` per interval, and messages beyond it (in a seeded order that changes
every tick) are dropped for everyone; the rest reach j with probability p_ij.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from channel_proxy.loss import CTRL, DATA, bernoulli, keyed_uniform

NS = 1_000_000_000
TOLERANCE_NS = 100  # overlaps of at most this much are rounding, not collisions
_MAX_NS = 1 << 40  # ~1100 s: claims beyond are clipped (they overflow anyway)


def airtime_ns(size_bytes: np.ndarray, bandwidth_bps: float) -> np.ndarray:
    """Duration of each payload on air: s * 8 / B, rounded to the nanosecond."""
    s = np.asarray(size_bytes, dtype=np.float64)
    return np.minimum(np.rint(s * 8.0 * NS / bandwidth_bps), _MAX_NS).astype(np.int64)


def to_ns(t_s: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(np.asarray(t_s, dtype=np.float64) * NS), 0, _MAX_NS).astype(np.int64)


def serialize(sender: np.ndarray, start_ns: np.ndarray, duration_ns: np.ndarray) -> np.ndarray:
    """Actual start of each transmission when every sender's radio is a FIFO: in order
    of claimed start (ties: given order), each starts at max(claim, end of the previous
    one of the same sender)."""
    T = len(sender)
    if T == 0:
        return np.zeros(0, dtype=np.int64)
    order = np.lexsort((np.arange(T), start_ns, sender))
    g, s, d = sender[order], start_ns[order], duration_ns[order]
    first = np.r_[True, g[1:] != g[:-1]]
    cum = np.cumsum(d)
    before = cum - d  # airtime queued before each, counted from the array start
    group_base = before[np.maximum.accumulate(np.where(first, np.arange(T), 0))]
    queued = before - group_base  # airtime of the same sender queued before it
    # end_k = sum_{j<=k} d_j + max_{j<=k}(s_j - sum_{j'<j} d_j'), within each sender; the
    # rank offset makes one cumulative max restart at every sender (exact in int64)
    rank = np.cumsum(first) - 1
    shift = rank.astype(np.int64) << 50
    slack = np.maximum.accumulate(s - queued + shift) - shift
    out = np.empty(T, dtype=np.int64)
    out[order] = slack + queued
    return out


def overlaps(sender: np.ndarray, start_ns: np.ndarray, end_ns: np.ndarray, on_air: np.ndarray) -> np.ndarray:
    """(T, T) bool: transmissions of different senders, both on air, whose airtimes
    share more than ``TOLERANCE_NS``."""
    s, e = start_ns, end_ns
    ov = (s[:, None] < e[None, :] - TOLERANCE_NS) & (s[None, :] < e[:, None] - TOLERANCE_NS)
    ov &= sender[:, None] != sender[None, :]
    ov &= on_air[:, None] & on_air[None, :]
    return ov


def collided_at(ov: np.ndarray, sender: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """(T, C) bool: transmission t is lost at receiver c because an overlapping
    transmission's sender reaches c (``reach`` (C, C), reach[i, i] = True, so a receiver
    that is itself transmitting is deaf: half duplex)."""
    out = np.zeros((len(sender), reach.shape[1]), dtype=bool)
    rows = np.flatnonzero(ov.any(axis=1))  # a TDMA schedule overlaps few airtimes, if any: the product of those
    if len(rows):  # (a sum of zeros and ones is > 0 with or without the zero terms left out)
        cols = np.flatnonzero(ov.any(axis=0))
        out[rows] = (ov[np.ix_(rows, cols)].astype(np.float32) @ reach[sender[cols]].astype(np.float32)) > 0.0
    return out


def busy_ns(start_ns: np.ndarray, end_ns: np.ndarray) -> int:
    """Length of the union of the airtimes (how long the channel was busy)."""
    if len(start_ns) == 0:
        return 0
    order = np.argsort(start_ns, kind="stable")
    s, e = start_ns[order], end_ns[order]
    reach_end = np.maximum.accumulate(e)
    new = np.r_[True, s[1:] > reach_end[:-1]]  # a gap before it: a new busy stretch starts
    seg = np.cumsum(new) - 1
    seg_start = s[new]
    seg_end = np.zeros(len(seg_start), dtype=np.int64)
    np.maximum.at(seg_end, seg, e)
    return int(np.sum(seg_end - seg_start))


def occurrence(sender: np.ndarray, item: np.ndarray) -> np.ndarray:
    """How many earlier entries have the same (sender, item): keys a re-sent object's
    second copy apart from its first in the loss draws."""
    T = len(sender)
    order = np.lexsort((np.arange(T), item, sender))
    g, i = sender[order], item[order]
    first = np.r_[True, (g[1:] != g[:-1]) | (i[1:] != i[:-1])] if T else np.zeros(0, bool)
    idx = np.arange(T)
    occ = idx - np.maximum.accumulate(np.where(first, idx, 0))
    out = np.empty(T, dtype=np.int64)
    out[order] = occ
    return out


@dataclass(frozen=True, slots=True)
class DataOutcome:
    """What the data channel did to each transmission t at each receiver c."""

    start_ns: np.ndarray  # (T,) actual start (after the sender's own queue)
    end_ns: np.ndarray  # (T,) end of airtime = reception time
    overflow: np.ndarray  # (T,) not sent: would not end by T_d
    in_range: np.ndarray  # (T, C) c is not the sender and within its cutoff
    collided: np.ndarray  # (T, C) lost to another sender's overlapping airtime (or half duplex)
    lost_channel: np.ndarray  # (T, C) survived collisions, lost to the link's p_ij draw
    delivered: np.ndarray  # (T, C)
    busy_ns: int  # union of the airtimes of what was sent


def play_data(
    vids: np.ndarray,
    sender: np.ndarray,
    item: np.ndarray,
    start_s: np.ndarray,
    size_bytes: np.ndarray,
    p: np.ndarray,
    reach: np.ndarray,
    *,
    bandwidth_bps: float,
    interval_s: float,
    seed: int,
    tick: int,
    channel: int = DATA,
) -> DataOutcome:
    """One interval of the data channel.

    ``vids`` (C,) the vehicles of the interval; ``sender`` (T,) index into ``vids``;
    ``item`` (T,) object id; ``start_s`` (T,) claimed start from the phase start;
    ``p`` (C, C) p_ij; ``reach`` (C, C) bool, j within i's cutoff.
    """
    vids = np.asarray(vids, dtype=np.int64)
    sender = np.asarray(sender, dtype=np.int64)
    item = np.asarray(item, dtype=np.int64)
    T, C = len(sender), len(vids)
    duration = airtime_ns(size_bytes, bandwidth_bps)
    start = serialize(sender, to_ns(start_s), duration)
    end = start + duration
    overflow = end > int(round(interval_s * NS)) + TOLERANCE_NS
    on_air = ~overflow
    ov = overlaps(sender, start, end, on_air)
    collided = collided_at(ov, sender, reach) if T else np.zeros((0, C), dtype=bool)
    in_range = reach[sender] & (np.arange(C)[None, :] != sender[:, None])
    in_range &= on_air[:, None]
    collided &= in_range
    survive = bernoulli(p[sender], seed, tick, channel, vids[sender][:, None], vids[None, :],
                        item[:, None], occurrence(sender, item)[:, None]) if T else np.zeros((0, C), dtype=bool)
    lost_channel = in_range & ~collided & ~survive
    delivered = in_range & ~collided & survive
    return DataOutcome(start, end, overflow, in_range, collided, lost_channel, delivered,
                       busy_ns(start[on_air], end[on_air]))


@dataclass(frozen=True, slots=True)
class CtrlOutcome:
    overflow: np.ndarray  # (S,) dropped: the control pool was full
    in_range: np.ndarray  # (S, C)
    heard: np.ndarray  # (S, C) receiver c decoded sender s's message
    lost_channel: np.ndarray  # (S, C)


def play_control(
    vids: np.ndarray,
    sender: np.ndarray,
    size_bytes: np.ndarray,
    p: np.ndarray,
    reach: np.ndarray,
    *,
    capacity_bytes: int,
    seed: int,
    tick: int,
) -> CtrlOutcome:
    """One interval of the control channel (``sender`` (S,) indices into ``vids``, one
    message each)."""
    vids = np.asarray(vids, dtype=np.int64)
    sender = np.asarray(sender, dtype=np.int64)
    size = np.asarray(size_bytes, dtype=np.int64)
    C = len(vids)
    order = np.argsort(keyed_uniform(seed, tick, CTRL, -1, vids[sender]), kind="stable")  # fair, per tick
    fits = np.cumsum(size[order]) <= capacity_bytes
    overflow = np.ones(len(sender), dtype=bool)
    overflow[order[fits]] = False
    in_range = reach[sender] & (np.arange(C)[None, :] != sender[:, None]) & ~overflow[:, None]
    survive = bernoulli(p[sender], seed, tick, CTRL, vids[sender][:, None], vids[None, :], 0) if len(sender) \
        else np.zeros((0, C), dtype=bool)
    return CtrlOutcome(overflow, in_range, in_range & survive, in_range & ~survive)


def control_onair_bytes(n_objects: int, n_receivers: int, n_waypoints: int, n_heard: int) -> int:
    """What a control message occupies on air, coded compactly (the radio does not carry
    our msgpack float32 arrays): 48 B header (tick, time, vid, pose, speed), 12 B per
    trajectory waypoint, 16 B per object (id, size, centroid), 4 B per receiver id,
    1 B per (object, receiver) pair (v as 1 bit, r as 7 bits), 4 B per heard vid."""
    return 48 + 12 * n_waypoints + 16 * n_objects + 4 * n_receivers + n_objects * n_receivers + 4 * n_heard
