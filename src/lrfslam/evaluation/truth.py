"""Trajectory error against ground truth: the one error measure, offline and as a run goes.

An estimate lives in its own map frame (SLAM's first pose is its origin). It is put in the
truth's frame by the transform that makes their first common pose agree (:func:`anchor`), and
its positions are compared with the truth's at the same stamps: the absolute trajectory error
(:func:`ate_rmse`, RMSE of the position differences in metres, no other alignment). The
simulator's Monte Carlo, ``lrfslam export`` and ``lrfslam up``'s live line all report this.
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np

from lrfslam.algo.geometry import compose, inverse, wrap_angle

#: Truth held for an estimate that has not come yet, at most (over two minutes at 75 Hz): a
#: stalled or dead slam must not make ``up`` grow without bound.
MAX_PENDING_TRUTH = 10_000


def ate_rmse(true_poses: np.ndarray, est_poses: np.ndarray) -> float:
    """Absolute trajectory error of the positions, RMSE in metres, of poses (T, 3) paired row by row."""
    return float(np.sqrt(np.mean(np.sum((true_poses[:, :2] - est_poses[:, :2]) ** 2, axis=1))))


def anchor(true_pose: np.ndarray, est_pose: np.ndarray) -> np.ndarray:
    """The transform (3,) from an estimate's frame to the truth's that maps ``est_pose`` onto ``true_pose``."""
    return compose(true_pose, inverse(est_pose))


def matched_ate_rmse(stamps_ns: np.ndarray, poses: np.ndarray, ref_stamps_ns, ref_poses: np.ndarray) -> float | None:
    """:func:`ate_rmse` of ``poses`` (T, 3) against ``ref_poses`` (K, 3) at the stamps both have; None if none.

    Both must already be in one frame.
    """
    index = {int(s): i for i, s in enumerate(stamps_ns)}
    pairs = [(index[int(s)], k) for k, s in enumerate(ref_stamps_ns) if int(s) in index]
    if not pairs:
        return None
    i, k = np.array(pairs).T
    return ate_rmse(np.asarray(ref_poses)[k], np.asarray(poses)[i])


class RunningTruthError:
    """Each estimate matched to the truth of its stamp as both arrive, with running sums: memory
    stays bounded however long a run goes (truth waits for its estimate, at most
    :data:`MAX_PENDING_TRUTH` of it). Estimates come in stamp order; the first matched one anchors
    the frame (:func:`anchor`).

    Attributes
    ----------
    matched : int
        Estimates matched to a truth so far.
    final : tuple of float
        Position error (m) and heading error (rad) of the last matched estimate.
    pending : OrderedDict
        Truth (stamp ns -> pose (3,)) waiting for its estimate.
    """

    def __init__(self) -> None:
        self.pending: OrderedDict[int, np.ndarray] = OrderedDict()
        self.matched = 0
        self.final: tuple[float, float] = (0.0, 0.0)
        self._sum_sq_m2 = 0.0
        self._anchor: np.ndarray | None = None

    @property
    def ate_rmse_m(self) -> float:
        """:func:`ate_rmse` over every matched estimate (m); NaN before the first."""
        return float(np.sqrt(self._sum_sq_m2 / self.matched)) if self.matched else float("nan")

    def add_truth(self, stamp_ns: int, pose) -> None:
        self.pending[stamp_ns] = np.asarray(pose, dtype=float)
        while len(self.pending) > MAX_PENDING_TRUTH:
            self.pending.popitem(last=False)

    def add_estimate(self, stamp_ns: int, pose: np.ndarray) -> bool:
        """Match the estimate ``pose`` (3,) at ``stamp_ns``; False when no truth has its stamp."""
        # Estimates come in stamp order: older truth will never be matched (its estimate was lost).
        while self.pending and next(iter(self.pending)) < stamp_ns:
            self.pending.popitem(last=False)
        true = self.pending.pop(stamp_ns, None)
        if true is None:
            return False
        if self._anchor is None:
            self._anchor = anchor(true, pose)
        est = compose(self._anchor, pose)
        d = float(np.hypot(*(est[:2] - true[:2])))
        self.matched += 1
        self._sum_sq_m2 += d * d
        self.final = (d, abs(wrap_angle(est[2] - true[2])))
        return True
