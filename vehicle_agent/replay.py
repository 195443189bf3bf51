"""Replay agents from a run's MCAP log, in one process, and diff what they send.

Each vehicle's agent is fed what it got in the run (its mission, the map, its scans,
the channel's control and data bundles, or EMP's relay bundles) tick by tick, and what
it sends (control messages, data transmissions, EMP uploads, commands, the ego's
report) is compared byte for byte with what the log holds. Lock-step runs are
deterministic, so a change that only makes the agent faster must replay every agent
of every logged run identically; and the replay times the agent's whole tick without
the other 40 processes of a run competing for the cores.

    autocast run --vehicles 40 --scans all --duration 3 --out runs --run-id r40
    python -m vehicle_agent.replay runs/r40                  # every agent whose scans were logged
    python -m vehicle_agent.replay runs/r40 --vids 0,7 --profile /tmp/agents.pstats

The run needs its scans in the log (``--scans all``; the default ``ego`` keeps vehicle
0's). The CPU per tick counts the agent's step and the decoding its subscriber threads
do in a live run (the scan, the whole control and data bundles), not Zenoh's own work.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import sys
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from protocol import keys
from protocol.codec import decode, encode, peek_envelope
from protocol.messages import (ControlMsg, CtrlBundle, DataBundle, DataTx, EmpBundle, EmpUpload, MapMsg, Mission,
                               Pose, Reception, Scan, Transmission)
from protocol.session import DropCounter
from vehicle_agent.agreement import HeardControl
from vehicle_agent.link import heard_in, received_in

OUTPUTS = ("ctrl", "data", "emp", "cmd", "report")


@dataclass
class Log:
    """One run's log, by key: the raw payloads of every message, per tick where it has one."""

    run_id: str
    metadata: dict[str, str]
    static: dict[str, bytes] = field(default_factory=dict)  # map and missions
    by_key: dict[str, dict[int, bytes]] = field(default_factory=dict)  # key -> tick -> payload

    @staticmethod
    def read(path: Path) -> Log:
        from mcap.reader import make_reader

        with open(path, "rb") as f:
            reader = make_reader(f)
            meta = {}
            for m in reader.iter_metadata():
                meta.update(m.metadata)
            out = Log(meta.get("run_id", ""), meta)
            for _, channel, message in reader.iter_messages():
                env = peek_envelope(message.data)
                if env is None:
                    continue
                if channel.topic.endswith("/world/map") or "/mission" in channel.topic:
                    out.static[channel.topic] = message.data
                else:
                    out.by_key.setdefault(channel.topic, {})[env.tick] = message.data
        if not out.run_id and out.static:
            out.run_id = next(iter(out.static)).split("/")[1]
        return out

    def payloads(self, key: str) -> dict[int, bytes]:
        return self.by_key.get(key, {})

    def vids_with_scans(self) -> list[int]:
        return sorted(v for v in range(1024) if keys.scan(self.run_id, v) in self.by_key)


class ReplayLink:
    """``V2VLink``'s interface over the logged bundles; keeps what the agent sent."""

    def __init__(self, log: Log, vid: int, drops: DropCounter) -> None:
        run = log.run_id
        self.vid, self.drops, self.wait_s, self.missed_bundles = vid, drops, 0.0, 0
        self.ctrl_rx, self.data_rx = log.payloads(keys.net_ctrl_rx(run)), log.payloads(keys.net_data_rx(run))
        self.emp_rx = log.payloads(keys.net_emp_down(run, vid))
        self.sent: dict[str, dict[int, bytes]] = {name: {} for name in OUTPUTS}
        self.decode_s = 0.0  # decoding the bundles, done by the subscriber threads in a live run

    def _decode(self, raw: bytes | None, cls: type):
        if raw is None:
            return None
        t0 = time.process_time()
        try:
            return decode(raw, cls)
        finally:
            self.decode_s += time.process_time() - t0

    def exchange_control(self, msg: ControlMsg) -> list[HeardControl]:
        self.sent["ctrl"][msg.tick] = encode(msg)
        heard = heard_in(self._decode(self.ctrl_rx.get(msg.tick), CtrlBundle), self.vid, self.drops)
        self.missed_bundles += heard is None
        return heard or []

    def exchange_control_raw(self, raw: bytes, tick: int) -> CtrlBundle | None:
        self.sent["ctrl"][tick] = raw
        return self._decode(self.ctrl_rx.get(tick), CtrlBundle)

    def exchange_data(self, tick: int, t_sim_s: float, transmissions: list[Transmission],
                      receive: bool = True) -> list[Reception]:
        self.sent["data"][tick] = encode(DataTx(tick, t_sim_s, self.vid, transmissions))
        if not receive:  # as V2VLink: a vehicle that fuses nothing takes no data bundle
            return []
        mine = received_in(self._decode(self.data_rx.get(tick), DataBundle), self.vid)
        self.missed_bundles += mine is None
        return mine or []

    def exchange_emp(self, tick: int, t_sim_s: float, pose: Pose, segment_world: np.ndarray) -> EmpBundle | None:
        self.sent["emp"][tick] = encode(EmpUpload(tick, t_sim_s, self.vid, pose, segment_world.astype(np.float32)))
        bundle = self._decode(self.emp_rx.get(tick), EmpBundle)
        self.missed_bundles += bundle is None
        return bundle


