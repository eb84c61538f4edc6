"""Relation-based SLAM accuracy metric of Kümmerle et al. (2009).

Ground truth is a set of relations ``(t1, t2, delta*)``: the robot pose at ``t2``
expressed in the frame of the robot pose at ``t1``. For an estimated trajectory
the estimated relation is ``delta = x(t1)^-1 ⊕ x(t2)`` and the error is
``e = delta*^-1 ⊕ delta``; the translational error is ``‖(e_x, e_y)‖`` (m), the
rotational error ``|e_theta|`` (deg). Results are reported as mean ± standard
deviation of the absolute and of the squared errors over all relations.

Pure: lines of text and arrays in, dataclasses out.

References
----------
R. Kümmerle, B. Steder, C. Dornhege, M. Ruhnke, G. Grisetti, C. Stachniss,
A. Kleiner, "On measuring the accuracy of SLAM algorithms", Autonomous Robots
27(4), 2009.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from decimal import Decimal

import numpy as np

from lrfslam.algo.geometry import relative
from lrfslam.errors import InputError

#: Stamp-matching tolerance (s) of the Freiburg evaluator: a relation stamp is
#: paired with a trajectory pose no further away in time than this.
DEFAULT_MAX_STAMP_GAP_S = 0.1

# t1 t2 x y z roll pitch yaw
_RELATION_TOKENS = 8


class RelationsInputError(InputError):
    """Arrays handed to :func:`relation_errors` are inconsistent or not finite."""


@dataclass(frozen=True)
class RelationIssue:
    """A malformed line of a relations file, skipped.

    Attributes
    ----------
    line_no : int
        1-based line number.
    reason : str
        What was wrong.
    """

    line_no: int
    reason: str


@dataclass(frozen=True, eq=False)
class Relations:
    """Parsed ground-truth relations (planar part only).

    ``eq=False``: the fields are arrays, so equality is identity.

    Attributes
    ----------
    stamp1_s, stamp2_s : ndarray, shape (M,), read-only
        Timestamps (s) of the reference pose and of the related pose; in the
        Freiburg files these are laser ipc timestamps of the raw log.
    delta : ndarray, shape (M, 3), read-only
        ``(x_m, y_m, yaw_rad)``: pose at ``stamp2_s`` in the frame at ``stamp1_s``.
    line_no : ndarray, shape (M,), read-only
        1-based line number of each relation.
    issues : tuple of RelationIssue
        Malformed lines that were skipped.
    """

    stamp1_s: np.ndarray
    stamp2_s: np.ndarray
    delta: np.ndarray
    line_no: np.ndarray
    issues: tuple[RelationIssue, ...]

    def __len__(self) -> int:
        return int(self.stamp1_s.shape[0])


@dataclass(frozen=True)
class ErrorSummary:
    """Mean, population standard deviation (ddof=0) and maximum of one error kind.

    Units are those of the :class:`RelationStats` field holding it. All are NaN
    when no relation could be evaluated.
    """

    mean: float
    std: float
    max: float


@dataclass(frozen=True, eq=False)
class RelationStats:
    """Result of :func:`relation_errors`.

    Attributes
    ----------
    n_relations : int
        Relations given.
    n_used : int
        Relations whose two stamps both matched a trajectory pose.
    n_unmatched : int
        ``n_relations - n_used``.
    trans_abs_m : ErrorSummary
        Translational error ‖e_xy‖ (m).
    trans_sqr_m2 : ErrorSummary
        Squared translational error (m²).
    rot_abs_deg : ErrorSummary
        Rotational error |e_theta| (deg).
    rot_sqr_deg2 : ErrorSummary
        Squared rotational error (deg²).
    max_match_gap_s : float
        Largest |stamp difference| (s) among the matches used; NaN if none.
    trans_err_m, rot_err_deg : ndarray, shape (M,), read-only
        Per-relation errors in input order, NaN where unmatched.
    matched : ndarray of bool, shape (M,), read-only
        Which relations were evaluated.
    """

    n_relations: int
    n_used: int
    n_unmatched: int
    trans_abs_m: ErrorSummary
    trans_sqr_m2: ErrorSummary
    rot_abs_deg: ErrorSummary
    rot_sqr_deg2: ErrorSummary
    max_match_gap_s: float
    trans_err_m: np.ndarray
    rot_err_deg: np.ndarray
    matched: np.ndarray


def _frozen(a: np.ndarray) -> np.ndarray:
    # Frozen dataclasses; read-only arrays keep their contents frozen as well.
    a.setflags(write=False)
    return a


def load_relations(lines: Iterable[str] | str) -> Relations:
    """Parse a Freiburg relations file (``t1 t2 x y z roll pitch yaw`` per line).

    Parameters
    ----------
    lines : iterable of str, or str
        One relation per line; ``#`` comments and blank lines are skipped. A
        single ``str`` is split into lines first. Units: s, m, rad.

    Returns
    -------
    Relations
        ``z``, ``roll`` and ``pitch`` are checked to be numbers and dropped (the
        metric here is planar). Malformed lines are listed in ``issues``; this
        function never raises on bad content.
    """
    if isinstance(lines, str):
        lines = lines.splitlines()
    rows: list[np.ndarray] = []
    numbers: list[int] = []
    issues: list[RelationIssue] = []
    for line_no, line in enumerate(lines, start=1):
        if not isinstance(line, str):
            issues.append(RelationIssue(line_no, f"expected str, got {type(line).__name__}"))
            continue
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        if len(tokens) != _RELATION_TOKENS:
            issues.append(RelationIssue(line_no, f"expected {_RELATION_TOKENS} numbers, got {len(tokens)} tokens"))
            continue
        try:
            values = np.array(tokens, dtype=float)
        except ValueError:
            issues.append(RelationIssue(line_no, "not a number"))
            continue
        if not np.all(np.isfinite(values)):
            issues.append(RelationIssue(line_no, "not finite"))
            continue
        rows.append(values)
        numbers.append(line_no)
    table = np.array(rows, dtype=float).reshape(-1, _RELATION_TOKENS)
    return Relations(
        stamp1_s=_frozen(table[:, 0].copy()),
        stamp2_s=_frozen(table[:, 1].copy()),
        delta=_frozen(table[:, [2, 3, 7]].copy()),
        line_no=_frozen(np.array(numbers, dtype=int)),
        issues=tuple(issues),
    )


def match_stamps(stamps_s: np.ndarray, query_s: np.ndarray, max_gap_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Nearest trajectory stamp for each query stamp.

    Parameters
    ----------
    stamps_s : ndarray, shape (T,)
        Trajectory stamps (s), any order (raw logs are not monotonic).
    query_s : ndarray, shape (Q,)
        Stamps to look up (s).
    max_gap_s : float
        Largest accepted |difference| (s), >= 0.

    Returns
    -------
    index : ndarray of int, shape (Q,)
        Index into ``stamps_s`` of the nearest stamp, -1 if none lies within
        ``max_gap_s``. Ties go to the smaller stamp; equal stamps to the one
        first in input order.
    gap_s : ndarray, shape (Q,)
        |difference| (s) to that stamp, ``inf`` where unmatched.
    """
    stamps_s = np.asarray(stamps_s, dtype=float).reshape(-1)
    query_s = np.asarray(query_s, dtype=float).reshape(-1)
    index = np.full(query_s.shape, -1, dtype=int)
    gap = np.full(query_s.shape, np.inf)
    if stamps_s.size == 0:
        return index, gap
    # Stable sort so that, among equal stamps, the first in file order wins.
    order = np.argsort(stamps_s, kind="stable")
    ordered = stamps_s[order]
    right = np.clip(np.searchsorted(ordered, query_s, side="left"), 0, ordered.size - 1)
    left = np.clip(right - 1, 0, ordered.size - 1)
    # ordered[left] may end a run of equal stamps; step back to the run's first
    # element, which the stable sort made the first in input order.
    left = np.searchsorted(ordered, ordered[left], side="left")
    gap_left = np.abs(query_s - ordered[left])
    gap_right = np.abs(query_s - ordered[right])
    take_left = gap_left <= gap_right
    best = np.where(take_left, left, right)
    best_gap = np.where(take_left, gap_left, gap_right)
    ok = best_gap <= max_gap_s
    index[ok] = order[best[ok]]
    gap[ok] = best_gap[ok]
    return index, gap


