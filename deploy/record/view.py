"""``autocast view RUN.mcap [--save out.rrd | --spawn | --connect URL] [--foxglove out.mcap]``.

Turns a run's MCAP log into a rerun recording on the sim-time timeline: the map, every
vehicle's box, route, shared trajectory and trace, the ego's LiDAR (every vehicle's
with ``--scans all``), the points each vehicle received (red, as in the paper's
figures), the boxes each vehicle knows of from the control messages it heard, the
ego's fused view, the schedule of each interval and the channel statistics as time
series. The layout saved with it opens on one 3-D view per vehicle that follows that
vehicle. ``docs/viewing.md`` lists the entities.

The log is read message by message (the MCAP reader holds one chunk at a time) and
logged as it goes, so memory does not grow with the run. A message that does not
decode is skipped and counted; a damaged file is shown up to the damage.
``--foxglove`` writes what ``autocast export --foxglove`` writes (``deploy.record.export``).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import math
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from deploy.record.runlog import (DEFAULT_SCAN_POINTS, GROUND_Z_M, LogStats, Prelude, iter_log, read_prelude,
                           received_world, run_metadata, scan_points, stack)
from protocol.codec import MalformedMessage, decode
from protocol.messages import (AgentReport, ChannelStats, Command, ControlMsg, CtrlBundle, DataBundle, DataTx,
                               EmpBundle, EmpUpload, LidarConfig, MapMsg, Mission, Outcome, Pose, Scan, Signed, Tick,
                               VehicleSpec, WorldTruth)
from protocol.security import opened
from vehicle_agent.frames import sensor_to_world

log = logging.getLogger("deploy.record.view")

ViewStats = LogStats  # what a view read (the name the CLI and its tests know)

APP_ID = "autocast"
SIM_TIME = "sim_time"  # seconds of simulated time
TICK = "tick"  # decision interval number
CAR = VehicleSpec(4.6, 1.9, 1.5, 2.8, 3.0, 7.5, 0.6)  # a vehicle whose mission is not in the log

ROLE_COLORS = {"ego": (30, 110, 255), "occluder": (120, 120, 120), "background": (40, 170, 80)}
OTHER_COLOR = (255, 140, 0)  # no mission: the passive collider and other traffic without V2V
RECEIVED_COLOR = (230, 25, 25)
FUSED_COLOR = (255, 190, 0)
GROUND_COLOR = (85, 85, 85)
ABOVE_GROUND_COLOR = (160, 200, 235)
LIGHT_COLORS = {"red": (230, 30, 30), "yellow": (240, 200, 0), "green": (30, 200, 60)}

# Sizes in metres (rerun draws a positive radius in scene units). A LiDAR scan thinned
# to 20000 of its ~110000 returns has one column every ~1.2 degrees, 21 cm apart at
# 10 m, and its 64 beams are 0.43 degrees apart (7.5 cm at 10 m): 5 cm dots stay apart.
# Received object points are whole-resolution and quantized to 1 cm; they are drawn
# at the same size so that own and shared returns of one surface look alike.
POINT_RADIUS_M = 0.05
FUSED_RADIUS_M = 0.04  # the ego's fused view, flat on the ground (2-D)
CENTROID_RADIUS_M = 0.15  # an object map's centroids (hidden labels)
LANE_RADIUS_M = 0.05
OUTLINE_RADIUS_M = 0.05
ROUTE_RADIUS_M = 0.05
TRAJECTORY_RADIUS_M = 0.12
TRACE_RADIUS_M = 0.05
BOX_LINE_RADIUS_M = 0.04  # edges of a vehicle's box
KNOWN_LINE_RADIUS_M = 0.03
LIGHT_HEAD_M = (0.4, 0.4, 1.0)  # a signal head on a 5 m pole
LIGHT_HEIGHT_M = 5.0
GRID_SPACING_M = 10.0
CHASE_BACK_M = 16.0  # the default camera: behind the vehicle's first heading ...
CHASE_UP_M = 30.0  # ... and above it, looking down at the vehicle (34 m away), following it


class Series:
    """Scalar time series, sent in columns every ``flush_every`` ticks instead of one
    ``log`` call per value (tens of values per tick). Each series gets a short name for
    the plot legends when it first appears."""

    def __init__(self, rec: rr.RecordingStream, flush_every: int = 50) -> None:
        self.rec = rec
        self.flush_every = flush_every
        self.values: dict[str, tuple[list[float], list[int], list[float]]] = {}
        self.first_tick: int | None = None
        self.named: set[str] = set()
        self.history: dict[str, list[np.ndarray]] = {}  # path -> (k, 2) sim time, value: for the legends

    def points(self, path: str) -> np.ndarray:
        """Every (sim time, value) of a series sent so far."""
        parts = self.history.get(path)
        return np.vstack(parts) if parts else np.zeros((0, 2))

    def add(self, path: str, t_sim_s: float, tick: int, value: float, name: str) -> None:
        if path not in self.named:
            self.named.add(path)
            self.rec.log(path, rr.SeriesLines(names=[name]), static=True)
        times, ticks, values = self.values.setdefault(path, ([], [], []))
        times.append(t_sim_s)
        ticks.append(tick)
        values.append(value)
        if self.first_tick is None:
            self.first_tick = tick
        elif tick - self.first_tick >= self.flush_every:
            self.flush()

    def flush(self) -> None:
        for path, (times, ticks, values) in self.values.items():
            self.rec.send_columns(path, indexes=[rr.TimeColumn(SIM_TIME, duration=times),
                                                 rr.TimeColumn(TICK, sequence=ticks)],
                                  columns=rr.Scalars.columns(scalars=values))
            self.history.setdefault(path, []).append(np.column_stack([times, values]))
        self.values.clear()
        self.first_tick = None


class Columns:
    """Rows of one archetype per entity, sent in columns every ``flush_every`` ticks. A
    10-vehicle run has ~10 entities per vehicle that change every tick; one ``log`` call
    each cost more than reading and decoding the whole log. Components that do not
    change (a vehicle's colour, a line's radius) are logged once, static."""

    def __init__(self, rec: rr.RecordingStream, flush_every: int = 50) -> None:
        self.rec = rec
        self.flush_every = flush_every
        self.rows: dict[str, tuple[type, list[float], list[int], list[int], dict[str, list]]] = {}
        self.first_tick: int | None = None
        self.static_done: set[str] = set()

    def static(self, path: str, kind: type, **components: object) -> None:
        """The components of ``path`` that never change, logged the first time only."""
        if path not in self.static_done:
            self.static_done.add(path)
            self.rec.log(path, kind.from_fields(**components), static=True)

    def add(self, path: str, kind: type, t_sim_s: float, tick: int, **components: list | np.ndarray) -> None:
        """One row of ``path`` at this time: each component holds the row's instances."""
        entry = self.rows.get(path)
        if entry is None:
            entry = self.rows[path] = (kind, [], [], [], {name: [] for name in components})
        _, times, ticks, lengths, columns = entry
        for name, value in components.items():
            columns[name].append(value)
        times.append(t_sim_s)
        ticks.append(tick)
        lengths.append(len(next(iter(components.values()))))
        if self.first_tick is None:
            self.first_tick = tick
        elif tick - self.first_tick >= self.flush_every:
            self.flush()

    def flush(self) -> None:
        for path, (kind, times, ticks, lengths, columns) in self.rows.items():
            flat = {name: np.concatenate(parts) if isinstance(parts[0], np.ndarray) else [x for p in parts for x in p]
                    for name, parts in columns.items()}
            self.rec.send_columns(path, indexes=[rr.TimeColumn(SIM_TIME, duration=times),
                                                 rr.TimeColumn(TICK, sequence=ticks)],
                                  columns=kind.columns(**flat).partition(lengths))
        self.rows.clear()
        self.first_tick = None


