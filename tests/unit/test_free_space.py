"""Moved points (algo.free_space) and the scan tracker that leaves them out: people walking
in the corridors must not drag the tracked motion, and a static world loses no point."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lrfslam.algo import scan_match as sm
from lrfslam.algo.free_space import MAX_SPREAD_BINS, FreeSpace, seen_through
from lrfslam.algo.geometry import compose, polar_to_xy
from lrfslam.algo.scan_match import ScanMatchParams, ScanTracker
from lrfslam.errors import InputError
from lrfslam.sim.floor_plans import build_world
from lrfslam.sim.lidar import LidarModel, simulate_scan
from lrfslam.sim.simulator import SimConfig, Simulator

BIN = sm.FREE_SPACE_BIN_RAD
P = ScanMatchParams()
MARGINS = (sm.FREE_SPACE_MARGIN_M, sm.FREE_SPACE_MARGIN_PER_M, sm.FREE_SPACE_LATERAL_M, sm.FREE_SPACE_BEARING_RAD)
LIDAR = LidarModel()  # 1 cm noise, 1 cm quantum, mixed pixels
# Mixed pixels lie between an edge and what is behind it, in space seen empty from elsewhere:
# rightly left out by the check, so the static-world properties are without them.
SOLID = LidarModel(mixed_pixel_prob=0.0)
HALL = build_world("hallway_loop")


def returns(world, pose, rng, lidar=LIDAR):
    scan = simulate_scan(world, pose, lidar, rng)
    ok = np.isfinite(scan.ranges_m) & (scan.ranges_m < LIDAR.max_range_m)
    return polar_to_xy(scan.ranges_m[ok], scan.angles_rad[ok])


def world_points(xy, pose):
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return xy @ np.array([[c, s], [-s, c]]) + pose[:2]


def test_a_point_nearer_than_every_return_of_its_bearing_is_inside_and_unknown_space_condemns_nothing():
    # Returns at 5 m over the front half; nothing behind.
    angles = np.radians(np.arange(-90.0, 90.5, 1.0))
    free = FreeSpace.of_scan(np.zeros(3), polar_to_xy(np.full(angles.size, 5.0), angles), BIN, 8.0)
    ahead = np.array([[2.0, 0.0], [4.5, 0.0], [4.9, 0.0], [-2.0, 0.0], [6.0, 0.0]])
    # 2 m is 3 m short of the wall (inside); 4.5 and 4.9 m are within the margin; behind: no return.
    assert free.contains(ahead, *MARGINS).tolist() == [True, False, False, False, False]


def test_a_point_beside_an_edge_is_kept_when_a_neighbouring_beam_stopped_near_it():
    # A wall at 5 m with a 3 m pillar in one bearing: the pillar's bin guards its neighbours.
    angles = np.radians(np.arange(-90.0, 90.5, 1.0))
    ranges = np.where(np.isclose(angles, 0.0), 3.0, 5.0)
    free = FreeSpace.of_scan(np.zeros(3), polar_to_xy(ranges, angles), BIN, 8.0)
    beside = polar_to_xy(np.array([2.9, 2.9, 2.9]), np.radians([1.0, 0.0, -1.0]))
    assert not free.contains(beside, *MARGINS).any()


def test_a_bin_width_must_be_positive():
    with pytest.raises(InputError):
        FreeSpace.of_scan(np.zeros(3), np.zeros((0, 2)), 0.0, 8.0)


@settings(max_examples=60, deadline=None)
@given(x=st.floats(1.0, 15.0), y=st.floats(-1.3, -0.7), heading=st.floats(-0.4, 0.4),
       dx=st.floats(-0.9, 0.9), dy=st.floats(-0.2, 0.2), dheading=st.floats(-0.3, 0.3),
       error_m=st.floats(-0.02, 0.02), error_rad=st.floats(-0.01, 0.01), seed=st.integers(0, 2**16))
def test_a_static_world_seen_from_two_poses_has_no_moved_point(x, y, heading, dx, dy, dheading, error_m, error_rad,
                                                                seed):
    rng = np.random.default_rng(seed)
    a = np.array([x, y, heading])
    b = compose(a, np.array([dx, dy, dheading]))
    free = FreeSpace.of_scan(a, returns(HALL, a, rng, lidar=SOLID), BIN, SOLID.max_range_m)
    # The second scan placed with the error of a tracker's guess: an odometry step's, a slip's at worst.
    placed = world_points(returns(HALL, b, rng, lidar=SOLID), b + [error_m, -error_m, error_rad])
    assert not free.contains(placed, *MARGINS).any()


@pytest.mark.parametrize("check", [True, False])
def test_people_walking_in_the_corridors_do_not_drag_the_tracked_motion(check):
    # The first 400 scans (40 s) of the simulated building with people, run 1: a person walks
    # towards the robot down a corridor from about scan 137 (docs/slam.md, "On the simulator").. The tracker alone, chained, against the truth.
    sim = Simulator(SimConfig(world_name="large_building_people", seed=1))
    tracker = ScanTracker(ScanMatchParams(free_space_check=check))
    est, errors, moved = None, [], 0
    for k in range(400):
        frame = next(sim)
        ok = np.isfinite(frame.scan.ranges_m)
        step = tracker.step(polar_to_xy(frame.scan.ranges_m[ok], frame.scan.angles_rad[ok]),
                            frame.odom_delta if k else np.zeros(3), np.diag([0.02**2, 0.02**2, 0.01**2]))
        est = frame.true_pose.copy() if est is None else compose(est, step.increment)
        errors.append(np.hypot(*(est[:2] - frame.true_pose[:2])))
        moved += step.moved_points
    if check:
        assert moved > 0 and max(errors) < 0.15, (moved, max(errors))
    else:
        # Without the check the person drags the chain along the corridor (the failure it removes).
        assert max(errors) > 0.5, max(errors)


def test_a_static_walk_round_the_hallway_leaves_out_no_point():
    tracker = ScanTracker(ScanMatchParams())
    rng = np.random.default_rng(5)
    pose = np.array([1.0, -1.0, 0.0])          # along the hallway's south corridor
    for k in range(100):
        step = tracker.step(returns(HALL, pose, rng, lidar=SOLID), np.array([0.1, 0.0, 0.0]) if k else np.zeros(3),
                            np.diag([0.01**2, 0.01**2, 0.005**2]))
        assert step.moved_points == 0
        pose = compose(pose, np.array([0.1, 0.0, 0.0]))


def contains_by_hand(free, points, margin_m, margin_per_m, lateral_m, bearing_rad):
    """The definition of FreeSpace.contains, point by point: every bin within the margin across the
    beam, and one more on each side, saw empty space beyond the point's range plus its margin."""
    out = []
    n_bins = free.nearest_m.size
    for x, y in points:
        c, s = np.cos(free.pose[2]), np.sin(free.pose[2])
        lx, ly = c * (x - free.pose[0]) + s * (y - free.pose[1]), -s * (x - free.pose[0]) + c * (y - free.pose[1])
        r = np.hypot(lx, ly)
        k = min(int((np.arctan2(ly, lx) + np.pi) / free.bin_rad), n_bins - 1)
        spread = min(max(np.ceil((lateral_m / max(r, 1e-9) + bearing_rad) / free.bin_rad), 1) + 1, MAX_SPREAD_BINS)
        out.append(all(free.nearest_m[(k + o) % n_bins] > r + margin_m + margin_per_m * r
                       for o in range(-int(spread), int(spread) + 1)))
    return np.array(out, dtype=bool)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**16), n=st.integers(0, 60), pose=st.tuples(st.floats(-2, 2), st.floats(-2, 2),
                                                                        st.floats(-3.1, 3.1)))
