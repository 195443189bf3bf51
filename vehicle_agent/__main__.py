"""One connected vehicle as its own process: ``python -m vehicle_agent --vid 3``."""

from __future__ import annotations

import argparse
import cProfile
import faulthandler
import gc
import json
import logging
import os
import queue
import resource
import signal
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TextIO

import numpy as np

from channel_proxy.emp import voronoi_segment
from channel_proxy.profiles import get_profile
from protocol import keys, phases, shm
from protocol.codec import encode
from protocol.faults import Injector
from protocol.messages import AgentReport, Command, MapMsg, Mission, Outcome, Rejected, Scan, Transmission
from protocol.model import OURS, Model, ModelError, add_model_args, model_from
from protocol.security import Credentials, Verdicts, plain, with_digests
from protocol.session import (DropCounter, add_zenoh_args, query_one, reliable_publisher, session_scope, typed_handler,
                              zenoh_args_from)
from vehicle_agent.agent import Agent, LaneFollower, timed
from vehicle_agent.agreement import AgreementConfig, decide, unscheduled_after
from vehicle_agent.agreement import plan as plan_transmissions
from vehicle_agent.frames import scan_to_world
from vehicle_agent.domains import schedule_domains
from vehicle_agent.guard import CTRL_STREAM, Guard
from vehicle_agent.link import V2VLink
from vehicle_agent.planning import holds_still
from vehicle_agent.scheduler import UnknownSchedulerError
from vehicle_agent.scheduler import get as get_scheduler
from vehicle_agent.warmup import warm_up

log = logging.getLogger("vehicle_agent")

STALL_DUMP_S = 5.0
SCHEMES = ("single", "agnostic", "autocast", "autocast-fptas", "emp", "lane")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python -m vehicle_agent", description=__doc__)
    ap.add_argument("--run-id", required=True, help="the run's id (key prefix ac/<run>/)")
    ap.add_argument("--vid", type=int, required=True, help="this vehicle's id")
    ap.add_argument("--startup-timeout-s", type=float, default=120.0,
                    help="give up if the world does not answer within this long")
    ap.add_argument("--idle-exit-s", type=float, default=60.0,
                    help="exit if no scan arrives for this long (the world is gone)")
    ap.add_argument("--scheme", default="autocast", choices=SCHEMES,
                    help="sharing scheme: single (no V2V), agnostic, autocast, autocast-fptas, emp; "
                         "lane: a blind lane follower (the world server's test agents)")
    ap.add_argument("--channel-profile", default=None,
                    help="the radio profile the proxy plays (B, T_n, N must agree with it)")
    ap.add_argument("--scheduler", default=None,
                    help="schedule with this registered scheduler or package.module:function instead of "
                         "the scheme's own (docs/scheduler.md)")
    ap.add_argument("--credentials", default=None, metavar="FILE",
                    help="this vehicle's key and certificate from the run's authority (protocol/security.py): "
                         "sign what it sends, accept only what verifies (docs/security.md)")
    ap.add_argument("--log-level", default="WARNING")
    add_model_args(ap)
    shm.add_shm_arg(ap)
    add_zenoh_args(ap)
    return ap.parse_args(argv)


def _ask(session, key: str, expected: type, deadline: float, drops: DropCounter):
    """Query until the world answers (it may start after us)."""
    while True:
        try:
            return query_one(session, key, expected, timeout_s=2.0, drops=drops)
        except TimeoutError:
            if time.monotonic() > deadline:
                raise


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format=f"%(asctime)s agent{args.vid} %(levelname)s %(message)s")
    try:  # a bad plug-in name or model setting fails here, not at the first schedule
        args.model = model_from(args)
        args.channel_profile = args.channel_profile or args.model.channel_profile
        try:
            get_profile(args.channel_profile)
        except KeyError as exc:
            raise KeyError(f"channel_profile: {exc.args[0]}") from None
        get_scheduler(args.scheduler or scheduler_of(args.scheme, args.model))
    except (KeyError, UnknownSchedulerError, ModelError) as exc:
        print(f"error: {exc.args[0]}", file=sys.stderr)
        return 2
    try:
        args.credentials_dir = Path(args.credentials).parent if args.credentials else None
        args.credentials = Credentials.load(args.credentials) if args.credentials else None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        print(f"error: credentials: {exc}", file=sys.stderr)
        return 2
    if args.credentials is not None and args.credentials.vid != args.vid:
        print(f"error: credentials: issued to vehicle {args.credentials.vid}, not {args.vid}", file=sys.stderr)
        return 2
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        scope = session_scope(zenoh_args_from(args), wait_s=args.startup_timeout_s)
        with scope as session:
            return serve(session, args, stop)
    except ConnectionError as exc:  # no hub within the startup timeout
        log.error("%s", exc)
        return 2


