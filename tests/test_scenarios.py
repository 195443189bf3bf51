import numpy as np
import pytest

from vehicle_agent.domains import DomainTable
from world_server import scenarios
from world_server.geometry import box_corners, first_crossing, point_at, rect_distance
from world_server.roadmap import DOMAIN_RADIUS_M, corridor, grid, intersection
from world_server.scenarios import SCENARIOS, ScenarioError, ScenarioParams, build, load_scenario_file, \
    params_from_dict, vehicle_bound


@pytest.mark.parametrize("name", SCENARIOS)
@pytest.mark.parametrize("delta, kmh", [(-2.0, 20.0), (0.0, 30.0), (1.25, 40.0), (2.0, 30.0)])
def test_ego_and_collider_cross_at_the_configured_delta(name, delta, kmh):
    sc = build(ScenarioParams(scenario=name, vehicles=5, delta_s=delta, collider_speed_kmh=kmh))
    ego, col = sc.ego, sc.collider
    # both routes pass through the conflict point ...
    for actor in (ego, col):
        s = np.arange(0.0, 200.0, 0.01)
        pts, _ = point_at(actor.route, s)
        assert np.min(np.linalg.norm(pts - sc.conflict_xy, axis=1)) < 0.01
    # ... and the collider gets there delta seconds after the ego
    assert sc.arrival_s(col) - sc.arrival_s(ego) == pytest.approx(delta, abs=1e-6)
    assert col.speed_mps == pytest.approx(kmh / 3.6)


@pytest.mark.parametrize("name", ["left_turn", "red_light"])
def test_intersection_routes_really_cross(name):
    sc = build(ScenarioParams(scenario=name, vehicles=5))
    hit = first_crossing(sc.ego.route, sc.collider.route)
    assert hit is not None and np.allclose(hit[0], sc.conflict_xy)


def test_left_turn_geometry_by_hand():
    # ego turns left on a quarter circle centred (-8, -8) of radius 8 + 1.75; the collider drives
    # south on x = -5.25: (x + 8)^2 + (y + 8)^2 = 9.75^2 at x = -5.25 gives y = sqrt(9.75^2 - 2.75^2) - 8
    sc = build(ScenarioParams(scenario="left_turn", vehicles=5))
    assert sc.conflict_xy[0] == pytest.approx(-5.25)
    assert sc.conflict_xy[1] == pytest.approx(np.sqrt(9.75**2 - 2.75**2) - 8, abs=0.02)  # arc drawn as chords


def _assert_no_overlap(sc):
    poses = np.array([a.start_pose() for a in sc.actors])
    corners = box_corners(poses[:, 0], poses[:, 1], poses[:, 2], [a.spec.length_m for a in sc.actors],
                          [a.spec.width_m for a in sc.actors])
    for i in range(len(corners)):
        for j in range(i + 1, len(corners)):
            assert rect_distance(corners[i], corners[j]) > 0.3, (sc.actors[i], sc.actors[j])


def _members_at_start(sc) -> np.ndarray:
    """Connected vehicles per scheduler domain at t = 0, by the agents' membership rule."""
    table = DomainTable.of(sc.roadmap.to_msg())
    members = np.zeros(len(table), dtype=np.int64)
    for a in sc.connected():
        members[list(table.membership(*a.route[0]))] += 1
    return members


@pytest.mark.parametrize("name", SCENARIOS)
@pytest.mark.parametrize("n", [2, 5, 20, 40, 64])
def test_vehicles_are_placed_without_overlap(name, n):
    sc = build(ScenarioParams(scenario=name, vehicles=n, seed=3))
    assert [a.vid for a in sc.connected()] == list(range(n))
    assert [a.vid for a in sc.passive()] == list(range(n, len(sc.actors)))
    _assert_no_overlap(sc)


def test_same_seed_same_scene_other_seed_other_scene():
    a, b, c = (build(ScenarioParams(scenario="left_turn", vehicles=20, seed=s)) for s in (1, 1, 2))
    assert all(np.array_equal(x.route, y.route) for x, y in zip(a.actors, b.actors))
    assert not all(np.array_equal(x.route, y.route) for x, y in zip(a.actors, c.actors))


@pytest.mark.parametrize("values, field", [
    ({"scenario": "roundabout"}, "scenario"),
    ({"vehicles": 64 * 256 + 1}, "vehicles"),  # beyond any map's: 64 a domain, at most 256 domains
    ({"vehicles": 2.5}, "vehicles"),
    ({"collider_speed_kmh": -3}, "collider_speed_kmh"),
    ({"delta_s": float("nan")}, "delta_s"),
    ({"colider_speed_kmh": 30}, "colider_speed_kmh"),
])
def test_bad_values_name_the_field(values, field):
    with pytest.raises(ScenarioError, match=f"^{field}:"):
        params_from_dict(values)


