"""Feature-extraction accuracy on simulated worlds: ``lrfslam eval features``.

For many poses in the hallway loop and in random rotated rooms, simulate LMS200
scans at several noise levels, run the angle-histogram filter and forward/backward
searching in the paper-literal and default configurations (and ablations of the
default), and score them against the map (docs/paper-reading.md, 'Evaluating features'):

* precision: forward detections within ``radius_m`` of a map corner (one-to-one,
  nearest first); recall against the *eligible* corners (both walls visible over the
  1.2 m arms) and against all *visible* ones;
* localisation RMSE of the matched detections (mm) and their mean NEES
  ``eᵀ C⁻¹ e`` (2 for a consistent covariance);
* wall points kept and mixed pixels removed by the filter (%), the latter with its
  95 % Wilson interval (a world set holds only about a hundred mixed pixels);
* jump edges per scan and the share of them that are phantoms (farther than
  ``phantom_radius_m`` from any convex corner or free wall end).

The scoring functions are pure; :func:`main` prints markdown tables.
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from lrfslam.algo.features import FORWARD, FeatureParams, FeatureSet, extract_features
from lrfslam.algo.geometry import from_frame, to_frame
from lrfslam.algo.histogram import DenoiseParams, DenoiseResult, denoise
from lrfslam.sim.floor_plans import hallway_loop, waypoints
from lrfslam.sim.lidar import LidarModel, SimScan, simulate_scan
from lrfslam.sim.trajectory import loop_path
from lrfslam.sim.truth import eligible_corners, jump_edge_vertices, visible_corners
from lrfslam.sim.world import World, closed_polygon

#: Detections farther than this from every truth point are false
#: (docs/paper-reading.md, 'Matching and scores').
MATCH_RADIUS_M = 0.10
#: A jump edge within this of a convex corner or free wall end is stationary.
PHANTOM_RADIUS_M = 0.15


def match_nearest(det_xy: np.ndarray, truth_xy: np.ndarray, radius_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Greedy one-to-one matching, nearest pairs first, within a radius.

    Parameters
    ----------
    det_xy : ndarray, shape (D, 2)
    truth_xy : ndarray, shape (T, 2)
        Same frame and unit (metres) as ``det_xy``.
    radius_m : float

    Returns
    -------
    det_idx, truth_idx : ndarray of int, shape (K,)
        Matched pairs, nearest first.
    """
    det = np.asarray(det_xy, dtype=float).reshape(-1, 2)
    truth = np.asarray(truth_xy, dtype=float).reshape(-1, 2)
    if len(det) == 0 or len(truth) == 0:
        return np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp)
    d = np.sqrt(((det[:, None, :] - truth[None, :, :]) ** 2).sum(axis=2))
    di, ti = np.nonzero(d <= radius_m)
    order = np.argsort(d[di, ti], kind="stable")
    used_d, used_t, out_d, out_t = set(), set(), [], []
    for k in order:
        a, b = int(di[k]), int(ti[k])
        if a not in used_d and b not in used_t:
            used_d.add(a)
            used_t.add(b)
            out_d.append(a)
            out_t.append(b)
    return np.array(out_d, dtype=np.intp), np.array(out_t, dtype=np.intp)


@dataclass(frozen=True)
class ScanTruth:
    """Ground truth of one pose, robot frame.

    Attributes
    ----------
    corners_xy : ndarray, shape (C, 2)
        Every map corner, metres.
    eligible : ndarray of int, shape (E,)
        Indices into ``corners_xy`` of corners eligible for forward searching.
    visible : ndarray of int, shape (V,)
        Indices of visible corners.
    edge_vertices_xy : ndarray, shape (J, 2)
        Convex corners and free wall ends, metres.
    """

    corners_xy: np.ndarray
    eligible: np.ndarray
    visible: np.ndarray
    edge_vertices_xy: np.ndarray


