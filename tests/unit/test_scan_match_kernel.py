"""The compiled Gauss–Newton pass of scan matching equals its NumPy form (the oracle), step by step and end to end."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lrfslam.algo import scan_match
from lrfslam.algo.geometry import compose, polar_to_xy
from lrfslam.algo.scan_match import ReferenceScan, ScanMatchParams, ScanTracker, match
from lrfslam.sim.floor_plans import build_world
from lrfslam.sim.lidar import LidarModel, simulate_scan

P = ScanMatchParams()
HALL = build_world("hallway_loop")
NOISY = LidarModel(range_sigma_m=0.01)


def numpy_linearise(reference, current, u, gate_m, params):
    """The oracle: ``scan_match._linearise`` as plain NumPy calls (its form before the compiled pass)."""
    c, s = np.cos(u[2]), np.sin(u[2])
    rot_t = np.array([[c, s], [-s, c]])
    moved = current.points_xy_m @ rot_t + u[:2]
    dist, j = reference.tree.query(moved, distance_upper_bound=gate_m)
    paired = np.isfinite(dist)
    cos_angle = np.einsum("ij,ij->i", reference.normals[np.where(paired, j, 0)], current.normals @ rot_t)
    paired &= np.abs(cos_angle) >= np.cos(params.max_normal_angle_rad)
    pairs = np.where(paired, j, -1)
    q, nrm = reference.points_xy_m[j[paired]], reference.normals[j[paired]]
    p, m = current.points_xy_m[paired], moved[paired]
    r = np.einsum("ij,ij->i", nrm, m - q)
    w = 1.0 / (1.0 + (r / params.robust_scale_m) ** 2)
    d_theta = nrm[:, 0] * (-s * p[:, 0] - c * p[:, 1]) + nrm[:, 1] * (c * p[:, 0] - s * p[:, 1])
    jac = np.column_stack((nrm, d_theta))
    info = jac.T @ (w[:, None] * jac)
    lever = float(np.sqrt(np.mean(np.sum(p * p, axis=1)))) if p.size else 1.0
    scale = np.array([1.0, 1.0, 1.0 / max(lever, 1e-9)])
    eigvals, eigvecs = np.linalg.eigh(info * np.outer(scale, scale) / max(float(w.sum()), 1e-300))
    return scan_match._Linearisation(pairs, r, w, info, jac.T @ (w * r), scale, eigvals, eigvecs)


def scan_at(pose, seed: int) -> np.ndarray:
    scan = simulate_scan(HALL, pose, NOISY, np.random.default_rng(seed))
    return polar_to_xy(scan.ranges_m, scan.angles_rad)


def close(a, b) -> bool:
    return np.allclose(a, b, rtol=1e-9, atol=1e-12)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(0.0, 60.0), st.floats(0.02, 0.6))
def test_one_linearisation_equals_the_numpy_form(seed, along_m, gate_m):
    rng = np.random.default_rng(seed)
    # Somewhere on the hallway loop, the current scan a little off, evaluated at a guess off again.
    start = np.array([2.0 + along_m % 14.0, -0.5 + rng.uniform(-0.3, 0.3), rng.uniform(-np.pi, np.pi)])
    truth = compose(start, rng.normal(0.0, [0.1, 0.1, 0.05]))
    reference = ReferenceScan.build(scan_at(start, seed), P)
    current = ReferenceScan.build(scan_at(truth, seed + 1), P)
    u = compose(truth, rng.normal(0.0, [0.05, 0.05, 0.02])) - np.r_[start[:2], 0.0]
    u[2] = rng.uniform(-0.3, 0.3)
    got = scan_match._linearise(reference, current, u, gate_m, P)
    want = numpy_linearise(reference, current, u, gate_m, P)
    assert np.array_equal(got.pairs, want.pairs)
    for name in ("residual_m", "weight", "info", "gradient", "scale", "eigvals"):
        assert close(getattr(got, name), getattr(want, name)), name
    assert close(np.abs(got.eigvecs.T @ want.eigvecs), np.eye(3)) or np.ptp(want.eigvals) < 1e-9


def test_no_pair_gives_empty_equations():
    reference = ReferenceScan.build(scan_at(np.array([3.0, -0.5, 0.0]), 1), P)
    current = ReferenceScan.build(scan_at(np.array([3.0, -0.5, 0.0]), 2), P)
    far = np.array([500.0, 500.0, 0.0])
    got = scan_match._linearise(reference, current, far, 0.15, P)
    assert np.all(got.pairs == -1) and got.residual_m.size == 0 and np.all(got.info == 0.0)
    assert np.array_equal(got.scale, np.ones(3))


def test_a_tracker_run_equals_the_numpy_form(monkeypatch):
    """Matches chained over a lap's first scans: every increment and covariance as with the NumPy form."""
    poses = [np.array([2.0 + 0.12 * k, -0.5 + 0.01 * np.sin(k / 5), 0.02 * np.sin(k / 7)]) for k in range(40)]
    scans = [scan_at(p, k) for k, p in enumerate(poses)]
    odom_cov = np.diag([1e-4, 1e-4, 1e-5])

    def run():
        tracker = ScanTracker(P)
        prev, out = poses[0], []
        for pose, pts in zip(poses, scans):
            step = tracker.step(pts, np.array(compose(np.zeros(3), pose - prev)), odom_cov)
            out.append((step.matched, step.increment, step.cov))
            prev = pose
        return out

    compiled = run()
    monkeypatch.setattr(scan_match, "_linearise", numpy_linearise)
    reference = run()
    assert sum(m for m, _, _ in reference) >= 35
    for (m1, inc1, cov1), (m2, inc2, cov2) in zip(compiled, reference):
        assert m1 == m2
        assert np.allclose(inc1, inc2, rtol=0.0, atol=1e-9)
        assert np.allclose(cov1, cov2, rtol=1e-6, atol=1e-15) or not m1


@pytest.mark.parametrize("offset", [(0.1, 0.0, 0.0), (0.0, 0.08, 0.05)])
def test_a_match_equals_the_numpy_form(offset, monkeypatch):
    start = np.array([6.0, -0.5, 0.3])
    reference = ReferenceScan.build(scan_at(start, 5), P)
    points = scan_at(compose(start, offset), 6)
    got = match(reference, points, np.zeros(3), P)
    monkeypatch.setattr(scan_match, "_linearise", numpy_linearise)
    want = match(reference, points, np.zeros(3), P)
    assert got.status is want.status and got.iterations == want.iterations
    assert np.allclose(got.pose, want.pose, rtol=0.0, atol=1e-12)
    assert np.allclose(got.cov, want.cov, rtol=1e-9, equal_nan=True)
