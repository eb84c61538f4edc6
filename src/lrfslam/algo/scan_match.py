"""Point-to-line ICP: the motion between laser scans from their overlap.

Symbols (used only inside this module; public names are by role):

* reference points ``q_j`` (M, 2) with unit normals ``n_j`` (M, 2), in the
  reference frame; current points ``p_i`` (N, 2) in the current robot frame;
* the sought pose ``u = (x_m, y_m, theta_rad)`` of the current scan in the
  reference frame (an odometry increment when the reference is the previous
  scan's robot frame): a current point maps to ``R(theta) p_i + (x, y)``;
* residual ``r_i = n_j · (R p_i + t − q_j)`` for the nearest reference point
  ``q_j``; Jacobian ``J_i = (n_jx, n_jy, n_j · R' p_i)`` with ``R' = dR/dθ``.

Design choices
--------------
* **Point-to-line** (Chen & Medioni; Censi's PL-ICP uses the same metric): walls
  are lines and two scans sample them at different spots, so the point-to-point
  error of standard ICP is biased by the beam spacing; the distance to the
  reference's local line is not, and Gauss–Newton on it converges in a few
  iterations.
* **Normals** come from a line fit (PCA) to up to ``normal_neighbours``
  nearest points within ``normal_radius_m``, in the reference and in the
  current scan alike. Points whose neighbourhood is not line-like (clutter,
  corners, isolated returns) get no normal and take no part: they have no line
  to be compared along, and a scan matched to itself is then exactly the
  identity. A pair must also have normals within ``max_normal_angle_rad``: near
  a corner the nearest reference point may lie on the other wall.
* **Robustness.** Pairs farther apart than a gate are not correspondences; the
  gate starts wide (initial-guess error) and narrows after
  ``wide_gate_iterations``. Remaining pairs get Cauchy weights
  ``1 / (1 + (r/s)²)``, so people walking by and newly seen walls count little.
* **Things that moved** (``free_space_check``). Cauchy weights do not stop a person walking
  towards the robot down a corridor: matched as if they stood still, they give the along-corridor
  direction its only constraint and drag the motion at walking speed. A static world never puts a
  return where an earlier beam went on to a farther one, so :class:`ScanTracker` leaves out the
  points that lie where one of its last reference scans saw through, and drops from its recent
  reference scans the points the current scan sees through (:mod:`lrfslam.algo.free_space`;
  docs/slam.md, "On the simulator").
* **Degenerate geometry.** In a featureless corridor the motion along it leaves
  every residual unchanged: the information matrix (rotation scaled to metres of
  arc at the rms range, divided by the total weight) has a near-zero eigenvalue.
  Gauss–Newton then steps only in the constrained directions ("solution
  remapping", Zhang et al. 2016) so the unconstrained ones keep the initial
  guess (odometry): in a corridor the scan still fixes heading and lateral
  offset. Without a covariance for the guess a degenerate match fails instead.
  On the Intel log this beats both a full fallback to odometry and a Gaussian
  odometry prior on every direction: the wheel heading is biased (about −0.8°
  per 1.5 s there), and a prior lets that bias into every match.
* **Covariance** ``(Jᵀ W J / (cov_scale σ̂²) + Π Σ_guess⁻¹ Π)⁻¹``: the Gauss–Newton
  information with the residual variance ``σ̂²`` estimated from the weighted
  residuals, plus the guess's information projected (``Π``) onto the remapped
  directions only, which carry the odometry's uncertainty: the estimate takes
  nothing from the guess elsewhere, so neither may its covariance (wheel
  odometry's near-zero lateral variance made the first matches 15× overconfident
  across the corridor before). It ignores that neighbouring beams' errors
  correlate and that the normals are themselves noisy, so alone it is
  optimistic; ``cov_scale`` is the factor that makes the NEES consistent on the
  simulator (``tests/unit/test_scan_match.py``).
* **Termination**: a step below ``converged_*``, or a correspondence set met
  before (nearest neighbours can swap back and forth with sub-mm steps).
* **Failure is reported, not hidden**: too few points, no convergence, too few
  inliers, a correction larger than any plausible guess error. The caller then
  uses odometry.

:class:`ScanTracker` chains matches into odometry against *reference scans*: the
current scan is matched to the last few reference scans, merged and thinned to one
point per ``map_cell_m`` cell. Matching to a reference scan instead of the previous
scan stops the error from accumulating while the robot stands or creeps. The
normals are fitted on the merged points, so a wall seen twice out of register
is thick there and drops out instead of dragging the match. Old reference scans near
the predicted pose are not taken in: under the EKF, whose landmarks close the
loop themselves, such snaps arrive as motion and correct the same drift twice.
(A scan tracker's *reference scans* are not the mapper's *keyframes*, the nodes
of its pose graph published on ``map/keyframes``.)

The increments' covariances are meant to be summed by a filter as a random
walk, which matches against reference scans are not (see ``ScanTracker._fresh_cov``):
the match's error relative to its reference is handed out once, as a running
maximum, and each change of reference adds the part of a reference scan's error it
brings. Naive chaining would hand the same reference error out again with every
scan matched against it: overconfident while the reference stays, then too
conservative.

References
----------
Y. Chen, G. Medioni, "Object modelling by registration of multiple range
images", Image and Vision Computing 10(3), 1992. A. Censi, "An ICP variant using
a point-to-line metric", ICRA 2008. J. Zhang, M. Kaess, S. Singh, "On degeneracy
of optimization-based state estimation problems", ICRA 2016.
"""

