"""A recording's trajectories scored against ground-truth relations (Kümmerle et al. 2009).

The trajectories a recording holds — the slam estimate, the mapper's online and final
trajectories, raw odometry — read from it and scored with :mod:`lrfslam.evaluation.relations`;
one table of the result. ``lrfslam eval relations`` prints it for one recording and
``lrfslam eval relations --all`` for every log.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from lrfslam.errors import DecodeError
from lrfslam.evaluation.map_trajectory import final_trajectory
from lrfslam.evaluation.relations import (
    DEFAULT_MAX_STAMP_GAP_S,
    SPANS_S,
    Relations,
    RelationStats,
    errors_by_span,
    load_relations,
    relation_errors,
    span_label,
    stamp_s,
)
from lrfslam.io.textfile import open_log
from lrfslam.msgs import topics
from lrfslam.runtime.recording import read_recording

#: Trajectories scored by ``relations``: row label -> topic whose poses form it. "slam estimate"
#: and "mapper online" are as published at each scan; "mapper final" (computed from the last
#: map/keyframes) is the trajectory with every loop closure solved for.
TRAJECTORIES = {"slam estimate": topics.SLAM_STATE, "mapper online": topics.MAP_POSE, "raw odometry": topics.ODOM}
MAPPER_FINAL = "mapper final"


def read_trajectories(path: str | Path, wanted: Mapping[str, topics.Topic] = TRAJECTORIES
                      ) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], int]:
    """Stamps (s, shape (T,)) and poses (x_m, y_m, theta_rad; shape (T, 3)) per label of ``wanted``.

    Returns the trajectories, in log-time order, and the number of messages that
    could not be decoded (skipped). A label whose topic is absent gets T = 0.
    """
    by_topic = {topic.name: (label, topic) for label, topic in wanted.items()}
    rows: dict[str, tuple[list[float], list[np.ndarray]]] = {label: ([], []) for label in wanted}
    undecodable = 0
    for rec in read_recording(path, list(by_topic)):
        label, topic = by_topic[rec.topic]
        try:
            value = topic.codec.decode(rec.data, rec.schema)
        except DecodeError:
            undecodable += 1
            continue
        rows[label][0].append(stamp_s(value.stamp_ns))
        rows[label][1].append(value.pose)
    return ({label: (np.array(s, dtype=float), np.array(p, dtype=float).reshape(-1, 3))
             for label, (s, p) in rows.items()}, undecodable)


def evaluate_relations(path: str | Path, relations_path: str | Path,
                       max_gap_s: float = DEFAULT_MAX_STAMP_GAP_S,
                       extra: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None
                       ) -> tuple[dict[str, RelationStats], int]:
    """Relation metric of each trajectory of the recording ``path`` present in it.

    Parameters
    ----------
    path : path-like
        Recording with ``slam/state`` and/or ``odom``; stamps on the relations' clock.
    relations_path : path-like
        Freiburg relations file (plain, .bz2 or .gz).
    max_gap_s : float
        Stamp-matching tolerance (s).
    extra : mapping, optional
        More trajectories to score, label -> (stamps s (T,), poses (T, 3)), e.g. scan matching alone.

    Returns
    -------
    dict of str to RelationStats, int
        Per trajectory label with at least one pose; messages that did not decode.
    """
    with open_log(relations_path) as f:
        relations = load_relations(f)
    trajectories, undecodable = read_trajectories(path)
    final = final_trajectory(path)
    if final is not None:
        trajectories[MAPPER_FINAL] = (np.array([stamp_s(v) for v in final[0]]), final[1])
    trajectories.update(extra or {})
    return ({label: relation_errors(stamps, poses, relations, max_gap_s)
             for label, (stamps, poses) in trajectories.items() if stamps.size},
            undecodable)


def relations_table(results: Mapping[str, RelationStats], relations: Relations | None = None) -> str:
    """Mean ± std of the absolute and squared translational (m, m²) and rotational (deg, deg²) errors;
    with ``relations``, the mean translational error (m) per relation span too."""
    spans = [span_label(span) for span in SPANS_S] if relations is not None else []
    head = (f"{'trajectory':15s} {'used':>6s} {'unmatched':>9s} {'trans abs (m)':>17s} {'trans sqr (m^2)':>17s} "
            f"{'rot abs (deg)':>15s} {'rot sqr (deg^2)':>17s} {'max trans (m)':>13s}"
            + "".join(f" {label:>8s}" for label in spans))
    lines = [head, "-" * len(head)]
    for label, s in results.items():
        by_span = errors_by_span(s, relations) if relations is not None else {}
        lines.append(
            f"{label:15s} {s.n_used:6d} {s.n_unmatched:9d} "
            f"{s.trans_abs_m.mean:8.3f} ± {s.trans_abs_m.std:6.3f} {s.trans_sqr_m2.mean:8.3f} ± {s.trans_sqr_m2.std:6.3f} "
            f"{s.rot_abs_deg.mean:6.2f} ± {s.rot_abs_deg.std:6.2f} {s.rot_sqr_deg2.mean:7.1f} ± {s.rot_sqr_deg2.std:7.1f} "
            f"{s.trans_abs_m.max:13.3f}" + "".join(f" {by_span[k][1].mean:8.3f}" for k in spans))
    return "\n".join(lines)
