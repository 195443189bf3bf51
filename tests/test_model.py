"""The modelling profiles (protocol.model) and what each setting changes, by hand."""

from __future__ import annotations

import numpy as np
import pytest

from deploy.launch import table
from deploy.launch.run import InputError, options_from, parse_args
from protocol.messages import Pose
from protocol.model import OURS, PAPER, ModelError, lidar_config, resolve
from vehicle_agent.__main__ import Pipeline, scheduler_of
from vehicle_agent.fusion import ReceivedStore
from vehicle_agent.payload import (HEADER_BYTES, column_thinned, decode_object, decode_objects, encode_objects,
                                   payload_size)
from vehicle_agent.scheduler import SchedulerState, SenderOffers, get, make_instance
from vehicle_agent.scheduler.agnostic import shuffled_order


def test_profiles_and_settings_alone():
    assert resolve() == OURS and resolve("paper") == PAPER
    assert (PAPER.bytes_per_point, PAPER.hold_s, PAPER.fill_spare, PAPER.group_size) == (24, 0.0, False, 0)
    m = resolve("paper", ["hold_s=1.0", "fill_spare=true"])
    assert m.hold_s == 1.0 and m.fill_spare and m.bytes_per_point == 24
    assert m.label() == "paper+fill_spare=true+hold_s=1.0"
    assert resolve(m.args()[1], m.args()[3::2]) == m  # what another process is told resolves to the same
    assert resolve("ours", {"agnostic_order": "shuffle"}).differences() == {"agnostic_order": "shuffle"}
    lidar = lidar_config(PAPER)
    assert (lidar.range_m, lidar.fov_up_deg, lidar.fov_down_deg, lidar.beams) == (50.0, 4.0, -20.0, 64)


@pytest.mark.parametrize("name, sets, field", [
    ("nope", [], "model"), ("paper", ["hold_s"], "model_set"), ("paper", ["hold=1"], "hold"),
    ("paper", ["hold_s=-1"], "hold_s"), ("paper", ["hold_s=x"], "hold_s"), ("ours", ["bytes_per_point=8"],
                                                                          "bytes_per_point"),
    ("ours", ["fill_spare=maybe"], "fill_spare"), ("ours", ["group_size=1.5"], "group_size"),
    ("ours", ["object_points=some"], "object_points"), ("ours", ["lidar_fov_up_deg=-30"], "lidar_fov_up_deg"),
    ("ours", ["lidar_fov_down_deg=-95"], "lidar_fov_down_deg"), ("ours", ["ground_cut_m=0.5"], "ground_cut_m"),
    ("paper", ["object_points=all"], "ground_cut_m"),
])
def test_a_bad_setting_names_its_field(name, sets, field):
    with pytest.raises(ModelError, match=f"^{field}:"):
        resolve(name, sets)


def test_the_launcher_refuses_a_bad_model_and_passes_a_good_one_to_every_process(tmp_path):
    with pytest.raises(InputError, match="^hold_s:"):
        options_from(parse_args(["--out", str(tmp_path), "--model", "paper", "--model-set", "hold_s=-2"]),
                     hub="tcp/127.0.0.1:1")
    opts = options_from(parse_args(["--out", str(tmp_path), "--model", "paper", "--model-set", "hold_s=0.5",
                                    "--vehicles", "3"]), hub="tcp/127.0.0.1:1")
    cfg = opts.run
    assert cfg.channel_profile == "lte-direct-100ms"  # the model's radio, as no flag named one
    for spec in table.processes(cfg):
        if spec.name in (table.WORLD,) or spec.name.startswith("agent"):
            argv = list(spec.args)
            assert argv[argv.index("--model") + 1] == "paper"
            assert argv[argv.index("--model-set") + 1] == "hold_s=0.5"
        if spec.name == table.PROXY:
            argv = list(spec.args)
            assert argv[argv.index("--profile") + 1] == "lte-direct-100ms" and "--model" in argv
        if spec.name == table.RECORDER:
            assert "model=paper+hold_s=0.5" in spec.args
    own = options_from(parse_args(["--out", str(tmp_path), "--model", "paper", "--channel-profile", "lte-direct"]),
                       hub="tcp/127.0.0.1:1")
    assert own.run.channel_profile == "lte-direct"  # a run's own radio wins over the model's, and is recorded
    assert own.run.model.channel_profile == "lte-direct" and own.run.model.label() == "paper+channel_profile=lte-direct"


