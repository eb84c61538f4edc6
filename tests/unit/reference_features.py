"""Reference (oracle) for :mod:`lrfslam.algo.features`: the previous, slower implementation.

Kept verbatim apart from this docstring and the name of its params class (once
``CornerParams``) so ``test_features_oracle.py`` can check that the
optimised module returns the same features on many random scans. It computes every
arm pick of every base point and fits every arm, with no screening, so it is the
obviously-complete version of forward searching. Do not optimise it.

Original module docstring follows.

Corner features: forward and backward searching (paper §IV).

Forward searching (docs/paper-reading.md, 'Forward searching'): from each base
point, walk outward in scan order on both sides and pick the first point at Euclidean distance ≥ 0.3, 0.6, 0.9 and 1.2 m.
A total-least-squares (TLS) line is fitted to each arm (base point + its picks); the
base point is a corner when the two lines are at a right angle within
``corner_tol_deg``. Points removed by the histogram filter are skipped; an arm fails
when it meets a no-return beam or a gap wider than ``arm_break_gap_m``.

Backward searching (docs/paper-reading.md, 'Backward searching'): along the kept
points in scan order, two successive finite points more than ``jump_m`` apart make the nearer one a feature (an occluding
edge). A finite point next to a no-return beam is a feature only if
``r < max_range_m - jump_m``: then the hidden surface is guaranteed to be more than
``jump_m`` behind it.

Improvements over the paper, each switchable in :class:`FeatureParams`: an arm
straightness check (rejects arms bent round a second corner), non-maximum suppression
(one detection per corner), refinement (refit both walls densely and intersect), arms
that break at 0.5 m gaps, and no jump edges across long stretches of removed points.

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

from dataclasses import dataclass

import numpy as np

from lrfslam.algo.geometry import polar_to_xy
from lrfslam.algo.histogram import valid_returns
from lrfslam.errors import ConfigError

FORWARD = np.int8(0)
BACKWARD = np.int8(1)

_ARM_METRICS = ("euclidean", "arclength")
_INF_EDGE_RULES = ("margin", "any")
# Points scanned in the first window of the Euclidean pick search (then doubled);
# it changes speed only, never results.
_FIRST_WINDOW = 8


@dataclass(frozen=True)
class FeatureParams:
    """Knobs of forward and backward searching (docs/paper-reading.md, 'Parameter defaults').

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


def _tls(x: np.ndarray, y: np.ndarray, w: np.ndarray | None = None, axis: int = -1) -> dict[str, np.ndarray]:
    """Total-least-squares lines, batched, optionally over a subset of the points.

    Parameters
    ----------
    x, y : ndarray, same shape
        Point coordinates in metres; ``axis`` runs over the points of one line.
    w : ndarray of float, optional
        0/1 membership weights, broadcastable to ``x`` (all points when omitted). A
        line needs two members to be defined; callers reject smaller groups by ``n``.
    axis : int
        The points axis. Keep the long batch axis innermost: numpy loops over short
        inner axes slowly.

    Returns
    -------
    dict of ndarray, shapes of ``x`` without ``axis``
        ``cx``, ``cy`` centroid; ``theta`` direction in radians; ``nx``, ``ny`` unit
        normal; ``n`` member count; ``rms`` and ``max_resid`` perpendicular residuals
        in m; ``spread2`` along-line variance in m².
    """
    if w is None:
        w = np.ones(x.shape)
    n = w.sum(axis=axis)
    # Empty groups get a harmless denominator; callers reject them by ``n``.
    nz = np.maximum(n, 1.0)
    cx, cy = (w * x).sum(axis=axis) / nz, (w * y).sum(axis=axis) / nz
    qx, qy = x - np.expand_dims(cx, axis), y - np.expand_dims(cy, axis)
    wqx, wqy = w * qx, w * qy
    sxx, syy, sxy = (wqx * qx).sum(axis=axis), (wqy * qy).sum(axis=axis), (wqx * qy).sum(axis=axis)
    # Principal axis of the 2x2 scatter matrix in closed form.
    theta = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)
    ct, st = np.cos(theta), np.sin(theta)
    resid = wqy * np.expand_dims(ct, axis) - wqx * np.expand_dims(st, axis)
    ss_resid = (resid * resid).sum(axis=axis)
    return {
        "cx": cx, "cy": cy, "theta": theta, "nx": -st, "ny": ct, "n": n,
        "rms": np.sqrt(ss_resid / nz),
        "max_resid": np.abs(resid).max(axis=axis),
        "spread2": (sxx + syy - ss_resid) / nz,
    }