PROFILE_ENV = "AUTOCAST_AGENT_PROFILE"  # a directory: each agent profiles its ticks into <dir>/agent<vid>.pstats
SCHEDULER_OF = {"agnostic": "agnostic", "autocast": "autocast", "autocast-fptas": "autocast-fptas"}


def scheduler_of(scheme: str, model: Model = OURS) -> str:
    """The scheme's own scheduler under ``model``: agnostic's order, and whether AutoCast
    fills its spare airtime (``autocast``, ``autocast-fptas``) or not (``greedy``,
    Algorithm 1 alone; ``fptas``)."""
    if scheme == "agnostic" and model.agnostic_order == "shuffle":
        return "agnostic-shuffle"
    if scheme == "autocast" and not model.fill_spare:
        return "greedy"
    if scheme == "autocast-fptas" and not model.fill_spare:
        return "fptas"
    return SCHEDULER_OF.get(scheme, "autocast")


def serve(session, args: argparse.Namespace, stop: threading.Event) -> int:
    """Fetch the map and mission, then answer every scan with a command until stopped."""
    run, vid = args.run_id, args.vid
    drops, missed = DropCounter(), shm.missed_counter()
    scans: queue.Queue[Scan | None] = queue.Queue()  # None: the outcome came, stop now
    deadline = time.monotonic() + args.startup_timeout_s
    try:
        mapmsg = _ask(session, keys.world_map(run), MapMsg, deadline, drops)
        mission = _ask(session, keys.mission(run, vid), Mission, deadline, drops)
    except TimeoutError as exc:
        log.error("world never answered: %s", exc)
        return 2
    report_pub = reliable_publisher(session, keys.report(run, vid)) if mission.role == "ego" else None
    link = None if args.scheme in ("single", "lane") else \
        V2VLink(session, run, vid, drops, stop, receives_data=fuses(mission, report_pub is not None),
                shm_dir=args.shm_dir, missed=missed, channels=[d.channel for d in mapmsg.scheduler_domains()])
    guard = None
    if args.credentials is not None:  # the host's receivers share verified signatures (tmpfs if the run has it)
        guard = Guard(args.credentials, drops, Verdicts.open(args.shm_dir or args.credentials_dir))
    step = Pipeline(mission, mapmsg, args.scheme, args.channel_profile, args.scheduler, link,
                    report_pub.put if report_pub is not None else None, guard, args.model)
    if step.link is not None:  # one line per agent, like agent_timings at exit: what this vehicle runs with
        config = {"vid": vid, "scheme": args.scheme, "scheduler": step.agreement.scheduler,
                  "channel_profile": args.channel_profile, "model": args.model.label()}
        print(f"agent_config {json.dumps(config)}", file=sys.stderr, flush=True)
    if args.scheme != "lane":
        warm_up(step.agent, step.agreement)  # before the token: the world waits for it at startup
    subs = [
        shm.subscribe(session, keys.scan(run, vid), args.shm_dir, Scan, lambda k, m: scans.put(m), drops, missed),
        session.declare_subscriber(keys.world_outcome(run),
                                   typed_handler(Outcome, lambda k, m: _halt(stop, scans), drops)),
    ]
    cmd_pub = reliable_publisher(session, keys.cmd(run, vid))
    rejected_pub = reliable_publisher(session, keys.rejected(run, vid)) if guard is not None else None
    published_rejections = 0
    token = session.liveliness().declare_token(keys.alive(run, vid))
    faults = Injector(f"agent{vid}")
    profile_dir = os.environ.get(PROFILE_ENV)
    profiler = cProfile.Profile(time.thread_time) if profile_dir else None  # CPU, not the waits
    last_scan = time.monotonic()
    proc = ProcessCpu()
    stall = StallDump(STALL_DUMP_S)
    try:
        while not stop.is_set():
            try:
                scan = scans.get(timeout=0.2)
            except queue.Empty:
                if time.monotonic() - last_scan > args.idle_exit_s:
                    log.warning("no scan for %.0f s; exiting", args.idle_exit_s)
                    break
                continue
            if scan is None:
                break
            last_scan = time.monotonic()
            phases.mark("agent.scan", scan.tick)
            faults.at(scan.tick)
            try:
                with stall:  # a stalled tick leaves its stack in the log
                    cmd = step.run(scan) if profiler is None else profiler.runcall(step.run, scan)
            except Exception:  # a bug in one stage must not take the vehicle down: fail safe
                log.exception("tick %d failed; braking", scan.tick)
                spec = mission.spec
                cmd = Command(scan.tick, scan.t_sim_s, vid, -spec.max_brake_mps2, 0.0)
            wire = step.wire(cmd)
            phases.mark("agent.cmd_sent", scan.tick)
            cmd_pub.put(wire)
            if guard is not None and guard.rejections.version != published_rejections:  # for the log
                published_rejections = guard.rejections.version
                rejected_pub.put(encode(Rejected(scan.tick, scan.t_sim_s, vid, guard.rejections.summary())))
            proc.tick_done()
    finally:
        stall.close()
        proc.loop_done()
        token.undeclare()
        if rejected_pub is not None:
            rejected_pub.undeclare()
        for sub in subs:
            sub.undeclare()
        if link is not None:
            link.close()
        if report_pub is not None:
            report_pub.undeclare()
    if drops.total:
        log.warning("dropped %d malformed messages", drops.total)
    print(drops.exit_line(f"agent{vid}"), file=sys.stderr, flush=True)
    if missed.total:
        print(missed.exit_line(f"agent{vid}"), file=sys.stderr, flush=True)
    if guard is not None:
        print(guard.rejections.exit_line(f"agent{vid}"), file=sys.stderr, flush=True)
    print("agent_timings " + json.dumps(step.timing_summary() | proc.summary()), file=sys.stderr, flush=True)
    if profiler is not None:
        Path(profile_dir).mkdir(parents=True, exist_ok=True)
        profiler.dump_stats(Path(profile_dir) / f"agent{vid}.pstats")
    return 0


