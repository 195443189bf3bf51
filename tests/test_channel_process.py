"""The channel proxy as a real process on loopback: this test plays the world (ticks)
and the vehicles (control messages, transmissions) through a real Zenoh session and
checks what each receiver is handed."""

from __future__ import annotations

import contextlib
import subprocess
import sys
import time
from collections.abc import Iterator

import numpy as np
import pytest

from channel_proxy.harness import Harness
from protocol import keys
from protocol.codec import decode, encode
from protocol.messages import ControlMsg, DataBundle, DataTx, EmpUpload, ObjectMap, Pose, Transmission
from protocol.session import ZenohArgs, session_scope
from tests.conftest import free_port

RUN = "tc"
MS = 1e-3


@contextlib.contextmanager
def proxy(*flags: str) -> Iterator[str]:
    """A proxy process that is the hub; killed and reaped however the test ends."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    p = subprocess.Popen([sys.executable, "-m", "channel_proxy", "--run-id", RUN, "--listen", ep, *flags],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        yield ep
        assert p.poll() is None, p.communicate()[1]  # it is still running
    finally:
        p.kill()
        p.communicate()


@contextlib.contextmanager
def driver(ep: str, vids, emp: bool = False) -> Iterator[Harness]:
    with session_scope(ZenohArgs(connect=(ep,))) as session:
        h = Harness(session, RUN, vids, emp=emp)
        try:
            h.wait_proxy()
            yield h
        finally:
            h.close()


def ctrl(vid: int, k: int, xy=(0.0, 0.0)) -> ControlMsg:
    om = ObjectMap(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2), np.float32), np.zeros(0, np.int64),
                   np.zeros((0, 0), np.float32), np.zeros((0, 0), np.float32))
    return ControlMsg(k, k * 0.1, vid, Pose(float(xy[0]), float(xy[1]), 0.0), 0.0, np.zeros((1, 3), np.float32), om,
                      np.zeros(0, np.int64))


def interval(h: Harness, k: int, data: dict[int, list[Transmission]], xy: dict[int, tuple] | None = None,
             senders=None):
    """One lock-step interval: tick, control from every sender, then each sender's DataTx."""
    senders = h.vids if senders is None else senders
    h.tick(k)
    for v in senders:
        h.send_ctrl(ctrl(v, k, (xy or {}).get(v, (10.0 * v, 0.0))))
    bundles = h.wait_ctrl(k)
    for v in senders:
        h.send_data(DataTx(k, k * 0.1, v, data.get(v, [])))
    return bundles, h.wait_data(k), h.wait_stats(k)


def tx(oid: int, start_s: float, size: int) -> Transmission:
    return Transmission(oid, start_s, bytes([oid % 256]) * size)


def got(bundle) -> list[tuple[int, int, float]]:
    return [(r.sender, r.object_id, round(r.rx_time_s, 6)) for r in bundle.receptions]


# ------------------------------------------------------------------ an ideal channel


# The module-scoped fixtures below start runs once per worker: keep the module on one.
pytestmark = pytest.mark.xdist_group("test_channel_process")


@pytest.fixture(scope="module")
def ideal():
    """One proxy (no link loss, unlimited range) for several tests; each takes fresh ticks."""
    with proxy("--profile", "ideal") as ep, driver(ep, [1, 2, 3]) as h:
        ticks = iter(range(1000))
        yield h, ticks


def test_two_senders_claiming_overlapping_airtime_both_lose(ideal):
    h, ticks = ideal
    k = next(ticks)
    # 900 B = 1 ms: 1 on [0, 1) ms and 2 on [0.5, 1.5) ms collide; 3 on [5, 6) ms is clear
    _, data, stats = interval(h, k, {1: [tx(11, 0.0, 900)], 2: [tx(22, 0.5 * MS, 900)], 3: [tx(33, 5 * MS, 900)]})
    assert got(data[3]) == []
    assert got(data[1]) == [(3, 33, 0.006)] and got(data[2]) == [(3, 33, 0.006)]
    assert stats["data"]["collided_tx"] == 2 and stats["data"]["lost_collision_bytes"] == 4 * 900


def test_a_burst_larger_than_the_interval_is_cut_at_capacity(ideal):
    h, ticks = ideal
    k = next(ticks)
    # 12 x 9000 B (10 ms each) all claimed at t = 0: the radio queues them; 10 end by 100 ms
    _, data, stats = interval(h, k, {1: [tx(i, 0.0, 9000) for i in range(12)]})
    assert got(data[2]) == [(1, i, round(0.01 * (i + 1), 6)) for i in range(10)]
    assert got(data[3]) == got(data[2]) and got(data[1]) == []
    d = stats["data"]
    assert d["overflow_tx"] == 2 and d["overflow_bytes"] == 18000 and d["utilization"] == pytest.approx(1.0)
    assert [r.payload for r in data[2].receptions] == [bytes([i]) * 9000 for i in range(10)]


