"""The recorder: envelope peeking, the MCAP layout, and the process finalizing its file
whatever ends the run (the outcome, SIGINT, SIGTERM, the hub going away)."""

from __future__ import annotations

import io
import json
import math
import signal

import msgpack
import numpy as np
import pytest
import zenoh
from mcap.reader import make_reader

from deploy.record.recorder import JSON_PREFIX, McapLog, json_schema_of, subscriptions, to_json
from protocol.codec import peek_envelope
from protocol import keys
from protocol.codec import decode, encode
from protocol.messages import Command, Outcome, Pose, Scan, Tick
from protocol.session import ZenohArgs, open_session
from tests.conftest import wait_until

RUN = "rec"


def scan(tick: int, vid: int = 0, n: int = 1000) -> Scan:
    return Scan(tick, tick * 0.1, vid, Pose(1.0, 2.0, 0.5), 3.0, np.ones((n, 6), np.uint16))  # 12 bytes a row


def read(data: bytes):
    reader = make_reader(io.BytesIO(data))
    summary = reader.get_summary()
    msgs = [(ch.topic, schema.name if schema else None, m) for schema, ch, m in reader.iter_messages()]
    meta = {m.name: m.metadata for m in reader.iter_metadata()}
    return summary, msgs, meta


def test_the_envelope_is_read_without_decoding_the_body():
    env = peek_envelope(encode(scan(7, n=100_000)))  # a 1.2 MB payload
    assert (env.cls, env.tick, env.t_sim_s) == (Scan, 7, pytest.approx(0.7))
    assert peek_envelope(encode(Command(3, 0.3, 1, -2.0, 0.1))).cls is Command


@pytest.mark.parametrize("payload", [b"\xc1\xc1 not msgpack", b"", msgpack.packb([5, 99, 0, 0.0, 0, 0.0, 0.0]),
                                     msgpack.packb([77, 1, 0, 0.0]), msgpack.packb([5, 1, 0, 0.0]),
                                     msgpack.packb({"a": 1}), msgpack.packb([5, 1, "x", 0.0, 0, 0.0, 0.0])])
def test_a_bad_envelope_is_none(payload):
    assert peek_envelope(payload) is None


def test_subscriptions_keep_only_the_egos_scans_by_default():
    ego = subscriptions(RUN, "ego")
    assert keys.scan(RUN, 0) in ego and keys.scan(RUN, "*") not in ego
    # every scheduler domain's channel keys (docs/domains.md), the plain ones among them
    assert {keys.world_tick(RUN), keys.world_outcome(RUN), keys.cmd(RUN, "*"), keys.net_ctrl_tx(RUN, "*", "*", "*"),
            keys.net_data_rx(RUN, "*", "*"), keys.net_stats(RUN)} <= set(ego)
    assert not any("scan" in k for k in subscriptions(RUN, "none"))
    assert subscriptions(RUN, "all") == [keys.everything(RUN)]


def test_payloads_are_written_as_they_arrived_with_a_schema_per_type():
    buf = io.BytesIO()
    out = McapLog(buf, {"scenario": "left_turn", "seed": "3"})
    sent = [(keys.world_tick(RUN), encode(Tick(k, k * 0.1, [0, 1], []))) for k in range(3)]
    sent += [(keys.scan(RUN, 0), encode(scan(k))) for k in range(3)]
    sent += [(keys.cmd(RUN, 1), encode(Command(k, k * 0.1, 1, 0.5, 0.0))) for k in range(3)]
    sent += [(keys.cmd(RUN, 1), b"garbage")]
    for i, (key, payload) in enumerate(sent):
        out.write(key, payload, log_time_ns=1_000 + i)
    out.finish()

    summary, msgs, meta = read(buf.getvalue())
    assert [m.data for _, _, m in msgs] == [p for _, p in sent]  # byte for byte, in order
    assert {ch.message_encoding for ch in summary.channels.values()} == {"msgpack"}
    assert {s.name for s in summary.schemas.values()} == {"Tick", "Scan", "Command"}
    scans = [m for topic, schema, m in msgs if topic == keys.scan(RUN, 0)]
    assert [m.publish_time for m in scans] == [0, 100_000_000, 200_000_000]  # t_sim_s in ns
    assert [m.sequence for m in scans] == [0, 1, 2]
    assert decode(scans[2].data).tick == 2
    bad = [(schema, m) for topic, schema, m in msgs if m.data == b"garbage"]
    assert bad == [(None, bad[0][1])] and bad[0][1].publish_time == bad[0][1].log_time
    assert meta["autocast"] == {"scenario": "left_turn", "seed": "3"}
    assert meta["autocast.recorder"]["malformed"] == "1" and meta["autocast.recorder"]["messages"] == str(len(sent))