def _halt(stop: threading.Event, scans: queue.Queue) -> None:
    """The outcome: stop, and wake the loop if it waits for a scan (the run's teardown
    waits for every agent to go)."""
    stop.set()
    scans.put(None)


class StallDump:
    """``with StallDump(limit_s):`` dumps every thread's stack to ``file`` (stderr: the
    process's log) if the block runs longer than ``limit_s``, and goes on.

    A real-time timer (``SIGALRM``) is armed as the block starts and disarmed as it ends;
    faulthandler handles the signal in C, without the GIL, so a tick stuck in a kernel
    that holds it still dumps. Not ``faulthandler.dump_traceback_later``: it starts and
    joins a watchdog thread each time, which costs far more than the two timer calls
    (docs/performance.md, "What a tick costs around the step"). Where there is no
    ``SIGALRM`` (Windows) it does nothing."""

    def __init__(self, limit_s: float, file: TextIO | None = None) -> None:
        self.limit_s = limit_s
        self.active = hasattr(signal, "SIGALRM") and hasattr(faulthandler, "register")
        if self.active:
            faulthandler.register(signal.SIGALRM, file=file if file is not None else sys.stderr, all_threads=True)

    def __enter__(self) -> StallDump:
        if self.active:
            signal.setitimer(signal.ITIMER_REAL, self.limit_s)
        return self

    def __exit__(self, *exc: object) -> None:
        if self.active:
            signal.setitimer(signal.ITIMER_REAL, 0.0)

    def close(self) -> None:
        if self.active:
            signal.setitimer(signal.ITIMER_REAL, 0.0)
            faulthandler.unregister(signal.SIGALRM)
            self.active = False


