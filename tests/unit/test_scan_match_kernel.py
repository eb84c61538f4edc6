"""The compiled ICP kernels against their NumPy forms (reference_scan_match.py), within round-off."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from reference_scan_match import line_normals as normals_oracle
from reference_scan_match import linearise as oracle

from lrfslam.algo import scan_match as sm
from lrfslam.algo import scan_match_kernel as kernel
from lrfslam.algo.scan_match import ReferenceScan, ScanMatchParams

P = ScanMatchParams()


def walls(rng: np.random.Generator, n: int) -> np.ndarray:
    """Points on a few random walls with range noise, (n, 2)."""
    ends = rng.uniform(-6, 6, (4, 4))
    t = rng.uniform(0, 1, n)
    k = rng.integers(0, 4, n)
    pts = ends[k, :2] + t[:, None] * (ends[k, 2:] - ends[k, :2])
    return pts + rng.normal(0, 0.01, pts.shape)


@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 2**31), gate=st.sampled_from([sm.NARROW_GATE_M, sm.WIDE_GATE_M]),
       offset=st.floats(0.0, 0.4))
def test_the_kernel_pairs_and_sums_as_the_numpy_form(seed, gate, offset):
    rng = np.random.default_rng(seed)
    ref = ReferenceScan.build(walls(rng, 400))
    cur = ReferenceScan.build(walls(rng, 200))
    u = np.array([*rng.uniform(-offset, offset, 2), rng.uniform(-0.2, 0.2) * offset])
    got = kernel.linearise(ref.points_xy_m, ref.normals, ref.grid(sm.WIDE_GATE_M), cur.points_xy_m, cur.normals,
                           u, gate, sm.MAX_NORMAL_ANGLE_RAD, sm.ROBUST_SCALE_M)
    want = oracle(ref.points_xy_m, ref.normals, cur.points_xy_m, cur.normals, u, gate, sm.MAX_NORMAL_ANGLE_RAD,
                  sm.ROBUST_SCALE_M)
    # Random reals: no two reference points are equally near, so the pairs are the same.
    np.testing.assert_array_equal(got.pairs, want.pairs)
    for name in ("residual_m", "weight", "info", "gradient", "lever_m", "scale", "eigvals"):
        np.testing.assert_allclose(getattr(got, name), getattr(want, name), rtol=1e-10, atol=1e-12, err_msg=name)
    # Eigenvectors up to sign, where the eigenvalues are apart.
    if np.min(np.diff(want.eigvals)) > 1e-6 * max(abs(want.eigvals[-1]), 1e-12):
        np.testing.assert_allclose(np.abs(np.sum(got.eigvecs * want.eigvecs, axis=0)), 1.0, atol=1e-8)


def test_points_beyond_the_grid_or_with_no_reference_pair_with_nothing():
    ref = np.array([[0.0, 0.0], [0.1, 0.0], [0.2, 0.0]])
    normals = np.tile([0.0, 1.0], (3, 1))
    cur = np.array([[50.0, 50.0], [-50.0, 0.0], [0.1, 0.05]])
    got = kernel.linearise(ref, normals, kernel.grid(ref, 0.5), cur, np.tile([0.0, 1.0], (3, 1)), np.zeros(3),
                           0.5, sm.MAX_NORMAL_ANGLE_RAD, sm.ROBUST_SCALE_M)
    assert got.pairs.tolist() == [-1, -1, 1]
    np.testing.assert_allclose(got.residual_m, [0.05])
    empty = kernel.linearise(np.zeros((0, 2)), np.zeros((0, 2)), kernel.grid(np.zeros((0, 2)), 0.5), cur,
                             np.tile([0.0, 1.0], (3, 1)), np.zeros(3), 0.5, sm.MAX_NORMAL_ANGLE_RAD, sm.ROBUST_SCALE_M)
    assert empty.pairs.tolist() == [-1, -1, -1] and empty.lever_m == 1.0


@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(0, 400))
def test_line_normals_are_the_numpy_forms(seed, n):
    pts = walls(np.random.default_rng(seed), n)
    args = (sm.NORMAL_NEIGHBOURS, sm.NORMAL_RADIUS_M, sm.NORMAL_MIN_NEIGHBOURS, sm.NORMAL_MAX_THICKNESS)
    line, normals = kernel.line_normals(pts, *args)
    want_line, want_normals = normals_oracle(pts, *args) if n else (np.zeros(0, bool), np.zeros((0, 2)))
    np.testing.assert_array_equal(line, want_line)
    # The same line up to its normal's sign (a scatter's axis has two).
    np.testing.assert_allclose(np.abs(np.sum(normals[line] * want_normals[line], axis=1)), 1.0, atol=1e-9)
