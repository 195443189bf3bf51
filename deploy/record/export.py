"""``autocast export RUN --foxglove OUT.mcap``: a run's scene in Foxglove's well-known schemas.

A new file beside the run's log, written with the ``foxglove-sdk`` package: the map,
every vehicle's box and shared path, each LiDAR scan the recorder kept and the points
each vehicle received, as ``foxglove.SceneUpdate``, ``foxglove.PointCloud`` and
``foxglove.FrameTransforms`` messages that Foxglove's 3-D panel draws without any
setup, plus the JSON mirror of every message (``deploy.record.recorder``) for its plots.

Every message's log time is its sim time (``t_sim_s`` in ns; the map at 0), so the
file plays back at the pace of the simulated world, whatever the wall time of the run.
The run's ``run.mcap`` stays as recorded: the raw payloads at their arrival times.
``docs/viewing.md`` lists the topics and frames.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import foxglove
import numpy as np
from foxglove.channels import FrameTransformsChannel, PointCloudChannel, SceneUpdateChannel
from foxglove.messages import (Color, CubePrimitive, FrameTransform, FrameTransforms, LinePrimitive,
                               LinePrimitiveLineType, PackedElementField, PackedElementFieldNumericType, Point3,
                               PointCloud, Quaternion, SceneEntity, SceneUpdate, TextPrimitive, Timestamp, Vector3)
from foxglove.messages import Pose as FoxPose

from deploy.record.recorder import JSON_PREFIX, JSON_SCHEMA_ENCODING, JSON_SCHEMA_PREFIX, json_schema_of, to_json
from deploy.record.runlog import (DEFAULT_SCAN_POINTS, GROUND_Z_M, LogStats, iter_log, read_prelude, received_world,
                           run_metadata, scan_points, stack)
from protocol.codec import MalformedMessage
from protocol.messages import (ControlMsg, DataBundle, EmpBundle, LidarConfig, MapMsg, Mission, Scan, Tick,
                               WorldTruth)
from protocol.security import opened

log = logging.getLogger("deploy.record.export")

WORLD_FRAME = "world"
MAX_SIM_S = 1.8e10  # below 2^64 ns
METADATA_NAME = "autocast.export"

# topics
TF_TOPIC = "/tf"
MAP_TOPIC = "/map"
LIGHTS_TOPIC = "/lights"
VEHICLES_TOPIC = "/vehicles"


def vehicle_frame(vid: int) -> str:
    """A vehicle's body frame: origin on the ground under its centre, x forward, z up."""
    return f"vehicle/{vid}"


def lidar_frame(vid: int) -> str:
    """Its LiDAR's sensor frame (``protocol.messages``: x forward, y left, z up)."""
    return f"vehicle/{vid}/lidar"


def path_topic(vid: int) -> str:
    return f"/vehicles/{vid}/path"


def lidar_topic(vid: int) -> str:
    return f"/vehicles/{vid}/lidar"


def received_topic(vid: int) -> str:
    return f"/vehicles/{vid}/received"


ROLE_RGBA = {"ego": (0.12, 0.43, 1.0), "occluder": (0.47, 0.47, 0.47), "background": (0.16, 0.67, 0.31)}
OTHER_RGBA = (1.0, 0.55, 0.0)  # no mission: the passive collider
RECEIVED_RGB = (230, 25, 25)  # the paper's red for shared points
GROUND_RGB = (85, 85, 85)
ABOVE_GROUND_RGB = (160, 200, 235)
LIGHT_RGBA = {"red": (0.9, 0.12, 0.12), "yellow": (0.94, 0.78, 0.0), "green": (0.12, 0.78, 0.24)}
LIGHT_HEAD_M = (0.4, 0.4, 1.0)
LIGHT_HEIGHT_M = 5.0
LINE_THICKNESS_M = 0.1  # lanes, outlines and paths, in metres (not scale-invariant)

# x, y, z float32 and red, green, blue, alpha uint8: Foxglove colours such a cloud by its
# rgba fields without any settings
POINT_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1"),
                        ("alpha", "u1")])
