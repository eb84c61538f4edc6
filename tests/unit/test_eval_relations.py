"""``lrfslam eval relations``: the relation metric of a recording's estimate and odometry."""

from __future__ import annotations

import math
import sys

import numpy as np
import pytest

from lrfslam.evaluation.recording_relations import evaluate_relations
from lrfslam.evaluation.relations import stamp_s
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.runtime.recording import RecordingWriter, SegmentedWriter, read_recording
from lrfslam.tools import evaluate
from lrfslam.tools.importers import stamp_ns

# Unix-epoch stamps like Intel's, 0.2 s apart: where ns -> s conversion must be exact.
STAMPS_S = [976052857.337530, 976052857.537530, 976052857.737530, 976052857.937530]
# The estimate drives 1 m along x per stamp; odometry over-counts distance by 10 %.
ESTIMATE = [(k, 0.0, 0.0) for k in range(4)]
ODOMETRY = [(1.1 * k, 0.0, 0.0) for k in range(4)]
# (i, j, delta*): pose j in the frame of pose i.
RELATIONS = [
    (0, 1, (1.0, 0.0, 0.0)),   # estimate exact; odometry 0.1 m long
    (1, 3, (2.0, 0.5, 0.0)),   # estimate misses 0.5 m sideways; odometry sqrt(0.2² + 0.5²)
    (0, 2, (2.0, 0.0, 0.1)),   # estimate exact in x, 0.1 rad off; odometry 0.2 m and 0.1 rad
]
EST_TRANS = np.array([0.0, 0.5, 0.0])
ODOM_TRANS = np.array([0.1, math.sqrt(0.29), 0.2])
ROT_DEG = np.array([0.0, 0.0, math.degrees(0.1)])


def write_recording(path, estimate=True, odometry=True):
    with RecordingWriter(path) as writer:
        for k, s in enumerate(STAMPS_S):
            ns = stamp_ns(s)
            values = []
            if odometry:
                values.append((topics.ODOM, t.Odometry(stamp_ns=ns, seq=k + 1, pose=ODOMETRY[k])))
            if estimate:
                values.append((topics.SLAM_STATE, t.SlamState(stamp_ns=ns, seq=k + 1, scan_seq=k + 1, pose=ESTIMATE[k],
                                                              pose_cov=np.eye(3))))
            for topic, value in values:
                writer.write(topic.name, topic.schema, topic.codec.encode(value), ns)
    return path


def write_relations(path, offset_s=0.0):
    lines = ["# t1 t2 x y z roll pitch yaw"]
    for i, j, (x, y, yaw) in RELATIONS:
        lines.append(f"{STAMPS_S[i] + offset_s:.6f} {STAMPS_S[j] + offset_s:.6f} {x} {y} 0 0 0 {yaw}")
    path.write_text("\n".join(lines) + "\n")
    return path


def check(stats, trans, rot):
    assert (stats.n_relations, stats.n_used, stats.n_unmatched) == (3, 3, 0)
    assert stats.trans_abs_m.mean == pytest.approx(trans.mean(), abs=1e-12)
    assert stats.trans_abs_m.std == pytest.approx(trans.std(), abs=1e-12)
    assert stats.trans_sqr_m2.mean == pytest.approx((trans**2).mean(), abs=1e-12)
    assert stats.trans_sqr_m2.std == pytest.approx((trans**2).std(), abs=1e-12)
    assert stats.rot_abs_deg.mean == pytest.approx(rot.mean(), abs=1e-9)
    assert stats.rot_abs_deg.std == pytest.approx(rot.std(), abs=1e-9)
    assert stats.rot_sqr_deg2.mean == pytest.approx((rot**2).mean(), abs=1e-9)


def test_hand_computed_errors(tmp_path):
    results, undecodable = evaluate_relations(write_recording(tmp_path / "r.mcap"),
                                              write_relations(tmp_path / "r.relations"))
    assert undecodable == 0 and list(results) == ["slam estimate", "raw odometry"]
    # By hand: estimate 1/6 ± sqrt(1/12 - 1/36) m, odometry (0.1 + 0.5385 + 0.2) / 3 m.
    assert results["slam estimate"].trans_abs_m.mean == pytest.approx(1 / 6)
    assert results["slam estimate"].trans_abs_m.std == pytest.approx(math.sqrt(1 / 12 - 1 / 36))
    assert results["raw odometry"].trans_abs_m.mean == pytest.approx((0.3 + math.sqrt(0.29)) / 3)
    check(results["slam estimate"], EST_TRANS, ROT_DEG)
    check(results["raw odometry"], ODOM_TRANS, ROT_DEG)
    # Stamps survive ns -> s exactly, so the logged relation stamps match with no gap.
    assert results["slam estimate"].max_match_gap_s == 0.0