def test_the_json_mirror_sits_beside_the_raw_channels():
    buf = io.BytesIO()
    out = McapLog(buf, {}, json_mirror=True)
    image = np.zeros((18, 4), np.uint16)
    image[3, 1] = 1234
    good = [(keys.world_tick(RUN), encode(Tick(0, 0.0, [0, 1], []))),
            (keys.scan(RUN, 0), encode(Scan(0, 0.0, 0, Pose(1.0, 2.0, 0.5), 3.0, image))),
            (keys.cmd(RUN, 1), encode(Command(0, 0.0, 1, -2.5, 0.125))),
            (keys.world_outcome(RUN), encode(Outcome(1, 0.1, {"outcome": "safe", "reaction_time_s": math.nan})))]
    truncated = encode(Command(1, 0.1, 1, 0.0, 0.0))[:-3]  # a valid envelope, a broken body
    for i, (key, payload) in enumerate([*good, (keys.cmd(RUN, 1), truncated), (keys.cmd(RUN, 1), b"garbage")]):
        out.write(key, payload, log_time_ns=1_000 + i)
    out.finish()

    summary, msgs, meta = read(buf.getvalue())
    raw = [m.data for topic, _, m in msgs if not topic.startswith(JSON_PREFIX)]
    assert raw == [p for _, p in good] + [truncated, b"garbage"]  # the raw log is unchanged
    mirror = {topic[len(JSON_PREFIX):]: (schema, json.loads(m.data)) for topic, schema, m in msgs
              if topic.startswith(JSON_PREFIX)}
    assert set(mirror) == {key for key, _ in good}  # neither the broken body nor the garbage is mirrored
    assert {ch.message_encoding for ch in summary.channels.values()} == {"msgpack", "json"}
    name, cmd = mirror[keys.cmd(RUN, 1)]
    (schema,) = [s for s in summary.schemas.values() if s.name == name]
    assert (schema.name, schema.encoding) == ("autocast.Command", "jsonschema")
    assert json.loads(schema.data) == json_schema_of(Command)
    assert cmd == {"tick": 0, "t_sim_s": 0.0, "vid": 1, "accel_mps2": -2.5, "steer_rad": 0.125}
    scan_doc = mirror[keys.scan(RUN, 0)][1]
    assert scan_doc["range_cm_shape"] == [18, 4] and "range_cm" not in scan_doc  # the image is left out
    assert scan_doc["pose"] == {"x_m": 1.0, "y_m": 2.0, "yaw_rad": 0.5}
    assert mirror[keys.world_outcome(RUN)][1]["result"] == {"outcome": "safe", "reaction_time_s": None}  # NaN
    stats = meta["autocast.recorder"]
    assert (stats["malformed"], stats["json_failed"], stats["json_messages"]) == ("1", "1", "4")


def test_float32_arrays_are_mirrored_without_float_noise():
    from protocol.messages import AgentReport

    doc = json.loads(to_json(AgentReport(2, 0.2, 0, np.array([[0.1, 37.805]], np.float32), 5, True)))
    assert doc == {"tick": 2, "t_sim_s": 0.2, "vid": 0, "fused_xy_shape": [1, 2], "received_points": 5,
                   "braking": True}


class Hub:
    """The test as the run's hub, publishing what the world would."""

    def __init__(self, endpoint: str) -> None:
        self.session = open_session(ZenohArgs(listen=(endpoint,)))
        self.probes = [self.session.declare_publisher(k) for k in (keys.world_tick(RUN), keys.world_outcome(RUN))]

    def wait_subscribed(self) -> None:
        wait_until(lambda: all(p.matching_status.matching for p in self.probes), "the recorder subscribed")

    def put(self, key: str, payload: bytes) -> None:
        # BLOCK, as the world publishes: with the default (DROP), a put behind a busy
        # egress queue on a loaded machine was silently lost (an outcome the recorder
        # never got, so it never finished)
        self.session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

    def publish_ticks(self, n: int) -> None:
        for k in range(n):
            self.put(keys.world_tick(RUN), encode(Tick(k, k * 0.1, [0], [])))
            self.put(keys.scan(RUN, 0), encode(scan(k)))
            self.put(keys.scan(RUN, 1), encode(scan(k, vid=1)))
            self.put(keys.cmd(RUN, 0), encode(Command(k, k * 0.1, 0, 1.0, 0.0)))

    def close(self) -> None:
        if not self.session.is_closed():
            for p in self.probes:
                p.undeclare()
            self.session.close()


