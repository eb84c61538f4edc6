"""The loop-closure evaluation's pure parts: parameter overrides and relation spans."""

from __future__ import annotations

import numpy as np
import pytest

from lrfslam.algo.geometry import relative
from lrfslam.algo.loop_closure import LoopClosureParams
from lrfslam.errors import ConfigError
from lrfslam.evaluation.loop_closure import apply_sets, span_stats
from lrfslam.evaluation.relations import load_relations


def test_sets_reach_nested_tables_and_keep_types():
    params = apply_sets(LoopClosureParams(), ["min_score=0.6", "correlative.levels=5", "max_candidates=3"])
    assert params.min_score == 0.6
    assert params.correlative.levels == 5 and isinstance(params.correlative.levels, int)
    assert params.max_candidates == 3
    with pytest.raises(ConfigError):
        apply_sets(LoopClosureParams(), ["no_such_field=1"])
    with pytest.raises(ConfigError):
        apply_sets(LoopClosureParams(), ["min_score"])


def test_spans_split_the_relations():
    stamps = np.arange(0.0, 100.0, 0.5)
    truth = np.column_stack((stamps * 0.1, np.zeros_like(stamps), np.zeros_like(stamps)))
    # The estimate drifts 1 cm per second sideways: error grows with the span.
    est = truth + np.column_stack((np.zeros_like(stamps), 0.01 * stamps, np.zeros_like(stamps)))
    lines = []
    for t1, t2 in ((0.0, 1.0), (10.0, 11.5), (0.0, 10.0), (20.0, 40.0), (0.0, 50.0), (10.0, 90.0)):
        d = relative(truth[int(t1 * 2)], truth[int(t2 * 2)])
        lines.append(f"{t1} {t2} {d[0]} {d[1]} 0 0 0 {d[2]}")
    stats = span_stats(stamps, est, load_relations(lines))
    assert stats["all"].n_used == 6
    assert [stats[k].n_used for k in ("< 2 s", "2-30 s", ">= 30 s")] == [2, 2, 2]
    assert stats["< 2 s"].trans_abs_m.mean == pytest.approx(0.0125, abs=1e-9)
    assert stats[">= 30 s"].trans_abs_m.mean == pytest.approx(0.65, abs=1e-9)
