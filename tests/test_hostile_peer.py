"""A hostile peer on a run's hub: thousands of malformed and wrong-typed payloads on
every data key, and forgeries of a compromised vehicle (vehicle 1's own credentials)
and of a stranger (bench/hostile.py ``Forger``): commands and reports in the ego's
name, control messages in its name claiming a phantom object of the highest reward,
forged object payloads, replays of earlier genuine messages. A real signed run
(launcher, recorder, world, proxy, agents as processes) plays out in lock-step. The
run must end judged exactly as without the peer, no process may die, each process's
malformed counter must equal, key by key, the garbage the peer sent on its keys, and
every forgery must be rejected, for its reason, by every process it reached. The peer
is slow on purpose (``--late-s``: it gets ready only after every agent and the proxy
are up): the world, told ``--wait-for hostile``, starts only once it is ready."""

from __future__ import annotations

import hashlib
import io
import json
import signal
import threading
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack
from dataclasses import replace
from pathlib import Path

import msgpack
import pytest
import zenoh
from mcap.reader import make_reader

from deploy.launch import table
from bench.hostile import KEY_TYPES, NOT_DATA, key_functions
from processes.factory import Factory
from processes.manager import ProcessManager, ProcSpec
from deploy.record.recorder import EGO_VID, McapLog, subscriptions
from deploy.launch.run import Launcher, RunResult, open_hub, options_from, parse_args, prepare
from deploy.launch.warmup import warm_numba_caches
from protocol import keys, shm
from protocol.codec import MalformedMessage, decode, encode
from protocol.messages import ChannelStats, CtrlBundle, DataBundle, Outcome, Rejected, Tick
from protocol.session import DropCounter, ZenohArgs, query_one, session_scope
from vehicle_agent.__main__ import fuses
from vehicle_agent.guard import CTRL_STREAM, DATA_STREAM
from world_server.sim import Simulation

FLAGS = ("--scenario", "left_turn", "--vehicles", "3", "--scheme", "autocast", "--duration", "2.5", "--seed", "2",
         "--sign")
UNSTABLE = ("run_id", "wall_s", "realtime_factor", "run_dir", "mcap", "malformed", "malformed_dropped", "rejected",
            "cpu_ms_per_tick")
LATE_S = "2.0"  # the peer's injected delay past the moment a world that did not wait for it would start
INSIDER, VICTIM = 1, 0  # the compromised vehicle (the occluder truck: it sends objects), the one it claims to be (the ego)


def _run(out: Path, run_id: str, hostile: bool, factory: Factory, via_shm: bool = True,
         ) -> tuple[RunResult, dict[str, int | None]]:
    """One run as ``autocast run`` makes it, its processes forked from ``factory``
    (``via_shm`` False: every payload over Zenoh, as across hosts), optionally with the
    hostile peer as one more process on its hub; returns the result and every process's
    exit code."""
    opts = options_from(parse_args(["--out", str(out), "--run-id", run_id, *FLAGS]), hub="")
    opts.run.log_dir.mkdir(parents=True)
    opts = replace(opts, run=prepare(opts.run))
    with ExitStack() as stack:
        session, endpoint = open_hub(stack, opts.run.run_dir)
        shm_dir = stack.enter_context(shm.run_directory(run_id)) if via_shm else ""  # as autocast run
        assert shm_dir is not None, "no /dev/shm"
        cfg = replace(opts.run, hub=endpoint, wait_for=("hostile",) if hostile else (), shm_dir=str(shm_dir))
        specs = table.processes(cfg)
        if hostile:
            vids = [str(v) for v in table.connected_vids(cfg.params)]
            specs.append(ProcSpec("hostile", "bench.hostile", (
                "--run-id", run_id, "--connect", endpoint, "--vids", *vids, "--proxy", "--forge", "--insider",
                str(table.v2x_credentials_path(cfg, INSIDER)), "--victim", str(VICTIM), "--name", "hostile",
                "--late-s", LATE_S)))
        launcher = Launcher(replace(opts, run=cfg), session, threading.Event(),
                            procs=ProcessManager(cfg.log_dir, factory), specs=specs)
        result = launcher.run()
    return result, {name: proc.returncode for name, (_, proc) in launcher.procs.procs.items()}


# The module-scoped fixtures below start runs once per worker: keep the module on one.
pytestmark = pytest.mark.xdist_group("test_hostile_peer")


