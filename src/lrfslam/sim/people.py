"""People walking up and down corridors: moving obstacles that hide the walls from the scanner.

Each walker paces a straight lane back and forth at constant speed. To the ray
caster a person is a small regular polygon (a body about 0.4 m across); people are
never part of the map, so they add no ground-truth corner.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lrfslam.errors import ConfigError
from lrfslam.sim.world import closed_polygon

#: Sides of the polygon that stands for a person; 8 gives 135° vertices, never a "corner".
PERSON_SIDES = 8


@dataclass(frozen=True, eq=False)
class Walkers:
    """People pacing lanes, all positions a function of time alone.

    Attributes
    ----------
    lanes_m : ndarray, shape (P, 4)
        Lane of each walker ``(x0, y0, x1, y1)``, metres; the walker turns round at both ends.
    speed_mps : ndarray, shape (P,)
        Walking speed, m/s, > 0.
    phase_m : ndarray, shape (P,)
        Distance walked along the out-and-back circuit at time 0, metres.
    radius_m : float
        Body radius, metres.
    """

    lanes_m: np.ndarray
    speed_mps: np.ndarray
    phase_m: np.ndarray
    radius_m: float = 0.2

    def __post_init__(self) -> None:
        lanes = np.asarray(self.lanes_m, dtype=float).reshape(-1, 4)
        if np.any(np.hypot(lanes[:, 2] - lanes[:, 0], lanes[:, 3] - lanes[:, 1]) <= 0):
            raise ConfigError("a walker lane has zero length")
        if np.any(np.asarray(self.speed_mps) <= 0) or not self.radius_m > 0:
            raise ConfigError("walker speeds and radius must be > 0")
        object.__setattr__(self, "lanes_m", lanes)

    def __len__(self) -> int:
        return len(self.lanes_m)

    def positions(self, t_s: float) -> np.ndarray:
        """Walker centres at time ``t_s`` (seconds); shape (P, 2), metres."""
        a, b = self.lanes_m[:, :2], self.lanes_m[:, 2:]
        length = np.hypot(*(b - a).T)
        s = np.mod(self.phase_m + self.speed_mps * t_s, 2.0 * length)
        # Out along the lane, then back: a triangle wave in the distance from the lane start.
        along = np.where(s <= length, s, 2.0 * length - s)
        return a + (b - a) * (along / length)[:, None]

    def segments(self, t_s: float) -> np.ndarray:
        """The walkers' outlines at time ``t_s``, for the ray caster; shape (P * PERSON_SIDES, 4), metres."""
        return body_segments(self.positions(t_s), self.radius_m)


def body_segments(centres_m, radius_m: float) -> np.ndarray:
    """Regular :data:`PERSON_SIDES`-gons of circumradius ``radius_m`` round each centre.

    Parameters
    ----------
    centres_m : array_like, shape (P, 2)
    radius_m : float

    Returns
    -------
    ndarray, shape (P * PERSON_SIDES, 4)
        Solid polygons (free space outside).
    """
    c = np.asarray(centres_m, dtype=float).reshape(-1, 2)
    a = 2.0 * np.pi * np.arange(PERSON_SIDES) / PERSON_SIDES
    ring = radius_m * np.column_stack((np.cos(a), np.sin(a)))
    if len(c) == 0:
        return np.zeros((0, 4))
    return np.vstack([closed_polygon(centre + ring, free_inside=False) for centre in c])


def draw_walkers(lanes_m, n_walkers: int, rng: np.random.Generator, speed_range_mps=(0.6, 1.4)) -> Walkers:
    """Put ``n_walkers`` people on randomly chosen lanes with random speeds and starting points.

    Parameters
    ----------
    lanes_m : array_like, shape (L, 4)
        Candidate lanes, metres; may be empty only when ``n_walkers`` is 0.
    n_walkers : int
    rng : numpy.random.Generator
        Always draws ``3 * n_walkers`` variates.
    speed_range_mps : tuple of float
        Walking speeds are uniform in this range, m/s.

    Returns
    -------
    Walkers
    """
    lanes = np.asarray(lanes_m, dtype=float).reshape(-1, 4)
    if n_walkers < 0 or (n_walkers > 0 and len(lanes) == 0):
        raise ConfigError(f"cannot place {n_walkers} walkers on {len(lanes)} lanes")
    pick = rng.integers(0, max(len(lanes), 1), n_walkers)
    speed = rng.uniform(*speed_range_mps, n_walkers)
    frac = rng.random(n_walkers)
    chosen = lanes[pick] if n_walkers else np.zeros((0, 4))
    length = np.hypot(chosen[:, 2] - chosen[:, 0], chosen[:, 3] - chosen[:, 1])
    return Walkers(lanes_m=chosen, speed_mps=speed, phase_m=2.0 * length * frac)
