"""Channel bench: decentralised schedule agreement through the real channel proxy, and
the proxy's own cost (autocast bench channel [--quick]).

The proxy runs as its own process (the Zenoh hub); this process stands in for the world
(ticks) and for every connected vehicle (synthetic agents). Each interval every agent
publishes a real ``ControlMsg`` (pose, trajectory, an object map of 1-5 kB point clouds
with v and r for every other vehicle of the domain, whom it heard last interval), reads
the ``CtrlBundle`` the proxy delivers to it, applies the agreement rule
(``vehicle_agent.agreement``), runs the real scheduler and TDMA layout, and transmits
its part in a ``DataTx``; the proxy plays the medium and counts collisions.

Scene: a four-arm intersection (the scheduler bench's geometry): connected vehicles and
as many unconnected cars on the approaches, pedestrians at the corners; cars drive
through at 0-12 m/s (some queue), so object maps change every tick. Each (vehicles,
control loss) pair gets its own proxy; both rules see the same scene sequence.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import signal
import socket
import statistics
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from bench.scheduler import (ARM_LENGTH_M, BYTES_PER_POINT, HEADER_BYTES, LANE_OFFSET_M, SENSOR_RANGE_M, Scene,
                             line_of_sight, relevance)
from channel_proxy.harness import Harness
from protocol.codec import decode
from protocol.messages import ControlMsg, DataTx, ObjectMap, Pose, Transmission
from protocol.session import ZenohArgs, session_scope
from vehicle_agent.agreement import AgreementConfig, decide, plan

VEHICLES = (20, 40)
LOSSES_PCT = (0, 5, 10, 20, 30)
QUICK_VEHICLES, QUICK_LOSSES_PCT = (40,), (0, 10)  # the headline's configuration and a lossless one
OBJECTS_PER_VEHICLE = 30
DOMAIN_RADIUS_M = 86.8  # R/2 plus the guard band
T_D = 0.1


# ------------------------------------------------------------------------- the scene


@dataclass(frozen=True, slots=True)
class Traffic:
    """Cars on the four approaches driving through, pedestrians at the corners; the
    state at tick k is a pure function of k."""

    arm: np.ndarray  # (A,) 0..3 (E, N, W, S); -1 for pedestrians
    lateral_m: np.ndarray  # (A,)
    along0_m: np.ndarray  # (A,) distance to the centre along the arm at tick 0
    speed_mps: np.ndarray  # (A,)
    ped_xy: np.ndarray  # (P, 2)
    n_connected: int

    @staticmethod
    def make(seed: int, n_connected: int) -> Traffic:
        rng = np.random.default_rng([seed, n_connected])
        n_cars = 2 * n_connected
        speed = rng.uniform(4.0, 12.0, n_cars) * (rng.random(n_cars) > 0.3)  # ~30% queue
        pedestrians = 4 + n_connected // 2
        corner = rng.integers(0, 4, pedestrians) * (np.pi / 2) + np.pi / 4
        ped_r = rng.uniform(13.0, 18.0, pedestrians)
        return Traffic(
            arm=rng.integers(0, 4, n_cars),
            lateral_m=rng.choice(LANE_OFFSET_M, n_cars) * rng.choice((-1.0, 1.0), n_cars),
            along0_m=rng.uniform(-20.0, ARM_LENGTH_M, n_cars),
            speed_mps=speed,
            ped_xy=np.stack([ped_r * np.cos(corner), ped_r * np.sin(corner)], axis=1),
            n_connected=n_connected,
        )

    def scene(self, k: int) -> Scene:
        span = ARM_LENGTH_M + 20.0
        along = (self.along0_m - self.speed_mps * T_D * k + 20.0) % span - 20.0  # drive through, re-enter
        angle = self.arm * (np.pi / 2)
        ux, uy = np.cos(angle), np.sin(angle)
        car_xy = np.stack([ux * along - uy * self.lateral_m, uy * along + ux * self.lateral_m], axis=1)
        P = len(self.ped_xy)
        return Scene(
            xy=np.concatenate([car_xy, self.ped_xy]),
            arm=np.concatenate([self.arm, -np.ones(P, dtype=np.int64)]),
            along_m=np.concatenate([along, np.hypot(*self.ped_xy.T)]),
            radius_m=np.concatenate([np.full(len(car_xy), 2.2), np.full(P, 0.4)]),
            n_connected=self.n_connected,
        )


VID_BASE = 100  # vehicle c is vid VID_BASE + c


def control_messages(traffic: Traffic, k: int, tick: int, heard: dict[int, list[int]]) -> tuple[list[ControlMsg], dict]:
    """Every connected vehicle's control message for interval ``tick`` in the scene at
    step k, and the rewards y[(sender vid, object id)] = {receiver vid: y} behind them."""
    scene = traffic.scene(k)
    detects, seen = line_of_sight(scene)  # (C, A)
    r = relevance(scene)  # (A, C)
    C = traffic.n_connected
    vids = VID_BASE + np.arange(C)
    in_domain = np.hypot(*scene.xy[:C].T) <= DOMAIN_RADIUS_M
    rng = np.random.default_rng([k, C, 7])
    noise = rng.uniform(0.9, 1.1, (C, len(scene.xy)))  # point counts vary from scan to scan
    msgs, rewards = [], {}
    for i in range(C):
        cand = np.flatnonzero(detects[i])
        dist = np.hypot(*(scene.xy[cand] - scene.xy[i]).T)
        keep = dist < SENSOR_RANGE_M
        objs = cand[keep][np.argsort(dist[keep], kind="stable")][:OBJECTS_PER_VEHICLE]
        objs = np.sort(objs)
        d_obj = np.hypot(*(scene.xy[objs] - scene.xy[i]).T)
        points = np.clip(5000.0 / np.maximum(d_obj, 5.0), 60, 300) * noise[i, objs]
        size = (points.astype(np.int64) * BYTES_PER_POINT + HEADER_BYTES).astype(np.int64)
        rx = np.flatnonzero(in_domain & (np.arange(C) != i))
        vis = seen[rx][:, objs].T.astype(np.float32)  # (n, m)
        rel = r[objs][:, rx].astype(np.float32)
        rel[objs[:, None] == rx[None, :]] = 0.0  # a vehicle needs no point cloud of itself
        y = (1.0 - vis) * rel
        for t, oid in enumerate(objs.tolist()):
            want = np.flatnonzero(y[t] > 0)
            if len(want):
                rewards[(int(vids[i]), oid)] = dict(zip(vids[rx[want]].tolist(), y[t, want].tolist()))
        x, yy = scene.xy[i]
        heading = float(scene.arm[i]) * np.pi / 2 + np.pi  # driving towards the centre
        steps = np.arange(7, dtype=np.float64)
        v = float(traffic.speed_mps[i])
        traj = np.stack([x + np.cos(heading) * v * steps, yy + np.sin(heading) * v * steps, tick * T_D + steps], axis=1)
        msgs.append(ControlMsg(
            tick, tick * T_D, int(vids[i]), Pose(float(x), float(yy), heading), v, traj.astype(np.float32),
            ObjectMap(objs.astype(np.int64), size, scene.xy[objs].astype(np.float32), vids[rx].astype(np.int64), vis, rel),
            np.array(sorted(heard.get(int(vids[i]), [])), dtype=np.int64),
        ))
    return msgs, rewards


def payload(vid: int, oid: int, k: int, size: int) -> bytes:
    head = f"{vid}:{oid}:{k}:".encode()
    return head + bytes(max(0, size - len(head)))


# ------------------------------------------------------------------------- the agents


RULES = {
    "heard": AgreementConfig(rule="heard"),  # the paper's: schedule over what was heard
    "grouped": AgreementConfig(),  # vehicle_agent.agreement's rule
}
ORACLE = "oracle"  # every vehicle handed every control message: the paper's assumption


@dataclass
class Interval:
    """One interval's figures, as the proxy counted them and as the agents scored them."""

    transmissions: int
    collided: int
    members: int
    abstained: int
    intended_bytes: int  # sum over sent objects of size x receivers that want it
    delivered_intended_bytes: int
    reward: float  # sum of y over (object, receiver) pairs delivered
    proxy_cpu_ms: float
    proxy_work_ms: float
    ctrl_overflow: int


