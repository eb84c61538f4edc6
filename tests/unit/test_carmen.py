"""Tests for the CARMEN log parser (lrfslam.io.carmen) and open_log."""

from __future__ import annotations

import bz2
import gzip
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lrfslam.algo.geometry import beam_angles
from lrfslam.errors import ConfigError, InputError
from lrfslam.io.carmen import (
    CARMEN_FLASER_MAX_RANGE_M,
    CarmenIssue,
    CarmenLineError,
    CarmenReader,
    LaserRecord,
    OdomRecord,
    flaser_beam_geometry,
    iter_records,
    laser_trajectory,
    parse_line,
)
from lrfslam.io.textfile import open_log

DATA = Path(__file__).resolve().parents[1] / "data"


def flaser_line(name, ranges, laser=(0.0, 0.0, 0.0), odom=(0.0, 0.0, 0.0), stamp=1.5, logger=0.5):
    values = " ".join(f"{r:.2f}" for r in ranges)
    poses = " ".join(f"{v:.6f}" for v in (*laser, *odom))
    return f"{name} {len(ranges)} {values} {poses} {stamp:.6f} nohost {logger:.6f}"


# --- FLASER beam geometry -------------------------------------------------------


@pytest.mark.parametrize(
    ("n", "step_deg", "last_deg"),
    [(180, 1.0, 89.0), (181, 1.0, 90.0), (360, 0.5, 89.5), (361, 0.5, 90.0), (400, 0.25, 9.75), (5, 45.0, 90.0)],
)
def test_flaser_beam_geometry_follows_carmen_table(n, step_deg, last_deg):
    line = flaser_line("FLASER", [1.0] * n)
    rec = parse_line(line, 7)
    assert isinstance(rec, LaserRecord)
    assert rec.n_beams == n
    assert rec.angle_min_rad == pytest.approx(-math.pi / 2)
    assert rec.angle_increment_rad == pytest.approx(math.radians(step_deg))
    angles = beam_angles(rec.n_beams, rec.angle_min_rad, rec.angle_increment_rad)
    assert angles[-1] == pytest.approx(math.radians(last_deg))


def test_flaser_beam_geometry_rejects_too_few_beams():
    with pytest.raises(InputError):
        flaser_beam_geometry(1)


def test_flaser_fields_land_in_the_right_places():
    line = flaser_line(
        "FLASER", [0.5, 81.83, 79.99, 80.0], laser=(1.0, 2.0, 0.3), odom=(4.0, 5.0, -0.6), stamp=976052857.337530
    )
    rec = parse_line(line, 3)
    assert rec.source == "FLASER"
    assert rec.line_no == 3
    assert rec.stamp_s == 976052857.337530
    assert rec.logger_stamp_s == 0.5
    np.testing.assert_array_equal(rec.ranges_m, [0.5, np.inf, 79.99, np.inf])
    np.testing.assert_array_equal(rec.laser_pose, [1.0, 2.0, 0.3])
    np.testing.assert_array_equal(rec.odom_pose, [4.0, 5.0, -0.6])
    assert rec.max_range_m == CARMEN_FLASER_MAX_RANGE_M
    with pytest.raises(ValueError):
        rec.ranges_m[0] = 1.0  # read-only


def test_no_return_threshold_override():
    line = flaser_line("FLASER", [49.99, 50.0, 3.0])
    assert np.isfinite(parse_line(line).ranges_m[1])
    rec = parse_line(line, no_return_min_m=50.0)
    np.testing.assert_array_equal(rec.ranges_m, [49.99, np.inf, 3.0])
    with pytest.raises(ConfigError):
        CarmenReader([line], no_return_min_m=0.0)


# --- the hand-made mixed fixture ---------------------------------------------------


def read_fixture():
    with open_log(DATA / "carmen_mixed.clf") as f:
        reader = CarmenReader(f)
        return reader, list(reader)


def test_mixed_fixture_order_records_and_issues():
    reader, items = read_fixture()
    kinds = [(type(i).__name__, i.line_no) for i in items]
    assert kinds == [
        ("OdomRecord", 3),
        ("LaserRecord", 4),
        ("CarmenIssue", 7),
        ("CarmenIssue", 8),
        ("LaserRecord", 9),
        ("OdomRecord", 10),
        ("LaserRecord", 11),
        ("CarmenIssue", 12),
        ("CarmenIssue", 14),
        ("CarmenIssue", 15),
        ("CarmenIssue", 16),
    ]
    assert reader.skipped == {"#": 2, "PARAM": 1, "": 1, "SYNC": 1, "RAWLASER1": 1}
    assert reader.lines_read == 17


def test_mixed_fixture_issue_reasons():
    _, items = read_fixture()
    issues = {i.line_no: i for i in items if isinstance(i, CarmenIssue)}
    assert "expected 16 tokens" in issues[7].reason and issues[7].message_type == "FLASER"
    assert "not a number" in issues[8].reason and issues[8].message_type == "ODOM"
    assert "negative" in issues[12].reason
    assert "not finite" in issues[14].reason
    assert "num_readings" in issues[15].reason
    assert "expected 10 tokens" in issues[16].reason


def test_mixed_fixture_odom():
    _, items = read_fixture()
    odom = items[0]
    assert odom == OdomRecord(3, 100.25, 1.0, 2.0, 0.5, 0.1, -0.2, 0.3, 0.25)
    np.testing.assert_array_equal(odom.pose, [1.0, 2.0, 0.5])
    # file order is kept although this ODOM's stamp (100.2) is older than the scan before it
    assert items[5].stamp_s == 100.2