@pytest.fixture(scope="module")
def runs(tmp_path_factory, run_factory):
    """The same run without and with the hostile peer, side by side (lock-step: the
    outcome does not depend on timing)."""
    out = tmp_path_factory.mktemp("hostile")
    warm_numba_caches(options_from(parse_args(["--run-id", "x", *FLAGS]), hub="").run.params)
    with ThreadPoolExecutor(2) as pool:
        calm, hostile = (pool.submit(_run, out, "calm", False, run_factory),
                         pool.submit(_run, out, "hostile", True, run_factory))
        return calm.result(timeout=300), hostile.result(timeout=300)


@pytest.fixture(scope="module")
def zenoh_run(tmp_path_factory, run_factory):
    """The hostile run once more with every payload over Zenoh, as across hosts."""
    return _run(tmp_path_factory.mktemp("hostile-zenoh"), "hostile-zenoh", True, run_factory, via_shm=False)


def _vehicles() -> tuple[list[int], set[int]]:
    """The run's connected vehicles, and those that take the data bundle: a vehicle that
    fuses nothing does not (``V2VLink``'s ``receives_data``)."""
    params = options_from(parse_args(["--run-id", "x", *FLAGS]), hub="").run.params
    sim = Simulation(params)
    vids = table.connected_vids(params)
    return vids, {v for v in vids if fuses(sim.mission(v), reports=v == EGO_VID)}


def _peer_report(run_dir: Path) -> dict:
    lines = [ln for ln in (run_dir / "logs" / "hostile.log").read_text().splitlines() if ln.startswith("hostile_peer ")]
    assert lines, "the hostile peer printed no report"
    return json.loads(lines[-1].split(" ", 1)[1])


def test_the_peer_covers_every_data_key():
    """A key added to protocol/keys.py without a message type here would go unfuzzed."""
    assert {fn for fn in key_functions() if fn not in NOT_DATA} == set(KEY_TYPES)


@pytest.mark.heavy
def test_the_run_ends_judged_as_without_the_hostile_peer_and_nobody_dies(runs):
    (calm, calm_codes), (hostile, codes) = runs
    assert calm.result is not None and hostile.result is not None, (calm.failure, hostile.failure)
    assert hostile.exit_code == calm.exit_code
    assert {k: v for k, v in hostile.result.items() if k not in UNSTABLE} == \
        {k: v for k, v in calm.result.items() if k not in UNSTABLE}
    assert hostile.result["dead_agents"] == {} and hostile.result.get("interrupted") is None
    for res, exits in ((calm, calm_codes), (hostile, codes)):
        assert set(res.result["malformed"]) == {n for n in exits if n not in ("recorder", "hostile")}  # all finished
        logs = Path(res.result["run_dir"]) / "logs"
        assert "wrote " in (logs / "recorder.log").read_text()  # the MCAP was finalized
        # 0, or SIGINT from the launcher's shutdown when a finished process was still
        # tearing down after its settle time (a loaded machine): never a crash
        assert set(exits.values()) <= {0, -signal.SIGINT}, exits
    assert all(r["total"] == 0 for r in calm.result["malformed"].values()), calm.result["malformed"]
    assert all(r["total"] == 0 for r in calm.result["rejected"].values()), calm.result["rejected"]


def test_the_world_waited_for_the_late_peer(runs):
    """The peer got ready only after the run's agents and proxy (and LATE_S more): the
    world, told --wait-for hostile, played no tick before, so the peer saw tick 0 and
    forged from there (what it forged landed: the tests below)."""
    _, (hostile, _) = runs
    logs = Path(hostile.result["run_dir"]) / "logs"
    assert "fault injection: every agent and the proxy are up" in (logs / "hostile.log").read_text()
    world_log = (logs / "world.log").read_text()
    assert "also up before tick 0: hostile, proxy" in world_log and "3 of 3 agents up; starting" in world_log
    peer = _peer_report(Path(hostile.result["run_dir"]))
    assert peer["first_tick"] == 0, peer["first_tick"]
    assert sum(n for per in peer["forged"].values() for n in per.values()) > 0


