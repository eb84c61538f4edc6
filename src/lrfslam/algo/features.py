"""Feature extraction (paper §IV): corners by forward searching, jump edges by backward searching.

One stage, one name: the ``features`` service runs :func:`extract_features` on each
denoised scan and publishes the result on the ``features`` topic. A feature is either a
*corner* (``FORWARD``, found by forward searching) or a *jump edge* (``BACKWARD``, found
by backward searching). Both searches walk the kept points (those that survived noise
reduction) in scan order; points removed by the filter are skipped as if never measured.

Forward searching finds corners (:func:`right_angle_bases`). From each base point, walk
outward in scan order on both sides and pick the first point at distance ≥ 0.3, 0.6,
0.9 and 1.2 m (``arm_dists_m``). An arm is the base point and its picks; a total-least-
squares (TLS) line is fitted to each arm, and the base point is a corner when the two
lines are at a right angle within ``corner_tol_deg``. An arm fails when it meets a
no-return beam or a gap wider than ``arm_break_gap_m``: the kept points are cut into
*stretches* there, and an arm stays within its base point's stretch.

Backward searching finds jump edges (:func:`jump_edges`): two successive kept points more
than ``jump_m`` (1.5 m) apart make the nearer one an edge; a kept point next to a
no-return beam is an edge only if ``r < max_range_m - jump_m``, since only then is the
hidden surface surely more than ``jump_m`` behind it.

Improvements over the paper, each switchable in :class:`FeatureParams` (``paper()``
turns them all off, ``default()`` on; docs/features.md measures each):

* **straightness check** (``arm_max_resid_m``, None = off): every point of an arm must
  lie within this distance of the arm's line, so an arm bent round a second corner
  does not count;
* **non-maximum suppression** (``nms_radius_m``, 0 = off): of corners closer than this
  only the one nearest 90° is kept, and a jump edge this close to a corner gives way
  to it (a convex corner with one wall occluded fires both searches);
* **dense refit** (``refine_corner``): both walls are refitted on every kept point
  ``refine_rmin_m``–``refine_rmax_m`` from the base point and the corner is placed at
  their intersection (:func:`_refit`);
* **short arm breaks** (``arm_break_gap_m`` = 0.5 m; the paper's only scale is 1.5 m);
* **edge guard** (``edge_max_removed``, None = off): no jump edge across a long run of
  removed points, and a no-return edge only beside the no-return itself.

Speed. The functions here state the method one base point at a time and are the
reference. Forward searching on every base point in Python is slow, so
:func:`extract_features` runs by default an accelerated version of
:func:`right_angle_bases` (``lrfslam/algo/forward_search_kernel.py``) that returns the
same base points and angles; ``tests/unit/test_features_oracle.py`` holds the two to
that on simulated, real and generated scans. Everything else runs as written here.

Covariance model (robot frame, m²):

* refined corner: each wall line ``k`` is a TLS fit of ``m_k`` points with residual
  σ_k = max(``range_sigma_m``, residual RMS) and along-line spread ``s_k``. Its offset at
  the corner has variance ``σ_k² / m_k · (1 + t_k² / s_k²)``, where ``t_k`` is the
  distance from the fit centroid to the corner (offset plus lever-arm of the angle
  error). The corner is the intersection ``A p = c`` with ``A`` the stacked unit normals,
  so ``cov = A⁻¹ diag(var_1, var_2) A⁻ᵀ``;
* any feature placed on a measured point (jump edges, unrefined corners): σ =
  ``range_sigma_m`` along the beam and ``r Δθ / √12`` across it, since the true edge lies
  anywhere within one beam step of the point.

Points are complex numbers ``x + iy`` (metres, robot frame) throughout.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from operator import attrgetter
from typing import NamedTuple

import numpy as np

from lrfslam.algo import forward_search_kernel
from lrfslam.algo.histogram import valid_returns
from lrfslam.algo.mixed_pixels import beam_tables
from lrfslam.algo.scalars import const
from lrfslam.errors import ConfigError

FORWARD = np.int8(0)   # a corner, found by forward searching
BACKWARD = np.int8(1)  # a jump edge, found by backward searching

_ARM_METRICS = ("euclidean", "arclength")
_INF_EDGE_RULES = ("margin", "any")


@dataclass(frozen=True)
class FeatureParams:
    """Knobs of forward and backward searching.

    Parameters
    ----------
    max_range_m : float
        Ranges beyond this are "no return" (paper: 4.0 m).
    arm_dists_m : tuple of float
        Distances of the arm picks from the base point (paper: 0.3, 0.6, 0.9, 1.2 m),
        increasing.
    arm_metric : str
        ``"euclidean"`` distance from the base point, or ``"arclength"`` along the
        polyline of kept points.
    arm_break_gap_m : float
        An arm fails at a gap wider than this between successive kept points; must not
        exceed ``jump_m`` so a corner is never built across a jump edge.
    corner_tol_deg : float
        Corner if ``|90° - angle| <= corner_tol_deg``.
    arm_max_resid_m : float or None
        Straightness check: the largest perpendicular TLS residual of each arm must not
        exceed this. None turns it off.
    nms_radius_m : float
        Non-maximum suppression radius: among forward candidates closer than this keep
        the one nearest 90°, and drop jump features this close to a forward corner.
        0 turns it off.
    refine_corner : bool
        Refit both walls on all kept points ``refine_rmin_m``–``refine_rmax_m`` from
        the base point and place the corner at their intersection.
    refine_rmin_m, refine_rmax_m : float
        Annulus of the refit; keep ``refine_rmax_m`` below half the narrowest hallway
        so the refit never reaches a second corner.
    refine_accept_m : float
        The refined corner is used only if within this distance of the base point.
    refine_min_points : int
        Minimum number of points per wall for the refit.
    jump_m : float
        Depth jump between successive finite points for backward searching (paper: 1.5 m).
    inf_edge_rule : str
        ``"margin"``: a finite point next to a no-return is a feature if
        ``r < max_range_m - jump_m`` (the reading of the paper); ``"any"``: always.
    edge_max_removed : int or None
        Backward searching skips points removed by the filter, so a mixed pixel does
        not split a jump; but it judges no jump across more than this many removed
        beams, and a finite/no-return edge only where the two are neighbours. None
        skips any number (the paper: only denoised data exist).
    range_sigma_m : float
        Range noise used by the covariance model.
    """

    max_range_m: float = 4.0
    arm_dists_m: tuple[float, ...] = (0.3, 0.6, 0.9, 1.2)
    arm_metric: str = "euclidean"
    arm_break_gap_m: float = 0.5
    corner_tol_deg: float = 10.0
    arm_max_resid_m: float | None = 0.05
    nms_radius_m: float = 0.3
    refine_corner: bool = True
    refine_rmin_m: float = 0.1
    refine_rmax_m: float = 0.7
    refine_accept_m: float = 0.2
    refine_min_points: int = 4
    jump_m: float = 1.5
    inf_edge_rule: str = "margin"
    edge_max_removed: int | None = 2
    range_sigma_m: float = 0.015

    def __post_init__(self) -> None:
        d = np.asarray(self.arm_dists_m, dtype=float)
        if d.ndim != 1 or len(d) < 2 or not np.all(d > 0) or not np.all(np.diff(d) > 0):
            raise ConfigError(f"arm_dists_m must be >= 2 increasing positive values, got {self.arm_dists_m}")
        if self.arm_metric not in _ARM_METRICS:
            raise ConfigError(f"arm_metric must be one of {_ARM_METRICS}, got {self.arm_metric!r}")
        if self.inf_edge_rule not in _INF_EDGE_RULES:
            raise ConfigError(f"inf_edge_rule must be one of {_INF_EDGE_RULES}, got {self.inf_edge_rule!r}")
        if not 0 < self.jump_m < self.max_range_m:
            raise ConfigError(f"jump_m must be in (0, max_range_m), got {self.jump_m}")
        if not 0 < self.arm_break_gap_m <= self.jump_m:
            raise ConfigError(f"arm_break_gap_m must be in (0, jump_m], got {self.arm_break_gap_m}")
        if not 0 <= self.corner_tol_deg < 90:
            raise ConfigError(f"corner_tol_deg must be in [0, 90), got {self.corner_tol_deg}")
        if self.arm_max_resid_m is not None and not self.arm_max_resid_m > 0:
            raise ConfigError(f"arm_max_resid_m must be > 0 or None, got {self.arm_max_resid_m}")
        if not self.nms_radius_m >= 0:
            raise ConfigError(f"nms_radius_m must be >= 0, got {self.nms_radius_m}")
        if not 0 <= self.refine_rmin_m < self.refine_rmax_m:
            raise ConfigError("need 0 <= refine_rmin_m < refine_rmax_m")
        if not self.refine_accept_m > 0:
            raise ConfigError(f"refine_accept_m must be > 0, got {self.refine_accept_m}")
        if not (isinstance(self.refine_min_points, int) and self.refine_min_points >= 2):
            raise ConfigError(f"refine_min_points must be an integer >= 2, got {self.refine_min_points!r}")
        if self.edge_max_removed is not None and not (
            isinstance(self.edge_max_removed, int) and self.edge_max_removed >= 0
        ):
            raise ConfigError(f"edge_max_removed must be an integer >= 0 or None, got {self.edge_max_removed!r}")
        if not self.range_sigma_m > 0:
            raise ConfigError(f"range_sigma_m must be > 0, got {self.range_sigma_m}")

    @classmethod
    def paper(cls) -> FeatureParams:
        """The literal reading: no straightness check, no suppression, no refinement.

        Arms break only at gaps of ``jump_m``, the paper's only discontinuity scale.
        """
        return cls(
            arm_break_gap_m=1.5, arm_max_resid_m=None, nms_radius_m=0.0, refine_corner=False, edge_max_removed=None
        )

    @classmethod
    def default(cls) -> FeatureParams:
        """Measured improvements (docs/features.md): straightness, NMS, dense refit, edge guard."""
        return cls()


@dataclass(frozen=True)
class FeatureSet:
    """Features of one scan, K of them, in beam order.

    Attributes
    ----------
    kind : ndarray of int8, shape (K,)
        ``FORWARD`` (0) corner or ``BACKWARD`` (1) jump edge.
    xy_m : ndarray, shape (K, 2)
        Position in the robot (sensor) frame, metres.
    cov_m2 : ndarray, shape (K, 2, 2)
        Position covariance, m² (model in the module docstring).
    beam : ndarray of int, shape (K,)
        Index of the source beam (the base point for corners).
    angle_deg : ndarray, shape (K,)
        Measured corner angle in [0°, 90°]; NaN for jump edges.
    refined : ndarray of bool, shape (K,)
        True where the position comes from the dense wall refit.
    """

    kind: np.ndarray
    xy_m: np.ndarray
    cov_m2: np.ndarray
    beam: np.ndarray
    angle_deg: np.ndarray
    refined: np.ndarray

    def __len__(self) -> int:
        return len(self.kind)


def _no_features() -> FeatureSet:
    """The FeatureSet of a scan without features, read-only (one shared by all such scans)."""
    empty = FeatureSet(np.empty(0, np.int8), np.empty((0, 2)), np.empty((0, 2, 2)), np.empty(0, np.intp),
                       np.empty(0), np.empty(0, bool))
    for a in (empty.kind, empty.xy_m, empty.cov_m2, empty.beam, empty.angle_deg, empty.refined):
        a.setflags(write=False)
    return empty


_NO_FEATURES = _no_features()


class _Feature(NamedTuple):
    """One feature while a scan's features are collected."""

    column: int               # kept-point column (the base point for corners)
    kind: np.int8             # FORWARD or BACKWARD
    xy: complex               # position, metres
    cov: list[list[float]] | None  # 2×2 covariance, m²; None: the point model (module docstring)
    angle_deg: float          # corner angle; NaN for jump edges
    refined: bool             # placed by the dense refit


