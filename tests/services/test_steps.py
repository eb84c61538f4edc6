"""Each service's step, driven in memory exactly as the runner drives it live and on replay."""

from __future__ import annotations

import numpy as np
import pytest
from lrfslam.services import stage

from lrfslam.algo.geometry import compose, relative
from lrfslam.algo.wall_direction import wrap_quarter
from lrfslam.errors import InputError
from lrfslam.evaluation import slam_resume
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.msgs.landmark_map import LandmarkMapReplica
from lrfslam.runtime import checkpoints
from lrfslam.runtime.chain import Chain
from lrfslam.runtime.step import Message, Output
from lrfslam.sim.floor_plans import l_corner
from lrfslam.sim.lidar import LidarModel, simulate_scan

ROBOT = "r1"


def build(name: str, *sets: str):
    """The step of service ``name`` with ``sets`` (replay: no checkpoints), and its config."""
    st = stage(name, sets=sets)
    return st.build(ROBOT), st.config


def run(name: str, messages, *sets: str):
    """The output values of a one-stage chain of ``name`` over ``messages`` (of the slam stage: its
    states, not its whole maps), and its step."""
    ch = Chain([stage(name, sets=sets)], robot=ROBOT)
    return [m.value for m in ch.feed(messages) if m.topic is not topics.SLAM_MAP], ch.step(name)


def rebuilt_map(values) -> t.Landmarks:
    """The landmark map a subscriber rebuilds from the slam stage's outputs ``values``."""
    replica = LandmarkMapReplica()
    for v in values:
        replica.apply_message(v)
    assert replica.complete
    return replica.landmarks


msg = Message.of


def sim_outputs(n: int, seed: int = 1):
    sensor, _ = build("sensor", "speedup=0", f"seed={seed}", "source=sim")
    outs = []
    for _ in range(n):
        outs += list(sensor.poll(0.1))
    return outs


def test_modes_select_presets_and_flags_still_override():
    _, paper = build("denoise", "mode=paper")
    _, default = build("denoise")
    assert (paper.histogram.bin_deg, paper.histogram.period_deg) == (10.0, 180.0)
    assert default.histogram.period_deg == 90.0
    _, custom = build("denoise", "mode=paper", "histogram.bin_deg=20")
    assert (custom.histogram.bin_deg, custom.histogram.period_deg) == (20.0, 180.0)
    _, feat = build("features", "mode=paper", "corners.arm_dists_m=0.3,0.6")
    assert feat.corners.arm_dists_m == (0.3, 0.6) and feat.corners.refine_corner is False


def test_denoise_applies_the_4m_cut_and_keeps_a_subset():
    step, _ = build("denoise")
    r = np.array([1.0, 1.01, 1.02, 5.0, np.nan, np.inf, 2.0, 2.01])
    scan = t.LaserScan.from_ranges(10, 1, r, -0.2, np.radians(1))
    (out,) = step.on_message(msg(Output(topics.SCAN, scan)))
    fs = out.value
    assert out.topic is topics.SCAN_FILTERED and fs.stamp_ns == 10
    assert np.isinf(fs.scan.ranges_m[3]) and fs.scan.status[3] == t.BEAM_NO_RETURN   # beyond 4 m
    assert np.isnan(fs.scan.ranges_m[4]) and fs.scan.status[4] == t.BEAM_INVALID
    assert set(fs.kept_beams.tolist()) <= {0, 1, 2, 6, 7}
    with pytest.raises(InputError):
        list(step.on_message(msg(Output(topics.SCAN, t.LaserScan.from_ranges(1, 1, [1.0], 0.0, 0.1)))))


def test_feature_step_finds_the_corner_of_an_l():
    den, _ = build("denoise")
    feat, _ = build("features")
    world = l_corner()
    lidar = LidarModel(range_sigma_m=0.0, quantum_m=0.0, mixed_pixel_prob=0.0)
    sim = simulate_scan(world, np.array([0.0, 0.0, 0.3]), lidar, np.random.default_rng(0))
    scan = t.LaserScan.from_ranges(5, 1, sim.ranges_m, lidar.angle_min_rad, lidar.angle_increment_rad)
    (fs,) = den.on_message(msg(Output(topics.SCAN, scan)))
    (out,) = feat.on_message(msg(fs))
    forward = out.value.xy_m[out.value.kind == t.FEATURE_FORWARD]
    corner = world.corners().xy_m[0]
    c, s = np.cos(-0.3), np.sin(-0.3)
    expected = np.array([[c, -s], [s, c]]) @ corner
    assert forward.shape == (1, 2)
    np.testing.assert_allclose(forward[0], expected, atol=0.005)


@pytest.mark.parametrize("sets, published", [((), True), (("wall_direction=false",), False),
                                               (("mode=paper",), False)])
def test_feature_step_publishes_the_wall_direction(sets, published):
    den, _ = build("denoise")
    feat, _ = build("features", *sets)
    lidar = LidarModel(range_sigma_m=0.0, quantum_m=0.0, mixed_pixel_prob=0.0)
    sim = simulate_scan(l_corner(), np.array([0.0, 0.0, 0.3]), lidar, np.random.default_rng(0))
    scan = t.LaserScan.from_ranges(5, 1, sim.ranges_m, lidar.angle_min_rad, lidar.angle_increment_rad)
    (fs,) = den.on_message(msg(Output(topics.SCAN, scan)))
    (out,) = feat.on_message(msg(fs))
    assert out.value.has_wall_direction == published
    if published:
        # The L's walls run at ±45° in the world, so at 45° - 0.3 rad (mod 90°) seen from heading 0.3.
        assert abs(wrap_quarter(out.value.wall_direction_rad - (np.pi / 4 - 0.3))) < 1e-6
        assert 0 < out.value.wall_direction_sigma_rad < 0.003
        assert feat.counts["wall_direction"] == 1