class Fleet:
    """All synthetic agents of one run, driven through a running proxy."""

    def __init__(self, harness: Harness, traffic: Traffic, rule: str) -> None:
        self.h = harness
        self.traffic = traffic
        self.rule = rule
        self.cfg = RULES.get(rule, RULES["heard"])
        self.heard: dict[int, list[int]] = {}
        self._decoded: dict[bytes, ControlMsg] = {}

    def interval(self, k: int, tick: int) -> Interval:
        h = self.h
        msgs, rewards = control_messages(self.traffic, k, tick, self.heard)
        h.tick(tick)
        for m in msgs:
            h.send_ctrl(m)
        bundles = h.wait_ctrl(tick)
        members = abstained = 0
        self.heard = {}
        sent: list[DataTx] = []
        for m in msgs:
            got = [self._decode(raw) for raw in bundles[m.vid].messages]
            self.heard[m.vid] = [g.vid for g in got]
            decision = decide(m.vid, tick, m, msgs if self.rule == ORACLE else got, self.cfg)
            members += decision.is_member
            abstained += decision.is_member and not decision.transmits
            txs = [Transmission(t.object_id, t.start_s, payload(m.vid, t.object_id, tick, t.size_bytes))
                   for t in plan(decision, self.cfg)]
            sent.append(DataTx(tick, tick * T_D, m.vid, txs))
        for d in sent:
            h.send_data(d)
        data = h.wait_data(tick)
        stats = h.wait_stats(tick)
        self._decoded = {}
        intended = sum(len(t.payload) * len(rewards.get((d.vid, t.object_id), {})) for d in sent for t in d.transmissions)
        delivered = reward = 0.0
        for receiver, bundle in data.items():
            got_pairs = set()
            for r in bundle.receptions:
                y = rewards.get((r.sender, r.object_id), {}).get(receiver)
                if y:
                    delivered += len(r.payload)
                    if (r.sender, r.object_id) not in got_pairs:
                        reward += y
                        got_pairs.add((r.sender, r.object_id))
        return Interval(stats["data"]["transmissions"], stats["data"]["collided_tx"], members, abstained, intended,
                        int(delivered), reward, stats["cpu_ms"], stats["work_ms"], stats["ctrl"]["overflow_msgs"])

    def _decode(self, raw: bytes) -> ControlMsg:
        msg = self._decoded.get(raw)
        if msg is None:
            msg = self._decoded[raw] = decode(raw, ControlMsg)
        return msg


