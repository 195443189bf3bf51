"""``autocast view RUN.mcap [--save out.rrd | --spawn | --connect URL] [--foxglove out.mcap]``.

Turns a run's MCAP log into a rerun recording on the sim-time timeline: the map, every
vehicle's box, route, shared trajectory and trace, the ego's LiDAR (every vehicle's
with ``--scans all``), the points each vehicle received (red, as in the paper's
figures), the ego's fused view, the schedule of each interval and the channel
statistics as time series. ``docs/viewing.md`` lists the entities.

The log is read message by message (the MCAP reader holds one chunk at a time) and
logged as it goes, so memory does not grow with the run. A message that does not
decode is skipped and counted; a damaged file is shown up to the damage.
``--foxglove`` writes a copy of the log with a JSON mirror of every message (see
``deploy.recorder``), which Foxglove and other MCAP tools can read.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import math
import os
import sys
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
from mcap.reader import make_reader

from deploy.recorder import MESSAGE_ENCODING, METADATA_NAME, mirror_file, read_messages, read_metadata
from protocol.codec import MalformedMessage, decode
from protocol.security import opened
from protocol.messages import (Signed, AgentReport, ChannelStats, Command, ControlMsg, CtrlBundle, DataBundle, DataTx,
                               EmpBundle, EmpUpload, LidarConfig, MapMsg, Mission, Outcome, Pose, Scan, Tick,
                               VehicleSpec, WorldTruth)
from vehicle_agent.frames import sensor_to_world
from vehicle_agent.payload import decode_object

log = logging.getLogger("deploy.view")

APP_ID = "autocast"
SIM_TIME = "sim_time"  # seconds of simulated time
TICK = "tick"  # decision interval number
DEFAULT_SCAN_POINTS = 20_000
CAR = VehicleSpec(4.6, 1.9, 1.5, 2.8, 3.0, 7.5, 0.6)  # a vehicle whose mission is not in the log

ROLE_COLORS = {"ego": (30, 110, 255), "occluder": (120, 120, 120), "background": (40, 170, 80)}
OTHER_COLOR = (255, 140, 0)
RECEIVED_COLOR = (230, 25, 25)
FUSED_COLOR = (255, 190, 0)
GROUND_COLOR = (85, 85, 85)
ABOVE_GROUND_COLOR = (160, 200, 235)
LIGHT_COLORS = {"red": (230, 30, 30), "yellow": (240, 200, 0), "green": (30, 200, 60)}
GROUND_Z_M = 0.2  # LiDAR returns below this height are drawn as ground


@dataclass
class ViewStats:
    """What a view read: messages per type, what it skipped, and whether the file ended early."""

    messages: int = 0
    per_type: Counter = field(default_factory=Counter)
    malformed: int = 0
    malformed_topics: Counter = field(default_factory=Counter)
    other_encoding: int = 0  # JSON mirrors and anything else not msgpack: skipped
    damaged: str | None = None  # why reading stopped early, if it did
    run_id: str = ""
    wall_s: float = 0.0

    def summary(self) -> str:
        text = (f"{self.messages} messages of run {self.run_id or '?'} in {self.wall_s:.1f} s, "
                f"{self.malformed} malformed skipped")
        return text + (f"; the file is damaged, read up to: {self.damaged}" if self.damaged else "")


# ---------------------------------------------------------------------------- reading


def iter_log(path: Path, stats: ViewStats, topics: list[str] | None = None) -> Iterator[tuple[str, object]]:
    """(topic, decoded message) for every msgpack message, in the order they were recorded.

    Malformed payloads are counted in ``stats`` and skipped; an error of the file itself
    (truncated, bad chunk) ends the iteration and is recorded in ``stats.damaged``.
    """
    with open(path, "rb") as f:
        try:
            messages = read_messages(f, topics)
            while True:
                try:
                    _, channel, message = next(messages)
                except StopIteration:
                    return
                if channel.message_encoding != MESSAGE_ENCODING:
                    stats.other_encoding += 1
                    continue
                try:
                    yield channel.topic, decode(message.data)
                except MalformedMessage as exc:
                    count_malformed(stats, channel.topic, exc)
        except Exception as exc:  # the mcap reader raises many unrelated types for a damaged file
            stats.damaged = f"{type(exc).__name__}: {exc}"
            log.warning("%s: stopped reading: %s", path, stats.damaged)


def count_malformed(stats: ViewStats, topic: str, exc: Exception) -> None:
    stats.malformed += 1
    stats.malformed_topics[topic] += 1
    if stats.malformed_topics[topic] == 1:
        log.warning("malformed message on %s skipped: %s", topic, exc)


def static_topics(path: Path) -> list[str]:
    """The topics of the map and the missions, from the file's summary (none if unfinalized)."""
    try:
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
    except Exception:  # a damaged or unfinalized file: no summary
        return []
    if summary is None:
        return []
    names = {MapMsg.__name__, Mission.__name__}
    return sorted({ch.topic for ch in summary.channels.values()
                   if ch.message_encoding == MESSAGE_ENCODING and ch.schema_id in summary.schemas
                   and summary.schemas[ch.schema_id].name in names})


