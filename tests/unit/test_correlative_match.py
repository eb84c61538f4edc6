"""Branch-and-bound correlative search: finds the true pose, equals brute force, reports a second peak."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lrfslam.algo.correlative_match import (
    ANGLE_STEP_RAD,
    CorrelativeParams,
    LikelihoodGrid,
    PositionMask,
    search,
)
from lrfslam.algo.geometry import from_frame, to_frame
from lrfslam.errors import ConfigError, InputError


def walls(vertices, step_m: float = 0.03) -> np.ndarray:
    """Points every ``step_m`` along the closed polygon ``vertices`` (V, 2), shape (M, 2)."""
    v = np.asarray(vertices, dtype=float)
    out = []
    for a, b in zip(v, np.roll(v, -1, axis=0), strict=True):
        n = max(int(np.hypot(*(b - a)) / step_m), 1)
        out.append(a + np.linspace(0.0, 1.0, n, endpoint=False)[:, None] * (b - a))
    return np.vstack(out)


ROOM = walls([(0, 0), (8, 0), (8, 3), (5, 3), (5, 6), (1, 6), (1, 3.5), (0, 3.5)])


def seen_from(pose, rng: np.random.Generator, n: int = 150, noise_m: float = 0.01) -> np.ndarray:
    """A random subset of the map's points in the robot frame at ``pose``, with range noise."""
    local = to_frame(ROOM, pose)
    pick = rng.choice(local.shape[0], size=n, replace=False)
    return local[pick] + rng.normal(0.0, noise_m, (n, 2))


def test_finds_the_true_pose_from_far_off():
    rng = np.random.default_rng(0)
    params = CorrelativeParams()
    grid = LikelihoodGrid(ROOM, params)
    truth = np.array([3.0, 1.5, 0.3])
    pts = seen_from(truth, rng)
    result = search(grid, pts, truth + (1.2, -0.9, -0.25), half_width_m=2.0, half_angle_rad=0.4, min_score=0.3)
    assert result.exact
    assert np.hypot(*(result.pose[:2] - truth[:2])) < 2 * params.cell_m
    assert abs(result.pose[2] - truth[2]) < 0.02
    assert result.score > 0.7
    assert result.second_score < result.score


def brute_force(grid: LikelihoodGrid, pts, centre, half_width_m, half_angle_rad, where: PositionMask | None = None):
    """Every leaf of the search (that ``where`` admits), scored one by one (the reference the bound must reproduce)."""
    p = grid.params
    step = ANGLE_STEP_RAD
    n_ang = int(np.ceil(half_angle_rad / step))
    n_xy = int(np.ceil(half_width_m / p.cell_m))
    best = -1.0
    for a in range(-n_ang, n_ang + 1):
        th = centre[2] + a * step
        moved = from_frame(pts, (centre[0], centre[1], th))
        cols = np.floor((moved[:, 0] - grid.origin_xy_m[0]) / p.cell_m).astype(int)
        rows = np.floor((moved[:, 1] - grid.origin_xy_m[1]) / p.cell_m).astype(int)
        for i in range(-n_xy, n_xy + 1):
            for j in range(-n_xy, n_xy + 1):
                if where is not None and not where.admits(0, centre[:2], np.array([[0, i, j]]))[0]:
                    continue
                r = np.clip(rows + j, 0, grid.grid.shape[0] - 1)
                c = np.clip(cols + i, 0, grid.grid.shape[1] - 1)
                best = max(best, float(grid.grid[r, c].mean()))
    return best


@settings(max_examples=8, deadline=None)
@given(st.floats(1.0, 7.0), st.floats(0.5, 5.0), st.floats(-np.pi, np.pi), st.integers(0, 2**31))
def test_bound_is_exact(x, y, th, seed):
    rng = np.random.default_rng(seed)
    params = CorrelativeParams(cell_m=0.1, levels=4)
    grid = LikelihoodGrid(ROOM, params)
    pts = seen_from((x, y, th), rng, n=40)
    centre = np.array([x, y, th]) + rng.uniform(-0.4, 0.4, 3) * (1, 1, 0.2)
    result = search(grid, pts, centre, half_width_m=0.6, half_angle_rad=0.08, min_score=0.0)
    assert result.exact
    assert result.score == pytest.approx(brute_force(grid, pts, centre, 0.6, 0.08), abs=1e-6)


@settings(max_examples=8, deadline=None)
@given(st.floats(1.0, 7.0), st.floats(0.5, 5.0), st.floats(-np.pi, np.pi), st.integers(0, 2**31))
def test_a_position_mask_keeps_the_search_exact_over_what_it_admits(x, y, th, seed):
    """Positions admitted in a few random patches (the truth among them or not): the search's best
    equals the best admitted leaf, and lies on an admitted position."""
    rng = np.random.default_rng(seed)
    grid = LikelihoodGrid(ROOM, CorrelativeParams(cell_m=0.1, levels=4))
    pts = seen_from((x, y, th), rng, n=40)
    centre = np.array([x, y, th]) + rng.uniform(-0.4, 0.4, 3) * (1, 1, 0.2)
    where = PositionMask(grid, centre[:2] + rng.uniform(-0.8, 0.8, (3, 2)), margin_m=0.1)
    result = search(grid, pts, centre, half_width_m=0.8, half_angle_rad=0.06, min_score=0.0, where=where)
    assert result.exact
    assert result.score == pytest.approx(brute_force(grid, pts, centre, 0.8, 0.06, where), abs=1e-6)
    offset = np.round((result.pose[:2] - centre[:2]) / 0.1).astype(np.int64)
    assert where.admits(0, centre[:2], np.array([[0, *offset]]))[0]


