"""The agent's data plane for one decision interval, stage by stage.

perceive (grid, components, tracking) -> reason (visibility, relevance) -> control
message -> payloads of its objects -> fuse what others sent. Every stage is a method
over plain arrays, timed into ``timings_ms`` for the perception bench.
"""

from __future__ import annotations

import time
from collections import deque
from itertools import accumulate
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numba import njit

from protocol.codec import MalformedMessage
from protocol.messages import DEFAULT_DOMAIN, ControlMsg, MapMsg, Mission, ObjectMap, Pose, Scan
from protocol.model import OURS, Model
from vehicle_agent.agreement import HeardControl
from vehicle_agent.domains import GUARD_BAND_M, DomainTable
from vehicle_agent.paths import arc_lengths, progress_along
from vehicle_agent.frames import check_fits, ray_tables, scan_to_world, world_to_sensor
from vehicle_agent.fusion import MAX_AGE_S, FusedGrid, ReceivedStore, SharedBatch, SharedObject, fused_now
from vehicle_agent.payload import (BYTES_PER_POINT, column_thinned, decode_objects, encode_objects,
                                   encode_world_objects, payload_size)
from vehicle_agent.perception import (DrivableRaster, Grid, GridSpec, build_grid, extract_objects, scan_grid,
                                      scan_objects)
from vehicle_agent.spatial import match_vehicles, relevance, visible
from vehicle_agent.tracking import STILL_MPS, Track, Tracker

DOMAIN_CENTER_XY = (DEFAULT_DOMAIN.x_m, DEFAULT_DOMAIN.y_m)  # a map's domain when it declares none
DOMAIN_RADIUS_M = DEFAULT_DOMAIN.radius_m  # R/2, R ~ 170 m urban LTE-Direct (paper 4.1)
TRAJECTORY_HORIZON_S = 8.0  # as far as others judge relevance (spatial.HORIZON_S)
TRAJECTORY_STEP_S = 1.0  # the shared trajectory is down-sampled to 1 s segments
DEFAULT_DIMS = (4.5, 1.8)  # a car, for other vehicles' bodies


@dataclass(frozen=True, slots=True)
class View:
    """What the agent perceived this tick."""

    tick: int
    t_sim_s: float
    pose: Pose
    grid: Grid
    tracks: list[Track]


@dataclass(frozen=True, slots=True)
class Neighbors:
    """Other vehicles as their latest control messages say they are now, as arrays: row
    i is vehicle ``vid[i]``, its trajectory ``waypoints[starts[i]:starts[i + 1]]``."""

    vid: np.ndarray  # int64 (n,), ascending
    xy: np.ndarray  # float64 (n, 2)
    waypoints: np.ndarray  # float64 (P, 3) [x, y, t], every trajectory, waypoints already passed evicted
    starts: np.ndarray  # int64 (n + 1,)
    fresh: np.ndarray  # bool (n,): its control message arrived this interval

    @staticmethod
    def none() -> Neighbors:
        return Neighbors(np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 3)), np.zeros(1, np.int64),
                         np.zeros(0, bool))

    def __len__(self) -> int:
        return len(self.vid)

    def trajectory(self, i: int) -> np.ndarray:
        return self.waypoints[self.starts[i]:self.starts[i + 1]]

    def in_domain(self, center: np.ndarray | None = None, limit_m: np.ndarray | None = None) -> Neighbors:
        """``self.take(in_domain(self.xy))`` in one kernel call (``_take_in_domain``): the
        rows within ``limit_m[d]`` of ``center[d]`` for some domain d (default: the one
        default domain and its guard band)."""
        if center is None:
            center = np.array([DOMAIN_CENTER_XY], dtype=np.float64)
            limit_m = np.array([DOMAIN_RADIUS_M + GUARD_BAND_M])
        whole, vid, xy, waypoints, starts, fresh = _take_in_domain(
            self.vid, self.xy, self.waypoints, self.starts, self.fresh, center, limit_m)
        return self if whole else Neighbors(vid, xy, waypoints, starts, fresh)

    def take(self, keep: np.ndarray) -> Neighbors:
        """The rows where ``keep`` (bool (n,)) holds, in order."""
        if keep.all():  # every neighbour in the domain
            return self
        waypoints, starts = _take_packed(self.waypoints, self.starts, keep)
        return Neighbors(self.vid[keep], self.xy[keep], waypoints, starts, self.fresh[keep])


