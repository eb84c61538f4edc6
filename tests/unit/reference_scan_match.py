"""The NumPy form of one ICP linearisation: the oracle of lrfslam/algo/scan_match_kernel.py.

A k-d tree gives each moved current point its nearest reference point within the gate, and
array operations give the residuals, weights and normal equations, as scan matching did
before the compiled kernel; ``test_scan_match_kernel.py`` holds the kernel to it.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from lrfslam.algo.scan_match_kernel import Linearised


def linearise(ref_pts, ref_normals, cur_pts, cur_normals, u, gate_m, max_normal_angle_rad,
              robust_scale_m) -> Linearised:
    c, s = np.cos(u[2]), np.sin(u[2])
    rot_t = np.array([[c, s], [-s, c]])  # row vectors: p @ R^T = (R p)^T
    moved = cur_pts @ rot_t + u[:2]
    dist, j = cKDTree(ref_pts).query(moved, distance_upper_bound=gate_m)
    paired = np.isfinite(dist)
    cos_angle = np.einsum("ij,ij->i", ref_normals[np.where(paired, j, 0)], cur_normals @ rot_t)
    paired &= np.abs(cos_angle) >= np.cos(max_normal_angle_rad)
    pairs = np.where(paired, j, -1)
    q, nrm = ref_pts[j[paired]], ref_normals[j[paired]]
    p, m = cur_pts[paired], moved[paired]
    r = np.einsum("ij,ij->i", nrm, m - q)
    w = 1.0 / (1.0 + (r / robust_scale_m) ** 2)
    d_theta = nrm[:, 0] * (-s * p[:, 0] - c * p[:, 1]) + nrm[:, 1] * (c * p[:, 0] - s * p[:, 1])
    jac = np.column_stack((nrm, d_theta))
    lever = float(np.sqrt(np.mean(np.sum(p * p, axis=1)))) if p.size else 1.0
    info = jac.T @ (w[:, None] * jac)
    scale = np.array([1.0, 1.0, 1.0 / max(lever, 1e-9)])
    eigvals, eigvecs = np.linalg.eigh(info * np.outer(scale, scale) / max(float(w.sum()), 1e-300))
    return Linearised(pairs, r, w, info, jac.T @ (w * r), lever, scale, eigvals, eigvecs)


def line_normals(pts, k, radius_m, min_neighbours, max_thickness) -> tuple[np.ndarray, np.ndarray]:
    """Which points lie on a line and its normal there: each point's k nearest within the radius
    (a k-d tree), their weighted scatter, and its closed-form eigen-decomposition."""
    dist, idx = cKDTree(pts).query(pts, k=k, distance_upper_bound=radius_m)
    found = np.isfinite(dist)
    count = found.sum(axis=1)
    enough = count >= min_neighbours
    wts = found / np.maximum(count, 1)[:, None]
    nb = pts[np.where(found, idx, 0)]
    d = nb - np.einsum("nk,nkc->nc", wts, nb)[:, None, :]
    sxx, sxy, syy = (np.sum(wts * d[..., a] * d[..., b], axis=1) for a, b in ((0, 0), (0, 1), (1, 1)))
    half_trace = 0.5 * (sxx + syy)
    disc = np.sqrt(0.25 * (sxx - syy) ** 2 + sxy**2)
    lam_major, lam_minor = half_trace + disc, np.maximum(half_trace - disc, 0.0)
    phi = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)
    normals = np.column_stack((-np.sin(phi), np.cos(phi)))
    line = enough & (lam_major > 0)
    line[line] = np.sqrt(lam_minor[line] / lam_major[line]) <= max_thickness
    return line, normals
