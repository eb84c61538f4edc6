"""The mapper's trajectories from a recording: as published at each scan, and final.

The *online* trajectory is ``map/pose``: each scan's pose as the mapper knew it then.
The *final* trajectory places every scan of ``map/pose`` by the last ``map/keyframes``:
a scan belongs to the newest keyframe made at or before it, and keeps its local pose
relative to that keyframe's — exactly how the mapper places its own scans. Recordings
made before ``map/pose`` carried the local pose place the ``slam/state`` poses instead
(the mapper's local trajectory was the slam poses then).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lrfslam.algo.geometry import relative
from lrfslam.algo.loop_closure import place_scans
from lrfslam.errors import DecodeError
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.runtime.recording import read_recording


def final_poses(stamps_ns: np.ndarray, local_poses: np.ndarray, keyframes: t.MapKeyframes,
                interpolate: bool = True) -> np.ndarray:
    """Every scan's local pose corrected by the optimised keyframes, as the mapper places its scans.

    Parameters
    ----------
    stamps_ns : ndarray of int, shape (T,)
        Stamps of the scans the mapper was fed, ascending.
    local_poses : ndarray, shape (T, 3)
        Their poses on the mapper's local trajectory ``(x_m, y_m, theta_rad)``.
    keyframes : MapKeyframes
        The last one of the recording (K keyframes, their scans' stamps ascending).
    interpolate : bool
        As the mapper's ``loop_closure.interpolate``.

    Returns
    -------
    ndarray, shape (T, 3)
        Final poses; scans before the first keyframe keep their local pose.
    """
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    local_poses = np.asarray(local_poses, dtype=float).reshape(-1, 3)
    out = local_poses.copy()
    k = np.searchsorted(keyframes.scan_stamp_ns, stamps_ns, side="right") - 1
    placed = np.flatnonzero(k >= 0)
    if placed.size:
        kk = k[placed]
        rel = np.asarray(relative(keyframes.local_pose[kk].T, local_poses[placed].T)).T
        first = np.searchsorted(stamps_ns[placed], keyframes.scan_stamp_ns)
        out[placed] = place_scans(kk, rel, keyframes.map_pose, keyframes.local_pose, first, keyframes.local_edge,
                                  interpolate)
    return out


class FinalTrajectoryBuilder:
    """Collects what the final trajectory needs from a recording's decoded messages, in log order.

    Feed every ``slam/state``, ``map/pose`` and ``map/keyframes`` to :meth:`add` (others are
    ignored), then ask :meth:`result`; a reader that decodes these topics anyway (``export``)
    needs no second pass over the recording.
    """

    #: The topics :meth:`add` uses.
    TOPICS = (topics.SLAM_STATE.name, topics.MAP_POSE.name, topics.MAP_KEYFRAMES.name)

    def __init__(self) -> None:
        self._local: dict[str, tuple[list[int], list[np.ndarray]]] = {"map": ([], []), "slam": ([], [])}
        self._last: t.MapKeyframes | None = None

    def add(self, topic: str, value) -> None:
        if topic == topics.MAP_KEYFRAMES.name:
            self._last = value
        elif topic == topics.SLAM_STATE.name:
            self._local["slam"][0].append(value.stamp_ns)
            self._local["slam"][1].append(value.pose)
        elif topic == topics.MAP_POSE.name and value.local_pose is not None:
            self._local["map"][0].append(value.stamp_ns)
            self._local["map"][1].append(value.local_pose)

    def result(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Stamps (ns, (T,)) and final poses ((T, 3)); None without ``map/keyframes``."""
        stamps, poses = self._local["map"] if self._local["map"][0] else self._local["slam"]
        if self._last is None or not stamps:
            return None
        order = np.argsort(np.array(stamps, dtype=np.int64), kind="stable")
        s = np.array(stamps, dtype=np.int64)[order]
        return s, final_poses(s, np.array(poses)[order], self._last)


def final_trajectory(path: str | Path) -> tuple[np.ndarray, np.ndarray] | None:
    """Stamps (ns, (T,)) and final poses ((T, 3)) of a recording's scans; None without ``map/keyframes``."""
    builder = FinalTrajectoryBuilder()
    for rec in read_recording(path, list(FinalTrajectoryBuilder.TOPICS)):
        try:
            builder.add(rec.topic, topics.by_name(rec.topic).codec.decode(rec.data, rec.schema))
        except DecodeError:
            continue
    return builder.result()
