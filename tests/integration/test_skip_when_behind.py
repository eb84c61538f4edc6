"""A stage that falls behind skips to its newest input, over real Zenoh (lrfslam/runtime/bus.py).

One router session and client sessions on loopback in this process. A producer publishes the
slam's inputs (odometry, scans, features) with wall-clock stamps while the consumer does not
read, as a stage busy with one long update would; then the consumer reads its backlog.
"""

from __future__ import annotations

import time
from collections import Counter

import numpy as np
import pytest
import zenoh

from lrfslam.msgs import codec, topics
from lrfslam.msgs import types as t
from lrfslam.runtime.bus import ZenohBus
from lrfslam.tools.status import client_config

pytestmark = pytest.mark.integration

ROBOT = "behind"

SCANS = 40
PERIOD_NS = 13_333_333   # 75 scans/s


def inputs(i: int, stamp_ns: int) -> list[tuple]:
    """Scan ``i``'s odometry, scan and features, all stamped ``stamp_ns``."""
    scan = t.LaserScan.from_ranges(stamp_ns, i, np.full(181, 2.0), -np.pi / 2, np.pi / 180)
    feats = t.Features(stamp_ns=stamp_ns, seq=i, scan_seq=i, kind=[], xy_m=np.zeros((0, 2)), cov_m2=np.zeros((0, 2, 2)),
                       beam=[], angle_deg=[])
    return [(topics.ODOM, codec.ODOMETRY.encode(t.Odometry(stamp_ns=stamp_ns, seq=i, pose=(0.01 * i, 0.0, 0.0)))),
            (topics.SCAN, codec.LASER_SCAN.encode(scan)), (topics.FEATURES, codec.FEATURES.encode(feats))]


def wait_until(predicate, what: str, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, what
        time.sleep(0.02)


def backlog(endpoint: str, max_lag_s: float, age_s: float) -> tuple[list, Counter]:
    """Publish ``SCANS`` scans' inputs stamped from ``age_s`` in the past (negative: the future), then read them
    all: (messages, receive counts)."""
    with zenoh.open(client_config([endpoint])) as stage_s, zenoh.open(client_config([endpoint])) as pub_s:
        stage = ZenohBus(stage_s, ROBOT, (topics.ODOM, topics.SCAN, topics.FEATURES), False, 1000, Counter(),
                         (topics.SCAN, topics.FEATURES), max_lag_s)
        producer = ZenohBus(pub_s, ROBOT, (), False, 16, Counter())
        for topic in (topics.ODOM, topics.SCAN, topics.FEATURES):
            pub = producer.publisher(topic)
            wait_until(lambda pub=pub: pub.matching_status.matching, "no subscriber matched")
        start = time.time_ns() - int(age_s * 1e9)
        for i in range(1, SCANS + 1):
            for topic, payload in inputs(i, start + i * PERIOD_NS):
                producer.put(topic, payload, start + i * PERIOD_NS, i)
        wait_until(lambda: stage.pending() == 3 * SCANS, "not every sample arrived")
        got = []
        while (msg := stage.get(0.05)) is not None:
            got.append(msg)
        counts = stage.receive_counts()
        stage.close()
        producer.close()
        return got, counts


def test_a_stage_behind_skips_to_the_newest_scan_and_keeps_every_odometry(router):
    got, counts = backlog(router, max_lag_s=0.25, age_s=1.0)
    by_topic = {tp: [m.seq for m in got if m.topic is tp] for tp in (topics.ODOM, topics.SCAN, topics.FEATURES)}
    # Odometry is never skipped: the stage needs it to bridge the scans it skips.
    assert by_topic[topics.ODOM] == list(range(1, SCANS + 1))
    # Every scan and its features but the newest were older than the lag with a newer one waiting.
    assert by_topic[topics.SCAN] == by_topic[topics.FEATURES] == [SCANS]
    assert counts == Counter({"skip.scan": SCANS - 1, "skip.features": SCANS - 1})


@pytest.mark.parametrize("max_lag_s, age_s", [(0.25, -0.5), (0.0, 1.0), (0.25, 3600.0)],
                         ids=["fresh", "skipping off", "a recording's stamps"])
def test_fresh_inputs_skipping_off_or_a_replay_lose_nothing(router, max_lag_s, age_s):
    """Inputs newer than the lag are handled; so is every input of a replay, whose stamps (an hour
    old here) are not on this wall clock: played as fast as the stages go, it must give the offline
    chain's outputs."""
    got, counts = backlog(router, max_lag_s, age_s)
    assert len(got) == 3 * SCANS
    assert not any(k.startswith("skip.") for k in counts)
