"""Every schema's decode path, fuzzed: random bytes, truncations, bit flips, wrong encodings,
unknown versions, oversize payloads. The services decode with
:func:`lrfslam.runtime.decoding.decode_message` (live in runtime/bus.py, on replay in
runtime/chain.py); it must never raise, and must count every rejection and log it once.
"""

from __future__ import annotations

import dataclasses
import logging
import zlib
from collections import Counter

import numpy as np
import pytest
from google.protobuf.descriptor import FieldDescriptor as FD
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from lrfslam import services
from lrfslam.msgs import codec, topics
from lrfslam.msgs import types as t
from lrfslam.runtime.chain import Chain
from lrfslam.runtime.decoding import MAX_PAYLOAD_BYTES, LogOnce, decode_message
from lrfslam.runtime.step import Message

FUZZ = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _scan(rng, n=30):
    return t.LaserScan.from_ranges(5, 1, np.where(rng.random(n) < 0.1, np.inf, rng.uniform(0.1, 8, n)),
                                   -np.pi / 2, np.pi / (n - 1), source="fuzz")


def _cov(rng, k):
    a = rng.normal(size=(k, 2, 2))
    return a @ a.transpose(0, 2, 1) + 1e-3 * np.eye(2)


def _landmarks(rng):
    return t.Landmarks(ids=[4, 7], xy_m=rng.normal(size=(2, 2)), cov_m2=_cov(rng, 2), kind=[1, 2], sightings=[3, 1],
                       confirmed=[True, False])


#: One valid value per schema name. The registry (codec.CODECS) decides what must be here:
#: test_every_schema_is_fuzzed fails for a schema added without a sample.
SAMPLES = {
    codec.LASER_SCAN.schema: _scan,
    codec.ODOMETRY.schema: lambda rng: t.Odometry(stamp_ns=5, seq=1, pose=rng.normal(size=3), linear_mps=0.3,
                                                  angular_radps=0.1),
    codec.FILTERED_SCAN.schema: lambda rng: t.FilteredScan(stamp_ns=5, seq=1, scan=_scan(rng),
                                                           kept_beams=np.arange(0, 30, 3),
                                                           points_xy_m=rng.normal(size=(10, 2)), max_range_m=4.0,
                                                           mode="default"),
    codec.FEATURES.schema: lambda rng: t.Features(stamp_ns=5, seq=1, scan_seq=1, kind=[1, 2, 1],
                                                  xy_m=rng.normal(size=(3, 2)), cov_m2=_cov(rng, 3),
                                                  beam=[3, 9, 20], angle_deg=[90.0, np.nan, 85.0],
                                                  wall_direction_rad=0.1, wall_direction_sigma_rad=0.01),
    codec.SLAM_STATE.schema: lambda rng: t.SlamState(stamp_ns=5, seq=1, scan_seq=1, pose=rng.normal(size=3),
                                                     pose_cov=np.eye(3) * 0.01, landmarks=_landmarks(rng),
                                                     removed_landmark_ids=[2], landmarks_complete=False, n_landmarks=9,
                                                     n_confirmed=4, associated=2, added=1, rejected=0,
                                                     motion=rng.normal(size=3), motion_matched=True),
    codec.LANDMARK_MAP.schema: lambda rng: t.LandmarkMap(stamp_ns=5, seq=1, state_seq=1, landmarks=_landmarks(rng),
                                                         tolerance_m=0.005),
    codec.GROUND_TRUTH.schema: lambda rng: t.GroundTruth(stamp_ns=5, seq=1, pose=rng.normal(size=3), corner_ids=[1, 2],
                                                         corners_xy_m=rng.normal(size=(2, 2)), world="hallway"),
    codec.SERVICE_STATUS.schema: lambda rng: t.ServiceStatus(service="slam", robot="r1", level=0, message="ok",
                                                             wall_stamp_ns=7, uptime_s=1.5, counters={"in.scan": 3},
                                                             last_data_stamp_ns=5, config_json="{}", schemas=("a",),
                                                             pid=42, host="host"),
    codec.MAP_POSE.schema: lambda rng: t.MapPose(stamp_ns=5, seq=1, scan_seq=1, pose=rng.normal(size=3),
                                                 map_from_slam=rng.normal(size=3), keyframes=2, closures=1,
                                                 closures_rejected=0,
                                                 local_pose=rng.normal(size=3)),
    codec.MAP_KEYFRAMES.schema: lambda rng: t.MapKeyframes(stamp_ns=5, seq=1, scan_stamp_ns=[1, 2, 3],
                                                           local_pose=rng.normal(size=(3, 3)),
                                                           map_pose=rng.normal(size=(3, 3)),
                                                           local_edge=[True, False, True]),
    codec.MAP_GRID.schema: lambda rng: t.MapGrid(stamp_ns=5, seq=1, resolution_m=0.05, tile_cells=4,
                                                 tiles=[[0, 0], [-1, 2]],
                                                 cells=rng.choice([-1, 0, 100], size=(2, 4, 4)), keyframes=3),
}

