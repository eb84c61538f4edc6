"""``lrfslam import carmen``: CARMEN logs into recordings (lrfslam.tools.importers)."""

from __future__ import annotations

import bz2
import math
from pathlib import Path

import numpy as np
import pytest

from lrfslam.algo.geometry import compose
from lrfslam.errors import ConfigError
from lrfslam.evaluation.recording_relations import evaluate_relations
from lrfslam.evaluation.relations import stamp_s
from lrfslam.io.carmen import CarmenReader, LaserRecord
from lrfslam.io.textfile import open_log
from lrfslam.msgs import codec, topics
from lrfslam.msgs import types as t
from lrfslam.runtime.recording import read_metadata, read_recording
from lrfslam.tools import importers, info
from lrfslam.tools.importers import import_carmen, stamp_ns

DATA = Path(__file__).resolve().parents[1] / "data"
HEAD = DATA / "intel_head.clf"
MIXED = DATA / "carmen_mixed.clf"


def decoded(path, topic):
    """Decoded messages of ``topic`` with their MCAP log times, in read order."""
    return [(topic.codec.decode(r.data, r.schema), r.log_time_ns, r.schema)
            for r in read_recording(path, [topic.name])]


def laser_records(path):
    with open_log(path) as f:
        return [r for r in CarmenReader(f) if isinstance(r, LaserRecord)]


def flaser(ranges, pose, stamp, laser=None):
    values = " ".join(f"{r:.2f}" for r in ranges)
    p = " ".join(f"{v:.6f}" for v in pose)
    lp = p if laser is None else " ".join(f"{v:.6f}" for v in laser)
    return f"FLASER {len(ranges)} {values} {lp} {p} {stamp:.6f} nohost 0.0"


def test_stamp_ns_is_the_logged_decimal_and_converts_back_exactly():
    assert stamp_ns(976052857.337530) == 976052857337530000
    assert stamp_ns(100.3) == 100300000000
    # round(s * 1e9) is off here: the reason stamp_ns exists.
    assert round(976052857.337530 * 1e9) != 976052857337530000
    for s in (976052857.337530, 976052858.861784, 100.3, 0.0):
        assert stamp_s(stamp_ns(s)) == s


def test_intel_head_scans_and_odometry(tmp_path):
    out = tmp_path / "head.mcap"
    result = import_carmen(HEAD, out, robot="intel")
    records = laser_records(HEAD)
    assert (result.scans, result.odom, result.issues, result.stamp_backsteps) == (10, 10, (), 0)
    assert result.skipped == {"#": 9, "PARAM": 2, "ODOM": 19}

    scans = decoded(out, topics.SCAN)
    odoms = decoded(out, topics.ODOM)
    assert len(scans) == len(odoms) == len(records) == 10
    for i, ((scan, log_ns, schema), (odom, odom_log_ns, _), rec) in enumerate(zip(scans, odoms, records)):
        assert schema == codec.LASER_SCAN.schema
        assert scan.seq == odom.seq == i + 1
        assert scan.stamp_ns == odom.stamp_ns == log_ns == odom_log_ns == stamp_ns(rec.stamp_s)
        assert stamp_s(scan.stamp_ns) == rec.stamp_s
        # The schema stores ranges and angles as float32 (sub-micrometre rounding).
        np.testing.assert_array_equal(scan.ranges_m, rec.ranges_m.astype(np.float32))
        np.testing.assert_array_equal(scan.status, np.where(np.isinf(rec.ranges_m), t.BEAM_NO_RETURN, t.BEAM_VALID))
        assert (scan.angle_min_rad, scan.angle_increment_rad) == (np.float32(-math.pi / 2), np.float32(math.radians(1)))
        assert scan.source == "carmen:FLASER" and scan.range_max_m == np.float32(81.83)  # the log's code
        np.testing.assert_array_equal(odom.pose, rec.odom_pose)
    first = scans[0][0]
    assert first.ranges_m[89] == math.inf and first.status[89] == t.BEAM_NO_RETURN  # logged as 81.83
    assert read_metadata(out)["lrfslam"] == {
        "robot": "intel", "importer": importers.IMPORTER, "source_file": "intel_head.clf",
        "beams": "180 beams at 1.00 deg from -90.0 deg (10 lines)", "no_return_m": "81.83",
        "no_return_from": "the log: 7.94 % of readings are exactly this value", "laser_mount": "0.0000 0.0000 0.00000"}


