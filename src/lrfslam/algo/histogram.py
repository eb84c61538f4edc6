"""Angle-histogram noise reduction (paper §III, eqs. (1)–(2)).

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
bin), wider bins, a sliding window (exactly rotation invariant) and mixed-pixel
tests (:mod:`lrfslam.algo.mixed_pixels`) run before the histogram.

A scan is a few hundred beams, so the cost is the number of numpy calls: the beam
trigonometry is shared between scans (:func:`~lrfslam.algo.mixed_pixels.beam_tables`),
points are handled as complex numbers ``x + iy`` and the fixed-bin path avoids sorting.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np

from lrfslam.algo.mixed_pixels import (
    along_beam,
    beam_tables,
    depth_outliers,
    line_vouched,
)
from lrfslam.algo.scalars import const
from lrfslam.errors import ConfigError

_BIN_MODES = ("fixed", "sliding")
_KEEP_RULES = ("or", "and")
_MIXED_MODELS = ("line", "range")
_ZERO = const(0.0)
_NAN = const(np.nan)


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
        Mixed-pixel test: a point whose range misses the prediction from both sides
        by more than this is removed before the histogram. 0 turns it off.
    mixed_model : str
        The prediction of that test: ``"line"``, the straight line through the two
        neighbours on that side (:func:`~lrfslam.algo.mixed_pixels.off_line`), or
        ``"range"``, their linear range trend
        (:func:`~lrfslam.algo.mixed_pixels.depth_outliers`).
    """

    max_range_m: float = 4.0
    keep_frac: float = 0.15
    bin_deg: float = 22.5
    period_deg: float = 90.0
    stride: int = 1
    bin_mode: str = "sliding"
    keep_rule: str = "or"
    jump_m: float = 1.5
    shadow_min_angle_deg: float = 0.0
    mixed_tol_m: float = 0.08
    mixed_model: str = "line"

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
        if self.mixed_model not in _MIXED_MODELS:
            raise ConfigError(f"mixed_model must be one of {_MIXED_MODELS}, got {self.mixed_model!r}")

    @property
    def n_bins(self) -> int:
        """Number of fixed bins covering one period."""
        return round(self.period_deg / self.bin_deg)

    @classmethod
    def paper(cls) -> DenoiseParams:
        """The literal reading: 10° fixed bins over 180°, consecutive points, no mixed-pixel tests."""
        return cls(bin_deg=10.0, period_deg=180.0, bin_mode="fixed", shadow_min_angle_deg=0.0, mixed_tol_m=0.0)

    @classmethod
    def default(cls) -> DenoiseParams:
        """Measured improvements (docs/features.md): 90° fold, 22.5° sliding window, straight-line mixed-pixel test.

        The sliding window makes the keep decision exactly invariant under rotating the
        scan; with fixed bins it depends on where the walls' directions fall against the
        bin edges, which in the hallway loop costs about one wall point in a hundred.

        The veiling (shadow-angle) test stays off: it also strips walls seen at grazing
        incidence, which cost 3–4 points of corner recall in simulation, and the
        straight-line test already removes the mixed pixels it would.
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
    segment_dirs_deg : ndarray, shape (n_segments,)
        Directions of the valid segments in degrees, in ``[0, period_deg)``: the
        histogram's data.
    hist_edges_deg : ndarray, shape (n_bins + 1,)
        Bin edges in degrees, starting at ``-bin_deg / 2``.
    n_segments : int
        Number of valid segments (the denominator of ``keep_frac``).
    """

    kept: np.ndarray
    valid: np.ndarray
    points_xy: np.ndarray
    mixed: np.ndarray
    segment_dirs_deg: np.ndarray
    hist_edges_deg: np.ndarray
    n_segments: int

    @cached_property
    def hist_counts(self) -> np.ndarray:
        """Number of valid segments per fixed direction bin, shape (n_bins,) int.

        Computed on first use: the sliding window does not need it, and nothing on the
        per-scan path reads it.
        """
        n_bins = len(self.hist_edges_deg) - 1
        bins = _fixed_bins(self.segment_dirs_deg, self.hist_edges_deg[1] - self.hist_edges_deg[0], n_bins)
        return np.bincount(bins, minlength=n_bins)


def valid_returns(ranges_m: np.ndarray, max_range_m: float) -> np.ndarray:
    """Beams with a usable return, shape (N,) bool: finite and ``0 < r <= max_range_m``."""
    r = np.asarray(ranges_m, dtype=float)
    # NaN compares False (without a warning), so NaN and ±inf both end up invalid.
    return (r > _ZERO) & (r <= const(max_range_m))


@lru_cache(maxsize=8)
def _bin_edges(bin_deg: float, n_bins: int) -> np.ndarray:
    """Fixed bin edges in degrees, shape (n_bins + 1,), read-only (shared by results)."""
    edges = -0.5 * bin_deg + bin_deg * np.arange(n_bins + 1)
    edges.setflags(write=False)
    return edges


