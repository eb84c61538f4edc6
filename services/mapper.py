"""mapper: loop closing behind the EKF — keyframes in a pose graph, closures found by correlative search.

in:  scan           LaserScan (the raw scan: the keyframes' points)
     slam/state     SlamState (the EKF's pose after each scan)
out: map/pose       MapPose (per slam state: the pose corrected by every closure so far; published
                    before the keyframe work the state may cause, whose closures the next pose carries)
     map/keyframes  MapKeyframes (after each optimisation and at the end: the graph's optimised
                    keyframes, and those retired from it since the last, once)
     map/grid       MapGrid (at most once a second of data, and at the end: the tiles of the
                    live occupancy grid that changed; whole for a late joiner's query)

The EKF with corner landmarks stays the online estimator; this stage (``lrfslam.algo.loop_closure``)
closes the loops it cannot, from a large prior error. The EKF's pose of each scan tells the closure
search where else to look: after a long loop the EKF, having re-observed its landmarks, may know
where the robot is when the mapper's chain of motions has drifted beyond its search window. A slam state waits for its scan (or for a newer
scan: its own was lost), so the result does not depend on how the two streams interleave. The final
trajectory of a recording is every slam state placed by the last ``map/keyframes``
(``lrfslam.evaluation.map_trajectory``).

The step is :class:`Resumable`: where the runtime keeps checkpoints (``bus.checkpoint_dir``,
``lrfslam.runtime.checkpoints``) a restarted mapper continues its graph. The local trajectory is the chain of the
states' motions; where that chain breaks (a state number skipped: states lost, this stage or the slam
stage restarted) the filter's own pose change bridges the gap, taken as the motion across it: the
closures that follow correct what the filter got wrong meanwhile.

On a saved map (``map``) the mapper maps on from it (:class:`MapperStep`: found on the map first,
then joined to its graph; docs/maps.md "Mapping on from a saved map"), or with ``localize`` only
localizes in it (:class:`LocalizeStep`).

The live occupancy grid (``lrfslam.algo.keyframe_grid``) is the graph's keyframes' raw scans at
their optimised poses, traced as ``lrfslam export`` traces a recording's; keyframes an optimisation
moved are laid again, one per scan. It travels as the tiles whose cells changed, so a message
stays small however large the building; the checkpoint keeps the keyframes' scans, so a restarted
mapper has its grid again.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from lrfslam.algo import kernels
from lrfslam.algo.geometry import compose, polar_to_xy, relative
from lrfslam.algo.keyframe_grid import KeyframeGrid
from lrfslam.algo.localization import LocalizationMap, Localizer, Status, Walls
from lrfslam.algo.loop_closure import LoopClosingMapper, LoopClosureParams
from lrfslam.algo.stream_alignment import AlignmentParams, StreamAligner
from lrfslam.algo.tiled_grid import tiles_of
from lrfslam.errors import ConfigError, InputError, MapFormatError
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.runtime.saved_map import SavedMap, load_map
from lrfslam.runtime.step import Message, Output, RunContext, ServiceSpec, StepBase

log = logging.getLogger("lrfslam.mapper")

#: Slam states held for their scan at most, then placed without one (a lost scan must not hold
#: the map back: 2 s at the LMS200's 10 Hz).
MAX_WAITING_STATES = 20
#: The live grid's changed tiles go out at most this often, ns of data time (slam_toolbox's
#: ``map_update_interval`` is 5 s; a viewer wants a driving robot's map sooner).
GRID_PERIOD_NS = 1_000_000_000


@dataclass(frozen=True)
class MapperConfig:
    """The mapper stage's configuration; ``SETTINGS`` are the names an operator sets (docs/settings.md).

    ``map``: a saved map's folder (``lrfslam map save``) to map on from (``lrfslam up --map MAP``);
    with ``localize``, find and track the robot on it instead, the map unchanged (``lrfslam up
    --map MAP --localize``; docs/maps.md).
    """

    loop_closure: LoopClosureParams = field(default_factory=LoopClosureParams)
    map: str = ""
    localize: bool = False

    SETTINGS: ClassVar[tuple[str, ...]] = (
        "map", "localize",
        *(f"loop_closure.{name}" for name in (
            "keyframe_trans_m", "keyframe_rot_rad", "max_range_m", "min_travel_m", "candidate_radius_m",
            "max_window_m", "min_score", "max_second_ratio", "gate_chi2", "match_cov_scale",
            "odom_trans_sigma_per_m", "odom_rot_sigma_per_m", "odom_rot_sigma_per_rad",
            "fold_revisits", "fold_after_keyframes", "correlative.cell_m")),
    )
    RETIRED: ClassVar[dict[str, str]] = {
        "checkpoint_path": "the runtime keeps every stage's checkpoint: bus.checkpoint_dir (<dir>/mapper.checkpoint.npz)",
        "checkpoint_every_keyframes": "the runtime saves every bus.checkpoint_period_s of data time",
        "max_waiting_states": f"fixed at {MAX_WAITING_STATES} (services/mapper.py MAX_WAITING_STATES)",
        "local_trajectory": "the local trajectory is always the chain of the slam's motions (slam_motion)",
        "loop_closure.drift_scale": "replaced by the drift model (loop_closure.odom_*); 1 did nothing",
        "loop_closure.interpolate": "always on: each scan is placed between its keyframes",
    }

    def __post_init__(self) -> None:
        if self.localize and not self.map:
            raise ConfigError("mapper: localize needs map, a saved map's folder (lrfslam map save)")


class LocalTrajectory:
    """The chain of the slam states' motions: the mapper's local trajectory (the module's docstring).

    The filter's own pose jumps when it corrects itself; the chain of the motions that moved it
    does not, so over metres it is as good as scan matching.
    """

    def __init__(self, counts) -> None:
        self.counts = counts
        self.pose: np.ndarray | None = None       # the last state's pose on the local trajectory
        self.last_slam_pose = np.zeros(3)
        self.last_state_seq = -1                  # the last state's number; -1: none yet

    def add(self, state: t.SlamState) -> tuple[np.ndarray, np.ndarray | None]:
        """The state's pose on the local trajectory (3,), and the step the mapper checks it
        against for jumps (3,): the scan-matched motion; None if there is none."""
        matched = state.motion if state.motion is not None and state.motion_matched else None
        if self.pose is None:
            local, reference = state.pose, matched   # (a chain starts where the filter does)
        elif state.motion is None:
            # A slam state recorded before they carried their motion: follow the filter's pose.
            self.counts["motion_missing"] += 1
            local, reference = compose(self.pose, relative(self.last_slam_pose, state.pose)), None
        elif state.seq != self.last_state_seq + 1:
            # States missed (this stage or the slam stage restarted, or lost): the motion is from a
            # state this stage never saw. The filter's own pose change bridges the gap; it is
            # trusted as it stands, because the keyframes' scans cannot check a step metres long.
            self.counts["motion_bridged"] += 1
            bridge = relative(self.last_slam_pose, state.pose)
            local, reference = compose(self.pose, bridge), bridge
        else:
            local, reference = compose(self.pose, state.motion), matched
        self.pose, self.last_slam_pose, self.last_state_seq = local, state.pose, state.seq
        return local, reference


def load_saved(path: str) -> SavedMap:
    """The saved map at ``path``; :class:`ConfigError` (one line) where it cannot be read."""
    try:
        return load_map(path)
    except MapFormatError as exc:
        raise ConfigError(f"mapper: map {path}: {exc}") from None


def localizer_on(saved: SavedMap, points: list[np.ndarray]) -> Localizer:
    """A :class:`Localizer` on the saved map's keyframes (``points``: each one's, robot frame) and walls."""
    return Localizer(LocalizationMap(saved.map_pose, points,
                                     Walls(saved.grid_cells, saved.grid_resolution_m, saved.grid_origin_xy_m)))


def keyframe_point_sets(saved: SavedMap) -> list[np.ndarray]:
    """Each saved keyframe's scan points (N_k, 2), robot frame, m."""
    return [saved.keyframe_points(k) for k in range(saved.map_pose.shape[0])]