def test_compressed_log_gives_the_same_messages(tmp_path):
    packed = tmp_path / "head.clf.bz2"
    packed.write_bytes(bz2.compress(HEAD.read_bytes()))
    import_carmen(HEAD, tmp_path / "plain.mcap")
    import_carmen(packed, tmp_path / "packed.mcap")
    plain = [(r.topic, r.data, r.log_time_ns) for r in read_recording(tmp_path / "plain.mcap")]
    assert plain == [(r.topic, r.data, r.log_time_ns) for r in read_recording(tmp_path / "packed.mcap")]


def test_mixed_log_reports_malformed_lines_and_skips_them(tmp_path, capsys):
    out = tmp_path / "mixed.mcap"
    assert importers.main(["carmen", str(MIXED), "-o", str(out), "--quiet"]) == 0
    captured = capsys.readouterr()
    reported = [line.split(":")[0] for line in captured.err.splitlines()]
    assert reported == ["line 7", "line 8", "line 12", "line 14", "line 15", "line 16"]
    assert "3 scans, 3 odom" in captured.out and "6 malformed" in captured.out

    scans = [s for s, _, _ in decoded(out, topics.SCAN)]
    assert [s.source for s in scans] == ["carmen:FLASER", "carmen:ROBOTLASER1", "carmen:RLASER"]
    assert [s.stamp_ns for s in scans] == [100_300_000_000, 100_600_000_000, 100_800_000_000]
    assert [s.seq for s in scans] == [1, 2, 3]
    # FLASER line 4: 81.83 and 80.00 are no returns; ROBOTLASER1 line 9 uses its 50 m maximum range.
    np.testing.assert_array_equal(scans[0].ranges_m, np.float32([1.0, 2.0, np.inf, 3.0, np.inf]))
    np.testing.assert_array_equal(scans[0].status, [0, 0, t.BEAM_NO_RETURN, 0, t.BEAM_NO_RETURN])
    np.testing.assert_array_equal(scans[1].ranges_m, np.float32([0.5, 1.5, np.inf, 2.5, np.inf]))
    assert scans[1].angle_increment_rad == np.float32(0.7854)
    odoms = [o for o, _, _ in decoded(out, topics.ODOM)]
    np.testing.assert_array_equal([o.pose for o in odoms], [[1.0, 2.0, 0.5], [1.0, 2.0, 0.5], [0.0, 0.0, 3.0]])


def test_only_the_first_issues_are_printed_then_a_count(tmp_path, capsys):
    log = tmp_path / "bad.clf"
    good = flaser([1.0, 2.0, 3.0], (0, 0, 0), 5.0)
    log.write_text("\n".join([good] + ["FLASER x"] * (importers.MAX_REPORTED_ISSUES + 3)) + "\n")
    assert importers.main(["carmen", str(log), "-o", str(tmp_path / "bad.mcap"), "-q"]) == 0
    err = capsys.readouterr().err.splitlines()
    assert len(err) == importers.MAX_REPORTED_ISSUES + 1
    assert err[0].startswith("line 2:") and err[-1] == "... and 3 more malformed lines (skipped)"


def test_backward_stamps_keep_their_stamp_and_file_order_seq(tmp_path):
    log = tmp_path / "back.clf"
    log.write_text("\n".join([
        flaser([1.0, 1.0], (0.0, 0.0, 0.0), 10.0),
        flaser([1.0, 1.0], (0.1, 0.0, 0.0), 10.2),
        flaser([1.0, 1.0], (0.2, 0.0, 0.0), 9.9),   # stamp runs backwards; pose continues
        flaser([1.0, 1.0], (0.3, 0.0, 0.0), 10.4),
        flaser([1.0, 1.0], (0.4, 0.0, 0.0), -1.0),  # negative stamp: cannot be an MCAP log time
    ]) + "\n")
    result = import_carmen(log, tmp_path / "back.mcap")
    assert result.scans == 4 and result.stamp_backsteps == 1
    assert [(i.line_no, i.reason) for i in result.issues] == [(5, "negative timestamp -1.0")]
    odoms = [o for o, _, _ in decoded(tmp_path / "back.mcap", topics.ODOM)]
    # Read back in log-time (stamp) order; each stamp keeps its own line's seq and pose.
    assert [(o.stamp_ns, o.seq, o.pose[0]) for o in odoms] == [
        (9_900_000_000, 3, 0.2), (10_000_000_000, 1, 0.0), (10_200_000_000, 2, 0.1), (10_400_000_000, 4, 0.3)]


