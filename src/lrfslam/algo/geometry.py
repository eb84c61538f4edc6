"""Small 2-D geometry helpers shared by the algorithms.

Conventions: robot frame x forward, y left, angles counter-clockwise in radians.
A pose is ``(x_m, y_m, theta_rad)``.
"""

from __future__ import annotations

import numpy as np

from lrfslam.errors import InputError


def wrap_angle(a):
    """Wrap angle(s) to [-pi, pi).

    Parameters
    ----------
    a : float or ndarray
        Angle(s) in radians.

    Returns
    -------
    float or ndarray
        Same shape as ``a``.
    """
    wrapped = (np.asarray(a, dtype=float) + np.pi) % (2.0 * np.pi) - np.pi
    return wrapped if np.ndim(a) else float(wrapped)


def beam_angles(n_beams: int, angle_min_rad: float, angle_increment_rad: float) -> np.ndarray:
    """Bearings of the beams of a scan, shape (n_beams,), radians in the robot frame."""
    return angle_min_rad + angle_increment_rad * np.arange(n_beams, dtype=float)


def polar_to_xy(ranges_m: np.ndarray, angles_rad: np.ndarray) -> np.ndarray:
    """Convert ranges and bearings to points in the sensor frame (paper eq. 1 with pose 0).

    Parameters
    ----------
    ranges_m : ndarray, shape (N,)
        Ranges in metres; non-finite entries give non-finite points.
    angles_rad : ndarray, shape (N,)
        Bearings in radians, 0 = straight ahead, counter-clockwise positive.

    Returns
    -------
    ndarray, shape (N, 2)
        Points ``(x_m, y_m)``.
    """
    r = np.asarray(ranges_m, dtype=float)
    a = np.asarray(angles_rad, dtype=float)
    with np.errstate(invalid="ignore"):
        return np.column_stack((r * np.cos(a), r * np.sin(a)))


def compose(pose, delta):
    """Compose a pose with a relative motion expressed in the pose's frame.

    Parameters
    ----------
    pose, delta : array_like, shape (3,) or (3, N)
        ``(x_m, y_m, theta_rad)``; with N columns, composed column by column (rows of
        poses (N, 3) go in and come out transposed).

    Returns
    -------
    ndarray, shape (3,) or (3, N)
        ``pose ⊕ delta``, heading wrapped.
    """
    x, y, t = pose
    dx, dy, dt = delta
    c, s = np.cos(t), np.sin(t)
    return np.array([x + c * dx - s * dy, y + s * dx + c * dy, wrap_angle(t + dt)])


def relative(pose_a, pose_b):
    """Motion from ``pose_a`` to ``pose_b`` in ``pose_a``'s frame (``pose_a ⊖ pose_b``).

    Parameters
    ----------
    pose_a, pose_b : array_like, shape (3,) or (3, N)
        As for :func:`compose`.

    Returns
    -------
    ndarray, shape (3,) or (3, N)
        ``delta`` such that ``compose(pose_a, delta) == pose_b``.
    """
    xa, ya, ta = pose_a
    xb, yb, tb = pose_b
    c, s = np.cos(ta), np.sin(ta)
    dx, dy = xb - xa, yb - ya
    return np.array([c * dx + s * dy, -s * dx + c * dy, wrap_angle(tb - ta)])


def rotate_covariance(cov, theta):
    """Covariances of points (..., 2, 2) or poses (..., 3, 3) in a frame turned by ``theta`` (rad, scalar or (...)).

    ``R C Rᵀ`` with ``R`` rotating (x, y) and keeping the heading: how a covariance given in a
    pose's frame reads in the frame that pose is in.
    """
    cov = np.asarray(cov, dtype=float)
    n = cov.shape[-1]
    c, s = np.cos(theta), np.sin(theta)
    rot = np.zeros(np.shape(theta) + (n, n))
    rot[..., 0, 0], rot[..., 0, 1], rot[..., 1, 0], rot[..., 1, 1] = c, -s, s, c
    if n == 3:
        rot[..., 2, 2] = 1.0
    return rot @ cov @ np.swapaxes(rot, -1, -2)


def inverse(pose) -> np.ndarray:
    """``⊖pose``: the origin in ``pose``'s frame, (3,) (``compose(pose, inverse(pose))`` is 0)."""
    return relative(pose, np.zeros(3))


def thin_points(points_xy_m: np.ndarray, cell_m: float) -> np.ndarray:
    """Mean of the points (N, 2) in each occupied ``cell_m`` square, (M, 2), in cell order (deterministic).

    Makes a cloud's density even before it is matched or stored: the cost of matching is
    linear in the points, and a wall seen close by would otherwise outweigh one far away.
    """
    points_xy_m = np.asarray(points_xy_m, dtype=float).reshape(-1, 2)
    if points_xy_m.shape[0] == 0:
        return points_xy_m
    cells, index = np.unique(np.floor(points_xy_m / cell_m).astype(np.int64), axis=0, return_inverse=True)
    index = index.reshape(-1)
    sums = np.zeros((cells.shape[0], 2))
    np.add.at(sums, index, points_xy_m)
    return sums / np.bincount(index, minlength=cells.shape[0])[:, None]


