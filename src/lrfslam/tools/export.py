"""``lrfslam export RECORDING -o DIR``: the map of a recording — occupancy grid, landmarks, trajectory.

RECORDING is an MCAP file, a recording folder or several files (one stream).

Writes into DIR:

* ``map.json``: the last SLAM state's landmarks (with their place on the map), the EKF's
  trajectory, the mapper's final trajectory when there is one, and the figures;
* ``map.pgm`` + ``map.yaml``: the occupancy grid in the ROS map_server format (trinary:
  occupied 0, free 254, unknown 205), as map_saver writes it and map_server (ROS 1, ROS 2 nav2) loads it;
* ``map.png``: walls (the grid), landmarks with their 95 % ellipses, the estimate against the
  ground truth (or the odometry when there is no truth), axes fitted to the map.

Everything is drawn in the map frame of the *best* trajectory: the mapper's final trajectory
(``lrfslam.evaluation.map_trajectory``) when the recording has ``map/keyframes``, else the EKF's
``slam/state`` poses. The grid is built from the raw ``scan`` messages placed at those poses
(``lrfslam.algo.occupancy_grid``). Truth and odometry are brought into that frame by their
first pose; landmarks (the EKF's, in its own frame) move with the correction the mapper made
to the pose of the scan that saw them last.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lrfslam.algo.geometry import compose, inverse, relative
from lrfslam.algo.occupancy_grid import (
    FREE,
    FREE_THRESH,
    OCCUPIED,
    OCCUPIED_THRESH,
    GridParams,
    OccupancyGrid,
    build_grid,
)
from lrfslam.errors import DecodeError, MissingExtraError, RecordingError
from lrfslam.evaluation import truth as trajectory_error
from lrfslam.evaluation.map_trajectory import FinalTrajectoryBuilder
from lrfslam.extras import require
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.msgs.landmark_map import LandmarkMapReplica
from lrfslam.runtime.outputs import atomic_output
from lrfslam.runtime.recording import RecordingSource, describe_source, read_recording

CHI2_2D_95 = 5.991
#: What map.png can draw (``--layers``).
LAYERS = ("grid", "landmarks", "trajectory", "truth", "odometry")
#: map_saver's trinary pixel values.
PGM_OCCUPIED, PGM_FREE, PGM_UNKNOWN = 0, 254, 205
#: Ellipse magnifications offered when the true-size 95 % ellipses would be too small to see.
ELLIPSE_SCALES = (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000)
#: Resolution of map.png, dots per inch (10 inches wide).
PNG_DPI = 150
#: A drawn ellipse's median semi-major axis is at least this fraction of the picture's diagonal.
ELLIPSE_MIN_FRACTION = 0.004


def collect(path: RecordingSource, scans: bool = True) -> dict:
    """Trajectory, odometry, truth, scans, the last SLAM state, the mapper's final trajectory
    (``"final"``) and every keyframe of its graph (``"keyframes"``, a ``MapKeyframes``; both None
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
    last = None
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
            scan_of[value.stamp_ns] = _ranges(value)
    if last is None:
        raise RecordingError(f"{describe_source(path)} has no decodable {topics.SLAM_STATE.name} messages")
    return {"states": states, "odom": odom, "truth": truth, "last": last, "landmarks": landmarks.landmarks,
            "undecodable": undecodable,
            "scans": scan_of, "scans_read": scans, "seen_ns": seen_ns, "final": final.result(),
            "keyframes": final.keyframes()}


def _grown(ids: np.ndarray, sightings: np.ndarray, old_ids: np.ndarray, old_sightings: np.ndarray) -> np.ndarray:
    """Mask over ``ids``: new landmarks and those seen again since the previous state."""
    if old_ids.size == 0:
        return np.ones(ids.size, bool)
    order = np.argsort(old_ids)
    pos = np.clip(np.searchsorted(old_ids[order], ids), 0, old_ids.size - 1)
    known = old_ids[order][pos] == ids
    return ~known | (old_sightings[order][pos] != sightings)


def _ranges(scan: t.LaserScan) -> tuple[np.ndarray, float, float]:
    """A scan as (ranges float32 with NaN for every beam neither valid nor no-return, angle_min, increment)."""
    r = np.where(scan.status == t.BEAM_VALID, scan.ranges_m,
                 np.where(scan.status == t.BEAM_NO_RETURN, np.inf, np.nan)).astype(np.float32)
    return r, scan.angle_min_rad, scan.angle_increment_rad


def ellipse(mean: np.ndarray, cov: np.ndarray, n: int = 48) -> np.ndarray:
    """Points (n, 2) of the 95 % ellipse of a 2-D Gaussian."""
    vals, vecs = np.linalg.eigh(0.5 * (cov + cov.T))
    radii = np.sqrt(np.maximum(vals, 0.0) * CHI2_2D_95)
    a = np.linspace(0, 2 * np.pi, n)
    return mean + (vecs @ (radii[:, None] * np.vstack((np.cos(a), np.sin(a))))).T


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


def _in_frame(stamps_ns: np.ndarray, poses: np.ndarray, others: dict) -> np.ndarray | None:
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
    rots = [np.array([[np.cos(c[2]), -np.sin(c[2])], [np.sin(c[2]), np.cos(c[2])]]) for c in corrections]
    cov = np.array([r @ c @ r.T for r, c in zip(rots, lms.cov_m2)]).reshape(-1, 2, 2)
    truth_poses = {s: g.pose for s, g in data["truth"].items()}
    sc = Scene(name=describe_source(path), trajectory_label=label, stamps_ns=stamps, estimate=poses,
               landmark_xy=xy, landmark_cov=cov, landmark_confirmed=np.asarray(lms.confirmed, bool),
               truth=_in_frame(stamps, poses, truth_poses), odometry=_in_frame(stamps, poses, data["odom"]))
    if sc.truth is not None:
        corners = {}
        for g in data["truth"].values():
            corners.update({int(i): c for i, c in zip(g.corner_ids, g.corners_xy_m)})
        anchor = _anchor(stamps, poses, truth_poses)
        sc.true_corners = np.array([relative(anchor, (*c, 0.0))[:2] for c in corners.values()]).reshape(-1, 2)
    if grid_params is not None and data["scans"]:
        sc.grid, sc.scans_placed = _grid(stamps, poses, data["scans"], grid_params, fit)
        sc.scans_unplaced = len(data["scans"]) - sc.scans_placed
    sc.figures = _figures(sc, data)
    sc.view = _view(sc)
    return sc


def map_of(path: RecordingSource, resolution_m: float | None = None, max_range_m: float = GridParams.max_range_m,
           grid: bool = True) -> tuple[dict, Scene]:
    """:func:`collect` and :func:`scene` as ``lrfslam export`` (and ``lrfslam map save``) build the map.

    ``resolution_m`` None: :class:`GridParams`' default, or the finest of its doublings a map
    too large for it fits (:func:`resolution_note` says so); ``max_range_m``: returns up to it mark walls
    and it caps the free space a beam marks, metres; ``grid`` False: no scans read, no grid.
    """
    params = GridParams(resolution_m=GridParams.resolution_m if resolution_m is None else resolution_m,
                        max_range_m=max_range_m, free_range_m=max_range_m) if grid else None
    data = collect(path, scans=grid)
    return data, scene(path, data, params, fit=resolution_m is None)


def notes(data: dict, sc: Scene) -> list[str]:
    """Warnings for a user of :func:`map_of`'s map: undecodable messages skipped, scans left out of the grid."""
    out = [f"skipped {data['undecodable']} undecodable messages"] if data["undecodable"] else []
    if sc.grid is not None and sc.scans_unplaced:
        out.append(f"{sc.scans_unplaced} of {len(data['scans'])} scans have no pose at their stamp and are not in "
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


def _view(sc: Scene) -> tuple[float, float, float, float]:
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


def to_json(data: dict, sc: Scene | None = None) -> dict:
    last, lms = data["last"], data["landmarks"]
    xy_map = sc.landmark_xy if sc is not None else lms.xy_m
    doc = {
        "frame": "map (the first SLAM pose); landmarks' x_m, y_m in the EKF's frame, map_xy_m on map_trajectory",
        "landmarks": [
            {"id": int(i), "x_m": float(xy[0]), "y_m": float(xy[1]), "covariance_m2": c.tolist(),
             "kind": "forward" if k == 1 else "backward", "sightings": int(n), "confirmed": bool(ok),
             "map_xy_m": [float(v) for v in m]}
            for i, xy, c, k, n, ok, m in zip(lms.ids, lms.xy_m, lms.cov_m2, lms.kind, lms.sightings,
                                             lms.confirmed, xy_map)
        ],
        "trajectory": [{"stamp_ns": int(s), "x_m": float(p[0]), "y_m": float(p[1]), "theta_rad": float(p[2])}
                       for s, p in data["states"]],
        "final_pose_covariance": last.pose_cov.tolist(),
    }
    if sc is not None:
        doc["map_trajectory"] = [{"stamp_ns": int(s), "x_m": float(p[0]), "y_m": float(p[1]),
                                  "theta_rad": float(p[2])} for s, p in zip(sc.stamps_ns, sc.estimate)]
        doc["figures"] = sc.figures
    return doc


def ellipse_scale(sc: Scene) -> int:
    """The smallest of :data:`ELLIPSE_SCALES` that makes the median 95 % ellipse visible in the view."""
    if not sc.landmark_cov.size:
        return 1
    major = np.sqrt(CHI2_2D_95 * np.linalg.eigvalsh(0.5 * (sc.landmark_cov + sc.landmark_cov.transpose(0, 2, 1)))
                    [:, -1].clip(min=0))
    x0, x1, y0, y1 = sc.view
    want = ELLIPSE_MIN_FRACTION * np.hypot(x1 - x0, y1 - y0)
    return next((s for s in ELLIPSE_SCALES if s * np.median(major) >= want), ELLIPSE_SCALES[-1])


def title(sc: Scene) -> str:
    f = sc.figures
    scans = f"{f['scans']} scans, " if f["scans"] is not None else ""
    line1 = (f"{sc.name}: {scans}{f['poses']} poses ({sc.trajectory_label}), "
             f"{f['landmarks']} landmarks ({f['confirmed_landmarks']} confirmed)")
    parts = []
    if f.get("rmse_vs_truth_m") is not None:
        odo = f.get("odometry_rmse_vs_truth_m")
        parts.append(f"position RMSE vs truth {f['rmse_vs_truth_m']:.3f} m"
                     + (f", odometry {odo:.2f} m" if odo is not None else "") + " (anchored at the first pose)")
    if sc.grid is not None:
        w, h = f["grid_cells"]
        parts.append(f"grid {f['grid_resolution_m']:g} m, {w} x {h} cells")
    return line1 + ("\n" + "; ".join(parts) if parts else "")


def plot(sc: Scene, png: Path, layers: frozenset[str], ellipse_x: int | None = None) -> int:
    """Draw ``layers`` of ``sc`` into ``png``; returns the ellipse magnification used."""
    require("matplotlib", "plot", "the map picture (map.png)").use("Agg")
    plt = require("matplotlib.pyplot", "plot", "the map picture (map.png)")
    x0, x1, y0, y1 = sc.view
    # The axes take the figure's width; its height follows the map's shape, plus the title and the legend below.
    height = float(np.clip(9.2 * (y1 - y0) / (x1 - x0), 3.0, 14.0)) + 1.9
    fig, ax = plt.subplots(figsize=(10, height))
    ax.set_facecolor(np.full(3, PGM_UNKNOWN / 255) if "grid" in layers and sc.grid is not None else "white")
    if "grid" in layers and sc.grid is not None:
        # About the axes' size in pixels: a larger grid is reduced first, so no wall falls between pixels.
        image, extent = grid_picture(sc.grid, (int(0.9 * 10 * PNG_DPI), int(0.9 * (height - 1.9) * PNG_DPI)))
        ax.imshow(image, origin="lower", extent=extent, interpolation="nearest", zorder=0)
        ax.plot([], [], "s", color="black", ms=6, label="walls (occupancy grid)")
    if "truth" in layers and sc.truth is not None:
        ax.plot(sc.truth[:, 0], sc.truth[:, 1], color="#74c476", lw=4.5, alpha=0.8, solid_capstyle="round",
                label="ground truth", zorder=2)
    if "odometry" in layers and sc.odometry is not None:
        ax.plot(sc.odometry[:, 0], sc.odometry[:, 1], color="#e6550d", lw=0.9, ls="--", label="odometry", zorder=3)
    if "trajectory" in layers:
        ax.plot(sc.estimate[:, 0], sc.estimate[:, 1], color="#08306b", lw=0.9, label=f"estimate: {sc.trajectory_label}",
                zorder=4)
    scale = ellipse_x if ellipse_x is not None else ellipse_scale(sc)
    if "landmarks" in layers and sc.landmark_xy.size:
        for xy, cov, ok in zip(sc.landmark_xy, sc.landmark_cov, sc.landmark_confirmed):
            e = ellipse(xy, cov * scale**2)
            ax.plot(e[:, 0], e[:, 1], color="#cb181d" if ok else "#fc9272", lw=0.8, zorder=5)
        for ok, colour, text in ((True, "#cb181d", "landmarks"), (False, "#fc9272", "tentative landmarks")):
            sel = sc.landmark_confirmed == ok
            if sel.any():
                ax.plot(sc.landmark_xy[sel, 0], sc.landmark_xy[sel, 1], "+", color=colour, ms=5, zorder=6,
                        label=f"{text}, 95 % ellipses" + (f" ×{scale}" if scale != 1 else ""))
        if "truth" in layers and sc.true_corners is not None and sc.true_corners.size:
            ax.scatter(sc.true_corners[:, 0], sc.true_corners[:, 1], marker="s", s=14, facecolors="none",
                       edgecolors="#006d2c", lw=0.6, label="true corners", zorder=5)
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m] (map frame)")
    ax.set_ylabel("y [m]")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.09), ncol=3, fontsize=8, frameon=False)
    ax.set_title(title(sc), fontsize=9)
    fig.tight_layout()
    fig.savefig(png, dpi=PNG_DPI)
    plt.close(fig)
    return scale


