"""Load every numba kernel the agent uses before it reports ready.

With 40 agents starting at once on 2 cores, loading kernels from the numba cache at
first use made the first tick take longer than the world's per-tick timeout. Running
one synthetic interval through every stage before the agent declares its liveliness
token moves that cost into the startup wait, which the world allows for. The synthetic
messages go through the codec, as real ones do: decoded arrays are read-only, which
numba types apart from writable ones, so a kernel warmed on a writable array was
loaded a second time at the first real tick.
"""

from __future__ import annotations

import numpy as np

from channel_proxy.emp import voronoi_segment
from protocol.codec import decode, encode
from protocol.messages import ControlMsg, LidarConfig, Pose, Scan
from vehicle_agent.agent import Agent, _mark_cells, _received_movers
from vehicle_agent.agreement import AgreementConfig, HeardControl, decide
from vehicle_agent.dataplane import Neighbors, _lane_segment
from vehicle_agent.frames import scan_to_world
from vehicle_agent.fusion import warm_kernels as warm_fusion_kernels
from vehicle_agent.payload import warm_kernels as warm_payload_kernels
from vehicle_agent.agreement import plan as plan_transmissions
from vehicle_agent.paths import arc_lengths
from vehicle_agent.perception import build_grid, extract_objects
from vehicle_agent.planning import Obstacle, first_blocked, first_conflict
from vehicle_agent.scheduler.state import _merge_join
from vehicle_agent.tracking import associate, registered_velocity, warm_kernels as warm_tracking_kernels


def warm_up(agent: Agent, agreement: AgreementConfig) -> None:
    """One synthetic interval: a car ahead, another vehicle to reason for, a shared object.

    It runs on a scratch agent of the same mission, map and model: the kernels it loads
    are the process's, and nothing of the synthetic scene (its tracks, the path planned
    round its obstacle, the neighbours it heard) reaches the real agent. Warmed in place,
    the planner kept the synthetic detour while it stayed passable: in grid4_handover
    (60 vehicles, seed 3) the ego and an oncoming car both began their run swerving
    toward the centre line round an obstacle that was never there, and met at 1.3 s."""
    agent = Agent(agent.mission, agent.mapmsg, agent.model)
    m = agent.mission
    x, y = float(m.route[0, 0]), float(m.route[0, 1])
    d = m.route[1] - m.route[0]
    yaw = float(np.arctan2(d[1], d[0]))
    scan = _as_received(Scan(0, 0.0, m.vid, Pose(x, y, yaw), m.cruise_speed_mps, synthetic_ranges(m.lidar)))
    view = agent.perceive(scan)
    _warm_merged_perception(agent, scan)
    other = m.vid + 1
    other_msg = _as_received(ControlMsg(0, 0.0, other, Pose(x + 5.0, y + 5.0, yaw), 5.0,
                                        np.array([[x + 5.0, y + 5.0, 0.0], [x + 30.0, y + 5.0, 5.0]], np.float32),
                                        agent.dataplane.object_map(view, Neighbors.none()),
                                        np.array([m.vid], np.int64)))
    heard = HeardControl.read(encode(other_msg))  # as the link reads it: the codec's reader of its fields is built
    agent.dataplane.neighbors.update([heard])
    # every object once unscheduled: the scheduler state's join of starvation counters loads too
    own = agent.control_message(view, scan, heard=[other], unscheduled={t.track_id: 1 for t in view.tracks})
    slots = plan_transmissions(decide(m.vid, 0, own, [heard], agreement), agreement)
    payloads = agent.dataplane.payloads(view, [t.track_id for t in view.tracks])
    agent.drive(view, agent.fuse(view, list(payloads.values())), scan)
    del slots
    agent.dataplane.neighbors.current(0.0, exclude=m.vid).take(np.zeros(1, dtype=bool))  # one out of the domain
    _warm_conflict(agent)
    # the fast check of a kept path (``_still_good``) reads the passable cells with
    # ``_first_along``, which the planner's blocked-cell test no longer calls (it reads
    # the static grids too: ``_first_blocked_leaving``): load it here, with its real types
    if agent.planner.path_planner.blocked is not None:  # a vehicle that holds still plans no path
        first_blocked(np.array([[x, y], [x + 10.0, y]]), view.grid, agent.planner.path_planner.blocked)
    _warm_registration()
    warm_tracking_kernels()
    associate(np.zeros((1, 2)), np.ones(1), np.zeros((1, 2)))  # the tracker pairs tracks from an object's second frame
    warm_fusion_kernels()
    warm_payload_kernels()
    _mark_cells(np.zeros((1, 2)), 0, 0, 0.5, 2.0, np.zeros((2, 2), dtype=np.bool_))  # movers' cells: none here
    _received_movers(np.zeros((1, 3)), np.ones(1, dtype=np.int64), np.ones((1, 2)), 0.5, 0, 0, 0.5, 2.0,
                     np.zeros((2, 2), dtype=np.bool_))  # a received mover: its box and its cells
    lanes = agent.dataplane.lanes  # a mover's lane (none moves in the first scan)
    _lane_segment(np.zeros((1, 2)), np.ones((1, 2)), np.ones(1), lanes.a, lanes.d, lanes.length, lanes.half, 0.9)
    key = np.zeros((1, 2), dtype=np.int64)  # one starved object: its key's columns are contiguous
    oid = np.zeros(1, dtype=np.int64)
    key.setflags(write=False)
    oid.setflags(write=False)
    _merge_join(np.zeros(1, dtype=np.int64), oid, key[:, 0], key[:, 1])


