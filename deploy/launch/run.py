"""``autocast run``: one run of a scenario, every participant its own OS process.

The launcher validates every flag before anything starts, warms the numba caches once,
becomes the run's Zenoh hub (a router on a free loopback port), and starts what
``deploy.launch.table.processes`` lists: the recorder first (and waits until its subscription
has reached the hub), then the world, the channel proxy and one agent per connected
vehicle. It waits for the world's judged ``Outcome``, watches the processes meanwhile
(the world dying without an outcome fails the run; a dead agent is the world's
business), stops everything (SIGINT, grace, SIGKILL; the world first, the recorder
last) and prints the outcome.

Outputs: ``runs/<id>/run.mcap``, ``runs/<id>/outcome.json``, ``runs/<id>/pids.json``,
``runs/<id>/logs/<process>.log``. Exit code: 0 safe passage, 1 another judged outcome
(of a scenario of several events, its worst event's), 2 bad input, 3 the run failed
without an outcome, 130 interrupted (Ctrl-C).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import secrets
import signal
import socket
import sys
import threading
import time
from contextlib import ExitStack
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, NoReturn

import zenoh

from deploy.launch import table
from deploy.launch.warmup import warm_numba_caches
from processes import factory as process_factory
from processes.manager import ProcessManager, ProcSpec, RunCpu, batch_scheduling, exit_records, usable_cores
from protocol import faults, keys, shm
from protocol.codec import MalformedMessage, decode
from protocol.messages import Outcome, Tick
from protocol.model import OURS, Model, ModelError, add_model_args, model_from
from protocol.security import REJECTED_LINE
from protocol.session import MALFORMED_LINE, DropCounter, ZenohArgs, session_scope, typed_handler
from world_server.__main__ import summary
from world_server.scenarios import ScenarioError, ScenarioParams, build, params_from_dict

log = logging.getLogger("deploy.launch.run")

EXIT_SAFE, EXIT_JUDGED, EXIT_BAD_INPUT, EXIT_FAILED, EXIT_INTERRUPTED = 0, 1, 2, 3, 130
RECORDER_READY_TIMEOUT_S = 30.0
SETTLE_S = 5.0  # after the outcome, processes get this long to exit on their own
CRITICAL_EXIT_WAIT_S = 2.0  # a critical process may exit just before its outcome reaches us
GRACE_S = 3.0
# The hub forwards every message of the run. Zenoh drops a CongestionControl.DROP message
# whose egress queue (two batches) stays full for 1 ms, e.g. behind a 1.3 MB scan to the
# recorder: measured, commands went missing from the log and, before the agents sent them
# with BLOCK, from the world. 200 ms of patience costs nothing when queues are healthy.
HUB_CONFIG = {"transport": {"link": {"tx": {"queue": {"congestion_control": {"drop": {"wait_before_drop": 200000}}}}}}}
HUB_CONFIG_JSON5 = json.dumps(HUB_CONFIG) + "\n"
SIGN_DEFAULT = False  # see docs/security.md for what signing costs an agent


class InputError(ValueError):
    """A bad flag or scenario value; the message starts with the field's name."""


@dataclass(frozen=True, slots=True)
class LaunchOptions:
    """The launcher's own knobs (the processes' knobs are in ``table.RunConfig``)."""

    run: table.RunConfig
    timeout_s: float  # wall clock; no outcome by then fails the run
    warm_up: bool = True


@dataclass(frozen=True, slots=True)
class RunResult:
    exit_code: int
    result: dict[str, Any] | None  # the judged outcome (plus scheme, run_dir, mcap)
    failure: str | None = None


# ---------------------------------------------------------------------------- input


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> NoReturn:
        self.print_usage(sys.stderr)
        self.exit(EXIT_BAD_INPUT, f"error: {message}\n")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    return build_parser().parse_args(argv)


