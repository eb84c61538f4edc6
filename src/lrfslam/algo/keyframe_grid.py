"""The live occupancy grid of a pose graph: each keyframe's scan laid at its pose, and laid again
when an optimisation moves it.

The map is the scans of the graph's keyframes at their optimised poses, as slam_toolbox draws the
scans of its graph's nodes and as ``lrfslam export`` draws a recording with the mapper's output.
Scans wait by stamp (the last ``recent``) until the mapper makes a keyframe of one, which is then
laid at once (:class:`~lrfslam.algo.tiled_grid.TiledGrid`).

After an optimisation, the keyframes that moved by more than a quarter of a cell (at the end of a beam of
the grid's reach, for a turn) are *pending*; :meth:`KeyframeGrid.work` lays at most
``relays_per_call`` of them again each time it is called (once per scan), those that moved most
first, so a closure that bends the whole map is spread over the scans that follow instead of
stalling the mapper for seconds, and what a viewer sees wrong shrinks fastest. A keyframe that leaves the graph (folded into an older one) is taken out: the
grid holds what the graph holds, so it grows with the area mapped, not with the hours driven.
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np

from lrfslam.algo.occupancy_grid import GridParams
from lrfslam.algo.tiled_grid import TILE_CELLS, TiledGrid
from lrfslam.errors import InputError


class KeyframeGrid:
    """The keyframes' scans at their poses, as tiles.

    Parameters
    ----------
    params : GridParams, optional
        As :class:`TiledGrid`'s (default ``lrfslam export``'s).
    tile_cells : int
        Side of a tile, cells (a power of two).
    recent : int
        Scans held for a keyframe still to come (the mapper makes a keyframe of a scan after its
        slam state, which waits for it a few scans at most).
    relays_per_call : int
        Moved keyframes laid again per :meth:`work`.
    """

    def __init__(self, params: GridParams | None = None, tile_cells: int = TILE_CELLS, recent: int = 64,
                 relays_per_call: int = 1) -> None:
        self.grid = TiledGrid(params, tile_cells)
        self.relays_per_call = int(relays_per_call)
        self._recent_size = int(recent)
        self._recent: OrderedDict[int, tuple[np.ndarray, float, float]] = OrderedDict()
        self._target: dict[int, np.ndarray] = {}   # laid keyframe -> its pose in the graph now
        self._pending: list[tuple[float, int]] = []   # (how far moved, m; keyframe), the farthest last
        self.missing = 0                           # keyframes whose scan was not held

    @property
    def pending(self) -> int:
        """Moved keyframes not laid again yet."""
        return len(self._pending)

    @property
    def largest_pending_m(self) -> float:
        """How far from the graph's pose the farthest moved pending keyframe lies, m (0: none)."""
        return self._pending[-1][0] if self._pending else 0.0

    @property
    def keyframes(self) -> int:
        """Keyframes laid."""
        return len(self._target)

    def add_scan(self, stamp_ns: int, ranges, angle_min_rad: float, angle_increment_rad: float) -> None:
        """Hold a scan (ranges (N,) m, +inf no return, NaN invalid) for a keyframe to come."""
        self._recent[int(stamp_ns)] = (np.asarray(ranges, np.float32), float(angle_min_rad), float(angle_increment_rad))
        while len(self._recent) > self._recent_size:
            self._recent.popitem(last=False)

    def add_keyframe(self, stamp_ns: int, pose) -> bool:
        """Lay the scan stamped ``stamp_ns`` at ``pose`` (3,); False when that scan is not held."""
        scan = self._recent.pop(int(stamp_ns), None)
        if scan is None:
            self.missing += 1
            return False
        pose = np.asarray(pose, dtype=float).reshape(3)
        self.grid.lay(int(stamp_ns), pose, *scan)
        self._target[int(stamp_ns)] = pose.copy()
        return True

    def set_poses(self, stamps_ns, poses) -> None:
        """The graph's keyframes now: stamps (K,) and poses (K, 3). Laid keyframes not among them
        are taken out; those that moved become pending."""
        stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        poses = np.asarray(poses, dtype=float).reshape(-1, 3)
        if stamps.size != poses.shape[0]:
            raise InputError(f"{stamps.size} keyframe stamps but {poses.shape[0]} poses")
        now = dict(zip(stamps.tolist(), poses))
        for key in [k for k in self._target if k not in now]:
            self.grid.remove(key)
            del self._target[key]
        for key in self._target:
            self._target[key] = now[key].copy()
        self._queue()

    def work(self, limit: int | None = None) -> int:
        """Lay again up to ``limit`` (default ``relays_per_call``; -1: all) pending keyframes; returns how many."""
        limit = self.relays_per_call if limit is None else limit
        done = 0
        while self._pending and (limit < 0 or done < limit):
            _, key = self._pending.pop()
            self.grid.move(key, self._target[key])
            done += 1
        return done

    def _queue(self) -> None:
        """Pending: every keyframe whose graph pose is more than a quarter of a cell from where it is laid
        (the larger of its shift and its turn at the grid's reach), the farthest moved at the end (taken first)."""
        keys = list(self._target)
        if not keys:
            self._pending = []
            return
        laid = np.array([self.grid.laid(k).pose for k in keys])
        target = np.array([self._target[k] for k in keys])
        turn = np.abs((target[:, 2] - laid[:, 2] + np.pi) % (2 * np.pi) - np.pi)
        far = np.maximum(np.hypot(*(target[:, :2] - laid[:, :2]).T), turn * self.grid.reach_m)
        moved = np.flatnonzero(far > 0.25 * self.grid.resolution_m)
        self._pending = [(float(far[i]), keys[i]) for i in moved[np.argsort(far[moved], kind="stable")]]

    # -- checkpoint ----------------------------------------------------------------------------

    def snapshot(self) -> dict[str, np.ndarray]:
        """The laid keyframes (stamps, laid poses, graph poses, scans) as named arrays."""
        keys = sorted(self._target)
        laid = [self.grid.laid(k) for k in keys]
        width = max((scan.ranges.size for scan in laid), default=0)
        ranges = np.full((len(keys), width), np.nan, np.float32)
        for row, scan in enumerate(laid):
            ranges[row, :scan.ranges.size] = scan.ranges
        state = {f"grid_{name}": value for name, value in self.grid.state().items()}
        return state | {"grid_stamp_ns": np.array(keys, np.int64),
                "grid_laid_pose": np.array([s.pose for s in laid], float).reshape(-1, 3),
                "grid_target_pose": np.array([self._target[k] for k in keys], float).reshape(-1, 3),
                "grid_ranges": ranges,
                "grid_angles": np.array([(s.angle_min_rad, s.angle_increment_rad) for s in laid], float).reshape(-1, 2)}

    def restore(self, arrays) -> None:
        """Lay again what :meth:`snapshot` gave, at its resolution, with the same tiles changed since they
        were last taken (a checkpoint without a grid leaves this one empty).

        Raises
        ------
        InputError
            The arrays disagree with each other.
        """
        if "grid_stamp_ns" not in arrays:
            return
        stamps = np.asarray(arrays["grid_stamp_ns"], np.int64)
        laid, target = np.asarray(arrays["grid_laid_pose"], float), np.asarray(arrays["grid_target_pose"], float)
        ranges, angles = np.asarray(arrays["grid_ranges"], np.float32), np.asarray(arrays["grid_angles"], float)
        if not (laid.shape == target.shape == (stamps.size, 3) and ranges.shape[0] == stamps.size
                and angles.shape == (stamps.size, 2)):
            raise InputError("grid checkpoint: arrays of different lengths")
        state = {name: arrays[f"grid_{name}"] for name in ("resolution_m", "resolution_changes", "bounds", "changed")}
        self.grid.set_state(state)
        for i, key in enumerate(stamps.tolist()):
            self.grid.lay(key, laid[i], ranges[i], angles[i, 0], angles[i, 1])
            self._target[key] = target[i].copy()
        self.grid.set_state(state)
        self._queue()
