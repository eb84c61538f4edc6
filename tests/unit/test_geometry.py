"""Pose inverse and point thinning, against their definitions."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from lrfslam.algo.geometry import compose, inverse, relative, thin_points

coord = st.floats(-100.0, 100.0, allow_nan=False)
angle = st.floats(-np.pi, np.pi, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(x=coord, y=coord, th=angle, bx=coord, by=coord, bth=angle)
def test_inverse_undoes_a_pose_and_turns_a_relative_motion_round(x, y, th, bx, by, bth):
    p, q = np.array([x, y, th]), np.array([bx, by, bth])
    np.testing.assert_allclose(compose(p, inverse(p)), 0.0, atol=1e-9)
    np.testing.assert_allclose(compose(inverse(p), p), 0.0, atol=1e-9)
    back = relative(q, p)
    np.testing.assert_allclose(inverse(relative(p, q))[:2], back[:2], atol=1e-9)
    assert abs(np.angle(np.exp(1j * (inverse(relative(p, q))[2] - back[2])))) < 1e-9


@settings(max_examples=100, deadline=None)
@given(points=st.lists(st.tuples(coord, coord), max_size=60), cell=st.floats(0.01, 5.0))
def test_thinning_keeps_one_mean_per_occupied_cell(points, cell):
    pts = np.array(points, dtype=float).reshape(-1, 2)
    thinned = thin_points(pts, cell)
    cells = {tuple(c) for c in np.floor(pts / cell).astype(np.int64)}
    assert thinned.shape == (len(cells), 2)
    for c in cells:
        inside = pts[np.all(np.floor(pts / cell).astype(np.int64) == c, axis=1)]
        assert np.any(np.all(np.isclose(thinned, inside.mean(axis=0), atol=1e-9), axis=1))
