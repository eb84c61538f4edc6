"""Messages survive the wire: round trips, schema names, and clear errors on bad payloads."""

from __future__ import annotations

import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from lrfslam.errors import ConfigError, DecodeError, SchemaVersionError
from lrfslam.msgs import codec, topics
from lrfslam.msgs import types as t

ranges = arrays(np.float32, st.integers(2, 400),
                elements=st.one_of(st.floats(0, 80, width=32), st.just(np.inf), st.just(np.nan)))


@settings(max_examples=60, deadline=None)
@given(r=ranges, stamp=st.integers(0, 2**63 - 1), seq=st.integers(0, 2**64 - 1))
def test_laser_scan_round_trip(r, stamp, seq):
    scan = t.LaserScan.from_ranges(stamp, seq, r.astype(float), -np.pi / 2, np.radians(1.0), source="sim")
    back = codec.LASER_SCAN.decode(codec.LASER_SCAN.encode(scan))
    np.testing.assert_array_equal(back.ranges_m, r.astype(float))  # NaN == NaN here, inf kept
    np.testing.assert_array_equal(back.status, scan.status)
    assert (back.stamp_ns, back.seq, back.source) == (stamp, seq, "sim")
    assert set(back.status[np.isinf(back.ranges_m)]) <= {t.BEAM_NO_RETURN}


@settings(max_examples=40, deadline=None)
@given(k=st.integers(0, 12), seed=st.integers(0, 2**32 - 1))
def test_features_and_slam_state_round_trip(k, seed):
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(k, 2, 2))
    feats = t.Features(stamp_ns=7, seq=3, scan_seq=2, kind=rng.choice([1, 2], k), xy_m=rng.normal(size=(k, 2)),
                       cov_m2=a @ a.transpose(0, 2, 1),
                       beam=rng.integers(0, 181, k), angle_deg=rng.uniform(80, 100, k))
    back = codec.FEATURES.decode(codec.FEATURES.encode(feats))
    for name in ("kind", "xy_m", "cov_m2", "beam", "angle_deg"):
        np.testing.assert_array_equal(getattr(back, name), getattr(feats, name))
    lms = t.Landmarks(ids=np.arange(k) * 3, xy_m=rng.normal(size=(k, 2)), cov_m2=a @ a.transpose(0, 2, 1),
                      kind=rng.choice([1, 2], k),
                      sightings=rng.integers(1, 9, k), confirmed=rng.integers(0, 2, k).astype(bool))
    state = t.SlamState(stamp_ns=9, seq=1, scan_seq=2, pose=rng.normal(size=3), pose_cov=np.eye(3), landmarks=lms,
                        removed_landmark_ids=[1, 4], landmarks_complete=False, n_landmarks=k + 5, n_confirmed=k,
                        associated=1, added=2, rejected=3,
                        motion=rng.normal(size=3) if k % 2 else None, motion_matched=k % 3 == 0)
    back = codec.SLAM_STATE.decode(codec.SLAM_STATE.encode(state))
    for name in ("pose", "pose_cov", "removed_landmark_ids", "motion"):
        np.testing.assert_array_equal(getattr(back, name), getattr(state, name))
    assert_same_landmarks(back.landmarks, lms)
    assert (back.n_landmarks, back.n_confirmed, back.landmarks_complete) == (k + 5, k, False)
    assert (back.associated, back.added, back.rejected, back.motion_matched) == (1, 2, 3, k % 3 == 0)
    whole = t.LandmarkMap(stamp_ns=9, seq=4, state_seq=1, landmarks=lms, tolerance_m=0.005)
    back_map = codec.LANDMARK_MAP.decode(codec.LANDMARK_MAP.encode(whole))
    assert (back_map.stamp_ns, back_map.seq, back_map.state_seq, back_map.tolerance_m) == (9, 4, 1, 0.005)
    assert_same_landmarks(back_map.landmarks, lms)