def compose_with_covariance(a, cov_a, b, cov_b) -> tuple[np.ndarray, np.ndarray]:
    """``a ⊕ b`` of two independent uncertain relative poses, and its covariance to first order.

    Parameters
    ----------
    a, b : array_like, shape (3,)
        ``(x_m, y_m, theta_rad)``; ``b`` in ``a``'s frame.
    cov_a, cov_b : array_like, shape (3, 3)
        Their covariances (m², m·rad, rad²).

    Returns
    -------
    pose : ndarray, shape (3,)
    cov : ndarray, shape (3, 3)
    """
    t = float(a[2])
    c, s = np.cos(t), np.sin(t)
    bx, by = float(b[0]), float(b[1])
    jac_a = np.array([[1.0, 0.0, -s * bx - c * by], [0.0, 1.0, c * bx - s * by], [0.0, 0.0, 1.0]])
    jac_b = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    cov = jac_a @ np.asarray(cov_a, dtype=float) @ jac_a.T + jac_b @ np.asarray(cov_b, dtype=float) @ jac_b.T
    return compose(a, b), 0.5 * (cov + cov.T)


def inverse_with_covariance(a, cov_a) -> tuple[np.ndarray, np.ndarray]:
    """``⊖a`` (the origin seen from ``a``) and its covariance to first order, (3,) and (3, 3)."""
    x, y, t = (float(v) for v in a)
    c, s = np.cos(t), np.sin(t)
    jac = np.array([[-c, -s, s * x - c * y], [s, -c, c * x + s * y], [0.0, 0.0, -1.0]])
    cov = jac @ np.asarray(cov_a, dtype=float) @ jac.T
    return inverse(a), 0.5 * (cov + cov.T)


def ellipse_axes(cov_m2: np.ndarray, scale2: float) -> tuple[float, float, float]:
    """The ellipse ``x^T cov^-1 x = scale2`` of a 2-D covariance ``cov_m2`` (2, 2), m².

    Returns
    -------
    (major_m, minor_m, yaw_rad)
        Semi-axes ``sqrt(scale2 × eigenvalue)`` (a negative rounding error counts as 0) and the
        direction of the major axis. ``scale2`` is a χ² quantile (2 dof) for a confidence
        ellipse, or k² for the k-sigma one.
    """
    vals, vecs = np.linalg.eigh(0.5 * (cov_m2 + cov_m2.T))
    minor, major = np.sqrt(scale2 * np.maximum(vals, 0.0))
    return float(major), float(minor), float(np.arctan2(vecs[1, 1], vecs[0, 1]))


def to_frame(points_xy: np.ndarray, pose) -> np.ndarray:
    """Express world points in the frame of ``pose``.

    Parameters
    ----------
    points_xy : ndarray, shape (N, 2)
        World coordinates in metres.
    pose : array_like, shape (3,)

    Returns
    -------
    ndarray, shape (N, 2)
    """
    x, y, t = pose
    c, s = np.cos(t), np.sin(t)
    d = np.asarray(points_xy, dtype=float).reshape(-1, 2) - (x, y)
    return np.column_stack((c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]))


def from_frame(points_xy: np.ndarray, pose) -> np.ndarray:
    """Express points given in the frame of ``pose`` in the world frame; shape (N, 2)."""
    x, y, t = pose
    c, s = np.cos(t), np.sin(t)
    p = np.asarray(points_xy, dtype=float).reshape(-1, 2)
    return np.column_stack((x + c * p[:, 0] - s * p[:, 1], y + s * p[:, 0] + c * p[:, 1]))


def anchored_poses(known_ids: np.ndarray, known_poses: np.ndarray, ids: np.ndarray, anchor_ids: np.ndarray,
                   offsets: np.ndarray) -> np.ndarray:
    """Poses given on anchors ((R, 3)): each its anchor's pose composed with its offset.

    An anchor is a known pose or an earlier (smaller id) anchored one: the mapper's retired
    keyframes, each on the older keyframe it was folded into (src/lrfslam/algo/loop_closure/keyframes.py).

    Parameters
    ----------
    known_ids : ndarray of int, shape (K,)
        Ids of the poses known (the mapper's ordinals, or scan stamps in a recording).
    known_poses : ndarray, shape (K, 3)
        Those poses.
    ids, anchor_ids : ndarray of int, shape (R,)
        Each anchored pose's id and its anchor's.
    offsets : ndarray, shape (R, 3)
        Each one's pose in its anchor's frame.

    Raises
    ------
    InputError
        If an anchor is neither known nor anchored with a smaller id.
    """
    known = dict(zip(np.asarray(known_ids, dtype=np.int64).tolist(), np.asarray(known_poses, dtype=float),
                     strict=True))
    out = np.zeros((len(ids), 3))
    for r in np.argsort(ids, kind="stable").tolist():
        anchor = known.get(int(anchor_ids[r]))
        if anchor is None:
            raise InputError(f"pose {int(ids[r])}: its anchor {int(anchor_ids[r])} is not known")
        out[r] = compose(anchor, offsets[r])
        known[int(ids[r])] = out[r]
    return out