def test_scenario_file(tmp_path):
    good = tmp_path / "s.toml"
    good.write_text('scenario = "red_light"\nvehicles = 12\ncollider_speed_kmh = 40\ndelta_s = -1\n')
    assert load_scenario_file(good) == ScenarioParams(scenario="red_light", vehicles=12, collider_speed_kmh=40.0,
                                                      delta_s=-1.0)
    bad = tmp_path / "bad.toml"
    bad.write_text('scenario = "red_light"\nspeed = 3\n')
    with pytest.raises(ScenarioError, match="^speed: unknown field"):
        load_scenario_file(bad)


def test_a_map_holds_64_connected_vehicles_a_scheduler_domain():
    assert (vehicle_bound(intersection()), vehicle_bound(corridor(3)), vehicle_bound(grid(2, 2))) == (64, 192, 256)
    with pytest.raises(ScenarioError, match=r"^vehicles: 65 is not in \[2, 64\] \(64 a scheduler domain; "
                                            r"left_turn's map has 1\)"):
        build(ScenarioParams(scenario="left_turn", vehicles=65))
    with pytest.raises(ScenarioError, match=r"^vehicles: 193 is not in \[2, 192\] \(64 a scheduler domain; "
                                            r"corridor3's map has 3\)"):
        build(ScenarioParams(scenario="corridor3", vehicles=193))


def test_too_many_vehicles_for_the_scene_is_a_clear_error():
    with pytest.raises(ScenarioError, match="^vehicles: only 1[0-9][0-9] connected vehicles fit the corridor3x scene, "
                                            "asked for 192"):  # within the bound, beyond what its lanes hold
        build(ScenarioParams(scenario="corridor3x", vehicles=192, duration_s=0.5))


def test_the_background_fills_the_places_near_a_junction_first_then_stands_further_out():
    near = build(ScenarioParams(scenario="left_turn", vehicles=59, seed=0))  # the places within R/2 hold 59
    far = build(ScenarioParams(scenario="left_turn", vehicles=64, seed=0))
    out = [a for a in far.actors if a.role == "background" and np.hypot(*a.route[0]) > DOMAIN_RADIUS_M]
    assert all(np.hypot(*a.route[0]) <= DOMAIN_RADIUS_M for a in near.actors if a.role == "background")
    assert len(out) >= 5 and all(a.speed_mps == 0 for a in out)
    assert all(np.array_equal(a.route, b.route) and a.kind == b.kind for a, b in zip(near.actors, far.actors)
               if a.role == "background")  # the near places as if the far ones were not there


def test_a_corridor_of_three_holds_120_no_domain_over_64():
    sc = build(ScenarioParams(scenario="corridor3x", vehicles=120, seed=0))
    assert len(sc.connected()) == 120 and _members_at_start(sc).max() <= 64
    _assert_no_overlap(sc)


def test_no_domain_gets_more_members_than_it_holds(monkeypatch):
    p = ScenarioParams(scenario="corridor3", vehicles=30, duration_s=2.0)
    assert _members_at_start(build(p)).max() > 12  # placed freely, one junction's domain gets more than 12
    monkeypatch.setattr(scenarios, "MAX_VEHICLES_PER_DOMAIN", 12)
    members = _members_at_start(build(p))
    assert members.max() == 12 and members.sum() >= 30  # (a vehicle in an overlap counts in both)


def test_rect_distance_by_hand():
    a = box_corners(0.0, 0.0, 0.0, 4.0, 2.0)
    assert rect_distance(a, box_corners(7.0, 0.0, 0.0, 4.0, 2.0)) == pytest.approx(3.0)
    assert rect_distance(a, box_corners(0.0, 5.0, np.pi / 2, 4.0, 2.0)) == pytest.approx(2.0)
    assert rect_distance(a, box_corners(1.0, 0.5, 0.3, 4.0, 2.0)) == 0.0
    # a plus shape: no corner inside the other, still overlapping
    assert rect_distance(box_corners(0, 0, 0, 10.0, 1.0), box_corners(0, 0, np.pi / 2, 10.0, 1.0)) == 0.0


def _rect_distance_numpy(a: np.ndarray, b: np.ndarray) -> float:
    """rect_distance as numpy arrays say it: the reference its numba kernel must equal bit for bit."""

    def inside(pts, poly):
        e = np.roll(poly, -1, axis=0) - poly
        rel = pts[:, None, :] - poly[None]
        return np.all(e[None, :, 0] * rel[..., 1] - e[None, :, 1] * rel[..., 0] >= 0, axis=1)

    def point_segment_dist(pts, a, b):
        ab = b - a
        ap = pts[:, None, :] - a[None, :, :]
        t = np.clip(np.einsum("nmk,mk->nm", ap, ab) / np.maximum(np.einsum("mk,mk->m", ab, ab), 1e-12), 0, 1)
        return np.linalg.norm(pts[:, None, :] - (a[None] + t[..., None] * ab[None]), axis=2)

    if inside(a, b).any() or inside(b, a).any():
        return 0.0
    if first_crossing(np.vstack([a, a[:1]]), np.vstack([b, b[:1]])) is not None:
        return 0.0
    ea, eb = np.roll(a, -1, axis=0), np.roll(b, -1, axis=0)
    return float(min(point_segment_dist(a, b, eb).min(), point_segment_dist(b, a, ea).min()))


