"""The correlative search's compiled scores against their NumPy form (reference_correlative.py)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from reference_correlative import scores as oracle

from lrfslam.algo import correlative_kernel as kernel


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31), height=st.integers(1, 40), width=st.integers(1, 40),
       angles=st.integers(1, 5), points=st.integers(1, 200), candidates=st.integers(0, 300))
def test_the_kernel_scores_as_the_numpy_form(seed, height, width, angles, points, candidates):
    rng = np.random.default_rng(seed)
    grid = rng.uniform(0, 1, (height, width)).astype(np.float32)
    # Cells and offsets reaching past every edge: the clipping is part of what is compared.
    rows = rng.integers(-10, height + 10, (angles, points))
    cols = rng.integers(-10, width + 10, (angles, points))
    cand = np.column_stack((rng.integers(0, angles, candidates), rng.integers(-15, 15, candidates),
                            rng.integers(-15, 15, candidates)))
    got, want = kernel.scores(grid, kernel.PointCells(rows, cols, grid.shape[1]), cand), oracle(grid, rows, cols, cand)
    assert got.shape == want.shape == (candidates,)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=0)
    # With a bound, what cannot reach it is cut (-1) and the rest score as without one.
    bound = float(rng.uniform(0, 1))
    cut = kernel.scores(grid, kernel.PointCells(rows, cols, grid.shape[1]), cand, bound)
    assert np.all((cut == got) | ((cut == -1.0) & (want < bound + 1e-12)))
    assert np.all(cut[want >= bound + 1e-12] == got[want >= bound + 1e-12])


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31), points=st.integers(1, 100), candidates=st.integers(0, 100))
def test_a_uint8_level_scores_its_values_over_255(seed, points, candidates):
    """A pooled level kept as uint8 (value / 255): the same means as the NumPy form, cut by a bound
    as a float32 grid is."""
    rng = np.random.default_rng(seed)
    grid = rng.integers(0, 256, (20, 30)).astype(np.uint8)
    rows, cols = rng.integers(-5, 25, (2, points)), rng.integers(-5, 35, (2, points))
    cand = np.column_stack((rng.integers(0, 2, candidates), rng.integers(-8, 8, candidates),
                            rng.integers(-8, 8, candidates)))
    want = oracle(grid.astype(np.float64) / 255.0, rows, cols, cand)
    got = kernel.scores(grid, kernel.PointCells(rows, cols, grid.shape[1]), cand)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)
    bound = float(rng.uniform(0, 1))
    cut = kernel.scores(grid, kernel.PointCells(rows, cols, grid.shape[1]), cand, bound)
    assert np.all((cut == got) | ((cut == -1.0) & (want < bound + 1e-12)))
    assert np.all(cut[want >= bound + 1e-12] == got[want >= bound + 1e-12])


def test_a_point_off_the_grid_scores_the_edge_cell():
    grid = np.zeros((3, 4), np.float32)
    grid[2, 3] = 1.0          # the top-right cell
    rows, cols = np.array([[50]]), np.array([[50]])
    cand = np.array([[0, 0, 0], [0, -60, -60]])
    np.testing.assert_array_equal(kernel.scores(grid, kernel.PointCells(rows, cols, grid.shape[1]), cand), [1.0, 0.0])


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31), angles=st.integers(1, 4), points=st.integers(1, 150),
       candidates=st.integers(1, 200), uint8=st.booleans())
def test_candidates_wholly_on_the_grid_score_as_the_numpy_form(seed, angles, points, candidates, uint8):
    """The path without clipping: every point of every candidate inside the grid (and some just
    across an edge, to pass between the two paths)."""
    rng = np.random.default_rng(seed)
    height, width = 30, 45
    grid = rng.integers(0, 256, (height, width)).astype(np.uint8) if uint8 else \
        rng.uniform(0, 1, (height, width)).astype(np.float32)
    rows = rng.integers(5, height - 5, (angles, points))
    cols = rng.integers(5, width - 5, (angles, points))
    cand = np.column_stack((rng.integers(0, angles, candidates), rng.integers(-6, 7, candidates),
                            rng.integers(-6, 7, candidates)))
    values = grid.astype(np.float64) / 255.0 if uint8 else grid
    np.testing.assert_allclose(kernel.scores(grid, kernel.PointCells(rows, cols, grid.shape[1]), cand),
                               oracle(values, rows, cols, cand), rtol=1e-12, atol=1e-15)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31), candidates=st.integers(0, 200), level=st.integers(1, 5), masked=st.booleans())
def test_expand_gives_the_children_the_mask_admits(seed, candidates, level, masked):
    """The compiled children of a level against their NumPy form: four sub-blocks per candidate in
    order, those starting beyond the window dropped, and with a pooled mask those it does not admit
    (a block reaching into the mask from below an edge judged by the edge's cell)."""
    rng = np.random.default_rng(seed)
    half, n_xy = 1 << (level - 1), int(rng.integers(0, 40))
    cand = np.column_stack((rng.integers(0, 3, candidates), rng.integers(-45, n_xy + 1, candidates),
                            rng.integers(-45, n_xy + 1, candidates)))
    want = np.repeat(cand, 4, axis=0)
    want[:, 1] += np.tile([0, half, 0, half], candidates)
    want[:, 2] += np.tile([0, 0, half, half], candidates)
    want = want[(want[:, 1] <= n_xy) & (want[:, 2] <= n_xy)]
    if not masked:
        np.testing.assert_array_equal(kernel.expand(cand, half, n_xy), want.reshape(-1, 3))
        return
    mask = rng.random((30, 25)) < 0.3
    base_col, base_row = int(rng.integers(-10, 30)), int(rng.integers(-10, 35))
    col, row = base_col + want[:, 1], base_row + want[:, 2]
    inside = (col + half > 0) & (col < 25) & (row + half > 0) & (row < 30)
    admitted = np.zeros(want.shape[0], dtype=bool)
    admitted[inside] = mask[np.maximum(row[inside], 0), np.maximum(col[inside], 0)]
    np.testing.assert_array_equal(kernel.expand(cand, half, n_xy, mask, base_col, base_row),
                                  want[admitted].reshape(-1, 3))
