"""Wheel-odometry error model: noisy pose increments integrated into a drifting pose.

The errors are random walks: their variance grows linearly with the distance
travelled and the angle turned, so a sigma "per metre" is the standard deviation
accumulated over one metre. Splitting a motion into more, smaller steps therefore
gives the same drift statistics, and the simulated drift does not depend on the
scan rate.

:class:`SystematicOdometryError` adds what a random walk does not: a robot whose
wheel radius and wheelbase are mis-calibrated over- or under-reports every metre and
every turn by the same fraction, unequal wheel radii curve a straight line, and a
wheel that slips on a threshold or a cable adds a burst of error at once. These
errors do not average out, so they give metres of drift over a large loop.
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
    trans_sigma_per_sqrt_m : float
        Along-track distance error accumulated over 1 m travelled, metres.
    rot_sigma_per_sqrt_rad : float
        Heading error accumulated over 1 rad turned, radians.
    rot_sigma_per_sqrt_m : float
        Heading error accumulated over 1 m travelled, radians (wheel slip on straights).
    """

    trans_sigma_per_sqrt_m: float = 0.02
    rot_sigma_per_sqrt_rad: float = 0.02
    rot_sigma_per_sqrt_m: float = 0.005

    def __post_init__(self) -> None:
        if min(self.trans_sigma_per_sqrt_m, self.rot_sigma_per_sqrt_rad, self.rot_sigma_per_sqrt_m) < 0:
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
    trans_err_m = z_trans * noise.trans_sigma_per_sqrt_m * np.sqrt(dist_m)
    rot_var = noise.rot_sigma_per_sqrt_rad**2 * abs(dtheta) + noise.rot_sigma_per_sqrt_m**2 * dist_m
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


@dataclass(frozen=True)
class SystematicOdometryError:
    """Calibration errors and wheel slip of a differential-drive robot; all zero by default.

    Attributes
    ----------
    distance_scale : float
        Fractional error of the mean wheel radius: the odometry reports
        ``(1 + distance_scale)`` times the distance travelled (0.01 = 1 % too far).
    rotation_scale : float
        Fractional wheelbase error: the odometry reports ``(1 + rotation_scale)`` times
        the angle turned.
    heading_drift_rad_per_m : float
        Unequal left and right wheel radii: heading the odometry adds per metre
        travelled, radians per metre (counter-clockwise positive), so a straight line
        is reported as an arc.
    slip_rate_per_m : float
        Expected number of slip events per metre travelled (Poisson).
    slip_trans_sigma_m : float
        Scale of the extra distance a slip event reports, metres; a slipping wheel turns
        without moving the robot, so the extra distance is always positive (half-normal).
    slip_rot_sigma_rad : float
        Standard deviation of the heading error of a slip event, radians.
    """

    distance_scale: float = 0.0
    rotation_scale: float = 0.0
    heading_drift_rad_per_m: float = 0.0
    slip_rate_per_m: float = 0.0
    slip_trans_sigma_m: float = 0.0
    slip_rot_sigma_rad: float = 0.0

    def __post_init__(self) -> None:
        if min(self.slip_rate_per_m, self.slip_trans_sigma_m, self.slip_rot_sigma_rad) < 0:
            raise ConfigError(f"slip rate and sigmas must be >= 0, got {self}")
        if min(self.distance_scale, self.rotation_scale) <= -1.0:
            raise ConfigError(f"scale errors must be > -1, got {self}")


#: No systematic error: odometry as the random walks alone make it.
CALIBRATED = SystematicOdometryError()
#: An uncalibrated indoor robot: 1.5 % long on distance (worn tyres, nominal radius), 2 % long
#: on turns (wheelbase set 2 % too narrow), 1 mrad/m of left curve from a 0.03 % wheel radius
#: difference on a 0.33 m wheelbase, and a slip every 40 m on average (door thresholds,
#: cables). The two heading errors add up on a loop driven counter-clockwise.
REALISTIC = SystematicOdometryError(
    distance_scale=0.015,
    rotation_scale=0.02,
    heading_drift_rad_per_m=0.001,
    slip_rate_per_m=0.025,
    slip_trans_sigma_m=0.10,
    slip_rot_sigma_rad=0.03,
)


def biased_increment(delta_true, error: SystematicOdometryError, rng: np.random.Generator) -> np.ndarray:
    """Apply calibration errors and slip to one true motion increment.

    Always draws three variates from ``rng`` (slip or not), so the random stream
    does not depend on the error settings.

    Parameters
    ----------
    delta_true : array_like, shape (3,)
        True motion ``(dx_m, dy_m, dtheta_rad)`` in the frame of the previous pose.
    error : SystematicOdometryError
    rng : numpy.random.Generator

    Returns
    -------
    ndarray, shape (3,)
        The increment the mis-calibrated wheels report, before the random walk of
        :func:`noisy_increment`.
    """
    dx, dy, dtheta = (float(v) for v in delta_true)
    dist_m = np.hypot(dx, dy)
    slip_draw = rng.random()
    z_trans, z_rot = rng.standard_normal(2)
    slipped = slip_draw < -np.expm1(-error.slip_rate_per_m * dist_m)
    extra_m = abs(z_trans) * error.slip_trans_sigma_m if slipped else 0.0
    scale = 1.0 + error.distance_scale
    if dist_m > 0:
        scale += extra_m / dist_m
    dtheta_meas = dtheta * (1.0 + error.rotation_scale) + error.heading_drift_rad_per_m * dist_m
    if slipped:
        dtheta_meas += z_rot * error.slip_rot_sigma_rad
    return np.array([dx * scale, dy * scale, dtheta_meas])