from __future__ import annotations

import enum
from collections import deque
from dataclasses import dataclass, field, replace

import numpy as np

from lrfslam.algo import scan_match_kernel as kernel
from lrfslam.algo.checks import require_finite
from lrfslam.algo.free_space import FreeSpace, seen_through
from lrfslam.algo.geometry import (
    compose,
    from_frame,
    relative,
    rotate_covariance,
    thin_points,
    wrap_angle,
)
from lrfslam.errors import InputError


class MatchStatus(enum.IntEnum):
    """Outcome of :func:`match`; anything but OK means "use odometry instead"."""

    OK = 0
    TOO_FEW_POINTS = 1  # in the reference (with normals) or in the current scan
    NOT_CONVERGED = 2
    FEW_INLIERS = 3  # inlier ratio below ``min_inlier_ratio``
    DEGENERATE = 4  # a direction unconstrained and no guess covariance to take it from
    IMPLAUSIBLE = 5  # the correction to the initial guess exceeds the plausible guess error
    NO_REFERENCE = 6  # ScanTracker: first scan, nothing to match against yet


#: A point's normal: a line fitted to its nearest points (itself included), at most
#: ``NORMAL_NEIGHBOURS`` of those within ``NORMAL_RADIUS_M`` (m), at least ``NORMAL_MIN_NEIGHBOURS``.
NORMAL_NEIGHBOURS = 10
NORMAL_RADIUS_M = 0.3
NORMAL_MIN_NEIGHBOURS = 4

#: Largest ratio of the line fit's minor to major standard deviation for a neighbourhood to count as a line
#: (dimensionless, 0 = perfect line): loose enough for cluttered walls to keep their line points, tight
#: enough to drop corners.
NORMAL_MAX_THICKNESS = 0.35

#: Largest distance between a current point and its nearest reference point for a correspondence: during the
#: first ``WIDE_GATE_ITERATIONS`` iterations, then after (m).
WIDE_GATE_M = 0.5
NARROW_GATE_M = 0.15

#: The reference grid's cell (m): as wide as the widest gate, so the 3×3 cells round a point hold every pair.
GRID_CELL_M = max(WIDE_GATE_M, NARROW_GATE_M)

#: Iterations run with the wide gate.
WIDE_GATE_ITERATIONS = 3

#: Scale ``s`` of the Cauchy weight on the point-to-line residual (m).
ROBUST_SCALE_M = 0.03

#: Gauss–Newton iterations at most.
MAX_ITERATIONS = 40

#: An iteration whose step is below both ends the search (m, rad); so does a correspondence set met before (a
#: cycle).
CONVERGED_TRANS_M = 1e-6
CONVERGED_ROT_RAD = 1e-6

#: A current point pairs only with a reference point whose normal is within this angle of its own (rad).
MAX_NORMAL_ANGLE_RAD = 0.5

