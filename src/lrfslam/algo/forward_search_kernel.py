"""Forward searching, accelerated: :func:`right_angle_bases` for whole scans at once.

What it computes is stated in plain code by :func:`lrfslam.algo.features.right_angle_bases`:
the base points whose two arms (picks at ``arm_dists_m`` walking outward on each side)
are straight, when checked, and at a right angle within ``corner_tol_deg``, with the
angle between the arm lines. This module returns the same base points and angles, faster;
``tests/unit/test_features_oracle.py`` pins the two together on many scans, and
``extract_features`` uses this one unless asked for the plain one.

How it is fast. A scan is a few hundred points, so the run time is the number of numpy
calls and the size of their arrays, not arithmetic. The search therefore drops base
points as early as it can prove they cannot be corners, and still returns exactly what
picking and fitting every arm of every base point returns:

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
4. the TLS fits of the arms left, one arm per column.

Points are complex numbers ``x + iy``, so one array operation moves both coordinates,
and the lower side of every base point is searched as the upper side of the scan
reversed, so one operation serves both sides. Two numpy habits recur: scalar operands
are read-only 0-d arrays (``lrfslam/algo/scalars.py``), which numpy does not convert on
every call, and reductions are ufunc ``reduce`` calls, which skip the Python wrappers of
``ndarray.any``/``sum``.

The steps are public functions (:func:`doubled`, :func:`screen_tan` and :func:`square`,
:func:`arm_picks`, :func:`arm_fit`) so that ``tests/unit/test_features_kernel.py`` holds
each to a plain walk, with search windows narrow enough to send most picks down the
rare paths.
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from lrfslam.algo.scalars import const

if TYPE_CHECKING:
    from lrfslam.algo.features import FeatureParams

# Columns tried at once by the Euclidean pick search from the arc-length bound
# before searching the rest. Speed only: the screen's nearest pick lies within NEAR
# of its bound for 95 % of base points (a miss passes the screen), every pick within
# FAR for 85-95 % (the rest are searched for); wider windows cost more per element
# than they save.
NEAR = 8
FAR = 16
# Arms (base points times two sides) whose pick thresholds are laid out in full: past
# the screen a scan has 20 or so, without it (the paper mode) 100 or so; a full-size
# comparison is the cheaper one.
_EVERY_ROWS = 256
# Arc-length lower bounds are taken this much short of the distance, so rounding in
# the cumulative sum can never start a Euclidean search past its answer.
_ARC_SLACK_M = 1e-9
# Added to the chord screen's bound so rounding can never drop a true corner.
_SCREEN_SLACK_DEG = 1e-6
_ZERO_F = np.zeros(1)
# Padding after the doubled scan, for search windows that run off its end: points
# so far away that every distance to them passes, yet finite, so chords to them
# multiply without overflow or NaN. A pick there lies past every stretch's end.
_FAR_AWAY = 1e150
_HALF = const(0.5)
_MINUS_I = const(-1j)
_RIGHT_DEG = const(90.0)
_INF = const(math.inf)


def right_angle_bases(z: np.ndarray, step_m: np.ndarray, breaks: list[int],
                      params: FeatureParams) -> tuple[list[int], list[float], list[tuple[int, int]]]:
    """Base points whose arms pass the right-angle test (and the straightness check, if on).

    The arguments and the results (columns, angles in degrees, arm ends) are those of
    :func:`lrfslam.algo.features.right_angle_bases`, which documents them.
    """
    m = len(z)
    if m < 2 * len(params.arm_dists_m) + 1:
        return [], [], []
    zz, arc, end = doubled(z, step_m, breaks)
    arms = arm_picks(zz, arc, end, params)
    n = arms.shape[1]
    if not n:
        return [], [], []
    # One arm per column, the lower sides first.
    theta, max_resid = arm_fit(zz[arms.reshape(2 * n, -1).T])
    # The angle between the lines is min(d, 180° - d), d in [0°, 180°] (θ in
    # [-90°, 90°]), so its distance from a right angle is |d - 90°|, exactly.
    d = np.degrees(np.abs(theta[:n] - theta[n:]))
    ok = np.abs(d - _RIGHT_DEG) <= const(params.corner_tol_deg)
    if params.arm_max_resid_m is not None:
        ok &= np.maximum(max_resid[:n], max_resid[n:]) <= const(params.arm_max_resid_m)
    ok = ok.nonzero()[0]
    # Upper-side columns are scan columns; lower-side column c is scan column 2M - 1 - c.
    lower_end, upper_end = arms[:, ok, -1].tolist()
    ends = [(2 * m - 1 - lo, hi) for lo, hi in zip(lower_end, upper_end)]
    return arms[1, ok, 0].tolist(), [min(x, 180.0 - x) for x in d[ok].tolist()], ends


def _reach(z: np.ndarray, col: np.ndarray, start: np.ndarray, stop: np.ndarray, d_m: float, width: int) -> np.ndarray:
    """First column in ``[start, stop]`` at least ``d_m`` from ``z[col]``.

    The columns are tried in a window of ``width`` from ``start``; the pairs not
    settled there get all that is left in a second window.

    Parameters
    ----------
    z : ndarray of complex, shape (K + width - 1,)
        Points, metres, followed by at least ``width - 1`` far-away points (:func:`_tail`).
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
    out = np.where(np.logical_or.reduce(far, axis=1) & (hit <= stop), hit, -1)
    rest = ((out < 0) & (start + width <= stop)).nonzero()[0]
    if len(rest):
        s, e = start[rest] + width, stop[rest]
        cand = np.minimum(s[:, None] + np.arange(int((e - s).max()) + 1), e[:, None])
        far = np.abs(z[cand] - zc[rest]) >= d_m
        out[rest] = np.where(np.logical_or.reduce(far, axis=1), np.minimum(s + far.argmax(axis=1), e), -1)
    return out