@dataclass
class NeighborTable:
    """Latest control message per vehicle (whole, or as the ``HeardControl`` that carries
    its motion); stale ones are aged (paper 4.1, loss compensation)."""

    max_age_s: float = 2.0
    last: dict[int, ControlMsg | HeardControl] = field(default_factory=dict)

    def update(self, msgs: Sequence[ControlMsg | HeardControl]) -> None:
        for m in msgs:
            prev = self.last.get(m.vid)
            if prev is None or m.tick >= prev.tick:
                self.last[m.vid] = m

    def current(self, t_now_s: float, exclude: int) -> Neighbors:
        """Every vehicle heard from within ``max_age_s`` but ``exclude``. A fresh message
        (or one of fewer than two waypoints) stands for its pose and trajectory as sent;
        an older one for where its trajectory puts the vehicle now (np.interp's clamping
        and formula) and the rest of it (``_place``). At 40 vehicles a vehicle places 39
        every interval, all of them a tick old when it writes its control message."""
        vids, poses, sent, trajs = [], [], [], []
        for vid in sorted(self.last):
            m = self.last[vid]
            if vid == exclude or t_now_s - m.t_sim_s > self.max_age_s:
                continue
            vids.append(vid)
            poses.append((m.pose.x_m, m.pose.y_m))
            sent.append(m.t_sim_s)
            trajs.append(m.trajectory)
        if not vids:
            return Neighbors.none()
        starts = np.fromiter(accumulate(map(len, trajs), initial=0), dtype=np.int64, count=len(trajs) + 1)
        fresh = np.array(sent, dtype=np.float64) >= t_now_s - 1e-9
        # concatenated in their own dtype, then widened: the same values (float32 and float64 alike)
        xy, waypoints, placed_starts = _place(np.concatenate(trajs).astype(np.float64, copy=False).reshape(-1, 3),
                                              starts, np.array(poses, dtype=np.float64), fresh, float(t_now_s))
        return Neighbors(np.array(vids, dtype=np.int64), xy, waypoints, placed_starts, fresh)


@njit(cache=True)
def _take_in_domain(vid, xy, waypoints, starts, fresh, center, limit):
    """``in_domain`` (np.hypot of the offsets from a centre ``center[d]``, within
    ``limit[d]``, for some d) of every row, and whether all are; if not, the rows kept
    (``Neighbors.take``'s arrays)."""
    keep = np.zeros(len(vid), dtype=np.bool_)
    for i in range(len(vid)):
        for d in range(len(limit)):
            if np.hypot(xy[i, 0] - center[d, 0], xy[i, 1] - center[d, 1]) <= limit[d]:
                keep[i] = True
                break
    n = keep.sum()
    if n == len(vid):
        return True, vid, xy, waypoints, starts, fresh
    out_vid, out_xy, out_fresh = np.empty(n, dtype=vid.dtype), np.empty((n, 2), dtype=xy.dtype), np.empty(n, np.bool_)
    j = 0
    for i in range(len(vid)):
        if keep[i]:
            out_vid[j], out_xy[j, 0], out_xy[j, 1], out_fresh[j] = vid[i], xy[i, 0], xy[i, 1], fresh[i]
            j += 1
    out_wp, out_starts = _take_packed(waypoints, starts, keep)
    return False, out_vid, out_xy, out_wp, out_starts, out_fresh


