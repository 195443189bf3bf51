"""A participant of a locked-down run (``--lock-down --wait-for NAME``): the access list
grants it its own token and nothing else, so the world starts as soon as it is up, and
whatever it puts in a vehicle's name never reaches anybody."""

from __future__ import annotations

import threading
from contextlib import ExitStack
from dataclasses import replace

import pytest

from deploy.launch import credentials, table
from processes.manager import ProcessManager, ProcSpec
from deploy.record.recorder import read_messages
from deploy.launch.run import Launcher, open_hub, options_from, parse_args, prepare
from protocol import keys, shm
from protocol.codec import decode
from protocol.messages import Command
from tests.acl_probe import FORGED_STEER_RAD

FLAGS = ("--scenario", "red_light", "--vehicles", "3", "--scheme", "autocast", "--duration", "1.0", "--seed", "1",
         "--lock-down", "--wait-for", "logger")


def test_the_access_list_grants_a_participant_its_token_and_nothing_else(tmp_path):
    cfg = options_from(parse_args(["--out", str(tmp_path), "--run-id", "acl", *FLAGS]), hub="").run
    user = credentials.participant_user("logger")
    assert credentials.own_keys(cfg, user) == ([], [keys.participant_alive("acl", "logger")])
    acl = credentials.access_control(cfg, credentials.users_of(cfg), [])
    granted = {rule for policy in acl["policies"] if user in policy["subjects"] for rule in policy["rules"]}
    assert granted == {"receive", "ask", f"token-{user}"}
    rules = {rule["id"]: rule for rule in acl["rules"]}
    assert rules[f"token-{user}"]["messages"] == ["liveliness_token"]
    assert rules[f"token-{user}"]["key_exprs"] == [keys.participant_alive("acl", "logger")]


@pytest.mark.heavy
def test_a_locked_down_run_starts_with_its_participant_who_cannot_put_on_any_vehicles_keys(tmp_path, run_factory):
    run_id = "locked-participant"
    opts = options_from(parse_args(["--out", str(tmp_path), "--run-id", run_id, *FLAGS]), hub="")
    opts.run.log_dir.mkdir(parents=True)
    opts = replace(opts, run=prepare(opts.run))
    with ExitStack() as stack:
        session, endpoint = open_hub(stack, opts.run.run_dir, locked=opts.run)  # writes every user's credentials
        shm_dir = stack.enter_context(shm.run_directory(run_id))
        cfg = replace(opts.run, hub=endpoint, shm_dir=str(shm_dir or ""))
        config = table.zenoh_config_path(cfg, credentials.participant_user("logger"))
        assert config.exists()
        vids = [str(v) for v in table.connected_vids(cfg.params)]
        specs = [*table.processes(cfg),
                 ProcSpec("logger", "tests.acl_probe", ("participant", endpoint, str(config), run_id, "logger", *vids))]
        launcher = Launcher(replace(opts, run=cfg), session, threading.Event(),
                            procs=ProcessManager(cfg.log_dir, run_factory), specs=specs)
        result = launcher.run()
    assert result.result is not None, result.failure
    assert result.result["lock_down"] is True
    logs = cfg.log_dir
    # the world waited for the participant's token and got it: it never waited out its startup timeout
    assert "never came up" not in (logs / "world.log").read_text()
    probe = (logs / "logger.log").read_text()
    assert "ready" in probe and f"forged {6 * len(vids)}" in probe, probe
    assert launcher.procs.procs["logger"][1].returncode == 0, probe
    # nothing it put reached the hub's subscribers: the recorder, which takes every key, has none of it
    commands, cmd_keys = [], {keys.cmd(run_id, int(v)) for v in vids}
    never = {key(run_id, int(v)) for v in vids for key in (keys.rejected, keys.alive)}
    with open(cfg.mcap_path, "rb") as f:
        for _, channel, message in read_messages(f):
            if channel.topic in cmd_keys:
                commands.append(decode(message.data, Command))
            assert channel.topic not in never, channel.topic
    assert commands and not [c for c in commands if c.steer_rad == pytest.approx(FORGED_STEER_RAD, abs=1e-9)]
    assert result.result["malformed_dropped"] == 0
    assert all(r["total"] == 0 for r in result.result["malformed"].values()), result.result["malformed"]
