"""``autocast view``: a real run's MCAP turned into a rerun recording that loads back, the
JSON mirror that Foxglove reads, and damaged logs shown as far as they go."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from mcap.reader import make_reader
from rerun.chunk import RrdReader

from deploy.recorder import JSON_ENCODING, JSON_PREFIX, JSON_SCHEMA_ENCODING, McapLog, mirror_file
from deploy.view import ViewStats, build, iter_log, main
from protocol import keys
from protocol.codec import encode
from protocol.messages import DataBundle, Reception

RUN = "view5"
VEHICLES = 5


@pytest.fixture(scope="module")
def run_mcap(tmp_path_factory):
    """One short real run (5 vehicles, autocast, loopback) shared by every test here."""
    out = tmp_path_factory.mktemp("runs")
    flags = ["--scenario", "left_turn", "--vehicles", str(VEHICLES), "--scheme", "autocast", "--duration", "4"]
    proc = subprocess.run([sys.executable, "-m", "deploy.cli", "run", *flags, "--out", str(out), "--run-id", RUN],
                          capture_output=True, text=True, timeout=180)
    assert proc.returncode in (0, 1), proc.stderr[-2000:]
    return out / RUN / "run.mcap"


def raw_messages(path) -> list[tuple[str, bytes, int]]:
    """The recording's wire messages (the msgpack channels; the JSON mirror left out)."""
    with open(path, "rb") as f:
        return [(ch.topic, m.data, m.log_time) for _, ch, m in make_reader(f).iter_messages()
                if ch.message_encoding == "msgpack"]


def test_view_saves_an_rrd_that_loads_back_with_every_entity(run_mcap, tmp_path):
    rrd = tmp_path / "out.rrd"
    assert main([str(run_mcap), "--save", str(rrd)]) == 0
    store = RrdReader(rrd).store()
    paths = set(store.schema().entity_paths())
    expected = {"/world/map/lanes", "/world/map/buildings", "/world/map/lights", "/world/vehicles/0/lidar/objects",
                "/world/vehicles/0/fused", "/stats/data/utilization", "/stats/ctrl/delivered_pairs",
                "/judge/ego_collider_distance_m", "/outcome"}
    for v in range(VEHICLES):
        expected |= {f"/world/vehicles/{v}/{part}" for part in ("box", "route", "trace", "trajectory", "received")}
        expected |= {f"/schedule/tx_bytes/{v}", f"/vehicles/{v}/speed_mps", f"/vehicles/{v}/accel_mps2"}
    expected.add("/world/vehicles/5/box")  # the passive collider, from the world's ground truth
    assert expected <= paths, sorted(expected - paths)
    timelines = {t for line in str(store.summary()).splitlines() if "/world/vehicles/0/box" in line
                 for t in ("sim_time", "tick") if t in line}
    assert timelines == {"sim_time", "tick"}
    assert RrdReader(rrd).blueprints()  # the layout travels with the file
    received = [v for chunk in RrdReader(rrd).stream().to_chunks() if chunk.entity_path.endswith("/received")
                for v in chunk.to_record_batch().column("Points3D:positions").to_pylist()]
    assert any(received), "no vehicle shows received points"
    verify = subprocess.run([sys.executable, "-m", "rerun", "rrd", "verify", str(rrd)], capture_output=True, text=True,
                            timeout=120)
    assert verify.returncode == 0, verify.stderr[-2000:]  # the viewer's own loader accepts it


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
