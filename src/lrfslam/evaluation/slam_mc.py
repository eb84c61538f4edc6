"""Monte-Carlo accuracy and consistency of the EKF-SLAM on the simulated hallway loop.

Each run drives the simulator's loop with its drifting odometry. Two feature
sources (``McConfig.features``):

* ``"truth"``: the filter is fed the *true* visible corners, corrupted with
  Gaussian range and bearing noise of exactly the filter's assumed size, so the
  run tests the estimator itself (linearisation, association, landmark
  management), not the front end.
* ``"extractor"``: the real pipeline. Each simulated scan goes through the
  denoise, features and slam *service steps* (built from their default configs,
  as ``lrfslam up`` runs them, in one :class:`~lrfslam.runtime.chain.Chain`),
  so what is measured is what runs live. Only the filter's start pose is set
  to the true one, so no alignment is needed.

Every observation is labelled with the map point it came from: its true corner
("truth"), or the nearest map corner or free wall end within
``label_radius_m`` of where the feature lies in the world (extractor); a
feature near neither is a *phantom* (label -1). A landmark takes the label of
the observation that created it.

Metrics, over ``n_runs`` seeded runs:

* ATE RMSE of the position (m), against the same for raw odometry, over all
  frames and over the last ``final_lap_frac`` of each run.
* Confirmed landmarks with a real label: position error at the end of the run
  (m) and 2-dof NEES. The landmarks of one run are correlated, so the χ² band
  printed for their mean NEES (which assumes independence) is only indicative.
  Confirmed phantoms are counted apart; there should be none.
* Pose NEES per step averaged over runs, against the two-sided 95 % band of the
  mean of N χ²₃ variables, ``[χ²_{3N}(0.025)/N, χ²_{3N}(0.975)/N]``.
* Mean NIS of the matched observations (2 for a consistent filter), and wrong
  pairings: matched observations whose label differs from their landmark's
  (a phantom paired with a real landmark or the reverse counts), split by
  whether the landmark was confirmed (the update moved the robot) or not.
* Extractor only: the features' own 2-dof NEES against the covariance the
  extractor reports (2 if calibrated) and their RMS position error.
* With the mapper: the ATE of its pose as published and of its final trajectory,
  and every closure it tried judged by the true poses of its keyframes
  (:func:`lrfslam.evaluation.closure_audit.judge_by_truth`): right, false
  accepts, precision and recall.

Run ``python -m lrfslam.evaluation.slam_mc --help``.
"""

from __future__ import annotations

import argparse
import multiprocessing
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.stats import chi2

from lrfslam import services
from lrfslam.algo.ekf_slam import EkfParams, EkfSlam, ObsStatus
from lrfslam.algo.geometry import from_frame, to_frame, wrap_angle
from lrfslam.algo.loop_closure import VERDICTS
from lrfslam.evaluation.closure_audit import (
    CHI2_99,
    RIGHT_M,
    RIGHT_RAD,
    judge_by_truth,
    observed_stages,
    precision_recall,
    summary_counts,
)
from lrfslam.evaluation.map_trajectory import KeyframeHistory, final_poses
from lrfslam.evaluation.truth import ate_rmse
from lrfslam.msgs import topics
from lrfslam.runtime import config as config_mod
from lrfslam.runtime.chain import Chain, Stage
from lrfslam.runtime.step import Message
from lrfslam.services import stage
from lrfslam.services.sensor import frame_outputs
from lrfslam.sim import OdometryNoise, SimConfig, SimFrame, Simulator

