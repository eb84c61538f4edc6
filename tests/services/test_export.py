"""Map export: JSON, the occupancy grid as map_server files, and a PNG, on the simulator and on Intel.

The simulator knows its walls: the grid ``lrfslam export`` writes, read back as ROS
map_server reads it and placed in the world by the first true pose, must have its
occupied cells on those walls and its free cells in the corridors.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from lrfslam.services import stage
from test_mapper import GRID_AGREEMENT, occupied_near
from test_steps import chain, sim_outputs

from lrfslam.algo.geometry import from_frame
from lrfslam.algo.occupancy_grid import GridParams, fitting_resolution
from lrfslam.errors import InputError
from lrfslam.evaluation.map_trajectory import final_trajectory
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.msgs.grid_replica import GridReplica
from lrfslam.runtime.chain import Chain
from lrfslam.runtime.recording import RecordingWriter, read_recording
from lrfslam.sim import SimConfig, Simulator
from lrfslam.sim.odometry import OdometryNoise
from lrfslam.sim.world import distance_to_segments, inside_polygons
from lrfslam.tools import export, recording_map
from lrfslam.tools.importers import import_carmen
from lrfslam.tools.pipeline import DEFAULT_STAGES, build_stages, run_pipeline

T0_NS = 1_000_000_000_000
N_SCANS = 300   # 30 s: 15 m of the hallway loop and its first turn
ROOT = Path(__file__).resolve().parents[2]
INTEL_150 = ROOT / "tests" / "data" / "golden" / "intel_150.pipeline.mcap"
INTEL_LOG = ROOT.parent / "shared" / "datasets" / "intel" / "intel.clf.bz2"


def read_map_server(yaml_path: Path) -> tuple[dict, np.ndarray]:
    """The map as ROS map_server loads it: the YAML, and the cells (H, W), row 0 the lowest y: 100 / 0 / -1.

    map_server reads a trinary image pixel by pixel: p = (255 - value) / 255 (negate 0),
    occupied when p > occupied_thresh, free when p < free_thresh, unknown otherwise; the
    image's last row is the row at ``origin``.
    """
    meta = yaml.safe_load(yaml_path.read_text())
    data = (yaml_path.parent / meta["image"]).read_bytes()
    fields, pos = [], 0
    while len(fields) < 4:   # magic, width, height, maxval; '#' comments run to the end of their line
        while data[pos:pos + 1].isspace():
            pos += 1
        if data[pos:pos + 1] == b"#":
            pos = data.index(b"\n", pos) + 1
            continue
        end = pos
        while not data[end:end + 1].isspace():
            end += 1
        fields.append(data[pos:end].decode("ascii"))
        pos = end
    magic, w, h, maxval = fields[0], int(fields[1]), int(fields[2]), int(fields[3])
    assert magic == "P5" and maxval == 255
    pixels = np.frombuffer(data[pos + 1:], dtype=np.uint8)
    assert pixels.size == w * h
    p = (255 - pixels.reshape(h, w).astype(float)) / 255.0
    if meta["negate"]:
        p = 1.0 - p
    cells = np.full((h, w), -1, dtype=np.int8)
    cells[p > meta["occupied_thresh"]] = 100
    cells[p < meta["free_thresh"]] = 0
    return meta, np.flipud(cells)


def cell_centres(meta: dict, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Map-frame centres (K, 2) of cells, from the YAML's origin and resolution (yaw 0)."""
    assert meta["origin"][2] == 0.0
    return np.array(meta["origin"][:2]) + meta["resolution"] * (np.column_stack((cols, rows)) + 0.5)


def write(writer: RecordingWriter, topic, value) -> None:
    writer.write(topic.name, topic.schema, topic.codec.encode(value), value.stamp_ns, value.stamp_ns, value.seq)