_COLUMN = attrgetter("column")


class _Refit(NamedTuple):
    """A corner placed by the dense refit."""

    xy: complex               # intersection of the two walls, metres
    cov: list[list[float]]    # its 2×2 covariance, m²
    angle_deg: float          # angle between the walls, degrees in [0, 90]


class _Wall(NamedTuple):
    """A TLS line through one wall's points, for the refit."""

    n: int                    # points
    centre: complex           # their centroid, metres
    theta: float              # direction, radians
    normal: complex           # unit normal
    offset: float             # normal · p = offset on the line, metres
    var: float                # offset variance per point, m²: max(range_sigma_m², residual mean square)
    spread2: float            # along-line variance of the points, m²


# -- forward searching --------------------------------------------------------------


def _stretches(m: int, breaks: list[int]) -> list[tuple[int, int]]:
    """First and last column of each stretch of ``m`` kept points cut after ``breaks``."""
    starts = [0, *(b + 1 for b in breaks)]
    ends = [*breaks, m - 1]
    return list(zip(starts, ends))


def _arm(points: list[complex], j: int, direction: int, end: int, params: FeatureParams) -> list[int] | None:
    """The arm of base point ``j`` on one side: the columns of the base point and its picks.

    Walks from ``j`` in ``direction`` (+1 up the scan, -1 down) and takes, for each
    distance in ``arm_dists_m``, the first point at least that far from the base point
    (Euclidean, or along the polyline). None if column ``end``, the last of the stretch
    that way, comes first.
    """
    base = points[j]
    arm = [j]
    k, walked, reach = j, 0.0, 0.0
    for dist in params.arm_dists_m:
        while reach < dist:
            if k == end:
                return None
            k += direction
            walked += abs(points[k] - points[k - direction])
            reach = abs(points[k] - base) if params.arm_metric == "euclidean" else walked
        arm.append(k)
    return arm


