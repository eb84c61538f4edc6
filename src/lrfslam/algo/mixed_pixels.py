"""Mixed-pixel ("veiling") tests run before the angle histogram.

Where a beam's footprint straddles a depth edge the scanner returns a range between
the two surfaces: a point floating in empty space on the beam. The angle histogram
is a weak filter for these, because down a corridor they line up with the walls
(notes §5.3), so two local tests remove them first. Both leave the edge points of the
surfaces themselves alone, which backward searching needs.
"""

from __future__ import annotations

import numpy as np


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
