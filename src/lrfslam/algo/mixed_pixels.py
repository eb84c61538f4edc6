"""Mixed-pixel ("veiling") tests run before the angle histogram.

Where a beam's footprint straddles a depth edge the scanner returns a range between
the two surfaces: a point floating in empty space on the beam. The angle histogram
is a weak filter for these, because down a corridor they line up with the walls
(docs/paper-reading.md, 'Mixed pixels'), so local tests remove them first. All
leave the edge points of the surfaces themselves alone, which backward searching
needs.

* :func:`off_line` (the default): a point must lie on the straight line through its
  two neighbours on one side. A flat wall satisfies this exactly at any incidence,
  so the tolerance only has to cover the range noise. :func:`line_vouched` is its
  core, for callers that already hold the ranges with NaN where there is no return.
* :func:`depth_outliers`: the same with a linear range trend instead of the line.
  The trend bends with the wall's range curve, ``r'' Δθ²`` (8 cm at 10° incidence),
  so it both loses grazing wall points and vouches for mixed pixels there.
* :func:`along_beam`: the veiling-angle test of ROS ``ScanShadowsFilter``.

:func:`beam_tables` holds the per-beam trigonometry the filters share.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lrfslam.algo.scalars import const

_ONE = const(1.0)
# A subnormal "range" would overflow 1/r; clamped to this, every product stays finite.
_TINY = const(1e-300)
_NAN2 = np.full(2, np.nan)
_NAN2.setflags(write=False)


@dataclass(frozen=True)
class BeamTables:
    """Trigonometry of one beam layout (N bearings θ), read-only arrays.

    Attributes
    ----------
    cos, sin : ndarray, shape (N,)
        ``cos θ_k``, ``sin θ_k``.
    expi : ndarray of complex, shape (N,)
        ``cos θ_k + i sin θ_k`` (the same values), so a point ``x + iy`` is one product.
    sin1 : ndarray, shape (N - 1,)
        ``sin(θ_{k+1} - θ_k)``.
    sin2 : ndarray, shape (N - 2,)
        ``sin(θ_{k+2} - θ_k)`` (empty for N < 2).
    line : tuple of 3 ndarray, shape (2N,) each
        The sines of :func:`off_line` for the scan followed by its reverse (empty for
        N < 3): element ``u`` serves the point ``u`` of that doubled sequence, with the
        two points before it; the first two elements and the two after the seam, which
        have no such points, are NaN. A tuple,
        not a 2-D array: unpacking an array's rows costs more than the rest of a step.
    step_rad : float
        Median ``|θ_{k+1} - θ_k|``, radians (0 for N < 2).
    """

    cos: np.ndarray
    sin: np.ndarray
    expi: np.ndarray
    sin1: np.ndarray
    sin2: np.ndarray
    line: tuple[np.ndarray, np.ndarray, np.ndarray]
    step_rad: float


def beam_tables(angles_rad: np.ndarray) -> BeamTables:
    """The :class:`BeamTables` of a scan's bearings (radians, shape (N,)).

    A scanner repeats one layout scan after scan, so the tables of the last layout
    seen are kept and reused while the bearings are byte-for-byte the same: a pure
    function of its argument, memoised, which saves a handful of array operations on
    every scan (at 181 beams the count of operations is what costs).
    """
    key = np.ascontiguousarray(angles_rad, dtype=float).tobytes()
    # One (bytes, tables) pair, read and replaced whole, so concurrent callers with
    # different layouts never mix them up. Comparing the bytes is a memcmp; hashing
    # them (as a dict or lru_cache would) costs more than the tables.
    last = _LAST[0]
    if last[0] != key:
        last = (key, _tables(np.frombuffer(key, dtype=float)))
        _LAST[0] = last
    return last[1]


def _tables(a: np.ndarray) -> BeamTables:
    d = np.abs(a[1:] - a[:-1])
    # np.median without its overhead: the middle of the sorted steps.
    srt, k = np.sort(d), len(d) // 2
    step = 0.0 if not len(d) else float(srt[k]) if len(d) % 2 else float((srt[k - 1] + srt[k]) / 2.0)
    cos, sin = np.cos(a), np.sin(a)
    expi = np.empty(len(a), dtype=complex)
    expi.real, expi.imag = cos, sin
    s1, s2 = np.sin(a[1:] - a[:-1]), np.sin(a[2:] - a[:-2])
    if len(a) >= 3:
        # Reversing the scan flips the sign of every sine; off_line's test is written
        # for increasing bearings, so the reversed half reuses the forward values.
        nan2 = np.full(2, np.nan)
        line = (np.concatenate((nan2, s2, nan2, s2[::-1])), np.concatenate((nan2, s1[1:], nan2, s1[:-1][::-1])),
                np.concatenate((nan2, s1[:-1], nan2, s1[1:][::-1])))
    else:
        line = (np.empty(0), np.empty(0), np.empty(0))
    for t in (cos, sin, expi, s1, s2, *line):
        t.setflags(write=False)
    return BeamTables(cos, sin, expi, s1, s2, line, step_rad=step)


# The last layout seen and its tables (see beam_tables).
_LAST: list = [(None, None)]


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


def off_line(ranges_m: np.ndarray, beams: BeamTables, valid: np.ndarray, tol_m: float) -> np.ndarray:
    """Points that lie on neither neighbouring wall line.

    Beam ``i`` is cut with the straight line through the points of beams ``i-2, i-1``
    and with the one through ``i+2, i+1``. A point on a flat surface lies on at least
    one of them (corner points on both walls, edge points on their own surface); a
    mixed pixel floats between surfaces and lies on neither. A side without two valid
    beams cannot vouch for the point.

    The mismatch is measured along the beam, in range: a point's range noise moves it
    along its beam, and at grazing incidence mostly along the wall, so the line through
    two neighbours stays close to the wall and the predicted range scatters by about
    ``√6 σ`` at any incidence. In inverse range a line is ``1/r = A cos θ + B sin θ``,
    so the prediction from beams ``j, k`` at beam ``i`` is exact and needs no points:
    ``sin(θ_k - θ_j) / r_i = sin(θ_i - θ_j) / r_k - sin(θ_i - θ_k) / r_j``.

    Parameters
    ----------
    ranges_m : ndarray, shape (N,)
        Ranges in metres.
    beams : BeamTables
        Of the beam bearings, which must increase by less than π per beam.
    valid : ndarray of bool, shape (N,)
    tol_m : float
        Largest range mismatch that still counts as on the line; 0 returns an
        all-False mask. Keep it well above the noise of the prediction (≈ 2.5 σ).

    Returns
    -------
    ndarray of bool, shape (N,)
    """
    n = len(valid)
    if tol_m <= 0 or n < 3:
        return np.zeros(n, dtype=bool)
    return valid & ~line_vouched(np.where(valid, ranges_m, np.nan), beams, tol_m)


def line_vouched(r: np.ndarray, beams: BeamTables, tol_m: float) -> np.ndarray:
    """Points vouched for by the line through two neighbours on either side, shape (N,) bool.

    ``r`` (N,) holds the ranges, NaN where not valid; ``N >= 3``. The side after each
    point is the side before it in the reversed scan, so both sides take one pass
    over the scan followed by its reverse (``beams.line``).
    """
    n = len(r)
    # Element u + 2 is point u of the scan followed by its reverse; the two before the
    # first have no return.
    rr = np.concatenate((_NAN2, r, r[::-1]))
    s2, s1_before, s1_after = beams.line
    inv = _ONE / np.maximum(rr, _TINY)
    # The prediction is s1 / num, in front of the scanner only if num > 0; testing
    # |r num - s1| <= tol num needs no division and fails for num <= 0. A NaN (a
    # neighbour without return, or the seam) compares False: no vouching.
    num = inv[1:-1] * s2 - inv[:-2] * s1_before
    on = np.abs(rr[2:] * num - s1_after) <= const(tol_m) * num
    # on[u] tests point u of the scan and its reverse against the two before it: the
    # side before in the first half, the side after in the second.
    return on[:n] | on[:n - 1:-1]


def depth_outliers(ranges_m: np.ndarray, valid: np.ndarray, tol_m: float) -> np.ndarray:
    """Points whose range fits neither neighbouring surface's range trend.

    The range of beam ``i`` is predicted linearly from beams ``i-2, i-1`` and from
    ``i+2, i+1``. A point on a surface matches at least one prediction (corner points
    match both walls, edge points their own surface); a mixed pixel floats between
    surfaces and matches neither. A side without two valid beams cannot vouch for the
    point. The trend is exact only for a wall seen head-on: below about 10° incidence
    the range curves fast, the wall loses points and a mixed pixel on it can pass
    (measured in docs/features.md; :func:`off_line` has neither problem).

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