#: Current and reference points with normals (line points) needed, and paired points at every iteration.
MIN_POINTS = 30

#: Fraction of the current line points that must have a correspondence at the end.
MIN_INLIER_RATIO = 0.3

#: Directions whose normalised information eigenvalue is below this are unconstrained (dimensionless; 1/3 for
#: ideal isotropic geometry, 0 for the direction along a corridor).
MIN_INFORMATION_RATIO = 0.01

#: A result that differs from the initial guess by more than this is rejected as a false minimum (m, rad).
MAX_CORRECTION_TRANS_M = 0.5
MAX_CORRECTION_ROT_RAD = 0.35

#: Floor of the estimated per-point residual standard deviation (m): a near-perfect fit must not make the scan
#: infinitely certain.
MIN_RESIDUAL_SIGMA_M = 0.005

#: Factor on the scan's Gauss–Newton covariance that makes the matches' NEES consistent on the simulator
#: (see **Covariance** in the module docstring).
COV_SCALE = 1.6

#: :class:`ScanTracker` makes the current scan a reference scan once it is this far (m) or turned this much
#: (rad) from the last reference scan.
REFERENCE_TRANS_M = 0.3
REFERENCE_ROT_RAD = 0.2

#: The last this many reference scans are kept and matched against.
REFERENCES_KEPT = 3

#: The reference scans' points are merged to one point per square of this side (m).
MAP_CELL_M = 0.05

#: The free-space check (``ScanMatchParams.free_space_check``): a point is seen through when it is nearer
#: than a later return along its beam by ``FREE_SPACE_MARGIN_M + FREE_SPACE_MARGIN_PER_M * r`` (m, and m per
#: m of its range ``r``), and so is every return within ``FREE_SPACE_LATERAL_M`` across the beam (m) plus
#: ``FREE_SPACE_BEARING_RAD`` of its bearing (rad).
FREE_SPACE_MARGIN_M = 0.5
FREE_SPACE_MARGIN_PER_M = 0.1
FREE_SPACE_LATERAL_M = 0.05
FREE_SPACE_BEARING_RAD = 0.0175

#: Width of the bearing bins the free space is kept in (rad).
FREE_SPACE_BIN_RAD = 0.0175

#: A bin without a return inside a scan's field of view saw empty space to this range (m; 0: unknown).
FREE_SPACE_SILENT_M = 8.0

#: The free space of this many last reference scans is kept and checked (>= 1).
FREE_SPACE_SCANS = 10


@dataclass(frozen=True)
class ScanMatchParams:
    """The settings of :func:`match` and :class:`ScanTracker` (the rest are this module's constants).

    Attributes
    ----------
    max_point_range_m : float
        Current-scan points farther than this from the sensor are not used (m).
    free_space_check : bool
        :class:`ScanTracker` leaves out of the match, and out of its reference scans, the
        points that lie where one of the last reference scans' beams passed on to farther
        returns (or to none: ``FREE_SPACE_SILENT_M``), and drops
        from the recent reference scans the points the current scan sees through:
        things that moved (:mod:`lrfslam.algo.free_space`).
    """

    # Farther than the paper's 4 m: scan matching needs the long walls that pin its heading.
    max_point_range_m: float = 8.0
    free_space_check: bool = True

    def __post_init__(self) -> None:
        require_finite(self, ("max_point_range_m",), positive=True, what="scan matching ")


