"""``lrfslam eval closures RECORDING RELATIONS``: every loop closure the mapper tried, judged by the relations.

The pipeline's stages run over a recording (a log imported with ``lrfslam import carmen``) in
this process, with the mapper observed (:attr:`LoopClosingMapper.observer`): each closure it
verified or dropped is kept with its verdict. Then each one is judged where the relations
cover it: a relation whose two stamps lie within :data:`BRIDGE_S` of the closure's old and new
keyframe scans (either way round) gives the true pose of the new keyframe in the old one's
frame, bridged from the relation's scans to the keyframes' along the EKF's published
trajectory (at most :data:`BRIDGE_S` each side, where the EKF drifts by millimetres).

Against that truth:

- a closure the mapper **accepted** is a *false accept* when its error's χ² under its own
  covariance exceeds the 99 % quantile for 3 degrees of freedom (the issue's definition: the
  measurement claims to be better than it is by more than its own gate allows);
- the truth is not exact either: a relation carries its own error, and each bridge the EKF's
  drift over it. Both are estimated from the relations under :data:`SHORT_SPAN_S`
  (:func:`reference_noise`) and carried to the closure's frame; a false accept *beyond the
  reference's error* is one whose χ² under both covariances still exceeds the quantile;
- any attempt is *right* when its pose lies within :data:`RIGHT_M` and :data:`RIGHT_RAD` of
  the truth: precision is the share of covered accepted closures that are right, recall the
  share of covered right attempts that were accepted (an attempt the verification dropped
  although it was right is a missed closure).
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, replace

import numpy as np
from scipy.stats import chi2

from lrfslam.algo.geometry import (
    compose_with_covariance,
    inverse,
    relative,
    rotate_covariance,
    wrap_angle,
)
from lrfslam.algo.loop_closure import VERDICTS, ClosureAttempt
from lrfslam.evaluation.relations import Relations, match_stamps, stamp_s
from lrfslam.runtime import chain

#: Farthest (s) a relation's scan may lie from a closure's keyframe scan to judge it.
BRIDGE_S = 1.0

#: An attempt within this of the truth (m, rad) is right.
RIGHT_M = 0.2
RIGHT_RAD = math.radians(2.0)

#: χ² (3 dof) beyond which an accepted closure contradicts its own covariance.
CHI2_99 = float(chi2.ppf(0.99, 3))

#: Relations at most this long (s) estimate the reference's own error (:func:`reference_noise`).
SHORT_SPAN_S = 2.0


@dataclass(frozen=True)
class Judged:
    """One closure attempt and, where the relations cover it, its error against them."""

    attempt: ClosureAttempt
    error: np.ndarray | None   # (3,) the measured pose in the true one's frame (m, m, rad); None: not covered
    chi2: float | None         # error's χ² under the attempt's covariance (accepted and gated ones)
    chi2_reference: float | None = None   # ...under it plus the truth's own error's (= chi2 for exact truth)

    @property
    def covered(self) -> bool:
        return self.error is not None

    @property
    def right(self) -> bool:
        return bool(self.covered and math.hypot(self.error[0], self.error[1]) <= RIGHT_M
                    and abs(self.error[2]) <= RIGHT_RAD)

    @property
    def false_accept(self) -> bool:
        return self.attempt.verdict == "accepted" and self.chi2 is not None and self.chi2 > CHI2_99

    @property
    def false_accept_beyond_reference(self) -> bool:
        return self.attempt.verdict == "accepted" and self.chi2_reference is not None \
            and self.chi2_reference > CHI2_99


@dataclass(frozen=True)
class ReferenceNoise:
    """The error of the truth an attempt is judged by, as variances (3,) of (x m, y m, θ rad):
    ``relation`` a relation's own, ``per_s`` the EKF's bridge's per second bridged."""

    relation: np.ndarray
    per_s: np.ndarray


def reference_noise(relations: Relations, ekf_stamps_s: np.ndarray, ekf_poses: np.ndarray,
                    max_gap_s: float) -> ReferenceNoise:
    """Estimated from the relations of at most :data:`SHORT_SPAN_S`: the EKF's error against each,
    squared, per component, fitted by least squares as ``relation + span_s × per_s`` (each ≥ 0).

    Over spans this short the EKF has hardly drifted: what its error keeps at zero span is the
    relations' own error (and the EKF's per-scan noise), what grows with the span the EKF's
    drift. Zero where no relation is short enough.
    """
    ia, _ = match_stamps(ekf_stamps_s, relations.stamp1_s, max_gap_s)
    ib, _ = match_stamps(ekf_stamps_s, relations.stamp2_s, max_gap_s)
    span = np.abs(relations.stamp2_s - relations.stamp1_s)
    short = np.flatnonzero((ia >= 0) & (ib >= 0) & (span <= SHORT_SPAN_S))
    if short.size < 2:
        return ReferenceNoise(np.zeros(3), np.zeros(3))
    err = np.array([relative(relations.delta[i], relative(ekf_poses[ia[i]], ekf_poses[ib[i]])) for i in short])
    err[:, 2] = wrap_angle(err[:, 2])
    design = np.column_stack((np.ones(short.size), span[short]))
    relation, per_s = np.zeros(3), np.zeros(3)
    for c in range(3):
        (a, b), *_ = np.linalg.lstsq(design, err[:, c] ** 2, rcond=None)
        if b < 0.0:   # no growth with the span within these: all of it the relation's
            a, b = float(np.mean(err[:, c] ** 2)), 0.0
        relation[c], per_s[c] = max(a, 0.0), b
    return ReferenceNoise(relation, per_s)


