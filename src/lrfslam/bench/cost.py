"""In-process costs for ``lrfslam bench`` (src/lrfslam/bench/command.py): stages, the EKF, the codecs.

Everything here runs in the calling process on simulated LMS200 scans (the hallway loop, 181
beams, the sensor service's defaults) and times single calls on the monotonic high-resolution
clock (``time.perf_counter``). Figures are medians: per scan, the fastest of a few calls (a
call another job interrupted is not the call's cost); per EKF size, the median of repeated
updates. Run single-threaded (``OPENBLAS_NUM_THREADS=1``) for figures that do not depend on how
many cores BLAS grabs.

* :func:`stage_rows`: denoise, corner extraction, wall direction (each with the service's
  default parameters) and one scan-matching tracker step, per scan;
* :func:`ekf_shape`: ``EkfSlam.update_known`` (sparse Jacobian, O(n²)) against filterpy's dense
  ``ExtendedKalmanFilter.update`` (Joseph form, O(n³)) on the same random filter, and the
  log-log slope of each against the landmark count; :func:`check_ekf` holds the shape;
* :func:`codec_rows`: protobuf encode and decode of every message the pipeline's stages make
  (run in one :class:`~lrfslam.runtime.chain.Chain`), and of the slam stage's whole map
  (``slam/map``) once it holds 50, 200 or 1,000 landmarks (the filter restored from a checkpoint);
* :func:`state_rows`: the slam stage's per-scan message in a recorded run, at its start and at
  its end, beside the v1 message that held the whole map: its cost must not grow with the map.
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter

from lrfslam import services
from lrfslam.algo import checkpoint
from lrfslam.algo.ekf_slam import EkfParams, EkfSlam
from lrfslam.algo.features import extract_features
from lrfslam.algo.geometry import polar_to_xy, relative, wrap_angle
from lrfslam.algo.histogram import denoise
from lrfslam.algo.scan_match import ScanTracker
from lrfslam.algo.wall_direction import wall_direction
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.msgs.landmark_map import LandmarkMapReplica
from lrfslam.msgs.v1 import slam_state_pb2 as slam_state_v1
from lrfslam.runtime import checkpoints, npz_file
from lrfslam.runtime.chain import Chain
from lrfslam.runtime.recording import read_recording
from lrfslam.runtime.step import Message
from lrfslam.services.sensor import frame_outputs
from lrfslam.sim.simulator import SimConfig, Simulator

#: Odometry covariance given to the scan-matching tracker (per scan; m², m², rad²).
ODOM_COV = np.diag([1e-4, 1e-4, 1e-4])
#: Landmark counts of the EKF rows of the table, and of the check's fit (where O(n²) dominates).
EKF_TABLE_SIZES = (50, 200, 500, 1000)
EKF_CHECK_SIZES = (200, 400, 700, 1000)
#: The slopes are fitted from this many landmarks on: below, fixed per-call costs flatten the curve.
EKF_FIT_FROM = 200
#: The shape the check holds (issue 18, item 7): at this many landmarks ours is at least this many
#: times faster than the dense update, and its log-log slope against the landmark count is in range.
CHECK_AT_LANDMARKS = 400
CHECK_MIN_RATIO = 10.0
CHECK_SLOPE_RANGE = (1.5, 2.5)
#: Map sizes of the slam-state codec rows.
STATE_MAP_SIZES = (50, 200, 1000)


@dataclass(frozen=True)
class Row:
    """One row of the bench's table: ``value`` in ``unit``; ``compared`` names what ``ratio`` is
    taken against (ratio = compared / value: how many times faster ours is)."""

    section: str
    measure: str
    value: float
    unit: str
    compared: str = ""
    ratio: float | None = None
    note: str = ""


def _configs():
    """The default configs of the denoise, features and slam services (no environment, no file)."""
    return {name: services.stage(name, env={}).config for name in ("denoise", "features", "slam")}


def sim_messages(n_scans: int, seed: int) -> list[Message]:
    """The sensor's messages for ``n_scans`` simulated frames: odometry then scan, stamped by data time."""
    sim = Simulator(SimConfig(seed=seed))
    return [Message.of(out) for frame in (next(sim) for _ in range(n_scans))
            for out in frame_outputs(frame, round(frame.t_s * 1e9), sim)]