def scan_truth(world: World, pose, max_range_m: float = 4.0) -> ScanTruth:
    """Corner truth for one pose (see :class:`ScanTruth`)."""
    return ScanTruth(
        corners_xy=to_frame(world.corners().xy_m, pose),
        eligible=eligible_corners(world, pose, max_range_m=max_range_m),
        visible=visible_corners(world, pose, max_range_m),
        edge_vertices_xy=to_frame(jump_edge_vertices(world), pose),
    )


@dataclass
class Tally:
    """Running sums over scans for one configuration; see :meth:`row`."""

    scans: int = 0
    detections: int = 0
    true_positives: int = 0
    eligible: int = 0
    eligible_found: int = 0
    visible: int = 0
    visible_found: int = 0
    sq_err_m2: float = 0.0
    nees_sum: float = 0.0
    wall_points: int = 0
    wall_kept: int = 0
    spurious_points: int = 0
    spurious_removed: int = 0
    jumps: int = 0
    phantoms: int = 0

    def add(self, scan: SimScan, den: DenoiseResult, feats: FeatureSet, truth: ScanTruth, radius_m: float) -> None:
        """Score one scan and add it to the sums."""
        self.scans += 1
        fwd = feats.kind == FORWARD
        xy, cov = feats.xy_m[fwd], feats.cov_m2[fwd]
        self.detections += len(xy)
        di, ti = match_nearest(xy, truth.corners_xy, radius_m)
        self.true_positives += len(di)
        err = xy[di] - truth.corners_xy[ti]
        self.sq_err_m2 += float((err**2).sum())
        self.nees_sum += float(np.einsum("ki,kij,kj->", err, np.linalg.inv(cov[di]), err)) if len(di) else 0.0
        for ids, name in ((truth.eligible, "eligible"), (truth.visible, "visible")):
            found = len(match_nearest(xy, truth.corners_xy[ids], radius_m)[0])
            setattr(self, name, getattr(self, name) + len(ids))
            setattr(self, name + "_found", getattr(self, name + "_found") + found)
        wall = den.valid & ~scan.spurious & np.isfinite(scan.true_ranges_m)
        self.wall_points += int(wall.sum())
        self.wall_kept += int((wall & den.kept).sum())
        spur = den.valid & scan.spurious
        self.spurious_points += int(spur.sum())
        self.spurious_removed += int((spur & ~den.kept).sum())
        jxy = feats.xy_m[~fwd]
        self.jumps += len(jxy)
        if len(jxy):
            near = np.sqrt(((jxy[:, None, :] - truth.edge_vertices_xy[None, :, :]) ** 2).sum(axis=2))
            stationary = near.min(axis=1) <= PHANTOM_RADIUS_M if near.size else np.zeros(len(jxy), bool)
            self.phantoms += int((~stationary).sum())

    def row(self) -> dict[str, float]:
        """Scores: precision, recall (eligible, visible), RMSE mm, NEES, percentages, rates."""

        def ratio(a: float, b: float) -> float:
            return a / b if b else float("nan")

        lo, hi = wilson_interval(self.spurious_removed, self.spurious_points)
        return {
            "precision": ratio(self.true_positives, self.detections),
            "recall_eligible": ratio(self.eligible_found, self.eligible),
            "recall_visible": ratio(self.visible_found, self.visible),
            "rmse_mm": 1e3 * np.sqrt(ratio(self.sq_err_m2, self.true_positives)),
            "nees": ratio(self.nees_sum, self.true_positives),
            "corners_per_scan": ratio(self.detections, self.scans),
            "wall_kept_pct": 100.0 * ratio(self.wall_kept, self.wall_points),
            "spurious_removed_pct": 100.0 * ratio(self.spurious_removed, self.spurious_points),
            "spurious_removed_lo_pct": 100.0 * lo,
            "spurious_removed_hi_pct": 100.0 * hi,
            "jumps_per_scan": ratio(self.jumps, self.scans),
            "phantom_pct": 100.0 * ratio(self.phantoms, self.jumps),
        }