def observed_stages(stages: Iterable[chain.Stage], journal: list[ClosureAttempt]) -> list[chain.Stage]:
    """``stages`` with the mapper's closure attempts appended to ``journal`` as they happen."""
    def watched(build):
        def build_and_observe(cfg, ctx):
            step = build(cfg, ctx)
            step.mapper.observer = journal.append
            return step
        return build_and_observe
    return [replace(s, spec=replace(s.spec, build=watched(s.spec.build))) if s.spec.name == "mapper" else s
            for s in stages]


def judge(attempts: Iterable[ClosureAttempt], relations: Relations, ekf_stamps_s: np.ndarray,
          ekf_poses: np.ndarray, max_gap_s: float, noise: ReferenceNoise | None = None) -> list[Judged]:
    """Each attempt with its error against the relations where they cover it.

    Parameters
    ----------
    attempts : iterable of ClosureAttempt
    relations : Relations
    ekf_stamps_s, ekf_poses : ndarray, shapes (T,) and (T, 3)
        The EKF's published trajectory (s; m, m, rad), which bridges a relation's scans to the
        keyframes' scans.
    max_gap_s : float
        Stamp-matching tolerance (s) between a relation's or a keyframe's stamp and the EKF's.
    noise : ReferenceNoise, optional
        The truth's own error; :func:`reference_noise` of these relations when not given.
    """
    rel_a, _ = match_stamps(ekf_stamps_s, relations.stamp1_s, max_gap_s)
    rel_b, _ = match_stamps(ekf_stamps_s, relations.stamp2_s, max_gap_s)
    usable = (rel_a >= 0) & (rel_b >= 0)
    t1, t2 = relations.stamp1_s[usable], relations.stamp2_s[usable]
    ia, ib, delta = rel_a[usable], rel_b[usable], relations.delta[usable]
    if noise is None:
        noise = reference_noise(relations, ekf_stamps_s, ekf_poses, max_gap_s)
    attempts = list(attempts)
    old_all = np.array([stamp_s(a.old_stamp_ns) for a in attempts])
    new_all = np.array([stamp_s(a.new_stamp_ns) for a in attempts])
    at_old, _ = match_stamps(ekf_stamps_s, old_all, max_gap_s)
    at_new, _ = match_stamps(ekf_stamps_s, new_all, max_gap_s)
    judged = []
    for att, old_s, new_s, io, inew in zip(attempts, old_all, new_all, at_old, at_new, strict=True):
        truth, truth_cov = None, None
        if io >= 0 and inew >= 0:
            forward = np.abs(t1 - old_s) + np.abs(t2 - new_s)
            backward = np.abs(t2 - old_s) + np.abs(t1 - new_s)
            near_f = (np.abs(t1 - old_s) <= BRIDGE_S) & (np.abs(t2 - new_s) <= BRIDGE_S)
            near_b = (np.abs(t2 - old_s) <= BRIDGE_S) & (np.abs(t1 - new_s) <= BRIDGE_S)
            cost = np.minimum(np.where(near_f, forward, np.inf), np.where(near_b, backward, np.inf))
            best = int(np.argmin(cost)) if cost.size else -1
            if best >= 0 and np.isfinite(cost[best]):
                if near_f[best] and forward[best] <= backward[best]:
                    a, b, between = ia[best], ib[best], delta[best]        # a near old, b near new
                else:
                    a, b, between = ib[best], ia[best], inverse(delta[best])
                to_a = relative(ekf_poses[io], ekf_poses[a])       # old keyframe -> relation's first scan
                from_b = relative(ekf_poses[b], ekf_poses[inew])   # relation's second scan -> new keyframe
                bridged_a = abs(ekf_stamps_s[a] - ekf_stamps_s[io])
                bridged_b = abs(ekf_stamps_s[inew] - ekf_stamps_s[b])
                head, head_cov = compose_with_covariance(to_a, np.diag(noise.per_s * bridged_a),
                                                         between, np.diag(noise.relation))
                truth, truth_cov = compose_with_covariance(head, head_cov, from_b, np.diag(noise.per_s * bridged_b))
        judged.append(_against(att, truth, truth_cov))
    return judged


