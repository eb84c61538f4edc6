"""``lrfslam eval relations --all``: every log of a datasets folder, one configuration, one table."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from lrfslam.algo.geometry import relative
from lrfslam.errors import ConfigError
from lrfslam.evaluation.relations import ErrorSummary
from lrfslam.io.carmen import iter_records, laser_trajectory
from lrfslam.io.textfile import carmen_logs, open_log
from lrfslam.msgs import topics
from lrfslam.runtime.recording import read_recording
from lrfslam.tools import eval_logs, evaluate

HEAD = Path(__file__).resolve().parents[1] / "data" / "intel_head.clf"


@pytest.fixture
def datasets(tmp_path):
    """Two logs: one with relations made from its own odometry, one without."""
    root = tmp_path / "datasets"
    (root / "scored").mkdir(parents=True)
    (root / "unscored").mkdir()
    (root / "notes").mkdir()   # a folder without a log is not a log
    shutil.copy(HEAD, root / "scored" / "head.clf")
    shutil.copy(HEAD, root / "unscored" / "head.clf")
    with open_log(HEAD) as f:
        stamps, poses = laser_trajectory(iter_records(f))
    rows = []
    for i, j in ((0, 1), (2, 5), (0, 9)):
        dx, dy, dth = relative(poses[i], poses[j])
        rows.append(" ".join(repr(float(v)) for v in (stamps[i], stamps[j], dx, dy, 0, 0, 0, dth)))
    (root / "scored" / "head.relations").write_text("\n".join(rows) + "\n")
    return root


def test_every_log_runs_with_one_configuration_and_the_scored_ones_get_a_table(datasets, tmp_path):
    results = [runs[0] for runs in eval_logs.evaluate_all(datasets, tmp_path / "work", [], {}, {}, draw_maps=False)]
    assert [r.log.name for r in results] == ["scored", "unscored"]
    scored, unscored = results
    assert scored.scans == unscored.scans == 10 and not unscored.scores
    assert set(scored.scores) == {"mapper final", "mapper online", "slam estimate", "scan matching alone",
                                  "raw odometry"}
    # The relations are the odometry's own: its error is zero; every relation is used.
    odom = scored.scores["raw odometry"]
    assert odom.n_used == 3 and odom.trans_abs_m.max == pytest.approx(0.0, abs=1e-6)
    assert sum(n for n, _ in scored.by_span["raw odometry"].values()) == 3   # the head spans under 2 s
    table = eval_logs.markdown(results)
    assert "| scored | raw odometry | 3 | 0.000 ± 0.000 |" in table
    assert "| unscored | (no relations) 10 scans" in table
    assert np.isfinite(scored.scores["slam estimate"].trans_abs_m.mean)


def test_logs_run_side_by_side_give_what_they_give_one_after_another(datasets, tmp_path):
    one = [runs[0] for runs in eval_logs.evaluate_all(datasets, tmp_path / "one", [], {}, {}, draw_maps=False)]
    two = [runs[0] for runs in eval_logs.evaluate_all(datasets, tmp_path / "two", [], {}, {}, draw_maps=False,
                                                      jobs=2)]
    assert [r.log.name for r in two] == ["scored", "unscored"]
    # Same machine, same inputs: the same figures (the time per scan aside).
    for a, b in zip(one, two):
        a.pipeline_s = b.pipeline_s = 0.0
    assert eval_logs.markdown(one) == eval_logs.markdown(two)


def test_trials_run_each_scored_log_under_perturbations_that_must_not_matter(datasets, tmp_path):
    found = eval_logs.evaluate_all(datasets, tmp_path / "work", [], {}, {}, draw_maps=False, jobs=2, trials=3)
    scored, unscored = found
    assert [len(scored), len(unscored)] == [3, 1]   # a log without relations has nothing to spread
    # Trial k adds 1e-6 m of noise seeded k to every return; trial 0 none.
    ranges = []
    for k in range(3):
        [rec] = [r for r in read_recording(tmp_path / "work" / "scored" / f"trial-{k}" / "scored.mcap",
                                           [topics.SCAN.name]) if r.sequence == 5]
        ranges.append(topics.SCAN.codec.decode(rec.data, rec.schema).ranges_m)
    returns = np.isfinite(ranges[0]) & (ranges[0] > 0)
    for k in (1, 2):
        noise = ranges[k][returns] - ranges[0][returns]
        assert 0 < np.abs(noise).max() < 1e-5 and np.all(ranges[k][~returns] == ranges[0][~returns])
    assert not np.array_equal(ranges[1], ranges[2])
    # The odometry is not perturbed: its relations error is zero in every trial, with no spread.
    table = eval_logs.trials_markdown(found)
    assert "| scored | raw odometry | 3 | 0.000 [0.000, 0.000] 0 % |" in table
    assert "unscored" not in table
    assert all(np.isfinite(r.scores["mapper final"].trans_abs_m.mean) for r in scored)


def test_each_run_starts_in_a_process_of_its_own_with_its_trials_environment():
    calls = [(os.getenv, ("OPENBLAS_CORETYPE",), path) for path in eval_logs.FP_PATHS[:3]]
    before = os.environ.get("OPENBLAS_CORETYPE")
    assert eval_logs.in_processes(calls, jobs=2) == [before, "Haswell", "Prescott"]
    assert os.environ.get("OPENBLAS_CORETYPE") == before
    with pytest.raises(ZeroDivisionError):
        eval_logs.in_processes([(divmod, (1, 0), {})], jobs=1)


def test_a_folder_without_logs_is_an_error(tmp_path):
    with pytest.raises(ConfigError, match="no CARMEN log"):
        eval_logs.find_logs(tmp_path)


def test_a_log_folder_linked_in_is_found_and_a_link_back_up_does_not_loop(datasets, tmp_path):
    # A datasets folder of symbolic links to where the logs are kept, one of them pointing at itself.
    linked = tmp_path / "linked"
    linked.mkdir()
    (linked / "scored").symlink_to(datasets / "scored", target_is_directory=True)
    (linked / "scored" / "up").symlink_to(linked, target_is_directory=True)
    logs = eval_logs.find_logs(linked)
    assert [(log.name, log.path.name, log.relations.name) for log in logs] == [("scored", "head.clf", "head.relations")]


def test_the_command_prints_one_table(datasets, tmp_path, capsys):
    assert evaluate.main(["relations", "--all", str(datasets), "--work", str(tmp_path / "w"),
                          "--set", "features.mode=paper"]) == 0
    out = capsys.readouterr().out
    assert out.count("| scored |") == 5 and "map" in out
    verdict = next(line for line in out.splitlines() if line.startswith("scored: mapper final "))
    assert verdict.endswith("trials clean") and "unscored: mapper final" not in out


def test_the_mapper_is_held_to_its_inputs_span_by_span_within_1_mm_or_2_percent():
    def spans(*means):
        return {span: (10, ErrorSummary(m, 0.0, m)) for span, m in zip(("< 2 s", "2-30 s", ">= 30 s"), means,
                                                                         strict=True)}
    result = eval_logs.LogResult(eval_logs.Log("x", Path("x.clf"), Path("x.relations")))
    result.by_span = {"mapper final": spans(0.0109, 0.0520, 0.500),
                      "slam estimate": spans(0.0100, 0.0500, 0.700),
                      eval_logs.SCAN_MATCHING: spans(0.0100, 0.0505, 0.400)}
    # < 2 s: 0.9 mm over both, within the 1 mm margin; 2-30 s: 2.0 mm over the EKF (4 %, beyond 2 %
    # of 0.05 = 1 mm) and 1.5 mm over scan matching; >= 30 s: better than the EKF, worse than scan matching.
    assert eval_logs.worse_than_inputs(result) == [
        "2-30 s: 0.052 m against slam estimate 0.050 m",
        "2-30 s: 0.052 m against scan matching alone 0.051 m",
        ">= 30 s: 0.500 m against scan matching alone 0.400 m",
    ]
    result.by_span["mapper final"] = spans(0.0100, 0.0500, 0.4079)   # 0.4079 <= 0.4 + 2 %
    assert eval_logs.worse_than_inputs(result) == []
    assert eval_logs.worse_than_inputs(eval_logs.LogResult(eval_logs.Log("y", Path("y.clf"), None))) == []


def test_the_closure_nis_band_holds_the_mean_of_consistent_closures_95_percent_of_the_time():
    # Oracle: means of N chi-squared(3) draws; the band must hold about 95 % of them and be
    # centred near 3, narrowing as N grows.
    rng = np.random.default_rng(3)
    for n in (20, 200):
        lo, hi = eval_logs.nis_mean_band(3, n)
        means = rng.chisquare(3, size=(4000, n)).mean(axis=1)
        inside = np.mean((means >= lo) & (means <= hi))
        assert 0.93 < inside < 0.97 and lo < 3.0 < hi
    assert np.diff(eval_logs.nis_mean_band(3, 1000)) < np.diff(eval_logs.nis_mean_band(3, 100))
    assert all(np.isnan(eval_logs.nis_mean_band(3, 0)))


def test_the_closure_audit_runs_the_pipeline_on_an_imported_log(datasets, tmp_path, capsys):
    from lrfslam.tools.importers import import_carmen
    imported = tmp_path / "head.mcap"
    import_carmen(datasets / "scored" / "head.clf", imported)
    rc = evaluate.main(["closures", str(imported), str(datasets / "scored" / "head.relations"),
                        "--work", str(tmp_path / "audit")])
    out = capsys.readouterr().out
    assert rc == 0 and "0 closure attempts, 0 covered" in out and "false accepts" in out
    assert (tmp_path / "audit" / "head.closures.mcap").exists()
    assert evaluate.main(["closures", str(tmp_path / "missing.mcap"), str(datasets / "scored" / "head.relations"),
                          "--work", str(tmp_path / "audit")]) == 2


def test_of_two_links_to_one_log_folder_the_first_by_name_is_given(datasets, tmp_path):
    linked = tmp_path / "linked"
    linked.mkdir()
    for name in ("b_scored", "a_scored"):
        (linked / name).symlink_to(datasets / "scored", target_is_directory=True)
    assert [p.relative_to(linked).as_posix() for p in carmen_logs(linked)] == ["a_scored/head.clf"]
