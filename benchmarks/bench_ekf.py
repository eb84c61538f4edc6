"""Cost of one EKF-SLAM observation update against the number of landmarks.

Compares ``EkfSlam.update_known`` (sparse H, rank-2 Cholesky downdate, O(n²))
with filterpy's dense ``ExtendedKalmanFilter.update`` (Joseph form, O(n³)) on
the same random state, and fits the log–log slope of each against the landmark
count. Also times ``EkfSlam.predict`` (O(n)).

Run single-threaded for stable numbers::

    OPENBLAS_NUM_THREADS=1 python benchmarks/bench_ekf.py
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter

from lrfslam.algo.ekf_slam import EkfParams, EkfSlam
from lrfslam.algo.geometry import wrap_angle


def random_filter(n_lm: int, rng: np.random.Generator) -> EkfSlam:
    """A filter with ``n_lm`` confirmed landmarks and a dense, well-conditioned covariance."""
    n = 3 + 2 * n_lm
    a = rng.normal(size=(n, 8)) * 0.05  # low-rank correlations keep every entry non-zero
    cov = a @ a.T + 1e-3 * np.eye(n)
    lms = rng.uniform(-20, 20, size=(n_lm, 2))
    snap = {
        "format": 1,
        "state_mean": np.concatenate(([0.0, 0.0, 0.0], lms.ravel())),
        "state_cov": cov,
        "landmark_ids": np.arange(n_lm, dtype=np.int64),
        "landmark_kinds": np.zeros(n_lm, dtype=np.int8),
        "landmark_sightings": np.full(n_lm, 3),
        "landmark_confirmed": np.ones(n_lm, dtype=bool),
        "landmark_born": np.zeros(n_lm, dtype=np.int64),
        "landmark_view_ref_rad": np.zeros(n_lm),
        "landmark_view_spread_rad": np.zeros(n_lm),
        "next_id": n_lm,
        "n_observe": 0,
    }
    return EkfSlam.restore(EkfParams(), snap)


def range_bearing(x: np.ndarray, i: int):
    """Dense model for filterpy: h (2, 1) and H (2, n) of landmark index ``i``."""
    dx, dy = x[3 + 2 * i] - x[0], x[4 + 2 * i] - x[1]
    q = dx * dx + dy * dy
    r = np.sqrt(q)
    H = np.zeros((2, x.size))
    H[:, :3] = [[-dx / r, -dy / r, 0.0], [dy / q, -dx / q, -1.0]]
    H[:, 3 + 2 * i: 5 + 2 * i] = [[dx / r, dy / r], [-dy / q, dx / q]]
    return np.array([[r], [wrap_angle(np.arctan2(dy, dx) - x[2])]]), H


def bearing_residual(a, b):
    y = a - b
    y[1, 0] = wrap_angle(y[1, 0])
    return y


def timed(fn, budget_s: float, min_reps: int = 3) -> float:
    """Median wall time of ``fn()`` in seconds over a time budget."""
    times: list[float] = []
    start = time.perf_counter()
    while len(times) < min_reps or time.perf_counter() - start < budget_s:
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def bench_size(n_lm: int, rng, budget_s: float, with_filterpy: bool):
    f = random_filter(n_lm, rng)
    R = np.diag([0.015**2, 0.005**2])
    z = np.array([5.0, 0.3])
    ours = timed(lambda: f.update_known(int(rng.integers(n_lm)), z, R), budget_s)
    pred = timed(lambda: f.predict([0.1, 0.0, 0.01]), budget_s)
    dense = float("nan")
    if with_filterpy:
        ekf = ExtendedKalmanFilter(dim_x=f.state_mean.size, dim_z=2)
        ekf.x = f.state_mean.reshape(-1, 1)
        ekf.P = f.state_cov

        def dense_update():
            i = int(rng.integers(n_lm))
            ekf.update(
                z.reshape(2, 1), lambda x, j: range_bearing(x.ravel(), j)[1],
                lambda x, j: range_bearing(x.ravel(), j)[0], R=R, args=(i,), hx_args=(i,),
                residual=bearing_residual,
            )

        dense = timed(dense_update, budget_s)
    return ours, dense, pred


def slope(sizes, times) -> float:
    ok = np.isfinite(times)
    if ok.sum() < 2:
        return float("nan")
    return float(np.polyfit(np.log(np.asarray(sizes)[ok]), np.log(np.asarray(times)[ok]), 1)[0])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[50, 100, 200, 400, 700, 1000])
    ap.add_argument("--filterpy-max-landmarks", type=int, default=1000,
                    help="skip filterpy's dense update above this landmark count")
    ap.add_argument("--budget-s", type=float, default=1.0, help="timing budget per cell")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    rows = []
    print(f"{'landmarks':>9} {'n':>5} {'ours ms':>9} {'filterpy ms':>12} {'ratio':>7} {'predict ms':>11}")
    for n_lm in args.sizes:
        ours, dense, pred = bench_size(n_lm, rng, args.budget_s, n_lm <= args.filterpy_max_landmarks)
        rows.append((n_lm, ours, dense))
        dense_s = f"{dense * 1e3:12.3f}" if np.isfinite(dense) else f"{'skipped':>12}"
        ratio_s = f"{dense / ours:7.1f}" if np.isfinite(dense) else f"{'-':>7}"
        print(f"{n_lm:9d} {3 + 2 * n_lm:5d} {ours * 1e3:9.3f} {dense_s} {ratio_s} {pred * 1e3:11.4f}")
    sizes, ours_t, dense_t = (np.array(c, dtype=float) for c in zip(*rows, strict=True))
    big = sizes >= 200
    print(f"log-log slope vs landmarks, all sizes: ours {slope(sizes, ours_t):.2f}, "
          f"filterpy {slope(sizes, dense_t):.2f}")
    print(f"log-log slope vs landmarks, >= 200:    ours {slope(sizes[big], ours_t[big]):.2f}, "
          f"filterpy {slope(sizes[big], dense_t[big]):.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
