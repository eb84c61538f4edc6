"""Points where another scan saw through: things that moved, such as people.

A static world never puts a return where an earlier beam passed on to a farther
one. A person walking towards the robot does, in every scan: matched as if it
stood still, it drags the estimate along a corridor at walking speed (the
simulator's ``large_building_people``; docs/slam.md, "On the
simulator"). :class:`FreeSpace` keeps what one scan saw as empty, the nearest
return in each bearing bin, and :meth:`FreeSpace.contains` names the points of
another scan that lie well inside it.

A bin between the scan's first and last return that holds none saw nothing up
to ``empty_m`` (a beam without an echo: a corridor longer than the laser's
reach, so the beams beside a person coming down it still say the space was
empty); bins outside the scan's field of view are unknown. A point must be
nearer than the ranges of its bin and its neighbours by a margin that grows
with range, so a pose error of a few centimetres and grazing walls, whose range
changes fast with bearing, do not condemn it; so must every bin within a
lateral margin across the beam, so a point beside an edge is not condemned either. Something
moving away from the scanner hides behind its old place and is not found from
that side; the tracker checks both ways (:class:`~lrfslam.algo.scan_match.ScanTracker`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from lrfslam.algo import free_space_kernel as kernel
from lrfslam.errors import InputError

#: Most bins on each side a point's range is compared with (a near point's lateral margin).
MAX_SPREAD_BINS = 10


@dataclass(frozen=True, eq=False)
class FreeSpace:
    """The space one scan saw as empty.

    Attributes
    ----------
    pose : ndarray, shape (3,)
        The scan's pose ``(x m, y m, heading rad)`` in the frame :meth:`contains` is asked in.
    nearest_m : ndarray, shape (B,)
        Range seen empty in each bearing bin of the scan's frame, m: the nearest return's, else
        ``empty_m`` inside the field of view; NaN outside it (unknown).
    bin_rad : float
        Width of a bearing bin, rad; bin ``k`` starts at ``-pi + k * bin_rad``.
    """

    pose: np.ndarray
    nearest_m: np.ndarray
    bin_rad: float

    @classmethod
    def of_scan(cls, pose, points_xy_m, bin_rad: float, empty_m: float) -> FreeSpace:
        """What a scan at ``pose`` (3,) whose returns are ``points_xy_m`` (N, 2; its own frame, m) saw.

        Non-finite rows are ignored; ``bin_rad`` > 0 (about the beam spacing or wider); a bin
        without a return between the first and the last return's bearings was empty to
        ``empty_m`` (m, >= 0; 0: unknown).
        """
        if not bin_rad > 0:
            raise InputError(f"bin_rad must be > 0, got {bin_rad}")
        pts = np.asarray(points_xy_m, dtype=float).reshape(-1, 2)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        n_bins = int(np.ceil(2.0 * np.pi / bin_rad))
        nearest = np.full(n_bins, np.inf)
        bins = _bins(pts[:, 0], pts[:, 1], bin_rad, n_bins)
        np.minimum.at(nearest, bins, np.hypot(pts[:, 0], pts[:, 1]))
        silent = np.isinf(nearest)
        nearest[silent] = np.nan
        if bins.size and empty_m > 0:
            inside = np.zeros(n_bins, dtype=bool)
            inside[bins.min(): bins.max() + 1] = True
            nearest[silent & inside] = empty_m
        return cls(np.asarray(pose, dtype=float).copy(), nearest, float(bin_rad))

    def contains(self, points_xy_m, margin_m: float, margin_per_m: float, lateral_m: float,
                 bearing_rad: float) -> np.ndarray:
        """Which points (N, 2; the common frame, m) lie inside the seen free space, bool (N,).

        A point at range ``r`` is inside when every bin within ``lateral_m / r +
        bearing_rad`` of its bearing (at least one bin) and one bin more on each side
        (at most :data:`MAX_SPREAD_BINS`) saw empty space beyond ``r + margin_m +
        margin_per_m * r``. The lateral margin keeps a point near an edge, or on a wall
        seen edge-on or at a grazing angle (whose range changes by metres a degree),
        from being condemned by a few centimetres or a degree or two of pose error.
        """
        return seen_through((self,), points_xy_m, margin_m, margin_per_m, lateral_m, bearing_rad)


def seen_through(spaces: Sequence[FreeSpace], points_xy_m, margin_m: float, margin_per_m: float,
                 lateral_m: float, bearing_rad: float) -> np.ndarray:
    """Which points (N, 2; the common frame, m) any of ``spaces`` contains, bool (N,).

    The same as OR-ing :meth:`FreeSpace.contains` over ``spaces`` (K of them, one bin width), in
    one compiled pass (:mod:`lrfslam.algo.free_space_kernel`): the tracker asks its ten last
    reference scans about every scan.
    """
    pts = np.asarray(points_xy_m, dtype=float).reshape(-1, 2)
    if not spaces:
        return np.zeros(pts.shape[0], dtype=bool)
    bin_rad = spaces[0].bin_rad
    if any(space.bin_rad != bin_rad for space in spaces):
        raise InputError("free spaces of different bin widths cannot be asked together")
    nearest = np.stack([space.nearest_m for space in spaces])  # (K, B)
    origins = np.stack([space.pose[:2] for space in spaces])  # (K, 2)
    cos_sin = np.array([(math.cos(space.pose[2]), math.sin(space.pose[2])) for space in spaces])  # (K, 2)
    return kernel.seen_through(nearest, origins, cos_sin, pts, bin_rad, margin_m, margin_per_m, lateral_m,
                               bearing_rad, MAX_SPREAD_BINS)


def _bins(x: np.ndarray, y: np.ndarray, bin_rad: float, n_bins: int) -> np.ndarray:
    """Bearing bin of each point ``(x, y)`` (arrays of one shape, m) seen from its frame's origin."""
    return np.minimum(((np.arctan2(y, x) + np.pi) / bin_rad).astype(np.int64), n_bins - 1)
