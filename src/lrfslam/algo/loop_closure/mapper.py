"""The loop-closing mapper (:class:`LoopClosingMapper`): keyframes in a pose graph, joined by
the local trajectory's motion, closed by :class:`~lrfslam.algo.loop_closure.search.ClosureSearch`,
optimised, and revisits folded away (the package notes, :mod:`lrfslam.algo.loop_closure`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np

from lrfslam.algo.geometry import (
    anchored_poses,
    compose,
    from_frame,
    relative,
    rotate_covariance,
    thin_points,
)
from lrfslam.algo.loop_closure.keyframes import (
    NO_POINTS,
    Keyframe,
    Retired,
    RetiredKeyframes,
    place_scans,
)
from lrfslam.algo.loop_closure.params import (
    EKF_JUMP_M,
    EKF_JUMP_RAD,
    KEYFRAME_CELL_M,
    MAX_PENDING_CLOSURES,
    MAX_SCAN_STEP_M,
    MIN_WEIGHT,
    ODOM_ROT_SIGMA_RAD,
    ODOM_TRANS_SIGMA_M,
    ODOMETRY_KEYFRAMES,
    OPTIMISE_CHI2,
    SAVED_EDGE_SIGMA_M,
    SAVED_EDGE_SIGMA_RAD,
    SCAN_MATCH,
    LoopClosureParams,
)
from lrfslam.algo.loop_closure.search import ClosureAttempt, ClosureSearch, ClosureStats
from lrfslam.algo.loop_closure.snapshot import restore as restore_arrays
from lrfslam.algo.loop_closure.snapshot import snapshot as snapshot_arrays
from lrfslam.algo.pose_graph import CAUCHY_SCALE, PoseGraph
from lrfslam.algo.scan_match import ReferenceScan, match
from lrfslam.errors import ConfigError, InputError


class LoopClosingMapper:
    """The loop-closing back end (mutable state; see the module notes).

    Parameters
    ----------
    params : LoopClosureParams
    keep_scans : bool
        Keep every scan's place (its keyframe and local pose relative to it, ~60 B a
        scan) for :meth:`trajectory`. A long-running service does not: its published
        local poses and keyframes give the same trajectory
        (``lrfslam.evaluation.map_trajectory.final_poses``).

    Attributes
    ----------
    observer : callable or None
        Called with a :class:`ClosureAttempt` for every closure verified or dropped (an audit;
        None, the default: nothing is kept).
    """

    def __init__(self, params: LoopClosureParams | None = None, keep_scans: bool = True) -> None:
        self.params = params or LoopClosureParams()
        self.graph = PoseGraph()
        self._keyframes: list[Keyframe] = []   # the graph's, node i the i-th
        self._made = 0   # keyframes made, retired ones included
        self._retired: list[Retired] = []   # retired since the last take_retired()
        self._retired_kept: list[Retired] = []   # every one retired (keep_scans: the trajectory places them)
        self._keep_scans = keep_scans
        self._scans_fed = 0
        self._scan_kf: list[int] = []  # per scan fed (keep_scans): its keyframe's ordinal
        self._scan_rel: list[np.ndarray] = []  # per scan: local pose relative to that keyframe's
        self._stamps: list[int] = []
        self._loop_edges: list[int] = []  # graph edge ids of the closures in the graph
        self._counts = dict.fromkeys(ClosureStats.__dataclass_fields__, 0)
        self._last_local_pose = np.zeros(3)  # the previous scan's local pose
        # The reference steps since the last keyframe composed (3,); None once one was missing.
        self._reference: np.ndarray | None = np.zeros(3)
        self._pending = 0  # closures added since the last optimisation
        self._pending_strong = False  # one of them disagrees strongly with the estimate they were added to
        self._fold_queue: list[int] = []  # revisit keyframes not folded yet, oldest first
        self.observer: Callable[[ClosureAttempt], None] | None = None
        self._search = ClosureSearch(self.params, self._counts, self._observe)

    @property
    def stats(self) -> ClosureStats:
        return ClosureStats(**self._counts)

    @property
    def keyframe_count(self) -> int:
        """Keyframes made so far, retired ones included."""
        return self._made

    @property
    def graph_keyframes(self) -> int:
        """Keyframes in the graph (made, less the retired)."""
        return len(self._keyframes)

    @property
    def waiting_for_join(self) -> bool:
        """Seeded with a saved map (:meth:`seeded`) and its run's first scan not placed yet (:meth:`join`)."""
        return bool(self._keyframes) and self._keyframes[-1].ordinal < self._search.run_start

    def place(self, local_pose) -> np.ndarray:
        """Where the graph as it stands puts a scan at ``local_pose`` (3,): the last keyframe's corrected
        pose and the local motion since, as :meth:`add_scan` gives it for a scan that makes no keyframe.

        Cheap, and changes nothing: a caller answers with it before :meth:`add_scan`'s work on a
        keyframe (its motion check, closure search and optimisation), whose result the next scan's
        pose then carries.
        """
        pose = np.asarray(local_pose, dtype=float)
        if pose.shape != (3,) or not np.all(np.isfinite(pose)):
            raise InputError("local_pose must be (3,) and finite")
        if not self._keyframes:
            return pose.copy()
        k = len(self._keyframes) - 1
        return compose(self.graph.poses[k], relative(self._keyframes[k].local_pose, pose))

    def add_scan(self, stamp_ns: int, local_pose, points_xy_m, reference_step=None, online_pose=None) -> np.ndarray:
        """Take one scan; returns its corrected pose (3,), as known now.

        Parameters
        ----------
        stamp_ns : int
            The scan's stamp (ns): the keyframes' and :meth:`trajectory`'s.
        local_pose : array_like, shape (3,)
            The scan's pose on the local trajectory, ``(x_m, y_m, theta_rad)``.
        points_xy_m : array_like, shape (N, 2)
            The scan's points in the robot frame (m); non-finite rows are ignored.
        reference_step : array_like, shape (3,), optional
            The motion from the previous scan to this one found by scan matching
            (dx m, dy m, dtheta rad), if it was: an odometry edge whose every step
            has one is checked against their chain (``ekf_jump_*``), the others
            against the keyframes' scans matched.
        online_pose : array_like, shape (3,), optional
            The online estimator's pose of this scan (the EKF's, in its own map frame): the
            closure search also looks where it puts the robot (module notes).
        """
        pose = np.asarray(local_pose, dtype=float)
        if pose.shape != (3,) or not np.all(np.isfinite(pose)):
            raise InputError("local_pose must be (3,) and finite")
        if self.waiting_for_join:
            raise InputError("a mapper seeded with a saved map takes its first scan by join()")
        p = self.params
        stamp_ns = int(stamp_ns)
        online = None if online_pose is None else np.asarray(online_pose, dtype=float)
        if online is not None and (online.shape != (3,) or not np.all(np.isfinite(online))):
            raise InputError("online_pose must be (3,) and finite")
        if not self._keyframes:
            self._add_keyframe(pose, points_xy_m, None, stamp_ns, online)
        else:
            if self._reference is not None and reference_step is not None:
                self._reference = compose(self._reference, np.asarray(reference_step, dtype=float))
            else:
                self._reference = None
            last = self._keyframes[-1]
            moved = relative(last.local_pose, pose)
            jumped = np.hypot(*(pose[:2] - self._last_local_pose[:2])) > MAX_SCAN_STEP_M
            if jumped or np.hypot(moved[0], moved[1]) >= p.keyframe_trans_m or abs(moved[2]) >= p.keyframe_rot_rad:
                self._add_keyframe(pose, points_xy_m, moved, stamp_ns, online)
                self._reference = np.zeros(3)
                self._close_loops()
        self._last_local_pose = pose
        k = len(self._keyframes) - 1
        rel = relative(self._keyframes[k].local_pose, pose)
        self._scans_fed += 1
        if self._keep_scans:
            self._scan_kf.append(self._keyframes[k].ordinal)
            self._scan_rel.append(rel)
            self._stamps.append(stamp_ns)
        return compose(self.graph.poses[k], rel)

    @classmethod
    def seeded(cls, params: LoopClosureParams | None, map_poses, keyframe_points, stamps_ns) -> LoopClosingMapper:
        """A mapper that goes on from a saved map (``lrfslam up --map MAP``): its K keyframes in the graph.

        The saved map holds its keyframes' optimised poses, not the closures that shaped them. So
        each saved keyframe is tied to the one before as an odometry edge is (the drift model,
        ``odom_*``), at their saved relative pose, and to the first (the gauge) by a loose edge
        (``SAVED_EDGE_SIGMA_*``) at its saved pose: at rest where it was saved, as flexible
        locally as the map was built, held in place over the building where a chain's flex would
        add up. A new run's closures move the saved keyframes near them as they would have moved
        the first run's.
        They are closure candidates like any old keyframe; the run's first scan is placed on them
        by :meth:`join`, every later one by :meth:`add_scan`. Keeps no per-scan history.

        Parameters
        ----------
        params : LoopClosureParams or None
        map_poses : array_like, shape (K, 3)
            The keyframes' poses in the map frame (m, m, rad), in the order they were made.
        keyframe_points : sequence of K arrays, shape (N_k, 2)
            Each keyframe's scan points in its robot frame (m).
        stamps_ns : array_like of int, shape (K,)
            The stamps of the scans that made them.
        """
        poses = np.asarray(map_poses, dtype=float).reshape(-1, 3)
        stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        if poses.shape[0] == 0 or len(keyframe_points) != poses.shape[0] or stamps.shape != (poses.shape[0],) \
                or not np.all(np.isfinite(poses)):
            raise InputError("a saved map needs K finite poses, K point sets and K stamps, K >= 1")
        mapper = cls(params, keep_scans=False)
        held = np.diag([SAVED_EDGE_SIGMA_M ** -2] * 2 + [SAVED_EDGE_SIGMA_RAD ** -2])
        travel = 0.0
        for k, pose in enumerate(poses):
            mapper.graph.add_node(pose)
            if k:
                step = relative(poses[k - 1], pose)
                dist = float(np.hypot(step[0], step[1]))
                mapper.graph.add_edge(k - 1, k, step, np.linalg.inv(mapper._odometry_cov(dist, abs(step[2]))))
                mapper.graph.add_edge(0, k, relative(poses[0], pose), held)
                travel += dist
            mapper._keyframes.append(Keyframe(pose.copy(), mapper._keyframe_points(keyframe_points[k]), travel, False,
                                              -1, int(stamps[k]), k))
        mapper._made = mapper._search.run_start = poses.shape[0]
        return mapper

    def join(self, stamp_ns: int, local_pose, points_xy_m, map_pose, map_cov, online_pose=None) -> np.ndarray:
        """The run's first scan of a :meth:`seeded` mapper, found on the saved map (a localizer's fix);
        returns its pose (3,), ``map_pose``.

        It makes a keyframe at ``map_pose``, tied to the nearest saved keyframe by an edge of
        covariance ``map_cov`` (3, 3; in the map frame, the saved keyframe held fixed); its travel
        starts ``min_travel_m`` past the saved map's, so every saved keyframe is a candidate from
        the next keyframe on. ``local_pose``, ``points_xy_m``, ``online_pose``: as :meth:`add_scan`'s.

        Raises
        ------
        InputError
            The mapper is not a seeded one waiting for its run, or an input is malformed.
        """
        if not self.waiting_for_join:
            raise InputError("join() takes the first scan of a mapper seeded with a saved map")
        local = np.asarray(local_pose, dtype=float)
        at = np.asarray(map_pose, dtype=float)
        cov = np.asarray(map_cov, dtype=float)
        if local.shape != (3,) or at.shape != (3,) or cov.shape != (3, 3) or not (
                np.all(np.isfinite(local)) and np.all(np.isfinite(at)) and np.all(np.isfinite(cov))):
            raise InputError("join needs a finite local pose (3,), map pose (3,) and covariance (3, 3)")
        poses = self.graph.poses
        k = int(np.argmin(np.hypot(poses[:, 0] - at[0], poses[:, 1] - at[1])))
        node = self.graph.add_node(at)
        self.graph.add_edge(k, node, relative(poses[k], at), np.linalg.inv(rotate_covariance(cov, -poses[k, 2])))
        self._made += 1
        online = None if online_pose is None else np.asarray(online_pose, dtype=float)
        self._keyframes.append(Keyframe(local.copy(), self._keyframe_points(points_xy_m),
                                        self._keyframes[-1].travel_m + self.params.min_travel_m, False,
                                        self._scans_fed, int(stamp_ns), self._made - 1, online_pose=online))
        self._last_local_pose = local
        self._reference = np.zeros(3)
        self._scans_fed += 1
        return at.copy()

    def solve(self) -> None:
        """Optimise the graph for every closure not solved for yet (the keyframe poses are then final)."""
        if self._pending:
            self._optimise()

    def finish(self) -> None:
        """The run ended: optimise for every closure not solved for yet, then fold every revisit
        still queued (``fold_revisits``), the recent ones too — no later keyframe needs them as its
        neighbours — so what stays in the graph is the place, not the last minutes of revisiting it."""
        self.solve()
        self._fold_settled(final=True)
        if self._search.run_start:
            self._retire_redundant()

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """Stamps (ns, (T,)) and poses ((T, 3)) of every scan fed, from the graph with every closure solved for.

        Raises
        ------
        ConfigError
            The mapper was made with ``keep_scans=False``.
        """
        if not self._keep_scans:
            raise ConfigError("this mapper keeps no per-scan history (keep_scans=False)")
        self.solve()
        live, gone = self._keyframes, self._retired_kept
        ordinals = np.array([k.ordinal for k in live] + [r.ordinal for r in gone], dtype=np.int64)
        order = np.argsort(ordinals)   # (every ordinal below self._made is one of the two)
        live_ordinals = ordinals[: len(live)]
        kf_poses = np.vstack((self.graph.poses, anchored_poses(
            live_ordinals, self.graph.poses, ordinals[len(live):],
            np.array([r.anchor_ordinal for r in gone], dtype=np.int64),
            np.array([r.offset for r in gone], dtype=float).reshape(-1, 3))))[order]
        kf_local = np.vstack((self.keyframe_local_poses(),
                              np.array([r.local_pose for r in gone], dtype=float).reshape(-1, 3)))[order]
        kf_scan = np.concatenate((self.keyframe_scans(), np.array([r.scan_index for r in gone], dtype=np.int64)))
        kf_edge = np.concatenate((self.keyframe_local_edges(), np.array([r.local_edge for r in gone], dtype=bool)))
        poses = place_scans(np.array(self._scan_kf, dtype=np.int64), np.array(self._scan_rel, dtype=float),
                            kf_poses, kf_local, kf_scan[order], kf_edge[order])
        return np.array(self._stamps, dtype=np.int64), poses

    @property
    def closure_nis(self) -> tuple[int, float]:
        """How many closures passed verification, and their NIS (3 dof, against the graph's
        prediction) summed: the mean is the consistency report's figure."""
        return self._search.closure_nis

    def keyframe_poses(self) -> np.ndarray:
        """The graph's K keyframes' poses as they stand (optimised at the last optimisation), (K, 3).

        Every keyframe accessor gives the keyframes in the graph, oldest first; the retired
        ones are given once, by :meth:`take_retired`.
        """
        return self.graph.poses.copy()

    def keyframe_local_poses(self) -> np.ndarray:
        """Each keyframe's pose on the local trajectory, (K, 3)."""
        return np.array([k.local_pose for k in self._keyframes], dtype=float).reshape(-1, 3)

    def keyframe_local_edges(self) -> np.ndarray:
        """Whether the odometry edge into each keyframe is the local motion (no jump), (K,) bool."""
        return np.array([k.local_edge for k in self._keyframes], dtype=bool)

    def keyframe_scans(self) -> np.ndarray:
        """Index (in the order fed) of the scan that made each keyframe, (K,)."""
        return np.array([k.scan_index for k in self._keyframes], dtype=np.int64)

    def keyframe_stamped_local_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """Stamps (ns, (K,)) of the scans that made the keyframes, and their local poses (K, 3)."""
        return np.array([k.stamp_ns for k in self._keyframes], dtype=np.int64), self.keyframe_local_poses()

    def take_retired(self) -> RetiredKeyframes:
        """The keyframes retired from the graph since the last call (each given once), oldest first."""
        gone, self._retired = self._retired, []
        return RetiredKeyframes(np.array([r.stamp_ns for r in gone], dtype=np.int64),
                                np.array([r.local_pose for r in gone], dtype=float).reshape(-1, 3),
                                np.array([r.local_edge for r in gone], dtype=bool),
                                np.array([r.anchor_stamp_ns for r in gone], dtype=np.int64),
                                np.array([r.offset for r in gone], dtype=float).reshape(-1, 3))

    def closures(self) -> list[tuple[int, int, np.ndarray]]:
        """The closures in the graph: (old keyframe, new keyframe, pose of the new in the old's frame (3,))."""
        return [(self.graph.edge_nodes(e)[0], self.graph.edge_nodes(e)[1], self.graph.edge_measurement(e))
                for e in self._loop_edges]

    # -- checkpoint -----------------------------------------------------------------------------

    def snapshot(self) -> dict[str, np.ndarray]:
        """Everything needed to continue exactly where this mapper stands, as named arrays (copies):
        :func:`lrfslam.algo.loop_closure.snapshot.snapshot`."""
        return snapshot_arrays(self)

    @classmethod
    def restore(cls, params: LoopClosureParams | None, arrays) -> LoopClosingMapper:
        """The mapper :meth:`snapshot` gave ``arrays`` of (e.g. loaded from an ``.npz``).

        Raises
        ------
        InputError
            If the arrays are not a snapshot of this format or disagree with each other.
        """
        return restore_arrays(cls, params, arrays)

    # -- keyframes and odometry edges -----------------------------------------------------------

    def _add_keyframe(self, local_pose: np.ndarray, points_xy_m, moved: np.ndarray | None, stamp_ns: int,
                      online_pose: np.ndarray | None) -> None:
        pts = self._keyframe_points(points_xy_m)
        self._made += 1
        if moved is None:
            self.graph.add_node(local_pose)
            self._keyframes.append(Keyframe(local_pose.copy(), pts, 0.0, True, self._scans_fed, stamp_ns,
                                             self._made - 1, online_pose=online_pose))
            return
        prev = len(self._keyframes) - 1
        dist = float(np.hypot(moved[0], moved[1]))
        cov = self._odometry_cov(dist, abs(moved[2]))
        if self._reference is None:
            step = self._checked_motion(prev, pts, moved, cov)
        else:
            step = self._step_or_jump(moved, self._reference)
        node = self.graph.add_node(compose(self.graph.poses[prev], step))
        self.graph.add_edge(prev, node, step, np.linalg.inv(cov))
        self._keyframes.append(Keyframe(local_pose.copy(), pts, self._keyframes[-1].travel_m + dist,
                                         step is moved, self._scans_fed, stamp_ns, self._made - 1,
                                         online_pose=online_pose))
        self._trim(len(self._keyframes) - 1 - self._recent_keyframes)

    def _keyframe_points(self, points_xy_m) -> np.ndarray:
        """A keyframe's points (N, 2) as it keeps them: finite, within ``max_range_m``, thinned."""
        pts = np.asarray(points_xy_m, dtype=float).reshape(-1, 2)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        pts = pts[np.hypot(pts[:, 0], pts[:, 1]) < self.params.max_range_m]
        return thin_points(pts, KEYFRAME_CELL_M)

    @property
    def _recent_keyframes(self) -> int:
        """The last this many keyframes keep their points whatever they are (the query and the edge checks use them)."""
        return max(self.params.query_keyframes, ODOMETRY_KEYFRAMES)

    def _mark_revisit(self, k: int) -> None:
        """Keyframe ``k`` closed a loop: with ``trim_revisits``, no candidate, and no points once not recent."""
        if self.params.trim_revisits and not self._keyframes[k].revisit:
            self._keyframes[k] = replace(self._keyframes[k], revisit=True)
            self._trim(k)
            if self.params.fold_revisits:
                self._fold_queue.append(k)

    def _trim(self, k: int) -> None:
        """Drop keyframe ``k``'s points if it is a revisit and no longer one of the recent keyframes."""
        if 0 <= k < len(self._keyframes) - self._recent_keyframes and self._keyframes[k].revisit \
                and self._keyframes[k].points_xy_m.shape[0]:
            self._keyframes[k] = replace(self._keyframes[k], points_xy_m=NO_POINTS)

    def _step_or_jump(self, moved: np.ndarray, reference: np.ndarray) -> np.ndarray:
        """``moved`` (3,), or ``reference`` (3,) where the two differ by more than ``ekf_jump_*``."""
        jump = relative(moved, reference)
        if np.hypot(jump[0], jump[1]) > EKF_JUMP_M or abs(jump[2]) > EKF_JUMP_RAD:
            self._counts["ekf_jumps"] += 1
            return reference
        return moved

    def _checked_motion(self, prev: int, pts: np.ndarray, moved: np.ndarray, cov: np.ndarray) -> np.ndarray:
        """``moved`` (3,), the local motion from keyframe ``prev`` to the new one, or the scans' match where it jumped."""
        # The EKF's poses hold its landmark corrections as jumps (2.3 m at once
        # on ACES), which are not motion. The keyframes' scans, matched with
        # the local motion as the guess, say what the motion was:
        # where the two disagree by more than ``ekf_jump_*`` the match is taken.
        recent = self._recent_map(prev)
        found = match(recent, pts, moved, SCAN_MATCH, cov)
        if not found.ok:
            # A jump beyond the matcher's reach (its largest correction): the keyframes
            # are at most ``keyframe_*`` apart, so standing still is a guess within it.
            found = match(recent, pts, np.zeros(3), SCAN_MATCH, cov)
        return self._step_or_jump(moved, found.pose) if found.ok else moved

    def _recent_map(self, last: int) -> ReferenceScan:
        """The ``ODOMETRY_KEYFRAMES`` keyframes up to ``last`` merged in ``last``'s frame by their graph poses."""
        poses = self.graph.poses
        first = max(0, last - ODOMETRY_KEYFRAMES + 1)
        same = self._search.same_side
        pts = np.vstack([from_frame(self._keyframes[i].points_xy_m, relative(poses[last], poses[i]))
                         for i in range(first, last + 1)
                         if same(self._keyframes[i].ordinal, self._keyframes[last].ordinal)])
        return ReferenceScan.build(thin_points(pts, KEYFRAME_CELL_M))

    def _odometry_cov(self, dist_m: float, turn_rad: float) -> np.ndarray:
        """Covariance (3, 3) of an odometry edge over ``dist_m`` metres and ``turn_rad`` radians."""
        p = self.params
        var_xy = ODOM_TRANS_SIGMA_M**2 + (p.odom_trans_sigma_per_m * dist_m) ** 2
        var_th = ODOM_ROT_SIGMA_RAD**2 + (p.odom_rot_sigma_per_m * dist_m) ** 2 \
            + (p.odom_rot_sigma_per_rad * turn_rad) ** 2
        return np.diag([var_xy, var_xy, var_th])

    # -- closures -------------------------------------------------------------------------------

    def _close_loops(self) -> None:
        """Search the newest keyframe's closures; add those found as robust edges, and optimise
        when one disagrees with the graph or enough wait (``OPTIMISE_CHI2``, ``MAX_PENDING_CLOSURES``)."""
        found = self._search.find(self._keyframes, self.graph)
        urgent = False
        for k, n_, z, cov, innovation in found:
            self._mark_revisit(n_)
            info = np.linalg.inv(cov)
            self._loop_edges.append(self.graph.add_edge(k, n_, z, info, robust=True))
            self._counts["accepted"] += 1
            self._observe(k, n_, z, cov, "accepted")
            edge_chi2 = float(innovation @ info @ innovation)
            self._pending += 1
            urgent |= edge_chi2 > OPTIMISE_CHI2
            self._pending_strong |= edge_chi2 > CAUCHY_SCALE**2
        if urgent or self._pending >= MAX_PENDING_CLOSURES:
            self._optimise()

    def _observe(self, k: int, n: int, pose: np.ndarray, cov: np.ndarray | None, verdict: str) -> None:
        """Tell the :attr:`observer` what became of a closure between keyframes ``k`` and ``n``."""
        if self.observer is not None:
            self.observer(ClosureAttempt(self._keyframes[k].stamp_ns, self._keyframes[n].stamp_ns,
                                         np.array(pose, float), None if cov is None else np.array(cov, float), verdict))

    def _optimise(self) -> None:
        """Optimise; drop closures the graph disagrees with (the worst first) and optimise again."""
        # Every closure passed the gate against the graph. One that disagrees
        # strongly with the estimate would start with a tiny robust weight: solve
        # with all of them first, then let the kernel find the ones the others disagree with.
        if self._pending_strong:
            self.graph.optimize(robust=False)
        self._pending, self._pending_strong = 0, False
        while True:
            self.graph.optimize()
            self._counts["optimisations"] += 1
            self._search.submaps.clear()  # neighbours moved: the submaps are rebuilt from the new poses
            if not self._loop_edges:
                break
            weights = self.graph.loop_weights()[self._loop_edges]
            worst = int(np.argmin(weights))
            if weights[worst] >= MIN_WEIGHT:
                break
            edge = self._loop_edges.pop(worst)
            if self.observer is not None:
                i, j = self.graph.edge_nodes(edge)
                self._observe(i, j, self.graph.edge_measurement(edge), None, "removed")
            self.graph.remove_edge(edge)
            self._counts["removed"] += 1
        self._fold_settled()

    # -- folding revisits -----------------------------------------------------------------------

    def _fold_settled(self, final: bool = False) -> None:
        """Fold every queued revisit keyframe that is no longer recent (``fold_revisits``; ``final``:
        every one).

        Run right after an optimisation: every closure in the graph has been through one and
        kept its weight, and the poses are the optimum the folded edges are linearised at.
        """
        last = len(self._keyframes) - (0 if final else max(self._recent_keyframes, self.params.fold_after_keyframes))
        if not self._fold_queue or self._fold_queue[0] >= last:
            return
        weights = self.graph.loop_weights()
        loops = {e: self.graph.edge_nodes(e) for e in self._loop_edges}
        folded = []
        while self._fold_queue and self._fold_queue[0] < last:
            n = self._fold_queue.pop(0)
            into = [e for e, (_, j) in loops.items() if j == n]
            if into:   # (its closure may have been removed: then it stays a node like any other)
                anchor = max(into, key=lambda e: weights[e])
                self._fold(n, anchor, weights)
                folded.append((n, anchor))
        if folded:
            self._retire(folded)

    def _retire_redundant(self) -> None:
        """Mapping on from a saved map, at the end of the run: fold each of the run's keyframes that
        lies within ``2 × keyframe_trans_m`` of a saved keyframe and whose scan lies on that saved
        keyframe's map there (mean likelihood ≥ ``min_score`` at the graph's relative pose) into it.

        Such a keyframe revisits a saved place whose closures were refused (a corridor seen end-on
        does not constrain a match; a person in view) and adds nothing the saved map does not
        hold; one whose scan disagrees with the map (a moved cupboard, a closed door) is kept.
        Folded at the graph's relative pose with the graph's covariance of it, it leaves every
        pose where the last optimisation put it."""
        kfs, graph, p = self._keyframes, self.graph, self.params
        saved = np.array([i for i, kf in enumerate(kfs) if kf.ordinal < self._search.run_start], dtype=np.int64)
        folded = []
        for n in range(len(kfs)):
            if kfs[n].ordinal < self._search.run_start or not kfs[n].points_xy_m.shape[0]:
                continue
            poses = graph.poses
            dist = np.hypot(poses[saved, 0] - poses[n, 0], poses[saved, 1] - poses[n, 1])
            k = int(saved[np.argmin(dist)])
            if dist.min() > 2.0 * p.keyframe_trans_m:
                continue
            rel = relative(poses[k], poses[n])
            grid, _ = self._search.submap(kfs, graph, k, p.min_window_m)
            if grid.score(kfs[n].points_xy_m, rel) < p.min_score:
                continue
            edge = graph.add_edge(k, n, rel, np.linalg.inv(graph.relative_covariance(k, n)), robust=True)
            self._fold(n, edge, graph.loop_weights())
            folded.append((n, edge))
        if folded:
            self._retire(folded)

    def _retire(self, leaves: list[tuple[int, int]]) -> None:
        """Take the folded keyframes ``(node, its closure's edge)`` out of the graph, remembering
        each one's place on its anchor (:class:`RetiredKeyframes`), and renumber what refers to
        the graph. A leaf sits exactly on its closure at every optimum, so this changes no pose."""
        graph, kfs = self.graph, self._keyframes
        for n, edge in leaves:
            k = graph.edge_nodes(edge)[0]
            kf = kfs[n]
            retired = Retired(kf.ordinal, kf.stamp_ns, kf.local_pose, kf.local_edge, kf.scan_index,
                               kfs[k].ordinal, kfs[k].stamp_ns, graph.edge_measurement(edge))
            self._retired.append(retired)
            if self._keep_scans:
                self._retired_kept.append(retired)
        node_map, edge_map = graph.remove_nodes([n for n, _ in leaves])
        self._keyframes = [kf for i, kf in enumerate(kfs) if node_map[i] >= 0]
        self._loop_edges = [int(edge_map[e]) for e in self._loop_edges if edge_map[e] >= 0]
        self._fold_queue = [int(node_map[n]) for n in self._fold_queue]
        search = self._search
        if search.tentative is not None:
            k, n, *rest = search.tentative
            kept = node_map[k] >= 0 and node_map[n] >= 0
            search.tentative = (int(node_map[k]), int(node_map[n]), *rest) if kept else None
        search.submaps.clear()

    def _fold(self, n: int, anchor_edge: int, weights: np.ndarray) -> None:
        """Fold keyframe ``n`` into the keyframe its closure ``anchor_edge`` comes from
        (:meth:`PoseGraph.fold`); a second closure of ``n`` becomes a plain edge between old keyframes."""
        moved = set(self.graph.fold(n, anchor_edge, weights))
        self._loop_edges = [e for e in self._loop_edges if e not in moved]
        self._counts["folded"] += 1