@njit(cache=True)
def _take_packed(waypoints, starts, keep):
    """The packed trajectories (waypoints, starts) of the rows where ``keep`` holds."""
    out_starts = np.zeros(int(keep.sum()) + 1, dtype=np.int64)
    j = 0
    for i in range(len(keep)):
        if keep[i]:
            out_starts[j + 1] = out_starts[j] + starts[i + 1] - starts[i]
            j += 1
    out = np.empty((out_starts[j], 3))
    j = 0
    for i in range(len(keep)):
        if keep[i]:
            out[out_starts[j]:out_starts[j + 1]] = waypoints[starts[i]:starts[i + 1]]
            j += 1
    return out, out_starts


@njit(cache=True)
def _place(waypoints, starts, pose_xy, fresh, t_now_s):
    """Each vehicle ``i`` (trajectory ``waypoints[starts[i]:starts[i + 1]]``) now: where
    it is (xy (n, 2)) and its trajectory from there, packed (waypoints, starts). A fresh
    one, or one of fewer than two waypoints, as sent (at ``pose_xy[i]``); an older one
    placed along its trajectory at ``t_now_s`` with np.interp's clamping and formula, its
    waypoints at or before ``t_now_s`` dropped for that point. The first waypoint after
    ``t_now_s`` is found as np.searchsorted(side="right") finds it, NaN times sorting last
    (``t_now_s``, the world's clock, is never NaN)."""
    n = len(starts) - 1
    xy = np.empty((n, 2))
    first = np.full(n, -1, dtype=np.int64)  # -1: as sent; else the first waypoint after now
    out_starts = np.zeros(n + 1, dtype=np.int64)
    for i in range(n):
        a, b = starts[i], starts[i + 1]
        if fresh[i] or b - a < 2:
            xy[i, 0], xy[i, 1] = pose_xy[i, 0], pose_xy[i, 1]
            out_starts[i + 1] = out_starts[i] + b - a
            continue
        lo, hi = 0, b - a
        while lo < hi:
            mid = lo + ((hi - lo) >> 1)
            v = waypoints[a + mid, 2]
            if t_now_s < v or v != v:
                hi = mid
            else:
                lo = mid + 1
        first[i] = lo
        if lo == b - a:  # past its last waypoint: held there
            xy[i, 0], xy[i, 1] = waypoints[b - 1, 0], waypoints[b - 1, 1]
            out_starts[i + 1] = out_starts[i] + 1
            continue
        if lo == 0:
            xy[i, 0], xy[i, 1] = waypoints[a, 0], waypoints[a, 1]
        else:
            p, q = a + lo - 1, a + lo
            dt = waypoints[q, 2] - waypoints[p, 2]
            for c in range(2):
                slope = (waypoints[q, c] - waypoints[p, c]) / dt
                xy[i, c] = slope * (t_now_s - waypoints[p, 2]) + waypoints[p, c]
        out_starts[i + 1] = out_starts[i] + b - a - lo + 1
    out = np.empty((out_starts[n], 3))
    for i in range(n):
        a, b, o = starts[i], starts[i + 1], out_starts[i]
        if first[i] < 0:
            out[o:o + b - a] = waypoints[a:b]
        elif first[i] == b - a:
            out[o] = waypoints[b - 1]
        else:
            out[o, 0], out[o, 1], out[o, 2] = xy[i, 0], xy[i, 1], t_now_s
            out[o + 1:out_starts[i + 1]] = waypoints[a + first[i]:b]
    return xy, out, out_starts


def in_domain(xy: np.ndarray) -> np.ndarray:
    """Whether each position is within the default domain and its guard band."""
    return np.hypot(xy[..., 0] - DOMAIN_CENTER_XY[0], xy[..., 1] - DOMAIN_CENTER_XY[1]) <= DOMAIN_RADIUS_M + GUARD_BAND_M


def lane_trajectory(route: np.ndarray, pose: Pose, speed_mps: float, t_now_s: float) -> np.ndarray:
    """Waypoints [x, y, t] every TRAJECTORY_STEP_S along the route at ``speed_mps``."""
    s0 = progress_along(route, np.array([pose.x_m, pose.y_m]))
    times = np.arange(0.0, TRAJECTORY_HORIZON_S + 1e-9, TRAJECTORY_STEP_S)
    cum = arc_lengths(route)
    s = np.clip(s0 + speed_mps * times, 0.0, cum[-1])
    xs = np.interp(s, cum, route[:, 0])
    ys = np.interp(s, cum, route[:, 1])
    xs[0], ys[0] = pose.x_m, pose.y_m  # the first waypoint is the current pose
    return np.stack([xs, ys, t_now_s + times], axis=1).astype(np.float32)