def run_chain(messages: Sequence[Message], stage_names: Sequence[str], sets: dict[str, list[str]] | None = None,
              checkpoint_dir: Path | None = None) -> dict[str, list[Message]]:
    """Every message of ``messages`` and of what the named stages made of them, by topic name
    (as the bus carries them: encoded and decoded between stages)."""
    sets = sets or {}
    stages = [services.stage(name, sets=sets.get(name, ()), env={}) for name in stage_names]
    by_topic: dict[str, list[Message]] = defaultdict(list)
    with Chain(stages, robot="bench", checkpoint_dir=checkpoint_dir, checkpoint_period_s=1e9) as chain:
        for msg in messages:
            by_topic[msg.name].append(msg)
        for msg in chain.feed(messages):
            by_topic[msg.name].append(msg)
    return by_topic


def fastest_s(fn: Callable[[], object], repeat: int) -> float:
    """The fastest of ``repeat`` calls of ``fn``, s."""
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def median_s(fn: Callable[[], object], budget_s: float, min_reps: int = 3,
             clock: Callable[[], float] = time.perf_counter) -> float:
    """Median time of ``fn()`` on ``clock`` over at least ``min_reps`` calls and ``budget_s`` seconds of it, s."""
    times: list[float] = []
    start = clock()
    while len(times) < min_reps or clock() - start < budget_s:
        t0 = clock()
        fn()
        times.append(clock() - t0)
    return statistics.median(times)


#: The calibration workloads: fixed, so their times say how fast this machine is against another's.
CALIBRATION_ADDITIONS = 3_000_000
CALIBRATION_NUMPY_CALLS = 20_000


def calibration_rows(repeat: int = 3) -> list[Row]:
    """How fast this machine runs plain Python and small NumPy calls (the pipeline's two kinds of
    work), fastest of ``repeat``: read every other figure of a table against these two."""
    def python_loop() -> int:
        total = 0
        for i in range(CALIBRATION_ADDITIONS):
            total += i
        return total

    a = np.linspace(0.0, 1.0, 181)

    def numpy_calls() -> None:
        for _ in range(CALIBRATION_NUMPY_CALLS // 4):
            np.hypot(a, a).sum() + np.sin(a).max()

    return [Row("calibration", f"pure Python: {CALIBRATION_ADDITIONS:,} additions", fastest_s(python_loop, repeat),
                "s", note="int additions in a loop inside a function"),
            Row("calibration", f"NumPy: {CALIBRATION_NUMPY_CALLS:,} small calls", fastest_s(numpy_calls, repeat),
                "s", note="hypot, sin, sum, max on 181 floats: call overhead, as in the stages")]


def kernel_compile_rows() -> list[Row]:
    """The compiled kernels (scan matching, correlative search): compiling them in a fresh process with an empty cache,
    then loading them from that cache in another (what each slam and mapper start costs)."""
    code = "from lrfslam.algo.kernels import prepare; prepare()"
    rows = []
    with tempfile.TemporaryDirectory(prefix="lrfslam_numba_") as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache}
        for what in ("compile (empty cache)", "load from the cache"):
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-c", code], env=env, check=True)
            rows.append(Row("stage cost", f"compiled kernels: {what}", time.perf_counter() - t0, "s",
                            note="a fresh process: import, then every kernel on a few points"))
    return rows


def _per_scan_row(measure: str, seconds: Sequence[float], note: str) -> Row:
    ms = 1e3 * np.asarray(seconds)
    return Row("stage cost", measure, float(np.median(ms)), "ms/scan",
               note=f"p90 {np.percentile(ms, 90):.3f} ms; {note}")


