"""Foxglove's views of the pipeline's messages, decoded with the schemas a recording embeds.

The views of a simulated run are encoded by foxglove-sdk and decoded here with the protobuf
FileDescriptorSets the recorder embeds (``schema_sets``), by the mcap library's protobuf
decoder, and compared with their sources: the same ranges, poses, covariance ellipses.
"""

from __future__ import annotations

import math
from collections import Counter

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from lrfslam.services import stage
from mcap.records import Schema
from mcap_protobuf.decoder import DecoderFactory
from scipy.stats import chi2
from test_steps import sim_outputs

from lrfslam.algo.geometry import compose
from lrfslam.errors import DecodeError
from lrfslam.msgs import codec, topics
from lrfslam.msgs import types as t
from lrfslam.msgs.landmark_map import LandmarkMapReplica
from lrfslam.runtime.chain import Chain
from lrfslam.runtime.step import Message
from lrfslam.viz import foxglove as fx

_FACTORY = DecoderFactory()
_SCHEMAS = fx.schema_sets()


def decode(view: fx.View):
    """``view`` as a reader of a recording sees it: through the embedded schema."""
    # The decoder factory caches by schema id, as within one recording.
    schema = Schema(id=sorted(_SCHEMAS).index(view.schema) + 1, name=view.schema, encoding="protobuf",
                    data=_SCHEMAS[view.schema])
    return _FACTORY.decoder_for("protobuf", schema)(view.encode())


def ns(ts) -> int:
    return ts.seconds * 1_000_000_000 + ts.nanos


def xyt(p) -> np.ndarray:
    """(x, y, yaw) of a decoded foxglove.Pose (a rotation about z)."""
    q = p.orientation
    assert q.x == q.y == 0.0
    return np.array([p.position.x, p.position.y, 2 * math.atan2(q.z, q.w)])


def tf_pose(tr) -> np.ndarray:
    q = tr.rotation
    return np.array([tr.translation.x, tr.translation.y, 2 * math.atan2(q.z, q.w)])


def same_angle(a, b, tol=1e-9) -> bool:
    return abs(math.remainder(a - b, 2 * math.pi)) < tol


@pytest.fixture(scope="module")
def run():
    """A simulated run through every stage, as the recorder receives it (decoded off the wire)."""
    stream = []
    with Chain([stage(n) for n in ("denoise", "features", "slam", "mapper")], robot="r1") as ch:
        for out in sim_outputs(120):
            m = Message.of(out)
            stream += [m, *ch.push(m)]
    wire = []
    for m in stream:
        tp = topics.by_name(m.name)
        data = tp.codec.encode(m.value)
        wire.append((m.name, tp.schema, data, tp.codec.decode(data), m.stamp_ns))
    views = fx.FoxgloveViews()
    made = [(name, value, [*views.from_payload(name, schema, data, stamp)]) for name, schema, data, value, stamp in wire]
    return made


def views_on(run, channel):
    return [(name, value, v) for name, value, vs in run for v in vs if v.topic == channel]


def test_constant_is_the_chi2_quantile():
    assert fx.CHI2_2D_95 == pytest.approx(chi2.ppf(0.95, 2), rel=1e-12)
    assert round(fx.CHI2_2D_95, 3) == 5.991


@settings(max_examples=300, deadline=None)
@given(st.floats(0.01, 30.0), st.floats(-30.0, 30.0), st.floats(0.01, 30.0), st.floats(-2.0, 2.0))
def test_ellipse_axes_are_the_scaled_eigenvalues(l11, l21, l22, log_scale):
    low = np.array([[l11, 0.0], [l21, l22]]) * 10.0 ** log_scale
    cov = low @ low.T
    major, minor, yaw = fx.ellipse_axes(cov)
    # Oracles that do not use an eigen solver: trace and determinant are the eigenvalues' sum
    # and product, and both axis ends lie on the chi-square contour.
    lam = np.array([major, minor]) ** 2 / fx.CHI2_2D_95
    assert lam.sum() == pytest.approx(np.trace(cov), rel=1e-9)
    assert lam.prod() == pytest.approx(np.linalg.det(cov), rel=1e-6, abs=1e-12 * np.trace(cov) ** 2)
    assert major >= minor >= 0
    inv = np.linalg.inv(cov)
    for length, angle in ((major, yaw), (minor, yaw + math.pi / 2)):
        end = length * np.array([math.cos(angle), math.sin(angle)])
        assert end @ inv @ end == pytest.approx(fx.CHI2_2D_95, rel=1e-6)
    # The drawn ellipsoid: diameters and heading as computed.
    sphere = fx.ellipse(1.0, 2.0, cov, fx.LANDMARK_RGBA)
    msg = decode(fx.View(fx.LANDMARKS, fx.replace_all(5, [fx.fm.SceneEntity(spheres=[sphere])]), 5))
    drawn = msg.entities[0].spheres[0]
    assert (drawn.size.x, drawn.size.y) == pytest.approx((2 * major, 2 * minor))
    assert same_angle(xyt(drawn.pose)[2], yaw) and xyt(drawn.pose)[:2] == pytest.approx([1.0, 2.0])