def _tls_line(points: list[complex]) -> tuple[float, float]:
    """TLS line through ``points``: its direction (radians, in [-π/2, π/2]) and the
    largest perpendicular distance of a point from it (metres)."""
    centre = sum(points) / len(points)
    q = [p - centre for p in points]
    # Σq² = (Σx² - Σy²) + 2i Σxy: the principal direction is half its argument.
    s = sum(w * w for w in q)
    theta = 0.5 * math.atan2(s.imag, s.real)
    # Turned by -θ the line lies along the x axis; each offset from it is an imaginary part.
    turn = complex(math.cos(theta), -math.sin(theta))
    return theta, max(abs((w * turn).imag) for w in q)


def _line_angle_deg(theta_a: float, theta_b: float) -> float:
    """Angle between two undirected lines of directions in [-π/2, π/2] (radians), degrees in [0, 90]."""
    d = math.degrees(abs(theta_a - theta_b))
    return min(d, 180.0 - d)


def right_angle_bases(z: np.ndarray, step_m: np.ndarray, breaks: list[int],
                      params: FeatureParams) -> tuple[list[int], list[float], list[tuple[int, int]]]:
    """Forward searching: the base points whose two arms are at a right angle.

    Every kept point is tried as the base: its arm on each side (:func:`_arm`) gets a
    TLS line (:func:`_tls_line`), and it passes when the lines are at a right angle
    within ``corner_tol_deg`` and, with the straightness check on, no point of either
    arm lies farther than ``arm_max_resid_m`` from its line.

    Parameters
    ----------
    z : ndarray of complex, shape (M,)
        Kept points ``x + iy`` in scan order, metres.
    step_m : ndarray, shape (M - 1,)
        Distances between successive points, metres (unused here; the accelerated
        version, which takes the same arguments, needs them).
    breaks : list of int
        Points after which a new stretch starts, increasing: an arm never crosses
        from one stretch to the next.
    params : FeatureParams

    Returns
    -------
    columns : list of int
        Columns in ``z`` of the base points, increasing.
    angles_deg : list of float
        Angle between each base point's two arm lines, degrees in [0, 90].
    arm_ends : list of (int, int)
        Columns of each base point's farthest picks, below and above it.
    """
    points = z.tolist()
    columns, angles, arm_ends = [], [], []
    if len(points) < 2 * len(params.arm_dists_m) + 1:
        # Too few points for two arms of distinct picks: no corner is searched for (one far
        # point would otherwise be every pick of an arm).
        return columns, angles, arm_ends
    for first, last in _stretches(len(points), breaks):
        for j in range(first, last + 1):
            lower, upper = _arm(points, j, -1, first, params), _arm(points, j, 1, last, params)
            if lower is None or upper is None:
                continue
            theta_lower, resid_lower = _tls_line([points[k] for k in lower])
            theta_upper, resid_upper = _tls_line([points[k] for k in upper])
            angle = _line_angle_deg(theta_lower, theta_upper)
            square = 90.0 - angle <= params.corner_tol_deg
            straight = params.arm_max_resid_m is None or max(resid_lower, resid_upper) <= params.arm_max_resid_m
            if square and straight:
                columns.append(j)
                angles.append(angle)
                arm_ends.append((lower[-1], upper[-1]))
    return columns, angles, arm_ends