class DataPlane:
    def __init__(self, mission: Mission, mapmsg: MapMsg, grid_spec: GridSpec | None = None,
                 relevance_mode: str = "bool", model: Model = OURS) -> None:
        """``model``: what an object's shared points are, their bytes on the air and how
        long a received object is held (``protocol.model``)."""
        self.mission = mission
        self.model = model
        self.spec = grid_spec or GridSpec()
        self.mount_m = mission.lidar.mount_height_m
        self.raster = DrivableRaster(mapmsg.drivable, self.spec.cell_m)
        self.buildings = _box_corners(np.asarray(mapmsg.buildings, dtype=np.float64).reshape(-1, 6))
        self.tracker = Tracker(cell_m=self.spec.cell_m)
        self.lanes = LaneDirections(mapmsg.lanes)
        self.received = ReceivedStore(max_age_s=model.hold_s)
        self.neighbors = NeighborTable()
        self.domains = DomainTable.of(mapmsg)
        self.relevance_mode = relevance_mode
        self.timings_ms: dict[str, float] = {}
        self.shared_batch = SharedBatch.of([])  # this interval's received objects, placed, ourselves excluded
        self._offered_cache: tuple[View, np.ndarray | None, np.ndarray] | None = None
        self._recent_poses: deque[Pose] = deque(maxlen=int(round(MAX_AGE_S / mission.decision_interval_s)) + 1)

    def _timed(self, stage: str) -> _Timed:
        return _Timed(self.timings_ms, stage)

    # ----------------------------------------------------------------- perceive

    def perceive(self, scan: Scan, extra_world: np.ndarray | None = None) -> View:
        """Perceive this tick's scan; ``extra_world`` are points (world x, y, height) others
        sent as raw point clouds (the EMP baseline), perceived as if our own."""
        self.timings_ms = {}
        if extra_world is not None and len(extra_world):
            with self._timed("grid"):
                world = np.concatenate([scan_to_world(scan, self.mission.lidar), extra_world[:, :3]])
                grid, cell_idx = build_grid(world, (scan.pose.x_m, scan.pose.y_m), self.spec, self.raster)
            with self._timed("components"):
                detections = extract_objects(world, grid, cell_idx, (scan.pose.x_m, scan.pose.y_m))
        else:  # the same grid and objects from the range image, without the scan's world points
            lidar, pose = self.mission.lidar, (scan.pose.x_m, scan.pose.y_m, scan.pose.yaw_rad)
            check_fits(scan, lidar)
            tables = ray_tables(lidar)
            with self._timed("grid"):
                grid, binned = scan_grid(scan.range_cm, tables, pose, self.mount_m, self.spec, self.raster)
            with self._timed("components"):
                detections = scan_objects(scan.range_cm, tables, pose, self.mount_m, grid, binned)
        with self._timed("tracking"):
            tracks = self.tracker.update(detections, scan.t_sim_s)
            self.lanes.snap(tracks)
        return View(scan.tick, scan.t_sim_s, scan.pose, grid, tracks)

    # ----------------------------------------------------------------- reason

    def object_map(self, view: View, neighbors: Neighbors, domains: tuple[int, ...] = (0,)) -> ObjectMap:
        """v and r of every tracked object for every other vehicle of the ``domains``. The
        tracks' fields are gathered once, and the footprints (``corners_of``'s), the
        own body (``_box_corners``'), the vehicles' own objects (``match_vehicles``) and
        the objects' dims and headings (``Track.heading_rad``) are worked out from them
        with the same operations, in a few calls instead of a few per track."""
        tracks = view.tracks
        rows = list(domains)
        receivers = neighbors.in_domain(self.domains.center[rows], self.domains.limit_m[rows])
        dets = [t.detection for t in tracks]
        ids = np.array([t.track_id for t in tracks], dtype=np.int64)
        sizes = payload_size(self._offered(view)[1], self.model.bytes_per_point)
        centroids = np.array([t.xy for t in tracks], dtype=np.float64).reshape(-1, 2)
        viewers = receivers.xy
        with self._timed("visibility"):
            yaw = np.array([d.yaw_rad for d in dets], dtype=np.float64)
            extent = np.array([(d.length_m, d.width_m) for d in dets], dtype=np.float64).reshape(-1, 2)
            targets = _footprints(yaw, extent, np.array([d.centroid[:2] for d in dets], dtype=np.float64))
            pose = view.pose
            own = _body_corners(pose.x_m, pose.y_m, pose.yaw_rad, self.mission.spec.length_m,
                                self.mission.spec.width_m)
            occluders = np.concatenate([targets, own, self.buildings])
            vis = visible(viewers, np.full(len(viewers), self.mission.lidar.range_m), targets, occluders,
                          np.arange(len(tracks)), match_vehicles(viewers, centroids))
        with self._timed("relevance"):
            vel = np.array([t.velocity for t in tracks], dtype=np.float64).reshape(-1, 2)
            dims = _object_dims(extent)
            # Track.heading_rad: the direction of motion (np.arctan2, as there) when moving
            heading = np.where(np.hypot(vel[:, 0], vel[:, 1]) > STILL_MPS, np.arctan2(vel[:, 1], vel[:, 0]), yaw)
            dims_j = np.empty((len(receivers), 2))
            dims_j[:] = DEFAULT_DIMS
            rel = relevance(receivers.waypoints, dims_j, centroids, vel, dims, view.t_sim_s, mode=self.relevance_mode,
                            obj_heading=heading, starts=receivers.starts)
        return ObjectMap(ids, sizes, centroids.astype(np.float32),
                         receivers.vid,
                         np.ascontiguousarray(vis.T), np.ascontiguousarray(rel.T))

    def control_message(self, view: View, scan: Scan, trajectory: np.ndarray, heard: list[int],
                        unscheduled: Mapping[int, int] | None = None) -> ControlMsg:
        """``unscheduled``: the starvation counter m of each object id (0 if absent),
        from ``agreement.unscheduled_after`` on the previous interval. The message of
        the vehicle's first domain; ``control_messages`` gives one per domain."""
        domain = self.domains.membership(view.pose.x_m, view.pose.y_m)[0]
        return self.control_messages(view, scan, trajectory, {domain: heard}, {domain: unscheduled or {}},
                                     (domain,))[domain]

    def control_messages(self, view: View, scan: Scan, trajectory: np.ndarray, heard: Mapping[int, list[int]],
                         unscheduled: Mapping[int, Mapping[int, int]], domains: tuple[int, ...]
                         ) -> dict[int, ControlMsg]:
        """This vehicle's control message in each of ``domains``: the object map is
        worked out once for every receiver of any of them, and each domain's message
        keeps the receivers of that domain; ``heard[d]`` and ``unscheduled[d]`` are the
        vehicle's ballot and starvation counters in domain d. In a map of one domain
        the message names no domains (``ControlMsg.domains`` empty)."""
        neighbors = self.neighbors.current(view.t_sim_s, exclude=self.mission.vid)
        whole = self.object_map(view, neighbors, domains)
        named = np.array(domains if len(self.domains) > 1 else (), dtype=np.int64)
        out = {}
        for d in domains:
            objects = whole
            if len(domains) > 1:  # the receivers of this domain only
                rx_xy = neighbors.xy[np.searchsorted(neighbors.vid, whole.receivers)].reshape(-1, 2)
                cols = np.hypot(rx_xy[:, 0] - self.domains.center[d, 0],
                                rx_xy[:, 1] - self.domains.center[d, 1]) <= self.domains.limit_m[d]
                objects = ObjectMap(whole.object_id, whole.size_bytes, whole.centroid_xy, whole.receivers[cols],
                                    np.ascontiguousarray(whole.visibility[:, cols]),
                                    np.ascontiguousarray(whole.relevance[:, cols]))
            counts = unscheduled.get(d) or {}
            m = np.array([counts.get(int(k), 0) for k in objects.object_id.tolist()], dtype=np.int64)
            out[d] = ControlMsg(view.tick, view.t_sim_s, self.mission.vid, view.pose, scan.speed_mps, trajectory,
                                objects, np.array(sorted(heard.get(d, [])), dtype=np.int64), m,
                                domains=named)
        return out

    # ----------------------------------------------------------------- share

    def payloads(self, view: View, object_ids: list[int]) -> dict[int, bytes]:
        """The encoded point clouds of the given tracked objects (``encode_object`` of
        each, all of their points taken to our sensor frame at once; in our model's
        int16 coding, taken there and encoded in one pass: ``encode_world_objects``)."""
        with self._timed("encoding"):
            if not object_ids:
                return {}
            at = {t.track_id: k for k, t in enumerate(view.tracks)}
            rows = [at[oid] for oid in object_ids]
            tracks = [view.tracks[k] for k in rows]
            points, counts = self._offered(view)
            if points is None:
                points_of = [t.detection.points_world for t in tracks]
            else:
                starts = np.cumsum(counts) - counts
                points_of = [points[starts[k]:starts[k] + counts[k]] for k in rows]
            centroids = np.array([[t.xy[0], t.xy[1], t.detection.centroid[2]] for t in tracks])
            velocities = np.array([t.velocity for t in tracks])
            sizes = np.array([len(p) for p in points_of], dtype=np.int64)
            if self.model.bytes_per_point == BYTES_PER_POINT:  # to the sensor frame and encoded in one pass
                encoded = encode_world_objects(self.mission.vid, view.tick, view.t_sim_s, view.pose, self.mount_m,
                                               object_ids, centroids, velocities, np.concatenate(points_of), sizes)
            else:
                pts = world_to_sensor(np.concatenate(points_of).astype(np.float64), view.pose, self.mount_m)
                centroids_sensor = world_to_sensor(centroids, view.pose, self.mount_m).astype(np.float32)
                encoded = encode_objects(self.mission.vid, view.tick, view.t_sim_s, view.pose, self.mount_m,
                                         object_ids, centroids_sensor, velocities.astype(np.float32),
                                         pts.astype(np.float32), sizes, self.model.bytes_per_point)
        return dict(zip(object_ids, encoded))

    def _offered(self, view: View) -> tuple[np.ndarray | None, np.ndarray]:
        """The points each tracked object offers, in the view's track order: (None, each
        track's point count) when it offers all of its points (our model), else (the kept
        points, object after object, and their counts): ``payload.column_thinned``, worked
        out once per view."""
        cached = self._offered_cache
        if cached is not None and cached[0] is view:
            return cached[1], cached[2]
        all_counts = np.array([len(t.detection.points_world) for t in view.tracks], dtype=np.int64)
        if self.model.object_points == "all":
            points, counts = None, all_counts
        else:
            stacked = np.concatenate([t.detection.points_world for t in view.tracks]) if view.tracks \
                else np.zeros((0, 3))
            keep = column_thinned(stacked, all_counts, self.model.column_m, self.model.ground_cut_m)
            points = stacked[keep]
            owner = np.repeat(np.arange(len(all_counts)), all_counts)[keep]
            counts = np.bincount(owner, minlength=len(all_counts)).astype(np.int64)
        self._offered_cache = (view, points, counts)
        return points, counts

    def fuse(self, view: View, payloads: list[bytes]) -> tuple[FusedGrid, list[MalformedMessage]]:
        """Merge this interval's receptions (and carried-forward older ones) into the grid.

        Returns the fused grid and why each malformed payload was dropped.
        """
        with self._timed("fusion"):
            batch, refused = decode_objects(payloads)
            self.received.add_batch(batch)
            spec = self.mission.spec
            self._recent_poses.append(view.pose)
            # fuse(grid, not_contradicted(not_me(received.current(...)))) in one placement of the stack
            fused = fused_now(self.received, view.t_sim_s, (batch.sender, batch.object_id), list(self._recent_poses),
                              spec.length_m, spec.width_m, view.grid)
            self.shared_batch = fused.shared
        return fused, refused

    @property
    def shared(self) -> list[SharedObject]:
        """This interval's received objects, placed, ourselves excluded, one by one."""
        return self.shared_batch.objects()


