"""Where along the lap the EKF-SLAM breaks: error, its sigma and NEES before and after the first revisit.

``slam_mc`` sums a run up; on a large loop what matters is the drift piled up by
the time the robot is back where it started, and whether the filter closes the
loop then. This runs the same Monte Carlo (``slam_mc.run_many``) and prints, at
chosen distances travelled and at the first revisit of the start, the mean
position error, the filter's own position sigma and the run-mean pose NEES
against its 95 % band.

Run ``python -m lrfslam.evaluation.slam_revisit --help``.
"""

from __future__ import annotations

import argparse

import numpy as np

from lrfslam.evaluation.slam_mc import (
    FEATURE_SOURCES,
    McConfig,
    RunResult,
    nees_band,
    pose_nees,
    run_many,
)

#: The robot has revisited its start when it comes back within this of it, metres ...
REVISIT_RADIUS_M = 1.0
#: ... after having been at least this far away, metres.
LEAVE_RADIUS_M = 5.0


def first_revisit(true_poses: np.ndarray) -> int | None:
    """Index of the first pose back within ``REVISIT_RADIUS_M`` of the start, or None.

    Parameters
    ----------
    true_poses : ndarray, shape (T, 3)
        ``(x_m, y_m, theta_rad)``.
    """
    d = np.hypot(*(true_poses[:, :2] - true_poses[0, :2]).T)
    away = np.flatnonzero(d > LEAVE_RADIUS_M)
    if len(away) == 0:
        return None
    back = np.flatnonzero(d[away[0]:] < REVISIT_RADIUS_M)
    return int(away[0] + back[0]) if len(back) else None


def along_lap(results: list[RunResult], steps) -> list[dict]:
    """Error, sigma and NEES at the given step indices, over runs.

    Parameters
    ----------
    results : list of RunResult
        Runs of the same length T.
    steps : iterable of int
        Indices in [1, T).

    Returns
    -------
    list of dict
        Per step: ``step``, ``err_m`` (mean over runs of the position error),
        ``err_max_m``, ``sigma_m`` (mean of sqrt(trace) of the 2 x 2 position
        covariance) and ``nees`` (run-mean 3-dof pose NEES).
    """
    err = np.array([np.hypot(*(r.true_poses[:, :2] - r.est_poses[:, :2]).T) for r in results])
    sigma = np.array([np.sqrt(np.trace(r.pose_covs[:, :2, :2], axis1=1, axis2=2)) for r in results])
    # The first pose is known exactly (zero covariance), so NEES starts at step 1.
    nees = np.array([pose_nees(r.true_poses[1:], r.est_poses[1:], r.pose_covs[1:]) for r in results])
    return [{"step": k, "err_m": float(err[:, k].mean()), "err_max_m": float(err[:, k].max()),
             "sigma_m": float(sigma[:, k].mean()), "nees": float(nees[:, k - 1].mean())} for k in steps]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="EKF-SLAM error along the lap and at the first revisit, on the simulator.")
    ap.add_argument("--runs", type=int, default=4)
    ap.add_argument("--steps", type=int, default=McConfig.n_steps)
    ap.add_argument("--world", default=McConfig.world_name)
    ap.add_argument("--features", choices=FEATURE_SOURCES, default="extractor")
    ap.add_argument("--every-m", type=float, default=25.0, help="also report every this many metres travelled")
    ap.add_argument("--seed", type=int, default=McConfig.seed)
    ap.add_argument("--jobs", type=int, default=1, help="worker processes")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="SERVICE.NAME=VALUE",
                    help="extractor only: override a denoise/feature/slam setting, as for slam_mc")
    args = ap.parse_args(argv)
    cfg = McConfig(n_runs=args.runs, n_steps=args.steps, world_name=args.world, features=args.features,
                   seed=args.seed, stage_sets=tuple(args.sets))
    results = run_many(cfg, args.jobs)
    true = results[0].true_poses
    travelled = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(true[:, :2], axis=0).T))))
    marks = np.searchsorted(travelled, np.arange(args.every_m, travelled[-1], args.every_m))
    revisit = first_revisit(true)
    extra = [] if revisit is None else [revisit - 1, revisit, min(revisit + 200, len(true) - 1)]
    steps = sorted({int(k) for k in (*marks, *extra, len(true) - 1) if k >= 1})
    lo, hi = nees_band(len(results), 3)
    print(f"{args.world}: {len(results)} runs x {args.steps} steps, features {args.features}; "
          f"first revisit of the start at step {revisit}; pose NEES band [{lo:.2f}, {hi:.2f}]")
    print("  step  travelled m   error m (max)       sigma m    NEES")
    for row in along_lap(results, steps):
        k = row["step"]
        note = "  <- revisit" if k == revisit else ""
        print(f"{k:6d}  {travelled[k]:11.1f}   {row['err_m']:7.3f} ({row['err_max_m']:6.3f})   "
              f"{row['sigma_m']:7.3f}  {row['nees']:7.1f}{note}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
