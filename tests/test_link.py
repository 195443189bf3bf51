"""The agent's side of the V2V channel (``vehicle_agent.link.V2VLink``) over real Zenoh
sessions: a test session is the hub, each link has its own client session."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from conftest import wait_until
from protocol import keys
from protocol.codec import MalformedMessage, encode
from protocol.messages import DataBundle, Reception, Transmission
from protocol.session import DropCounter, ZenohArgs, open_session
from vehicle_agent.__main__ import fuses
from vehicle_agent.link import V2VLink
from vehicle_agent.planning import Planner
from world_server.scenarios import ScenarioParams
from world_server.sim import Simulation

RUN = "linktest"


@pytest.fixture
def sessions(hub):
    """(the hub's session, a client session for a link); both closed at teardown."""
    opened = [open_session(ZenohArgs(listen=(hub,)))]
    opened.append(open_session(ZenohArgs(connect=(hub,))))
    yield opened
    for s in reversed(opened):
        s.close()


def _subscribed(hub_session, link_session, key: str) -> bool:
    """Whether the link's session subscribes to ``key``, once everything it declared
    before this call reached the hub: a probe subscriber declared now, after the link's,
    must be seen first (one session's declarations arrive in order)."""
    probe_key = keys.world_tick(RUN)  # a key no link subscribes to
    probe = link_session.declare_subscriber(probe_key, lambda sample: None)
    try:
        probe_pub, pub = hub_session.declare_publisher(probe_key), hub_session.declare_publisher(key)
        wait_until(lambda: probe_pub.matching_status.matching, "the probe's subscription reached the hub")
        return pub.matching_status.matching
    finally:
        probe.undeclare()


@pytest.mark.parametrize("receives", [True, False])
def test_a_link_that_receives_no_data_does_not_subscribe_to_the_bundle_nor_wait_for_it(sessions, receives):
    hub_session, link_session = sessions
    stop = threading.Event()
    link = V2VLink(link_session, RUN, 3, DropCounter(), stop, timeout_s=60.0, receives_data=receives)
    try:
        assert _subscribed(hub_session, link_session, keys.net_data_rx(RUN)) is receives
        assert _subscribed(hub_session, link_session, keys.net_ctrl_rx(RUN)), "every link hears the control phase"
        sent = []
        hub_session.declare_subscriber(keys.net_data_tx(RUN, 3), lambda sample: sent.append(sample))
        known = link_session.declare_publisher(keys.net_data_tx(RUN, 3))  # a client sends what its hub wants
        wait_until(lambda: known.matching_status.matching, "the link's session knows the hub's subscriber")
        if receives:  # it waits for the interval's bundle and takes its row
            bundle = DataBundle(7, 0.7, np.array([3]), np.ones((1, 1), dtype=bool), [Reception(1, 5, 0.01, b"p")])
            hub_session.put(keys.net_data_rx(RUN), encode(bundle))
            got = link.exchange_data(7, 0.7, [Transmission(9, 0.0, b"q")])
            assert got == [Reception(1, 5, 0.01, b"p")]
        else:  # no proxy answers here: a link that waited would wait its 60 s
            assert link.exchange_data(7, 0.7, [Transmission(9, 0.0, b"q")], receive=False) == []
            assert link.wait_s == 0.0
            with pytest.raises(ValueError, match="does not take the data bundle"):
                link.exchange_data(8, 0.8, [], receive=True)  # refused before it transmits
        wait_until(lambda: len(sent) == 1, "the DataTx reached the hub")  # it transmits either way
    finally:
        stop.set()
        link.close()


@pytest.mark.parametrize("scenario", ["left_turn", "red_light", "overtaking"])
def test_a_vehicle_receives_data_exactly_when_its_plan_can_use_it(scenario):
    sim = Simulation(ScenarioParams(scenario=scenario, vehicles=10, seed=0))
    missions = [sim.mission(a.vid) for a in sim.scenario.connected()]
    for m in missions:
        assert fuses(m, reports=False) is not Planner(m).holds_still
        assert fuses(m, reports=True)
    assert any(fuses(m, False) for m in missions) and not all(fuses(m, False) for m in missions)


def test_a_dropped_payloads_log_record_holds_its_text_not_the_exception(caplog):
    """A handler that keeps records (pytest's capture, a buffer) must not keep what the
    refusal's traceback holds: its frames, and the whole pipeline they ran in."""
    drops = DropCounter()
    try:
        raise MalformedMessage("ControlMsg.tick: -1 is not in [0, 1e+09]")
    except MalformedMessage as err:
        drops.add("ctrl bundle item", err)
    [record] = [r for r in caplog.records if "dropped" in r.getMessage()]
    assert "ControlMsg.tick" in record.getMessage()
    assert not any(isinstance(a, BaseException) for a in record.args)
