"""The mapper's keyframes: what it keeps of each node of its pose graph, the keyframes it retired,
and every scan placed by them (:func:`place_scans`, also how a recording's reader places them).

A *keyframe* is a scan the mapper made a node of its pose graph (every ``keyframe_trans_m`` or
``keyframe_rot_rad`` of the local trajectory), published on ``map/keyframes``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lrfslam.algo.geometry import compose, relative

#: The points of a keyframe that has none (trimmed), one array for all of them (read-only).
NO_POINTS = np.zeros((0, 2))
NO_POINTS.flags.writeable = False


# Slots: a long run keeps thousands of these (~0.2 KB each without a __dict__).
@dataclass(frozen=True, eq=False, slots=True)
class Keyframe:
    """One node of the pose graph as the mapper keeps it (the graph holds its pose)."""

    local_pose: np.ndarray  # (3,) its pose on the local trajectory
    points_xy_m: np.ndarray  # (N, 2) its scan, robot frame, thinned
    travel_m: float  # local trajectory length from the first keyframe (m)
    local_edge: bool  # the odometry edge into it is the local motion (no jump)
    scan_index: int  # the scan that made it, in the order fed
    stamp_ns: int  # that scan's stamp
    ordinal: int  # keyframes made before it (its graph node, until keyframes are retired)
    revisit: bool = False  # it closed a loop into an older part of the map
    online_pose: np.ndarray | None = None  # (3,) the online estimator's pose of it, in its own frame


@dataclass(frozen=True, eq=False)
class RetiredKeyframes:
    """R keyframes folded into older ones and taken out of the graph (``fold_revisits``).

    Each one's pose is, ever after, its anchor's (the old keyframe its closure came from)
    composed with ``offset``: place it from the anchor's latest pose.

    Attributes
    ----------
    stamp_ns : ndarray of int, shape (R,)
        The scans that made them, ascending.
    local_pose : ndarray, shape (R, 3)
        Their poses on the local trajectory.
    local_edge : ndarray of bool, shape (R,)
        Whether the odometry edge into each was the local motion (as ``keyframe_local_edges``).
    anchor_stamp_ns : ndarray of int, shape (R,)
        The stamp of each one's anchor keyframe (older than it).
    offset : ndarray, shape (R, 3)
        Its pose in the anchor's frame ``(dx_m, dy_m, dtheta_rad)``.
    """

    stamp_ns: np.ndarray
    local_pose: np.ndarray
    local_edge: np.ndarray
    anchor_stamp_ns: np.ndarray
    offset: np.ndarray

    def __len__(self) -> int:
        return int(self.stamp_ns.size)


@dataclass(frozen=True, eq=False, slots=True)
class Retired:
    """One retired keyframe, as the mapper remembers it until it is taken (and, keeping scans, always)."""

    ordinal: int
    stamp_ns: int
    local_pose: np.ndarray  # (3,)
    local_edge: bool
    scan_index: int
    anchor_ordinal: int
    anchor_stamp_ns: int
    offset: np.ndarray  # (3,) its pose in the anchor's frame


def place_scans(scan_kf: np.ndarray, scan_rel: np.ndarray, kf_poses: np.ndarray, kf_local_poses: np.ndarray,
                kf_first_scan: np.ndarray, kf_local_edge: np.ndarray) -> np.ndarray:
    """Every scan placed by the (optimised) keyframes: the one way the mapper and a recording's reader do it.

    Parameters
    ----------
    scan_kf : ndarray of int, shape (T,)
        Keyframe of each scan (the newest one made at or before it), ascending.
    scan_rel : ndarray, shape (T, 3)
        Each scan's local pose relative to its keyframe's.
    kf_poses, kf_local_poses : ndarray, shape (K, 3)
        The keyframes' optimised poses and their local poses.
    kf_first_scan : ndarray of int, shape (K,)
        Index of the scan that made each keyframe.
    kf_local_edge : ndarray of bool, shape (K,)
        Whether the odometry edge into each keyframe is the local motion.

    Returns
    -------
    ndarray, shape (T, 3)
    """
    kf = np.asarray(scan_kf, dtype=np.int64)
    rel = np.asarray(scan_rel, dtype=float).reshape(-1, 3)
    poses = compose(kf_poses[kf].T, rel.T).T
    if kf.size == 0:
        return poses
    # A scan between two keyframes is placed from both, weighted by where it lies between
    # them, so the trajectory does not step at the next keyframe by what the optimisation
    # changed in between. Not across a jump: the local motion from the scan to the next
    # keyframe would hold it.
    nxt = np.minimum(kf + 1, len(kf_poses) - 1)
    blend = (nxt > kf) & np.asarray(kf_local_edge, dtype=bool)[nxt]
    if blend.any():
        idx = np.flatnonzero(blend)
        local_scan = compose(kf_local_poses[kf[idx]].T, rel[idx].T)
        from_next = compose(kf_poses[nxt[idx]].T, relative(kf_local_poses[nxt[idx]].T, local_scan)).T
        first = np.asarray(kf_first_scan, dtype=np.int64)
        w = (idx - first[kf[idx]]) / (first[nxt[idx]] - first[kf[idx]]).astype(float)
        poses[idx] = compose(poses[idx].T, relative(poses[idx].T, from_next.T) * w).T
    return poses