def test_scans_keep_every_range_and_the_beam_layout(run):
    raw = views_on(run, fx.SCAN)
    assert len(raw) == 120
    for _, scan, view in raw:
        msg = decode(view)
        assert view.stamp_ns == scan.stamp_ns == ns(msg.timestamp)
        np.testing.assert_array_equal(np.array(msg.ranges), scan.ranges_m)   # inf and NaN where they were
        assert msg.frame_id == "laser" and msg.start_angle == scan.angle_min_rad
        assert msg.end_angle == pytest.approx(scan.angle_min_rad + (scan.ranges_m.size - 1) * scan.angle_increment_rad)
    kept = views_on(run, fx.SCAN_FILTERED)
    assert len(kept) == 120
    for _, fs, view in kept:
        ranges = np.array(decode(view).ranges)
        np.testing.assert_array_equal(ranges[fs.kept_beams], fs.scan.ranges_m[fs.kept_beams])
        assert np.isnan(np.delete(ranges, fs.kept_beams)).all()


def test_features_are_spheres_with_their_ellipses(run):
    seen = Counter()
    for _, f, view in views_on(run, fx.FEATURES):
        msg = decode(view)
        assert [d.type for d in msg.deletions] == [1] and ns(msg.deletions[0].timestamp) == f.stamp_ns
        assert len(msg.entities) == len(f)
        for i, ent in enumerate(msg.entities):
            kind = "corner" if f.kind[i] == t.FEATURE_FORWARD else "jump_edge"
            seen[kind] += 1
            assert ent.id == f"{kind}/{i}" and ent.frame_id == "laser"
            dot, ell = ent.spheres
            assert xyt(dot.pose)[:2] == pytest.approx(f.xy_m[i]) and xyt(ell.pose)[:2] == pytest.approx(f.xy_m[i])
            vals = np.linalg.eigvalsh(f.cov_m2[i])
            assert (ell.size.x / 2) ** 2 / 5.991 == pytest.approx(vals[1], rel=1e-3)
            assert (ell.size.y / 2) ** 2 / 5.991 == pytest.approx(vals[0], rel=1e-3)
    assert seen["corner"] > 0


def test_landmarks_carry_ids_and_95_percent_ellipses(run):
    sent = views_on(run, fx.LANDMARKS)
    states = [v for name, v, _ in run if name == topics.SLAM_STATE.name]
    # At most every landmark_period_s of data time (0.5 s at 10 Hz: every 5th state), the first at once.
    assert sent[0][1] is states[0] and len(sent) == pytest.approx(len(states) / 5, abs=1)
    # The map drawn is the one the slam stage's messages add up to at that state.
    replica, map_at = LandmarkMapReplica(), {}
    for name, value, _ in run:
        if name in (topics.SLAM_STATE.name, topics.SLAM_MAP.name):
            replica.apply_message(value)
            if name == topics.SLAM_STATE.name:
                map_at[value.seq] = replica.landmarks
    last = map_at[sent[-1][1].seq]
    assert len(last) > 3
    msg = decode(sent[-1][2])
    by_id = {e.id: e for e in msg.entities}
    assert set(by_id) == {f"landmark/{i}" for i in last.ids} | {"pose"}
    for i, lid in enumerate(last.ids):
        ent = by_id[f"landmark/{lid}"]
        assert ent.frame_id == "slam" and ent.texts[0].text == str(lid)
        ell = ent.spheres[1]
        vals = np.linalg.eigvalsh(last.cov_m2[i])
        assert (ell.size.x / 2) ** 2 / 5.991 == pytest.approx(vals[1], rel=1e-3)
        assert (ell.size.y / 2) ** 2 / 5.991 == pytest.approx(vals[0], rel=1e-3)
        assert {kv.key: kv.value for kv in ent.metadata}["sightings"] == str(last.sightings[i])