#: Every topic a service can receive: the data topics and the health of any service.
TOPICS = (*topics.DATA_TOPICS, topics.health("slam"))
topic_st = st.sampled_from(TOPICS)


def payload_of(topic, seed: int = 0) -> bytes:
    return topic.codec.encode(SAMPLES[topic.schema](np.random.default_rng(seed)))


def decode(topic, payload, schema):
    """``decode_message`` with fresh counters; (message or None, counts)."""
    counts: Counter = Counter()
    msg = decode_message(topic, payload, schema, counts, LogOnce(logging.getLogger("fuzz")), "fuzz")
    return msg, counts


def assert_counted(msg, counts) -> None:
    """A rejection (None) is counted exactly once, under an ``error.*`` kind; an acceptance not at all."""
    errors = sum(v for k, v in counts.items() if k.startswith("error."))
    assert errors == (msg is None), counts


def test_every_schema_is_fuzzed():
    assert set(SAMPLES) == set(codec.CODECS)
    assert {tp.schema for tp in TOPICS} == set(codec.CODECS)


@pytest.mark.parametrize("topic", TOPICS, ids=lambda tp: tp.name)
def test_samples_are_valid(topic):
    msg, counts = decode(topic, payload_of(topic), topic.schema)
    assert msg is not None and not counts


@FUZZ
@given(topic=topic_st, data=st.binary(max_size=2000))
def test_random_bytes_never_raise(topic, data):
    msg, counts = decode(topic, data, topic.schema)
    assert_counted(msg, counts)


@FUZZ
@given(topic=topic_st, seed=st.integers(0, 2**32 - 1), cut=st.floats(0, 1, exclude_max=True))
def test_truncated_payloads_never_raise(topic, seed, cut):
    payload = payload_of(topic, seed)
    msg, counts = decode(topic, payload[:int(cut * len(payload))], topic.schema)
    assert_counted(msg, counts)