@pytest.mark.parametrize("via_shm", [True, False], ids=["shared-memory", "zenoh"])
def test_every_process_counted_exactly_what_the_peer_sent_on_its_keys(via_shm, request):
    hostile, _ = request.getfixturevalue("runs")[1] if via_shm else request.getfixturevalue("zenoh_run")
    result = hostile.result
    run = result["run_id"]
    peer = _peer_report(Path(result["run_dir"]))
    sent = peer["sent"]
    assert sum(sent.values()) >= 3000
    # the precondition of exactness: every payload was routed before the run's last tick
    assert peer["confirmed_before_tick"] is not None and peer["confirmed_before_tick"] < result["ticks"], peer
    vids, takes_data = _vehicles()
    into = keys.in_shm if via_shm else (lambda key: key)  # with shared memory an agent takes the notices only
    data_rx = {v: [into(keys.net_data_rx(run))] if v in takes_data else [] for v in vids}
    assert [] in data_rx.values() and any(data_rx.values()), "the run has no vehicle of one kind"
    listens = {  # which keys each process subscribes to (and decodes as their type)
        "world": [keys.cmd(run, v) for v in vids] + [keys.report(run, EGO_VID)],
        "proxy": [keys.world_tick(run), keys.world_outcome(run)] + [k for v in vids for k in (
            keys.net_ctrl_tx(run, v), keys.net_data_tx(run, v))],
        **{f"agent{v}": [into(keys.scan(run, v)), keys.world_outcome(run), into(keys.net_ctrl_rx(run)),
                         *data_rx[v], keys.net_emp_down(run, v)] for v in vids},
    }
    assert set(result["malformed"]) == set(listens)
    signed = peer["signed_envelope"]  # a valid Signed envelope the world's verifier rejects: no certificate of ours
    verified = {keys.cmd(run, v) for v in vids} | {keys.report(run, EGO_VID)}
    for name, ks in listens.items():
        want = {k: sent[k] - (signed[k] if k in verified else 0) for k in sorted(ks)}
        assert result["malformed"][name]["by_key"] == {k: n for k, n in want.items() if n}, name
    assert result["malformed_dropped"] == result["malformed"]["world"]["total"]
    world = result["rejected"]["world"]["by_stream"]
    for key in verified:
        want = dict(peer["forged"].get(key, {}))
        if signed[key]:
            want["bad_certificate"] = want.get("bad_certificate", 0) + signed[key]
        assert world.get(key, {}) == want, key


def _messages(mcap: str, topics: list[str]):
    """(topic, message) of every message on ``topics`` that decodes (the peer's garbage does not)."""
    with open(mcap, "rb") as f:
        for _, channel, message in make_reader(f).iter_messages(topics=topics):
            try:
                yield channel.topic, decode(message.data)
            except MalformedMessage:
                continue


def test_every_forgery_was_rejected_for_its_reason_by_every_vehicle_it_reached(runs):
    """What each agent was owed, read from the bundles the proxy published: each forged
    control message in the insider's slot, at every receiver that heard that slot; each
    forged payload, at every receiver that decoded it. Each agent's counts, at its exit
    and in its last ``Rejected`` message in the MCAP, are exactly that; the world's are
    in its ``Outcome`` in the MCAP too; the replayed control messages died at the medium."""
    _, (hostile, _) = runs
    run, result = "hostile", hostile.result
    peer = _peer_report(Path(result["run_dir"]))
    frames = peer["frames"]  # "<tick>:<sha256>" -> reason
    owed: dict[str, dict[str, dict[str, int]]] = {}

    def owe(receiver: int, stream: str, reason: str) -> None:
        per = owed.setdefault(f"agent{receiver}", {}).setdefault(stream, {})
        per[reason] = per.get(reason, 0) + 1

    _, takes_data = _vehicles()
    relayed: dict[str, set[str]] = {CTRL_STREAM: set(), DATA_STREAM: set()}
    for topic, b in _messages(result["mcap"], [keys.net_ctrl_rx(run), keys.net_data_rx(run)]):
        if topic == keys.net_ctrl_rx(run) and isinstance(b, CtrlBundle):  # not the peer's garbage of another type
            for s, raw in enumerate(b.messages):
                reason = frames.get(f"{b.tick}:{hashlib.sha256(raw).hexdigest()}")
                for receiver in (b.receivers[b.heard[:, s]].tolist() if reason else []):
                    owe(receiver, CTRL_STREAM, reason)
                    relayed[CTRL_STREAM].add(reason)
        elif topic == keys.net_data_rx(run) and isinstance(b, DataBundle):
            for t, r in enumerate(b.receptions):
                reason = frames.get(f"{b.tick}:{hashlib.sha256(r.payload).hexdigest()}")
                for receiver in (b.receivers[b.decoded[:, t]].tolist() if reason else []):
                    if receiver in takes_data:  # a vehicle that fuses nothing does not take the bundle
                        owe(receiver, DATA_STREAM, reason)
                    relayed[DATA_STREAM].add(reason)
    assert relayed == {CTRL_STREAM: {"unsigned", "bad_certificate", "wrong_key"},
                       DATA_STREAM: {"bad_signature", "wrong_key", "replayed"}}, relayed  # the test tested something
    agents = {n: r["by_stream"] for n, r in result["rejected"].items() if n != "world"}
    assert agents == {n: owed.get(n, {}) for n in agents}
    last = {}
    vids = table.connected_vids(options_from(parse_args(["--run-id", "x", *FLAGS]), hub="").run.params)
    mine = {keys.world_outcome(run): Outcome, keys.net_stats(run): ChannelStats,
            **{keys.rejected(run, v): Rejected for v in vids}}
    for topic, msg in _messages(result["mcap"], list(mine)):
        if not isinstance(msg, mine[topic]):  # the peer's valid messages of another type
            continue
        if isinstance(msg, Rejected):
            last[f"agent{msg.vid}"] = msg.counts["by_stream"]
        elif isinstance(msg, Outcome):
            last["world"] = msg.result["rejected"]["by_stream"]
        else:
            last["proxy late"] = msg.stats["late"]
    assert {n: last.get(n, {}) for n in agents} == agents
    assert last["world"] == result["rejected"]["world"]["by_stream"]
    assert last["proxy late"] >= peer["forged"][keys.net_ctrl_tx(run, VICTIM)]["late"] > 0