class _Timed:
    """``with plane._timed(stage):`` sets ``timings_ms[stage]`` to the block's wall time
    in ms (an exception records nothing). A class, not a generator context manager
    (agent.timed's reason: its machinery cost 1.6 us a block, six blocks a tick)."""

    __slots__ = ("timings_ms", "stage", "t0")

    def __init__(self, timings_ms: dict[str, float], stage: str) -> None:
        self.timings_ms, self.stage = timings_ms, stage

    def __enter__(self) -> None:
        self.t0 = time.perf_counter()

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.timings_ms[self.stage] = (time.perf_counter() - self.t0) * 1e3


class LaneDirections:
    """The map's lanes as segments with their direction of travel. A mover on a lane,
    heading along it (within ``SNAP_DEG``), keeps its speed but takes the lane's
    direction: its tracked heading wavers by a few degrees as its visible faces change,
    and extrapolated over the planner's 8 s horizon that puts an oncoming car in the
    ego's own lane (measured: 0.2 m/s sideways, 1.6 m in 8 s)."""

    SNAP_DEG = 20.0

    def __init__(self, lanes) -> None:
        a, d, length, half = [], [], [], []
        for lane in lanes:
            c = np.asarray(lane.centerline, dtype=np.float64)
            seg = np.diff(c, axis=0)
            n = np.hypot(seg[:, 0], seg[:, 1])
            ok = n > 1e-6
            a.append(c[:-1][ok])
            d.append(seg[ok] / n[ok, None])
            length.append(n[ok])
            half.append(np.full(ok.sum(), lane.width_m / 2))
        self.a = np.concatenate(a) if a else np.zeros((0, 2))
        self.d = np.concatenate(d) if d else np.zeros((0, 2))
        self.length = np.concatenate(length) if length else np.zeros(0)
        self.half = np.concatenate(half) if half else np.zeros(0)

    def snap(self, tracks: list[Track]) -> None:
        """Turn each moving track's velocity to the direction of the lane it drives along:
        of the segments it is on (along it, within half the lane's width across, heading
        within ``SNAP_DEG``), the nearest across; the first such one on a tie."""
        movers = [t for t in tracks if t.speed_mps > 0.0]
        if not movers or not len(self.a):
            return
        xy = np.array([t.xy for t in movers], dtype=np.float64)  # (T, 2)
        vel = np.array([t.velocity for t in movers], dtype=np.float64)
        speed = np.hypot(vel[:, 0], vel[:, 1])
        best = _lane_segment(xy, vel, speed, self.a, self.d, self.length, self.half,
                             float(np.cos(np.radians(self.SNAP_DEG))))
        for i, tr in enumerate(movers):
            if best[i] >= 0:
                tr.velocity = speed[i] * self.d[best[i]]


