"""Which points earlier scans saw through, compiled: :func:`seen_through` of :mod:`lrfslam.algo.free_space`.

The tracker asks its ten last reference scans about every point of every scan, twice (both
ways). In NumPy that was some thirty array calls over a (10, N) array, each cheap, together
a tenth of the slam stage's time; here one loop asks each point of each space in turn and
stops at the first space that contains it. The definition is the NumPy form's, which
``tests/unit/test_free_space.py`` states point by point; the bearing comes from libm's
``atan2``, so a point within a rounding of a bin's edge may fall in the other bin.

Compiled on first use and cached beside the module (numba's ``cache=True``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True)
def _seen_through(nearest_m, origins, cos_sin, points, bin_rad, margin_m, margin_per_m, lateral_m, bearing_rad,
                  max_spread):
    n_spaces, n_bins = nearest_m.shape
    inside = np.zeros(points.shape[0], dtype=np.bool_)
    for i in range(points.shape[0]):
        for k in range(n_spaces):
            dx, dy = points[i, 0] - origins[k, 0], points[i, 1] - origins[k, 1]
            c, s = cos_sin[k, 0], cos_sin[k, 1]
            x, y = c * dx + s * dy, -s * dx + c * dy
            r = math.hypot(x, y)
            b = min(int((math.atan2(y, x) + math.pi) / bin_rad), n_bins - 1)
            beyond = r + margin_m + margin_per_m * r
            # Most points end where their own bin's beam did: only the rest need their neighbours.
            if not nearest_m[k, b] > beyond:   # NaN (outside the field of view) compares False
                continue
            # One bin more than the margin: a point anywhere in its bin has a whole bin of beams each side.
            tolerance = max(math.ceil((lateral_m / max(r, 1e-9) + bearing_rad) / bin_rad), 1.0)
            spread = int(min(tolerance + 1.0, max_spread))
            clear = True
            for o in range(-spread, spread + 1):
                if not nearest_m[k, (b + o) % n_bins] > beyond:
                    clear = False
                    break
            if clear:
                inside[i] = True
                break
    return inside


def seen_through(nearest_m: np.ndarray, origins_xy_m: np.ndarray, cos_sin: np.ndarray, points_xy_m: np.ndarray,
                 bin_rad: float, margin_m: float, margin_per_m: float, lateral_m: float, bearing_rad: float,
                 max_spread: int) -> np.ndarray:
    """Which points (N, 2; m) any of K free spaces contains, bool (N,).

    ``nearest_m`` (K, B) is each space's range seen empty per bin (NaN: unknown), ``origins_xy_m``
    (K, 2) and ``cos_sin`` (K, 2) its pose's position and heading; the margins are
    :meth:`lrfslam.algo.free_space.FreeSpace.contains`'s, with at most ``max_spread`` bins each side.
    """
    return _seen_through(np.ascontiguousarray(nearest_m, dtype=np.float64),
                         np.ascontiguousarray(origins_xy_m, dtype=np.float64),
                         np.ascontiguousarray(cos_sin, dtype=np.float64),
                         np.ascontiguousarray(points_xy_m, dtype=np.float64).reshape(-1, 2),
                         float(bin_rad), float(margin_m), float(margin_per_m), float(lateral_m), float(bearing_rad),
                         int(max_spread))


def warm_up() -> None:
    """Compile the kernel now (or load it from numba's cache)."""
    seen_through(np.full((1, 4), 2.0), np.zeros((1, 2)), np.array([[1.0, 0.0]]), np.array([[0.5, 0.0]]),
                 np.pi / 2, 0.1, 0.01, 0.1, 0.01, 3)
