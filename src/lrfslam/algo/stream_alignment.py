"""Lining up the slam inputs: features wait for the odometry and the scan of their instant.

The slam service receives three streams: odometry poses, raw scans (for scan
matching) and the features extracted from those scans, in whatever order the
bus or a recording delivers them. A :class:`StreamAligner` holds each set of
features until odometry up to its stamp and its own scan have arrived, and then
hands it out with the odometry pose interpolated at its stamp and the scan's
points, so the sequence handed out does not depend on how the streams
interleave. The one exception: features that arrive before the very first scan
are not held for it, so that inputs without scans (odometry and features only)
still flow. A scan newer than a set of features means theirs was lost (scans
arrive in stamp order); features are then handed out without their scan.

The holding is bounded: with more than ``max_wait`` sets of features waiting,
the oldest goes out with what has arrived, and scans never asked for are
dropped beyond ``2 max_wait + 2``.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np

from lrfslam.algo.geometry import wrap_angle
from lrfslam.errors import InputError

T = TypeVar("T")


def interpolate_pose(stamps_ns: np.ndarray, poses: np.ndarray, stamp_ns: int) -> np.ndarray:
    """Odometry pose at ``stamp_ns``, linear between the bracketing samples (heading via the short way).

    Parameters
    ----------
    stamps_ns : ndarray, shape (M,), int64
        Ascending sample stamps (ns).
    poses : ndarray, shape (M, 3)
        (x m, y m, heading rad) at those stamps.
    stamp_ns : int

    Returns
    -------
    ndarray, shape (3,)
        A new array; outside the samples' range, the nearest sample.
    """
    i = int(np.searchsorted(stamps_ns, stamp_ns))
    if i < len(stamps_ns) and stamps_ns[i] == stamp_ns:
        return poses[i].copy()
    if i == 0:
        return poses[0].copy()
    if i == len(stamps_ns):
        return poses[-1].copy()
    a, b = poses[i - 1], poses[i]
    w = (stamp_ns - stamps_ns[i - 1]) / (stamps_ns[i] - stamps_ns[i - 1])
    out = a + w * (b - a)
    out[2] = wrap_angle(a[2] + w * wrap_angle(b[2] - a[2]))
    return out


@dataclass(frozen=True)
class AlignmentParams:
    """How long features wait.

    Attributes
    ----------
    wait_for_odometry : bool
        Hold features until odometry at or after their stamp has arrived
        (false for a laser without odometry).
    wait_for_scans : bool
        Hold features until their scan has arrived (scan matching needs it).
    max_wait : int
        With more sets of features than this waiting, the oldest goes out anyway.
    scans_optional : bool
        Features that arrive before the very first scan are not held for it, so that
        inputs without scans still flow (the slam stage); false holds them too (the
        mapper, whose keyframes are scans).
    """

    wait_for_odometry: bool = True
    wait_for_scans: bool = True
    max_wait: int = 20
    scans_optional: bool = True


@dataclass(frozen=True)
class Aligned(Generic[T]):
    """One set of features with what arrived for it.

    Attributes
    ----------
    features : T
        As given to :meth:`StreamAligner.add_features`.
    odom_pose : ndarray, shape (3,), or None
        Odometry pose (x m, y m, heading rad) interpolated at the features' stamp;
        None if no odometry has arrived at all.
    scan_xy_m : ndarray, shape (N, 2), or None
        The points of the features' scan, robot frame (m); None if it did not arrive.
    """

    features: T
    odom_pose: np.ndarray | None
    scan_xy_m: np.ndarray | None


class StreamAligner(Generic[T]):
    """Odometry, scans and features in; features with their odometry pose and scan out, in order."""

    def __init__(self, params: AlignmentParams) -> None:
        self.params = params
        self._odom: deque[tuple[int, np.ndarray]] = deque()
        # Features waiting: (stamp ns, seq of their scan, features).
        self._pending: deque[tuple[int, int, T]] = deque()
        # Scans waiting for their features, by scan seq: (stamp ns, points (N, 2)).
        self._scans: dict[int, tuple[int, np.ndarray]] = {}
        self._newest_scan_ns: int | None = None

    @property
    def scans_held(self) -> int:
        return len(self._scans)

    def add_odometry(self, stamp_ns: int, pose: np.ndarray) -> bool:
        """Take an odometry pose (3,); False (and ignored) if not newer than the last one.

        Raises
        ------
        InputError
            If the pose is not finite.
        """
        if not np.all(np.isfinite(pose)):
            raise InputError(f"odometry at {stamp_ns} ns has a non-finite pose")
        if self._odom and stamp_ns <= self._odom[-1][0]:
            return False
        self._odom.append((stamp_ns, np.array(pose, dtype=float)))
        return True

    def add_scan(self, seq: int, stamp_ns: int, points_xy_m: np.ndarray) -> None:
        """Take the points (N, 2) of scan ``seq``, robot frame (m)."""
        self._scans[seq] = (stamp_ns, points_xy_m)
        # Bounded even if no features ever come: no more than the features that may wait.
        while len(self._scans) > 2 * self.params.max_wait + 2:
            del self._scans[min(self._scans, key=lambda q: (self._scans[q][0], q))]
        self._newest_scan_ns = stamp_ns if self._newest_scan_ns is None else max(self._newest_scan_ns, stamp_ns)

    def add_features(self, stamp_ns: int, scan_seq: int, features: T) -> None:
        """Take a set of features extracted from scan ``scan_seq`` taken at ``stamp_ns``."""
        self._pending.append((stamp_ns, scan_seq, features))

    def ready(self, final: bool = False) -> list[Aligned[T]]:
        """The features whose inputs are in (all of them if ``final``), oldest first."""
        out = []
        p = self.params
        while self._pending:
            stamp, scan_seq, _ = self._pending[0]
            give_up = final or len(self._pending) > p.max_wait
            odom_ready = not p.wait_for_odometry or (bool(self._odom) and self._odom[-1][0] >= stamp)
            newest = self._newest_scan_ns
            scan_ready = not p.wait_for_scans or scan_seq in self._scans \
                or (p.scans_optional if newest is None else newest > stamp)
            if not (give_up or (odom_ready and scan_ready)):
                break
            out.append(self._take())
        return out

    def _take(self) -> Aligned[T]:
        stamp, scan_seq, features = self._pending.popleft()
        odom_pose = None
        if self._odom:
            stamps = np.fromiter((s for s, _ in self._odom), dtype=np.int64, count=len(self._odom))
            odom_pose = interpolate_pose(stamps, np.array([q for _, q in self._odom]), stamp)
            # Keep one sample at or before this stamp for the next interpolation.
            while len(self._odom) > 1 and self._odom[1][0] <= stamp:
                self._odom.popleft()
        scan = self._scans.pop(scan_seq, None)
        # Scans older than these features will never be asked for.
        for seq in [q for q, (s, _) in self._scans.items() if s < stamp]:
            del self._scans[seq]
        return Aligned(features, odom_pose, None if scan is None else scan[1])