def test_max_range_sets_the_no_return_threshold(tmp_path):
    import_carmen(MIXED, tmp_path / "m.mcap", no_return_min_m=2.5)
    first = decoded(tmp_path / "m.mcap", topics.SCAN)[0][0]
    np.testing.assert_array_equal(first.ranges_m, np.float32([1.0, 2.0, np.inf, np.inf, np.inf]))
    assert first.range_max_m == 2.5
    meta = read_metadata(tmp_path / "m.mcap")["lrfslam"]
    assert (meta["no_return_m"], meta["no_return_from"]) == ("2.5", "--max-range-m")


def test_bad_arguments_fail_cleanly(tmp_path, capsys):
    with pytest.raises(ConfigError):
        import_carmen(HEAD, tmp_path / "x.mcap", robot="a/b")
    assert importers.main(["carmen", str(tmp_path / "missing.clf"), "-o", str(tmp_path / "x.mcap")]) == 2
    assert "missing.clf" in capsys.readouterr().err
    assert importers.main(["carmen", str(HEAD), "-o", str(tmp_path / "x.mcap"), "--max-range-m", "0"]) == 2


INTEL = Path(__file__).resolve().parents[2].parent / "shared" / "datasets" / "intel"


@pytest.mark.skipif(not (INTEL / "intel.clf.bz2").is_file() or not (INTEL / "intel.relations").is_file(),
                    reason="Intel dataset not present")
@pytest.mark.slow   # end to end, long: the slow step (.ci/run step 3)
def test_intel_import_reproduces_the_odometry_baseline(tmp_path):
    """Imported odometry scores as the log's own (7.37 ± 14.35 m), every relation stamp matched exactly."""
    out = tmp_path / "intel.mcap"
    result = import_carmen(INTEL / "intel.clf.bz2", out)
    assert (result.scans, result.issues, result.stamp_backsteps) == (13631, (), 631)
    results, undecodable = evaluate_relations(out, INTEL / "intel.relations")
    odom = results["raw odometry"]
    assert undecodable == 0 and "slam estimate" not in results
    assert (odom.n_used, odom.max_match_gap_s) == (2984, 0.0)
    assert odom.trans_abs_m.mean == pytest.approx(7.37, abs=0.005)
    assert odom.trans_abs_m.std == pytest.approx(14.35, abs=0.005)


def test_the_no_return_code_is_read_from_the_log_not_its_name(tmp_path):
    # A 50 m code as ACES writes it, in a file named like nothing known.
    rng = np.random.default_rng(3)
    lines = [flaser(np.where(rng.random(180) < 0.05, 50.0, rng.uniform(0.5, 20.0, 180)), (0.1 * k, 0.0, 0.0),
                    10.0 + 0.1 * k) for k in range(20)]
    log = tmp_path / "building.clf"
    log.write_text("\n".join(lines) + "\n")
    result = import_carmen(log, tmp_path / "b.mcap")
    assert result.sensor["no_return_m"] == "50.0" and result.sensor["no_return_from"].startswith("the log")
    assert result.sensor["beams"].startswith("180 beams at 1.00 deg from -90.0 deg")
    for scan, _, _ in decoded(tmp_path / "b.mcap", topics.SCAN):
        assert np.all(np.isinf(scan.ranges_m) == (scan.status == t.BEAM_NO_RETURN))
        assert np.all(scan.ranges_m[np.isfinite(scan.ranges_m)] <= 20.0)
    assert read_metadata(tmp_path / "b.mcap")["lrfslam"]["no_return_m"] == "50.0"


