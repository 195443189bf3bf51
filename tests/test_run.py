"""``autocast run`` end to end: the launcher, the world, the agents and the recorder as
real processes on loopback, driven through the CLI as a user would."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader

from deploy.launch import table
from processes.manager import BATCH_SLICE_MS, ProcSpec, scheduling
from deploy.launch.run import main as run_main
from deploy.launch.run import Launcher, options_from, parse_args
from protocol.session import ZenohArgs, session_scope
from tests.conftest import batch_allowed, free_port, reports_slices
from protocol import keys
from protocol.codec import decode
from protocol.messages import Outcome, Scan, Tick

OUTCOMES = ("safe", "near_miss", "crash", "deadlock")
UNSTABLE = ("run_id", "wall_s", "realtime_factor", "run_dir", "mcap", "cpu_ms_per_tick")  # differ between identical runs


class Launch:
    """One ``python -m deploy.cli run`` process; reads its outputs once it has exited."""

    def __init__(self, out: Path, run_id: str, *flags: str, faults: str = "") -> None:
        """``faults``: what fails, and at which tick, in this run (protocol/faults.py)."""
        self.run_id, self.run_dir = run_id, out / run_id
        self.proc = subprocess.Popen([sys.executable, "-m", "deploy.cli", "run", "--out", str(out), "--run-id", run_id,
                                      "--json", *flags], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                     start_new_session=True, env=dict(os.environ, AUTOCAST_FAULTS=faults))
        self.stdout = self.stderr = ""

    def finish(self, timeout: float = 90) -> int:
        self.stdout, self.stderr = self.proc.communicate(timeout=timeout)
        return self.proc.returncode

    @property
    def result(self) -> dict:
        return json.loads(self.stdout.strip().splitlines()[-1])

    def pids(self, timeout: float = 30) -> dict[str, int]:
        path = self.run_dir / "pids.json"
        deadline = time.monotonic() + timeout
        while not path.exists():
            assert time.monotonic() < deadline and self.proc.poll() is None, self.stderr
            time.sleep(0.05)
        return json.loads(path.read_text())

    def wait_ticking(self, timeout: float = 60) -> None:
        """Until the world has started ticking (all agents up)."""
        log = self.run_dir / "logs" / "world.log"
        deadline = time.monotonic() + timeout
        while not (log.exists() and "agents up" in log.read_text()):
            assert time.monotonic() < deadline and self.proc.poll() is None, "the world never started ticking"
            time.sleep(0.05)

    def leftovers(self) -> list[int]:
        """Processes of this run still alive (there must be none once the launcher exited)."""
        out = subprocess.run(["pgrep", "-f", f"--run-id {self.run_id}( |$)"], capture_output=True, text=True)
        return [int(p) for p in out.stdout.split()]

    def kill_all(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.communicate()
        for pid in self.leftovers():
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass


# The module-scoped fixtures below start runs once per worker: keep the module on one.
pytestmark = pytest.mark.xdist_group("test_run")


@pytest.fixture(scope="module")
def launches(tmp_path_factory):
    """Start launches; whatever is left of them is killed at the end of the module."""
    out = tmp_path_factory.mktemp("runs")
    started: list[Launch] = []

    def start(name: str, *flags: str, faults: str = "") -> Launch:
        started.append(Launch(out, f"t{os.getpid()}-{name}", *flags, faults=faults))
        return started[-1]

    yield start
    for launch in started:
        launch.kill_all()


@pytest.fixture(scope="module")
def scenario_runs(launches):
    """Each scenario with 5 vehicles and scheme single, run once for the module."""
    done: dict[str, Launch] = {}

    def get(scenario: str) -> Launch:
        if scenario not in done:
            launch = launches(scenario, "--scenario", scenario, "--vehicles", "5", "--scheme", "single")
            launch.finish()
            done[scenario] = launch
        return done[scenario]

    return get


def stable(result: dict) -> dict:
    return {k: v for k, v in result.items() if k not in UNSTABLE}


@pytest.mark.parametrize("scenario", ["overtaking", "left_turn", "red_light"])
def test_each_scenario_runs_to_a_judged_outcome(scenario_runs, scenario):
    launch = scenario_runs(scenario)
    r = launch.result
    assert launch.proc.returncode == (0 if r["outcome"] == "safe" else 1), launch.stderr
    assert r["outcome"] in OUTCOMES and r["scenario"] == scenario and r["scheme"] == "single"
    assert r["dead_agents"] == {} and r["ticks"] > 0
    for key in ("closest_distance_m", "reaction_time_s", "collider_visible_share_own", "seed", "run_dir", "mcap"):
        assert key in r
    assert json.loads((launch.run_dir / "outcome.json").read_text()) == r
    assert r["mcap"] == str(launch.run_dir / "run.mcap")
    assert r["outcome"] in launch.stdout.splitlines()[-2]  # the summary line before the JSON
    logs = {p.name for p in (launch.run_dir / "logs").iterdir()}
    assert logs == {"recorder.log", "world.log"} | {f"agent{v}.log" for v in range(5)}
    assert launch.leftovers() == []


def test_each_agent_reports_the_cpu_time_of_its_stages(scenario_runs):
    """The agent's exit line (read by ``autocast bench pipeline``) has every stage's CPU
    time per tick; the stages' means add up to no more than the whole tick's."""
    launch = scenario_runs("left_turn")
    for vid in range(5):
        lines = (launch.run_dir / "logs" / f"agent{vid}.log").read_text().splitlines()
        t = json.loads([ln for ln in lines if ln.startswith("agent_timings ")][-1].removeprefix("agent_timings "))
        names = [s for s in ("perception", "spatial_reasoning", "fusion", "planning", "control") if f"{s}_cpu_mean" in t]
        stages = [t[f"{s}_cpu_mean"] for s in names]
        # single: no spatial reasoning; a vehicle that holds still fuses nothing (Pipeline.fuses), the ego does
        assert {"perception", "planning", "control"} <= set(names) and all(x >= 0.0 for x in stages), t
        assert vid != 0 or "fusion" in names, t
        assert t["perception_cpu_mean"] > 0.0 and 0.0 < sum(stages) <= t["cpu_mean"] + 5e-3, t  # means rounded to 1 us


def test_the_outcome_says_what_each_kind_of_process_spent_a_tick(scenario_runs):
    """``cpu_ms_per_tick`` (processes.manager.RunCpu): each kind of process of the run, the
    agents together, and the whole; the parts add up to the whole."""
    r = scenario_runs("left_turn").result
    cpu = r["cpu_ms_per_tick"]
    assert set(cpu) == {"recorder", "world", "agents", "launcher", "all"}, cpu  # single: no channel proxy
    assert all(cpu[k] > 0.0 for k in ("recorder", "world", "agents")) and cpu["launcher"] >= 0.0, cpu
    assert cpu["all"] == pytest.approx(sum(v for k, v in cpu.items() if k != "all"), abs=0.03), cpu  # each rounded
    assert r["cores"] >= 1


def test_the_same_seed_gives_the_same_outcome(scenario_runs, launches):
    first = scenario_runs("left_turn")
    again = launches("again", "--scenario", "left_turn", "--vehicles", "5", "--scheme", "single")
    again.finish()
    assert stable(again.result) == stable(first.result)


def test_the_mcap_holds_every_topic(scenario_runs):
    launch = scenario_runs("left_turn")
    run, r = launch.run_id, launch.result
    with open(launch.run_dir / "run.mcap", "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        ticks = [decode(m.data, Tick).tick for _, _, m in reader.iter_messages(topics=[keys.world_tick(run)])]
        f.seek(0)
        scans = [decode(m.data, Scan) for _, _, m in make_reader(f).iter_messages(topics=[keys.scan(run, 0)])]
        f.seek(0)
        (outcome,) = [decode(m.data, Outcome) for _, _, m in
                      make_reader(f).iter_messages(topics=[keys.world_outcome(run)])]
    counts = {ch.topic: summary.statistics.channel_message_counts.get(cid, 0) for cid, ch in summary.channels.items()}
    expected = {keys.world_tick(run), keys.world_map(run), keys.world_outcome(run), keys.world_truth(run),
                keys.scan(run, 0)}
    expected |= {keys.cmd(run, v) for v in range(5)} | {keys.mission(run, v) for v in range(5)}
    assert expected <= set(counts)
    assert keys.scan(run, 1) not in counts  # only the ego's scans by default
    assert ticks == list(range(r["ticks"]))
    assert [s.tick for s in scans] == ticks and scans[0].range_cm.shape == (1800, 64)
    assert all(counts[keys.cmd(run, v)] > 0 for v in range(5))
    assert outcome.result["outcome"] == r["outcome"]
    assert {ch.message_encoding for ch in summary.channels.values()} == {"msgpack", "json"}  # the JSON mirror
    assert counts[f"json/{keys.world_truth(run)}"] == counts[keys.world_truth(run)] == r["ticks"]
    assert {"Tick", "WorldTruth", "Scan", "Command", "Outcome", "MapMsg", "Mission"} <= {
        s.name for s in summary.schemas.values()}
    assert {k: meta["autocast"][k] for k in ("scenario", "seed", "scheme", "vehicles", "run_id")} == {
        "scenario": "left_turn", "seed": "0", "scheme": "single", "vehicles": "5", "run_id": run}
    assert meta["autocast"]["git_revision"]


def test_a_one_host_run_moves_scans_and_bundles_through_shared_memory_and_leaves_none(launches):
    """Every scan and both bundles go through the run's shared memory (protocol.shm):
    with ``--scans all`` the recorder listens on every key, so each payload also goes
    over Zenoh and each notice is recorded beside it; every notice was read (nothing
    dropped anywhere), and the run's directory is gone once the launcher exited."""
    launch = launches("shm", "--scenario", "left_turn", "--vehicles", "4", "--scheme", "autocast", "--duration", "1.5",
                      "--scans", "all")
    assert launch.finish() in (0, 1), launch.stderr
    run, r = launch.run_id, launch.result
    with open(launch.run_dir / "run.mcap", "rb") as f:
        summary = make_reader(f).get_summary()
    counts = {ch.topic: summary.statistics.channel_message_counts.get(cid, 0) for cid, ch in summary.channels.items()}
    for key in [keys.scan(run, v) for v in range(4)] + [keys.net_ctrl_rx(run), keys.net_data_rx(run)]:
        assert counts[key] == counts[keys.in_shm(key)] == r["ticks"], key
    assert all(m["total"] == 0 for m in r["malformed"].values()), r["malformed"]
    assert not list(Path("/dev/shm").glob(f"autocast-{launch.proc.pid}-{run}-*"))