@njit(cache=True)
def _lane_segment(xy, vel, speed, a, d, length, half, cos_min):
    """``LaneDirections.snap``'s segment of each mover, -1 if none: one pass over the
    (mover, segment) pairs instead of six (T, S) numpy arrays (48.6 -> 2.5 us for ten movers
    and the left-turn map's 184 segments). The products are written as two-term sums; numpy's ``einsum`` and
    matrix product may round the last bit otherwise, which moves a decision only for a
    mover within ~1e-15 of a segment's end or of the heading bound."""
    best = np.full(xy.shape[0], -1, dtype=np.int64)
    for t in range(xy.shape[0]):
        sp = max(speed[t], 1e-9)
        nearest = np.inf
        for s in range(a.shape[0]):
            rx, ry = xy[t, 0] - a[s, 0], xy[t, 1] - a[s, 1]
            along = rx * d[s, 0] + ry * d[s, 1]
            across = abs(rx * d[s, 1] - ry * d[s, 0])
            if along < 0.0 or along > length[s] or across > half[s] or across >= nearest:
                continue
            if (vel[t, 0] * d[s, 0] + vel[t, 1] * d[s, 1]) / sp >= cos_min:
                nearest = across
                best[t] = s
    return best


def _footprints(yaw: np.ndarray, extent: np.ndarray, centroid: np.ndarray) -> np.ndarray:
    """``corners_of`` the objects of heading ``yaw`` (K,), length and width ``extent``
    (K, 2) and centroid (K, 2): the same arrays (``_corner_factors``) into the same
    matrix product, so the same values (numpy's product may fuse a multiply and an add;
    its rounding is left to it)."""
    if not len(yaw):
        return np.zeros((0, 4, 2))
    local, rotation = np.empty((len(yaw), 4, 2)), np.empty((len(yaw), 2, 2))
    _corner_factors(np.cos(yaw), np.sin(yaw), extent, local, rotation)
    return centroid[:, None, :] + local @ rotation