@FUZZ
@given(topic=topic_st, seed=st.integers(0, 2**32 - 1), flips=st.lists(st.integers(0, 2**31), min_size=1, max_size=8))
def test_bit_flips_never_raise(topic, seed, flips):
    payload = bytearray(payload_of(topic, seed))
    for bit in flips:
        payload[(bit // 8) % len(payload)] ^= 1 << (bit % 8)
    msg, counts = decode(topic, bytes(payload), topic.schema)
    assert_counted(msg, counts)


@FUZZ
@given(topic=topic_st, other=topic_st, seed=st.integers(0, 2**32 - 1))
def test_another_schemas_payload_never_raises(topic, other, seed):
    """Mislabelled: ``other``'s bytes sent as ``topic``'s schema (protobuf may parse them)."""
    msg, counts = decode(topic, payload_of(other, seed), topic.schema)
    assert_counted(msg, counts)


@FUZZ
@given(topic=topic_st, other=topic_st)
def test_a_wrong_schema_name_is_a_schema_error(topic, other):
    if other.schema == topic.schema:
        return
    msg, counts = decode(topic, payload_of(topic), other.schema)
    assert msg is None and counts == Counter({"error.schema": 1})


@FUZZ
@given(topic=topic_st, encoding=st.text(max_size=80))
def test_any_encoding_string_gives_a_counted_result(topic, encoding):
    """Whatever the Zenoh encoding says, the schema parsed from it decodes or is counted."""
    msg, counts = decode(topic, payload_of(topic), codec.parse_encoding(encoding))
    assert_counted(msg, counts)
    assert msg is None or codec.parse_encoding(encoding) == topic.schema


@pytest.mark.parametrize("topic", TOPICS, ids=lambda tp: tp.name)
@pytest.mark.parametrize("schema", ["", "lrfslam.msgs.v9.{}", "lrfslam.msgs.v0.{}", "lrfslam.msgs.v1.{}Extra"])
def test_no_schema_and_unknown_versions_are_schema_errors(topic, schema):
    name = schema.format(topic.schema.rsplit(".", 1)[1]) if schema else ""
    msg, counts = decode(topic, payload_of(topic), name)
    assert msg is None and counts == Counter({"error.schema": 1})


def test_an_oversize_payload_is_refused_unparsed():
    topic = topics.SCAN
    big = payload_of(topic) + b"\0" * MAX_PAYLOAD_BYTES
    msg, counts = decode(topic, big, topic.schema)
    assert msg is None and counts == Counter({"error.oversize": 1})


def test_every_rejection_is_counted_and_each_kind_logged_once(caplog):
    """Many bad payloads of a few kinds: every one counted, one log line per (topic, kind)."""
    counts: Counter = Counter()
    once = LogOnce(logging.getLogger("fuzz.once"))
    bad = [(topics.SCAN, b"\xff" * 9, topics.SCAN.schema), (topics.SCAN, payload_of(topics.SCAN), "x.v9.Scan"),
           (topics.ODOM, b"\x0a\xff", topics.ODOM.schema)]
    with caplog.at_level(logging.WARNING, logger="fuzz.once"):
        for _ in range(50):
            for topic, payload, schema in bad:
                assert decode_message(topic, payload, schema, counts, once, "k") is None
    assert counts == Counter({"error.decode": 100, "error.schema": 50})
    assert len(caplog.records) == 3, [r.getMessage() for r in caplog.records]


# ---- well-formed payloads with hostile values -------------------------------------------------

_INT_RANGES = {FD.CPPTYPE_INT32: (-2**31, 2**31 - 1), FD.CPPTYPE_INT64: (-2**63, 2**63 - 1),
               FD.CPPTYPE_UINT32: (0, 2**32 - 1), FD.CPPTYPE_UINT64: (0, 2**64 - 1),
               FD.CPPTYPE_ENUM: (-2**31, 2**31 - 1)}   # proto3 enums are open: any int32 arrives
_HOSTILE_FLOATS = (np.nan, np.inf, -np.inf, -1.0, 0.0, 1e-300, 1e300, -1e300, 3.4e38)


#: A megabyte of zeros in a kilobyte: a decoder must not inflate more than the message says it holds.
_BOMB = zlib.compress(bytes(1_000_000))


def _value(data, field):
    ct = field.cpp_type
    if ct in _INT_RANGES:
        lo, hi = _INT_RANGES[ct]
        return data.draw(st.one_of(st.sampled_from([lo, hi, 0, 1, -1 if lo < 0 else 2, 255, 256]),
                                   st.integers(lo, hi)))
    if ct in (FD.CPPTYPE_DOUBLE, FD.CPPTYPE_FLOAT):
        return data.draw(st.one_of(st.sampled_from(_HOSTILE_FLOATS),
                                   st.floats(width=32 if ct == FD.CPPTYPE_FLOAT else 64)))
    if ct == FD.CPPTYPE_BOOL:
        return data.draw(st.booleans())
    if field.type == FD.TYPE_BYTES:   # zlib-compressed cells among others: garbage, or a small bomb
        return data.draw(st.one_of(st.binary(max_size=40), st.just(_BOMB)))
    return data.draw(st.text(max_size=20))


def mutate(msg, data, depth: int = 0) -> None:
    """Overwrite random scalar fields of ``msg`` (recursively) with hostile values of their types.

    Works from the schema's descriptor, so it covers every field of every schema, and
    fields added later, without a list here.
    """
    for field in msg.DESCRIPTOR.fields:
        repeated = field.is_repeated
        if field.message_type is not None:
            if field.message_type.GetOptions().map_entry:
                continue
            subs = list(getattr(msg, field.name)) if repeated else [getattr(msg, field.name)]
            for sub in subs:
                if depth < 3 and data.draw(st.booleans()):
                    mutate(sub, data, depth + 1)
            continue
        if not data.draw(st.booleans()):
            continue
        if repeated:
            values = getattr(msg, field.name)
            if len(values):
                for _ in range(data.draw(st.integers(1, 3))):
                    values[data.draw(st.integers(0, len(values) - 1))] = _value(data, field)
        else:
            setattr(msg, field.name, _value(data, field))


def hostile_payload(topic, data) -> bytes:
    proto = topic.codec.to_proto(SAMPLES[topic.schema](np.random.default_rng(data.draw(st.integers(0, 99)))))
    mutate(proto, data)
    return proto.SerializeToString()


@settings(max_examples=60, deadline=None)
@given(topic=topic_st, data=st.data())
def test_hostile_field_values_never_raise(topic, data):
    msg, counts = decode(topic, hostile_payload(topic, data), topic.schema)
    assert_counted(msg, counts)


# ---- the steps, fed what the decoders let through -----------------------------------------------

STAGES = ("denoise", "features", "slam", "mapper")
#: Topics some stage of STAGES takes (the chain routes each to its consumers).
CONSUMED = tuple(tp for tp in topics.DATA_TOPICS
                 if any(tp in services.spec(name).inputs for name in STAGES))


@pytest.fixture(scope="module")
def sim_frames():
    """Valid sensor output (scan, odom, truth per frame), as the sensor service publishes it."""
    sensor = services.build_step("sensor", sets=["speedup=0", "seed=2", "source=sim"])
    outs = []
    while len(outs) < 3 * 8:
        outs += list(sensor.poll(0.1))
    sensor.close()
    return [Message.of(o) for o in outs]


def _finite_outputs(outputs) -> None:
    for m in outputs:
        if m.topic in (topics.SLAM_STATE, topics.MAP_POSE):
            assert np.all(np.isfinite(m.value.pose)), f"{m.topic.name} pose {m.value.pose} after hostile input"


def _drive(frames, hostile: list[Message]) -> Chain:
    """Valid frames, the hostile messages in the middle, more valid frames: nothing may escape."""
    chain = Chain([services.stage(n) for n in STAGES], robot="fuzz")
    half = len(frames) // 2
    outputs = []
    for m in frames[:half]:
        outputs += chain.push(m)
    for m in hostile:
        outputs += chain.push(m)
    for m in frames[half:]:
        _finite_outputs(chain.push(m))
    _finite_outputs(list(chain.feed([])))
    chain.close()
    return chain


def _at(value, stamp_ns: int, seq: int):
    """``value`` restamped into the middle of the stream."""
    fields = {"stamp_ns": stamp_ns, "seq": seq} if hasattr(value, "__dataclass_fields__") else {}
    return dataclasses.replace(value, **fields)


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                  HealthCheck.function_scoped_fixture])
@given(topic=st.sampled_from(CONSUMED), data=st.data())
def test_steps_survive_whatever_decodes(sim_frames, topic, data):
    """Hostile values that pass decoding reach the steps; they reject them (counted) or cope."""
    counts: Counter = Counter()
    once = LogOnce(logging.getLogger("fuzz.steps"))
    mid = sim_frames[len(sim_frames) // 2]
    hostile = []
    for _ in range(3):
        msg = decode_message(topic, hostile_payload(topic, data), topic.schema, counts, once, "fuzz")
        if msg is not None:
            hostile.append(Message(topic, _at(msg.value, mid.stamp_ns, mid.seq), mid.stamp_ns, topic.schema,
                                   topic.name, mid.seq))
    _drive(sim_frames, hostile)


hostile_ranges = st.lists(st.one_of(st.sampled_from(_HOSTILE_FLOATS), st.floats(0, 100)), min_size=0, max_size=800)


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                  HealthCheck.function_scoped_fixture])
@given(ranges=hostile_ranges, angle_min=st.sampled_from((-np.pi / 2, 0.0, -1e300, 1e300, np.inf, np.nan)),
       increment=st.sampled_from((np.radians(0.5), 1e-300, 1e-9, 10.0, 1e300, np.inf)))