# -- improvements on the corners ------------------------------------------------------


def _suppress(xy: list[complex], score: list[float], radius_m: float) -> list[int]:
    """Greedy non-maximum suppression: indices kept, best (lowest score) first.

    Going from the best, an item is kept unless it lies within ``radius_m`` of one
    already kept. ``radius_m`` 0 keeps every item.
    """
    order = sorted(range(len(score)), key=score.__getitem__)  # stable: ties keep scan order
    if radius_m <= 0:
        return order
    r2 = radius_m * radius_m
    chosen: list[int] = []
    for i in order:
        for c in chosen:
            d = xy[i] - xy[c]
            if d.real * d.real + d.imag * d.imag < r2:
                break
        else:
            chosen.append(i)
    return chosen


def _dist2(a: complex, b: complex) -> float:
    """Squared distance between two points, m²."""
    d = a - b
    return d.real * d.real + d.imag * d.imag


def _wall_fit(walk: list[complex], params: FeatureParams) -> _Wall | None:
    """TLS line through one wall of a corner, for the refit.

    ``walk`` holds the points of one side relative to the base point, walking outward;
    the wall is every point up to the first one farther than ``refine_rmax_m`` (so it
    is never followed round a second corner), less those nearer than
    ``refine_rmin_m``. None if that leaves fewer than ``refine_min_points`` or no
    spread along the line.
    """
    # Moment sums over the wall: count, Σw, Σw² and Σ|w|². Relative to the base point
    # they stay small, so centring them afterwards loses no precision.
    n, s1, s2, sa = 0, 0j, 0j, 0.0
    for w in walk:
        d = abs(w)
        if d > params.refine_rmax_m:
            break
        if d >= params.refine_rmin_m:
            n += 1
            s1 += w
            s2 += w * w
            sa += d * d
    if n < params.refine_min_points:
        return None
    centre = s1 / n
    # Σ(w - c)² = (sxx - syy) + 2i sxy and Σ|w - c|² = sxx + syy.
    q = s2 - s1 * centre
    tot = sa - (s1 * centre.conjugate()).real
    theta = 0.5 * math.atan2(q.imag, q.real)
    # Residual sum of squares about the line = the smaller scatter eigenvalue;
    # rounding may leave it a hair below 0.
    ss = max(0.5 * (tot - abs(q)), 0.0)
    spread2 = (tot - ss) / n
    if not spread2 > 0:
        return None
    normal = complex(-math.sin(theta), math.cos(theta))
    offset = normal.real * centre.real + normal.imag * centre.imag
    return _Wall(n, centre, theta, normal, offset, max(params.range_sigma_m**2, ss / n), spread2)


