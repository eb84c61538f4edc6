"""Scoring helpers and smoke runs of the feature evaluations (evaluation.features, evaluation.intel_features)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lrfslam.algo.geometry import from_frame, relative
from lrfslam.evaluation import features as ef
from lrfslam.evaluation import intel_features as ei

SHARED_INTEL = Path(__file__).resolve().parents[3] / "shared" / "datasets" / "intel"


def test_match_nearest_is_one_to_one_and_nearest_first():
    det = np.array([[0.0, 0.0], [0.05, 0.0], [1.0, 1.0]])
    truth = np.array([[0.04, 0.0], [5.0, 5.0]])
    di, ti = ef.match_nearest(det, truth, 0.1)
    assert di.tolist() == [1] and ti.tolist() == [0]  # the nearer detection wins the one truth point
    assert len(ef.match_nearest(det, np.zeros((0, 2)), 0.1)[0]) == 0
    assert len(ef.match_nearest(det, truth, 0.001)[0]) == 0


def test_repeatability_of_a_static_world_seen_from_two_poses():
    world_pts = np.array([[3.0, 1.0], [2.0, -1.0], [9.0, 0.0]])  # the last is out of range
    poses = np.array([[0.0, 0.0, 0.0], [0.3, 0.1, 0.2]])
    seen = [from_frame(world_pts, relative(p, np.zeros(3))) for p in poses]
    rep = ei.repeatability(seen, poses, 1, 0.1, 4.0)
    assert (rep.matched, rep.possible, rep.pairs) == (2, 2, 1) and rep.value == 1.0
    moved = [seen[0], seen[1] + 0.5]  # every detection of scan 2 half a metre off
    assert ei.repeatability(moved, poses, 1, 0.1, 4.0).matched == 0
    assert np.isnan(ei.repeatability([seen[0], np.zeros((0, 2))], poses, 1, 0.1, 4.0).value)


def test_random_rooms_have_eligible_corners_and_free_poses():
    rng = np.random.default_rng(0)
    room = ef.random_room(rng)
    poses = ef.room_poses(room, 5, rng)
    assert len(room.corners()) >= 8 and poses.shape == (5, 3)
    assert sum(len(ef.scan_truth(room, p).eligible) for p in poses) > 0


def test_quick_simulated_evaluation_prints_both_modes(capsys):
    assert ef.main(["--quick"]) == 0
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith(("| hallway_loop", "| rooms"))]
    assert len(rows) == 4 and any("| default |" in r for r in rows) and any("| paper |" in r for r in rows)


@pytest.mark.skipif(not (SHARED_INTEL / "intel.clf.bz2").exists(), reason="Intel log not available")
def test_quick_intel_run(capsys):
    assert ei.main(["--quick", "--log", str(SHARED_INTEL / "intel.clf.bz2"),
                    "--relations", str(SHARED_INTEL / "intel.relations")]) == 0
    out = capsys.readouterr().out
    assert "400 FLASER scans" in out and out.count("| default |") == 2