@dataclass(frozen=True, slots=True)
class Replayed:
    vid: int
    ticks: int
    mismatches: list[str]  # "<output> tick <k>" where the replay differs from the log
    cpu_ms: float  # the agent's step and its decoding, per tick, the first tick left out
    decode_ms: float  # of which decoding the scans and bundles
    stages_ms: dict[str, float]  # each stage's CPU time per tick (the agent's own timings)


def model_of(metadata: dict[str, str]):
    """The run's model from its MCAP metadata (``model``, ``model_settings``); ours for a
    log that names none."""
    from protocol.model import resolve

    settings = json.loads(metadata.get("model_settings") or "{}")
    return resolve((metadata.get("model") or "ours").partition("+")[0], settings)


def replay(log: Log, vid: int, profiler: cProfile.Profile | None = None, credentials: Path | None = None) -> Replayed:
    """Replay vehicle ``vid`` over the log and diff its outputs; a run that signed needs
    the vehicle's ``credentials`` (``<run>/credentials/agent<vid>.v2x.json``): Ed25519
    signatures are deterministic, so the replay signs what the run signed."""
    from protocol.security import Credentials
    from vehicle_agent.__main__ import Pipeline
    from vehicle_agent.guard import Guard
    from vehicle_agent.warmup import warm_up

    run = log.run_id
    scheme = log.metadata.get("scheme", "autocast")
    mission = decode(log.static[keys.mission(run, vid)], Mission)
    mapmsg = decode(log.static[keys.world_map(run)], MapMsg)
    drops = DropCounter()
    link = None if scheme in ("single", "lane") else ReplayLink(log, vid, drops)
    reports: dict[int, bytes] = {}
    guard = Guard(Credentials.load(credentials), drops) if credentials is not None else None
    step = Pipeline(mission, mapmsg, scheme, log.metadata.get("channel_profile") or "lte-direct",
                    log.metadata.get("scheduler") or None, link,
                    (lambda raw: reports.__setitem__(decode(raw).tick, raw)) if mission.role == "ego" else None,
                    guard, model_of(log.metadata))
    if scheme != "lane":
        warm_up(step.agent, step.agreement)
    cmds: dict[int, bytes] = {}
    costs, decoding = [], []
    for tick, raw in sorted(log.payloads(keys.scan(run, vid)).items()):
        t0 = time.process_time()
        before = link.decode_s if link is not None else 0.0
        scan = decode(raw, Scan)
        t_scan = time.process_time() - t0
        cmd = step.run(scan) if profiler is None else profiler.runcall(step.run, scan)
        cmds[tick] = step.wire(cmd)
        costs.append(time.process_time() - t0)
        decoding.append(t_scan + (link.decode_s - before if link is not None else 0.0))
    sent = dict(link.sent) if link is not None else {}
    sent.update(cmd=cmds, report=reports)
    logged = {"ctrl": keys.net_ctrl_tx(run, vid), "data": keys.net_data_tx(run, vid),
              "emp": keys.net_emp_up(run, vid), "cmd": keys.cmd(run, vid), "report": keys.report(run, vid)}
    mismatches = []
    for name, key in logged.items():
        got, want = sent.get(name, {}), log.payloads(key)
        ticks = sorted(set(got) & set(cmds) | set(want) & set(cmds))
        mismatches += [f"{name} tick {k}" for k in ticks if got.get(k) != want.get(k)]
    summary = step.timing_summary()
    stages = {k.removesuffix("_cpu_mean"): v for k, v in summary.items() if k.endswith("_cpu_mean")}
    return Replayed(vid, len(costs), mismatches, _mean_ms(costs[1:]), _mean_ms(decoding[1:]), stages)


def _mean_ms(seconds: list[float]) -> float:
    return float(np.mean(seconds)) * 1e3 if seconds else 0.0


def main(argv: Iterable[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m vehicle_agent.replay", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run_dir", type=Path, help="a run's directory (its run.mcap) or an .mcap file")
    ap.add_argument("--vids", default=None, help="comma-separated vehicle ids (default: every one with scans)")
    ap.add_argument("--profile", default=None, help="write a cProfile of every replayed tick here")
    args = ap.parse_args(list(argv) if argv is not None else None)
    path = args.run_dir if args.run_dir.suffix == ".mcap" else args.run_dir / "run.mcap"
    log = Log.read(path)
    vids = [int(v) for v in args.vids.split(",")] if args.vids else log.vids_with_scans()
    if not vids:
        print(f"error: {path} holds no scans (record with --scans all)", file=sys.stderr)
        return 2
    profiler = cProfile.Profile(time.process_time) if args.profile else None
    bad = 0
    results = []
    for vid in vids:
        creds = path.parent / "credentials" / f"agent{vid}.v2x.json"
        r = replay(log, vid, profiler, creds if log.metadata.get("signed") == "True" and creds.exists() else None)
        results.append(r)
        bad += bool(r.mismatches)
        verdict = "identical" if not r.mismatches else f"DIFFERENT ({len(r.mismatches)}: {', '.join(r.mismatches[:5])})"
        stages = " ".join(f"{k}={v:.2f}" for k, v in r.stages_ms.items() if k != "cpu")
        print(f"agent{vid}: {r.ticks} ticks, {verdict}, {r.cpu_ms:.2f} ms CPU per tick (decoding {r.decode_ms:.2f}; "
              f"{stages})", flush=True)
    if profiler is not None:
        profiler.dump_stats(args.profile)
    cpu = [r.cpu_ms for r in results]
    print(f"replay: agents={len(results)} different={bad} cpu_median_ms={np.median(cpu):.2f} "
          f"cpu_mean_ms={np.mean(cpu):.2f}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
