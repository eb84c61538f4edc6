"""A saved map on disk (``lrfslam map save``): its versioned format, writing it, and the one loader.

A saved map is one folder (docs/maps.md describes every file and array):

* ``manifest.json``: ``format`` (:data:`FORMAT`), frames, the laser's layout, the software
  that wrote it, the recording it came from, counts, the grid's size, resolution and origin;
* ``keyframes.npz``: the mapper's pose graph, its K keyframes (stamps, optimised map poses,
  local poses), the E odometry edges between consecutive ones, and each keyframe's scan points;
* ``landmarks.npz``: the EKF's L landmarks with their covariances, in the map frame;
* ``map.pgm`` + ``map.yaml``: the occupancy grid as ROS map_server reads it (written by
  ``lrfslam.tools.recording_map.write_grid``, the files ``lrfslam export`` writes).

The version rule: a reader reads every format up to its own :data:`FORMAT` (an older one
upgraded in memory, where one exists) and refuses a newer one with :class:`MapFormatError`
saying so — a newer writer may have changed what an array means. Format 1 is the first.

:func:`load_map` is the one reader (``lrfslam map info`` and, later, localization on a saved map
use it); :func:`write_map` writes everything but the grid files, which the tool that built the
grid writes beside them.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lrfslam.errors import MapFormatError
from lrfslam.runtime import npz_file

#: The format this build writes, and the newest it reads.
FORMAT = 1
MANIFEST, KEYFRAMES, LANDMARKS, PGM, YAML = "manifest.json", "keyframes.npz", "landmarks.npz", "map.pgm", "map.yaml"
#: Every file of a saved map.
FILES = (MANIFEST, KEYFRAMES, LANDMARKS, PGM, YAML)
#: map_saver's trinary pixel values, and the cells they stand for (``nav_msgs/OccupancyGrid``'s 100 / 0 / -1).
_PIXEL_CELL = {0: 100, 254: 0, 205: -1}

# (file, array name) -> (dtype, shape with "K", "E", "P", "L" for the counts, K1 = K + 1)
_ARRAYS: dict[tuple[str, str], tuple[type, tuple]] = {
    (KEYFRAMES, "stamp_ns"): (np.int64, ("K",)),
    (KEYFRAMES, "map_pose"): (np.float64, ("K", 3)),
    (KEYFRAMES, "local_pose"): (np.float64, ("K", 3)),
    (KEYFRAMES, "local_edge"): (np.bool_, ("K",)),
    (KEYFRAMES, "edge_from"): (np.int64, ("E",)),
    (KEYFRAMES, "edge_to"): (np.int64, ("E",)),
    (KEYFRAMES, "edge_motion"): (np.float64, ("E", 3)),
    (KEYFRAMES, "points_xy_m"): (np.float64, ("P", 2)),
    (KEYFRAMES, "point_start"): (np.int64, ("K1",)),
    (LANDMARKS, "ids"): (np.int64, ("L",)),
    (LANDMARKS, "xy_m"): (np.float64, ("L", 2)),
    (LANDMARKS, "cov_m2"): (np.float64, ("L", 2, 2)),
    (LANDMARKS, "kind"): (np.int8, ("L",)),
    (LANDMARKS, "sightings"): (np.int64, ("L",)),
    (LANDMARKS, "confirmed"): (np.bool_, ("L",)),
}
#: The manifest's ``counts`` key of each letter of :data:`_ARRAYS`' shapes.
_COUNTS = {"K": "keyframes", "E": "odometry_edges", "P": "scan_points", "L": "landmarks"}


@dataclass(frozen=True, eq=False)
class SavedMap:
    """A saved map in memory: all in the map frame, metres and radians, poses ``(x_m, y_m, theta_rad)``.

    Attributes
    ----------
    manifest : dict
        ``manifest.json`` as read (``format``, ``frames``, ``laser``, ``software``, ``source``,
        ``created_from``, ``counts``, ``grid``; docs/maps.md).
    stamp_ns : ndarray of int64, shape (K,)
        Each keyframe's scan stamp (data time), ascending.
    map_pose : ndarray, shape (K, 3)
        Each keyframe's optimised pose in the map frame.
    local_pose : ndarray, shape (K, 3)
        Each keyframe's pose on the mapper's local trajectory (the chain of the EKF's motions).
    local_edge : ndarray of bool, shape (K,)
        Whether the edge into keyframe k is the local motion (False: a jump, or the first).
    edge_from, edge_to : ndarray of int64, shape (E,)
        The odometry edges: keyframe indices, ``edge_to = edge_from + 1`` where ``local_edge``.
    edge_motion : ndarray, shape (E, 3)
        Each edge's motion, ``local_pose[edge_from] ⊖ local_pose[edge_to]`` (in the first's frame).
    points_xy_m : ndarray, shape (P, 2)
        Every keyframe's scan points, each in its keyframe's robot frame, one block per keyframe.
    point_start : ndarray of int64, shape (K + 1,)
        Keyframe k's points are ``points_xy_m[point_start[k]:point_start[k + 1]]``.
    landmark_ids : ndarray of int64, shape (L,)
    landmark_xy_m : ndarray, shape (L, 2)
    landmark_cov_m2 : ndarray, shape (L, 2, 2)
    landmark_kind : ndarray of int8, shape (L,)
        ``lrfslam.msgs.types.FEATURE_*`` codes: 1 forward (a corner), 2 backward (a jump edge).
    landmark_sightings : ndarray of int64, shape (L,)
    landmark_confirmed : ndarray of bool, shape (L,)
    grid_cells : ndarray of int8, shape (H, W)
        The occupancy grid as map_server reads ``map.pgm``: 100 occupied, 0 free, -1 unknown;
        row 0 the lowest y, cell ``[r, c]`` covers ``origin + (c, r) · resolution`` to ``+ resolution``.
    grid_resolution_m : float
    grid_origin_xy_m : ndarray, shape (2,)
        The map-frame corner of cell ``[0, 0]`` (lowest x and y).
    """

    manifest: dict
    stamp_ns: np.ndarray
    map_pose: np.ndarray
    local_pose: np.ndarray
    local_edge: np.ndarray
    edge_from: np.ndarray
    edge_to: np.ndarray
    edge_motion: np.ndarray
    points_xy_m: np.ndarray
    point_start: np.ndarray
    landmark_ids: np.ndarray
    landmark_xy_m: np.ndarray
    landmark_cov_m2: np.ndarray
    landmark_kind: np.ndarray
    landmark_sightings: np.ndarray
    landmark_confirmed: np.ndarray
    grid_cells: np.ndarray
    grid_resolution_m: float
    grid_origin_xy_m: np.ndarray

    def keyframe_points(self, k: int) -> np.ndarray:
        """Keyframe ``k``'s scan points in its robot frame, (N, 2) metres."""
        return self.points_xy_m[self.point_start[k]:self.point_start[k + 1]]

    def keyframe_scan(self, k: int) -> tuple[np.ndarray, float, float]:
        """Keyframe ``k``'s scan as the manifest's laser took it: ranges (B,) float32 (m; NaN where the
        scan had no valid return, whose beams the map does not keep), first angle and step (rad)."""
        laser = self.manifest["laser"]
        a0, da, beams = float(laser["angle_min_rad"]), float(laser["angle_increment_rad"]), int(laser["beams"])
        pts = self.keyframe_points(k)
        ranges = np.full(beams, np.nan, dtype=np.float32)
        beam = np.rint((np.arctan2(pts[:, 1], pts[:, 0]) - a0) / da).astype(np.int64)
        ok = (beam >= 0) & (beam < beams)
        ranges[beam[ok]] = np.hypot(pts[ok, 0], pts[ok, 1])
        return ranges, a0, da

    def counts(self) -> dict[str, int]:
        """The manifest's ``counts`` of these arrays: keyframes, odometry edges, scan points, landmarks."""
        return {"keyframes": int(self.stamp_ns.size), "odometry_edges": int(self.edge_from.size),
                "scan_points": int(self.points_xy_m.shape[0]), "landmarks": int(self.landmark_ids.size)}