def flat_numbers(d: dict, prefix: str = "") -> Iterator[tuple[str, float]]:
    """(path, value) for every number in a nested dict (bools and lists left out)."""
    for k, v in d.items():
        if isinstance(v, bool):
            continue
        if isinstance(v, (int, float)):
            yield f"{prefix}{k}", float(v)
        elif isinstance(v, dict):
            yield from flat_numbers(v, f"{prefix}{k}/")


def stat_unit(path: str) -> str:
    """The unit of a channel statistic, from its name (``docs/channel.md``)."""
    name = path.rsplit("/", 1)[-1]
    if name.endswith("_bytes"):
        return "bytes"
    if name.endswith("_ms"):
        return "ms"
    if name == "utilization":
        return "busy share of the interval"
    return "count"


def stat_name(path: str) -> str:
    """A statistic's legend entry: its name without the unit the plot's title gives."""
    name = path.rsplit("/", 1)[-1]
    for suffix in ("_bytes", "_ms"):
        name = name.removesuffix(suffix)
    return name


def yaw_quaternion(yaw_rad: float) -> tuple[float, float, float, float]:
    """x, y, z, w of a rotation by ``yaw_rad`` about +z (a pose's yaw; the body centre is
    on the ground under the box's centre)."""
    return 0.0, 0.0, math.sin(yaw_rad / 2), math.cos(yaw_rad / 2)


def xy_to_3d(xy: np.ndarray, z_m: float) -> np.ndarray:
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    return np.column_stack([xy, np.full(len(xy), z_m)])


