"""Simulated SICK LMS200: vectorised ray casting plus the scanner's error model.

The error model follows the LMS200 Technical Description (statistical σ 5 mm typ.,
10 mm resolution, 8 m limit in mm-mode) with a conservative σ of 10 mm by default,
and adds mixed pixels at depth edges (Ye and Borenstein, ICRA 2002). The 4 m range
cut of the paper is applied downstream by the feature extractor, not here.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lrfslam.algo.geometry import beam_angles
from lrfslam.errors import ConfigError
from lrfslam.sim.world import World

# Rays closer than this to parallel with a wall never hit it (|cross(d, e)| / |e|).
_PARALLEL_EPS = 1e-12
# Lets a ray aimed exactly at a shared vertex hit one of the two walls instead of leaking through.
_VERTEX_SLACK = 1e-9


@dataclass(frozen=True)
class LidarModel:
    """Beam layout and error model of the scanner.

    Attributes
    ----------
    n_beams : int
        Beams per scan (181 for the LMS200 at 1° over 180°).
    angle_min_rad : float
        Bearing of beam 0 in the robot frame (x forward, y left), radians.
    angle_increment_rad : float
        Bearing step between beams, radians.
    max_range_m : float
        Farthest return; beyond it the beam reports no return (``inf``).
    range_sigma_m : float
        Standard deviation of the white range noise, metres.
    quantum_m : float
        Range resolution; reported ranges are multiples of it (0 disables).
    mixed_pixel_prob : float
        Probability that a depth edge produces a mixed pixel on its far side.
    mixed_pixel_min_jump_m : float
        Smallest range difference between neighbours that counts as a depth edge.
    dropout_prob : float
        Probability that a beam with a return reports none.
    range_bias_sigma_m : float
        Standard deviation of the systematic range offset (LMS200: ±15 mm typ.). It
        does not average out over scans, so the :class:`~lrfslam.sim.simulator.Simulator`
        draws it once per run and passes it to :func:`simulate_scan`.
    """

    n_beams: int = 181
    angle_min_rad: float = -np.pi / 2
    angle_increment_rad: float = np.radians(1.0)
    max_range_m: float = 8.0
    range_sigma_m: float = 0.01
    quantum_m: float = 0.01
    mixed_pixel_prob: float = 0.3
    mixed_pixel_min_jump_m: float = 0.3
    dropout_prob: float = 0.0
    range_bias_sigma_m: float = 0.0

    def __post_init__(self) -> None:
        if self.n_beams < 2:
            raise ConfigError(f"n_beams must be >= 2, got {self.n_beams}")
        if not self.max_range_m > 0 or min(self.range_sigma_m, self.quantum_m, self.range_bias_sigma_m) < 0:
            raise ConfigError("max_range_m must be > 0; range_sigma_m, quantum_m, range_bias_sigma_m must be >= 0")
        for name in ("mixed_pixel_prob", "dropout_prob"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ConfigError(f"{name} must be in [0, 1], got {getattr(self, name)}")

    def angles_rad(self) -> np.ndarray:
        """Beam bearings in the robot frame, shape (n_beams,), radians."""
        return beam_angles(self.n_beams, self.angle_min_rad, self.angle_increment_rad)


@dataclass(frozen=True, eq=False)
class SimScan:
    """One simulated scan.

    Attributes
    ----------
    ranges_m : ndarray, shape (N,)
        Measured ranges in metres (noise, mixed pixels, dropouts, quantisation);
        ``inf`` where there is no return.
    true_ranges_m : ndarray, shape (N,)
        Exact ranges to the first wall, ``inf`` beyond ``max_range_m`` or where nothing is hit.
    spurious : ndarray of bool, shape (N,)
        Beams replaced by a mixed pixel: points floating in empty space at a depth edge.
    angles_rad : ndarray, shape (N,)
        Beam bearings in the robot frame, radians.
    on_mover : ndarray of bool, shape (N,)
        Beams whose true first hit is a moving obstacle (a walking person), not the map.
    """

    ranges_m: np.ndarray
    true_ranges_m: np.ndarray
    spurious: np.ndarray
    angles_rad: np.ndarray
    on_mover: np.ndarray


def raycast(segments_m: np.ndarray, pose, angles_rad: np.ndarray, max_range_m: float = np.inf) -> np.ndarray:
    """Distance along each beam to the first wall.

    Parameters
    ----------
    segments_m : ndarray, shape (M, 4)
        Walls ``(x0, y0, x1, y1)`` in metres, world frame; both sides reflect.
    pose : array_like, shape (3,)
        Sensor pose ``(x_m, y_m, theta_rad)`` in the world frame.
    angles_rad : ndarray, shape (N,)
        Beam bearings relative to the sensor heading, radians.
    max_range_m : float
        Hits farther than this are reported as ``inf``.

    Returns
    -------
    ndarray, shape (N,)
        Ranges in metres; ``inf`` where no wall is hit within ``max_range_m``.
    """
    return first_hit(segments_m, pose, angles_rad, max_range_m)[0]


def first_hit(segments_m, pose, angles_rad, max_range_m: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """Ranges (N,) as :func:`raycast`, and the index (N,) of the segment hit, -1 where none.

    The index tells :func:`simulate_scan` whether a beam met a person or a wall.
    """
    seg = np.asarray(segments_m, dtype=float).reshape(-1, 4)
    if len(seg) == 0:
        n = len(np.atleast_1d(angles_rad))
        return np.full(n, np.inf), np.full(n, -1)

    x, y, theta = (float(v) for v in pose)
    index_of = None
    if np.isfinite(max_range_m):
        # Only walls within range can be hit within it: the rest would come out inf anyway, so
        # leaving them out (order kept, ties still to the lower index) changes no output.
        near = _segment_distance(seg, x, y) <= max_range_m
        if not near.all():
            index_of, seg = np.flatnonzero(near), seg[near]
            if len(seg) == 0:
                n = len(np.atleast_1d(angles_rad))
                return np.full(n, np.inf), np.full(n, -1)
    bearing = theta + np.asarray(angles_rad, dtype=float)
    d = np.stack((np.cos(bearing), np.sin(bearing)), axis=-1)[:, None, :]  # (N, 1, 2)
    a = seg[None, :, :2]
    e = seg[None, :, 2:] - a  # (1, M, 2)
    w = a - np.array([x, y])

    den = d[..., 0] * e[..., 1] - d[..., 1] * e[..., 0]  # (N, M)
    parallel = np.abs(den) <= _PARALLEL_EPS * np.hypot(e[..., 0], e[..., 1])
    safe_den = np.where(parallel, 1.0, den)
    t = (w[..., 0] * e[..., 1] - w[..., 1] * e[..., 0]) / safe_den
    u = (w[..., 0] * d[..., 1] - w[..., 1] * d[..., 0]) / safe_den
    hit = ~parallel & (t > 0.0) & (u >= -_VERTEX_SLACK) & (u <= 1.0 + _VERTEX_SLACK)
    t_hit = np.where(hit, t, np.inf)
    index = t_hit.argmin(axis=1)
    ranges = t_hit[np.arange(len(index)), index]
    none = ~np.isfinite(ranges) | (ranges > max_range_m)
    if index_of is not None:
        index = index_of[index]
    index[none] = -1
    ranges[ranges > max_range_m] = np.inf
    return ranges, index


def _segment_distance(seg: np.ndarray, x: float, y: float) -> np.ndarray:
    """Distance (M,) from the point ``(x, y)`` to each segment ``(x0, y0, x1, y1)`` of ``seg`` (M, 4), m."""
    a, e = seg[:, :2], seg[:, 2:] - seg[:, :2]
    w = np.array([x, y]) - a
    length2 = np.einsum("ij,ij->i", e, e)
    along = np.clip(np.einsum("ij,ij->i", w, e) / np.where(length2 > 0, length2, 1.0), 0.0, 1.0)
    gap = w - along[:, None] * e
    return np.hypot(gap[:, 0], gap[:, 1])


def simulate_scan(
    world: World,
    pose,
    model: LidarModel,
    rng: np.random.Generator,
    range_bias_m: float = 0.0,
    movers_m: np.ndarray | None = None,
) -> SimScan:
    """Simulate one scan of ``world`` from ``pose``.

    Glass segments of the world let the beam through; ``movers_m`` (people) block it.

    Every call draws the same number of variates from ``rng`` whatever the geometry,
    so a change of pose or map does not reshuffle the noise of later scans.

    Parameters
    ----------
    world : World
    pose : array_like, shape (3,)
        Sensor pose ``(x_m, y_m, theta_rad)`` in the world frame.
    model : LidarModel
    rng : numpy.random.Generator
    range_bias_m : float
        Systematic offset added to every return, metres (see ``LidarModel.range_bias_sigma_m``).
    movers_m : ndarray, shape (P, 4), optional
        Segments of moving obstacles at the time of the scan, metres, world frame.

    Returns
    -------
    SimScan
    """
    angles = model.angles_rad()
    n = len(angles)
    opaque = world.opaque_segments_m
    movers = np.zeros((0, 4)) if movers_m is None else np.asarray(movers_m, dtype=float).reshape(-1, 4)
    true_ranges, index = first_hit(np.vstack((opaque, movers)), pose, angles, model.max_range_m)

    edge_draw = rng.random(n - 1)
    weight = rng.uniform(0.2, 0.8, n - 1)
    noise = rng.standard_normal(n) * model.range_sigma_m
    dropout_draw = rng.random(n)

    ranges, spurious = _mixed_pixels(true_ranges, model, edge_draw, weight)
    ranges[dropout_draw < model.dropout_prob] = np.inf
    finite = np.isfinite(ranges)
    measured = np.maximum(ranges[finite] + range_bias_m + noise[finite], 0.0)
    if model.quantum_m > 0:
        measured = np.round(measured / model.quantum_m) * model.quantum_m
    ranges[finite] = measured
    ranges[ranges > model.max_range_m] = np.inf
    # A mixed pixel that dropped out is no longer a point in empty space.
    spurious &= np.isfinite(ranges)
    return SimScan(
        ranges_m=ranges, true_ranges_m=true_ranges, spurious=spurious, angles_rad=angles, on_mover=index >= len(opaque)
    )


def _mixed_pixels(true_ranges, model: LidarModel, edge_draw, weight):
    """Blend the far-side beam of selected depth edges towards the near side.

    Edges are found on the true ranges: the footprint straddles two real surfaces,
    whatever the noise on either. ``edge_draw`` and ``weight`` (N - 1,) are the
    per-neighbour-pair uniform draws. Returns the new ranges (N,) and the mask of
    blended beams (N,).
    """
    ranges = true_ranges.copy()
    spurious = np.zeros(len(ranges), dtype=bool)
    left, right = true_ranges[:-1], true_ranges[1:]
    with np.errstate(invalid="ignore"):
        jump = np.abs(right - left)
    # A beam with no return has no far surface to blend with, so only finite pairs count.
    edges = np.flatnonzero(
        np.isfinite(jump) & (jump > model.mixed_pixel_min_jump_m) & (edge_draw < model.mixed_pixel_prob)
    )
    for i in edges:
        near, far = (i, i + 1) if left[i] < right[i] else (i + 1, i)
        if spurious[far]:
            continue
        w = weight[i]
        ranges[far] = w * true_ranges[far] + (1.0 - w) * true_ranges[near]
        spurious[far] = True
    return ranges, spurious
