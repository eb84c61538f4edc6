"""The ROS 2 topics a robot's messages become (src/lrfslam/ros2/views.py), on the golden pipeline recording."""

from __future__ import annotations

import dataclasses
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from lrfslam.algo.geometry import compose, wrap_angle
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.ros2 import convert, views

GOLDEN = Path(__file__).resolve().parents[1] / "data" / "golden"


def pipeline_messages():
    from lrfslam.runtime.recording import read_recording
    return [(m.topic, topics.by_name(m.topic).codec.decode(m.data, m.schema))
            for m in read_recording(GOLDEN / "sim_head.pipeline.mcap")]


def xyt(p) -> np.ndarray:
    return np.array([p.position.x, p.position.y, convert.yaw(p.orientation)])


def tf_xyt(tr) -> np.ndarray:
    return np.array([tr.translation.x, tr.translation.y, convert.yaw(tr.rotation)])


def test_a_recording_through_the_views():
    v = views.RosViews("/robot1")
    odom_at, out = {}, []
    for name, value in pipeline_messages():
        if name == "odom":
            odom_at[value.stamp_ns] = value.pose
        for pub in v.on_message(name, value):
            out.append((name, value, pub))
    by = Counter(pub.topic.name for _, _, pub in out)
    n = sum(1 for name, _ in pipeline_messages() if name == "scan")
    assert by["scan"] == by["scan_filtered"] == by["odom"] == by["pose"] == n == 80
    assert by["/tf_static"] == 1 and by["/tf"] == 2 * n   # odom -> base_link and map -> odom per scan
    assert 14 <= by["landmarks"] <= 17                     # every 0.5 s of the 7.9 s of data
    for name, value, pub in out:
        assert pub.stamp_ns == value.stamp_ns
        if pub.topic is views.POSE:     # the EKF's pose and covariance, in the map frame
            assert pub.message.header.frame_id == "robot1/map"
            np.testing.assert_allclose(xyt(pub.message.pose.pose), value.pose, atol=1e-12)
            np.testing.assert_array_equal(pub.message.pose.covariance.reshape(6, 6)[np.ix_([0, 1, 5], [0, 1, 5])],
                                          value.pose_cov)
        if pub.topic is views.TF and name == "slam/state":   # map -> odom puts the odometry on the EKF's pose
            (tr,) = pub.message.transforms
            assert (tr.header.frame_id, tr.child_frame_id) == ("robot1/map", "robot1/odom")
            on_map = compose(tf_xyt(tr.transform), odom_at[value.stamp_ns])
            np.testing.assert_allclose(on_map[:2], value.pose[:2], atol=1e-9)
            assert wrap_angle(on_map[2] - value.pose[2]) == pytest.approx(0, abs=1e-9)
        if pub.topic is views.TF_STATIC:
            (tr,) = pub.message.transforms
            assert (tr.header.frame_id, tr.child_frame_id) == ("robot1/base_link", "robot1/laser")
    last = [pub for _, _, pub in out if pub.topic is views.LANDMARKS][-1]
    assert len(last.message.markers) - 1 == len(v.landmarks_in_map()) > 0


def test_the_mappers_pose_takes_over_with_the_ekfs_covariance_turned():
    v = views.RosViews("/r")
    v.on_message("odom", t.Odometry(stamp_ns=100, seq=1, pose=(1.0, 0.0, 0.0)))
    cov = np.diag([0.04, 0.01, 0.001])
    state = t.SlamState(stamp_ns=100, seq=1, scan_seq=1, pose=(1.0, 0.0, 0.0), pose_cov=cov,
                        landmarks=t.Landmarks(ids=[1], xy_m=[[2.0, 0.0]], cov_m2=[np.diag([0.01, 0.04])], kind=[1],
                                              sightings=[2], confirmed=[True]), n_landmarks=1)
    assert {p.topic.name for p in v.on_message("slam/state", state)} == {"pose", "/tf", "landmarks"}
    map_pose = t.MapPose(stamp_ns=100, seq=1, scan_seq=1, pose=(0.0, 1.0, np.pi / 2),
                         map_from_slam=(0.0, 0.0, np.pi / 2))
    pubs = {p.topic.name: p.message for p in v.on_message("map/pose", map_pose)}
    np.testing.assert_allclose(xyt(pubs["pose"].pose.pose), map_pose.pose, atol=1e-12)
    c = pubs["pose"].pose.covariance.reshape(6, 6)
    assert (c[0, 0], c[1, 1], c[5, 5]) == pytest.approx((0.01, 0.04, 0.001))   # x and y swap under 90 degrees
    np.testing.assert_allclose(tf_xyt(pubs["/tf"].transforms[0].transform), (0.0, 0.0, np.pi / 2), atol=1e-12)
    # Now the EKF's state gives no pose of its own, and its landmarks are drawn in the mapper's frame.
    later = t.SlamState(stamp_ns=700_000_100, seq=2, scan_seq=2, pose=(1.0, 0.0, 0.0), pose_cov=cov, n_landmarks=1)
    assert [p.topic.name for p in v.on_message("slam/state", later)] == ["landmarks"]
    np.testing.assert_allclose(v.landmarks_in_map().xy_m, [[0.0, 2.0]], atol=1e-12)
    np.testing.assert_allclose(v.landmarks_in_map().cov_m2[0], np.diag([0.04, 0.01]), atol=1e-12)