def test_a_signed_runs_medium_relays_every_frame_of_a_slot_after_the_vehicles_own():
    """``--relay-extra-frames`` (a signed run: receivers verify). In vehicle 3's slot: a
    frame naming vehicle 1 that comes before 3's own, 3's own, a second frame naming 3.
    The medium plays 3's own (its position: 1 hears 3 at 30 m, its size) and relays the
    other two after it, heard by the same receivers. A second DataTx in 3's slot: its
    object 33 shares the fate of 3's own object 33, its unknown object 99 that of 3's
    first decoded one; nobody's reception changes."""
    with proxy("--profile", "ideal", "--relay-extra-frames") as ep, driver(ep, [1, 2, 3]) as h:
        k = 0
        h.tick(k)
        foreign, second = encode(ctrl(1, k, (500.0, 0.0))), encode(ctrl(3, k, (900.0, 0.0)))
        # one session, one link, one receiving thread: the proxy files them in this order,
        # and 1's and 2's own, which close the phase, come last
        h.put(keys.net_ctrl_tx(RUN, 3), foreign)
        h.send_ctrl(ctrl(3, k, (30.0, 0.0)))
        h.put(keys.net_ctrl_tx(RUN, 3), second)
        h.put(keys.net_ctrl_tx(RUN, 3), second)  # the same bytes again: a duplicate, dropped
        for v in (1, 2):
            h.send_ctrl(ctrl(v, k, (10.0 * v, 0.0)))
        bundles = h.wait_ctrl(k)
        assert bundles[1].messages == [encode(ctrl(2, k, (20.0, 0.0))), encode(ctrl(3, k, (30.0, 0.0))), foreign,
                                       second]
        assert bundles[3].messages == [encode(ctrl(1, k, (10.0, 0.0))), encode(ctrl(2, k, (20.0, 0.0)))]
        h.put(keys.net_data_tx(RUN, 3), encode(DataTx(k, k * 0.1, 1, [Transmission(33, 0.0, b"x" * 10),
                                                                   Transmission(99, 0.0, b"y" * 20)])))
        h.send_data(DataTx(k, k * 0.1, 3, [tx(33, 5 * MS, 900)]))
        h.send_data(DataTx(k, k * 0.1, 1, [tx(11, 0.0, 900)]))
        h.send_data(DataTx(k, k * 0.1, 2, []))
        data = h.wait_data(k)
        stats = h.wait_stats(k)
        assert got(data[2]) == [(1, 11, 0.001), (3, 33, 0.006), (3, 33, 0.006), (3, 99, 0.006)]
        assert [r.payload for r in data[2].receptions][2:] == [b"x" * 10, b"y" * 20]
        assert got(data[3]) == [(1, 11, 0.001)] and got(data[1]) == [(3, 33, 0.006), (3, 33, 0.006), (3, 99, 0.006)]
        assert stats["ctrl"]["extra_frames"] == 2 and stats["data"]["extra_receptions"] == 2
        assert stats["data"]["transmissions"] == 2 and stats["duplicate"] == 1


def test_a_malformed_packet_is_dropped_and_counted_and_the_proxy_keeps_running(ideal):
    h, ticks = ideal
    k = next(ticks)
    h.tick(k)
    h.put(keys.net_ctrl_tx(RUN, 1), b"\x93not a message")
    h.put(keys.net_data_tx(RUN, 2), encode(ctrl(2, k)))  # a valid message of the wrong type
    h.put(keys.net_ctrl_tx(RUN, 3), encode(ctrl(1, k)))  # vehicle 1's message on 3's key
    for v in (1, 2, 3):
        h.send_ctrl(ctrl(v, k, (10.0 * v, 0.0)))
    bundles = h.wait_ctrl(k)
    assert sorted(decode(m, ControlMsg).vid for m in bundles[1].messages) == [2, 3]
    for v in (1, 2, 3):
        h.send_data(DataTx(k, k * 0.1, v, [tx(v, v * MS, 100)]))
    data = h.wait_data(k)
    stats = h.wait_stats(k)
    assert stats["malformed_dropped"] >= 3
    assert got(data[1]) == [(2, 2, round(2 * MS + 100 * 8 / 7.2e6, 6)), (3, 3, round(3 * MS + 100 * 8 / 7.2e6, 6))]
    _, _, stats = interval(h, next(ticks), {})  # and the next interval runs as usual
    assert stats["data"]["absent"] == []


# ------------------------------------------------------------------ a lossy channel


@pytest.fixture(scope="module")
def lossy():
    """p = 0.7 on every link up to 500 m; vehicle 4 is 2 km away."""
    with proxy("--curve", "fixed", "--p-fixed", "0.7", "--range-m", "500", "--seed", "11") as ep, \
            driver(ep, [1, 2, 3, 4]) as h:
        yield h, iter(range(1000))


XY = {1: (0.0, 0.0), 2: (100.0, 0.0), 3: (0.0, 200.0), 4: (2000.0, 0.0)}


def test_a_lossy_links_delivery_rate_matches_p(lossy):
    h, ticks = lossy
    delivered = draws = 0
    for _ in range(3):
        # 300 x 100 B from vehicle 1, back to back (0.11 ms each): 600 draws per interval to 2 and 3
        _, data, stats = interval(h, next(ticks), {1: [tx(i, 0.0, 100) for i in range(300)]}, XY)
        delivered += len(data[2].receptions) + len(data[3].receptions)
        draws += 600
        assert stats["data"]["collided_tx"] == 0 and stats["data"]["overflow_tx"] == 0
    rate = delivered / draws
    assert rate == pytest.approx(0.7, abs=4 * (0.7 * 0.3 / draws) ** 0.5)