@njit(cache=True)
def _corner_factors(c, s, extent, local, rotation):
    """``corners_of``'s corners about the centroid (``local``, (K, 4, 2)) and rotations
    (``rotation``, (K, 2, 2)), from the cosines ``c`` and sines ``s`` of the headings."""
    for k in range(len(c)):
        hl, hw = extent[k, 0] / 2, extent[k, 1] / 2
        local[k, 0, 0], local[k, 0, 1] = hl, hw
        local[k, 1, 0], local[k, 1, 1] = -hl, hw
        local[k, 2, 0], local[k, 2, 1] = -hl, -hw
        local[k, 3, 0], local[k, 3, 1] = hl, -hw
        rotation[k, 0, 0], rotation[k, 0, 1] = c[k], s[k]
        rotation[k, 1, 0], rotation[k, 1, 1] = -s[k], c[k]


@njit(cache=True)
def _object_dims(extent):
    """(K, 2) each object's [max(length, width, 1.0), max(width, 1.0)], as Python's
    ``max`` picks (a later value only if greater)."""
    dims = np.empty((extent.shape[0], 2))
    for k in range(extent.shape[0]):
        length, width = extent[k, 0], extent[k, 1]
        m = length
        if width > m:
            m = width
        if 1.0 > m:
            m = 1.0
        dims[k, 0] = m
        dims[k, 1] = 1.0 if 1.0 > width else width
    return dims