@dataclass(frozen=True, eq=False)
class ReferenceScan:
    """Points with line normals, ready to be matched against.

    Attributes
    ----------
    points_xy_m : ndarray, shape (M, 2)
        The usable reference points (those with a normal) (m).
    normals : ndarray, shape (M, 2)
        Unit normals of the local line at each point.
    """

    points_xy_m: np.ndarray
    normals: np.ndarray
    _grid: list = field(default_factory=list, repr=False)   # [cell m, Grid] once asked for

    @classmethod
    def build(cls, points_xy_m) -> ReferenceScan:
        """Fit a line to each point's neighbourhood; keep the points on a line.

        ``points_xy_m`` (N, 2) in one frame (m): a scan's, or several scans'
        moved into one frame; non-finite rows are ignored.
        """
        pts = _usable(points_xy_m, np.inf)
        if pts.shape[0] < NORMAL_MIN_NEIGHBOURS:
            return cls(np.zeros((0, 2)), np.zeros((0, 2)))
        # Up to k neighbours within the radius: near the sensor the beams are dense and k spans
        # enough wall for the line to stand out of the range noise. Over several scans, a wall
        # seen twice out of register is thick here and drops out, so a misaligned old reference scan
        # cannot drag the match.
        line, normals = kernel.line_normals(pts, NORMAL_NEIGHBOURS, NORMAL_RADIUS_M,
                                            NORMAL_MIN_NEIGHBOURS, NORMAL_MAX_THICKNESS)
        return cls(pts[line], normals[line])

    def grid(self, cell_m: float) -> kernel.Grid:
        """The points bucketed in ``cell_m`` squares for the nearest-neighbour search (the last one kept)."""
        cached = self._grid
        if not cached or cached[0] != cell_m:
            self._grid[:] = [cell_m, kernel.grid(self.points_xy_m, cell_m)]
        return self._grid[1]

    def __len__(self) -> int:
        return int(self.points_xy_m.shape[0])


@dataclass(frozen=True, eq=False)
class MatchResult:
    """What :func:`match` found.

    Attributes
    ----------
    status : MatchStatus
        OK, or why the result must not be used.
    pose : ndarray, shape (3,)
        ``(x_m, y_m, theta_rad)`` of the current scan in the reference frame.
        The initial guess when the status is not OK.
    cov : ndarray, shape (3, 3)
        Its covariance (m², m·rad, rad²); NaN when the status is not OK.
    iterations : int
        Gauss–Newton iterations run.
    inlier_ratio : float
        Fraction of the current line points with a correspondence at the end.
    residual_rms_m : float
        Weighted rms of the point-to-line residuals at the end (m).
    information_ratio : float
        Smallest normalised information eigenvalue (see ``min_information_ratio``).
    unconstrained : int
        Directions (0–3) taken from the guess because the scan did not constrain them.
    """

    status: MatchStatus
    pose: np.ndarray
    cov: np.ndarray
    iterations: int = 0
    inlier_ratio: float = 0.0
    residual_rms_m: float = float("nan")
    information_ratio: float = float("nan")
    unconstrained: int = 0

    @property
    def ok(self) -> bool:
        return self.status is MatchStatus.OK


def _residual_variance(lin: kernel.Linearised) -> float:
    """Per-point residual variance (m²) of a linearisation: weighted, 3 degrees of freedom used, floored."""
    sigma2 = float(np.sum(lin.weight * lin.residual_m**2) / max(float(lin.weight.sum()) - 3.0, 1.0))
    return max(sigma2, MIN_RESIDUAL_SIGMA_M**2)


def _usable(points_xy_m, max_range_m: float) -> np.ndarray:
    pts = np.asarray(points_xy_m, dtype=float).reshape(-1, 2)
    finite = np.all(np.isfinite(pts), axis=1)
    if np.isfinite(max_range_m):
        finite[finite] = np.hypot(pts[finite, 0], pts[finite, 1]) <= max_range_m
    return pts[finite]


def _linearise(reference: ReferenceScan, current: ReferenceScan, u: np.ndarray, gate_m: float) -> kernel.Linearised:
    """Correspondences and normal equations at pose ``u`` (the compiled kernel)."""
    return kernel.linearise(reference.points_xy_m, reference.normals, reference.grid(GRID_CELL_M),
                            current.points_xy_m, current.normals, u, gate_m, MAX_NORMAL_ANGLE_RAD,
                            ROBUST_SCALE_M)