def chain(outs):
    """sensor outputs -> denoise -> features -> slam inputs (odom + features), in sensor order."""
    front = Chain([stage("denoise"), stage("features")], robot=ROBOT, wire=False)
    fed = []
    for o in outs:
        if o.topic is topics.ODOM:
            fed.append(msg(o))
        elif o.topic is topics.SCAN:
            fed += [m for m in front.push(msg(o)) if m.topic is topics.FEATURES]
    return fed


def test_slam_result_does_not_depend_on_how_odom_and_features_interleave():
    fed = chain(sim_outputs(60))
    out_a, _ = run("slam", fed)
    # The other tie order of a replay: each scan's features before the odometry of the same stamp.
    swapped = list(fed)
    for i in range(len(swapped) - 1):
        if swapped[i].topic is topics.ODOM and swapped[i + 1].topic is topics.FEATURES:
            swapped[i], swapped[i + 1] = swapped[i + 1], swapped[i]
    assert [m.topic for m in swapped] != [m.topic for m in fed]
    out_b, _ = run("slam", swapped)
    assert len(out_a) == len(out_b) == 60
    for x, y in zip(out_a, out_b):
        np.testing.assert_allclose(x.pose, y.pose, atol=1e-12)
        np.testing.assert_array_equal(x.landmarks.ids, y.landmarks.ids)
        np.testing.assert_array_equal(x.removed_landmark_ids, y.removed_landmark_ids)


def test_pipeline_tracks_ground_truth_over_a_corridor():
    outs = sim_outputs(150)
    truth = {o.value.stamp_ns: o.value.pose for o in outs if o.topic is topics.TRUTH}
    states, _ = run("slam", chain(outs))
    anchor = compose(truth[states[0].stamp_ns], relative(states[0].pose, np.zeros(3)))
    err = [np.linalg.norm(compose(anchor, s.pose)[:2] - truth[s.stamp_ns][:2]) for s in states]
    assert states[-1].n_landmarks >= 2
    assert max(err) < 0.25, max(err)


def test_slam_step_corrects_the_heading_with_the_wall_direction():
    fed = chain(sim_outputs(30))
    assert all(m.value.has_wall_direction for m in fed if m.topic is topics.FEATURES)
    states_on, on = run("slam", fed)
    states_off, off = run("slam", fed, "use_wall_direction=false")
    last_on, last_off = states_on[-1], states_off[-1]
    assert on.counts["wall_initialised"] == 1 and on.counts["wall_applied"] >= 25
    assert not any(k.startswith("wall_") for k in off.counts)
    # Hundreds of wall points per scan pin the heading far below what odometry and corners give.
    assert np.sqrt(last_on.pose_cov[2, 2]) < 0.5 * np.sqrt(last_off.pose_cov[2, 2])
    assert on.slam.ekf.building_orientation is not None and off.slam.ekf.building_orientation is None


def test_slam_resumes_from_its_checkpoint(tmp_path):
    fed = chain(sim_outputs(40))
    ckpt = checkpoints.path_for(tmp_path, "slam")
    live = [stage("slam")]
    with Chain(live, robot=ROBOT, checkpoint_dir=tmp_path, checkpoint_period_s=1.0) as first:
        head_out = [m.value for m in first.feed(fed[:40])]
    head = [v for v in head_out if isinstance(v, t.SlamState)]
    assert ckpt.exists()
    with Chain(live, robot=ROBOT, checkpoint_dir=tmp_path, checkpoint_period_s=1.0) as second:
        resumed = second.step("slam")
        assert resumed.slam.scans == head[-1].seq
        np.testing.assert_allclose(resumed.slam.ekf.pose, head[-1].pose, atol=1e-12)
        tail_out = [m.value for m in second.feed(fed[40:])]
    tail = [v for v in tail_out if isinstance(v, t.SlamState)]
    assert tail and tail[0].seq == head[-1].seq + 1
    # A restarted stage sends its whole map with its first state: a subscriber that held the map
    # before holds the resumed filter's after.
    assert isinstance(tail_out[1], t.LandmarkMap) and tail_out[1].state_seq == tail[0].seq
    assert set(rebuilt_map(head_out).ids.tolist()) <= set(rebuilt_map(head_out + tail_out).ids.tolist())


def test_a_killed_slam_bridges_what_it_missed_within_its_own_uncertainty(tmp_path):
    """Killed without a word (no final checkpoint) 20 scans after its checkpoint at 400, restarted
    13 s of driving later: one odometry step bridges 150 scans, and the resumed filter's position
    error stays inside its own 99.9 % bound at every state after, because the step's covariance holds
    the sideways drift of its heading walk (without it, 50 to 230 where the bound is 13.8)."""
    stream = slam_resume.sim_stream(seed=5, scans=650)
    r = slam_resume.resume_once(stream, kill=420, down_scans=130, folder=tmp_path)
    assert r.nees_max < 13.8 and r.final_cm < 3 * r.sigma_cm, r


def test_bad_input_is_counted_and_skipped():
    bad = Message(topics.SCAN, t.LaserScan.from_ranges(1, 1, [1.0], 0.0, 0.1), 1, "", "scan")
    good = Message(topics.SCAN, t.LaserScan.from_ranges(2, 2, [1.0, 1.0, 1.0], 0.0, 0.1), 2, "", "scan")
    ch = Chain([stage("denoise")], robot=ROBOT)
    outs = list(ch.feed([bad, good]))
    assert ch.counts()["denoise"]["error.input"] == 1 and len(outs) == 1 and outs[0].value.stamp_ns == 2
