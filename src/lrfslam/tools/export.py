"""``lrfslam export RECORDING -o DIR``: the final map and the trajectory as JSON and a PNG plot.

RECORDING is an MCAP file, a recording folder or several files (one stream).

The plot shows landmarks with their 95 % covariance ellipses, the estimated
trajectory, raw odometry, and — when the recording has it — the ground truth
(trajectory and map corners), all in the frame of the first SLAM pose anchored
to the first true pose so they can be compared by eye.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from lrfslam.algo.geometry import compose, relative
from lrfslam.errors import DecodeError, MissingExtraError, RecordingError
from lrfslam.extras import require
from lrfslam.msgs import topics
from lrfslam.runtime.outputs import atomic_output
from lrfslam.runtime.recording import RecordingSource, describe_source, read_recording

CHI2_2D_95 = 5.991


def collect(path: RecordingSource) -> dict:
    """Trajectory, odometry, truth and the last SLAM state of a recording (file, folder or files).

    Undecodable messages are skipped and counted (``"undecodable"``).

    Raises
    ------
    RecordingError
        ``path`` is no recording, or has no decodable ``slam/state``.
    """
    states, odom, truth = [], {}, {}
    last = None
    undecodable = 0
    for m in read_recording(path, [topics.SLAM_STATE.name, topics.ODOM.name, topics.TRUTH.name]):
        try:
            value = topics.by_name(m.topic).codec.decode(m.data, m.schema)
        except DecodeError:
            undecodable += 1
            continue
        if m.topic == topics.SLAM_STATE.name:
            last = value
            states.append((last.stamp_ns, last.pose))
        elif m.topic == topics.ODOM.name:
            odom[value.stamp_ns] = value.pose
        else:
            truth[value.stamp_ns] = value
    if last is None:
        raise RecordingError(f"{describe_source(path)} has no decodable {topics.SLAM_STATE.name} messages")
    return {"states": states, "odom": odom, "truth": truth, "last": last, "undecodable": undecodable}


def anchor_of(states, frames: dict) -> np.ndarray:
    """Transform from the SLAM map frame to the frame of ``frames`` (truth or odometry), by the first pose."""
    for stamp, pose in states:
        if stamp in frames:
            ref = frames[stamp].pose if hasattr(frames[stamp], "pose") else frames[stamp]
            return compose(ref, relative(pose, np.zeros(3)))
    return np.zeros(3)


def to_json(data: dict) -> dict:
    last = data["last"]
    return {
        "frame": "map (the first SLAM pose)",
        "landmarks": [
            {"id": int(i), "x_m": float(xy[0]), "y_m": float(xy[1]), "covariance_m2": c.tolist(),
             "kind": "forward" if k == 1 else "backward", "sightings": int(n), "confirmed": bool(ok)}
            for i, xy, c, k, n, ok in zip(last.landmark_ids, last.landmark_xy_m, last.landmark_cov_m2,
                                          last.landmark_kind, last.landmark_sightings, last.landmark_confirmed)
        ],
        "trajectory": [{"stamp_ns": int(s), "x_m": float(p[0]), "y_m": float(p[1]), "theta_rad": float(p[2])}
                       for s, p in data["states"]],
        "final_pose_covariance": last.pose_cov.tolist(),
    }


def ellipse(mean: np.ndarray, cov: np.ndarray, n: int = 48) -> np.ndarray:
    """Points (n, 2) of the 95 % ellipse of a 2-D Gaussian."""
    vals, vecs = np.linalg.eigh(0.5 * (cov + cov.T))
    radii = np.sqrt(np.maximum(vals, 0.0) * CHI2_2D_95)
    a = np.linspace(0, 2 * np.pi, n)
    return mean + (vecs @ (radii[:, None] * np.vstack((np.cos(a), np.sin(a))))).T


def plot(data: dict, png: Path) -> None:
    require("matplotlib", "plot", "the map picture (map.png)").use("Agg")
    plt = require("matplotlib.pyplot", "plot", "the map picture (map.png)")

    have_truth = bool(data["truth"])
    anchor = anchor_of(data["states"], data["truth"]) if have_truth else np.zeros(3)
    fig, ax = plt.subplots(figsize=(9, 7))
    est = np.array([compose(anchor, p) for _, p in data["states"]])
    if have_truth:
        tru = np.array([g.pose for _, g in sorted(data["truth"].items())])
        ax.plot(tru[:, 0], tru[:, 1], color="0.6", lw=2, label="ground truth")
        corners = {}
        for g in data["truth"].values():
            corners.update({int(i): xy for i, xy in zip(g.corner_ids, g.corners_xy_m)})
        if corners:
            c = np.array(list(corners.values()))
            ax.scatter(c[:, 0], c[:, 1], marker="s", s=18, facecolors="none", edgecolors="0.4",
                       label="true corners")
    if data["odom"]:
        odom_anchor = compose(anchor, relative(anchor_of(data["states"], data["odom"]), np.zeros(3)))
        od = np.array([compose(odom_anchor, p) for _, p in sorted(data["odom"].items())])
        ax.plot(od[:, 0], od[:, 1], color="tab:orange", lw=1, ls="--", label="odometry")
    ax.plot(est[:, 0], est[:, 1], color="tab:blue", lw=1.2, label="EKF estimate")
    last = data["last"]
    c, s = np.cos(anchor[2]), np.sin(anchor[2])
    rot = np.array([[c, -s], [s, c]])
    for xy, cov, ok in zip(last.landmark_xy_m, last.landmark_cov_m2, last.landmark_confirmed):
        m = anchor[:2] + rot @ xy
        e = ellipse(m, rot @ cov @ rot.T)
        ax.plot(e[:, 0], e[:, 1], color="tab:red" if ok else "tab:pink", lw=0.8)
        ax.plot(*m, "+", color="tab:red" if ok else "tab:pink", ms=6)
    ax.plot([], [], "+", color="tab:red", label="landmarks (95 % ellipses)")
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.legend(loc="best", fontsize=8)
    ax.set_title(f"{len(last.landmark_ids)} landmarks, {len(data['states'])} poses")
    fig.tight_layout()
    fig.savefig(png, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lrfslam export", description=__doc__.splitlines()[0])
    parser.add_argument("recording", type=Path, nargs="+",
                        help="recording (or --replay output) with slam/state: a file, a folder or several files")
    parser.add_argument("-o", "--out-dir", type=Path, default=Path("."), help="folder for map.json and map.png")
    parser.add_argument("--no-png", action="store_true", help="write map.json only (no plotting extra needed)")
    parser.add_argument("--foxglove", type=Path, metavar="OUT.mcap",
                        help="instead: copy the recording to OUT.mcap with Foxglove's views added, to open it in "
                             "Foxglove as a map (docs/monitoring.md)")
    args = parser.parse_args(argv)
    if args.foxglove:
        from lrfslam.tools import foxglove_export
        return foxglove_export.main(args.recording, args.foxglove)
    data = collect(args.recording)
    if data["undecodable"]:
        print(f"lrfslam export: skipped {data['undecodable']} undecodable messages", file=sys.stderr)
    with atomic_output(args.out_dir / "map.json") as partial:
        partial.write_text(json.dumps(to_json(data), indent=1))
    if args.no_png:
        print(f"wrote {args.out_dir / 'map.json'}")
        return 0
    try:
        with atomic_output(args.out_dir / "map.png") as partial:
            plot(data, partial)
    except MissingExtraError as exc:
        print(f"lrfslam export: error: wrote {args.out_dir / 'map.json'}; {exc} (or pass --no-png)",
              file=sys.stderr)
        return 2
    print(f"wrote {args.out_dir / 'map.json'} and {args.out_dir / 'map.png'}")
    return 0