def _refit(z: np.ndarray, first: int, last: int, j: int, params: FeatureParams) -> _Refit | None:
    """Dense wall refit round the corner at base point ``j``: the two walls' intersection.

    Each wall is fitted (:func:`_wall_fit`) to the kept points walking outward from the
    base point, within columns ``first`` to ``last``: its stretch, or less where a
    point farther than ``refine_rmax_m`` ends the walls anyway. None if a wall has too
    few points or the intersection is farther than ``refine_accept_m`` from the base
    point. A wall is a few dozen points: Python scalars beat array calls.
    """
    base = z[j]
    rel = (z[first:last + 1] - base).tolist()
    k = j - first
    lower = _wall_fit(rel[k - 1::-1] if k else [], params)
    upper = _wall_fit(rel[k + 1:], params) if lower is not None else None
    if upper is None:
        return None
    n1x, n1y, n2x, n2y = lower.normal.real, lower.normal.imag, upper.normal.real, upper.normal.imag
    det = n1x * n2y - n1y * n2x
    if det == 0.0:
        return None
    # Intersection of the walls n_k · p = offset_k (Cramer's rule), relative to the base point.
    o1, o2 = lower.offset, upper.offset
    x, y = (o1 * n2y - o2 * n1y) / det, (n1x * o2 - n2x * o1) / det
    if not x * x + y * y <= params.refine_accept_m**2:
        return None
    v1 = _offset_var(lower, x, y)
    v2 = _offset_var(upper, x, y)
    # cov = A⁻¹ diag(v1, v2) A⁻ᵀ with A = [n1; n2] and A⁻¹ = [[n2y, -n1y], [-n2x, n1x]] / det.
    det2 = det * det
    cxy = -(n2y * n2x * v1 + n1y * n1x * v2) / det2
    cov = [[(n2y * n2y * v1 + n1y * n1y * v2) / det2, cxy], [cxy, (n2x * n2x * v1 + n1x * n1x * v2) / det2]]
    return _Refit(complex(base) + complex(x, y), cov, _line_angle_deg(lower.theta, upper.theta))


