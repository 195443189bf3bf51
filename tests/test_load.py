"""``deploy.experiments.load``: offered load, share sent and the collider's delivery to the ego, per
interval, on small MCAPs written with the recorder's own writer, answers derived by hand."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from deploy.experiments import load
from deploy.record.recorder import McapLog
from protocol import keys
from protocol.codec import encode
from protocol.messages import (ChannelStats, ControlMsg, DataBundle, EmpBundle, EmpSegment, EmpUpload, ObjectMap, Pose,
                               Reception, Tick, WorldTruth)

RUN = "load"
COLLIDER = 3  # the run's vehicle count: vids 0 (ego), 1, 2 connected, 3 the collider
META = {"run_id": RUN, "vehicles": "3", "scheme": "autocast", "channel_profile": "lte-direct"}


def objects(rows: list[tuple[int, int, tuple[float, float], bool]], receivers=(0, 2)) -> ObjectMap:
    """(object id, size_bytes, centroid, wanted): a wanted object has v = 0, r = 1 for the
    first receiver; the others v = 1 (everyone sees it already), r = 1."""
    n, m = len(rows), len(receivers)
    vis = np.ones((n, m), np.float32)
    for i, row in enumerate(rows):
        vis[i, 0] = 0.0 if row[3] else 1.0
    return ObjectMap(np.array([r[0] for r in rows], np.int64), np.array([r[1] for r in rows], np.int64),
                     np.array([r[2] for r in rows], np.float32).reshape(n, 2), np.array(receivers, np.int64),
                     vis, np.ones((n, m), np.float32))


def ctrl(tick: int, vid: int, om: ObjectMap) -> ControlMsg:
    return ControlMsg(tick, tick * 0.1, vid, Pose(0.0, 0.0, 0.0), 5.0, np.zeros((2, 3), np.float32), om,
                      np.array([], np.int64))


def truth(tick: int, collider_xy: tuple[float, float]) -> WorldTruth:
    pose = np.array([[0, -30, 0], [0, -10, 0], [20, 0, 0], [*collider_xy, 0]], np.float32)
    return WorldTruth(tick, tick * 0.1, np.arange(4), pose, np.zeros(4, np.float32),
                      np.tile(np.array([4.5, 1.8, 1.5], np.float32), (4, 1)))


def bundle(tick: int, rx: list[tuple[int, int]], decoded: list[list[bool]]) -> DataBundle:
    """``decoded`` rows are receivers 0, 1, 2."""
    return DataBundle(tick, tick * 0.1, np.arange(3), np.array(decoded, bool).reshape(3, len(rx)),
                      [Reception(s, o, 0.01, b"x") for s, o in rx])


def write(path, messages: list[tuple[str, object]], meta=META) -> None:
    with open(path, "wb") as f:
        log = McapLog(f, meta, json_mirror=True)  # the mirror's JSON copies must not count
        for i, (key, msg) in enumerate(messages):
            log.write(key, encode(msg), 1_000 + i)
        log.finish()


# Three intervals. Every interval the ego offers its own view of the collider (18 kB, not a copy
# *to* the ego), vehicle 1 the collider (object 7, 30 kB, wanted by the ego) and a car nobody
# needs (8, 15 kB), vehicle 2 a pedestrian (5, 9 kB): 72 kB = 0.8 of 90 kB; in tick 1 vehicle 2
# adds 36 kB more (1.2). Tick 0: the ego decodes object 7. Tick 1: only vehicle 2 does; the ego
# decodes object 8. Tick 2: the collider has moved 3.5 m from object 7's centroid, so 7 is not it,
# and the ego's reception of 7 is no copy of the collider.
SENDER1 = [(7, 30_000, (10.5, 0.0), True), (8, 15_000, (50.0, 0.0), False)]
SENDER2 = [(5, 9_000, (-20.0, 0.0), True)]
EGO_OWN = [(3, 18_000, (10.2, 0.1), False)]


def three_intervals() -> list[tuple[str, object]]:
    out: list[tuple[str, object]] = []
    where = {0: (10.0, 0.0), 1: (10.0, 1.0), 2: (14.0, 0.0)}
    sent = {0: 45_000, 1: 54_000, 2: 72_000}
    rx = {0: ([(1, 7), (2, 5)], [[True, True], [False, True], [True, False]]),
          1: ([(1, 7), (1, 8)], [[False, True], [False, False], [True, True]]),
          2: ([(1, 7)], [[True], [False], [True]])}
    for k in range(3):
        extra = [(6, 36_000, (-40.0, 0.0), False)] if k == 1 else []
        out += [(keys.world_tick(RUN), Tick(k, k * 0.1, [0, 1, 2], [])),
                (keys.world_truth(RUN), truth(k, where[k])),
                (keys.net_ctrl_tx(RUN, 0), ctrl(k, 0, objects(EGO_OWN, receivers=(1, 2)))),
                (keys.net_ctrl_tx(RUN, 1), ctrl(k, 1, objects(SENDER1))),
                (keys.net_ctrl_tx(RUN, 2), ctrl(k, 2, objects(SENDER2 + extra, receivers=(0, 1)))),
                (keys.net_data_rx(RUN), bundle(k, *rx[k])),
                (keys.net_stats(RUN), ChannelStats(k, k * 0.1, {"data": {"offered_bytes": sent[k]}}))]
    return out


def test_each_interval_by_hand(tmp_path):
    path = tmp_path / "run.mcap"
    write(path, three_intervals())
    rows = load.interval_load(path)
    assert [r.tick for r in rows] == [0, 1, 2]
    assert [r.objects_offered for r in rows] == [4, 5, 4]
    assert [r.objects_wanted for r in rows] == [2, 2, 2]  # the collider (7) and the pedestrian (5)
    assert [r.bytes_offered for r in rows] == [72_000, 108_000, 72_000]
    assert {r.capacity_bytes for r in rows} == {90_000}
    assert [r.load for r in rows] == pytest.approx([0.8, 1.2, 0.8])
    assert [r.bytes_sent for r in rows] == [45_000, 54_000, 72_000]
    assert [r.share_sent for r in rows] == pytest.approx([0.625, 0.5, 1.0])
    assert [r.collider_offered for r in rows] == [True, True, False]
    assert [r.collider_to_ego for r in rows] == [True, False, False]


def test_every_domain_counts_and_the_ego_hears_the_collider_in_another_than_domain_0(tmp_path):
    """The same three intervals on a map of two domains: vehicle 1, the collider's sender,
    is in domain 1 on channel 1, the others in domain 0, and each domain's data bundle
    holds its own receptions, domain 1's first. The load is over two domains' capacity
    (72 kB over 180 kB), and the ego's copy of the collider in tick 0 is in domain 1's
    bundle, not in domain 0's that follows it."""
    split = {0: ([(1, 7)], [[True], [False], [True]], [(2, 5)], [[True], [True], [False]]),
             1: ([(1, 7), (1, 8)], [[False, True], [False, False], [True, True]], [], []),
             2: ([(1, 7)], [[True], [False], [True]], [], [])}
    messages: list[tuple[str, object]] = []
    for key, msg in three_intervals():
        if key == keys.net_ctrl_tx(RUN, 1):
            key = keys.net_ctrl_tx(RUN, 1, 1, 1)
        if key == keys.net_data_rx(RUN):
            rx1, dec1, rx0, dec0 = split[msg.tick]
            messages += [(keys.net_data_rx(RUN, 1, 1), bundle(msg.tick, rx1, dec1)),
                         (key, bundle(msg.tick, rx0, dec0))]
            continue
        messages.append((key, msg))
    path = tmp_path / "run.mcap"
    write(path, messages)
    rows = load.interval_load(path)
    assert [r.bytes_offered for r in rows] == [72_000, 108_000, 72_000]
    assert {r.capacity_bytes for r in rows} == {180_000}
    assert [r.load for r in rows] == pytest.approx([0.4, 0.6, 0.4])
    assert [r.collider_offered for r in rows] == [True, True, False]
    assert [r.collider_to_ego for r in rows] == [True, False, False]


