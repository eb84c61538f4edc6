"""Point-to-line ICP, compiled: :func:`line_normals` of a scan, :func:`linearise` at one current pose.

What it computes is what :func:`lrfslam.algo.scan_match.match` needs from one Gauss–Newton
iteration: each current point's nearest reference point within the gate (its pair, if their
normals agree within the angle), the point-to-line residuals, their Cauchy weights, and the
normal equations ``JᵀWJ`` and ``JᵀWr``, and the eigen-decomposition of the information
normalised per unit weight (which directions the scan constrains). ``tests/unit/reference_scan_match.py`` states the same
in NumPy (a k-d tree query and array operations), and :func:`line_normals` what
``ReferenceScan.build`` did with a k-d tree: each point's line fit (PCA) to its ``k`` nearest
neighbours within a radius; ``tests/unit/test_scan_match_kernel.py`` holds both to their NumPy
forms within round-off.

Why compiled. A match is 5-10 iterations over a few hundred points, so in NumPy its time was
some twenty array calls' overhead per iteration, not arithmetic (0.23 ms an iteration, two
thirds of the slam stage's time). Here one call does an iteration: the nearest neighbours
come from a grid over the reference (:func:`grid`, cells as wide as the widest gate, built
once per reference), searched in the 3×3 cells around each moved point; the sums run in the
loop. Sums in another order than BLAS's round the last bits otherwise: the results equal the
NumPy form's within round-off, not bit for bit.

Compiled on first use and cached beside the module (numba's ``cache=True``); the first
process after an install pays the compilation (seconds), the rest load it.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from lrfslam.errors import ConfigError


class Grid(NamedTuple):
    """Reference points bucketed by square cells: point indices of cell ``c`` are
    ``order[start[c]:start[c + 1]]``, cells numbered ``row * cols + col`` from ``origin``."""

    origin: np.ndarray  # (2,) lower-left corner (m)
    cell_m: float
    cols: int
    rows: int
    start: np.ndarray   # (rows * cols + 1,) int64
    order: np.ndarray   # (M,) int64


def grid(points_xy_m: np.ndarray, cell_m: float) -> Grid:
    """The grid of ``points_xy_m`` (M, 2) with cells ``cell_m`` wide (at least the widest gate)."""
    pts = np.ascontiguousarray(points_xy_m, dtype=np.float64).reshape(-1, 2)
    if pts.shape[0] == 0:
        return Grid(np.zeros(2), float(cell_m), 1, 1, np.zeros(2, np.int64), np.zeros(0, np.int64))
    origin = pts.min(axis=0)
    cells = np.floor((pts - origin) / cell_m).astype(np.int64)
    cols, rows = int(cells[:, 0].max()) + 1, int(cells[:, 1].max()) + 1
    flat = cells[:, 1] * cols + cells[:, 0]
    order = np.argsort(flat, kind="stable").astype(np.int64)
    start = np.zeros(rows * cols + 1, np.int64)
    np.cumsum(np.bincount(flat, minlength=rows * cols), out=start[1:])
    return Grid(origin, float(cell_m), cols, rows, start, order)


@njit(cache=True)
def _linearise(ref_pts, ref_nrm, origin, cell_m, cols, rows, start, order,
               cur_pts, cur_nrm, x, y, theta, gate_m, cos_max, robust_scale_m):
    c, s = math.cos(theta), math.sin(theta)
    n = cur_pts.shape[0]
    pairs = np.full(n, -1, np.int64)
    residual = np.empty(n)
    weight = np.empty(n)
    info = np.zeros((3, 3))
    gradient = np.zeros(3)
    gate2 = gate_m * gate_m
    sum_sq_range = 0.0
    k = 0
    for i in range(n):
        px, py = cur_pts[i, 0], cur_pts[i, 1]
        mx, my = c * px - s * py + x, s * px + c * py + y
        fx, fy = math.floor((mx - origin[0]) / cell_m), math.floor((my - origin[1]) / cell_m)
        if not (-2.0 < fx < cols + 1.0 and -2.0 < fy < rows + 1.0):   # no cell of the grid within a cell
            continue
        col, row = int(fx), int(fy)
        best, best_d2 = -1, gate2
        for r in range(max(row - 1, 0), min(row + 2, rows)):
            first, last = r * cols + max(col - 1, 0), r * cols + min(col + 1, cols - 1)
            for q in range(start[first], start[last + 1]):
                j = order[q]
                dx, dy = ref_pts[j, 0] - mx, ref_pts[j, 1] - my
                d2 = dx * dx + dy * dy
                if d2 < best_d2 or (d2 == best_d2 and best >= 0 and j < best):
                    best, best_d2 = j, d2
        if best < 0:
            continue
        nx, ny = ref_nrm[best, 0], ref_nrm[best, 1]
        cnx, cny = c * cur_nrm[i, 0] - s * cur_nrm[i, 1], s * cur_nrm[i, 0] + c * cur_nrm[i, 1]
        if abs(nx * cnx + ny * cny) < cos_max:
            continue
        pairs[i] = best
        r_i = nx * (mx - ref_pts[best, 0]) + ny * (my - ref_pts[best, 1])
        u = r_i / robust_scale_m
        w_i = 1.0 / (1.0 + u * u)
        jac = (nx, ny, nx * (-s * px - c * py) + ny * (c * px - s * py))
        for a in range(3):
            gradient[a] += jac[a] * w_i * r_i
            for b in range(3):
                info[a, b] += jac[a] * w_i * jac[b]
        residual[k], weight[k] = r_i, w_i
        sum_sq_range += px * px + py * py
        k += 1
    lever = math.sqrt(sum_sq_range / k) if k else 1.0
    # Rotation in metres of arc at the rms range, information per unit weight: the
    # eigenvalues are then comparable between scans and directions.
    scale = np.array([1.0, 1.0, 1.0 / max(lever, 1e-9)])
    total = 0.0
    for q in range(k):
        total += weight[q]
    normalised = info * np.outer(scale, scale) / max(total, 1e-300)
    eigvals, eigvecs = np.linalg.eigh(normalised)
    return pairs, residual[:k].copy(), weight[:k].copy(), info, gradient, lever, scale, eigvals, eigvecs


class Linearised(NamedTuple):
    """One iteration's correspondences and normal equations (see the module docstring)."""

    pairs: np.ndarray       # (N,) int64: each current point's reference point, -1 if none
    residual_m: np.ndarray  # (K,) point-to-line residuals of the paired points, in point order
    weight: np.ndarray      # (K,) their Cauchy weights
    info: np.ndarray        # (3, 3) JᵀWJ
    gradient: np.ndarray    # (3,) JᵀWr
    lever_m: float          # rms range of the paired current points (1 if none)
    scale: np.ndarray       # (3,) (1, 1, 1 / lever): the information's normalisation
    eigvals: np.ndarray     # (3,) ascending eigenvalues of the information normalised per unit weight
    eigvecs: np.ndarray     # (3, 3) their eigenvectors (columns), in scaled coordinates

    @property
    def paired(self) -> np.ndarray:
        """(N,) bool: the current point has a correspondence."""
        return self.pairs >= 0


