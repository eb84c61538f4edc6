"""Loop closing behind the EKF: keyframes in a pose graph, closures found by correlative search.

:class:`LoopClosingMapper` is fed every scan with its pose on a *local trajectory* and the
scan's points. It keeps a pose graph (:mod:`lrfslam.algo.pose_graph`) of keyframes
joined by the local trajectory's relative motion, looks for each new keyframe in the maps
of keyframes seen long before, adds what it finds as robust loop edges and
optimises. Per scan it returns the corrected (online) pose; at any time it
gives the optimised trajectory of every scan fed (:meth:`LoopClosingMapper.trajectory`).

Design choices
--------------
* **The local trajectory** is what the mapper service feeds: the chain of the
  motions that moved the EKF (its scan-matched motion, else odometry;
  ``services/mapper.py``), not the EKF's poses: those also hold its landmark
  corrections, as jumps (2.3 m at once on ACES), and a jump is not motion. Older
  recordings' states carry no motion and give the poses. So the new keyframe's
  scan is matched against the last few keyframes with the local motion as the
  guess (standing still if that fails: a jump beyond the matcher's reach), and
  where the two differ by more than ``ekf_jump_*`` the match is the edge. An
  edge made only of scan-matched motions is not checked: it has no jump, and
  the keyframes' match, no better than the slam stage's, would only add noise
  (ACES 0.042 → 0.041 m; short spans 0.040 → 0.039 m). Odometry's motions
  (the paper's filter, a failed match) are checked like jumps.
  The edge covariance grows with the distance and the angle travelled
  (``odom_*``): a model of the drift the local trajectory does not see, not the EKF's
  covariance, which is absolute and shrinks whenever it re-observes a
  landmark (on ACES it claims 3° where the heading is 20° off).
* **Two uncertainties.** The edges' covariance is the local one (0.2° and 1 cm
  per half metre), so loop closures do not bend what the local trajectory got right; but
  the drift over a long loop is systematic (20° of heading round ACES's loops),
  far beyond what a random walk of local errors predicts: a random walk's standard
  deviation grows with the square root of the loop, a heading bias's error with the loop.
  The search window and the gate therefore use the graph's relative covariance grown by
  its own heading variance, ``× (1 + σθ² / drift_onset_rad²)``: unchanged over a short
  loop or right after a closure, growing with the square of the loop past the onset;
  the optimisation does not. It replaced a constant factor (window and gate on 9 × the
  covariance), which was three times too wide for short loops and
  still overconfident for long ones (docs/slam.md, "The mapper").
  (Loose edges, 2.5 cm and 0.9° per half metre, with no model: Intel 0.028 m relation
  error against 0.022 m, ACES 0.051 m either way.)
* **Search window from the graph.** A candidate is an old keyframe (at least
  ``min_travel_m`` back along the trajectory) near the predicted pose. The
  covariance of the new keyframe relative to it (:meth:`PoseGraph.relative_covariance`)
  sets the window, ``WINDOW_SIGMAS`` standard deviations, clamped: after a long
  loop without a closure the window is metres wide, right after one it is small.
  The search is only worth it if the candidate's map can overlap the query
  anywhere in the window (``candidate_radius_m``).
* **Where the online estimate puts it.** The EKF closes loops of its own when it
  re-observes old landmarks; the local trajectory, a chain of motions, never does,
  so after a long loop (MIT Killian's, 2 km) the graph may hold the robot tens of
  metres from where it is, beyond any window. Each scan therefore also brings the
  online estimator's pose (``add_scan(online_pose=...)``, the slam stage's). After
  the candidates near the new keyframe in the graph, up to ``max_candidates`` more
  are taken near it in the online estimate (apart from those: other places), and
  searched around the online relative pose, with the window and every check of the
  others: the gate stays against the graph's own prediction, drift model included.
  The online poses only say where to look; a closure is still the scans' match.
* **Submaps.** The candidate and its ``SUBMAP_KEYFRAMES`` neighbours on each
  side (more where the window is wider than they reach: a map narrower than the
  window favours a look-alike place inside it over the true one at its edge),
  placed by their graph poses in the candidate's frame, make the map
  (likelihood grid, :mod:`lrfslam.algo.correlative_match`); the new keyframe
  and its ``query_keyframes − 1`` predecessors, placed by their graph poses
  (the odometry edges), make the query: more wall than one scan, so less ambiguity.
* **Verification**, in order: the best score must reach ``min_score``; the best
  pose separated from it (another corridor, a turned copy) must score below
  ``max_second_ratio`` of it; the point-to-line matcher
  (:func:`lrfslam.algo.scan_match.match`) started there must converge and
  constrain all three directions (a corridor seen end-on cannot say where along
  it the robot is), and gives the covariance; the match must agree with the
  graph's prediction within ``gate_chi2`` (Mahalanobis, the drift-scaled relative and the
  match covariances summed). Accepted closures are Cauchy-robust edges; after
  each optimisation, a closure whose weight fell below ``MIN_WEIGHT`` (the rest
  of the graph disagrees) is removed and the graph optimised again. A closure
  found in a wide window (after a long excursion) waits for the next wide one
  to agree with it (``confirm_*``): in two identical corridors the best peak
  in a wide window can be the twin's, but the twin's peaks of consecutive
  keyframes do not agree with each other (``tests/unit/test_loop_closure.py``).

* **Cost.** A search's cost grows with its window's area, so wide searches
  are spaced (``WIDE_SEARCH_SPACING_M``); a closure the graph already agrees
  with is not solved for at once (``OPTIMISE_CHI2``, ``MAX_PENDING_CLOSURES``).

Everything is deterministic: same calls, same results.

Modules
-------
* :mod:`~lrfslam.algo.loop_closure.params`: :class:`LoopClosureParams`.
* :mod:`~lrfslam.algo.loop_closure.keyframes`: what the mapper keeps of each keyframe, the
  keyframes it retired, and :func:`place_scans`.
* :mod:`~lrfslam.algo.loop_closure.search`: candidates, windows, search and verification
  (:class:`~lrfslam.algo.loop_closure.search.ClosureSearch`).
* :mod:`~lrfslam.algo.loop_closure.mapper`: :class:`LoopClosingMapper`, which keeps the keyframes
  and the odometry edges, adds the closures found, optimises and folds revisits (the graph
  surgery itself is :meth:`PoseGraph.fold <lrfslam.algo.pose_graph.PoseGraph.fold>`).
* :mod:`~lrfslam.algo.loop_closure.snapshot`: the checkpoint's arrays.
"""

from lrfslam.algo.loop_closure.keyframes import RetiredKeyframes, place_scans
from lrfslam.algo.loop_closure.mapper import LoopClosingMapper
from lrfslam.algo.loop_closure.params import LoopClosureParams
from lrfslam.algo.loop_closure.search import VERDICTS, ClosureAttempt, ClosureStats
from lrfslam.algo.loop_closure.snapshot import SNAPSHOT_FORMAT

__all__ = ["SNAPSHOT_FORMAT", "VERDICTS", "ClosureAttempt", "ClosureStats", "LoopClosingMapper", "LoopClosureParams",
           "RetiredKeyframes", "place_scans"]