def stage_rows(n_scans: int, seed: int, repeat: int) -> list[Row]:
    """Per-scan cost of denoise, corners, wall direction and scan matching on ``n_scans`` simulated scans."""
    cfg = _configs()
    msgs = run_chain(sim_messages(n_scans, seed), ["denoise"])
    scans = [m.value for m in msgs[topics.SCAN.name]]
    filtered = [m.value for m in msgs[topics.SCAN_FILTERED.name]]
    odom = [m.value.pose for m in msgs[topics.ODOM.name]]
    hist, corners, walls = cfg["denoise"].histogram, cfg["features"].corners, cfg["features"].wall_lines
    where = f"{len(scans)} simulated scans, fastest of {repeat} call{'s' * (repeat > 1)} each"
    rows = [
        _per_scan_row("denoise (angle histogram)", [fastest_s(lambda s=s: denoise(s.ranges_m, s.angles_rad, hist),
                                                              repeat) for s in scans], where),
        _per_scan_row("corners (forward + backward searching)",
                      [fastest_s(lambda f=f: extract_features(f.scan.ranges_m, f.scan.angles_rad, f.kept_mask,
                                                              corners), repeat) for f in filtered], where),
        _per_scan_row("wall direction", [fastest_s(lambda f=f: wall_direction(f.points_xy_m, walls), repeat)
                                         for f in filtered], where),
    ]
    # The tracker keeps state (its keyframes): each scan is matched once, in order.
    tracker, times = ScanTracker(cfg["slam"].tracker), []
    for k, scan in enumerate(scans):
        valid = (scan.status == t.BEAM_VALID) & np.isfinite(scan.ranges_m)
        points = polar_to_xy(scan.ranges_m[valid], scan.angles_rad[valid])
        step = np.zeros(3) if k == 0 else relative(odom[k - 1], odom[k])
        t0 = time.perf_counter()
        tracker.step(points, step, ODOM_COV)
        times.append(time.perf_counter() - t0)
    rows.append(_per_scan_row("scan matching (tracker step)", times[1:], f"{len(scans) - 1} simulated scans, once each"))
    return rows


# -- the EKF against filterpy's dense update

def random_filter(n_lm: int, rng: np.random.Generator) -> EkfSlam:
    """A filter with ``n_lm`` confirmed landmarks within ±20 m and a dense, well-conditioned covariance.

    Built on an empty filter's snapshot, so it has whatever the filter's state holds before its
    landmarks (the pose, the building orientation: set) and every landmark field, in the current format.
    """
    snap = EkfSlam(EkfParams()).snapshot()
    head = snap["state_mean"]
    n = head.size + 2 * n_lm
    a = rng.normal(size=(n, 8)) * 0.05   # low-rank correlations keep every entry non-zero
    snap.update({key: np.zeros(n_lm, dtype=value.dtype) for key, value in snap.items() if key.startswith("landmark_")})
    snap.update(state_mean=np.concatenate((head, rng.uniform(-20, 20, size=2 * n_lm))),
                state_cov=a @ a.T + 1e-3 * np.eye(n), landmark_ids=np.arange(n_lm, dtype=np.int64),
                landmark_sightings=np.full(n_lm, 3), landmark_confirmed=np.ones(n_lm, dtype=bool), next_id=n_lm,
                psi_set=True)   # the building orientation known, as in a running map
    return EkfSlam.restore(EkfParams(), snap)


