"""Feature counts and repeatability on the real Intel Research Lab log: ``lrfslam eval intel-features``.

Runs the angle-histogram filter and forward/backward searching (paper-literal and
default configurations) on every FLASER scan of the raw CARMEN log (180 beams at 1°,
cut at 4 m) and reports features per scan and their repeatability.

Repeatability (as in FLIRT/FALKO; docs/paper-reading.md, 'Matching and scores'):
for scan pairs ``(k, k + d)``, bring both detection sets into one frame with the relative pose, keep those inside the
other scan's field of view and range, and count mutual one-to-one matches within
``radius_m``; repeatability = Σ matches / Σ min(#A, #B) over all pairs.

Relative poses come from the raw wheel odometry between the two scans. The
Kümmerle relations are exact but link scans seconds apart (a few per baseline), so
they are used instead to *measure* the odometry error at the same short baselines,
which is printed with the table: a repeatability figure is only as good as that.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lrfslam.algo.features import FORWARD, FeatureParams, extract_features
from lrfslam.algo.geometry import from_frame, relative, to_frame, wrap_angle
from lrfslam.algo.histogram import DenoiseParams, denoise
from lrfslam.evaluation.features import match_nearest
from lrfslam.evaluation.relations import Relations, load_relations, match_stamps
from lrfslam.io.carmen import LaserRecord, iter_records
from lrfslam.io.textfile import open_log

#: Where the shared datasets sit relative to the project root (see the project README).
DEFAULT_LOG = Path("..") / "shared" / "datasets" / "intel" / "intel.clf.bz2"
DEFAULT_RELATIONS = Path("..") / "shared" / "datasets" / "intel" / "intel.relations"
BASELINES = (1, 5, 20)


@dataclass(frozen=True)
class Repeatability:
    """Pooled repeatability over all scan pairs of one baseline.

    Attributes
    ----------
    matched : int
        Mutual matches summed over pairs.
    possible : int
        Σ min(#A, #B) over pairs, counting only features inside the other view.
    pairs : int
        Scan pairs with ``min(#A, #B) > 0``.
    """

    matched: int
    possible: int
    pairs: int

    @property
    def value(self) -> float:
        """matched / possible (NaN without pairs)."""
        return self.matched / self.possible if self.possible else float("nan")


def inside_view(xy: np.ndarray, max_range_m: float, half_fov_rad: float = np.pi / 2) -> np.ndarray:
    """Points (K, 2) within range and field of view of a scanner at the origin; (K,) bool."""
    r = np.sqrt((xy * xy).sum(axis=1))
    return (r <= max_range_m) & (np.abs(np.arctan2(xy[:, 1], xy[:, 0])) <= half_fov_rad)


def repeatability(
    features_xy: Sequence[np.ndarray], poses: np.ndarray, baseline: int, radius_m: float, max_range_m: float
) -> Repeatability:
    """Repeatability of detections between scans ``baseline`` apart.

    Parameters
    ----------
    features_xy : sequence of ndarray, each (K_k, 2)
        Detections of scan k in its own frame, metres.
    poses : ndarray, shape (T, 3)
        Pose of each scan in one common frame (odometry).
    baseline : int
        Scan offset d >= 1.
    radius_m : float
        Matching radius, metres.
    max_range_m : float
        Range of the view test, metres.

    Returns
    -------
    Repeatability
    """
    matched = possible = pairs = 0
    for k in range(len(features_xy) - baseline):
        a, b = features_xy[k], features_xy[k + baseline]
        if len(a) == 0 or len(b) == 0:
            continue
        rel = relative(poses[k], poses[k + baseline])
        a_in = a[inside_view(to_frame(a, rel), max_range_m)]
        b_in_a = from_frame(b, rel)
        b_in_a = b_in_a[inside_view(b, max_range_m) & inside_view(b_in_a, max_range_m)]
        n = min(len(a_in), len(b_in_a))
        if n == 0:
            continue
        pairs += 1
        possible += n
        matched += len(match_nearest(a_in, b_in_a, radius_m)[0])
    return Repeatability(matched, possible, pairs)


def odometry_error(
    stamps_s: np.ndarray, poses: np.ndarray, relations: Relations, max_scan_gap: int
) -> tuple[np.ndarray, np.ndarray]:
    """Error of odometry relative poses against relations between nearby scans.

    Returns
    -------
    trans_m, rot_deg : ndarray, shape (R,)
        Translational and absolute rotational error of each relation whose scans are
        at most ``max_scan_gap`` apart in file order.
    """
    i1, _ = match_stamps(stamps_s, relations.stamp1_s, 1e-3)
    i2, _ = match_stamps(stamps_s, relations.stamp2_s, 1e-3)
    use = (i1 >= 0) & (i2 >= 0) & (np.abs(i2 - i1) <= max_scan_gap)
    trans, rot = [], []
    for a, b, d in zip(i1[use], i2[use], relations.delta[use]):
        e = relative(poses[a], poses[b]) - d
        trans.append(np.hypot(e[0], e[1]))
        rot.append(abs(np.degrees(wrap_angle(e[2]))))
    return np.array(trans), np.array(rot)


def read_scans(log_path: Path, max_scans: int | None):
    """FLASER scans of a CLF in file order: stamps (T,), odometry poses (T, 3), records."""
    records: list[LaserRecord] = []
    with open_log(log_path) as log:
        for item in iter_records(log):
            if isinstance(item, LaserRecord):
                records.append(item)
                if max_scans is not None and len(records) >= max_scans:
                    break
    stamps = np.array([r.stamp_s for r in records])
    poses = np.array([r.odom_pose for r in records]).reshape(-1, 3)
    return stamps, poses, records


def main(argv: Sequence[str] | None = None) -> int:
    """``lrfslam eval intel-features``: print the table in markdown."""
    ap = argparse.ArgumentParser(prog="lrfslam eval intel-features", description=__doc__.split("\n\n")[0])
    ap.add_argument("--log", type=Path, default=DEFAULT_LOG, help="CARMEN log (plain, .bz2 or .gz)")
    ap.add_argument("--relations", type=Path, default=DEFAULT_RELATIONS, help="relations file (odometry check)")
    ap.add_argument("--max-scans", type=int, default=None, help="only the first N scans")
    ap.add_argument("--quick", action="store_true", help="test-sized run: the first 400 scans")
    ap.add_argument("--radius-m", type=float, default=0.10)
    args = ap.parse_args(argv)
    if args.quick:
        args.max_scans = 400

    stamps, poses, records = read_scans(args.log, args.max_scans)
    modes = {"paper": (DenoiseParams.paper(), FeatureParams.paper()),
             "default": (DenoiseParams.default(), FeatureParams.default())}
    found: dict[tuple[str, str], list[np.ndarray]] = {(m, k): [] for m in modes for k in ("corners", "jump edges")}
    for rec in records:
        angles = rec.angle_min_rad + rec.angle_increment_rad * np.arange(rec.n_beams)
        for mode, (dp, cp) in modes.items():
            fs = extract_features(rec.ranges_m, angles, denoise(rec.ranges_m, angles, dp).kept, cp)
            fwd = fs.kind == FORWARD
            found[(mode, "corners")].append(fs.xy_m[fwd])
            found[(mode, "jump edges")].append(fs.xy_m[~fwd])

    print(f"# Features on the Intel Research Lab log ({len(records)} FLASER scans, 4 m cut)\n")
    if args.relations.exists():
        with open(args.relations, encoding="utf-8") as f:
            rel = load_relations(f)
        for gap in BASELINES:
            t, r = odometry_error(stamps, poses, rel, gap)
            if len(t):
                print(f"- odometry vs relations, scans ≤ {gap} apart: {len(t)} relations, translation error "
                      f"median {1e3 * np.median(t):.0f} mm (p90 {1e3 * np.percentile(t, 90):.0f}), "
                      f"rotation median {np.median(r):.2f}° (p90 {np.percentile(r, 90):.2f}°)")
            else:
                print(f"- odometry vs relations, scans ≤ {gap} apart: no relation in the scans read")
        print()
    head = ["mode", "features", "per scan"] + [f"repeatability d={d} (pairs)" for d in BASELINES]
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for (mode, kind), xy in found.items():
        cells = [mode, kind, f"{np.mean([len(x) for x in xy]):.2f}"]
        for d in BASELINES:
            rep = repeatability(xy, poses, d, args.radius_m, modes[mode][1].max_range_m)
            cells.append(f"{rep.value:.2f} ({rep.pairs})" if rep.pairs else "–")
        print("| " + " | ".join(cells) + " |")
    print(f"\nMatching radius {args.radius_m * 1e3:.0f} mm; relative poses from raw odometry.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
