"""The EMP baseline's edge relay (V2I), as plain functions over numpy arrays.

EMP (the paper's infrastructure baseline) splits the scene into the Voronoi cells of
the participating vehicles: each vehicle uploads the part of its full point cloud that
lies in its own cell to an edge relay, which forwards every segment to the others.
Nothing is prioritised: no object extraction, no visibility or relevance.

The relay's medium, per interval T_d: one channel of B (default 50 Mbps) shared by
uploads and forwards, time-divided: the relay serves uploaders round robin (the start
rotates by one vehicle every tick, so no vehicle is always last), and each segment is
uploaded and then broadcast once to every vehicle in the relay's range (store and
forward). A segment whose forward would not end by T_d is not sent (overflow). Both hops
use the profile's distance-based loss around the relay's position.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from channel_proxy.loss import EMP_DOWN, EMP_UP, bernoulli
from channel_proxy.medium import NS, TOLERANCE_NS, airtime_ns

RELAY_VID = -1  # the relay's id in loss draws
HEADER_BYTES = 64


def voronoi_segment(points_xy: np.ndarray, own_xy: np.ndarray, others_xy: np.ndarray) -> np.ndarray:
    """bool (n,): the points that lie in the vehicle's own Voronoi cell (no other site is
    strictly nearer; squared distances compared as ``dx * dx + dy * dy`` in float64)."""
    pts = np.ascontiguousarray(np.asarray(points_xy, dtype=np.float64).reshape(-1, 2))
    others = np.asarray(others_xy, dtype=np.float64).reshape(-1, 2)
    own = np.asarray(own_xy, dtype=np.float64).reshape(2)
    if len(others) == 0:
        return np.ones(len(pts), dtype=bool)
    # nearest sites first, with their distance from our own site: a site at least twice as
    # far from us as a point is cannot be nearer to it than we are (triangle inequality),
    # so a point stops testing at the first such site. The brute-force test over every
    # site (a (n, sites, 2) array) was an EMP agent's whole tick at 40 vehicles: ~70 ms.
    gap = np.hypot(others[:, 0] - own[0], others[:, 1] - own[1])
    order = np.argsort(gap, kind="stable")
    return _in_own_cell(pts, own[0], own[1], np.ascontiguousarray(others[order]), gap[order])


@njit(cache=True)
def _in_own_cell(pts, ox, oy, sites, gap):
    """``voronoi_segment``'s test, point by point, over ``sites`` ascending by ``gap``
    (their distance from ours). The cut-off keeps a margin far above rounding: a site
    skipped is farther from the point than ours by much more than any rounding error,
    so the answer is the brute force's, bit for bit."""
    out = np.empty(len(pts), dtype=np.bool_)
    for i in range(len(pts)):
        x, y = pts[i, 0], pts[i, 1]
        dx, dy = x - ox, y - oy
        d_own = dx * dx + dy * dy
        reach = 2.0 * np.sqrt(d_own) * (1.0 + 1e-9) + 1e-9
        mine = True
        for k in range(len(sites)):
            if gap[k] > reach:
                break
            ex, ey = x - sites[k, 0], y - sites[k, 1]
            if ex * ex + ey * ey < d_own:
                mine = False
                break
        out[i] = mine
    return out


def segment_onair_bytes(n_points: np.ndarray, bytes_per_point: float) -> np.ndarray:
    """A segment on air: a header plus the points, coded at ``bytes_per_point``."""
    return (HEADER_BYTES + np.ceil(np.asarray(n_points, dtype=np.float64) * bytes_per_point)).astype(np.int64)


@dataclass(frozen=True, slots=True)
class RelayOutcome:
    up_start_ns: np.ndarray  # (U,)
    fwd_end_ns: np.ndarray  # (U,) reception time of the forward
    overflow: np.ndarray  # (U,) not sent: the forward would not end by T_d
    uploaded: np.ndarray  # (U,) the relay decoded the upload
    in_range: np.ndarray  # (U, C) receiver c (not the uploader) is within the relay's cutoff
    delivered: np.ndarray  # (U, C)
    busy_ns: int


def play_relay(
    vids: np.ndarray,
    sender: np.ndarray,
    size_bytes: np.ndarray,
    p_up: np.ndarray,
    p_down: np.ndarray,
    reach: np.ndarray,
    *,
    bandwidth_bps: float,
    interval_s: float,
    seed: int,
    tick: int,
) -> RelayOutcome:
    """One interval of the relay. ``sender`` (U,) indices into ``vids`` (C,), one
    upload each; ``p_up`` (U,) uploader -> relay, ``p_down`` (C,) relay -> receiver,
    ``reach`` (C,) bool, receiver within the relay's cutoff."""
    vids = np.asarray(vids, dtype=np.int64)
    sender = np.asarray(sender, dtype=np.int64)
    U, C = len(sender), len(vids)
    by_vid = np.argsort(vids[sender], kind="stable")
    order = np.roll(by_vid, -(tick % U)) if U else by_vid  # round robin, rotating by a vehicle a tick
    d = airtime_ns(size_bytes, bandwidth_bps)[order]
    slot_end = np.cumsum(2 * d)  # upload then forward, back to back
    up_start = np.empty(U, dtype=np.int64)
    fwd_end = np.empty(U, dtype=np.int64)
    up_start[order] = slot_end - 2 * d
    fwd_end[order] = slot_end
    overflow = fwd_end > int(round(interval_s * NS)) + TOLERANCE_NS
    sv = vids[sender]
    uploaded = ~overflow & reach[sender] & bernoulli(p_up, seed, tick, EMP_UP, sv, RELAY_VID, 0)
    in_range = reach[None, :] & (np.arange(C)[None, :] != sender[:, None]) & ~overflow[:, None]
    down = bernoulli(p_down[None, :], seed, tick, EMP_DOWN, sv[:, None], vids[None, :], 0) if U \
        else np.zeros((0, C), dtype=bool)
    delivered = in_range & uploaded[:, None] & down
    return RelayOutcome(up_start, fwd_end, overflow, uploaded, in_range, delivered,
                        int(np.sum(2 * airtime_ns(size_bytes, bandwidth_bps)[~overflow])))
