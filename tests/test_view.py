"""``autocast view`` and ``autocast export``: a real run's MCAP turned into a rerun
recording that loads back (sizes in metres, a camera per vehicle, a schedule per
interval) and into Foxglove's schemas (decoded with the schemas the file carries and
checked against the run), the JSON mirror, and damaged logs shown as far as they go."""

from __future__ import annotations

import dataclasses
import functools
import json
import subprocess
import sys

import numpy as np
import pytest
import rerun.blueprint as rrb
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from rerun.chunk import RrdReader

from deploy.record import export
from deploy.record.recorder import JSON_ENCODING, JSON_PREFIX, JSON_SCHEMA_ENCODING, McapLog, mirror_file
from deploy.record.runlog import DEFAULT_SCAN_POINTS, read_prelude, received_world, scan_points
from deploy.record.view import POINT_RADIUS_M, Legend, ViewStats, build, iter_log, legend_for, main
from protocol import keys
from protocol.codec import decode, encode
from protocol.messages import ChannelStats, DataBundle, Reception, Scan, Tick, WorldTruth
from vehicle_agent.frames import sensor_to_world

RUN = "view5"
VEHICLES = 5


# The module-scoped fixtures below start runs once per worker: keep the module on one.
pytestmark = pytest.mark.xdist_group("test_view")


@pytest.fixture(scope="module")
def run_mcap(tmp_path_factory):
    """One short real run (5 vehicles, autocast, loopback) shared by every test here."""
    out = tmp_path_factory.mktemp("runs")
    flags = ["--scenario", "left_turn", "--vehicles", str(VEHICLES), "--scheme", "autocast", "--duration", "4"]
    proc = subprocess.run([sys.executable, "-m", "deploy.cli", "run", *flags, "--out", str(out), "--run-id", RUN],
                          capture_output=True, text=True, timeout=180)
    assert proc.returncode in (0, 1), proc.stderr[-2000:]
    return out / RUN / "run.mcap"