def test_column_thinning_by_hand():
    # object 0: two points in column (0, 0), then column (1, 0) whose first point is ground
    # (thinned first, cut after: the whole column goes); object 1: one point in (0, 0)
    pts = np.array([[0.01, 0.01, 1.0], [0.02, 0.03, 2.0], [0.06, 0.0, 0.3], [0.07, 0.01, 1.0],
                    [0.01, 0.01, 1.0], [np.nan, 0.0, 1.0]])
    keep = column_thinned(pts, np.array([4, 2]), 0.05, 0.5)
    assert keep.tolist() == [True, False, False, False, True, False]
    assert not column_thinned(np.zeros((0, 3)), np.zeros(0, dtype=np.int64), 0.05, 0.5).any()


def test_float64_payloads_round_trip_beside_int16_ones():
    pose = Pose(10.0, -5.0, 0.3)
    pts = np.array([[1.234567, 2.5, 0.7], [1.5, 2.25, 1.1], [3.0, 1.0, 0.6]], dtype=np.float32)
    centroid = np.array([[1.5, 2.0, 0.8], [3.0, 1.0, 0.6]], dtype=np.float32)
    velocity = np.zeros((2, 2), dtype=np.float32)
    counts = np.array([2, 1])
    wide = encode_objects(1, 7, 0.7, pose, 1.9, [4, 5], centroid, velocity, pts, counts, bytes_per_point=24)
    narrow = encode_objects(1, 7, 0.7, pose, 1.9, [4, 5], centroid, velocity, pts, counts)
    assert [len(p) for p in wide] == [payload_size(2, 24), payload_size(1, 24)] == [HEADER_BYTES + 48, HEADER_BYTES + 24]
    assert [len(p) for p in narrow] == [HEADER_BYTES + 12, HEADER_BYTES + 6]
    one = decode_object(wide[0])
    np.testing.assert_allclose(one.points_sensor, pts[:2], atol=1e-6)  # float64 offsets: no centimetre rounding
    batch, refused = decode_objects([narrow[0], wide[0], b"junk", wide[1], narrow[1]])
    assert len(refused) == 1 and batch.object_id.tolist() == [4, 4, 5, 5] and batch.counts.tolist() == [2, 2, 1, 1]
    singles = np.concatenate([decode_object(p).points_sensor for p in (narrow[0], wide[0], wide[1], narrow[1])])
    assert np.array_equal(batch.points_sensor, singles)


def _instance(senders=(0, 1, 2), per_sender=4, size=3000):
    offers = {v: SenderOffers(np.arange(per_sender), np.full(per_sender, size), np.array([9]),
                              np.zeros((per_sender, 1)), np.ones((per_sender, 1))) for v in senders}
    return make_instance(offers, lambda i, j: 1.0, vids=[*senders, 9])


def test_the_shuffle_is_a_permutation_drawn_alike_and_new_every_interval():
    inst = _instance()
    a = shuffled_order(inst, 11)
    assert sorted(a.tolist()) == list(range(inst.n_objects))
    # another member heard the same messages in another order: the same objects in the same order
    other = _instance(senders=(2, 0, 1))
    key = lambda i, order: [(int(i.vids[i.owner[k]]), int(i.object_id[k])) for k in order]  # noqa: E731
    assert key(other, shuffled_order(other, 11)) == key(inst, a)
    orders = {tuple(shuffled_order(inst, k).tolist()) for k in range(20)}
    assert len(orders) > 15  # 12! orders: twenty intervals all but never repeat one
    sched = get("agnostic-shuffle")(inst, SchedulerState(order_key=11))
    # ten 9000 B frames (10 ms at 7.2 Mbps) of 3000 B objects: three a frame, in the drawn order
    assert [list(f) for f in sched.frames][:4] == [sorted(a[3 * n:3 * n + 3].tolist()) for n in range(4)]


def test_each_model_picks_its_schemes_schedulers():
    assert scheduler_of("agnostic") == "agnostic" and scheduler_of("autocast") == "autocast"
    assert scheduler_of("agnostic", PAPER) == "agnostic-shuffle" and scheduler_of("autocast", PAPER) == "greedy"
    assert scheduler_of("autocast-fptas", PAPER) == "fptas" and scheduler_of("autocast-fptas") == "autocast-fptas"


def test_a_zero_hold_keeps_this_intervals_receptions_only():
    pose = Pose(0.0, 0.0, 0.0)
    pts = np.ones((3, 3), dtype=np.float32)
    store = ReceivedStore(max_age_s=0.0)
    t = 7.1  # float32(7.1) < 7.1: a fresh reception's age comes out ~1e-7 s, not 0
    raw = encode_objects(2, 71, t, pose, 1.9, [1], np.ones((1, 3), np.float32), np.zeros((1, 2), np.float32), pts,
                         np.array([3]))
    store.add_batch(decode_objects(raw)[0])
    assert len(store.current(t)) == 1
    assert len(store.current(t + 0.1)) == 0  # one interval later it is gone: no coasting


