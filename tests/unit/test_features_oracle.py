"""extract_features against the previous implementation (reference_corners.py).

The optimised forward search screens base points before picking and fitting their
arms (module docstring of lrfslam.algo.corners); the reference picks and fits every
arm of every base point. Both must give the same features, to rounding, on many
random scans and under every option that changes the search.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import reference_corners as R
from oracle_scans import garbage, simulated

from lrfslam.algo.features import FORWARD, FeatureParams, extract_features
from lrfslam.algo.histogram import DenoiseParams, denoise

SCANS = simulated(24, 8, seed=5)
GARBAGE = garbage(80, seed=6)

VARIANTS = {
    "default": {},
    "arclength": {"arm_metric": "arclength"},
    "no straightness check": {"arm_max_resid_m": None},
    # The screen's angle bound passes 90°: no screening at all.
    "loose straightness": {"arm_max_resid_m": 0.5},
    "tolerance 25°": {"corner_tol_deg": 25.0},
    "two picks per arm": {"arm_dists_m": (0.25, 0.8)},
    "five picks per arm": {"arm_dists_m": (0.2, 0.4, 0.7, 1.0, 1.4)},
    "no refinement": {"refine_corner": False},
    # The refit walls reach past the farthest picks: the whole stretch is searched.
    "wide refit": {"refine_rmax_m": 1.5},
    "break gap 1.5 m": {"arm_break_gap_m": 1.5},
    "no suppression": {"nms_radius_m": 0.0},
    "every finite/∞ edge": {"inf_edge_rule": "any"},
    "edges across removed": {"edge_max_removed": None},
}


def corner_params(variant: str) -> FeatureParams:
    return dataclasses.replace(FeatureParams.default(), **VARIANTS[variant])


def assert_same(new, old):
    assert new.kind.tolist() == old.kind.tolist()
    assert new.beam.tolist() == old.beam.tolist()
    assert new.refined.tolist() == old.refined.tolist()
    np.testing.assert_allclose(new.xy_m, old.xy_m, rtol=0, atol=1e-9)
    np.testing.assert_allclose(new.angle_deg, old.angle_deg, rtol=0, atol=1e-9)
    scale = np.abs(old.cov_m2).max(axis=(1, 2), keepdims=True) if len(old) else 1.0
    np.testing.assert_allclose(new.cov_m2 / scale, old.cov_m2 / scale, rtol=0, atol=1e-9)


def compare(scans, cp: FeatureParams, dp: DenoiseParams, seed: int) -> int:
    """Compare on each scan with the filter's kept points and with a random tenth dropped too; corners seen."""
    rp = R.FeatureParams(**dataclasses.asdict(cp))
    rng = np.random.default_rng(seed)
    corners = 0
    for r, a in scans:
        kept = denoise(r, a, dp).kept
        for k in (kept, kept & (rng.random(len(r)) > 0.1)):
            new = extract_features(r, a, k, cp)
            assert_same(new, R.extract_features(r, a, k, rp))
            corners += int(np.count_nonzero(new.kind == FORWARD))
    return corners


@pytest.mark.parametrize("variant", VARIANTS)
def test_simulated_scans_give_the_reference_features(variant):
    corners = compare(SCANS, corner_params(variant), DenoiseParams.default(), 1)
    assert corners >= 20  # the comparison covered corners, not only empty results


def test_paper_mode_gives_the_reference_features():
    assert compare(SCANS, FeatureParams.paper(), DenoiseParams.paper(), 2) >= 20


@pytest.mark.parametrize("variant", ["default", "arclength", "no straightness check", "five picks per arm"])
def test_garbage_scans_give_the_reference_features(variant):
    cp = corner_params(variant)
    rp = R.FeatureParams(**dataclasses.asdict(cp))
    rng = np.random.default_rng(3)
    for r, a in GARBAGE:
        kept = rng.random(len(r)) > 0.2
        assert_same(extract_features(r, a, kept, cp), R.extract_features(r, a, kept, rp))


def test_the_oracle_comparison_can_fail():
    r, a = SCANS[0]
    kept = denoise(r, a, DenoiseParams.default()).kept
    fs = R.extract_features(r, a, kept, R.FeatureParams())
    moved = dataclasses.replace(fs, xy_m=fs.xy_m + 1e-6)
    with pytest.raises(AssertionError):
        assert_same(moved, fs)