@pytest.fixture(scope="module")
def rrd(run_mcap, tmp_path_factory):
    """The run's rerun recording, as ``autocast view --save`` writes it."""
    out = tmp_path_factory.mktemp("rrd") / "run.rrd"
    assert main([str(run_mcap), "--save", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def fox(run_mcap, tmp_path_factory):
    """The run exported for Foxglove, as ``autocast export --foxglove`` writes it."""
    out = tmp_path_factory.mktemp("fox") / "run.foxglove.mcap"
    assert export.main([str(run_mcap), "--foxglove", str(out)]) == 0
    return out


def decoded(path) -> list:
    """The wire messages of a run, decoded with the project's codec."""
    return [decode(data) for topic, data, _ in raw_messages(path)]


def raw_messages(path) -> list[tuple[str, bytes, int]]:
    """The recording's wire messages (the msgpack channels; the JSON mirror left out)."""
    with open(path, "rb") as f:
        return [(ch.topic, m.data, m.log_time) for _, ch, m in make_reader(f).iter_messages()
                if ch.message_encoding == "msgpack"]


def test_view_saves_an_rrd_that_loads_back_with_every_entity(rrd):
    store = RrdReader(rrd).store()
    paths = set(store.schema().entity_paths())
    expected = {"/world/map/lanes", "/world/map/buildings", "/world/map/lights", "/world/vehicles/0/lidar/objects",
                "/world/vehicles/0/fused", "/stats/data/utilization", "/stats/ctrl/delivered_pairs",
                "/judge/ego_collider_distance_m", "/outcome"}
    for v in range(VEHICLES):
        expected |= {f"/world/vehicles/{v}/{part}" for part in ("box", "route", "trace", "trajectory", "received",
                                                                "known")}
        expected |= {f"/schedule/tx_bytes/{v}", f"/vehicles/{v}/speed_mps", f"/vehicles/{v}/accel_mps2"}
    expected.add("/world/vehicles/5/box")  # the passive collider, from the world's ground truth
    assert expected <= paths, sorted(expected - paths)
    timelines = {t for line in str(store.summary()).splitlines() if "/world/vehicles/0/box" in line
                 for t in ("sim_time", "tick") if t in line}
    assert timelines == {"sim_time", "tick"}
    assert RrdReader(rrd).blueprints()  # the layout travels with the file
    received = [v for rb in batches(rrd, "/received", "Points3D:positions")
                for v in rb.column("Points3D:positions").to_pylist()]
    assert any(received), "no vehicle shows received points"
    verify = subprocess.run([sys.executable, "-m", "rerun", "rrd", "verify", str(rrd)], capture_output=True, text=True,
                            timeout=120)
    assert verify.returncode == 0, verify.stderr[-2000:]  # the viewer's own loader accepts it


@functools.cache
def chunks_of(rrd) -> list[tuple[str, object]]:
    """(entity path, record batch) of every chunk of a recording, read once."""
    return [(ch.entity_path, ch.to_record_batch()) for ch in RrdReader(rrd).stream().to_chunks()]


def batches(rrd, suffix: str, column: str) -> list:
    """The record batches of the entities ending in ``suffix`` that hold ``column``."""
    return [rb for path, rb in chunks_of(rrd) if path.endswith(suffix) and column in rb.schema.names]


def values(rrd, entity: str, column: str) -> list:
    """Every instance of ``column`` logged on ``entity``, static and temporal rows alike."""
    return [v for rb in batches(rrd, entity, column) for row in rb.column(column).to_pylist() if row for v in row]


def test_points_are_centimetres_across_and_shared_points_look_like_own_ones(rrd):
    """Radii are in metres (the issue: spheres metres across beside LiDAR points of a few
    centimetres): LiDAR and received points alike, every point marker well under a
    vehicle's width, the traffic lights' heads smaller than a metre."""
    assert 0.02 <= POINT_RADIUS_M <= 0.1
    for entity in ("/world/vehicles/0/lidar/ground", "/world/vehicles/0/lidar/objects",
                   *(f"/world/vehicles/{v}/received" for v in range(VEHICLES))):
        radii = values(rrd, entity, "Points3D:radii")
        assert radii, entity
        np.testing.assert_allclose(radii, POINT_RADIUS_M, rtol=1e-6, err_msg=entity)
    markers = [r for rb in batches(rrd, "", "Points3D:radii") for row in rb.column("Points3D:radii").to_pylist()
               if row for r in row]
    assert markers and max(markers) <= 0.2
    heads = values(rrd, "/world/map/lights", "Boxes3D:half_sizes")
    assert heads and max(max(h) for h in heads) <= 0.5


def test_each_vehicle_has_a_view_whose_camera_follows_it(run_mcap, rrd):
    prelude = read_prelude(run_mcap)
    reader = RrdReader(rrd)
    eyes = {}
    for rb in (ch.to_record_batch() for ch in reader.stream(store=reader.blueprints()[0]).to_chunks()):
        if "EyeControls3D:tracking_entity" in rb.schema.names:
            track, position, target = (rb.column(f"EyeControls3D:{name}").to_pylist()[-1][0]
                                       for name in ("tracking_entity", "position", "look_target"))
            eyes[track.lstrip("/")] = (np.array(position), np.array(target))
    assert set(eyes) == {f"world/vehicles/{v}/box" for v in range(VEHICLES)}
    for v in range(VEHICLES):
        position, target = eyes[f"world/vehicles/{v}/box"]
        x, y, _ = prelude.first_pose(v)
        assert np.hypot(target[0] - x, target[1] - y) < 1.0  # looking at the vehicle where it starts ...
        assert 20.0 <= np.linalg.norm(position - target) <= 60.0  # ... from a few tens of metres


def test_a_legend_goes_where_it_hides_no_data():
    """Worked by hand for a plot of the nominal size (220 px high): two series take
    (2 x 19 + 14) / 220 = 0.236 of its height for the legend."""
    t = np.linspace(0.0, 10.0, 11)
    high, rising = np.column_stack([t, np.full(11, 10.0)]), np.column_stack([t, t])
    # the legend's columns are the right 190 / 700 of the time axis (t >= 7.29): both series
    # are at 8 or more there, above the bottom 0.236 of the range: the bottom-right corner is free
    assert legend_for([high, rising]) == Legend(rrb.Corner2D.RightBottom, True)
    # a line at 0 and a line at 10 the whole time: no corner is free; the legend goes top
    # right over a value axis raised to 10 / (1 - 0.236) x 1.03 = 13.48
    legend = legend_for([high, np.column_stack([t, np.zeros(11)])])
    assert legend.corner == rrb.Corner2D.RightTop and legend.visible
    assert legend.y_range == pytest.approx((0.0, 13.48), abs=0.01)
    assert not legend_for([high]).visible  # one series: the plot's title names it
    assert not legend_for([high] * 7).visible  # more rows than a plot has room for: hover for names


def test_the_schedule_has_one_entry_per_interval_with_every_transmission(run_mcap, rrd):
    stats = [m for m in decoded(run_mcap) if isinstance(m, ChannelStats)]
    docs: dict[int, list[str]] = {}
    for rb in batches(rrd, "/schedule/interval", "TextDocument:text"):
        for tick, text in zip(rb.column("tick").to_pylist(), rb.column("TextDocument:text").to_pylist()):
            docs.setdefault(tick, []).extend(text)
    assert sorted(docs) == sorted(s.tick for s in stats) and all(len(d) == 1 for d in docs.values())
    busy = 0
    for s in stats:
        on_air = s.stats["data"].get("objects") or []
        rows = [line for line in docs[s.tick][0].splitlines() if line.startswith("| ")]
        assert len(rows) == (len(on_air) + 1 if on_air else 0), docs[s.tick][0]  # a header and one row each
        busy += bool(on_air)
    assert busy > len(stats) // 2


def cloud_points(cloud) -> np.ndarray:
    """A decoded foxglove.PointCloud's x, y, z, read through the fields it declares."""
    formats = {7: "<f4", 8: "<f8", 1: "u1"}  # PackedElementField.NumericType: FLOAT32, FLOAT64, UINT8
    dtype = np.dtype({"names": [f.name for f in cloud.fields], "formats": [formats[f.type] for f in cloud.fields],
                      "offsets": [f.offset for f in cloud.fields], "itemsize": cloud.point_stride})
    data = np.frombuffer(cloud.data, dtype=dtype)
    return np.column_stack([data["x"], data["y"], data["z"]]).astype(np.float64)


def test_the_foxglove_export_decodes_with_its_schemas_and_matches_the_run(run_mcap, fox):
    run = decoded(run_mcap)
    prelude = read_prelude(run_mcap)
    truth = {m.tick: m for m in run if isinstance(m, WorldTruth)}
    ticks = [m.tick for m in run if isinstance(m, Tick)]
    with open(fox, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        schema = {ch.topic: summary.schemas[ch.schema_id] for ch in summary.channels.values()}
        scene = sorted(t for t, s in schema.items() if s.encoding == "protobuf")
        got: dict[str, list] = {}
        for _, channel, message, msg in reader.iter_decoded_messages(topics=scene):
            got.setdefault(channel.topic, []).append((message.log_time, msg))
    assert {schema[t].name for t in scene} == {"foxglove.SceneUpdate", "foxglove.PointCloud",
                                                "foxglove.FrameTransforms"}
    assert {t for t, s in schema.items() if s.encoding == JSON_SCHEMA_ENCODING} == \
        {JSON_PREFIX + topic for topic, _, _ in raw_messages(run_mcap)}  # the JSON mirror of every channel

    def sim_time(log_time: int, stamp) -> float:
        assert log_time == stamp.seconds * 1_000_000_000 + stamp.nanos  # log time = the message's sim time
        return log_time / 1e9

    # frames: every tick, every vehicle of the truth on the world, each connected one's LiDAR on it
    assert len(got["/tf"]) == len(truth) == len(ticks)
    tf_at = {}
    for log_time, tf in got["/tf"]:
        t = sim_time(log_time, tf.transforms[0].timestamp)
        w = next(m for m in truth.values() if abs(m.t_sim_s - t) < 1e-9)
        assert {x.child_frame_id for x in tf.transforms} == \
            {export.vehicle_frame(v) for v in w.vids.tolist()} | {export.lidar_frame(v) for v in prelude.missions}
        tf_at[w.tick] = {x.child_frame_id: x for x in tf.transforms}
    # boxes: one scene per tick, an entity per vehicle in its own frame, of its true size
    assert len(got["/vehicles"]) == len(truth)
    for log_time, update in got["/vehicles"]:
        w = next(m for m in truth.values() if abs(m.t_sim_s - sim_time(log_time, update.entities[0].timestamp)) < 1e-9)
        assert [e.frame_id for e in update.entities] == [export.vehicle_frame(v) for v in w.vids.tolist()]
        sizes = np.array([[e.cubes[0].size.x, e.cubes[0].size.y, e.cubes[0].size.z] for e in update.entities])
        np.testing.assert_allclose(sizes, w.size_m, rtol=1e-6)
    assert len(got["/map"]) == 1 and got["/map"][0][0] == 0
    # the ego's scans, in its LiDAR's frame: through the transforms they land where the scan's pose puts them
    scans = [m for m in run if isinstance(m, Scan)]
    lidar = prelude.missions[0].lidar
    assert len(got[export.lidar_topic(0)]) == len(scans) > 0
    for (log_time, cloud), scan in zip(got[export.lidar_topic(0)], scans):
        assert cloud.frame_id == export.lidar_frame(0) and sim_time(log_time, cloud.timestamp) == \
            pytest.approx(scan.t_sim_s)
        body = tf_at[scan.tick][export.vehicle_frame(0)]
        yaw = 2 * np.arctan2(body.rotation.z, body.rotation.w)
        xyz = cloud_points(cloud)
        world = np.column_stack([body.translation.x + np.cos(yaw) * xyz[:, 0] - np.sin(yaw) * xyz[:, 1],
                                 body.translation.y + np.sin(yaw) * xyz[:, 0] + np.cos(yaw) * xyz[:, 1],
                                 xyz[:, 2] + tf_at[scan.tick][export.lidar_frame(0)].translation.z])
        expected = sensor_to_world(scan_points(scan, lidar, DEFAULT_SCAN_POINTS), scan.pose, lidar.mount_height_m)
        np.testing.assert_allclose(world, expected, atol=2e-3)
    # the points each vehicle decoded, in the world, per interval
    bundles = [m for m in run if isinstance(m, DataBundle)]
    for v in range(VEHICLES):
        clouds = got[export.received_topic(v)]
        assert len(clouds) == len(bundles)
        for (_, cloud), b in zip(clouds, bundles):
            world, _ = received_world(b)
            row = int(np.searchsorted(b.receivers, v))
            expected = [world[t] for t in np.flatnonzero(b.decoded[row]).tolist()]
            assert cloud.frame_id == export.WORLD_FRAME
            np.testing.assert_allclose(cloud_points(cloud), np.vstack(expected) if expected else np.zeros((0, 3)),
                                       atol=1e-4)
    assert sum(len(c.data) for _, c in got[export.received_topic(0)]) > 0


def test_every_message_of_the_run_is_shown_once(run_mcap, tmp_path):
    import rerun as rr

    rec = rr.RecordingStream("autocast-test")
    rec.save(tmp_path / "count.rrd")
    stats = build(run_mcap, rec)
    rec.disconnect()
    assert stats.malformed == 0 and stats.damaged is None and stats.run_id == RUN
    assert stats.messages == len(raw_messages(run_mcap))
    assert stats.per_type["Mission"] == VEHICLES and stats.per_type["MapMsg"] == 1
    assert stats.per_type["Tick"] == stats.per_type["Scan"] > 0  # the ego's scans, one per tick


def check(value, schema: dict, where: str = "$") -> None:
    """The subset of JSON Schema the recorder writes: type, properties, required, items."""
    kinds = schema.get("type")
    if kinds is not None:
        kinds = [kinds] if isinstance(kinds, str) else kinds
        python = {"object": dict, "array": list, "string": str, "boolean": bool, "null": type(None),
                  "integer": int, "number": (int, float)}
        ok = any(isinstance(value, python[k]) and not (k in ("integer", "number") and isinstance(value, bool))
                 for k in kinds)
        assert ok, f"{where}: {value!r} is not {kinds}"
    if isinstance(value, dict):
        for name in schema.get("required", []):
            assert name in value, f"{where}: no {name}"
        for name, sub in schema.get("properties", {}).items():
            if name in value:
                check(value[name], sub, f"{where}.{name}")
    if isinstance(value, list) and "items" in schema:
        for i, item in enumerate(value):
            check(item, schema["items"], f"{where}[{i}]")


def test_the_json_mirror_validates_against_its_schemas(run_mcap, tmp_path):
    fox = tmp_path / "run.foxglove.mcap"
    stats = mirror_file(run_mcap, fox)
    raw = raw_messages(run_mcap)
    assert stats.json_messages == stats.messages == len(raw) and stats.json_failed == 0
    with open(fox, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        mirrored = {ch.topic: ch for ch in summary.channels.values() if ch.message_encoding == JSON_ENCODING}
        assert set(mirrored) == {JSON_PREFIX + topic for topic, _, _ in raw}
        assert {summary.schemas[ch.schema_id].encoding for ch in mirrored.values()} == {JSON_SCHEMA_ENCODING}
        schemas = {sid: json.loads(s.data) for sid, s in summary.schemas.items() if s.encoding == JSON_SCHEMA_ENCODING}
        try:
            import jsonschema  # not a dependency: a second opinion where it is installed
            validators = {sid: jsonschema.Draft7Validator(s) for sid, s in schemas.items()}
        except ImportError:
            validators = {}
        copied, ticks = [], []
        for schema, channel, message in reader.iter_messages():
            if channel.message_encoding != JSON_ENCODING:
                copied.append((channel.topic, message.data, message.log_time))
                continue
            doc = json.loads(message.data)
            check(doc, schemas[schema.id])
            if validators:
                validators[schema.id].validate(doc)
            if channel.topic == JSON_PREFIX + keys.world_tick(RUN):
                ticks.append(doc["tick"])
                assert doc["live"] == list(range(VEHICLES))
            if channel.topic == JSON_PREFIX + keys.scan(RUN, 0):
                assert "range_cm" not in doc and "points" not in doc  # big arrays left out of the mirror
    assert copied == raw  # the msgpack channels byte for byte, same times
    assert ticks == list(range(len(ticks))) and ticks


def test_a_corrupted_message_is_counted_and_skipped(run_mcap, tmp_path):
    raw = raw_messages(run_mcap)
    ctrl = next((i for i, (topic, _, _) in enumerate(raw) if topic == keys.net_ctrl_tx(RUN, 1)))
    topic, payload, t = raw[ctrl]
    broken = [
        (topic, payload[: len(payload) // 2], t),  # a valid envelope, a truncated body
        (keys.cmd(RUN, 2), b"\xc1 not msgpack", t),  # garbage: recorded on a schemaless channel
        (keys.net_data_rx(RUN), encode(DataBundle(3, 0.3, np.array([0]), np.ones((1, 1), dtype=bool),
                                                  [Reception(1, 7, 0.01, b"junk")])), t),  # bad object
    ]
    path = tmp_path / "corrupt.mcap"
    with open(path, "wb") as f:
        out = McapLog(f, {"run_id": RUN})
        for item in raw[: ctrl + 1] + broken + raw[ctrl + 1:]:
            out.write(*item)
        out.finish()
    rrd = tmp_path / "corrupt.rrd"
    assert main([str(path), "--save", str(rrd)]) == 0
    import rerun as rr

    rec = rr.RecordingStream("autocast-test")
    rec.save(tmp_path / "again.rrd")
    stats = build(path, rec)
    rec.disconnect()
    assert stats.malformed == 3 and stats.messages == len(raw) + 1  # the bundle decoded; its object did not
    assert set(stats.malformed_topics) == {topic, keys.cmd(RUN, 2), keys.net_data_rx(RUN)}
    assert "/world/vehicles/1/box" in set(RrdReader(rrd).store().schema().entity_paths())


def test_a_truncated_file_is_shown_up_to_the_damage(run_mcap, tmp_path):
    data = run_mcap.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])  # as if the recorder had been SIGKILLed
    stats = ViewStats()
    got = sum(1 for _ in iter_log(cut, stats))
    assert 0 < got < len(raw_messages(run_mcap)) and stats.damaged
    assert main([str(cut), "--save", str(tmp_path / "cut.rrd")]) == 0
    assert (tmp_path / "cut.rrd").stat().st_size > 0


def test_without_a_display_or_a_file_it_says_what_to_do(run_mcap, monkeypatch, capsys):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(sys, "platform", "linux")
    assert main([str(run_mcap)]) == 2  # at once: no viewer is started, nothing is read
    err = capsys.readouterr().err
    assert "--save" in err and "rerun" in err and "--foxglove" in err


def test_a_missing_file_is_refused(tmp_path, capsys):
    assert main([str(tmp_path / "nothing.mcap"), "--save", str(tmp_path / "x.rrd")]) == 2
    assert "no such" in capsys.readouterr().err
    assert export.main([str(tmp_path / "nothing.mcap"), "--foxglove", str(tmp_path / "x.mcap")]) == 2
    assert "no such" in capsys.readouterr().err and not (tmp_path / "x.mcap").exists()


def signed_twin(run_mcap, path):
    """The run's log as a ``--sign`` run records it: every control message, command and
    report in its vehicle's ``Signed`` envelope, and so every control bundle's messages;
    in vehicle 1's slot, after its own, a forgery (it 50 m away, signed by vehicle 2) that
    its receivers heard and dropped, as the proxy relays such frames."""
    from protocol.messages import AgentReport, Command, ControlMsg, CtrlBundle
    from protocol.security import Authority, Signer

    authority = Authority(RUN)
    signers = {v: Signer(authority.issue(v, 0.0, 60.0)) for v in range(VEHICLES)}

    def sealed(msg):
        return signers[msg.vid].seal(msg)

    with open(path, "wb") as f:
        out = McapLog(f, {"run_id": RUN})
        for topic, data, t in raw_messages(run_mcap):
            msg = decode(data)
            if isinstance(msg, (ControlMsg, Command, AgentReport)):
                data = sealed(msg)
            elif isinstance(msg, CtrlBundle):
                own = [decode(m) for m in msg.messages]
                frames = [sealed(m) for m in own]
                senders, heard = msg.senders, msg.heard
                if 1 in senders.tolist():
                    s = senders.tolist().index(1)
                    pose = dataclasses.replace(own[s].pose, x_m=own[s].pose.x_m + 50.0)
                    frames.insert(s + 1, signers[2].seal(dataclasses.replace(own[s], pose=pose)))
                    senders, heard = np.insert(senders, s + 1, 1), np.insert(heard, s + 1, heard[:, s], axis=1)
                data = encode(dataclasses.replace(msg, senders=senders, heard=heard, messages=frames))
            out.write(topic, data, t)
        out.finish()
    return path


def test_a_signed_run_is_shown_as_its_unsigned_twin(run_mcap, fox, tmp_path):
    """The viewers read a signed run's vehicle messages through their envelopes: the same
    paths, heard counts and known boxes as the same run unsigned."""
    import rerun as rr

    twin = signed_twin(run_mcap, tmp_path / "signed.mcap")
    assert sum(topic.endswith("/cmd") for topic, _, _ in raw_messages(twin)) > 0
    fox_twin = tmp_path / "signed.foxglove.mcap"
    assert export.main([str(twin), "--foxglove", str(fox_twin), "--no-json"]) == 0
    paths = [export.path_topic(v) for v in range(VEHICLES)]

    def on(path) -> list[tuple[str, bytes, int]]:
        with open(path, "rb") as f:
            return [(ch.topic, m.data, m.log_time) for _, ch, m in make_reader(f).iter_messages(topics=paths)]

    assert on(fox) and on(fox_twin) == on(fox)
    rrds = {}
    for name, path in (("plain", run_mcap), ("signed", twin)):
        rec = rr.RecordingStream("autocast-test")
        rrds[name] = tmp_path / f"{name}.rrd"
        rec.save(rrds[name])
        stats = build(path, rec)
        rec.disconnect()
        assert stats.malformed == 0
    for v in range(VEHICLES):
        for entity, column in ((f"/vehicles/{v}/heard", "Scalars:scalars"),
                               (f"/world/vehicles/{v}/known", "Boxes3D:centers"),
                               (f"/world/vehicles/{v}/trajectory", "LineStrips3D:strips")):
            plain = values(rrds["plain"], entity, column)
            assert plain and values(rrds["signed"], entity, column) == plain, entity
