"""The accelerated forward search (algo.forward_search_kernel) step by step.

Its picks against a point-by-point walk with the search windows made tiny and wide, and
the screen's bound against corners built to lie on it. ``test_features_oracle.py``
compares its whole output with the plain forward search of ``algo.features``.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from lrfslam.algo import forward_search_kernel as K
from lrfslam.algo.features import FeatureParams

DEFAULT = FeatureParams.default()


def naive_picks(p, first, last, dists, euclidean):
    """First point at >= d, walking outward, one point at a time.

    The reading of docs/paper-reading.md, 'Picking the arm points'.
    """
    m = len(p)
    out = np.full((m, 2, len(dists)), -1)
    for j in range(m):
        for side, step in ((0, -1), (1, 1)):
            arc, k = 0.0, j
            for a, d in enumerate(dists):
                while True:
                    k2 = k + step
                    if k2 < first[j] or k2 > last[j]:
                        k = None
                        break
                    arc += np.hypot(*(p[k2] - p[k]))
                    k = k2
                    reach = np.hypot(*(p[k] - p[j])) if euclidean else arc
                    if reach >= d:
                        out[j, side, a] = k
                        break
                if k is None:
                    break
    return out


def arms_by_scan_column(arms, m):
    """arm_picks output as {base: (2 sides, A) pick columns in scan order}."""
    cols = np.where(arms[0] >= m, 2 * m - 1 - arms[0], arms[0])
    return {int(j): np.stack((cols[:, 1:][i], arms[1, i, 1:])) for i, j in enumerate(arms[1, :, 0])}


@pytest.mark.parametrize("near, far", [(4, 12), (1, 2), (16, 32)])
@pytest.mark.parametrize("metric", ["euclidean", "arclength"])
def test_arm_picks_match_a_point_by_point_walk(metric, near, far):
    # The search windows change speed only: tiny ones send most picks through the
    # slow paths, wide ones through none.
    rng = np.random.default_rng(11)
    # No straightness check: no screen, so every base with both arms is returned.
    params = dataclasses.replace(DEFAULT, arm_metric=metric, arm_max_resid_m=None)
    checked = 0
    for _ in range(40):
        m = int(rng.integers(10, 120))
        p = np.cumsum(rng.normal(0.0, 0.05, (m, 2)) + rng.uniform(-0.05, 0.08, 2), axis=0)
        breaks = np.sort(rng.choice(np.arange(1, m), size=int(rng.integers(0, 4)), replace=False))
        run = np.searchsorted(breaks, np.arange(m), side="right")
        starts = np.concatenate(([0], breaks))
        ends = np.concatenate((breaks - 1, [m - 1]))
        first, last = starts[run], ends[run]
        z = p[:, 0] + 1j * p[:, 1]
        doubled = K.doubled(z, np.abs(np.diff(z)), (breaks - 1).tolist(), far)
        got = arms_by_scan_column(K.arm_picks(*doubled, params, near, far), m)
        expect = naive_picks(p, first, last, params.arm_dists_m, metric == "euclidean")
        full = np.flatnonzero(np.all(expect >= 0, axis=(1, 2)))
        assert sorted(got) == full.tolist()
        for j in full:
            assert np.array_equal(got[j], expect[j])
        checked += len(full)
    assert checked > 200


def line_angle_deg(theta_a, theta_b):
    """Angle between undirected lines of directions theta_a, theta_b (radians), degrees in [0, 90]."""
    d = np.degrees(np.abs(theta_a - theta_b)) % 180.0
    return np.minimum(d, 180.0 - d)


def test_the_screen_never_drops_a_corner():
    # Pairs of 5-point arms built against the screen's bound: each arm's nearest pick
    # and the shared base point lie on opposite sides of the arm's line, nearly
    # arm_max_resid_m off (the other picks balance them, so the line is their
    # least-squares fit), and the lines are nearly corner_tol_deg off a right angle.
    # Wherever the reference's TLS test sees a corner, the chords to the nearest
    # picks must pass the screen.
    rng = np.random.default_rng(12)
    tan_tol = K.screen_tan(DEFAULT)
    rho, dists = DEFAULT.arm_max_resid_m, np.array(DEFAULT.arm_dists_m)
    n = 4000
    direction = rng.uniform(0, 2 * np.pi, n)
    angle = np.radians(90.0 - DEFAULT.corner_tol_deg * rng.uniform(0.97, 1.0, n))
    arms = []
    for theta in (direction, direction + angle):
        a = 0.999 * rho * rng.choice([-1.0, 1.0], (n, 1))
        # The nearest pick exactly its distance from the base point, 2a across the line.
        along = np.concatenate((np.zeros((n, 1)), np.sqrt(dists[0] ** 2 - 4 * a * a), dists[1:] * np.ones((n, 1))), axis=1)
        b2 = a * along[:, 1:2] / (along[:, 4:5] - along[:, 2:3])
        off = np.concatenate((-a, a, b2, np.zeros((n, 1)), -b2), axis=1)  # Σoff = 0, Σ along·off = 0
        arms.append((along + 1j * (off - off[:, :1])) * np.exp(1j * theta)[:, None])  # base point at 0
    arms = np.stack(arms)  # (2, n, A + 1)
    theta, max_resid = (v.reshape(2, n) for v in K.arm_fit(arms.reshape(2 * n, -1).T))
    corner = (90.0 - line_angle_deg(theta[0], theta[1]) <= DEFAULT.corner_tol_deg) & np.all(max_resid <= rho, axis=0)
    assert corner.sum() > 1000
    assert K.square(arms[:, corner, 1], tan_tol).all()
    # The same chords through a screen 1° tighter lose corners: the bound is tight.
    assert not K.square(arms[:, corner, 1], np.tan(np.arctan(tan_tol) - np.radians(1.0))).all()