def square(c: np.ndarray, tan_tol: float) -> np.ndarray:
    """Chord pairs whose lines may be at a right angle, shape (B,) bool.

    ``c`` (2, B) holds the chords ``x + iy`` of both sides; ``tan_tol`` is
    ``tan(tol)`` from :func:`screen_tan`.
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


def doubled(z: np.ndarray, step_m: np.ndarray, breaks: list[int], far: int = FAR):
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
    far : int
        The widest search window :func:`arm_picks` will use on it.

    Returns
    -------
    zz : ndarray of complex, shape (2M + far + 1,)
        The points, then in reverse, then ``far + 1`` points far away (search windows
        may run off the end).
    arc : ndarray, shape (2M,)
        Cumulative arc length along ``zz``, metres.
    end : ndarray of int, shape (2M,)
        Column of the last point of each point's stretch; the seam ends one too.
    """
    last = 2 * len(z) - 1
    zz = np.concatenate((z, z[::-1], _tail(far)))
    arc = np.concatenate((_ZERO_F, step_m, _ZERO_F, step_m[::-1])).cumsum()
    # A scan has a stretch or two (2.4 on average in the simulation): their ends are
    # listed in Python and repeated over their columns. Stretch [s, e] is columns
    # last - e to last - s in the reversed half.
    starts, ends = [0, *(p + 1 for p in breaks)], [*breaks, last // 2]
    sizes = [e - s + 1 for s, e in zip(starts, ends)]
    # The method, not np.repeat: that wrapper converts list arguments on a slow path (7 µs against 1).
    return zz, arc, np.array(ends + [last - s for s in reversed(starts)]).repeat(sizes + sizes[::-1])


def screen_tan(params: FeatureParams) -> float | None:
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
    """:func:`screen_tan` of ``arm_max_resid_m``, ``arm_dists_m[0]`` (m) and ``corner_tol_deg``, memoised."""
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


def arm_picks(zz: np.ndarray, arc: np.ndarray, end: np.ndarray, params: FeatureParams,
              near: int = NEAR, far: int = FAR) -> np.ndarray:
    """Arms of the base points that have both, as columns of the doubled scan.

    Parameters
    ----------
    zz, arc, end
        From :func:`doubled` (M points, with the same or a wider ``far``).
    params : FeatureParams
    near, far : int
        Widths of the screen's and the picks' first search windows, columns: speed
        only, every width gives the same arms.

    Returns
    -------
    ndarray of int, shape (2, B, A + 1)
        Per side (0 = lower beams, in the reversed half) and base point (by scan
        column), the column in ``zz`` of the base point followed by its picks, nearest
        first. Every base point with both arms is there, less those the screen
        (:func:`screen_tan`) proves cannot be corners.
    """
    m = len(arc) // 2
    dists = params.arm_dists_m
    euclid = params.arm_metric == "euclidean"
    tables = _pick_tables(dists, _ARC_SLACK_M if euclid else 0.0, far)
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
    windows = _windows(zz, far + 1)
    tan_tol = screen_tan(params)
    if tan_tol is not None:
        # Stage 1 (the screen): the nearest pick, in a window of near columns from its
        # arc-length bound, where it nearly always is (zz's tail lets the window run
        # off the end). A side without a hit there gets a zero chord, which passes:
        # stage 2 decides it. A hit past the stretch's end is no pick, but then there
        # is no farthest pick either and stage 2 drops the base.
        lb0 = arc.searchsorted(arc[col] + tables.offset_first)
        chords = _windows(zz, near + 1)[lb0[:, None]].view(np.complex128)
        chords -= zb[:, None]
        dist = np.abs(chords)
        # The window's last column is its sentinel: far enough, and a zero chord.
        dist[:, -1] = _INF
        chords[:, -1] = 0.0
        hit = (dist >= tables.first).argmax(axis=1)
        chord = chords.ravel()[np.arange(0, chords.size, near + 1) + hit]
        ok = square(chord.reshape(2, len(base)), tan_tol)
        ok = np.concatenate((ok, ok))
        col, zb = col[ok], zb[ok]
    # Stage 2: every pick, each in a window of far columns from its arc-length bound
    # (the farthest lags its bound most: arc length gathers the most noise there).
    lb = arc.searchsorted(arc[col][:, None] + offsets)  # (2B, A)
    every = tables.every[:len(col)] if len(col) <= _EVERY_ROWS else tables.every[0]
    hit = (np.abs(windows[lb[..., None]].view(np.complex128) - zb[:, None, None]) >= every).argmax(axis=2)
    pick = lb + hit
    got = hit < tables.far
    stop = end[col]
    farthest = pick[:, -1]
    if np.count_nonzero(got) == got.size:
        # Nearly always every pick lies in its window: a base keeps its arms if both
        # farthest picks lie in their stretches.
        inside = farthest <= stop
        arms = np.concatenate((col[:, None], pick), axis=1).reshape(2, len(col) // 2, len(dists) + 1)
        if np.count_nonzero(inside) == inside.size:
            return arms
        inside = inside.reshape(2, -1)
        return arms[:, (inside[0] & inside[1]).nonzero()[0]]
    got[:, -1] &= farthest <= stop
    # The farthest pick must lie in the stretch; where its window found nothing and
    # ended inside the stretch, the rest of the stretch is searched.
    far_lb = lb[:, -1]
    j = ((far_lb + far <= stop) > got[:, -1]).nonzero()[0]
    if len(j):
        farthest[j] = _reach(zz, col[j], far_lb[j] + far, stop[j], dists[-1], far)
        got[j, -1] = farthest[j] >= 0
    has = got[:, -1].reshape(2, -1)
    has = (has[0] & has[1]).nonzero()[0]
    arms = np.concatenate((col[:, None], pick), axis=1).reshape(2, len(col) // 2, len(dists) + 1)[:, has]
    # With the farthest pick every nearer one exists, at or before it (a window that
    # ran past the stretch met it first); the few outside their window are searched
    # for up to it.
    got = got.reshape(2, -1, len(dists))[:, has, :-1]
    if np.count_nonzero(got) != got.size:
        missed, farthest, lb = ~got, arms[..., -1], lb.reshape(2, -1, len(dists))[:, has]
        for a in range(len(dists) - 1):
            j = missed[..., a].nonzero()
            if len(j[0]):
                arms[..., a + 1][j] = _reach(zz, arms[..., 0][j], lb[..., a][j] + far, farthest[j], dists[a], far)
    return arms


@lru_cache(maxsize=8)
def _tail(far: int) -> np.ndarray:
    """``far + 1`` points ``_FAR_AWAY`` off, read-only: the padding after the doubled scan."""
    t = np.full(far + 1, complex(_FAR_AWAY, 0.0))
    t.setflags(write=False)
    return t


@lru_cache(maxsize=8)
def _centring(p: int) -> np.ndarray:
    """``I - 1/p``, shape (p, p), complex, read-only: ``it @ x`` subtracts the mean of each column."""
    c = (np.eye(p) - 1.0 / p).astype(complex)
    c.setflags(write=False)
    return c


def arm_fit(arm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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
    q2 = np.add.reduce(q * q, axis=0)
    theta = _HALF * np.arctan2(q2.imag, q2.real)
    return theta, np.maximum.reduce(np.abs((q * np.exp(_MINUS_I * theta)).imag), axis=0)