def schedule_markdown(tick: int, t_sim_s: float, on_air: list, sizes: dict, missions: dict[int, Mission],
                      stats: dict) -> str:
    """One interval's data phase as a table: who sent which object when, its size, and
    how many receivers decoded it of those in range (the channel's own account)."""
    data = stats.get("data") or {}
    head = f"**tick {tick}, {t_sim_s:.1f} s**"
    if not on_air:
        return head + ": nothing on the data channel this interval."
    util = data.get("utilization")
    lines = [head + f": {len(on_air)} objects on air" + (f", the channel busy {util:.0%} of the interval" if
                                                          isinstance(util, (int, float)) else ""),
             "", "| on air (ms) | sender | object | bytes | decoded / in range |", "|---|---|---|---|---|"]
    for sender, oid, start_s, end_s, decoded, in_range in sorted(on_air, key=lambda o: (o[2], o[0])):
        role = missions[sender].role if sender in missions else "?"
        size = sizes.get((sender, oid, round(start_s * 1e6)), "")
        lines.append(f"| {start_s * 1e3:.1f}-{end_s * 1e3:.1f} | {sender} {role} | {oid} | {size} | "
                     f"{decoded}/{in_range} |")
    return "\n".join(lines)


class Scene:
    """Logs decoded messages as rerun entities; keeps what later messages need (the map's
    lights, missions, traces, the sizes of this interval's transmissions)."""

    def __init__(self, rec: rr.RecordingStream, stats: LogStats, scan_points: int = DEFAULT_SCAN_POINTS) -> None:
        self.rec = rec
        self.stats = stats
        self.scan_points = scan_points
        self.missions: dict[int, Mission] = {}
        self.map_logged = False
        self.lights_xy: dict[int, tuple[float, float]] = {}
        self.specs: dict[int, VehicleSpec] = {}  # true sizes, from the ground truth
        self.trace: dict[int, list[tuple[float, float]]] = {}
        self.last_pose_tick: dict[int, int] = {}
        self.live: set[int] = set()
        self.tx_sizes: dict[int, dict[tuple[int, int, int], int]] = {}  # tick -> (sender, object, start us) -> B
        self.series = Series(rec)
        self.columns = Columns(rec)
        self.now = (0.0, 0)  # sim time and tick of the message being logged
        self.handlers = {MapMsg: self.map, Mission: self.mission, Tick: self.tick, WorldTruth: self.truth,
                         Scan: self.scan,
                         Command: self.command, ControlMsg: self.control, CtrlBundle: self.ctrl_bundle,
                         DataTx: self.data_tx, DataBundle: self.data_bundle, ChannelStats: self.channel_stats,
                         AgentReport: self.report, Outcome: self.outcome, EmpUpload: self.emp_upload,
                         EmpBundle: self.emp_bundle}

    def add(self, topic: str, msg: object) -> None:
        if isinstance(msg, Signed):  # a vehicle's signed message: shown as what it says (not checked here)
            body = opened(msg)
            if body is None:
                self.stats.count_malformed(topic, MalformedMessage("a signed envelope whose body does not decode"))
                return
            msg = body
        handler = self.handlers.get(type(msg))
        if handler is None:
            return
        self.stats.messages += 1
        self.stats.per_type[type(msg).__name__] += 1
        if isinstance(msg, MapMsg) and self.map_logged or isinstance(msg, Mission) and msg.vid in self.missions:
            return  # already logged from the prelude (or a repeated reply)
        if not isinstance(msg, (MapMsg, Mission)):
            self.rec.set_time(SIM_TIME, duration=msg.t_sim_s)
            self.rec.set_time(TICK, sequence=msg.tick)
            self.now = (msg.t_sim_s, msg.tick)
        try:
            handler(msg)
        except (MalformedMessage, ValueError) as exc:  # a bad inner payload, a scan that fits no LiDAR
            self.stats.count_malformed(topic, exc)

    def scalar(self, path: str, value: float, name: str | None = None) -> None:
        self.series.add(path, *self.now, float(value), name or path.rsplit("/", 1)[-1])

    def row(self, path: str, kind: type, **components: list | np.ndarray) -> None:
        self.columns.add(path, kind, *self.now, **components)

    def finish(self) -> None:
        self.series.flush()
        self.columns.flush()

    def role_name(self, vid: int) -> str:
        mission = self.missions.get(vid)
        return f"{vid} {mission.role}" if mission else f"{vid} no V2V"

    # -- world

    def map(self, m: MapMsg) -> None:
        self.map_logged = True
        rec = self.rec
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        rec.log("world/map/lanes", rr.LineStrips3D([xy_to_3d(lane.centerline, 0.02) for lane in m.lanes],
                                                   colors=[(200, 200, 200)], radii=LANE_RADIUS_M,
                                                   labels=[lane.lane_id for lane in m.lanes], show_labels=False),
                static=True)
        outlines = [xy_to_3d(np.vstack([p, p[:1]]), 0.0) for p in m.drivable if len(p)]
        rec.log("world/map/drivable", rr.LineStrips3D(outlines, colors=[(110, 110, 110)], radii=OUTLINE_RADIUS_M),
                static=True)
        b = np.asarray(m.buildings, dtype=np.float64).reshape(-1, 6)  # cx, cy, yaw, length, width, height
        rec.log("world/map/buildings", rr.Boxes3D(
            centers=np.column_stack([b[:, 0], b[:, 1], b[:, 5] / 2]), half_sizes=b[:, 3:6] / 2,
            rotation_axis_angles=[rr.RotationAxisAngle(axis=[0, 0, 1], radians=yaw) for yaw in b[:, 2]],
            colors=[(150, 120, 90)], fill_mode="solid"), static=True)
        self.lights_xy = {light.light_id: (light.x_m, light.y_m) for light in m.lights}
        if m.lights:
            rec.log("world/map/poles", rr.LineStrips3D(
                [[[x, y, 0.0], [x, y, LIGHT_HEIGHT_M - LIGHT_HEAD_M[2] / 2]] for x, y in self.lights_xy.values()],
                colors=[(90, 90, 90)], radii=0.05), static=True)

    def mission(self, m: Mission) -> None:
        self.missions[m.vid] = m
        self.rec.log(f"world/vehicles/{m.vid}/route", rr.LineStrips3D([xy_to_3d(m.route, 0.05)],
                                                                        colors=[self.color_of(m.vid)],
                                                                        radii=ROUTE_RADIUS_M), static=True)

    def tick(self, t: Tick) -> None:
        for vid in sorted(self.live - set(t.live)):  # its agent died: the vehicle brakes to a stop, unseen
            self.rec.log("events", rr.TextLog(f"tick {t.tick}: vehicle {vid} left play; its box stays where it was "
                                              "last reported", level=rr.TextLogLevel.WARN))
        self.live = set(t.live)
        known = [s for s in t.lights if s.light_id in self.lights_xy]
        if known:
            self.rec.log("world/map/lights", rr.Boxes3D(
                centers=[[*self.lights_xy[s.light_id], LIGHT_HEIGHT_M] for s in known],
                half_sizes=[[h / 2 for h in LIGHT_HEAD_M]] * len(known), fill_mode="solid",
                colors=[LIGHT_COLORS.get(s.state, (255, 255, 255)) for s in known]))

    def truth(self, w: WorldTruth) -> None:
        """Every vehicle's true box, the passive collider's included (it has no scan or
        control message of its own)."""
        for vid, (x, y, yaw), speed, (length, width, height) in zip(w.vids.tolist(), w.pose.tolist(),
                                                                    w.speed_mps.tolist(), w.size_m.tolist()):
            spec = self.specs.get(vid)
            if spec is None:
                spec = self.specs[vid] = dataclasses.replace(CAR, length_m=length, width_m=width, height_m=height)
            self.pose(vid, w.tick, Pose(x, y, yaw), speed, spec)

    # -- one vehicle

    def color_of(self, vid: int) -> tuple[int, int, int]:
        mission = self.missions.get(vid)
        return ROLE_COLORS.get(mission.role, OTHER_COLOR) if mission else OTHER_COLOR

    def spec_of(self, vid: int) -> VehicleSpec:
        mission = self.missions.get(vid)
        return self.specs.get(vid) or (mission.spec if mission else CAR)

    def pose(self, vid: int, tick: int, pose: Pose, speed_mps: float | None, spec: VehicleSpec | None = None) -> None:
        """A vehicle's box and trace, once per tick (the world's truth, its scan and its
        control message carry the same pose; the first to arrive is drawn)."""
        if self.last_pose_tick.get(vid, -1) >= tick:
            return
        self.last_pose_tick[vid] = tick
        spec = spec or self.spec_of(vid)
        box, trace_path = f"world/vehicles/{vid}/box", f"world/vehicles/{vid}/trace"
        self.columns.static(box, rr.Boxes3D, colors=[self.color_of(vid)], labels=[self.role_name(vid)],
                            radii=BOX_LINE_RADIUS_M)
        self.row(box, rr.Boxes3D, centers=np.array([[pose.x_m, pose.y_m, spec.height_m / 2]]),
                 half_sizes=np.array([[spec.length_m / 2, spec.width_m / 2, spec.height_m / 2]]),
                 quaternions=np.array([yaw_quaternion(pose.yaw_rad)]))
        trace = self.trace.setdefault(vid, [])
        trace.append((pose.x_m, pose.y_m, 0.1))
        if len(trace) > 1:
            self.columns.static(trace_path, rr.LineStrips3D, colors=[self.color_of(vid)], radii=TRACE_RADIUS_M)
            self.row(trace_path, rr.LineStrips3D, strips=[np.array(trace)])
        if speed_mps is not None:
            self.scalar(f"vehicles/{vid}/speed_mps", speed_mps, self.role_name(vid))

    def lidar_of(self, vid: int) -> LidarConfig:
        mission = self.missions.get(vid)
        return mission.lidar if mission else LidarConfig()

    def scan(self, s: Scan) -> None:
        self.pose(s.vid, s.tick, s.pose, s.speed_mps)
        lidar = self.lidar_of(s.vid)
        world = sensor_to_world(scan_points(s, lidar, self.scan_points), s.pose, lidar.mount_height_m)
        world = world.astype(np.float32)
        ground = world[:, 2] < GROUND_Z_M
        self.rec.log(f"world/vehicles/{s.vid}/lidar/ground", rr.Points3D(world[ground], colors=[GROUND_COLOR],
                                                                         radii=POINT_RADIUS_M))
        self.rec.log(f"world/vehicles/{s.vid}/lidar/objects", rr.Points3D(world[~ground],
                                                                          colors=[ABOVE_GROUND_COLOR],
                                                                          radii=POINT_RADIUS_M))

    def command(self, c: Command) -> None:
        self.scalar(f"vehicles/{c.vid}/accel_mps2", c.accel_mps2, self.role_name(c.vid))
        self.scalar(f"vehicles/{c.vid}/steer_rad", c.steer_rad, self.role_name(c.vid))

    def control(self, c: ControlMsg) -> None:
        self.pose(c.vid, c.tick, c.pose, c.speed_mps)
        color = self.color_of(c.vid)
        traj = np.asarray(c.trajectory, dtype=np.float64).reshape(-1, 3)
        path, objects = f"world/vehicles/{c.vid}/trajectory", f"world/vehicles/{c.vid}/objects"
        self.columns.static(path, rr.LineStrips3D, colors=[color], radii=TRAJECTORY_RADIUS_M)
        self.row(path, rr.LineStrips3D, strips=[xy_to_3d(traj[:, :2], 0.3)] if len(traj) > 1 else [])
        om = c.objects
        self.columns.static(objects, rr.Points3D, colors=[color], radii=CENTROID_RADIUS_M, show_labels=False)
        self.row(objects, rr.Points3D, positions=xy_to_3d(om.centroid_xy, 1.0),
                 labels=[f"{c.vid}/{oid}: {size} B" for oid, size in zip(om.object_id.tolist(),
                                                                         om.size_bytes.tolist())])

    def ctrl_bundle(self, b: CtrlBundle) -> None:
        """What each receiver heard: a count, and the boxes of the senders it heard, where
        their control messages put them (what the vehicle knows of the others). A signed
        run's messages are read through their envelopes, unverified; of a slot only its
        first frame, the one the medium played as the sender's (any other is relayed
        after it and its receivers drop it: docs/security.md)."""
        sent: list[ControlMsg | None] = []
        for s, raw in enumerate(b.messages):
            try:
                msg = opened(decode(raw))
            except MalformedMessage:
                msg = None
            own = s == 0 or b.senders[s] != b.senders[s - 1]
            sent.append(msg if own and isinstance(msg, ControlMsg) else None)
        for receiver, row in zip(b.receivers.tolist(), b.heard):
            heard = [m for m in (sent[s] for s in np.flatnonzero(row).tolist()) if m is not None]
            self.scalar(f"vehicles/{receiver}/heard", len(heard), self.role_name(receiver))
            specs = [self.spec_of(m.vid) for m in heard]
            known = f"world/vehicles/{receiver}/known"
            self.columns.static(known, rr.Boxes3D, radii=KNOWN_LINE_RADIUS_M)
            self.row(known, rr.Boxes3D,
                     centers=np.array([[m.pose.x_m, m.pose.y_m, s.height_m / 2] for m, s in zip(heard, specs)]
                                      ).reshape(-1, 3),
                     half_sizes=np.array([[s.length_m / 2, s.width_m / 2, s.height_m / 2] for s in specs]
                                         ).reshape(-1, 3),
                     quaternions=np.array([yaw_quaternion(m.pose.yaw_rad) for m in heard]).reshape(-1, 4),
                     colors=np.array([self.color_of(m.vid) for m in heard], dtype=np.uint8).reshape(-1, 3),
                     labels=[self.role_name(m.vid) for m in heard])

    def report(self, r: AgentReport) -> None:
        self.rec.log(f"world/vehicles/{r.vid}/fused", rr.Points3D(xy_to_3d(r.fused_xy, 0.05), colors=[FUSED_COLOR],
                                                                   radii=FUSED_RADIUS_M))
        self.scalar(f"vehicles/{r.vid}/fused_received_points", r.received_points, self.role_name(r.vid))
        self.scalar(f"vehicles/{r.vid}/braking", float(r.braking), self.role_name(r.vid))

    # -- the channel

    def data_tx(self, d: DataTx) -> None:
        """Who sends what in which slot: one line per sender with a non-empty schedule."""
        size = sum(len(t.payload) for t in d.transmissions)
        self.scalar(f"schedule/tx_bytes/{d.vid}", size, self.role_name(d.vid))
        sizes = self.tx_sizes.setdefault(d.tick, {})
        for t in d.transmissions:
            sizes[(d.vid, t.object_id, round(t.start_s * 1e6))] = len(t.payload)
        if d.transmissions:
            slots = ", ".join(f"obj {t.object_id} @ {t.start_s * 1e3:.1f} ms ({len(t.payload)} B)"
                              for t in d.transmissions)
            self.rec.log("schedule/tx", rr.TextLog(f"tick {d.tick} v{d.vid}: {slots}"))

    def data_bundle(self, b: DataBundle) -> None:
        """Each receiver's decoded objects, in the world frame (T_s V_s of each sender)."""
        world, size = received_world(b)
        for receiver, row in zip(b.receivers.tolist(), b.decoded):
            got = np.flatnonzero(row).tolist()
            self.received(receiver, [world[t] for t in got])
            self.scalar(f"schedule/rx_bytes/{receiver}", int(size[got].sum()), self.role_name(receiver))

    def received(self, vid: int, parts: list[np.ndarray]) -> None:
        path = f"world/vehicles/{vid}/received"
        self.columns.static(path, rr.Points3D, colors=[RECEIVED_COLOR], radii=POINT_RADIUS_M)
        self.row(path, rr.Points3D, positions=stack(parts).astype(np.float32))

    def emp_upload(self, u: EmpUpload) -> None:
        self.pose(u.vid, u.tick, u.pose, None)

    def emp_bundle(self, b: EmpBundle) -> None:
        self.received(b.receiver, [np.asarray(s.points_world, dtype=np.float64) for s in b.segments])

    def channel_stats(self, c: ChannelStats) -> None:
        for path, value in flat_numbers(c.stats):
            if path != "tick":
                self.scalar(f"stats/{path}", value, stat_name(path))
        on_air = (c.stats.get("data") or {}).get("objects") or []
        sizes = self.tx_sizes.pop(c.tick, {})
        for old in [t for t in self.tx_sizes if t < c.tick]:
            del self.tx_sizes[old]
        self.rec.log("schedule/interval", rr.TextDocument(
            schedule_markdown(c.tick, c.t_sim_s, on_air, sizes, self.missions, c.stats),
            media_type=rr.MediaType.MARKDOWN))
        if on_air:  # [sender, object, start_s, end_s, receivers decoded, receivers in range]
            self.rec.log("schedule/air", rr.TextLog(f"tick {c.tick}: " + ", ".join(
                f"v{o[0]}/obj {o[1]} {o[2] * 1e3:.1f}-{o[3] * 1e3:.1f} ms -> {o[4]}/{o[5]}" for o in on_air)))

    def outcome(self, o: Outcome) -> None:
        r = o.result
        series = np.asarray(r.get("distance_series_m") or [], dtype=np.float64).reshape(-1, 2)
        if len(series):
            self.rec.log("judge/ego_collider_distance_m", rr.SeriesLines(names=["ego-collider distance"]),
                         static=True)
            self.rec.send_columns("judge/ego_collider_distance_m",
                                  indexes=[rr.TimeColumn(SIM_TIME, duration=series[:, 0])],
                                  columns=rr.Scalars.columns(scalars=series[:, 1]))
            self.series.history["judge/ego_collider_distance_m"] = [series]
        brief = {k: v for k, v in r.items() if not isinstance(v, (list, dict))}
        level = rr.TextLogLevel.INFO if r.get("outcome") == "safe" else rr.TextLogLevel.WARN
        self.rec.log("outcome", rr.TextLog(" ".join(f"{k}={v}" for k, v in brief.items()), level=level))


