"""Corner features: forward and backward searching (paper §IV).

Forward searching (notes §5.4): from each base point, walk outward in scan order on
both sides and pick the first point at Euclidean distance ≥ 0.3, 0.6, 0.9 and 1.2 m.
A total-least-squares (TLS) line is fitted to each arm (base point + its picks); the
base point is a corner when the two lines are at a right angle within
``corner_tol_deg``. Points removed by the histogram filter are skipped; an arm fails
when it meets a no-return beam or a gap wider than ``arm_break_gap_m``.

Backward searching (notes §5.5): along the kept points in scan order, two successive
finite points more than ``jump_m`` apart make the nearer one a feature (an occluding
edge). A finite point next to a no-return beam is a feature only if
``r < max_range_m - jump_m``: then the hidden surface is guaranteed to be more than
``jump_m`` behind it.

Improvements over the paper, each switchable in :class:`CornerParams`: an arm
straightness check (rejects arms bent round a second corner), non-maximum suppression
(one detection per corner), refinement (refit both walls densely and intersect), arms
that break at 0.5 m gaps, and no jump edges across long stretches of removed points.

Cost. A scan is a few hundred points, so the run time is the number of numpy calls
and the size of their arrays, not arithmetic. Forward searching therefore drops base
points as early as it can prove they cannot be corners, and still returns exactly
what picking and fitting every arm of every base point returns
(``tests/unit/reference_corners.py`` is that slow version, the oracle of the tests):

1. a base point needs both stretches at least ``arm_dists_m[-1]`` long in arc length
   (arc length bounds the Euclidean distance from above);
2. with the Euclidean metric and the straightness check on, a *screen*: every point of
   an arm lies within ``ρ = arm_max_resid_m`` of its TLS line, so the chord from the
   base point to its nearest pick (at least ``d = arm_dists_m[0]`` long) is within
   ``asin(2ρ / d)`` of that line (19.5° for the defaults), and a corner's two chords
   are at a right angle within ``corner_tol_deg`` plus twice that. On straight walls
   the chords are nearly collinear: about four base points in five drop out here;
3. the picks of the rest, all distances at once; each is found a few columns past its
   arc-length bound, the rare one that is not is searched for up to the stretch end
   (the farthest) or the farthest pick (the others, which lie before it);
4. the TLS fits, suppression and the dense refit, for the few base points left.

Points are complex numbers ``x + iy``, so one array operation moves both coordinates,
and the lower side of every base point is searched as the upper side of the scan
reversed, so one operation serves both sides.

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
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from operator import itemgetter
from typing import NamedTuple

import numpy as np

from lrfslam.algo.histogram import valid_returns
from lrfslam.algo.mixed_pixels import beam_tables
from lrfslam.algo.scalars import const
from lrfslam.errors import ConfigError

FORWARD = np.int8(0)
BACKWARD = np.int8(1)

_ARM_METRICS = ("euclidean", "arclength")
_INF_EDGE_RULES = ("margin", "any")
# Columns tried at once by the Euclidean pick search from the arc-length bound
# before searching the rest. Speed only: the screen's nearest pick lies within _NEAR
# of its bound for 95 % of base points (a miss passes the screen), every pick within
# _FAR for 85-95 % (the rest are searched for); wider windows cost more per element
# than they save.
_NEAR = 8
_FAR = 16
# Arms (base points times two sides) whose pick thresholds are laid out in full: past
# the screen a scan has 20 or so, without it (the paper mode) 100 or so; a full-size
# comparison is the cheaper one.
_EVERY_ROWS = 256
# Arc-length lower bounds are taken this much short of the distance, so rounding in
# the cumulative sum can never start a Euclidean search past its answer.
_ARC_SLACK_M = 1e-9
# Added to the chord screen's bound so rounding can never drop a true corner.
_SCREEN_SLACK_DEG = 1e-6
# ndarray.any/.sum go through Python wrappers; the ufunc reductions do not. "All true" is a
# count_nonzero: over a whole array that needs no iterator.
_ANY = np.logical_or.reduce
_SUM = np.add.reduce
_ZERO_F = np.zeros(1)
# Padding after the doubled scan, for search windows that run off its end: points
# so far away that every distance to them passes, yet finite, so chords to them
# multiply without overflow or NaN. A pick there lies past every stretch's end.
_FAR_AWAY = 1e150
_TAIL = np.full(_FAR + 1, complex(_FAR_AWAY, 0.0))
_HALF = const(0.5)
_MINUS_I = const(-1j)
_RIGHT_DEG = const(90.0)
_INF = const(math.inf)


@dataclass(frozen=True)
class CornerParams:
    """Knobs of forward and backward searching (notes §5.7).

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
    def paper(cls) -> CornerParams:
        """The literal reading: no straightness check, no suppression, no refinement.

        Arms break only at gaps of ``jump_m``, the paper's only discontinuity scale.
        """
        return cls(
            arm_break_gap_m=1.5, arm_max_resid_m=None, nms_radius_m=0.0, refine_corner=False, edge_max_removed=None
        )

    @classmethod
    def default(cls) -> CornerParams:
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
_BEAM = itemgetter(0)