def _offset_var(wall: _Wall, x: float, y: float) -> float:
    """Variance of a wall's offset at the corner ``(x, y)``, m²: its offset error plus
    its direction error times the lever arm from the fit centroid to the corner."""
    t = (x - wall.centre.real) * wall.normal.imag - (y - wall.centre.imag) * wall.normal.real
    return wall.var / wall.n * (1.0 + t * t / wall.spread2)


def _corners(z: np.ndarray, breaks: list[int], columns: list[int], angles_deg: list[float],
             arm_ends: list[tuple[int, int]], params: FeatureParams) -> list[_Feature]:
    """The corners among the right-angle base points (:func:`right_angle_bases`):
    suppression, then the dense refit."""
    xy = z[columns].tolist()
    # Picked by Euclidean distance, the farthest picks are farther than refine_rmax_m
    # from the base point, so the refit walls end before them: the refit need look no
    # farther. (Along the polyline a pick can lie nearer than its distance.)
    within_arms = params.arm_metric == "euclidean" and params.arm_dists_m[-1] > params.refine_rmax_m
    out = []
    for i in sorted(_suppress(xy, [90.0 - a for a in angles_deg], params.nms_radius_m)):
        j = columns[i]
        refit = None
        if params.refine_corner:
            if within_arms:
                first, last = arm_ends[i]
            else:
                first, last = next((s, e) for s, e in _stretches(len(z), breaks) if s <= j <= e)
            refit = _refit(z, first, last, j, params)
        if refit is None:
            out.append(_Feature(j, FORWARD, xy[i], None, angles_deg[i], False))
        else:
            out.append(_Feature(j, FORWARD, refit.xy, refit.cov, refit.angle_deg, True))
    return out