class ProcessCpu:
    """The whole process's CPU time (user + system, every thread: the Zenoh threads that
    receive and decode the scans and bundles too) per tick, from the end of the first
    tick (which may still load code) to the end of the last; the main thread's over the
    same span, to tell the two apart; and, where /proc tells, each thread's by name
    (``net-0``, ``rx-1``, ...: Zenoh's; the main thread and those Zenoh runs our callbacks
    in carry the process's name) from the first tick to the loop's end (``loop_done``),
    divided by the same number of ticks."""

    def __init__(self) -> None:
        self.ticks = 0
        self.first: tuple[float, float, float, int] | None = None
        self.last: tuple[float, float, float, int] | None = None
        self.thread_names: dict[int, str] = {}
        self.threads_first: dict[int, float] = {}
        self.threads_last: dict[int, float] = {}
        self.gc_s = self.gc_first = self.gc_last = 0.0  # the cyclic garbage collector's CPU time, any thread
        self._gc_started: dict[int, float] = {}
        gc.callbacks.append(self._on_gc)

    def _on_gc(self, phase: str, info: dict) -> None:
        if phase == "start":
            self._gc_started[threading.get_ident()] = time.thread_time()
        else:
            self.gc_s += time.thread_time() - self._gc_started.pop(threading.get_ident(), time.thread_time())

    @staticmethod
    def _now() -> tuple[float, float, float, int]:
        """(user + system CPU, the main thread's CPU, system CPU, minor page faults)."""
        ru = resource.getrusage(resource.RUSAGE_SELF)
        return ru.ru_utime + ru.ru_stime, time.thread_time(), ru.ru_stime, ru.ru_minflt

    @staticmethod
    def _thread_names() -> dict[int, str]:
        """The process's threads by id, with their names (``comm``); empty without /proc."""
        out: dict[int, str] = {}
        for task in Path("/proc/self/task").glob("*") if Path("/proc/self/task").exists() else []:
            try:
                out[int(task.name)] = (task / "comm").read_text().strip()
            except (OSError, ValueError):  # the thread ended
                continue
        return out

    def _threads(self) -> dict[int, float]:
        """CPU seconds of each thread named at the first tick that still runs, by thread
        id, read from its CPU-time clock (Linux: clock id ``~tid << 3 | 6``; nanoseconds,
        where /proc's stat counts 10 ms clock ticks)."""
        out: dict[int, float] = {}
        for tid in self.thread_names:
            try:
                out[tid] = time.clock_gettime((~tid << 3) | 6)
            except OSError:  # the thread ended
                continue
        return out

    def tick_done(self) -> None:
        self.ticks += 1
        self.last = self._now()
        self.gc_last = self.gc_s
        if self.first is None:
            self.first = self.last
            self.gc_first = self.gc_s
            self.thread_names = self._thread_names()
            self.threads_first = self._threads()

    def loop_done(self) -> None:
        """Read the threads' clocks once the loop ends, before the teardown, rather than
        after every tick, where they were a measurable part of it. Their span so runs
        past the last tick by the wait for the outcome (or, without one, by up to
        ``--idle-exit-s`` of waiting), when the threads do little."""
        if self.first is not None:
            self.threads_last = self._threads()
        if self._on_gc in gc.callbacks:  # the collector's time counts no further
            gc.callbacks.remove(self._on_gc)

    def summary(self) -> dict[str, float]:
        """``proc_cpu``: whole-process CPU ms per tick; ``proc_main_cpu``: the main
        thread's; ``proc_sys_cpu``: the system part of ``proc_cpu``; ``proc_minflt``: minor
        page faults per tick; ``proc_gc_cpu``: the garbage collector's CPU per tick (any
        thread); ``thread_<name>_cpu``: per thread name (the threads that ran
        at the first tick: Zenoh's ``rx-0``, ``net-0``, ...; ours the process's name), ms per tick,
        over the same ticks (to the loop's end: ``loop_done``)."""
        if self.first is None or self.last is None or self.ticks < 2:
            return {}
        n = self.ticks - 1
        out = {"proc_cpu": round((self.last[0] - self.first[0]) * 1e3 / n, 3),
               "proc_main_cpu": round((self.last[1] - self.first[1]) * 1e3 / n, 3),
               "proc_sys_cpu": round((self.last[2] - self.first[2]) * 1e3 / n, 3),
               "proc_minflt": round((self.last[3] - self.first[3]) / n, 1),
               "proc_gc_cpu": round((self.gc_last - self.gc_first) * 1e3 / n, 3), "proc_ticks": n}
        by_name: dict[str, float] = {}  # threads of one name added up; one that ended meanwhile is left out
        for tid, cpu_s in self.threads_last.items():
            name = self.thread_names[tid]
            by_name[name] = by_name.get(name, 0.0) + cpu_s - self.threads_first.get(tid, cpu_s)
        for name, cpu_s in sorted(by_name.items()):
            out[f"thread_{name}_cpu"] = round(cpu_s * 1e3 / n, 3)
        return out


