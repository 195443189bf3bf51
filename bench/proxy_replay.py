"""The channel proxy replayed alone: a recorded run's ticks and vehicles' frames through
the proxy's own code in one process, no Zenoh; prints the CPU of each part of an
interval and checks what it publishes against the recording (or writes it out).

    python -m bench.proxy_replay runs/<id>/run.mcap [--rounds 5] [--json]
    python -m bench.proxy_replay --wake

The proxy is built as ``autocast run`` builds it (the profile and the seed from the
recording's metadata, ``relay_extra_frames`` for a signed run) and fed tick by tick:
the world's ``Tick``, then every control frame through the subscriber callback, the
control phase played, then every data frame and the data phase played. What the
inbound callbacks cost runs on Zenoh's threads live, the phases on the proxy's main
thread (the serial part every agent waits for). Run it under another tree's code with
``PYTHONPATH=<tree> python <this file>``: the bundles it publishes are compared to the
recording's, byte for byte, so two trees can be compared on the same input.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import pickle
import statistics
import sys
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import msgpack

from channel_proxy import proxy as proxy_mod
from channel_proxy.profiles import get_profile
from deploy.record.recorder import read_messages, read_metadata
from protocol.codec import decode
from protocol.messages import ChannelStats, ControlMsg, DataTx, Tick


@dataclass
class Recording:
    run: str
    ticks: list[bytes] = field(default_factory=list)  # the world's Tick payloads, in order
    ctrl: dict[int, list[tuple[str, bytes]]] = field(default_factory=lambda: defaultdict(list))  # by tick: (key, raw)
    data: dict[int, list[tuple[str, bytes]]] = field(default_factory=lambda: defaultdict(list))
    ctrl_rx: dict[int, bytes] = field(default_factory=dict)  # the bundles the proxy published, by tick
    data_rx: dict[int, bytes] = field(default_factory=dict)
    stats: dict[int, dict] = field(default_factory=dict)
    meta: dict[str, str] = field(default_factory=dict)


def load(path: Path) -> Recording:
    with open(path, "rb") as f:
        meta = read_metadata(f)
    run = None
    rec = Recording("")
    rec.meta = meta.get("autocast", {})
    with open(path, "rb") as f:
        for _, channel, msg in read_messages(f):
            topic = channel.topic
            if topic.startswith("json/"):
                continue
            parts = topic.split("/")
            if run is None:
                run = parts[1]
            tail = "/".join(parts[2:])
            data = bytes(msg.data)
            if tail == "world/tick":
                rec.ticks.append(data)
            elif tail.startswith("net/ctrl/tx/"):
                rec.ctrl[_tick_of(data)].append((topic, data))
            elif tail.startswith("net/data/tx/"):
                rec.data[_tick_of(data)].append((topic, data))
            elif tail == "net/ctrl/rx":
                rec.ctrl_rx[_tick_of(data)] = data
            elif tail == "net/data/rx":
                rec.data_rx[_tick_of(data)] = data
            elif tail == "net/stats":
                s = decode(data, ChannelStats)
                rec.stats[s.tick] = s.stats
    rec.run = run or ""
    return rec


def _tick_of(raw: bytes) -> int:
    """The tick of a message (every message's first field; a ``Signed`` envelope repeats its body's)."""
    return msgpack.unpackb(raw, raw=False)[2]


class _Payload:
    __slots__ = ("raw",)

    def __init__(self, raw: bytes) -> None:
        self.raw = raw

    def to_bytes(self) -> bytes:
        return self.raw


class _Sample:
    __slots__ = ("key_expr", "payload")

    def __init__(self, key: str, raw: bytes) -> None:
        self.key_expr = key
        self.payload = _Payload(raw)


class _Pub:
    def __init__(self) -> None:
        self.sent: dict[int, bytes] = {}

    def put(self, tick: int, t_sim_s: float, payload: bytes) -> None:
        self.sent[tick] = payload


class _StatsPub:
    def __init__(self) -> None:
        self.sent: list[bytes] = []

    def put(self, payload: bytes) -> None:
        self.sent.append(payload)


def build(rec: Recording):
    from protocol import keys
    meta = rec.meta
    profile = get_profile(meta.get("channel_profile", "lte-direct") or "lte-direct")
    signed = meta.get("signed", "False") == "True"
    cfg = proxy_mod.ProxyConfig(run_id=rec.run, profile=profile, seed=int(meta.get("seed", 0)),
                                relay_extra_frames=signed)
    p = proxy_mod.ChannelProxy(cfg, session=None)
    ctrl_pub, data_pub, stats_pub = _Pub(), _Pub(), _StatsPub()
    p._bundles = {keys.net_ctrl_rx(rec.run): ctrl_pub, keys.net_data_rx(rec.run): data_pub}
    p._pubs = dict(p._bundles)
    p._pubs["stats"] = stats_pub
    return p, ctrl_pub, data_pub, stats_pub


def replay(rec: Recording) -> tuple[dict[str, list[float]], dict[int, bytes], dict[int, bytes], list[bytes]]:
    """One pass over the recording; thread CPU (ms) of each part, per tick."""
    p, ctrl_pub, data_pub, stats_pub = build(rec)
    on_ctrl, on_data = p._inbound("ctrl", ControlMsg), p._inbound("data", DataTx)
    cpu: dict[str, list[float]] = defaultdict(list)
    clock = time.thread_time
    # the two phases are one call; split it where the control phase ends (its bundle out)
    real_put = ctrl_pub.put
    split = [0.0]

    def put(tick: int, t_sim_s: float, payload: bytes) -> None:
        real_put(tick, t_sim_s, payload)
        split[0] = clock()

    ctrl_pub.put = put
    for raw_tick in rec.ticks:
        tick = decode(raw_tick, Tick)
        k = tick.tick
        p._tick = tick
        ctrl_samples = [_Sample(key, raw) for key, raw in rec.ctrl.get(k, [])]
        data_samples = [_Sample(key, raw) for key, raw in rec.data.get(k, [])]
        t0 = clock()
        for s in ctrl_samples:
            on_ctrl(s)
        t1 = clock()
        for s in data_samples:  # filed before the phases play: the data phase then finds them all there
            on_data(s)
        t2 = clock()
        p._play_v2v(tick, time.monotonic())
        t3 = clock()
        cpu["ctrl_in"].append((t1 - t0) * 1e3)
        cpu["data_in"].append((t2 - t1) * 1e3)
        cpu["ctrl_play"].append((split[0] - t2) * 1e3)
        cpu["data_play"].append((t3 - split[0]) * 1e3)
        cpu["all"].append((t3 - t0) * 1e3)
    return cpu, ctrl_pub.sent, data_pub.sent, stats_pub.sent


def collector_cpu(vehicles: int = 40, gap_s: float = 0.001, rounds: int = 8) -> list[float]:
    """CPU (ms, thread time) of the proxy's collecting thread in one control phase while
    ``vehicles`` minimal control messages arrive ``gap_s`` apart through the subscriber
    callback, in another thread (as Zenoh's callback threads deliver them live)."""
    import threading

    import numpy as np

    from protocol import keys
    from protocol.codec import encode
    from protocol.messages import ObjectMap, Pose

    empty = np.zeros(0, dtype=np.int64)
    objects = ObjectMap(empty, empty, np.zeros((0, 2), np.float32), empty, np.zeros((0, 0), np.float32),
                        np.zeros((0, 0), np.float32))
    out = []
    for _ in range(rounds):
        cfg = proxy_mod.ProxyConfig(run_id="w", profile=get_profile("ideal"), phase_timeout_s=30.0)
        p = proxy_mod.ChannelProxy(cfg, session=None)
        vids = list(range(vehicles))
        p._tick = Tick(0, 0.0, vids, [])
        on_ctrl = p._inbound("ctrl", ControlMsg)
        samples = [_Sample(keys.net_ctrl_tx("w", v), encode(ControlMsg(0, 0.0, v, Pose(0.0, 0.0, 0.0), 0.0,
                                                                         np.zeros((0, 3), np.float32), objects, empty)))
                   for v in vids]
        cpu: list[float] = []

        def collect() -> None:
            t = time.thread_time()
            p._collect("ctrl", 0, set(vids), time.monotonic() + 30.0)
            cpu.append(time.thread_time() - t)

        collector = threading.Thread(target=collect)
        collector.start()
        time.sleep(0.05)
        for sample in samples:
            on_ctrl(sample)
            time.sleep(gap_s)
        collector.join()
        out.append(cpu[0] * 1e3)
    return out


_TIMING = ("work_ms", "cpu_ms")


def _stats_without_timing(raw: bytes) -> dict:
    s = decode(raw, ChannelStats)
    return {k: v for k, v in s.stats.items() if k not in _TIMING}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("mcap", type=Path, nargs="?")
    ap.add_argument("--wake", action="store_true", help="instead: the collecting thread's CPU in one control phase "
                    "while 40 messages arrive 1 ms apart (collector_cpu)")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--skip", type=int, default=3, help="ticks left out of the medians (warm-up)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if args.wake:
        cpu = collector_cpu()
        print(json.dumps({"collector_ms_per_phase": round(statistics.median(cpu), 3),
                          "rounds": [round(x, 3) for x in cpu]}))
        return 0
    if args.mcap is None:
        ap.error("a recording is needed (or --wake)")
    rec = load(args.mcap)
    if rec.meta.get("scheme") == "emp":
        ap.error("an EMP run: its proxy plays the edge relay, which this replay does not drive")
    med: dict[str, list[float]] = defaultdict(list)
    for r in range(args.rounds):
        cpu, ctrl, data, stats = replay(rec)
        for part, values in cpu.items():
            med[part].append(statistics.mean(values[args.skip:]))
    diff_ctrl = sum(ctrl.get(k) != raw for k, raw in rec.ctrl_rx.items())
    diff_data = sum(data.get(k) != raw for k, raw in rec.data_rx.items())
    rec_stats = {k: {n: v for n, v in s.items() if n not in _TIMING} for k, s in rec.stats.items()}
    got_stats = {decode(raw, ChannelStats).tick: _stats_without_timing(raw) for raw in stats}
    diff_stats = sum(got_stats.get(k) != s for k, s in rec_stats.items())
    digest = hashlib.sha256(pickle.dumps((sorted(ctrl.items()), sorted(data.items()),
                                          sorted(got_stats.items())))).hexdigest()[:16]
    out = {"ticks": len(rec.ticks), "ctrl_bundles": len(rec.ctrl_rx), "data_bundles": len(rec.data_rx),
           "different": {"ctrl": diff_ctrl, "data": diff_data, "stats": diff_stats}, "digest": digest,
           "ms_per_tick": {part: round(statistics.median(v), 4) for part, v in med.items()},
           "rounds": {part: [round(x, 4) for x in v] for part, v in med.items()}}
    print(json.dumps(out) if args.json else json.dumps(out, indent=1))
    return 0 if diff_ctrl == diff_data == diff_stats == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