# ---------------------------------------------------------------------------- the layout


def chase_eye(vid: int, pose: tuple[float, float, float] | None) -> rrb.EyeControls3D | None:
    """An orbiting eye behind and above the vehicle's first pose that follows its box."""
    if pose is None:
        return None
    x, y, yaw = pose
    return rrb.EyeControls3D(kind=rrb.Eye3DKind.Orbital, look_target=[x, y, 0.0],
                             position=[x - CHASE_BACK_M * math.cos(yaw), y - CHASE_BACK_M * math.sin(yaw), CHASE_UP_M],
                             eye_up=[0, 0, 1], tracking_entity=f"world/vehicles/{vid}/box")


# The legend is drawn over the plot, in a corner, ~19 px per series plus a margin; a plot
# of the default layout in a 1920 x 1080 window is ~700 x 220 px (docs/viewing.md).
LEGEND_ROW_PX, LEGEND_PAD_PX, LEGEND_W_PX = 19, 14, 190
PLOT_W_PX, PLOT_H_PX = 700, 220
MAX_LEGEND_ROWS = 6  # more series than this: no legend (hover a line for its name)
CORNERS = (rrb.Corner2D.RightTop, rrb.Corner2D.RightBottom, rrb.Corner2D.LeftBottom, rrb.Corner2D.LeftTop)