FEATURE_SOURCES = ("truth", "extractor")
PHANTOM = -1


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
    features : {"truth", "extractor"}
        Feature source; see the module docstring.
    range_sigma_m, bearing_sigma_rad : float
        "truth" only: noise added to the true corners, and assumed by the filter.
    truth_wall_sigma_rad : float
        "truth" only: also give the filter the true wall direction (the world's
        walls are axis-aligned, so ``-theta`` mod 90°) with this noise and sigma;
        0 gives none. ("extractor" runs get the features service's measurement.)
    association : {"nn", "jcbb"}
    odometry : lrfslam.sim.OdometryNoise
        Simulated odometry noise, and the filter's odometry model.
    label_radius_m : float
        A feature farther than this from every map corner and free wall end is a phantom.
    final_lap_frac : float
        Fraction of each run, at its end, over which the second ATE is taken.
    seed : int
    stage_sets : tuple of str
        "extractor" only: ``"<service>.<name>=<value>"`` overrides of the
        denoise, features and slam configs, as ``--set`` gives them to a service.
    mapper : bool
        "extractor" only: the mapper stage runs behind the slam stage, and its
        trajectories (as published at each scan, and final) are scored too.
    """

    n_runs: int = 30
    n_steps: int = 1200
    world_name: str = "hallway_loop"
    features: str = "truth"
    range_sigma_m: float = 0.015
    bearing_sigma_rad: float = 0.005
    truth_wall_sigma_rad: float = 0.0
    association: str = "nn"
    odometry: OdometryNoise = field(default_factory=OdometryNoise)
    label_radius_m: float = 0.15
    final_lap_frac: float = 0.25
    seed: int = 0
    stage_sets: tuple[str, ...] = ()
    mapper: bool = False

    def ekf_params(self) -> EkfParams:
        """Filter parameters.

        "truth": the measurement noise is the one added (corners and, if any, the
        wall direction), and tiny odometry floors keep P invertible. "extractor":
        the slam service's config (its defaults with ``stage_sets``). In both the
        odometry model is set to the simulated one (the service's defaults already
        are at the simulator's default noise) and the association as configured.
        """
        odometry = {
            "odom_trans_sigma_per_sqrt_m": self.odometry.trans_sigma_per_sqrt_m,
            "odom_rot_sigma_per_sqrt_rad": self.odometry.rot_sigma_per_sqrt_rad,
            "odom_rot_sigma_per_sqrt_m": self.odometry.rot_sigma_per_sqrt_m,
            "association": self.association,
        }
        if self.features == "extractor":
            return replace(self.stage("slam").config.ekf, **odometry)
        return EkfParams(
            odom_trans_sigma_floor_m=1e-5,
            odom_rot_sigma_floor_rad=1e-6,
            corner_range_sigma_m=self.range_sigma_m,
            corner_bearing_sigma_rad=self.bearing_sigma_rad,
            wall_model_sigma_rad=0.0,  # the added wall noise is exactly the sigma given
            **odometry,
        )

    def stage(self, name: str) -> Stage:
        """The ``name`` service configured as the runner layers it: ``stage_sets``, no file, no environment."""
        return stage(name, sets=config_mod.by_service(self.stage_sets, services.NAMES)[name])


@dataclass(frozen=True, eq=False)
class RunResult:
    """Trace of one run (T frames, L confirmed and labelled landmarks at the end).

    Attributes
    ----------
    true_poses, est_poses, odom_poses : ndarray, shape (T, 3)
    pose_covs : ndarray, shape (T, 3, 3)
    landmark_err_m : ndarray, shape (L,)
        Distance from each landmark to the map point that created it.
    landmark_nees : ndarray, shape (L,)
        2-dof NEES of each landmark.
    n_phantom_confirmed : int
        Confirmed landmarks created by a phantom.
    nis_matched : ndarray, shape (M,)
        NIS of every matched observation.
    n_wrong : int
        Matched observations with another label than their landmark's.
    n_wrong_confirmed : int
        Of those, the ones paired with a confirmed landmark (a full update).
    n_observations : int
        Observations given to the filter.
    n_phantom_obs : int
        Of those, phantoms.
    feature_err_m : ndarray, shape (F,)
        Extractor: position error of every labelled observation, robot frame; empty for "truth".
    feature_nees : ndarray, shape (F,)
        Their 2-dof NEES against the extractor's own covariance.
    map_online_poses, map_final_poses : ndarray, shape (T, 3) or (0, 3)
        With the mapper: its pose as published at each step, and its final trajectory.
    closures : Counter
        With the mapper: its closure attempts judged by the truth
        (:func:`lrfslam.evaluation.closure_audit.summary_counts`).
    """

    true_poses: np.ndarray
    est_poses: np.ndarray
    odom_poses: np.ndarray
    pose_covs: np.ndarray
    landmark_err_m: np.ndarray
    landmark_nees: np.ndarray
    n_phantom_confirmed: int
    nis_matched: np.ndarray
    n_wrong: int
    n_wrong_confirmed: int
    n_observations: int
    n_phantom_obs: int
    feature_err_m: np.ndarray
    feature_nees: np.ndarray
    map_online_poses: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    map_final_poses: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    closures: Counter = field(default_factory=Counter)


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


def nees_band(n_runs: int, dof: int, prob: float = 0.95) -> tuple[float, float]:
    """Two-sided ``prob`` interval of the mean of ``n_runs`` χ²_dof variables."""
    lo, hi = chi2.ppf([(1 - prob) / 2, (1 + prob) / 2], dof * n_runs)
    return float(lo / n_runs), float(hi / n_runs)


def label_points(world_xy: np.ndarray, truth_xy: np.ndarray, radius_m: float) -> np.ndarray:
    """Index of the nearest truth point within ``radius_m`` of each point, else ``PHANTOM``.

    Parameters
    ----------
    world_xy : ndarray, shape (K, 2)
    truth_xy : ndarray, shape (V, 2)
    radius_m : float

    Returns
    -------
    ndarray, shape (K,), int64
    """
    if len(world_xy) == 0 or len(truth_xy) == 0:
        return np.full(len(world_xy), PHANTOM, dtype=np.int64)
    d2 = ((world_xy[:, None, :] - truth_xy[None, :, :]) ** 2).sum(axis=2)
    best = d2.argmin(axis=1)
    return np.where(d2[np.arange(len(best)), best] <= radius_m**2, best, PHANTOM).astype(np.int64)


def truth_clusters(truth_xy: np.ndarray, radius_m: float) -> np.ndarray:
    """Physical feature of each truth point: points closer than ``radius_m`` (chained) are one.

    The two vertices of a 0.15 m thick door jamb are one physical feature: a
    jump edge on the jamb's end slides from one to the other as the robot
    passes, and a labeller with a ``radius_m`` tolerance cannot tell them apart.

    Parameters
    ----------
    truth_xy : ndarray, shape (V, 2)
    radius_m : float

    Returns
    -------
    ndarray, shape (V,), int64
        The smallest index in each point's cluster.
    """
    close = ((truth_xy[:, None, :] - truth_xy[None, :, :]) ** 2).sum(axis=2) <= radius_m**2
    cluster = np.arange(len(truth_xy))
    # Spread the smallest index along chains of close points until nothing changes.
    while True:
        merged = np.where(close, cluster[None, :], len(truth_xy)).min(axis=1)
        if np.array_equal(merged, cluster):
            return cluster.astype(np.int64)
        cluster = merged


class _Pipeline:
    """The denoise, features and slam service steps, one in-memory chain driven frame by frame.

    The frames are turned into the sensor service's messages (an odometry pose
    and a scan with the same stamp); the slam step starts at the true start pose.
    """

    def __init__(self, sim: Simulator, cfg: McConfig, params: EkfParams, pose0: np.ndarray) -> None:
        slam = cfg.stage("slam")
        stages = [cfg.stage("denoise"), cfg.stage("features"), Stage(slam.spec, replace(slam.config, ekf=params))]
        self.closure_attempts: list = []   # the mapper's, each ClosureAttempt as it happens
        self.stamps_ns: list[int] = []      # every frame's, as fed
        stages = observed_stages(stages + ([cfg.stage("mapper")] if cfg.mapper else []), self.closure_attempts)
        self.chain = Chain(stages, robot="slam_mc", wire=False)
        self.map_online: list[np.ndarray] = []
        self.map_local: list[tuple[int, np.ndarray]] = []   # (stamp ns, local pose (3,)) per map/pose
        self.map_keyframes = KeyframeHistory()
        self.slam = self.chain.step("slam").slam
        self.slam.start_at(pose0)
        self.sim = sim

    def _take_map(self, outs: list[Message]) -> None:
        for m in outs:
            if m.topic is topics.MAP_POSE:
                self.map_online.append(m.value.pose)
                self.map_local.append((m.value.stamp_ns, m.value.local_pose))
            elif m.topic is topics.MAP_KEYFRAMES:
                self.map_keyframes.add(m.value)

    def map_trajectories(self) -> tuple[np.ndarray, np.ndarray]:
        """The mapper's online poses (T, 3) and its final trajectory (T, 3); empty without a mapper.

        Ends the run: the stages' final outputs are taken first. The final trajectory is
        rebuilt from the published messages, as ``lrfslam eval`` does from a recording.
        """
        self._take_map([it.msg for it in self.chain.finish_items()])
        keyframes = self.map_keyframes.keyframes()
        if keyframes is None:
            return np.zeros((0, 3)), np.zeros((0, 3))
        stamps, local = zip(*self.map_local, strict=True)
        final = final_poses(np.array(stamps, dtype=np.int64), np.array(local), keyframes)
        return np.array(self.map_online).reshape(-1, 3), final

    def step(self, frame: SimFrame):
        """Feed one frame; returns (pose, pose_cov, features xy (K, 2), covs (K, 2, 2), report)."""
        stamp = round(frame.t_s * 1e9)
        self.stamps_ns.append(stamp)
        odom, scan = frame_outputs(frame, stamp, self.sim)
        outs = self.chain.push(Message.of(odom)) + self.chain.push(Message.of(scan))
        (state,) = (m.value for m in outs if m.topic is topics.SLAM_STATE)
        self._take_map(outs)
        last = self.slam.last_update
        return state.pose, state.pose_cov, last.xy_m, last.cov_m2, last.report


def run_once(cfg: McConfig, run_index: int) -> RunResult:
    """One seeded run of the filter on the simulator; see the module docstring."""
    if cfg.features not in FEATURE_SOURCES:
        raise ValueError(f"features must be one of {FEATURE_SOURCES}, got {cfg.features!r}")
    sim = Simulator(SimConfig(world_name=cfg.world_name, odometry=cfg.odometry, seed=cfg.seed + run_index))
    truth_xy = np.vstack((sim.map_corners.xy_m, sim.world.free_endpoints()))
    cluster = truth_clusters(truth_xy, cfg.label_radius_m)
    # Measurement noise from its own stream, so it is independent of the simulator's.
    rng = np.random.default_rng([cfg.seed, run_index, 1])
    params = cfg.ekf_params()
    pipeline: _Pipeline | None = None
    filt: EkfSlam | None = None
    label_of: dict[int, int] = {}  # landmark id -> label of the observation that created it
    trace: list[tuple] = []
    nis_matched: list[float] = []
    feat_err: list[np.ndarray] = []
    feat_nees: list[np.ndarray] = []
    n_wrong = n_wrong_confirmed = n_obs = n_phantom = 0
    for frame in (next(sim) for _ in range(cfg.n_steps)):
        if cfg.features == "extractor":
            if pipeline is None:
                pipeline = _Pipeline(sim, cfg, params, frame.true_pose)
            pose, pose_cov, xy, covs, rep = pipeline.step(frame)
            labels = label_points(from_frame(xy, frame.true_pose), truth_xy, cfg.label_radius_m)
            real = labels >= 0
            err = xy[real] - to_frame(truth_xy[labels[real]], frame.true_pose)
            feat_err.append(np.hypot(err[:, 0], err[:, 1]))
            feat_nees.append(np.einsum("ki,ki->k", err, np.linalg.solve(covs[real], err[..., None])[..., 0]))
        else:
            if filt is None:
                filt = EkfSlam(params, pose0=frame.true_pose)
            else:
                filt.predict(frame.odom_delta)
            rel = frame.visible_corners_robot_xy
            rng_m = np.hypot(rel[:, 0], rel[:, 1]) + rng.normal(scale=cfg.range_sigma_m, size=len(rel))
            brg = np.arctan2(rel[:, 1], rel[:, 0]) + rng.normal(scale=cfg.bearing_sigma_rad, size=len(rel))
            if cfg.truth_wall_sigma_rad > 0:
                wall = -frame.true_pose[2] + rng.normal(scale=cfg.truth_wall_sigma_rad)
                filt.observe_wall_direction(wall, cfg.truth_wall_sigma_rad)
            rep = filt.observe(rng_m[:, None] * np.column_stack((np.cos(brg), np.sin(brg))))
            pose, pose_cov, labels = filt.pose, filt.pose_cov, frame.visible_corner_ids
        n_obs += labels.size
        n_phantom += int(np.sum(labels == PHANTOM))
        physical = np.where(labels >= 0, cluster[np.maximum(labels, 0)], PHANTOM)
        for k, label in enumerate(physical.tolist()):
            lm_id = int(rep.landmark_ids[k])
            if rep.status[k] == ObsStatus.NEW:
                label_of[lm_id] = label
            elif rep.status[k] == ObsStatus.MATCHED:
                nis_matched.append(float(rep.nis[k]))
                wrong = label_of[lm_id] != label
                n_wrong += int(wrong)
                n_wrong_confirmed += int(wrong and bool(rep.pose_corrected[k]))
        trace.append((frame.true_pose, pose, frame.odom_pose, pose_cov))
    true_p, est_p, odom_p, covs_p = (np.array(c) for c in zip(*trace, strict=True))
    table = (pipeline.slam.ekf if pipeline is not None else filt).landmarks()
    lm_labels = np.array([label_of[int(i)] for i in table.ids], dtype=np.int64)
    use = table.confirmed & (lm_labels >= 0)
    # Each landmark against the nearest point of the physical feature that created it.
    members = cluster[None, :] == lm_labels[use, None]
    d2 = np.where(members, ((truth_xy[None] - table.xy[use, None]) ** 2).sum(axis=2), np.inf)
    err = truth_xy[d2.argmin(axis=1)].reshape(-1, 2) - table.xy[use]
    lm_nees = np.einsum("li,li->l", err, np.linalg.solve(table.cov[use], err[..., None])[..., 0])
    cat = (lambda parts: np.concatenate(parts) if parts else np.zeros(0))
    online, final = pipeline.map_trajectories() if pipeline is not None else (np.zeros((0, 3)),) * 2
    closures = Counter()
    if pipeline is not None and cfg.mapper:
        closures = summary_counts(judge_by_truth(pipeline.closure_attempts, np.array(pipeline.stamps_ns, dtype=np.int64),
                                                 true_p))
    return RunResult(
        true_p, est_p, odom_p, covs_p, np.hypot(err[:, 0], err[:, 1]), lm_nees,
        int(np.sum(table.confirmed & (lm_labels == PHANTOM))), np.array(nis_matched), n_wrong,
        n_wrong_confirmed, n_obs, n_phantom, cat(feat_err), cat(feat_nees), online, final, closures,
    )


def summarise(results: list[RunResult], final_lap_frac: float = McConfig.final_lap_frac) -> dict:
    """Aggregate runs into the figures printed by :func:`main`.

    The first frame is left out of the NEES: the pose is known exactly there.
    """
    n = len(results)
    nees = np.array([pose_nees(r.true_poses[1:], r.est_poses[1:], r.pose_covs[1:]) for r in results])
    mean_nees = nees.mean(axis=0)
    lo, hi = nees_band(n, 3)
    lm_err = np.concatenate([r.landmark_err_m for r in results])
    lm_nees = np.concatenate([r.landmark_nees for r in results])
    lm_lo, lm_hi = nees_band(max(lm_nees.size, 1), 2)
    tail = max(1, round(final_lap_frac * results[0].true_poses.shape[0]))
    feat_err = np.concatenate([r.feature_err_m for r in results])
    feat_nees = np.concatenate([r.feature_nees for r in results])
    nis = np.concatenate([r.nis_matched for r in results])
    nan = float("nan")
    return {
        "n_runs": n,
        "ate_rmse_m": np.array([ate_rmse(r.true_poses, r.est_poses) for r in results]),
        "ate_final_rmse_m": np.array([ate_rmse(r.true_poses[-tail:], r.est_poses[-tail:]) for r in results]),
        "odom_ate_rmse_m": np.array([ate_rmse(r.true_poses, r.odom_poses) for r in results]),
        "final_err_m": np.array([float(np.hypot(*(r.true_poses[-1, :2] - r.est_poses[-1, :2]))) for r in results]),
        "mean_nees_per_step": mean_nees,
        "nees_band": (lo, hi),
        "frac_steps_in_band": float(np.mean((mean_nees >= lo) & (mean_nees <= hi))),
        "frac_steps_above_band": float(np.mean(mean_nees > hi)),
        "landmark_rmse_m": float(np.sqrt(np.mean(lm_err**2))) if lm_err.size else nan,
        "landmark_max_err_m": float(lm_err.max()) if lm_err.size else nan,
        "landmark_mean_nees": float(np.mean(lm_nees)) if lm_nees.size else nan,
        "landmark_nees_band": (lm_lo, lm_hi),
        "landmarks_per_run": float(np.mean([r.landmark_err_m.size for r in results])),
        "phantoms_confirmed": int(sum(r.n_phantom_confirmed for r in results)),
        "mean_nis_matched": float(np.mean(nis)) if nis.size else nan,
        "wrong_associations": int(sum(r.n_wrong for r in results)),
        "wrong_confirmed": int(sum(r.n_wrong_confirmed for r in results)),
        "runs_with_wrong": [i for i, r in enumerate(results) if r.n_wrong_confirmed],
        "matched_observations": int(nis.size),
        "observations": int(sum(r.n_observations for r in results)),
        "phantom_observations": int(sum(r.n_phantom_obs for r in results)),
        "feature_rmse_m": float(np.sqrt(np.mean(feat_err**2))) if feat_err.size else nan,
        "feature_mean_nees": float(np.mean(feat_nees)) if feat_nees.size else nan,
        "map_online_ate_rmse_m": np.array([ate_rmse(r.true_poses, r.map_online_poses) for r in results
                                           if r.map_online_poses.shape == r.true_poses.shape]),
        "map_final_ate_rmse_m": np.array([ate_rmse(r.true_poses, r.map_final_poses) for r in results
                                          if r.map_final_poses.shape == r.true_poses.shape]),
        "closures": sum((r.closures for r in results), Counter()),
    }


def format_summary(s: dict, cfg: McConfig) -> str:
    """Human-readable report of :func:`summarise` output."""
    lo, hi = s["nees_band"]
    m = s["mean_nees_per_step"]
    quarters = np.array_split(m, 4)
    walls = f", wall direction sigma {cfg.truth_wall_sigma_rad} rad" if cfg.truth_wall_sigma_rad > 0 else ""
    noise = (f"sigma_r {cfg.range_sigma_m} m, sigma_b {cfg.bearing_sigma_rad} rad{walls}" if cfg.features == "truth"
             else "denoise -> features -> slam service steps, default configs")
    head = (
        f"EKF-SLAM Monte Carlo: {s['n_runs']} runs x {cfg.n_steps} steps, world {cfg.world_name}, "
        f"features {cfg.features} ({noise}), association {cfg.association}"
    )
    ate = (
        f"ATE RMSE (m)        EKF {s['ate_rmse_m'].mean():.4f} +- {s['ate_rmse_m'].std():.4f} "
        f"(max {s['ate_rmse_m'].max():.4f}); last {100 * cfg.final_lap_frac:.0f} % of the run "
        f"{s['ate_final_rmse_m'].mean():.4f}; final error {s['final_err_m'].mean():.4f}; "
        f"odometry {s['odom_ate_rmse_m'].mean():.4f} +- {s['odom_ate_rmse_m'].std():.4f}"
    )
    lm_lo, lm_hi = s["landmark_nees_band"]
    landmarks = (
        f"landmarks           {s['landmarks_per_run']:.1f} confirmed per run, RMSE {s['landmark_rmse_m']:.4f} m, "
        f"max {s['landmark_max_err_m']:.4f} m, mean NEES {s['landmark_mean_nees']:.2f} "
        f"(band {lm_lo:.2f}-{lm_hi:.2f} if landmarks were independent); "
        f"confirmed phantoms {s['phantoms_confirmed']}"
    )
    nees = (
        f"pose NEES           mean over steps {m.mean():.2f}, max {m.max():.2f}; 95 % band of the run mean "
        f"[{lo:.2f}, {hi:.2f}]; steps inside {100 * s['frac_steps_in_band']:.0f} %, "
        f"above {100 * s['frac_steps_above_band']:.0f} %"
    )
    by_quarter = "pose NEES by quarter of the run: " + ", ".join(f"{q.mean():.2f}" for q in quarters)
    nis = (
        f"matched NIS         mean {s['mean_nis_matched']:.2f} (2.00 if consistent) over "
        f"{s['matched_observations']} of {s['observations']} observations "
        f"({s['phantom_observations']} phantoms); wrong pairings {s['wrong_associations']}, "
        f"{s['wrong_confirmed']} with confirmed landmarks (runs {s['runs_with_wrong']})"
    )
    lines = [head, ate, landmarks, nees, by_quarter, nis]
    if s["map_final_ate_rmse_m"].size:
        on, fin = s["map_online_ate_rmse_m"], s["map_final_ate_rmse_m"]
        lines.append(f"mapper ATE RMSE (m) final {fin.mean():.4f} +- {fin.std():.4f} (max {fin.max():.4f}); "
                     f"as published at each step {on.mean():.4f} +- {on.std():.4f} (max {on.max():.4f})")
        c = s["closures"]
        precision, recall = precision_recall(c)
        lines.append(f"mapper closures     {c['accepted']} accepted of {sum(c[v] for v in VERDICTS)} tried, "
                     f"{c['accepted.right']} right (within {RIGHT_M} m and {np.degrees(RIGHT_RAD):.0f} deg of the truth), "
                     f"{c['false_accepts']} false accepts (chi2 > {CHI2_99:.2f}), {c['removed']} removed; "
                     f"precision {precision:.3f}, recall {recall:.3f} (of the {sum(c[v + '.right'] for v in VERDICTS)} "
                     "right attempts)")
    if cfg.features == "extractor":
        lines.append(f"features            RMSE {s['feature_rmse_m']:.4f} m, mean NEES against their own "
                     f"covariance {s['feature_mean_nees']:.2f} (2.00 if calibrated)")
    return "\n".join(lines)


def run_many(cfg: McConfig, jobs: int = 1) -> list[RunResult]:
    """All ``cfg.n_runs`` runs, in ``jobs`` worker processes; results in run order."""
    if jobs <= 1:
        return [run_once(cfg, i) for i in range(cfg.n_runs)]
    # Spawned, not forked: a compiled kernel's threads, once started, cannot be copied by a fork.
    with ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
        return list(pool.map(run_once, [cfg] * cfg.n_runs, range(cfg.n_runs)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="Monte-Carlo accuracy and consistency of the EKF-SLAM on the simulator.")
    ap.add_argument("--runs", type=int, default=McConfig.n_runs)
    ap.add_argument("--steps", type=int, default=McConfig.n_steps)
    ap.add_argument("--world", default=McConfig.world_name)
    ap.add_argument("--features", choices=FEATURE_SOURCES, default=McConfig.features,
                    help="true corners plus matched noise, or the real denoise -> features -> slam steps")
    ap.add_argument("--association", choices=("nn", "jcbb"), default=McConfig.association)
    ap.add_argument("--range-sigma-m", type=float, default=McConfig.range_sigma_m, help="truth features only")
    ap.add_argument("--bearing-sigma-rad", type=float, default=McConfig.bearing_sigma_rad, help="truth features only")
    ap.add_argument("--truth-wall-sigma-rad", type=float, default=McConfig.truth_wall_sigma_rad,
                    help="truth features only: add the true wall direction with this noise (0: none)")
    ap.add_argument("--odom-scale", type=float, default=1.0, help="multiply the simulator's odometry noise")
    ap.add_argument("--seed", type=int, default=McConfig.seed)
    ap.add_argument("--jobs", type=int, default=1, help="worker processes")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="SERVICE.NAME=VALUE",
                    help="extractor only: override a denoise/features/slam/mapper setting, e.g. slam.scan_matching=false")
    ap.add_argument("--mapper", action="store_true",
                    help="extractor only: run the mapper (loop closing) behind the EKF and score its trajectories")
    args = ap.parse_args(argv)
    if args.mapper and args.features != "extractor":
        ap.error("--mapper needs --features extractor")
    base = OdometryNoise()
    cfg = McConfig(
        n_runs=args.runs, n_steps=args.steps, world_name=args.world, features=args.features,
        association=args.association, range_sigma_m=args.range_sigma_m, bearing_sigma_rad=args.bearing_sigma_rad,
        truth_wall_sigma_rad=args.truth_wall_sigma_rad,
        seed=args.seed, stage_sets=tuple(args.sets), mapper=args.mapper,
        odometry=OdometryNoise(base.trans_sigma_per_sqrt_m * args.odom_scale, base.rot_sigma_per_sqrt_rad * args.odom_scale,
                               base.rot_sigma_per_sqrt_m * args.odom_scale),
    )
    print(format_summary(summarise(run_many(cfg, args.jobs), cfg.final_lap_frac), cfg))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