def test_rect_distance_equals_the_numpy_reference_bit_for_bit():
    """The judge's closest distance is reported to the mm and decides near misses: the
    kernel gives exactly what the numpy formulation gave, apart, touching, crossing."""
    rng = np.random.default_rng(11)
    n = 20000
    boxes = np.column_stack([rng.uniform(-8, 8, (n, 2)), rng.uniform(-np.pi, np.pi, n),
                             rng.uniform(1.0, 12.0, n), rng.uniform(0.5, 3.0, n)])
    a = box_corners(0.0, 0.0, 0.0, 4.5, 1.8)
    apart = 0
    for cx, cy, yaw, length, width in boxes:
        b = box_corners(cx, cy, yaw, length, width)
        got, want = rect_distance(a, b), _rect_distance_numpy(a, b)
        assert got == want and np.float64(got).tobytes() == np.float64(want).tobytes(), (cx, cy, yaw, length, width)
        apart += want > 0
    assert 0.2 * n < apart < 0.8 * n  # both cases well covered


EXAMPLE = "world_server.example_scenarios:left_turn_from_east"


def test_a_scenario_by_import_path_is_left_turn_turned_a_quarter():
    """The example builder rotates left_turn by +90 degrees about the intersection centre:
    every actor's route is left_turn's rotated, so the geometry (and the delta) carry over."""
    ref = build(ScenarioParams(scenario="left_turn", vehicles=5, delta_s=1.0))
    ex = build(ScenarioParams(scenario=EXAMPLE, vehicles=5, delta_s=1.0))
    rot = np.array([[0.0, -1.0], [1.0, 0.0]])  # +90 deg: south arm -> east arm
    for role in ("ego", "occluder", "collider"):
        a, b = ref._role(role), ex._role(role)
        assert (a.vid, a.connected) == (b.vid, b.connected)
        np.testing.assert_allclose(a.route @ rot.T, b.route, atol=1e-9)
    np.testing.assert_allclose(ref.conflict_xy @ rot.T, ex.conflict_xy, atol=1e-9)
    assert ex.arrival_s(ex.collider) - ex.arrival_s(ex.ego) == pytest.approx(1.0, abs=1e-6)


def test_unknown_or_broken_scenarios_name_the_field():
    with pytest.raises(ScenarioError, match=r"^scenario: 'nope' is not one of"):
        ScenarioParams(scenario="nope")
    with pytest.raises(ScenarioError, match=r"^scenario: cannot load 'no_such_pkg.x:f'"):
        ScenarioParams(scenario="no_such_pkg.x:f")
    with pytest.raises(ScenarioError, match=r"^scenario: cannot load 'world_server.example_scenarios:nope'"):
        ScenarioParams(scenario="world_server.example_scenarios:nope")


def test_a_builder_that_misplaces_a_role_is_refused(monkeypatch):
    import world_server.example_scenarios as ex

    def ego_as_vid_3(p):
        sc = ex.left_turn_from_east(p)
        sc.ego.vid = 3
        return sc

    monkeypatch.setattr(ex, "bad", ego_as_vid_3, raising=False)
    with pytest.raises(ScenarioError, match=r"must place the ego as vid 0"):
        build(ScenarioParams(scenario="world_server.example_scenarios:bad", vehicles=5))


def test_a_run_without_a_duration_takes_its_scenarios_time_limit():
    """The authors' scenario timeouts; an import-path scenario without one gets 20 s;
    a duration given is kept."""
    assert [ScenarioParams(scenario=s).duration_s for s in ("overtaking", "left_turn", "red_light")] == [40, 30, 40]
    assert ScenarioParams(scenario=EXAMPLE).duration_s == 20.0
    assert ScenarioParams(scenario="overtaking", duration_s=7.5).duration_s == 7.5


def test_a_scenario_built_of_ints_still_goes_on_the_wire():
    """A user's builder may write ``np.array([[0, -100], [0, 100]])``: the map and the
    missions go out float64, as the wire declares them (the encoder refuses an int64
    array where float64 is declared)."""
    from dataclasses import replace

    from protocol.codec import decode, encode
    from protocol.messages import MapMsg, Mission
    from world_server.sim import Simulation

    sim = Simulation(ScenarioParams(scenario="left_turn", vehicles=4))
    roadmap, vid = sim.scenario.roadmap, sim.connected_vids[0]
    roadmap.buildings = np.rint(roadmap.buildings).astype(np.int64)
    roadmap.drivable = [np.rint(p).astype(np.int64) for p in roadmap.drivable]
    sim.scenario.actors[vid] = replace(sim.scenario.actors[vid], route=np.rint(sim.scenario.actors[vid].route).astype(int))
    got = decode(encode(roadmap.to_msg()), MapMsg)
    assert got.buildings.dtype == np.float64 and got.buildings.tolist() == roadmap.buildings.tolist()
    mission = decode(encode(sim.mission(vid)), Mission)
    assert mission.route.tolist() == sim.scenario.actors[vid].route.tolist()