@dataclasses.dataclass(frozen=True, slots=True)
class Legend:
    corner: rrb.Corner2D
    visible: bool
    y_range: tuple[float, float] | None = None  # widened so that no data runs under the legend


def legend_for(series: list[np.ndarray]) -> Legend:
    """Where a plot's legend hides no data: the corner whose columns hold no data in its
    rows, else the one that needs the least extra room on the value axis, and that room."""
    series = [s for s in series if len(s)]
    if not 2 <= len(series) <= MAX_LEGEND_ROWS:
        return Legend(rrb.Corner2D.RightTop, False)
    data = np.vstack(series)
    t, v = data[:, 0], data[:, 1]
    t0, t1, lo, hi = t.min(), t.max(), v.min(), v.max()
    hi = hi if hi > lo else lo + 1.0
    h = min(0.9, (len(series) * LEGEND_ROW_PX + LEGEND_PAD_PX) / PLOT_H_PX)  # the legend's share of the height
    w = LEGEND_W_PX / PLOT_W_PX * (t1 - t0)
    best: tuple[float, int, tuple[float, float] | None] | None = None
    for rank, corner in enumerate(CORNERS):
        right, top = corner in (rrb.Corner2D.RightTop, rrb.Corner2D.RightBottom), \
            corner in (rrb.Corner2D.RightTop, rrb.Corner2D.LeftTop)
        under = v[t >= t1 - w] if right else v[t <= t0 + w]
        span = (lo, hi)
        if len(under) and top and under.max() > lo + (1 - h) * (hi - lo):
            span = (lo, lo + (under.max() - lo) / (1 - h) * 1.03)
        elif len(under) and not top and under.min() < hi - (1 - h) * (hi - lo):
            span = (hi - (hi - under.min()) / (1 - h) * 1.03, hi)
        cost = (span[1] - span[0]) / (hi - lo)
        if best is None or cost < best[0] - 1e-9:
            best = (cost, rank, None if span == (lo, hi) else span)
    _, rank, y_range = best
    return Legend(CORNERS[rank], True, y_range)