def run_id_of(path: Path) -> str:
    with open(path, "rb") as f:
        return read_metadata(f).get(METADATA_NAME, {}).get("run_id", "")


# ---------------------------------------------------------------------------- the scene


def box_of(pose: Pose, spec: VehicleSpec, color: tuple[int, int, int], label: str) -> rr.Boxes3D:
    """A vehicle's body: the pose is the body centre on the ground, yaw about +z."""
    return rr.Boxes3D(centers=[[pose.x_m, pose.y_m, spec.height_m / 2]],
                      half_sizes=[[spec.length_m / 2, spec.width_m / 2, spec.height_m / 2]],
                      rotation_axis_angles=[rr.RotationAxisAngle(axis=[0, 0, 1], radians=pose.yaw_rad)],
                      colors=[color], labels=[label])


def xy_to_3d(xy: np.ndarray, z_m: float) -> np.ndarray:
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    return np.column_stack([xy, np.full(len(xy), z_m)])


def decimate(points: np.ndarray, max_points: int) -> np.ndarray:
    if max_points <= 0 or len(points) <= max_points:
        return points
    return points[:: math.ceil(len(points) / max_points)]


def scan_points(scan: Scan, lidar: LidarConfig, max_points: int) -> np.ndarray:
    """About ``max_points`` sensor-frame points of a scan, thinned evenly in azimuth.

    A scan is a range image (azimuth x beam): every k-th azimuth column is the range
    image of a LiDAR with ``azimuth_steps / k`` steps, so it is thinned before the points
    are computed.
    """
    rays = int(np.count_nonzero(scan.range_cm))
    k = 1
    if 0 < max_points < rays:
        k = next((d for d in range(math.ceil(rays / max_points), lidar.azimuth_steps + 1)
                  if lidar.azimuth_steps % d == 0), 1)
    if k > 1:
        scan = dataclasses.replace(scan, range_cm=np.ascontiguousarray(scan.range_cm[::k]))
        lidar = dataclasses.replace(lidar, azimuth_steps=lidar.azimuth_steps // k)
    return scan.points(lidar)


class Series:
    """Scalar time series, sent in columns every ``flush_every`` ticks instead of one
    ``log`` call per value (tens of values per tick)."""

    def __init__(self, rec: rr.RecordingStream, flush_every: int = 50) -> None:
        self.rec = rec
        self.flush_every = flush_every
        self.values: dict[str, tuple[list[float], list[int], list[float]]] = {}
        self.first_tick: int | None = None

    def add(self, path: str, t_sim_s: float, tick: int, value: float) -> None:
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
        self.values.clear()
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


class Scene:
    """Logs decoded messages as rerun entities; keeps what later messages need (the map's
    lights, missions, traces)."""

    def __init__(self, rec: rr.RecordingStream, stats: ViewStats, scan_points: int = DEFAULT_SCAN_POINTS) -> None:
        self.rec = rec
        self.stats = stats
        self.scan_points = scan_points
        self.missions: dict[int, Mission] = {}
        self.lights_xy: dict[int, tuple[float, float]] = {}
        self.trace: dict[int, list[tuple[float, float]]] = {}
        self.last_pose_tick: dict[int, int] = {}
        self.live: set[int] = set()
        self.static_logged: set[str] = set()  # topics of the map and missions already logged
        self.series = Series(rec)
        self.now = (0.0, 0)  # sim time and tick of the message being logged
        self.handlers = {MapMsg: self.map, Mission: self.mission, Tick: self.tick, WorldTruth: self.truth,
                         Scan: self.scan,
                         Command: self.command, ControlMsg: self.control, CtrlBundle: self.ctrl_bundle,
                         DataTx: self.data_tx, DataBundle: self.data_bundle, ChannelStats: self.channel_stats,
                         AgentReport: self.report, Outcome: self.outcome, EmpUpload: self.emp_upload,
                         EmpBundle: self.emp_bundle}

    def add(self, topic: str, msg: object) -> None:
        if isinstance(msg, Signed):  # a vehicle's signed message: shown as what it says (not checked here)
            msg = opened(msg)
        handler = self.handlers.get(type(msg))
        if handler is None:
            return
        self.stats.messages += 1
        self.stats.per_type[type(msg).__name__] += 1
        if isinstance(msg, (MapMsg, Mission)):
            if topic in self.static_logged:
                return
            self.static_logged.add(topic)
        else:
            self.rec.set_time(SIM_TIME, duration=msg.t_sim_s)
            self.rec.set_time(TICK, sequence=msg.tick)
            self.now = (msg.t_sim_s, msg.tick)
        try:
            handler(msg)
        except (MalformedMessage, ValueError) as exc:  # a bad inner payload, a scan that fits no LiDAR
            count_malformed(self.stats, topic, exc)

    def scalar(self, path: str, value: float) -> None:
        self.series.add(path, *self.now, float(value))

    def finish(self) -> None:
        self.series.flush()

    # -- world

    def map(self, m: MapMsg) -> None:
        rec = self.rec
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        rec.log("world/map/lanes", rr.LineStrips3D([xy_to_3d(lane.centerline, 0.02) for lane in m.lanes],
                                                   colors=[(200, 200, 200)], radii=0.05,
                                                   labels=[lane.lane_id for lane in m.lanes]), static=True)
        outlines = [xy_to_3d(np.vstack([p, p[:1]]), 0.0) for p in m.drivable if len(p)]
        rec.log("world/map/drivable", rr.LineStrips3D(outlines, colors=[(110, 110, 110)], radii=0.08), static=True)
        b = np.asarray(m.buildings, dtype=np.float64).reshape(-1, 6)  # cx, cy, yaw, length, width, height
        rec.log("world/map/buildings", rr.Boxes3D(
            centers=np.column_stack([b[:, 0], b[:, 1], b[:, 5] / 2]), half_sizes=b[:, 3:6] / 2,
            rotation_axis_angles=[rr.RotationAxisAngle(axis=[0, 0, 1], radians=yaw) for yaw in b[:, 2]],
            colors=[(150, 120, 90)], fill_mode="solid"), static=True)
        self.lights_xy = {light.light_id: (light.x_m, light.y_m) for light in m.lights}

    def mission(self, m: Mission) -> None:
        self.missions[m.vid] = m
        self.rec.log(f"world/vehicles/{m.vid}/route", rr.LineStrips3D([xy_to_3d(m.route, 0.05)],
                                                                        colors=[self.color_of(m.vid)], radii=0.1),
                     static=True)

    def tick(self, t: Tick) -> None:
        for vid in sorted(self.live - set(t.live)):  # its agent died: the vehicle brakes to a stop, unseen
            self.rec.log("events", rr.TextLog(f"tick {t.tick}: vehicle {vid} left play; its box stays where it was "
                                              "last reported", level=rr.TextLogLevel.WARN))
        self.live = set(t.live)
        known = [s for s in t.lights if s.light_id in self.lights_xy]
        if known:
            self.rec.log("world/map/lights", rr.Points3D(
                [[*self.lights_xy[s.light_id], 5.0] for s in known], radii=0.8,
                colors=[LIGHT_COLORS.get(s.state, (255, 255, 255)) for s in known]))

    def truth(self, w: WorldTruth) -> None:
        """Every vehicle's true box, the passive collider's included (it has no scan or
        control message of its own)."""
        for vid, (x, y, yaw), speed, (length, width, height) in zip(w.vids.tolist(), w.pose.tolist(),
                                                                    w.speed_mps.tolist(), w.size_m.tolist()):
            spec = dataclasses.replace(CAR, length_m=length, width_m=width, height_m=height)
            self.pose(vid, w.tick, Pose(x, y, yaw), speed, spec)

    # -- one vehicle

    def color_of(self, vid: int) -> tuple[int, int, int]:
        mission = self.missions.get(vid)
        return ROLE_COLORS.get(mission.role, OTHER_COLOR) if mission else OTHER_COLOR

    def pose(self, vid: int, tick: int, pose: Pose, speed_mps: float | None, spec: VehicleSpec | None = None) -> None:
        """A vehicle's box and trace, once per tick (the world's truth, its scan and its
        control message carry the same pose; the first to arrive is drawn)."""
        if self.last_pose_tick.get(vid, -1) >= tick:
            return
        self.last_pose_tick[vid] = tick
        mission = self.missions.get(vid)
        label = f"{vid} {mission.role}" if mission else f"{vid} (no V2V)"
        spec = spec or (mission.spec if mission else CAR)
        self.rec.log(f"world/vehicles/{vid}/box", box_of(pose, spec, self.color_of(vid), label))
        trace = self.trace.setdefault(vid, [])
        trace.append((pose.x_m, pose.y_m))
        if len(trace) > 1:
            self.rec.log(f"world/vehicles/{vid}/trace", rr.LineStrips3D([xy_to_3d(np.array(trace), 0.1)],
                                                                         colors=[self.color_of(vid)], radii=0.15))
        if speed_mps is not None:
            self.scalar(f"vehicles/{vid}/speed_mps", speed_mps)

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
                                                                         radii=0.04))
        self.rec.log(f"world/vehicles/{s.vid}/lidar/objects", rr.Points3D(world[~ground],
                                                                          colors=[ABOVE_GROUND_COLOR], radii=0.05))

    def command(self, c: Command) -> None:
        self.scalar(f"vehicles/{c.vid}/accel_mps2", c.accel_mps2)
        self.scalar(f"vehicles/{c.vid}/steer_rad", c.steer_rad)

    def control(self, c: ControlMsg) -> None:
        self.pose(c.vid, c.tick, c.pose, c.speed_mps)
        color = self.color_of(c.vid)
        traj = np.asarray(c.trajectory, dtype=np.float64).reshape(-1, 3)
        self.rec.log(f"world/vehicles/{c.vid}/trajectory", rr.LineStrips3D(
            [xy_to_3d(traj[:, :2], 0.3)] if len(traj) > 1 else [], colors=[color], radii=0.25))
        om = c.objects
        self.rec.log(f"world/vehicles/{c.vid}/objects", rr.Points3D(
            xy_to_3d(om.centroid_xy, 1.0), radii=0.4, colors=[color],
            labels=[f"{c.vid}/{oid}: {size} B" for oid, size in zip(om.object_id.tolist(), om.size_bytes.tolist())],
            show_labels=False))

    def ctrl_bundle(self, b: CtrlBundle) -> None:
        for receiver, heard in zip(b.receivers.tolist(), b.heard.sum(axis=1).tolist()):
            self.scalar(f"vehicles/{receiver}/heard", heard)

    def report(self, r: AgentReport) -> None:
        self.rec.log(f"world/vehicles/{r.vid}/fused", rr.Points3D(xy_to_3d(r.fused_xy, 0.05), colors=[FUSED_COLOR],
                                                                   radii=0.06))
        self.scalar(f"vehicles/{r.vid}/fused_received_points", r.received_points)
        self.scalar(f"vehicles/{r.vid}/braking", float(r.braking))

    # -- the channel

    def data_tx(self, d: DataTx) -> None:
        """Who sends what in which slot: one line per sender with a non-empty schedule."""
        size = sum(len(t.payload) for t in d.transmissions)
        self.scalar(f"schedule/tx_bytes/{d.vid}", size)
        if d.transmissions:
            slots = ", ".join(f"obj {t.object_id} @ {t.start_s * 1e3:.1f} ms ({len(t.payload)} B)"
                              for t in d.transmissions)
            self.rec.log("schedule/tx", rr.TextLog(f"tick {d.tick} v{d.vid}: {slots}"))

    def data_bundle(self, b: DataBundle) -> None:
        """Each receiver's decoded objects, in the world frame (T_s V_s of each sender)."""
        world = []  # each reception decoded once, shared by the receivers that got it
        for r in b.receptions:
            obj = decode_object(r.payload)
            world.append(sensor_to_world(obj.points_sensor, obj.sender_pose, obj.mount_height_m))
        size = np.array([len(r.payload) for r in b.receptions], dtype=np.int64)
        for receiver, row in zip(b.receivers.tolist(), b.decoded):
            got = np.flatnonzero(row).tolist()
            self.received(receiver, [world[t] for t in got])
            self.scalar(f"schedule/rx_bytes/{receiver}", int(size[got].sum()))

    def received(self, vid: int, parts: list[np.ndarray]) -> None:
        points = np.vstack(parts) if parts else np.zeros((0, 3))
        self.rec.log(f"world/vehicles/{vid}/received", rr.Points3D(points, colors=[RECEIVED_COLOR], radii=0.08))

    def emp_upload(self, u: EmpUpload) -> None:
        self.pose(u.vid, u.tick, u.pose, None)

    def emp_bundle(self, b: EmpBundle) -> None:
        self.received(b.receiver, [np.asarray(s.points_world, dtype=np.float64) for s in b.segments])

    def channel_stats(self, c: ChannelStats) -> None:
        for path, value in flat_numbers(c.stats):
            if path != "tick":
                self.scalar(f"stats/{path}", value)
        on_air = (c.stats.get("data") or {}).get("objects") or []
        if on_air:  # [sender, object, start_s, end_s, receivers decoded, receivers in range]
            self.rec.log("schedule/air", rr.TextLog(f"tick {c.tick}: " + ", ".join(
                f"v{o[0]}/obj {o[1]} {o[2] * 1e3:.1f}-{o[3] * 1e3:.1f} ms -> {o[4]}/{o[5]}" for o in on_air)))

    def outcome(self, o: Outcome) -> None:
        r = o.result
        series = np.asarray(r.get("distance_series_m") or [], dtype=np.float64).reshape(-1, 2)
        if len(series):
            self.rec.send_columns("judge/ego_collider_distance_m",
                                  indexes=[rr.TimeColumn(SIM_TIME, duration=series[:, 0])],
                                  columns=rr.Scalars.columns(scalars=series[:, 1]))
        brief = {k: v for k, v in r.items() if not isinstance(v, (list, dict))}
        level = rr.TextLogLevel.INFO if r.get("outcome") == "safe" else rr.TextLogLevel.WARN
        self.rec.log("outcome", rr.TextLog(" ".join(f"{k}={v}" for k, v in brief.items()), level=level))


