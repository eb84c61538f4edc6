"""The map of a recording: its poses, landmarks and scans on its best trajectory, the grid and its figures.

What ``lrfslam export`` draws and writes and ``lrfslam map save`` keeps.

Everything is placed in the map frame of the *best* trajectory: the mapper's final trajectory
(``lrfslam.evaluation.map_trajectory``) when the recording has ``map/keyframes``, else the EKF's
``slam/state`` poses. The grid (``lrfslam.algo.occupancy_grid``) is the raw scans of the mapper's
graph (its last ``map/keyframes``) at their optimised poses, the map the mapper kept live
(``map/grid``) and slam_toolbox's kind; without the mapper, every ``scan`` at the EKF's poses. Truth and odometry are brought into that frame by their
first pose; landmarks (the EKF's, in its own frame) move with the correction the mapper made
to the pose of the scan that saw them last. The figures (:attr:`Scene.figures`) score the
trajectory against the truth with the one error measure (``lrfslam.evaluation.truth``).
The grid is written in ROS map_server's format (:func:`write_grid`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lrfslam.algo.geometry import compose, inverse, relative, rotate_covariance
from lrfslam.algo.occupancy_grid import (
    FREE,
    FREE_THRESH,
    OCCUPIED,
    OCCUPIED_THRESH,
    GridParams,
    OccupancyGrid,
    build_grid,
)
from lrfslam.errors import DecodeError, RecordingError
from lrfslam.evaluation import truth as trajectory_error
from lrfslam.evaluation.map_trajectory import FinalTrajectoryBuilder
from lrfslam.msgs import topics
from lrfslam.msgs.landmark_map import LandmarkMapReplica
from lrfslam.runtime.outputs import atomic_output
from lrfslam.runtime.recording import RecordingSource, describe_source, read_recording

#: map_saver's trinary pixel values.
PGM_OCCUPIED, PGM_FREE, PGM_UNKNOWN = 0, 254, 205
def collect(path: RecordingSource, scans: bool = True) -> dict:
    """Trajectory, odometry, truth, scans, the last SLAM state, the mapper's final trajectory
    (``"final"``) and its graph at the end (``"graph"``, the last ``map/keyframes``; both None
    without ``map/keyframes``) of a recording (file, folder or files), in one pass.

    ``"landmarks"`` is the landmark map rebuilt from ``slam/map`` and the states' changes (at
    the last state). Undecodable messages are skipped and counted (``"undecodable"``). ``"seen_ns"`` maps each
    landmark id to the stamp of the last state whose sightings of it grew. ``scans`` False:
    the ``scan`` messages are not read (``"scans"`` is empty).

    Raises
    ------
    RecordingError
        ``path`` is no recording, or has no decodable ``slam/state``.
    """
    states, odom, truth, scan_of = [], {}, {}, {}
    last = graph = None
    undecodable = 0
    landmarks = LandmarkMapReplica()
    seen_ns: dict[int, int] = {}
    final = FinalTrajectoryBuilder()
    wanted = [*FinalTrajectoryBuilder.TOPICS, topics.SLAM_MAP.name, topics.ODOM.name, topics.TRUTH.name] \
        + ([topics.SCAN.name] if scans else [])
    for m in read_recording(path, wanted):
        try:
            value = topics.by_name(m.topic).codec.decode(m.data, m.schema)
        except DecodeError:
            undecodable += 1
            continue
        final.add(m.topic, value)
        if m.topic == topics.MAP_KEYFRAMES.name:
            graph = value
        if m.topic in (topics.MAP_POSE.name, topics.MAP_KEYFRAMES.name):
            continue
        if m.topic == topics.SLAM_MAP.name:
            landmarks.apply_map(value)
        elif m.topic == topics.SLAM_STATE.name:
            last = value
            states.append((last.stamp_ns, last.pose))
            held = landmarks.landmarks
            changed = landmarks.apply_state(last)
            for i in changed.ids[_grown(changed.ids, changed.sightings, held.ids, held.sightings)]:
                seen_ns[int(i)] = last.stamp_ns
        elif m.topic == topics.ODOM.name:
            odom[value.stamp_ns] = value.pose
        elif m.topic == topics.TRUTH.name:
            truth[value.stamp_ns] = value
        else:
            scan_of[value.stamp_ns] = (value.grid_ranges(), value.angle_min_rad, value.angle_increment_rad)
    if last is None:
        raise RecordingError(f"{describe_source(path)} has no decodable {topics.SLAM_STATE.name} messages")
    return {"states": states, "odom": odom, "truth": truth, "last": last, "landmarks": landmarks.landmarks,
            "undecodable": undecodable,
            "scans": scan_of, "scans_read": scans, "seen_ns": seen_ns, "final": final.result(), "graph": graph}


def _grown(ids: np.ndarray, sightings: np.ndarray, old_ids: np.ndarray, old_sightings: np.ndarray) -> np.ndarray:
    """Mask over ``ids``: new landmarks and those seen again since the previous state."""
    if old_ids.size == 0:
        return np.ones(ids.size, bool)
    order = np.argsort(old_ids)
    pos = np.clip(np.searchsorted(old_ids[order], ids), 0, old_ids.size - 1)
    known = old_ids[order][pos] == ids
    return ~known | (old_sightings[order][pos] != sightings)


@dataclass
class Scene:
    """Everything map.png and the grid files show, in the map frame of the best trajectory (metres).

    ``stamps_ns`` (T,) and ``estimate`` (T, 3) the best trajectory; ``truth`` and ``odometry``
    (K, 3) brought into its frame (None without); ``landmark_xy`` (L, 2), ``landmark_cov`` (L, 2, 2)
    and ``landmark_confirmed`` (L,) on the same map; ``view`` (x_min, x_max, y_min, y_max) the
    picture's extent: the observed grid, the estimate, the truth and the landmarks — not the
    odometry, which drifts off the map.
    """

    name: str
    trajectory_label: str
    stamps_ns: np.ndarray
    estimate: np.ndarray
    landmark_xy: np.ndarray
    landmark_cov: np.ndarray
    landmark_confirmed: np.ndarray
    truth: np.ndarray | None = None
    true_corners: np.ndarray | None = None
    odometry: np.ndarray | None = None
    grid: OccupancyGrid | None = None
    scans_placed: int = 0
    scans_unplaced: int = 0
    figures: dict = field(default_factory=dict)
    view: tuple[float, float, float, float] = (0.0, 1.0, 0.0, 1.0)


def best_trajectory(data: dict) -> tuple[np.ndarray, np.ndarray, str]:
    """Stamps (T,), poses (T, 3) and a label: the mapper's final trajectory when recorded, else the EKF's."""
    final = data["final"]
    if final is not None:
        return final[0], final[1], "mapper's final trajectory"
    return (np.array([s for s, _ in data["states"]], dtype=np.int64),
            np.array([p for _, p in data["states"]]).reshape(-1, 3), "EKF trajectory (slam/state)")


def _anchor(stamps_ns: np.ndarray, poses: np.ndarray, others: dict) -> np.ndarray | None:
    """Transform from the frame of ``poses`` to that of ``others`` (stamp -> pose), by the first stamp both have."""
    index = {int(s): i for i, s in enumerate(stamps_ns)}
    first = next((s for s in sorted(others) if s in index), None)
    return None if first is None else trajectory_error.anchor(others[first], poses[index[first]])


def in_frame(stamps_ns: np.ndarray, poses: np.ndarray, others: dict) -> np.ndarray | None:
    """``others`` (stamp -> pose) in the frame of ``poses`` (:func:`_anchor`), in stamp order; (K, 3)."""
    anchor = _anchor(stamps_ns, poses, others)
    if anchor is None:
        return None
    return np.array([relative(anchor, others[s]) for s in sorted(others)])


def scene(path: RecordingSource, data: dict, grid_params: GridParams | None, fit: bool = False) -> Scene:
    """Place everything of ``data`` (from :func:`collect`) on the best trajectory's map; build the grid.

    ``grid_params`` None: no grid. ``fit``: a grid too large at ``grid_params.resolution_m`` is
    built at the finest coarser resolution that fits (``build_grid``'s ``fit``) instead of refused.
    """
    stamps, poses, label = best_trajectory(data)
    last, lms = data["last"], data["landmarks"]
    # Each landmark moves with the correction of the pose of the scan that saw it last.
    slam_at = dict(data["states"])
    corrections = []
    for i in lms.ids:
        s = data["seen_ns"].get(int(i), last.stamp_ns)
        k = max(int(np.searchsorted(stamps, s, side="right")) - 1, 0)
        slam = slam_at.get(int(stamps[k]), slam_at[last.stamp_ns])
        corrections.append(compose(poses[k], inverse(slam)))
    xy = np.array([compose(c, (*m, 0.0))[:2] for c, m in zip(corrections, lms.xy_m)]).reshape(-1, 2)
    cov = rotate_covariance(np.asarray(lms.cov_m2, dtype=float).reshape(-1, 2, 2),
                            np.array([c[2] for c in corrections]))
    truth_poses = {s: g.pose for s, g in data["truth"].items()}
    sc = Scene(name=describe_source(path), trajectory_label=label, stamps_ns=stamps, estimate=poses,
               landmark_xy=xy, landmark_cov=cov, landmark_confirmed=np.asarray(lms.confirmed, bool),
               truth=in_frame(stamps, poses, truth_poses), odometry=in_frame(stamps, poses, data["odom"]))
    if sc.truth is not None:
        corners = {}
        for g in data["truth"].values():
            corners.update({int(i): c for i, c in zip(g.corner_ids, g.corners_xy_m)})
        anchor = _anchor(stamps, poses, truth_poses)
        sc.true_corners = np.array([relative(anchor, (*c, 0.0))[:2] for c in corners.values()]).reshape(-1, 2)
    if grid_params is not None and data["scans"]:
        graph = data["graph"]
        on = (graph.scan_stamp_ns, graph.map_pose) if graph is not None else (stamps, poses)
        sc.grid, sc.scans_placed = _grid(*on, data["scans"], grid_params, fit)
        sc.scans_unplaced = on[0].size - sc.scans_placed
    sc.figures = _figures(sc, data)
    sc.view = view_limits(sc)
    return sc


def map_of(path: RecordingSource, resolution_m: float | None = None, max_range_m: float = GridParams.max_range_m,
           grid: bool = True, scans: dict | None = None) -> tuple[dict, Scene]:
    """:func:`collect` and :func:`scene` as ``lrfslam export`` (and ``lrfslam map save``) build the map.

    ``resolution_m`` None: :class:`GridParams`' default, or the finest of its doublings a map
    too large for it fits (:func:`resolution_note` says so); ``max_range_m``: returns up to it mark walls
    and it caps the free space a beam marks, metres; ``grid`` False: no scans read, no grid.
    ``scans``: more scans by stamp, as :func:`collect` keeps them (a saved map's keyframes', for a run
    that mapped on from it); the recording's own come first.
    """
    params = GridParams(resolution_m=GridParams.resolution_m if resolution_m is None else resolution_m,
                        max_range_m=max_range_m, free_range_m=max_range_m) if grid else None
    data = collect(path, scans=grid)
    if scans and grid:
        data["scans"] = {**scans, **data["scans"]}
    return data, scene(path, data, params, fit=resolution_m is None)


def notes(data: dict, sc: Scene) -> list[str]:
    """Warnings for a user of :func:`map_of`'s map: undecodable messages skipped, scans left out of the grid."""
    out = [f"skipped {data['undecodable']} undecodable messages"] if data["undecodable"] else []
    if sc.grid is not None and sc.scans_unplaced and data["graph"] is not None:
        out.append(f"{sc.scans_unplaced} of the graph's {data['graph'].scan_stamp_ns.size} keyframes have no scan "
                   "in the recording: not in the grid")
    elif sc.grid is not None and sc.scans_unplaced:
        out.append(f"{sc.scans_unplaced} of {len(sc.stamps_ns)} poses have no scan at their stamp and are not in "
                   "the grid")
    return out


def resolution_note(sc: Scene, resolution_m: float | None) -> str | None:
    """What :func:`map_of` did to fit a large map in :class:`GridParams`' cells, None if nothing."""
    asked = GridParams.resolution_m if resolution_m is None else resolution_m
    if sc.grid is None or sc.grid.resolution_m == asked:
        return None
    h, w = sc.grid.log_odds.shape
    return (f"the map spans {w * sc.grid.resolution_m:.0f} x {h * sc.grid.resolution_m:.0f} m, more than "
            f"{GridParams.max_cells:,} cells at {asked:g} m: grid at {sc.grid.resolution_m:g} m (--resolution sets it)")


def _grid(stamps: np.ndarray, poses: np.ndarray, scans: dict, params: GridParams,
          fit: bool) -> tuple[OccupancyGrid | None, int]:
    """The grid of the scans that have a pose at their stamp, and how many those are (``fit``: see :func:`scene`)."""
    placed = [(i, scans[int(s)]) for i, s in enumerate(stamps) if int(s) in scans]
    if not placed:
        return None, 0
    width = max(r.size for _, (r, _, _) in placed)
    ranges = np.full((len(placed), width), np.nan, dtype=np.float32)
    layouts = {(r.size, a0, da) for _, (r, a0, da) in placed}
    for row, (_, (r, _, _)) in enumerate(placed):
        ranges[row, :r.size] = r
    if len(layouts) == 1:
        _, a0, da = placed[0][1]
        angles = a0 + da * np.arange(width)
    else:
        angles = np.array([a0 + da * np.arange(width) for _, (_, a0, da) in placed])
    return build_grid(poses[[i for i, _ in placed]], ranges, angles, params, fit), len(placed)


def _figures(sc: Scene, data: dict) -> dict:
    truth_stamps = sorted(data["truth"])
    fig = {"scans": len(data["scans"]) if data["scans_read"] else None, "scans_placed": sc.scans_placed, "poses": len(sc.stamps_ns),
           "landmarks": int(sc.landmark_xy.shape[0]), "confirmed_landmarks": int(sc.landmark_confirmed.sum()),
           "trajectory": sc.trajectory_label}
    if sc.truth is not None:
        fig["rmse_vs_truth_m"] = trajectory_error.matched_ate_rmse(sc.stamps_ns, sc.estimate, truth_stamps, sc.truth)
        if sc.odometry is not None:
            odom_stamps = sorted(data["odom"])
            odom_at = {s: sc.odometry[k] for k, s in enumerate(odom_stamps)}
            common = [s for s in truth_stamps if s in odom_at]
            if common:
                fig["odometry_rmse_vs_truth_m"] = trajectory_error.matched_ate_rmse(
                    np.array(common), np.array([odom_at[s] for s in common]), truth_stamps, sc.truth)
    if sc.grid is not None:
        tri = trinary(sc.grid)
        h, w = sc.grid.shape
        fig.update({"grid_resolution_m": sc.grid.resolution_m, "grid_cells": [w, h],
                    "occupied_cells": int(np.count_nonzero(tri == OCCUPIED)),
                    "free_cells": int(np.count_nonzero(tri == FREE))})
    return fig


def view_limits(sc: Scene) -> tuple[float, float, float, float]:
    """Axis limits: what is on the map (observed cells, estimate, truth, landmarks), 4 % margin, at least 0.5 m."""
    pts = [sc.estimate[:, :2], sc.landmark_xy]
    if sc.truth is not None:
        pts.append(sc.truth[:, :2])
    if sc.grid is not None:
        rows, cols = np.nonzero(trinary(sc.grid) != -1)
        if rows.size:
            res = sc.grid.resolution_m
            pts.append(sc.grid.cell_centres_m(np.array([rows.min(), rows.max()]), np.array([cols.min(), cols.max()]))
                       + np.array([[-0.5, -0.5], [0.5, 0.5]]) * res)
    xy = np.vstack([p for p in pts if p.size])
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    pad = np.maximum(0.04 * (hi - lo), 0.5)
    return float(lo[0] - pad[0]), float(hi[0] + pad[0]), float(lo[1] - pad[1]), float(hi[1] + pad[1])


def trinary(grid: OccupancyGrid) -> np.ndarray:
    """The grid's cells by map_server's default thresholds (occupied 0.65, free 0.196): 100 / 0 / -1, (H, W)."""
    return grid.trinary(OCCUPIED_THRESH, FREE_THRESH)


def pgm_image(grid: OccupancyGrid) -> np.ndarray:
    """The grid as map_saver's trinary image: uint8 (H, W), first row the top (highest y)."""
    tri = trinary(grid)
    img = np.full(tri.shape, PGM_UNKNOWN, dtype=np.uint8)
    img[tri == OCCUPIED] = PGM_OCCUPIED
    img[tri == FREE] = PGM_FREE
    return np.flipud(img)


def write_grid(grid: OccupancyGrid, pgm: Path, yaml: Path, comment: str = "") -> None:
    """``pgm`` (binary P5) and ``yaml`` (ROS map_server), both written atomically; yaml names pgm by file name."""
    img = pgm_image(grid)
    h, w = img.shape
    header = f"P5\n# {comment}\n{w} {h}\n255\n" if comment else f"P5\n{w} {h}\n255\n"
    x0, y0 = (round(float(v), 9) for v in grid.origin_xy_m)
    text = (f"image: {pgm.name}\nmode: trinary\nresolution: {grid.resolution_m!r}\n"
            f"origin: [{x0!r}, {y0!r}, 0.0]\nnegate: 0\n"
            f"occupied_thresh: {OCCUPIED_THRESH!r}\nfree_thresh: {FREE_THRESH!r}\n")
    with atomic_output(pgm) as pgm_partial, atomic_output(yaml) as yaml_partial:
        pgm_partial.write_bytes(header.encode("ascii") + img.tobytes())
        yaml_partial.write_text(text)
