"""Any CARMEN log of the Intel kind works: a simulated run written as FLASER lines, imported, run, scored.

The only public log of this kind available offline is Intel's (docs/slam.md has
its figures). Here the simulator stands in for a second one: its scans and a
poor odometry go into a ``.clf`` exactly as a CARMEN logger writes them, its
truth into a Freiburg relations file, and the same commands as on Intel
(``lrfslam import carmen``, ``lrfslam pipeline``, ``lrfslam eval relations``)
must recover the motion far better than the odometry.
"""

from __future__ import annotations

import numpy as np
import pytest

from lrfslam.algo.geometry import relative
from lrfslam.algo.scan_match import ScanMatchParams
from lrfslam.evaluation.laser_odometry import scan_matched_trajectory
from lrfslam.evaluation.recording_relations import evaluate_relations
from lrfslam.sim.odometry import OdometryNoise
from lrfslam.sim.simulator import SimConfig, Simulator
from lrfslam.tools import evaluate
from lrfslam.tools.importers import import_carmen
from lrfslam.tools.pipeline import DEFAULT_STAGES, build_stages, run_pipeline

T0_S = 1_000.0
N_SCANS = 400  # 40 s, 20 m of the hallway loop and its first corner
NO_RETURN_M = 81.91  # what Intel's logger wrote for "no return"


def flaser(ranges_m: np.ndarray, odom_pose: np.ndarray, stamp_s: float) -> str:
    """One FLASER line: ranges, laser pose and odometry pose (the same: no mounting offset), stamps."""
    values = " ".join(f"{r:.3f}" for r in np.where(np.isfinite(ranges_m), ranges_m, NO_RETURN_M))
    pose = " ".join(f"{v:.6f}" for v in odom_pose)
    return f"FLASER {ranges_m.size} {values} {pose} {pose} {stamp_s:.6f} simhost {stamp_s:.6f}"


@pytest.fixture(scope="module")
def simulated_log(tmp_path_factory):
    """(log path, relations path) of a simulated run with 10 %/m odometry and 0.1 rad/rad heading noise."""
    root = tmp_path_factory.mktemp("carmen")
    sim = Simulator(SimConfig(seed=5, odometry=OdometryNoise(0.1, 0.1, 0.02)))
    assert sim.config.lidar.n_beams == 181  # CARMEN's 181-beam FLASER layout: -90° in 1° steps
    frames = [next(sim) for _ in range(N_SCANS)]
    stamps = [T0_S + f.t_s for f in frames]
    log = root / "sim.clf"
    log.write_text("# simulated CARMEN log\n" + "\n".join(
        flaser(f.scan.ranges_m, f.odom_pose, s) for f, s in zip(frames, stamps)) + "\n")
    # Relations as in Kümmerle et al.: short ones along the path, and long ones across it.
    pairs = [(i, i + 10) for i in range(0, N_SCANS - 10, 5)] + [(i, i + 200) for i in range(0, N_SCANS - 200, 20)]
    rows = []
    for i, j in pairs:
        d = relative(frames[i].true_pose, frames[j].true_pose)
        rows.append(f"{stamps[i]:.6f} {stamps[j]:.6f} {d[0]:.6f} {d[1]:.6f} 0 0 0 {d[2]:.6f}")
    relations = root / "sim.relations"
    relations.write_text("\n".join(rows) + "\n")
    return log, relations


def test_a_simulated_carmen_log_imports_runs_and_beats_its_odometry(simulated_log, tmp_path):
    log, relations = simulated_log
    recording, out = tmp_path / "sim.mcap", tmp_path / "run.mcap"
    imported = import_carmen(log, recording)
    assert imported.scans == N_SCANS and not imported.issues
    counts = run_pipeline(build_stages(DEFAULT_STAGES, [], {}, {}), "robot1", recording, out)
    assert counts["slam"]["step.match_ok"] >= N_SCANS - 10
    results, undecodable = evaluate_relations(out, relations)
    slam, odom = results["slam estimate"], results["raw odometry"]
    assert undecodable == 0 and slam.n_used == odom.n_used == slam.n_relations
    assert slam.trans_abs_m.mean < 0.03 and slam.trans_abs_m.mean < 0.2 * odom.trans_abs_m.mean, \
        (slam.trans_abs_m.mean, odom.trans_abs_m.mean)
    assert slam.rot_abs_deg.mean < 0.3 < odom.rot_abs_deg.mean


def test_eval_relations_scores_scan_matching_alone(simulated_log, tmp_path, capsys):
    """``lrfslam eval relations --scan-matching``: the tracker by itself, between odometry and the filter."""
    log, relations = simulated_log
    recording = tmp_path / "sim.mcap"
    import_carmen(log, recording)
    stamps_ns, poses, undecodable = scan_matched_trajectory(recording, ScanMatchParams())
    assert undecodable == 0 and len(stamps_ns) == len(poses) == N_SCANS
    assert evaluate.main(["relations", str(recording), str(relations), "--scan-matching",
                          "--set", "max_point_range_m=4.0"]) == 0
    rows = {line.split("  ")[0]: line for line in capsys.readouterr().out.splitlines()}
    assert "scan matching" in rows and "raw odometry" in rows
    sm = float(rows["scan matching"].split()[4])
    odom = float(rows["raw odometry"].split()[4])
    # The simulated walls are lines: matching alone already beats 10 %/m odometry by far.
    assert sm < 0.2 * odom, (sm, odom)