def test_the_recorder_kept_every_payload_it_could_not_read_on_a_malformed_channel(runs):
    _, (hostile, _) = runs
    run, peer = "hostile", _peer_report(Path(hostile.result["run_dir"]))
    with open(hostile.result["mcap"], "rb") as f:
        summary = make_reader(f).get_summary()
    counts = summary.statistics.channel_message_counts
    malformed = {ch.topic: counts.get(cid, 0) for cid, ch in summary.channels.items()
                 if ch.metadata.get("malformed") == "true"}
    exprs = [zenoh.KeyExpr(e) for e in subscriptions(run, "ego")]
    recorded = {k: n for k, n in peer["bad_envelope"].items() if any(e.intersects(zenoh.KeyExpr(k)) for e in exprs)}
    assert malformed == recorded


def test_the_recorder_keeps_a_message_whose_sim_time_mcap_cannot_hold():
    """A valid envelope with t_sim_s = 1e300, inf or NaN (the hostile peer sent some):
    publish time falls back to the log time instead of crashing the recorder."""
    log = McapLog(io.BytesIO(), {})
    for t_sim_s in (1e300, float("inf"), float("nan"), -1.0, 2.0):
        log.write(keys.world_tick("r"), msgpack.packb([Tick.TYPE_ID, Tick.VERSION, 0, t_sim_s, [], []]), 5)
    log.finish()
    assert log.stats.messages == 5 and log.stats.malformed == 0


class _SignallingDrops(DropCounter):
    def __init__(self) -> None:
        super().__init__()
        self.dropped = threading.Event()

    def add(self, key: str, err: Exception) -> None:
        super().add(key, err)
        self.dropped.set()


def test_a_strangers_garbage_reply_to_a_query_is_dropped_and_the_real_one_taken(hub):
    """Agents ask the world for the map and their mission by query. A stranger's
    queryable on the same key answers garbage first (the world's answers only once the
    garbage was counted): the agent takes the world's, and counts the other."""
    key, real = keys.world_map("q"), Tick(3, 0.3, [0, 1], [])
    drops = _SignallingDrops()

    def world(query: zenoh.Query) -> None:
        assert drops.dropped.wait(30.0), "the stranger's reply never reached the asker"
        query.reply(key, encode(real))

    with session_scope(ZenohArgs(listen=(hub,))) as router, session_scope(ZenohArgs(connect=(hub,))) as stranger, \
            session_scope(ZenohArgs(connect=(hub,))) as agent:
        entities = [router.declare_queryable(key, world),
                    stranger.declare_queryable(key, lambda q: q.reply(key, b"\xc1garbage")),
                    stranger.liveliness().declare_token("q/stranger")]  # after its queryable: the hub knows both
        seen = threading.Event()
        watch = agent.liveliness().declare_subscriber("q/stranger", lambda s: seen.set(), history=True)
        assert seen.wait(30.0)
        assert query_one(agent, key, Tick, timeout_s=30.0, drops=drops) == real
        assert drops.by_key() == {key: 1}
        for entity in (*entities, watch):
            entity.undeclare()