def _reach(z: np.ndarray, col: np.ndarray, start: np.ndarray, stop: np.ndarray, d_m: float, width: int) -> np.ndarray:
    """First column in ``[start, stop]`` at least ``d_m`` from ``z[col]``.

    The columns are tried in a window of ``width`` from ``start``; the pairs not
    settled there get all that is left in a second window.

    Parameters
    ----------
    z : ndarray of complex, shape (K + width - 1,)
        Points, metres, followed by at least ``width - 1`` of ``_TAIL``.
    col, start, stop : ndarray of int, shape (P,)
        Base column and inclusive search range of each pair; ``start <= stop < K``.
    d_m : float
    width : int

    Returns
    -------
    ndarray of int, shape (P,)
        The column, -1 where none in range.
    """
    zc = z[col][:, None]
    # The window may run past the stretch and past the points (into the tail, which
    # is always far): a hit there is past stop and rejected.
    cand = start[:, None] + np.arange(width)
    far = np.abs(z[cand] - zc) >= d_m
    hit = start + far.argmax(axis=1)
    out = np.where(_ANY(far, axis=1) & (hit <= stop), hit, -1)
    rest = ((out < 0) & (start + width <= stop)).nonzero()[0]
    if len(rest):
        s, e = start[rest] + width, stop[rest]
        cand = np.minimum(s[:, None] + np.arange(int((e - s).max()) + 1), e[:, None])
        far = np.abs(z[cand] - zc[rest]) >= d_m
        out[rest] = np.where(_ANY(far, axis=1), np.minimum(s + far.argmax(axis=1), e), -1)
    return out


def _square(c: np.ndarray, tan_tol: float) -> np.ndarray:
    """Chord pairs whose lines may be at a right angle, shape (B,) bool.

    ``c`` (2, B) holds the chords ``x + iy`` of both sides; ``tan_tol`` is
    ``tan(tol)`` from :func:`_screen_tan`.
    """
    # c_lo · conj(c_hi) = dot + i cross, and the angle between the chords' lines is
    # >= 90° - tol  <=>  |dot| <= |cross| tan(tol).
    p = c[0] * c[1].conjugate()
    return np.abs(p.real) <= np.abs(p.imag) * const(tan_tol)


@lru_cache(maxsize=8)
def _window_dtype(width: int, itemsize: int) -> np.dtype:
    """An opaque element of ``width`` items of ``itemsize`` bytes."""
    return np.dtype((np.void, width * itemsize))


def _windows(zz: np.ndarray, width: int) -> np.ndarray:
    """Every run of ``width`` successive elements of ``zz`` as one opaque element, shape (len - width + 1,).

    An overlapping view, no copy. Indexing it copies each window as one block on
    numpy's one-dimensional gather path, a third of the cost of indexing the rows of
    a 2-D strided view (which moves them element by element). Indexed with an
    index array of shape S + (1,), the result viewed as ``zz.dtype`` is the windows,
    shape S + (width,). ``zz`` must be contiguous; the view is only read.
    """
    return np.ndarray((len(zz) - width + 1,), _window_dtype(width, zz.itemsize), zz, 0, (zz.itemsize,))


