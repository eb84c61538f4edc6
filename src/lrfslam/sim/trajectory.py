"""The robot's true motion: a closed waypoint loop with rounded corners, driven at constant speed.

Corners are replaced by circular arcs of a fixed radius, so the heading changes
continuously and the turn rate never exceeds ``speed_mps / corner_radius_m``. A
scan-to-scan heading step of a few degrees is what a real robot would produce;
an instant 90° jump would not be.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from lrfslam.algo.geometry import wrap_angle
from lrfslam.errors import ConfigError

# Turns smaller than this are treated as straight-through waypoints (no arc).
_STRAIGHT_RAD = 1e-9


@dataclass(frozen=True, eq=False)
class LoopPath:
    """A closed path made of straight lines and circular arcs, parameterised by arc length.

    Primitive k starts at ``start_xy_m[k]`` with heading ``start_heading_rad[k]`` and
    runs for ``length_m[k]`` with constant curvature ``curvature_per_m[k]`` (0 for a line).

    Attributes
    ----------
    start_xy_m : ndarray, shape (K, 2)
    start_heading_rad : ndarray, shape (K,)
    length_m : ndarray, shape (K,)
    curvature_per_m : ndarray, shape (K,)
        Signed, counter-clockwise positive, 1/m.
    """

    start_xy_m: np.ndarray
    start_heading_rad: np.ndarray
    length_m: np.ndarray
    curvature_per_m: np.ndarray
    _start_s_m: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_start_s_m", np.concatenate(([0.0], np.cumsum(self.length_m)[:-1])))

    @property
    def total_length_m(self) -> float:
        """Length of one lap, metres."""
        return float(np.sum(self.length_m))

    def pose_at(self, s_m) -> np.ndarray:
        """Pose at arc length ``s_m`` (taken modulo one lap).

        Parameters
        ----------
        s_m : float or ndarray, shape (T,)
            Distance travelled from the start, metres.

        Returns
        -------
        ndarray, shape (3,) or (T, 3)
            ``(x_m, y_m, theta_rad)``, heading tangent to the path and wrapped.
        """
        s = np.mod(np.asarray(s_m, dtype=float), self.total_length_m)
        k = np.clip(np.searchsorted(self._start_s_m, s, side="right") - 1, 0, len(self.length_m) - 1)
        sigma = s - self._start_s_m[k]
        h0 = self.start_heading_rad[k]
        kappa = self.curvature_per_m[k]
        h = h0 + kappa * sigma
        straight = kappa == 0.0
        safe_kappa = np.where(straight, 1.0, kappa)
        dx = np.where(straight, sigma * np.cos(h0), (np.sin(h) - np.sin(h0)) / safe_kappa)
        dy = np.where(straight, sigma * np.sin(h0), (np.cos(h0) - np.cos(h)) / safe_kappa)
        p0 = self.start_xy_m[k]
        return np.stack((p0[..., 0] + dx, p0[..., 1] + dy, wrap_angle(h)), axis=-1)


def loop_path(waypoints_m, corner_radius_m: float) -> LoopPath:
    """Close a waypoint polygon into a loop whose corners are arcs of radius ``corner_radius_m``.

    The loop starts at the first waypoint, which should lie on a straight stretch
    (its own corner, if any, is rounded and driven last).

    Parameters
    ----------
    waypoints_m : array_like, shape (P, 2)
        Loop vertices in metres; the last connects back to the first.
    corner_radius_m : float
        Radius of every rounded corner, metres.

    Returns
    -------
    LoopPath

    Raises
    ------
    ConfigError
        If fewer than three waypoints are given, two coincide, the path reverses on
        itself, or a leg is too short for the arcs at its two ends.
    """
    w = np.asarray(waypoints_m, dtype=float)
    if w.ndim != 2 or w.shape[1] != 2 or len(w) < 3:
        raise ConfigError(f"a loop needs at least 3 waypoints of shape (P, 2), got {w.shape}")
    if corner_radius_m <= 0:
        raise ConfigError(f"corner_radius_m must be > 0, got {corner_radius_m}")
    leg = np.roll(w, -1, axis=0) - w  # leg i runs from waypoint i to i+1
    leg_len = np.hypot(leg[:, 0], leg[:, 1])
    if np.any(leg_len <= 0):
        raise ConfigError("consecutive waypoints coincide")
    heading = np.arctan2(leg[:, 1], leg[:, 0])
    turn = wrap_angle(heading - np.roll(heading, 1))  # turn at waypoint i, from leg i-1 to leg i
    if np.any(np.abs(turn) > np.radians(170.0)):
        raise ConfigError("the loop reverses on itself at a waypoint; arcs cannot round it")
    cut = corner_radius_m * np.tan(np.abs(turn) / 2.0)  # tangent length taken off each side
    line_len = leg_len - cut - np.roll(cut, -1)
    if np.any(line_len < 0):
        raise ConfigError(f"corner_radius_m={corner_radius_m} is too large for the shortest leg")

    starts, headings, lengths, curvatures = [], [], [], []
    for i in range(len(w)):
        j = (i + 1) % len(w)
        unit = leg[i] / leg_len[i]
        starts.append(w[i] + cut[i] * unit)
        headings.append(heading[i])
        lengths.append(line_len[i])
        curvatures.append(0.0)
        if abs(turn[j]) > _STRAIGHT_RAD:
            starts.append(w[j] - cut[j] * unit)
            headings.append(heading[i])
            lengths.append(corner_radius_m * abs(turn[j]))
            curvatures.append(np.sign(turn[j]) / corner_radius_m)
    return LoopPath(
        start_xy_m=np.array(starts),
        start_heading_rad=np.array(headings),
        length_m=np.array(lengths),
        curvature_per_m=np.array(curvatures),
    )


@dataclass(frozen=True, eq=False)
class LoopTrajectory:
    """Constant-speed traversal of a :class:`LoopPath`, sampled at a fixed rate, lap after lap.

    Attributes
    ----------
    path : LoopPath
    speed_mps : float
        Forward speed, m/s.
    rate_hz : float
        Sampling rate (the scan rate), Hz.
    start_m : float
        Arc length where sample 0 lies, m (0: the path's first waypoint).
    """

    path: LoopPath
    speed_mps: float = 0.5
    rate_hz: float = 10.0
    start_m: float = 0.0

    def __post_init__(self) -> None:
        if not (self.speed_mps > 0 and self.rate_hz > 0):
            raise ConfigError(f"speed_mps and rate_hz must be > 0, got {self.speed_mps}, {self.rate_hz}")

    @property
    def max_turn_rate_rad_s(self) -> float:
        """Largest heading rate on the loop, rad/s."""
        return float(self.speed_mps * np.max(np.abs(self.path.curvature_per_m)))

    def pose(self, index) -> np.ndarray:
        """True pose at sample ``index`` (time ``index / rate_hz``); shape (3,) or (T, 3) for an index array."""
        return self.path.pose_at(self.start_m + np.asarray(index, dtype=float) * self.speed_mps / self.rate_hz)

    def __iter__(self) -> Iterator[np.ndarray]:
        """Poses at samples 0, 1, 2, ... without end."""
        index = 0
        while True:
            yield self.pose(index)
            index += 1
