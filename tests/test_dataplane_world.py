"""The data plane on real scans from the world: the paper's left-turn case."""

from __future__ import annotations

import numpy as np
import pytest

from protocol.messages import Scan
from vehicle_agent.control import VehicleController
from vehicle_agent.dataplane import DataPlane, lane_trajectory
from world_server.geometry import box_corners
from world_server.scenarios import ScenarioParams
from world_server.sim import Simulation

EGO, TRUCK = 0, 1


# The module-scoped fixtures below start runs once per worker: keep the module on one.
pytestmark = pytest.mark.xdist_group("test_dataplane_world")


@pytest.fixture(scope="module")
def left_turn_at_5s():
    """Everyone drives its lane; the ego and truck agents perceive every tick up to t = 5 s."""
    sim = Simulation(ScenarioParams(scenario="left_turn", vehicles=8, delta_s=0.0, seed=2))
    mapmsg = sim.scenario.roadmap.to_msg()
    planes = {vid: DataPlane(sim.mission(vid), mapmsg) for vid in (EGO, TRUCK)}
    ctl = {a.vid: VehicleController(a.spec) for a in sim.scenario.connected()}
    while True:
        views = sim.sense(sim.connected_vids)
        scans = {vid: Scan(sim.tick, sim.t_sim_s, vid, v.pose, v.speed_mps, v.range_cm) for vid, v in views.items()}
        perceived = {vid: planes[vid].perceive(scans[vid]) for vid in planes}
        if sim.t_sim_s >= 5.0 - 1e-9:
            return sim, planes, scans, perceived
        sim.step({vid: ctl[vid].run_step(v.pose, v.speed_mps, sim.scenario.actors[vid].route,
                                         sim.scenario.actors[vid].speed_mps) for vid, v in views.items()})


def collider_truth(sim):
    c = sim.scenario.collider
    p = sim.physics
    return box_corners(p.x[c.vid], p.y[c.vid], p.yaw[c.vid], c.spec.length_m, c.spec.width_m)


def nearest_track(view, xy):
    d = [np.hypot(*(t.xy - xy)) for t in view.tracks]
    return view.tracks[int(np.argmin(d))], min(d)


def test_truck_extracts_the_collider_and_the_ego_does_not(left_turn_at_5s):
    sim, planes, scans, views = left_turn_at_5s
    truth = collider_truth(sim).mean(axis=0)
    track, dist = nearest_track(views[TRUCK], truth)
    assert dist < 1.5 and len(track.detection.points_world) > 100
    assert track.speed_mps == pytest.approx(30 / 3.6, abs=1.5)  # tracked at its 30 km/h
    if views[EGO].tracks:
        assert nearest_track(views[EGO], truth)[1] > 3.0  # the ego's own LiDAR has nothing there


def test_collider_is_invisible_to_the_ego_and_relevant_to_it(left_turn_at_5s):
    sim, planes, scans, views = left_turn_at_5s
    ego_scan = scans[EGO]
    ego_traj = lane_trajectory(sim.scenario.ego.route, ego_scan.pose, sim.scenario.ego.speed_mps, ego_scan.t_sim_s)
    ego_msg = planes[EGO].control_message(views[EGO], ego_scan, ego_traj, heard=[])
    planes[TRUCK].neighbors.update([ego_msg])
    truck_msg = planes[TRUCK].control_message(views[TRUCK], scans[TRUCK], np.zeros((1, 3), np.float32), heard=[EGO])
    om = truck_msg.objects
    col_track, _ = nearest_track(views[TRUCK], collider_truth(sim).mean(axis=0))
    row = int(np.flatnonzero(om.object_id == col_track.track_id)[0])
    col = int(np.flatnonzero(om.receivers == EGO)[0])
    assert om.visibility[row, col] == 0.0
    assert om.relevance[row, col] == 1.0
    assert om.size_bytes[row] == 64 + 6 * len(col_track.detection.points_world)
    # the ego's own body, as the truck sees it, is "visible" to the ego: nothing to send it
    ego_track, d = nearest_track(views[TRUCK], np.array([ego_scan.pose.x_m, ego_scan.pose.y_m]))
    assert d < 3.0
    assert om.visibility[int(np.flatnonzero(om.object_id == ego_track.track_id)[0]), col] == 1.0


def test_after_fusion_the_collider_is_in_the_egos_grid_at_its_true_position(left_turn_at_5s):
    sim, planes, scans, views = left_turn_at_5s
    truth = collider_truth(sim)
    col_track, _ = nearest_track(views[TRUCK], truth.mean(axis=0))
    payload = planes[TRUCK].payloads(views[TRUCK], [col_track.track_id])[col_track.track_id]
    fused, refused = planes[EGO].fuse(views[EGO], [payload])
    assert refused == []
    rows, cols = np.nonzero(fused.received)
    assert len(rows) > 5
    centers = views[EGO].grid.cell_centers(rows, cols)
    # every received cell centre lies on the collider's true footprint, grown by one cell (0.5 m)
    lo, hi = truth.min(axis=0) - 0.5 * np.sqrt(2), truth.max(axis=0) + 0.5 * np.sqrt(2)
    assert np.all((centers >= lo) & (centers <= hi))


def test_under_the_paper_model_an_object_offers_its_columns_and_says_their_size(left_turn_at_5s):
    """The truck's view under ``--model paper``: every object's size in its object map is
    its float64 payload's length, its points one per 5 cm column above 0.5 m."""
    from protocol.model import PAPER
    from vehicle_agent.dataplane import Neighbors
    from vehicle_agent.payload import decode_object

    sim, _, scans, _ = left_turn_at_5s
    plane = DataPlane(sim.mission(TRUCK), sim.scenario.roadmap.to_msg(), model=PAPER)
    view = plane.perceive(scans[TRUCK])
    om = plane.object_map(view, Neighbors.none())
    payloads = plane.payloads(view, om.object_id.tolist())
    assert len(payloads) > 3
    for oid, size in zip(om.object_id.tolist(), om.size_bytes.tolist()):
        raw = payloads[oid]
        assert len(raw) == size and (size - 64) % 24 == 0
        track = next(t for t in view.tracks if t.track_id == oid)
        pts = track.detection.points_world
        kept = np.unique(np.floor(pts[pts[:, 2] > 0.5][:, :2] / 0.05), axis=0)
        n = (size - 64) // 24
        assert n <= len(kept) and n <= len(pts)  # no more than one point per column above the cut
        assert len(decode_object(raw).points_sensor) == n