def _line_angle_deg(theta_a: np.ndarray, theta_b: np.ndarray) -> np.ndarray:
    """Angle between two undirected lines, degrees in [0, 90]."""
    d = np.degrees(np.abs(theta_a - theta_b)) % 180.0
    return np.minimum(d, 180.0 - d)


def _first_hits(p: np.ndarray, last: np.ndarray, dists_m: np.ndarray, euclidean: bool) -> np.ndarray:
    """Walking to higher columns, the first point at least each distance from each base.

    Arc length along the polyline is never shorter than the chord, so no point before
    the first one at arc length ``d`` can be ``d`` away: the Euclidean search starts
    there and scans forward in windows that double until every (base, distance) pair
    has its point or has left its stretch.

    Parameters
    ----------
    p : ndarray, shape (M, 2)
        Kept points in scan order, metres.
    last : ndarray of int, shape (M,)
        Column of the last point of each point's stretch.
    dists_m : ndarray, shape (A,)
        Arm distances, increasing, metres.
    euclidean : bool
        Distance from the base point; False measures arc length along the polyline.

    Returns
    -------
    ndarray of int, shape (M, A)
        Column of each pick, -1 where the stretch ends first.
    """
    m, n_arm = len(p), len(dists_m)
    x, y = p[:, 0].copy(), p[:, 1].copy()
    dx, dy = x[1:] - x[:-1], y[1:] - y[:-1]
    arc = np.concatenate(([0.0], np.cumsum(np.sqrt(dx * dx + dy * dy))))
    # Pairs are laid out distance-major, (A, M), so the long axis is the inner one
    # throughout: numpy loops over short inner axes slowly.
    hits = np.searchsorted(arc, (arc + dists_m[:, None]).ravel())
    if euclidean:
        base = np.tile(np.arange(m), n_arm)
        d2 = np.repeat(dists_m * dists_m, m)
        start = hits
        hits = np.full(m * n_arm, -1, dtype=np.intp)
        todo = np.flatnonzero(start <= last[base])
        width = _FIRST_WINDOW
        while len(todo):
            cand = np.minimum(start[todo] + np.arange(width)[:, None], m - 1)  # (W, P)
            b = base[todo]
            ex, ey = x[cand] - x[b], y[cand] - y[b]
            past = ex * ex + ey * ey >= d2[todo]
            t = past.argmax(axis=0)
            got = past[t, np.arange(len(todo))]
            hits[todo[got]] = cand[t[got], np.flatnonzero(got)]
            start[todo] += width
            todo = todo[~got & (start[todo] <= last[b])]
            width *= 2
    hits = hits.reshape(n_arm, m).T.copy()
    hits[hits > last[:, None]] = -1
    return hits


def _arm_picks(p: np.ndarray, first: np.ndarray, last: np.ndarray, params: FeatureParams):
    """Picks of every base point on both sides.

    Parameters
    ----------
    p : ndarray, shape (M, 2)
        Kept points in scan order, metres.
    first, last : ndarray of int, shape (M,)
        Columns of the first and last point of each point's stretch.
    params : FeatureParams

    Returns
    -------
    picks : ndarray of int, shape (M, 2, A)
        Column of each pick (side 0 = lower beams); -1 where not found.
    ok : ndarray of bool, shape (M,)
        Both arms found all their picks.
    """
    m = len(p)
    # The lower side is the higher side of the reversed scan; stacking both halves
    # answers the two sides in one call (stretches never cross the seam).
    both = np.concatenate((p, p[::-1]))
    both_last = np.concatenate((last, 2 * m - 1 - first[::-1]))
    hits = _first_hits(both, both_last, np.asarray(params.arm_dists_m, dtype=float), params.arm_metric == "euclidean")
    hi = hits[:m]
    lo = np.where(hits[m:] < 0, -1, 2 * m - 1 - hits[m:])[::-1]
    picks = np.stack((lo, hi), axis=1)
    return picks, np.all(picks >= 0, axis=(1, 2))


