"""Forward and backward searching (algo.features) on simulated and hand-made scans."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from lrfslam.algo.features import BACKWARD, FORWARD, FeatureParams, extract_features
from lrfslam.algo.geometry import from_frame, polar_to_xy, to_frame
from lrfslam.algo.histogram import DenoiseParams, denoise
from lrfslam.errors import ConfigError
from lrfslam.sim.floor_plans import corridor_end, doorway_room, l_corner, straight_wall
from lrfslam.sim.lidar import LidarModel, raycast, simulate_scan
from lrfslam.sim.world import World, closed_polygon, polyline

ANGLES = np.radians(np.arange(-90.0, 91.0))
PAPER, DEFAULT = FeatureParams.paper(), FeatureParams.default()
DENOISE = DenoiseParams.default()


def features(world, params=DEFAULT, pose=(0.0, 0.0, 0.0), den=DENOISE):
    r = raycast(world.segments_m, pose, ANGLES, 8.0)
    return extract_features(r, ANGLES, denoise(r, ANGLES, den).kept, params)


def forward(fs):
    return fs.xy_m[fs.kind == FORWARD]


def test_presets():
    assert PAPER.arm_dists_m == DEFAULT.arm_dists_m == (0.3, 0.6, 0.9, 1.2)
    assert (PAPER.arm_max_resid_m, PAPER.nms_radius_m, PAPER.refine_corner) == (None, 0.0, False)
    assert DEFAULT.arm_max_resid_m and DEFAULT.nms_radius_m and DEFAULT.refine_corner
    assert DEFAULT.arm_break_gap_m < DEFAULT.jump_m == PAPER.jump_m == 1.5


@pytest.mark.parametrize(
    "change",
    [{"arm_dists_m": (0.6, 0.3)}, {"arm_dists_m": (0.3,)}, {"arm_metric": "manhattan"}, {"jump_m": 5.0},
     {"arm_break_gap_m": 2.0}, {"corner_tol_deg": 90.0}, {"arm_max_resid_m": 0.0}, {"nms_radius_m": -1.0},
     {"refine_rmin_m": 0.8}, {"refine_min_points": 1}, {"inf_edge_rule": "all"}, {"edge_max_removed": -1},
     {"range_sigma_m": 0.0}],
)
def test_bad_parameters_are_config_errors(change):
    with pytest.raises(ConfigError):
        dataclasses.replace(DEFAULT, **change)


@pytest.mark.parametrize("corner", [(2.0, 0.0), (1.6, 0.7), (3.0, -0.9)])
def test_noise_free_l_corner_gives_one_refined_corner_within_1mm(corner):
    fs = features(l_corner(4.0, 90.0, corner))
    fwd = fs.kind == FORWARD
    assert fwd.sum() == 1  # (3, -0.9) also shows a free wall end: a jump feature
    assert np.hypot(*(fs.xy_m[fwd][0] - corner)) < 1e-3
    assert fs.refined[fwd][0] and abs(fs.angle_deg[fwd][0] - 90.0) < 0.1


def test_unrefined_corner_sits_on_the_base_point():
    fs = features(l_corner(), dataclasses.replace(DEFAULT, refine_corner=False))
    assert len(fs) == 1 and not fs.refined[0]
    r = raycast(l_corner().segments_m, (0, 0, 0), ANGLES, 8.0)
    np.testing.assert_allclose(fs.xy_m[0], r[fs.beam[0]] * np.array([np.cos(ANGLES[fs.beam[0]]), np.sin(ANGLES[fs.beam[0]])]))


def test_paper_mode_reports_a_cluster_of_base_points_round_the_corner():
    xy = forward(features(l_corner(), PAPER, den=DenoiseParams.paper()))
    assert len(xy) > 1 and np.all(np.hypot(*(xy - (2.0, 0.0)).T) < 0.35)


@pytest.mark.parametrize("params", [PAPER, DEFAULT])
def test_straight_wall_gives_nothing(params):
    assert len(features(straight_wall(6.0, 2.0), params)) == 0


def test_60_degree_corner_is_not_a_corner():
    assert len(forward(features(l_corner(4.0, 60.0)))) == 0


def test_short_end_wall_gives_its_two_corners():
    fs = features(corridor_end(1.6, 6.0, 3.0))
    xy = forward(fs)
    assert len(fs) == len(xy) == 2
    np.testing.assert_allclose(xy, [[3.0, -0.8], [3.0, 0.8]], atol=1e-3)
    # Without the straightness check, arms bent round the second corner pass too.
    assert len(forward(features(corridor_end(1.6, 6.0, 3.0), dataclasses.replace(DEFAULT, arm_max_resid_m=None)))) > 2


def test_doorway_gives_jump_features_at_both_jambs_and_none_on_the_far_wall():
    for params in (PAPER, DEFAULT):
        fs = features(doorway_room(1.0, 1.0, 2.5, 3.0), params)
        assert fs.kind.tolist() == [BACKWARD, BACKWARD]
        assert np.all(np.abs(fs.xy_m[:, 0] - 1.0) < 1e-9)  # both on the near wall (x = 1)
        np.testing.assert_allclose(np.abs(fs.xy_m[:, 1]), 0.5, atol=0.03)
        assert np.isnan(fs.angle_deg).all()


def test_shallow_door_recess_gives_no_jump_feature():
    wall = polyline([(2.0, -3.0), (2.0, -0.5), (2.5, -0.5), (2.5, 0.5), (2.0, 0.5), (2.0, 3.0)])
    fs = features(World(wall, "recess"))
    assert (fs.kind == BACKWARD).sum() == 0


def test_wall_end_with_nothing_behind_is_one_feature():
    fs = features(World(polyline([(2.0, -3.0), (2.0, 0.0)]), "wall_end"))
    assert fs.kind.tolist() == [BACKWARD]
    assert np.hypot(*(fs.xy_m[0] - (2.0, 0.0))) < 0.04


def test_receding_wall_past_the_cut_needs_the_margin_rule():
    world = straight_wall(12.0, 2.0)  # crosses the 4 m circle at |y| = 3.46
    assert len(features(world)) == 0
    fs = features(world, dataclasses.replace(DEFAULT, inf_edge_rule="any"))
    assert fs.kind.tolist() == [BACKWARD, BACKWARD]


def test_no_false_jumps_driving_close_along_a_wall():
    wall = World(polyline([(-5.0, -0.2), (10.0, -0.2)]), "side_wall")
    for heading in np.radians(np.linspace(-0.5, 0.5, 50)):
        assert len(features(wall, pose=(0.0, 0.0, heading))) == 0


def test_arm_crossing_a_wide_gap_breaks():
    # L corner whose lower wall has a 0.6 m opening 0.45 m from the corner, a wall 1 m behind it.
    segs = np.vstack((
        polyline([(2.0, -0.45), (2.0, 0.0), (-1.0, 0.0 + 3.0)]),
        polyline([(2.0, -3.0), (2.0, -1.05)]),
        polyline([(3.0, -1.2), (3.0, -0.3)]),
    ))
    corner_world = World(polyline([(2.0, -3.0), (2.0, 0.0), (-1.0, 3.0)]), "l45")
    assert len(forward(features(corner_world, dataclasses.replace(DEFAULT, corner_tol_deg=50.0)))) == 1
    assert len(forward(features(World(segs, "gap"), dataclasses.replace(DEFAULT, corner_tol_deg=50.0)))) == 0


def test_features_rotate_with_the_scan():
    r = raycast(corridor_end(1.6, 6.0, 3.0).segments_m, (0, 0, 0), ANGLES, 8.0)
    kept = np.ones(181, bool)
    base = extract_features(r, ANGLES, kept, DEFAULT)
    turn = np.radians(23.0)
    turned = extract_features(r, ANGLES + turn, kept, DEFAULT)
    np.testing.assert_allclose(turned.xy_m, from_frame(base.xy_m, (0.0, 0.0, turn)), atol=1e-9)
    rot = np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]])
    np.testing.assert_allclose(turned.cov_m2, rot @ base.cov_m2 @ rot.T, atol=1e-12)


def test_removed_points_are_skipped_not_walked_over():
    r = raycast(l_corner().segments_m, (0, 0, 0), ANGLES, 8.0)
    kept = np.ones(181, bool)
    kept[::2] = False  # every other point removed: still the same corner
    fs = extract_features(r, ANGLES, kept, DEFAULT)
    assert len(fs) == 1 and np.hypot(*(fs.xy_m[0] - (2.0, 0.0))) < 1e-3
    assert len(extract_features(r, ANGLES, np.zeros(181, bool), DEFAULT)) == 0


def test_noisy_corner_is_found_and_refinement_beats_the_base_point():
    world, model, rng = l_corner(4.0, 90.0, (2.5, 0.3)), LidarModel(range_sigma_m=0.01), np.random.default_rng(7)
    err = {True: [], False: []}
    nees, found = [], 0
    for _ in range(60):
        scan = simulate_scan(world, (0.0, 0.0, 0.0), model, rng)
        kept = denoise(scan.ranges_m, scan.angles_rad, DenoiseParams.default()).kept
        for refine in (True, False):
            xy = forward(extract_features(scan.ranges_m, scan.angles_rad, kept, dataclasses.replace(DEFAULT, refine_corner=refine)))
            if refine and len(xy) == 1:
                found += 1
                fs = extract_features(scan.ranges_m, scan.angles_rad, kept, DEFAULT)
                e = fs.xy_m[0] - (2.5, 0.3)
                nees.append(e @ np.linalg.solve(fs.cov_m2[0], e))
            err[refine] += [np.hypot(*(p - (2.5, 0.3))) for p in xy]
    assert found >= 57
    rmse = {k: np.sqrt(np.mean(np.square(v))) for k, v in err.items()}
    assert rmse[True] < 0.012 < rmse[False]
    assert 0.3 < np.mean(nees) < 4.0  # the covariance model is neither wild nor overconfident


def test_covariances_are_symmetric_positive_definite():
    for world in (corridor_end(1.6, 6.0, 3.0), doorway_room(), l_corner()):
        fs = features(world)
        np.testing.assert_allclose(fs.cov_m2, fs.cov_m2.transpose(0, 2, 1))
        assert np.all(np.linalg.eigvalsh(fs.cov_m2) > 0)


@st.composite
def rooms(draw):
    w, h = draw(st.floats(2.5, 6.0)), draw(st.floats(2.5, 6.0))
    rect = closed_polygon([(0, 0), (w, 0), (w, h), (0, h)], free_inside=True)
    place = (draw(st.floats(-3, 3)), draw(st.floats(-3, 3)), draw(st.floats(-np.pi, np.pi)))
    world = World(from_frame(rect.reshape(-1, 2), place).reshape(-1, 4), "room")
    inside = (draw(st.floats(0.3, w - 0.3)), draw(st.floats(0.3, h - 0.3)))
    pose = (*from_frame(np.array([inside]), place)[0], draw(st.floats(-np.pi, np.pi)))
    return world, pose


@settings(max_examples=60, deadline=None)
@given(rooms(), st.sampled_from([0.0, 0.005, 0.01]), st.integers(0, 2**31 - 1))
def test_every_forward_corner_in_a_random_room_is_a_map_corner(room, sigma_m, seed):
    world, pose = room
    scan = simulate_scan(world, pose, LidarModel(range_sigma_m=sigma_m), np.random.default_rng(seed))
    kept = denoise(scan.ranges_m, scan.angles_rad, DenoiseParams.default()).kept
    fs = extract_features(scan.ranges_m, scan.angles_rad, kept, DEFAULT)
    assert np.isfinite(fs.xy_m).all() and np.isfinite(fs.cov_m2).all()
    truth = to_frame(world.corners().xy_m, pose)
    ok = kept & np.isfinite(scan.ranges_m)
    returns = polar_to_xy(scan.ranges_m[ok], scan.angles_rad[ok])
    for xy, refined in zip(forward(fs), fs.refined[fs.kind == FORWARD]):
        miss = np.hypot(*(truth - xy).T)
        k = int(np.argmin(miss))
        if refined:   # noise-free ranges are still quantised to 1 cm
            assert miss[k] < (0.01 if sigma_m == 0 else 0.1)
        else:
            # Too few wall points for the refit (e.g. at grazing incidence): the corner sits on its
            # base point, a return beside the true corner, as far from it as the returns there lie
            # apart (6 cm at 3.5 m, more on a wall seen edge-on), noise and quantisation aside.
            beside = np.sort(np.hypot(*(returns - truth[k]).T))[:2]
            assert miss[k] < max(0.1, beside[-1] + 3.0 * sigma_m + 0.01)


ranges_st = arrays(
    np.float64, st.integers(0, 200),
    elements=st.one_of(st.floats(-1.0, 10.0), st.sampled_from([np.nan, np.inf, -np.inf, 0.0])),
)


@settings(max_examples=150, deadline=None)
@given(ranges_st, st.data(), st.sampled_from(["paper", "default", "arclength"]))
def test_arbitrary_ranges_never_raise(r, data, preset):
    params = {"paper": PAPER, "default": DEFAULT, "arclength": dataclasses.replace(DEFAULT, arm_metric="arclength")}[preset]
    kept = data.draw(arrays(bool, len(r)))
    fs = extract_features(r, np.radians(np.arange(len(r), dtype=float) * 0.5), kept, params)
    k = len(fs)
    assert fs.xy_m.shape == (k, 2) and fs.cov_m2.shape == (k, 2, 2) and fs.beam.shape == (k,)
    assert np.isfinite(fs.xy_m).all() and np.isfinite(fs.cov_m2).all()
    assert np.all(np.diff(fs.beam) >= 0) and np.all(kept[fs.beam])