def test_the_summary_of_those_intervals(tmp_path):
    path = tmp_path / "run.mcap"
    write(path, three_intervals())
    s = load.load_summary(load.interval_load(path))
    assert s["intervals"] == 3 and s["capacity_bytes"] == 90_000
    assert s["load_median"] == pytest.approx(0.8)
    assert s["load_p90"] == pytest.approx(0.8 + 0.8 * 0.4)  # linear between the 2nd (0.8) and 3rd (1.2) of three
    assert s["overloaded_share"] == pytest.approx(1 / 3)
    assert s["share_sent_median"] == pytest.approx(0.625)
    assert (s["collider_offered_intervals"], s["collider_delivered_intervals"]) == (2, 1)
    assert s["delivery_offered"] == pytest.approx(0.5)
    assert s["delivery_all"] == pytest.approx(1 / 3)
    assert s["objects_offered_median"] == 4 and s["objects_wanted_median"] == 2
    json.dumps(s, allow_nan=False)  # plain JSON: what the report caches


def test_a_run_whose_mcap_the_sweep_deletes_keeps_its_figures_for_the_report(tmp_path):
    from deploy.experiments import report, runner

    run_dir = tmp_path / "runs" / RUN
    run_dir.mkdir(parents=True)
    write(run_dir / "run.mcap", three_intervals())
    assert runner.limit_mcap(run_dir, 1.0) == {}  # within the limit: kept, nothing else written
    assert not (run_dir / load.KEPT).exists()
    assert runner.limit_mcap(run_dir, 0.0)["mcap"] is None
    assert not (run_dir / "run.mcap").exists()
    kept = load.kept_summary(run_dir / load.KEPT)
    assert (kept["intervals"], kept["collider_offered_intervals"], kept["collider_delivered_intervals"]) == (3, 2, 1)
    assert kept["load_median"] == pytest.approx(0.8)  # the figures of the summary test above
    record = {"run_id": RUN, "run_key": RUN, "scheme": "autocast", "vehicles": 3, "status": "judged",
              "outcome": "safe", "mcap": None, "mcap_deleted_mb": 0.1}
    assert report.load_of_runs(tmp_path, None, [record], tmp_path / "cache") == ([(record, kept)], [])
    (run_dir / load.KEPT).write_text(json.dumps({"version": load.SUMMARY_VERSION - 1, "summary": kept}))
    assert report.load_of_runs(tmp_path, None, [record], tmp_path / "cache") == ([], [record])  # stale: not used