class NoReturnBearings:
    """Each scan's bearings of beams with no return (rad, robot frame), kept by scan number until
    its slam state takes them: what the localizer follows through free space. Bounded as the
    aligner's scans are."""

    def __init__(self) -> None:
        self._by_seq: dict[int, np.ndarray] = {}

    def add(self, scan: t.LaserScan) -> None:
        self._by_seq[scan.seq] = scan.angles_rad[scan.status == t.BEAM_NO_RETURN]
        while len(self._by_seq) > 2 * MAX_WAITING_STATES + 2:
            del self._by_seq[next(iter(self._by_seq))]

    def take(self, scan_seq: int) -> np.ndarray:
        """Scan ``scan_seq``'s bearings (K,), none if it never came or was dropped."""
        return self._by_seq.pop(scan_seq, np.zeros(0))


def count_localizer(counts, localizer: Localizer) -> None:
    """The localizer's own counters as the stage's (``lrfslam status``)."""
    counts["global_searches"] = localizer.searches
    counts["fixes"] = localizer.fixes
    counts["fixes_lost"] = localizer.lost
    counts["matches_gated"] = localizer.gated
    counts["scans_doubted"] = localizer.doubted
    for why, n in localizer.refused.items():
        counts[f"searches_{why}"] = n


class MapperStep(StepBase):
    """The mapper: from an empty map, or with ``map`` from a saved one (mapping on).

    On a saved map the graph starts as the saved keyframes
    (:meth:`LoopClosingMapper.seeded`) and the grid as their scans; the robot is first found on
    the map as in localization (:class:`~lrfslam.algo.localization.Localizer`; ``map/pose`` says
    "not localized" meanwhile, and those scans make no keyframe), and at the fix the run joins the
    graph (:meth:`LoopClosingMapper.join`); from then on it maps as from an empty map, and closes
    its revisits into the saved keyframes.
    """

    def __init__(self, cfg: MapperConfig, ctx: RunContext, saved: SavedMap | None = None) -> None:
        super().__init__()
        self.cfg = cfg
        kernels.prepare()
        if cfg.map and saved is None:
            saved = load_saved(cfg.map)
        self.saved = saved
        self.mapper = LoopClosingMapper(cfg.loop_closure, keep_scans=False)
        #: Finds the robot on the saved map until the run joins it (None: from an empty map, or joined).
        self.finder: Localizer | None = None
        if saved is not None:
            points = keyframe_point_sets(saved)
            self.mapper = LoopClosingMapper.seeded(cfg.loop_closure, saved.map_pose, points, saved.stamp_ns)
            self.finder = localizer_on(saved, points)
        # A slam state waits for its scan as features do in the slam stage (no odometry here).
        self.align: StreamAligner[t.SlamState] = StreamAligner(AlignmentParams(
            wait_for_odometry=False, max_wait=MAX_WAITING_STATES, scans_optional=False))
        self.no_returns = NoReturnBearings()
        self.seq = 0
        self.keyframes_seq = 0
        self.optimisations = 0
        self._last_stamp = 0
        self.local = LocalTrajectory(self.counts)
        self.grid = KeyframeGrid()
        self.grid_seq = 0
        self._grid_due_ns: int | None = None
        self._grid_sent: dict[tuple[int, int], bytes] = {}   # tile -> its cells as last published
        self._grid_resolution_changes = 0
        if saved is not None:
            try:
                for k, (stamp, pose) in enumerate(zip(saved.stamp_ns.tolist(), saved.map_pose, strict=True)):
                    self.grid.add_scan(stamp, *saved.keyframe_scan(k))
                    self.grid.add_keyframe(stamp, pose)
            except (KeyError, TypeError, ValueError) as exc:
                raise ConfigError(f"mapper: map {cfg.map}: no laser layout in its manifest ({exc!r})") from None
            self._grid_resolution_changes = self.grid.grid.resolution_changes

    def on_message(self, msg: Message):
        v = msg.value
        if msg.topic is topics.SCAN:
            valid = (v.status == t.BEAM_VALID) & np.isfinite(v.ranges_m)
            self.align.add_scan(v.seq, v.stamp_ns, polar_to_xy(v.ranges_m[valid], v.angles_rad[valid]))
            self.no_returns.add(v)
            self.grid.add_scan(v.stamp_ns, v.grid_ranges(), v.angle_min_rad, v.angle_increment_rad)
        elif msg.topic is topics.SLAM_STATE:
            self.align.add_features(v.stamp_ns, v.scan_seq, v)
        return self._placing(self.align.ready())

    def finish(self):
        outs = list(self._placing(self.align.ready(final=True)))
        if self.mapper.keyframe_count:
            self.mapper.finish()   # every closure still pending solved for, every revisit folded
            outs.append(self._keyframes(self._last_stamp))
            self.grid.work(-1)
            outs += self._grid_changes(self._last_stamp, final=True)
        return outs

    def latest(self, topic):
        """The whole grid for a late joiner (the other outputs: the newest published)."""
        if topic is not topics.MAP_GRID or not len(self.grid.grid):
            return None
        tiles = self.grid.grid.tiles()
        return self._grid_message(self._last_stamp, tiles, [self.grid.grid.trinary(tl) for tl in tiles], whole=True,
                                  seq=self.grid_seq)

    def _grid_changes(self, stamp_ns: int, final: bool = False) -> list[Output]:
        """The grid's changed tiles, once ``GRID_PERIOD_NS`` of data has passed since the last (or ``final``)."""
        if not final and self._grid_due_ns is not None and stamp_ns < self._grid_due_ns:
            return []
        grid = self.grid.grid
        changed = grid.take_changed()
        whole = grid.resolution_changes != self._grid_resolution_changes
        if whole:   # every tile anew, at the new resolution
            self._grid_resolution_changes = grid.resolution_changes
            self._grid_sent.clear()
            changed = grid.tiles()
        tiles, cells = [], []
        for tile in changed:
            tri = grid.trinary(tile)
            data = tri.tobytes()
            if self._grid_sent.get(tile) != data:
                self._grid_sent[tile] = data
                tiles.append(tile)
                cells.append(tri)
        if not tiles and not whole:
            return []
        self._grid_due_ns = stamp_ns + GRID_PERIOD_NS
        self.grid_seq += 1
        self.counts["grid_updates"] += 1
        return [Output(topics.MAP_GRID, self._grid_message(stamp_ns, tiles, cells, whole, self.grid_seq))]

    def _grid_message(self, stamp_ns: int, tiles, cells, whole: bool, seq: int) -> t.MapGrid:
        side = self.grid.grid.tile_cells
        return t.MapGrid(stamp_ns=stamp_ns, seq=seq, resolution_m=self.grid.grid.resolution_m, tile_cells=side,
                         tiles=np.array(tiles, np.int64).reshape(-1, 2),
                         cells=np.array(cells, np.int8).reshape(-1, side, side), whole=whole,
                         keyframes=self.grid.keyframes, pending=self.grid.pending)

    def _placing(self, ready) -> Iterator[Output]:
        for a in ready:
            yield from self._place(a.features, a.scan_xy_m)

    def _place(self, state: t.SlamState, points: np.ndarray | None) -> Iterator[Output]:
        """The scan's ``map/pose`` first, on the graph as it stands; then the keyframe it may make (its closure
        search, an optimisation: up to tens of ms), the keyframes after an optimisation, and the grid. Live, the
        pose goes out before that work (the runner puts each output as it comes), and the next scan's pose
        carries what the work found."""
        if points is None:
            self.counts["scan_missing"] += 1
            points = np.zeros((0, 2))
        local, reference = self.local.add(state)
        if self.mapper.waiting_for_join:
            yield from self._find(state, local, points)
            return
        yield self._pose(state, self.mapper.place(local), local)
        made = self.mapper.keyframe_count
        pose = self.mapper.add_scan(state.stamp_ns, local, points, reference, online_pose=state.pose)
        if self.mapper.keyframe_count != made:   # this scan made a keyframe: the grid lays its scan there
            self.grid.add_keyframe(state.stamp_ns, pose)
        yield from self._after(state.stamp_ns)

    def _find(self, state: t.SlamState, local: np.ndarray, points: np.ndarray) -> Iterator[Output]:
        """On a saved map before the fix: the scan to the localizer; at the fix the run joins the graph."""
        found = self.finder.add_scan(local, points, self.no_returns.take(state.scan_seq))
        count_localizer(self.counts, self.finder)
        if found.status is not Status.LOCALIZED:
            self.counts["not_localized"] += 1
            self.counts["scans"] += 1
            self._last_stamp = state.stamp_ns
            self.seq += 1
            yield Output(topics.MAP_POSE, t.MapPose(
                stamp_ns=state.stamp_ns, seq=self.seq, scan_seq=state.scan_seq, pose=found.pose,
                map_from_slam=compose(found.pose, relative(state.pose, np.zeros(3))),
                keyframes=self.mapper.keyframe_count, local_pose=local, localization=t.NOT_LOCALIZED))
            yield from self._grid_changes(state.stamp_ns)
            return
        log.info("found on the saved map after %d global searches: mapping on from it", self.finder.searches)
        pose = self.mapper.join(state.stamp_ns, local, points, found.pose, found.cov, online_pose=state.pose)
        self.grid.add_keyframe(state.stamp_ns, pose)
        self.finder = None
        yield self._pose(state, pose, local)
        yield from self._after(state.stamp_ns)

    def _pose(self, state: t.SlamState, pose: np.ndarray, local: np.ndarray) -> Output:
        """``map/pose`` of a scan the graph places at ``pose``."""
        self._last_stamp = state.stamp_ns
        stats = self.mapper.stats
        self.counts["scans"] += 1
        self.seq += 1
        rejected = stats.ambiguous + stats.refine_failed + stats.gated + stats.removed
        return Output(topics.MAP_POSE, t.MapPose(
            stamp_ns=state.stamp_ns, seq=self.seq, scan_seq=state.scan_seq, pose=pose,
            map_from_slam=compose(pose, relative(state.pose, np.zeros(3))), keyframes=self.mapper.keyframe_count,
            closures=stats.accepted - stats.removed, closures_rejected=rejected, local_pose=local))

    def _after(self, stamp_ns: int) -> list[Output]:
        """After a scan's keyframe work: the keyframes if it optimised the graph, the grid's changes."""
        verified, nis_sum = self.mapper.closure_nis
        self.counts["closures_verified"] = verified
        self.counts["closure_nis_milli"] = round(1000.0 * nis_sum)
        outs = []
        if self.mapper.stats.optimisations != self.optimisations:
            self.optimisations = self.mapper.stats.optimisations
            outs.append(self._keyframes(stamp_ns))
        self.grid.work()
        return outs + self._grid_changes(stamp_ns)

    def _keyframes(self, stamp_ns: int) -> Output:
        stamps, local_poses = self.mapper.keyframe_stamped_local_poses()
        retired = self.mapper.take_retired()   # told once: a reader of the whole run keeps them
        map_poses = self.mapper.keyframe_poses()
        self.grid.set_poses(stamps, map_poses)
        self.keyframes_seq += 1
        self.counts["keyframe_updates"] += 1
        self.counts["keyframes_retired"] += len(retired)
        return Output(topics.MAP_KEYFRAMES, t.MapKeyframes(
            stamp_ns=stamp_ns, seq=self.keyframes_seq, scan_stamp_ns=stamps, local_pose=local_poses,
            map_pose=map_poses, local_edge=self.mapper.keyframe_local_edges(),
            retired_scan_stamp_ns=retired.stamp_ns, retired_local_pose=retired.local_pose,
            retired_local_edge=retired.local_edge, retired_anchor_stamp_ns=retired.anchor_stamp_ns,
            retired_offset=retired.offset))

    def snapshot(self) -> dict | None:
        """The pose graph with its keyframes' points, and where the streams stood; None before the first keyframe."""
        if not self.mapper.keyframe_count:
            return None
        arrays = self.mapper.snapshot()
        arrays.update(service_seq=self.seq, service_keyframes_seq=self.keyframes_seq,
                      service_last_stamp_ns=self._last_stamp, service_last_state_seq=self.local.last_state_seq,
                      service_local_pose=np.full(3, np.nan) if self.local.pose is None else self.local.pose,
                      service_last_slam_pose=self.local.last_slam_pose, service_grid_seq=self.grid_seq,
                      service_grid_due_ns=-1 if self._grid_due_ns is None else self._grid_due_ns,
                      service_grid_resolution_changes=self._grid_resolution_changes)
        arrays.update(self.grid.snapshot())
        # The tiles changed since the last map/grid, as then published: every other tile is as published.
        changed = [tile for tile in map(tuple, arrays["grid_changed"].tolist()) if tile in self._grid_sent]
        side = self.grid.grid.tile_cells
        arrays.update(service_grid_sent_tiles=np.array(changed, np.int64).reshape(-1, 2),
                      service_grid_sent_cells=np.frombuffer(b"".join(self._grid_sent[tl] for tl in changed),
                                                            np.int8).reshape(-1, side, side))
        return arrays

    def restore(self, arrays) -> str:
        mapper = LoopClosingMapper.restore(self.cfg.loop_closure, arrays)
        local = np.array(arrays["service_local_pose"], dtype=float).reshape(3)
        last_slam_pose = np.array(arrays["service_last_slam_pose"], dtype=float).reshape(3)
        counters = [int(arrays[k]) for k in ("service_seq", "service_keyframes_seq", "service_last_stamp_ns",
                                             "service_last_state_seq")]
        if mapper.waiting_for_join and self.finder is None:
            raise InputError("a checkpoint of a mapper mapping on from a saved map, and this one has no map")
        self.mapper = mapper
        if not mapper.waiting_for_join:
            self.finder = None   # (it had joined the saved map)
        self.seq, self.keyframes_seq, self._last_stamp, self.local.last_state_seq = counters
        self.local.pose = None if np.any(np.isnan(local)) else local
        self.local.last_slam_pose = last_slam_pose
        self.optimisations = mapper.stats.optimisations
        self.grid = KeyframeGrid()
        self.grid.restore(arrays)
        if "service_grid_seq" in arrays:
            due = int(arrays["service_grid_due_ns"])
            self.grid_seq, self._grid_due_ns = int(arrays["service_grid_seq"]), None if due < 0 else due
            self._grid_resolution_changes = int(arrays["service_grid_resolution_changes"])
            changed = {tuple(tl) for tl in arrays["grid_changed"].tolist()}
            self._grid_sent = {tl: self.grid.grid.trinary(tl).tobytes() for tl in self.grid.grid.tiles()
                               if tl not in changed}
            self._grid_sent.update((tuple(tl), cells.tobytes()) for tl, cells in
                                   zip(arrays["service_grid_sent_tiles"].tolist(), arrays["service_grid_sent_cells"]))
        else:   # a checkpoint from before the grid: it starts empty, and its first message is whole
            self._grid_resolution_changes = self.grid.grid.resolution_changes - 1
        return f"{mapper.keyframe_count} keyframes, {mapper.stats.accepted - mapper.stats.removed} closures"

    def health(self) -> tuple[int, str]:
        s = self.mapper.stats
        if self.saved is None:
            return t.HEALTH_OK, f"{self.mapper.keyframe_count} keyframes, {s.accepted - s.removed} closures"
        if self.mapper.waiting_for_join:
            return t.HEALTH_OK, f"not localized: searching the saved map ({self.counts['global_searches']} global searches)"
        return t.HEALTH_OK, (f"mapping on the saved map: {self.mapper.keyframe_count - self.saved.map_pose.shape[0]} "
                             f"keyframes made, {s.accepted - s.removed} closures")


