"""The run's recorder: ``python -m deploy.record.recorder --run-id R --out runs/R/run.mcap``.

One process subscribed to a run's keys (``ac/<run>/...``) writes one MCAP file:
a channel per key, message encoding ``msgpack`` (the payload bytes exactly as they
crossed Zenoh, never re-encoded), a schema per message type named after its
``protocol.messages`` dataclass, log time = receive time (Unix ns), publish time = the
message's ``t_sim_s`` (ns of sim time). Only the envelope (type id, version, tick,
t_sim_s) is read, so recording costs one copy per payload. A payload that is not a
valid envelope is still written, raw, on a schemaless channel of the same topic, and
counted. LiDAR scans (~1.3 MB per vehicle per tick) are kept for the ego only by
default (``--scans ego|all|none``).

With ``--json-mirror`` every valid message is also written decoded, as JSON with a
``jsonschema`` schema, on topic ``json/<key>``, so Foxglove and other MCAP tools that
know nothing of msgpack show it (big point arrays are left out there, see
``JSON_OMITTED``). ``mirror_file`` adds the same mirror to a finished recording.

The file is always finalized (summary and index written): on SIGINT or SIGTERM, after
the world's outcome once the run's processes have gone, or when the hub has been gone
for a few seconds.

After the outcome it keeps recording until every liveliness token of the run (agents,
proxy, participants: ``ac/<run>/alive/**``) has dropped and nothing more arrived for
``SETTLE_S``, or at most ``drain_s``. In lock-step everything a process sends before the
outcome is causally ahead of it, so the wait is for whatever a free-running process
still sends on its way out; the settle covers a token drop overtaking its owner's last
data (Zenoh sends declarations at a higher priority than data).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import inspect
import json
import logging
import math
import os
import queue
import signal
import subprocess
import sys
import threading
import time
import typing
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zenoh
from mcap.reader import NonSeekingReader, make_reader
from mcap.records import Channel, Message, Schema
from mcap.writer import CompressionType, Writer

from protocol import keys
from protocol.codec import MalformedMessage, decode, peek_envelope
from protocol.faults import Injector
from protocol import messages
from protocol.messages import Outcome, Tick
from protocol.session import ZenohArgs, add_zenoh_args, session_scope, zenoh_args_from

log = logging.getLogger("deploy.record.recorder")

MESSAGE_ENCODING = "msgpack"
SCHEMA_ENCODING = "autocast-dataclass"  # JSON: type id, version, field names and types
METADATA_NAME = "autocast"
STATS_NAME = "autocast.recorder"
SCAN_CHOICES = ("ego", "all", "none")
EGO_VID = 0
MAX_PUBLISH_S = 1.8e10  # below 2^64 ns
DRAIN_S = 2.0  # after the outcome, wait at most this long for the run's processes to go
SETTLE_S = 0.05  # after the outcome and the last token's drop, finish once nothing arrived for this long

JSON_PREFIX = "json/"  # a mirror's topic is JSON_PREFIX + the key
JSON_ENCODING = "json"
JSON_SCHEMA_ENCODING = "jsonschema"
JSON_SCHEMA_PREFIX = "autocast."  # a mirror's schema name is this + the dataclass name
# Arrays too big for a readable mirror: the mirror carries ``<field>_shape`` instead.
JSON_OMITTED = frozenset({
    (messages.Scan, "range_cm"), (messages.Scan, "points"),  # Scan v2 range image; v1 points
    (messages.AgentReport, "fused_xy"), (messages.EmpUpload, "points_world"),
    (messages.EmpSegment, "points_world"), (messages.ObjectMap, "visibility"), (messages.ObjectMap, "relevance"),
})


@dataclass(frozen=True, slots=True)
class RecorderConfig:
    run_id: str
    path: Path
    scans: str = "ego"
    metadata: dict[str, str] = field(default_factory=dict)
    compression: str = "zstd"
    drain_s: float = DRAIN_S
    hub_lost_s: float = 3.0  # finalize when no hub was connected for this long
    json_mirror: bool = False  # also write every message as JSON on json/<key>


def _is_a(payload: bytes, cls: type) -> bool:
    """A whole, valid ``cls`` (a valid envelope alone is not enough: anybody can put
    garbage on the outcome key). Only for small messages: ticks and the outcome."""
    try:
        decode(payload, cls)
    except MalformedMessage:
        return False
    return True


def schema_of(cls: type) -> bytes:
    """The schema data of a message type: how to read its msgpack array."""
    hints = typing.get_type_hints(cls)
    fields = [{"name": f.name, "type": _type_name(hints[f.name])} for f in dataclasses.fields(cls)]
    return json.dumps({"type_id": cls.TYPE_ID, "version": cls.VERSION, "module": cls.__module__,
                       "wire": "msgpack array [type_id, version, *fields]; numpy arrays as [dtype, shape, bytes], "
                               "packed ones as [dtype, shape, ones, others, values] (protocol/codec.py)",
                       "fields": fields}).encode()


def _type_name(hint: typing.Any) -> str:
    return hint.__name__ if isinstance(hint, type) and not typing.get_args(hint) else str(hint).replace("typing.", "")


def subscriptions(run: str, scans: str) -> list[str]:
    """The key expressions to record.

    ``scans="all"``: the whole run (``ac/<run>/**``). Otherwise every key that a
    ``protocol.keys`` function builds (``*`` for vehicle ids), with the scans narrowed to
    the ego's or none: a subscriber on ``ac/<run>/**`` would make the hub forward every
    vehicle's 1.3 MB scan to the recorder only for it to be dropped, and that traffic
    measurably slowed runs and crowded out small ``DROP`` messages (commands).
    """
    if scans == "all":
        return [keys.everything(run)]
    skip = {keys.everything(run), keys.alive_any(run), keys.scan(run, "*")}
    out = {keys.scan(run, EGO_VID)} if scans == "ego" else set()
    for name, fn in inspect.getmembers(keys, inspect.isfunction):
        params = list(inspect.signature(fn).parameters)
        if fn.__module__ != keys.__name__ or name.startswith("_") or params[:1] != ["run"]:
            continue
        try:
            key = fn(run, *["*"] * (len(params) - 1))
        except (TypeError, ValueError):
            continue
        if key not in skip:
            out.add(key)
    return sorted(out)


def git_revision() -> str:
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).resolve().parent, capture_output=True,
                             text=True, timeout=5)
    except (OSError, subprocess.TimeoutExpired):
        return "unknown"
    return out.stdout.strip() if out.returncode == 0 and out.stdout.strip() else "unknown"


@dataclass
class RecorderStats:
    messages: int = 0
    bytes: int = 0
    malformed: int = 0
    per_topic: dict[str, int] = field(default_factory=dict)
    json_messages: int = 0
    json_bytes: int = 0
    json_failed: int = 0  # a valid envelope whose body did not decode: recorded raw only

    def as_metadata(self) -> dict[str, str]:
        return {"messages": str(self.messages), "bytes": str(self.bytes), "malformed": str(self.malformed),
                "topics": str(len(self.per_topic)), "json_messages": str(self.json_messages),
                "json_bytes": str(self.json_bytes), "json_failed": str(self.json_failed)}


# ------------------------------------------------------------------ JSON mirror

Converter = typing.Callable[[typing.Any], typing.Any]


def _finite(x: float) -> float | None:
    return x if math.isfinite(x) else None


_FLOAT32 = np.dtype(np.float32)  # what ``a.dtype == np.float32`` compares with, made once


def _array_to_json(a: np.ndarray) -> list:
    if a.dtype == _FLOAT32:  # float32 -> shortest decimals it holds, not 2.140781044769287
        return a.astype(np.float64).round(6).tolist()  # np.round's own method, without its wrapper
    return a.tolist()


def _plan(hint: typing.Any, owner: type | None = None, name: str = "") -> tuple[str, Converter, dict]:
    """How one field goes to JSON: its name in the mirror, a converter, its JSON schema."""
    if hint is np.ndarray:
        if (owner, name) in JSON_OMITTED:
            return f"{name}_shape", lambda a: list(a.shape), {
                "type": "array", "items": {"type": "integer"}, "description": f"shape of {name} (left out)"}
        return name, _array_to_json, {"type": "array", "description": "numpy array as nested lists"}
    if hint is bytes:
        return f"{name}_size_bytes", len, {"type": "integer", "description": f"length of {name} (left out)"}
    if hint is float:
        return name, _finite, {"type": ["number", "null"]}
    if hint is bool:
        return name, bool, {"type": "boolean"}
    if hint is int:
        return name, int, {"type": "integer"}
    if hint is str:
        return name, str, {"type": "string"}
    origin = typing.get_origin(hint)
    if origin is list:
        (inner,) = typing.get_args(hint)
        inner_name, conv, schema = _plan(inner, owner, name)
        return inner_name, (lambda v: [conv(x) for x in v]), {"type": "array", "items": schema}
    if origin is dict:
        return name, (lambda v: v), {"type": "object"}  # free-form (outcome, channel statistics)
    if dataclasses.is_dataclass(hint):
        conv, schema = _record_plan(hint)
        return name, conv, schema
    if hint is typing.Any:
        return name, (lambda v: v), {}
    raise TypeError(f"{owner.__name__ if owner else '?'}.{name}: no JSON mirror for {hint!r}")


@functools.cache
def _record_plan(cls: type) -> tuple[Converter, dict]:
    hints = typing.get_type_hints(cls)
    plans = [(f.name, *_plan(hints[f.name], cls, f.name)) for f in dataclasses.fields(cls)]

    def convert(value: typing.Any) -> dict:
        return {out: conv(getattr(value, name)) for name, out, conv, _ in plans}

    schema = {"type": "object", "title": cls.__name__, "properties": {out: sch for _, out, _, sch in plans},
              "required": [out for _, out, _, _ in plans]}
    if cls.__doc__ and not cls.__doc__.startswith(f"{cls.__name__}("):
        schema["description"] = " ".join(cls.__doc__.split())
    return convert, schema


@functools.cache
def _record_json(cls: type) -> Converter:
    """``_record_plan(cls)[0]`` written out as one generated function of the record: a
    dict display of its fields, each field's conversion inline (an attribute read and at
    most one call), where the plan calls a closure per field and a dict comprehension
    per record. The same values, but a float field stays as it is when it is not finite:
    ``to_json`` turns any non-finite float into null, as ``_finite`` does."""
    env: dict[str, typing.Any] = {"_array_to_json": _array_to_json, "len": len, "list": list}
    exec(f"def convert(value):\n    return {_record_display(cls, 'value', env, 0)}", env)  # noqa: S102 - from the fields
    return env["convert"]


_INLINE_DEPTH = 4  # nested records written out in their owner's function down to this depth; deeper ones called


def _record_display(cls: type, v: str, env: dict, depth: int) -> str:
    """The dict display of record ``v`` (an expression) of type ``cls``: nested records,
    a list of them too (a data bundle's receptions), inline instead of a call each."""
    hints = typing.get_type_hints(cls)
    items = [f"{out!r}: {expr}" for out, expr in
             (_field_json(hints[f.name], cls, f.name, f"{v}.{f.name}", env, depth) for f in dataclasses.fields(cls))]
    return f"{{{', '.join(items)}}}"


def _field_json(hint: typing.Any, owner: type, name: str, v: str, env: dict, depth: int) -> tuple[str, str]:
    """A field's name in the mirror and its conversion as an expression of ``v`` (the
    code of ``_plan``'s converter); what the expression calls goes into ``env``."""
    if hint is np.ndarray:
        if (owner, name) in JSON_OMITTED:
            return f"{name}_shape", f"list({v}.shape)"
        return name, f"_array_to_json({v})"
    if hint is bytes:
        return f"{name}_size_bytes", f"len({v})"
    if hint is float or hint is typing.Any or typing.get_origin(hint) is dict:
        return name, v
    if hint in (bool, int, str):
        env[hint.__name__] = hint
        return name, f"{hint.__name__}({v})"
    if typing.get_origin(hint) is list:
        (inner,) = typing.get_args(hint)
        item = f"x{depth}"
        out, expr = _field_json(inner, owner, name, item, env, depth + 1)
        return out, f"[{expr} for {item} in {v}]"
    if dataclasses.is_dataclass(hint):
        if depth < _INLINE_DEPTH:
            return name, _record_display(hint, v, env, depth + 1)
        env[f"r_{hint.__name__}"] = _record_json(hint)
        return name, f"r_{hint.__name__}({v})"
    raise TypeError(f"{owner.__name__}.{name}: no JSON mirror for {hint!r}")


_ENCODE_JSON = json.JSONEncoder(separators=(",", ":"), allow_nan=False).encode  # json.dumps' own encoder, made once


def json_schema_of(cls: type) -> dict:
    """The JSON schema of a message type's mirror."""
    return {"$schema": "http://json-schema.org/draft-07/schema#", **_record_plan(cls)[1],
            "$comment": f"autocast wire type {cls.TYPE_ID} v{cls.VERSION}, mirrored from msgpack"}


def to_json(msg: typing.Any) -> bytes:
    """A decoded message as its mirror's JSON (non-finite numbers become null)."""
    obj = _record_json(type(msg))(msg)
    try:
        return _ENCODE_JSON(obj).encode()
    except ValueError:  # NaN or inf: in a float field, an array or a free-form dict
        return _ENCODE_JSON(_no_nan(obj)).encode()


def _no_nan(v: typing.Any) -> typing.Any:
    if isinstance(v, float):
        return _finite(v)
    if isinstance(v, dict):
        return {k: _no_nan(x) for k, x in v.items()}
    if isinstance(v, list):
        return [_no_nan(x) for x in v]
    return v


class WholeRecords:
    """The stream an MCAP writer writes a file through, on disk only in whole records:
    the writer's many small writes gather in memory and reach the file in one
    ``write(2)`` when ``McapLog`` commits, after each of its calls. A recorder killed at
    any moment (SIGKILL: no finalizing) so leaves a file whose every record is whole and
    which reads to its end, up to the last chunk written; only its summary is missing
    (``read_messages`` reads such a file from the start). Through Python's buffered file
    a killed recorder left an 8 KB block boundary in the middle of a record."""

    def __init__(self, path: Path) -> None:
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        self._pending = bytearray()
        self._written = 0

    def write(self, data: bytes) -> int:
        self._pending += data
        return len(data)

    def tell(self) -> int:
        return self._written + len(self._pending)

    def commit(self) -> None:
        view = memoryview(self._pending)
        while view:
            n = os.write(self._fd, view)
            view = view[n:]
            self._written += n
        del view
        self._pending.clear()

    flush = commit

    def close(self) -> None:
        if self._fd >= 0:
            self.commit()
            os.close(self._fd)
            self._fd = -1

    def __enter__(self) -> WholeRecords:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class McapLog:
    """An MCAP writer with a channel per (key, message type) and a schema per type;
    with ``json_mirror``, also a JSON channel per key (``json/<key>``). Given a
    ``WholeRecords`` stream, it commits after each call: the file is always whole records."""

    def __init__(self, stream: typing.BinaryIO | WholeRecords, metadata: dict[str, str], compression: str = "zstd",
                 json_mirror: bool = False) -> None:
        kind = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}[compression]
        self.writer = Writer(stream, compression=kind)
        self._commit = stream.commit if isinstance(stream, WholeRecords) else (lambda: None)
        self.writer.start(profile="", library="autocast-recorder")
        self.writer.add_metadata(METADATA_NAME, metadata)
        self._commit()
        self.json_mirror = json_mirror
        self.schemas: dict[type, int] = {}
        self.json_schemas: dict[type, int] = {}
        self.channels: dict[tuple[str, type | None], int] = {}
        self.json_channels: dict[str, int] = {}
        self.stats = RecorderStats()

    def write(self, key: str, payload: bytes, log_time_ns: int) -> None:
        env = peek_envelope(payload)
        if env is None:
            self.stats.malformed += 1
            if self.stats.malformed == 1 or self.stats.malformed % 100 == 0:
                log.warning("malformed payload #%d on %s (recorded raw)", self.stats.malformed, key)
        channel = self._channel(key, env.cls if env else None)
        # MCAP's publish time is a uint64 of ns: a t_sim_s it cannot hold (negative, inf,
        # NaN or ~585 years and more: anybody can publish garbage) falls back to log time
        publish_ns = int(round(env.t_sim_s * 1e9)) if env and 0 <= env.t_sim_s < MAX_PUBLISH_S else log_time_ns
        seq = self.stats.per_topic.get(key, 0)
        self.writer.add_message(channel, log_time=log_time_ns, data=payload, publish_time=publish_ns, sequence=seq)
        self.stats.per_topic[key] = seq + 1
        self.stats.messages += 1
        self.stats.bytes += len(payload)
        if self.json_mirror and env is not None:
            self._mirror(key, env.cls, payload, log_time_ns, publish_ns, seq)
        self._commit()

    def _mirror(self, key: str, cls: type, payload: bytes, log_time_ns: int, publish_ns: int, seq: int) -> None:
        try:
            data = to_json(decode(payload, cls))
        except MalformedMessage as exc:
            self.stats.json_failed += 1
            if self.stats.json_failed == 1 or self.stats.json_failed % 100 == 0:
                log.warning("no JSON mirror #%d on %s: %s", self.stats.json_failed, key, exc)
            return
        channel = self.json_channels.get(key)
        if channel is None:
            schema = self.json_schemas.get(cls)
            if schema is None:
                schema = self.json_schemas[cls] = self.writer.register_schema(
                    JSON_SCHEMA_PREFIX + cls.__name__, JSON_SCHEMA_ENCODING, json.dumps(json_schema_of(cls)).encode())
            channel = self.json_channels[key] = self.writer.register_channel(
                JSON_PREFIX + key, JSON_ENCODING, schema, {"mirror_of": key})
        self.writer.add_message(channel, log_time=log_time_ns, data=data, publish_time=publish_ns, sequence=seq)
        self.stats.json_messages += 1
        self.stats.json_bytes += len(data)

    def _channel(self, key: str, cls: type | None) -> int:
        got = self.channels.get((key, cls))
        if got is None:
            if cls is None:
                got = self.writer.register_channel(key, MESSAGE_ENCODING, 0, {"malformed": "true"})
            else:
                got = self.writer.register_channel(key, MESSAGE_ENCODING, self._schema(cls),
                                                   {"type_id": str(cls.TYPE_ID), "version": str(cls.VERSION)})
            self.channels[(key, cls)] = got
        return got

    def _schema(self, cls: type) -> int:
        got = self.schemas.get(cls)
        if got is None:
            got = self.schemas[cls] = self.writer.register_schema(cls.__name__, SCHEMA_ENCODING, schema_of(cls))
        return got

    def finish(self) -> None:
        self.writer.add_metadata(STATS_NAME, self.stats.as_metadata())
        self.writer.finish()
        self._commit()


class Recorder:
    """Subscribes to a run's keys and hands payloads to the writer (the caller's thread).

    The map and the missions are served by queries, not published: once the first tick
    shows the world is up, a helper thread fetches them so the log is self-contained.
    """

    def __init__(self, cfg: RecorderConfig, session: zenoh.Session, stop: threading.Event) -> None:
        self.cfg = cfg
        self.session = session
        self.stop = stop
        self._inbox: queue.SimpleQueue[tuple[str, bytes, int]] = queue.SimpleQueue()
        self._lock = threading.Lock()
        self._outcome_at: float | None = None
        self._first_tick: bytes | None = None
        self._live: set[str] = set()  # the run's liveliness tokens (agents, proxy, participants)
        self._last_event = time.monotonic()  # the latest sample or token change
        self._outcome_key = keys.world_outcome(cfg.run_id)
        self._tick_key = keys.world_tick(cfg.run_id)
        self.faults = Injector("recorder")

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        payload = sample.payload.to_bytes()
        self._inbox.put((key, payload, time.time_ns()))
        with self._lock:  # only a real outcome or tick counts: anybody can put garbage on their keys
            self._last_event = time.monotonic()
            if key == self._outcome_key and self._outcome_at is None and _is_a(payload, Outcome):
                self._outcome_at = time.monotonic()
            if key == self._tick_key and self._first_tick is None and _is_a(payload, Tick):
                self._first_tick = payload

    def _on_token(self, sample: zenoh.Sample) -> None:
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._live.add(str(sample.key_expr))
            else:
                self._live.discard(str(sample.key_expr))
            self._last_event = time.monotonic()

    def _done_after(self, outcome_at: float, now: float) -> bool:
        """After the outcome: the run's processes have gone and nothing arrived since, or
        the longest wait has passed."""
        with self._lock:  # now >= t + d, not now - t >= d: the same sum as a caller's t + d, whatever t
            settled = not self._live and now >= self._last_event + SETTLE_S
        return settled or now >= outcome_at + self.cfg.drain_s

    def run(self, out: McapLog) -> None:
        """Record until stopped, the outcome has drained, or the hub is gone."""
        exprs = subscriptions(self.cfg.run_id, self.cfg.scans)
        subs = [self.session.liveliness().declare_subscriber(keys.alive_any(self.cfg.run_id), self._on_token,
                                                             history=True)]
        subs += [self.session.declare_subscriber(expr, self._on_sample) for expr in exprs]
        log.info("recording into %s: %s", self.cfg.path, " ".join(exprs))
        fetcher: threading.Thread | None = None
        hub_seen = last_check = time.monotonic()
        try:
            outcome_at = None
            while not self.stop.is_set():
                self._drain(out, timeout_s=0.2 if outcome_at is None else SETTLE_S / 2)
                now = time.monotonic()
                with self._lock:
                    outcome_at, first_tick = self._outcome_at, self._first_tick
                if fetcher is None and first_tick is not None:
                    fetcher = threading.Thread(target=self._fetch_static, args=(first_tick,), daemon=True)
                    fetcher.start()
                if outcome_at is not None and self._done_after(outcome_at, now):
                    with self._lock:
                        left = sorted(self._live)
                    if left:
                        log.warning("outcome recorded; %.1f s later still alive: %s; finishing", now - outcome_at,
                                    " ".join(left))
                    else:
                        log.info("outcome recorded and the run's processes gone (%.2f s); finishing", now - outcome_at)
                    break
                if now - last_check >= 0.5:
                    last_check = now
                    if self.session.info.routers_zid():
                        hub_seen = now
                    elif now - hub_seen > self.cfg.hub_lost_s:
                        log.warning("hub gone for %.0f s; finishing", self.cfg.hub_lost_s)
                        break
        finally:
            for sub in subs:
                sub.undeclare()
            if fetcher is not None:
                fetcher.join(timeout=3.0)
            self._drain(out, timeout_s=0.0)

    def _fetch_static(self, first_tick: bytes) -> None:
        """Record the map and every live vehicle's mission, as the world serves them."""
        try:
            live = decode(first_tick, Tick).live
        except MalformedMessage:
            return
        run = self.cfg.run_id
        for key in [keys.world_map(run), *(keys.mission(run, vid) for vid in live)]:
            try:
                for reply in self.session.get(key, timeout=2.0):
                    if reply.ok is not None:
                        self._inbox.put((str(reply.ok.key_expr), reply.ok.payload.to_bytes(), time.time_ns()))
            except zenoh.ZError as exc:
                log.warning("query %s: %s", key, exc)

    def _drain(self, out: McapLog, timeout_s: float) -> None:
        try:
            item = self._inbox.get(timeout=timeout_s) if timeout_s > 0 else self._inbox.get_nowait()
            while True:
                if self.faults.faults and (env := peek_envelope(item[1])) is not None:
                    self.faults.at(env.tick)
                out.write(*item)
                item = self._inbox.get_nowait()
        except queue.Empty:
            return


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python -m deploy.record.recorder", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--run-id", required=True, help="the run's id (records ac/<run>/**)")
    ap.add_argument("--out", required=True, type=Path, metavar="FILE", help="the MCAP file to write")
    ap.add_argument("--scans", choices=SCAN_CHOICES, default="ego",
                    help="LiDAR scans to keep: the ego's only (default), every vehicle's, or none")
    ap.add_argument("--meta", action="append", default=[], metavar="KEY=VALUE",
                    help=f"an entry of the '{METADATA_NAME}' metadata record (scenario, seed, scheme, ...)")
    ap.add_argument("--compression", choices=("zstd", "lz4", "none"), default="zstd")
    ap.add_argument("--drain-s", type=float, default=DRAIN_S,
                    help="after the outcome, wait at most this long for the run's processes to go "
                         "(default %(default)s)")
    ap.add_argument("--json-mirror", action="store_true",
                    help="also write every message as JSON (jsonschema) on json/<key>, for Foxglove")
    ap.add_argument("--log-level", default="INFO")
    add_zenoh_args(ap)
    return ap.parse_args(argv)


def metadata_from(args: argparse.Namespace) -> dict[str, str]:
    meta = {"run_id": args.run_id, "scans": args.scans}
    for item in args.meta:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise ValueError(f"meta: {item!r} is not KEY=VALUE")
        meta[name] = value
    meta["git_revision"] = git_revision()
    meta["recorded_at"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
    return meta


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s recorder %(levelname)s %(message)s")
    try:
        keys.everything(args.run_id)
        cfg = RecorderConfig(args.run_id, args.out, args.scans, metadata_from(args), args.compression, args.drain_s,
                             json_mirror=args.json_mirror)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    cfg.path.parent.mkdir(parents=True, exist_ok=True)
    try:
        return record(cfg, zenoh_args_from(args), stop)
    except ConnectionError as exc:  # no hub within the startup timeout
        log.error("%s", exc)
        return 3


def record(cfg: RecorderConfig, zargs: ZenohArgs, stop: threading.Event) -> int:
    """Record one run into ``cfg.path`` until ``stop``; the file is finalized whatever ends the run."""
    with session_scope(zargs) as session, WholeRecords(cfg.path) as stream:
        recorder = Recorder(cfg, session, stop)
        out = McapLog(stream, cfg.metadata, cfg.compression, json_mirror=cfg.json_mirror)
        try:
            recorder.run(out)
        finally:
            out.finish()
            s = out.stats
            log.info("wrote %s: %d messages, %.1f MB, %d topics, %d malformed", cfg.path, s.messages, s.bytes / 1e6,
                     len(s.per_topic), s.malformed)
    return 0


def read_messages(stream: typing.BinaryIO, topics: list[str] | None = None,
                  ) -> typing.Iterator[tuple[Schema | None, Channel, Message]]:
    """A recording's messages in file order (= arrival order), one chunk in memory at a time.

    A file whose summary cannot be read (the recorder was killed) is read from the start
    until it ends or breaks; the reader's error then reaches the caller.
    """
    try:
        reader = make_reader(stream)
        usable = reader.get_summary() is not None
    except Exception:  # the mcap reader raises several unrelated types for a damaged footer
        usable = False
    if not usable:
        stream.seek(0)
        reader = NonSeekingReader(stream)
    yield from reader.iter_messages(topics=topics, log_time_order=False)  # time order would sort it all in memory


def read_metadata(stream: typing.BinaryIO) -> dict[str, dict[str, str]]:
    """The recording's metadata records by name ({} if the file's index cannot be read)."""
    try:
        return {m.name: dict(m.metadata) for m in make_reader(stream).iter_metadata()}
    except Exception:
        return {}


def mirror_file(src: Path, dst: Path, compression: str = "zstd") -> RecorderStats:
    """Copy a recording with its JSON mirror added (raw channels byte for byte, same times).

    Streams message by message; a mirror already in ``src`` is not copied. A damaged
    ``src`` is copied up to the damage.
    """
    with open(src, "rb") as fin, open(dst, "wb") as fout:
        meta = read_metadata(fin)
        fin.seek(0)
        out = McapLog(fout, meta.get(METADATA_NAME, {}), compression, json_mirror=True)
        try:
            for _, channel, msg in read_messages(fin):
                if channel.message_encoding == MESSAGE_ENCODING:
                    out.write(channel.topic, msg.data, msg.log_time)
        except Exception as exc:  # a damaged file: keep what was read
            log.warning("%s: stopped reading after %d messages: %s: %s", src, out.stats.messages,
                        type(exc).__name__, exc)
        finally:
            out.finish()
    return out.stats


if __name__ == "__main__":
    sys.exit(main())