def test_transforms_chain_to_the_estimated_pose(run):
    """map→odom at a state's stamp, then the odometry's odom→base_link: the robot at the corrected EKF pose."""
    odom_tf, checked = {}, 0
    map_from_slam = np.zeros(3)
    for name, value, views in run:
        if name == topics.MAP_POSE.name:
            map_from_slam = value.map_from_slam
        for v in views:
            if v.topic != fx.TF:
                continue
            trs = {(tr.parent_frame_id, tr.child_frame_id): tr for tr in decode(v).transforms}
            if name == topics.ODOM.name:
                odom_tf[value.stamp_ns] = tf_pose(trs[("odom", "base_link")])
                assert tf_pose(trs[("base_link", "laser")]) == pytest.approx(np.zeros(3))
            elif name == topics.SLAM_STATE.name:
                assert ns(trs[("map", "odom")].timestamp) == value.stamp_ns
                robot = compose(tf_pose(trs[("map", "odom")]), odom_tf[value.stamp_ns])
                expected = compose(map_from_slam, value.pose)
                assert robot[:2] == pytest.approx(expected[:2], abs=1e-9) and same_angle(robot[2], expected[2])
                assert tf_pose(trs[("map", "slam")]) == pytest.approx(map_from_slam)
                # world→map ties the EKF to the truth by its first pose
                world = tf_pose(trs[("world", "map")])
                checked += 1
    assert checked == 120
    truth0 = next(v.pose for n, v, _ in run if n == topics.TRUTH.name)
    first = next(v.pose for n, v, _ in run if n == topics.SLAM_STATE.name)
    assert compose(world, first) == pytest.approx(truth0, abs=1e-9)


def test_trajectories_are_thinned_sent_at_a_bounded_rate_and_end_at_the_robot(run):
    cfg = fx.ViewConfig()
    for channel, topic, frame in ((fx.TRAJECTORY_SLAM, topics.SLAM_STATE, "slam"),
                                  (fx.TRAJECTORY_ODOM, topics.ODOM, "odom"),
                                  (fx.TRAJECTORY_TRUTH, topics.TRUTH, "world")):
        sent = views_on(run, channel)
        stamps = [v.stamp_ns for _, _, v in sent]
        assert np.all(np.diff(stamps) >= cfg.path_period_s * 1e9)
        assert len(sent) >= 11        # 12 s of data at 1 Hz
        for _, value, view in sent:
            msg = decode(view)
            assert msg.frame_id == frame and ns(msg.timestamp) == value.stamp_ns
            poses = np.array([xyt(p) for p in msg.poses])
            assert poses[-1][:2] == pytest.approx(value.pose[:2]) and same_angle(poses[-1][2], value.pose[2], 1e-6)
            steps = np.hypot(*np.diff(poses[:-1, :2], axis=0).T)
            turns = np.abs(np.remainder(np.diff(poses[:-1, 2]) + np.pi, 2 * np.pi) - np.pi)
            assert np.all((steps >= cfg.path_step_m - 1e-9) | (turns >= cfg.path_turn_rad - 1e-9))
        # the whole path: every pose of the source is within one thinning step of it
        everything = np.array([v.pose for n, v, _ in run if n == topic.name and v.stamp_ns <= stamps[-1]])
        drawn = np.array([xyt(p) for p in decode(sent[-1][2]).poses])
        gap = np.min(np.hypot(*(everything[:, None, :2] - drawn[None, :, :2]).transpose(2, 0, 1)), axis=1)
        assert gap.max() < cfg.path_step_m + 0.05