def test_stamp_matching_tolerance(tmp_path):
    rec = write_recording(tmp_path / "r.mcap")
    shifted = write_relations(tmp_path / "r.relations", offset_s=0.05)
    results, _ = evaluate_relations(rec, shifted)
    assert results["raw odometry"].n_used == 3
    results, _ = evaluate_relations(rec, shifted, max_gap_s=0.01)
    assert results["raw odometry"].n_unmatched == 3


def test_table_from_the_command_line(tmp_path, capsys):
    rec, rel = write_recording(tmp_path / "r.mcap"), write_relations(tmp_path / "r.relations")
    assert evaluate.main(["relations", str(rec), str(rel)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert "3 relations" in out[0]
    estimate = next(line for line in out if line.startswith("slam estimate"))
    odometry = next(line for line in out if line.startswith("raw odometry"))
    assert "0.167 ±  0.236" in estimate and f"{ROT_DEG.mean():6.2f} ± {ROT_DEG.std():6.2f}" in estimate
    assert f"{ODOM_TRANS.mean():8.3f} ± {ODOM_TRANS.std():6.3f}" in odometry


def test_missing_trajectories(tmp_path, capsys):
    rel = write_relations(tmp_path / "r.relations")
    only_odom = write_recording(tmp_path / "odom.mcap", estimate=False)
    assert evaluate.main(["relations", str(only_odom), str(rel)]) == 0
    out = capsys.readouterr().out
    assert "raw odometry" in out and "(no slam estimate, mapper online in the recording)" in out
    empty = write_recording(tmp_path / "empty.mcap", estimate=False, odometry=False)
    assert evaluate.main(["relations", str(empty), str(rel)]) == 2
    assert evaluate.main(["relations", str(tmp_path / "absent.mcap"), str(rel)]) == 2


def test_stamp_s_is_exact():
    for s in STAMPS_S:
        assert stamp_s(stamp_ns(s)) == s
    assert stamp_s(1_500_000_001) == 1.500000001


def test_delegated_subcommands(tmp_path, monkeypatch, capsys):
    (tmp_path / "fake_eval_ok.py").write_text("def main(argv):\n    print('got', argv)\n    return 3\n")
    (tmp_path / "fake_eval_broken.py").write_text("import no_such_dependency_xyz\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(evaluate.DELEGATED, "features", "fake_eval_ok")
    assert evaluate.main(["features", "--x", "1"]) == 3
    assert "got ['--x', '1']" in capsys.readouterr().out
    monkeypatch.setitem(evaluate.DELEGATED, "slam", "fake_eval_absent_xyz")
    assert evaluate.main(["slam"]) == 2
    assert "not available" in capsys.readouterr().err
    # A module that exists but lacks a dependency is a bug, not "not available".
    monkeypatch.setitem(evaluate.DELEGATED, "slam", "fake_eval_broken")
    with pytest.raises(ModuleNotFoundError):
        evaluate.main(["slam"])
    sys.modules.pop("fake_eval_ok", None)


def test_a_recording_folder_scores_as_its_single_file(tmp_path, capsys):
    single, rel = write_recording(tmp_path / "r.mcap"), write_relations(tmp_path / "r.relations")
    # The same messages in a folder of one-message segments.
    folder = SegmentedWriter(tmp_path / "run", "run", max_bytes=1)
    for m in read_recording(single):
        folder.write(m.topic, m.schema, m.data, m.stamp_ns)
    folder.close()
    assert len(folder.segments) == 2 * len(STAMPS_S)
    assert evaluate.main(["relations", str(single), str(rel)]) == 0
    from_file = capsys.readouterr().out.splitlines()[1:]
    assert evaluate.main(["relations", str(tmp_path / "run"), str(rel)]) == 0
    assert capsys.readouterr().out.splitlines()[1:] == from_file
