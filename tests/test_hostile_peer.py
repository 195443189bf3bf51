"""A hostile peer on a run's hub: thousands of malformed and wrong-typed payloads on
every data key, while a real run (launcher, recorder, world, proxy, agents as
processes) plays out in lock-step. The run must end judged exactly as without it, no
process may die, and each process's malformed counter must equal, key by key, what
the peer sent on the keys that process subscribes to."""

from __future__ import annotations

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

from deploy import table
from deploy.hostile import KEY_TYPES, NOT_DATA, key_functions
from deploy.procs import ProcSpec
from deploy.recorder import EGO_VID, McapLog, subscriptions
from deploy.run import Launcher, RunResult, open_hub, options_from, parse_args, warm_numba_caches
from protocol import keys
from protocol.codec import encode
from protocol.messages import Tick
from protocol.session import DropCounter, ZenohArgs, query_one, session_scope

FLAGS = ("--scenario", "left_turn", "--vehicles", "3", "--scheme", "autocast", "--duration", "2.5", "--seed", "2")
UNSTABLE = ("run_id", "wall_s", "realtime_factor", "run_dir", "mcap", "malformed", "malformed_dropped")


def _run(out: Path, run_id: str, hostile: bool) -> tuple[RunResult, dict[str, int | None]]:
    """One run as ``autocast run`` makes it, optionally with the hostile peer as one
    more process on its hub; returns the result and every process's exit code."""
    opts = options_from(parse_args(["--out", str(out), "--run-id", run_id, *FLAGS]), hub="")
    opts.run.log_dir.mkdir(parents=True)
    with ExitStack() as stack:
        session, endpoint = open_hub(stack, opts.run.run_dir)
        cfg = replace(opts.run, hub=endpoint)
        specs = table.processes(cfg)
        if hostile:
            vids = [str(v) for v in table.connected_vids(cfg.params)]
            specs.append(ProcSpec("hostile", "deploy.hostile", ("--run-id", run_id, "--connect", endpoint,
                                                                  "--vids", *vids, "--proxy")))
        launcher = Launcher(replace(opts, run=cfg), session, threading.Event(), specs=specs)
        result = launcher.run()
    return result, {name: proc.returncode for name, (_, proc) in launcher.procs.procs.items()}


# The module-scoped fixtures below start runs once per worker: keep the module on one.
pytestmark = pytest.mark.xdist_group("test_hostile_peer")


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The same run without and with the hostile peer, side by side (lock-step: the
    outcome does not depend on timing)."""
    out = tmp_path_factory.mktemp("hostile")
    warm_numba_caches(options_from(parse_args(["--run-id", "x", *FLAGS]), hub="").run.params)
    with ThreadPoolExecutor(2) as pool:
        calm, hostile = pool.submit(_run, out, "calm", False), pool.submit(_run, out, "hostile", True)
        return calm.result(timeout=300), hostile.result(timeout=300)


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


def test_every_process_counted_exactly_what_the_peer_sent_on_its_keys(runs):
    _, (hostile, _) = runs
    run, result = "hostile", hostile.result
    peer = _peer_report(Path(result["run_dir"]))
    sent = peer["sent"]
    assert sum(sent.values()) >= 3000
    # the precondition of exactness: every payload was routed before the run's last tick
    assert peer["confirmed_before_tick"] is not None and peer["confirmed_before_tick"] < result["ticks"], peer
    vids = table.connected_vids(options_from(parse_args(["--run-id", "x", *FLAGS]), hub="").run.params)
    listens = {  # which keys each process subscribes to (and decodes as their type)
        "world": [keys.cmd(run, v) for v in vids] + [keys.report(run, EGO_VID)],
        "proxy": [keys.world_tick(run), keys.world_outcome(run)] + [k for v in vids for k in (
            keys.net_ctrl_tx(run, v), keys.net_data_tx(run, v))],
        **{f"agent{v}": [keys.scan(run, v), keys.world_outcome(run), keys.net_ctrl_rx(run), keys.net_data_rx(run),
                         keys.net_emp_down(run, v)] for v in vids},
    }
    assert set(result["malformed"]) == set(listens)
    for name, ks in listens.items():
        assert result["malformed"][name]["by_key"] == {k: sent[k] for k in sorted(ks)}, name
    assert result["malformed_dropped"] == result["malformed"]["world"]["total"]


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