def match(reference: ReferenceScan, points_xy_m, initial_guess, params: ScanMatchParams,
          guess_cov=None) -> MatchResult:
    """Align the current scan's points to ``reference`` by point-to-line ICP.

    Parameters
    ----------
    reference : ReferenceScan
        An earlier scan (or several, merged) in the reference frame.
    points_xy_m : array_like, shape (N, 2)
        Current scan's points in its robot frame (m); non-finite rows and points
        beyond ``params.max_point_range_m`` are ignored.
    initial_guess : array_like, shape (3,)
        ``(x_m, y_m, theta_rad)`` of the current pose in the reference frame,
        e.g. the odometry increment when the reference is the previous scan.
    params : ScanMatchParams
    guess_cov : array_like, shape (3, 3), optional
        Covariance of ``initial_guess`` (m², m·rad, rad²). With it, directions
        the scan leaves unconstrained keep the guess and the result's covariance
        includes the guess's information; without it such a match fails as
        DEGENERATE and the covariance is the scan's alone.

    Returns
    -------
    MatchResult
    """
    guess = np.asarray(initial_guess, dtype=float)
    if guess.shape != (3,) or not np.all(np.isfinite(guess)):
        raise InputError(f"initial_guess must be 3 finite numbers, got {initial_guess!r}")
    prior_info = np.zeros((3, 3))
    if guess_cov is not None:
        g_cov = np.asarray(guess_cov, dtype=float)
        if g_cov.shape != (3, 3) or not np.all(np.isfinite(g_cov)):
            raise InputError("guess_cov must be a finite (3, 3) array")
        # The floor keeps a zero variance (no turn, no heading noise) invertible.
        prior_info = np.linalg.inv(0.5 * (g_cov + g_cov.T) + 1e-12 * np.eye(3))
    # Only line points of the current scan take part, with their own normals: clutter
    # and corner points have no line to be compared along, and a scan matched to
    # itself is then exactly the identity.
    current = ReferenceScan.build(_usable(points_xy_m, params.max_point_range_m))
    if len(current) < MIN_POINTS or len(reference) < MIN_POINTS:
        return MatchResult(MatchStatus.TOO_FEW_POINTS, guess.copy(), np.full((3, 3), np.nan))

    def failed(status: MatchStatus, lin: kernel.Linearised, iterations: int) -> MatchResult:
        return MatchResult(status, guess.copy(), np.full((3, 3), np.nan), iterations, float(lin.paired.mean()),
                           information_ratio=float(lin.eigvals[0]))

    u = guess.copy()
    converged = False
    iterations = 0
    seen: set[bytes] = set()  # correspondence sets met with the narrow gate
    for it in range(MAX_ITERATIONS):
        iterations = it + 1
        gate = WIDE_GATE_M if it < WIDE_GATE_ITERATIONS else NARROW_GATE_M
        lin = _linearise(reference, current, u, gate)
        if lin.paired.sum() < MIN_POINTS:
            return failed(MatchStatus.FEW_INLIERS, lin, iterations)
        constrained = lin.eigvals >= MIN_INFORMATION_RATIO
        if not constrained.all() and (guess_cov is None or not constrained.any()):
            return failed(MatchStatus.DEGENERATE, lin, iterations)
        # Gauss–Newton step in the constrained directions only (in scaled coordinates,
        # where the eigen-decomposition was taken); the others keep the guess.
        v = lin.eigvecs[:, constrained]
        step = -lin.scale * (v @ ((v.T @ (lin.scale * lin.gradient)) / (lin.eigvals[constrained] * lin.weight.sum())))
        u = u + step
        u[2] = wrap_angle(u[2])
        if it + 1 < WIDE_GATE_ITERATIONS:
            continue
        small = np.hypot(step[0], step[1]) < CONVERGED_TRANS_M and abs(step[2]) < CONVERGED_ROT_RAD
        # Nearest neighbours can swap back and forth between a few sets with
        # sub-mm steps: meeting a set again (narrow gate) ends the search too.
        key = lin.pairs.tobytes()
        if small or key in seen:
            converged = True
            break
        seen.add(key)

    lin = _linearise(reference, current, u, NARROW_GATE_M)
    if not converged:
        return failed(MatchStatus.NOT_CONVERGED, lin, iterations)
    inlier_ratio = float(lin.paired.mean())
    if inlier_ratio < MIN_INLIER_RATIO or lin.paired.sum() < MIN_POINTS:
        return failed(MatchStatus.FEW_INLIERS, lin, iterations)
    constrained = lin.eigvals >= MIN_INFORMATION_RATIO
    if not constrained.all() and guess_cov is None:
        return failed(MatchStatus.DEGENERATE, lin, iterations)
    correction = relative(guess, u)
    if np.hypot(correction[0], correction[1]) > MAX_CORRECTION_TRANS_M \
            or abs(correction[2]) > MAX_CORRECTION_ROT_RAD:
        return failed(MatchStatus.IMPLAUSIBLE, lin, iterations)
    # The estimate takes the guess only in the unconstrained directions, so its
    # covariance does too: the guess's information elsewhere would make it
    # overconfident (odometry claims sub-mm lateral precision that the match
    # does not use). Projected in the scaled coordinates, where eigvecs are orthonormal.
    free = lin.eigvecs[:, ~constrained]
    to_free = free @ free.T
    inv_scale = 1.0 / lin.scale
    info_scaled = np.outer(lin.scale, lin.scale) * lin.info / (COV_SCALE * _residual_variance(lin)) \
        + to_free @ (np.outer(inv_scale, inv_scale) * prior_info) @ to_free
    cov = np.outer(lin.scale, lin.scale) * np.linalg.inv(info_scaled)
    rms = float(np.sqrt(np.sum(lin.weight * lin.residual_m**2) / lin.weight.sum()))
    return MatchResult(MatchStatus.OK, u, 0.5 * (cov + cov.T), iterations, inlier_ratio, rms,
                       float(lin.eigvals[0]), int((~constrained).sum()))


