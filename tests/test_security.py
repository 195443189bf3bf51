"""Authenticated V2X messages (protocol/security.py), in one process: each way a message
can fail is dropped and counted under its reason, and only what the vehicle signed gets
through; the agent's bundle checks (vehicle_agent/guard.py); the channel proxy's slots
(what it plays, what it relays); the Zenoh access-control list the launcher writes.
Cross-process behaviour is in test_hostile_peer.py and test_multihost.py."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from channel_proxy.proxy import read_frame
from deploy.launch import credentials, table
from deploy.launch.run import build_parser, options_from
from protocol import keys
from protocol.codec import MalformedMessage, decode, encode
from protocol.messages import Command, ControlMsg, CtrlBundle, DataTx, ObjectMap, Pose, Reception, Signed
from protocol.security import (VERDICTS_DIR, Authority, Credentials, PayloadCheck, Rejections, Signer, Verdicts,
                               VerdictTable, Verifier, with_digests)
from protocol.session import DropCounter
from vehicle_agent.agreement import HeardControl
from vehicle_agent.guard import CTRL_STREAM, DATA_STREAM, Guard
from vehicle_agent.payload import ObjectPayload, encode_object, header_of

RUN = "sec"


@pytest.fixture(scope="module")
def authority() -> Authority:
    return Authority(RUN)


@pytest.fixture(scope="module")
def creds(authority) -> dict[int, Credentials]:
    return {vid: authority.issue(vid, 0.0, 100.0) for vid in range(3)}


def verifier(authority) -> Verifier:
    return Verifier(authority.public_key, RUN)


def cmd(vid: int, tick: int = 5) -> Command:
    return Command(tick, tick * 0.1, vid, -2.0, 0.1)


def reasons(v: Verifier) -> dict[str, int]:
    return v.rejections.summary()["by_reason"]


def test_a_message_signed_by_its_vehicle_opens_to_what_it_signed(authority, creds):
    v = verifier(authority)
    raw = Signer(creds[1]).seal(cmd(1))
    assert v.open(raw, Command, 1, "k") == cmd(1)
    assert v.rejections.summary()["total"] == 0


def test_each_forgery_is_dropped_and_counted_under_its_reason(authority, creds):
    v = verifier(authority)
    stranger = Signer(Authority(RUN).issue(1, 0.0, 100.0))  # right run id and vehicle, another authority
    other_run = Signer(Authority("other").issue(1, 0.0, 100.0))
    expired = Signer(authority.issue(1, 0.0, 0.2))  # valid until 0.2 s of sim time; the command is at 0.5 s
    genuine = decode(Signer(creds[1]).seal(cmd(1)), Signed)
    tampered = encode(Signed(5, 0.5, genuine.certificate, encode(Command(5, 0.5, 1, 3.0, 0.0)), genuine.signature))
    relabelled = encode(Signed(6, 0.5, genuine.certificate, genuine.body, genuine.signature))
    cases = [(encode(cmd(1)), "unsigned"), (stranger.seal(cmd(1)), "bad_certificate"),
             (other_run.seal(cmd(1)), "bad_certificate"), (expired.seal(cmd(1)), "bad_certificate"),
             (Signer(creds[2]).seal(cmd(1)), "wrong_key"),  # vehicle 2's key, on vehicle 1's key expression
             (Signer(creds[2]).seal(cmd(2)), "wrong_key"),  # 2's own command, on 1's key expression
             (tampered, "bad_signature"), (relabelled, "bad_signature")]
    for raw, reason in cases:
        before = dict(reasons(v))
        assert v.open(raw, Command, 1, keys.cmd(RUN, 1)) is None, reason
        after = reasons(v)
        assert after.get(reason, 0) == before.get(reason, 0) + 1, (reason, after)
    assert v.open(Signer(creds[1]).seal(cmd(1, 3)), Command, 1, "k", fresh=lambda m: m.tick > 4) is None
    assert reasons(v)["replayed"] == 1
    assert v.rejections.summary()["by_stream"][keys.cmd(RUN, 1)]["bad_certificate"] == 3


def test_garbage_is_malformed_not_a_rejection(authority):
    v = verifier(authority)
    with pytest.raises(MalformedMessage):
        v.open(b"\xc1 not a message", Command, 1, "k")
    with pytest.raises(MalformedMessage):  # a valid message of another type
        v.open(encode(DataTx(0, 0.0, 1, [])), Command, 1, "k")
    assert v.rejections.summary()["total"] == 0


@given(st.data())
def test_no_single_flipped_byte_of_a_signed_message_gets_through(authority, creds, data):
    """Whatever byte of the envelope changes, the receiver either gets exactly what the
    vehicle signed (a change msgpack reads the same) or nothing."""
    raw = bytearray(Signer(creds[1]).seal(cmd(1)))
    i = data.draw(st.integers(0, len(raw) - 1))
    raw[i] ^= data.draw(st.integers(1, 255))
    try:
        got = verifier(authority).open(bytes(raw), Command, 1, "k")
    except MalformedMessage:
        return
    assert got is None or got == cmd(1)


def test_credentials_survive_their_file(tmp_path, creds):
    path = tmp_path / "agent1.v2x.json"
    creds[1].save(path)
    assert Credentials.load(path) == creds[1]
    assert path.stat().st_mode & 0o777 == 0o600


# ---------------------------------------------------------------------------- payloads


def payload(sender: int, oid: int, tick: int, shift: float = 0.0) -> bytes:
    pts = np.array([[1.0 + shift, 2.0, 0.5], [1.5, 2.5, 0.7]], np.float32)
    return encode_object(ObjectPayload(sender, oid, tick, tick * 0.1, Pose(3.0, 4.0, 0.2), 1.9,
                                       pts.mean(axis=0), np.zeros(2, np.float32), pts))


def control(vid: int, tick: int, oids: list[int]) -> ControlMsg:
    n = len(oids)
    om = ObjectMap(np.array(oids, np.int64), np.full(n, 76, np.int64), np.zeros((n, 2), np.float32),
                   np.array([9], np.int64), np.zeros((n, 1), np.float32), np.ones((n, 1), np.float32))
    return ControlMsg(tick, tick * 0.1, vid, Pose(0.0, 0.0, 0.0), 0.0, np.zeros((2, 3), np.float32), om,
                      np.zeros(0, np.int64))


def test_a_payload_is_checked_against_its_senders_signed_digest():
    r = Rejections()
    check = PayloadCheck(7, r)
    good = {10: payload(1, 10, 7), 11: payload(1, 11, 7)}
    check.vouch(with_digests(control(1, 7, [10, 11]), good))
    assert check.check(1, good[10], header_of(good[10]))
    cases = [(2, payload(2, 5, 7), "unsigned"),  # vehicle 2 vouched for nothing this interval
             (1, payload(2, 10, 7), "wrong_key"),  # 2's object in 1's slot
             (1, payload(1, 11, 6), "replayed"),  # 1's object of the interval before
             (1, payload(1, 11, 7, shift=0.5), "bad_signature"),  # points moved
             (1, payload(1, 12, 7), "bad_signature"),  # an object 1 never listed
             (1, b"ACOB" + bytes(10), "bad_signature")]  # no payload at all
    for sender, raw, reason in cases:
        assert not check.check(sender, raw, header_of(raw)), reason
    assert r.summary()["by_reason"] == {"bad_signature": 3, "replayed": 1, "unsigned": 1, "wrong_key": 1}
    assert check.check(1, good[11], header_of(good[11]))
    assert check.check(1, good[10], header_of(good[10]))  # sent twice in the interval: still what 1 signed


def test_bytes_a_sender_signed_that_are_no_payload_pass_for_the_decoder_to_drop():
    """A liar vouching for garbage: authentic, so not a rejection; the decoder drops it as
    malformed, as in a plain run. The same bytes unvouched are a bad signature."""
    r = Rejections()
    check = PayloadCheck(7, r)
    junk, negative = b"ACOB" + bytes(10), payload(1, 12, -1)
    assert header_of(junk) is None and header_of(negative) is None
    check.vouch(with_digests(control(1, 7, [10, 12]), {10: junk, 12: negative}))
    assert check.check(1, junk, None) and check.check(1, negative, None)
    assert not check.check(1, b"ACOB" + bytes(11), None)
    assert r.summary()["by_reason"] == {"bad_signature": 1}


def test_the_agent_takes_only_its_row_and_one_verified_message_per_sender(authority, creds):
    """The bundle's row for vehicle 0: vehicle 1's message, then a forgery in 1's slot
    naming 1 (signed by 2), then 2's message; vehicle 2's slot also holds a message
    nobody heard. Payloads of 1 and of 2 (unheard: vouched by 2's slot in the bundle)."""
    guard = Guard(creds[0], DropCounter())
    p1, p2 = payload(1, 10, 4), payload(2, 20, 4)
    m1 = with_digests(control(1, 4, [10]), {10: p1})
    m2 = with_digests(control(2, 4, [20]), {20: p2})
    frames = [Signer(creds[1]).seal(m1), Signer(creds[2]).seal(m1), Signer(creds[2]).seal(m2)]
    bundle = CtrlBundle(4, 0.4, np.array([1, 1, 2], np.int64), np.array([0, 1, 2], np.int64),
                        np.array([[True, True, False], [False, False, True], [True, True, False]]), frames)
    heard, check = guard.heard(bundle, 4)
    assert [encode(m) for m in heard] == [encode(m1)]
    assert guard.rejections.summary()["by_stream"] == {CTRL_STREAM: {"wrong_key": 1}}
    forged = payload(1, 10, 4, shift=1.0)
    got = guard.payloads([Reception(1, 10, 0.01, p1), Reception(2, 20, 0.02, p2), Reception(1, 10, 0.03, forged)],
                         check, bundle)
    assert got == [p1, p2]
    assert guard.rejections.summary()["by_stream"][DATA_STREAM] == {"bad_signature": 1}


def test_a_vehicle_that_signs_two_control_messages_in_an_interval_is_heard_once(authority, creds):
    """Vehicle 1 (compromised, its own key) signs a message whose digests do not fit its
    object map, so it vouches for no payload, then a second one: the first is heard, the
    second is a replay, as for any second message of a sender (the schedule gets one
    message per vehicle, or the agreement sees vehicle 1 twice)."""
    guard = Guard(creds[0], DropCounter())
    p1 = payload(1, 10, 4)
    unfit = replace(with_digests(control(1, 4, [10]), {10: p1}), digests=np.zeros((0, 16), np.uint8))
    fit = with_digests(control(1, 4, [10]), {10: p1})
    bundle = CtrlBundle(4, 0.4, np.array([1, 1], np.int64), np.array([0], np.int64), np.array([[True, True]]),
                        [Signer(creds[1]).seal(unfit), Signer(creds[1]).seal(fit)])
    heard, check = guard.heard(bundle, 4)
    assert [encode(m) for m in heard] == [encode(unfit)]
    assert guard.rejections.summary()["by_stream"] == {CTRL_STREAM: {"replayed": 1}}
    assert guard.payloads([Reception(1, 10, 0.01, p1)], check, bundle) == []  # vouched by nothing it signed first


# ---------------------------------------------------------------------------- shared on a host


def _forgeries_bundle(authority, creds) -> tuple[CtrlBundle, dict[int, bytes], bytes]:
    """Tick 4, heard by vehicles 0 and 3. Slot 1: vehicle 1's message, a copy of it
    signed by vehicle 2, a second message of 1's; slot 2: vehicle 2's message, its body
    changed under its signature, 2's message of tick 3; slot 3: a plain message. Also
    the payloads they vouch for, and one with its points moved."""
    p1, p2 = payload(1, 10, 4), payload(2, 20, 4)
    m1, m2 = with_digests(control(1, 4, [10]), {10: p1}), with_digests(control(2, 4, [20]), {20: p2})
    s1, s2 = Signer(creds[1]), Signer(creds[2])
    genuine = decode(s2.seal(m2), Signed)
    changed_body = encode(with_digests(control(2, 4, [20, 21]), {20: p2, 21: p2}))
    frames = [s1.seal(m1), s2.seal(m1), s1.seal(with_digests(control(1, 4, [11]), {11: p1})),
              s2.seal(m2), encode(replace(genuine, body=changed_body)),
              s2.seal(with_digests(control(2, 3, [20]), {20: payload(2, 20, 3)})), encode(control(3, 4, []))]
    bundle = CtrlBundle(4, 0.4, np.array([1, 1, 1, 2, 2, 2, 3], np.int64), np.array([0, 3], np.int64),
                        np.ones((2, len(frames)), bool), frames)
    return bundle, {10: p1, 20: p2}, payload(1, 10, 4, shift=1.0)


def test_vehicles_on_a_host_share_what_they_found_authentic_and_check_the_rest_alike(authority, creds, tmp_path):
    """A vehicle checking alone, the first on the host and the second (who finds the
    first's table) hear the same messages, drop the same forgeries for the same reasons
    and take the same payloads; the table lists only the two authentic frames, and the
    second reads their messages from it in part (HeardControl), as without signing."""
    bundle, payloads, forged = _forgeries_bundle(authority, creds)
    tmp_path.chmod(0o700)
    verdicts = Verdicts.open(tmp_path)
    alone = Guard(creds[0], DropCounter())
    first = Guard(creds[0], DropCounter(), verdicts)
    second = Guard(authority.issue(3, 0.0, 100.0), DropCounter(), Verdicts.open(tmp_path))
    received = [Reception(1, 10, 0.01, payloads[10]), Reception(2, 20, 0.02, payloads[20]),
                Reception(1, 10, 0.03, forged)]
    for guard in (alone, first, second):
        heard, check = guard.heard(decode(encode(bundle)), 4)
        assert [(m.vid, m.tick) for m in heard] == [(1, 4), (2, 4)]
        assert guard.payloads(received, check, bundle) == [payloads[10], payloads[20]]
        assert guard.rejections.summary()["by_stream"] == {
            CTRL_STREAM: {"bad_signature": 1, "replayed": 2, "unsigned": 1, "wrong_key": 1},
            DATA_STREAM: {"bad_signature": 1}}
    assert all(isinstance(m, HeardControl) for m in heard)
    tables = list((tmp_path / VERDICTS_DIR / "4").iterdir())
    assert len(tables) == 1 and VerdictTable(str(tables[0])).places() == [0, 3]


def test_what_a_table_lists_counts_only_for_its_own_bundle(authority, creds, tmp_path):
    """A bundle whose first frame is vehicle 1's message with another body under the
    same signature is another bundle: its table is its own, and the frame is verified,
    and refused, as if nobody had checked the genuine one."""
    tmp_path.chmod(0o700)
    p1 = payload(1, 10, 4)
    genuine = Signer(creds[1]).seal(with_digests(control(1, 4, [10]), {10: p1}))
    env = decode(genuine, Signed)
    other = encode(replace(env, body=encode(with_digests(control(1, 4, [10, 11]), {10: p1, 11: p1}))))

    def bundle(frame: bytes) -> CtrlBundle:
        return CtrlBundle(4, 0.4, np.array([1], np.int64), np.array([0, 2], np.int64), np.array([[True], [True]]),
                          [frame])

    assert [m.vid for m in Guard(creds[0], DropCounter(), Verdicts.open(tmp_path)).heard(bundle(genuine), 4)[0]] == [1]
    guard = Guard(creds[2], DropCounter(), Verdicts.open(tmp_path))
    assert guard.heard(bundle(other), 4)[0] == []
    assert guard.rejections.summary()["by_reason"] == {"bad_signature": 1}


def test_verdicts_are_shared_only_where_nobody_else_may_write(tmp_path):
    tmp_path.chmod(0o777)
    assert Verdicts.open(tmp_path) is None
    tmp_path.chmod(0o700)
    assert Verdicts.open(tmp_path) is not None
    assert (tmp_path / VERDICTS_DIR).stat().st_mode & 0o777 == 0o700


def test_a_tables_record_is_taken_whole_and_in_its_place_or_not_at_all(tmp_path):
    """A record read while it is being written (part of it still zero) or found at
    another frame's place lists nothing; a whole one lists its frame's span."""
    path = str(tmp_path / "4" / "bundle")
    for _ in range(2):  # a second receiver writes the same record
        with VerdictTable(path) as table:
            table.put(3, 100, 200)
            whole = table._record(5, 7, 9)
    with open(path, "r+b") as f:
        for place, record in ((5, whole[:8] + bytes(8)), (6, bytes(8) + whole[8:]), (7, whole),
                              (8, whole[:4] + bytes(4) + whole[8:])):
            f.seek(VerdictTable.RECORD * place)
            f.write(record)
    with VerdictTable(path) as table:
        assert table.places() == [3] and table.get(3) == (100, 200) and table.get(7) is None
        assert table.has(3, 100, 200) and not table.has(3, 100, 201) and not table.has(4, 100, 200)
        table.claim(9)  # a mark is no record
    with VerdictTable(path, 10) as table:
        assert table.places() == [3] and table.claimed(9) and not table.claimed(3)
    with VerdictTable(str(tmp_path / "none")) as table:
        assert table.places() == []


def test_frames_another_vehicle_is_checking_are_checked_after_the_others_alike(authority, creds, tmp_path):
    """Every frame of the bundle marked as being checked by a vehicle that never lists
    it (it stalled, or they are forgeries): a vehicle checks the others first, then
    these itself, a sender's frames in their order, and hears, drops and takes exactly
    what a vehicle checking alone does."""
    bundle, payloads, forged = _forgeries_bundle(authority, creds)
    tmp_path.chmod(0o700)
    verdicts = Verdicts.open(tmp_path)
    with verdicts.table(4, bundle.messages) as table:
        for at in range(len(bundle.messages)):
            table.claim(at)
    received = [Reception(1, 10, 0.01, payloads[10]), Reception(2, 20, 0.02, payloads[20]),
                Reception(1, 10, 0.03, forged)]
    alone, shared = Guard(creds[0], DropCounter()), Guard(creds[0], DropCounter(), verdicts)
    for guard in (alone, shared):
        heard, check = guard.heard(decode(encode(bundle)), 4)
        assert [(m.vid, m.tick) for m in heard] == [(1, 4), (2, 4)]
        assert guard.payloads(received, check, bundle) == [payloads[10], payloads[20]]
    assert shared.rejections.summary() == alone.rejections.summary()
    with verdicts.table(4, bundle.messages) as table:
        assert table.places() == [0, 3]


# ---------------------------------------------------------------------------- the medium reads, never checks


def test_the_proxy_reads_a_signed_frame_through_its_envelope(creds):
    m = control(1, 3, [])
    assert encode(read_frame(Signer(creds[2]).seal(m), ControlMsg)) == encode(m)  # whoever signed: not checked
    assert encode(read_frame(encode(m), ControlMsg)) == encode(m)
    with pytest.raises(MalformedMessage):
        read_frame(encode(cmd(1)), ControlMsg)


# ---------------------------------------------------------------------------- Zenoh's access-control list


def test_the_acl_lets_each_process_put_only_on_its_own_keys(tmp_path):
    opts = options_from(build_parser().parse_args(["--vehicles", "3", "--out", str(tmp_path), "--run-id", "acl",
                                                   "--lock-down"]), hub="tcp/127.0.0.1:1")
    cfg = opts.run
    names = [s.name for s in table.processes(cfg)]
    acl = credentials.access_control(cfg, names + [credentials.LAUNCHER], ["router-a"])
    rules = {r["id"]: r for r in acl["rules"]}
    puts = {p["subjects"][0]: rules[p["rules"][0]]["key_exprs"] for p in acl["policies"]
            if p["rules"][0].startswith("own-")}
    assert acl["default_permission"] == "deny"
    assert puts["agent1"] == [keys.cmd("acl", 1), keys.report("acl", 1), keys.rejected("acl", 1),
                              keys.net_ctrl_tx("acl", 1), keys.net_data_tx("acl", 1), keys.net_emp_up("acl", 1)]
    assert keys.net_ctrl_rx("acl") in puts["proxy"] and keys.scan("acl", "*") in puts["world"]
    assert "recorder" not in puts and credentials.LAUNCHER not in puts
    assert all("put" not in r["messages"] for r in acl["rules"] if r["id"] in ("ask",))
    paths = credentials.lock_down(cfg, {"router-a": "10.0.0.1"})
    users = (table.credentials_dir(cfg) / "zenoh-users.txt").read_text().splitlines()
    assert sorted(u.split(":")[0] for u in users) == sorted(names + [credentials.LAUNCHER, "router-a"])
    agent = json.loads(paths["agent1"].read_text())["transport"]["auth"]["usrpwd"]
    assert agent["user"] == "agent1" and f"agent1:{agent['password']}" in users
    assert json.loads(paths["router-a"].read_text())["access_control"] == acl
    assert all(p.stat().st_mode & 0o777 == 0o600 for p in paths.values())
    assert table.agent_args(cfg, 1)[table.agent_args(cfg, 1).index("--zenoh-config") + 1] == str(paths["agent1"])


def test_the_acl_of_a_map_of_several_domains_has_each_domains_net_keys(tmp_path):
    """corridor3: domains 0, 1, 2 on channels 0, 1, 0; an agent may send in each, the
    proxy deliver in each (a locked-down run of it was stuck at tick 0 without them)."""
    cfg = options_from(build_parser().parse_args(["--scenario", "corridor3", "--vehicles", "3", "--out", str(tmp_path),
                                                   "--run-id", "acl", "--lock-down"]), hub="tcp/127.0.0.1:1").run
    puts = {name: credentials.own_keys(cfg, name)[0] for name in ("agent2", "proxy")}
    net = [(0, 0), (1, 1), (0, 2)]
    assert [k for k in puts["agent2"] if "/net/" in k] == [
        k for c, d in net for k in (keys.net_ctrl_tx("acl", 2, c, d), keys.net_data_tx("acl", 2, c, d))] + [
        keys.net_emp_up("acl", 2)]
    for c, d in net:
        assert {keys.net_ctrl_rx("acl", c, d), keys.net_data_rx("acl", c, d)} <= set(puts["proxy"])
    assert "ac/acl/net/c1/d1/data/tx/2" in puts["agent2"] and "ac/acl/net/c1/d1/data/rx" in puts["proxy"]


def test_the_world_takes_each_report_once_and_a_late_one_is_no_replay(authority):
    """The ego's reports, verified, reach the world's bookkeeping in order: one of a tick
    already accepted (or older) is a replay; one the world never had, of a tick it has
    moved past (a slow ego), is stale but honest, not counted as an attack."""
    from protocol.messages import AgentReport
    from world_server.scenarios import ScenarioParams
    from world_server.server import WorldServer
    from world_server.sim import Simulation

    sim = Simulation(ScenarioParams(scenario="left_turn", vehicles=3, seed=0, delta_s=0.0))
    server = WorldServer(sim, None, RUN, ego_reports=True, verifier=verifier(authority))
    key = keys.report(RUN, 0)

    def report(tick: int) -> AgentReport:
        return AgentReport(tick, tick * 0.1, 0, np.zeros((0, 2), np.float32), 0, False)

    server._on_report(key, report(0))
    for _ in range(3):  # the world goes on to tick 3 without the ego's next reports
        sim.step({})
    server._on_report(key, report(2))  # late: never had it
    server._on_report(key, report(2))  # had it
    server._on_report(key, report(1))  # older than one it had
    assert reasons(server.verifier) == {"replayed": 2}


def test_a_signed_control_message_of_another_shape_is_dropped_and_vouches_for_nothing(authority, creds):
    """A compromised vehicle signs what it likes, bytes no encoder of ours writes:
    digests of another dtype or shape, or an object map whose ids are a matrix. The
    codec refuses each (an array is the dtype and shape its field declares): the
    message is dropped and counted, not heard, its payloads are left unvouched, and the
    agent's tick goes on."""
    import msgpack

    p1 = payload(1, 10, 4)
    good = with_digests(control(1, 4, [10]), {10: p1})
    wire = lambda a: [a.dtype.str, list(a.shape), a.tobytes()]  # noqa: E731
    digests, objects = 2 + 9, 2 + 6  # places in the wire list: type id and version, then the fields
    odd = [(digests, None, wire(good.digests.astype(np.float64))), (digests, None, wire(good.digests.reshape(-1))),
           (objects, 0, wire(good.objects.object_id.reshape(1, 1)))]  # the map's ids
    signer = Signer(creds[1])
    for at, inner, value in odd:
        body = msgpack.unpackb(encode(good))
        if inner is None:
            body[at] = value
        else:
            body[at][inner] = value
        raw_body = msgpack.packb(body)
        raw = encode(Signed(4, 0.4, signer.credentials.certificate, raw_body, signer.signature(raw_body)))
        drops = DropCounter()
        guard = Guard(creds[0], drops)
        bundle = CtrlBundle(4, 0.4, np.array([1], np.int64), np.array([0], np.int64), np.array([[True]]), [raw])
        heard, check = guard.heard(decode(encode(bundle)), 4)
        assert heard == [] and drops.total == 1
        assert guard.payloads([Reception(1, 10, 0.01, p1)], check, bundle) == []
