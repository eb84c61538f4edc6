"""Ray casting against analytic distances, and the LMS200 error model."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lrfslam.errors import ConfigError
from lrfslam.sim.floor_plans import doorway_room, hallway_loop, straight_wall
from lrfslam.sim.lidar import LidarModel, first_hit, raycast, simulate_scan

ANGLES = LidarModel().angles_rad()


def test_beam_layout_is_lms200():
    assert len(ANGLES) == 181
    np.testing.assert_allclose(ANGLES[[0, 90, 180]], [-np.pi / 2, 0.0, np.pi / 2], atol=1e-12)


def test_wall_ahead_gives_distance_over_cosine():
    seg = straight_wall(length_m=100.0, distance_m=2.0).segments_m
    r = raycast(seg, (0.0, 0.0, 0.0), ANGLES)
    inside = np.abs(ANGLES) < np.radians(80)
    np.testing.assert_allclose(r[inside], 2.0 / np.cos(ANGLES[inside]), rtol=1e-12)
    # Beams at exactly ±90° run parallel to the wall and never hit it.
    assert np.isinf(r[0]) and np.isinf(r[-1])


@settings(max_examples=60, deadline=None)
@given(
    x=st.floats(-5, 5),
    y=st.floats(-5, 5),
    theta=st.floats(-np.pi, np.pi),
    dist=st.floats(0.2, 6.0),
    normal=st.floats(-np.pi, np.pi),
)
def test_raycast_matches_plane_distance_for_any_pose(x, y, theta, dist, normal):
    # A long wall whose closest point to the sensor is `dist` away along `normal`.
    n = np.array([np.cos(normal), np.sin(normal)])
    t = np.array([-n[1], n[0]])
    foot = np.array([x, y]) + dist * n
    seg = np.array([[*(foot - 1e4 * t), *(foot + 1e4 * t)]])
    r = raycast(seg, (x, y, theta), ANGLES)
    cos_inc = np.cos(theta + ANGLES - normal)
    facing = cos_inc > 0.05
    np.testing.assert_allclose(r[facing], dist / cos_inc[facing], rtol=1e-8)
    assert np.all(np.isinf(r[cos_inc < -1e-9]))


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31), max_range=st.floats(0.5, 12.0))
def test_walls_out_of_range_left_out_change_nothing(seed, max_range):
    """The broad phase (walls farther than the range are not intersected) gives what intersecting
    every wall and cutting at the range gives: the same ranges and the same wall indices."""
    rng = np.random.default_rng(seed)
    seg = rng.uniform(-10, 10, (40, 4))
    seg[:5] = np.round(seg[:5])   # some walls sharing vertices with others
    pose = (*rng.uniform(-5, 5, 2), rng.uniform(-np.pi, np.pi))
    ranges, index = first_hit(seg, pose, ANGLES, max_range)
    every, every_index = first_hit(seg, pose, ANGLES)
    beyond = every > max_range
    np.testing.assert_array_equal(ranges, np.where(beyond, np.inf, every))
    np.testing.assert_array_equal(index, np.where(beyond, -1, every_index))


def test_nearest_of_two_walls_wins_and_max_range_cuts():
    seg = np.vstack((straight_wall(10, 3.0).segments_m, straight_wall(10, 1.5).segments_m))
    r = raycast(seg, (0, 0, 0), np.array([0.0]))
    assert r[0] == pytest.approx(1.5)
    assert np.isinf(raycast(seg, (0, 0, 0), np.array([0.0]), max_range_m=1.4)[0])


def test_ray_through_a_shared_vertex_does_not_leak():
    # Closed square room; beams aimed exactly at its corners must still hit.
    from lrfslam.sim.world import closed_polygon

    seg = closed_polygon([(-1, -1), (1, -1), (1, 1), (-1, 1)], free_inside=True)
    r = raycast(seg, (0, 0, 0), np.radians([45.0, 135.0, -45.0, -135.0]))
    np.testing.assert_allclose(r, np.sqrt(2.0), rtol=1e-12)


def test_pose_heading_rotates_the_beams():
    seg = straight_wall(100.0, 2.0).segments_m
    r = raycast(seg, (0, 0, np.radians(30.0)), np.array([-np.radians(30.0)]))
    assert r[0] == pytest.approx(2.0)


def _quiet(**changes):
    base = LidarModel(range_sigma_m=0.0, quantum_m=0.0, mixed_pixel_prob=0.0)
    return dataclasses.replace(base, **changes)


def test_noise_statistics_match_sigma():
    world = straight_wall(1e5, 2.0)
    rng = np.random.default_rng(3)
    # With no range limit the wall returns beams 1..179; beams at exactly ±90° run parallel to it.
    model = _quiet(range_sigma_m=0.01, max_range_m=1e6)
    err = np.concatenate(
        [
            s.ranges_m[1:-1] - s.true_ranges_m[1:-1]
            for s in (simulate_scan(world, (0, 0, 0), model, rng) for _ in range(50))
        ]
    )
    assert err.size == 179 * 50
    assert abs(np.std(err) - 0.01) < 0.2 * 0.01
    assert abs(np.mean(err)) < 0.001


def test_ranges_are_quantised_to_one_centimetre():
    s = simulate_scan(hallway_loop(), (8.0, -1.0, 0.3), LidarModel(), np.random.default_rng(1))
    finite = s.ranges_m[np.isfinite(s.ranges_m)]
    assert len(finite) > 150
    np.testing.assert_allclose(finite / 0.01, np.round(finite / 0.01), atol=1e-9)


def test_noise_free_scan_equals_truth():
    s = simulate_scan(hallway_loop(), (8.0, -1.0, 0.3), _quiet(), np.random.default_rng(0))
    np.testing.assert_array_equal(s.ranges_m, s.true_ranges_m)
    assert not s.spurious.any()


def test_no_return_beyond_max_range():
    model = _quiet(max_range_m=3.0)
    s = simulate_scan(straight_wall(100.0, 2.0), (0, 0, 0), model, np.random.default_rng(0))
    assert np.all(np.isinf(s.ranges_m[np.abs(s.angles_rad) > np.arccos(2.0 / 3.0) + 1e-9]))
    assert np.all(np.isfinite(s.ranges_m[np.abs(s.angles_rad) < np.arccos(2.0 / 3.0) - 1e-9]))


def test_mixed_pixels_sit_between_the_surfaces_of_a_depth_edge():
    # Looking through the doorway: jambs at 1 m, far wall at 3.5 m.
    model = _quiet(mixed_pixel_prob=1.0)
    world = doorway_room()
    for seed in range(20):
        s = simulate_scan(world, (0.0, 0.0, 0.0), model, np.random.default_rng(seed))
        t = s.true_ranges_m
        pair_finite = np.isfinite(t[:-1]) & np.isfinite(t[1:])
        jump = np.zeros(len(t) - 1, dtype=bool)
        jump[pair_finite] = np.abs(t[1:][pair_finite] - t[:-1][pair_finite]) > 0.3
        at_edge = np.zeros_like(s.spurious)
        at_edge[:-1] |= jump
        at_edge[1:] |= jump
        assert s.spurious.any()
        assert np.all(at_edge[s.spurious])
        for i in np.flatnonzero(s.spurious):
            near = min(t[i - 1], t[i + 1])  # inf neighbours never form an edge
            # Blended range r = w*far + (1-w)*near with w in [0.2, 0.8].
            w = (s.ranges_m[i] - near) / (t[i] - near)
            assert 0.2 <= w <= 0.8
        assert np.array_equal(s.ranges_m[~s.spurious], t[~s.spurious])


def test_mixed_pixel_probability_is_respected():
    model = _quiet(mixed_pixel_prob=0.3)
    world = doorway_room()
    rng = np.random.default_rng(5)
    hits = sum(simulate_scan(world, (0, 0, 0), model, rng).spurious.sum() for _ in range(400))
    # Two depth edges per scan (one at each jamb).
    assert abs(hits / 800 - 0.3) < 0.05


def test_dropouts_report_no_return():
    model = _quiet(dropout_prob=0.5)
    rng = np.random.default_rng(2)
    s = simulate_scan(straight_wall(100.0, 2.0), (0, 0, 0), model, rng)
    lost = np.isinf(s.ranges_m[10:-10])
    assert 0.3 < lost.mean() < 0.7


def test_same_seed_same_scan():
    w = hallway_loop()
    a = simulate_scan(w, (3.0, -1.0, 0.2), LidarModel(), np.random.default_rng(42))
    b = simulate_scan(w, (3.0, -1.0, 0.2), LidarModel(), np.random.default_rng(42))
    np.testing.assert_array_equal(a.ranges_m, b.ranges_m)
    np.testing.assert_array_equal(a.spurious, b.spurious)


@pytest.mark.parametrize(
    "changes", [{"n_beams": 1}, {"max_range_m": 0.0}, {"range_sigma_m": -1.0}, {"mixed_pixel_prob": 1.5}]
)
def test_invalid_model_is_a_config_error(changes):
    with pytest.raises(ConfigError):
        LidarModel(**changes)


def test_range_bias_shifts_every_return():
    s = simulate_scan(straight_wall(100.0, 2.0), (0, 0, 0), _quiet(), np.random.default_rng(0), range_bias_m=0.05)
    finite = np.isfinite(s.true_ranges_m)
    np.testing.assert_allclose(s.ranges_m[finite], s.true_ranges_m[finite] + 0.05, rtol=1e-12)