def _summary(values: np.ndarray) -> ErrorSummary:
    # Explicit empty case: np.mean of nothing would emit a RuntimeWarning.
    if values.size == 0:
        return ErrorSummary(float("nan"), float("nan"), float("nan"))
    return ErrorSummary(float(np.mean(values)), float(np.std(values)), float(np.max(values)))


def relation_errors(
    stamps_s: np.ndarray,
    poses: np.ndarray,
    relations: Relations,
    max_stamp_gap_s: float = DEFAULT_MAX_STAMP_GAP_S,
) -> RelationStats:
    """Evaluate an estimated trajectory against ground-truth relations.

    Parameters
    ----------
    stamps_s : ndarray, shape (T,)
        Stamp (s) of each estimated pose, on the clock the relations use (the
        laser ipc timestamps for the Freiburg files). Any order.
    poses : ndarray, shape (T, 3)
        Estimated poses ``(x_m, y_m, theta_rad)`` in any common world frame (the
        metric only uses relative poses).
    relations : Relations
        Ground truth from :func:`load_relations`.
    max_stamp_gap_s : float
        Matching tolerance (s): a relation stamp uses the nearest pose within it.

    Returns
    -------
    RelationStats
        Relations with an unmatched stamp are counted in ``n_unmatched`` and left
        out of the statistics.

    Raises
    ------
    RelationsInputError
        If shapes disagree, an input is not finite, or ``max_stamp_gap_s < 0``.
    """
    stamps_s = np.asarray(stamps_s, dtype=float)
    poses = np.asarray(poses, dtype=float)
    if stamps_s.ndim != 1 or poses.shape != (stamps_s.shape[0], 3):
        raise RelationsInputError(f"need stamps (T,) and poses (T, 3), got {stamps_s.shape} and {poses.shape}")
    if not (np.all(np.isfinite(stamps_s)) and np.all(np.isfinite(poses))):
        raise RelationsInputError("stamps and poses must be finite")
    if not max_stamp_gap_s >= 0.0:
        raise RelationsInputError(f"max_stamp_gap_s must be >= 0, got {max_stamp_gap_s}")

    index1, gap1 = match_stamps(stamps_s, relations.stamp1_s, max_stamp_gap_s)
    index2, gap2 = match_stamps(stamps_s, relations.stamp2_s, max_stamp_gap_s)
    matched = (index1 >= 0) & (index2 >= 0)

    # geometry.relative unpacks its arguments into x, y, theta, so passing (3, K)
    # arrays evaluates all K relations at once; its result is (3, K).
    estimated = relative(poses[index1[matched]].T, poses[index2[matched]].T)
    error = relative(relations.delta[matched].T, estimated)
    trans = np.hypot(error[0], error[1])
    rot = np.degrees(np.abs(error[2]))

    trans_all = np.full(len(relations), np.nan)
    rot_all = np.full(len(relations), np.nan)
    trans_all[matched] = trans
    rot_all[matched] = rot
    n_used = int(np.count_nonzero(matched))
    return RelationStats(
        n_relations=len(relations),
        n_used=n_used,
        n_unmatched=len(relations) - n_used,
        trans_abs_m=_summary(trans),
        trans_sqr_m2=_summary(trans**2),
        rot_abs_deg=_summary(rot),
        rot_sqr_deg2=_summary(rot**2),
        max_match_gap_s=float(np.max(np.maximum(gap1[matched], gap2[matched]))) if n_used else float("nan"),
        trans_err_m=_frozen(trans_all),
        rot_err_deg=_frozen(rot_all),
        matched=_frozen(matched),
    )