def test_a_mask_admitting_everywhere_changes_nothing():
    rng = np.random.default_rng(3)
    grid = LikelihoodGrid(ROOM, CorrelativeParams(levels=5))
    truth = np.array([3.0, 1.5, 0.3])
    pts = seen_from(truth, rng)
    everywhere = PositionMask(grid, np.mgrid[-2:10:0.1, -2:8:0.1].reshape(2, -1).T, margin_m=0.0)
    plain = search(grid, pts, truth + (1.2, -0.9, -0.25), 2.0, 0.4, 0.3, second_ratio=0.5)
    masked = search(grid, pts, truth + (1.2, -0.9, -0.25), 2.0, 0.4, 0.3, second_ratio=0.5, where=everywhere)
    assert masked.score == plain.score and masked.second_score == plain.second_score
    np.testing.assert_array_equal(masked.pose, plain.pose)


def test_two_identical_rooms_give_two_equal_peaks():
    rng = np.random.default_rng(1)
    params = CorrelativeParams()
    twin = np.vstack([ROOM, ROOM + (10.0, 0.0)])
    grid = LikelihoodGrid(twin, params)
    truth = np.array([3.0, 1.5, 0.0])
    pts = seen_from(truth, rng)
    result = search(grid, pts, truth + (5.0, 0.0, 0.0), half_width_m=6.0, half_angle_rad=0.1, min_score=0.3)
    assert result.second_score > 0.9 * result.score
    peaks = sorted([result.pose[0], result.second_pose[0]])
    assert peaks[0] == pytest.approx(3.0, abs=0.1)
    assert peaks[1] == pytest.approx(13.0, abs=0.1)


def test_three_identical_rooms_are_each_a_rival_once():
    """With a second ratio, every copy of the place comes back as a rival, once, best first: a
    localizer that sees only the second peak never hears of the third copy, which may be the truth."""
    rng = np.random.default_rng(2)
    params = CorrelativeParams()
    triple = np.vstack([ROOM, ROOM + (10.0, 0.0), ROOM + (20.0, 0.0)])
    grid = LikelihoodGrid(triple, params)
    truth = np.array([3.0, 1.5, 0.0])
    pts = seen_from(truth, rng)
    centre = truth + (10.0, 0.0, 0.0)
    result = search(grid, pts, centre, half_width_m=12.0, half_angle_rad=0.1, min_score=0.3, second_ratio=0.9)
    assert result.rival_poses.shape == (2, 3)
    np.testing.assert_array_equal(result.rival_poses[0], result.second_pose)
    xs = sorted([result.pose[0], *result.rival_poses[:, 0]])
    np.testing.assert_allclose(xs, [3.0, 13.0, 23.0], atol=0.15)
    # Without a second ratio the search does not look for every copy.
    assert search(grid, pts, centre, 12.0, 0.1, 0.3).rival_poses.shape == (0, 3)


@settings(max_examples=8, deadline=None)
@given(st.floats(1.0, 7.0), st.floats(0.5, 5.0), st.floats(-np.pi, np.pi), st.integers(0, 2**31))
def test_a_whole_turn_from_more_greedy_starts_finds_the_same_best(x, y, th, seed):
    """The localizer's global search: a window of a whole turn, the first bound from 32 greedy
    descents, the second peak only above 0.9 of the best. The best is the one-start search's (both
    are exact), and a second peak is never the winner's own heading seen a turn later."""
    rng = np.random.default_rng(seed)
    grid = LikelihoodGrid(ROOM, CorrelativeParams(cell_m=0.1, levels=5))
    pts = seen_from((x, y, th), rng, n=60)
    centre = np.array([4.0, 3.0, 0.0])
    one = search(grid, pts, centre, 5.0, np.pi, 0.3, max_frontier=10**7)
    many = search(grid, pts, centre, 5.0, np.pi, 0.3, max_frontier=10**7, greedy_starts=32, second_ratio=0.9)
    assert one.exact and many.exact and many.score == one.score
    np.testing.assert_array_equal(many.pose, one.pose)
    if many.second_score:
        assert many.second_score >= 0.9 * many.score
        d = many.second_pose - many.pose
        turned = abs((d[2] + np.pi) % (2 * np.pi) - np.pi)
        assert np.hypot(d[0], d[1]) >= 1.0 - 1e-9 or turned >= 0.35 - 1e-9
    else:
        assert one.second_score < 0.9 * one.score


def test_nothing_above_the_minimum():
    grid = LikelihoodGrid(ROOM, CorrelativeParams())
    far_away = np.array([[100.0, 0.0], [100.0, 1.0], [101.0, 0.0]])
    result = search(grid, far_away, (3.0, 1.5, 0.0), 0.5, 0.1, min_score=0.5)
    assert result.score == 0.0 and np.isnan(result.second_pose).all()


def test_bad_input_is_refused():
    with pytest.raises(ConfigError):
        CorrelativeParams(levels=0)
    with pytest.raises(InputError):
        LikelihoodGrid(np.zeros((0, 2)), CorrelativeParams())
    grid = LikelihoodGrid(ROOM, CorrelativeParams())
    with pytest.raises(InputError):
        search(grid, np.zeros((0, 2)), (0.0, 0.0, 0.0), 1.0, 0.1, 0.5)
