"""extract_features against its two oracles, on many scans and under every option that changes the search.

* The accelerated forward search (``algo/forward_search_kernel.py``, the default) against
  the plain one (``right_angle_bases`` in ``algo/features.py``) on every scan below: the
  kernel screens base points before picking and fitting their arms, the plain code
  walks and fits every arm of every base point. Same base points and arm ends, the same
  angles to rounding (the two fit the arm lines with different arithmetic). Everything
  after forward searching is code the two share.
* The whole stage against the previous implementation (``reference_features.py``, array
  code written apart from the current one), which also checks that shared code:
  suppression, the dense refit, backward searching, covariances. Same features: the same
  kinds, beams and refits, positions and angles to rounding.

Rounding can decide between two base points of exactly equal angle (a noise-free
symmetric corner) in suppression, so the plain and the accelerated search are compared
where they meet, not by the features that come out; and the generated scans, where such
corners occur, are compared with the previous implementation without suppression.
"""

from __future__ import annotations

import dataclasses
import itertools
from pathlib import Path
from unittest import mock

import numpy as np
import pytest
import reference_features as R
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from oracle_scans import garbage, simulated

from lrfslam.algo import forward_search_kernel as K
from lrfslam.algo.features import (
    FORWARD,
    FeatureParams,
    extract_features,
    right_angle_bases,
)
from lrfslam.algo.geometry import from_frame
from lrfslam.algo.histogram import DenoiseParams, denoise
from lrfslam.io.carmen import CarmenReader, LaserRecord
from lrfslam.io.textfile import open_log
from lrfslam.sim.lidar import LidarModel, simulate_scan
from lrfslam.sim.world import World, closed_polygon

SCANS = simulated(24, 8, seed=5)
GARBAGE = garbage(80, seed=6)
INTEL_HEAD = Path(__file__).resolve().parents[1] / "data" / "intel_head.clf"
INTEL_LOG = Path(__file__).resolve().parents[2].parent / "shared" / "datasets" / "intel" / "intel.clf.bz2"

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
    # Every base point that passes the right-angle test becomes a feature, with its angle.
    "every right-angle base": {"refine_corner": False, "nms_radius_m": 0.0},
    "wide refit": {"refine_rmax_m": 1.5},
    "break gap 1.5 m": {"arm_break_gap_m": 1.5},
    "no suppression": {"nms_radius_m": 0.0},
    "every finite/∞ edge": {"inf_edge_rule": "any"},
    "edges across removed": {"edge_max_removed": None},
}


def feature_params(variant: str) -> FeatureParams:
    return dataclasses.replace(FeatureParams.default(), **VARIANTS[variant])


def assert_same(new, old):
    assert new.kind.tolist() == old.kind.tolist()
    assert new.beam.tolist() == old.beam.tolist()
    assert new.refined.tolist() == old.refined.tolist()
    np.testing.assert_allclose(new.xy_m, old.xy_m, rtol=0, atol=1e-9)
    np.testing.assert_allclose(new.angle_deg, old.angle_deg, rtol=0, atol=1e-9)
    scale = np.abs(old.cov_m2).max(axis=(1, 2), keepdims=True) if len(old) else 1.0
    np.testing.assert_allclose(new.cov_m2 / scale, old.cov_m2 / scale, rtol=0, atol=1e-9)


def assert_same_bases(new, old):
    (columns, angles, ends), (old_columns, old_angles, old_ends) = new, old
    assert columns == old_columns
    assert ends == old_ends
    np.testing.assert_allclose(angles, old_angles, rtol=0, atol=1e-9)


def pinned_search(z, step_m, breaks, params):
    """The accelerated forward search, after checking it against the plain one."""
    fast = ACCELERATED(z, step_m, breaks, params)
    assert_same_bases(fast, right_angle_bases(z, step_m, breaks, params))
    return fast


ACCELERATED = K.right_angle_bases


def check(r, a, kept, fp: FeatureParams):
    """The features, after checking the forward search against the plain one and the
    features against the previous implementation."""
    with mock.patch.object(K, "right_angle_bases", pinned_search):
        fast = extract_features(r, a, kept, fp)
    assert_same(fast, R.extract_features(r, a, kept, R.FeatureParams(**dataclasses.asdict(fp))))
    return fast


def compare(scans, fp: FeatureParams, dp: DenoiseParams, seed: int) -> int:
    """Compare on each scan with the filter's kept points and with a random tenth dropped too; corners seen."""
    rng = np.random.default_rng(seed)
    corners = 0
    for r, a in scans:
        kept = denoise(r, a, dp).kept
        for k in (kept, kept & (rng.random(len(r)) > 0.1)):
            corners += int(np.count_nonzero(check(r, a, k, fp).kind == FORWARD))
    return corners


@pytest.mark.parametrize("variant", VARIANTS)
def test_simulated_scans_give_the_oracles_features(variant):
    corners = compare(SCANS, feature_params(variant), DenoiseParams.default(), 1)
    assert corners >= 20  # the comparison covered corners, not only empty results


def test_paper_mode_gives_the_oracles_features():
    assert compare(SCANS, FeatureParams.paper(), DenoiseParams.paper(), 2) >= 20


