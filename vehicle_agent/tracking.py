"""Tracking objects across ticks in the world frame (the agent knows its pose exactly).

Each track is a constant-velocity Kalman filter on the object's centroid (state
position and velocity; the x and y axes share one 2x2 covariance, since the noise is
isotropic). A new track starts with its position measured and its velocity unknown
(``INIT_SPEED_SIGMA_MPS``): after two frames the velocity is the finite difference,
after three it is filtered; a car moving 1 m per 0.1 s is estimated at 10 m/s +-1 by
its third frame. Association is greedy nearest-first on the normalised innovation
(Mahalanobis distance), gated at the chi-square 99% bound of two degrees of freedom,
but never narrower than ``GATE_MIN_M`` (a centroid jumps when the visible faces change)
nor wider than ``GATE_MAX_M``; a detection outside every gate starts a new track.

Two objects closer than the segmentation's reach (1.5 m) come out of perception as one
detection: a car passing a waiting truck joins it for as long as they are that close.
Before association, a detection that holds the predicted points of two tracks, one of
them moving, whose predicted cells are not the same, is split between them
(``split_merged``): each point goes to the track whose predicted points are nearest. So
the mover keeps its id and its velocity through the pass, and the truck stands still.

A partial view makes a centroid move as the visible faces change while the observer
drives by, which would give a parked truck a phantom velocity. So a track counts as
moving only when its cells confirm the filter's velocity: the cells it occupied
``lag`` ticks ago, shifted by the filtered velocity times the elapsed time, explain
its cells now better than the same cells unshifted (at least ``EVIDENCE_CELLS`` and
``EVIDENCE_SHARE`` of them more). The lag is the shortest (from ``EVIDENCE_LAG_MIN``
ticks, 0.2 s, so by an object's third frame) over which the shift is at least
``EVIDENCE_SHIFT_M``, two cells: a change of view moves a centroid, but it does not
carry the object's surfaces along. Once moving, a track stays moving while its
filtered speed is at least ``STILL_MPS``; otherwise its velocity is zero. Ids are
stable for as long as a track is matched; a track unmatched for ``max_missed`` ticks
is dropped.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from vehicle_agent.perception import DetectedObject, object_of_points

MEAS_SIGMA_M = 0.3  # centroid noise per axis
ACCEL_SIGMA_MPS2 = 3.0  # white-acceleration process noise
INIT_SPEED_SIGMA_MPS = 15.0  # a new track's velocity: unknown, up to ~50 km/h per axis at 1 sigma
GATE_CHI2 = 9.21  # chi-square, 2 degrees of freedom, 99%
GATE_MIN_M = 2.5  # a car's centroid jumps by up to half its length when its side comes into view
GATE_MAX_M = 4.0
STILL_MPS = 1.0
EVIDENCE_LAG_MIN = 2  # ticks: motion is confirmed by an object's third frame at the earliest
EVIDENCE_SHIFT_M = 0.6  # the filter's shift over the lag tested: three voxels
VOXEL_M = 0.2  # a point persists when the other frame has a point in its voxel or a neighbouring one
EVIDENCE_MARGIN = 0.15  # moved, the old points persist in this larger share than unmoved...
EVIDENCE_MIN_SHARE = 0.5  # ...and in at least this share
EVIDENCE_MIN_POINTS = 30  # of the old detection
_OFFSETS = VOXEL_M * np.array([[a, b] for a in range(-2, 3) for b in range(-2, 3)], dtype=float)  # around the filter's shift
REGISTERED_SIGMA_MPS = 1.0  # a voxel over 0.2 s
REGISTERED_POINTS = 400  # at most about this many old points are registered (every k-th)
HISTORY = 10  # ticks of points kept per track: a mover at STILL_MPS shifts 1 m in 1 s
HELD_SHARE = 0.5  # a track whose predicted points fall this much in a detection's cells is in it
SHARED_CELLS = 0.5  # two tracks sharing this much of their predicted cells are one object, not two
SPLIT_VOXEL_M = 0.25  # a merged detection's points go to the track whose predicted points are nearest, to this
SPLIT_SAMPLE = 256  # at most about this many predicted points a track, for the tests (every k-th)


@dataclass(slots=True)
class Track:
    track_id: int
    xy: np.ndarray  # filtered centroid, world frame
    velocity: np.ndarray  # m/s, world frame: the filtered velocity once moving, else zero
    t_sim_s: float
    detection: DetectedObject
    hits: int = 1
    missed: int = 0
    moving: bool = False
    points_history: deque = field(default_factory=lambda: deque(maxlen=HISTORY))  # (t, points) when matched
    # the filter's state as Python floats: x, y, vx, vy, P00, P01, P10, P11 (None: ``xy`` as
    # first measured, the velocity unknown); the filter reads and writes no array per tick
    kf: tuple[float, float, float, float, float, float, float, float] | None = None

    @property
    def filter_state(self) -> tuple[float, float, float, float, float, float, float, float]:
        if self.kf is None:
            x, y = self.xy.tolist()
            return x, y, 0.0, 0.0, MEAS_SIGMA_M**2, 0.0, 0.0, INIT_SPEED_SIGMA_MPS**2
        return self.kf

    @property
    def filtered_velocity(self) -> np.ndarray:
        return np.array(self.filter_state[2:4])

    @property
    def cov(self) -> np.ndarray:
        """The per-axis covariance of [position, velocity]."""
        p = self.filter_state
        return np.array([[p[4], p[5]], [p[6], p[7]]])

    @property
    def speed_mps(self) -> float:
        return float(np.hypot(*self.velocity))

    @property
    def heading_rad(self) -> float:
        if self.speed_mps > STILL_MPS:
            return float(np.arctan2(self.velocity[1], self.velocity[0]))
        return self.detection.yaw_rad

    def predict(self, t_sim_s: float) -> np.ndarray:
        """Where the filter expects the centroid at ``t_sim_s``."""
        return self.xy + self.filtered_velocity * (t_sim_s - self.t_sim_s)

    def innovation_var(self, t_sim_s: float) -> float:
        """Per-axis variance of the predicted measurement at ``t_sim_s`` (S = H P H^T + R)."""
        return float(_predict_cov(self.cov, t_sim_s - self.t_sim_s)[0, 0] + MEAS_SIGMA_M**2)


def _predicted(tr: Track, t_sim_s: float) -> list[float]:
    """``tr.predict(t_sim_s)`` and ``tr.innovation_var(t_sim_s)`` on Python floats (the
    same sums)."""
    dt = t_sim_s - tr.t_sim_s
    x, y, vx, vy, p00, p01, _, p11 = tr.filter_state
    q = ACCEL_SIGMA_MPS2**2
    return [x + vx * dt, y + vy * dt, p00 + 2 * dt * p01 + dt * dt * p11 + q * dt**4 / 4 + MEAS_SIGMA_M**2]


def _predict_cov(cov: np.ndarray, dt: float) -> np.ndarray:
    """P' = F P F^T + Q for one axis, F = [[1, dt], [0, 1]], Q of white acceleration."""
    a, b, c = _predicted_cov(cov, dt)
    return np.array([[a, b], [b, c]])