def test_a_long_path_is_sent_less_often():
    cfg = fx.ViewConfig(path_period_s=1.0, path_poses_per_s=20.0, path_step_m=0.1)
    path = fx.Trajectory("map", cfg)
    # 10 Hz, every pose kept: the path grows by 10 poses per second of data time
    sent = [i for i in range(600) if path.add(i * 100_000_000, np.array([0.2 * i, 0.0, 0.0])) is not None]
    gaps = np.diff(sent) / 10          # in seconds of data time
    assert gaps[0] == 1.0 and gaps[-1] > 10.0   # 1 s at first, n / 20 s once n poses outgrow it
    assert np.all(gaps[1:] >= (np.array(sent[1:-1]) + 1) / 20 - 1e-9)
    assert path.add(5, np.zeros(3)) is not None  # a stamp from before: a restarted source, sent at once


@settings(max_examples=25, deadline=None)
@given(n=st.integers(1, 3000), max_poses=st.integers(2, 64), keyframes=st.integers(0, 500))
def test_a_path_stays_bounded_however_long_the_run(n, max_poses, keyframes):
    cfg = fx.ViewConfig(path_period_s=0.0, path_poses_per_s=1e9, path_step_m=0.1, path_max_poses=max_poses)
    path = fx.Trajectory("map", cfg)
    path.replace(0, np.column_stack((np.arange(keyframes), np.ones(keyframes), np.zeros(keyframes))), 0)
    for i in range(1, n + 1):
        msg = path.add(i * 1_000_000, np.array([0.2 * i, 0.0, 0.0]))
        poses = np.array([xyt(p) for p in decode(fx.View(fx.TRAJECTORY_MAP, msg, i)).poses])
        driven = poses[poses[:, 1] == 0.0, 0]   # the keyframes lie on y = 1
        # Bounded (the newest pose may come on top), in order, and ending at the newest pose.
        assert len(poses) <= max_poses + 1 and poses[-1, 0] == pytest.approx(0.2 * i)
        assert np.all(np.diff(driven) > 0)
    # Thinned evenly: no gap of the kept part (all but the newest pose) is more than twice another.
    if driven.size > 3:
        gaps = np.diff(driven[:-1])
        assert gaps.max() <= 2 * gaps.min() + 1e-9


def test_keyframes_replace_the_mapper_path():
    views = fx.FoxgloveViews()
    for i in range(1, 6):
        views.convert(topics.MAP_POSE.name, t.MapPose(stamp_ns=i, seq=i, scan_seq=i, pose=[float(i), 0, 0],
                                                      map_from_slam=np.zeros(3)), i)
    kf = t.MapKeyframes(stamp_ns=10, seq=1, scan_stamp_ns=np.array([3, 1]), local_pose=np.zeros((2, 3)),
                        map_pose=np.array([[1.0, 1.0, 0], [3.0, 1.0, 0]]))
    (view,) = views.convert(topics.MAP_KEYFRAMES.name, kf, 10)
    poses = [xyt(p)[:2].tolist() for p in decode(view).poses]
    assert poses == [[3.0, 1.0], [1.0, 1.0], [4.0, 0.0], [5.0, 0.0]]   # keyframes by stamp, then the poses after


def test_without_odometry_the_ekf_pose_places_the_robot():
    views = fx.FoxgloveViews()
    state = t.SlamState(stamp_ns=7, seq=1, scan_seq=1, pose=[1.0, 2.0, 0.5], pose_cov=np.eye(3) * 0.01)
    tfs = [v for v in views.convert(topics.SLAM_STATE.name, state, 7) if v.topic == fx.TF]
    trs = {(tr.parent_frame_id, tr.child_frame_id): tf_pose(tr) for tr in decode(tfs[0]).transforms}
    assert trs[("map", "odom")] == pytest.approx(np.zeros(3)) and trs[("odom", "base_link")] == pytest.approx(state.pose)


def test_health_is_logged_when_it_changes():
    views = fx.FoxgloveViews()
    name = topics.health("slam").name

    def status(level, message, at):
        return views.convert(name, t.ServiceStatus(service="slam", robot="r1", level=level, message=message,
                                                   wall_stamp_ns=at, uptime_s=1.0, counters={}), at)
    logs = [status(t.HEALTH_OK, "ok", 1), status(t.HEALTH_OK, "ok", 2), status(t.HEALTH_WARN, "slow", 3),
            status(t.HEALTH_WARN, "slow", 4), status(t.HEALTH_OK, "ok", 5)]
    assert [len(x) for x in logs] == [1, 0, 1, 0, 1]
    msg = decode(logs[2][0])
    assert (msg.level, msg.name, msg.message, ns(msg.timestamp)) == (3, "slam", "slow", 3)   # 3: WARNING