def linearise(ref_pts: np.ndarray, ref_normals: np.ndarray, ref_grid: Grid, cur_pts: np.ndarray,
              cur_normals: np.ndarray, u: np.ndarray, gate_m: float, max_normal_angle_rad: float,
              robust_scale_m: float) -> Linearised:
    """Pairs, residuals, weights and normal equations of the current points moved to pose ``u`` (3,).

    ``ref_pts``, ``ref_normals`` (M, 2) and ``ref_grid`` (:func:`grid` of ``ref_pts``, cells at least
    ``gate_m`` wide); ``cur_pts``, ``cur_normals`` (N, 2) in the current robot frame; a point pairs
    with its nearest reference point closer than ``gate_m`` (m) whose normal is within
    ``max_normal_angle_rad`` of its own (either way round).
    """
    if gate_m > ref_grid.cell_m:
        raise ConfigError(f"gate {gate_m} m wider than the grid's cells ({ref_grid.cell_m} m)")
    g = ref_grid
    return Linearised(*_linearise(ref_pts, ref_normals, g.origin, g.cell_m, g.cols, g.rows, g.start, g.order,
                                  cur_pts, cur_normals, float(u[0]), float(u[1]), float(u[2]), float(gate_m),
                                  math.cos(max_normal_angle_rad), float(robust_scale_m)))


