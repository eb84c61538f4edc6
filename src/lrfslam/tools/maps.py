"""``lrfslam map save RECORDING -o MAP/`` and ``lrfslam map info MAP/``: a map a user keeps.

``save`` turns a recording with the mapper's output (``map/keyframes``) into one folder in the
versioned format of :mod:`lrfslam.runtime.saved_map` (docs/maps.md): the occupancy grid exactly
as ``lrfslam export`` builds it (:func:`lrfslam.tools.recording_map.map_of`: the raw scans on the
mapper's final trajectory), the pose graph's keyframes with their scans, the EKF's landmarks
on the same map, and a manifest. RECORDING is an MCAP file, a recording folder or several files
(one stream). A folder MAP/ that exists and is not empty is never overwritten (``--force``
replaces it); the map is written into a hidden sibling folder and renamed at the end, so a save
that fails or is stopped leaves nothing behind. ``info`` describes a saved map.

Exit codes: 0 done; 1 the map was not saved or cannot be read (MAP/ taken, no mapper output,
a missing or damaged file, a format newer than this build reads), in one line; 2 usage, or a
recording that cannot be read (as every command).
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import sys
from importlib import metadata
from pathlib import Path

import numpy as np

from lrfslam.algo.geometry import polar_to_xy, relative
from lrfslam.algo.occupancy_grid import (
    FREE_THRESH,
    OCCUPIED_THRESH,
    GridParams,
    OccupancyGrid,
)
from lrfslam.errors import InputError, MapError, RecordingError
from lrfslam.msgs import topics
from lrfslam.runtime.recording import (
    RecordingSource,
    describe_source,
    read_recording,
    recording_files,
)
from lrfslam.runtime.saved_map import FORMAT, PGM, YAML, SavedMap, load_map, write_map
from lrfslam.tools import recording_map

#: The frame the grid, the keyframes' map poses and the landmarks are in, and the robot's
#: (the laser's pose on the robot is the identity: the scans' points are the robot's).
MAP_FRAME, ROBOT_FRAME = "map", "base_link"
#: A run's landmark within this of one of the saved map's it mapped on from is that one (m).
SAME_LANDMARK_M = 0.5


def check_target(out: Path, force: bool = False) -> None:
    """Refuse ``out`` as a saved map's folder unless it is absent or empty (``force``: or any folder).

    Raises
    ------
    MapError
        ``out`` is a file, or a folder that is not empty (without ``force``).
    """
    if out.exists() and not out.is_dir():
        raise MapError(f"{out} exists and is not a folder: a saved map is a folder")
    if out.is_dir() and any(out.iterdir()) and not force:
        raise MapError(f"{out} exists and is not empty: a saved map never overwrites one (--force replaces it)")


def build(recording: RecordingSource, resolution_m: float | None = None,
          max_range_m: float = GridParams.max_range_m, base: SavedMap | None = None
          ) -> tuple[SavedMap, OccupancyGrid, list[str]]:
    """The saved map of ``recording`` (its grid not yet as read back: :func:`recording_map.trinary` of it),
    the grid to write, and what the user should be told (:func:`recording_map.notes`, :func:`recording_map.resolution_note`).

    The keyframes are the mapper's graph at the end (its last ``map/keyframes``): revisits it folded
    into the places they revisited are not kept, so a map grows with the building, not the hours.
    ``base``: the saved map the run mapped on from (``lrfslam up --map MAP``); its keyframes, still
    in the graph, bring their scans from it, and its landmarks are kept, with the run's new ones
    (those more than :data:`SAME_LANDMARK_M` from every one of the base's).

    Raises
    ------
    MapError
        The recording has no ``map/keyframes`` (no mapper output), no scan at a pose, or a
        retired keyframe that cannot be placed.
    RecordingError
        The recording cannot be read, or has no ``slam/state``.
    """
    base_scans = {} if base is None else {int(s): base.keyframe_scan(k) for k, s in enumerate(base.stamp_ns.tolist())}
    try:
        data, sc = recording_map.map_of(recording, resolution_m, max_range_m, scans=base_scans)
    except InputError as exc:
        raise MapError(f"{describe_source(recording)}: {exc}") from None
    kf = data["graph"]
    if kf is None:
        raise MapError(f"{describe_source(recording)} has no {topics.MAP_KEYFRAMES.name} (no mapper output): "
                       "nothing to save; run the mapper over it (lrfslam pipeline --replay IN --out OUT)")
    if sc.grid is None:
        raise MapError(f"{describe_source(recording)} has no {topics.SCAN.name} messages at the mapper's poses: "
                       "no occupancy grid")
    first_scan = next(read_recording(recording, [topics.SCAN.name]))
    scan = topics.SCAN.codec.decode(first_scan.data, first_scan.schema)
    # The mapper's keyframe points: every valid beam of the raw scan (services/mapper.py).
    blocks, without_scan = [], 0
    for s in kf.scan_stamp_ns:
        ranges, a0, da = data["scans"].get(int(s), (np.zeros(0), 0.0, 0.0))
        without_scan += ranges.size == 0
        ok = np.isfinite(ranges)
        blocks.append(polar_to_xy(ranges[ok].astype(float), (a0 + da * np.arange(ranges.size))[ok]).reshape(-1, 2))
    edge_to = np.flatnonzero(kf.local_edge[1:]) + 1
    motion = np.asarray(relative(kf.local_pose[edge_to - 1].T, kf.local_pose[edge_to].T)).T.reshape(-1, 3)
    lms = data["landmarks"]
    landmarks = (lms.ids, sc.landmark_xy, sc.landmark_cov, lms.kind, lms.sightings, lms.confirmed)
    if base is not None:
        landmarks = _with_base_landmarks(base, *landmarks)
    stamps = [data["states"][0][0], data["states"][-1][0], *(s for s in data["scans"] if s not in base_scans)]
    h, w = sc.grid.shape
    manifest = {
        "software": {"name": "lrfslam", "version": metadata.version("lrfslam")},
        "frames": {"map": MAP_FRAME, "robot": ROBOT_FRAME, "laser": scan.frame_id or "laser",
                   "laser_in_robot": [0.0, 0.0, 0.0]},
        "laser": {"beams": int(scan.ranges_m.size), "angle_min_rad": scan.angle_min_rad,
                  "angle_increment_rad": scan.angle_increment_rad, "range_max_m": scan.range_max_m},
        "source": {"recording": describe_source(recording), "files": [p.name for p in recording_files(recording)],
                   "first_stamp_ns": int(min(stamps)), "last_stamp_ns": int(max(stamps))},
        "created_from": {"keyframes_stamp_ns": int(kf.stamp_ns), "last_state_stamp_ns": int(data["last"].stamp_ns)},
        "scan_points": f"the valid beams of each keyframe's {topics.SCAN.name} message, as the mapper takes them "
                       "(before its range cut and thinning)",
        "keyframes_without_scan": int(without_scan),
        **({} if base is None else {"based_on": [base.manifest["source"], *base.manifest.get("based_on", [])]}),
        "grid": {"resolution_m": sc.grid.resolution_m, "origin_xy_m": [float(v) for v in sc.grid.origin_xy_m],
                 "cells": [w, h], "occupied_thresh": OCCUPIED_THRESH, "free_thresh": FREE_THRESH,
                 "max_range_m": max_range_m, "image": PGM, "yaml": YAML},
    }
    saved = SavedMap(
        manifest=manifest, stamp_ns=kf.scan_stamp_ns, map_pose=kf.map_pose, local_pose=kf.local_pose,
        local_edge=kf.local_edge, edge_from=edge_to - 1, edge_to=edge_to, edge_motion=motion,
        points_xy_m=np.vstack(blocks) if blocks else np.zeros((0, 2)),
        point_start=np.concatenate(([0], np.cumsum([b.shape[0] for b in blocks]))).astype(np.int64),
        **dict(zip(("landmark_ids", "landmark_xy_m", "landmark_cov_m2", "landmark_kind", "landmark_sightings",
                    "landmark_confirmed"), landmarks, strict=True)),
        grid_cells=recording_map.trinary(sc.grid).astype(np.int8), grid_resolution_m=sc.grid.resolution_m,
        grid_origin_xy_m=np.asarray(sc.grid.origin_xy_m, dtype=float))
    note = recording_map.resolution_note(sc, resolution_m)
    return saved, sc.grid, [*recording_map.notes(data, sc), *([note] if note else [])]


def _with_base_landmarks(base: SavedMap, ids, xy, cov, kind, sightings, confirmed) -> tuple[np.ndarray, ...]:
    """The base map's landmarks, then the run's (L, …, as the :class:`SavedMap` fields) farther than
    :data:`SAME_LANDMARK_M` from every one of them, their ids after the base's."""
    if not base.landmark_ids.size:
        return ids, xy, cov, kind, sightings, confirmed
    dist = np.linalg.norm(xy[:, None, :] - base.landmark_xy_m[None, :, :], axis=2)
    new = dist.min(axis=1) > SAME_LANDMARK_M if xy.shape[0] else np.zeros(0, bool)
    return (np.concatenate((base.landmark_ids, ids[new] + int(base.landmark_ids.max()) + 1)),
            np.vstack((base.landmark_xy_m, xy[new])),
            np.concatenate((base.landmark_cov_m2, cov[new].reshape(-1, 2, 2))),
            np.concatenate((base.landmark_kind, kind[new])),
            np.concatenate((base.landmark_sightings, sightings[new])),
            np.concatenate((base.landmark_confirmed, confirmed[new])))


def save_map(recording: RecordingSource, out: Path, force: bool = False, resolution_m: float | None = None,
             max_range_m: float = GridParams.max_range_m, base: SavedMap | None = None) -> tuple[SavedMap, list[str]]:
    """Save ``recording``'s map into the folder ``out``, all or nothing; the map as written, and notes
    (``base``: :func:`build`'s).

    Raises
    ------
    MapError
        ``out`` is taken (:func:`check_target`), or :func:`build` refuses the recording.
    RecordingError
        The recording cannot be read.
    """
    out = Path(out).resolve()   # a name to put the sibling folders beside, even for "."
    check_target(out, force)
    saved, grid, notes = build(recording, resolution_m, max_range_m, base)
    out.parent.mkdir(parents=True, exist_ok=True)
    partial = out.with_name(f".{out.name}.{os.getpid()}.partial")
    old = out.with_name(f".{out.name}.{os.getpid()}.old")
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir()
    try:
        recording_map.write_grid(grid, partial / PGM, partial / YAML,
                          comment=f"lrfslam map save of {saved.manifest['source']['recording']}")
        write_map(partial, saved)
        check_target(out, force)   # taken meanwhile?
        if out.exists():
            os.rename(out, old)
        os.rename(partial, out)
    finally:
        shutil.rmtree(partial, ignore_errors=True)
        shutil.rmtree(old, ignore_errors=True)
    return saved, notes


def summary_line(saved: SavedMap) -> str:
    """One line: keyframes, landmarks, the grid's size."""
    h, w = saved.grid_cells.shape
    res = saved.grid_resolution_m
    return (f"{saved.stamp_ns.size} keyframes, {saved.landmark_ids.size} landmarks, grid {w} x {h} cells "
            f"({w * res:.1f} x {h * res:.1f} m at {res:g} m)")


def describe(path: Path, saved: SavedMap) -> str:
    """Everything ``lrfslam map info`` prints about the saved map ``saved`` read from ``path``."""
    m = saved.manifest
    src, laser, frames = m["source"], m["laser"], m["frames"]
    h, w = saved.grid_cells.shape
    res = saved.grid_resolution_m
    x0, y0 = saved.grid_origin_xy_m
    span_s = (src["last_stamp_ns"] - src["first_stamp_ns"]) / 1e9
    last_beam = laser["angle_min_rad"] + (laser["beams"] - 1) * laser["angle_increment_rad"]
    n_edges = saved.edge_from.size
    jumps = saved.stamp_ns.size - 1 - n_edges if saved.stamp_ns.size else 0
    travel = float(np.hypot(*saved.edge_motion[:, :2].T).sum()) if n_edges else 0.0
    lines = [
        f"map:       {path} (format {m['format']}, written by {m['software']['name']} {m['software']['version']})",
        (f"source:    {src['recording']} ({len(src['files'])} file{'s' * (len(src['files']) > 1)}), data stamps "
        f"{src['first_stamp_ns'] / 1e9:.3f} to {src['last_stamp_ns'] / 1e9:.3f} s ({span_s:.1f} s)"),
        (f"frames:    map {frames['map']!r}, robot {frames['robot']!r}, laser {frames['laser']!r} "
        f"(on the robot at {frames['laser_in_robot']})"),
        (f"laser:     {laser['beams']} beams, {math.degrees(laser['angle_increment_rad']):.2f} deg apart, "
        f"{math.degrees(laser['angle_min_rad']):+.1f} to {math.degrees(last_beam):+.1f} deg, "
        f"range max {laser['range_max_m']:.2f} m"),
        f"keyframes: {saved.stamp_ns.size} ({n_edges} odometry edges, {travel:.1f} m along them, {jumps} jumps), "
        f"{saved.points_xy_m.shape[0]} scan points"
        + (f", {m['keyframes_without_scan']} keyframes without their scan" if m.get("keyframes_without_scan") else ""),
        f"landmarks: {saved.landmark_ids.size} ({int(saved.landmark_confirmed.sum())} confirmed)",
        *(f"based on:  {b.get('recording', '?')}" for b in m.get("based_on", [])),
        (f"grid:      {w} x {h} cells at {res:g} m = {w * res:.2f} x {h * res:.2f} m; "
        f"extent x {x0:.2f} to {x0 + w * res:.2f} m, y {y0:.2f} to {y0 + h * res:.2f} m; "
        f"{int(np.count_nonzero(saved.grid_cells == 100))} occupied, {int(np.count_nonzero(saved.grid_cells == 0))} "
        "free cells"),
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lrfslam map", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="action", required=True, metavar="{save,info}")
    save = sub.add_parser("save", help="save a recording's map into one folder (docs/maps.md)",
                          description="Save the map of a recording with mapper output into one folder, "
                                      f"format {FORMAT} (docs/maps.md).")
    save.add_argument("recording", type=Path, nargs="+",
                      help="recording with map/keyframes (a file, a folder or several files)")
    save.add_argument("-o", "--out", type=Path, required=True, metavar="MAP",
                      help="the map's folder: must not exist, or be empty")
    save.add_argument("--force", action="store_true", help="replace MAP even if it is not empty")
    save.add_argument("--resolution", type=float, default=None, metavar="M",
                      help="grid cell size in metres, as lrfslam export's (default: its default)")
    save.add_argument("--max-range", type=float, default=GridParams.max_range_m, metavar="M",
                      help=f"as lrfslam export's --max-range (default {GridParams.max_range_m})")
    save.add_argument("--base", type=Path, metavar="MAP",
                      help="the saved map the run mapped on from (lrfslam up --map MAP): its keyframes' scans")
    info = sub.add_parser("info", help="describe a saved map", description="Describe a saved map.")
    info.add_argument("map", type=Path, metavar="MAP", help="a saved map's folder")
    args = parser.parse_args(argv)
    prog = f"lrfslam map {args.action}"
    try:
        if args.action == "info":
            print(describe(args.map, load_map(args.map)))
            return 0
        recording = args.recording[0] if len(args.recording) == 1 else args.recording
        base = load_map(args.base) if args.base else None
        saved, notes = save_map(recording, args.out, args.force, args.resolution, args.max_range, base)
    except MapError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 1
    except RecordingError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    for note in notes:
        print(f"{prog}: {note}", file=sys.stderr)
    print(f"wrote {args.out}/: {summary_line(saved)}")
    return 0
