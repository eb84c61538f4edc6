"""Dominant wall direction of a scan, modulo 90°: a heading measurement for SLAM.

Not in the paper. The paper's angle histogram (``histogram.py``) rests on the
observation that the walls of a building share a few directions, and with the
90° fold one direction; the peak of that histogram is the Hinkel–Knieriemen
angle-histogram idea, which measures the robot's heading against the building.
Here the peak is measured precisely, with an error estimate, so the filter can
use it (``EkfSlam.observe_wall_direction``).

Method, on the denoised points of one scan in scan order:

1. Split them into runs at gaps wider than ``MAX_GAP_M``, and each run into
   straight pieces by iterative end-point fit (split where a point lies more than
   ``SPLIT_TOL_M`` from the chord).
2. Drop ``TRIM_POINTS`` at both ends of each piece (the points next to a corner
   or a mixed pixel belong to neither wall) and fit a total-least-squares line to
   the rest. Keep lines of at least ``MIN_POINTS`` points and ``MIN_LENGTH_M``.
   A line's direction variance is ``σ_r² / Σ t²``, with ``σ_r`` its residual
   standard deviation (floored at ``POINT_SIGMA_FLOOR_M``) and ``t`` the points'
   centred positions along the line.
3. Consensus: the line whose direction, modulo 90°, agrees within
   ``ALIGN_TOL_RAD`` with the largest total length of lines fixes the dominant
   direction; the agreeing lines are its support. A scan whose support is less
   than ``min_support_frac`` of the length of all lines, or shorter than
   ``min_support_length_m``, has no dominant direction (clutter, a single short
   wall).
4. The direction is the inverse-variance weighted mean of the supporting lines
   (modulo 90°). Its variance ``1 / Σ wᵢ`` is multiplied by the Birge ratio
   ``χ² / (m − 1)`` when the m lines scatter more than their own errors say
   (walls that are not quite square).

Angles are in the sensor frame; a direction ``α`` modulo 90° is reported in
[−π/4, π/4). For a robot at heading ``θ`` in a building whose walls run at
``ψ`` (mod 90°) in the world, ``α = wrap_quarter(ψ − θ)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lrfslam.algo.checks import require_finite
from lrfslam.errors import ConfigError, InputError

QUARTER_TURN_RAD = 0.5 * np.pi
#: Successive points farther apart than this (m) start a new run.
MAX_GAP_M = 0.3
#: A run is split where a point lies farther than this (m) from the chord of its piece (about 3–4
#: times the scanner's range σ).
SPLIT_TOL_M = 0.04
#: Points dropped at each end of a piece before the line fit.
TRIM_POINTS = 1
#: Points a line needs after trimming (≥ 3).
MIN_POINTS = 8
#: Length a line needs, end to end after trimming (m).
MIN_LENGTH_M = 0.5
#: Floor on a line's residual standard deviation (m), so a lucky fit of few points does not claim a
#: tiny error.
POINT_SIGMA_FLOOR_M = 0.003
#: Lines whose directions agree within this modulo 90° (rad) support one direction.
ALIGN_TOL_RAD = 0.06


def wrap_quarter(a):
    """Wrap angle(s) modulo 90° to [−π/4, π/4) (rad); same shape as ``a``."""
    wrapped = (np.asarray(a, dtype=float) + 0.25 * np.pi) % QUARTER_TURN_RAD - 0.25 * np.pi
    return wrapped if np.ndim(a) else float(wrapped)


@dataclass(frozen=True)
class WallDirectionParams:
    """Settings of :func:`wall_direction` (the rest are this module's constants); see the module
    docstring for the method.

    Attributes
    ----------
    min_support_frac : float
        Smallest share of the total line length that must support the dominant
        direction, in (0, 1].
    min_support_length_m : float
        Smallest total length of the supporting lines.
    """

    min_support_frac: float = 0.6
    min_support_length_m: float = 1.0

    def __post_init__(self) -> None:
        require_finite(self, ("min_support_length_m",), positive=True)
        if not 0 < self.min_support_frac <= 1:
            raise ConfigError(f"min_support_frac must be in (0, 1], got {self.min_support_frac!r}")


@dataclass(frozen=True)
class WallDirection:
    """The dominant wall direction of one scan.

    Attributes
    ----------
    direction_rad : float
        Direction of the walls in the sensor frame modulo 90°, in [−π/4, π/4).
    sigma_rad : float
        Its standard deviation (rad).
    n_lines : int
        Lines that support it.
    support_frac : float
        Their share of the total length of all fitted lines.
    """

    direction_rad: float
    sigma_rad: float
    n_lines: int
    support_frac: float


def _pieces(points: np.ndarray, tol_m: float) -> list[tuple[int, int]]:
    """Iterative end-point fit of one run (M, 2): ``[start, stop)`` ranges of straight pieces."""
    out: list[tuple[int, int]] = []
    stack = [(0, points.shape[0])]
    while stack:
        a, b = stack.pop()
        if b - a <= 2:
            out.append((a, b))
            continue
        chord = points[b - 1] - points[a]
        norm = float(np.hypot(chord[0], chord[1]))
        rel = points[a:b] - points[a]
        if norm > 0:
            dist = np.abs(rel[:, 0] * chord[1] - rel[:, 1] * chord[0]) / norm
        else:
            dist = np.hypot(rel[:, 0], rel[:, 1])
        k = int(np.argmax(dist))
        if dist[k] <= tol_m:
            out.append((a, b))
        else:
            # The farthest point is where the direction changes: it ends the first
            # piece and starts the second (iterative end-point fit).
            stack += [(a, a + k + 1), (a + k, b)]
    return out


def _fit_lines(points: np.ndarray, params: WallDirectionParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lines of straight pieces: directions (J,) mod π, direction variances (J,) rad², lengths (J,) m."""
    steps = np.hypot(*np.diff(points, axis=0).T)
    cuts = np.concatenate(([0], np.flatnonzero(steps > MAX_GAP_M) + 1, [points.shape[0]]))
    trim = TRIM_POINTS
    spans = [
        (r0 + a + trim, r0 + b - trim)
        for r0, r1 in zip(cuts[:-1].tolist(), cuts[1:].tolist(), strict=True)
        if r1 - r0 >= MIN_POINTS + 2 * trim
        for a, b in _pieces(points[r0:r1], SPLIT_TOL_M)
    ]
    spans = np.array([s for s in spans if s[1] - s[0] >= MIN_POINTS], dtype=np.intp).reshape(-1, 2)
    lo, hi = spans[:, 0], spans[:, 1]
    # Scatter matrices of all pieces at once from cumulative sums (points relative
    # to the scan's first point, so the sums lose no precision).
    rel = points - points[0]
    x, y = rel[:, 0], rel[:, 1]
    cums = np.zeros((5, points.shape[0] + 1))
    np.cumsum(np.stack((x, y, x * x, y * y, x * y)), axis=1, out=cums[:, 1:])
    n = (hi - lo).astype(float)
    sx, sy, sxx, syy, sxy = cums[:, hi] - cums[:, lo]
    cxx, cyy, cxy = sxx - sx * sx / n, syy - sy * sy / n, sxy - sx * sy / n
    # TLS in closed form: the line runs along the scatter's major axis; the minor
    # eigenvalue is the residual sum of squares, the major one Σ t² along the line.
    direction = 0.5 * np.arctan2(2.0 * cxy, cxx - cyy)
    half_trace, radius = 0.5 * (cxx + cyy), np.hypot(0.5 * (cxx - cyy), cxy)
    along_ss, resid_ss = half_trace + radius, np.maximum(half_trace - radius, 0.0)
    chord = points[hi - 1] - points[lo]
    length = np.abs(chord[:, 0] * np.cos(direction) + chord[:, 1] * np.sin(direction))
    resid_var = np.maximum(resid_ss / (n - 2.0), POINT_SIGMA_FLOOR_M**2)
    ok = length >= MIN_LENGTH_M
    return direction[ok], resid_var[ok] / along_ss[ok], length[ok]


def wall_direction(points_xy: np.ndarray, params: WallDirectionParams) -> WallDirection | None:
    """Dominant wall direction modulo 90° of one scan's denoised points.

    Parameters
    ----------
    points_xy : ndarray, shape (K, 2)
        Points in the sensor frame (m), in scan (beam) order; e.g. the points the
        angle-histogram filter kept.
    params : WallDirectionParams

    Returns
    -------
    WallDirection or None
        None when the scan has no dominant direction (see the module docstring).

    Raises
    ------
    InputError
        If a point is not finite.
    """
    pts = np.asarray(points_xy, dtype=float).reshape(-1, 2)
    if not np.all(np.isfinite(pts)):
        raise InputError("points_xy must be finite")
    if pts.shape[0] < MIN_POINTS:
        return None
    dirs, variances, lengths = _fit_lines(pts, params)
    if dirs.size == 0:
        return None
    # Consensus by length: for each line, the total length of the lines agreeing with it mod 90°.
    agree = np.abs(wrap_quarter(dirs[:, None] - dirs[None, :])) <= ALIGN_TOL_RAD
    support = agree @ lengths
    best = int(np.argmax(support))
    members = agree[best]
    support_frac = float(support[best] / lengths.sum())
    if support_frac < params.min_support_frac or support[best] < params.min_support_length_m:
        return None
    w = 1.0 / variances[members]
    offsets = wrap_quarter(dirs[members] - dirs[best])
    mean_offset = float(np.sum(w * offsets) / np.sum(w))
    variance = 1.0 / float(np.sum(w))
    n_lines = int(members.sum())
    if n_lines >= 2:
        # Birge ratio: lines that scatter more than their own errors allow (walls
        # not quite square, a bent piece) widen the estimate; never narrow it.
        birge = float(np.sum(w * (offsets - mean_offset) ** 2)) / (n_lines - 1)
        variance *= max(1.0, birge)
    return WallDirection(
        direction_rad=wrap_quarter(dirs[best] + mean_offset),
        sigma_rad=float(np.sqrt(variance)),
        n_lines=n_lines,
        support_frac=support_frac,
    )