# -- backward searching ---------------------------------------------------------------


def jump_edges(ranges_m: np.ndarray, valid: np.ndarray, idx: np.ndarray, step_m: np.ndarray,
               n_invalid: np.ndarray, n_no_return: int, breaks: list[int], params: FeatureParams) -> list[int]:
    """Backward searching: the kept points that are jump edges, as positions in ``idx``, increasing.

    The walk goes over the kept points and the no-return beams in scan order:

    * *jump*: two successive kept points more than ``jump_m`` apart; the nearer is an edge;
    * *no-return edge*: a kept point beside a no-return beam is an edge if
      ``r < max_range_m - jump_m`` (``inf_edge_rule`` "margin"), or always ("any");
    * *edge guard* (``edge_max_removed``, None = off): no jump across more than
      ``edge_max_removed`` removed beams, and a no-return edge only where the no-return
      is the point's neighbouring beam (a removed return in between shows the surface
      went on).

    Both lie where forward searching cuts its stretches: a jump is longer than
    ``arm_break_gap_m <= jump_m``, and a no-return between two kept points starts a new
    stretch. So only the breaks and the two ends of the scan are looked at.

    Parameters
    ----------
    ranges_m : ndarray, shape (N,)
    valid : ndarray of bool, shape (N,)
        Beams with a return.
    idx : ndarray of int, shape (M,)
        Beams of the kept points, increasing.
    step_m : ndarray, shape (M - 1,)
        Distances between successive kept points, metres.
    n_invalid : ndarray of int, shape (M,)
        Number of no-return beams before each kept point.
    n_no_return : int
        Number of no-return beams in the scan.
    breaks : list of int
        Stretch breaks of forward searching: kept points after which a new stretch starts.
    params : FeatureParams
    """
    m = len(idx)
    if not m:
        return []
    margin = params.max_range_m - params.jump_m if params.inf_edge_rule == "margin" else math.inf
    guard = params.edge_max_removed

    def no_return_edge(p: int, side: int) -> bool:
        """Is kept point ``p``, with a no-return on ``side`` (-1 below, +1 above), an edge?"""
        i = int(idx[p])
        if guard is not None and valid[i + side]:
            return False
        return bool(ranges_m[i] < margin)

    def jump_edge(p: int) -> int | None:
        """The nearer of kept points ``p`` and ``p + 1`` if they are a jump apart."""
        i, k = int(idx[p]), int(idx[p + 1])
        if not step_m[p] > params.jump_m or (guard is not None and k - i - 1 > guard):
            return None
        return p + 1 if ranges_m[k] < ranges_m[i] else p

    found = []
    if n_invalid[0] and no_return_edge(0, -1):
        found.append(0)
    for p in breaks:
        if n_invalid[p] == n_invalid[p + 1]:
            edge = jump_edge(p)
            if edge is not None:
                found.append(edge)
        else:
            if no_return_edge(p, 1):
                found.append(p)
            if no_return_edge(p + 1, -1):
                found.append(p + 1)
    if n_invalid[-1] < n_no_return and no_return_edge(m - 1, 1):
        found.append(m - 1)
    # A point can be the near side of two jumps, or of a jump and a no-return edge.
    return sorted(set(found))


# -- the stage ------------------------------------------------------------------------


def _point_cov(range_m: float, bearing_rad: float, beam_step_rad: float, range_sigma_m: float) -> list[list[float]]:
    """Covariance of a feature placed on a measured point, 2×2 nested lists, m².

    ``range_sigma_m`` along the beam; across it the uniform spread of one beam step,
    ``r Δθ / √12``.
    """
    c, s = math.cos(bearing_rad), math.sin(bearing_rad)
    var_r = range_sigma_m**2
    var_t = (range_m * beam_step_rad) ** 2 / 12.0
    cxy = c * s * (var_r - var_t)
    return [[c * c * var_r + s * s * var_t, cxy], [cxy, s * s * var_r + c * c * var_t]]