def test_a_bad_payload_is_a_decode_error_and_other_topics_have_no_views():
    views = fx.FoxgloveViews()
    with pytest.raises(DecodeError):
        views.from_payload("scan", topics.SCAN.schema, b"\xff\xfe garbage", 1)
    with pytest.raises(DecodeError):
        views.from_payload("scan", "lrfslam.msgs.v9.LaserScan", codec.LASER_SCAN.encode(
            t.LaserScan.from_ranges(1, 1, [1.0], 0.0, 0.1)), 1)
    assert views.from_payload("some/other", "x.Y", b"\x00", 1) == []


@pytest.mark.parametrize("period_s", [0.05, 0.0])
def test_a_fast_sensors_scans_and_transforms_are_viewed_at_most_every_frame_period(period_s):
    views = fx.FoxgloveViews(fx.ViewConfig(frame_period_s=period_s))
    period_ns = round(1e9 / 75)   # an LMS200 at 500 kBd
    shown, transforms = [], 0
    for i in range(150):
        stamp = 5_000_000_000 + i * period_ns
        data = codec.LASER_SCAN.encode(t.LaserScan.from_ranges(stamp, i + 1, np.full(181, 2.0), -np.pi / 2,
                                                               np.radians(1)))
        if views.from_payload("scan", topics.SCAN.schema, data, stamp):
            shown.append(stamp)
        elif period_s:   # between two views a payload is not even decoded
            assert views.from_payload("scan", topics.SCAN.schema, b"\xff\xfe garbage", stamp) == []
        odom = codec.ODOMETRY.encode(t.Odometry(stamp_ns=stamp, seq=i + 1, pose=np.array([0.01 * i, 0.0, 0.0])))
        transforms += sum(v.topic == fx.TF for v in views.from_payload("odom", topics.ODOM.schema, odom, stamp))
    gaps = np.diff(shown)
    if period_s:
        assert gaps.min() >= period_s * 1e9 and gaps.max() < period_s * 1e9 + period_ns and len(shown) == 38
    else:
        assert len(shown) == 150
    assert transforms == len(shown)
    # data time going back (a restarted sensor) starts afresh
    back = codec.LASER_SCAN.encode(t.LaserScan.from_ranges(1, 1, np.full(181, 2.0), -np.pi / 2, np.radians(1)))
    assert views.from_payload("scan", topics.SCAN.schema, back, 1)


def test_every_channel_is_under_the_prefix_with_a_foxglove_schema():
    assert all(topics.is_foxglove(c) for c in fx.CHANNELS)
    assert set(_SCHEMAS) == {"foxglove.LaserScan", "foxglove.SceneUpdate", "foxglove.PosesInFrame",
                             "foxglove.FrameTransforms", "foxglove.Grid", "foxglove.Log"}


def test_the_map_is_the_tiles_put_together_at_most_every_map_period():
    views = fx.FoxgloveViews(fx.ViewConfig(map_period_s=5.0))
    wall, free = np.full((4, 4), 100, np.int8), np.zeros((4, 4), np.int8)

    def grid(stamp_s: float, tiles: dict) -> t.MapGrid:
        return t.MapGrid(stamp_ns=round(stamp_s * 1e9), seq=1, resolution_m=0.1, tile_cells=4, tiles=list(tiles),
                         cells=np.array(list(tiles.values()), np.int8).reshape(-1, 4, 4))

    (view,) = views.convert(topics.MAP_GRID.name, grid(10.0, {(0, 0): wall, (1, -1): free}), 10)
    assert view.topic == fx.GRID and view.schema == "foxglove.Grid"
    msg = decode(view)
    assert msg.frame_id == "map" and msg.column_count == 8 and msg.row_stride == 8 and msg.cell_stride == 1
    assert (msg.pose.position.x, msg.pose.position.y) == pytest.approx((-0.4, 0.0))
    assert (msg.cell_size.x, msg.cell_size.y) == pytest.approx((0.1, 0.1))
    assert [(f.name, f.offset) for f in msg.fields] == [("occupancy", 0)]
    cells = np.frombuffer(msg.data, np.int8).reshape(8, 8)   # row 0 at the lowest y
    want = np.full((8, 8), -1, np.int8)
    want[0:4, 4:8], want[4:8, 0:4] = wall, free
    np.testing.assert_array_equal(cells, want)
    # Changes within five seconds of data wait; the first after them brings every tile as it is now.
    assert views.convert(topics.MAP_GRID.name, grid(12.0, {(0, 0): free}), 12) == []
    (later,) = views.convert(topics.MAP_GRID.name, grid(15.0, {(2, 2): wall}), 15)
    cells = np.frombuffer(decode(later).data, np.int8)
    assert (cells == 100).sum() == 16 and (cells == 0).sum() == 32


