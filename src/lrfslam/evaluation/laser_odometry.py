"""Scan matching alone (laser odometry) over a recording: the slam service's motion input, without the filter.

The slam service predicts with :class:`lrfslam.algo.scan_match.ScanTracker`'s
increments; this chains the same increments into a trajectory, from the same
inputs (raw scans, the odometry increment as the guess with the filter's
odometry covariance), so ``lrfslam eval relations --scan-matching`` can show what
the tracker achieves by itself and what the EKF's landmarks add on top.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lrfslam.algo.ekf_slam import EkfParams, EkfSlam
from lrfslam.algo.geometry import compose, polar_to_xy, relative
from lrfslam.algo.scan_match import ScanMatchParams, ScanTracker
from lrfslam.errors import DecodeError
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.runtime.recording import read_recording


def scan_matched_trajectory(path: str | Path, params: ScanMatchParams, odometry: EkfParams | None = None
                            ) -> tuple[np.ndarray, np.ndarray, int]:
    """Chain the tracker's increments over the recording's scans.

    Parameters
    ----------
    path : path-like
        Recording with ``scan`` and ``odom``; an odometry sample pairs with the scan of the
        same ``seq`` (as ``lrfslam import carmen`` and the simulator write them).
    params : ScanMatchParams
    odometry : EkfParams, optional
        Its odometry model gives the guess's covariance (the slam service's default if None).

    Returns
    -------
    stamps_ns : ndarray of int, shape (T,)
    poses : ndarray, shape (T, 3)
        ``(x_m, y_m, theta_rad)`` in the first scan's frame.
    undecodable : int
        Messages skipped because they did not decode.
    """
    model = EkfSlam(odometry or EkfParams())
    tracker = ScanTracker(params)
    scans: dict[int, tuple[int, np.ndarray]] = {}
    stamps, poses = [], []
    pose, last_odom = np.zeros(3), None
    undecodable = 0
    for rec in read_recording(path, [topics.SCAN.name, topics.ODOM.name]):
        topic = topics.by_name(rec.topic)
        try:
            value = topic.codec.decode(rec.data, rec.schema)
        except DecodeError:
            undecodable += 1
            continue
        if topic is topics.SCAN:
            ok = (value.status == t.BEAM_VALID) & np.isfinite(value.ranges_m)
            scans[value.seq] = (value.stamp_ns, polar_to_xy(value.ranges_m[ok], value.angles_rad[ok]))
            continue
        entry = scans.pop(value.seq, None)
        if entry is None:
            continue
        u = np.zeros(3) if last_odom is None else relative(last_odom, value.pose)
        last_odom = value.pose
        step = tracker.step(entry[1], u, model.odometry_cov(u))
        if poses:
            pose = compose(pose, step.increment)
        stamps.append(entry[0])
        poses.append(pose.copy())
    return np.array(stamps, dtype=np.int64), np.array(poses, dtype=float).reshape(-1, 3), undecodable