def test_a_code_written_with_jitter_is_no_return_across_its_band(tmp_path):
    # As MIT Killian writes it: mostly 51.06 m, the rest of the band 51.01-51.22 m round it, a real
    # return at 50.9 m just below the band, and the band's top (51.22) once: not the code.
    rng = np.random.default_rng(5)
    band = np.array([51.01, 51.05, 51.06, 51.06, 51.06, 51.06, 51.07, 51.11])
    lines = []
    for k in range(30):
        ranges = rng.uniform(0.5, 20.0, 180)
        ranges[rng.random(180) < 0.1] = rng.choice(band)
        ranges[0] = 50.9
        ranges[1] = 51.22 if k == 7 else ranges[1]
        lines.append(flaser(ranges, (0.1 * k, 0.0, 0.0), 10.0 + 0.1 * k))
    log = tmp_path / "killian.clf"
    log.write_text("\n".join(lines) + "\n")
    result = import_carmen(log, tmp_path / "k.mcap")
    assert result.sensor["no_return_m"] == "51.01"
    assert "round the code 51.06 m" in result.sensor["no_return_from"]
    for scan, _, _ in decoded(tmp_path / "k.mcap", topics.SCAN):
        finite = scan.ranges_m[np.isfinite(scan.ranges_m)]
        assert np.all(finite < 51.0) and scan.ranges_m[0] == pytest.approx(50.9)   # float32 on the wire
        assert np.all(np.isinf(scan.ranges_m) == (scan.status == t.BEAM_NO_RETURN))


def test_a_log_without_a_repeated_maximum_keeps_carmens_rule(tmp_path):
    log = tmp_path / "plain.clf"
    log.write_text("\n".join(flaser([1.0 + 0.01 * k, 2.0, 3.0], (0.0, 0.0, 0.0), 1.0 + k) for k in range(5)) + "\n")
    assert import_carmen(log, tmp_path / "p.mcap").sensor["no_return_m"] == ""


def test_the_laser_mounting_moves_the_odometry_to_the_laser(tmp_path):
    # Laser 0.3 m ahead of and 0.1 m left of the robot centre, turned 0.05 rad, as the lines' poses say.
    mount = np.array([0.3, 0.1, 0.05])
    poses = [np.array([k * 0.2, 0.05 * k, 0.1 * k]) for k in range(6)]
    lines = [flaser([1.0, 2.0], pose, 1.0 + k, laser=compose(pose, mount)) for k, pose in enumerate(poses)]
    log = tmp_path / "mounted.clf"
    log.write_text("\n".join(lines) + "\n")
    result = import_carmen(log, tmp_path / "m.mcap")
    np.testing.assert_allclose([float(v) for v in result.sensor["laser_mount"].split()], mount, atol=1e-4)
    odoms = [o.pose for o, _, _ in decoded(tmp_path / "m.mcap", topics.ODOM)]
    np.testing.assert_allclose(odoms, [compose(p, mount) for p in poses], atol=1e-5)


def test_the_front_laser_offset_parameter_applies_when_the_lines_do_not(tmp_path):
    lines = ["PARAM robot_frontlaser_offset 0.25 nohost 0"]
    lines += [flaser([1.0, 2.0], (0.0, 0.0, 0.5 * k), 1.0 + k) for k in range(3)]
    log = tmp_path / "param.clf"
    log.write_text("\n".join(lines) + "\n")
    import_carmen(log, tmp_path / "p.mcap")
    odoms = [o.pose for o, _, _ in decoded(tmp_path / "p.mcap", topics.ODOM)]
    np.testing.assert_allclose(odoms, [compose((0.0, 0.0, 0.5 * k), (0.25, 0.0, 0.0)) for k in range(3)],
                               atol=1e-9)


def test_info_shows_what_the_log_says_of_its_laser(tmp_path):
    out = tmp_path / "head.mcap"
    import_carmen(HEAD, out)
    text = info.describe(out)
    assert "laser:     180 beams, 1.00 deg apart, -90.0 to +89.0 deg, range max 81.83 m" in text
    assert "no return (m): 81.83" in text and "laser mount (x m, y m, theta rad): 0.0000 0.0000 0.00000" in text


def test_range_noise_must_not_be_negative(tmp_path):
    with pytest.raises(ConfigError, match="range_noise_m"):
        import_carmen(HEAD, tmp_path / "noisy.mcap", range_noise_m=-1e-6)
    assert not (tmp_path / "noisy.mcap").exists()