def build_parser(prog: str = "autocast run", description: str | None = __doc__,
                 lock_down_default: bool = False, sign_default: bool | None = SIGN_DEFAULT) -> argparse.ArgumentParser:
    """The run's flags; ``autocast deploy`` adds its own to the same parser (and locks
    Zenoh down by default: its processes span hosts)."""
    from vehicle_agent.__main__ import SCHEMES

    ap = _Parser(prog=prog, description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    sc = ap.add_argument_group("scenario (python -m world_server --help)")
    sc.add_argument("--scenario", default="left_turn", help="overtaking | left_turn | red_light (default left_turn); "
                    "corridor3 | grid4 | corridor3x | grid4_handover: several junctions (docs/domains.md)")
    sc.add_argument("--vehicles", default="10",
                    help="connected vehicles in range, ego included (default 10; at most 64 a scheduler domain "
                    "of the map)")
    sc.add_argument("--collider-speed", default="30", metavar="KMH", help="the collider's speed (default 30)")
    sc.add_argument("--delta", default="0", metavar="SECONDS",
                    help="collider reaches the conflict point this long after the ego (default 0)")
    sc.add_argument("--seed", default="0", help="background placement and channel loss (default 0)")
    sc.add_argument("--duration", default=None, metavar="SECONDS",
                    help="sim time limit (default: the scenario's own; overtaking 40, left_turn 30, red_light 40)")
    ap.add_argument("--scheme", default="autocast", help=f"{' | '.join(SCHEMES)} (default autocast)")
    ap.add_argument("--scheduler", default=None, metavar="NAME",
                    help="replace the scheme's scheduler (agnostic, autocast, autocast-fptas) with a registered "
                         "one or package.module:function (docs/extending.md)")
    ap.add_argument("--channel-profile", default=None, metavar="NAME",
                    help="the V2V radio: a registered profile or package.module:NAME (default: the model's, lte-direct; "
                         "python -m channel_proxy --list-profiles)")
    ap.add_argument("--realtime", action="store_true", help="the world ticks on the wall clock instead of lock-step")
    add_model_args(ap)
    sec = ap.add_argument_group("security (docs/security.md)")
    sign_default_text = {True: "on", False: "off", None: "on; off for a --compose file and for a map of several domains"}[sign_default]
    sec.add_argument("--sign", action=argparse.BooleanOptionalAction, default=sign_default,
                     help="V2X messages signed by each vehicle's certificate from the run's authority and verified "
                          f"by every receiver (default {sign_default_text})")
    sec.add_argument("--lock-down", action=argparse.BooleanOptionalAction, default=lock_down_default,
                     help="Zenoh: a password per process, and an access-control list that lets each process put "
                          f"only on its own keys (default {'on' if lock_down_default else 'off'})")
    ap.add_argument("--json", action="store_true", help="end stdout with the outcome as one JSON line")
    ap.add_argument("--out", default="runs", metavar="DIR", help="runs go to DIR/<run id>/ (default runs/)")
    ap.add_argument("--run-id", default=None, help="default: <date>-<time>-<4 hex>")
    ap.add_argument("--scans", default="ego", help="LiDAR scans the recorder keeps: ego (default) | all | none")
    ap.add_argument("--no-json-mirror", action="store_true",
                    help="the recorder writes no JSON mirror beside the msgpack channels (half its CPU; "
                         "`autocast export --foxglove` writes one later); sweeps record so")
    ap.add_argument("--agent-timeout-s", default="10", help="wall time an agent may take for a tick before "
                    "the world declares it dead (default 10)")
    ap.add_argument("--wait-for", nargs="+", default=[], metavar="NAME",
                    help="the world waits before tick 0 for each named participant's liveliness token "
                         "ac/<run>/alive/p/NAME too: a process of your own that must see the run from its start")
    ap.add_argument("--timeout-s", default="900", help="wall-clock limit for the whole run (default 900)")
    ap.add_argument("--no-warm-up", action="store_true", help="skip warming the numba caches")
    ap.add_argument("--log-level", default="INFO", help="the launcher's, world's, proxy's and recorder's")
    return ap


def _number(field: str, text: str, kind: type) -> Any:
    try:
        value = kind(text)
    except ValueError:
        raise InputError(f"{field}: {text!r} is not {'an integer' if kind is int else 'a number'}") from None
    if kind is float and not math.isfinite(value):
        raise InputError(f"{field}: {text!r} is not a finite number")
    return value


def _one_of(field: str, value: str, choices: tuple[str, ...]) -> str:
    if value not in choices:
        raise InputError(f"{field}: {value!r} is not one of {', '.join(choices)}")
    return value


def scenario_from(args: argparse.Namespace) -> ScenarioParams:
    """The validated scenario: field names and messages are ``world_server.scenarios``'s."""
    values = {"scenario": args.scenario, "vehicles": _number("vehicles", args.vehicles, int),
              "collider_speed_kmh": _number("collider_speed_kmh", args.collider_speed, float),
              "delta_s": _number("delta_s", args.delta, float), "seed": _number("seed", args.seed, int)}
    if args.duration is not None:
        values["duration_s"] = _number("duration_s", args.duration, float)
    try:
        params = params_from_dict(values)
        table.connected_vids(params)  # building the scenario catches what the ranges cannot
    except ScenarioError as exc:
        raise InputError(str(exc)) from None
    return params


def options_from(args: argparse.Namespace, hub: str, fresh: bool = True) -> LaunchOptions:
    """Every flag checked, nothing started; raises ``InputError`` naming the field.
    ``fresh``: the run's directory must not exist yet (a file that only describes the
    run, such as a compose file, may be made again)."""
    from vehicle_agent.__main__ import SCHEMES

    params = scenario_from(args)
    scheme = _one_of("scheme", args.scheme, SCHEMES)
    scans = _one_of("scans", args.scans, ("ego", "all", "none"))
    level = _one_of("log_level", args.log_level.upper(), ("DEBUG", "INFO", "WARNING", "ERROR"))
    agent_timeout_s = _positive("agent_timeout_s", _number("agent_timeout_s", args.agent_timeout_s, float))
    timeout_s = _positive("timeout_s", _number("timeout_s", args.timeout_s, float))
    run_id = args.run_id or time.strftime("%Y%m%d-%H%M%S-") + secrets.token_hex(2)
    try:
        keys.everything(run_id)
    except ValueError as exc:
        raise InputError(f"run_id: {exc}") from None
    wait_for = tuple(args.wait_for)
    try:
        for name in wait_for:
            keys.participant_alive(run_id, name)
    except ValueError as exc:
        raise InputError(f"wait_for: {exc}") from None
    run_dir = Path(args.out) / run_id
    if fresh and run_dir.exists():
        raise InputError(f"run_id: {run_dir} already exists")
    try:
        model = model_from(args)
    except ModelError as exc:
        raise InputError(str(exc)) from None
    scheduler, profile = plug_ins_from(args, scheme, model)
    model = replace(model, channel_profile=profile)  # what the run uses is what its record says
    try:
        faults.parse(os.environ.get(faults.ENV, ""))
    except ValueError as exc:
        raise InputError(str(exc)) from None
    cfg = table.RunConfig(run_id, hub, params, scheme, run_dir, realtime=args.realtime, scans=scans,
                          agent_timeout_s=agent_timeout_s, log_level=level, scheduler=scheduler,
                          channel_profile=profile, signing=args.sign, lock_down=args.lock_down,
                          wait_for=wait_for, json_mirror=not args.no_json_mirror, model=model)
    return LaunchOptions(cfg, timeout_s, warm_up=not args.no_warm_up)


def plug_ins_from(args: argparse.Namespace, scheme: str, model: Model = OURS) -> tuple[str | None, str]:
    """The scheduler and channel profile (the flag's, else the model's), loaded here once so a
    bad name fails before anything starts."""
    from channel_proxy.profiles import get_profile
    from vehicle_agent.scheduler import UnknownSchedulerError, get

    scheduler = args.scheduler
    if scheduler is not None:
        if scheme not in table.SCHEDULING_SCHEMES:
            raise InputError(f"scheduler: only schemes that schedule ({', '.join(table.SCHEDULING_SCHEMES)}) "
                             f"take one, not {scheme!r}")
        try:
            get(scheduler)
        except UnknownSchedulerError as exc:
            raise InputError(f"scheduler: {exc}") from None
    profile = args.channel_profile or model.channel_profile
    if args.channel_profile is not None and args.channel_profile != table.DEFAULT_PROFILE and \
            scheme in (*table.NO_PROXY_SCHEMES, table.EMP_SCHEME):
        raise InputError(f"channel_profile: scheme {scheme!r} has no V2V channel to apply it to")
    try:
        get_profile(profile)
    except KeyError as exc:
        raise InputError(f"channel_profile: {exc.args[0]}") from None
    return scheduler, profile


def _positive(field: str, value: float) -> float:
    if value <= 0:
        raise InputError(f"{field}: {value!r} is not > 0")
    return value


# ---------------------------------------------------------------------------- pieces


def free_endpoint() -> str:
    """A loopback endpoint nobody listens on right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def prepare(cfg: table.RunConfig) -> table.RunConfig:
    """The run's V2X credentials, if it signs (``deploy.launch.credentials``); before the table's
    command lines are made."""
    from deploy.launch import credentials

    return credentials.issue_v2x(cfg) if cfg.signing and not cfg.authority else cfg


def open_hub(stack: ExitStack, run_dir: Path, tries: int = 5,
             locked: table.RunConfig | None = None) -> tuple[zenoh.Session, str]:
    """The launcher's router session on a free loopback port, closed with ``stack``;
    ``locked``: the run whose Zenoh is locked down (its processes' passwords and ACL)."""
    if locked is not None and locked.lock_down:
        from deploy.launch import credentials

        config = credentials.hub_config(locked, HUB_CONFIG)
    else:
        config = run_dir / "zenoh-hub.json5"
        config.write_text(HUB_CONFIG_JSON5)
    for attempt in range(tries):
        endpoint = free_endpoint()
        try:
            zargs = ZenohArgs(listen=(endpoint,), config_file=str(config))
            return stack.enter_context(session_scope(zargs, wait_s=0.0)), endpoint
        except ConnectionError:  # somebody took the port in between
            if attempt == tries - 1:
                raise
    raise AssertionError("unreachable")


def wait_recorder_ready(session: zenoh.Session, run_id: str, procs: ProcessManager | None, timeout_s: float,
                        stop: threading.Event) -> bool:
    """True once subscribers matching the world's tick and outcome keys are on the hub
    (only the recorder is up): the first tick and the last word are both recorded.
    ``procs``: gives up early once the recorder has exited (None: the recorder runs elsewhere)."""
    probes = [session.declare_publisher(key) for key in (keys.world_tick(run_id), keys.world_outcome(run_id))]
    try:
        deadline = time.monotonic() + timeout_s
        while not all(p.matching_status.matching for p in probes):
            gone = procs is not None and table.RECORDER not in procs.running()
            if stop.is_set() or time.monotonic() > deadline or gone:
                return False
            time.sleep(0.02)
        return True
    finally:
        for p in probes:
            p.undeclare()


# ---------------------------------------------------------------------------- the run


class Launcher:
    """Starts the table's processes for one run and sees them through to the outcome."""

    def __init__(self, opts: LaunchOptions, session: zenoh.Session, stop: threading.Event,
                 procs: ProcessManager | None = None, specs: list[ProcSpec] | None = None) -> None:
        """``procs`` and ``specs`` default to local processes and ``table.processes``;
        ``autocast deploy`` passes its own (the same rows, started on other hosts)."""
        self.opts = opts
        self.cfg = opts.run
        self.session = session
        self.stop = stop
        self.outcome: Outcome | None = None
        self.outcome_after_stop = False  # judged only because Ctrl-C stopped the world
        self._got_outcome = threading.Event()
        self._drops = DropCounter()
        self.procs = procs if procs is not None else ProcessManager(self.cfg.log_dir)
        self.specs = specs
        self.cpu = RunCpu(self.procs) if procs is None else None  # local processes only
        self._subs: list = []  # the launcher's own (_listen)
        self.faults = faults.Injector("hub")  # AUTOCAST_FAULTS: the launcher hosts the run's hub

    def _on_tick(self, sample: zenoh.Sample) -> None:
        """The world's first tick: the processes' CPU so far (``RunCpu``), once."""
        if self.cpu is None or self.cpu.ticking:
            return
        try:
            decode(sample.payload.to_bytes(), Tick)
        except MalformedMessage:  # anybody can put garbage on the key: only a real tick counts
            return
        self.cpu.first_tick()

    def _on_tick_fault(self, sample: zenoh.Sample) -> None:
        """``hub:<action>@N`` (``protocol.faults``): the launcher, and with it the hub, at tick N."""
        try:
            tick = decode(sample.payload.to_bytes(), Tick)
        except MalformedMessage:
            return
        self.faults.at(tick.tick)

    def _on_outcome(self, key: str, msg: Outcome) -> None:
        if self.outcome is None:
            if self.cpu is not None:
                self.cpu.outcome()
            self.outcome = msg
            self.outcome_after_stop = self.stop.is_set()
            self._got_outcome.set()

    def run(self) -> RunResult:
        cfg = self.cfg
        specs = self.specs if self.specs is not None else table.processes(cfg)
        try:
            failure = self._start(specs)
            if failure is None:
                failure = self._watch()
        finally:
            self._shutdown(specs)
            for sub in self._subs:
                sub.undeclare()
        return self._result(failure)

    def _listen(self) -> None:
        """The launcher's own subscribers (the world's outcome; its first tick, for
        ``RunCpu``): declared once the recorder is ready, not before, since
        ``wait_recorder_ready`` asks the hub whether anybody subscribes to those keys and a
        subscriber of the launcher's would answer for the recorder; and before the world
        starts, which publishes on them."""
        run = self.cfg.run_id
        self._subs.append(self.session.declare_subscriber(keys.world_outcome(run),
                                                          typed_handler(Outcome, self._on_outcome, self._drops)))
        if self.cpu is not None:
            self._subs.append(self.session.declare_subscriber(keys.world_tick(run), self._on_tick))
        if self.faults.faults:
            self._subs.append(self.session.declare_subscriber(keys.world_tick(run), self._on_tick_fault))

    def _start(self, specs: list) -> str | None:
        recorder, rest = specs[0], specs[1:]
        assert recorder.name == table.RECORDER, "the table starts with the recorder"
        t0 = time.monotonic()
        self.procs.start(recorder)
        if not wait_recorder_ready(self.session, self.cfg.run_id, self.procs, RECORDER_READY_TIMEOUT_S, self.stop):
            return None if self.stop.is_set() else "the recorder did not come up (see logs/recorder.log)"
        self._listen()
        for spec in rest:
            if self.stop.is_set():
                return None
            self.procs.start(spec)
        self._write_pids()
        log.info("%d processes started in %.1f s: %s", len(specs), time.monotonic() - t0, " ".join(s.name for s in specs))
        return None

    def _write_pids(self) -> None:
        (self.cfg.run_dir / "pids.json").write_text(json.dumps(self.procs.pids(), indent=1) + "\n")

    def _watch(self) -> str | None:
        """Wait for the outcome; a failure message if the run cannot reach one."""
        deadline = time.monotonic() + self.opts.timeout_s
        while not self._got_outcome.wait(0.1):
            if self.stop.is_set():
                return None
            for spec, rc in self.procs.died():
                if not spec.critical:
                    log.log(logging.WARNING if rc else logging.DEBUG, "%s exited (code %d); the world carries on",
                            spec.name, rc)
                elif not self._got_outcome.wait(CRITICAL_EXIT_WAIT_S):
                    return f"{spec.name} exited (code {rc}) before the outcome; see {self.cfg.log_dir / spec.name}.log"
            if time.monotonic() > deadline:
                return f"no outcome within {self.opts.timeout_s:.0f} s of wall time"
        return None

    def _shutdown(self, specs: list) -> None:
        """Let everyone finish on its own briefly, then stop: the world, the others, the recorder."""
        names = [s.name for s in specs if s.name in self.procs.procs]
        t0 = time.monotonic()
        if self._got_outcome.is_set() and not self.stop.is_set():
            self.procs.wait(names, SETTLE_S)
        elif self.procs.running():  # interrupted or failed: the world says where it stopped (nothing judged)
            self.procs.stop([table.WORLD], GRACE_S)
            self._got_outcome.wait(1.0)
        others = [n for n in names if n not in (table.WORLD, table.RECORDER)]
        self.procs.stop(others, GRACE_S)
        self.procs.stop([table.WORLD], GRACE_S)
        self.procs.stop([table.RECORDER], GRACE_S + 2.0)  # it finalizes the MCAP
        log.debug("all processes stopped %.1f s after the watch ended", time.monotonic() - t0)

    def _result(self, failure: str | None) -> RunResult:
        """Judged only if the world judged a scenario that played out on its own.

        A run stopped by the wall-clock limit, by a process that died or by Ctrl-C is
        failed (or interrupted) with its reason, whatever the world said on its way out:
        stopped from outside, it publishes an outcome of ``None`` (nothing judged).
        """
        if self.stop.is_set() and (self.outcome is None or self.outcome_after_stop):
            return RunResult(EXIT_INTERRUPTED, None, "interrupted before the scenario played out")
        if failure is not None:
            return RunResult(EXIT_FAILED, None, failure)
        if self.outcome is None:
            return RunResult(EXIT_FAILED, None, "the world never published an outcome")
        result = dict(self.outcome.result)
        if result.get("outcome") is None:
            return RunResult(EXIT_FAILED, None, result.get("failure") or "the world judged nothing")
        recorder = self.procs.procs.get(table.RECORDER)
        rc = recorder[1].returncode if recorder is not None else 0
        if rc:  # judged all the same: the outcome is the world's; but the log may be cut short
            result["recorder_failed"] = (f"the recorder exited with code {rc} after the outcome: "
                                         f"{self.cfg.mcap_path} may be incomplete (see logs/recorder.log)")
            log.warning("%s", result["recorder_failed"])
        result.update({"scheme": self.cfg.scheme, "model": self.cfg.model.label(),
                       "model_settings": self.cfg.model.settings(), "run_dir": str(self.cfg.run_dir),
                       "mcap": str(self.cfg.mcap_path) if self.cfg.mcap_path.exists() else None,
                       "malformed": {name: {k: r[k] for k in ("total", "by_key")}  # each process's exit line
                                     for name, r in exit_records(self.cfg.log_dir, MALFORMED_LINE).items()},
                       "signed": self.cfg.signing, "lock_down": self.cfg.lock_down})
        cpu = self.cpu.per_tick_ms(int(result.get("ticks") or 0)) if self.cpu is not None else None
        if cpu is not None:  # what the run cost while it ticked: docs/running.md, "outcome.json"
            result["cpu_ms_per_tick"] = cpu
            result["cores"] = usable_cores()
        missed = exit_records(self.cfg.log_dir, shm.MISSED_LINE)
        if missed:  # real time only: an agent two ticks late missed the tick it was told of (protocol.shm)
            result["shm_missed"] = {name: {k: r[k] for k in ("total", "by_key")} for name, r in missed.items()}
        if self.cfg.signing:
            result["rejected"] = {name: {k: r[k] for k in ("total", "by_reason", "by_stream")}
                                  for name, r in exit_records(self.cfg.log_dir, REJECTED_LINE).items()}
        return RunResult(EXIT_SAFE if result["outcome"] == "safe" else EXIT_JUDGED, result)


def launch(opts: LaunchOptions, stop: threading.Event) -> RunResult:
    """One run from validated options; ``stop`` (Ctrl-C) ends it early and cleanly."""
    opts.run.log_dir.mkdir(parents=True, exist_ok=False)
    opts = replace(opts, run=prepare(opts.run))
    if opts.warm_up:
        warm_numba_caches(opts.run.params)
    with ExitStack() as stack:
        stack.enter_context(process_factory.activated())  # warm, and before any Zenoh session: see its docstring
        session, endpoint = open_hub(stack, opts.run.run_dir, locked=opts.run)
        shm_dir = stack.enter_context(shm.run_directory(opts.run.run_id))  # every process is on this host
        opts = replace(opts, run=replace(opts.run, hub=endpoint, shm_dir=str(shm_dir or "")))
        return Launcher(opts, session, stop).run()


# ---------------------------------------------------------------------------- CLI


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=args.log_level.upper() if args.log_level.upper() in logging.getLevelNamesMapping()
                        else "INFO", format="autocast run: %(message)s")
    try:
        opts = options_from(args, hub="")
        if opts.run.signing and len(build(opts.run.params).roadmap.domains) > 1:  # the agents would refuse it
            raise InputError("sign: a map of several scheduler domains runs unsigned (docs/domains.md); drop --sign")
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    t0 = time.monotonic()
    log.info("run %s: %s, %d vehicles, scheme %s -> %s", opts.run.run_id, opts.run.params.scenario,
             opts.run.params.vehicles, opts.run.scheme, opts.run.run_dir)
    # this launcher and all it starts: throughput in lock-step, wake-up latency in real time (processes.manager)
    batch_scheduling(batch=not opts.run.realtime)
    outcome = launch(opts, stop)
    return report(outcome, opts.run, args.json, time.monotonic() - t0)


def exit_now(code: int) -> None:
    """End the process without the interpreter's teardown. After a run everything is
    closed and written (the hub, the processes, the outcome); what is left is freeing
    the numba kernels' LLVM modules one by one, measured at 0.3 s of CPU (1.5 s of wall
    time on the loaded 2-core machine) per run."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        stream.flush()
    os._exit(code)


def json_ready(value: Any) -> Any:
    """``value`` with every float JSON cannot carry (inf, NaN) as None, at any depth."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_ready(v) for v in value]
    return value


def report(res: RunResult, cfg: table.RunConfig, as_json: bool, wall_s: float) -> int:
    """Print the outcome, write ``outcome.json``; return the exit code.

    A run that failed without an outcome still writes (and with ``--json`` prints) a
    record with ``"outcome": null`` and the reason, so sweeps can count it.
    """
    record = res.result
    if record is not None:
        model = "" if cfg.model == OURS else f", model {cfg.model.label()}"
        print(summary(record) + f"  [{cfg.scheme}{model}, {wall_s:.1f} s total]")
    else:
        record = {"outcome": None, "failure": res.failure, "scenario": cfg.params.scenario,
                  "vehicles": cfg.params.vehicles, "seed": cfg.params.seed, "scheme": cfg.scheme,
                  "model": cfg.model.label(), "model_settings": cfg.model.settings(), "run_id": cfg.run_id, "run_dir": str(cfg.run_dir),
                  "mcap": str(cfg.mcap_path) if cfg.mcap_path.exists() else None}
        if res.exit_code == EXIT_INTERRUPTED:
            record["interrupted"] = True
        print(f"run {'interrupted' if res.exit_code == EXIT_INTERRUPTED else 'failed'}: {res.failure}",
              file=sys.stderr)
    record = write_record(cfg.run_dir, record)
    if as_json:
        print(json.dumps(record, allow_nan=False), flush=True)
    return res.exit_code


def write_record(run_dir: Path, record: dict[str, Any]) -> dict[str, Any]:
    """``run_dir/outcome.json``, whole or not at all (a sweep, a cluster worker or a test
    may be polling for it), if the directory exists; returns the record as written."""
    record = json_ready(record)
    if run_dir.is_dir():
        part = run_dir / "outcome.json.part"
        part.write_text(json.dumps(record, allow_nan=False, indent=1) + "\n")
        os.replace(part, run_dir / "outcome.json")
    return record