def test_the_report_reads_a_sweeps_runs_in_parallel_in_record_order(tmp_path, caplog):
    """Three runs: two logs by hand, the second on a dsrc channel, and a torn one."""
    from deploy.experiments import report

    def record(run_id: str) -> dict:
        return {"run_id": run_id, "run_key": run_id, "scheme": "autocast", "vehicles": 3, "status": "judged",
                "outcome": "safe"}

    for run_id, meta in (("a", META), ("b", {**META, "channel_profile": "dsrc"}), ("torn", META)):
        (tmp_path / "runs" / run_id).mkdir(parents=True)
        write(tmp_path / "runs" / run_id / "run.mcap", three_intervals(), meta=meta)
    torn = tmp_path / "runs" / "torn" / "run.mcap"
    torn.write_bytes(torn.read_bytes()[: torn.stat().st_size // 2])
    records = [record("a"), record("torn"), record("b")]
    got, missing = report.load_of_runs(tmp_path, None, records, tmp_path / "cache")
    assert [r["run_id"] for r, _ in got] == ["a", "b"] and missing == [records[1]]
    assert [s["load_median"] for _, s in got] == pytest.approx([0.8, 72 / 75])
    assert "offered load not read" in caplog.text
    assert report.load_of_runs(tmp_path, None, records, tmp_path / "cache")[0] == got  # again, from the cache


def test_capacity_is_the_profiles_interval(tmp_path):
    assert load.capacity_bytes("lte-direct") == 90_000  # 7.2 Mbps x 10 frames x 10 ms / 8
    assert load.capacity_bytes("dsrc") == 75_000  # 6 Mbps x one 100 ms frame / 8
    path = tmp_path / "run.mcap"
    write(path, three_intervals(), meta={**META, "channel_profile": "dsrc"})
    assert [r.load for r in load.interval_load(path)] == pytest.approx([72 / 75, 108 / 75, 72 / 75])


def test_a_run_without_a_channel_has_no_intervals(tmp_path):
    path = tmp_path / "run.mcap"
    write(path, [(keys.world_tick(RUN), Tick(0, 0.0, [0, 1, 2], [])), (keys.world_truth(RUN), truth(0, (0, 0)))])
    assert load.interval_load(path) == []
    assert load.load_summary([])["delivery_all"] is None


def test_unreadable_messages_are_left_out_and_counted(tmp_path, caplog):
    path = tmp_path / "run.mcap"
    with open(path, "wb") as f:
        log = McapLog(f, META)
        for i, (key, msg) in enumerate(three_intervals()):
            log.write(key, encode(msg), i)
        log.write(keys.net_ctrl_tx(RUN, 2), b"\xc1 not msgpack", 99)
        log.finish()
    with caplog.at_level("WARNING", logger="deploy.experiments.load"):
        rows = load.interval_load(path)
    assert [r.bytes_offered for r in rows] == [72_000, 108_000, 72_000]
    assert any("1 messages unreadable" in r.getMessage() for r in caplog.records)


def points_on(xy: tuple[float, float], n: int) -> np.ndarray:
    """n points on a car's roof at ``xy`` (world frame), within its 4.5 x 1.8 m box."""
    return np.column_stack([np.linspace(xy[0] - 1.5, xy[0] + 1.5, n), np.full(n, xy[1]), np.full(n, 1.4)]
                           ).astype(np.float32)


def test_emp_delivery_counts_the_colliders_points(tmp_path):
    """Tick 0: vehicle 1 uploads 6 points on the collider and the ego's bundle holds them.
    Tick 1: it uploads them again, but the ego's bundle holds only 4 of them (and the ego's
    own segment, which does not count). No load on the V2V channel: NaN."""
    far = points_on((60.0, 0.0), 50)
    messages: list[tuple[str, object]] = []
    for k, got in ((0, 6), (1, 4)):
        on = points_on((10.0, 0.0), 6)
        messages += [(keys.world_tick(RUN), Tick(k, k * 0.1, [0, 1, 2], [])),
                     (keys.world_truth(RUN), truth(k, (10.0, 0.0))),
                     (keys.net_emp_up(RUN, 1), EmpUpload(k, k * 0.1, 1, Pose(0, 0, 0), np.vstack([on, far]))),
                     (keys.net_emp_up(RUN, 2), EmpUpload(k, k * 0.1, 2, Pose(0, 0, 0), far)),
                     (keys.net_emp_down(RUN, 0), EmpBundle(k, k * 0.1, 0, [
                         EmpSegment(1, Pose(0, 0, 0), 0.02, np.vstack([on[:got], far])),
                         EmpSegment(0, Pose(0, 0, 0), 0.03, points_on((10.0, 0.0), 20))],
                         np.array([0, 1, 2]), np.zeros((3, 2))))]
    path = tmp_path / "run.mcap"
    write(path, messages, meta={**META, "scheme": "emp"})
    rows = load.interval_load(path)
    assert [(r.collider_offered, r.collider_to_ego) for r in rows] == [(True, True), (True, False)]
    assert all(math.isnan(r.load) and math.isnan(r.share_sent) for r in rows)
    s = load.load_summary(rows)
    assert s["delivery_offered"] == pytest.approx(0.5) and s["load_median"] is None


def test_cli_prints_the_summary_and_json(tmp_path, capsys):
    path = tmp_path / "run.mcap"
    write(path, three_intervals())
    assert load.main([str(path)]) == 0
    out = capsys.readouterr().out
    assert "median 0.80, p90 1.12" in out and "1 of 2 intervals" in out
    assert load.main([str(path), "--json"]) == 0
    got = json.loads(capsys.readouterr().out)
    assert got["summary"]["delivery_offered"] == 0.5 and len(got["intervals"]) == 3
    assert load.main([str(tmp_path / "none.mcap")]) == 2
