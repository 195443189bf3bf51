"""Tracking objects across ticks in the world frame (the agent knows its pose exactly).

Nearest-neighbour association with gating on the predicted position, then an
alpha-beta filter on the centroid for velocity. A partial view makes a centroid move
as the visible faces change while the observer drives by, which would give a parked
truck a phantom velocity. So a track counts as moving only if it has left most of the
world cells it occupied ``MOTION_WINDOW`` ticks ago (the cells are on the world
lattice, so the observer's own motion does not matter) and its filtered speed is
above ``STILL_MPS``; otherwise its velocity is zero. Ids are stable for as long as a
track is matched; a track unmatched for ``max_missed`` ticks is dropped.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from vehicle_agent.perception import DetectedObject

GATE_M = 2.5
ALPHA, BETA = 0.6, 0.25
STILL_MPS = 1.0
MOTION_WINDOW = 10  # ticks: an object is moving only if it left most of its cells of 1 s ago
STATIC_OVERLAP = 0.5


@dataclass(slots=True)
class Track:
    track_id: int
    xy: np.ndarray  # filtered centroid, world frame
    velocity: np.ndarray  # m/s, world frame
    t_sim_s: float
    detection: DetectedObject
    hits: int = 1
    missed: int = 0
    filtered_velocity: np.ndarray = field(default_factory=lambda: np.zeros(2))

    @property
    def speed_mps(self) -> float:
        return float(np.hypot(*self.velocity))

    @property
    def heading_rad(self) -> float:
        if self.speed_mps > STILL_MPS:
            return float(np.arctan2(self.velocity[1], self.velocity[0]))
        return self.detection.yaw_rad

    def predict(self, t_sim_s: float) -> np.ndarray:
        return self.xy + self.velocity * (t_sim_s - self.t_sim_s)


@dataclass
class Tracker:
    max_missed: int = 3
    tracks: list[Track] = field(default_factory=list)
    _next_id: int = 0

    _history: deque = field(default_factory=lambda: deque(maxlen=MOTION_WINDOW + 1))

    def update(self, detections: list[DetectedObject], t_sim_s: float) -> list[Track]:
        """Associate this tick's detections; returns the tracks seen this tick, by id."""
        ids = [_cell_ids(d.cells) for d in detections]
        all_ids = np.concatenate(ids) if ids else np.zeros(0, dtype=np.int64)
        self._history.append(np.unique(all_ids))  # sorted: membership is a binary search
        past = self._history[0] if len(self._history) > MOTION_WINDOW else None
        stayed = _share_in(all_ids, np.array([len(i) for i in ids], dtype=np.int64), past)
        centroids = np.array([d.centroid[:2] for d in detections]).reshape(-1, 2)
        predicted = np.array([tr.predict(t_sim_s) for tr in self.tracks]).reshape(-1, 2)
        pairs = _associate(predicted, centroids, GATE_M)
        matched_tracks, matched_dets = set(), set()
        for ti, di in pairs:
            self._correct(self.tracks[ti], detections[di], t_sim_s, None if stayed is None else stayed[di])
            matched_tracks.add(ti)
            matched_dets.add(di)
        for ti, tr in enumerate(self.tracks):
            if ti not in matched_tracks:
                tr.missed += 1
        self.tracks = [tr for tr in self.tracks if tr.missed <= self.max_missed]
        for di, det in enumerate(detections):
            if di not in matched_dets:
                self.tracks.append(Track(self._next_id, det.centroid[:2].copy(), np.zeros(2), t_sim_s, det))
                self._next_id += 1
        return sorted((tr for tr in self.tracks if tr.missed == 0), key=lambda tr: tr.track_id)

    @staticmethod
    def _correct(tr: Track, det: DetectedObject, t_sim_s: float, stayed: float | None) -> None:
        """``stayed``: the share of the detection's cells it also occupied MOTION_WINDOW ago."""
        dt = max(t_sim_s - tr.t_sim_s, 1e-3)
        predicted = tr.xy + tr.filtered_velocity * dt
        residual = det.centroid[:2] - predicted
        tr.xy = predicted + ALPHA * residual
        tr.filtered_velocity = tr.filtered_velocity + (BETA / dt) * residual
        moved = stayed is not None and stayed < STATIC_OVERLAP
        if moved and np.hypot(*tr.filtered_velocity) >= STILL_MPS:
            tr.velocity = tr.filtered_velocity.copy()
        else:
            tr.velocity = np.zeros(2)
        tr.t_sim_s = t_sim_s
        tr.detection = det
        tr.hits += 1
        tr.missed = 0


def _cell_ids(cells: np.ndarray) -> np.ndarray:
    """One int64 per global lattice cell (i, j)."""
    return cells[:, 0].astype(np.int64) * 1_000_003 + cells[:, 1].astype(np.int64)


def _share_in(ids: np.ndarray, counts: np.ndarray, past: np.ndarray | None) -> np.ndarray | None:
    """Per detection (``counts`` consecutive ``ids`` each), the share of its cells in the
    sorted ``past``; None without a past."""
    if past is None:
        return None
    if len(past) == 0 or len(ids) == 0:
        return np.zeros(len(counts))
    pos = np.minimum(np.searchsorted(past, ids), len(past) - 1)
    hit = past[pos] == ids
    owner = np.repeat(np.arange(len(counts)), counts)
    return np.bincount(owner, weights=hit, minlength=len(counts)) / np.maximum(counts, 1)


def _associate(a: np.ndarray, b: np.ndarray, gate: float) -> list[tuple[int, int]]:
    """Greedy nearest pairs within ``gate``, closest first (ties by index)."""
    if len(a) == 0 or len(b) == 0:
        return []
    d = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=2)
    ii, jj = np.nonzero(d <= gate)
    order = np.lexsort((jj, ii, d[ii, jj]))
    used_a, used_b, pairs = set(), set(), []
    for k in order:
        i, j = int(ii[k]), int(jj[k])
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            pairs.append((i, j))
    return pairs
