"""Raw-odometry baseline of the relation metric on a CARMEN log (reads files).

The "do nothing" reference a SLAM estimate must beat: the odometry pose carried
on each laser line, scored against the ground-truth relations.
"""

from __future__ import annotations

from pathlib import Path

from lrfslam.evaluation.relations import (
    DEFAULT_MAX_STAMP_GAP_S,
    RelationStats,
    load_relations,
    relation_errors,
)
from lrfslam.io.carmen import iter_records, laser_trajectory
from lrfslam.io.textfile import open_log


def evaluate_odometry_baseline(
    log_path: str | Path,
    relations_path: str | Path,
    max_stamp_gap_s: float = DEFAULT_MAX_STAMP_GAP_S,
) -> RelationStats:
    """Score the raw odometry of a CLF against a relations file.

    Parameters
    ----------
    log_path : str or Path
        CARMEN log (plain, .bz2 or .gz) with FLASER/RLASER/ROBOTLASERk lines.
    relations_path : str or Path
        Freiburg relations file keyed by the laser ipc timestamps of that log.
    max_stamp_gap_s : float
        Stamp-matching tolerance (s).

    Returns
    -------
    RelationStats
        Errors of the odometry pose of every scan (file order). Malformed log or
        relation lines are skipped; unmatched relations are counted in the result.
    """
    with open_log(log_path) as log:
        stamps_s, poses = laser_trajectory(iter_records(log), pose="odom")
    with open_log(relations_path) as rel:
        relations = load_relations(rel)
    return relation_errors(stamps_s, poses, relations, max_stamp_gap_s)