def plot(name: str, paths: list[str], series: Series) -> rrb.TimeSeriesView:
    """A plot of series of one unit, its legend where it hides no data."""
    legend = legend_for([series.points(p) for p in paths])
    return rrb.TimeSeriesView(origin="/", contents=[f"+ {p}" for p in paths] or ["- /**"], name=name,
                              plot_legend=rrb.PlotLegend(corner=legend.corner, visible=legend.visible),
                              axis_y=rrb.ScalarAxis(range=legend.y_range) if legend.y_range else None)


def stat_groups(stats: ChannelStats | None) -> dict[str, list[str]]:
    """Plot title -> the channel statistics of one channel and one unit, in the order the
    proxy reports them (``data``, ``ctrl``, then the proxy's own)."""
    groups: dict[str, list[str]] = {}
    sections = {"data": "data channel", "ctrl": "control channel"}
    for path, _ in flat_numbers(stats.stats if stats else {}):
        if path == "tick":
            continue
        section = sections.get(path.split("/")[0], path.split("/")[0]) if "/" in path else "proxy"
        unit = stat_unit(path)
        per = "" if unit.endswith("interval") else " per interval"
        groups.setdefault(f"{section}: {unit}{per}", []).append(f"stats/{path}")
    return groups


def blueprint(prelude: Prelude, series: Series) -> rrb.Blueprint:
    """Left: one 3-D tab per connected vehicle (ego first), following that vehicle, with
    the map, its own box, path, LiDAR and received points, the boxes it knows of and the
    vehicles without V2V (the collider) as the world has them; the whole map last.
    Right: plots grouped by unit, and the schedule of the interval under the cursor. The
    side panels start collapsed, the time panel as its one-line bar: the views get the
    window."""
    vids = sorted(prelude.missions)
    passive = prelude.passive_vids()
    others = [f"+ world/vehicles/{p}/{part}" for p in passive for part in ("box", "trace")]
    views = [rrb.Spatial3DView(origin="world", name=f"{v} {prelude.missions[v].role}",
                               contents=["+ world", "+ world/map/**", f"+ world/vehicles/{v}/**", *others,
                                         f"- world/vehicles/{v}/objects"],
                               line_grid=rrb.LineGrid3D(visible=True, spacing=GRID_SPACING_M),
                               eye_controls=chase_eye(v, prelude.first_pose(v)))
             for v in vids]
    views.append(rrb.Spatial3DView(origin="world", name="whole map",
                                   contents=["+ world/**", *[f"- world/vehicles/{v}/lidar/**" for v in vids]]))
    ego = [v for v in vids if prelude.missions[v].role == "ego"]
    groups = stat_groups(prelude.stats)
    motion = rrb.Tabs(
        plot("ego-collider distance (m)", ["judge/ego_collider_distance_m"], series),
        plot("ego and collider speed (m/s)", [f"vehicles/{v}/speed_mps" for v in ego + passive], series),
        plot("every vehicle's speed (m/s)", [f"vehicles/{v}/speed_mps" for v in vids + passive], series),
        plot("ego's acceleration (m/s²)", [f"vehicles/{v}/accel_mps2" for v in ego], series),
        plot("received points in the ego's fused view", [f"vehicles/{v}/fused_received_points" for v in ego],
             series))
    channel = rrb.Tabs(*[plot(title, paths, series) for title, paths in groups.items()],
                       plot("bytes sent per vehicle", [f"schedule/tx_bytes/{v}" for v in vids], series),
                       plot("bytes decoded per vehicle", [f"schedule/rx_bytes/{v}" for v in vids], series),
                       plot("control messages heard", [f"vehicles/{v}/heard" for v in vids], series))
    schedule = rrb.Tabs(rrb.TextDocumentView(origin="schedule/interval", name="schedule of this interval"),
                        rrb.TextLogView(origin="/", contents=["+ schedule/air", "+ outcome", "+ events"],
                                        name="on air, outcome, events"))
    return rrb.Blueprint(rrb.Horizontal(rrb.Tabs(*views), rrb.Vertical(motion, channel, schedule,
                                                                       row_shares=[1, 1, 1.3]),
                                        column_shares=[3, 2]),
                         rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"),
                         rrb.TimePanel(state="collapsed", timeline=SIM_TIME))