def test_scans_with_hostile_ranges_and_angles(sim_frames, ranges, angle_min, increment):
    mid = sim_frames[len(sim_frames) // 2]
    scan = t.LaserScan.from_ranges(mid.stamp_ns, mid.seq, np.array(ranges, float), angle_min, increment)
    counts: Counter = Counter()
    msg = decode_message(topics.SCAN, codec.LASER_SCAN.encode(scan), topics.SCAN.schema, counts,
                         LogOnce(logging.getLogger("fuzz.scan")), "fuzz")
    _drive(sim_frames, [] if msg is None else [msg])


def test_a_huge_scan_is_handled(sim_frames):
    mid = sim_frames[len(sim_frames) // 2]
    rng = np.random.default_rng(0)
    scan = t.LaserScan.from_ranges(mid.stamp_ns, mid.seq, rng.uniform(0.1, 8.0, 20_000), -np.pi, 2 * np.pi / 20_000)
    _drive(sim_frames, [Message(topics.SCAN, scan, scan.stamp_ns, topics.SCAN.schema, "scan", scan.seq)])


def test_a_rejected_input_is_counted_each_time_and_logged_once(sim_frames, caplog):
    mid = sim_frames[len(sim_frames) // 2]
    one_beam = t.LaserScan.from_ranges(mid.stamp_ns, mid.seq, [1.0], 0.0, 0.01)
    bad = Message(topics.SCAN, one_beam, mid.stamp_ns, topics.SCAN.schema, "scan", mid.seq)
    with caplog.at_level(logging.WARNING, logger="lrfslam.chain"):
        chain = _drive(sim_frames, [bad] * 5)
    assert chain.counts()["denoise"]["error.input"] == 5
    assert len([r for r in caplog.records if "skipping bad input" in r.getMessage()]) == 1
