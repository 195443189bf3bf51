"""``autocast sweep --cluster``: real ``dask scheduler`` and ``dask worker`` processes on
loopback (free ports), tiny sweeps (2 vehicles, 1 s of sim time). The same plan
judged the same on the cluster as locally; a worker killed in the middle of a run;
Ctrl-C; the scheduler going away. Faults are deterministic: a run hangs at a tick on
the worker the test means to kill (``AUTOCAST_FAULTS`` in that worker's environment),
and the test acts once the run's ``pids.json`` shows it started."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

from deploy.experiments import cluster, plan, report
from deploy.experiments.plan import RunKey
from tests.conftest import free_port, wait_until
from tests.test_sweep import autocast, leftovers, lines

pytest.importorskip("distributed")

# differ between identical runs, or say where a run ran
# what says how and where a run ran, not how it ended: ``cores`` comes with ``cpu_ms_per_tick``, only
# from runs whose processes were all forked by the factory (deploy/launch/run.py), so either may be absent
UNSTABLE = ("alone", "run_id", "wall_s", "realtime_factor", "run_dir", "mcap", "malformed", "wall_total_s", "cpu_s", "cpu_ms_per_tick",
            "cores", "finished_at", "worker", "host", "attempt")
HANG = "agent1:hang@5"  # agent 1 stops answering at tick 5: the run goes on until it is stopped


def plan_file(tmp_path: Path, scenarios: list[str], schemes: list[str], agent_timeout_s: float = 300) -> Path:
    f = tmp_path / "plan.toml"
    f.write_text(f"scenarios = {json.dumps(scenarios)}\ncollider_speeds_kmh = [30]\ndeltas_s = [0]\nvehicles = [2]\n"
                 f"schemes = {json.dumps(schemes)}\nseeds = [0]\nduration_s = 1\nagent_timeout_s = {agent_timeout_s}\n")
    return f


class Cluster:
    """A scheduler and workers as processes of this test; all stopped at teardown."""

    def __init__(self, tmp_path: Path) -> None:
        self.tmp = tmp_path
        self.procs: list[subprocess.Popen] = []
        self.names: list[str] = []  # the scheduler's first
        self.address = ""

    def _start(self, name: str, args: list[str], ready: str, env: dict[str, str]) -> subprocess.Popen:
        log = self.tmp / f"{name}.log"
        with open(log, "wb") as err:
            p = subprocess.Popen([sys.executable, "-m", "dask", *args], stdin=subprocess.DEVNULL,
                                 stdout=subprocess.DEVNULL, stderr=err, start_new_session=True,
                                 env={**os.environ, **env})
        self.procs.append(p)
        self.names.append(name)
        wait_until(lambda: ready in log.read_text() or p.poll() is not None, f"{name} ready", timeout_s=120)
        assert p.poll() is None, log.read_text()
        return p

    def scheduler(self) -> subprocess.Popen:
        port = free_port()
        self.address = f"tcp://127.0.0.1:{port}"
        return self._start("scheduler", ["scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"],
                           "Scheduler at:", {})

    def worker(self, name: str, **env: str) -> tuple[subprocess.Popen, str]:
        """A worker holding one 2-vehicle run at a time; ``env`` reaches its runs."""
        port = free_port()
        p = self._start(name, ["worker", self.address, "--name", name, "--host", "127.0.0.1", "--worker-port",
                               str(port), "--nthreads", "1", "--no-nanny", "--no-dashboard", "--resources",
                               "vehicles=2", "--local-directory", str(self.tmp / name)],
                        "Registered to:", {"DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT": "5s", **env})
        return p, f"tcp://127.0.0.1:{port}"

    def stop(self) -> None:
        """The workers first, each waited for while the scheduler still answers their
        goodbye (SIGTERM closes a worker; its runs get SIGINT from the kernel), then the
        scheduler. A process that outlasts the safety net is killed and named in a
        warning with its log's tail."""
        procs = list(zip(self.names, self.procs))
        for batch in (procs[1:], procs[:1]):
            for _, p in batch:
                if p.poll() is None:
                    os.killpg(p.pid, signal.SIGTERM)
            for name, p in batch:
                try:
                    p.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    os.killpg(p.pid, signal.SIGKILL)
                    p.wait()
                    tail = (self.tmp / f"{name}.log").read_text(errors="replace")[-2000:]
                    warnings.warn(f"dask {name} outlasted 30 s after SIGTERM and was killed; its log ends:\n{tail}")


@pytest.fixture
def dask_cluster(tmp_path):
    c = Cluster(tmp_path)
    yield c
    c.stop()


def sweep_proc(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "deploy.cli", "sweep", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)


def finish(proc: subprocess.Popen, timeout_s: float = 240) -> str:
    try:
        _, err = proc.communicate(timeout=timeout_s)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    return err


# ---------------------------------------------------------------------------- pure parts