def _doubled(z: np.ndarray, step_m: np.ndarray, breaks: list[int]):
    """The kept points followed by their reverse, for searching both sides at once.

    The lower side of base j is the upper side of column 2M - 1 - j.

    Parameters
    ----------
    z : ndarray of complex, shape (M,)
        Kept points in scan order, metres.
    step_m : ndarray, shape (M - 1,)
        Distances between successive points, metres.
    breaks : list of int
        Points after which a new stretch starts, increasing.

    Returns
    -------
    zz : ndarray of complex, shape (2M + _FAR + 1,)
        The points, then in reverse, then ``_TAIL`` (search windows may run off the end).
    arc : ndarray, shape (2M,)
        Cumulative arc length along ``zz``, metres.
    end : ndarray of int, shape (2M,)
        Column of the last point of each point's stretch; the seam ends one too.
    """
    last = 2 * len(z) - 1
    zz = np.concatenate((z, z[::-1], _TAIL))
    arc = np.concatenate((_ZERO_F, step_m, _ZERO_F, step_m[::-1])).cumsum()
    # A scan has a stretch or two (2.4 on average in the simulation): their ends are
    # listed in Python and repeated over their columns. Stretch [s, e] is columns
    # last - e to last - s in the reversed half.
    starts, ends = [0, *(p + 1 for p in breaks)], [*breaks, last // 2]
    sizes = [e - s + 1 for s, e in zip(starts, ends)]
    # The method, not np.repeat: that wrapper converts list arguments on a slow path (7 µs against 1).
    return zz, arc, np.array(ends + [last - s for s in reversed(starts)]).repeat(sizes + sizes[::-1])


def _screen_tan(params: CornerParams) -> float | None:
    """Tangent of the screen's tolerance (module docstring, step 2), or None for no screen.

    The screen compares the chords from a base point to its nearest picks, at least
    ``d = arm_dists_m[0]`` long. An arm whose points all lie within
    ``ρ = arm_max_resid_m`` of its TLS line makes an angle of at most ``asin(2ρ / d)``
    with such a chord, so a corner's chords are at a right angle within
    ``corner_tol_deg`` plus twice that. Without the Euclidean metric or the
    straightness check there is no such bound; past 90° it rejects nothing.
    """
    if params.arm_metric != "euclidean" or params.arm_max_resid_m is None:
        return None
    return _screen_tan_of(params.arm_max_resid_m, params.arm_dists_m[0], params.corner_tol_deg)


@lru_cache(maxsize=16)
def _screen_tan_of(rho_m: float, d_m: float, tol_deg: float) -> float | None:
    """:func:`_screen_tan` of ``arm_max_resid_m``, ``arm_dists_m[0]`` (m) and ``corner_tol_deg``, memoised."""
    slope = min(1.0, 2.0 * rho_m / d_m)
    tol = tol_deg + 2.0 * math.degrees(math.asin(slope)) + _SCREEN_SLACK_DEG
    return math.tan(math.radians(tol)) if tol < 90.0 else None


class _PickTables(NamedTuple):
    """Per-parameter constants of the pick search, read-only arrays.

    Each search window ends in a sentinel column that every distance passes: the first
    pass in a window is then at its last column exactly when none of the window's own
    columns is far enough. The screen's sentinel is in its distances (set to inf, so
    the threshold is one 0-d array); the picks' is in their thresholds (-inf), which
    differ from pick to pick anyway. Those thresholds are laid out for ``_EVERY_ROWS``
    arms, so that the comparison with up to that many is elementwise (numpy's plain
    loop) rather than broadcast (its iterator, which costs more than the comparing).
    """

    offsets: np.ndarray       # (A,) d - slack: the arc-length offsets of the lower bounds
    offset_first: np.ndarray  # 0-d, offsets[0]
    offset_last: np.ndarray   # 0-d, offsets[-1]
    first: np.ndarray         # 0-d, d[0]
    every: np.ndarray         # (_EVERY_ROWS, A, far + 1) each d repeated, then the sentinel
    far: np.ndarray           # 0-d, the stage-2 window width


@lru_cache(maxsize=16)
def _pick_tables(dists_m: tuple[float, ...], slack_m: float, far: int) -> _PickTables:
    """The :class:`_PickTables` of arm distances ``dists_m`` (m), ``slack_m`` and the stage-2 window width."""
    offsets = np.array([d - slack_m for d in dists_m])
    first = np.array(dists_m[0])
    every = np.array([[[d] * far + [-np.inf] for d in dists_m]] * _EVERY_ROWS)
    tables = _PickTables(offsets, np.array(offsets[0]), np.array(offsets[-1]), first, every, np.array(far))
    for t in tables:
        t.setflags(write=False)
    return tables


def _arm_picks(zz: np.ndarray, arc: np.ndarray, end: np.ndarray, params: CornerParams) -> np.ndarray:
    """Arms of the base points that have both, as columns of the doubled scan.

    Parameters
    ----------
    zz, arc, end
        From :func:`_doubled` (M points).
    params : CornerParams

    Returns
    -------
    ndarray of int, shape (2, B, A + 1)
        Per side (0 = lower beams, in the reversed half) and base point (by scan
        column), the column in ``zz`` of the base point followed by its picks, nearest
        first. Every base point with both arms is there, less those the screen
        (:func:`_screen_tan`) proves cannot be corners.
    """
    m = len(arc) // 2
    dists = params.arm_dists_m
    euclid = params.arm_metric == "euclidean"
    tables = _pick_tables(dists, _ARC_SLACK_M if euclid else 0.0, _FAR)
    offsets = tables.offsets
    # Arc length is never shorter than the distance from the base: a stretch too
    # short in arc length on either side has no farthest pick (step 1).
    fits = arc[end] >= arc + tables.offset_last
    base = (fits[:m] & fits[:m - 1:-1]).nonzero()[0]
    # Both sides in one flat run, lower then upper: flat arrays keep the gathers and
    # arithmetic below on numpy's one-dimensional paths (no broadcasting iterator).
    col = np.concatenate((2 * m - 1 - base, base))
    if not euclid:
        return np.concatenate((col[:, None], arc.searchsorted(arc[col][:, None] + offsets)), axis=1).reshape(
            2, len(base), len(dists) + 1)
    zb = zz[col]
    windows = _windows(zz, _FAR + 1)
    tan_tol = _screen_tan(params)
    if tan_tol is not None:
        # Stage 1 (the screen): the nearest pick, in a window of _NEAR columns from its
        # arc-length bound, where it nearly always is (zz's tail lets the window run
        # off the end). A side without a hit there gets a zero chord, which passes:
        # stage 2 decides it. A hit past the stretch's end is no pick, but then there
        # is no farthest pick either and stage 2 drops the base.
        lb0 = arc.searchsorted(arc[col] + tables.offset_first)
        chords = _windows(zz, _NEAR + 1)[lb0[:, None]].view(np.complex128)
        chords -= zb[:, None]
        dist = np.abs(chords)
        # The window's last column is its sentinel: far enough, and a zero chord.
        dist[:, -1] = _INF
        chords[:, -1] = 0.0
        hit = (dist >= tables.first).argmax(axis=1)
        chord = chords.ravel()[np.arange(0, chords.size, _NEAR + 1) + hit]
        ok = _square(chord.reshape(2, len(base)), tan_tol)
        ok = np.concatenate((ok, ok))
        col, zb = col[ok], zb[ok]
    # Stage 2: every pick, each in a window of _FAR columns from its arc-length bound
    # (the farthest lags its bound most: arc length gathers the most noise there).
    lb = arc.searchsorted(arc[col][:, None] + offsets)  # (2B, A)
    every = tables.every[:len(col)] if len(col) <= _EVERY_ROWS else tables.every[0]
    hit = (np.abs(windows[lb[..., None]].view(np.complex128) - zb[:, None, None]) >= every).argmax(axis=2)
    pick = lb + hit
    got = hit < tables.far
    stop = end[col]
    far = pick[:, -1]
    if np.count_nonzero(got) == got.size:
        # Nearly always every pick lies in its window: a base keeps its arms if both
        # farthest picks lie in their stretches.
        inside = far <= stop
        arms = np.concatenate((col[:, None], pick), axis=1).reshape(2, len(col) // 2, len(dists) + 1)
        if np.count_nonzero(inside) == inside.size:
            return arms
        inside = inside.reshape(2, -1)
        return arms[:, (inside[0] & inside[1]).nonzero()[0]]
    got[:, -1] &= far <= stop
    # The farthest pick must lie in the stretch; where its window found nothing and
    # ended inside the stretch, the rest of the stretch is searched.
    far_lb = lb[:, -1]
    j = ((far_lb + _FAR <= stop) > got[:, -1]).nonzero()[0]
    if len(j):
        far[j] = _reach(zz, col[j], far_lb[j] + _FAR, stop[j], dists[-1], _FAR)
        got[j, -1] = far[j] >= 0
    has = got[:, -1].reshape(2, -1)
    has = (has[0] & has[1]).nonzero()[0]
    arms = np.concatenate((col[:, None], pick), axis=1).reshape(2, len(col) // 2, len(dists) + 1)[:, has]
    # With the farthest pick every nearer one exists, at or before it (a window that
    # ran past the stretch met it first); the few outside their window are searched
    # for up to it.
    got = got.reshape(2, -1, len(dists))[:, has, :-1]
    if np.count_nonzero(got) != got.size:
        missed, far, lb = ~got, arms[..., -1], lb.reshape(2, -1, len(dists))[:, has]
        for a in range(len(dists) - 1):
            j = missed[..., a].nonzero()
            if len(j[0]):
                arms[..., a + 1][j] = _reach(zz, arms[..., 0][j], lb[..., a][j] + _FAR, far[j], dists[a], _FAR)
    return arms


@lru_cache(maxsize=8)
def _centring(p: int) -> np.ndarray:
    """``I - 1/p``, shape (p, p), complex, read-only: ``it @ x`` subtracts the mean of each column."""
    c = (np.eye(p) - 1.0 / p).astype(complex)
    c.setflags(write=False)
    return c


def _arm_fit(arm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """TLS lines through the points of each arm.

    Parameters
    ----------
    arm : ndarray of complex, shape (P, K)
        Points ``x + iy`` of each of K arms down its column, metres.

    Returns
    -------
    theta : ndarray, shape (K,)
        Line direction, radians.
    max_resid : ndarray, shape (K,)
        Largest perpendicular distance of a point from its line, metres.
    """
    # Arms down the columns: the centring is one matrix product (with I - 1/P), and
    # the sums and the maximum over an arm's points are reductions across P rows,
    # which numpy runs as P long loops rather than K short ones.
    q = _centring(len(arm)) @ arm
    # Σq² = (sxx - syy) + 2i sxy; rotating by -θ leaves the perpendicular offset in
    # the imaginary part.
    q2 = _SUM(q * q, axis=0)
    theta = _HALF * np.arctan2(q2.imag, q2.real)
    return theta, np.maximum.reduce(np.abs((q * np.exp(_MINUS_I * theta)).imag), axis=0)


def _suppress(z: list[complex], score: list[float], radius_m: float) -> list[int]:
    """Greedy non-maximum suppression; indices kept, best (lowest score) first.

    A handful of candidates per scan: plain Python beats array calls here.
    """
    order = sorted(range(len(score)), key=score.__getitem__)  # stable, like argsort(kind="stable")
    if radius_m <= 0:
        return order
    r2 = radius_m * radius_m
    chosen: list[int] = []
    for i in order:
        q = z[i]
        for c in chosen:
            d = q - z[c]
            if d.real * d.real + d.imag * d.imag < r2:
                break
        else:
            chosen.append(i)
    return chosen


def _refine(z: np.ndarray, lo: int, hi: int, j: int, params: CornerParams):
    """Dense wall refit around one corner candidate.

    Each wall is every kept point from the base outwards, within the base's stretch,
    up to the first point farther than ``refine_rmax_m`` (so a wall is never followed
    round a second corner), less those nearer than ``refine_rmin_m``. There are only a
    few candidates per scan, with a few dozen points per wall: the fit works on Python
    scalars.

    Parameters
    ----------
    z : ndarray of complex, shape (M,)
        Kept points, metres.
    lo, hi : int
        Columns of the first and last point that may belong to a wall: the
        candidate's stretch, or less where that is known to reach past
        ``refine_rmax_m`` on both sides.
    j : int
        Column of the candidate.
    params : CornerParams

    Returns
    -------
    tuple or None
        ``(xy, cov, angle_deg)``: the intersection of the two walls as ``x + iy``,
        its covariance as nested lists (m²) and the angle between the walls; None
        if a wall has fewer than ``refine_min_points`` points or the intersection is
        farther than ``refine_accept_m`` from the candidate.
    """
    # Coordinates relative to the candidate keep the moment sums small, so centring
    # them afterwards loses no precision. A wall is a few dozen points: a Python loop
    # over them costs half the numpy calls that would find its ends and sum it.
    zj = z[j]
    e = (z[lo:hi + 1] - zj).tolist()
    k = j - lo
    rmin, rmax = params.refine_rmin_m, params.refine_rmax_m
    # Per wall (below the base, then above): count, Σw, Σw² and Σ|w|².
    sums = []
    for wall in (e[k - 1::-1] if k else (), e[k + 1:]):
        n, s1, s2, sa = 0, 0j, 0j, 0.0
        for w in wall:
            d = abs(w)
            if d > rmax:
                break
            if d >= rmin:
                n += 1
                s1 += w
                s2 += w * w
                sa += d * d
        if n < params.refine_min_points:
            return None
        sums.append((n, s1, s2, sa))
    walls = []
    for n, s1, s2, sa in sums:
        c = s1 / n
        # Σ(w - c)² = (sxx - syy) + 2i sxy and Σ|w - c|² = sxx + syy.
        q = s2 - s1 * c
        tot = sa - (s1 * c.conjugate()).real
        theta = 0.5 * math.atan2(q.imag, q.real)
        # Residual sum of squares about the line = the smaller scatter eigenvalue;
        # rounding may leave it a hair below 0.
        ss = max(0.5 * (tot - abs(q)), 0.0)
        spread2 = (tot - ss) / n
        if not spread2 > 0:
            return None
        nx, ny = -math.sin(theta), math.cos(theta)
        walls.append((n, c, theta, nx, ny, nx * c.real + ny * c.imag, max(params.range_sigma_m**2, ss / n), spread2))
    (n1, c1, th1, nx1, ny1, o1, g1, sp1), (n2, c2, th2, nx2, ny2, o2, g2, sp2) = walls
    det = nx1 * ny2 - ny1 * nx2
    if det == 0.0:
        return None
    # Intersection of the walls n_k · p = o_k (Cramer's rule).
    x, y = (o1 * ny2 - o2 * ny1) / det, (nx1 * o2 - nx2 * o1) / det
    if not x * x + y * y <= params.refine_accept_m**2:
        return None
    # Distance along each wall from its fit centroid to the corner: the lever arm of
    # the wall's direction error.
    t1 = (x - c1.real) * ny1 - (y - c1.imag) * nx1
    t2 = (x - c2.real) * ny2 - (y - c2.imag) * nx2
    v1 = g1 / n1 * (1.0 + t1 * t1 / sp1)
    v2 = g2 / n2 * (1.0 + t2 * t2 / sp2)
    # cov = A⁻¹ diag(v1, v2) A⁻ᵀ with A = [n1; n2] and A⁻¹ = [[ny2, -ny1], [-nx2, nx1]] / det.
    det2 = det * det
    cxy = -(ny2 * nx2 * v1 + ny1 * nx1 * v2) / det2
    cov = [[(ny2 * ny2 * v1 + ny1 * ny1 * v2) / det2, cxy], [cxy, (nx2 * nx2 * v1 + nx1 * nx1 * v2) / det2]]
    d = math.degrees(abs(th1 - th2)) % 180.0
    return complex(zj) + complex(x, y), cov, min(d, 180.0 - d)


@lru_cache(maxsize=16)
def _refit_bound(dists_m: tuple[float, ...], rmax_m: float) -> int | None:
    """Index of the first pick farther than ``rmax_m``, or None."""
    return next((a for a, d in enumerate(dists_m) if d > rmax_m), None)


def _forward(z: np.ndarray, step_m: np.ndarray, breaks: list[int], params: CornerParams):
    """Forward searching on kept points.

    Parameters
    ----------
    z : ndarray of complex, shape (M,)
        Kept points in scan order, metres.
    step_m : ndarray, shape (M - 1,)
        Distances between successive points, metres.
    breaks : list of int
        Points after which a new stretch starts, increasing: an arm never crosses
        from one stretch to the next.
    params : CornerParams

    Returns
    -------
    list of tuple
        One ``(column, xy, cov, angle_deg, refined)`` per corner, by column: ``xy`` is
        ``x + iy``; ``cov`` nested lists (m²), or None where the caller has to fill in
        the point model.
    """
    m = len(z)
    if m < 2 * len(params.arm_dists_m) + 1:
        return []
    zz, arc, end = _doubled(z, step_m, breaks)
    arms = _arm_picks(zz, arc, end, params)
    if not arms.shape[1]:
        return []
    n = arms.shape[1]
    # One arm per column, the lower sides first.
    arm = zz[arms.reshape(2 * n, -1).T]
    theta, max_resid = _arm_fit(arm)
    # The angle between the lines is min(d, 180° - d), d in [0°, 180°] (θ in
    # [-90°, 90°]), so its distance from a right angle is |d - 90°|, exactly.
    d = np.degrees(np.abs(theta[:n] - theta[n:]))
    dev = np.abs(d - _RIGHT_DEG)
    cand = dev <= const(params.corner_tol_deg)
    if params.arm_max_resid_m is not None:
        cand &= np.maximum(max_resid[:n], max_resid[n:]) <= const(params.arm_max_resid_m)
    cand = cand.nonzero()[0]
    if not len(cand):
        return []
    # Upper-side base columns are scan columns; lower-side picks are in the reversed half.
    arms = arms.take(cand, axis=1)
    cols = arms[1, :, 0].tolist()
    d, dev = d[cand].tolist(), dev[cand].tolist()
    # With the Euclidean metric, a pick farther than refine_rmax_m bounds each refit
    # wall (the wall stops at the first point that far out); otherwise the whole
    # stretch is searched.
    bound = _refit_bound(params.arm_dists_m, params.refine_rmax_m)
    if params.arm_metric != "euclidean" or bound is None:
        ends = [(2 * m - 1 - int(end[2 * m - 1 - j]), int(end[j])) for j in cols]
    else:
        lower, upper = arms[:, :, bound + 1].tolist()
        ends = [(2 * m - 1 - lo, hi) for lo, hi in zip(lower, upper)]
    out = []
    for i in sorted(_suppress(arm[0, n:][cand].tolist(), dev, params.nms_radius_m)):
        j = cols[i]
        fit = _refine(z, *ends[i], j, params) if params.refine_corner else None
        if fit is None:
            out.append((j, complex(z[j]), None, min(d[i], 180.0 - d[i]), False))
        else:
            out.append((j, *fit, True))
    return out


def _backward(ranges_m: np.ndarray, valid: np.ndarray, idx: np.ndarray, step_m: np.ndarray,
              n_invalid: np.ndarray, n_no_return: int, breaks: list[int], params: CornerParams) -> list[int]:
    """Jump-edge features, as positions in ``idx``, increasing.

    Backward searching walks the kept points and the no-returns in scan order; points
    removed by the filter are skipped as if never measured. Every place where it can
    find a feature is a stretch break of forward searching, so the walk visits those
    and the two ends of the scan only: a jump between kept points is longer than
    ``jump_m >= arm_break_gap_m``, and between a kept point and its kept neighbour
    across a no-return ``n_invalid`` changes; the no-returns before the first kept
    point and after the last are the scan's ends.

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
    params : CornerParams
    """
    m = len(idx)
    if not m:
        return []
    # The places to look: (p, side) with side ±1 for kept point p beside a no-return
    # on that side, 0 for a jump from kept point p to p + 1.
    spots = [(0, -1)] if n_invalid[0] else []
    for p in breaks:
        if n_invalid[p] == n_invalid[p + 1]:
            spots.append((p, 0))
        else:
            spots += ((p, 1), (p + 1, -1))
    if n_invalid[-1] < n_no_return:
        spots.append((m - 1, 1))
    margin = params.max_range_m - params.jump_m if params.inf_edge_rule == "margin" else math.inf
    max_removed = params.edge_max_removed
    out: list[int] = []
    for p, side in spots:
        i = int(idx[p])
        if side:
            # A finite point beside a no-return is an edge if the hidden surface must
            # lie more than jump_m behind it. Any removed return in between shows that
            # the surface went on, so (with the guard on) the no-return must be its
            # neighbour.
            if (max_removed is not None and valid[i + side]) or not ranges_m[i] < margin:
                continue
        else:
            if not step_m[p] > params.jump_m:
                continue
            k = int(idx[p + 1])
            # A jump, unless a longer removed stretch than a mixed pixel or two (a wall
            # at grazing incidence, a noise cluster) hides what lies between.
            if max_removed is not None and k - i > max_removed + 1:
                continue
            if ranges_m[k] < ranges_m[i]:
                p += 1
        # A point can be the near side of two jumps or a jump and an edge.
        if not out or out[-1] != p:
            out.append(p)
    return out


def _point_cov(range_m: float, bearing_rad: float, beam_step_rad: float, range_sigma_m: float) -> list:
    """Covariance of a feature placed on a measured point, 2×2 nested lists, m².

    ``range_sigma_m`` along the beam; across it the uniform spread of one beam step,
    ``r Δθ / √12``.
    """
    c, s = math.cos(bearing_rad), math.sin(bearing_rad)
    var_r = range_sigma_m**2
    var_t = (range_m * beam_step_rad) ** 2 / 12.0
    cxy = c * s * (var_r - var_t)
    return [[c * c * var_r + s * s * var_t, cxy], [cxy, s * s * var_r + c * c * var_t]]


def extract_features(ranges_m: np.ndarray, angles_rad: np.ndarray, kept: np.ndarray, params: CornerParams) -> FeatureSet:
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
    params : CornerParams

    Returns
    -------
    FeatureSet
        Forward corners and jump edges, in beam order.
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
    feats = [(int(idx[j]), FORWARD, *rest) for j, *rest in _forward(z, step, breaks, params)]
    edges = [(int(idx[p]), complex(z[p]))
             for p in _backward(r, valid, idx, step, n_invalid, len(no_return), breaks, params)]
    if params.nms_radius_m > 0 and feats and edges:
        # A convex corner with one wall occluded fires both searches; the forward
        # corner is better localised, so the jump edge gives way.
        r2 = params.nms_radius_m**2
        corners = [f[2] for f in feats]
        edges = [e for e in edges if all(((q := e[1] - c).real ** 2 + q.imag**2) >= r2 for c in corners)]
    feats += [(i, BACKWARD, zi, None, math.nan, False) for i, zi in edges]
    if not feats:
        return _NO_FEATURES
    # A handful of features per scan: assembled in Python, sorted by beam (corners
    # before edges on the same beam), the numbers of each in one row of one array.
    feats.sort(key=_BEAM)
    rows = []
    for i, _, xy, cov, angle, _ in feats:
        (c00, c01), (c10, c11) = cov or _point_cov(float(r[i]), float(ang[i]), beams.step_rad, params.range_sigma_m)
        rows.append((xy.real, xy.imag, c00, c01, c10, c11, angle))
    values = np.array(rows)
    beam, kind, _, _, _, refined = zip(*feats)
    return FeatureSet(
        kind=np.array(kind, dtype=np.int8),
        xy_m=values[:, :2],
        cov_m2=values[:, 2:6].reshape(-1, 2, 2),
        beam=np.array(beam, dtype=np.intp),
        angle_deg=values[:, 6],
        refined=np.array(refined, dtype=bool),
    )
