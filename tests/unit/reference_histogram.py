"""Reference (oracle) for :mod:`lrfslam.algo.histogram` and :mod:`lrfslam.algo.mixed_pixels`.

The previous implementation of ``denoise`` (the linear range-trend mixed-pixel test,
``mixed_model="range"``), kept verbatim apart from this docstring, the inlined
mixed-pixel functions it used and the optional ``mixed_test`` argument of
``denoise``; plus :func:`off_line_slow`, the straight-line test written out point by
point as a line intersection. ``test_denoise_oracle.py`` checks the optimised module
against them on many random scans. Do not optimise this file.

Original module docstring follows.

Angle-histogram noise reduction (paper §III, eqs. (1)–(2)).

The paper converts a scan to Cartesian points (eq. 1), computes the direction of the
segment between consecutive points (eq. 2), builds a histogram of those directions and
keeps the data whose direction bin holds "over 15 percent". Indoor walls are straight,
so wall segments pile up in a few bins while isolated noise points produce segments in
random directions.

Reading used here (docs/paper-reading.md, 'Angle histogram'):

* eq. (2) is an *undirected* line direction: ``atan2(dy, dx) mod period``; the
  histogram is circular, so there is no singularity at ``dy = 0``;
* "over 15 percent" = bin count / number of valid segments > ``keep_frac``;
* a valid segment joins two successive valid points (finite, ``0 < r <= max_range_m``)
  and is not a depth jump (length ``<= jump_m``);
* a point is kept if one of its adjacent segments falls in a passing bin (OR rule),
  which keeps corner points that sit between two wall directions.

Improvements over the literal reading, each switchable on its own through
:class:`DenoiseParams`: folding directions modulo 90° (Manhattan walls share one
bin), wider bins, a sliding window (exactly rotation invariant) and two mixed-pixel
tests (:mod:`lrfslam.algo.mixed_pixels`) run before the histogram.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lrfslam.algo.geometry import polar_to_xy
from lrfslam.errors import ConfigError

_BIN_MODES = ("fixed", "sliding")
_KEEP_RULES = ("or", "and")


@dataclass(frozen=True)
class DenoiseParams:
    """Knobs of the angle-histogram filter (docs/paper-reading.md, 'Parameter defaults').

    Parameters
    ----------
    max_range_m : float
        Ranges beyond this are "no return" (paper: 4.0 m).
    keep_frac : float
        A bin passes when it holds more than this fraction of the valid segments
        (paper: 0.15).
    bin_deg : float
        Bin width in degrees (fixed mode) or full window width (sliding mode). In
        fixed mode ``period_deg / bin_deg`` must be an integer.
    period_deg : float
        Period of the undirected direction: 180 is the paper's ``atan``; 90 folds
        perpendicular walls onto one direction.
    stride : int
        Segments join valid point ``j`` to valid point ``j + stride`` (paper: 1).
        Longer baselines average range noise down.
    bin_mode : str
        ``"fixed"``: bins ``[k w - w/2, k w + w/2)``, so an axis-aligned wall sits in
        the middle of a bin rather than on an edge. ``"sliding"``: a segment's support
        is the number of segments within ``±bin_deg/2`` of its own direction, which
        makes the decision exactly invariant under rotating the scan.
    keep_rule : str
        ``"or"``: keep a point if any adjacent segment passes; ``"and"``: if all do.
    jump_m : float
        Segments longer than this are depth jumps and take no part in the histogram.
    shadow_min_angle_deg : float
        Veiling test: a point whose segments to both neighbouring beams make less than
        this angle with its own beam is removed before the histogram
        (:func:`~lrfslam.algo.mixed_pixels.along_beam`). 0 turns it off.
    mixed_tol_m : float
        Depth-outlier test: a point whose range misses the linear extrapolation from
        both sides by more than this is removed before the histogram
        (:func:`~lrfslam.algo.mixed_pixels.depth_outliers`). 0 turns it off.
    """

    max_range_m: float = 4.0
    keep_frac: float = 0.15
    bin_deg: float = 22.5
    period_deg: float = 90.0
    stride: int = 1
    bin_mode: str = "fixed"
    keep_rule: str = "or"
    jump_m: float = 1.5
    shadow_min_angle_deg: float = 0.0
    mixed_tol_m: float = 0.08

    def __post_init__(self) -> None:
        if not self.max_range_m > 0:
            raise ConfigError(f"max_range_m must be > 0, got {self.max_range_m}")
        if not 0 <= self.keep_frac < 1:
            raise ConfigError(f"keep_frac must be in [0, 1), got {self.keep_frac}")
        if not 0 < self.bin_deg <= self.period_deg:
            raise ConfigError(f"bin_deg must be in (0, period_deg], got {self.bin_deg}")
        if self.period_deg not in (90.0, 180.0):
            raise ConfigError(f"period_deg must be 90 or 180, got {self.period_deg}")
        n_bins = self.period_deg / self.bin_deg
        if abs(n_bins - round(n_bins)) > 1e-9:
            # Both modes report the fixed-bin histogram, so the bins must tile the period.
            raise ConfigError(
                f"period_deg / bin_deg must be an integer, got {self.period_deg}/{self.bin_deg}"
            )
        if not (isinstance(self.stride, int) and self.stride >= 1):
            raise ConfigError(f"stride must be an integer >= 1, got {self.stride!r}")
        if self.bin_mode not in _BIN_MODES:
            raise ConfigError(f"bin_mode must be one of {_BIN_MODES}, got {self.bin_mode!r}")
        if self.keep_rule not in _KEEP_RULES:
            raise ConfigError(f"keep_rule must be one of {_KEEP_RULES}, got {self.keep_rule!r}")
        if not self.jump_m > 0:
            raise ConfigError(f"jump_m must be > 0, got {self.jump_m}")
        if not 0 <= self.shadow_min_angle_deg < 90:
            raise ConfigError(
                f"shadow_min_angle_deg must be in [0, 90), got {self.shadow_min_angle_deg}"
            )
        if not self.mixed_tol_m >= 0:
            raise ConfigError(f"mixed_tol_m must be >= 0, got {self.mixed_tol_m}")

    @property
    def n_bins(self) -> int:
        """Number of fixed bins covering one period."""
        return round(self.period_deg / self.bin_deg)

    @classmethod
    def paper(cls) -> DenoiseParams:
        """The literal reading: 10° fixed bins over 180°, consecutive points, no mixed-pixel tests."""
        return cls(bin_deg=10.0, period_deg=180.0, shadow_min_angle_deg=0.0, mixed_tol_m=0.0)

    @classmethod
    def default(cls) -> DenoiseParams:
        """Measured improvements (docs/features.md): 90° fold, 22.5° bins, depth-outlier test.

        The veiling (shadow-angle) test stays off: it also strips walls seen at grazing
        incidence, which cost 3–4 points of corner recall in simulation, and the
        depth-outlier test already removes the mixed pixels it would.
        """
        return cls()


@dataclass(frozen=True)
class DenoiseResult:
    """Outcome of :func:`denoise` for one scan of N beams.

    Attributes
    ----------
    kept : ndarray of bool, shape (N,)
        Points that survive the filter (always a subset of ``valid``).
    valid : ndarray of bool, shape (N,)
        Beams with a return: finite and ``0 < r <= max_range_m``.
    points_xy : ndarray, shape (N, 2)
        Sensor-frame points in metres; NaN where not ``valid``.
    mixed : ndarray of bool, shape (N,)
        Valid points removed by the mixed-pixel tests before the histogram.
    hist_counts : ndarray of int, shape (n_bins,)
        Number of valid segments per fixed direction bin.
    hist_edges_deg : ndarray, shape (n_bins + 1,)
        Bin edges in degrees, starting at ``-bin_deg / 2``.
    n_segments : int
        Number of valid segments (the denominator of ``keep_frac``).
    """

    kept: np.ndarray
    valid: np.ndarray
    points_xy: np.ndarray
    mixed: np.ndarray
    hist_counts: np.ndarray
    hist_edges_deg: np.ndarray
    n_segments: int


def valid_returns(ranges_m: np.ndarray, max_range_m: float) -> np.ndarray:
    """Beams with a usable return, shape (N,) bool: finite and ``0 < r <= max_range_m``."""
    r = np.asarray(ranges_m, dtype=float)
    with np.errstate(invalid="ignore"):
        # NaN compares False, so NaN and ±inf both end up invalid.
        return (r > 0.0) & (r <= max_range_m)


def _segment_support(angle_deg: np.ndarray, params: DenoiseParams) -> tuple[np.ndarray, np.ndarray]:
    """Per-segment bin count and the fixed-bin histogram.

    Returns
    -------
    support : ndarray of int, shape (S,)
        Number of segments sharing each segment's bin (fixed) or window (sliding).
    counts : ndarray of int, shape (n_bins,)
    """
    w, period, n_bins = params.bin_deg, params.period_deg, params.n_bins
    # Bins start at -w/2 so an axis-aligned wall falls mid-bin; the modulo folds the
    # last half bin (e.g. -0.0° folded to 89.99°) back onto bin 0.
    idx = np.floor((angle_deg + 0.5 * w) / w).astype(np.intp) % n_bins
    counts = np.bincount(idx, minlength=n_bins)
    if params.bin_mode == "fixed":
        return counts[idx], counts
    # Sliding window on the circle: sort once, append a copy shifted by one period
    # so windows that cross 0° count the wrapped segments too.
    srt = np.sort(angle_deg)
    ext = np.concatenate((srt - period, srt, srt + period))
    lo = np.searchsorted(ext, angle_deg - 0.5 * w, side="left")
    hi = np.searchsorted(ext, angle_deg + 0.5 * w, side="right")
    return hi - lo, counts


def denoise(ranges_m: np.ndarray, angles_rad: np.ndarray, params: DenoiseParams, mixed_test=None) -> DenoiseResult:
    """Remove points whose neighbouring segments have a rare direction.

    Parameters
    ----------
    ranges_m : ndarray, shape (N,)
        Ranges in metres; NaN, ±inf, ``<= 0`` or ``> max_range_m`` mean no return.
    angles_rad : ndarray, shape (N,)
        Beam bearings in radians in the sensor frame, increasing.
    params : DenoiseParams

    Returns
    -------
    DenoiseResult
    """
    r = np.asarray(ranges_m, dtype=float)
    a = np.asarray(angles_rad, dtype=float)
    if r.shape != a.shape or r.ndim != 1:
        raise ValueError(f"ranges_m {r.shape} and angles_rad {a.shape} must be equal 1-D shapes")
    valid = valid_returns(r, params.max_range_m)
    xy = polar_to_xy(np.where(valid, r, np.nan), a)
    if mixed_test is None:
        mixed = along_beam(xy, valid, params.shadow_min_angle_deg) | depth_outliers(r, valid, params.mixed_tol_m)
    else:
        mixed = along_beam(xy, valid, params.shadow_min_angle_deg) | mixed_test(r, a, valid, params.mixed_tol_m)
    usable = valid & ~mixed
    n_bins = params.n_bins
    edges = -0.5 * params.bin_deg + params.bin_deg * np.arange(n_bins + 1)

    idx = np.flatnonzero(usable)
    s = params.stride
    kept = np.zeros(len(r), dtype=bool)
    if len(idx) <= s:
        return DenoiseResult(kept, valid, xy, mixed, np.zeros(n_bins, np.intp), edges, 0)

    p = xy[idx]
    step = p[1:] - p[:-1]
    # A strided segment is a jump if any of the consecutive steps it spans is one.
    n_jumps = np.concatenate(([0], np.cumsum((step * step).sum(axis=1) > params.jump_m**2)))
    seg_ok = n_jumps[s:] == n_jumps[:-s]
    d = p[s:] - p[:-s]
    ang = np.degrees(np.arctan2(d[:, 1], d[:, 0])) % params.period_deg
    n_seg = int(seg_ok.sum())
    support = np.zeros(len(d), dtype=np.intp)
    counts = np.zeros(n_bins, dtype=np.intp)
    if n_seg:
        support[seg_ok], counts = _segment_support(ang[seg_ok], params)
    passes = seg_ok & (support > params.keep_frac * n_seg)

    # Segment j joins compressed points j and j + s; gather both sides of each point.
    pad_pass = np.zeros(s, dtype=bool)
    after_pass = np.concatenate((passes, pad_pass))
    before_pass = np.concatenate((pad_pass, passes))
    if params.keep_rule == "or":
        keep_c = after_pass | before_pass
    else:
        after_ok = np.concatenate((seg_ok, pad_pass))
        before_ok = np.concatenate((pad_pass, seg_ok))
        # Missing neighbours (run ends, jumps) do not veto; at least one must pass.
        keep_c = ((after_pass | ~after_ok) & (before_pass | ~before_ok)) & (after_ok | before_ok)
    kept[idx[keep_c]] = True
    return DenoiseResult(kept, valid, xy, mixed, counts, edges, n_seg)


# Mixed-pixel tests of the previous implementation (lrfslam.algo.mixed_pixels).


def along_beam(points_xy: np.ndarray, valid: np.ndarray, min_angle_deg: float) -> np.ndarray:
    """Points whose segments to both neighbouring beams run along their own beam.

    A mixed pixel lies on its beam between the near and the far surface, so both of
    its segments are almost parallel to the beam; a neighbour without a return counts
    as parallel (the far surface may lie beyond the range cut). A surface's edge point
    has one segment along its wall, so it stays. Wall points seen at grazing incidence
    (below ``min_angle_deg``) also go: their range is poorly defined.

    Parameters
    ----------
    points_xy : ndarray, shape (N, 2)
        Sensor-frame points in metres (NaN where not valid).
    valid : ndarray of bool, shape (N,)
    min_angle_deg : float
        Segments closer than this to the point's beam count as "along"; 0 returns an
        all-False mask.

    Returns
    -------
    ndarray of bool, shape (N,)
        Only valid points with at least one valid neighbour can be flagged.
    """
    n = len(valid)
    out = np.zeros(n, dtype=bool)
    if min_angle_deg <= 0 or n < 2:
        return out
    tan_min = np.tan(np.radians(min_angle_deg))
    seg = points_xy[1:] - points_xy[:-1]
    # Pad both ends with a "no neighbour" so every point has a previous and a next.
    no_nb = np.zeros(1, dtype=bool)
    has_prev = np.concatenate((no_nb, valid[:-1]))
    has_next = np.concatenate((valid[1:], no_nb))
    nan_seg = np.full((1, 2), np.nan)
    prev_seg = np.concatenate((nan_seg, seg))
    next_seg = np.concatenate((seg, nan_seg))

    def along(d: np.ndarray) -> np.ndarray:
        # |cross| < tan(min) |dot| compares the angle without normalising lengths.
        cross = np.abs(points_xy[:, 0] * d[:, 1] - points_xy[:, 1] * d[:, 0])
        dot = np.abs(points_xy[:, 0] * d[:, 0] + points_xy[:, 1] * d[:, 1])
        return cross < tan_min * dot

    with np.errstate(invalid="ignore"):
        prev_ok = along(prev_seg) | ~has_prev
        next_ok = along(next_seg) | ~has_next
    return valid & (has_prev | has_next) & prev_ok & next_ok


def depth_outliers(ranges_m: np.ndarray, valid: np.ndarray, tol_m: float) -> np.ndarray:
    """Points whose range fits neither neighbouring surface.

    The range of beam ``i`` is predicted linearly from beams ``i-2, i-1`` and from
    ``i+2, i+1``. A point on a surface matches at least one prediction (corner points
    match both walls, edge points their own surface); a mixed pixel floats between
    surfaces and matches neither. A side without two valid beams cannot vouch for the
    point. Range, not Cartesian, collinearity is used on purpose: down a corridor the
    near surface is often seen at grazing incidence, and a mixed pixel behind its end
    then lies on the extension of its line but not on its range trend. The price is
    that a wall seen below about 10° incidence, where the range curves fast, loses
    points too.

    Parameters
    ----------
    ranges_m : ndarray, shape (N,)
        Ranges in metres.
    valid : ndarray of bool, shape (N,)
    tol_m : float
        Largest range mismatch that still counts as on the surface; 0 returns an
        all-False mask. Keep it well above the noise of the prediction (≈ 2.5 σ).

    Returns
    -------
    ndarray of bool, shape (N,)
    """
    n = len(valid)
    if tol_m <= 0 or n < 3:
        return np.zeros(n, dtype=bool)
    r = np.where(valid, ranges_m, np.nan)
    pad = np.full(2, np.nan)
    from_prev = np.concatenate((pad, 2.0 * r[1:-1] - r[:-2]))
    from_next = np.concatenate((2.0 * r[1:-1] - r[2:], pad))
    with np.errstate(invalid="ignore"):
        # A NaN prediction (a neighbour without return) compares False: no vouching.
        on_prev = np.abs(r - from_prev) <= tol_m
        on_next = np.abs(r - from_next) <= tol_m
    return valid & ~on_prev & ~on_next


def off_line_slow(ranges_m, angles_rad, valid, tol_m):
    """Straight-line mixed-pixel test, one point and one side at a time.

    Point i is vouched for by a side if the line through the points of the two
    beams on that side meets beam i in front of the scanner within ``tol_m`` of its
    range.
    """
    n = len(valid)
    out = np.zeros(n, dtype=bool)
    if tol_m <= 0 or n < 3:
        return out
    pts = [(r * np.cos(a), r * np.sin(a)) if v else None for r, a, v in zip(ranges_m, angles_rad, valid)]
    for i in range(n):
        if not valid[i]:
            continue
        vouched = False
        for j, k in ((i - 2, i - 1), (i + 2, i + 1)):
            if j < 0 or j >= n or not (valid[j] and valid[k]):
                continue
            (px, py), (qx, qy) = pts[j], pts[k]
            dx, dy = qx - px, qy - py
            ux, uy = np.cos(angles_rad[i]), np.sin(angles_rad[i])
            den = ux * dy - uy * dx
            if den == 0.0:
                continue
            r_hit = (px * dy - py * dx) / den
            if r_hit > 0 and abs(ranges_m[i] - r_hit) <= tol_m:
                vouched = True
        out[i] = not vouched
    return out