@lru_cache(maxsize=4)
def _period_shifts(period_deg: float) -> np.ndarray:
    """``[[-period], [0], [period]]`` in degrees, shape (3, 1), read-only."""
    shifts = np.array(((-period_deg,), (0.0,), (period_deg,)))
    shifts.setflags(write=False)
    return shifts


def _fixed_bins(dirs_deg: np.ndarray, bin_deg: float, n_bins: int) -> np.ndarray:
    """Fixed bin of each direction ``dirs_deg`` (degrees, >= 0), same shape, int.

    Bins start at -w/2 so an axis-aligned wall falls mid-bin; the modulo folds the last
    half bin (e.g. -0.0° folded to 89.99°) back onto bin 0. The directions are >= 0,
    so the integer conversion (truncation) is the floor.
    """
    return ((dirs_deg + 0.5 * bin_deg) / bin_deg).astype(np.intp) % n_bins


def _sliding_support(angle_deg: np.ndarray, members: np.ndarray, params: DenoiseParams) -> np.ndarray:
    """Number of ``members`` within ``±bin_deg/2`` of each direction, shape (S,).

    ``angle_deg`` (S,) holds the segment directions, ``members`` (M,) those that count.
    """
    w, period = params.bin_deg, params.period_deg
    # Sort once and lay copies shifted by one period each way either side, so windows
    # that cross 0° count the wrapped segments too (x + 0.0 is x).
    srt = members.copy()  # np.sort is this behind a Python wrapper
    srt.sort()
    ext = (srt + _period_shifts(period)).ravel()
    half = const(0.5 * w)
    return ext.searchsorted(angle_deg + half, side="right") - ext.searchsorted(angle_deg - half, side="left")


def denoise(ranges_m: np.ndarray, angles_rad: np.ndarray, params: DenoiseParams) -> DenoiseResult:
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
    n = len(r)
    beams = beam_tables(a)
    valid = valid_returns(r, params.max_range_m)
    # Paper eq. (1) with pose 0; NaN where no return. The complex z = x + iy moves
    # both coordinates in one array operation; points_xy is a view of it.
    rv = np.where(valid, r, _NAN)
    z_all = rv * beams.expi
    xy = z_all.view(np.float64).reshape(n, 2)
    if params.mixed_tol_m > 0 and n >= 3:
        if params.mixed_model == "line":
            mixed = valid & ~line_vouched(rv, beams, params.mixed_tol_m)
        else:
            mixed = depth_outliers(rv, valid, params.mixed_tol_m)
    else:
        mixed = np.zeros(n, dtype=bool)
    if params.shadow_min_angle_deg > 0:
        mixed |= along_beam(xy, valid, params.shadow_min_angle_deg)
    w, n_bins = params.bin_deg, params.n_bins
    edges = _bin_edges(w, n_bins)

    # mixed is a subset of valid: valid ^ mixed = valid & ~mixed.
    idx = (valid ^ mixed).nonzero()[0]
    s = params.stride
    kept = np.zeros(n, dtype=bool)
    if len(idx) <= s:
        return DenoiseResult(kept, valid, xy, mixed, np.empty(0), edges, 0)

    z = z_all[idx]
    step = z[1:] - z[:-1]
    # Successive valid points are finite, so "no jump" is the negated comparison.
    seg_len = np.abs(step)
    if s == 1:
        seg_ok, d = seg_len <= const(params.jump_m), step
    else:
        # A strided segment is a jump if any of the consecutive steps it spans is one.
        n_jumps = np.concatenate(([0], (seg_len > params.jump_m).cumsum()))
        seg_ok, d = n_jumps[s:] == n_jumps[:-s], z[s:] - z[:-s]
    ang = np.degrees(np.arctan2(d.imag, d.real)) % const(params.period_deg)
    members = ang[seg_ok]
    n_seg = len(members)
    if params.bin_mode == "fixed":
        # Every segment gets a bin, jumps too (ignored below).
        bins = _fixed_bins(ang, w, n_bins)
        support = np.bincount(bins[seg_ok], minlength=n_bins)[bins]
    else:
        # Supports of jump segments are computed too (fewer calls than masking them
        # out) and ignored below.
        support = _sliding_support(ang, members, params)
    # support > keep_frac * n_seg for an integer support: compared with the floor, the
    # integers never have to be converted to floats.
    passes = seg_ok & (support > int(params.keep_frac * n_seg))

    # Segment j joins compressed points j and j + s; gather both sides of each point.
    if params.keep_rule == "or":
        keep_c = np.zeros(len(idx), dtype=bool)
        keep_c[:-s] = passes
        keep_c[s:] |= passes
    else:
        pad_pass = np.zeros(s, dtype=bool)
        after_pass = np.concatenate((passes, pad_pass))
        before_pass = np.concatenate((pad_pass, passes))
        after_ok = np.concatenate((seg_ok, pad_pass))
        before_ok = np.concatenate((pad_pass, seg_ok))
        # Missing neighbours (run ends, jumps) do not veto; at least one must pass.
        keep_c = ((after_pass | ~after_ok) & (before_pass | ~before_ok)) & (after_ok | before_ok)
    kept[idx] = keep_c
    return DenoiseResult(kept, valid, xy, mixed, members, edges, n_seg)