def test_a_float64_body_beyond_float32_decodes_to_inf_without_a_warning():
    import warnings

    head = encode_objects(1, 7, 0.7, Pose(0, 0, 0), 1.9, [4], np.zeros((1, 3), np.float32), np.zeros((1, 2), np.float32),
                          np.zeros((1, 3), np.float32), np.array([1]), bytes_per_point=24)[0][:HEADER_BYTES]
    raw = head + np.array([1e300, np.nan, -np.inf], dtype="<f8").tobytes()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        one = decode_object(raw).points_sensor
        batch, refused = decode_objects([raw])
    assert refused == [] and np.array_equal(batch.points_sensor, one, equal_nan=True)
    assert np.isinf(one[0, 0]) and np.isnan(one[0, 1]) and one[0, 2] == -np.inf


@pytest.mark.parametrize("model, held", [(OURS, True), (PAPER, False)])
def test_an_agent_holds_a_received_object_as_its_model_says_after_its_warm_up(model, held):
    """The truck shares what it sees at tick 0; the ego fuses it, then hears nothing at
    tick 1: our model still shows the objects (carried forward), the paper's does not."""
    from channel_proxy.profiles import get_profile
    from protocol.codec import decode, encode
    from protocol.messages import Mission, Scan
    from vehicle_agent.agent import Agent
    from vehicle_agent.agreement import AgreementConfig
    from vehicle_agent.warmup import warm_up
    from world_server.scenarios import ScenarioParams
    from world_server.sim import Simulation

    sim = Simulation(ScenarioParams(scenario="red_light", vehicles=5, delta_s=0.0, seed=0), lidar_config(model))
    mapmsg = sim.scenario.roadmap.to_msg()
    ego, truck = (Agent(decode(encode(sim.mission(vid)), Mission), mapmsg, model) for vid in (0, 1))
    warm_up(ego, AgreementConfig.from_profile(get_profile(model.channel_profile), scheduler="greedy"))
    scans = []
    for _ in range(2):
        views = sim.sense(sim.connected_vids)
        scans.append({vid: Scan(sim.tick, sim.t_sim_s, vid, views[vid].pose, views[vid].speed_mps,
                                views[vid].range_cm) for vid in (0, 1)})
        sim.step({})
    truck_view = truck.perceive(scans[0][1])
    payloads = list(truck.dataplane.payloads(truck_view, [t.track_id for t in truck_view.tracks]).values())
    assert payloads
    ego.fuse(ego.perceive(scans[0][0]), payloads)
    assert len(ego.dataplane.shared_batch) > 0
    ego.fuse(ego.perceive(scans[1][0]), [])
    assert (len(ego.dataplane.shared_batch) > 0) == held


@pytest.mark.parametrize("mode, radio", [("v2v", "lte-direct-100ms"), ("emp", "emp-v2i")])
def test_no_channel_loss_keeps_the_radio_and_loses_nothing(mode, radio):
    """The paper's model has no channel loss (the authors' simulator wires none in): the proxy and
    every agent play the same radio, each packet in it arriving at any distance."""
    from channel_proxy.__main__ import parse_args as proxy_args, profile_from
    lossy = profile_from(proxy_args(["--mode", mode, "--profile", radio]), OURS)
    lossless = profile_from(proxy_args(["--mode", mode]), PAPER)
    assert lossless.name == radio and lossless.frame_bytes == lossy.frame_bytes
    far = np.array([50.0, 170.0, 600.0])
    assert lossy.prr.prr(far)[-1] < 0.5 and list(lossless.prr.prr(far)) == [1.0, 1.0, 1.0]
    assert resolve("paper", ["channel_loss=modelled"]).label() == "paper+channel_loss=modelled"
    with pytest.raises(ModelError, match="^channel_loss:"):
        resolve("ours", ["channel_loss=some"])
    if mode == "v2v":  # an agent's p_ij comes from the same reception model as the proxy's draws
        from world_server.scenarios import ScenarioParams
        from world_server.sim import Simulation

        sim = Simulation(ScenarioParams(scenario="red_light", vehicles=3, seed=0))
        for model, prr in ((OURS, lossy.prr), (PAPER, lossless.prr)):
            step = Pipeline(sim.mission(0), sim.scenario.roadmap.to_msg(), "autocast", radio, model=model)
            assert step.agreement.prr == prr
