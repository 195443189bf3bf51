"""One lying sender against a real agent's whole tick (hypothesis).

A short real run is recorded with every scan (plain, and signed); the ego's pipeline
(``vehicle_agent.__main__.Pipeline``) is replayed from its log up to a tick (the replay
link feeds it the logged bundles: ``vehicle_agent.replay``), and then plays that tick
with one sender's frame in the control bundle, or its payload in the data bundle,
replaced by a well-typed lie: dtype-valid, with a shape, length or value mutated so that
it breaks a declared invariant (``protocol.messages``). In the signed run the liar
signs its lie with its own valid certificate. The agent must finish the tick, count
what it dropped (once, if it read the lie), and decide exactly what it decides when the
liar's frame is not in the bundle at all: the same members, group, frames, missing
members and messages, the same transmissions and the same command. A lying payload
the liar vouches for (its digest in the liar's signed control message) is authentic:
the decoder's own checks drop it, counted as malformed, not as rejected.

The suite runs the ``ci`` hypothesis profile (25 examples per property);
``AUTOCAST_HYPOTHESIS=fuzz`` runs 10,000 (``python -m pytest tests/test_liar_tick.py``).
"""

from __future__ import annotations

import copy
import math
import struct
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from unittest import mock

import msgpack
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import vehicle_agent.__main__ as agent_main
from test_invariants import _array, _header_float, _set  # a wire list's arrays and fields, changed
from protocol import keys
from protocol.codec import COORD_BOUND_M, MalformedMessage, _packed_to_wire, decode, encode
from protocol.messages import ControlMsg, CtrlBundle, DataBundle, Mission, MapMsg, Reception, Scan, Signed
from protocol.security import Credentials, Signer, payload_digest
from protocol.session import DropCounter
from vehicle_agent.__main__ import Pipeline
from vehicle_agent.agreement import HeardControl
from vehicle_agent.guard import Guard
from vehicle_agent.payload import DATA_STREAM, HEADER_BOUNDS
from vehicle_agent.replay import Log, ReplayLink, model_of
from vehicle_agent.warmup import warm_up

EGO, TICK = 0, 6
FLAGS = ["--scenario", "red_light", "--vehicles", "4", "--scheme", "autocast", "--duration", "0.8", "--seed", "3",
         "--scans", "all", "--no-json-mirror", "--log-level", "WARNING"]

pytestmark = [pytest.mark.xdist_group("test_liar_tick"), pytest.mark.heavy]


def _record(out: Path, run_id: str, *extra: str) -> Path:
    done = subprocess.run([sys.executable, "-m", "deploy.cli", "run", *FLAGS, *extra, "--out", str(out),
                           "--run-id", run_id, "--json"], capture_output=True, text=True, timeout=600)
    assert done.returncode in (0, 1), done.stderr[-2000:]
    return out / run_id


