"""A soak of faulted runs: many short runs, each with one process killed, hung or
stopped at a random tick under a random loss profile; then what was left behind.

    python -m bench.soak --runs 200 --out runs/soak          # resumes where it stopped
    python -m bench.soak --runs 4 --out /tmp/soak --fault hub:kill --fault recorder:stop

Run ``i`` draws from ``random.Random(f"soak {seed} {i}")``: the scenario, 3-5
vehicles, the scheme (``autocast`` or ``agnostic``), the loss profile (one of
``LOSS_PROFILES`` below, on the control and the data channel alike, each draw its own),
and the fault: which process (an agent, the world, the proxy, the recorder, or the
hub, which is the launcher), what happens to it (``kill``: SIGKILL; ``hang``: it stays
alive and silent; ``stop``: SIGSTOP, nobody continues it) and at which tick
(``protocol.faults``). Each run is ``autocast run ... --json`` in its own process
group, as ``autocast sweep`` starts it, stopped and cleaned up as the sweep does if it
outlives ``--timeout-s`` plus a slack (``deploy.experiments.sweep.Sweep._terminate``), and as the
sweep cleans up after a launcher killed under it.

After each run it records, in ``results.jsonl`` (one line per run, fsynced): the
verdict (judged, or failed with its reason), the processes of the run still alive
(any process whose command line carries the run id, ``LEFT_WAIT_S`` after the launcher
is gone; they are then killed), its ``/dev/shm`` directories still there, whether
``run.mcap`` reads record by record to its end (and whether it was finalized), and the
wall time from the fault (``AUTOCAST_FAULTS_LOG``) to the verdict. The last line is

    soak: runs=... judged=... failed=... lost=... procs_left=... shm_left=... mcap_unreadable=... fault_to_verdict_max_s=...

``lost``: planned runs without a record; ``procs_left``, ``shm_left`` and
``mcap_unreadable`` must be 0, like ``lost`` (exit 1 otherwise).
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import json
import os
import random
import signal
import subprocess
import sys
import threading
import time
from collections import Counter
from concurrent.futures import FIRST_COMPLETED, ThreadPoolExecutor, wait
from dataclasses import asdict, dataclass
from pathlib import Path

from channel_proxy.loss import PrrModel
from channel_proxy.profiles import ChannelProfile
from processes.manager import has_argument
from deploy.experiments.plan import _last_json, append_record
from deploy.experiments.runner import clean_after_launcher, stop_launcher
from protocol import faults, shm

# The loss profiles a run draws from (``--channel-profile bench.soak:NAME``): LTE-Direct's
# radio with a fixed reception probability on every link, or a short-range shadowed one.
_LTE = dict(bandwidth_bps=7.2e6, frame_duration_s=0.01)
LOSS_NONE = ChannelProfile("soak-loss-0", **_LTE, prr=PrrModel(curve="fixed", p_fixed=1.0))
LOSS_10 = ChannelProfile("soak-loss-10", **_LTE, prr=PrrModel(curve="fixed", p_fixed=0.9))
LOSS_30 = ChannelProfile("soak-loss-30", **_LTE, prr=PrrModel(curve="fixed", p_fixed=0.7))
LOSS_60 = ChannelProfile("soak-loss-60", **_LTE, prr=PrrModel(curve="fixed", p_fixed=0.4))
LOSS_ALL = ChannelProfile("soak-loss-100", **_LTE, prr=PrrModel(curve="fixed", p_fixed=0.0))
SHORT_RANGE = ChannelProfile("soak-range-40m", **_LTE, prr=PrrModel(range_m=40.0))
LOSS_PROFILES = ("LOSS_NONE", "LOSS_10", "LOSS_30", "LOSS_60", "LOSS_ALL", "SHORT_RANGE")

SCENARIOS = ("left_turn", "red_light", "overtaking")
SCHEMES = ("autocast", "agnostic")
PROCESSES = ("agent", "world", "proxy", "recorder", "hub")
DURATION_S = 2.5  # sim seconds: 25 ticks
SLACK_S = 30.0  # beyond --timeout-s before the soak stops a launcher itself (the sweep's LAUNCHER_GRACE_S)
LEFT_WAIT_S = 20.0  # for a killed launcher's factory to stop its children (SIGINT, 3 s, SIGKILL)
MCAP_MAGIC = b"\x89MCAP0\r\n"
SOAK_TOKEN = f"{os.getpid():x}"  # in every run id: this soak's; a resumed soak's runs get new ids
PR_SET_CHILD_SUBREAPER = 36  # prctl(2): orphaned descendants become our children, so we reap them


@dataclass(frozen=True, slots=True)
class Plan:
    index: int
    scenario: str
    vehicles: int
    scheme: str
    profile: str
    fault: str  # protocol.faults' "<process>:<action>@<tick>"

    @property
    def run_id(self) -> str:
        """Unique to this soak: run ids name a run's Zenoh keys and find its processes,
        so two soaks at once (a test beside a user's soak) must not share one."""
        process = self.fault.split(":")[0]
        return f"soak{SOAK_TOKEN}-{self.index:04d}-{process}-{self.fault.split(':')[1].split('@')[0]}"


def plan(index: int, seed: int, forced: list[str]) -> Plan:
    """Run ``index``'s draws; ``forced`` (``PROCESS:ACTION``) cycles instead of drawing the fault's kind."""
    rng = random.Random(f"soak {seed} {index}")  # a string seed is hashed: runs do not draw alike
    scenario, vehicles, scheme = rng.choice(SCENARIOS), rng.randint(3, 5), rng.choice(SCHEMES)
    profile = rng.choice(LOSS_PROFILES)
    if forced:
        process, action = forced[index % len(forced)].split(":")
    else:
        process, action = rng.choice(PROCESSES), rng.choice(faults.ACTIONS)
    if process == "agent":
        process = f"agent{rng.randrange(vehicles)}"  # the connected vehicles are 0 .. vehicles-1
    tick = rng.randrange(int(DURATION_S * 10))
    return Plan(index, scenario, vehicles, scheme, profile, f"{process}:{action}@{tick}")


def launcher_argv(p: Plan, out: Path, timeout_s: float, agent_timeout_s: float) -> list[str]:
    return [sys.executable, "-m", "deploy.cli", "run", "--scenario", p.scenario, "--vehicles", str(p.vehicles),
            "--scheme", p.scheme, "--seed", str(p.index), "--duration", str(DURATION_S),
            "--channel-profile", f"bench.soak:{p.profile}", "--json", "--out", str(out / "runs"),
            "--run-id", p.run_id, "--scans", "none", "--no-json-mirror", "--no-warm-up", "--log-level", "WARNING",
            "--timeout-s", repr(timeout_s), "--agent-timeout-s", repr(agent_timeout_s)]


def processes_of(run_id: str) -> list[int]:
    """Every process whose command line carries ``run_id`` as an argument."""
    me = os.getpid()
    return [int(d.name) for d in Path("/proc").iterdir()
            if d.name.isdigit() and int(d.name) != me and has_argument(int(d.name), run_id)]


_LOCK = threading.Lock()
_LAUNCHERS: set[int] = set()  # our launchers not yet reaped by their Popen


def reap_orphans() -> None:
    """Wait for our children that exited (descendants of killed launchers, reparented to
    us), leaving the launchers alone (their Popen reaps them)."""
    me = str(os.getpid())
    with _LOCK:
        keep = set(_LAUNCHERS)
    for d in Path("/proc").iterdir():
        if not d.name.isdigit() or int(d.name) in keep:
            continue
        try:
            if (d / "stat").read_text().rsplit(")", 1)[1].split()[1] == me:
                os.waitpid(int(d.name), os.WNOHANG)
        except (OSError, IndexError, ChildProcessError):
            pass


def mcap_state(path: Path) -> tuple[bool | None, bool]:
    """(whether ``path`` reads to its end: every record whole, each chunk's CRC right;
    whether it was finalized: it ends with a footer); (None, False) if there is no file."""
    from mcap.exceptions import EndOfFile
    from mcap.records import Footer
    from mcap.stream_reader import StreamReader

    if not path.exists():
        return None, False
    try:
        with open(path, "rb") as f:
            for record in StreamReader(f, validate_crcs=True).records:
                if isinstance(record, Footer):
                    return True, True
    except EndOfFile:  # no footer: the recorder did not finalize; whole records to the end?
        return records_whole(path.read_bytes()), False
    except Exception:  # noqa: BLE001 - any other error is the answer: it does not read to its end
        return False, False
    return True, False


def records_whole(data: bytes) -> bool:
    """Whether an MCAP without a footer is its magic and whole records up to its last byte
    (each record: opcode, uint64 length, that many bytes; the reader checked their contents)."""
    pos = len(MCAP_MAGIC)
    if data[:pos] != MCAP_MAGIC:
        return False
    while pos + 9 <= len(data):
        pos += 9 + int.from_bytes(data[pos + 1:pos + 9], "little")
    return pos == len(data)


def soak_one(p: Plan, out: Path, timeout_s: float, agent_timeout_s: float) -> dict:
    fault_log = out / "faults" / f"{p.run_id}.jsonl"
    fault_log.parent.mkdir(parents=True, exist_ok=True)
    fault_log.unlink(missing_ok=True)
    env = dict(os.environ, PYTHONUNBUFFERED="1", **{faults.ENV: p.fault, faults.LOG_ENV: str(fault_log)})
    logs = out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    with open(logs / f"{p.run_id}.out", "wb") as so, open(logs / f"{p.run_id}.err", "wb") as se, _LOCK:
        proc = subprocess.Popen(launcher_argv(p, out, timeout_s, agent_timeout_s), stdout=so, stderr=se,
                                stdin=subprocess.DEVNULL, start_new_session=True, env=env)
        _LAUNCHERS.add(proc.pid)
    try:
        return _watch(p, proc, out, timeout_s, fault_log, t0)
    finally:
        with _LOCK:
            _LAUNCHERS.discard(proc.pid)


def _watch(p: Plan, proc: subprocess.Popen, out: Path, timeout_s: float, fault_log: Path, t0: float) -> dict:
    logs = out / "logs"
    timed_out, cleaned = False, 0
    try:
        proc.wait(timeout=timeout_s + SLACK_S)
    except subprocess.TimeoutExpired:  # a stopped or hung launcher: what the sweep does with it
        timed_out = True
        cleaned = stop_launcher(proc, out / "runs" / p.run_id, p.run_id, SLACK_S)
    run_dir = out / "runs" / p.run_id
    if proc.returncode < 0 and not timed_out:  # the launcher was killed: the sweep cleans up after it
        cleaned = clean_after_launcher(run_dir, p.run_id, proc.pid)
    verdict_unix = time.time()
    result = _last_json((logs / f"{p.run_id}.out").read_text(errors="replace"))
    judged = result is not None and result.get("outcome") is not None and proc.returncode in (0, 1)
    if judged:
        reason = None
    elif timed_out:
        reason = f"the launcher did not exit within {timeout_s + SLACK_S:.0f} s; stopped it"
    elif result is not None:
        reason = result.get("failure") or f"exit code {proc.returncode}"
    else:
        reason = f"the launcher exited with code {proc.returncode} and no record"
    deadline = time.monotonic() + LEFT_WAIT_S  # a killed launcher's factory stops the rest (SIGINT, grace, SIGKILL)
    while (left := processes_of(p.run_id)) and time.monotonic() < deadline:
        reap_orphans()
        time.sleep(0.2)
    for pid in left:  # counted; then gone, so the next run starts clean
        with contextlib.suppress(OSError):
            os.kill(pid, signal.SIGKILL)
    reap_orphans()
    shm_left = sorted(str(d) for d in shm.TMPFS.glob(f"{shm.DIR_PREFIX}*-{p.run_id}-*"))
    readable, finalized = mcap_state(run_dir / "run.mcap")
    fired = [json.loads(line) for line in fault_log.read_text().splitlines()] if fault_log.exists() else []
    return {**asdict(p), "run_id": p.run_id, "status": "judged" if judged else "failed", "failure": reason,
            "exit_code": proc.returncode, "outcome": (result or {}).get("outcome"),
            "dead_agents": (result or {}).get("dead_agents"), "wall_s": round(time.monotonic() - t0, 2),
            "fault_fired": bool(fired),
            "fault_to_verdict_s": round(verdict_unix - fired[0]["t_unix"], 2) if fired else None,
            "procs_killed_by_cleanup": cleaned, "procs_left": len(left), "procs_left_cmd": [_cmdline(pid) for pid in left], "shm_left": shm_left,
            "mcap_readable": readable, "mcap_finalized": finalized}


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")[:200]
    except OSError:
        return ""


def read_records(path: Path) -> list[dict]:
    """The soak's records so far; a torn last line (the soak was killed mid-write) is skipped."""
    out = []
    for line in path.read_text().splitlines() if path.exists() else []:
        with contextlib.suppress(ValueError):
            out.append(json.loads(line))
    return out


def summary(records: list[dict], planned: int) -> dict:
    done = {r["index"]: r for r in records}
    waits = [r["fault_to_verdict_s"] for r in done.values() if r["fault_to_verdict_s"] is not None]
    return {"runs": planned, "judged": sum(r["status"] == "judged" for r in done.values()),
            "failed": sum(r["status"] == "failed" for r in done.values()),
            "lost": sum(i not in done for i in range(planned)),
            "procs_left": sum(r["procs_left"] for r in done.values()),
            "procs_killed_by_cleanup": sum(r["procs_killed_by_cleanup"] for r in done.values()),
            "shm_left": sum(len(r["shm_left"]) for r in done.values()),
            "mcap_unreadable": sum(r["mcap_readable"] is False for r in done.values()),
            "mcap_missing": sum(r["mcap_readable"] is None for r in done.values()),
            "mcap_unfinalized": sum(r["mcap_readable"] is True and not r["mcap_finalized"] for r in done.values()),
            "faults_fired": sum(r["fault_fired"] for r in done.values()),
            "fault_to_verdict_max_s": max(waits, default=0.0),
            "fault_to_verdict_median_s": sorted(waits)[len(waits) // 2] if waits else 0.0}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.soak", description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=200)
    ap.add_argument("--out", type=Path, default=Path("runs/soak"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=2, help="runs at a time")
    ap.add_argument("--timeout-s", type=float, default=45.0, help="each run's wall-clock limit (autocast run)")
    ap.add_argument("--agent-timeout-s", type=float, default=5.0, help="each run's agent timeout (autocast run)")
    ap.add_argument("--no-warm-up", action="store_true", help="the numba caches are warm already: skip filling them")
    ap.add_argument("--fault", action="append", default=[], metavar="PROCESS:ACTION",
                    help="cycle through these kinds of fault instead of drawing one (e.g. hub:kill)")
    args = ap.parse_args(argv)
    for kind in args.fault:
        process, _, action = kind.partition(":")
        if process not in PROCESSES or action not in faults.ACTIONS:
            ap.error(f"--fault {kind!r}: PROCESS in {PROCESSES}, ACTION in {faults.ACTIONS}")
    args.out.mkdir(parents=True, exist_ok=True)
    results = args.out / "results.jsonl"
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0)  # a killed launcher's orphans come to us, not to init
    if not args.no_warm_up:
        from deploy.launch.warmup import warm_numba_caches
        from world_server.scenarios import params_from_dict

        for scenario in SCENARIOS:  # what every run then skips (--no-warm-up), as a sweep does
            warm_numba_caches(params_from_dict({"scenario": scenario, "vehicles": 5}))
    done = {r["index"] for r in read_records(results)}
    t0 = time.monotonic()
    todo = [i for i in range(args.runs) if i not in done]
    with ThreadPoolExecutor(args.jobs) as pool:
        running = set()
        while todo or running:
            while todo and len(running) < args.jobs:
                running.add(pool.submit(soak_one, plan(todo.pop(0), args.seed, args.fault), args.out, args.timeout_s,
                                        args.agent_timeout_s))
            finished, running = wait(running, return_when=FIRST_COMPLETED)
            for fut in finished:
                rec = fut.result()
                append_record(results, rec)
                what = rec["outcome"] if rec["status"] == "judged" else f"FAILED: {rec['failure']}"
                print(f"[{rec['index'] + 1}/{args.runs}] {rec['run_id']} {rec['fault']} {rec['profile']}: {what}  "
                      f"(fault->verdict {rec['fault_to_verdict_s']} s, left {rec['procs_left']} procs "
                      f"{len(rec['shm_left'])} shm, mcap {rec['mcap_readable']}/{rec['mcap_finalized']}, "
                      f"{rec['wall_s']:.0f} s; {time.monotonic() - t0:.0f} s in)", file=sys.stderr, flush=True)
    records = read_records(results)
    s = summary(records, args.runs)
    reasons = Counter(r["failure"].split(";")[0].split(" (")[0] for r in records if r["status"] == "failed")
    print("failures by reason:")
    for reason, n in reasons.most_common():
        print(f"  {n:4d}  {reason}")
    kinds = Counter((r["fault"].split(":")[0].rstrip("0123456789"), r["fault"].split(":")[1].split("@")[0],
                     r["status"]) for r in records)
    print("runs by fault and verdict:")
    for (process, action, status), n in sorted(kinds.items()):
        print(f"  {process:8s} {action:5s} {status:7s} {n:4d}")
    print("soak: " + " ".join(f"{k}={v}" for k, v in s.items()), flush=True)
    bad = s["lost"] or s["procs_left"] or s["shm_left"] or s["mcap_unreadable"]
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