@njit(cache=True)
def _line_normals(pts, origin, cell_m, cols, rows, start, order, k, radius_m, min_neighbours, max_thickness):
    n = pts.shape[0]
    keep = np.zeros(n, np.bool_)
    normals = np.zeros((n, 2))
    radius2 = radius_m * radius_m
    cand = np.empty(n, np.int64)
    cand_d2 = np.empty(n)
    for i in range(n):
        col = math.floor((pts[i, 0] - origin[0]) / cell_m)
        row = math.floor((pts[i, 1] - origin[1]) / cell_m)
        m = 0
        for r in range(max(row - 1, 0), min(row + 2, rows)):
            first, last = r * cols + max(col - 1, 0), r * cols + min(col + 1, cols - 1)
            for q in range(start[first], start[last + 1]):
                j = order[q]
                dx, dy = pts[j, 0] - pts[i, 0], pts[j, 1] - pts[i, 1]
                d2 = dx * dx + dy * dy
                if d2 < radius2:
                    cand[m], cand_d2[m] = j, d2
                    m += 1
        if m < min_neighbours:
            continue
        # The k nearest: by distance, ties to the lower index (the order a stable sort of the indices keeps).
        by_index = np.argsort(cand[:m], kind="mergesort")
        nearest = by_index[np.argsort(cand_d2[:m][by_index], kind="mergesort")][:k]
        count = nearest.size
        mx, my = 0.0, 0.0
        for q in nearest:
            mx += pts[cand[q], 0]
            my += pts[cand[q], 1]
        mx, my = mx / count, my / count
        sxx, sxy, syy = 0.0, 0.0, 0.0
        for q in nearest:
            dx, dy = pts[cand[q], 0] - mx, pts[cand[q], 1] - my
            sxx += dx * dx
            sxy += dx * dy
            syy += dy * dy
        sxx, sxy, syy = sxx / count, sxy / count, syy / count
        # Closed-form eigen-decomposition of the 2×2 scatter [[sxx, sxy], [sxy, syy]].
        half_trace = 0.5 * (sxx + syy)
        disc = math.sqrt(0.25 * (sxx - syy) ** 2 + sxy * sxy)
        major, minor = half_trace + disc, max(half_trace - disc, 0.0)
        if major > 0 and math.sqrt(minor / major) <= max_thickness:
            phi = 0.5 * math.atan2(2.0 * sxy, sxx - syy)   # direction of the major axis
            keep[i] = True
            normals[i, 0], normals[i, 1] = -math.sin(phi), math.cos(phi)
    return keep, normals


def line_normals(points_xy_m: np.ndarray, k: int, radius_m: float, min_neighbours: int,
                 max_thickness: float) -> tuple[np.ndarray, np.ndarray]:
    """Which points (N, 2) lie on a line, (N,) bool, and its unit normal there, (N, 2).

    A point's line is fitted (PCA) to its ``k`` nearest points (itself included) closer than
    ``radius_m``; it needs ``min_neighbours`` of them, and a spread across the line at most
    ``max_thickness`` times the spread along it.
    """
    pts = np.ascontiguousarray(points_xy_m, dtype=np.float64).reshape(-1, 2)
    g = grid(pts, radius_m)
    return _line_normals(pts, g.origin, g.cell_m, g.cols, g.rows, g.start, g.order, int(k), float(radius_m),
                         int(min_neighbours), float(max_thickness))


def warm_up() -> None:
    """Compile both kernels now (or load them from numba's cache), on a few points: what an image
    build runs once so that no service pays the compilation at its first scan."""
    pts = np.array([[0.0, 0.0], [0.1, 0.0], [0.2, 0.0], [0.3, 0.0]])
    normals = np.tile([0.0, 1.0], (4, 1))
    line_normals(pts, 10, 0.3, 3, 0.35)
    linearise(pts, normals, grid(pts, 0.5), pts, normals, np.zeros(3), 0.5, 0.5, 0.03)