class Tick:
    """The ego's pipeline replayed up to ``TICK`` (kept, and copied for each example), and
    the logged inputs of ``TICK``."""

    def __init__(self, run_dir: Path) -> None:
        self.log = Log.read(run_dir / "run.mcap")
        run = self.run = self.log.run_id
        self.signed = self.log.metadata.get("signed") == "True"
        self.creds = {int(p.stem.removeprefix("agent").split(".")[0]): Credentials.load(p)
                      for p in (run_dir / "credentials").glob("agent*.v2x.json")} if self.signed else {}
        self.mission = decode(self.log.static[keys.mission(run, EGO)], Mission)
        self.mapmsg = decode(self.log.static[keys.world_map(run)], MapMsg)
        self.scans = {t: decode(raw, Scan) for t, raw in self.log.payloads(keys.scan(run, EGO)).items()}
        self.ctrl = self.log.payloads(keys.net_ctrl_rx(run))[TICK]
        self.data = self.log.payloads(keys.net_data_rx(run))[TICK]
        base = Pipeline(self.mission, self.mapmsg, self.log.metadata.get("scheme", "autocast"),
                        self.log.metadata.get("channel_profile") or "lte-direct", None, None, lambda raw: None, None,
                        model_of(self.log.metadata))
        base.link, base.guard = self._link_and_guard(DropCounter(), self.log.payloads(keys.net_ctrl_rx(run)))
        warm_up(base.agent, base.agreement)
        for t in range(TICK):
            base.run(self.scans[t])
        base.link, base.guard, base.report = None, None, None  # not copied: made anew for each example
        self.base = base
        bundle = decode(self.ctrl, CtrlBundle)
        # the liar: the sender the ego heard with the most objects (its lies reach the most fields)
        heard = {s: raw for s, raw in bundle.frames_heard_by(EGO) if s != EGO}
        self.liar = max(heard, key=lambda s: (self._body(heard[s])[8][0][1][0], s))
        self.liar_raw = heard[self.liar]

    def _link_and_guard(self, drops: DropCounter, ctrl_rx: dict[int, bytes], data_rx: dict[int, bytes] | None = None):
        link = ReplayLink(self.log, EGO, drops)
        link.ctrl_rx = ctrl_rx
        if data_rx is not None:
            link.data_rx = data_rx
        return link, Guard(self.creds[EGO], drops) if self.signed else None

    def _body(self, raw: bytes) -> list:
        """A control message's wire list, out of its envelope in a signed run."""
        if self.signed:
            raw = decode(raw, Signed).body
        return msgpack.unpackb(raw, raw=False)

    def lie(self, body: list) -> bytes:
        """The liar's frame carrying ``body``: signed by the liar with its own certificate in a signed run."""
        raw = msgpack.packb(body, use_bin_type=True)
        if not self.signed:
            return raw
        env = decode(self.liar_raw, Signed)
        return encode(Signed(env.tick, env.t_sim_s, env.certificate, raw, Signer(self.creds[self.liar]).signature(raw)))

    def play(self, ctrl: bytes, data: bytes):
        """The tick with these bundles: (the decision, what the ego sent, the command, the
        drops counted by key, the rejections by stream and reason, the decision)."""
        p = copy.deepcopy(self.base)
        drops = DropCounter()
        p.link, p.guard = self._link_and_guard(drops, {TICK: ctrl}, {TICK: data})
        p.report = lambda raw: None
        decisions = []

        def spy(*args, **kw):
            decisions.append(decide(*args, **kw))
            return decisions[-1]

        decide = agent_main.decide
        with mock.patch.object(agent_main, "decide", spy):
            cmd = p.run(self.scans[TICK])
        assert len(decisions) == 1
        d = decisions[0]
        seen = (d.members.tolist(), d.group.tolist(), d.frames, d.missing.tolist(),
                {v: encode(m) for v, m in sorted(d.messages.items())})
        rejected = p.guard.rejections.summary()["by_stream"] if p.guard is not None else {}
        return seen, p.link.sent["data"].get(TICK), p.wire(cmd), drops.by_key(), rejected, d


def _without(bundle_raw: bytes, sender: int) -> bytes:
    """The control bundle with ``sender``'s frames gone: the ego did not hear it."""
    b = decode(bundle_raw, CtrlBundle)
    keep = b.senders != sender
    return encode(CtrlBundle(b.tick, b.t_sim_s, b.senders[keep], b.receivers, np.ascontiguousarray(b.heard[:, keep]),
                             [m for m, k in zip(b.messages, keep) if k]))


def _with_frame(bundle_raw: bytes, sender: int, frame: bytes) -> bytes:
    b = decode(bundle_raw, CtrlBundle)
    messages = [frame if s == sender else m for s, m in zip(b.senders.tolist(), b.messages)]
    return encode(CtrlBundle(b.tick, b.t_sim_s, b.senders, b.receivers, b.heard, messages))


@pytest.fixture(scope="module")
def ticks(tmp_path_factory):
    out = tmp_path_factory.mktemp("liar")
    with ThreadPoolExecutor(2) as pool:
        plain, signed = pool.submit(_record, out, "plain"), pool.submit(_record, out, "signed", "--sign")
        return {"plain": Tick(plain.result()), "signed": Tick(signed.result())}


@pytest.fixture(scope="module")
def baselines(ticks):
    """Each run's tick with the liar's control frame gone, and with its data receptions gone."""
    out = {}
    for name, t in ticks.items():
        out[name, "ctrl"] = t.play(_without(t.ctrl, t.liar), t.data)
        out[name, "data"] = t.play(t.ctrl, _without_receptions(t.data, t.liar))
    return out


# ------------------------------------------------------------------ the lies

BAD = [math.nan, math.inf, -math.inf, 1e30, -1e30, 2 * COORD_BOUND_M]


def _set_entry(value, index: int):
    def change(a):
        if a.size == 0:  # nothing to change: a row that should not be there
            return np.concatenate([a, np.full((1, *a.shape[1:]), value, a.dtype)])
        a.reshape(-1)[index % a.size] = value
        return a
    return change


def _extra_row(a):
    return np.concatenate([a, a[:1] if len(a) else np.zeros((1, *a.shape[1:]), a.dtype)])


def _reversed_times(a):
    if len(a) == 0:
        return np.array([[0.0, 0.0, -1.0]], a.dtype)
    if len(a) < 2 or a[0, 2] == a[-1, 2]:  # nothing to reverse: a time before the run
        a[:1, 2] = -1.0
        return a
    return a[::-1].copy()


def _twice(a):
    if len(a) == 0:
        return np.array([1, 1], a.dtype)
    return np.concatenate([a, a[-1:]])


