"""denoise and the mixed-pixel tests against reference_histogram.py.

With ``mixed_model="range"`` the optimised ``denoise`` must equal the previous
implementation exactly; the straight-line test must equal the same line
intersection written out point by point.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import reference_histogram as RH
from oracle_scans import garbage, simulated

from lrfslam.algo.histogram import DenoiseParams, denoise, valid_returns
from lrfslam.algo.mixed_pixels import beam_tables, off_line

SCANS = simulated(24, 8, seed=7) + garbage(80, seed=8)

CHANGES = [
    {}, {"stride": 3}, {"bin_mode": "fixed"}, {"keep_rule": "and"}, {"shadow_min_angle_deg": 10.0},
    {"bin_deg": 10.0, "period_deg": 180.0}, {"keep_frac": 0.0}, {"mixed_tol_m": 0.0}, {"mixed_tol_m": 0.03},
]


def reference_params(p: DenoiseParams):
    return RH.DenoiseParams(**{k: v for k, v in dataclasses.asdict(p).items() if k != "mixed_model"})


def assert_same(new, old):
    for field in ("kept", "valid", "mixed", "hist_counts", "hist_edges_deg"):
        assert np.array_equal(getattr(new, field), getattr(old, field)), field
    assert new.n_segments == old.n_segments
    assert np.array_equal(new.points_xy, old.points_xy, equal_nan=True)


@pytest.mark.parametrize("change", CHANGES)
def test_range_model_is_the_previous_denoise(change):
    p = dataclasses.replace(DenoiseParams.default(), mixed_model="range", **change)
    for r, a in SCANS:
        assert_same(denoise(r, a, p), RH.denoise(r, a, reference_params(p)))


@pytest.mark.parametrize("change", CHANGES)
def test_line_model_is_the_previous_denoise_with_the_point_by_point_line_test(change):
    p = dataclasses.replace(DenoiseParams.default(), **change)
    removed = 0
    for r, a in SCANS:
        new = denoise(r, a, p)
        assert_same(new, RH.denoise(r, a, reference_params(p), mixed_test=RH.off_line_slow))
        removed += int(new.mixed.sum())
    assert removed > 0 or p.mixed_tol_m == 0


def test_off_line_is_the_line_intersection():
    flagged = 0
    for r, a in SCANS:
        valid = valid_returns(r, 4.0)
        for tol in (0.02, 0.08):
            new = off_line(r, beam_tables(a), valid, tol)
            assert np.array_equal(new, RH.off_line_slow(r, a, valid, tol))
            flagged += int(new.sum())
    assert flagged > 50


def test_beam_tables_follow_the_bearings():
    a = np.radians(np.arange(-90.0, 91.0))
    t = beam_tables(a)
    np.testing.assert_allclose(t.cos, np.cos(a))
    np.testing.assert_allclose(t.sin2, np.sin(a[2:] - a[:-2]))
    assert t.step_rad == pytest.approx(np.radians(1.0))
    other = beam_tables(a[:90] * 0.5)
    assert len(other.cos) == 90 and other.step_rad == pytest.approx(np.radians(0.5))
    assert beam_tables(a) is not other and np.array_equal(beam_tables(a).cos, t.cos)
    with pytest.raises(ValueError):
        t.cos[0] = 2.0  # shared between scans: read-only