#: The tracker also matches from the previous step's motion where it and odometry's differ by
#: more than this in heading (rad): beyond the matcher's basin in a turn.
SECOND_GUESS_MIN_RAD = float(np.radians(3.0))
#: Share of the scan's line points the second guess's match must fit more than the first's to be
#: taken: a clear difference, so a rounding never flips the choice.
SECOND_GUESS_INLIER_MARGIN = 0.05


def fits_better(other: MatchResult, first: MatchResult) -> bool:
    """Is ``other`` the match to take over ``first``: usable, every direction from the scan, and
    fitting at least :data:`SECOND_GUESS_INLIER_MARGIN` more of the points (or ``first`` failed)."""
    if not other.ok or other.unconstrained:
        return False
    return not first.ok or other.inlier_ratio >= first.inlier_ratio + SECOND_GUESS_INLIER_MARGIN


@dataclass(frozen=True, eq=False)
class TrackStep:
    """What :meth:`ScanTracker.step` returns: the motion to use, and how it was found.

    Attributes
    ----------
    increment : ndarray, shape (3,)
        ``(dx_m, dy_m, dtheta_rad)`` from the previous scan's pose to this one,
        in the previous robot frame: the matched one, or the odometry's.
    cov : ndarray, shape (3, 3)
        Its covariance: from the match, or the odometry's.
    match : MatchResult
        The match (its status says whether the increment is matched).
    moved_points : int
        The scan's points left out as moved (``free_space_check``).
    """

    increment: np.ndarray
    cov: np.ndarray
    match: MatchResult
    moved_points: int = 0

    @property
    def matched(self) -> bool:
        return self.match.ok


@dataclass(frozen=True, eq=False)
class _KeptScan:
    pose: np.ndarray  # (3,) in the tracker's frame
    points_xy_m: np.ndarray  # (N, 2) the scan's points in the tracker's frame


