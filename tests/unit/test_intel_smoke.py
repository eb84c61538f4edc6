"""Smoke tests on the real Intel Research Lab log (skipped when the dataset is absent)."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import numpy as np
import pytest

from lrfslam.evaluation.intel_baseline import evaluate_odometry_baseline
from lrfslam.evaluation.relations import load_relations
from lrfslam.io.carmen import CarmenIssue, CarmenReader, LaserRecord, OdomRecord
from lrfslam.io.textfile import open_log

INTEL = Path(__file__).resolve().parents[2].parent / "shared" / "datasets" / "intel"
LOG = INTEL / "intel.clf.bz2"
RELATIONS = INTEL / "intel.relations"
HEAD = Path(__file__).resolve().parents[1] / "data" / "intel_head.clf"

needs_intel = pytest.mark.skipif(not (LOG.is_file() and RELATIONS.is_file()), reason="Intel dataset not present")


def test_intel_head_fixture():
    """First 40 lines of intel.clf, committed: 10 FLASER, 19 ODOM, header lines skipped."""
    with open_log(HEAD) as f:
        reader = CarmenReader(f)
        items = list(reader)
    assert reader.skipped == {"#": 9, "PARAM": 2}
    assert sum(isinstance(i, LaserRecord) for i in items) == 10
    assert sum(isinstance(i, OdomRecord) for i in items) == 19
    first = next(i for i in items if isinstance(i, LaserRecord))
    assert first.line_no == 13 and first.stamp_s == 976052857.337530
    assert first.n_beams == 180 and first.ranges_m[0] == 1.07
    assert first.ranges_m[89] == math.inf  # logged as 81.83 ("no return")
    np.testing.assert_array_equal(first.laser_pose, first.odom_pose)


@needs_intel
def test_intel_first_2000_lines():
    with open_log(LOG) as f:
        reader = CarmenReader(itertools.islice(f, 2000))
        items = list(reader)
    assert reader.lines_read == 2000
    assert not [i for i in items if isinstance(i, CarmenIssue)]
    scans = [i for i in items if isinstance(i, LaserRecord)]
    assert len(scans) > 600
    assert all(s.n_beams == 180 and s.source == "FLASER" for s in scans)
    ranges = np.concatenate([s.ranges_m for s in scans])
    assert np.isinf(ranges).any() and np.all(ranges[np.isfinite(ranges)] < 80.0)
    # Every relation stamp is a FLASER ipc stamp, so the early ones must be found exactly.
    stamps = {s.stamp_s for s in scans}
    with open_log(RELATIONS) as f:
        rel = load_relations(f)
    early = rel.stamp1_s[rel.stamp1_s <= max(stamps)]
    assert early.size > 0 and all(t in stamps for t in early)


@needs_intel
def test_intel_odometry_baseline_matches_reference():
    """Raw odometry: 7.37 ± 14.35 m and 39.2 ± 53.8 deg (in-house reference, anchors note)."""
    stats = evaluate_odometry_baseline(LOG, RELATIONS)
    assert (stats.n_relations, stats.n_used, stats.n_unmatched) == (2984, 2984, 0)
    assert stats.max_match_gap_s == 0.0
    assert stats.trans_abs_m.mean == pytest.approx(7.37, abs=0.005)
    assert stats.trans_abs_m.std == pytest.approx(14.35, abs=0.005)
    assert stats.rot_abs_deg.mean == pytest.approx(39.2, abs=0.05)
    assert stats.rot_abs_deg.std == pytest.approx(53.8, abs=0.05)