F32, U8 = PackedElementFieldNumericType.Float32, PackedElementFieldNumericType.Uint8
POINT_FIELDS = [PackedElementField(name=name, offset=POINT_DTYPE.fields[name][1], type=F32 if name in "xyz" else U8)
                for name in POINT_DTYPE.names]


@dataclass
class ExportStats:
    """What an export read and wrote."""

    read: LogStats = field(default_factory=LogStats)
    written: Counter = field(default_factory=Counter)  # topic -> messages
    points: Counter = field(default_factory=Counter)  # point-cloud topic -> points
    wall_s: float = 0.0

    def summary(self) -> str:
        scene = sum(n for topic, n in self.written.items() if not topic.startswith(JSON_PREFIX))
        mirror = sum(n for topic, n in self.written.items() if topic.startswith(JSON_PREFIX))
        text = (f"{self.read.messages} messages of run {self.read.run_id or '?'} in {self.wall_s:.1f} s: "
                f"{scene} scene messages, {mirror} JSON mirrors, {self.read.malformed} malformed skipped")
        return text + (f"; the file is damaged, read up to: {self.read.damaged}" if self.read.damaged else "")


def stamp(t_sim_s: float) -> Timestamp:
    ns = sim_ns(t_sim_s)
    return Timestamp(ns // 1_000_000_000, ns % 1_000_000_000)


def sim_ns(t_sim_s: float) -> int:
    """A log time: the sim time in ns (0 for a time no clock can hold)."""
    return int(round(t_sim_s * 1e9)) if math.isfinite(t_sim_s) and 0 <= t_sim_s < MAX_SIM_S else 0


def yaw_quaternion(yaw_rad: float) -> Quaternion:
    return Quaternion(x=0.0, y=0.0, z=math.sin(yaw_rad / 2), w=math.cos(yaw_rad / 2))


IDENTITY = FoxPose(position=Vector3(x=0.0, y=0.0, z=0.0), orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))


def color(rgb: tuple[float, float, float], a: float = 1.0) -> Color:
    return Color(r=rgb[0], g=rgb[1], b=rgb[2], a=a)


def polyline(xy: np.ndarray, z_m: float, rgba: Color, loop: bool = False) -> LinePrimitive:
    pts = [Point3(x=x, y=y, z=z_m) for x, y in np.asarray(xy, dtype=np.float64).reshape(-1, 2).tolist()]
    return LinePrimitive(type=LinePrimitiveLineType.LineLoop if loop else LinePrimitiveLineType.LineStrip,
                         pose=IDENTITY, thickness=LINE_THICKNESS_M, points=pts, color=rgba)