def test_on_a_saved_map_a_pose_not_localized_is_not_published_in_map():
    v = views.RosViews("/r")
    v.on_message("odom", t.Odometry(stamp_ns=100, seq=1, pose=(1.0, 0.0, 0.0)))
    v.on_message("odom", t.Odometry(stamp_ns=200, seq=2, pose=(1.1, 0.0, 0.0)))

    def map_pose(stamp_ns, localization):
        return t.MapPose(stamp_ns=stamp_ns, seq=1, scan_seq=1, pose=(0.0, 1.0, 0.0), map_from_slam=(0.0, 1.0, 0.0),
                         localization=localization, pose_cov=np.eye(3) * 1e-3 if localization == t.LOCALIZED else None)
    assert v.on_message("map/pose", map_pose(100, t.NOT_LOCALIZED)) == []
    pubs = {p.topic.name: p.message for p in v.on_message("map/pose", map_pose(200, t.LOCALIZED))}
    assert set(pubs) == {"pose", "/tf"}
    assert pubs["pose"].pose.covariance.reshape(6, 6)[0, 0] == pytest.approx(1e-3)


def test_no_map_to_odom_without_odometry():
    v = views.RosViews("/r")
    state = t.SlamState(stamp_ns=5, seq=1, scan_seq=1, pose=(0, 0, 0), pose_cov=np.eye(3))
    assert [p.topic.name for p in v.on_message("slam/state", state)] == ["pose", "landmarks"]
    assert v.on_message("features", object()) == []


def keyframes(stamp_ns: int, seq: int, stamps, poses) -> t.MapKeyframes:
    poses = np.asarray(poses, float)
    return t.MapKeyframes(stamp_ns=stamp_ns, seq=seq, scan_stamp_ns=stamps, local_pose=poses, map_pose=poses)


def grid_fields(msg) -> tuple:
    back = convert.deserialize(convert.serialize(msg), msg.__msgtype__)
    info = back.info
    return (info.width, info.height, round(info.resolution, 6), info.origin.position.x, info.origin.position.y,
            back.data.tolist(), back.header.frame_id, convert.stamp_ns(back.header.stamp))


def grid_message(stamp_ns: int, seq: int, tiles: dict, whole: bool = False) -> t.MapGrid:
    return t.MapGrid(stamp_ns=stamp_ns, seq=seq, resolution_m=0.05, tile_cells=4, tiles=list(tiles),
                     cells=np.array(list(tiles.values()), np.int8).reshape(-1, 4, 4), whole=whole)


def test_the_map_is_the_mappers_grid_put_together_at_most_once_a_second():
    v = views.RosViews("/robot1")
    scan = next(value for name, value in pipeline_messages() if name == "scan")
    assert [p.topic.name for p in v.on_message("scan", scan)] == ["scan"]   # no grid yet: no map
    wall, free = np.full((4, 4), 100, np.int8), np.zeros((4, 4), np.int8)
    t0 = scan.stamp_ns
    (pub,) = v.on_message("map/grid", grid_message(t0, 1, {(0, 0): wall, (-1, 2): free}))
    assert pub.topic is views.MAP and pub.topic.latched
    # Tiles (0, 0) and (-1, 2): rows -4..3 and columns 0..11 at 5 cm; the rest unknown.
    want = np.full((8, 12), -1, np.int8)
    want[4:8, 0:4], want[0:4, 8:12] = wall, free
    assert grid_fields(pub.message) == (12, 8, 0.05, 0.0, -0.2, want.reshape(-1).tolist(), "robot1/map", t0)
    # A changed tile within a second of data: it waits for the first message a second after the last map.
    assert v.on_message("map/grid", grid_message(t0 + 500_000_000, 2, {(0, 0): free})) == []
    later = [dataclasses.replace(scan, stamp_ns=t0 + k * 250_000_000) for k in (3, 4, 5)]
    assert [[p.topic.name for p in v.on_message("scan", s)] for s in later] == [["scan"], ["scan", "map"], ["scan"]]
    # A whole grid (a resolution change, or the late joiner's reply) replaces every tile.
    (pub,) = v.on_message("map/grid", grid_message(t0 + 3_000_000_000, 3, {(1, 1): wall}, whole=True))
    assert grid_fields(pub.message)[:5] == (4, 4, 0.05, 0.2, 0.2)


def test_a_large_map_goes_out_less_often(monkeypatch):
    monkeypatch.setattr(views, "MAP_CELLS_PER_S", 32)   # the 8 x 12 cells below: every 3 s of data
    v = views.RosViews("/robot1")
    wall, free = np.full((4, 4), 100, np.int8), np.zeros((4, 4), np.int8)
    (first,) = v.on_message("map/grid", grid_message(10**9, 1, {(0, 0): wall, (-1, 2): free}))
    assert grid_fields(first.message)[:2] == (12, 8)
    assert v.on_message("map/grid", grid_message(3 * 10**9, 2, {(0, 0): free})) == []
    assert [p.topic for p in v.on_message("map/grid", grid_message(4 * 10**9, 3, {(0, 0): wall}))] == [views.MAP]