@st.composite
def control_lies(draw):
    """(what, the field index path into the wire list, new value) of one well-typed lie."""
    bad = draw(st.sampled_from(BAD))
    i = draw(st.integers(0, 10_000))
    kinds = {
        "pose": ((5, draw(st.integers(0, 1))), lambda v: bad),
        "yaw": ((5, 2), lambda v: draw(st.sampled_from([math.nan, math.inf]))),
        "speed": ((6,), lambda v: draw(st.sampled_from([math.nan, math.inf, 1e30, -1e4]))),
        "trajectory value": ((7,), lambda t: _array(t, _set_entry(draw(st.sampled_from(BAD[:5])), i))),
        "trajectory back in time": ((7,), lambda t: _array(t, _reversed_times)),
        "trajectory too long": ((7,), lambda t: _array(t, lambda a: np.zeros((2000, 3), a.dtype))),
        "object id twice": ((8, 0), lambda t: _array(t, _twice)),
        "object id negative": ((8, 0), lambda t: _array(t, _set_entry(-1 - i, i))),
        "size negative or huge": ((8, 1), lambda t: _array(t, _set_entry(draw(st.sampled_from([-1, -70, 1 << 62])), i))),
        "sizes of other objects": ((8, 1), lambda t: _array(t, _extra_row)),
        "centroid": ((8, 2), lambda t: _array(t, _set_entry(bad, i))),
        "centroids of other objects": ((8, 2), lambda t: _array(t, _extra_row)),
        "receivers twice": ((8, 3), lambda t: _array(t, _twice)),
        "visibility not a share": ((8, 4), lambda t: _packed_to_wire(np.full(t[1], draw(st.sampled_from(
            [math.nan, 2.0, -1.0, math.inf])), np.float32)) if 0 not in t[1] else ["<f4", [1, 1], b"\x00", b"\x00", b""]),
        "relevance not a share": ((8, 5), lambda t: _packed_to_wire(np.full(t[1], draw(st.sampled_from(
            [math.nan, 1.5, -0.5])), np.float32)) if 0 not in t[1] else ["<f4", [0, 70_000], b"", b"", b""]),
        "heard twice or out of range": ((9,), lambda t: _array(t, _twice if i % 2 else _set_entry(-1, i))),
        "starvation counts of other objects": ((10,), lambda t: _array(t, lambda a: np.zeros(
            len(a) + 1 if len(a) else 10_000, a.dtype))),
        "starvation count negative": ((10,), lambda t: _array(t, _set_entry(-3, i)) if t[1][0] else
                                      _array(t, lambda a: np.full(9_999, -3, a.dtype))),
        "digests of other objects": ((11,), lambda t: _array(t, lambda a: np.zeros(
            (len(a) + 1 if len(a) else 10_000, a.shape[1]), a.dtype))),
        "vehicle id out of range": ((4,), lambda v: draw(st.sampled_from([-1, 1 << 16, 1 << 40]))),
    }
    what = draw(st.sampled_from(sorted(kinds)))
    path, value = kinds[what]
    return what, path, value


def _without_receptions(data_raw: bytes, sender: int) -> bytes:
    b = decode(data_raw, DataBundle)
    keep = np.array([r.sender != sender for r in b.receptions], bool)
    return encode(DataBundle(b.tick, b.t_sim_s, b.receivers, np.ascontiguousarray(b.decoded[:, keep]),
                             [r for r, k in zip(b.receptions, keep) if k]))


@st.composite
def payload_lies(draw):
    """A function of a payload: the payload cut, its header's magic or version wrong, cut
    short, or a float of its header (pose, centroid, velocity, ...) not finite or beyond
    the codec's bounds."""
    cut = draw(st.integers(1, 5))
    field = draw(st.sampled_from(sorted(HEADER_BOUNDS)))
    beyond = [] if field.endswith("yaw_rad") else [1e30, -1e30]  # a heading need only be finite
    value = draw(st.sampled_from([math.nan, math.inf, -math.inf, *beyond]))
    short = draw(st.integers(0, 20))
    return draw(st.sampled_from([
        ("body not whole points", lambda p: p[:-cut] if len(p) > 64 else p + b"\x00" * cut),
        ("shorter than its header", lambda p: p[:short]),
        ("wrong magic", lambda p: b"XXXX" + p[4:]),
        ("unknown version", lambda p: p[:4] + bytes([0xEE]) + p[5:]),
        (f"{field} {value}", lambda p: _header_float(p, field, value)),
        ("tick negative", lambda p: p[:12] + struct.pack("<i", -1 - cut) + p[16:]),
    ]))