def test_mixed_fixture_flaser_and_rlaser():
    _, items = read_fixture()
    front, rear = items[1], items[6]
    np.testing.assert_array_equal(front.ranges_m, [1.0, 2.0, np.inf, 3.0, np.inf])
    assert front.angle_increment_rad == pytest.approx(math.pi / 4)
    np.testing.assert_array_equal(front.laser_pose, [1.1, 2.0, 0.5])
    np.testing.assert_array_equal(front.odom_pose, [1.0, 2.0, 0.5])
    assert rear.source == "RLASER"
    assert rear.angle_increment_rad == pytest.approx(math.pi / 2)
    np.testing.assert_array_equal(rear.ranges_m, [0.5, 0.6, 0.7])


def test_mixed_fixture_robotlaser1():
    _, items = read_fixture()
    rec = items[4]
    assert rec.source == "ROBOTLASER1"
    assert rec.stamp_s == 100.6 and rec.logger_stamp_s == 0.6
    assert rec.angle_min_rad == -1.5708 and rec.angle_increment_rad == 0.7854
    # the line's maximum_range (50 m) is the no-return threshold
    assert rec.max_range_m == 50.0
    np.testing.assert_array_equal(rec.ranges_m, [0.5, 1.5, np.inf, 2.5, np.inf])
    np.testing.assert_array_equal(rec.laser_pose, [1.2, 2.0, 0.5])
    np.testing.assert_array_equal(rec.odom_pose, [1.0, 2.0, 0.5])


def test_robotlaser_token_count_and_max_range_checks():
    good = "ROBOTLASER2 0 -1.0 2.0 1.0 8.0 0.01 0 3 1.0 9.0 2.0 0 0 0 0 0 0 0 0 0 0 0 0 5.0 h 1.0"
    rec = parse_line(good)
    assert rec.source == "ROBOTLASER2"
    np.testing.assert_array_equal(rec.ranges_m, [1.0, np.inf, 2.0])
    with pytest.raises(CarmenLineError, match="expected 27 tokens"):
        parse_line(good.replace(" 5.0 h", " 5.0 extra h"), 9)
    with pytest.raises(CarmenLineError, match="maximum_range"):
        parse_line(good.replace(" 8.0 ", " 0.0 "))
    with pytest.raises(CarmenLineError, match="does not fit"):
        parse_line("ROBOTLASER1 0 -1.0 2.0 1.0 8.0 0.01 0 300 1.0 2.0")


def test_laser_trajectory_picks_requested_pose():
    _, items = read_fixture()
    stamps, odom = laser_trajectory(items)
    np.testing.assert_array_equal(stamps, [100.3, 100.6, 100.8])
    np.testing.assert_array_equal(odom[:, 0], [1.0, 1.0, 0.0])
    _, laser = laser_trajectory(items, pose="laser")
    np.testing.assert_array_equal(laser[:, 0], [1.1, 1.2, 0.0])
    assert laser_trajectory([])[1].shape == (0, 3)


def test_single_string_input_and_non_text_lines():
    items = list(iter_records("# c\nODOM 0 0 0 0 0 0 1.0 h 2.0\n"))
    assert [type(i) for i in items] == [OdomRecord]
    assert items[0].line_no == 2
    (issue,) = list(iter_records([b"ODOM 0 0 0 0 0 0 1.0 h 2.0"]))
    assert issue == CarmenIssue(1, "", "expected str, got bytes")


@pytest.mark.parametrize("suffix", ["", ".bz2", ".gz"])
def test_open_log_handles_compression(tmp_path, suffix):
    text = (DATA / "carmen_mixed.clf").read_bytes()
    path = tmp_path / f"log{suffix}"
    opener = {"": open, ".bz2": bz2.open, ".gz": gzip.open}[suffix]
    with opener(path, "wb") as f:
        f.write(text)
    with open_log(path) as f:
        assert len(list(iter_records(f))) == 11


# --- properties ------------------------------------------------------------------------

_TOKENS = st.sampled_from(
    [
        "FLASER",
        "RLASER",
        "ODOM",
        "ROBOTLASER1",
        "ROBOTLASER2",
        "0",
        "1",
        "2",
        "3",
        "-1",
        "5",
        "180",
        "1e400",
        "nan",
        "-0.5",
        "81.83",
        "nohost",
        "#",
        "x",
        "1.5",
        "9" * 5000,
        "",
    ]
)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.one_of(st.text(max_size=60), st.lists(_TOKENS, max_size=40).map(" ".join)), max_size=20))
def test_garbage_never_raises(lines):
    reader = CarmenReader(lines)
    items = list(reader)
    assert all(isinstance(i, (LaserRecord, OdomRecord, CarmenIssue)) for i in items)
    numbers = [i.line_no for i in items]
    assert numbers == sorted(set(numbers))
    assert all(1 <= n <= len(lines) for n in numbers)
    assert len(items) + sum(reader.skipped.values()) == len(lines)


@settings(max_examples=100, deadline=None)
@given(
    st.lists(st.floats(0.0, 100.0), min_size=2, max_size=400),
    st.tuples(*[st.floats(-1e3, 1e3)] * 6),
    st.floats(0.0, 2e9),
)
def test_flaser_round_trip(ranges, poses, stamp):
    rounded = np.round(np.array(ranges), 2)
    rec = parse_line(flaser_line("FLASER", rounded, poses[:3], poses[3:], stamp), 1)
    expected = np.where(rounded >= CARMEN_FLASER_MAX_RANGE_M, np.inf, rounded)
    np.testing.assert_allclose(rec.ranges_m, expected, rtol=0, atol=1e-9)
    np.testing.assert_allclose(rec.laser_pose, poses[:3], atol=1e-6)
    np.testing.assert_allclose(rec.odom_pose, poses[3:], atol=1e-6)
    assert rec.stamp_s == pytest.approx(stamp, abs=1e-6)
