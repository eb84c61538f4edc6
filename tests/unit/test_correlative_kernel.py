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
    got, want = kernel.scores(grid, kernel.PointCells(rows, cols), cand), oracle(grid, rows, cols, cand)
    assert got.shape == want.shape == (candidates,)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=0)
    # With a bound, what cannot reach it is cut (-1) and the rest score as without one.
    bound = float(rng.uniform(0, 1))
    cut = kernel.scores(grid, kernel.PointCells(rows, cols), cand, bound)
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
    got = kernel.scores(grid, kernel.PointCells(rows, cols), cand)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)
    bound = float(rng.uniform(0, 1))
    cut = kernel.scores(grid, kernel.PointCells(rows, cols), cand, bound)
    assert np.all((cut == got) | ((cut == -1.0) & (want < bound + 1e-12)))
    assert np.all(cut[want >= bound + 1e-12] == got[want >= bound + 1e-12])


def test_a_point_off_the_grid_scores_the_edge_cell():
    grid = np.zeros((3, 4), np.float32)
    grid[2, 3] = 1.0          # the top-right cell
    rows, cols = np.array([[50]]), np.array([[50]])
    cand = np.array([[0, 0, 0], [0, -60, -60]])
    np.testing.assert_array_equal(kernel.scores(grid, kernel.PointCells(rows, cols), cand), [1.0, 0.0])


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
    np.testing.assert_allclose(kernel.scores(grid, kernel.PointCells(rows, cols), cand),
                               oracle(values, rows, cols, cand), rtol=1e-12, atol=1e-15)