@pytest.mark.parametrize("run", ["plain", "signed"])
@given(lie=control_lies())
def test_a_lying_control_message_is_dropped_counted_and_changes_nothing_for_the_honest(ticks, baselines, run, lie):
    t = ticks[run]
    what, path, value = lie
    frame = t.lie(_set(t._body(t.liar_raw), path, value))
    seen, sent, cmd, dropped, _, decision = t.play(_with_frame(t.ctrl, t.liar, frame), t.data)
    want_seen, want_sent, want_cmd, *_ = baselines[run, "ctrl"]
    plain = decode(frame, Signed).body if t.signed else frame
    with pytest.raises(MalformedMessage):
        decode(plain, ControlMsg)  # a lie by construction: it breaks a declared invariant
    try:
        HeardControl.read(plain)
        read_whole = t.signed or t.liar in decision.group.tolist()  # opened only by the liar's group (or verified)
    except MalformedMessage:
        read_whole = True  # its ballot or motion: refused as it is heard
    assert sum(dropped.values()) == (1 if read_whole else 0), what
    assert t.liar not in {v for v in seen[4]}, what
    assert seen == want_seen, what
    assert sent == want_sent, what
    assert cmd == want_cmd, what


@pytest.mark.parametrize("run", ["plain", "signed"])
@given(lie=payload_lies())
def test_a_lying_payload_is_dropped_and_changes_nothing(ticks, baselines, run, lie):
    t = ticks[run]
    what, change = lie
    b = decode(t.data, DataBundle)
    receptions = [Reception(r.sender, r.object_id, r.rx_time_s, change(r.payload)) if r.sender == t.liar else r
                  for r in b.receptions]
    if receptions == b.receptions:
        return
    seen, sent, cmd, dropped, rejected, _ = t.play(t.ctrl, encode(DataBundle(b.tick, b.t_sim_s, b.receivers,
                                                                            b.decoded, receptions)))
    want_seen, want_sent, want_cmd, _, want_rejected, _ = baselines[run, "data"]
    assert (seen, sent, cmd) == (want_seen, want_sent, want_cmd), what
    row = b.receivers.tolist().index(EGO)
    lies = sum(receptions[k] != b.receptions[k] for k in np.flatnonzero(b.decoded[row]).tolist())  # that it read
    if t.signed:  # not what the liar signed: rejected before it is decoded
        assert dropped == {}, what
        assert sum(rejected.get(DATA_STREAM, {}).values()) - sum(want_rejected.get(DATA_STREAM, {}).values()) == lies
    else:  # dropped as it is decoded, each counted once
        assert dropped == ({DATA_STREAM: lies} if lies else {}), what


DIGESTS = 11  # ControlMsg.digests' place in its wire list


def _swapped(digests: dict[bytes, bytes]):
    """A change of a control message's digests: each row that is a key of ``digests`` becomes its value."""
    def change(a):
        rows = [digests.get(row.tobytes(), row.tobytes()) for row in a]
        return np.frombuffer(b"".join(rows), a.dtype).reshape(a.shape)
    return change


@given(lie=payload_lies())
def test_a_lying_payload_its_sender_vouches_for_is_dropped_as_it_is_decoded(ticks, baselines, lie):
    """The liar puts its lying payloads' digests in its control message and signs it with its
    own valid certificate: the payloads are authentic (nothing more is rejected), and the
    decoder's checks drop each one the ego read, once, as malformed."""
    t = ticks["signed"]
    what, change = lie
    b = decode(t.data, DataBundle)
    receptions = [Reception(r.sender, r.object_id, r.rx_time_s, change(r.payload)) if r.sender == t.liar else r
                  for r in b.receptions]
    if receptions == b.receptions:
        return
    vouched = {payload_digest(r.payload): payload_digest(change(r.payload)) for r in b.receptions
               if r.sender == t.liar}
    body = t._body(t.liar_raw)
    signed = np.frombuffer(body[DIGESTS][2], np.uint8).reshape(body[DIGESTS][1])
    assert set(vouched) <= {row.tobytes() for row in signed}  # what it sent is what it had signed
    body = _set(body, (DIGESTS,), lambda d: _array(d, _swapped(vouched)))
    seen, sent, cmd, dropped, rejected, _ = t.play(_with_frame(t.ctrl, t.liar, t.lie(body)),
                                                   encode(DataBundle(b.tick, b.t_sim_s, b.receivers, b.decoded,
                                                                     receptions)))
    want_seen, want_sent, want_cmd, _, want_rejected, _ = baselines["signed", "data"]
    messages = dict(want_seen[4])
    if t.liar in messages:  # its message as it is now: vouching for its lies
        messages[t.liar] = encode(decode(msgpack.packb(body, use_bin_type=True), ControlMsg))
    assert (seen, sent, cmd) == ((*want_seen[:4], messages), want_sent, want_cmd), what
    row = b.receivers.tolist().index(EGO)
    lies = sum(receptions[k] != b.receptions[k] for k in np.flatnonzero(b.decoded[row]).tolist())  # that it read
    assert rejected == want_rejected, what
    assert dropped == ({DATA_STREAM: lies} if lies else {}), what
