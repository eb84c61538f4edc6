"""The slam step with scan matching: the scan-matched motion replaces poor odometry, in any arrival order."""

from __future__ import annotations

import numpy as np
import pytest
from lrfslam.services import stage
from lrfslam.services.slam import MAX_ODOM_WAIT_SCANS
from test_steps import ROBOT, build, msg, run

from lrfslam.algo.geometry import compose, relative
from lrfslam.msgs import topics
from lrfslam.runtime.chain import Chain


def sim_chain(n: int, *sensor_sets: str):
    """Simulated scans with noisy odometry -> slam inputs (scan, odom, features) in sensor order; and the truth."""
    sensor, _ = build("sensor", "speedup=0", "seed=4", "source=sim", *sensor_sets)
    front = Chain([stage("denoise"), stage("features")], robot=ROBOT, wire=False)
    fed, truth = [], {}
    while len(truth) < n:
        for o in sensor.poll(0.1):
            if o.topic is topics.TRUTH:
                truth[o.value.stamp_ns] = o.value.pose
            elif o.topic is topics.ODOM:
                fed.append(msg(o))
            elif o.topic is topics.SCAN:
                fed.append(msg(o))
                fed += [m for m in front.push(msg(o)) if m.topic is topics.FEATURES]
    return fed, truth


def position_errors(states, truth):
    """Distance (m) of each state's pose from the truth, both anchored at the first state."""
    anchor = compose(truth[states[0].stamp_ns], relative(states[0].pose, np.zeros(3)))
    return np.array([np.hypot(*(compose(anchor, s.pose)[:2] - truth[s.stamp_ns][:2])) for s in states])


# Wheel odometry five times worse than the simulator's default: 10 cm and 0.1 rad per metre / radian.
POOR_ODOMETRY = ("odom_trans_sigma_per_sqrt_m=0.1", "odom_rot_sigma_per_sqrt_rad=0.1")


@pytest.fixture(scope="module")
def poor_run():
    return sim_chain(300, *POOR_ODOMETRY)


def test_scan_matching_beats_poor_odometry_on_a_simulated_run(poor_run):
    fed, truth = poor_run
    states_sm, matched = run("slam", fed)
    states_odo, odometry = run("slam", fed, "scan_matching=false")
    err_sm = position_errors(states_sm, truth)
    err_odo = position_errors(states_odo, truth)
    assert len(err_sm) == len(err_odo) == 300
    assert matched.counts["match_ok"] >= 290 and "match_ok" not in odometry.counts
    assert err_sm.max() < 0.5 * err_odo.max() and err_sm.mean() < 0.05, (err_sm.max(), err_odo.max())


def test_the_result_does_not_depend_on_how_scans_odometry_and_features_interleave(poor_run):
    fed = poor_run[0][:200]
    out_a, a = run("slam", fed)
    # Another arrival order: each scan after its features (and after the odometry of its
    # stamp), but the first: features before any scan are not held (inputs without scans).
    late = list(fed)
    first_scan = next(i for i, m in enumerate(late) if m.topic is topics.SCAN)
    for i in range(first_scan + 1, len(late) - 1):
        if late[i].topic is topics.SCAN and late[i + 1].topic is not topics.SCAN:
            late[i], late[i + 1] = late[i + 1], late[i]
    assert [m.topic for m in late] != [m.topic for m in fed]
    out_b, b = run("slam", late)
    assert len(out_a) == len(out_b) > 60
    for x, y in zip(out_a, out_b):
        np.testing.assert_allclose(x.pose, y.pose, atol=1e-12)
        np.testing.assert_allclose(x.pose_cov, y.pose_cov, atol=1e-15)
    assert a.counts == b.counts


def test_lost_scans_fall_back_to_odometry(poor_run):
    fed = poor_run[0][:200]
    scans = [i for i, m in enumerate(fed) if m.topic is topics.SCAN]
    lost = set(scans[5::4])
    states, step = run("slam", [m for i, m in enumerate(fed) if i not in lost])
    assert len(states) == sum(m.topic is topics.FEATURES for m in fed)
    assert step.counts["scan_missing"] == len(lost)
    assert step.counts["match_ok"] >= len(scans) - len(lost) - 5


def test_without_odometry_the_scans_alone_move_the_filter(poor_run):
    """A bare LMS200: no odometry at all, the guess is "no motion" and the match finds the motion."""
    fed, truth = poor_run
    scans_and_features = [m for m in fed[:300] if m.topic is not topics.ODOM]
    states, step = run("slam", scans_and_features, "wait_for_odometry=false")
    err = position_errors(states, truth)
    travelled = np.hypot(*(truth[states[-1].stamp_ns][:2] - truth[states[0].stamp_ns][:2]))
    assert step.counts["no_odometry"] == len(states) and step.counts["match_ok"] >= len(states) - 3
    assert travelled > 3.0 and err.max() < 0.05 * travelled, (err.max(), travelled)


def test_scans_without_their_features_are_not_kept_forever(poor_run):
    step, _ = build("slam")
    for m in poor_run[0]:
        if m.topic is topics.SCAN:
            step.on_message(m)
    assert step.align.scans_held == 2 * MAX_ODOM_WAIT_SCANS + 2