def wilson_interval(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval of a proportion ``k / n`` (95 % for ``z = 1.96``); NaN for n = 0."""
    if n == 0:
        return float("nan"), float("nan")
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return float(centre - half), float(centre + half)


def hallway_poses(n_poses: int, rng: np.random.Generator) -> np.ndarray:
    """Poses spread round the hallway loop, off the centreline and off its heading.

    Returns
    -------
    ndarray, shape (n_poses, 3)
        Up to ±0.4 m sideways from the centreline and ±20° off its heading, so walls
        and corners are seen from varied, not only symmetric, viewpoints.
    """
    path = loop_path(waypoints("hallway_loop"), 0.8)
    s = np.linspace(0.0, path.total_length_m, n_poses, endpoint=False)
    base = path.pose_at(s)
    side = rng.uniform(-0.4, 0.4, n_poses)
    out = base.copy()
    out[:, 0] -= side * np.sin(base[:, 2])
    out[:, 1] += side * np.cos(base[:, 2])
    out[:, 2] += np.radians(rng.uniform(-20.0, 20.0, n_poses))
    return out


def random_room(rng: np.random.Generator) -> World:
    """A rotated rectangular room with a deep alcove and, half the time, a 0.5 m pillar.

    The alcove walls (≥ 1.3 m) are long enough for the 1.2 m arms; the pillar's are
    not, so its corners count as visible but never eligible.
    """
    w, h = rng.uniform(3.5, 6.0), rng.uniform(3.0, 5.0)
    aw, ad = rng.uniform(1.6, 2.4), rng.uniform(1.3, 2.0)
    a0 = rng.uniform(0.3, w - aw - 0.3)
    outer = [(0, 0), (w, 0), (w, h), (a0 + aw, h), (a0 + aw, h + ad), (a0, h + ad), (a0, h), (0, h)]
    parts = [closed_polygon(outer, free_inside=True)]
    if rng.random() < 0.5:
        cx, cy = rng.uniform(1.2, w - 1.2), rng.uniform(1.2, h - 1.2)
        pillar = [(cx - 0.25, cy - 0.25), (cx + 0.25, cy - 0.25), (cx + 0.25, cy + 0.25), (cx - 0.25, cy + 0.25)]
        parts.append(closed_polygon(pillar, free_inside=False))
    seg = np.vstack(parts)
    pose = (rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-np.pi, np.pi))
    ends = from_frame(seg.reshape(-1, 2), pose).reshape(-1, 4)
    return World(segments_m=ends, name="random_room")


def room_poses(world: World, n_poses: int, rng: np.random.Generator) -> np.ndarray:
    """Random poses inside a :func:`random_room`, at least 0.4 m from every wall."""
    seg = world.segments_m
    lo, hi = seg.reshape(-1, 2).min(axis=0), seg.reshape(-1, 2).max(axis=0)
    poses = []
    while len(poses) < n_poses:
        p = rng.uniform(lo, hi)
        if _inside(world, p) and _wall_clearance(seg, p) >= 0.4:
            poses.append((p[0], p[1], rng.uniform(-np.pi, np.pi)))
    return np.array(poses)


def _inside(world: World, p: np.ndarray) -> bool:
    """Free space of a room: an odd number of walls crossed by a ray to +x."""
    s = world.segments_m
    y0, y1 = s[:, 1], s[:, 3]
    crosses = (y0 > p[1]) != (y1 > p[1])
    with np.errstate(divide="ignore", invalid="ignore"):
        x_at = s[:, 0] + (p[1] - y0) * (s[:, 2] - s[:, 0]) / (y1 - y0)
    return bool(np.count_nonzero(crosses & (x_at > p[0])) % 2)


def _wall_clearance(seg: np.ndarray, p: np.ndarray) -> float:
    a, e = seg[:, :2], seg[:, 2:] - seg[:, :2]
    t = np.clip(((p - a) * e).sum(axis=1) / (e * e).sum(axis=1), 0.0, 1.0)
    return float(np.sqrt(((a + t[:, None] * e - p) ** 2).sum(axis=1)).min())


@dataclass(frozen=True)
class Scene:
    """A world, the poses scanned in it and their truth."""

    world: World
    poses: np.ndarray
    truth: tuple[ScanTruth, ...]


def build_scenes(n_hallway: int, n_rooms: int, poses_per_room: int, seed: int) -> dict[str, list[Scene]]:
    """Scene sets ``hallway_loop`` and ``rooms``, deterministic for a seed."""
    rng = np.random.default_rng(seed)
    hall = hallway_loop()
    hp = hallway_poses(n_hallway, rng)
    sets = {"hallway_loop": [Scene(hall, hp, tuple(scan_truth(hall, p) for p in hp))], "rooms": []}
    for _ in range(n_rooms):
        room = random_room(rng)
        rp = room_poses(room, poses_per_room, rng)
        sets["rooms"].append(Scene(room, rp, tuple(scan_truth(room, p) for p in rp)))
    return sets


Config = tuple[DenoiseParams, FeatureParams]


def mode_configs() -> dict[str, Config]:
    """The paper-literal and default configurations."""
    return {"paper": (DenoiseParams.paper(), FeatureParams.paper()), "default": (DenoiseParams.default(), FeatureParams.default())}


def ablation_configs() -> dict[str, Config]:
    """The default with one improvement switched off (or one option switched on)."""
    dp, cp = DenoiseParams.default(), FeatureParams.default()
    den = {
        "period 180° (no fold)": {"period_deg": 180.0},
        "bins 10°": {"bin_deg": 10.0},
        "bins 30°": {"bin_deg": 30.0},
        "no mixed-pixel test": {"mixed_tol_m": 0.0},
        "range-trend mixed-pixel test": {"mixed_model": "range"},
        "veiling test 10° on": {"shadow_min_angle_deg": 10.0},
        "fixed bins": {"bin_mode": "fixed"},
        "stride 3": {"stride": 3},
    }
    cor = {
        "no straightness check": {"arm_max_resid_m": None},
        "no NMS": {"nms_radius_m": 0.0},
        "no refinement": {"refine_corner": False},
        "arm break gap 1.5 m": {"arm_break_gap_m": 1.5},
        "edges across removed stretches": {"edge_max_removed": None},
        "every finite/∞ edge": {"inf_edge_rule": "any"},
    }
    # keep_frac 0 passes every bin: only the mixed-pixel tests remain.
    out: dict[str, Config] = {"default": (dp, cp), "no histogram": (dataclasses.replace(dp, keep_frac=0.0), cp)}
    out.update({k: (dataclasses.replace(dp, **v), cp) for k, v in den.items()})
    out.update({k: (dp, dataclasses.replace(cp, **v)) for k, v in cor.items()})
    return out


def evaluate(
    scenes: Iterable[Scene], configs: dict[str, Config], sigma_m: float, seed: int, radius_m: float = MATCH_RADIUS_M
) -> dict[str, dict[str, float]]:
    """Score every configuration on the same simulated scans.

    Parameters
    ----------
    scenes : iterable of Scene
    configs : dict of str to (DenoiseParams, FeatureParams)
    sigma_m : float
        Range noise of the simulated scanner, metres.
    seed : int
        Seeds the scan noise; each configuration sees identical scans.
    radius_m : float
        Matching radius, metres.

    Returns
    -------
    dict of str to dict
        :meth:`Tally.row` per configuration name.
    """
    rng = np.random.default_rng(seed)
    model = LidarModel(range_sigma_m=sigma_m)
    tallies = {name: Tally() for name in configs}
    for scene in scenes:
        for pose, truth in zip(scene.poses, scene.truth):
            scan = simulate_scan(scene.world, pose, model, rng)
            for name, (dp, cp) in configs.items():
                den = denoise(scan.ranges_m, scan.angles_rad, dp)
                feats = extract_features(scan.ranges_m, scan.angles_rad, den.kept, cp)
                tallies[name].add(scan, den, feats, truth, radius_m)
    return {name: t.row() for name, t in tallies.items()}


def _number(key: str, spec: str):
    return lambda row: format(row[key], spec)


def _share_with_interval(row: dict[str, float]) -> str:
    return (f"{row['spurious_removed_pct']:.1f} "
            f"[{row['spurious_removed_lo_pct']:.0f}–{row['spurious_removed_hi_pct']:.0f}]")


# (header, the score it shows, its cell)
_COLUMNS = (
    ("P", "precision", _number("precision", ".3f")),
    ("R elig.", "recall_eligible", _number("recall_eligible", ".3f")),
    ("R vis.", "recall_visible", _number("recall_visible", ".3f")),
    ("RMSE mm", "rmse_mm", _number("rmse_mm", ".1f")),
    ("NEES", "nees", _number("nees", ".2f")),
    ("corners/scan", "corners_per_scan", _number("corners_per_scan", ".2f")),
    ("wall kept %", "wall_kept_pct", _number("wall_kept_pct", ".1f")),
    ("mixed removed % [95 % CI]", "spurious_removed_pct", _share_with_interval),
    ("jumps/scan", "jumps_per_scan", _number("jumps_per_scan", ".2f")),
    ("phantom jumps %", "phantom_pct", _number("phantom_pct", ".1f")),
)


def features_table(rows: Sequence[tuple[Sequence[str], dict[str, float]]], key_names: Sequence[str]) -> str:
    """Markdown table: the key columns, then every score column."""
    head = list(key_names) + [c[0] for c in _COLUMNS]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for keys, row in rows:
        cells = list(keys) + [cell(row) if np.isfinite(row[key]) else "–" for _, key, cell in _COLUMNS]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """``lrfslam eval features``: print the accuracy tables in markdown."""
    ap = argparse.ArgumentParser(prog="lrfslam eval features", description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="test-sized run (few poses, σ = 10 mm, no ablation)")
    ap.add_argument("--hallway-poses", type=int, default=240, help="poses round the hallway loop")
    ap.add_argument("--rooms", type=int, default=12, help="random rooms")
    ap.add_argument("--poses-per-room", type=int, default=20)
    ap.add_argument("--sigmas-mm", type=float, nargs="+", default=[5.0, 10.0, 15.0])
    ap.add_argument("--radius-m", type=float, default=MATCH_RADIUS_M, help="matching radius")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--no-ablation", action="store_true")
    args = ap.parse_args(argv)
    if args.quick:
        args.hallway_poses, args.rooms, args.poses_per_room = 24, 2, 6
        args.sigmas_mm, args.no_ablation = [10.0], True

    scenes = build_scenes(args.hallway_poses, args.rooms, args.poses_per_room, args.seed)
    print(f"# Feature extraction on simulated scans (match radius {args.radius_m * 1e3:.0f} mm)\n")
    print(f"hallway_loop: {args.hallway_poses} poses; rooms: {args.rooms} × {args.poses_per_room} poses; seed {args.seed}\n")
    rows = []
    for sigma_mm in args.sigmas_mm:
        for set_name, scene_list in scenes.items():
            res = evaluate(scene_list, mode_configs(), sigma_mm * 1e-3, args.seed, args.radius_m)
            rows += [((set_name, mode, f"{sigma_mm:g}"), r) for mode, r in res.items()]
    print(features_table(rows, ("world", "mode", "σ mm")))
    if not args.no_ablation:
        print("\n## Ablation at σ = 10 mm (default with one change)\n")
        rows = []
        for set_name, scene_list in scenes.items():
            res = evaluate(scene_list, ablation_configs(), 0.01, args.seed, args.radius_m)
            rows += [((set_name, name), r) for name, r in res.items()]
        print(features_table(rows, ("world", "configuration")))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