def grid_picture(grid: OccupancyGrid, max_px: tuple[int, int]) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """The grid as an RGBA image (rows from the lowest y) of at most ``max_px`` (width, height) pixels, and its extent.

    A grid larger than that is reduced by a whole factor; a reduced pixel is occupied when any
    of its cells is, else free when any is, else unknown — walls stay.
    """
    tri = trinary(grid)
    h, w = tri.shape
    f = max(1, -(-w // max(max_px[0], 1)), -(-h // max(max_px[1], 1)))
    rank = np.full((-(-h // f) * f, -(-w // f) * f), 2, dtype=np.uint8)   # 0 occupied, 1 free, 2 unknown
    rank[:h, :w] = np.where(tri == OCCUPIED, 0, np.where(tri == FREE, 1, 2))
    rank = rank.reshape(rank.shape[0] // f, f, rank.shape[1] // f, f).min(axis=(1, 3))
    grey = np.array([PGM_OCCUPIED, PGM_FREE, PGM_UNKNOWN], dtype=np.uint8)[rank]
    x0, _, y0, _ = grid.extent_m
    size = f * grid.resolution_m
    # uint8 RGBA is what matplotlib draws with the least memory (no colour map, no conversion).
    rgba = np.dstack((grey, grey, grey, np.full_like(grey, 255)))
    return rgba, (x0, x0 + rank.shape[1] * size, y0, y0 + rank.shape[0] * size)


def parse_layers(text: str) -> frozenset[str]:
    names = frozenset(n.strip() for n in text.split(",") if n.strip())
    unknown = names - set(LAYERS)
    if unknown or not names:
        raise argparse.ArgumentTypeError(f"layers must be some of {','.join(LAYERS)}, not {text!r}")
    return names


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lrfslam export", description=__doc__.splitlines()[0])
    parser.add_argument("recording", type=Path, nargs="+",
                        help="recording (or --replay output) with slam/state: a file, a folder or several files")
    parser.add_argument("-o", "--out-dir", type=Path, default=Path("."),
                        help="folder for map.json, map.pgm, map.yaml and map.png")
    parser.add_argument("--no-png", action="store_true", help="no map.png (no plotting extra needed)")
    parser.add_argument("--no-grid", action="store_true",
                        help="no occupancy grid: no map.pgm/map.yaml, no walls in map.png")
    parser.add_argument("--resolution", type=float, default=None, metavar="M",
                        help=f"grid cell size in metres (default {GridParams.resolution_m}, or the finest of its "
                             f"doublings a map larger than {GridParams.max_cells:,} cells fits, said when so)")
    parser.add_argument("--max-range", type=float, default=GridParams.max_range_m, metavar="M",
                        help="returns up to this range mark walls, farther ones only clear the space before them; "
                             f"free space is marked up to it too (default {GridParams.max_range_m})")
    parser.add_argument("--layers", type=parse_layers, default=None, metavar="LIST",
                        help=f"what map.png draws, comma-separated from {','.join(LAYERS)} (default: all but "
                             "odometry when the recording has ground truth, all but truth otherwise)")
    parser.add_argument("--ellipse-scale", type=int, default=None, metavar="X",
                        help="draw the 95 %% ellipses X times their size (default: the smallest of "
                             f"{', '.join(map(str, ELLIPSE_SCALES))} that makes them visible; the legend says it)")
    parser.add_argument("--foxglove", type=Path, metavar="OUT.mcap",
                        help="instead: copy the recording to OUT.mcap with Foxglove's views added, to open it in "
                             "Foxglove as a map (docs/monitoring.md)")
    args = parser.parse_args(argv)
    if args.foxglove:
        from lrfslam.tools import foxglove_export
        return foxglove_export.main(args.recording, args.foxglove)
    if args.ellipse_scale is not None and args.ellipse_scale < 1:
        parser.error("--ellipse-scale must be >= 1")
    data, sc = map_of(args.recording, args.resolution, args.max_range, grid=not args.no_grid)
    for warning in notes(data, sc):
        print(f"lrfslam export: {warning}", file=sys.stderr)
    if note := resolution_note(sc, args.resolution):
        print(f"lrfslam export: {note}")
    out = args.out_dir
    with atomic_output(out / "map.json") as partial:
        partial.write_text(json.dumps(to_json(data, sc), indent=1))
    written = [out / "map.json"]
    if sc.grid is not None:
        write_grid(sc.grid, out / "map.pgm", out / "map.yaml",
                   comment=f"lrfslam export of {sc.name}, {sc.trajectory_label}")
        written += [out / "map.pgm", out / "map.yaml"]
    elif not args.no_grid:
        print(f"lrfslam export: no {topics.SCAN.name} messages with a pose: no occupancy grid (map.pgm, map.yaml)",
              file=sys.stderr)
    if not args.no_png:
        layers = args.layers if args.layers is not None else \
            frozenset(LAYERS) - {"odometry" if sc.truth is not None else "truth"}
        try:
            with atomic_output(out / "map.png") as partial:
                plot(sc, partial, layers, args.ellipse_scale)
        except MissingExtraError as exc:
            print(f"lrfslam export: error: wrote {', '.join(str(p) for p in written)}; {exc} (or pass --no-png)",
                  file=sys.stderr)
            return 2
        written.append(out / "map.png")
    print(f"wrote {', '.join(str(p) for p in written)}")
    return 0