def laser_scans(path: Path, n_lines: int | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """(ranges_m, angles_rad) of the FLASER records in the first ``n_lines`` of a CARMEN log."""
    with open_log(path) as f:
        records = [i for i in CarmenReader(itertools.islice(f, n_lines)) if isinstance(i, LaserRecord)]
    return [(rec.ranges_m, rec.angle_min_rad + rec.angle_increment_rad * np.arange(rec.n_beams)) for rec in records]


def preset(variant: str) -> tuple[FeatureParams, DenoiseParams]:
    if variant == "paper":
        return FeatureParams.paper(), DenoiseParams.paper()
    return feature_params(variant), DenoiseParams.default()


@pytest.mark.parametrize("variant", ["paper", *VARIANTS])
def test_the_intel_head_gives_the_oracles_features(variant):
    # Ten scans of a corridor, straight walls and no-returns: no corners within 4 m.
    scans = laser_scans(INTEL_HEAD)
    assert len(scans) == 10
    compare(scans, *preset(variant), 4)


@pytest.mark.skipif(not INTEL_LOG.is_file(), reason="Intel dataset not present")
@pytest.mark.parametrize("variant", ["paper", "default", "arclength", "every right-angle base"])
def test_the_intel_log_gives_the_oracles_features(variant):
    # The robot reaches rooms with corners within 4 m about 1700 scans in.
    scans = laser_scans(INTEL_LOG, 6600)[1700:]
    assert len(scans) > 400
    assert compare(scans, *preset(variant), 4) >= 20


@pytest.mark.parametrize("variant", ["default", "arclength", "no straightness check", "five picks per arm"])
def test_garbage_scans_give_the_oracles_features(variant):
    fp = feature_params(variant)
    rng = np.random.default_rng(3)
    for r, a in GARBAGE:
        check(r, a, rng.random(len(r)) > 0.2, fp)


@st.composite
def room_scans(draw):
    """A scan from inside a random rectangular room, at a random noise level."""
    w, h = draw(st.floats(2.0, 6.0)), draw(st.floats(2.0, 6.0))
    rect = closed_polygon([(0, 0), (w, 0), (w, h), (0, h)], free_inside=True)
    place = (draw(st.floats(-3, 3)), draw(st.floats(-3, 3)), draw(st.floats(-np.pi, np.pi)))
    world = World(from_frame(rect.reshape(-1, 2), place).reshape(-1, 4), "room")
    inside = (draw(st.floats(0.2, w - 0.2)), draw(st.floats(0.2, h - 0.2)))
    pose = (*from_frame(np.array([inside]), place)[0], draw(st.floats(-np.pi, np.pi)))
    sigma = draw(st.sampled_from([0.0, 0.005, 0.01, 0.03]))
    scan = simulate_scan(world, pose, LidarModel(range_sigma_m=sigma), np.random.default_rng(draw(st.integers(0, 2**31))))
    return scan.ranges_m, scan.angles_rad


@settings(max_examples=80, deadline=None)
@given(room_scans(), st.data(), st.sampled_from(["paper", *VARIANTS]))
def test_generated_room_scans_give_the_oracles_features(scan, data, variant):
    r, a = scan
    fp, dp = preset(variant)
    fp = dataclasses.replace(fp, nms_radius_m=0.0)
    kept = denoise(r, a, dp).kept & data.draw(arrays(bool, len(r), elements=st.just(True)) |
                                                                  arrays(bool, len(r)))
    check(r, a, kept, fp)


ranges_st = arrays(
    np.float64, st.integers(0, 200),
    elements=st.one_of(st.floats(-1.0, 10.0), st.sampled_from([np.nan, np.inf, -np.inf, 0.0])),
)


def a_jump_within_rounding(r: np.ndarray, a: np.ndarray, jump_m: float) -> bool:
    """Are two returns (ranges r, bearings a, (N,)) a jump apart to within rounding? There the
    previous implementation (squared distances) and this one (distances) may round either way."""
    ok = np.isfinite(r) & (r > 0)
    p = np.column_stack((r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])))
    return bool(np.any(np.abs(np.linalg.norm(p[:, None] - p[None], axis=2) - jump_m) < 1e-9))


@settings(max_examples=80, deadline=None)
@given(ranges_st, st.data(), st.sampled_from(["paper", *VARIANTS]))
def test_generated_arbitrary_ranges_give_the_oracles_features(r, data, variant):
    fp = dataclasses.replace(preset(variant)[0], nms_radius_m=0.0)
    a = np.radians(np.arange(len(r), dtype=float) * 0.5)
    assume(not a_jump_within_rounding(r, a, fp.jump_m))
    check(r, a, data.draw(arrays(bool, len(r))), fp)


def test_the_plain_forward_search_gives_the_same_features_on_the_simulated_scans():
    fp, dp = FeatureParams.default(), DenoiseParams.default()
    for r, a in SCANS:
        kept = denoise(r, a, dp).kept
        assert_same(extract_features(r, a, kept, fp, accelerated=False), extract_features(r, a, kept, fp))


def test_the_forward_search_comparison_can_fail():
    # An L of two 1.5 m walls meeting at (2, 0), points 3 cm apart.
    t = np.arange(0.0, 1.5, 0.03)
    z = np.concatenate((2.0 - 1j * t[::-1], 2.0 - t[1:]))
    bases = right_angle_bases(z, np.abs(np.diff(z)), [], FeatureParams.paper())
    assert 49 in bases[0]
    with pytest.raises(AssertionError):
        assert_same_bases(bases, (bases[0][1:], bases[1][1:], bases[2][1:]))
    with pytest.raises(AssertionError):
        assert_same_bases(bases, (bases[0], [x + 1e-6 for x in bases[1]], bases[2]))


def test_the_oracle_comparison_can_fail():
    r, a = SCANS[0]
    kept = denoise(r, a, DenoiseParams.default()).kept
    fs = extract_features(r, a, kept, FeatureParams.default(), accelerated=False)
    moved = dataclasses.replace(fs, xy_m=fs.xy_m + 1e-6)
    with pytest.raises(AssertionError):
        assert_same(moved, fs)
