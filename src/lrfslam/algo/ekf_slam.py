"""EKF-SLAM with 2-D point landmarks (corners and jump edges), O(n²) per observation.

State and symbols (used only inside this module; public names are by role):

* ``x`` (n,) = ``[x_m, y_m, theta_rad, psi_rad, m1x_m, m1y_m, ...]``, n = 4 + 2L;
  ``P`` (n, n) its covariance. ``psi`` is the building's orientation: the
  direction of its walls in the map frame, modulo 90°.
* Motion: ``x_r ← x_r ⊕ u`` with ``u = (dx_m, dy_m, dtheta_rad)`` the odometry
  increment in the previous robot frame; ``Q_u`` (3, 3) its covariance.
* Measurement of landmark ``m``: ``h = (range_m, bearing_rad)`` in the robot
  frame; ``R`` (2, 2) its covariance; ``H`` (2, n) the Jacobian, non-zero only in
  the 3 pose columns and the 2 columns of ``m``.
* Wall-direction measurement (not in the paper): the scan's dominant wall
  direction ``h = wrap_quarter(psi - theta)`` (rad, modulo 90°); ``H`` (1, n) is
  -1 in the ``theta`` column and +1 in the ``psi`` column.

Design choices
--------------
* **Range–bearing model.** Features arrive as robot-frame points with a 2×2
  covariance and are converted to (range, bearing) here. The laser's errors are
  polar (range noise along the beam, bearing quantisation), so the parameter
  noise is naturally expressed there and the landmark-initialisation Jacobians
  are the standard ones (Bailey's ``augment.m``). The point covariance is mapped
  through the polar Jacobian and the parameter noise (``corner_range_sigma_m``,
  ``corner_bearing_sigma_rad``) is *added* to it: it models error the extractor's
  fit does not see (corner rounding, beam quantisation, timing).
* **Tentative landmarks live in the state.** A new feature is augmented with full
  cross-covariances at once, so dropping a tentative is exact marginalisation
  (delete its rows and columns). Until it is confirmed, its re-observations are
  applied with a *Schmidt* (consider) update: the gain is zero on the pose and on
  every other landmark, so a phantom feature can refine its own estimate but
  never pull the robot or the map. Joseph form for this sub-optimal gain reduces
  to an O(n) change of the landmark's rows, and ``P`` stays the true error
  covariance of the estimator.
* **Confirmation.** A landmark is confirmed after ``min_sightings_to_confirm``
  gated sightings (the creating one included). Backward-search features
  (kind 1, jump edges) are viewpoint dependent: a receding wall's edge or an
  occluded phantom moves with the robot. They are confirmed only if they were
  also re-observed consistently (inside the association gate) from a viewing
  direction that changed by at least ``backward_min_view_change_rad``. A
  landmark once seen as a forward-search corner (kind 0) becomes kind 0.
* **Building orientation in the state, after the pose.** ``psi`` sits at index 3
  so that the pose block and every landmark's offset stay fixed whatever the
  number of landmarks; :meth:`EkfSlam.predict` leaves it alone (the building does
  not move) and only transforms its cross-covariance with the pose, as for a
  landmark. Until the first wall direction is accepted ``psi`` is *unset*: its
  mean is 0 and its row and column of ``P`` are zero, which every update keeps
  exactly zero (the gain on a state uncorrelated with everything is zero). The
  first measurement initialises it like a new landmark, ``psi = theta + z`` with
  the cross-covariances of ``theta``. Walls are measured modulo 90°, so the
  innovation is wrapped to [-45°, 45°) and the measurement is refused when the
  gate would reach past ±45° (a quarter-turn alias would fit as well).
* **Association** is done for all observations of a scan against the prior
  (gated NN or JCBB, ``association.py``), then the paired observations are
  applied one by one, then the new landmarks are augmented. Observations with
  ``gate_assoc_chi2 <= min NIS <= gate_new_chi2`` are discarded as ambiguous
  (Bailey's two-gate policy).

References
----------
T. Bailey, ekfslam_v2 (2004): ``predict.m``, ``augment.m``,
``KF_cholesky_update.m``, ``data_associate.m``.
S. F. Schmidt, "Application of state-space methods to navigation problems",
Advances in Control Systems 3, 1966 (consider / Schmidt-Kalman update).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from lrfslam.algo import association
from lrfslam.algo.checks import require_finite
from lrfslam.algo.geometry import compose, wrap_angle
from lrfslam.algo.wall_direction import wrap_quarter
from lrfslam.errors import ConfigError, InputError

FORWARD = 0
BACKWARD = 1
SNAPSHOT_FORMAT = 2  # 2: the building orientation psi at index 3 (format 1 had none; migrated)
_PSI = 3  # index of the building orientation in the state
_LM0 = 4  # index of the first landmark coordinate
_ROW_BLOCK = 64  # rows of P per block of the covariance downdate (64 × n doubles fit in L2)

#: Factor on every standard deviation of a backward-search feature. A jump edge's point is the last
#: beam on the near surface: it errs 2–3× its reported sigma, biased towards the robot the same way in
#: every scan, so the error does not average out over scans as the model assumes; the factor keeps the
#: filter's position NEES in its band on the simulator without letting door jambs' faces swap.
BACKWARD_SIGMA_SCALE = 6.0
#: Features (and landmark predictions) closer than this (m) are not used: the bearing is ill-defined
#: at the sensor.
MIN_FEATURE_RANGE_M = 0.05
#: Search budget of JCBB per scan (nodes).
JCBB_MAX_NODES = 100_000
#: χ²₁ gate on the NIS of a wall-direction measurement (6.63 = 99 %).
GATE_WALL_CHI2 = 6.63


class ObsStatus(enum.IntEnum):
    """What :meth:`EkfSlam.observe` did with one observation."""

    MATCHED = 0  # paired with an existing landmark and applied
    NEW = 1  # started a new (tentative) landmark
    AMBIGUOUS = 2  # between the two gates, or lost a contested landmark: discarded
    REJECTED = 3  # too close to the sensor, or the landmark cap is reached


class WallStatus(enum.IntEnum):
    """What :meth:`EkfSlam.observe_wall_direction` did with one measurement."""

    INITIALISED = 0  # first accepted measurement: set the building orientation
    APPLIED = 1  # inside the gate: full update
    GATED = 2  # NIS above GATE_WALL_CHI2: discarded
    AMBIGUOUS = 3  # the gate spans ±45°: a quarter-turn alias fits as well; discarded


@dataclass(frozen=True)
class EkfParams:
    """Parameters of :class:`EkfSlam`; every noise is a standard deviation.

    Odometry errors are random walks (as in ``lrfslam.sim.odometry``): their
    variance grows linearly with the distance travelled and the angle turned,
    so a sigma "per metre" is the standard deviation accumulated over one metre
    and the filter's uncertainty does not depend on how often ``predict`` runs
    (the sideways drift a heading walk causes within a step included; see
    :meth:`EkfSlam.odometry_cov`).

    Attributes
    ----------
    odom_trans_sigma_per_sqrt_m : float
        Along-track distance error accumulated over 1 m travelled (m).
    odom_rot_sigma_per_sqrt_rad : float
        Heading error accumulated over 1 rad turned (rad).
    odom_rot_sigma_per_sqrt_m : float
        Heading error accumulated over 1 m travelled (rad); integrated along the
        way, it also drifts the position sideways.
    odom_trans_sigma_floor_m, odom_rot_sigma_floor_rad : float
        Isotropic translation and heading noise added at every
        :meth:`EkfSlam.predict` call, even without motion (m, rad).
    corner_range_sigma_m, corner_bearing_sigma_rad : float
        Model error of a feature in range (m) and bearing (rad), added to the
        extractor's covariance; > 0.
    association : {"nn", "jcbb"}
        Gated nearest neighbour, or joint compatibility branch and bound.
    gate_assoc_chi2 : float
        χ²₂ gate on the NIS to pair an observation (9.21 = 99 %). JCBB uses the
        same probability for its joint χ²_{2k} gate.
    gate_new_chi2 : float
        Minimum NIS against every landmark to start a new one (≥ gate_assoc_chi2).
    unique_match_required : bool
        Discard an observation as ambiguous when another landmark would fit it
        as well: a second landmark inside its gate (NN), or a swap that keeps
        the hypothesis jointly compatible (JCBB). Door jambs 1 m apart make a
        nearest-neighbour guess at loop closure a coin toss, and one wrong
        pairing corrupts an EKF for good; the price is fewer pairings in
        repetitive scenes until the pose uncertainty shrinks.
    min_sightings_to_confirm : int
        Gated sightings, the creating one included, to confirm a landmark.
    backward_min_view_change_rad : float
        Change of viewing direction (rad) a backward-search landmark must have
        been seen across before it can be confirmed.
    tentative_max_age_updates : int
        An unconfirmed landmark is dropped this many :meth:`EkfSlam.observe`
        calls after its creation.
    max_landmarks : int
        Cap on the number of landmarks (tentative and confirmed).
    wall_model_sigma_rad : float
        Model error of a wall-direction measurement (rad), added in quadrature to
        the extractor's sigma: walls that are not quite square or straight give an
        error that does not average out over scans.
    """

    # The simulator's default odometry noise (lrfslam.sim.odometry.OdometryNoise),
    # so that the filter is matched at "default noise"; raise them for a real robot.
    odom_trans_sigma_per_sqrt_m: float = 0.02
    odom_rot_sigma_per_sqrt_rad: float = 0.02
    odom_rot_sigma_per_sqrt_m: float = 0.005
    odom_trans_sigma_floor_m: float = 1e-4
    odom_rot_sigma_floor_rad: float = 1e-4
    # Small: the extractor's own covariance of a refined corner is already
    # conservative in simulation (2-dof NEES 0.45-0.65 below 3.2 m, docs/slam.md).
    corner_range_sigma_m: float = 0.005
    corner_bearing_sigma_rad: float = 0.002
    association: str = "nn"
    gate_assoc_chi2: float = 9.21
    gate_new_chi2: float = 25.0
    unique_match_required: bool = True
    min_sightings_to_confirm: int = 2
    backward_min_view_change_rad: float = 0.2
    tentative_max_age_updates: int = 30
    max_landmarks: int = 1000
    # Real walls are square to a fraction of a degree; in the simulator (exact
    # walls) this guard costs under 1 mm of ATE, docs/slam.md.
    wall_model_sigma_rad: float = 0.002

    def __post_init__(self) -> None:
        sigmas = (
            "odom_trans_sigma_per_sqrt_m", "odom_rot_sigma_per_sqrt_rad", "odom_rot_sigma_per_sqrt_m",
            "odom_trans_sigma_floor_m", "odom_rot_sigma_floor_rad", "corner_range_sigma_m",
            "corner_bearing_sigma_rad", "backward_min_view_change_rad",
            "wall_model_sigma_rad",
        )
        require_finite(self, sigmas, positive=False)
        if not (self.corner_range_sigma_m > 0 and self.corner_bearing_sigma_rad > 0):
            # They keep every innovation covariance S positive definite.
            raise ConfigError("corner_range_sigma_m and corner_bearing_sigma_rad must be > 0")
        if self.association not in ("nn", "jcbb"):
            raise ConfigError(f"association must be 'nn' or 'jcbb', got {self.association!r}")
        if not 0 < self.gate_assoc_chi2 <= self.gate_new_chi2:
            raise ConfigError("need 0 < gate_assoc_chi2 <= gate_new_chi2")
        for name in ("min_sightings_to_confirm", "tentative_max_age_updates"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be >= 1")
        if self.max_landmarks < 0:
            raise ConfigError("max_landmarks must be >= 0")


@dataclass(frozen=True, eq=False)
class LandmarkTable:
    """Read-only copy of the map, one row per landmark, ordered by id.

    Attributes
    ----------
    ids : ndarray, shape (L,), int64
        Stable ids, never reused after a landmark is dropped.
    xy : ndarray, shape (L, 2)
        World position (m).
    cov : ndarray, shape (L, 2, 2)
        Marginal position covariance (m²).
    kinds : ndarray, shape (L,), int8
        0 forward-search corner, 1 backward-search (jump edge) only.
    sightings : ndarray, shape (L,), int64
        Gated sightings, the creating one included.
    confirmed : ndarray, shape (L,), bool
        True once the landmark corrects the pose.
    """

    ids: np.ndarray
    xy: np.ndarray
    cov: np.ndarray
    kinds: np.ndarray
    sightings: np.ndarray
    confirmed: np.ndarray


@dataclass(frozen=True, eq=False)
class UpdateReport:
    """Diagnostics of one :meth:`EkfSlam.observe` call (K observations).

    Attributes
    ----------
    landmark_ids : ndarray, shape (K,), int64
        Id of the landmark each observation was paired with or created, else -1.
    status : ndarray, shape (K,), int8
        :class:`ObsStatus` code per observation.
    nis : ndarray, shape (K,)
        NIS against the prior: of the chosen pairing when matched, else the
        smallest over all landmarks (inf without any).
    pose_corrected : ndarray, shape (K,), bool
        True where the update was a full one (confirmed landmark), False where it
        was a Schmidt update of a tentative landmark or no update at all.
    n_matched, n_new, n_ambiguous, n_rejected : int
        Counts of each status.
    n_confirmed : int
        Landmarks confirmed by this call.
    n_dropped : int
        Tentative landmarks dropped by age in this call.
    joint_nis : float
        JCBB's joint NIS of the chosen hypothesis (NaN with "nn").
    search_nodes : int
        JCBB interpretation-tree nodes visited (0 with "nn").
    """

    landmark_ids: np.ndarray
    status: np.ndarray
    nis: np.ndarray
    pose_corrected: np.ndarray
    n_matched: int
    n_new: int
    n_ambiguous: int
    n_rejected: int
    n_confirmed: int
    n_dropped: int
    joint_nis: float
    search_nodes: int


@dataclass(frozen=True)
class WallUpdate:
    """Outcome of one :meth:`EkfSlam.observe_wall_direction` call.

    Attributes
    ----------
    status : WallStatus
    nis : float
        NIS of the wrapped innovation against the prior (χ²₁ if consistent); NaN
        when the measurement initialised the building orientation.
    """

    status: WallStatus
    nis: float


class EkfSlam:
    """Mutable EKF-SLAM filter (in the manner of filterpy's filter objects).

    Parameters
    ----------
    params : EkfParams
    pose0 : array_like, shape (3,)
        Initial pose ``(x_m, y_m, theta_rad)``.
    pose0_cov : array_like, shape (3, 3), optional
        Initial pose covariance; zeros (the map frame is the first pose) if None.

    Notes
    -----
    Costs with n = 4 + 2L: :meth:`predict` O(n); one paired observation O(n²)
    (rank-2 downdate) or O(n) (tentative landmark); one wall direction O(n²)
    (rank-1 downdate); augmentation and dropping O(n²) (the covariance is
    reallocated).
    """

    def __init__(self, params: EkfParams, pose0=(0.0, 0.0, 0.0), pose0_cov=None) -> None:
        pose = np.asarray(pose0, dtype=float)
        cov = np.zeros((3, 3)) if pose0_cov is None else np.asarray(pose0_cov, dtype=float)
        if pose.shape != (3,) or cov.shape != (3, 3) or not np.all(np.isfinite(cov)):
            raise InputError("pose0 must have shape (3,) and pose0_cov shape (3, 3), finite")
        self.params = params
        self._x = np.concatenate((pose, [0.0]))  # psi unset
        self._x[2] = wrap_angle(self._x[2])
        self._P = np.zeros((_LM0, _LM0))
        self._P[:3, :3] = 0.5 * (cov + cov.T)
        self._psi_set = False
        self._ids = np.zeros(0, dtype=np.int64)
        self._kinds = np.zeros(0, dtype=np.int8)
        self._sightings = np.zeros(0, dtype=np.int64)
        self._confirmed = np.zeros(0, dtype=bool)
        self._born = np.zeros(0, dtype=np.int64)  # observe() count at creation
        self._view_ref = np.zeros(0)  # viewing direction at creation (rad, world)
        self._view_spread = np.zeros(0)  # largest change of viewing direction seen (rad)
        self._next_id = 0
        self._n_observe = 0

    # ------------------------------------------------------------------ views
    @property
    def pose(self) -> np.ndarray:
        """Robot pose ``(x_m, y_m, theta_rad)``, shape (3,), a copy."""
        return self._x[:3].copy()

    @property
    def pose_cov(self) -> np.ndarray:
        """Pose covariance, shape (3, 3), a copy."""
        return self._P[:3, :3].copy()

    @property
    def building_orientation(self) -> tuple[float, float] | None:
        """``(psi_rad, variance_rad2)``: the walls' direction in the map frame mod 90°; None until set."""
        return (float(self._x[_PSI]), float(self._P[_PSI, _PSI])) if self._psi_set else None

    @property
    def state_mean(self) -> np.ndarray:
        """Full state ``[pose, psi, m1, m2, ...]``, shape (4 + 2L,), landmarks in id order; a copy."""
        return self._x.copy()

    @property
    def state_cov(self) -> np.ndarray:
        """Full covariance, shape (4 + 2L, 4 + 2L), a copy."""
        return self._P.copy()

    @property
    def n_landmarks(self) -> int:
        """Number of landmarks L (tentative and confirmed)."""
        return self._ids.size

    def landmarks(self) -> LandmarkTable:
        """Copy of the map; see :class:`LandmarkTable`."""
        n = self._ids.size
        xy = self._x[_LM0:].reshape(n, 2).copy()
        cov = self._P[_LM0:, _LM0:].reshape(n, 2, n, 2)[np.arange(n), :, np.arange(n), :].copy()
        return LandmarkTable(
            self._ids.copy(), xy, cov, self._kinds.copy(), self._sightings.copy(),
            self._confirmed.copy(),
        )

    # ------------------------------------------------------------- prediction
    def predict(self, delta) -> None:
        """Apply one odometry increment with the odometry noise model; O(n).

        Parameters
        ----------
        delta : array_like, shape (3,)
            ``(dx_m, dy_m, dtheta_rad)`` in the previous robot frame.
        """
        self.predict_with_cov(delta, self.odometry_cov(delta))

    def odometry_cov(self, delta) -> np.ndarray:
        """Covariance (3, 3) the odometry model gives increment ``delta`` (3,), in its own frame.

        A wheel-scale error along the direction of travel, heading random
        walks, the sideways drift those walks cause on the way, and the
        isotropic floor (m², m·rad, rad²).

        The heading error grows along the step, so the position ends up beside
        where odometry puts it: with a heading variance ``v`` accumulated evenly
        over ``d`` metres, the sideways error has variance ``v d²/3`` and
        covariance ``v d/2`` with the heading (the integral of a random walk).
        Per scan this is nothing (millimetres travelled); for one increment
        bridging many scans (a slam resumed from its checkpoint) it is most of
        the error, and leaving it out made the filter sure of a wrong pose.
        With it, one increment has the covariance of the many small ones it
        replaces along a straight line.
        """
        u = np.asarray(delta, dtype=float)
        if u.shape != (3,) or not np.all(np.isfinite(u)):
            raise InputError(f"delta must be 3 finite numbers, got {delta!r}")
        p = self.params
        dist = float(np.hypot(u[0], u[1]))
        heading_walk = p.odom_rot_sigma_per_sqrt_rad**2 * abs(u[2]) + p.odom_rot_sigma_per_sqrt_m**2 * dist
        q_u = np.diag([p.odom_trans_sigma_floor_m**2, p.odom_trans_sigma_floor_m**2,
                       p.odom_rot_sigma_floor_rad**2 + heading_walk])
        if dist > 0:
            along = u[:2] / dist
            left = np.array([-along[1], along[0]])
            q_u[:2, :2] += (p.odom_trans_sigma_per_sqrt_m**2 * dist * np.outer(along, along)
                            + heading_walk * dist**2 / 3.0 * np.outer(left, left))
            q_u[:2, 2] = q_u[2, :2] = heading_walk * dist / 2.0 * left
        return q_u

    def predict_with_cov(self, delta, delta_cov) -> None:
        """Apply one motion increment with its own covariance (e.g. from scan matching); O(n).

        Parameters
        ----------
        delta : array_like, shape (3,)
            ``(dx_m, dy_m, dtheta_rad)`` in the previous robot frame.
        delta_cov : array_like, shape (3, 3)
            Its covariance in that frame (m², m·rad, rad²), symmetric positive semi-definite.
        """
        u = np.asarray(delta, dtype=float)
        q_u = np.asarray(delta_cov, dtype=float)
        if u.shape != (3,) or not np.all(np.isfinite(u)):
            raise InputError(f"delta must be 3 finite numbers, got {delta!r}")
        if q_u.shape != (3, 3) or not np.all(np.isfinite(q_u)):
            raise InputError("delta_cov must be a finite (3, 3) array")
        q_u = 0.5 * (q_u + q_u.T)
        c, s = np.cos(self._x[2]), np.sin(self._x[2])
        # Jacobians of pose ⊕ u with respect to the pose (Gv) and to u (Gu).
        gv = np.array([[1.0, 0.0, -s * u[0] - c * u[1]], [0.0, 1.0, c * u[0] - s * u[1]], [0, 0, 1]])
        gu = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        self._x[:3] = compose(self._x[:3], u)
        # Only the pose rows and columns change (Bailey's predict.m): O(n). The
        # building orientation psi is a fixed quantity like a landmark.
        P = self._P
        P[:3, :3] = gv @ P[:3, :3] @ gv.T + gu @ q_u @ gu.T
        P[:3, 3:] = gv @ P[:3, 3:]
        P[3:, :3] = P[:3, 3:].T

    # ---------------------------------------------------------------- updates
    def update_known(self, landmark_id: int, range_bearing, range_bearing_cov) -> float:
        """Full EKF correction with a known association; no bookkeeping.

        Parameters
        ----------
        landmark_id : int
            Id of an existing landmark.
        range_bearing : array_like, shape (2,)
            Measured ``(range_m, bearing_rad)`` in the robot frame.
        range_bearing_cov : array_like, shape (2, 2)
            Its covariance (m², m·rad, rad²).

        Returns
        -------
        float
            NIS of the innovation against the prior.
        """
        hits = np.flatnonzero(self._ids == landmark_id)
        if hits.size != 1:
            raise InputError(f"no landmark with id {landmark_id}")
        z = np.asarray(range_bearing, dtype=float)
        cov = np.asarray(range_bearing_cov, dtype=float)
        if z.shape != (2,) or cov.shape != (2, 2):
            raise InputError("range_bearing must have shape (2,) and its cov (2, 2)")
        return self._correct(int(hits[0]), z, cov, full=True)

    def observe(self, points_xy, covs=None, kinds=None) -> UpdateReport:
        """Associate, apply and augment one scan's features.

        Parameters
        ----------
        points_xy : array_like, shape (K, 2)
            Feature positions in the robot frame (m).
        covs : array_like, shape (K, 2, 2), optional
            Their covariances from the extractor (m²); zeros if None.
        kinds : array_like, shape (K,), optional
            0 forward-search corner, 1 backward-search jump edge; 0 if None.

        Returns
        -------
        UpdateReport
        """
        pts, covs_xy, kinds_arr = self._check_features(points_xy, covs, kinds)
        p = self.params
        self._n_observe += 1
        n_obs = pts.shape[0]
        z, r_obs, valid = self._to_range_bearing(pts, covs_xy, kinds_arr)

        nu, s_ind = self._individual_innovations(z, r_obs)
        nis, log_det = association.nis_2d(nu, s_ind)
        nis[~valid] = np.inf
        joint_nis, nodes = np.nan, 0
        if p.association == "nn":
            pairing = association.nearest_neighbour(nis, log_det, p.gate_assoc_chi2, p.unique_match_required)
        else:
            result = self._jcbb(nu, r_obs, nis)
            pairing, joint_nis, nodes = result.pairing, result.joint_nis, result.nodes
        min_nis = nis.min(axis=1) if nis.shape[1] else np.full(n_obs, np.inf)

        status = np.full(n_obs, ObsStatus.AMBIGUOUS, dtype=np.int8)
        out_ids = np.full(n_obs, -1, dtype=np.int64)
        out_nis = min_nis.copy()
        corrected = np.zeros(n_obs, dtype=bool)
        n_confirmed = 0
        # Updates never reorder landmarks (augmentation and dropping come after),
        # so the pairing's indices stay valid through the loop.
        for k in np.flatnonzero(pairing >= 0):
            i = int(pairing[k])
            out_nis[k] = nis[k, i]
            was_confirmed = bool(self._confirmed[i])
            self._register_sighting(i, int(kinds_arr[k]))
            n_confirmed += int(self._confirmed[i] and not was_confirmed)
            corrected[k] = bool(self._confirmed[i])
            self._correct(i, z[k], r_obs[k], full=corrected[k])
            status[k], out_ids[k] = ObsStatus.MATCHED, self._ids[i]

        for k in np.flatnonzero(pairing < 0):
            if not valid[k]:
                status[k] = ObsStatus.REJECTED
            elif min_nis[k] > p.gate_new_chi2:
                if self._ids.size >= p.max_landmarks:
                    status[k] = ObsStatus.REJECTED
                else:
                    out_ids[k] = self._augment(z[k], r_obs[k], int(kinds_arr[k]))
                    status[k] = ObsStatus.NEW
                    n_confirmed += int(self._confirmed[-1])

        n_dropped = self._drop_expired()
        counts = np.bincount(status, minlength=len(ObsStatus))
        return UpdateReport(
            out_ids, status, out_nis, corrected,
            n_matched=int(counts[ObsStatus.MATCHED]), n_new=int(counts[ObsStatus.NEW]),
            n_ambiguous=int(counts[ObsStatus.AMBIGUOUS]), n_rejected=int(counts[ObsStatus.REJECTED]),
            n_confirmed=n_confirmed, n_dropped=n_dropped, joint_nis=float(joint_nis),
            search_nodes=int(nodes),
        )

    def observe_wall_direction(self, direction_rad: float, sigma_rad: float) -> WallUpdate:
        """Correct the heading with the scan's dominant wall direction modulo 90°; O(n²).

        Model ``h = wrap_quarter(psi - theta)``; the innovation is wrapped to
        [-π/4, π/4). The first call sets ``psi`` (see the module docstring).

        Parameters
        ----------
        direction_rad : float
            Direction of the walls in the robot frame, modulo 90° (any representative).
        sigma_rad : float
            Its standard deviation (> 0); ``wall_model_sigma_rad`` is added in quadrature.

        Returns
        -------
        WallUpdate
        """
        z, sigma = float(direction_rad), float(sigma_rad)
        if not (np.isfinite(z) and np.isfinite(sigma) and sigma > 0):
            raise InputError(f"wall direction needs a finite direction and sigma > 0, got {z!r}, {sigma!r}")
        p = self.params
        r = sigma**2 + p.wall_model_sigma_rad**2
        P = self._P
        if not self._psi_set:
            # psi = theta + z: augmentation with d psi / d theta = 1 (its row was zero).
            row = P[2].copy()
            row[_PSI] = P[2, 2] + r
            P[_PSI], P[:, _PSI] = row, row
            self._x[_PSI] = wrap_quarter(self._x[2] + z)
            self._psi_set = True
            return WallUpdate(WallStatus.INITIALISED, float("nan"))
        pht = P[:, _PSI] - P[:, 2]  # P H^T, (n,)
        s = float(pht[_PSI] - pht[2]) + r
        nu = wrap_quarter(z - (self._x[_PSI] - self._x[2]))
        nis = nu * nu / s
        if GATE_WALL_CHI2 * s >= (0.25 * np.pi) ** 2:
            # The gate reaches a quarter turn away: an alias of the walls would pass it too.
            return WallUpdate(WallStatus.AMBIGUOUS, nis)
        if nis > GATE_WALL_CHI2:
            return WallUpdate(WallStatus.GATED, nis)
        self._full_update(pht[:, None] / np.sqrt(s), np.array([nu / np.sqrt(s)]))
        return WallUpdate(WallStatus.APPLIED, nis)

    # ------------------------------------------------------------ checkpoints
    def snapshot(self) -> dict:
        """Everything needed to resume the filter, as arrays and scalars (copies)."""
        return {
            "format": SNAPSHOT_FORMAT,
            "state_mean": self._x.copy(),
            "state_cov": self._P.copy(),
            "psi_set": self._psi_set,
            "landmark_ids": self._ids.copy(),
            "landmark_kinds": self._kinds.copy(),
            "landmark_sightings": self._sightings.copy(),
            "landmark_confirmed": self._confirmed.copy(),
            "landmark_born": self._born.copy(),
            "landmark_view_ref_rad": self._view_ref.copy(),
            "landmark_view_spread_rad": self._view_spread.copy(),
            "next_id": self._next_id,
            "n_observe": self._n_observe,
        }

    @classmethod
    def restore(cls, params: EkfParams, snapshot: dict) -> EkfSlam:
        """Rebuild a filter from :meth:`snapshot` output (e.g. loaded from an .npz).

        A format-1 snapshot (before the building orientation) is migrated: ``psi``
        is inserted after the pose, unset.

        Raises
        ------
        InputError
            If the snapshot is of another format or its arrays disagree in size.
        """
        try:
            fmt = int(snapshot["format"])
            if fmt not in (1, SNAPSHOT_FORMAT):
                raise InputError(f"snapshot format {fmt} is not {SNAPSHOT_FORMAT} (or 1, which is migrated)")
            x = np.array(snapshot["state_mean"], dtype=float)
            P = np.array(snapshot["state_cov"], dtype=float)
            psi_set = bool(snapshot["psi_set"]) if fmt == SNAPSHOT_FORMAT else False
            per_lm = {
                "_ids": np.array(snapshot["landmark_ids"], dtype=np.int64),
                "_kinds": np.array(snapshot["landmark_kinds"], dtype=np.int8),
                "_sightings": np.array(snapshot["landmark_sightings"], dtype=np.int64),
                "_confirmed": np.array(snapshot["landmark_confirmed"], dtype=bool),
                "_born": np.array(snapshot["landmark_born"], dtype=np.int64),
                "_view_ref": np.array(snapshot["landmark_view_ref_rad"], dtype=float),
                "_view_spread": np.array(snapshot["landmark_view_spread_rad"], dtype=float),
            }
            next_id, n_observe = int(snapshot["next_id"]), int(snapshot["n_observe"])
        except KeyError as exc:
            raise InputError(f"snapshot lacks {exc}") from None
        if x.ndim != 1 or P.shape != (x.size, x.size):
            raise InputError("snapshot state_mean / state_cov shapes disagree")
        if fmt == 1:
            x = np.insert(x, _PSI, 0.0)
            P = np.insert(np.insert(P, _PSI, 0.0, axis=0), _PSI, 0.0, axis=1)
        n_lm = (x.size - _LM0) // 2
        if x.size < _LM0 or x.size != _LM0 + 2 * n_lm:
            raise InputError("snapshot state_mean has no room for the pose, psi and whole landmarks")
        if not psi_set and (x[_PSI] != 0 or np.any(P[_PSI] != 0) or np.any(P[:, _PSI] != 0)):
            raise InputError("snapshot has an unset building orientation with a non-zero mean or covariance")
        if any(a.shape != (n_lm,) for a in per_lm.values()):
            raise InputError("snapshot landmark arrays disagree with the state size")
        if n_lm and next_id <= per_lm["_ids"].max():
            raise InputError("snapshot next_id would reuse a landmark id")
        filt = cls(params)
        filt._x, filt._P, filt._psi_set = x, P, psi_set
        for name, arr in per_lm.items():
            setattr(filt, name, arr)
        filt._next_id, filt._n_observe = next_id, n_observe
        return filt

    # ---------------------------------------------------------------- helpers
    def _check_features(self, points_xy, covs, kinds):
        pts = np.asarray(points_xy, dtype=float).reshape(-1, 2) if np.size(points_xy) else np.zeros((0, 2))
        n_obs = pts.shape[0]
        covs_xy = np.zeros((n_obs, 2, 2)) if covs is None else np.asarray(covs, dtype=float)
        kinds_arr = np.zeros(n_obs, dtype=np.int8) if kinds is None else np.asarray(kinds).astype(np.int8)
        if covs_xy.shape != (n_obs, 2, 2) or kinds_arr.shape != (n_obs,):
            raise InputError(f"covs must be ({n_obs}, 2, 2) and kinds ({n_obs},)")
        if not (np.all(np.isfinite(pts)) and np.all(np.isfinite(covs_xy))):
            raise InputError("feature points and covariances must be finite")
        if not np.all((kinds_arr == FORWARD) | (kinds_arr == BACKWARD)):
            raise InputError("kinds must be 0 (forward) or 1 (backward)")
        return pts, covs_xy, kinds_arr

    def _to_range_bearing(self, pts, covs_xy, kinds_arr):
        """Polar measurements (K, 2), their covariances (K, 2, 2), usable mask (K,)."""
        p = self.params
        rng = np.hypot(pts[:, 0], pts[:, 1])
        valid = rng >= MIN_FEATURE_RANGE_M
        safe = np.where(valid, rng, 1.0)
        z = np.column_stack((rng, np.arctan2(pts[:, 1], pts[:, 0])))
        # d(range, bearing) / d(x, y) at each point.
        jac = np.empty((pts.shape[0], 2, 2))
        jac[:, 0, 0], jac[:, 0, 1] = pts[:, 0] / safe, pts[:, 1] / safe
        jac[:, 1, 0], jac[:, 1, 1] = -pts[:, 1] / safe**2, pts[:, 0] / safe**2
        r_obs = jac @ covs_xy @ jac.transpose(0, 2, 1)
        r_obs[:, 0, 0] += p.corner_range_sigma_m**2
        r_obs[:, 1, 1] += p.corner_bearing_sigma_rad**2
        r_obs[kinds_arr == BACKWARD] *= BACKWARD_SIGMA_SCALE**2
        return z, 0.5 * (r_obs + r_obs.transpose(0, 2, 1)), valid

    def _model(self, idx: np.ndarray):
        """Predicted (range, bearing) (M, 2) and Jacobian blocks of landmarks ``idx``.

        Returns ``h``, ``Hv`` (M, 2, 3) for the pose and ``Hm`` (M, 2, 2) for the
        landmark, and a mask (M,) of landmarks far enough from the robot.
        """
        xr, yr, th = self._x[:3]
        m = self._x[_LM0:].reshape(-1, 2)[idx]
        dx, dy = m[:, 0] - xr, m[:, 1] - yr
        q = dx * dx + dy * dy
        ok = q >= MIN_FEATURE_RANGE_M**2
        q = np.where(ok, q, 1.0)
        r = np.sqrt(q)
        h = np.column_stack((r, wrap_angle(np.arctan2(dy, dx) - th)))
        hv = np.zeros((idx.size, 2, 3))
        hv[:, 0, 0], hv[:, 0, 1] = -dx / r, -dy / r
        hv[:, 1, 0], hv[:, 1, 1], hv[:, 1, 2] = dy / q, -dx / q, -1.0
        return h, hv, -hv[:, :, :2], ok

    def _individual_innovations(self, z, r_obs):
        """Innovations (K, L, 2) and covariances (K, L, 2, 2) against the prior."""
        n_lm = self._ids.size
        h, hv, hm, ok = self._model(np.arange(n_lm))
        P = self._P
        pvm = P[:3, _LM0:].reshape(3, n_lm, 2).transpose(1, 0, 2)  # (L, 3, 2)
        pmm = P[_LM0:, _LM0:].reshape(n_lm, 2, n_lm, 2)[np.arange(n_lm), :, np.arange(n_lm), :]
        # H P H^T from the 5 non-zero columns of each landmark's H: O(L).
        hph = hv @ P[:3, :3] @ hv.transpose(0, 2, 1) + hm @ pmm @ hm.transpose(0, 2, 1)
        cross = hv @ pvm @ hm.transpose(0, 2, 1)
        hph += cross + cross.transpose(0, 2, 1)
        nu = z[:, None, :] - h[None, :, :]
        nu[..., 1] = wrap_angle(nu[..., 1])
        s_ind = hph[None] + r_obs[:, None]
        # A landmark at the robot has no defined bearing: make it unmatchable.
        nu[:, ~ok] = 1e6
        s_ind[:, ~ok] = np.eye(2)
        return nu, s_ind

    def _jcbb(self, nu, r_obs, nis) -> association.JcbbResult:
        """Run JCBB on the individually compatible pairs with their joint covariance."""
        cand_obs, cand_lm = np.nonzero(nis < self.params.gate_assoc_chi2)
        n_cand = cand_obs.size
        lms = np.unique(cand_lm)
        _, hv, hm, _ = self._model(lms)
        # Columns of P involved: the pose and each candidate landmark.
        cols = np.concatenate(([0, 1, 2], np.ravel(np.column_stack((_LM0 + 2 * lms, _LM0 + 1 + 2 * lms)))))
        slot = np.searchsorted(lms, cand_lm)
        h_c = np.zeros((n_cand, 2, cols.size))
        h_c[:, :, :3] = hv[slot]
        for c in range(n_cand):
            h_c[c, :, 3 + 2 * slot[c]: 5 + 2 * slot[c]] = hm[slot[c]]
        h_c = h_c.reshape(2 * n_cand, cols.size)
        joint = h_c @ self._P[np.ix_(cols, cols)] @ h_c.T
        same_obs = cand_obs[:, None] == cand_obs[None, :]
        blocks = np.zeros((n_cand, n_cand, 2, 2))
        blocks[same_obs] = r_obs[cand_obs[np.nonzero(same_obs)[0]]]
        joint += blocks.transpose(0, 2, 1, 3).reshape(2 * n_cand, 2 * n_cand)
        confidence = float(chi2.cdf(self.params.gate_assoc_chi2, 2))
        return association.jcbb(
            nu.shape[0], cand_obs, cand_lm, nu[cand_obs, cand_lm], joint, confidence,
            JCBB_MAX_NODES, self.params.unique_match_required,
        )

    def _correct(self, i: int, z: np.ndarray, r_obs: np.ndarray, full: bool) -> float:
        """Apply observation ``z`` of landmark index ``i``; returns the prior NIS.

        ``full``: EKF update in Bailey's Cholesky form, ``P ← P − W1 W1^T`` with
        ``W1 = P H^T chol(S)^-T``, O(n²). Otherwise a Schmidt update that moves
        only landmark ``i``: its rows become ``P_l: − K_l H P`` with
        ``K_l = (P H^T)_l S^-1``, O(n).
        """
        h, hv, hm, _ = self._model(np.array([i]))
        j = _LM0 + 2 * i
        cols = [0, 1, 2, j, j + 1]
        hs = np.concatenate((hv[0], hm[0]), axis=1)  # (2, 5)
        pht = self._P[:, cols] @ hs.T  # (n, 2)
        s = hs @ pht[cols] + r_obs
        chol = np.linalg.cholesky(0.5 * (s + s.T))
        # Inverse of the 2×2 lower Cholesky factor in closed form: a generic
        # triangular solve costs more in call overhead than the arithmetic.
        c_inv = np.array([[1.0 / chol[0, 0], 0.0], [-chol[1, 0] / (chol[0, 0] * chol[1, 1]), 1.0 / chol[1, 1]]])
        nu = z - h[0]
        nu[1] = wrap_angle(nu[1])
        w = c_inv @ nu
        if full:
            self._full_update(pht @ c_inv.T, w)
        else:
            gain = pht[j:j + 2] @ c_inv.T @ c_inv
            self._x[j:j + 2] += gain @ nu
            rows = self._P[j:j + 2] - gain @ pht.T
            rows[:, j:j + 2] = 0.5 * (rows[:, j:j + 2] + rows[:, j:j + 2].T)
            self._P[j:j + 2] = rows
            self._P[:, j:j + 2] = rows.T
        return float(w @ w)

    def _full_update(self, w1: np.ndarray, w: np.ndarray) -> None:
        """``x ← x + W1 w``, ``P ← P − W1 W1ᵀ`` for ``W1 = P Hᵀ chol(S)⁻ᵀ`` (n, k), ``w = chol(S)⁻¹ ν`` (k,)."""
        self._x += w1 @ w
        # Row blocks keep the rank-k product in cache: one pass over P instead
        # of streaming a full n×n temporary (2-3× faster at 700+ landmarks).
        for r0 in range(0, w1.shape[0], _ROW_BLOCK):
            self._P[r0 : r0 + _ROW_BLOCK] -= w1[r0 : r0 + _ROW_BLOCK] @ w1.T
        self._x[2] = wrap_angle(self._x[2])

    def _register_sighting(self, i: int, kind: int) -> None:
        """Count a gated sighting of landmark ``i`` and confirm it when due."""
        self._sightings[i] += 1
        self._kinds[i] = min(self._kinds[i], kind)
        lx, ly = self._x[_LM0 + 2 * i: _LM0 + 2 + 2 * i]
        view = np.arctan2(self._x[1] - ly, self._x[0] - lx)
        self._view_spread[i] = max(self._view_spread[i], abs(wrap_angle(view - self._view_ref[i])))
        self._confirmed[i] |= self._due(i)

    def _due(self, i: int) -> bool:
        p = self.params
        enough = self._sightings[i] >= p.min_sightings_to_confirm
        if self._kinds[i] == BACKWARD:
            return bool(enough and self._view_spread[i] >= p.backward_min_view_change_rad)
        return bool(enough)

    def _augment(self, z: np.ndarray, r_obs: np.ndarray, kind: int) -> int:
        """Add a landmark from ``z`` with full cross-covariances; returns its id."""
        rng, brg = z
        xr, yr, th = self._x[:3]
        c, s = np.cos(th + brg), np.sin(th + brg)
        gv = np.array([[1.0, 0.0, -rng * s], [0.0, 1.0, rng * c]])
        gz = np.array([[c, -rng * s], [s, rng * c]])
        n = self._x.size
        P = np.empty((n + 2, n + 2))
        P[:n, :n] = self._P
        P[n:, :n] = gv @ self._P[:3, :]  # correlation with pose and every landmark
        P[:n, n:] = P[n:, :n].T
        pmm = gv @ self._P[:3, :3] @ gv.T + gz @ r_obs @ gz.T
        P[n:, n:] = 0.5 * (pmm + pmm.T)
        self._P = P
        self._x = np.concatenate((self._x, [xr + rng * c, yr + rng * s]))
        new_id = self._next_id
        self._next_id += 1
        self._ids = np.append(self._ids, new_id)
        self._kinds = np.append(self._kinds, np.int8(kind))
        self._sightings = np.append(self._sightings, 1)
        self._born = np.append(self._born, self._n_observe)
        self._view_ref = np.append(self._view_ref, np.arctan2(-rng * s, -rng * c))
        self._view_spread = np.append(self._view_spread, 0.0)
        self._confirmed = np.append(self._confirmed, False)
        self._confirmed[-1] = self._due(self._ids.size - 1)
        return new_id

    def _drop_expired(self) -> int:
        """Marginalise out unconfirmed landmarks older than the age limit."""
        age = self._n_observe - self._born
        drop = np.flatnonzero(~self._confirmed & (age >= self.params.tentative_max_age_updates))
        if drop.size == 0:
            return 0
        keep = np.setdiff1d(np.arange(self._x.size), np.ravel([(_LM0 + 2 * d, _LM0 + 1 + 2 * d) for d in drop]))
        self._x = self._x[keep]
        self._P = self._P[np.ix_(keep, keep)]
        for name in ("_ids", "_kinds", "_sightings", "_confirmed", "_born", "_view_ref", "_view_spread"):
            setattr(self, name, np.delete(getattr(self, name), drop))
        return int(drop.size)