@pytest.fixture
def recorder(procs, hub, tmp_path, request):
    """A recorder process on the test's hub; yields (process, hub, path). Extra flags by
    indirect parametrization."""
    path = tmp_path / "run.mcap"
    h = Hub(hub)
    p = procs("deploy.record.recorder", "--run-id", RUN, "--connect", hub, "--out", str(path), "--drain-s", "0.3",
              "--meta", "scheme=single", *getattr(request, "param", ()))
    h.wait_subscribed()
    yield p, h, path
    h.close()


def topics_in(path) -> dict[str, int]:
    summary, _, meta = read(path.read_bytes())
    assert meta["autocast"]["scheme"] == "single" and meta["autocast"]["run_id"] == RUN
    assert meta["autocast"]["git_revision"]
    return {ch.topic: summary.statistics.channel_message_counts.get(cid, 0) for cid, ch in summary.channels.items()}


def test_the_outcome_ends_the_recording(recorder):
    p, h, path = recorder
    h.publish_ticks(5)
    h.put(keys.world_outcome(RUN), encode(Outcome(5, 0.5, {"outcome": "safe"})))
    assert p.wait(timeout=60) == 0
    assert topics_in(path) == {keys.world_tick(RUN): 5, keys.scan(RUN, 0): 5, keys.cmd(RUN, 0): 5,
                               keys.world_outcome(RUN): 1}  # vehicle 1's scan is not kept


@pytest.mark.parametrize("recorder", [("--drain-s", "600")], indirect=True)
def test_the_recording_ends_when_the_last_token_drops_not_at_the_cap(recorder):
    """After the outcome, the drop of the run's last liveliness token ends the recording,
    long before the 600 s cap (the wait below is only a safety net). That a live token
    holds it open is the next test's."""
    p, h, path = recorder
    token = h.session.liveliness().declare_token(keys.alive(RUN, 3))
    h.publish_ticks(2)
    h.put(keys.world_outcome(RUN), encode(Outcome(2, 0.2, {"outcome": "safe"})))
    token.undeclare()
    assert p.wait(timeout=120) == 0
    assert topics_in(path)[keys.world_outcome(RUN)] == 1


def test_the_recording_ends_once_the_tokens_are_gone_and_the_run_is_quiet():
    """The rule, with the clock passed in: every token gone and nothing new for
    ``SETTLE_S``; or the cap."""
    from types import SimpleNamespace

    from deploy.record.recorder import SETTLE_S, Recorder, RecorderConfig

    rec = Recorder(RecorderConfig(RUN, None, drain_s=2.0), None, None)
    token = lambda kind, vid: SimpleNamespace(kind=kind, key_expr=keys.alive(RUN, vid))  # noqa: E731
    rec._on_token(token(zenoh.SampleKind.PUT, 1))
    rec._on_token(token(zenoh.SampleKind.PUT, 2))
    rec._on_token(token(zenoh.SampleKind.DELETE, 1))
    t = rec._last_event
    assert not rec._done_after(t, t + 1.0)  # vehicle 2 is still up
    assert rec._done_after(t, t + 2.0)  # the cap
    rec._on_token(token(zenoh.SampleKind.DELETE, 2))
    t = rec._last_event
    assert not rec._done_after(t, t + SETTLE_S / 2)  # gone, but not yet quiet
    assert rec._done_after(t, t + SETTLE_S)


@pytest.mark.parametrize("recorder", [("--json-mirror",)], indirect=True)
def test_the_recorder_process_writes_the_json_mirror(recorder):
    p, h, path = recorder
    h.publish_ticks(4)
    h.put(keys.world_outcome(RUN), encode(Outcome(4, 0.4, {"outcome": "safe"})))
    assert p.wait(timeout=60) == 0
    counts = topics_in(path)
    assert counts[JSON_PREFIX + keys.world_tick(RUN)] == counts[keys.world_tick(RUN)] == 4
    assert counts[JSON_PREFIX + keys.world_outcome(RUN)] == 1


def recorded_ticks(path) -> list[int]:
    _, msgs, _ = read(path.read_bytes())  # raises unless the file was finalized
    return [decode(m.data, Tick).tick for topic, _, m in msgs if topic == keys.world_tick(RUN)]


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_a_signal_finalizes_the_file(recorder, sig):
    """What had arrived when the signal came is in a finalized file, in order (how many
    ticks had arrived depends on the machine, so the count is not the verdict)."""
    p, h, path = recorder
    h.publish_ticks(3)
    p.send_signal(sig)
    assert p.wait(timeout=60) == 0
    ticks = recorded_ticks(path)
    assert ticks == list(range(len(ticks))) and len(ticks) <= 3


def test_losing_the_hub_finalizes_the_file(recorder):
    p, h, path = recorder
    h.publish_ticks(2)
    h.close()
    assert p.wait(timeout=60) == 0
    ticks = recorded_ticks(path)
    assert ticks == list(range(len(ticks))) and len(ticks) <= 2