def cloud(t_sim_s: float, frame_id: str, xyz: np.ndarray, rgb: np.ndarray | tuple[int, int, int]) -> PointCloud:
    """A point cloud of ``xyz`` (metres, in ``frame_id``), coloured per point or all alike."""
    data = np.empty(len(xyz), dtype=POINT_DTYPE)
    data["x"], data["y"], data["z"] = (xyz[:, i] if len(xyz) else [] for i in range(3))
    rgb = np.asarray(rgb, dtype=np.uint8).reshape(-1, 3)
    data["red"], data["green"], data["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    data["alpha"] = 255
    return PointCloud(timestamp=stamp(t_sim_s), frame_id=frame_id, pose=IDENTITY, point_stride=POINT_DTYPE.itemsize,
                      fields=POINT_FIELDS, data=data.tobytes())


class FoxgloveScene:
    """Turns decoded messages into Foxglove messages on a context whose sink is the file."""

    def __init__(self, ctx: foxglove.Context, stats: ExportStats, scan_points: int, json_mirror: bool = True) -> None:
        self.ctx = ctx
        self.stats = stats
        self.scan_points = scan_points
        self.json_mirror = json_mirror
        self.missions: dict[int, Mission] = {}
        self.lights_xy: dict[int, tuple[float, float]] = {}
        self.channels: dict[str, object] = {}
        self.map_written = False

    def channel(self, topic: str, kind: type) -> object:
        ch = self.channels.get(topic)
        if ch is None:
            ch = self.channels[topic] = kind(topic, context=self.ctx)
        return ch

    def write(self, topic: str, kind: type, msg: object, t_sim_s: float) -> None:
        self.channel(topic, kind).log(msg, log_time=sim_ns(t_sim_s))
        self.stats.written[topic] += 1

    def add(self, topic: str, msg: object) -> None:
        self.stats.read.messages += 1
        self.stats.read.per_type[type(msg).__name__] += 1
        recorded, msg = msg, opened(msg)  # a signed message: what it says, unverified (docs/security.md)
        try:
            if msg is None:
                raise MalformedMessage("a signed envelope whose body does not decode")
            if isinstance(msg, MapMsg):
                self.map(msg)
            elif isinstance(msg, Mission):
                self.missions.setdefault(msg.vid, msg)
            elif isinstance(msg, Tick):
                self.lights(msg)
            elif isinstance(msg, WorldTruth):
                self.truth(msg)
            elif isinstance(msg, Scan):
                self.scan(msg)
            elif isinstance(msg, ControlMsg):
                self.path(msg)
            elif isinstance(msg, DataBundle):
                world, _ = received_world(msg)
                for receiver, row in zip(msg.receivers.tolist(), msg.decoded):
                    self.received(receiver, msg.t_sim_s, [world[t] for t in np.flatnonzero(row).tolist()])
            elif isinstance(msg, EmpBundle):
                self.received(msg.receiver, msg.t_sim_s, [np.asarray(s.points_world, np.float64) for s in msg.segments])
        except (MalformedMessage, ValueError) as exc:  # a bad inner payload, a scan that fits no LiDAR
            self.stats.read.count_malformed(topic, exc)
        if self.json_mirror:
            self.mirror(topic, recorded)  # as the recorder's mirror has it: the envelope

    def mirror(self, key: str, msg: object) -> None:
        """The message as JSON on ``json/<key>``, as the recorder's mirror has it."""
        topic = JSON_PREFIX + key
        ch = self.channels.get(topic)
        if ch is None:
            cls = type(msg)
            schema = foxglove.Schema(name=JSON_SCHEMA_PREFIX + cls.__name__, encoding=JSON_SCHEMA_ENCODING,
                                     data=json.dumps(json_schema_of(cls)).encode())
            ch = self.channels[topic] = foxglove.Channel(topic, schema=schema, message_encoding="json",
                                                         context=self.ctx, metadata={"mirror_of": key})
        ch.log(to_json(msg), log_time=sim_ns(msg.t_sim_s))
        self.stats.written[topic] += 1

    def color_of(self, vid: int) -> tuple[float, float, float]:
        mission = self.missions.get(vid)
        return ROLE_RGBA.get(mission.role, OTHER_RGBA) if mission else OTHER_RGBA

    def label_of(self, vid: int) -> str:
        mission = self.missions.get(vid)
        return f"{vid} {mission.role}" if mission else f"{vid} no V2V"

    def lidar_of(self, vid: int) -> LidarConfig:
        mission = self.missions.get(vid)
        return mission.lidar if mission else LidarConfig()

    # -- the world

    def map(self, m: MapMsg) -> None:
        if self.map_written:
            return
        self.map_written = True
        self.lights_xy = {light.light_id: (light.x_m, light.y_m) for light in m.lights}
        b = np.asarray(m.buildings, dtype=np.float64).reshape(-1, 6)  # cx, cy, yaw, length, width, height
        entity = SceneEntity(
            timestamp=stamp(0.0), frame_id=WORLD_FRAME, id="map",
            lines=[polyline(lane.centerline, 0.02, color((0.8, 0.8, 0.8))) for lane in m.lanes]
            + [polyline(p, 0.0, color((0.45, 0.45, 0.45)), loop=True) for p in m.drivable if len(p)]
            + [LinePrimitive(type=LinePrimitiveLineType.LineList, pose=IDENTITY, thickness=LINE_THICKNESS_M,
                             points=[Point3(x=x, y=y, z=z) for x, y in self.lights_xy.values()
                                     for z in (0.0, LIGHT_HEIGHT_M - LIGHT_HEAD_M[2] / 2)],
                             color=color((0.35, 0.35, 0.35)))] * bool(self.lights_xy),
            cubes=[CubePrimitive(pose=FoxPose(position=Vector3(x=cx, y=cy, z=h / 2), orientation=yaw_quaternion(yaw)),
                                 size=Vector3(x=length, y=width, z=h), color=color((0.59, 0.47, 0.35)))
                   for cx, cy, yaw, length, width, h in b.tolist()])
        self.write(MAP_TOPIC, SceneUpdateChannel, SceneUpdate(entities=[entity]), 0.0)

    def lights(self, t: Tick) -> None:
        known = [s for s in t.lights if s.light_id in self.lights_xy]
        if not known:
            return
        cubes = [CubePrimitive(pose=FoxPose(position=Vector3(x=self.lights_xy[s.light_id][0],
                                                             y=self.lights_xy[s.light_id][1], z=LIGHT_HEIGHT_M),
                                            orientation=yaw_quaternion(0.0)),
                               size=Vector3(x=LIGHT_HEAD_M[0], y=LIGHT_HEAD_M[1], z=LIGHT_HEAD_M[2]),
                               color=color(LIGHT_RGBA.get(s.state, (1.0, 1.0, 1.0)))) for s in known]
        self.write(LIGHTS_TOPIC, SceneUpdateChannel, SceneUpdate(entities=[SceneEntity(
            timestamp=stamp(t.t_sim_s), frame_id=WORLD_FRAME, id="lights", cubes=cubes)]), t.t_sim_s)

    def truth(self, w: WorldTruth) -> None:
        """Every vehicle's frame (world -> vehicle/<vid>, and its LiDAR's for connected
        vehicles) and its box, drawn in its own frame, labelled with its role."""
        ts = stamp(w.t_sim_s)
        transforms, entities = [], []
        for vid, (x, y, yaw), (length, width, height) in zip(w.vids.tolist(), w.pose.tolist(), w.size_m.tolist()):
            transforms.append(FrameTransform(timestamp=ts, parent_frame_id=WORLD_FRAME,
                                             child_frame_id=vehicle_frame(vid), translation=Vector3(x=x, y=y, z=0.0),
                                             rotation=yaw_quaternion(yaw)))
            if vid in self.missions:
                transforms.append(FrameTransform(
                    timestamp=ts, parent_frame_id=vehicle_frame(vid), child_frame_id=lidar_frame(vid),
                    translation=Vector3(x=0.0, y=0.0, z=self.lidar_of(vid).mount_height_m),
                    rotation=yaw_quaternion(0.0)))
            entities.append(SceneEntity(
                timestamp=ts, frame_id=vehicle_frame(vid), id=vehicle_frame(vid), frame_locked=True,
                cubes=[CubePrimitive(pose=FoxPose(position=Vector3(x=0.0, y=0.0, z=height / 2),
                                                  orientation=yaw_quaternion(0.0)),
                                     size=Vector3(x=length, y=width, z=height), color=color(self.color_of(vid), 0.5))],
                texts=[TextPrimitive(pose=FoxPose(position=Vector3(x=0.0, y=0.0, z=height + 1.0),
                                                  orientation=yaw_quaternion(0.0)),
                                     billboard=True, font_size=14.0, scale_invariant=True,
                                     color=color((1.0, 1.0, 1.0)), text=self.label_of(vid))]))
        self.write(TF_TOPIC, FrameTransformsChannel, FrameTransforms(transforms=transforms), w.t_sim_s)
        self.write(VEHICLES_TOPIC, SceneUpdateChannel, SceneUpdate(entities=entities), w.t_sim_s)

    # -- one vehicle

    def scan(self, s: Scan) -> None:
        """The scan in its LiDAR's frame: grey ground, light blue above 0.2 m."""
        lidar = self.lidar_of(s.vid)
        xyz = scan_points(s, lidar, self.scan_points)
        above = xyz[:, 2] + lidar.mount_height_m >= GROUND_Z_M
        rgb = np.where(above[:, None], np.array(ABOVE_GROUND_RGB), np.array(GROUND_RGB))
        msg = cloud(s.t_sim_s, lidar_frame(s.vid), xyz, rgb)
        self.write(lidar_topic(s.vid), PointCloudChannel, msg, s.t_sim_s)
        self.stats.points[lidar_topic(s.vid)] += len(xyz)

    def path(self, c: ControlMsg) -> None:
        """The trajectory the vehicle shares (its planned path), in the world frame."""
        traj = np.asarray(c.trajectory, dtype=np.float64).reshape(-1, 3)
        lines = [polyline(traj[:, :2], 0.3, color(self.color_of(c.vid)))] if len(traj) > 1 else []
        self.write(path_topic(c.vid), SceneUpdateChannel, SceneUpdate(entities=[SceneEntity(
            timestamp=stamp(c.t_sim_s), frame_id=WORLD_FRAME, id=f"path/{c.vid}", lines=lines)]), c.t_sim_s)

    def received(self, vid: int, t_sim_s: float, parts: list[np.ndarray]) -> None:
        """What the vehicle decoded this interval, in the world frame, red."""
        xyz = stack(parts)
        self.write(received_topic(vid), PointCloudChannel, cloud(t_sim_s, WORLD_FRAME, xyz, RECEIVED_RGB), t_sim_s)
        self.stats.points[received_topic(vid)] += len(xyz)


def export_foxglove(src: Path, dst: Path, scan_points: int = DEFAULT_SCAN_POINTS, json_mirror: bool = True,
                    ) -> ExportStats:
    """Write ``dst``: the run at ``src`` in Foxglove's schemas, on the sim-time clock."""
    t0 = time.perf_counter()
    stats = ExportStats(read=LogStats(run_id=run_metadata(src).get("run_id", "")))
    prelude = read_prelude(src)
    ctx = foxglove.Context()
    dst.parent.mkdir(parents=True, exist_ok=True)
    with foxglove.open_mcap(dst, allow_overwrite=True, context=ctx) as writer:
        writer.write_metadata(METADATA_NAME, {"source": src.name, "run_id": stats.read.run_id,
                                              "log_time": "sim time (t_sim_s, ns)", "scan_points": str(scan_points)})
        meta = run_metadata(src)
        if meta:
            writer.write_metadata("autocast", meta)
        scene = FoxgloveScene(ctx, stats, scan_points, json_mirror)
        scene.missions.update(prelude.missions)
        if prelude.map is not None:
            scene.map(prelude.map)
        for topic, msg in iter_log(src, stats.read):
            scene.add(topic, msg)
    stats.wall_s = time.perf_counter() - t0
    return stats


# ---------------------------------------------------------------------------- CLI


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="autocast export", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("mcap", type=Path, help="a run's run.mcap (or its run directory)")
    ap.add_argument("--foxglove", type=Path, metavar="OUT.mcap", required=True,
                    help="write the scene in Foxglove's schemas, with the JSON mirror, to this MCAP file")
    ap.add_argument("--scan-points", type=int, default=DEFAULT_SCAN_POINTS,
                    help=f"at most this many LiDAR points per scan, thinned evenly (0: all; default "
                         f"{DEFAULT_SCAN_POINTS})")
    ap.add_argument("--no-json", action="store_true", help="leave out the JSON mirror (the scene only)")
    ap.add_argument("--log-level", default="WARNING")
    return ap.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="autocast export: %(levelname)s %(message)s")
    path = args.mcap / "run.mcap" if args.mcap.is_dir() else args.mcap
    if not path.is_file():
        print(f"error: {args.mcap}: no such run.mcap", file=sys.stderr)
        return 2
    stats = export_foxglove(path, args.foxglove, args.scan_points, json_mirror=not args.no_json)
    print(f"autocast export: {stats.summary()} -> {args.foxglove}")
    return 0 if stats.read.messages else 3


if __name__ == "__main__":
    sys.exit(main())