def _predicted_cov(cov: np.ndarray, dt: float) -> tuple[float, float, float]:
    """``_predict_cov``'s P'[0, 0], P'[0, 1] (= P'[1, 0]) and P'[1, 1] as Python floats
    (written out: the 2x2 products cost more in numpy calls than in arithmetic)."""
    (p00, p01), (_, p11) = cov.tolist()
    return _predicted_terms(p00, p01, p11, dt)


def _predicted_terms(p00: float, p01: float, p11: float, dt: float) -> tuple[float, float, float]:
    """``_predicted_cov`` of the covariance's terms."""
    q = ACCEL_SIGMA_MPS2**2
    return p00 + 2 * dt * p01 + dt * dt * p11 + q * dt**4 / 4, p01 + dt * p11 + q * dt**3 / 2, p11 + q * dt * dt


@dataclass
class Tracker:
    max_missed: int = 3
    cell_m: float = 0.5  # the detections' lattice (``DetectedObject.cells``)
    tracks: list[Track] = field(default_factory=list)
    _next_id: int = 0

    def update(self, detections: list[DetectedObject], t_sim_s: float) -> list[Track]:
        """Associate this tick's detections, merged ones split first (``split_merged``);
        returns the tracks seen this tick, by id."""
        detections = split_merged(self.tracks, detections, t_sim_s, self.cell_m)
        centroids = np.array([d.centroid[:2] for d in detections]).reshape(-1, 2)
        predicted = np.array([_predicted(tr, t_sim_s) for tr in self.tracks]).reshape(-1, 3)  # and the variance
        pairs = associate(predicted[:, :2], predicted[:, 2], centroids)
        matched_tracks, matched_dets = set(), set()
        for ti, di in pairs:
            self._correct(self.tracks[ti], detections[di], t_sim_s)
            matched_tracks.add(ti)
            matched_dets.add(di)
        for ti, tr in enumerate(self.tracks):
            if ti not in matched_tracks:
                tr.missed += 1
        self.tracks = [tr for tr in self.tracks if tr.missed <= self.max_missed]
        for di, det in enumerate(detections):
            if di not in matched_dets:
                tr = Track(self._next_id, det.centroid[:2].copy(), np.zeros(2), t_sim_s, det)
                tr.kf = tr.filter_state
                tr.points_history.append((t_sim_s, det.points_world))
                self.tracks.append(tr)
                self._next_id += 1
        return sorted((tr for tr in self.tracks if tr.missed == 0), key=lambda tr: tr.track_id)

    def _correct(self, tr: Track, det: DetectedObject, t_sim_s: float) -> None:
        """Kalman update with the detection's centroid, then the motion test on its cells.

        Written out on Python floats, element by element, in the order the 2-vector and
        2 x 2 numpy statements of the filter compute them (K = P H^T S^-1, (I - K H) P):
        the same values, without a numpy call per element (~20 per track and tick)."""
        dt = max(t_sim_s - tr.t_sim_s, 1e-3)
        x, y, vx, vy, p00, p01, _, p11 = tr.filter_state
        a, b, c = _predicted_terms(p00, p01, p11, dt)
        px, py = x + vx * dt, y + vy * dt  # predicted centroid
        cx, cy = det.centroid.tolist()[:2]
        rx, ry = cx - px, cy - py  # residual
        s = a + MEAS_SIGMA_M**2
        g0, g1 = a / s, b / s  # gain = P[:, 0] / S
        x, y = px + g0 * rx, py + g0 * ry
        vx, vy = vx + g1 * rx, vy + g1 * ry
        p00, p01, p10, p11 = a - g0 * a, b - g0 * b, b - g1 * a, c - g1 * b  # P - outer(gain, P[0, :])
        registered, speed = None, np.hypot(vx, vy)
        if speed >= STILL_MPS:
            registered = _registered(tr.points_history, det.points_world, t_sim_s, vx, vy, float(speed))
        if registered is not None:  # a velocity measurement too: H = [0, 1] per axis
            s_v = p11 + REGISTERED_SIGMA_MPS**2
            g0, g1 = p01 / s_v, p11 / s_v  # gain = P[:, 1] / S
            rx, ry = registered
            rx, ry = rx - vx, ry - vy
            x, y = x + g0 * rx, y + g0 * ry
            vx, vy = vx + g1 * rx, vy + g1 * ry
            # P - outer(gain, P[1, :])
            p00, p01, p10, p11 = p00 - g0 * p10, p01 - g0 * p11, p10 - g1 * p10, p11 - g1 * p11
            speed = np.hypot(vx, vy)
        tr.kf = (x, y, vx, vy, p00, p01, p10, p11)
        tr.xy = np.array([x, y])
        tr.moving = speed >= STILL_MPS and (tr.moving or registered is not None)
        tr.velocity = np.array([vx, vy]) if tr.moving else np.zeros(2)
        tr.t_sim_s = t_sim_s
        tr.detection = det
        tr.points_history.append((t_sim_s, det.points_world))
        tr.hits += 1
        tr.missed = 0