def test_a_run_id_never_reuses_a_directory(tmp_path):
    assert cluster.free_run_id(tmp_path, "k", 1) == "k"
    (tmp_path / "k").mkdir()
    (tmp_path / "k-a2").mkdir()
    assert cluster.free_run_id(tmp_path, "k", 1) == "k-a3"
    assert cluster.free_run_id(tmp_path, "k", 4) == "k-a4"


def test_a_run_lost_with_its_workers_is_a_failed_record_naming_them():
    key = RunKey("left_turn", 2, 30.0, 0.0, "single", 0, 1.0)
    rec = cluster.lost_record(key, key.name, ["tcp://10.0.0.1:4000", "tcp://10.0.0.2:4000"])
    assert rec["status"] == "failed" and rec["outcome"] is None and rec["run_key"] == key.name
    assert rec["error"]["failure"] == ("the worker died during each of its 2 attempts "
                                       "(tcp://10.0.0.1:4000, tcp://10.0.0.2:4000)")
    json.dumps(rec, allow_nan=False)  # a results line


def test_the_report_finds_mcaps_under_the_runs_dir_and_names_the_missing(tmp_path):
    shared = tmp_path / "shared"
    (shared / "r1").mkdir(parents=True)
    (shared / "r1" / "run.mcap").write_bytes(b"x")
    plan = {"runs_dir": str(shared)}
    found = {"run_id": "r1", "host": "node-a"}
    absent = {"run_id": "r2", "host": "node-b"}
    deleted = {"run_id": "r3", "mcap": None, "mcap_deleted_mb": 310.0}
    assert report.mcap_of(tmp_path / "sweep", plan, found) == shared / "r1" / "run.mcap"
    assert report.mcap_of(tmp_path / "sweep", plan, absent) is None
    note = report.missing_mcaps_note([absent, deleted], plan)
    assert note.startswith("scheduled_delay.png lacks the MCAPs of 2 of the runs chosen for it: ")
    assert "1 deleted after the run for their size (`mcap_limit_mb`): `r3`" in note
    assert f"1 not found on this machine (they ran on node-b; their runs directory, `{shared}`" in note
    assert report.missing_mcaps_note([], plan) == ""


# ---------------------------------------------------------------------------- real clusters


@pytest.mark.heavy
def test_a_cluster_sweep_judges_as_the_local_one_and_reports(tmp_path, dask_cluster):
    """Two scenarios x two schemes through a scheduler and two workers, and the same
    plan locally: the same judged outcomes, field by field (lock-step runs are
    deterministic); the report reads the MCAPs from the shared runs directory, and
    says which plot lacks them once that directory is gone."""
    dask_cluster.scheduler()
    workers = {dask_cluster.worker(name)[1] for name in ("w1", "w2")}
    f = plan_file(tmp_path, ["left_turn", "red_light"], ["single", "autocast"])
    out, shared = tmp_path / "on_cluster", tmp_path / "shared"
    res = autocast("sweep", "--file", str(f), "--out", str(out), "--cluster", dask_cluster.address,
                   "--runs-dir", str(shared), timeout=300)
    assert res.returncode == 0, res.stderr
    assert "[4/4]" in res.stderr and "ETA" in res.stderr
    local = autocast("sweep", "--file", str(f), "--out", str(tmp_path / "here"), timeout=300)
    assert local.returncode == 0, local.stderr

    there = {r["run_key"]: r for r in lines(out / "results.jsonl")}
    here = {r["run_key"]: r for r in lines(tmp_path / "here" / "results.jsonl")}
    assert len(there) == len(lines(out / "results.jsonl")) == 4 and there.keys() == here.keys()
    for name, r in there.items():
        assert r["status"] == "judged" and r["ticks"] > 0 and not r["dead_agents"], r
        assert r["worker"] in workers and r["attempt"] == 1
        assert {k: v for k, v in r.items() if k not in UNSTABLE} == \
            {k: v for k, v in here[name].items() if k not in UNSTABLE}, name
        assert (shared / r["run_id"] / "outcome.json").exists()
        assert "outcome" in (out / "logs" / f"{r['run_id']}.out").read_text()
    plan = json.loads((out / "plan.json").read_text())
    assert plan["cluster"] == dask_cluster.address and plan["runs_dir"] == str(shared)
    assert not leftovers(r["run_id"] for r in there.values())

    assert report.main([str(out)]) == 0
    summary = (out / "report" / "summary.md").read_text()
    assert "4 runs recorded (4 judged, 0 failed)" in summary and "has 4 runs, 0 of them not run yet" in summary
    assert "From the runs' MCAPs" in summary and "lacks the MCAPs" not in summary
    shared.rename(tmp_path / "elsewhere")  # as on workers without a shared filesystem
    assert report.main([str(out)]) == 0
    summary = (out / "report" / "summary.md").read_text()
    assert "scheduled_delay.png lacks the MCAPs of 2 of the runs chosen for it: 2 not found on this machine" \
        in summary


