"""Monte-Carlo consistency check of EkfSlam on the simulated hallway loop.

Each run drives the simulator's loop with its drifting odometry and feeds the
filter the *true* visible corners, corrupted with Gaussian range and bearing
noise of exactly the filter's assumed size. The filter's odometry model is set
to the simulator's, so the run tests the estimator itself (linearisation,
association, landmark management), not the front end. A variant fed by the
feature extractor can reuse :func:`summarise`.

Metrics, over ``n_runs`` seeded runs:

* ATE RMSE of the position (m), against the same for raw odometry. The filter's
  map frame is anchored at the true start pose, so no alignment is needed.
* Landmark position error at the end of each run (m) and its 2-dof NEES. The
  landmarks of one run are correlated, so the χ² band printed for their mean
  NEES (which assumes independence) is only indicative.
* Pose NEES per step averaged over runs, against the two-sided 95 % band of the
  mean of N χ²₃ variables, ``[χ²_{3N}(0.025)/N, χ²_{3N}(0.975)/N]``.
* Mean NIS of the matched observations (2 for a consistent filter) and the
  number of observations paired with the wrong true corner.

Run ``python -m lrfslam.evaluation.slam_mc --help``.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field

import numpy as np
from scipy.stats import chi2

from lrfslam.algo.ekf_slam import EkfParams, EkfSlam, ObsStatus
from lrfslam.algo.geometry import wrap_angle
from lrfslam.sim import OdometryNoise, SimConfig, Simulator


@dataclass(frozen=True)
class McConfig:
    """One Monte-Carlo experiment.

    Attributes
    ----------
    n_runs : int
        Independent runs (seeds ``seed .. seed + n_runs - 1``).
    n_steps : int
        Frames per run; 1200 is about one lap of the hallway loop at 0.5 m/s, 10 Hz.
    world_name : str
        Simulator world.
    range_sigma_m, bearing_sigma_rad : float
        Noise added to the true corners, and assumed by the filter.
    association : {"nn", "jcbb"}
    odometry : lrfslam.sim.OdometryNoise
        Simulated odometry noise, and the filter's odometry model.
    seed : int
    """

    n_runs: int = 30
    n_steps: int = 1200
    world_name: str = "hallway_loop"
    range_sigma_m: float = 0.015
    bearing_sigma_rad: float = 0.005
    association: str = "nn"
    odometry: OdometryNoise = field(default_factory=OdometryNoise)
    seed: int = 0

    def ekf_params(self) -> EkfParams:
        """Filter parameters matched to the simulation (tiny floors keep P invertible)."""
        return EkfParams(
            odom_trans_sigma_per_m=self.odometry.trans_sigma_per_m,
            odom_rot_sigma_per_rad=self.odometry.rot_sigma_per_rad,
            odom_rot_sigma_per_m=self.odometry.rot_sigma_per_m_rad,
            odom_trans_sigma_floor_m=1e-5,
            odom_rot_sigma_floor_rad=1e-6,
            corner_range_sigma_m=self.range_sigma_m,
            corner_bearing_sigma_rad=self.bearing_sigma_rad,
            association=self.association,
        )


@dataclass(frozen=True, eq=False)
class RunResult:
    """Trace of one run (T frames, L landmarks at the end).

    Attributes
    ----------
    true_poses, est_poses, odom_poses : ndarray, shape (T, 3)
    pose_covs : ndarray, shape (T, 3, 3)
    landmark_err_m : ndarray, shape (L,)
        Distance from each final landmark to the true corner that created it.
    landmark_nees : ndarray, shape (L,)
        2-dof NEES of each final landmark.
    nis_matched : ndarray, shape (M,)
        NIS of every matched observation.
    n_wrong : int
        Matched observations whose landmark was created by another true corner.
    """

    true_poses: np.ndarray
    est_poses: np.ndarray
    odom_poses: np.ndarray
    pose_covs: np.ndarray
    landmark_err_m: np.ndarray
    landmark_nees: np.ndarray
    nis_matched: np.ndarray
    n_wrong: int


def pose_nees(true_poses: np.ndarray, est_poses: np.ndarray, covs: np.ndarray) -> np.ndarray:
    """Normalised estimation error squared per pose, heading error wrapped.

    Parameters
    ----------
    true_poses, est_poses : ndarray, shape (T, 3)
    covs : ndarray, shape (T, 3, 3)
        Estimated pose covariances, positive definite.

    Returns
    -------
    ndarray, shape (T,)
        ``e^T P^-1 e`` with ``e = true - est`` (χ²₃ if consistent).
    """
    err = true_poses - est_poses
    err[:, 2] = wrap_angle(err[:, 2])
    return np.einsum("ti,ti->t", err, np.linalg.solve(covs, err[..., None])[..., 0])


def ate_rmse(true_poses: np.ndarray, est_poses: np.ndarray) -> float:
    """Absolute trajectory error of the positions, RMSE in metres (no alignment)."""
    return float(np.sqrt(np.mean(np.sum((true_poses[:, :2] - est_poses[:, :2]) ** 2, axis=1))))


def nees_band(n_runs: int, dof: int, prob: float = 0.95) -> tuple[float, float]:
    """Two-sided ``prob`` interval of the mean of ``n_runs`` χ²_dof variables."""
    lo, hi = chi2.ppf([(1 - prob) / 2, (1 + prob) / 2], dof * n_runs)
    return float(lo / n_runs), float(hi / n_runs)


def run_once(cfg: McConfig, run_index: int) -> RunResult:
    """One seeded run of the filter on the simulator; see the module docstring."""
    sim = Simulator(SimConfig(world_name=cfg.world_name, odometry=cfg.odometry, seed=cfg.seed + run_index))
    # Measurement noise from its own stream, so it is independent of the simulator's.
    rng = np.random.default_rng([cfg.seed, run_index, 1])
    filt: EkfSlam | None = None
    corner_of: dict[int, int] = {}  # landmark id -> true corner index that created it
    trace: list[tuple] = []
    nis_matched: list[float] = []
    n_wrong = 0
    for frame in (next(sim) for _ in range(cfg.n_steps)):
        if filt is None:
            filt = EkfSlam(cfg.ekf_params(), pose0=frame.true_pose)
        else:
            filt.predict(frame.odom_delta)
        rel = frame.visible_corners_robot_xy
        rng_m = np.hypot(rel[:, 0], rel[:, 1]) + rng.normal(scale=cfg.range_sigma_m, size=len(rel))
        brg = np.arctan2(rel[:, 1], rel[:, 0]) + rng.normal(scale=cfg.bearing_sigma_rad, size=len(rel))
        rep = filt.observe(rng_m[:, None] * np.column_stack((np.cos(brg), np.sin(brg))))
        for k, corner in enumerate(frame.visible_corner_ids):
            if rep.status[k] == ObsStatus.NEW:
                corner_of[int(rep.landmark_ids[k])] = int(corner)
            elif rep.status[k] == ObsStatus.MATCHED:
                nis_matched.append(float(rep.nis[k]))
                n_wrong += int(corner_of[int(rep.landmark_ids[k])] != corner)
        trace.append((frame.true_pose, filt.pose, frame.odom_pose, filt.pose_cov))
    true_p, est_p, odom_p, covs = (np.array(c) for c in zip(*trace, strict=True))
    table = filt.landmarks()
    truth = sim.map_corners.xy_m[[corner_of[int(i)] for i in table.ids]].reshape(-1, 2)
    err = truth - table.xy
    lm_nees = np.einsum("li,li->l", err, np.linalg.solve(table.cov, err[..., None])[..., 0])
    return RunResult(true_p, est_p, odom_p, covs, np.hypot(err[:, 0], err[:, 1]), lm_nees,
                     np.array(nis_matched), n_wrong)


def summarise(results: list[RunResult]) -> dict:
    """Aggregate runs into the figures printed by :func:`main`.

    The first frame is left out of the NEES: the pose is known exactly there.
    """
    n = len(results)
    nees = np.array([pose_nees(r.true_poses[1:], r.est_poses[1:], r.pose_covs[1:]) for r in results])
    mean_nees = nees.mean(axis=0)
    lo, hi = nees_band(n, 3)
    lm_err = np.concatenate([r.landmark_err_m for r in results])
    lm_lo, lm_hi = nees_band(sum(r.landmark_nees.size for r in results), 2)
    return {
        "n_runs": n,
        "ate_rmse_m": np.array([ate_rmse(r.true_poses, r.est_poses) for r in results]),
        "odom_ate_rmse_m": np.array([ate_rmse(r.true_poses, r.odom_poses) for r in results]),
        "mean_nees_per_step": mean_nees,
        "nees_band": (lo, hi),
        "frac_steps_in_band": float(np.mean((mean_nees >= lo) & (mean_nees <= hi))),
        "frac_steps_above_band": float(np.mean(mean_nees > hi)),
        "landmark_rmse_m": float(np.sqrt(np.mean(lm_err**2))),
        "landmark_max_err_m": float(lm_err.max()),
        "landmark_mean_nees": float(np.mean(np.concatenate([r.landmark_nees for r in results]))),
        "landmark_nees_band": (lm_lo, lm_hi),
        "landmarks_per_run": float(np.mean([r.landmark_err_m.size for r in results])),
        "mean_nis_matched": float(np.mean(np.concatenate([r.nis_matched for r in results]))),
        "wrong_associations": int(sum(r.n_wrong for r in results)),
        "runs_with_wrong": [i for i, r in enumerate(results) if r.n_wrong],
        "matched_observations": int(sum(r.nis_matched.size for r in results)),
    }


def format_summary(s: dict, cfg: McConfig) -> str:
    """Human-readable report of :func:`summarise` output."""
    lo, hi = s["nees_band"]
    m = s["mean_nees_per_step"]
    quarters = np.array_split(m, 4)
    head = (
        f"EKF-SLAM Monte Carlo: {s['n_runs']} runs x {cfg.n_steps} steps, world {cfg.world_name}, "
        f"association {cfg.association}, sigma_r {cfg.range_sigma_m} m, sigma_b {cfg.bearing_sigma_rad} rad"
    )
    ate = (
        f"ATE RMSE (m)        EKF {s['ate_rmse_m'].mean():.4f} +- {s['ate_rmse_m'].std():.4f}   "
        f"odometry {s['odom_ate_rmse_m'].mean():.4f} +- {s['odom_ate_rmse_m'].std():.4f}"
    )
    lm_lo, lm_hi = s["landmark_nees_band"]
    landmarks = (
        f"landmarks           {s['landmarks_per_run']:.1f} per run, RMSE {s['landmark_rmse_m']:.4f} m, "
        f"max {s['landmark_max_err_m']:.4f} m, mean NEES {s['landmark_mean_nees']:.2f} "
        f"(band {lm_lo:.2f}-{lm_hi:.2f} if landmarks were independent)"
    )
    nees = (
        f"pose NEES           mean over steps {m.mean():.2f}, max {m.max():.2f}; 95 % band of the run mean "
        f"[{lo:.2f}, {hi:.2f}]; steps inside {100 * s['frac_steps_in_band']:.0f} %, "
        f"above {100 * s['frac_steps_above_band']:.0f} %"
    )
    by_quarter = "pose NEES by quarter of the run: " + ", ".join(f"{q.mean():.2f}" for q in quarters)
    nis = (
        f"matched NIS         mean {s['mean_nis_matched']:.2f} (2.00 if consistent) over "
        f"{s['matched_observations']} observations; wrong associations {s['wrong_associations']} "
        f"in runs {s['runs_with_wrong']}"
    )
    lines = [head, ate, landmarks, nees, by_quarter, nis]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="Monte-Carlo consistency check of EkfSlam on the simulator.")
    ap.add_argument("--runs", type=int, default=McConfig.n_runs)
    ap.add_argument("--steps", type=int, default=McConfig.n_steps)
    ap.add_argument("--world", default=McConfig.world_name)
    ap.add_argument("--association", choices=("nn", "jcbb"), default=McConfig.association)
    ap.add_argument("--range-sigma-m", type=float, default=McConfig.range_sigma_m)
    ap.add_argument("--bearing-sigma-rad", type=float, default=McConfig.bearing_sigma_rad)
    ap.add_argument("--odom-scale", type=float, default=1.0, help="multiply the simulator's odometry noise")
    ap.add_argument("--seed", type=int, default=McConfig.seed)
    args = ap.parse_args(argv)
    base = OdometryNoise()
    cfg = McConfig(
        n_runs=args.runs, n_steps=args.steps, world_name=args.world, association=args.association,
        range_sigma_m=args.range_sigma_m, bearing_sigma_rad=args.bearing_sigma_rad, seed=args.seed,
        odometry=OdometryNoise(base.trans_sigma_per_m * args.odom_scale, base.rot_sigma_per_rad * args.odom_scale,
                               base.rot_sigma_per_m_rad * args.odom_scale),
    )
    results = [run_once(cfg, i) for i in range(cfg.n_runs)]
    print(format_summary(summarise(results), cfg))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