@pytest.fixture(scope="module")
def sim_run(tmp_path_factory):
    """(pipeline output, export folder, simulator): 300 scans with a poor odometry, run by every stage, exported."""
    root = tmp_path_factory.mktemp("export")
    sim = Simulator(SimConfig(seed=3, odometry=OdometryNoise(0.1, 0.1, 0.02)))
    lidar = sim.config.lidar
    recording = root / "sim.mcap"
    with RecordingWriter(recording) as writer:
        for frame in itertools.islice(sim, N_SCANS):
            stamp, seq = T0_NS + round(frame.t_s * 1e9), frame.index + 1
            ids = frame.visible_corner_ids
            write(writer, topics.ODOM, t.Odometry(stamp_ns=stamp, seq=seq, pose=frame.odom_pose))
            write(writer, topics.TRUTH, t.GroundTruth(stamp_ns=stamp, seq=seq, pose=frame.true_pose, corner_ids=ids,
                                                      corners_xy_m=sim.map_corners.xy_m[ids]))
            write(writer, topics.SCAN, t.LaserScan.from_ranges(stamp, seq, frame.scan.ranges_m, lidar.angle_min_rad,
                                                              lidar.angle_increment_rad, lidar.max_range_m))
    out = root / "run.mcap"
    run_pipeline(build_stages(DEFAULT_STAGES, [], {}, {}), "r1", recording, out)
    assert export.main([str(out), "-o", str(root / "map")]) == 0
    return out, root / "map", sim