def split_merged(tracks: list[Track], detections: list[DetectedObject], t_sim_s: float,
                 cell_m: float) -> list[DetectedObject]:
    """``detections`` with each one that holds two or more objects cut into one part per
    object. A detection holds a track when ``HELD_SHARE`` of the track's predicted points
    (its last points, moved by its velocity to ``t_sim_s``) fall in the detection's cells.
    It is cut when it holds a moving track and another track whose predicted cells are
    not the mover's (less than ``SHARED_CELLS`` of either's in common: two tracks of one
    object, such as a lost track and its successor, leave it whole); each point goes to
    the track whose predicted points are nearest (``_nearest_owner``) and each part with
    points becomes a detection, in the merged one's place. Only detections whose boxes
    come near a mover's and another track's are tested."""
    movers = [k for k, tr in enumerate(tracks) if tr.moving]
    if not movers or not detections:
        return detections
    centre = np.array([_predicted(tr, t_sim_s)[:2] for tr in tracks])
    reach = np.array([np.hypot(tr.detection.length_m, tr.detection.width_m) / 2 + 1.0 for tr in tracks])
    det_xy = np.array([d.centroid[:2] for d in detections])
    det_reach = np.array([np.hypot(d.length_m, d.width_m) / 2 for d in detections])
    gap = np.hypot(*(det_xy[:, None, :] - centre[None, :, :]).transpose(2, 0, 1)) - det_reach[:, None] - reach[None, :]
    near_mover = (gap[:, movers] <= 0.0).any(axis=1) & (np.count_nonzero(gap <= 0.0, axis=1) >= 2)  # and another
    if not near_mover.any():
        return detections
    cache: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def predicted(k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Track k's predicted points, every k-th of them (``SPLIT_SAMPLE``) and their cells."""
        if k not in cache:
            xy = _predicted_points(tracks[k], t_sim_s)
            sample = np.ascontiguousarray(xy[:: max(len(xy) // SPLIT_SAMPLE, 1)])
            cache[k] = xy, sample, np.floor(sample / cell_m).astype(np.int64)
        return cache[k]

    out: list[DetectedObject] = []
    for d, det in enumerate(detections):
        held = _held(det, [k for k in movers if gap[d, k] <= 0.0], np.flatnonzero(gap[d] <= 0.0).tolist(),
                     predicted, cell_m) if near_mover[d] else None
        if held is None:
            out.append(det)
            continue
        seeds = [predicted(k)[0] for k in held]
        owner = _nearest_owner(det.points_world[:, :2].astype(np.float64), np.concatenate(seeds),
                               np.repeat(np.arange(len(held)), [len(x) for x in seeds]), SPLIT_VOXEL_M)
        parts = [det.points_world[owner == o] for o in range(len(held))]
        if sum(len(part) > 0 for part in parts) < 2:
            out.append(det)
            continue
        out += [object_of_points(part, cell_m) for part in parts if len(part)]
    return out


def _predicted_points(tr: Track, t_sim_s: float) -> np.ndarray:
    """(n, 2) float64: the track's last points where its velocity takes them at ``t_sim_s``."""
    return tr.detection.points_world[:, :2].astype(np.float64) + tr.velocity * (t_sim_s - tr.t_sim_s)


def _held(det: DetectedObject, movers: list[int], near: list[int], predicted, cell_m: float) -> list[int] | None:
    """The tracks (indices) ``det`` holds, a mover first, if it holds a mover and another
    object; ``movers`` and ``near`` the candidates, ``predicted(k)`` track k's points, a
    sample of them and the sample's cells."""
    def holds(k: int) -> bool:
        sample = predicted(k)[1]
        return len(sample) > 0 and _share_in(det.cells, sample, cell_m) >= HELD_SHARE

    def one_object(k: int, h: int) -> bool:  # their cells share SHARED_CELLS of either's
        (_, a, a_cells), (_, b, b_cells) = predicted(k), predicted(h)
        return _share_in(b_cells, a, cell_m) >= SHARED_CELLS or _share_in(a_cells, b, cell_m) >= SHARED_CELLS

    mover = next((k for k in movers if holds(k)), None)
    if mover is None:
        return None
    held = [mover]
    for k in near:
        if k != mover and holds(k) and not any(one_object(k, h) for h in held):
            held.append(k)
    return held if len(held) >= 2 else None


@njit(cache=True)
def _share_in(cells, xy, cell_m):
    """The share of points ``xy`` (n >= 1, 2) whose lattice cell (``floor(xy / cell_m)``)
    is one of ``cells`` (m, 2); 0.0 without cells."""
    if cells.shape[0] == 0:
        return 0.0
    i_lo, i_hi, j_lo, j_hi = cells[:, 0].min(), cells[:, 0].max(), cells[:, 1].min(), cells[:, 1].max()
    mark = np.zeros((i_hi - i_lo + 1, j_hi - j_lo + 1), dtype=np.bool_)
    for c in range(cells.shape[0]):
        mark[cells[c, 0] - i_lo, cells[c, 1] - j_lo] = True
    hit = 0
    for p in range(xy.shape[0]):
        i = np.int64(np.floor(xy[p, 0] / cell_m)) - i_lo
        j = np.int64(np.floor(xy[p, 1] / cell_m)) - j_lo
        if 0 <= i < mark.shape[0] and 0 <= j < mark.shape[1] and mark[i, j]:
            hit += 1
    return hit / xy.shape[0]


@njit(cache=True)
def _nearest_owner(xy, seeds, seed_owner, voxel):
    """(n,) int64: for each point of ``xy``, the owner of the nearest seed, the distance
    taken on a ``voxel`` lattice over the points' box (8-connected steps from each seed's
    voxel, breadth first: ties go to the seed listed first). Seeds outside the box
    are left out; with none inside, every point gets -1."""
    n = xy.shape[0]
    out = np.full(n, -1, dtype=np.int64)
    if n == 0:
        return out
    lo_x, lo_y = xy[:, 0].min() - voxel, xy[:, 1].min() - voxel
    nx = int(np.floor((xy[:, 0].max() - lo_x) / voxel)) + 2
    ny = int(np.floor((xy[:, 1].max() - lo_y) / voxel)) + 2
    label = np.full(nx * ny, -1, dtype=np.int64)
    queue = np.empty(nx * ny, dtype=np.int64)
    head, tail = 0, 0
    for s in range(seeds.shape[0]):
        i = int(np.floor((seeds[s, 0] - lo_x) / voxel))
        j = int(np.floor((seeds[s, 1] - lo_y) / voxel))
        if 0 <= i < nx and 0 <= j < ny and label[j * nx + i] == -1:
            label[j * nx + i] = seed_owner[s]
            queue[tail] = j * nx + i
            tail += 1
    while head < tail:
        c = queue[head]
        head += 1
        i, j = c % nx, c // nx
        for dj in range(-1, 2):
            for di in range(-1, 2):
                a, b = i + di, j + dj
                if 0 <= a < nx and 0 <= b < ny and label[b * nx + a] == -1:
                    label[b * nx + a] = label[c]
                    queue[tail] = b * nx + a
                    tail += 1
    for p in range(n):
        i = int(np.floor((xy[p, 0] - lo_x) / voxel))
        j = int(np.floor((xy[p, 1] - lo_y) / voxel))
        out[p] = label[j * nx + i]
    return out


def warm_kernels() -> None:
    """Load the kernels of ``split_merged`` (they run only when a mover passes close by
    another object, so a warm-up scene never reaches them): the nearest-owner labelling
    and a part's box (``object_of_points``)."""
    xy = np.zeros((1, 2))
    _nearest_owner(xy, xy, np.zeros(1, dtype=np.int64), SPLIT_VOXEL_M)
    _share_in(np.zeros((1, 2), dtype=np.int64), xy, 0.5)
    object_of_points(np.zeros((1, 3), dtype=np.float32), 0.5)


def registered_velocity(history, now: np.ndarray, t_sim_s: float, velocity: np.ndarray) -> np.ndarray | None:
    """The velocity that carries the points of ``lag`` matches ago onto the points
    ``now``, if moving them explains ``now`` better than leaving them (None otherwise).

    A parked object seen from a new place shows new faces, but its old faces stay where
    they were; a mover carries them along. The moved hypothesis takes the best shift
    within two voxels per axis of the filter's (the filter follows a centroid, which
    also moves as the visible faces change); it must keep EVIDENCE_MIN_SHARE of the old
    points and EVIDENCE_MARGIN more than no shift at all. ``history`` holds (t, world
    points) per past match, oldest first; the lag is the shortest of at least
    EVIDENCE_LAG_MIN matches over which the filter's shift reaches EVIDENCE_SHIFT_M.
    """
    vx, vy = np.asarray(velocity, dtype=np.float64).tolist()
    registered = _registered(history, now, t_sim_s, vx, vy, float(np.hypot(*velocity)))
    return None if registered is None else np.array(registered)


def _registered(history, now: np.ndarray, t_sim_s: float, vx: float, vy: float,
                speed: float) -> tuple[float, float] | None:
    """``registered_velocity`` of the velocity (vx, vy), its norm ``speed``, as Python floats."""
    for back in range(EVIDENCE_LAG_MIN, len(history) + 1):
        t_old, old = history[-back]
        age = t_sim_s - t_old
        if speed * age < EVIDENCE_SHIFT_M:
            continue
        if len(old) < EVIDENCE_MIN_POINTS:  # too sparse (far away) to tell a change of view from a move
            return None
        now = np.ascontiguousarray(now)  # float32 as detected: the kernel widens each coordinate exactly
        found, rx, ry = _registration(old, max(len(old) // REGISTERED_POINTS, 1), now, vx, vy,
                                      age, _OFFSETS, VOXEL_M, EVIDENCE_MIN_SHARE, EVIDENCE_MARGIN)
        return (rx, ry) if found else None
    return None


@njit(cache=True)
def _registration(old, step, now, vx, vy, age, offsets, voxel, min_share, margin):
    """``registered_velocity``'s test over the lag ``age``, of every ``step``-th old point:
    the shifts (unmoved, then (vx, vy) * age plus each of ``offsets``), their shares
    (``_persisting``), and whether the best moved one wins: (found, the velocity it
    gives). Replaces half a dozen numpy calls on 26 shifts per mover and tick."""
    shifts = np.empty((offsets.shape[0] + 1, 2))
    shifts[0, 0], shifts[0, 1] = 0.0, 0.0
    sx, sy = vx * age, vy * age
    for o in range(offsets.shape[0]):
        shifts[o + 1, 0], shifts[o + 1, 1] = sx + offsets[o, 0], sy + offsets[o, 1]
    shares = _persisting(np.ascontiguousarray(old[::step]), now, shifts, voxel)
    best = 1  # the first of the largest moved shares
    for s in range(2, len(shares)):
        if shares[s] > shares[best]:
            best = s
    if shares[best] >= min_share and shares[best] - shares[0] >= margin:
        return True, shifts[best, 0] / age, shifts[best, 1] / age
    return False, 0.0, 0.0


@njit(cache=True)
def _persisting(old, now, shifts, voxel):
    """(S,) per shift (dx, dy): the share of the ``old`` points, shifted, that have a
    point of ``now`` in their voxel or a neighbouring one (3-D, edge ``voxel``).
    Float32 points are widened to float64 before any arithmetic, as numpy's astype
    would: the same shares.

    Written for speed (a near car has thousands of points; 175 -> 50 us a tick at 40
    vehicles): each division in a loop without branches, which the compiler
    vectorises; the window's corner as the least voxel (floor and division keep
    order); a voxel column (x, y) holds its occupied heights as the bits of words, so a
    point sets one bit and the neighbours are shifts and ors of words; each old point's
    column under each distinct dx (row under each dy) computed once, not per shift."""
    n_shift = shifts.shape[0]
    out = np.zeros(n_shift)
    if old.shape[0] == 0 or now.shape[0] == 0:
        return out
    vox = _voxels_of(now, voxel)
    lo = np.empty(3, dtype=np.int64)
    hi = np.empty(3, dtype=np.int64)
    for a in range(3):
        lo[a] = vox[:, a].min() - 1
        hi[a] = vox[:, a].max() + 1
    nx, ny, nz = hi[0] - lo[0] + 1, hi[1] - lo[1] + 1, hi[2] - lo[2] + 1
    nw = (nz + 63) // 64  # 64-bit words per column
    one, top = np.uint64(1), np.uint64(63)
    seen = np.zeros((nx, ny, nw), dtype=np.uint64)  # the voxels of ``now``: 1 <= i < nx - 1, alike j, k
    for p in range(now.shape[0]):
        i, j, k = vox[p, 0] - lo[0], vox[p, 1] - lo[1], vox[p, 2] - lo[2]
        seen[i, j, k >> 6] |= one << np.uint64(k & 63)
    occ = np.zeros((nx, ny, nw), dtype=np.uint64)  # ``seen`` grown by one voxel along every axis
    for i in range(1, nx - 1):
        for j in range(1, ny - 1):
            for w in range(nw):
                m = seen[i, j, w]
                grown = m | (m << one) | (m >> one)
                if w > 0:
                    grown |= seen[i, j, w - 1] >> top
                if w + 1 < nw:
                    grown |= seen[i, j, w + 1] << top
                if grown == 0:
                    continue
                for a in range(-1, 2):
                    for b in range(-1, 2):
                        occ[i + a, j + b, w] |= grown
    ks = _voxels_of(old, voxel)[:, 2] - lo[2]  # the height's voxel: no shift moves it
    ii, x_of = _voxels_under(old[:, 0].copy(), shifts[:, 0], voxel, lo[0])
    jj, y_of = _voxels_under(old[:, 1].copy(), shifts[:, 1], voxel, lo[1])
    for s in range(n_shift):
        hit = 0
        ci, cj = ii[x_of[s]], jj[y_of[s]]
        for p in range(old.shape[0]):
            i, j, k = ci[p], cj[p], ks[p]
            if 0 <= k < nz and 0 <= i < nx and 0 <= j < ny and (occ[i, j, k >> 6] >> np.uint64(k & 63)) & one:
                hit += 1
        out[s] = hit / old.shape[0]
    return out


@njit(cache=True)
def _voxels_of(points, voxel):
    """(P, 3) int64 voxel of each point, ``floor(p / voxel)`` (float32 widened first)."""
    flat = np.ascontiguousarray(points).ravel()
    vox = np.empty(len(flat), dtype=np.int64)
    for q in range(len(flat)):  # one flat loop: the compiler vectorises it
        vox[q] = np.int64(np.floor(np.float64(flat[q]) / voxel))
    return vox.reshape(points.shape[0], 3)


@njit(cache=True)
def _voxels_under(coord, shift, voxel, lo):
    """``floor((coord + shift[s]) / voxel) - lo`` per point for each distinct value of
    ``shift`` (row d of the first result), and the row of each shift: (int64 (D, P), (S,))."""
    distinct = np.empty(len(shift))
    row = np.empty(len(shift), dtype=np.int64)
    n = 0
    for s in range(len(shift)):
        row[s] = -1
        for d in range(n):
            if distinct[d] == shift[s]:
                row[s] = d
                break
        if row[s] < 0:
            distinct[n] = shift[s]
            row[s] = n
            n += 1
    out = np.empty((n, len(coord)), dtype=np.int64)
    for d in range(n):
        for p in range(len(coord)):
            out[d, p] = np.int64(np.floor((np.float64(coord[p]) + distinct[d]) / voxel)) - lo
    return out, row


def associate(predicted: np.ndarray, variance: np.ndarray, measured: np.ndarray) -> list[tuple[int, int]]:
    """Greedy pairs (track, detection), smallest Mahalanobis distance first (ties by
    index), each within its track's gate: d^2 = |z - z_pred|^2 / S <= GATE_CHI2, the
    gate's radius clipped to [GATE_MIN_M, GATE_MAX_M]."""
    if len(predicted) == 0 or len(measured) == 0:
        return []
    pairs = _greedy_pairs(np.ascontiguousarray(predicted, dtype=np.float64),
                          np.ascontiguousarray(variance, dtype=np.float64),
                          np.ascontiguousarray(measured, dtype=np.float64), GATE_CHI2, GATE_MIN_M, GATE_MAX_M)
    return [(i, j) for i, j in pairs.tolist()]


@njit(cache=True)
def _greedy_pairs(predicted, variance, measured, chi2, r_min, r_max):
    """``associate``'s pairs as an int64 (m, 2) array, in the order chosen. Replaces a
    dozen numpy calls on a few tracks (norm, clip, lexsort, ...) with the same
    arithmetic: the distance as the square root of dx^2 + dy^2, the candidates in (track,
    detection) order sorted stably by d^2."""
    n_t, n_d = predicted.shape[0], measured.shape[0]
    cand_i = np.empty(n_t * n_d, dtype=np.int64)
    cand_j = np.empty(n_t * n_d, dtype=np.int64)
    d2 = np.empty(n_t * n_d)
    m = 0
    for i in range(n_t):
        radius = min(max(np.sqrt(chi2 * variance[i]), r_min), r_max)
        var = max(variance[i], 1e-9)
        for j in range(n_d):
            dx, dy = predicted[i, 0] - measured[j, 0], predicted[i, 1] - measured[j, 1]
            dist = np.sqrt(dx * dx + dy * dy)
            if dist <= radius:
                cand_i[m], cand_j[m], d2[m] = i, j, dist * dist / var
                m += 1
    order = np.argsort(d2[:m], kind="mergesort")
    used_t = np.zeros(n_t, dtype=np.bool_)
    used_d = np.zeros(n_d, dtype=np.bool_)
    pairs = np.empty((min(n_t, n_d), 2), dtype=np.int64)
    k = 0
    for o in order:
        i, j = cand_i[o], cand_j[o]
        if not used_t[i] and not used_d[j]:
            used_t[i] = used_d[j] = True
            pairs[k, 0], pairs[k, 1] = i, j
            k += 1
    return pairs[:k]