# ---------------------------------------------------------------------------- building


def blueprint(vids: list[int]) -> rrb.Blueprint:
    """One 3-D tab per vehicle (the map, every box and path, that vehicle's points), the
    channel's series and the schedule."""
    common = ["+ world", "+ world/map/**"] + [f"+ world/vehicles/{v}/{part}" for v in vids
                                               for part in ("box", "trajectory", "trace")]
    views = [rrb.Spatial3DView(origin="world", name=f"vehicle {v}", contents=[*common, f"+ world/vehicles/{v}/**"])
             for v in vids] or [rrb.Spatial3DView(origin="world", name="world")]
    return rrb.Blueprint(rrb.Horizontal(
        rrb.Tabs(*views),
        rrb.Vertical(rrb.TimeSeriesView(origin="stats", name="channel"),
                     rrb.TimeSeriesView(origin="schedule", name="bytes per sender"),
                     rrb.TimeSeriesView(origin="judge", name="ego-collider distance"),
                     rrb.TextLogView(origin="/", contents=["+ schedule/**", "+ outcome", "+ events"],
                                     name="schedule")),
        column_shares=[3, 2]), collapse_panels=False)


def build(path: Path, rec: rr.RecordingStream, scan_points: int = DEFAULT_SCAN_POINTS) -> ViewStats:
    """Log the whole run at ``path`` into ``rec``; the map and missions first (they are
    fetched after the first tick, so they come late in the log)."""
    t0 = time.perf_counter()
    scene = Scene(rec, ViewStats(), scan_points)
    static = static_topics(path)
    if static:  # (an empty topic list would mean every topic)
        for topic, msg in iter_log(path, scene.stats, topics=static):
            scene.add(topic, msg)
    stats = scene.stats = ViewStats(run_id=run_id_of(path))  # the main pass counts the map and missions again
    rec.send_blueprint(blueprint(sorted(scene.missions)))
    for topic, msg in iter_log(path, stats):
        scene.add(topic, msg)
    scene.finish()
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
  autocast view {mcap} --foxglove run.foxglove.mcap
      a copy of the log that Foxglove can open (JSON channels)"""


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="autocast view", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("mcap", type=Path, help="a run's run.mcap (or its run directory)")
    ap.add_argument("--save", type=Path, metavar="OUT.rrd", help="write the rerun recording to a file (headless)")
    ap.add_argument("--spawn", action="store_true", help="start a rerun viewer and stream to it (needs a display)")
    ap.add_argument("--connect", metavar="URL", help="stream to a running viewer, e.g. rerun+http://HOST:9876/proxy")
    ap.add_argument("--foxglove", type=Path, metavar="OUT.mcap",
                    help="also write a copy of the log with JSON channels, for Foxglove")
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
        s = mirror_file(path, args.foxglove)
        print(f"autocast view: {args.foxglove}: {s.messages} messages, {s.json_messages} with a JSON mirror "
              f"({s.malformed + s.json_failed} without)")
        if not (args.save or args.connect or args.spawn):
            return 0
    # Writing a file: big chunks (the default flushes every 200 ms of wall time, which on a
    # busy machine makes thousands of tiny chunks that the viewer must compact on load).
    batching = rr.ChunkBatcherConfig(flush_tick=2.0, flush_num_bytes=4 << 20) if args.save else None
    rec = rr.RecordingStream(APP_ID, recording_id=run_id_of(path) or None, batcher_config=batching)
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
