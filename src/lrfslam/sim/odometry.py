"""Wheel-odometry error model: noisy pose increments integrated into a drifting pose.

The errors are random walks: their variance grows linearly with the distance
travelled and the angle turned, so a sigma "per metre" is the standard deviation
accumulated over one metre. Splitting a motion into more, smaller steps therefore
gives the same drift statistics, and the simulated drift does not depend on the
scan rate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lrfslam.algo.geometry import compose
from lrfslam.errors import ConfigError


@dataclass(frozen=True)
class OdometryNoise:
    """Standard deviations of the odometry random walks.

    Attributes
    ----------
    trans_sigma_per_m : float
        Along-track distance error accumulated over 1 m travelled, metres.
    rot_sigma_per_rad : float
        Heading error accumulated over 1 rad turned, radians.
    rot_sigma_per_m_rad : float
        Heading error accumulated over 1 m travelled, radians (wheel slip on straights).
    """

    trans_sigma_per_m: float = 0.02
    rot_sigma_per_rad: float = 0.02
    rot_sigma_per_m_rad: float = 0.005

    def __post_init__(self) -> None:
        if min(self.trans_sigma_per_m, self.rot_sigma_per_rad, self.rot_sigma_per_m_rad) < 0:
            raise ConfigError(f"odometry sigmas must be >= 0, got {self}")


def noisy_increment(delta_true, noise: OdometryNoise, rng: np.random.Generator) -> np.ndarray:
    """Corrupt one true motion increment as wheel odometry would.

    Always draws two standard normals from ``rng``, so zero noise leaves the
    random stream in the same place as any other setting.

    Parameters
    ----------
    delta_true : array_like, shape (3,)
        True motion ``(dx_m, dy_m, dtheta_rad)`` in the frame of the previous pose.
    noise : OdometryNoise
    rng : numpy.random.Generator

    Returns
    -------
    ndarray, shape (3,)
        The measured increment: translation scaled along its direction, heading offset.
    """
    dx, dy, dtheta = (float(v) for v in delta_true)
    dist_m = np.hypot(dx, dy)
    z_trans, z_rot = rng.standard_normal(2)
    trans_err_m = z_trans * noise.trans_sigma_per_m * np.sqrt(dist_m)
    rot_var = noise.rot_sigma_per_rad**2 * abs(dtheta) + noise.rot_sigma_per_m_rad**2 * dist_m
    rot_err_rad = z_rot * np.sqrt(rot_var)
    scale = 1.0 + trans_err_m / dist_m if dist_m > 0 else 1.0
    return np.array([dx * scale, dy * scale, dtheta + rot_err_rad])


def integrate_odometry(start_pose, increments) -> np.ndarray:
    """Chain increments onto a start pose.

    Parameters
    ----------
    start_pose : array_like, shape (3,)
        ``(x_m, y_m, theta_rad)``.
    increments : array_like, shape (T, 3)
        Each in the frame of the pose before it.

    Returns
    -------
    ndarray, shape (T + 1, 3)
        The start pose followed by each integrated pose.
    """
    poses = [np.asarray(start_pose, dtype=float)]
    for delta in np.asarray(increments, dtype=float).reshape(-1, 3):
        poses.append(compose(poses[-1], delta))
    return np.array(poses)