def fuses(mission: Mission, reports: bool) -> bool:
    """Whether the vehicle fuses what it receives. One that holds still plans the same
    whatever it receives (``Planner.hold``): it shares what it sees but fuses nothing,
    unless it reports its fused view (the ego, ``reports``)."""
    return not holds_still(mission) or reports


class Pipeline:
    """One scheme's per-interval step around the Agent's stages."""

    def __init__(self, mission: Mission, mapmsg: MapMsg, scheme: str, profile_name: str,
                 scheduler: str | None = None, link=None, report: Callable[[bytes], object] | None = None,
                 guard: Guard | None = None, model: Model = OURS) -> None:
        """``link``: the V2V channel (a ``V2VLink``; None for ``single`` and ``lane``);
        ``report``: where the ego's encoded ``AgentReport`` goes (None: not the ego);
        ``guard``: sign and verify (None: send plain messages, accept plain ones);
        ``model``: the modelling profile (``protocol.model``), the same on every vehicle."""
        self.mission, self.scheme, self.model = mission, scheme, model
        self.guard = guard
        self._sealed: tuple[Command, bytes] | None = None
        self.agent = Agent(mission, mapmsg, model)
        self.lane_follower = LaneFollower(mission)
        self.link = link
        self.agreement = AgreementConfig.from_profile(get_profile(profile_name, model.channel_loss),
                                                      scheduler=scheduler or scheduler_of(scheme, model),
                                                      group_size=model.group_size or None)
        self.emp_held: dict[int, tuple[float, np.ndarray]] = {}  # EMP: each sender's last segment (time, points)
        self.heard: list[int] = []
        self.unscheduled: dict[int, int] = {}  # m of our objects, reported in our next control message
        self.heard_in: dict[int, list[int]] = {}  # several domains: our ballot in each domain we take part in
        self.unscheduled_in: dict[int, dict[int, int]] = {}  # ... and the m of our objects there
        self.domains_taken: list[tuple[int, ...]] = []  # several domains: the ones we took part in, per tick
        if guard is not None and len(self.agent.dataplane.domains) > 1:
            raise ValueError("a signed run (--sign) of a map with several scheduler domains is not supported")
        self.emp_sites: dict[int, np.ndarray] = {}
        self.report = report
        self.fuses = fuses(mission, report is not None)
        self.timings: dict[str, list[float]] = {}

    def wire(self, cmd: Command) -> bytes:
        """The command as it goes to the world (sealed during the tick ``run`` made it in)."""
        got = self._sealed
        return got[1] if got is not None and got[0] is cmd else self.seal(cmd)

    def seal(self, msg) -> bytes:
        """``msg`` as this vehicle sends it: signed, or plain."""
        if self.guard is None:
            return plain(msg)
        with timed(self.agent.timings_ms, "security"):
            return self.guard.seal(msg)

    def run(self, scan: Scan) -> Command:
        if self.scheme == "lane":
            return self.lane_follower.run_step(scan)
        t0, cpu0 = time.perf_counter(), time.thread_time()
        if self.link is not None:
            self.link.wait_s = 0.0
        agent = self.agent
        extra = None
        if self.scheme == "emp":
            with timed(agent.timings_ms, "link"):
                extra = self._emp(scan)
        view = agent.perceive(scan, extra)
        payloads: list[bytes] = []
        if self.scheme in SCHEDULER_OF:
            several = len(agent.dataplane.domains) > 1
            payloads = self._share_domains(view, scan) if several else self._share(view, scan)
        drops = self.link.drops if self.link is not None else None  # the process's, which the link counts in
        fused = agent.fuse(view, payloads, drops) if self.fuses else None
        plan = agent.plan(view, fused, scan)
        cmd = agent.control(plan, scan)
        if self.guard is not None:  # within the tick, so that signing counts in its timings
            self._sealed = (cmd, self.seal(cmd))
        if self.report is not None:
            with timed(agent.timings_ms, "report"):
                self._report(view, plan, scan)
        agent.timings_ms["total"] = (time.perf_counter() - t0) * 1e3
        wait_ms = self.link.wait_s * 1e3 if self.link is not None else 0.0
        agent.timings_ms["channel_wait"] = wait_ms
        agent.timings_ms["compute"] = agent.timings_ms["total"] - wait_ms
        agent.timings_ms["cpu"] = (time.thread_time() - cpu0) * 1e3  # this agent's own cost, free of contention
        for k, v in agent.timings_ms.items():
            self.timings.setdefault(k, []).append(v)
        return cmd

    def _share(self, view, scan: Scan) -> list[bytes]:
        """Control message -> what we heard -> the agreed schedule -> our slots -> what we decoded."""
        agent, link, guard = self.agent, self.link, self.guard
        own = agent.control_message(view, scan, self.heard, self.unscheduled)
        blobs: dict[int, bytes] = {}
        if guard is None:
            with timed(agent.timings_ms, "link"):
                heard = link.exchange_control(own)
        else:  # the message vouches for every payload we may send, so all are encoded now
            with timed(agent.timings_ms, "encoding"):
                blobs = agent.dataplane.payloads(view, own.objects.object_id.tolist())
            with timed(agent.timings_ms, "security"):
                own = with_digests(own, blobs)
                raw = guard.seal(own)
            with timed(agent.timings_ms, "link"):
                bundle = link.exchange_control_raw(raw, own.tick)
            with timed(agent.timings_ms, "security"):
                heard, check = guard.heard(bundle, own.tick)
            if heard is None:
                link.missed_bundles += 1
                heard = []
        self.heard = sorted(m.vid for m in heard)
        agent.dataplane.neighbors.update(heard)
        with timed(agent.timings_ms, "schedule"):
            decision = decide(self.mission.vid, scan.tick, own, heard, self.agreement)
            for err in decision.malformed.values():  # a group member's object map: not heard after all
                link.drops.add(CTRL_STREAM, err)
            slots = plan_transmissions(decision, self.agreement)
            self.unscheduled = unscheduled_after(own, [t.object_id for t in slots])
        with timed(agent.timings_ms, "encoding"):
            if guard is None:
                blobs = agent.dataplane.payloads(view, [t.object_id for t in slots])
            txs = [Transmission(t.object_id, t.start_s, blobs[t.object_id]) for t in slots]
        with timed(agent.timings_ms, "link"):  # the second exchange adds to the first
            received = link.exchange_data(scan.tick, scan.t_sim_s, txs, receive=self.fuses)
        if guard is None:
            return [r.payload for r in received]
        with timed(agent.timings_ms, "security"):
            return guard.payloads(received, check, bundle)

    def _share_domains(self, view, scan: Scan) -> list[bytes]:
        """``_share`` in every scheduler domain the vehicle takes part in (docs/domains.md):
        a control message in each, each domain's schedule from that domain's messages
        alone (the agreement rule, unchanged, per domain), our slots in each on its
        channel, and what we decoded in all of them. A domain we just joined starts with
        an empty ballot, so we are its member from our second interval there, as any
        newcomer."""
        agent, link, vid = self.agent, self.link, self.mission.vid
        domains = agent.dataplane.domains.membership(scan.pose.x_m, scan.pose.y_m)
        self.domains_taken.append(domains)
        self.heard_in = {d: self.heard_in.get(d, []) for d in domains}
        self.unscheduled_in = {d: self.unscheduled_in.get(d, {}) for d in domains}
        own = agent.control_messages(view, scan, self.heard_in, self.unscheduled_in, domains)
        with timed(agent.timings_ms, "link"):
            heard = link.exchange_controls(own)
        for d in domains:
            self.heard_in[d] = sorted(m.vid for m in heard[d])
            agent.dataplane.neighbors.update(heard[d])
        with timed(agent.timings_ms, "schedule"):
            decided = schedule_domains(vid, scan.tick, own, heard, self.agreement)
            slots = {d: mine for d, (_, mine) in decided.items()}
            for d, (decision, mine) in decided.items():
                for err in decision.malformed.values():
                    link.drops.add("ctrl bundle item", err)
                self.unscheduled_in[d] = unscheduled_after(own[d], [t.object_id for t in mine])
        with timed(agent.timings_ms, "encoding"):
            blobs = agent.dataplane.payloads(view, sorted({t.object_id for d in domains for t in slots[d]}))
            txs = {d: [Transmission(t.object_id, t.start_s, blobs[t.object_id]) for t in slots[d]] for d in domains}
        with timed(agent.timings_ms, "link"):
            received = link.exchange_datas(scan.tick, scan.t_sim_s, txs, receive=self.fuses)
        return [r.payload for r in received]

    def _emp(self, scan: Scan) -> np.ndarray | None:
        """Upload our Voronoi segment of the scan; return the relay's segments' points
        (world frame), which perception then sees as if our own (EMP merges point clouds).

        Ground returns are left out of the segment, as a point-cloud sharing system
        removes them before it transmits. A receiver's perception takes obstacles only
        from points above the ground, so they carry nothing it uses. With them, one
        vehicle's segment (~600 KB) overflowed the relay's whole 100 ms and EMP
        delivered nothing at any density. Without them a segment is ~140 KB at 5
        vehicles (docs/channel.md). A sender whose segment does not come this interval
        stays in view with its last one for as long as the model holds a received object
        (``Model.hold_s``), where it was seen: raw points carry no velocity."""
        world = scan_to_world(scan, self.mission.lidar)
        world = world[world[:, 2] > self.agent.dataplane.spec.ground_clear_m]
        own_xy = np.array([scan.pose.x_m, scan.pose.y_m])
        others = np.array([xy for v, xy in sorted(self.emp_sites.items()) if v != self.mission.vid]).reshape(-1, 2)
        segment = world[voronoi_segment(world[:, :2], own_xy, others)]
        bundle = self.link.exchange_emp(scan.tick, scan.t_sim_s, scan.pose, segment)
        if bundle is not None:
            self.emp_sites = {int(v): xy for v, xy in zip(bundle.site_vids, bundle.site_xy)}
            for seg in bundle.segments:
                if seg.sender != self.mission.vid:
                    self.emp_held[int(seg.sender)] = (scan.t_sim_s, seg.points_world.astype(np.float64))
        # each sender's last segment, held for as long as the model holds a received object
        # (a raw point cloud has no velocity to carry it forward with: it stays where it was seen)
        self.emp_held = {v: held for v, held in self.emp_held.items()
                         if scan.t_sim_s - held[0] <= self.model.hold_s + 1e-9}
        segments = [points for _, (_, points) in sorted(self.emp_held.items())]
        return np.concatenate(segments) if segments else None

    def _report(self, view, plan, scan: Scan) -> None:
        own = [t.detection.points_world[:, :2] for t in view.tracks]
        shared = self.agent.dataplane.shared_batch.points[:, :2]  # every object's points, object after object
        # cast to float32 as it is gathered: the same rounding of each value as a float64 copy cast
        # after, without that copy (~67 000 points a tick for the ego at 40 vehicles, on the tick's
        # critical path: the world steps once it has this report)
        xy = np.concatenate(own + [shared], dtype=np.float32)
        n_shared = len(shared)
        msg = AgentReport(scan.tick, scan.t_sim_s, self.mission.vid, xy, n_shared, plan.braking)
        self.report(self.guard.seal(msg) if self.guard is not None else encode(msg))

    def timing_summary(self) -> dict[str, float]:
        """The median of every per-tick timing, ms (a stage's wall time, and its CPU
        time as ``<stage>_cpu``), and the mean of the CPU times as ``<stage>_cpu_mean``:
        the means add up to the agent's mean CPU per tick, which sets how many agents a
        core can carry."""
        out = {k: round(float(np.median(v)), 3) for k, v in sorted(self.timings.items())}
        out.update({f"{k}_mean": round(float(np.mean(v)), 3) for k, v in sorted(self.timings.items())
                    if k == "cpu" or k.endswith("_cpu")})
        return out


if __name__ == "__main__":
    sys.exit(main())