def _range_bearing(x: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Dense model for filterpy: h (2, 1) and H (2, n) of the landmark whose x coordinate is ``x[k]``."""
    dx, dy = x[k] - x[0], x[k + 1] - x[1]
    q = dx * dx + dy * dy
    r = np.sqrt(q)
    H = np.zeros((2, x.size))
    H[:, :3] = [[-dx / r, -dy / r, 0.0], [dy / q, -dx / q, -1.0]]
    H[:, k: k + 2] = [[dx / r, dy / r], [-dy / q, dx / q]]
    return np.array([[r], [wrap_angle(np.arctan2(dy, dx) - x[2])]]), H


def _bearing_residual(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    y = a - b
    y[1, 0] = wrap_angle(y[1, 0])
    return y


def dense_update(ekf: ExtendedKalmanFilter, z: np.ndarray, R: np.ndarray, k: int) -> None:
    """filterpy's update of ``ekf`` by the range and bearing ``z`` (2,) (covariance ``R``) of the landmark
    whose x coordinate is the state's ``k``-th entry."""
    ekf.update(z.reshape(2, 1), lambda x, j: _range_bearing(x.ravel(), j)[1],
               lambda x, j: _range_bearing(x.ravel(), j)[0], R=R, args=(k,), hx_args=(k,), residual=_bearing_residual)


def update_times(n_lm: int, rng: np.random.Generator, budget_s: float, min_reps: int, dense: bool,
                 clock: Callable[[], float] = time.perf_counter) -> tuple[float, float]:
    """Median seconds (on ``clock``) of one range-bearing update at ``n_lm`` landmarks: ours, and
    filterpy's dense one (NaN unless ``dense``)."""
    f = random_filter(n_lm, rng)
    R = np.diag([0.015**2, 0.005**2])
    z = np.array([5.0, 0.3])
    ours = median_s(lambda: f.update_known(int(rng.integers(n_lm)), z, R), budget_s, min_reps, clock)
    if not dense:
        return ours, float("nan")
    ekf = ExtendedKalmanFilter(dim_x=f.state_mean.size, dim_z=2)
    ekf.x = f.state_mean.reshape(-1, 1)
    ekf.P = f.state_cov

    first = f.state_mean.size - 2 * n_lm   # index of the first landmark's x
    return ours, median_s(lambda: dense_update(ekf, z, R, first + 2 * int(rng.integers(n_lm))), budget_s,
                          min_reps, clock)


def loglog_slope(sizes: Sequence[float], seconds: Sequence[float]) -> float:
    """Least-squares slope of log(seconds) against log(sizes) over the finite entries; NaN below two."""
    s, y = np.asarray(sizes, dtype=float), np.asarray(seconds, dtype=float)
    ok = np.isfinite(y) & (y > 0)
    if ok.sum() < 2:
        return float("nan")
    return float(np.polyfit(np.log(s[ok]), np.log(y[ok]), 1)[0])


@dataclass(frozen=True)
class EkfShape:
    """Update times (s) per landmark count: ours and filterpy's dense one (NaN where not timed)."""

    sizes: tuple[int, ...]
    ours_s: tuple[float, ...]
    dense_s: tuple[float, ...]

    @property
    def fitted(self) -> tuple[int, ...]:
        """The sizes the slopes are fitted over: from :data:`EKF_FIT_FROM` landmarks."""
        return tuple(n for n in self.sizes if n >= EKF_FIT_FROM)

    def _slope(self, seconds: Sequence[float]) -> float:
        keep = [i for i, n in enumerate(self.sizes) if n >= EKF_FIT_FROM]
        return loglog_slope([self.sizes[i] for i in keep], [seconds[i] for i in keep])

    @property
    def slope_ours(self) -> float:
        return self._slope(self.ours_s)

    @property
    def slope_dense(self) -> float:
        return self._slope(self.dense_s)

    def ratio_at(self, n_lm: int) -> float:
        """Dense time over ours at ``n_lm`` landmarks (NaN if either was not timed)."""
        if n_lm not in self.sizes:
            return float("nan")
        i = self.sizes.index(n_lm)
        return self.dense_s[i] / self.ours_s[i]


def ekf_shape(sizes: Sequence[int], dense_sizes: Sequence[int], seed: int, budget_s: float, min_reps: int,
              clock: Callable[[], float] = time.perf_counter) -> EkfShape:
    """Time both updates at every count of ``sizes`` (the dense one only at ``dense_sizes``) on ``clock``."""
    rng = np.random.default_rng(seed)
    ours, dense = zip(*(update_times(n, rng, budget_s, min_reps, n in dense_sizes, clock) for n in sizes),
                      strict=True)
    return EkfShape(tuple(sizes), ours, dense)


def check_ekf(shape: EkfShape, at: int = CHECK_AT_LANDMARKS, min_ratio: float = CHECK_MIN_RATIO,
              slope_range: tuple[float, float] = CHECK_SLOPE_RANGE) -> list[str]:
    """What breaks the EKF's shape, one line each (empty: it holds): ours at least ``min_ratio``
    times faster than the dense update at ``at`` landmarks, its log-log slope within ``slope_range``."""
    problems = []
    ratio = shape.ratio_at(at)
    if not ratio >= min_ratio:   # NaN fails too: the ratio was not measured
        problems.append(f"EKF update at {at} landmarks only {ratio:.1f}x faster than filterpy's dense update "
                        f"(needs >= {min_ratio:g}x)")
    lo, hi = slope_range
    if not lo <= shape.slope_ours <= hi:
        problems.append(f"EKF update log-log slope {shape.slope_ours:.2f} against the landmark count over "
                        f"{', '.join(map(str, shape.fitted))} (needs {lo:g}..{hi:g}: O(n^2))")
    return problems


def ekf_rows(shape: EkfShape) -> list[Row]:
    """One row per landmark count (ours, filterpy's, the ratio) and one for the slopes."""
    rows = [Row("EKF update", f"{n} landmarks", 1e3 * o, "ms",
                f"filterpy dense {1e3 * d:.3g} ms" if np.isfinite(d) else "", d / o if np.isfinite(d) else None)
            for n, o, d in zip(shape.sizes, shape.ours_s, shape.dense_s, strict=True)]
    dense = f"filterpy dense {shape.slope_dense:.2f}" if np.isfinite(shape.slope_dense) else ""
    rows.append(Row("EKF update", "log-log slope against landmarks", shape.slope_ours, "", dense, None,
                    f"fitted over {', '.join(map(str, shape.fitted))} landmarks; O(n^2) is 2, O(n^3) 3"))
    return rows


# -- codecs

def _codec_row(measure: str, msgs: Sequence[Message], repeat: int, note: str = "") -> Row:
    """Median encode + decode of ``msgs`` (one topic), µs per message, with their size."""
    codec = msgs[0].topic.codec
    payloads = [codec.encode(m.value) for m in msgs]
    enc = [fastest_s(lambda m=m: codec.encode(m.value), repeat) for m in msgs]
    dec = [fastest_s(lambda p=p: codec.decode(p), repeat) for p in payloads]
    size = statistics.median(len(p) for p in payloads)
    return Row("encode/decode", measure, 1e6 * (statistics.median(enc) + statistics.median(dec)), "µs/msg",
               note=f"encode {1e6 * statistics.median(enc):.1f} + decode {1e6 * statistics.median(dec):.1f} µs; "
                    f"{size:,.0f} B" + (f"; {note}" if note else ""))


def codec_rows(n_scans: int, seed: int, repeat: int) -> list[Row]:
    """Encode + decode per message of every topic of the pipeline, and the slam's per-scan outputs at map sizes."""
    msgs = run_chain(sim_messages(n_scans, seed), ["denoise", "features", "slam", "mapper"])
    rows = [_codec_row(name, found, repeat, f"{len(found)} messages of a {n_scans}-scan simulated run")
            for name, found in msgs.items()]
    slam_out = {tp.name for tp in services.spec("slam").outputs}
    rng = np.random.default_rng(seed)
    frames = sim_messages(10, seed)
    with tempfile.TemporaryDirectory(prefix="lrfslam_bench_") as tmp:
        for n_lm in STATE_MAP_SIZES:
            folder = Path(tmp) / str(n_lm)
            npz_file.write_atomic(checkpoints.path_for(folder, "slam"), checkpoint.encode(random_filter(n_lm, rng), 0, None))
            # A slam stage resumed from a filter of n_lm landmarks: its whole map. (Its states are
            # measured on real runs, state_rows: this random filter's landmarks are all correlated
            # with the pose, so each update moves every one of them, as no building does.)
            outs = run_chain(frames, ["denoise", "features", "slam"], checkpoint_dir=folder)
            rows += [_codec_row(f"{name}, {n_lm}-landmark map", found, repeat, f"{len(found)} messages")
                     for name, found in outs.items() if name in slam_out and name != topics.SLAM_STATE.name]
    return rows


def _as_v1(state: t.SlamState, lms: t.Landmarks) -> bytes:
    """``state`` as the v1 message that carried the whole map ``lms`` with every state."""
    p = slam_state_v1.SlamState(scan_seq=state.scan_seq, associated=state.associated, added=state.added,
                                rejected=state.rejected)
    p.header.stamp_ns, p.header.seq, p.header.frame_id = state.stamp_ns, state.seq, "map"
    p.pose.x_m, p.pose.y_m, p.pose.theta_rad = (float(v) for v in state.pose)
    p.pose_covariance.extend(state.pose_cov.ravel().tolist())
    if state.motion is not None:
        p.motion.x_m, p.motion.y_m, p.motion.theta_rad = (float(v) for v in state.motion)
    p.motion_matched = bool(state.motion_matched)
    for i in range(len(lms)):
        p.landmarks.add(id=int(lms.ids[i]), x_m=float(lms.xy_m[i, 0]), y_m=float(lms.xy_m[i, 1]),
                        covariance_m2=lms.cov_m2[i].ravel().tolist(), kind=int(lms.kind[i]),
                        sightings=int(lms.sightings[i]), confirmed=bool(lms.confirmed[i]))
    return p.SerializeToString()


def state_rows(name: str, recording: Path, window: int, repeat: int) -> list[Row]:
    """The slam stage's per-scan message in ``recording``: mean size and decode + encode over its first
    and its last ``window`` states, against the v1 state that held the whole map (decode; v1 is
    decoded through the upgrade path, as an old recording is)."""
    replica, rows, kept = LandmarkMapReplica(), [], []
    codec = topics.SLAM_STATE.codec
    v1_schema = slam_state_v1.SlamState.DESCRIPTOR.full_name
    for m in read_recording(recording, [topics.SLAM_STATE.name, topics.SLAM_MAP.name]):
        value = topics.by_name(m.topic).codec.decode(m.data, m.schema)
        replica.apply_message(value)
        if m.topic == topics.SLAM_STATE.name:
            kept.append((value.n_landmarks, m.data, _as_v1(value, replica.landmarks)))
    if not kept:
        return [Row("slam/state per scan", f"{name}: no slam/state recorded", float("nan"), "")]
    for part, states in (("first", kept[:window]), ("last", kept[-window:])):
        cost = [fastest_s(lambda d=d: codec.encode(codec.decode(d)), repeat) for _, d, _ in states]
        cost_v1 = [fastest_s(lambda d=d: codec.decode(d, v1_schema), repeat) for _, _, d in states]
        n, size = np.mean([k for k, _, _ in states]), np.mean([len(d) for _, d, _ in states])
        size_v1 = np.mean([len(d) for _, _, d in states])
        rows.append(Row("slam/state per scan", f"{name}, {part} {len(states):,} states ({n:.0f} landmarks)",
                        1e6 * np.mean(cost), "µs/msg", f"v1 whole-map state decode {1e6 * np.mean(cost_v1):.0f} µs",
                        np.mean(cost_v1) / np.mean(cost), f"decode + encode; {size:,.0f} B (v1 {size_v1:,.0f} B)"))
    return rows