def _suppress(xy: np.ndarray, score: np.ndarray, radius_m: float) -> np.ndarray:
    """Greedy non-maximum suppression; returns indices kept, best (lowest score) first."""
    order = np.argsort(score, kind="stable")
    if radius_m <= 0:
        return order
    chosen: list[int] = []
    for i in order:
        if all((xy[i, 0] - xy[j, 0]) ** 2 + (xy[i, 1] - xy[j, 1]) ** 2 >= radius_m**2 for j in chosen):
            chosen.append(int(i))
    return np.asarray(chosen, dtype=np.intp)


def _wall_members(p: np.ndarray, first: np.ndarray, last: np.ndarray, base: np.ndarray, params: FeatureParams):
    """Points of the two walls leaving each corner candidate, for the refit.

    Walks from the base on each side within its stretch, stops at the first point
    farther than ``refine_rmax_m`` (so a wall is never followed round a second
    corner) and keeps the points at least ``refine_rmin_m`` away.

    Returns
    -------
    ndarray of float, shape (2, C, M)
        0/1 membership weights; side 0 = lower beams.
    """
    m, c = len(p), len(base)
    # Lower side = higher side of the reversed scan; both halves in one pass.
    both = np.concatenate((p, p[::-1]))
    both_last = np.concatenate((last, 2 * m - 1 - first[::-1]))
    start = np.concatenate((base, 2 * m - 1 - base))
    col = np.arange(2 * m)
    d2 = ((both[None, :, :] - both[start, None, :]) ** 2).sum(axis=2)
    ahead = (col[None, :] > start[:, None]) & (col[None, :] <= both_last[start, None])
    beyond = ahead & (d2 > params.refine_rmax_m**2)
    stop = np.where(beyond.any(axis=1), beyond.argmax(axis=1), 2 * m)
    inside = (ahead & (col[None, :] < stop[:, None]) & (d2 >= params.refine_rmin_m**2)).astype(float)
    return np.stack((inside[c:, m:][:, ::-1], inside[:c, :m]))


def _refine(p: np.ndarray, first: np.ndarray, last: np.ndarray, base: np.ndarray, params: FeatureParams):
    """Dense wall refit around corner candidates.

    Parameters
    ----------
    p : ndarray, shape (M, 2)
        Kept points, metres.
    first, last : ndarray of int, shape (M,)
        Columns of the first and last point of each point's stretch.
    base : ndarray of int, shape (C,)
        Columns of the candidates.
    params : FeatureParams

    Returns
    -------
    xy : ndarray, shape (C, 2)
        Intersection of the refitted walls.
    cov : ndarray, shape (C, 2, 2)
    angle_deg : ndarray, shape (C,)
    ok : ndarray of bool, shape (C,)
        Enough points on both walls and the intersection within ``refine_accept_m``.
    """
    w = _wall_members(p, first, last, base, params)
    f = _tls(p[:, 0], p[:, 1], w)  # every field is (2 walls, C)
    (nx1, nx2), (ny1, ny2) = f["nx"], f["ny"]
    c1, c2 = f["nx"] * f["cx"] + f["ny"] * f["cy"]
    det = nx1 * ny2 - ny1 * nx2
    with np.errstate(invalid="ignore", divide="ignore"):
        # Intersection of the walls n_k · p = c_k (Cramer's rule).
        x, y = (c1 * ny2 - c2 * ny1) / det, (nx1 * c2 - nx2 * c1) / det
        ok = np.all(f["n"] >= params.refine_min_points, axis=0) & np.isfinite(x) & np.isfinite(y)
        ok &= (x - p[base, 0]) ** 2 + (y - p[base, 1]) ** 2 <= params.refine_accept_m**2
        sig2 = np.maximum(params.range_sigma_m**2, f["rms"] ** 2)
        # Distance along each wall from its fit centroid to the corner: the lever arm
        # of the wall's direction error.
        t = (x - f["cx"]) * f["ny"] - (y - f["cy"]) * f["nx"]
        v1, v2 = sig2 / f["n"] * (1.0 + t**2 / f["spread2"])
        # cov = A⁻¹ diag(v1, v2) A⁻ᵀ with A = [n1; n2] and A⁻¹ = [[ny2, -ny1], [-nx2, nx1]] / det.
        cov = np.empty((len(base), 2, 2))
        cov[:, 0, 0] = (ny2 * ny2 * v1 + ny1 * ny1 * v2) / det**2
        cov[:, 1, 1] = (nx2 * nx2 * v1 + nx1 * nx1 * v2) / det**2
        cov[:, 0, 1] = cov[:, 1, 0] = -(ny2 * nx2 * v1 + ny1 * nx1 * v2) / det**2
    return np.column_stack((x, y)), cov, _line_angle_deg(f["theta"][0], f["theta"][1]), ok