#: Relation spans reported apart (s): local accuracy, mid-range drift, loops. Half-open [lo, hi).
SPANS_S: tuple[tuple[float, float], ...] = ((0.0, 2.0), (2.0, 30.0), (30.0, float("inf")))


def span_label(span: tuple[float, float]) -> str:
    """``"< 2 s"``, ``"2-30 s"``, ``">= 30 s"`` for the spans of :data:`SPANS_S`."""
    lo, hi = span
    if lo <= 0.0:
        return f"< {hi:g} s"
    if np.isinf(hi):
        return f">= {lo:g} s"
    return f"{lo:g}-{hi:g} s"


def errors_by_span(stats: RelationStats, relations: Relations,
                   spans: tuple[tuple[float, float], ...] = SPANS_S) -> dict[str, tuple[int, ErrorSummary]]:
    """Translational error (m) of the evaluated relations, split by the time they span.

    Returns
    -------
    dict of str to (int, ErrorSummary)
        Per :func:`span_label`: relations evaluated in that span, and their
        translational error summary (NaN when none).
    """
    span_s = np.abs(relations.stamp2_s - relations.stamp1_s)
    out = {}
    for lo, hi in spans:
        used = stats.matched & (span_s >= lo) & (span_s < hi)
        out[span_label((lo, hi))] = (int(np.count_nonzero(used)), _summary(stats.trans_err_m[used]))
    return out


def stamp_s(stamp_ns: int) -> float:
    """Seconds of a stamp in ns, correctly rounded.

    ``stamp_ns / 1e9`` rounds twice at Unix-epoch stamps (1e18 ns is beyond double
    precision); the Decimal route gives the float nearest to the exact value,
    which for a stamp imported from a log is the very float its text parses to,
    so relation stamps match with zero gap.
    """
    return float(Decimal(int(stamp_ns)).scaleb(-9))