#: SavedMap's field of each array of :data:`_ARRAYS`.
_FIELD = {(f, name): (name if f == KEYFRAMES else f"landmark_{name}") for f, name in _ARRAYS}


def write_map(folder: Path, saved: SavedMap) -> None:
    """Write ``saved``'s manifest (its ``format`` set to :data:`FORMAT`, its ``counts`` to the
    arrays') and arrays into ``folder``; not the grid files (``map.pgm``, ``map.yaml``)."""
    manifest = {"format": FORMAT, **{k: v for k, v in saved.manifest.items() if k not in ("format", "counts")},
                "counts": saved.counts()}
    for file in (KEYFRAMES, LANDMARKS):
        npz_file.write_atomic(folder / file, {name: np.asarray(getattr(saved, _FIELD[f, name]), dtype=dtype)
                                              for (f, name), (dtype, _) in _ARRAYS.items() if f == file})
    (folder / MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")


def load_map(path: str | Path) -> SavedMap:
    """The saved map in folder ``path``, checked: every file there, every array of its dtype and shape.

    Raises
    ------
    MapFormatError
        A file is missing or damaged, an array is missing or of another shape than the
        manifest's counts say, or the map's format is newer than :data:`FORMAT` (or no format).
    """
    folder = Path(path)
    manifest = _manifest(folder)
    counts = manifest.get("counts")
    if not isinstance(counts, dict) or not all(isinstance(counts.get(v), int) for v in _COUNTS.values()):
        raise MapFormatError(f"{folder / MANIFEST}: no counts of {', '.join(_COUNTS.values())}")
    sizes = {letter: counts[key] for letter, key in _COUNTS.items()} | {"K1": counts["keyframes"] + 1}
    arrays = {}
    for file in (KEYFRAMES, LANDMARKS):
        loaded = _npz(folder / file)
        for (f, name), (dtype, shape) in _ARRAYS.items():
            if f != file:
                continue
            want = tuple(sizes.get(d, d) for d in shape)
            a = loaded.get(name)
            if a is None or a.shape != want or a.dtype != dtype:
                got = "missing" if a is None else f"{a.dtype} {a.shape}"
                raise MapFormatError(f"{folder / file}: {name} should be {np.dtype(dtype)} {want}, is {got}")
            arrays[_FIELD[f, name]] = a
    grid = manifest.get("grid")
    try:
        resolution, origin = float(grid["resolution_m"]), np.array(grid["origin_xy_m"], dtype=float).reshape(2)
        width, height = (int(v) for v in grid["cells"])
    except (TypeError, KeyError, ValueError) as exc:
        raise MapFormatError(f"{folder / MANIFEST}: no grid resolution_m, origin_xy_m, cells ({exc})") from None
    if not (folder / YAML).is_file():
        raise MapFormatError(f"{folder}: no {YAML}: not a complete saved map")
    cells = _pgm_cells(folder / PGM)
    if cells.shape != (height, width):
        raise MapFormatError(f"{folder / PGM}: {cells.shape[1]} x {cells.shape[0]} cells, the manifest says "
                             f"{width} x {height}")
    if arrays["point_start"].size and (arrays["point_start"][0] != 0 or arrays["point_start"][-1] != counts[
            "scan_points"] or np.any(np.diff(arrays["point_start"]) < 0)):
        raise MapFormatError(f"{folder / KEYFRAMES}: point_start does not divide the {counts['scan_points']} points")
    return SavedMap(manifest=manifest, grid_cells=cells, grid_resolution_m=resolution, grid_origin_xy_m=origin,
                    **arrays)


def _manifest(folder: Path) -> dict:
    """``manifest.json`` of ``folder``, its format checked (:func:`load_map`)."""
    if not folder.is_dir():
        raise MapFormatError(f"{folder} is not a folder (a saved map is one: lrfslam map save)")
    try:
        manifest = json.loads((folder / MANIFEST).read_text())
    except FileNotFoundError:
        raise MapFormatError(f"{folder} has no {MANIFEST}: not a saved map") from None
    except (OSError, ValueError) as exc:
        raise MapFormatError(f"{folder / MANIFEST} is damaged ({exc})") from None
    version = manifest.get("format") if isinstance(manifest, dict) else None
    if not isinstance(version, int) or isinstance(version, bool) or version < 1:
        raise MapFormatError(f"{folder / MANIFEST}: no format version (an integer >= 1)")
    if version > FORMAT:
        raise MapFormatError(f"{folder} is a map of format {version}, newer than this lrfslam reads (up to "
                             f"{FORMAT}): read it with the newer lrfslam that wrote it")
    return manifest


def _npz(path: Path) -> dict[str, np.ndarray]:
    """The arrays of ``path``, a damaged or missing file as :class:`MapFormatError`."""
    try:
        return npz_file.read(path)
    except FileNotFoundError:
        raise MapFormatError(f"{path.parent} has no {path.name}: not a complete saved map") from None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise MapFormatError(f"{path} is damaged ({exc})") from None


def _pgm_cells(path: Path) -> np.ndarray:
    """A trinary P5 image (map_saver's: 0 / 254 / 205, first row the top) as cells 100 / 0 / -1, row 0 the bottom."""
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise MapFormatError(f"{path.parent} has no {path.name}: not a complete saved map") from None
    fields, pos = [], 0
    while len(fields) < 4 and pos < len(data):   # magic, width, height, maxval; '#' comments to the line's end
        if data[pos:pos + 1].isspace():
            pos += 1
        elif data[pos:pos + 1] == b"#":
            newline = data.find(b"\n", pos)
            pos = len(data) if newline < 0 else newline + 1
        else:
            end = pos
            while end < len(data) and not data[end:end + 1].isspace():
                end += 1
            fields.append(data[pos:end])
            pos = end
    try:
        width, height, maxval = int(fields[1]), int(fields[2]), int(fields[3])
        ok = fields[0] == b"P5" and maxval == 255
    except (IndexError, ValueError):
        ok = False
    if not ok or len(data) - (pos + 1) != width * height:
        raise MapFormatError(f"{path} is damaged (not a complete 8-bit P5 image)")
    pixels = np.frombuffer(data, dtype=np.uint8, offset=pos + 1).reshape(height, width)
    lut = np.full(256, -2, dtype=np.int8)
    for pixel, cell in _PIXEL_CELL.items():
        lut[pixel] = cell
    cells = lut[pixels]
    if np.any(cells == -2):
        raise MapFormatError(f"{path} is no trinary map (pixels other than 0, 254, 205)")
    return np.flipud(cells)