def build(path: Path, rec: rr.RecordingStream, scan_points: int = DEFAULT_SCAN_POINTS) -> LogStats:
    """Log the whole run at ``path`` into ``rec``: the map and missions first (they are
    fetched after the first tick, so they come a few messages into the log), then every
    message in file order, then the layout (its legends go where the data leaves room)."""
    t0 = time.perf_counter()
    prelude = read_prelude(path)
    stats = LogStats(run_id=run_metadata(path).get("run_id", ""))
    scene = Scene(rec, stats, scan_points)
    if prelude.map is not None:
        scene.map(prelude.map)
    for vid in sorted(prelude.missions):
        scene.mission(prelude.missions[vid])
    for topic, msg in iter_log(path, stats):
        scene.add(topic, msg)
    scene.finish()
    rec.send_blueprint(blueprint(prelude, scene.series))
    rec.flush()
    stats.wall_s = time.perf_counter() - t0
    return stats


# ---------------------------------------------------------------------------- CLI


def has_display() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")) or sys.platform in ("darwin", "win32")


NO_VIEWER = """error: no display here to start a viewer on; choose an output:
  autocast view {mcap} --save run.rrd
      then `rerun run.rrd` where there is a display, or `rerun --serve-web run.rrd` and a browser on port 9090
  autocast view {mcap} --connect rerun+http://HOST:9876/proxy
      stream to a rerun viewer running elsewhere
  autocast export {mcap} --foxglove run.foxglove.mcap
      the run's scene in Foxglove's schemas, for its 3-D panel"""


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="autocast view", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("mcap", type=Path, help="a run's run.mcap (or its run directory)")
    ap.add_argument("--save", type=Path, metavar="OUT.rrd", help="write the rerun recording to a file (headless)")
    ap.add_argument("--spawn", action="store_true", help="start a rerun viewer and stream to it (needs a display)")
    ap.add_argument("--connect", metavar="URL", help="stream to a running viewer, e.g. rerun+http://HOST:9876/proxy")
    ap.add_argument("--foxglove", type=Path, metavar="OUT.mcap",
                    help="also write the run for Foxglove, as `autocast export --foxglove` does")
    ap.add_argument("--scan-points", type=int, default=DEFAULT_SCAN_POINTS,
                    help=f"at most this many LiDAR points per scan, thinned evenly (0: all; default "
                         f"{DEFAULT_SCAN_POINTS})")
    ap.add_argument("--log-level", default="WARNING")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="autocast view: %(levelname)s %(message)s")
    path = args.mcap / "run.mcap" if args.mcap.is_dir() else args.mcap
    if not path.is_file():
        print(f"error: {args.mcap}: no such run.mcap", file=sys.stderr)
        return 2
    spawn = args.spawn or not (args.save or args.connect or args.foxglove)
    if spawn and not has_display():
        print(NO_VIEWER.format(mcap=args.mcap), file=sys.stderr)
        return 2
    if args.foxglove:
        from deploy.record.export import export_foxglove  # the foxglove package only when asked for
        print(f"autocast view: {export_foxglove(path, args.foxglove, args.scan_points).summary()} -> {args.foxglove}")
        if not (args.save or args.connect or args.spawn):
            return 0
    # Writing a file: big chunks (the default flushes every 200 ms of wall time, which on a
    # busy machine makes thousands of tiny chunks that the viewer must compact on load).
    batching = rr.ChunkBatcherConfig(flush_tick=2.0, flush_num_bytes=4 << 20) if args.save else None
    rec = rr.RecordingStream(APP_ID, recording_id=run_metadata(path).get("run_id") or None, batcher_config=batching)
    rec.set_log_time_enabled(False)  # the sim-time and tick timelines only; wall clock means nothing here
    if args.save:
        args.save.parent.mkdir(parents=True, exist_ok=True)
        rec.save(args.save)
    elif args.connect:
        rec.connect_grpc(args.connect)
    else:
        rec.spawn()
    stats = build(path, rec, args.scan_points)
    rec.disconnect()
    where = args.save or args.connect or "the viewer"
    print(f"autocast view: {stats.summary()} -> {where}")
    return 0 if stats.messages else 3


if __name__ == "__main__":
    sys.exit(main())
