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


def _tls(pts: np.ndarray, w: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Total-least-squares lines, batched, optionally over a subset of the points.

    Parameters
    ----------
    pts : ndarray, shape (..., m, 2)
        Points in metres.
    w : ndarray of float, shape (..., m), optional
        0/1 membership weights (all points when omitted). A line needs two members
        to be defined; callers reject smaller groups by ``n``.

    Returns
    -------
    dict of ndarray
        ``centroid`` (..., 2); ``theta`` (...) direction in radians; ``normal`` (..., 2);
        ``n`` (...) member count; ``rms`` and ``max_resid`` (...) perpendicular
        residuals in m; ``spread2`` (...) along-line variance in m².
    """
    if w is None:
        w = np.ones(pts.shape[:-1])
    n = w.sum(axis=-1)
    # Empty groups get a harmless denominator; callers reject them by ``n``.
    nz = np.maximum(n, 1.0)
    c = (w[..., None] * pts).sum(axis=-2) / nz[..., None]
    qx = pts[..., 0] - c[..., None, 0]
    qy = pts[..., 1] - c[..., None, 1]
    sxx = (w * qx * qx).sum(axis=-1)
    syy = (w * qy * qy).sum(axis=-1)
    sxy = (w * qx * qy).sum(axis=-1)
    # Principal axis of the 2x2 scatter matrix in closed form.
    theta = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)
    ct, st = np.cos(theta), np.sin(theta)
    resid = w * (qy * ct[..., None] - qx * st[..., None])
    along2 = (sxx + syy) - (resid * resid).sum(axis=-1)
    return {
        "centroid": c,
        "theta": theta,
        "normal": np.stack((-st, ct), axis=-1),
        "n": n,
        "rms": np.sqrt((resid * resid).sum(axis=-1) / nz),
        "max_resid": np.abs(resid).max(axis=-1),
        "spread2": along2 / nz,
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
    step = p[1:] - p[:-1]
    arc = np.concatenate(([0.0], np.cumsum(np.sqrt((step * step).sum(axis=1)))))
    hits = np.searchsorted(arc, (arc[:, None] + dists_m).ravel())
    if euclidean:
        base = np.repeat(np.arange(m), n_arm)
        d2 = np.tile(dists_m * dists_m, m)
        start = hits
        hits = np.full(m * n_arm, -1, dtype=np.intp)
        todo = np.flatnonzero(start <= last[base])
        width = _FIRST_WINDOW
        while len(todo):
            cand = np.minimum(start[todo, None] + np.arange(width), m - 1)
            b = base[todo]
            dx = p[cand, 0] - p[b, 0, None]
            dy = p[cand, 1] - p[b, 1, None]
            past = dx * dx + dy * dy >= d2[todo, None]
            t = past.argmax(axis=1)
            got = past[np.arange(len(todo)), t]
            hits[todo[got]] = cand[got, t[got]]
            start[todo] += width
            todo = todo[~got & (start[todo] <= last[b])]
            width *= 2
    hits = hits.reshape(m, n_arm)
    hits[hits > last[:, None]] = -1
    return hits


def _arm_picks(p: np.ndarray, first: np.ndarray, last: np.ndarray, params: CornerParams):
    """Picks of every base point on both sides.

    Parameters
    ----------
    p : ndarray, shape (M, 2)
        Kept points in scan order, metres.
    first, last : ndarray of int, shape (M,)
        Columns of the first and last point of each point's stretch.
    params : CornerParams

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


def _wall_members(p: np.ndarray, last: np.ndarray, base: np.ndarray, params: CornerParams) -> np.ndarray:
    """Points of the wall leaving each base towards higher columns, for the refit.

    Walks from the base within its stretch, stops at the first point farther than
    ``refine_rmax_m`` (so the wall is never followed round a second corner) and keeps
    the points at least ``refine_rmin_m`` away.

    Returns
    -------
    ndarray of float, shape (C, M)
        0/1 membership weights.
    """
    col = np.arange(len(p))
    d2 = ((p[None, :, :] - p[base, None, :]) ** 2).sum(axis=2)
    ahead = (col[None, :] > base[:, None]) & (col[None, :] <= last[base, None])
    beyond = ahead & (d2 > params.refine_rmax_m**2)
    stop = np.where(beyond.any(axis=1), beyond.argmax(axis=1), len(p))
    inside = ahead & (col[None, :] < stop[:, None]) & (d2 >= params.refine_rmin_m**2)
    return inside.astype(float)


def _refine(p: np.ndarray, first: np.ndarray, last: np.ndarray, base: np.ndarray, params: CornerParams):
    """Dense wall refit around corner candidates.

    Parameters
    ----------
    p : ndarray, shape (M, 2)
        Kept points, metres.
    first, last : ndarray of int, shape (M,)
        Columns of the first and last point of each point's stretch.
    base : ndarray of int, shape (C,)
        Columns of the candidates.
    params : CornerParams

    Returns
    -------
    xy : ndarray, shape (C, 2)
        Intersection of the refitted walls.
    cov : ndarray, shape (C, 2, 2)
    angle_deg : ndarray, shape (C,)
    ok : ndarray of bool, shape (C,)
        Enough points on both walls and the intersection within ``refine_accept_m``.
    """
    m = len(p)
    w_hi = _wall_members(p, last, base, params)
    w_lo = _wall_members(p[::-1], m - 1 - first[::-1], m - 1 - base, params)[:, ::-1]
    pts = np.broadcast_to(p, (len(base), m, 2))
    a, b = _tls(pts, w_lo), _tls(pts, w_hi)
    enough = (a["n"] >= params.refine_min_points) & (b["n"] >= params.refine_min_points)
    n1, n2 = a["normal"], b["normal"]
    c1 = (n1 * a["centroid"]).sum(axis=1)
    c2 = (n2 * b["centroid"]).sum(axis=1)
    det = n1[:, 0] * n2[:, 1] - n1[:, 1] * n2[:, 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        xy = np.column_stack(((c1 * n2[:, 1] - c2 * n1[:, 1]) / det, (n1[:, 0] * c2 - n2[:, 0] * c1) / det))
        ok = enough & np.all(np.isfinite(xy), axis=1)
        ok &= ((xy - p[base]) ** 2).sum(axis=1) <= params.refine_accept_m**2
        var = []
        for f in (a, b):
            sig2 = np.maximum(params.range_sigma_m**2, f["rms"] ** 2)
            t = (xy[:, 0] - f["centroid"][:, 0]) * np.cos(f["theta"]) + (xy[:, 1] - f["centroid"][:, 1]) * np.sin(
                f["theta"]
            )
            var.append(sig2 / f["n"] * (1.0 + t**2 / f["spread2"]))
        # A⁻¹ for A = [n1; n2] (rows), then cov = A⁻¹ diag(var) A⁻ᵀ.
        ainv = np.stack(
            (np.stack((n2[:, 1], -n1[:, 1]), axis=1), np.stack((-n2[:, 0], n1[:, 0]), axis=1)), axis=1
        ) / det[:, None, None]
        cov = np.einsum("kij,kj,klj->kil", ainv, np.stack(var, axis=1), ainv)
        # Round-off leaves the two off-diagonal terms a few ulps apart.
        cov = 0.5 * (cov + cov.transpose(0, 2, 1))
    return xy, cov, _line_angle_deg(a["theta"], b["theta"]), ok


def _forward(p: np.ndarray, first: np.ndarray, last: np.ndarray, params: CornerParams):
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
    cols = np.zeros(0, dtype=np.intp)
    if len(p) >= 2 * len(params.arm_dists_m) + 1:
        picks, ok = _arm_picks(p, first, last, params)
        base = np.flatnonzero(ok)
        # Each arm is the base point followed by its picks: shape (B, 2, A + 1, 2).
        arm_cols = np.concatenate((np.broadcast_to(base[:, None, None], (len(base), 2, 1)), picks[base]), axis=2)
        fit = _tls(p[arm_cols])
        angle = _line_angle_deg(fit["theta"][:, 0], fit["theta"][:, 1])
        dev = 90.0 - angle
        cand = dev <= params.corner_tol_deg
        if params.arm_max_resid_m is not None:
            cand &= np.all(fit["max_resid"] <= params.arm_max_resid_m, axis=1)
        keep = np.sort(_suppress(p[base[cand]], dev[cand], params.nms_radius_m))
        cols, angle = base[cand][keep], angle[cand][keep]
    xy = p[cols]
    cov = np.full((len(cols), 2, 2), np.nan)
    refined = np.zeros(len(cols), dtype=bool)
    if params.refine_corner and len(cols):
        rxy, rcov, rangle, refined = _refine(p, first, last, cols, params)
        xy[refined], cov[refined], angle[refined] = rxy[refined], rcov[refined], rangle[refined]
    return cols, xy, cov, angle if len(cols) else np.zeros(0), refined


def _backward(ranges_m: np.ndarray, valid: np.ndarray, use: np.ndarray, xy: np.ndarray, params: CornerParams):
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
