"""The slam stage's map travels as changes: a recording of it rebuilds the filter's map at every
state, and a state's size does not grow with the map."""

from __future__ import annotations

import numpy as np
from lrfslam.services import stage
from lrfslam.services.slam import LANDMARK_TOLERANCE_M

from lrfslam.msgs import codec, topics
from lrfslam.msgs import types as t
from lrfslam.msgs.landmark_map import LandmarkMapReplica, axis_sigmas, by_id
from lrfslam.runtime.chain import Chain
from lrfslam.runtime.recording import RecordingWriter, read_recording
from lrfslam.runtime.step import Message

ROBOT = "r1"


def sensor_messages(n: int) -> list[Message]:
    sensor = stage("sensor", sets=["speedup=0", "seed=3", "source=sim", "world=hallway_loop"]).build(ROBOT)
    outs = []
    while sum(o.topic is topics.SCAN for o in outs) < n:
        outs += list(sensor.poll(0.1))
    sensor.close()
    return [Message.of(o) for o in outs if o.topic in (topics.SCAN, topics.ODOM)]


def test_a_recording_rebuilds_the_filters_map_at_every_state(tmp_path):
    chain = Chain([stage(n) for n in ("denoise", "features", "slam")], robot=ROBOT)
    slam = chain.step("slam")
    exact: dict[int, t.Landmarks] = {}          # state seq -> the filter's map right after it
    path = tmp_path / "run.mcap"
    with RecordingWriter(path) as rec:
        for m in [*sensor_messages(400), None]:
            outs = chain.push(m) if m is not None else list(chain.feed([]))
            for o in outs:
                if o.topic in (topics.SLAM_STATE, topics.SLAM_MAP):
                    rec.write(o.topic.name, o.topic.schema, o.topic.codec.encode(o.value), o.stamp_ns)
                if o.topic is topics.SLAM_STATE:
                    exact[o.value.seq] = by_id(slam.current)
    replica = LandmarkMapReplica()
    sizes, counts, checked, maps = [], [], 0, 0
    for r in read_recording(path, [topics.SLAM_STATE.name, topics.SLAM_MAP.name]):
        value = topics.by_name(r.topic).codec.decode(r.data, r.schema)
        replica.apply_message(value)
        if r.topic == topics.SLAM_MAP.name:
            maps += 1
            np.testing.assert_array_equal(replica.landmarks.xy_m, exact[value.state_seq].xy_m)  # exact at a map
            continue
        sizes.append(len(r.data))
        counts.append(value.n_landmarks)
        held, want = replica.landmarks, exact[value.seq]
        assert replica.complete
        np.testing.assert_array_equal(held.ids, want.ids)
        np.testing.assert_array_equal(held.sightings, want.sightings)
        np.testing.assert_array_equal(held.confirmed, want.confirmed)
        assert np.all(np.hypot(*(held.xy_m - want.xy_m).T) <= LANDMARK_TOLERANCE_M)
        assert np.all(np.abs(axis_sigmas(held.cov_m2) - axis_sigmas(want.cov_m2)) <= LANDMARK_TOLERANCE_M)
        assert value.n_landmarks == len(want)
        checked += 1
    assert checked == len(exact) >= 390 and maps >= 3
    # The map grows several-fold; a state's payload does not grow with it.
    quarter = len(sizes) // 4
    assert np.median(counts[-quarter:]) >= 3 * max(np.median(counts[:quarter]), 1)
    assert np.median(sizes[-quarter:]) <= 1.5 * np.median(sizes[:quarter]), (sizes[:quarter], sizes[-quarter:])
    # A v1 state of the same map would hold every landmark.
    assert np.median(sizes[-quarter:]) < 0.5 * len(codec.LANDMARK_MAP.encode(t.LandmarkMap(stamp_ns=0, seq=0,
                                                                                           state_seq=0,
                                                                                           landmarks=want)))