def assert_same_landmarks(a: t.Landmarks, b: t.Landmarks) -> None:
    for name in ("ids", "xy_m", "cov_m2", "kind", "sightings", "confirmed"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_a_v1_slam_state_decodes_as_a_whole_map():
    # v1 states carried every landmark in every message; recordings of them still replay.
    from lrfslam.msgs.v1 import slam_state_pb2 as v1
    p = v1.SlamState(scan_seq=8, associated=2, added=1, rejected=0, motion_matched=True)
    p.header.stamp_ns, p.header.seq = 50, 7
    p.pose.x_m, p.pose.theta_rad = 1.5, 0.25
    p.pose_covariance.extend(np.eye(3).ravel().tolist())
    for i, (x, ok) in enumerate([(2.0, True), (-1.0, False)]):
        p.landmarks.add(id=10 + i, x_m=x, y_m=0.5, covariance_m2=[0.01, 0, 0, 0.02], kind=1, sightings=3, confirmed=ok)
    old = codec.SLAM_STATE.decode(p.SerializeToString(), "lrfslam.msgs.v1.SlamState")
    assert old.landmarks_complete and (old.n_landmarks, old.n_confirmed) == (2, 1)
    assert (old.stamp_ns, old.seq, old.scan_seq, old.associated, old.motion_matched) == (50, 7, 8, 2, True)
    np.testing.assert_array_equal(old.landmarks.ids, [10, 11])
    np.testing.assert_array_equal(old.landmarks.xy_m, [[2.0, 0.5], [-1.0, 0.5]])
    assert old.motion is None   # absent in the v1 message
    p.landmarks[1].covariance_m2.append(0.0)
    with pytest.raises(DecodeError, match="v1.SlamState"):
        codec.SLAM_STATE.decode(p.SerializeToString(), "lrfslam.msgs.v1.SlamState")


def test_a_landmark_both_changed_and_removed_is_a_decode_error():
    lms = t.Landmarks(ids=[3], xy_m=[[1.0, 2.0]], cov_m2=[np.eye(2)], kind=[1], sightings=[2], confirmed=[True])
    state = t.SlamState(stamp_ns=9, seq=1, scan_seq=2, pose=np.zeros(3), pose_cov=np.eye(3), landmarks=lms,
                        removed_landmark_ids=[3], landmarks_complete=False, n_landmarks=1, n_confirmed=1)
    with pytest.raises(DecodeError, match="both changed and removed"):
        codec.SLAM_STATE.decode(codec.SLAM_STATE.encode(state))


def test_wall_direction_round_trips_and_absence_is_nan():
    feats = t.Features(stamp_ns=7, seq=3, scan_seq=2, kind=[1], xy_m=[(1.5, -0.25)], cov_m2=[np.eye(2) * 1e-4],
                       beam=[80], angle_deg=[90.0], wall_direction_rad=-0.3, wall_direction_sigma_rad=0.002)
    back = codec.FEATURES.decode(codec.FEATURES.encode(feats))
    assert back.has_wall_direction
    assert (back.wall_direction_rad, back.wall_direction_sigma_rad) == (-0.3, 0.002)
    none = t.Features(stamp_ns=7, seq=3, scan_seq=2, kind=[], xy_m=np.zeros((0, 2)), cov_m2=np.zeros((0, 2, 2)),
                      beam=[], angle_deg=[])
    back = codec.FEATURES.decode(codec.FEATURES.encode(none))
    assert not back.has_wall_direction and np.isnan(back.wall_direction_rad)
    assert not codec.FEATURES.to_proto(none).HasField("wall_direction")


def test_features_written_before_the_wall_direction_field_still_decode():
    # One forward corner as the v1 schema without field 4 serialised it (encoded
    # with the generated code of commit b422ad3).
    old = bytes.fromhex(
        "0a0b080710031a056c6173657210021a41080111000000000000f83f19000000000000d0bf22202d431ceb"
        "e2361a3f000000000000000000000000000000002d431cebe2361a3f2850310000000000805640"
    )
    back = codec.FEATURES.decode(old)
    assert (back.stamp_ns, back.seq, back.scan_seq, len(back)) == (7, 3, 2, 1)
    np.testing.assert_array_equal(back.xy_m, [[1.5, -0.25]])
    assert not back.has_wall_direction and np.isnan(back.wall_direction_sigma_rad)


@pytest.mark.parametrize("sigma", [0.0, -0.1, float("nan")])
def test_wall_direction_without_a_usable_sigma_is_a_decode_error(sigma):
    proto = codec.FEATURES.to_proto(t.Features(stamp_ns=7, seq=3, scan_seq=2, kind=[], xy_m=np.zeros((0, 2)),
                                               cov_m2=np.zeros((0, 2, 2)), beam=[], angle_deg=[]))
    proto.wall_direction.direction_rad, proto.wall_direction.sigma_rad = 0.1, sigma
    with pytest.raises(DecodeError, match="wall_direction"):
        codec.FEATURES.decode(proto.SerializeToString())


def test_filtered_scan_keeps_beams_and_points():
    scan = t.LaserScan.from_ranges(5, 1, [1.0, 2.0, np.inf, 3.0], -0.1, 0.05)
    fs = t.FilteredScan(stamp_ns=5, seq=1, scan=scan, kept_beams=[0, 3], points_xy_m=[[1.0, 0.0], [3.0, 0.1]],
                        max_range_m=4.0, mode="default")
    back = codec.FILTERED_SCAN.decode(codec.FILTERED_SCAN.encode(fs))
    np.testing.assert_array_equal(back.kept_mask, [True, False, False, True])
    np.testing.assert_allclose(back.points_xy_m, fs.points_xy_m, atol=1e-6)  # float32 on the wire


def test_every_topic_names_a_versioned_schema():
    for topic in topics.DATA_TOPICS + (topics.health("slam"),):
        assert re.fullmatch(r"lrfslam\.msgs\.v[1-9][0-9]*\.[A-Za-z]+", topic.schema), topic.schema
        assert codec.parse_encoding(topic.codec.encoding) == topic.schema


@pytest.mark.parametrize("payload", [b"\xff\xff\xff", b"\x0a\x05\x08", bytes(range(256))])
def test_garbage_is_a_decode_error(payload):
    with pytest.raises(DecodeError):
        codec.LASER_SCAN.decode(payload)


def test_inconsistent_message_is_a_decode_error():
    scan = t.LaserScan.from_ranges(1, 1, [1.0, 2.0], 0.0, 0.1)
    proto = codec.LASER_SCAN.to_proto(scan)
    del proto.status[-1]
    with pytest.raises(DecodeError, match="status"):
        codec.LASER_SCAN.decode(proto.SerializeToString())


def test_wrong_version_is_refused_by_name():
    data = codec.LASER_SCAN.encode(t.LaserScan.from_ranges(1, 1, [1.0, 2.0], 0.0, 0.1))
    with pytest.raises(SchemaVersionError, match="v9"):
        codec.LASER_SCAN.decode(data, "lrfslam.msgs.v9.LaserScan")
    with pytest.raises(SchemaVersionError):
        codec.LASER_SCAN.decode(data, codec.ODOMETRY.schema)


def test_an_upgrade_path_decodes_an_old_schema(monkeypatch):
    # How a v2 keeps v1 recordings replaying: an UPGRADES entry maps the old name to a converter.
    old = codec.ODOMETRY
    monkeypatch.setitem(codec.UPGRADES, ("lrfslam.msgs.v0.Odometry", old.schema),
                        (old.proto, lambda p: t.Odometry(stamp_ns=p.header.stamp_ns, seq=p.header.seq,
                                                         pose=(0.0, 0.0, 0.0))))
    data = old.encode(t.Odometry(stamp_ns=5, seq=2, pose=(1.0, 2.0, 3.0)))
    up = old.decode(data, "lrfslam.msgs.v0.Odometry")
    assert up.stamp_ns == 5 and np.all(up.pose == 0)


def test_robot_names_are_single_key_chunks():
    assert topics.key("r1", "scan") == "lrf/r1/scan"
    for bad in ("", "a/b", "a*", "a$b", "a b"):
        with pytest.raises(ConfigError):
            topics.check_robot(bad)


@settings(max_examples=40, deadline=None)
@given(k=st.integers(0, 50), seed=st.integers(0, 2**32 - 1))
def test_map_messages_round_trip(k, seed):
    rng = np.random.default_rng(seed)
    pose = t.MapPose(stamp_ns=11, seq=4, scan_seq=3, pose=rng.normal(size=3), map_from_slam=rng.normal(size=3),
                     keyframes=k, closures=2, closures_rejected=1, local_pose=rng.normal(size=3) if k % 2 else None)
    back = codec.MAP_POSE.decode(codec.MAP_POSE.encode(pose))
    for name in ("pose", "map_from_slam", "local_pose"):
        np.testing.assert_array_equal(getattr(back, name), getattr(pose, name))
    assert (back.stamp_ns, back.seq, back.scan_seq, back.keyframes, back.closures, back.closures_rejected) == (
        11, 4, 3, k, 2, 1)
    kf = t.MapKeyframes(stamp_ns=12, seq=5, scan_stamp_ns=rng.integers(0, 2**62, k), local_pose=rng.normal(size=(k, 3)),
                        map_pose=rng.normal(size=(k, 3)))
    back = codec.MAP_KEYFRAMES.decode(codec.MAP_KEYFRAMES.encode(kf))
    for name in ("scan_stamp_ns", "local_pose", "map_pose"):
        np.testing.assert_array_equal(getattr(back, name), getattr(kf, name))


def test_a_localized_pose_round_trips_and_an_old_one_reads_as_mapping():
    cov = np.array([[0.01, 0.002, 0.0], [0.002, 0.02, 0.001], [0.0, 0.001, 0.003]])
    pose = t.MapPose(stamp_ns=1, seq=1, scan_seq=1, pose=np.ones(3), map_from_slam=np.zeros(3),
                     localization=t.LOCALIZED, pose_cov=cov)
    back = codec.MAP_POSE.decode(codec.MAP_POSE.encode(pose))
    assert back.localization == t.LOCALIZED
    np.testing.assert_array_equal(back.pose_cov, cov)
    from lrfslam.msgs.v1 import map_pb2
    old = map_pb2.MapPose(scan_seq=1)   # written before the fields existed: none set
    back = codec.MAP_POSE.decode(old.SerializeToString())
    assert back.localization == t.MAPPING and back.pose_cov is None
    for bad in (map_pb2.MapPose(localization=7), map_pb2.MapPose(pose_covariance=[1.0] * 4)):
        with pytest.raises(DecodeError):
            codec.MAP_POSE.decode(bad.SerializeToString())


def test_keyframes_whose_poses_are_not_k_by_3_are_a_decode_error():
    from lrfslam.msgs.v1 import map_pb2
    bad = map_pb2.MapKeyframes(scan_stamp_ns=[1, 2], local_pose=[0.0] * 6, map_pose=[0.0] * 5)
    with pytest.raises(DecodeError):
        codec.MAP_KEYFRAMES.decode(bad.SerializeToString())


def test_messages_are_built_by_keyword():
    """A message of many fields built by position breaks silently when a field is added or moved
    (two of the same type swap unnoticed), so outside the tests none is built with more than three."""
    import ast
    import dataclasses
    from pathlib import Path
    root = Path(__file__).resolve().parents[2]
    classes = {name for name in dir(t) if dataclasses.is_dataclass(getattr(t, name))}
    found = []
    for path in sorted([*(root / "src").rglob("*.py"), *(root / "services").rglob("*.py")]):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and len(node.args) > 3:
                name = getattr(node.func, "attr", getattr(node.func, "id", None))
                if name in classes:
                    found.append(f"{path.relative_to(root)}:{node.lineno} {name}")
    assert not found, found
