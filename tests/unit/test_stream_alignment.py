"""Lining up odometry, scans and features (algo.stream_alignment): interpolation, holding, any interleaving."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lrfslam.algo.stream_alignment import (
    AlignmentParams,
    StreamAligner,
    interpolate_pose,
)
from lrfslam.errors import InputError

STAMPS = np.array([100, 200, 400], dtype=np.int64)
POSES = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 0.2], [3.0, 2.0, 0.6]])


@pytest.mark.parametrize("stamp, expected", [
    (100, [0.0, 0.0, 0.0]),      # on a sample
    (150, [0.5, 1.0, 0.1]),      # halfway
    (300, [2.0, 2.0, 0.4]),      # halfway in the longer gap
    (250, [1.5, 2.0, 0.3]),      # a quarter
    (50, [0.0, 0.0, 0.0]),       # before the first: the first
    (900, [3.0, 2.0, 0.6]),      # after the last: the last
])
def test_interpolation_against_hand_values(stamp, expected):
    np.testing.assert_allclose(interpolate_pose(STAMPS, POSES, stamp), expected, atol=1e-12)


def test_interpolated_heading_takes_the_short_way_round():
    poses = np.array([[0.0, 0.0, 3.0], [0.0, 0.0, -3.0]])   # 0.283 rad apart across ±π
    mid = interpolate_pose(np.array([0, 10]), poses, 5)
    assert abs(abs(mid[2]) - np.pi) < 1e-12
    quarter = interpolate_pose(np.array([0, 10]), poses, 2)
    np.testing.assert_allclose(quarter[2], 3.0 + 0.2 * (2 * np.pi - 6.0), atol=1e-12)


def test_the_sample_returned_is_a_copy():
    out = interpolate_pose(STAMPS, POSES, 100)
    out[0] = 99.0
    assert POSES[0, 0] == 0.0


def points(seq: int) -> np.ndarray:
    return np.full((3, 2), float(seq))


def summary(aligned) -> list[tuple]:
    """What the filter would get: features, odometry pose and scan, as comparable values."""
    return [(a.features, None if a.odom_pose is None else tuple(a.odom_pose.tolist()),
             None if a.scan_xy_m is None else a.scan_xy_m[0, 0]) for a in aligned]


@st.composite
def streams(draw):
    """Three streams of one run, each in its own order, and one interleaving of them.

    n scans at 100 ns apart (some lost, never the first), their features, and
    odometry at its own rate; the first scan comes first (features before any
    scan are deliberately not held, so they are not order-independent).
    """
    n = draw(st.integers(1, 10))
    lost = draw(st.sets(st.integers(1, n - 1), max_size=n - 1)) if n > 1 else set()
    odom_period = draw(st.sampled_from([30, 50, 100, 130]))
    odom_offset = draw(st.integers(0, 99))
    odom = [("odom", s, np.array([0.01 * s, -0.02 * s, 0.001 * s]))
            for s in range(odom_offset, 100 * n + 200, odom_period)]
    scans = [("scan", k) for k in range(n) if k not in lost]
    feats = [("features", k) for k in range(n)]
    order = draw(st.permutations(["odom"] * len(odom) + ["scan"] * (len(scans) - 1) + ["features"] * n))
    queues = {"odom": iter(odom), "scan": iter(scans[1:]), "features": iter(feats)}
    return [scans[0], *[next(queues[name]) for name in order]], odom, scans, feats


PATIENT = AlignmentParams(max_wait=50)   # never gives up within a test run


def run(events) -> list:
    align: StreamAligner[int] = StreamAligner(PATIENT)
    out = []
    for ev in events:
        if ev[0] == "odom":
            align.add_odometry(ev[1], ev[2])
        elif ev[0] == "scan":
            align.add_scan(ev[1], 100 * ev[1], points(ev[1]))
        else:
            align.add_features(100 * ev[1], ev[1], ev[1])
        out += align.ready()
    return summary(out + align.ready(final=True))


@settings(max_examples=200, deadline=None)
@given(streams())
def test_any_interleaving_gives_the_same_sequence(case):
    events, odom, scans, feats = case
    # The reference order: everything of one instant before the next (odometry, scan, features).
    reference = sorted(odom + scans + feats, key=lambda e: (e[1] * (1 if e[0] == "odom" else 100),
                                                            ("odom", "scan", "features").index(e[0])))
    got = run(events)
    assert got == run(reference)
    n = len(feats)
    assert [g[0] for g in got] == list(range(n))
    kept = {s[1] for s in scans}
    assert [g[2] for g in got] == [float(k) if k in kept else None for k in range(n)]


def test_features_wait_for_odometry_and_their_scan():
    align: StreamAligner[str] = StreamAligner(AlignmentParams())
    align.add_scan(1, 100, points(1))
    align.add_features(200, 2, "b")
    align.add_odometry(250, np.zeros(3))
    assert align.ready() == []             # scan 2 not in yet
    align.add_scan(2, 200, points(2))
    (a,) = align.ready()
    assert a.features == "b" and a.scan_xy_m[0, 0] == 2.0
    align.add_features(300, 3, "c")
    align.add_scan(4, 400, points(4))       # a newer scan: scan 3 was lost
    assert align.ready() == []             # but odometry has not reached 300 yet
    align.add_odometry(300, np.ones(3))
    (a,) = align.ready()
    assert a.scan_xy_m is None and a.odom_pose.tolist() == [1.0, 1.0, 1.0]


def test_features_before_any_scan_are_not_held_for_one():
    align: StreamAligner[str] = StreamAligner(AlignmentParams())
    align.add_odometry(100, np.zeros(3))
    align.add_features(100, 1, "a")
    (a,) = align.ready()
    assert a.scan_xy_m is None


def test_features_before_any_scan_wait_when_scans_are_not_optional():
    align: StreamAligner[str] = StreamAligner(AlignmentParams(wait_for_odometry=False, scans_optional=False))
    align.add_features(100, 1, "a")
    assert align.ready() == []
    align.add_scan(1, 100, points(1))
    (a,) = align.ready()
    assert a.features == "a" and a.scan_xy_m is not None


def test_without_odometry_they_wait_only_so_long():
    align: StreamAligner[int] = StreamAligner(AlignmentParams(max_wait=3))
    for k in range(3):
        align.add_features(100 * k, k, k)
    assert align.ready() == []
    align.add_features(300, 3, 3)
    (a,) = align.ready()                    # a fourth pushes the first out, without odometry
    assert a.features == 0 and a.odom_pose is None
    assert [a.features for a in align.ready(final=True)] == [1, 2, 3]
    loose: StreamAligner[int] = StreamAligner(AlignmentParams(wait_for_odometry=False, wait_for_scans=False))
    loose.add_features(100, 1, 1)
    assert [a.features for a in loose.ready()] == [1]


def test_odometry_out_of_order_is_refused_and_non_finite_is_bad_input():
    align: StreamAligner[int] = StreamAligner(AlignmentParams())
    assert align.add_odometry(100, np.zeros(3))
    assert not align.add_odometry(100, np.ones(3))
    assert not align.add_odometry(50, np.ones(3))
    with pytest.raises(InputError):
        align.add_odometry(200, np.array([0.0, np.nan, 0.0]))


def test_scans_without_features_are_bounded_and_old_ones_dropped():
    align: StreamAligner[int] = StreamAligner(AlignmentParams(max_wait=2))
    for k in range(20):
        align.add_scan(k, 100 * k, points(k))
    assert align.scans_held == 2 * 2 + 2
    align.add_odometry(2000, np.zeros(3))
    align.add_features(1700, 17, 17)
    (a,) = align.ready()
    assert a.scan_xy_m[0, 0] == 17.0
    assert align.scans_held == 2           # 18 and 19; the older ones will never be asked for
