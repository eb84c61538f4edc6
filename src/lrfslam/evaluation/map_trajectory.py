"""The mapper's trajectories from a recording: as published at each scan, and final.

The *online* trajectory is ``map/pose``: each scan's pose as the mapper knew it then.
The *final* trajectory places every scan of ``map/pose`` by every keyframe: the last
``map/keyframes``'s, and those retired from the graph before it (each told once, by the
message after its retirement, and placed on the keyframe it was folded into; :class:`KeyframeHistory`).
A scan belongs to the newest keyframe made at or before it, and keeps its local pose
relative to that keyframe's — exactly how the mapper places its own scans. Recordings
made before ``map/pose`` carried the local pose place the ``slam/state`` poses instead
(the mapper's local trajectory was the slam poses then).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lrfslam.algo.geometry import anchored_poses, relative
from lrfslam.algo.loop_closure import place_scans
from lrfslam.errors import DecodeError, InputError
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.runtime.recording import read_recording


def final_poses(stamps_ns: np.ndarray, local_poses: np.ndarray, keyframes: t.MapKeyframes) -> np.ndarray:
    """Every scan's local pose corrected by the optimised keyframes, as the mapper places its scans.

    Parameters
    ----------
    stamps_ns : ndarray of int, shape (T,)
        Stamps of the scans the mapper was fed, ascending.
    local_poses : ndarray, shape (T, 3)
        Their poses on the mapper's local trajectory ``(x_m, y_m, theta_rad)``.
    keyframes : MapKeyframes
        Every keyframe of the run (K, their scans' stamps ascending): :meth:`KeyframeHistory.keyframes`.

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
        out[placed] = place_scans(kk, rel, keyframes.map_pose, keyframes.local_pose, first, keyframes.local_edge)
    return out


class KeyframeHistory:
    """Every keyframe a run's ``map/keyframes`` told of: the last message's, and the ones retired
    before it. Feed the messages in order to :meth:`add`; what is kept grows with the keyframes
    retired (nine numbers each), the messages' graphs are not kept."""

    def __init__(self) -> None:
        self._last: t.MapKeyframes | None = None
        self._retired: list[tuple[np.ndarray, ...]] = []

    def add(self, keyframes: t.MapKeyframes) -> None:
        self._last = keyframes
        if keyframes.retired_scan_stamp_ns.size:
            self._retired.append((keyframes.retired_scan_stamp_ns, keyframes.retired_local_pose,
                                  keyframes.retired_local_edge, keyframes.retired_anchor_stamp_ns,
                                  keyframes.retired_offset))

    def keyframes(self) -> t.MapKeyframes | None:
        """All of them in one message (stamps ascending, none retired), each retired one placed on its
        anchor as the last message placed the graph; None before the first message.

        Raises
        ------
        InputError
            A retired keyframe's anchor is unknown (the message that retired it, or its anchor, was lost).
        """
        last = self._last
        if last is None or not self._retired:
            return last
        stamps, local, edge, anchors, offsets = (np.concatenate(cols) for cols in zip(*self._retired, strict=True))
        stamps, index = np.unique(stamps, return_index=True)   # (a restarted mapper may tell one again)
        local, edge, anchors, offsets = local[index], edge[index], anchors[index], offsets[index]
        keep = ~np.isin(stamps, last.scan_stamp_ns)
        stamps, local, edge, anchors, offsets = stamps[keep], local[keep], edge[keep], anchors[keep], offsets[keep]
        try:
            placed = anchored_poses(last.scan_stamp_ns, last.map_pose, stamps, anchors, offsets)
        except InputError as exc:
            raise InputError(f"map/keyframes: {exc}") from None
        order = np.argsort(np.concatenate((last.scan_stamp_ns, stamps)), kind="stable")
        return t.MapKeyframes(stamp_ns=last.stamp_ns, seq=last.seq,
                              scan_stamp_ns=np.concatenate((last.scan_stamp_ns, stamps))[order],
                              local_pose=np.vstack((last.local_pose, local))[order],
                              map_pose=np.vstack((last.map_pose, placed))[order],
                              local_edge=np.concatenate((last.local_edge, edge))[order])


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
        self._keyframes = KeyframeHistory()

    def add(self, topic: str, value) -> None:
        if topic == topics.MAP_KEYFRAMES.name:
            self._keyframes.add(value)
        elif topic == topics.SLAM_STATE.name:
            self._local["slam"][0].append(value.stamp_ns)
            self._local["slam"][1].append(value.pose)
        elif topic == topics.MAP_POSE.name and value.local_pose is not None \
                and value.localization != t.NOT_LOCALIZED:   # (not placed on a saved map: no final pose)
            self._local["map"][0].append(value.stamp_ns)
            self._local["map"][1].append(value.local_pose)

    def keyframes(self) -> t.MapKeyframes | None:
        """Every keyframe of the run, the retired ones placed (:meth:`KeyframeHistory.keyframes`); None without any.

        Raises
        ------
        InputError
            A retired keyframe cannot be placed.
        """
        return self._keyframes.keyframes()

    def result(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Stamps (ns, (T,)) and final poses ((T, 3)); None without ``map/keyframes``.

        Raises
        ------
        InputError
            A retired keyframe cannot be placed (:meth:`KeyframeHistory.keyframes`).
        """
        stamps, poses = self._local["map"] if self._local["map"][0] else self._local["slam"]
        keyframes = self.keyframes()
        if keyframes is None or not stamps:
            return None
        order = np.argsort(np.array(stamps, dtype=np.int64), kind="stable")
        s = np.array(stamps, dtype=np.int64)[order]
        return s, final_poses(s, np.array(poses)[order], keyframes)


def final_trajectory(path: str | Path) -> tuple[np.ndarray, np.ndarray] | None:
    """Stamps (ns, (T,)) and final poses ((T, 3)) of a recording's scans; None without ``map/keyframes``."""
    builder = FinalTrajectoryBuilder()
    for rec in read_recording(path, list(FinalTrajectoryBuilder.TOPICS)):
        try:
            builder.add(rec.topic, topics.by_name(rec.topic).codec.decode(rec.data, rec.schema))
        except DecodeError:
            continue
    return builder.result()