def _warm_merged_perception(agent: Agent, scan: Scan) -> None:
    """EMP cuts its Voronoi segment out of its scan (``voronoi_segment``) and perceives
    its scan merged with the relay's points, through the world-point kernels
    (``build_grid``, ``extract_objects``); every other scheme perceives from the
    range image. Left out here, the first EMP tick compiled them in every agent at once
    on a cold cache, past the world's 10 s per-tick timeout: all agents were declared
    dead. Called directly, so the agent's tracker sees one scan only."""
    world = scan_to_world(scan, agent.mission.lidar)
    xy = (scan.pose.x_m, scan.pose.y_m)
    grid, cell_idx = build_grid(world, xy, agent.dataplane.spec, agent.dataplane.raster)
    extract_objects(world, grid, cell_idx, xy)
    voronoi_segment(world[:, :2], np.array(xy), np.array([[xy[0] + 50.0, xy[1]]]))  # the segment it uploads


def _warm_conflict(agent: Agent) -> None:
    """The synthetic scene has nothing moving, so the planner never predicts a conflict
    in it: a car that crosses the route 10 m ahead when the vehicle gets there loads the
    conflict kernel (both its uses: the timed test and the swept zone). The route's
    first 30 m are taken every metre: the ego's first waypoints are 46 m apart, and the
    test looks at waypoints only, so the car passed between them unseen and the swept
    zone's kernel was left for the first real conflict to load."""
    route = np.asarray(agent.mission.route, dtype=float)
    s = arc_lengths(route)
    along = np.arange(0.0, min(30.0, float(s[-1])) + 1e-9, 1.0) if s[-1] >= 2.0 else s
    path = np.column_stack([np.interp(along, s, route[:, 0]), np.interp(along, s, route[:, 1])])
    a, b = path[0], path[-1]
    d = (b - a) / max(float(np.hypot(*(b - a))), 1e-9)
    normal = np.array([-d[1], d[0]])
    crossing = Obstacle(a + 10.0 * d - 10.0 * normal, 10.0 * normal, 4.5, 1.8, 0.0, float(np.arctan2(normal[1], normal[0])))
    t_path = arc_lengths(path) / 10.0
    first_conflict(path, t_path, agent.mission.spec, [crossing], 0.0, agent.planner.config)


def _warm_registration() -> None:
    """The tracker tests a track's motion by registering its points (``_persisting``)
    from the object's third frame on; the synthetic interval has only one frame, so the
    first real third frame loaded the kernel (and, cache cold, compiled it for seconds in
    every agent at once: they were declared dead). Three frames of one block load it."""
    grid = np.arange(8, dtype=np.float32) * 0.2
    points = np.stack(np.meshgrid(grid, grid, [0.5], indexing="ij"), axis=-1).reshape(-1, 3)
    registered_velocity([(0.0, points), (0.1, points), (0.2, points)], points, 0.3, np.array([10.0, 0.0]))
    points = points.astype(np.float32)  # as detected (the lines above register float64 points)
    registered_velocity([(0.0, points), (0.1, points), (0.2, points)], points, 0.3, np.array([10.0, 0.0]))


def _as_received(msg):
    """The message as a subscriber gets it: through the wire format."""
    return decode(encode(msg), type(msg))


def synthetic_ranges(lidar: LidarConfig) -> np.ndarray:
    """A range image of flat ground with two 2 m wide, 1.5 m tall blocks, 11 m straight
    ahead and 9 m straight behind (two objects: the shadow-merge kernel runs too)."""
    az, el = lidar.azimuths_rad(), lidar.elevations_rad()
    ground = np.where(el < 0.0, lidar.mount_height_m / np.tan(-np.minimum(el, -1e-6)), 0.0)
    ground[ground * np.sqrt(1.0 + np.tan(el) ** 2) > lidar.range_m] = 0.0
    d = np.broadcast_to(ground, (len(az), len(el))).copy()
    for direction, dist in ((0.0, 11.0), (np.pi, 9.0)):
        z_at_block = lidar.mount_height_m + dist * np.tan(el)
        facing = np.abs(np.arctan2(np.sin(az - direction), np.cos(az - direction))) < np.arctan2(1.0, dist)
        d[np.ix_(facing, (z_at_block >= 0.0) & (z_at_block <= 1.5))] = dist
    return np.rint(d * 100.0).astype(np.uint16)
