"""The world server's I/O: serve the map and missions, publish ticks and scans, collect
commands, step the simulation, publish the judged outcome.

Liveness (openpilot SubMaster style): every agent holds a Zenoh liveliness token while
its session is up. A token that disappears (the process died or closed) marks the agent
dead at once; an agent whose command for a tick does not arrive within
``agent_timeout_s`` of wall time is marked dead too. A dead agent's vehicle gets the
failsafe (full brake) and the run goes on without it.

Start: tick 0 is not played before every connected agent's token is up (or
``startup_timeout_s`` passed), the channel proxy's token ``keys.proxy_alive`` is up
when the run has one (``wait_for_proxy``: the agents' tick-0 messages go to the proxy, and
one it has not subscribed yet is lost), and every participant named in ``wait_for``
holds its token ``keys.participant_alive``: a process that is not an agent but must see
the run from tick 0 (a test's hostile peer) says so, whatever the machine's speed.

Reports: each event's ego agent reports its fused view every tick (``AgentReport`` on
``keys.report``), for its event's judge; a scenario of several events has several.

Authenticity (``verifier``): with the run's authority key, a command (and an ego's
report) is accepted only as a ``Signed`` envelope by that vehicle's certificate, of a
tick newer than the last one accepted from it; anything else is dropped and counted by
reason (``protocol.security``), and the counts go into the result as ``rejected``.

Modes: lock-step (default) waits, per tick, for every live agent's command: runs are
deterministic for a seed. Real-time (``realtime=True``) ticks on the wall clock every
decision interval; an agent whose command is late keeps its last one.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field

import zenoh

from protocol import keys, phases
from protocol.codec import encode
from protocol.faults import Injector
from protocol.messages import AgentReport, Command, Outcome, Scan, Tick
from protocol.security import Verifier
from protocol.session import DropCounter, reliable_publisher, typed_handler
from protocol.shm import ShmPublisher
from world_server.sim import Simulation
from world_server.wire import encode_parts

log = logging.getLogger(__name__)


@dataclass
class ServerStats:
    ticks: int = 0
    dead: dict[int, str] = field(default_factory=dict)  # vid -> why
    late_commands: int = 0
    wall_s: float = 0.0


class WorldServer:
    def __init__(self, sim: Simulation, session: zenoh.Session, run_id: str, *, realtime: bool = False,
                 agent_timeout_s: float = 10.0, startup_timeout_s: float = 120.0, ego_reports: bool = False,
                 verifier: Verifier | None = None, wait_for: tuple[str, ...] = (),
                 wait_for_proxy: bool = False, shm_dir: str | None = None) -> None:
        self.sim = sim
        self.shm_dir = shm_dir  # the scans go through shared memory (protocol.shm)
        self.verifier = verifier
        self.faults = Injector("world")
        self.session = session
        self.run_id = run_id
        self.realtime = realtime
        self.agent_timeout_s = agent_timeout_s
        self.startup_timeout_s = startup_timeout_s
        self.drops = DropCounter()
        self.stats = ServerStats()
        self._cv = threading.Condition()
        self._tokens: set[int] = set()
        self._cmds: dict[int, Command] = {}  # latest command per vid
        # lock-step: the tick whose commands ``_collect_lockstep`` waits for, and the live
        # vehicles it has not had one from when it last looked; a command wakes it only
        # when it is the last of these (one wake-up a tick, not one per command)
        self._waiting_tick = -1
        self._waiting: set[int] = set()
        self._egos = sorted({ev.ego for ev in sim.scenario.events})  # the vehicles that report
        self._reports: dict[int, dict[int, AgentReport]] = {}  # tick -> ego vid -> its fused-view report
        self._report_tick: dict[int, int] = {}  # per ego, the newest report accepted: an older one is a replay
        # the egos' agents report their fused view: lock-step waits for each. Told so up
        # front (--ego-reports), from the first tick; otherwise once an ego's first report
        # has come, and whether that beat the first command was a race that changed the
        # judged visibility share of identical runs
        self._reporting: set[int] = set(self._egos) if ego_reports else set()
        self._expected = set(sim.connected_vids)
        self._live = set(self._expected)
        # the tokens besides the agents' that tick 0 waits for: liveliness key -> name
        self._awaited = {keys.participant_alive(run_id, name): name for name in wait_for}
        if wait_for_proxy:
            self._awaited[keys.proxy_alive(run_id)] = "proxy"
        self._up: set[str] = set()  # the awaited keys whose token is up
        self._stopping = threading.Event()
        self._entities: list = []

    # ------------------------------------------------------------------ wiring

    def _declare(self) -> None:
        s, run = self.session, self.run_id
        map_bytes = encode(self.sim.scenario.roadmap.to_msg())
        missions = {vid: encode(self.sim.mission(vid)) for vid in self.sim.connected_vids}

        def on_map(query: zenoh.Query) -> None:
            query.reply(keys.world_map(run), map_bytes)

        def on_mission(query: zenoh.Query) -> None:
            try:
                vid = keys.vid_of(str(query.key_expr))
            except ValueError:
                return
            if vid in missions:
                query.reply(keys.mission(run, vid), missions[vid])

        # the publishers first: what Zenoh tells a new publisher of its subscribers comes on
        # the hub's link before the tokens the liveliness subscribers below ask for, so by
        # the time those let tick 0 go, a scan's ShmPublisher knows whether anyone listens
        # on its key (a recorder keeping scans); declared after them, tick 0's scans were
        # sometimes not recorded when every agent was up before the world
        self._tick_pub = reliable_publisher(s, keys.world_tick(run))
        self._truth_pub = reliable_publisher(s, keys.world_truth(run))
        self._scan_pubs = {vid: ShmPublisher(s, keys.scan(run, vid), self.shm_dir) for vid in self._expected}
        self._entities += [self._tick_pub, self._truth_pub, *self._scan_pubs.values()]
        self._entities += [
            s.declare_queryable(keys.world_map(run), on_map),
            s.declare_queryable(keys.mission(run, "*"), on_mission),
            s.declare_subscriber(keys.cmd(run, "*"), self._handler(Command, self._on_cmd)),
            *(s.declare_subscriber(keys.report(run, ego), self._handler(AgentReport, self._on_report))
              for ego in self._egos),
            s.liveliness().declare_subscriber(keys.alive(run, "*"), self._on_token, history=True),
        ]
        self._entities += [s.liveliness().declare_subscriber(key, self._on_awaited, history=True)
                           for key in self._awaited]

    def _on_token(self, sample: zenoh.Sample) -> None:
        try:
            vid = keys.vid_of(str(sample.key_expr))
        except ValueError:
            return
        with self._cv:
            if sample.kind == zenoh.SampleKind.PUT:
                self._tokens.add(vid)
            else:
                self._tokens.discard(vid)
                if vid in self._live:
                    self._mark_dead(vid, "liveliness token dropped")
            self._cv.notify_all()

    def _on_awaited(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        with self._cv:
            if sample.kind == zenoh.SampleKind.PUT:
                self._up.add(key)
            else:
                self._up.discard(key)
            self._cv.notify_all()

    def _handler(self, expected: type, on_msg):
        """Plain messages through ``typed_handler``; with a verifier, only verified ones."""
        verifier = self.verifier
        if verifier is None:
            return typed_handler(expected, on_msg, self.drops)
        return typed_handler(expected, on_msg, self.drops,
                             lambda payload, key: verifier.open(payload, expected, keys.vid_of(key), key))

    def _on_cmd(self, key: str, cmd: Command) -> None:
        if keys.vid_of(key) != cmd.vid:
            self.drops.add(key, ValueError(f"command for vid {cmd.vid} on another vehicle's key"))
            return
        with self._cv:
            prev = self._cmds.get(cmd.vid)
            if self.verifier is not None and prev is not None and cmd.tick <= prev.tick:
                self.verifier.rejections.add(key, "replayed", f"vehicle {cmd.vid}, tick {cmd.tick}")
                return
            if prev is None or cmd.tick >= prev.tick:
                self._cmds[cmd.vid] = cmd
            if cmd.tick >= self._waiting_tick and cmd.vid in self._waiting:
                self._waiting.discard(cmd.vid)
                if self._waiting:
                    return  # the collector waits for others' too: no use waking it
            self._cv.notify_all()

    def _on_report(self, key: str, report: AgentReport) -> None:
        vid = keys.vid_of(key)
        if vid != report.vid:
            self.drops.add(key, ValueError(f"report of vid {report.vid} on another vehicle's key"))
            return
        with self._cv:
            newest = self._report_tick.get(vid, -1)
            if self.verifier is not None and report.tick <= newest:
                self.verifier.rejections.add(key, "replayed", f"report of tick {report.tick}")
                return
            self._report_tick[vid] = max(newest, report.tick)
            self._reports.setdefault(report.tick, {})[vid] = report
            self._reporting.add(vid)
            self._cv.notify_all()

    def _mark_dead(self, vid: int, why: str) -> None:
        """Caller holds ``_cv``."""
        self._live.discard(vid)
        self.stats.dead[vid] = why
        log.warning("agent %d is dead (%s); its vehicle brakes to a stop", vid, why)

    # ------------------------------------------------------------------ running

    def stop(self) -> None:
        self._stopping.set()
        with self._cv:
            self._cv.notify_all()

    def serve(self) -> dict:
        """Run to the judged outcome; returns the result dict (also published)."""
        self._declare()
        try:
            self._wait_to_start()
            t0 = time.monotonic()
            while not self.sim.done and not self._stopping.is_set():
                self._one_tick(t0)
            self.stats.wall_s = time.monotonic() - t0
            result = self._result()
            if not self.sim.done:  # stopped from outside: the scenario did not play out, nothing is judged
                result.update(outcome=None, stopped_at_tick=self.sim.tick,
                              failure=f"the world was stopped at tick {self.sim.tick}, before the scenario played out")
            self.session.put(keys.world_outcome(self.run_id), encode(Outcome(self.sim.tick, self.sim.t_sim_s, result)),
                             congestion_control=zenoh.CongestionControl.BLOCK)
            return result
        finally:
            for entity in self._entities:
                entity.undeclare()

    def _wait_to_start(self) -> None:
        deadline = time.monotonic() + self.startup_timeout_s
        with self._cv:
            while not (self._expected <= self._tokens and self._up >= self._awaited.keys()) \
                    and not self._stopping.is_set():
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                self._cv.wait(min(left, 0.5))
            for vid in sorted(self._expected - self._tokens):
                self._mark_dead(vid, f"never came up within {self.startup_timeout_s:.0f} s")
            up = sorted(name for key, name in self._awaited.items() if key in self._up)
            missing = sorted(name for key, name in self._awaited.items() if key not in self._up)
        if missing:
            log.error("%s never came up within %.0f s; starting without them", ", ".join(missing), self.startup_timeout_s)
        if up:
            log.info("also up before tick 0: %s", ", ".join(up))
        log.info("%d of %d agents up; starting", len(self._live), len(self._expected))  # the benches key on this line

    def _one_tick(self, t0: float) -> None:
        sim = self.sim
        k = sim.tick
        self.faults.at(k)
        with self._cv:
            live = sorted(self._live)
        phases.mark("world.tick", k)
        self._tick_pub.put(encode(Tick(k, sim.t_sim_s, live, sim.lights())))
        self._truth_pub.put(encode(sim.truth()))
        for v in sim.sense_each(live):  # each scan goes out as soon as it is cast: its agent starts at once
            self._scan_pubs[v.vid].put_parts(k, sim.t_sim_s, encode_parts(Scan(k, sim.t_sim_s, v.vid, v.pose,
                                                                                v.speed_mps, v.range_cm)))
        phases.mark("world.scans_sent", k)
        if self.realtime:
            commands = self._collect_realtime(t0 + (k + 1) * sim.decision_interval_s)
        else:
            commands = self._collect_lockstep(k)
        with self._cv:
            reports = self._reports.pop(k, {})
            self._reports = {t: r for t, r in self._reports.items() if t > k}
        phases.mark("world.commands_in", k)
        sim.step(commands, fused_xy={vid: r.fused_xy for vid, r in reports.items()})
        self.stats.ticks += 1
        phases.mark("world.stepped", k)

    def _collect_lockstep(self, k: int) -> dict[int, tuple[float, float]]:
        deadline = time.monotonic() + self.agent_timeout_s
        with self._cv:
            while not self._stopping.is_set():
                waiting = [v for v in self._live if self._cmds.get(v) is None or self._cmds[v].tick < k]
                self._waiting_tick, self._waiting = k, set(waiting)
                had = self._reports.get(k, {})
                report_due = any(v in self._live and v not in had for v in self._reporting)
                if not waiting and not report_due:
                    break
                left = deadline - time.monotonic()
                if left <= 0:
                    for vid in waiting:
                        self._mark_dead(vid, f"no command for tick {k} within {self.agent_timeout_s:.1f} s")
                    break
                self._cv.wait(left)
            self._waiting_tick, self._waiting = -1, set()
            return {v: (self._cmds[v].accel_mps2, self._cmds[v].steer_rad) for v in self._live if v in self._cmds}

    def _collect_realtime(self, tick_end: float) -> dict[int, tuple[float, float]]:
        k = self.sim.tick
        with self._cv:
            while not self._stopping.is_set():
                left = tick_end - time.monotonic()
                if left <= 0:
                    break
                self._cv.wait(left)
            for vid in list(self._live):
                cmd = self._cmds.get(vid)
                if cmd is None or cmd.tick < k:
                    self.stats.late_commands += 1
                last_tick = cmd.tick if cmd is not None else -1
                if (k - last_tick) * self.sim.decision_interval_s > self.agent_timeout_s:
                    self._mark_dead(vid, f"no command for {self.agent_timeout_s:.1f} s")
            return {v: (self._cmds[v].accel_mps2, self._cmds[v].steer_rad) for v in self._live if v in self._cmds}

    def _result(self) -> dict:
        result = self.sim.result()
        result.update({
            "run_id": self.run_id,
            "mode": "realtime" if self.realtime else "lockstep",
            "ticks": self.stats.ticks,
            "wall_s": round(self.stats.wall_s, 3),
            "realtime_factor": round(self.sim.t_sim_s / self.stats.wall_s, 3) if self.stats.wall_s > 0 else None,
            "dead_agents": {str(k): v for k, v in sorted(self.stats.dead.items())},
            "malformed_dropped": self.drops.total,
            "late_commands": self.stats.late_commands,
        })
        if self.verifier is not None:
            result["rejected"] = self.verifier.rejections.summary()
        return result
