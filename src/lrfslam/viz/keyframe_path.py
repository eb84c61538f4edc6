"""The mapper's past path for a display: the graph's keyframes and, thinned, the ones retired from it.

Each ``map/keyframes`` carries the graph's keyframes and, once, the keyframes retired from it
since the previous message (folded revisits). A display that drew only the graph's would lose
every later lap of a place; one that kept every retired keyframe would grow with the hours driven.
:class:`KeyframePath` keeps the retired ones where the message that retired them placed them, at
most ``max_retired`` of them (every other one dropped when full), and merges them with each
message's graph by stamp.
"""

from __future__ import annotations

import numpy as np

from lrfslam.algo.geometry import anchored_poses
from lrfslam.msgs import types as t


class KeyframePath:
    """Poses of the mapper's keyframes in stamp order, for a path (bounded: see the module notes).

    Parameters
    ----------
    max_retired : int
        Retired keyframes kept at most (≥ 2).
    """

    def __init__(self, max_retired: int) -> None:
        self.max_retired = max(2, int(max_retired))
        self._stamps = np.zeros(0, np.int64)
        self._poses = np.zeros((0, 3))

    def update(self, keyframes: t.MapKeyframes) -> tuple[np.ndarray, np.ndarray]:
        """Take one message; the stamps (ns, (P,)) and poses ((P, 3)) of the path up to its last keyframe."""
        if keyframes.retired_scan_stamp_ns.size:
            # (One anchored on a keyframe retired before, which is rare, is not drawn.)
            known = np.isin(keyframes.retired_anchor_stamp_ns, keyframes.scan_stamp_ns)
            placed = anchored_poses(keyframes.scan_stamp_ns, keyframes.map_pose, keyframes.retired_scan_stamp_ns[known],
                                   keyframes.retired_anchor_stamp_ns[known], keyframes.retired_offset[known])
            stamps = np.concatenate((self._stamps, keyframes.retired_scan_stamp_ns[known]))
            poses = np.vstack((self._poses, placed))
            order = np.argsort(stamps, kind="stable")
            self._stamps, self._poses = stamps[order], poses[order]
            while self._stamps.size > self.max_retired:
                self._stamps, self._poses = self._stamps[1::2], self._poses[1::2]
        stale = np.isin(self._stamps, keyframes.scan_stamp_ns)   # back in the graph (a restarted mapper)
        stamps = np.concatenate((keyframes.scan_stamp_ns, self._stamps[~stale]))
        order = np.argsort(stamps, kind="stable")
        return stamps[order], np.vstack((keyframes.map_pose, self._poses[~stale]))[order]