def judge_by_truth(attempts: Iterable[ClosureAttempt], stamps_ns: np.ndarray, true_poses: np.ndarray) -> list[Judged]:
    """Each attempt with its error against the true poses of its keyframes' scans (the simulator's).

    Parameters
    ----------
    attempts : iterable of ClosureAttempt
    stamps_ns : ndarray of int64, shape (T,)
        Every scan's stamp (ns), increasing.
    true_poses : ndarray, shape (T, 3)
        The robot's true pose at each (m, m, rad). An attempt whose stamps are not among
        ``stamps_ns`` is left unjudged.
    """
    judged = []
    for att in attempts:
        i, j = np.searchsorted(stamps_ns, [att.old_stamp_ns, att.new_stamp_ns])
        known = i < len(stamps_ns) and j < len(stamps_ns) \
            and stamps_ns[i] == att.old_stamp_ns and stamps_ns[j] == att.new_stamp_ns
        judged.append(_against(att, relative(true_poses[i], true_poses[j]) if known else None))
    return judged


def _against(att: ClosureAttempt, truth: np.ndarray | None, truth_cov: np.ndarray | None = None) -> Judged:
    """``att`` judged by ``truth``, the new keyframe's true pose in the old one's frame (None:
    unknown), with ``truth_cov`` (3, 3) its own error's covariance in that frame (None: exact)."""
    if truth is None:
        return Judged(att, None, None)
    error = relative(truth, att.pose)
    error[2] = math.remainder(error[2], 2 * math.pi)
    if att.cov is None:
        return Judged(att, error, None)
    # The error is in the truth's axes; the closure's covariance (and the truth's) in the old
    # keyframe's: turned into the error's.
    cov = rotate_covariance(att.cov, -truth[2])
    chi = float(error @ np.linalg.solve(cov, error))
    if truth_cov is None:
        return Judged(att, error, chi, chi)
    return Judged(att, error, chi, float(error @ np.linalg.solve(cov + rotate_covariance(truth_cov, -truth[2]), error)))


def report(judged: list[Judged]) -> str:
    """Counts per verdict (covered, right, errors), false accepts, precision and recall; then every
    covered accepted closure and every false accept."""
    counts = summary_counts(judged)
    lines = [f"{'verdict':14s} {'tried':>6s} {'covered':>8s} {'right':>6s} {'median err m':>13s} {'max err m':>10s}"]
    for verdict in VERDICTS:
        errs = [math.hypot(j.error[0], j.error[1]) for j in judged if j.attempt.verdict == verdict and j.covered]
        lines.append(f"{verdict:14s} {counts[verdict]:6d} {counts[verdict + '.covered']:8d} "
                     f"{counts[verdict + '.right']:6d} "
                     + (f"{np.median(errs):13.3f} {max(errs):10.3f}" if errs else f"{'-':>13s} {'-':>10s}"))
    accepted = [j for j in judged if j.attempt.verdict == "accepted" and j.covered]
    precision, recall = precision_recall(counts)
    lines.append(f"false accepts (accepted, error's chi2 over its own covariance > {CHI2_99:.2f}): "
                 f"{counts['false_accepts']} of {len(accepted)} covered accepted closures; "
                 f"{counts['false_accepts_beyond_reference']} beyond the relations' and the bridges' own error too")
    lines.append(f"precision {precision:.3f} (covered accepted closures within {RIGHT_M} m and "
                 f"{math.degrees(RIGHT_RAD):.0f} deg of the truth), recall {recall:.3f} (of the covered "
                 "attempts that were right, the share accepted)")
    if accepted:
        lines.append("accepted closures the relations cover (stamps s; error x y m, theta deg; chi2):")
        for j in accepted:
            att = j.attempt
            flag = "  FALSE ACCEPT" if j.false_accept else ""
            flag += " (beyond the reference's error)" if j.false_accept_beyond_reference else ""
            lines.append(f"  {stamp_s(att.old_stamp_ns):.3f} -> {stamp_s(att.new_stamp_ns):.3f}  "
                         f"{j.error[0]:+.3f} {j.error[1]:+.3f} {math.degrees(j.error[2]):+.2f}  "
                         f"{j.chi2:.1f}{flag}")
    return "\n".join(lines)


def precision_recall(counts: Counter) -> tuple[float, float]:
    """Of :func:`summary_counts`: the share of covered accepted closures that are right, and the
    share of covered right attempts that were accepted (nan where there are none)."""
    right = sum(counts[v + ".right"] for v in VERDICTS)
    covered_accepted = counts["accepted.covered"]
    return (counts["accepted.right"] / covered_accepted if covered_accepted else float("nan"),
            counts["accepted.right"] / right if right else float("nan"))


def summary_counts(judged: list[Judged]) -> Counter:
    """``<verdict>``, ``<verdict>.covered``, ``<verdict>.right``, ``false_accepts`` and
    ``false_accepts_beyond_reference`` counts."""
    counts: Counter = Counter()
    for j in judged:
        v = j.attempt.verdict
        counts[v] += 1
        counts[f"{v}.covered"] += j.covered
        counts[f"{v}.right"] += j.right
        counts["false_accepts"] += j.false_accept
        counts["false_accepts_beyond_reference"] += j.false_accept_beyond_reference
    return counts
