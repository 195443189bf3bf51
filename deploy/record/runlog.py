"""Reading a run's MCAP for the viewers: ``autocast view`` (rerun) and ``autocast export``
(Foxglove) read the log the same way and draw the same points.

Messages come decoded in file order (= arrival order), one MCAP chunk in memory at a
time; a malformed payload is counted and skipped, a damaged file is read up to the
damage. ``read_prelude`` fetches what a layout needs before the main pass: the map, the
missions, the first ground truth and the first channel statistics.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.reader import make_reader

from deploy.record.recorder import MESSAGE_ENCODING, METADATA_NAME, read_messages, read_metadata
from protocol.codec import MalformedMessage, decode
from protocol.messages import (ChannelStats, DataBundle, LidarConfig, MapMsg, Mission, Scan, WorldTruth)
from vehicle_agent.frames import sensor_to_world
from vehicle_agent.payload import decode_object

log = logging.getLogger("deploy.record.runlog")

DEFAULT_SCAN_POINTS = 20_000
GROUND_Z_M = 0.2  # LiDAR returns below this height (world z) are drawn as ground


@dataclass
class LogStats:
    """What a reader read: messages per type, what it skipped, and whether the file ended early."""

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

    def count_malformed(self, topic: str, exc: Exception) -> None:
        self.malformed += 1
        self.malformed_topics[topic] += 1
        if self.malformed_topics[topic] == 1:
            log.warning("malformed message on %s skipped: %s", topic, exc)


def iter_log(path: Path, stats: LogStats, topics: list[str] | None = None) -> Iterator[tuple[str, object]]:
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
                    stats.count_malformed(channel.topic, exc)
        except Exception as exc:  # the mcap reader raises many unrelated types for a damaged file
            stats.damaged = f"{type(exc).__name__}: {exc}"
            log.warning("%s: stopped reading: %s", path, stats.damaged)


def topics_by_schema(path: Path) -> dict[str, list[str]]:
    """Schema name -> the msgpack topics of that type, from the file's summary ({} if the
    file has none: damaged or unfinalized)."""
    try:
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
    except Exception:  # a damaged or unfinalized file: no summary
        return {}
    if summary is None:
        return {}
    out: dict[str, list[str]] = {}
    for ch in summary.channels.values():
        if ch.message_encoding == MESSAGE_ENCODING and ch.schema_id in summary.schemas:
            out.setdefault(summary.schemas[ch.schema_id].name, []).append(ch.topic)
    return {name: sorted(topics) for name, topics in out.items()}


def run_metadata(path: Path) -> dict[str, str]:
    with open(path, "rb") as f:
        return read_metadata(f).get(METADATA_NAME, {})


@dataclass
class Prelude:
    """What a layout is built from before the main pass: the map and missions (fetched
    by query after the first tick, so a few messages into the log), the first ground
    truth (who is in play, where) and the first channel statistics (which series exist)."""

    map: MapMsg | None = None
    missions: dict[int, Mission] = field(default_factory=dict)
    truth: WorldTruth | None = None
    stats: ChannelStats | None = None

    def passive_vids(self) -> list[int]:
        """Vehicles in the ground truth without a mission: the passive collider and any
        other traffic that takes no part in V2V."""
        return [] if self.truth is None else sorted(set(self.truth.vids.tolist()) - set(self.missions))

    def first_pose(self, vid: int) -> tuple[float, float, float] | None:
        if self.truth is None:
            return None
        rows = np.flatnonzero(self.truth.vids == vid)
        return tuple(float(v) for v in self.truth.pose[rows[0]]) if len(rows) else None


def read_prelude(path: Path) -> Prelude:
    """The map, the missions, and the first truth and statistics, read through the file's
    index (nothing if it has none; the main pass then meets them in order)."""
    by_schema = topics_by_schema(path)
    wanted = {name: by_schema.get(name, []) for name in
              (MapMsg.__name__, Mission.__name__, WorldTruth.__name__, ChannelStats.__name__)}
    topics = sorted({t for ts in wanted.values() for t in ts})
    prelude = Prelude()
    if not topics:  # (an empty topic list would mean every topic)
        return prelude
    n_missions = len(wanted[Mission.__name__])
    for _, msg in iter_log(path, LogStats(), topics=topics):
        if isinstance(msg, MapMsg) and prelude.map is None:
            prelude.map = msg
        elif isinstance(msg, Mission):
            prelude.missions.setdefault(msg.vid, msg)
        elif isinstance(msg, WorldTruth) and prelude.truth is None:
            prelude.truth = msg
        elif isinstance(msg, ChannelStats) and prelude.stats is None:
            prelude.stats = msg
        done = (prelude.map is not None or not wanted[MapMsg.__name__]) and len(prelude.missions) >= n_missions
        if done and (prelude.truth is not None or not wanted[WorldTruth.__name__]) and \
                (prelude.stats is not None or not wanted[ChannelStats.__name__]):
            break
    return prelude


# ---------------------------------------------------------------------------- points


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


def received_world(bundle: DataBundle) -> tuple[list[np.ndarray], np.ndarray]:
    """Each reception of a data bundle decoded once and taken to the world with its
    sender's pose (T_s V_s), and each reception's payload size; a payload that does not
    decode raises ``MalformedMessage``."""
    world = []
    for r in bundle.receptions:
        obj = decode_object(r.payload)
        world.append(sensor_to_world(obj.points_sensor, obj.sender_pose, obj.mount_height_m))
    return world, np.array([len(r.payload) for r in bundle.receptions], dtype=np.int64)


def stack(parts: list[np.ndarray]) -> np.ndarray:
    return np.vstack(parts) if parts else np.zeros((0, 3))
