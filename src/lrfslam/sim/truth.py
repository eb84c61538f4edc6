"""Per-pose ground truth for feature evaluation: which map corners the scanner can see.

Definitions follow docs/paper-reading.md, 'Ground truth on a simulated map': a
corner is *visible* when it is inside the field of view, within range and not occluded; it is
*eligible* for the forward search when, in addition, both of its walls are visible at
every arm distance the search measures.
"""

from __future__ import annotations

import numpy as np

from lrfslam.algo.geometry import to_frame
from lrfslam.sim.lidar import raycast
from lrfslam.sim.world import World

#: A point counts as seen when the beam towards it stops no nearer than this before it.
OCCLUSION_TOL_M = 0.03
#: Arm distances of the paper's forward search, metres.
PAPER_ARM_DISTS_M = (0.3, 0.6, 0.9, 1.2)


def visible_points(
    world: World, pose, points_xy_m, max_range_m: float = 4.0, fov_rad: float = np.pi, movers_m=None
) -> np.ndarray:
    """Which world points the scanner at ``pose`` sees, through glass, not through walls, clutter or movers.

    Parameters
    ----------
    world : World
    pose : array_like, shape (3,)
        Sensor pose ``(x_m, y_m, theta_rad)``.
    points_xy_m : array_like, shape (P, 2)
        World points, metres.
    max_range_m : float
        Farthest visible range, metres.
    fov_rad : float
        Field of view centred on the heading, radians.
    movers_m : ndarray, shape (Q, 4), optional
        Segments of moving obstacles (people) at this instant, metres.

    Returns
    -------
    ndarray of bool, shape (P,)
    """
    local = to_frame(np.asarray(points_xy_m, dtype=float).reshape(-1, 2), pose)
    r = np.hypot(local[:, 0], local[:, 1])
    bearing = np.arctan2(local[:, 1], local[:, 0])
    # The small slack keeps the scanner's extreme beams (exactly ±fov/2) inside the view.
    candidate = (r <= max_range_m) & (np.abs(bearing) <= fov_rad / 2.0 + 1e-9)
    seen = np.zeros(len(local), dtype=bool)
    if candidate.any():
        blockers = world.opaque_segments_m if movers_m is None else np.vstack((world.opaque_segments_m, movers_m))
        first_hit = raycast(blockers, pose, bearing[candidate])
        seen[candidate] = first_hit >= r[candidate] - OCCLUSION_TOL_M
    return seen


def visible_corners(
    world: World, pose, max_range_m: float = 4.0, fov_rad: float = np.pi, movers_m=None
) -> np.ndarray:
    """Indices into ``world.corners()`` of the corners visible from ``pose``; shape (K,), int.

    ``movers_m`` (Q, 4), metres: moving obstacles that may hide corners, as in :func:`visible_points`.
    """
    return np.flatnonzero(visible_points(world, pose, world.corners().xy_m, max_range_m, fov_rad, movers_m))


def eligible_corners(
    world: World,
    pose,
    arm_dists_m=PAPER_ARM_DISTS_M,
    max_range_m: float = 4.0,
    fov_rad: float = np.pi,
) -> np.ndarray:
    """Indices of visible corners whose two walls are both visible at every arm distance.

    Parameters
    ----------
    world : World
    pose : array_like, shape (3,)
    arm_dists_m : sequence of float, non-empty
        Distances from the corner along each wall, metres.
    max_range_m, fov_rad : float
        As for :func:`visible_points`.

    Returns
    -------
    ndarray of int, shape (K,)
        A subset of :func:`visible_corners`; a wall shorter than the longest arm disqualifies its corner.
    """
    corners = world.corners()
    ids = visible_corners(world, pose, max_range_m, fov_rad)
    d = np.asarray(arm_dists_m, dtype=float)
    ids = ids[np.all(corners.wall_lengths_m[ids] >= d.max(), axis=1)]
    if len(ids) == 0:
        return ids
    # Arm points, shape (K, 2 walls, D, 2).
    arms = corners.xy_m[ids, None, None, :] + d[None, None, :, None] * corners.wall_dirs[ids, :, None, :]
    seen = visible_points(world, pose, arms.reshape(-1, 2), max_range_m, fov_rad)
    return ids[seen.reshape(len(ids), -1).all(axis=1)]


def corners_in_robot_frame(world: World, pose, ids) -> np.ndarray:
    """Positions of the given corners in the frame of ``pose``; shape (K, 2), metres."""
    return to_frame(world.corners().xy_m[np.asarray(ids, dtype=int)], pose)


def jump_edge_vertices(world: World) -> np.ndarray:
    """Map vertices where a stationary jump edge can occur: convex corners and free wall ends.

    Returns
    -------
    ndarray, shape (V, 2)
        World positions, metres. A backward-search feature near one of these is
        stationary; elsewhere it is a viewpoint-dependent phantom.
    """
    corners = world.corners()
    return np.vstack((corners.xy_m[corners.kind == "convex"], world.free_endpoints()))