def _body_corners(x: float, y: float, yaw: float, length: float, width: float) -> np.ndarray:
    """(1, 4, 2) ``_box_corners`` of one box, its cosine and sine taken as there (of a
    column of a (1, 6) array) and the sums in Python floats, in the same order."""
    column = np.array([[x, y, yaw, length, width, 0.0]])[:, 2]
    c, s = float(np.cos(column)[0]), float(np.sin(column)[0])
    hl, hw = length / 2, width / 2
    return np.array([[[x + hl * c - hw * s, y + hl * s + hw * c], [x + -hl * c - hw * s, y + -hl * s + hw * c],
                      [x + -hl * c - -hw * s, y + -hl * s + -hw * c], [x + hl * c - -hw * s, y + hl * s + -hw * c]]])


def _box_corners(boxes: np.ndarray) -> np.ndarray:
    """(m, 4, 2) footprints of [cx, cy, yaw, length, width, ...] rows."""
    c, s = np.cos(boxes[:, 2]), np.sin(boxes[:, 2])
    hl, hw = boxes[:, 3] / 2, boxes[:, 4] / 2
    local = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], dtype=float)
    lx, ly = local[None, :, 0] * hl[:, None], local[None, :, 1] * hw[:, None]
    return np.stack([boxes[:, 0, None] + lx * c[:, None] - ly * s[:, None],
                     boxes[:, 1, None] + lx * s[:, None] + ly * c[:, None]], axis=-1)
