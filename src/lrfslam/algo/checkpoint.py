"""The slam service's checkpoint: the filter and where the stream stood, as named arrays.

:func:`encode` gives a flat ``{name: array or scalar}`` dict (what ``np.savez``
stores) and :func:`decode` turns one back, migrating older filter formats as
:meth:`~lrfslam.algo.ekf_slam.EkfSlam.restore` does. Writing the file is the
service's business; a restarted service resumes with the next scan's motion
predicted by odometry (the scan tracker starts afresh).

Keys: the filter's snapshot (``format``, ``state_mean``, ...), ``service_seq``
(scans processed, so the next state's seq continues) and, once odometry has
been seen, ``last_odom_pose`` (3,). A checkpoint without ``service_seq`` (a bare
filter snapshot) resumes at scan 0.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from lrfslam.algo.ekf_slam import EkfParams, EkfSlam
from lrfslam.errors import InputError


@dataclass(frozen=True, eq=False)
class Checkpoint:
    """A decoded checkpoint.

    Attributes
    ----------
    ekf : EkfSlam
        The restored filter.
    scans : int
        Scans processed before it was written.
    last_odom_pose : ndarray, shape (3,), or None
        Odometry pose (x m, y m, heading rad) of the last processed scan.
    """

    ekf: EkfSlam
    scans: int
    last_odom_pose: np.ndarray | None


def encode(ekf: EkfSlam, scans: int, last_odom_pose: np.ndarray | None) -> dict:
    """The arrays of a checkpoint of ``ekf`` after ``scans`` scans."""
    snap = ekf.snapshot()
    snap["service_seq"] = scans
    if last_odom_pose is not None:
        snap["last_odom_pose"] = last_odom_pose
    return snap


def decode(params: EkfParams, arrays: Mapping) -> Checkpoint:
    """The checkpoint in ``arrays`` (as :func:`encode` made them, or loaded from a file).

    Raises
    ------
    InputError
        If the arrays are not a checkpoint of a format this version reads.
    """
    ekf = EkfSlam.restore(params, arrays)
    try:
        scans = int(arrays.get("service_seq", 0))
        pose = np.asarray(arrays["last_odom_pose"], dtype=float) if "last_odom_pose" in arrays else None
    except (TypeError, ValueError) as exc:
        raise InputError(f"checkpoint: {exc}") from None
    if pose is not None and (pose.shape != (3,) or not np.all(np.isfinite(pose))):
        raise InputError("checkpoint last_odom_pose must be 3 finite numbers")
    return Checkpoint(ekf, scans, pose)