class LocalizeStep(StepBase):
    """The mapper on a saved map (``localize``): finds the robot on it and tracks it, the map unchanged.

    Each slam state, once its scan is here, goes to :class:`~lrfslam.algo.localization.Localizer`
    on the mapper's local trajectory (:class:`LocalTrajectory`); ``map/pose`` says whether the scan was placed on
    the map, with the pose's covariance. The saved map's grid goes out whole on ``map/grid`` with
    the first pose (and to a late joiner), so viewers draw the map the robot is localized in.
    """

    def __init__(self, cfg: MapperConfig, ctx: RunContext, saved: SavedMap | None = None) -> None:
        super().__init__()
        kernels.prepare()
        saved = self.saved = saved if saved is not None else load_saved(cfg.map)
        self.localizer = localizer_on(saved, keyframe_point_sets(saved))
        self.tiles, self.tile_cells = tiles_of(saved.grid_cells, saved.grid_resolution_m, saved.grid_origin_xy_m)
        self.align: StreamAligner[t.SlamState] = StreamAligner(AlignmentParams(
            wait_for_odometry=False, max_wait=MAX_WAITING_STATES, scans_optional=False))
        self.local = LocalTrajectory(self.counts)
        self.no_returns = NoReturnBearings()
        self.seq = 0
        self.grid_sent = False
        self._last_stamp = 0
        self._status: Status | None = None

    def on_message(self, msg: Message):
        v = msg.value
        if msg.topic is topics.SCAN:
            valid = (v.status == t.BEAM_VALID) & np.isfinite(v.ranges_m)
            self.align.add_scan(v.seq, v.stamp_ns, polar_to_xy(v.ranges_m[valid], v.angles_rad[valid]))
            self.no_returns.add(v)
        elif msg.topic is topics.SLAM_STATE:
            self.align.add_features(v.stamp_ns, v.scan_seq, v)
        return [out for a in self.align.ready() for out in self._place(a.features, a.scan_xy_m)]

    def finish(self):
        return [out for a in self.align.ready(final=True) for out in self._place(a.features, a.scan_xy_m)]

    def _place(self, state: t.SlamState, points: np.ndarray | None) -> list[Output]:
        if points is None:
            self.counts["scan_missing"] += 1
            points = np.zeros((0, 2))
        local, _ = self.local.add(state)
        placed = self.localizer.add_scan(local, points, self.no_returns.take(state.scan_seq))
        if placed.status is not self._status:
            log.info("%s (%d global searches, %d fixes)", "localized" if placed.status is Status.LOCALIZED
                     else "not localized", self.localizer.searches, self.localizer.fixes)
            self._status = placed.status
        self.counts["scans"] += 1
        self.counts["localized" if placed.status is Status.LOCALIZED else "not_localized"] += 1
        count_localizer(self.counts, self.localizer)
        self._last_stamp = state.stamp_ns
        self.seq += 1
        outs = [Output(topics.MAP_POSE, t.MapPose(
            stamp_ns=state.stamp_ns, seq=self.seq, scan_seq=state.scan_seq, pose=placed.pose,
            map_from_slam=compose(placed.pose, relative(state.pose, np.zeros(3))),
            keyframes=self.saved.map_pose.shape[0], local_pose=local,
            localization=t.LOCALIZED if placed.status is Status.LOCALIZED else t.NOT_LOCALIZED, pose_cov=placed.cov))]
        if not self.grid_sent:
            self.grid_sent = True
            outs.append(Output(topics.MAP_GRID, self._grid(state.stamp_ns)))
        return outs

    def _grid(self, stamp_ns: int) -> t.MapGrid:
        return t.MapGrid(stamp_ns=stamp_ns, seq=1, resolution_m=self.saved.grid_resolution_m,
                         tile_cells=self.tile_cells.shape[1], tiles=self.tiles, cells=self.tile_cells, whole=True,
                         keyframes=self.saved.map_pose.shape[0], pending=0)

    def latest(self, topic):
        """The saved map's grid for a late joiner."""
        return self._grid(self._last_stamp) if topic is topics.MAP_GRID and self.grid_sent else None

    def health(self) -> tuple[int, str]:
        loc = self.localizer
        if self._status is Status.LOCALIZED:
            return t.HEALTH_OK, f"localized on {self.saved.map_pose.shape[0]} keyframes"
        what = "lost the map" if loc.localized else f"searching ({loc.searches} global searches)"
        return t.HEALTH_WARN if self._status is not None else t.HEALTH_OK, f"not localized: {what}"


def _build(cfg: MapperConfig, ctx: RunContext) -> MapperStep | LocalizeStep:
    return LocalizeStep(cfg, ctx) if cfg.localize else MapperStep(cfg, ctx)


SPEC = ServiceSpec(
    name="mapper",
    summary="Loop closing behind the EKF: keyframes in a pose graph, closures by correlative search; "
            "publishes the corrected pose per scan, the optimised keyframes and the live occupancy grid.",
    config_type=MapperConfig,
    inputs=(topics.SCAN, topics.SLAM_STATE),
    outputs=(topics.MAP_POSE, topics.MAP_KEYFRAMES, topics.MAP_GRID),
    latest=(topics.MAP_POSE, topics.MAP_KEYFRAMES, topics.MAP_GRID),
    skippable=(topics.SCAN, topics.SLAM_STATE),
    # An optimisation holds the mapper up to a second now and then (docs/delivery.md); it catches up
    # within milliseconds after, so it skips only when behind for longer than that.
    max_lag_s=1.0,
    build=_build,
)
