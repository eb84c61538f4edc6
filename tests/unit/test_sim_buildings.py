"""The worlds that break the filter: large_building and twin_corridors, glass, clutter and people."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lrfslam.errors import ConfigError
from lrfslam.sim.buildings import (
    CAMPUS_DOOR_PERIOD_M,
    TWIN_A_X_M,
    TWIN_SHIFT_M,
    Feature,
    alike,
    box,
    campus,
    large_building,
    outline,
    recess,
    twin_corridors,
)
from lrfslam.sim.floor_plans import (
    build_world,
    l_corner,
    scenario,
    waypoints,
    world_names,
)
from lrfslam.sim.lidar import LidarModel, raycast, simulate_scan
from lrfslam.sim.people import PERSON_SIDES, Walkers, body_segments, draw_walkers
from lrfslam.sim.simulator import SimConfig, Simulator
from lrfslam.sim.trajectory import loop_path
from lrfslam.sim.truth import visible_corners, visible_points
from lrfslam.sim.world import World

QUIET = LidarModel(range_sigma_m=0.0, quantum_m=0.0, mixed_pixel_prob=0.0)


def _point_segment_distance(points, seg):
    a, b = seg[None, :, :2], seg[None, :, 2:]
    p = points[:, None, :]
    ab = b - a
    u = np.clip(np.sum((p - a) * ab, axis=-1) / np.sum(ab * ab, axis=-1), 0.0, 1.0)
    return np.hypot(*(p - (a + u[..., None] * ab)).transpose(2, 0, 1))


def _path_samples(name, n=20000):
    path = loop_path(waypoints(name), 0.8)
    return path, path.pose_at(np.linspace(0.0, path.total_length_m, n, endpoint=False))


# --- registry ------------------------------------------------------------------------------


def test_new_worlds_are_registered_with_their_defaults():
    assert {"hallway_loop", "large_building", "twin_corridors"} <= set(world_names())
    assert build_world("large_building").name == "large_building"
    assert scenario("large_building").n_walkers > 0
    assert scenario("large_building").odometry_error.distance_scale != 0
    assert scenario("twin_corridors").n_walkers == 0
    assert scenario("hallway_loop").n_walkers == 0
    with pytest.raises(ConfigError):
        scenario("no_such_world")


# --- large_building ------------------------------------------------------------------------


def test_large_building_lap_is_long_and_its_first_revisit_comes_after_150_m():
    path, poses = _path_samples("large_building")
    assert path.total_length_m >= 250.0
    s = np.linspace(0.0, path.total_length_m, len(poses), endpoint=False)
    # The robot comes back within 1 m of where it started only after the outer loop.
    back = s[(np.hypot(*(poses[:, :2] - poses[0, :2]).T) < 1.0) & (s > 5.0)]
    assert back.min() >= 150.0


def test_large_building_has_long_corridors_with_few_corners():
    w = large_building()
    legs = np.diff(np.vstack((waypoints("large_building"), waypoints("large_building")[:1])), axis=0)
    assert np.all((legs[:, 0] == 0) | (legs[:, 1] == 0))
    assert np.hypot(*legs.T).max() >= 30.0
    # Corners with both walls long enough for the 1.2 m search arms are sparse: on average
    # more than 2 m of driving per such corner within 4 m (hallway_loop: about 1 per metre).
    c = w.corners()
    long_armed = c.xy_m[np.all(c.wall_lengths_m >= 1.2, axis=1)]
    _, poses = _path_samples("large_building", 3000)
    near = np.hypot(*(poses[:, None, :2] - long_armed[None]).transpose(2, 0, 1)) < 4.0
    assert np.mean(near.sum(axis=1) == 0) > 0.15  # stretches where no such corner is in reach


def test_large_building_repeats_the_same_place():
    # Block faces carry one feature pattern: the corners of the face beside the corridor, put
    # in the frame of a robot driving past its middle, are the same on several faces.
    c = large_building().corners().xy_m

    def block_face_view(centre, side):
        local = (c - centre) * [1.0, side]  # side -1 mirrors a face below the corridor
        return local[(np.abs(local[:, 0]) < 9.0) & (local[:, 1] > 0.9) & (local[:, 1] < 3.0)]

    sort = lambda p: p[np.lexsort((p[:, 1], p[:, 0]))]
    views = [block_face_view((12.0, 0.0), 1.0), block_face_view((12.0, 30.0), -1.0),
             block_face_view((36.0, 30.0), -1.0)]
    assert len(views[0]) >= 16
    for other in views[1:]:
        np.testing.assert_allclose(sort(other), sort(views[0]), atol=1e-9)


def test_large_building_path_keeps_to_corridors_clear_of_walls_and_clutter():
    w = large_building()
    _, poses = _path_samples("large_building")
    clearance = _point_segment_distance(poses[:, :2], w.segments_m).min(axis=1)
    # A Pioneer's 0.25 m half width plus 0.15 m; the closest is the pillar in the top corridor.
    assert clearance.min() >= 0.4


def test_large_building_walls_are_manhattan():
    w = large_building()
    seg = w.segments_m[w.material != "clutter"]
    dx, dy = seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1]
    assert np.all((np.abs(dx) < 1e-12) ^ (np.abs(dy) < 1e-12))
    np.testing.assert_allclose(w.corners().angle_deg, 90.0)


def test_large_building_has_an_inner_loop_through_the_middle_corridor():
    _, poses = _path_samples("large_building")
    middle = (np.abs(poses[:, 0] - 24.0) < 0.1) & (poses[:, 1] > 5.0) & (poses[:, 1] < 25.0)
    assert middle.any()
    # The top-left corridor is driven twice (outer loop, then the left loop), the top-right once.
    top_left = (np.abs(poses[:, 1] - 30.0) < 0.1) & (np.abs(poses[:, 0] - 12.0) < 0.05)
    top_right = (np.abs(poses[:, 1] - 30.0) < 0.1) & (np.abs(poses[:, 0] - 36.0) < 0.05)
    runs = lambda mask: int(np.sum(np.diff(mask.astype(int)) == 1) + mask[0])
    assert runs(top_left) == 2 and runs(top_right) == 1


# --- glass ---------------------------------------------------------------------------------


def test_outside_window_gives_no_return_and_the_wall_beside_it_does():
    w = large_building()
    # From the top corridor, looking straight up: x = 41 is behind the window (44..38), x = 46 is wall.
    angles = np.array([0.0])
    assert np.isinf(raycast(w.opaque_segments_m, (41.0, 30.0, np.pi / 2), angles, 8.0))[0]
    np.testing.assert_allclose(raycast(w.opaque_segments_m, (46.0, 30.0, np.pi / 2), angles, 8.0), [1.0])
    scan = simulate_scan(w, (41.0, 30.0, np.pi / 2), QUIET, np.random.default_rng(0))
    centre = np.argmin(np.abs(scan.angles_rad))
    assert np.isinf(scan.ranges_m[centre]) and np.isinf(scan.true_ranges_m[centre])


def test_glass_front_lets_the_scanner_see_into_the_room():
    w = large_building()
    # In front of the meeting room (x 33..39, y 1..5) looking north: the beam crosses the glass
    # at y = 1 and stops at the room's back wall, 5 m away.
    r = raycast(w.opaque_segments_m, (36.0, 0.0, np.pi / 2), np.array([0.0]), 8.0)
    np.testing.assert_allclose(r, [5.0])
    assert raycast(w.segments_m, (36.0, 0.0, np.pi / 2), np.array([0.0]), 8.0)[0] == pytest.approx(1.0)


def test_glass_is_not_part_of_the_map():
    seg = np.array([[0.0, 0.0, 2.0, 0.0], [2.0, 0.0, 2.0, 2.0]])
    walls = World(seg, "wall_corner")
    glassy = World(seg, "glass_corner", material=np.array(["wall", "glass"]))
    assert len(walls.corners()) == 1 and len(walls.free_endpoints()) == 2
    # A wall meeting a glass pane ends, to the scanner, in a jump edge.
    assert len(glassy.corners()) == 0 and len(glassy.free_endpoints()) == 2
    with pytest.raises(ConfigError):
        World(seg, "bad", material=np.array(["wall", "paper"]))


# --- clutter -------------------------------------------------------------------------------


def test_clutter_reflects_but_adds_no_corner():
    room = outline([(0.0, 0.0), (6.0, 0.0), (6.0, 4.0), (0.0, 4.0)], [(), (), (), ()])
    crate = box(3.0, 1.0, 3.6, 1.5)
    bare = World(room[0], "room", material=room[1])
    cluttered = World(np.vstack((room[0], crate)), "room", material=np.concatenate((room[1], ["clutter"] * 4)))
    np.testing.assert_array_equal(cluttered.corners().xy_m, bare.corners().xy_m)
    r = raycast(cluttered.opaque_segments_m, (1.0, 1.25, 0.0), np.array([0.0]), 8.0)
    np.testing.assert_allclose(r, [2.0])


def test_large_building_clutter_is_marked_and_off_the_map():
    w = large_building()
    clutter = w.segments_m[w.material == "clutter"].reshape(-1, 2)
    assert len(clutter) >= 8
    d = np.hypot(*(w.corners().xy_m[:, None] - clutter[None]).transpose(2, 0, 1))
    assert d.min() > 0.2


# --- people --------------------------------------------------------------------------------


def test_walkers_pace_their_lanes_back_and_forth():
    w = Walkers(lanes_m=[[0.0, 0.0, 4.0, 0.0]], speed_mps=np.array([1.0]), phase_m=np.array([0.0]))
    np.testing.assert_allclose(w.positions(1.0), [[1.0, 0.0]])
    np.testing.assert_allclose(w.positions(4.0), [[4.0, 0.0]])
    np.testing.assert_allclose(w.positions(5.0), [[3.0, 0.0]])
    np.testing.assert_allclose(w.positions(8.0), [[0.0, 0.0]], atol=1e-12)
    t = np.linspace(0.0, 30.0, 301)
    xy = np.array([w.positions(ti)[0] for ti in t])
    assert xy[:, 0].min() >= 0.0 and xy[:, 0].max() <= 4.0


def test_a_person_blocks_the_beams_behind_it_and_the_corners_it_hides():
    corner_world = l_corner()  # a concave corner at (2, 0), seen from the origin
    person = body_segments([(1.0, 0.0)], 0.2)
    assert len(person) == PERSON_SIDES
    free = simulate_scan(corner_world, (0.0, 0.0, 0.0), QUIET, np.random.default_rng(1))
    blocked = simulate_scan(corner_world, (0.0, 0.0, 0.0), QUIET, np.random.default_rng(1), movers_m=person)
    ahead = np.argmin(np.abs(free.angles_rad))
    assert free.true_ranges_m[ahead] == pytest.approx(2.0)
    assert blocked.true_ranges_m[ahead] == pytest.approx(0.8)
    assert blocked.on_mover[ahead] and not free.on_mover.any()
    assert 15 <= blocked.on_mover.sum() <= 30  # a 0.4 m body at 1 m covers about 23°
    assert visible_corners(corner_world, (0.0, 0.0, 0.0)).tolist() == [0]
    assert visible_corners(corner_world, (0.0, 0.0, 0.0), movers_m=person).tolist() == []
    assert visible_points(corner_world, (0.0, 0.0, 0.0), [[2.0, 0.0]], movers_m=person).tolist() == [False]


def test_people_in_the_large_building_move_occlude_and_are_not_corners():
    assert len(Simulator(SimConfig(world_name="large_building")).walkers) == scenario("large_building").n_walkers
    # A crowd, so that a short stretch of the bottom corridor meets some of them.
    sim = Simulator(SimConfig(world_name="large_building", lidar=QUIET, n_walkers=20, seed=3))
    frames = list(itertools.islice(sim, 600))
    track = np.array([f.walkers_xy for f in frames])  # (T, P, 2)
    assert np.all(np.hypot(*(track - track[0]).T).max(axis=1) > 5.0)  # everybody walked
    lanes = scenario("large_building").walker_lanes_m
    for f in frames[::20]:
        on_a_lane = _point_segment_distance(f.walkers_xy, lanes).min(axis=1)
        assert on_a_lane.max() < 1e-9
    hidden = [f for f in frames if f.scan.on_mover.any()]
    assert len(hidden) >= 20
    # Where a person is hit, the beam stops short of the static world.
    f = hidden[0]
    static = raycast(sim.world.opaque_segments_m, f.true_pose, f.scan.angles_rad, QUIET.max_range_m)
    assert np.all(f.scan.true_ranges_m[f.scan.on_mover] < static[f.scan.on_mover])
    corners = sim.map_corners.xy_m
    assert np.hypot(*(corners[:, None] - frames[0].walkers_xy[None]).transpose(2, 0, 1)).min() > 0.2


def test_walkers_are_seeded_and_zero_walkers_is_the_static_world():
    a = Simulator(SimConfig(world_name="large_building", seed=5)).walkers
    b = Simulator(SimConfig(world_name="large_building", seed=5)).walkers
    c = Simulator(SimConfig(world_name="large_building", seed=6)).walkers
    np.testing.assert_array_equal(a.positions(12.3), b.positions(12.3))
    assert not np.array_equal(a.positions(12.3), c.positions(12.3))
    none = Simulator(SimConfig(world_name="large_building", n_walkers=0))
    f = next(none)
    assert f.walkers_xy.shape == (0, 2) and not f.scan.on_mover.any()
    with pytest.raises(ConfigError):
        draw_walkers(np.zeros((0, 4)), 2, np.random.default_rng(0))


# --- twin corridors ------------------------------------------------------------------------


def _in_box(points, x_range):
    return points[(points[:, 0] >= x_range[0]) & (points[:, 0] <= x_range[1]) & (np.abs(points[:, 1]) < 3.0)]


def test_twin_corridors_are_congruent():
    w = twin_corridors()
    a_range = TWIN_A_X_M
    b_range = (a_range[0] + TWIN_SHIFT_M, a_range[1] + TWIN_SHIFT_M)
    c = w.corners()
    a, b = _in_box(c.xy_m, a_range), _in_box(c.xy_m, b_range)
    assert len(a) >= 20
    order = lambda p: p[np.lexsort((p[:, 1], p[:, 0]))]
    np.testing.assert_allclose(order(a + [TWIN_SHIFT_M, 0.0]), order(b), atol=1e-9)
    # The link between them is unlike either.
    link = _in_box(c.xy_m, (a_range[1] + 0.5, b_range[0] - 0.5))
    assert len(link) > 0


@pytest.mark.parametrize("along_m", [0.5, 3.0, 6.0, 10.0])
def test_twin_corridors_look_the_same_from_the_same_place_in_each(along_m):
    w = twin_corridors()
    angles = LidarModel().angles_rad()
    pose_a = np.array([TWIN_A_X_M[0] + along_m, 0.0, 0.0])
    pose_b = pose_a + [TWIN_SHIFT_M, 0.0, 0.0]
    ra = raycast(w.opaque_segments_m, pose_a, angles, 8.0)
    rb = raycast(w.opaque_segments_m, pose_b, angles, 8.0)
    np.testing.assert_allclose(ra, rb, atol=1e-9)
    assert np.isfinite(ra).sum() > 150


def test_twin_corridors_path_drives_both_twins_the_same_way():
    _, poses = _path_samples("twin_corridors")
    for lo, hi in (TWIN_A_X_M, (TWIN_A_X_M[0] + TWIN_SHIFT_M, TWIN_A_X_M[1] + TWIN_SHIFT_M)):
        inside = (poses[:, 0] > lo) & (poses[:, 0] < hi) & (np.abs(poses[:, 1]) < 0.5)
        assert inside.sum() > 100
        np.testing.assert_allclose(poses[inside, 2], 0.0, atol=1e-9)
    clearance = _point_segment_distance(poses[:, :2], twin_corridors().segments_m).min(axis=1)
    assert clearance.min() >= 0.5


# --- campus --------------------------------------------------------------------------------


def test_campus_laps_are_long_and_first_come_back_after_350_m():
    path, poses = _path_samples("campus")
    assert path.total_length_m >= 500.0
    s = np.linspace(0.0, path.total_length_m, len(poses), endpoint=False)
    back = s[(np.hypot(*(poses[:, :2] - poses[0, :2]).T) < 1.0) & (s > 5.0)]
    assert back.min() >= 350.0
    assert scenario("campus").odometry_error.heading_drift_rad_per_m != 0
    clearance = _point_segment_distance(poses[:, :2], campus().opaque_segments_m).min(axis=1)
    assert clearance.min() >= 0.9


@pytest.mark.parametrize("x_m", [86.0, 100.0, 118.0])
def test_campus_corridors_look_the_same_every_door_period(x_m):
    # The wing's bottom corridor, driving east: a scan and the one a door period on are alike.
    w = campus()
    angles = LidarModel().angles_rad()
    here = raycast(w.opaque_segments_m, np.array([x_m, 0.0, 0.0]), angles, 8.0)
    on = raycast(w.opaque_segments_m, np.array([x_m + CAMPUS_DOOR_PERIOD_M, 0.0, 0.0]), angles, 8.0)
    seen = np.isfinite(here) & np.isfinite(on)
    assert seen.sum() > 150
    assert np.median(np.abs(here[seen] - on[seen])) < 1e-6


def test_campus_courtyard_crossing_is_nearly_blind():
    # Halfway across the courtyard the 8 m scanner sees a pillar and nothing else.
    w = campus()
    ranges = raycast(w.opaque_segments_m, np.array([40.0, 25.0, np.pi / 2]), LidarModel().angles_rad(), 8.0)
    assert 0 < np.isfinite(ranges).sum() < 20
    # From the ring's corridor the courtyard is behind glass: one side of the corridor is mostly open.
    ranges = raycast(w.opaque_segments_m, np.array([20.0, 0.0, 0.0]), LidarModel().angles_rad(), 8.0)
    assert (~np.isfinite(ranges[120:170])).mean() > 0.3


def test_alike_puts_a_door_every_period_but_where_an_odd_feature_stands():
    faces = alike(30.0, recess(9.5, 2.0, 1.4))
    assert [f.s_m for f in faces] == [3.0, 9.5, 15.0, 21.0, 27.0]   # the door at 9 would overlap the alcove
    assert [f.width_m for f in faces] == [0.9, 2.0, 0.9, 0.9, 0.9]


# --- outline helper ------------------------------------------------------------------------


def test_outline_rejects_overlapping_and_unknown_features():
    square = [(0.0, 0.0), (4.0, 0.0), (4.0, 4.0), (0.0, 4.0)]
    with pytest.raises(ConfigError):
        outline(square, [(recess(1.0, 1.0, 0.3), recess(1.5, 1.0, 0.3)), (), (), ()])
    with pytest.raises(ConfigError):
        outline(square, [(recess(3.5, 1.0, 0.3),), (), (), ()])
    with pytest.raises(ConfigError):
        outline(square, [(Feature("hole", 1.0, 1.0),), (), (), ()])
    with pytest.raises(ConfigError):
        outline(square, [()])


def test_large_building_variants_differ_from_it_in_one_ingredient_each():
    full = scenario("large_building")
    empty, uncalibrated, people = (scenario(f"large_building_{v}") for v in ("empty", "uncalibrated", "people"))
    for variant in (empty, uncalibrated, people):
        assert variant.build is full.build and variant.path is full.path
    assert empty.n_walkers == 0 and empty.odometry_error != full.odometry_error
    assert uncalibrated.n_walkers == 0 and uncalibrated.odometry_error == full.odometry_error
    assert people.n_walkers == full.n_walkers and people.odometry_error == empty.odometry_error
    np.testing.assert_array_equal(people.walker_lanes_m, full.walker_lanes_m)


def test_people_keep_clear_of_the_robot_path():
    _, poses = _path_samples("large_building", 6000)
    lanes = scenario("large_building").walker_lanes_m
    # Body radius 0.2 m: at least 0.3 m between the scanner and a passing person.
    assert _point_segment_distance(poses[:, :2], lanes).min() >= 0.5 - 1e-9


@st.composite
def _recess_lists(draw):
    """Non-overlapping recesses on a 10 m face, kept 2.1 m from its ends so no two faces' recesses meet."""
    n = draw(st.integers(0, 4))
    cuts = sorted(draw(st.lists(st.floats(2.1, 7.9), min_size=2 * n, max_size=2 * n, unique=True)))
    feats = []
    for a, b in zip(cuts[::2], cuts[1::2], strict=True):
        if b - a > 0.05 and (not feats or a - (feats[-1].s_m + feats[-1].width_m) > 0.05):
            feats.append(recess(a, b - a, draw(st.floats(0.1, 2.0))))
    return tuple(feats)


@settings(max_examples=40, deadline=None)
@given(faces=st.lists(_recess_lists(), min_size=4, max_size=4), free_inside=st.booleans())
def test_outline_of_recesses_is_a_manhattan_polygon_of_right_angle_corners(faces, free_inside):
    square = [(0.0, 0.0), (10.0, 0.0), (10.0, 10.0), (0.0, 10.0)]
    # A room is counter-clockwise, a solid block clockwise (free space on the left).
    seg, material = outline(square if free_inside else square[::-1], faces)
    w = World(seg, "outline", material=material)
    c = w.corners()
    assert len(c) == len(seg) and len(w.free_endpoints()) == 0
    np.testing.assert_allclose(c.angle_deg, 90.0)
    # A simple rectilinear polygon has four more convex than reflex vertices.
    inside, outside = (c.kind == "concave").sum(), (c.kind == "convex").sum()
    assert (inside - outside if free_inside else outside - inside) == 4
