"""Angle-histogram noise reduction and the mixed-pixel tests (algo.histogram, algo.mixed_pixels)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from lrfslam.algo.histogram import DenoiseParams, denoise, valid_returns
from lrfslam.algo.mixed_pixels import along_beam, beam_tables, depth_outliers, off_line
from lrfslam.errors import ConfigError
from lrfslam.sim.floor_plans import corridor_end, hallway_loop, straight_wall, waypoints
from lrfslam.sim.lidar import LidarModel, raycast, simulate_scan
from lrfslam.sim.trajectory import loop_path
from lrfslam.sim.world import World, polyline

ANGLES = np.radians(np.arange(-90.0, 91.0))
PAPER, DEFAULT = DenoiseParams.paper(), DenoiseParams.default()


def scan_of(world, pose=(0.0, 0.0, 0.0)):
    return raycast(world.segments_m, pose, ANGLES, 8.0)


def hallway_scans(n, sigma_m, seed=0):
    world, rng = hallway_loop(), np.random.default_rng(seed)
    path = loop_path(waypoints("hallway_loop"), 0.8)
    model = LidarModel(range_sigma_m=sigma_m)
    return [simulate_scan(world, path.pose_at(s), model, rng) for s in np.linspace(0, path.total_length_m, n, endpoint=False)]


def test_presets_differ_where_the_paper_is_silent():
    assert (PAPER.bin_deg, PAPER.period_deg, PAPER.shadow_min_angle_deg, PAPER.mixed_tol_m) == (10.0, 180.0, 0.0, 0.0)
    assert (DEFAULT.period_deg, DEFAULT.max_range_m, DEFAULT.keep_frac) == (90.0, 4.0, 0.15)
    assert (PAPER.bin_mode, DEFAULT.bin_mode, DEFAULT.mixed_model) == ("fixed", "sliding", "line")
    assert DEFAULT.mixed_tol_m > 0


@pytest.mark.parametrize(
    "change",
    [{"bin_deg": 20.0}, {"period_deg": 120.0}, {"keep_frac": 1.0}, {"stride": 0}, {"bin_mode": "wide"},
     {"keep_rule": "xor"}, {"jump_m": 0.0}, {"shadow_min_angle_deg": 95.0}, {"mixed_tol_m": -1.0},
     {"mixed_model": "cubic"}],
)
def test_bad_parameters_are_config_errors(change):
    with pytest.raises(ConfigError):
        dataclasses.replace(DEFAULT, **change)


def test_valid_returns_cut_at_max_range_and_reject_non_finite():
    r = np.array([np.nan, np.inf, -np.inf, 0.0, -1.0, 0.5, 4.0, 4.0001, 8.0])
    assert valid_returns(r, 4.0).tolist() == [False] * 5 + [True, True, False, False]


def test_eq1_beam_layout_points():
    r = np.full(181, 2.0)
    xy = denoise(r, ANGLES, DEFAULT).points_xy
    np.testing.assert_allclose(xy[[90, 0, 180]], [[2, 0], [0, -2], [0, 2]], atol=1e-12)


def test_beyond_max_range_is_not_kept():
    r = scan_of(straight_wall(20.0, 2.0))
    res = denoise(r, ANGLES, DEFAULT)
    assert not res.kept[r > 4.0].any() and res.kept[r <= 4.0].all()
    assert np.isnan(res.points_xy[r > 4.0]).all()


@pytest.mark.parametrize("params", [DEFAULT, dataclasses.replace(DEFAULT, bin_mode="fixed"), PAPER])
def test_noise_free_walls_are_kept(params):
    # Wall at y = -1 seen side on (a dy = 0 direction in the robot frame) and a wall ahead.
    r = scan_of(corridor_end(2.0, 6.0, 3.0))
    res = denoise(r, ANGLES, params)
    assert res.kept[res.valid].mean() == 1.0
    assert np.isfinite(res.hist_counts).all() and res.hist_counts.sum() == res.n_segments


def test_directions_0_180_and_minus_180_share_a_bin():
    # Points on one line through the beams: segments pointing at 0° and at 180°.
    xs = np.array([1.0, 2.0, 3.0, 2.0, 1.0, 2.0, 3.0])
    r, a = np.full(7, 1.0) * np.hypot(xs, 0.5), np.arctan2(np.full(7, 0.5), xs)
    res = denoise(r, a, dataclasses.replace(PAPER, keep_frac=0.0))
    assert res.hist_counts.max() == res.n_segments == 6


def test_coincident_points_give_no_nan_or_warning():
    # Repeated beams: dx = dy = 0 exactly (pytest turns RuntimeWarnings into errors).
    a = np.repeat(np.radians([10.0, 11.0, 12.0]), 3)
    res = denoise(np.full(9, 2.0), a, DEFAULT)
    assert np.isfinite(res.points_xy).all() and res.n_segments == 8


def test_single_outlier_half_a_metre_off_a_wall_is_removed_in_both_modes():
    r = scan_of(straight_wall(6.0, 2.0))
    r[100] -= 0.5
    for params in (PAPER, DEFAULT):
        res = denoise(r, ANGLES, params)
        assert not res.kept[100], params
        assert res.kept[res.valid].sum() >= res.valid.sum() - 3


def test_mixed_pixel_at_a_door_jamb_is_removed_and_the_jamb_kept():
    r = scan_of(straight_wall(1.0, 1.0))  # a 1 m wall ending at (1, ±0.5): background beyond 4 m
    r[r > 4.0] = 3.0  # a far wall behind
    jamb = np.flatnonzero(r < 2.0).max()
    r[jamb + 1] = 0.5 * (r[jamb] + 3.0)  # the beam straddling the edge returns a blend
    res = denoise(r, ANGLES, DEFAULT)
    assert res.mixed[jamb + 1] and not res.kept[jamb + 1]
    assert res.kept[jamb] and res.kept[jamb + 2]
    assert not denoise(r, ANGLES, dataclasses.replace(DEFAULT, mixed_tol_m=0.0)).mixed.any()


def test_along_beam_flags_the_blend_not_the_surfaces():
    r = np.array([1.0, 1.0, 1.0, 2.0, 3.0, 3.0, 3.0])
    a = np.radians(np.arange(7.0))
    xy = np.column_stack((r * np.cos(a), r * np.sin(a)))
    flags = along_beam(xy, np.ones(7, bool), 10.0)
    assert flags.tolist() == [False, False, False, True, False, False, False]
    assert not along_beam(xy, np.ones(7, bool), 0.0).any()


def test_depth_outliers_keep_corner_and_edge_points():
    r = np.array([2.0, 2.02, 2.04, 2.06, 2.04, 2.02, 2.0, 3.0, 3.0])
    flags = depth_outliers(r, np.ones(9, bool), 0.08)
    assert not flags[:7].any()  # a corner at index 3 and the near edge at index 6 stay
    r2 = r.copy()
    r2[7] = 2.5  # a blend between the edge and the far wall
    assert depth_outliers(r2, np.ones(9, bool), 0.08)[7]


def test_line_test_keeps_a_grazing_wall_and_removes_a_blend_on_it_unlike_the_range_trend():
    # A wall 0.4 m to the side, seen down to 6° incidence before the 4 m cut: its range
    # curves fast, so the linear range trend misses real points and vouches for a
    # point 10 cm short of the wall; the line through two neighbours does neither.
    r = scan_of(World(polyline([(-1.0, 0.4), (8.0, 0.4)]), "side_wall"))
    valid = valid_returns(r, 4.0)
    beams = beam_tables(ANGLES)
    assert not off_line(r, beams, valid, 0.08).any()
    assert depth_outliers(r, valid, 0.08).sum() >= 2
    blend = np.flatnonzero(valid)[3]
    r[blend] -= 0.10
    assert off_line(r, beams, valid, 0.08)[blend] and not depth_outliers(r, valid, 0.08)[blend]
    assert denoise(r, ANGLES, DEFAULT).mixed[blend]
    assert not denoise(r, ANGLES, dataclasses.replace(DEFAULT, mixed_model="range")).mixed[blend]


def test_line_test_keeps_corner_and_edge_points():
    r = scan_of(corridor_end(1.6, 6.0, 3.0))
    valid = valid_returns(r, 4.0)
    assert not off_line(r, beam_tables(ANGLES), valid, 0.08).any()


def test_paper_literal_removes_a_short_end_wall_that_the_fold_keeps():
    # Looking down a 1.6 m corridor: the end wall holds ~13 % of segments (< 15 %).
    r = scan_of(corridor_end(1.6, 8.0, 3.8))
    end_wall = (np.abs(ANGLES) < np.radians(11.0)) & (r <= 4.0)
    assert end_wall.sum() >= 20
    assert denoise(r, ANGLES, PAPER).kept[end_wall].mean() < 0.2
    assert denoise(r, ANGLES, DEFAULT).kept[end_wall].all()


def test_sliding_decision_is_invariant_under_rotating_the_scan():
    scans = hallway_scans(8, 0.01, seed=3)
    params = dataclasses.replace(DEFAULT, mixed_tol_m=0.0)
    assert params.bin_mode == "sliding"
    for scan in scans:
        base = denoise(scan.ranges_m, scan.angles_rad, params).kept
        for turn_deg in (17.0, -61.0, 123.0):
            turned = denoise(scan.ranges_m, scan.angles_rad + np.radians(turn_deg), params).kept
            assert np.array_equal(base, turned)


def test_fixed_bins_are_rotation_invariant_up_to_bin_edges():
    fixed = dataclasses.replace(DEFAULT, bin_mode="fixed")
    for scan in hallway_scans(8, 0.01, seed=4):
        base = denoise(scan.ranges_m, scan.angles_rad, fixed).kept
        turned = denoise(scan.ranges_m, scan.angles_rad + np.radians(17.0), fixed).kept
        assert np.mean(base != turned) < 0.15


def test_default_keeps_walls_and_the_literal_reading_loses_them_at_10mm():
    kept = {"paper": [], "default": []}
    for scan in hallway_scans(30, 0.01, seed=5):
        for name, params in (("paper", PAPER), ("default", DEFAULT)):
            res = denoise(scan.ranges_m, scan.angles_rad, params)
            wall = res.valid & ~scan.spurious
            kept[name].append(res.kept[wall].mean())
    assert np.mean(kept["default"]) > 0.93
    assert np.mean(kept["paper"]) < 0.6


def test_and_rule_keeps_a_subset_of_the_or_rule():
    n_or = n_and = 0
    for scan in hallway_scans(6, 0.01, seed=6):
        k_or = denoise(scan.ranges_m, scan.angles_rad, DEFAULT).kept
        k_and = denoise(scan.ranges_m, scan.angles_rad, dataclasses.replace(DEFAULT, keep_rule="and")).kept
        assert not (k_and & ~k_or).any()
        n_or, n_and = n_or + k_or.sum(), n_and + k_and.sum()
    assert n_and < n_or


def test_jump_segments_take_no_part():
    r = scan_of(straight_wall(6.0, 2.0))
    r[120:] = 3.9  # a second wall 1.9 m farther: one jump segment between them
    res = denoise(r, ANGLES, dataclasses.replace(DEFAULT, mixed_tol_m=0.0))
    assert res.n_segments == res.valid.sum() - 2


ranges_st = arrays(
    np.float64, st.integers(0, 200),
    elements=st.one_of(st.floats(-1.0, 10.0), st.sampled_from([np.nan, np.inf, -np.inf, 0.0])),
)


@settings(max_examples=150, deadline=None)
@given(ranges_st, st.sampled_from(["paper", "default", "fixed", "stride3", "and", "shadow"]))
def test_arbitrary_ranges_never_raise(r, preset):
    params = {
        "paper": PAPER, "default": DEFAULT, "fixed": dataclasses.replace(DEFAULT, bin_mode="fixed"),
        "stride3": dataclasses.replace(DEFAULT, stride=3), "and": dataclasses.replace(DEFAULT, keep_rule="and"),
        "shadow": dataclasses.replace(DEFAULT, shadow_min_angle_deg=10.0),
    }[preset]
    a = np.radians(np.arange(len(r), dtype=float))
    res = denoise(r, a, params)
    assert res.kept.shape == res.valid.shape == (len(r),)
    assert not (res.kept & ~res.valid).any() and not (res.mixed & ~res.valid).any()
    assert res.hist_counts.sum() == res.n_segments and len(res.hist_edges_deg) == params.n_bins + 1
    assert np.isfinite(res.points_xy[res.valid]).all()