class ScanTracker:
    """Laser odometry: each scan matched against the last reference scans (mutable state).

    The tracker keeps its own pose chain in a frame fixed at the first scan; the
    caller only uses the increments between consecutive scans. Each scan is matched
    from the odometry increment; where the previous motion differs from it by more than
    :data:`SECOND_GUESS_MIN_RAD` in heading, also from the previous motion, and the
    clearly better fit is taken (:func:`fits_better`): odometry stamped a scan early
    is a turn's step off at the end of a turn. Deterministic: the same calls give the
    same results.

    Parameters
    ----------
    params : ScanMatchParams

    Attributes
    ----------
    pose : ndarray, shape (3,), or None
        Pose of the last scan in the tracker's frame; None before the first scan.
    reference_scans : list
        The reference scans kept, oldest first; each has ``pose`` (3,) and
        ``points_xy_m`` (N, 2) in the tracker's frame.
    """

    def __init__(self, params: ScanMatchParams) -> None:
        self.params = params
        self.pose: np.ndarray | None = None
        self.reference_scans: list[_KeptScan] = []
        self._dropped = 0  # reference scans forgotten so far: keeps the local map's cache key unique
        self._active: tuple[int, ...] = ()  # cache key of _reference
        self._reference: ReferenceScan | None = None
        # (reference key, match covariance handed out so far, tracker's frame); see _fresh_cov.
        self._budget: tuple[tuple[int, ...], np.ndarray] | None = None
        # What the last reference scans saw empty (tracker's frame), kept past the recent ones: someone
        # overtaking the robot walks on into space that reference scans from before saw empty.
        self._free: deque[FreeSpace] = deque(maxlen=FREE_SPACE_SCANS)
        self._last_increment: np.ndarray | None = None   # the previous step's motion (3,): a second guess

    def step(self, points_xy_m, odom_increment, odom_cov, follows_last: bool = True) -> TrackStep:
        """Match one scan; returns the increment from the previous scan.

        Parameters
        ----------
        points_xy_m : array_like, shape (N, 2)
            This scan's points in its robot frame (m).
        odom_increment : array_like, shape (3,)
            Odometry motion from the previous scan, in its frame (zeros for the first scan).
        odom_cov : array_like, shape (3, 3)
            Its covariance: the fallback's, and the prior of unconstrained directions.
        follows_last : bool
            This scan follows the previous one with none lost between them: only then is the
            previous motion a second guess (across a gap it is a step of another length).
        """
        u0 = np.asarray(odom_increment, dtype=float)
        q0 = np.asarray(odom_cov, dtype=float)
        if u0.shape != (3,) or q0.shape != (3, 3) or not (np.all(np.isfinite(u0)) and np.all(np.isfinite(q0))):
            raise InputError("odom_increment must be (3,) and odom_cov (3, 3), finite")
        returns = _usable(points_xy_m, np.inf)
        pts = _usable(returns, self.params.max_point_range_m)
        if self.pose is None:
            self.pose = np.zeros(3)
            self._add_reference_scan(pts, FreeSpace.of_scan(self.pose, returns, FREE_SPACE_BIN_RAD, FREE_SPACE_SILENT_M))
            return TrackStep(u0.copy(), q0.copy(), MatchResult(MatchStatus.NO_REFERENCE, u0.copy(),
                                                               np.full((3, 3), np.nan)))
        guess = compose(self.pose, u0)
        # The odometry covariance rotated from the previous robot frame into the tracker's frame.
        free = FreeSpace.of_scan(guess, returns, FREE_SPACE_BIN_RAD, FREE_SPACE_SILENT_M)
        moved = self._moved(pts, free)
        pts = pts[~moved]
        prior = rotate_covariance(q0, self.pose[2])
        result = match(self._local_map(), pts, guess, self.params, prior)
        last = self._last_increment if follows_last else None
        if last is not None and abs(wrap_angle(last[2] - u0[2])) > SECOND_GUESS_MIN_RAD:
            # Odometry and the motion so far disagree on the turn (the odometry of a log stamped
            # a scan early, a slipping wheel): matched from a guess that far off, the scan can
            # settle a turn short. The previous motion is the second guess; the fit decides.
            other = match(self._local_map(), pts, compose(self.pose, last), self.params, prior)
            if fits_better(other, result):
                result = other
        increment = relative(self.pose, result.pose) if result.ok else u0.copy()
        if result.ok:
            cov = rotate_covariance(self._fresh_cov(result), -self.pose[2])   # back into the robot frame
        else:
            cov = q0.copy()
            self._budget = None
        self.pose = compose(self.pose, increment)
        self._last_increment = increment
        since = relative(self.reference_scans[-1].pose, self.pose)
        # After a failure the recent reference scans no longer fit this pose: start afresh from this scan.
        if not result.ok or np.hypot(since[0], since[1]) >= REFERENCE_TRANS_M \
                or abs(since[2]) >= REFERENCE_ROT_RAD:
            self._add_reference_scan(pts, replace(free, pose=self.pose.copy()))
        return TrackStep(increment, 0.5 * (cov + cov.T), result, int(np.count_nonzero(moved)))

    def _moved(self, pts: np.ndarray, free: FreeSpace) -> np.ndarray:
        """Which of the scan's points (N, 2; robot frame at ``free.pose``) the last reference scans saw through, bool (N,).

        Also drops from the recent reference scans the points this scan (``free``) sees through.
        """
        if not self.params.free_space_check:
            return np.zeros(pts.shape[0], dtype=bool)
        margins = (FREE_SPACE_MARGIN_M, FREE_SPACE_MARGIN_PER_M, FREE_SPACE_LATERAL_M, FREE_SPACE_BEARING_RAD)
        moved = seen_through(self._free, from_frame(pts, free.pose), *margins)
        # Something walking away hides behind its old place from this side, and matched there
        # it would pull the robot after it; but this scan sees through where it was.
        recent = range(max(0, len(self.reference_scans) - REFERENCES_KEPT), len(self.reference_scans))
        kept = [self.reference_scans[k].points_xy_m for k in recent]
        gone = np.split(free.contains(np.concatenate(kept), *margins), np.cumsum([len(x) for x in kept])[:-1])
        for k, points, out in zip(recent, kept, gone):
            if out.any():
                self.reference_scans[k] = replace(self.reference_scans[k], points_xy_m=points[~out])
                self._reference = None
        return moved

    def _fresh_cov(self, result: MatchResult) -> np.ndarray:
        """Covariance of the error this match adds to the chain, in the tracker's frame.

        The chain's error is the reference's plus the match's relative to it, and
        the caller sums the increments' covariances as a random walk. Matches
        against the same reference are independent draws around it, so the
        match's part is handed out once, as a running maximum (``_budget``), not
        once per scan. A new reference of ``m`` reference scans mostly shares them with
        the last one: replacing one moves their merged points by about one
        reference scan's error over ``m``, so it adds ``cov / m``. A match that took
        directions from the odometry guess (a corridor) accumulates there, so it
        counts whole and starts the budget afresh.
        """
        key = self._active
        if result.unconstrained or self._budget is None:
            fresh = result.cov
        else:
            fresh = _psd_part(result.cov - self._budget[1])
            if self._budget[0] != key:
                fresh = fresh + result.cov / max(len(key), 1)
        self._budget = None if result.unconstrained else \
            (key, result.cov if self._budget is None else self._budget[1] + _psd_part(result.cov - self._budget[1]))
        return fresh

    def skip(self, increment) -> None:
        """A scan that will not be matched (lost): move the pose by ``increment`` (3,), e.g. odometry's."""
        self._budget = None
        self._last_increment = None
        if self.pose is not None:
            self.pose = compose(self.pose, np.asarray(increment, dtype=float))

    def _add_reference_scan(self, pts: np.ndarray, free: FreeSpace) -> None:
        """Keep the scan at :attr:`pose`: its points ``pts`` (N, 2; robot frame) and what it saw empty."""
        self.reference_scans.append(_KeptScan(self.pose.copy(), from_frame(pts, self.pose)))
        self._free.append(free)
        while len(self.reference_scans) > REFERENCES_KEPT:
            del self.reference_scans[0]
            self._dropped += 1

    def _local_map(self) -> ReferenceScan:
        """The recent reference scans as one reference (cached while unchanged)."""
        key = tuple(range(self._dropped, self._dropped + len(self.reference_scans)))
        if key != self._active or self._reference is None:
            self._active = key
            # Normals from the merged points (see ReferenceScan.build): a consistency
            # filter. Thinned to one point per cell first, or k neighbours of a
            # dense stack of scans would span less than the range noise.
            merged = np.vstack([kf.points_xy_m for kf in self.reference_scans])
            self._reference = ReferenceScan.build(thin_points(merged, MAP_CELL_M))
        return self._reference


def _psd_part(mat: np.ndarray) -> np.ndarray:
    """The positive semi-definite part of a symmetric (3, 3) matrix (negative eigenvalues set to 0)."""
    vals, vecs = np.linalg.eigh(0.5 * (mat + mat.T))
    return (vecs * np.clip(vals, 0.0, None)) @ vecs.T