@pytest.mark.heavy
def test_a_worker_killed_mid_run_gets_its_run_retried_once_elsewhere(tmp_path, dask_cluster):
    """Worker A's runs hang at tick 5. A alone takes the first run; once its pids.json
    shows it started, worker B joins and A is SIGKILLed: the run is run again on B,
    and each run of the plan is recorded exactly once. A's launcher, orphaned, got
    SIGINT from the kernel and stopped its processes."""
    dask_cluster.scheduler()
    a, a_addr = dask_cluster.worker("a", AUTOCAST_FAULTS=HANG)
    f = plan_file(tmp_path, ["left_turn"], ["single", "autocast"], agent_timeout_s=600)
    out, shared = tmp_path / "sw", tmp_path / "shared"
    proc = sweep_proc("--file", str(f), "--out", str(out), "--cluster", dask_cluster.address, "--runs-dir", str(shared))
    first = plan.expand(plan.spec_from(plan.load_file(f)[0], "plan"))[0].name
    try:
        wait_until(lambda: (shared / first / "pids.json").exists() or proc.poll() is not None, "the run started on A",
                   timeout_s=240)
        assert proc.poll() is None, proc.stderr.read()
        _, b_addr = dask_cluster.worker("b")
        a.kill()
        a.wait()
    finally:
        err = finish(proc)
    assert proc.returncode == 0, err
    recs = lines(out / "results.jsonl")
    assert len(recs) == 2 and len({r["run_key"] for r in recs}) == 2
    assert all(r["status"] == "judged" and r["worker"] == b_addr for r in recs), recs
    retried = next(r for r in recs if r["run_key"] == first)
    assert retried["attempt"] == 2 and retried["lost_workers"] == [a_addr] and retried["run_id"] == f"{first}-a2"
    assert (out / "logs" / f"{first}-a2.err").read_text().startswith(
        f"autocast sweep: attempt 1 on {a_addr}: the worker died during the run")
    orphan = shared / first / "outcome.json"
    wait_until(orphan.exists, "the orphaned launcher stopped its run", timeout_s=120)
    assert json.loads(orphan.read_text()).get("interrupted") is True
    wait_until(lambda: not leftovers([first, f"{first}-a2"]), "the orphaned launcher exited", timeout_s=60)


@pytest.mark.heavy
def test_ctrl_c_stops_the_runs_on_the_workers_and_a_lost_scheduler_stops_the_sweep(tmp_path, dask_cluster):
    """A plan larger than the workers offer is refused, naming the resource. Ctrl-C
    while a run hangs on a worker: exit 130, nothing recorded, the run's processes
    stopped. The same command resumes (a fresh run id); the scheduler is then
    SIGKILLed: the sweep exits 3 saying so, still nothing half-recorded, and the
    worker stops the run it can no longer report."""
    sched = dask_cluster.scheduler()
    dask_cluster.worker("a", AUTOCAST_FAULTS=HANG)
    f = plan_file(tmp_path, ["left_turn"], ["single"], agent_timeout_s=600)
    out, shared = tmp_path / "sw", tmp_path / "shared"
    args = ("--file", str(f), "--out", str(out), "--cluster", dask_cluster.address, "--runs-dir", str(shared))
    too_big = autocast("sweep", *args, "--vehicles", "3", "--out", str(tmp_path / "big"))
    assert too_big.returncode == 2 and "error: cluster: no worker offers 3 vehicles" in too_big.stderr

    run_id = "left_turn-v2-c30-d0-single-s0-t1"
    proc = sweep_proc(*args)
    try:
        wait_until(lambda: (shared / run_id / "pids.json").exists() or proc.poll() is not None, "the run started",
                   timeout_s=240)
        assert proc.poll() is None, proc.stderr.read()
        proc.send_signal(signal.SIGINT)
    finally:
        err = finish(proc, timeout_s=120)
    assert proc.returncode == 130, err
    assert "the same command resumes" in err
    assert not (out / "results.jsonl").exists() or not lines(out / "results.jsonl")
    assert json.loads((shared / run_id / "outcome.json").read_text()).get("interrupted") is True
    assert not leftovers([run_id])

    proc = sweep_proc(*args)
    try:
        wait_until(lambda: (shared / f"{run_id}-a2" / "pids.json").exists() or proc.poll() is not None,
                   "the resumed run started", timeout_s=240)
        assert proc.poll() is None, proc.stderr.read()
        sched.kill()
    finally:
        err = finish(proc, timeout_s=120)
    assert proc.returncode == cluster.EXIT_CLUSTER_LOST, err
    assert "error: cluster: the scheduler went away" in err and "the same command resumes" in err
    assert not (out / "results.jsonl").exists() or not lines(out / "results.jsonl")
    stopped = shared / f"{run_id}-a2" / "outcome.json"
    wait_until(stopped.exists, "the worker stopped the run it cannot report", timeout_s=120)
    assert json.loads(stopped.read_text()).get("interrupted") is True
    wait_until(lambda: not leftovers([run_id, f"{run_id}-a2"]), "the stopped launcher exited", timeout_s=60)