def _forward(p: np.ndarray, first: np.ndarray, last: np.ndarray, params: FeatureParams):
    """Forward searching on kept points.

    Returns
    -------
    cols : ndarray of int, shape (C,)
        Kept-point column of each corner, increasing.
    xy : ndarray, shape (C, 2)
    cov : ndarray, shape (C, 2, 2)
        NaN where the caller has to fill in the point model.
    angle_deg : ndarray, shape (C,)
    refined : ndarray of bool, shape (C,)
    """
    cols, angle = np.zeros(0, dtype=np.intp), np.zeros(0)
    if len(p) >= 2 * len(params.arm_dists_m) + 1:
        picks, ok = _arm_picks(p, first, last, params)
        base = np.flatnonzero(ok)
        # Each arm is the base point followed by its picks: shape (A + 1, 2 sides, B),
        # the long base axis innermost.
        arm_cols = np.concatenate((np.broadcast_to(base, (1, 2, len(base))), picks[base].transpose(2, 1, 0)))
        fit = _tls(p[arm_cols, 0], p[arm_cols, 1], axis=0)
        angle = _line_angle_deg(fit["theta"][0], fit["theta"][1])
        dev = 90.0 - angle
        cand = dev <= params.corner_tol_deg
        if params.arm_max_resid_m is not None:
            cand &= np.all(fit["max_resid"] <= params.arm_max_resid_m, axis=0)
        keep = np.sort(_suppress(p[base[cand]], dev[cand], params.nms_radius_m))
        cols, angle = base[cand][keep], angle[cand][keep]
    xy = p[cols]
    cov = np.full((len(cols), 2, 2), np.nan)
    refined = np.zeros(len(cols), dtype=bool)
    if params.refine_corner and len(cols):
        rxy, rcov, rangle, refined = _refine(p, first, last, cols, params)
        xy[refined], cov[refined], angle[refined] = rxy[refined], rcov[refined], rangle[refined]
    return cols, xy, cov, angle, refined


def _backward(ranges_m: np.ndarray, valid: np.ndarray, use: np.ndarray, xy: np.ndarray, params: FeatureParams):
    """Beam indices of jump-edge features, sorted, unique."""
    # The sequence seen by backward searching: kept points and no-returns in scan
    # order; points removed by the filter are skipped as if never measured.
    seq = np.flatnonzero(use | ~valid)
    fin = use[seq]
    r = ranges_m[seq]
    a, b = seq[:-1], seq[1:]
    fa, fb = fin[:-1], fin[1:]
    if params.edge_max_removed is None:
        judged = judged_inf = np.ones(len(a), dtype=bool)
    else:
        # A mixed pixel removed between the two sides of a jump must not hide it, but
        # a longer removed stretch (a wall at grazing incidence, a noise cluster) hides
        # what lies between. Next to a no-return, any removed return in between shows
        # that the surface went on, so the edge must be the no-return's neighbour.
        removed_between = b - a - 1
        judged = removed_between <= params.edge_max_removed
        judged_inf = removed_between == 0
    d = xy[b] - xy[a]
    with np.errstate(invalid="ignore"):
        # NaN gaps (a no-return on either side) compare False.
        jump = judged & ((d * d).sum(axis=1) > params.jump_m**2)
    near_is_a = r[:-1] <= r[1:]
    limit = params.max_range_m - params.jump_m if params.inf_edge_rule == "margin" else np.inf
    with np.errstate(invalid="ignore"):
        edge_a = judged_inf & fa & ~fb & (r[:-1] < limit)
        edge_b = judged_inf & fb & ~fa & (r[1:] < limit)
    out = np.concatenate((a[jump & near_is_a], b[jump & ~near_is_a], a[edge_a], b[edge_b]))
    return np.unique(out)