def extract_features(ranges_m: np.ndarray, angles_rad: np.ndarray, kept: np.ndarray, params: FeatureParams,
                     *, accelerated: bool = True) -> FeatureSet:
    """Forward and backward searching on one scan.

    Parameters
    ----------
    ranges_m : ndarray, shape (N,)
        Ranges in metres; NaN, ±inf, ``<= 0`` or ``> max_range_m`` mean no return.
    angles_rad : ndarray, shape (N,)
        Beam bearings in radians in the robot frame, increasing.
    kept : ndarray of bool, shape (N,)
        Points that survived noise reduction (e.g. ``DenoiseResult.kept``); valid beams
        not kept are skipped.
    params : FeatureParams
    accelerated : bool
        Forward searching by the accelerated kernel (the default) or by the plain
        :func:`right_angle_bases`; the features are the same.

    Returns
    -------
    FeatureSet
        Corners and jump edges, in beam order.
    """
    r = np.asarray(ranges_m, dtype=float)
    ang = np.asarray(angles_rad, dtype=float)
    kept = np.asarray(kept, dtype=bool)
    if not (r.shape == ang.shape == kept.shape and r.ndim == 1):
        raise ValueError(f"ranges_m {r.shape}, angles_rad {ang.shape}, kept {kept.shape} must be equal 1-D shapes")
    beams = beam_tables(ang)
    valid = valid_returns(r, params.max_range_m)
    idx = (valid & kept).nonzero()[0]
    # Paper eq. (1) in the robot frame, as complex numbers x + iy.
    z = r[idx] * beams.expi[idx]
    step = np.abs(z[1:] - z[:-1])
    # Stretches of kept points: a new one starts after a no-return beam (the count of
    # no-returns before the point changes) or a gap wider than arm_break_gap_m.
    no_return = (~valid).nonzero()[0]
    n_invalid = no_return.searchsorted(idx)
    breaks = ((n_invalid[1:] != n_invalid[:-1]) | (step > const(params.arm_break_gap_m))).nonzero()[0].tolist()

    search = forward_search_kernel.right_angle_bases if accelerated else right_angle_bases
    columns, angles, arm_ends = search(z, step, breaks, params)
    found = _corners(z, breaks, columns, angles, arm_ends, params) if columns else []
    edges = jump_edges(r, valid, idx, step, n_invalid, len(no_return), breaks, params)
    edge_xy = [complex(z[p]) for p in edges]
    if params.nms_radius_m > 0 and found and edges:
        # A convex corner with one wall occluded fires both searches; the corner is
        # better localised, so the jump edge gives way.
        r2 = params.nms_radius_m**2
        near = [all(_dist2(e, c.xy) >= r2 for c in found) for e in edge_xy]
        edges, edge_xy = [p for p, ok in zip(edges, near) if ok], [e for e, ok in zip(edge_xy, near) if ok]
    found += [_Feature(p, BACKWARD, e, None, math.nan, False) for p, e in zip(edges, edge_xy)]
    if not found:
        return _NO_FEATURES
    # A handful of features per scan: assembled in Python, in beam order (corners
    # before edges on the same point), the numbers of each in one row of one array.
    found.sort(key=_COLUMN)
    beam = idx[[f.column for f in found]]
    rows = []
    for f, i in zip(found, beam.tolist()):
        cov = f.cov or _point_cov(float(r[i]), float(ang[i]), beams.step_rad, params.range_sigma_m)
        rows.append((f.xy.real, f.xy.imag, *cov[0], *cov[1], f.angle_deg))
    values = np.array(rows)
    return FeatureSet(
        kind=np.array([f.kind for f in found], dtype=np.int8),
        xy_m=values[:, :2],
        cov_m2=values[:, 2:6].reshape(-1, 2, 2),
        beam=beam,
        angle_deg=values[:, 6],
        refined=np.array([f.refined for f in found], dtype=bool),
    )