def test_a_receiver_out_of_range_hears_nothing(lossy):
    h, ticks = lossy
    bundles, data, stats = interval(h, next(ticks), {1: [tx(i, i * MS, 100) for i in range(50)],
                                                     4: [tx(99, 60 * MS, 100)]}, XY)
    assert bundles[4].messages == [] and data[4].receptions == []
    assert all(decode(m, ControlMsg).vid != 4 for v in (1, 2, 3) for m in bundles[v].messages)
    assert all(r.sender != 4 for v in (1, 2, 3) for r in data[v].receptions)
    assert len(data[2].receptions) > 20  # the others do hear 1


# ------------------------------------------------------------------ reproducibility


def run_twice_inputs(ep: str) -> tuple[list, list]:
    with driver(ep, [1, 2, 3]) as h:
        for k in range(3):
            interval(h, k, {v: [tx(10 * v + i, (30 * (v - 1) + 2 * i) * MS, 1200) for i in range(10)] for v in (1, 2, 3)})
        return [h.ctrl_raw[k] for k in range(3)], [h.data_raw[k] for k in range(3)]


def test_the_same_seed_gives_byte_identical_deliveries():
    flags = ("--curve", "fixed", "--p-fixed", "0.5", "--range-m", "1000", "--seed", "5")
    with proxy(*flags) as ep:
        ctrl_a, data_a = run_twice_inputs(ep)
    with proxy(*flags) as ep:
        ctrl_b, data_b = run_twice_inputs(ep)
    assert ctrl_a == ctrl_b and data_a == data_b
    decoded = [int(decode(b, DataBundle).decoded.sum()) for b in data_a]  # (receiver, object) pairs
    assert 0 < sum(decoded) < 3 * 3 * 20  # some, not all, were lost


# ------------------------------------------------------------------ phases


def test_a_silent_vehicle_is_waited_for_then_declared_dead_and_revived_when_it_speaks():
    with proxy("--profile", "ideal", "--phase-timeout-s", "0.5", "--dead-after", "2") as ep, driver(ep, [1, 2, 3]) as h:
        waits = []
        for k in range(3):
            t0 = time.monotonic()
            _, _, stats = interval(h, k, {}, senders=[1, 2])
            waits.append(time.monotonic() - t0)
        assert waits[0] >= 0.5 and waits[1] >= 0.5  # each waited out its phase timeout for 3
        assert stats["dead"] == [3] and stats["ctrl"]["absent"] == []  # dead after two absences: not waited for
        _, _, stats = interval(h, 3, {}, senders=[3, 1, 2])  # 3 first: a phase does not wait for the dead
        assert stats["dead"] == [] and stats["ctrl"]["absent"] == []


def test_realtime_mode_closes_phases_at_wall_clock_deadlines():
    """Vehicle 3 never speaks and the phase timeout is 600 s, so only the real-time
    deadline can close the control phase before the harness gives up on the bundles. The
    deadlines are seconds long so that 1's and 2's messages are in time on any machine."""
    with proxy("--profile", "ideal", "--realtime", "--ctrl-deadline-s", "2", "--data-deadline-s", "5",
               "--phase-timeout-s", "600") as ep, driver(ep, [1, 2, 3]) as h:
        _, _, stats = interval(h, 0, {1: [tx(1, 0.0, 100)]}, senders=[1, 2])
        assert stats["ctrl"]["absent"] == [3]
        assert stats["data"]["delivered_pairs"] == 1  # to 2; 3 never said where it is, so it is nowhere


# ------------------------------------------------------------------ EMP


def test_emp_relay_forwards_voronoi_segments_until_the_interval_is_full():
    with proxy("--mode", "emp") as ep, driver(ep, [1, 2, 3], emp=True) as h:
        # 25 000 points x 6 B = 150 kB on air: upload + forward take 48.0 ms at 50 Mbps; two fit in 100 ms
        h.tick(0)
        for v in (1, 2, 3):
            pts = np.full((25_000, 3), v, dtype=np.float32)
            h.send_emp(EmpUpload(0, 0.0, v, Pose(10.0 * v, 0.0, 0.0), pts))
        bundles = h.wait_emp(0)
        stats = h.wait_stats(0)["emp"]
        assert stats["uploads"] == 3 and stats["overflow_tx"] == 1
        # tick 0: vehicle 1 first, then 2; 3's forward would end at 144 ms
        assert [(s.sender, round(s.rx_time_s, 4)) for s in bundles[3].segments] == [(1, 0.048), (2, 0.096)]
        assert [s.sender for s in bundles[1].segments] == [2] and bundles[2].segments[0].points_world[0, 0] == 1.0
        assert bundles[1].site_vids.tolist() == [1, 2, 3] and bundles[1].site_xy[2].tolist() == [30.0, 0.0]