def test_a_killed_agent_still_ends_in_a_judged_outcome(launches):
    """Agent 2 is SIGKILLed at tick 10: the world marks it dead (its liveliness token
    drops), its vehicle brakes, and the run plays out to a judged outcome."""
    launch = launches("kill", "--scenario", "left_turn", "--vehicles", "5", "--scheme", "single",
                      faults="agent2:kill@10")
    assert launch.finish() in (0, 1), launch.stderr
    r = launch.result
    assert r["outcome"] in OUTCOMES and r["mode"] == "lockstep" and r["ticks"] > 10
    assert list(r["dead_agents"]) == ["2"] and "liveliness" in r["dead_agents"]["2"]
    assert "fault injection: kill at tick 10" in (launch.run_dir / "logs" / "agent2.log").read_text()
    assert launch.leftovers() == []


def test_ctrl_c_stops_everything_and_finalizes_the_mcap(launches):
    """Agent 1 hangs at tick 5, so the run is still going whenever the SIGINT lands."""
    launch = launches("sigint", "--scenario", "left_turn", "--vehicles", "3", "--scheme", "single",
                      "--agent-timeout-s", "600", faults="agent1:hang@5")
    pids = launch.pids()
    launch.wait_ticking()
    if batch_allowed():  # a lock-step run: every thread of every process (processes.manager.batch_scheduling)
        want = (os.SCHED_BATCH, round(BATCH_SLICE_MS * 1e6) if reports_slices() else None)
        assert {name: thread_policies(pid) for name, pid in pids.items()} == {name: {want} for name in pids}
        assert thread_policies(launch.proc.pid) == {want}
    launch.proc.send_signal(signal.SIGINT)
    assert launch.finish(timeout=60) == 130, launch.stderr
    assert launch.result["interrupted"] is True and launch.result["outcome"] is None
    assert "run interrupted" in launch.stderr
    with open(launch.run_dir / "run.mcap", "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics.message_count > 0
    assert launch.leftovers() == []
    assert not [pid for pid in pids.values() if runs_for(pid, launch.run_id)]


def thread_policies(pid: int) -> set[tuple[int, int | None]]:
    """The scheduling policy and slice (``processes.manager.scheduling``) of each of ``pid``'s
    threads (one that ends meanwhile left out)."""
    out = set()
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            out.add(scheduling(int(tid)))
        except ProcessLookupError:
            continue
    return out


def runs_for(pid: int, run_id: str) -> bool:
    """Whether ``pid`` is alive and still one of this run's processes (not a reused pid)."""
    try:
        return run_id in Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace")
    except (FileNotFoundError, ProcessLookupError):
        return False


def recorded_outcome(launch: Launch) -> dict | None:
    """The outcome message in the run's MCAP (which must be finalized), or None."""
    with open(launch.run_dir / "run.mcap", "rb") as f:
        reader = make_reader(f)
        assert reader.get_summary() is not None  # finalized
        f.seek(0)
        found = [decode(m.data, Outcome).result for _, _, m in
                 make_reader(f).iter_messages(topics=[keys.world_outcome(launch.run_id)])]
    return found[0] if found else None


@pytest.mark.parametrize("process, scheme", [("world", "single"), ("proxy", "autocast")])
def test_a_critical_process_dying_fails_the_run(launches, process, scheme):
    """The world or the channel proxy is SIGKILLed at tick 5: the run cannot be judged,
    so it fails (exit 3) naming the process, the MCAP is finalized, nothing is left."""
    launch = launches(f"no{process}", "--scenario", "left_turn", "--vehicles", "3", "--scheme", scheme,
                      faults=f"{process}:kill@5")
    assert launch.finish(timeout=120) == 3, launch.stderr
    assert launch.result["outcome"] is None and f"{process} exited (code -9)" in launch.result["failure"]
    assert f"run failed: {process} exited (code -9)" in launch.stderr
    assert json.loads((launch.run_dir / "outcome.json").read_text()) == launch.result
    outcome = recorded_outcome(launch)
    assert outcome is None or outcome["outcome"] is None  # the world, stopped, judged nothing
    assert launch.leftovers() == []


def test_a_recorder_that_dies_at_the_outcome_is_reported_with_the_judged_run(launches):
    """The recorder is SIGKILLed as the outcome (tick 5 of a 5-tick run) reaches it: the
    world's outcome still stands, and the result says the MCAP may be incomplete."""
    launch = launches("recorderdies", "--scenario", "left_turn", "--vehicles", "2", "--scheme", "single",
                      "--duration", "0.5", faults="recorder:kill@5")
    assert launch.finish(timeout=120) in (0, 1), launch.stderr
    assert launch.result["outcome"] is not None
    assert "the recorder exited with code -9 after the outcome" in launch.result["recorder_failed"]
    assert "may be incomplete" in launch.stderr
    assert launch.leftovers() == []


def test_a_run_cut_short_by_the_wall_clock_limit_is_failed_not_judged(launches):
    """Agent 1 hangs at tick 3 (and may take 600 s before it is declared dead), so only
    the run's 2 s wall-clock limit ends it: the run is failed with that reason, never
    judged a deadlock (tests/test_world_process.py: the world, stopped, judges nothing)."""
    launch = launches("cut", "--scenario", "left_turn", "--vehicles", "2", "--scheme", "single",
                      "--agent-timeout-s", "600", "--timeout-s", "2", faults="agent1:hang@3")
    assert launch.finish(timeout=120) == 3, launch.stderr
    r = launch.result
    assert r["outcome"] is None and r["failure"] == "no outcome within 2 s of wall time"
    assert "interrupted" not in r
    outcome = recorded_outcome(launch)  # none if the limit came while the world was still starting
    assert outcome is None or outcome["outcome"] is None
    assert launch.leftovers() == []


@pytest.mark.parametrize("flags, field", [(["--vehicles", "500"], "vehicles"), (["--vehicles", "ten"], "vehicles"),
                                          (["--scenario", "roundabout"], "scenario"),
                                          (["--collider-speed", "-1"], "collider_speed_kmh"),
                                          (["--delta", "nan"], "delta_s"), (["--scheme", "telepathy"], "scheme"),
                                          (["--scans", "some"], "scans"), (["--run-id", "a/b"], "run_id"),
                                          (["--scheduler", "telepathy"], "scheduler"),
                                          (["--scheduler", "no_such_pkg:f"], "scheduler"),
                                          (["--scheme", "single", "--scheduler", "greedy"], "scheduler"),
                                          (["--channel-profile", "5g-magic"], "channel_profile"),
                                          (["--scheme", "emp", "--channel-profile", "dsrc"], "channel_profile"),
                                          (["--wait-for", "a/b"], "wait_for"),
                                          (["--scenario", "corridor3", "--sign"], "sign")])
def test_a_bad_flag_is_refused_naming_the_field(tmp_path, capsys, flags, field):
    assert run_main(["--out", str(tmp_path), *flags]) == 2
    assert f"error: {field}: " in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []  # nothing was started, nothing written


def test_wait_for_reaches_the_world_and_only_the_world():
    opts = options_from(parse_args(["--run-id", "w", "--wait-for", "logger", "peer"]), hub="tcp/127.0.0.1:1")
    assert opts.run.wait_for == ("logger", "peer")
    world = table.world_args(opts.run)
    assert world[world.index("--wait-for"):][:3] == ("--wait-for", "logger", "peer")
    assert not any("--wait-for" in spec.args for spec in table.processes(opts.run) if spec.name != table.WORLD)


def test_the_launcher_waits_for_the_recorder_not_for_its_own_subscribers(tmp_path):
    """The launcher starts the world once the hub says somebody subscribes to the world's
    tick and outcome (``wait_recorder_ready``): the recorder, never the launcher's own
    subscribers to those keys. A recorder that exits at once, subscribed to nothing,
    fails the run as one that did not come up. (When the launcher subscribed first, it
    answered for the recorder, and a run's first ticks could go unrecorded.)"""
    hub = f"tcp/127.0.0.1:{free_port()}"
    opts = options_from(parse_args(["--out", str(tmp_path), "--run-id", "r", "--timeout-s", "60"]), hub=hub)
    opts.run.log_dir.mkdir(parents=True)
    gone = ProcSpec(table.RECORDER, "deploy.record.recorder", ("--no-such-flag",))  # argparse refuses it: exit 2
    with session_scope(ZenohArgs(listen=(hub,)), wait_s=0.0) as session:
        res = Launcher(opts, session, threading.Event(), specs=[gone]).run()
    assert res.result is None and "the recorder did not come up" in res.failure, res


def test_the_recorder_writes_the_json_mirror_unless_told_not_to():
    def recorder_args(*flags):
        opts = options_from(parse_args(["--run-id", "w", *flags]), hub="tcp/127.0.0.1:1")
        return next(spec.args for spec in table.processes(opts.run) if spec.name == table.RECORDER)

    assert "--json-mirror" in recorder_args()
    assert "--json-mirror" not in recorder_args("--no-json-mirror")


@pytest.mark.parametrize("scheme", ["single", "lane", "emp", "agnostic", "autocast"])
def test_the_world_waits_for_the_proxy_exactly_when_the_run_has_one(scheme):
    """Tick 0's messages go through the proxy: a world that ticked before the proxy had
    subscribed lost them, and two runs of one seed differed by which process won."""
    opts = options_from(parse_args(["--run-id", "w", "--scheme", scheme]), hub="tcp/127.0.0.1:1")
    has_proxy = any(spec.name == table.PROXY for spec in table.processes(opts.run))
    assert ("--wait-for-proxy" in table.world_args(opts.run)) == has_proxy == (scheme not in ("single", "lane"))


def test_the_cli_refuses_a_bad_flag_before_starting_anything(tmp_path):
    p = subprocess.run([sys.executable, "-m", "deploy.cli", "run", "--out", str(tmp_path), "--vehicles", "500"],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 2 and "error: vehicles: 500 is not in [2, 64]" in p.stderr
    assert p.stdout == "" and list(tmp_path.iterdir()) == []


def test_a_scheduler_and_a_channel_profile_plug_in(launches):
    """--scheduler and --channel-profile reach the agents and the proxy: the proxy plays
    the named profile, the agents schedule with the named scheduler (here one given by
    import path) and the MCAP says which were used."""
    launch = launches("plugins", "--scenario", "left_turn", "--vehicles", "5", "--scheme", "autocast",
                      "--scheduler", "vehicle_agent.scheduler.agnostic:agnostic", "--channel-profile", "dsrc",
                      "--duration", "3")
    assert launch.finish(timeout=180) in (0, 1), launch.stderr
    assert launch.result["outcome"] in OUTCOMES
    assert "profile dsrc: B=6 Mbps, T_n=100 ms, N=1" in (launch.run_dir / "logs" / "proxy.log").read_text()
    configs = [line for log in (launch.run_dir / "logs").glob("agent*.log")
               for line in log.read_text().splitlines() if line.startswith("agent_config ")]
    assert len(configs) == 5
    for line in configs:
        cfg = json.loads(line.removeprefix("agent_config "))
        assert (cfg["scheduler"], cfg["channel_profile"]) == ("vehicle_agent.scheduler.agnostic:agnostic", "dsrc")
    with open(launch.run_dir / "run.mcap", "rb") as f:
        meta = {m.name: m.metadata for m in make_reader(f).iter_metadata()}["autocast"]
    assert meta["scheduler"] == "vehicle_agent.scheduler.agnostic:agnostic" and meta["channel_profile"] == "dsrc"


def test_a_channel_profile_by_import_path(tmp_path, monkeypatch):
    from channel_proxy.profiles import get_profile

    (tmp_path / "my_radio.py").write_text(
        "from channel_proxy.profiles import ChannelProfile\n"
        "WIDE = ChannelProfile('wide', 28e6, 0.005, description='a 28 Mbps test radio')\n"
        "NOT_A_PROFILE = 3\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert get_profile("my_radio:WIDE").bandwidth_bps == 28e6
    with pytest.raises(KeyError, match="not a ChannelProfile"):
        get_profile("my_radio:NOT_A_PROFILE")
    with pytest.raises(KeyError, match="cannot load"):
        get_profile("my_radio:MISSING")
