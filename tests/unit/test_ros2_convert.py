"""lrfslam's messages as ROS 2 messages and back (src/lrfslam/ros2/convert.py), each through rosbags' CDR
(``serialize_cdr`` / ``deserialize_cdr``, as a ROS 2 node would read it) and compared field by field
with the message it came from."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from lrfslam.algo.geometry import wrap_angle
from lrfslam.errors import InputError
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.ros2 import convert, wire
from lrfslam.runtime.recording import read_recording

GOLDEN = Path(__file__).resolve().parents[1] / "data" / "golden"
F32 = {"rtol": 1e-6, "atol": 1e-6}   # ROS LaserScan fields are float32


def recorded(path: Path, name: str, n: int = 5) -> list:
    out = [topics.by_name(m.topic).codec.decode(m.data, m.schema) for m in read_recording(path, [name])]
    return out[:n] + out[-n:]


def through_cdr(message):
    payload = convert.serialize(message)
    assert payload[:4] == b"\x00\x01\x00\x00"   # CDR, little endian
    return convert.deserialize(payload, message.__msgtype__)


def check_header(h, stamp_ns: int, frame_id: str) -> None:
    assert h.stamp.sec * 1_000_000_000 + h.stamp.nanosec == stamp_ns and 0 <= h.stamp.nanosec < 1_000_000_000
    assert h.frame_id == frame_id


def scans() -> list[t.LaserScan]:
    every_status = t.LaserScan(stamp_ns=1_700_000_000_250_000_001, seq=3,
                               ranges_m=[1.5, np.inf, 2.25, 80.0, 0.0, np.nan],
                               status=[t.BEAM_VALID, t.BEAM_NO_RETURN, t.BEAM_DAZZLE, t.BEAM_OVERFLOW,
                                       t.BEAM_INVALID, t.BEAM_INVALID],
                               angle_min_rad=-0.5, angle_increment_rad=0.2, range_max_m=40.0, range_min_m=0.1,
                               frame_id="laser", scan_time_s=0.0133)
    return [every_status, *recorded(GOLDEN / "sim_head.mcap", "scan"), *recorded(GOLDEN / "intel_150.mcap", "scan")]


@pytest.mark.parametrize("scan", scans(), ids=lambda s: f"{s.ranges_m.size}beams-{s.seq}")
def test_a_scan_as_laser_scan(scan):
    ros = through_cdr(convert.laser_scan(scan, "/robot1"))
    check_header(ros.header, scan.stamp_ns, "robot1/laser")
    n = scan.ranges_m.size
    assert ros.ranges.size == n and ros.intensities.size == 0
    np.testing.assert_allclose([ros.angle_min, ros.angle_increment, ros.range_min, ros.range_max, ros.scan_time],
                               [scan.angle_min_rad, scan.angle_increment_rad, scan.range_min_m, scan.range_max_m,
                                scan.scan_time_s], **F32)
    assert ros.angle_max == pytest.approx(scan.angle_min_rad + (n - 1) * scan.angle_increment_rad, rel=1e-6)
    assert ros.time_increment == 0.0
    valid = scan.status == t.BEAM_VALID
    np.testing.assert_allclose(ros.ranges[valid], scan.ranges_m[valid], **F32)
    no_return = np.isin(scan.status, (t.BEAM_NO_RETURN, t.BEAM_OVERFLOW))
    assert np.all(np.isposinf(ros.ranges[no_return]))            # REP-117: no return is +inf
    assert np.all(np.isnan(ros.ranges[~valid & ~no_return]))      # judged wrong: NaN


def test_the_every_status_scan_has_each_kind():
    ros = convert.laser_scan(scans()[0], "/r")
    assert ros.ranges[0] == np.float32(1.5) and np.isposinf(ros.ranges[[1, 3]]).all()
    assert np.isnan(ros.ranges[[2, 4, 5]]).all()


@pytest.mark.parametrize("filtered", recorded(GOLDEN / "sim_head.denoise.mcap", "scan/filtered"),
                         ids=lambda f: str(f.seq))
def test_a_denoised_scan_as_laser_scan(filtered):
    ros = through_cdr(convert.filtered_scan(filtered, "/robot1"))
    scan = filtered.scan
    check_header(ros.header, filtered.stamp_ns, "robot1/laser")
    assert ros.range_max == pytest.approx(filtered.max_range_m, rel=1e-6)
    kept = filtered.kept_mask
    assert kept.any() and (~kept & (scan.status == t.BEAM_VALID)).any()   # the case at hand: beams removed
    np.testing.assert_allclose(ros.ranges[kept], scan.ranges_m[kept], **F32)
    removed = ~kept & (scan.status == t.BEAM_VALID)
    assert np.isnan(ros.ranges[removed]).all()
    no_return = scan.status == t.BEAM_NO_RETURN
    assert np.isposinf(ros.ranges[no_return & ~kept]).all()


@pytest.mark.parametrize("odom", recorded(GOLDEN / "intel_150.mcap", "odom"), ids=lambda o: str(o.seq))
def test_odometry_as_nav_msgs_odometry(odom):
    cov = np.array([[0.04, 0.01, 0.002], [0.01, 0.09, -0.003], [0.002, -0.003, 0.0025]])
    ros = through_cdr(convert.odometry(odom, "/robot1", cov))
    check_header(ros.header, odom.stamp_ns, "robot1/odom")
    assert ros.child_frame_id == "robot1/base_link"
    p, q = ros.pose.pose.position, ros.pose.pose.orientation
    assert (p.x, p.y, p.z) == (odom.pose[0], odom.pose[1], 0.0)
    assert q.x == q.y == 0 and math.isclose(q.z ** 2 + q.w ** 2, 1.0)
    assert wrap_angle(convert.yaw(q) - odom.pose[2]) == pytest.approx(0.0, abs=1e-12)
    assert (ros.twist.twist.linear.x, ros.twist.twist.angular.z) == (odom.linear_mps, odom.angular_radps)
    c6 = ros.pose.covariance.reshape(6, 6)
    np.testing.assert_array_equal(c6[np.ix_([0, 1, 5], [0, 1, 5])], cov)
    assert np.count_nonzero(c6) == np.count_nonzero(cov)
    assert not np.any(through_cdr(convert.odometry(odom, "/robot1")).pose.covariance)   # unknown: zeros


def test_pose_with_covariance_and_transforms():
    cov = np.diag([0.01, 0.02, 0.003])
    ros = through_cdr(convert.pose_with_covariance(5_000_000_123, "robot1/map", (1.0, -2.0, 3.0), cov))
    check_header(ros.header, 5_000_000_123, "robot1/map")
    assert (ros.pose.pose.position.x, ros.pose.pose.position.y) == (1.0, -2.0)
    assert convert.yaw(ros.pose.pose.orientation) == pytest.approx(3.0)
    assert ros.pose.covariance[[0, 7, 35]].tolist() == [0.01, 0.02, 0.003]
    tf = through_cdr(convert.tf_message([convert.transform(9, "robot1/map", "robot1/odom", (0.5, 0.25, -1.0)),
                                         convert.transform(9, "robot1/odom", "robot1/base_link", (1, 2, 0.5))]))
    assert [(x.header.frame_id, x.child_frame_id) for x in tf.transforms] == \
        [("robot1/map", "robot1/odom"), ("robot1/odom", "robot1/base_link")]
    first = tf.transforms[0].transform
    assert (first.translation.x, first.translation.y, first.translation.z) == (0.5, 0.25, 0.0)
    assert convert.yaw(first.rotation) == pytest.approx(-1.0)
    check_header(tf.transforms[1].header, 9, "robot1/odom")


def test_landmarks_as_markers_with_their_2_sigma_ellipses():
    lm = t.Landmarks(ids=[4, 9], xy_m=[[1.0, 2.0], [-3.0, 0.5]],
                     cov_m2=[np.diag([0.01, 0.04]), [[0.02, 0.01], [0.01, 0.02]]], kind=[1, 2],
                     sightings=[3, 1], confirmed=[True, False])
    ros = through_cdr(convert.landmark_markers(lm, 77, "robot1/map"))
    first, *markers = ros.markers
    assert first.action == 3   # DELETEALL: landmarks the map dropped go
    assert [m.id for m in markers] == [4, 9] and all(m.type == 3 and m.action == 0 for m in markers)
    for m, xy in zip(markers, lm.xy_m, strict=True):
        check_header(m.header, 77, "robot1/map")
        assert (m.pose.position.x, m.pose.position.y) == tuple(xy) and m.ns == "landmarks"
    # Diagonal: sigma 0.1 m along x, 0.2 m along y; full axes 4 sigma, the major one along y.
    assert (markers[0].scale.x, markers[0].scale.y) == pytest.approx((0.8, 0.4))
    assert abs(convert.yaw(markers[0].pose.orientation)) == pytest.approx(math.pi / 2)
    # Correlated: eigenvalues 0.03 and 0.01, the major axis at 45 degrees.
    assert (markers[1].scale.x, markers[1].scale.y) == pytest.approx((4 * math.sqrt(0.03), 4 * math.sqrt(0.01)))
    assert wrap_angle(2 * (convert.yaw(markers[1].pose.orientation) - math.pi / 4)) == pytest.approx(0.0, abs=1e-9)
    assert markers[0].color.a > 0 and markers[0].color != markers[1].color   # confirmed and tentative differ


def ros_scan(ranges, angle_min=-1.0, inc=0.25, rmin=0.1, rmax=30.0, frame="robot1/laser", stamp_ns=1_234_567_890_5):
    ty = wire.typestore().types
    return ty[wire.LASER_SCAN](header=convert.header(stamp_ns, frame), angle_min=angle_min,
                               angle_max=angle_min + (len(ranges) - 1) * inc, angle_increment=inc, time_increment=0.0,
                               scan_time=0.1, range_min=rmin, range_max=rmax,
                               ranges=np.array(ranges, np.float32), intensities=np.zeros(0, np.float32))


def test_any_laser_scan_in():
    ros = through_cdr(ros_scan([0.5, np.inf, np.nan, 31.0, 0.05, -np.inf, 2.0]))
    scan = convert.scan_from_ros(ros, 4, "/robot1", "ros2:/robot1/scan")
    assert (scan.stamp_ns, scan.seq, scan.frame_id, scan.source) == (1_234_567_890_5, 4, "laser", "ros2:/robot1/scan")
    assert (scan.angle_min_rad, scan.angle_increment_rad, scan.range_min_m, scan.range_max_m) == \
        pytest.approx((-1.0, 0.25, 0.1, 30.0))
    # Beyond range_max, below range_min, inf and NaN: no return.
    assert scan.status.tolist() == [0, 1, 1, 1, 1, 1, 0]
    assert scan.ranges_m[[0, 6]].tolist() == [0.5, 2.0] and np.isposinf(scan.ranges_m[1:6]).all()


def test_a_clockwise_laser_is_turned_round():
    scan = convert.scan_from_ros(ros_scan([1.0, 2.0, 3.0], angle_min=1.0, inc=-0.5), 1)
    assert scan.angle_increment_rad == 0.5 and scan.angle_min_rad == pytest.approx(0.0)
    assert scan.ranges_m.tolist() == [3.0, 2.0, 1.0]   # the beam at 0 rad first


@pytest.mark.parametrize("scan", scans()[1:], ids=lambda s: f"{s.ranges_m.size}beams-{s.seq}")
def test_our_scan_out_and_back(scan):
    back = convert.scan_from_ros(through_cdr(convert.laser_scan(scan, "/robot1")), scan.seq, "/robot1")
    assert (back.stamp_ns, back.seq, back.frame_id, back.ranges_m.size) == \
        (scan.stamp_ns, scan.seq, scan.frame_id, scan.ranges_m.size)
    np.testing.assert_allclose(back.angles_rad, scan.angles_rad, **F32)
    valid = (scan.status == t.BEAM_VALID) & (scan.ranges_m <= scan.range_max_m)
    np.testing.assert_allclose(back.ranges_m[valid], scan.ranges_m[valid], **F32)
    assert np.all(back.status[~valid] == t.BEAM_NO_RETURN) and np.all(back.status[valid] == t.BEAM_VALID)


@pytest.mark.parametrize("odom", recorded(GOLDEN / "intel_150.mcap", "odom"), ids=lambda o: str(o.seq))
def test_our_odometry_out_and_back(odom):
    back = convert.odometry_from_ros(through_cdr(convert.odometry(odom, "/robot1")), odom.seq, "/robot1")
    assert (back.stamp_ns, back.seq, back.frame_id) == (odom.stamp_ns, odom.seq, odom.frame_id)
    np.testing.assert_allclose(back.pose[:2], odom.pose[:2], rtol=0, atol=1e-12)
    assert wrap_angle(back.pose[2] - odom.pose[2]) == pytest.approx(0.0, abs=1e-12)
    assert (back.linear_mps, back.angular_radps) == (odom.linear_mps, odom.angular_radps)


@pytest.mark.parametrize(("kwargs", "ranges"), [({}, []), ({"inc": 0.0}, [1.0]), ({"inc": float("nan")}, [1.0]),
                                                ({"angle_min": 20.0}, [1.0]), ({"rmax": float("inf")}, [1.0])])
def test_scans_we_cannot_take(kwargs, ranges):
    with pytest.raises(InputError):
        convert.scan_from_ros(ros_scan(ranges, **kwargs), 1)


def test_odometry_we_cannot_take_and_payloads_that_are_not_cdr():
    odom = convert.odometry(t.Odometry(stamp_ns=1, seq=1, pose=(0, 0, 0)), "/r")
    odom.pose.pose.position.x = float("nan")
    with pytest.raises(InputError):
        convert.odometry_from_ros(odom, 1)
    with pytest.raises(InputError, match="not a CDR"):
        convert.deserialize(b"\x00\x01\x00\x00\x05", wire.LASER_SCAN)
    with pytest.raises(InputError):
        convert.deserialize(convert.serialize(odom), wire.LASER_SCAN)