def test_the_mappers_correction_moves_the_slam_frame_and_the_robot():
    views = fx.FoxgloveViews()
    views.convert(topics.ODOM.name, t.Odometry(stamp_ns=5, seq=1, pose=[0.5, -0.2, 0.1]), 5)
    views.convert(topics.ODOM.name, t.Odometry(stamp_ns=15, seq=2, pose=[1.5, -0.2, 0.3]), 15)
    correction = np.array([1.0, 2.0, 0.3])
    views.convert(topics.MAP_POSE.name, t.MapPose(stamp_ns=9, seq=1, scan_seq=1, pose=[0.0, 0.0, 0.0],
                                                  map_from_slam=correction), 9)
    state = t.SlamState(stamp_ns=10, seq=1, scan_seq=1, pose=[4.0, -1.0, 0.7], pose_cov=np.eye(3) * 0.01)
    (tf,) = [v for v in views.convert(topics.SLAM_STATE.name, state, 10) if v.topic == fx.TF]
    trs = {(tr.parent_frame_id, tr.child_frame_id): tf_pose(tr) for tr in decode(tf).transforms}
    assert trs[("map", "slam")] == pytest.approx(correction)
    odom_at_10 = np.array([1.0, -0.2, 0.2])     # halfway between the two odometry samples
    robot, expected = compose(trs[("map", "odom")], odom_at_10), compose(correction, state.pose)
    assert robot[:2] == pytest.approx(expected[:2]) and same_angle(robot[2], expected[2])


def test_on_a_saved_map_the_localization_scene_says_whether_and_how_surely():
    views = fx.FoxgloveViews()
    cov = np.diag([0.04, 0.01, 0.001])

    def pose(stamp_s, localization):
        return t.MapPose(stamp_ns=int(stamp_s * 1e9), seq=1, scan_seq=1, pose=np.array([2.0, 3.0, 0.5]),
                         map_from_slam=np.zeros(3), keyframes=5, local_pose=np.zeros(3), localization=localization,
                         pose_cov=cov if localization == t.LOCALIZED else None)

    def scenes(stamp_s, localization):
        return [decode(v) for v in views.convert("map/pose", pose(stamp_s, localization), int(stamp_s * 1e9))
                if v.topic == fx.LOCALIZATION]

    assert scenes(0.0, t.MAPPING) == []                       # mapping: no localization to show
    (lost,) = scenes(1.0, t.NOT_LOCALIZED)
    (entity,) = lost.entities
    assert entity.frame_id == fx.MAP and entity.texts[0].text == "not localized" and not entity.spheres
    assert entity.texts[0].color.r > 0.8 and entity.texts[0].color.g < 0.2
    assert scenes(1.5, t.NOT_LOCALIZED) == []                 # unchanged: at most every path_period_s
    (found,) = scenes(1.6, t.LOCALIZED)                       # changed: at once
    (entity,) = found.entities
    assert entity.texts[0].text == "localized"
    major, minor, _ = fx.ellipse_axes(cov[:2, :2])            # the position's 95 % ellipse at the pose
    (sphere,) = entity.spheres
    assert (sphere.size.x, sphere.size.y) == pytest.approx((2 * major, 2 * minor))
    assert xyt(sphere.pose)[:2] == pytest.approx([2.0, 3.0])
    assert len(scenes(2.7, t.LOCALIZED)) == 1                 # and again a period later