def test_contains_is_its_definition(seed, n, pose):
    rng = np.random.default_rng(seed)
    angles = np.radians(np.arange(-90.0, 90.5, 1.0))
    ranges = rng.uniform(0.3, 9.0, angles.size)
    ranges[rng.random(angles.size) < 0.2] = np.nan                      # no returns
    ok = np.isfinite(ranges)
    free = FreeSpace.of_scan(np.array(pose), polar_to_xy(ranges[ok], angles[ok]), BIN, 8.0)
    points = rng.uniform(-8.0, 8.0, (n, 2)) + np.array(pose[:2])
    np.testing.assert_array_equal(free.contains(points, *MARGINS), contains_by_hand(free, points, *MARGINS))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**16), n=st.integers(0, 60), k=st.integers(0, 4))
def test_seen_through_is_any_of_its_spaces(seed, n, k):
    rng = np.random.default_rng(seed)
    angles = np.radians(np.arange(-90.0, 90.5, 1.0))
    spaces = []
    for _ in range(k):
        ranges = rng.uniform(0.3, 9.0, angles.size)
        ranges[rng.random(angles.size) < 0.2] = np.nan
        ok = np.isfinite(ranges)
        pose = np.array([*rng.uniform(-2.0, 2.0, 2), rng.uniform(-3.1, 3.1)])
        spaces.append(FreeSpace.of_scan(pose, polar_to_xy(ranges[ok], angles[ok]), BIN, 8.0))
    points = rng.uniform(-8.0, 8.0, (n, 2))
    expected = np.zeros(n, dtype=bool)
    for free in spaces:
        expected |= contains_by_hand(free, points, *MARGINS)
    np.testing.assert_array_equal(seen_through(spaces, points, *MARGINS), expected)