def free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


@contextlib.contextmanager
def proxy_process(run_id: str, ctrl_loss: float, seed: int, hub: str) -> Iterator[subprocess.Popen]:
    """A real proxy process, a client of the bench's hub (as it is of the world's in a
    run, so its CPU time is its own work, not the hub's routing); always stopped."""
    proc = subprocess.Popen([sys.executable, "-m", "channel_proxy", "--run-id", run_id, "--connect", hub,
                             "--ctrl-loss", str(ctrl_loss), "--seed", str(seed), "--phase-timeout-s", "20"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        yield proc
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def run_config(n: int, ctrl_loss: float, rules: list[str], intervals: int, seed: int) -> dict[str, list[Interval]]:
    """Every rule on the same scene sequence through one proxy (one warm-up interval each:
    the first has no heard sets yet)."""
    run_id = f"bench-{n}-{int(round(ctrl_loss * 100))}"
    traffic = Traffic.make(seed, n)
    out: dict[str, list[Interval]] = {}
    hub = free_endpoint()
    with session_scope(ZenohArgs(listen=(hub,))) as session, proxy_process(run_id, ctrl_loss, seed, hub):
        harness = Harness(session, run_id, [VID_BASE + c for c in range(n)])
        try:
            harness.wait_proxy()
            tick = 0
            for rule in rules:
                fleet = Fleet(harness, traffic, rule)
                runs = []
                for k in range(intervals + 1):
                    iv = fleet.interval(k, tick)
                    tick += 1
                    if k > 0:
                        runs.append(iv)
                out[rule] = runs
        finally:
            harness.close()
    return out


# ------------------------------------------------------------------------- report


def _med(xs) -> float:
    xs = list(xs)
    return statistics.median(xs) if xs else float("nan")


def summarize(ivs: list[Interval]) -> dict[str, float]:
    """Medians over the intervals of per-interval figures."""
    return {
        "tx": _med(i.transmissions for i in ivs),
        "coll": _med(i.collided for i in ivs),
        "coll_max": max((i.collided for i in ivs), default=0),
        "disagree_pct": _med(100.0 * i.collided / i.transmissions if i.transmissions else 0.0 for i in ivs),
        "abstain_pct": _med(100.0 * i.abstained / i.members if i.members else 0.0 for i in ivs),
        "delivered_pct": _med(100.0 * i.delivered_intended_bytes / i.intended_bytes for i in ivs if i.intended_bytes),
        "reward": _med(i.reward for i in ivs),
        "ctrl_overflow": _med(i.ctrl_overflow for i in ivs),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="autocast bench channel", description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true",
                    help=f"{QUICK_VEHICLES[0]} vehicles at {' and '.join(map(str, QUICK_LOSSES_PCT))}%% loss, "
                         "fewer intervals (well under a minute)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--vehicles", type=int, nargs="+", default=None, help="fleet sizes (headline: the largest)")
    ap.add_argument("--losses", type=int, nargs="+", default=None, metavar="PCT",
                    help="control loss rates in %% (headline: the one nearest 10)")
    ap.add_argument("--intervals", type=int, default=None, help="intervals per configuration and rule")
    args = ap.parse_args(argv)
    intervals = args.intervals or (5 if args.quick else 20)
    args.vehicles = args.vehicles or list(QUICK_VEHICLES if args.quick else VEHICLES)
    args.losses = args.losses or list(QUICK_LOSSES_PCT if args.quick else LOSSES_PCT)
    logging.basicConfig(level=logging.WARNING)
    big = max(args.vehicles)
    loss_head = min(args.losses, key=lambda x: abs(x - 10))

    rows = []
    proxy40: list[float] = []
    work40: list[float] = []
    for n in args.vehicles:
        oracle = None
        for loss_pct in args.losses:
            rules = ["heard", "grouped"] + ([ORACLE] if oracle is None else [])
            got = run_config(n, loss_pct / 100.0, rules, intervals, args.seed)
            if oracle is None:
                oracle = summarize(got[ORACLE])
            for rule in ("heard", "grouped"):
                s = summarize(got[rule])
                s["vs_oracle"] = s["reward"] / oracle["reward"] if oracle["reward"] else float("nan")
                rows.append((n, rule, loss_pct, s))
            if n == big:
                proxy40 += [i.proxy_cpu_ms for ivs in got.values() for i in ivs]
                work40 += [i.proxy_work_ms for ivs in got.values() for i in ivs]
        print(f"{n} vehicles: oracle (every vehicle holds every control message) {oracle['tx']:.0f} transmissions, "
              f"reward {oracle['reward']:.1f} per interval", flush=True)

    print()
    print(f"agreement vs control loss, medians over {intervals} intervals: tx = transmissions, coll = those that "
          "collided (max: in the worst interval), disagree = their share, abstain = members silent for an incomplete view, delivered = share of "
          "scheduled bytes x wanting receivers that arrived, reward = sum of y delivered, vs oracle = reward / the "
          "oracle's (every vehicle holding every control message)")
    head = f"{'veh':>4} {'rule':<8}{'loss%':>6}{'tx':>6}{'coll':>6}{'max':>5}{'disagree%':>10}{'abstain%':>9}{'delivered%':>11}" \
           f"{'reward':>8}{'vs oracle':>10}{'ctrl ovf':>9}"
    print(head)
    for n, rule, loss_pct, s in rows:
        print(f"{n:>4} {rule:<8}{loss_pct:>6}{s['tx']:>6.0f}{s['coll']:>6.0f}{s['coll_max']:>5}{s['disagree_pct']:>10.2f}"
              f"{s['abstain_pct']:>9.1f}{s['delivered_pct']:>11.1f}{s['reward']:>8.1f}{s['vs_oracle']:>10.2f}"
              f"{s['ctrl_overflow']:>9.0f}")
    print()
    print(f"proxy at {big} vehicles, per interval: cpu {_med(proxy40):.1f} ms (process CPU, all threads: decode, "
          f"medium, encode, Zenoh I/O), work {_med(work40):.1f} ms (wall time of the phase closes)")
    headline = next(s for n, rule, loss_pct, s in rows if n == big and rule == "grouped" and loss_pct == loss_head)
    print(f"channel: disagreement_loss10_pct={headline['disagree_pct']:.2f} proxy40_ms={_med(proxy40):.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
