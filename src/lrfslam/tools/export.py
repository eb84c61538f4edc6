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
when the recording has one, else the EKF's (``lrfslam.tools.recording_map`` places everything
and scores it; this module writes and draws it).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from lrfslam.algo.occupancy_grid import (
    FREE,
    OCCUPIED,
    GridParams,
    OccupancyGrid,
)
from lrfslam.errors import MissingExtraError
from lrfslam.extras import require
from lrfslam.msgs import topics
from lrfslam.runtime.outputs import atomic_output
from lrfslam.tools.recording_map import (
    PGM_FREE,
    PGM_OCCUPIED,
    PGM_UNKNOWN,
    Scene,
    map_of,
    notes,
    resolution_note,
    trinary,
    write_grid,
)

CHI2_2D_95 = 5.991
#: What map.png can draw (``--layers``).
LAYERS = ("grid", "landmarks", "trajectory", "truth", "odometry")
#: Ellipse magnifications offered when the true-size 95 % ellipses would be too small to see.
ELLIPSE_SCALES = (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000)
#: Resolution of map.png, dots per inch (10 inches wide).
PNG_DPI = 150
#: A drawn ellipse's median semi-major axis is at least this fraction of the picture's diagonal.
ELLIPSE_MIN_FRACTION = 0.004


def ellipse(mean: np.ndarray, cov: np.ndarray, n: int = 48) -> np.ndarray:
    """Points (n, 2) of the 95 % ellipse of a 2-D Gaussian."""
    vals, vecs = np.linalg.eigh(0.5 * (cov + cov.T))
    radii = np.sqrt(np.maximum(vals, 0.0) * CHI2_2D_95)
    a = np.linspace(0, 2 * np.pi, n)
    return mean + (vecs @ (radii[:, None] * np.vstack((np.cos(a), np.sin(a))))).T


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