def _point_cov(ranges_m: np.ndarray, bearings_rad: np.ndarray, beam_step_rad: float, range_sigma_m: float) -> np.ndarray:
    """Covariance of features placed on measured points, shape (K, 2, 2), m².

    ``range_sigma_m`` along the beam; across it the uniform spread of one beam step,
    ``r Δθ / √12``.
    """
    c, s = np.cos(bearings_rad), np.sin(bearings_rad)
    var_r = range_sigma_m**2
    var_t = (ranges_m * beam_step_rad) ** 2 / 12.0
    cov = np.empty((len(ranges_m), 2, 2))
    cov[:, 0, 0] = c * c * var_r + s * s * var_t
    cov[:, 1, 1] = s * s * var_r + c * c * var_t
    cov[:, 0, 1] = cov[:, 1, 0] = c * s * (var_r - var_t)
    return cov


def extract_features(ranges_m: np.ndarray, angles_rad: np.ndarray, kept: np.ndarray, params: FeatureParams) -> FeatureSet:
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
    valid = valid_returns(r, params.max_range_m)
    use = valid & kept
    xy_all = polar_to_xy(np.where(valid, r, np.nan), ang)
    idx = np.flatnonzero(use)
    p = xy_all[idx]
    beam_step = float(np.median(np.abs(np.diff(ang)))) if len(ang) > 1 else 0.0

    # Stretches of kept points: a new one starts after a no-return beam or a wide gap.
    n_invalid = np.concatenate(([0], np.cumsum(~valid)))
    step = p[1:] - p[:-1]
    brk = (n_invalid[idx[1:]] != n_invalid[idx[:-1] + 1]) | ((step * step).sum(axis=1) > params.arm_break_gap_m**2)
    ends = np.flatnonzero(np.append(brk, True))
    run = np.concatenate(([0], np.cumsum(brk)))
    first, last = np.concatenate(([0], ends[:-1] + 1))[run], ends[run]

    cols, f_xy, f_cov, f_angle, f_ref = _forward(p, first, last, params)
    f_beam = idx[cols]
    b_beam = _backward(r, valid, use, xy_all, params)
    if params.nms_radius_m > 0 and len(f_beam) and len(b_beam):
        # A convex corner with one wall occluded fires both searches; the forward
        # corner is better localised, so the jump edge gives way.
        d2 = ((xy_all[b_beam][:, None, :] - f_xy[None, :, :]) ** 2).sum(axis=2)
        b_beam = b_beam[np.all(d2 >= params.nms_radius_m**2, axis=1)]

    beam = np.concatenate((f_beam, b_beam))
    xy = np.concatenate((f_xy, xy_all[b_beam]))
    cov = np.concatenate((f_cov, np.full((len(b_beam), 2, 2), np.nan)))
    point_model = ~np.isfinite(cov[:, 0, 0])
    src = beam[point_model]
    cov[point_model] = _point_cov(r[src], ang[src], beam_step, params.range_sigma_m)
    kind = np.concatenate((np.full(len(f_beam), FORWARD), np.full(len(b_beam), BACKWARD))).astype(np.int8)
    angle = np.concatenate((f_angle, np.full(len(b_beam), np.nan)))
    refined = np.concatenate((f_ref, np.zeros(len(b_beam), dtype=bool)))
    order = np.argsort(beam, kind="stable")
    return FeatureSet(kind[order], xy[order], cov[order], beam[order], angle[order], refined[order])