def test_export_writes_json_and_png(tmp_path, capsys):
    outs = sim_outputs(40)
    slam = [m for m in Chain([stage("slam")], robot="r1").feed(chain(outs))]   # states and whole maps
    states = [m.value for m in slam if m.topic is topics.SLAM_STATE]
    path = tmp_path / "r.mcap"
    with RecordingWriter(path) as w:
        for o in [o for o in outs if o.topic in (topics.TRUTH, topics.ODOM)] + slam:
            w.write(o.topic.name, o.topic.schema, o.topic.codec.encode(o.value), o.value.stamp_ns)
    assert export.main([str(path), "-o", str(tmp_path / "out")]) == 0
    doc = json.loads((tmp_path / "out" / "map.json").read_text())
    last, final_map = states[-1], slam[-1].value
    assert slam[-1].topic is topics.SLAM_MAP and final_map.state_seq == last.seq   # the last state's whole map
    assert [lm["id"] for lm in doc["landmarks"]] == final_map.landmarks.ids.tolist()
    assert [lm["x_m"] for lm in doc["landmarks"]] == final_map.landmarks.xy_m[:, 0].tolist()
    assert len(doc["trajectory"]) == len(states)
    np.testing.assert_allclose([doc["trajectory"][-1][k] for k in ("x_m", "y_m", "theta_rad")], last.pose)
    png = (tmp_path / "out" / "map.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
    # No scans recorded: no grid, and one line saying so.
    assert not (tmp_path / "out" / "map.pgm").exists()
    assert "no scan messages" in capsys.readouterr().err


def test_ellipse_is_the_95_percent_contour():
    cov = np.array([[4.0, 0.0], [0.0, 1.0]])
    pts = export.ellipse(np.zeros(2), cov)
    d2 = np.einsum("ni,ij,nj->n", pts, np.linalg.inv(cov), pts)
    np.testing.assert_allclose(d2, export.CHI2_2D_95)


def test_the_grid_files_read_as_map_server_reads_them(sim_run):
    out, folder, _ = sim_run
    meta, cells = read_map_server(folder / "map.yaml")
    assert set(meta) == {"image", "mode", "resolution", "origin", "negate", "occupied_thresh", "free_thresh"}
    assert (meta["image"], meta["mode"], meta["resolution"], meta["negate"]) == ("map.pgm", "trinary", 0.05, 0)
    assert (meta["occupied_thresh"], meta["free_thresh"]) == (0.65, 0.196)
    # The same grid, built again: its shape, origin and every cell are what the files say.
    sc = recording_map.scene(out, recording_map.collect(out), GridParams())
    np.testing.assert_array_equal(cells, recording_map.trinary(sc.grid))
    np.testing.assert_allclose(meta["origin"], [*sc.grid.origin_xy_m, 0.0], atol=1e-9)
    fig = json.loads((folder / "map.json").read_text())["figures"]
    assert fig["grid_cells"] == [cells.shape[1], cells.shape[0]]
    assert fig["occupied_cells"] == np.count_nonzero(cells == 100) and fig["free_cells"] == np.count_nonzero(cells == 0)
    # Only the three map_saver values appear in the image.
    pgm = (folder / "map.pgm").read_bytes()
    assert set(np.unique(np.frombuffer(pgm[-cells.size:], np.uint8)).tolist()) == {0, 205, 254}


def test_the_grid_is_built_on_the_mappers_final_trajectory(sim_run):
    out, folder, _ = sim_run
    doc = json.loads((folder / "map.json").read_text())
    stamps, poses = final_trajectory(out)
    assert doc["figures"]["trajectory"] == "mapper's final trajectory"
    assert [p["stamp_ns"] for p in doc["map_trajectory"]] == stamps.tolist()
    np.testing.assert_allclose([[p["x_m"], p["y_m"], p["theta_rad"]] for p in doc["map_trajectory"]], poses)
    # The grid: the scans of the graph's keyframes (the last map/keyframes), every one recorded.
    graph = [topics.MAP_KEYFRAMES.codec.decode(m.data, m.schema)
             for m in read_recording(out, [topics.MAP_KEYFRAMES.name])][-1]
    assert doc["figures"]["scans_placed"] == graph.scan_stamp_ns.size < N_SCANS
    # Measured 0.025 m for the estimate and 0.46 m for this poor odometry.
    assert doc["figures"]["rmse_vs_truth_m"] < 0.1 < doc["figures"]["odometry_rmse_vs_truth_m"]


def test_the_live_grid_ends_as_the_map_export_draws_from_the_recording(sim_run):
    """The recording's map/grid messages put together, against export's map.pgm as map_server reads it:
    every occupied cell within one cell of an occupied cell of the other, but at most 1 %."""
    out, folder, _ = sim_run
    replica = GridReplica()
    for m in read_recording(out, [topics.MAP_GRID.name]):
        replica.apply(topics.MAP_GRID.codec.decode(m.data, m.schema))
    live = replica.image()
    meta, cells = read_map_server(folder / "map.yaml")
    assert meta["resolution"] == live.resolution_m and replica.pending == 0
    origin = np.array(meta["origin"][:2])
    assert occupied_near(live.cells, live.origin_xy_m, live.resolution_m, cells, origin) >= GRID_AGREEMENT
    assert occupied_near(cells, origin, live.resolution_m, live.cells, live.origin_xy_m) >= GRID_AGREEMENT
    assert (live.cells == 100).sum() > 100


def fit_to_truth(estimate_xy: np.ndarray, truth_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation (2, 2) and translation (2,) that best map the estimate's positions onto the truth's (least squares)."""
    me, mt = estimate_xy.mean(axis=0), truth_xy.mean(axis=0)
    u, _, vt = np.linalg.svd((estimate_xy - me).T @ (truth_xy - mt))
    rot = vt.T @ np.diag([1.0, np.sign(np.linalg.det(vt.T @ u.T))]) @ u.T
    return rot, mt - rot @ me


def test_occupied_cells_lie_on_the_true_walls_and_free_cells_in_the_corridors(sim_run):
    out, folder, sim = sim_run
    meta, cells = read_map_server(folder / "map.yaml")
    doc = json.loads((folder / "map.json").read_text())
    truth = {g.stamp_ns: g.pose for g in (topics.TRUTH.codec.decode(r.data, r.schema)
                                          for r in read_recording(out, [topics.TRUTH.name]))}
    # The map is placed in the world by its trajectory's best fit to the truth (fitted: 0.6 cm
    # RMSE), not by the first pose alone, whose 0.26° heading error moves the far walls by 7 cm:
    # that is the estimate's error, and this is the grid's test.
    est = np.array([[p["x_m"], p["y_m"]] for p in doc["map_trajectory"]])
    rot, shift = fit_to_truth(est, np.array([truth[p["stamp_ns"]][:2] for p in doc["map_trajectory"]]))
    walls = sim.world.opaque_segments_m
    res = meta["resolution"]
    occupied = cell_centres(meta, *np.nonzero(cells == 100)) @ rot.T + shift
    free = cell_centres(meta, *np.nonzero(cells == 0)) @ rot.T + shift
    assert len(occupied) > 800 and len(free) > 10_000
    # Measured: occupied cells 99.4 % within one cell of a wall, 99.9 % within two; free cells 0.3 %
    # within half a cell of a wall (a cell the wall crosses), 99.99 % in the corridors.
    to_wall = distance_to_segments(occupied, walls) / res
    assert np.mean(to_wall <= 2) >= 0.95 and np.mean(to_wall <= 1) >= 0.9
    assert np.mean(distance_to_segments(free, walls) < 0.5 * res) <= 0.02
    assert np.mean(inside_polygons(free, walls)) >= 0.995
    # The corner landmarks, as placed on the map, sit on the true corners (measured: 2.2 cm at most;
    # 3.1 cm where the EKF has them).
    corners = np.array([lm["map_xy_m"] for lm in doc["landmarks"] if lm["kind"] == "forward"]) @ rot.T + shift
    true = sim.world.corners().xy_m
    assert len(corners) >= 5
    assert np.max(np.min(np.linalg.norm(corners[:, None] - true[None], axis=2), axis=1)) < 0.05


def test_the_picture_fits_the_map_not_the_odometry(sim_run):
    out, _, _ = sim_run
    sc = recording_map.scene(out, recording_map.collect(out), GridParams())
    x0, x1, y0, y1 = sc.view
    lo, hi = sc.estimate[:, :2].min(axis=0), sc.estimate[:, :2].max(axis=0)
    assert x0 < lo[0] and hi[0] < x1 and y0 < lo[1] and hi[1] < y1
    gx0, gx1, gy0, gy1 = sc.grid.extent_m
    assert gx0 - 1.0 <= x0 and x1 <= gx1 + 1.0 and gy0 - 1.0 <= y0 and y1 <= gy1 + 1.0
    far = dataclasses.replace(sc, odometry=sc.odometry + (100.0, -50.0, 0.0))
    assert recording_map.view_limits(far) == sc.view
    # Ellipses of a centimetre are magnified, and the title carries the figures.
    assert export.ellipse_scale(sc) > 1
    assert f"{out.name}: {N_SCANS} scans" in export.title(sc) and "RMSE vs truth 0.0" in export.title(sc)


def test_resolution_layers_and_no_grid(sim_run, tmp_path):
    out, folder, _ = sim_run
    assert export.main([str(out), "-o", str(tmp_path / "coarse"), "--resolution", "0.1", "--no-png"]) == 0
    meta, cells = read_map_server(tmp_path / "coarse" / "map.yaml")
    _, fine = read_map_server(folder / "map.yaml")
    assert meta["resolution"] == 0.1 and abs(cells.shape[0] * 2 - fine.shape[0]) <= 4   # a margin cell each side
    assert not (tmp_path / "coarse" / "map.png").exists()
    assert export.main([str(out), "-o", str(tmp_path / "bare"), "--no-grid", "--layers", "trajectory,odometry"]) == 0
    assert sorted(p.name for p in (tmp_path / "bare").iterdir()) == ["map.json", "map.png"]
    with pytest.raises(SystemExit):
        export.main([str(out), "-o", str(tmp_path / "x"), "--layers", "walls"])


def test_a_grid_too_large_is_one_line_and_writes_nothing(sim_run, tmp_path):
    out, _, _ = sim_run
    run = subprocess.run([sys.executable, "-m", "lrfslam.cli", "export", str(out), "-o", str(tmp_path / "o"),
                          "--resolution", "0.0005"], capture_output=True, text=True, check=False)
    assert run.returncode == 2 and "Traceback" not in run.stderr
    assert run.stderr.strip().count("\n") == 0 and "exceeds" in run.stderr
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())


def test_a_map_too_large_for_the_default_cells_is_drawn_coarser_and_says_so(sim_run, monkeypatch, capsys):
    out, folder, _ = sim_run
    _, fine = read_map_server(folder / "map.yaml")
    # A cell budget the default 0.05 m grid exceeds, and 0.1 m (a quarter of its cells) fits.
    @dataclasses.dataclass(frozen=True)
    class SmallBudget(GridParams):
        max_cells: int = fine.size // 2

    monkeypatch.setattr(recording_map, "GridParams", SmallBudget)
    data = recording_map.collect(out)
    with pytest.raises(InputError, match="exceeds"):
        recording_map.scene(out, data, SmallBudget())
    sc = recording_map.scene(out, data, SmallBudget(), fit=True)
    assert sc.grid.resolution_m == 0.1 and sc.grid.log_odds.size <= fine.size // 2
    assert export.main([str(out), "-o", str(folder / "fit"), "--no-png"]) == 0
    meta, _ = read_map_server(folder / "fit" / "map.yaml")
    assert meta["resolution"] == 0.1
    assert "grid at 0.1 m (--resolution sets it)" in capsys.readouterr().out


def test_the_fitting_resolution_is_the_finest_doubling_that_fits():
    p = GridParams(resolution_m=0.05, max_cells=10_000)
    # 10 x 10 m: 203 x 203 cells at 0.05, 103 x 103 at 0.1 m, 53 x 53 at 0.2 m (border included).
    assert fitting_resolution(np.zeros(2), np.full(2, 10.0), p) == 0.2
    assert fitting_resolution(np.zeros(2), np.full(2, 1.0), p) == 0.05


def placed_hits(path: Path, stamps: np.ndarray, poses: np.ndarray, max_range_m: float) -> np.ndarray:
    """Every return up to ``max_range_m`` of the scans of ``path``, placed at the poses of their stamps; (K, 2)."""
    index = {int(s): i for i, s in enumerate(stamps)}
    points = []
    for rec in read_recording(path, [topics.SCAN.name]):
        scan = topics.SCAN.codec.decode(rec.data, rec.schema)
        if scan.stamp_ns in index:
            ok = (scan.status == t.BEAM_VALID) & (scan.ranges_m <= max_range_m)
            r, a = scan.ranges_m[ok], scan.angles_rad[ok]
            points.append(from_frame(np.column_stack((r * np.cos(a), r * np.sin(a))), poses[index[scan.stamp_ns]]))
    return np.vstack(points)


def check_intel_extent(run_mcap: Path, folder: Path) -> tuple[np.ndarray, np.ndarray]:
    """The grid's occupied cells span the returns of its scans placed on the estimate (the EKF's poses, or the
    mapper's graph's keyframes at theirs); their and the odometry's spans."""
    meta, cells = read_map_server(folder / "map.yaml")
    doc = json.loads((folder / "map.json").read_text())
    stamps = np.array([p["stamp_ns"] for p in doc["map_trajectory"]])
    est = np.array([[p["x_m"], p["y_m"], p["theta_rad"]] for p in doc["map_trajectory"]])
    data = recording_map.collect(run_mcap, scans=False)
    odom = recording_map.in_frame(stamps, est, data["odom"])
    odom_at = dict(zip(sorted(data["odom"]), odom))
    if data["graph"] is not None:   # the grid is the scans of the mapper's graph at their final poses
        stamps, est = data["graph"].scan_stamp_ns, data["graph"].map_pose
    on_est = placed_hits(run_mcap, stamps, est, GridParams.max_range_m)
    on_odom = placed_hits(run_mcap, stamps, np.array([odom_at[int(s)] for s in stamps]), GridParams.max_range_m)
    occ = cell_centres(meta, *np.nonzero(cells == 100))
    span = np.r_[occ.min(axis=0), occ.max(axis=0)]
    res = meta["resolution"]
    # Within 5 cells: an outlying return that one keyframe saw and another's beam crossed is not a
    # wall (measured 0.18 m on Intel's first 1000 scans, 3.6 cells).
    np.testing.assert_allclose(span, np.r_[on_est.min(axis=0), on_est.max(axis=0)], atol=5 * res)
    return span, np.r_[on_odom.min(axis=0), on_odom.max(axis=0)]


def test_intel_head_grid_spans_the_estimate(tmp_path):
    """150 Intel scans (a committed recording, EKF only): the grid spans the returns placed on the EKF's poses."""
    assert export.main([str(INTEL_150), "-o", str(tmp_path), "--no-png"]) == 0
    doc = json.loads((tmp_path / "map.json").read_text())
    assert doc["figures"]["trajectory"] == "EKF trajectory (slam/state)" and doc["figures"]["scans_placed"] == 150
    check_intel_extent(INTEL_150, tmp_path)


@pytest.mark.slow
@pytest.mark.skipif(not INTEL_LOG.is_file(), reason="Intel dataset not present")
def test_intel_grid_follows_the_estimate_not_the_drifting_odometry(tmp_path):
    """The first 1000 Intel scans: odometry ends 20 m off; the grid matches the mapper's trajectory."""
    import bz2
    head = tmp_path / "intel_1000.clf"
    with bz2.open(INTEL_LOG, "rt") as src, head.open("w") as dst:
        n = 0
        for line in src:
            n += line.startswith("FLASER")
            if n > 1000:
                break
            dst.write(line)
    import_carmen(head, tmp_path / "in.mcap")
    run_mcap = tmp_path / "run.mcap"
    run_pipeline(build_stages(DEFAULT_STAGES, [], {}, {}), "intel", tmp_path / "in.mcap", run_mcap)
    assert export.main([str(run_mcap), "-o", str(tmp_path / "map")]) == 0
    span, odom_span = check_intel_extent(run_mcap, tmp_path / "map")
    assert np.max(np.abs(span - odom_span)) > 3.0, (span, odom_span)
    sc = recording_map.scene(run_mcap, recording_map.collect(run_mcap), GridParams())
    x0, x1, y0, y1 = sc.view
    # The picture holds the observed grid, free space too: 2.07 m past the walls' span at most here
    # (beams through an opening), and nowhere near the odometry's 3 m and more.
    assert x0 >= span[0] - 2.5 and x1 <= span[2] + 2.5 and y0 >= span[1] - 2.5 and y1 <= span[3] + 2.5
