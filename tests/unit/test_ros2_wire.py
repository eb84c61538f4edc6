"""rmw_zenoh's wire format (src/lrfslam/ros2/wire.py): keys, tokens, QoS strings, attachment, names, hashes.

The fixtures are the examples of rmw_zenoh's design document (``design.md`` in its repository) and the
Jazzy type hashes as rosidl generates them (docs/ros2.md).
"""

from __future__ import annotations

import re
import struct

import pytest
import zenoh
from hypothesis import given
from hypothesis import strategies as st

from lrfslam.errors import ConfigError, InputError
from lrfslam.msgs import topics
from lrfslam.ros2 import wire

STRING = "std_msgs/msg/String"
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"


@pytest.mark.parametrize(("msgtype", "expected"), [
    (wire.LASER_SCAN, "RIHS01_64c191398013af96509d518dac71d5164f9382553fce5c1f8cca5be7924bd828"),
    (wire.ODOMETRY, "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0"),
    (wire.TF_MESSAGE, "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"),
    (wire.OCCUPANCY_GRID, "RIHS01_8d348150c12913a31ee0ec170fbf25089e4745d17035792a1ba94d6f0bc0cfc7"),
    (STRING, STRING_HASH),
])
def test_type_hashes_are_jazzys(msgtype, expected):
    assert wire.type_hash(msgtype) == expected


def test_every_published_type_has_a_hash():
    for msgtype in (wire.POSE_WITH_COVARIANCE_STAMPED, wire.MARKER_ARRAY):
        assert re.fullmatch(r"RIHS01_[0-9a-f]{64}", wire.type_hash(msgtype))


def test_data_keys_as_in_the_design_doc():
    assert wire.data_key(0, "/chatter", STRING) == f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    assert wire.data_key(0, "/robot1/chatter", STRING) == \
        f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    # Inner slashes stay in data keys (only tokens mangle them).
    assert wire.data_key(3, "/robot1/scan", wire.LASER_SCAN).startswith("3/robot1/scan/sensor_msgs::msg::dds_::LaserScan_/")


def test_tokens_as_in_the_design_doc():
    assert wire.node_token(2, "aac3178e146ba6f1fc6e6a4085e77f21", 0, "", "listener") == \
        "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
    assert wire.entity_token(2, "aac3178e146ba6f1fc6e6a4085e77f21", 0, 10, wire.SUBSCRIPTION, "", "listener",
                             "/chatter", STRING, wire.Qos(depth=10)) == (
        "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/std_msgs::msg::dds_::String_/"
        f"{STRING_HASH}/::,10:,:,:,,")
    assert wire.entity_token(2, "8b20917502ee955ac4476e0266340d5c", 0, 10, wire.PUBLISHER, "", "talker",
                             "/chatter", STRING, wire.Qos(depth=7)) == (
        "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/"
        f"{STRING_HASH}/::,7:,:,:,,")


def test_a_namespaced_token_mangles_namespace_and_topic_and_is_a_key_expression():
    node = wire.node_token(0, "ab12", 0, "/robot1", "lrfslam")
    pub = wire.entity_token(0, "ab12", 0, 3, wire.PUBLISHER, "/robot1", "lrfslam", "/robot1/scan", wire.LASER_SCAN,
                            wire.STREAM_QOS)
    assert node == "@ros2_lv/0/ab12/0/0/NN/%/%robot1/lrfslam"
    assert pub.split("/")[5:10] == ["MP", "%", "%robot1", "lrfslam", "%robot1%scan"]
    # rmw_zenoh's parser: no empty part, 13 parts for an entity, 9 for a node.
    assert len(pub.split("/")) == 13 and all(pub.split("/")) and len(node.split("/")) == 9
    for token in (node, pub):
        assert str(zenoh.KeyExpr(token)) == token
    with pytest.raises(ConfigError):
        wire.entity_token(0, "ab12", 0, 3, "SS", "/robot1", "lrfslam", "/robot1/scan", wire.LASER_SCAN, wire.Qos())


@pytest.mark.parametrize(("qos", "text"), [
    (wire.Qos(), "::,:,:,:,,"),                          # all rmw_zenoh's defaults: every field empty
    (wire.STREAM_QOS, "::,10:,:,:,,"),
    (wire.SENSOR_QOS, "2::,5:,:,:,,"),                   # BEST_EFFORT = 2
    (wire.LATCHED_QOS, ":1:,1:,:,:,,"),                  # TRANSIENT_LOCAL = 1
    (wire.Qos(history=wire.KEEP_ALL), "::2,:,:,:,,"),
])
def test_qos_strings(qos, text):
    assert qos.keyexpr() == text
    assert len(text.split(":")) == 6   # rel, dur, hist+depth, deadline, lifespan, liveliness


def test_the_attachment_is_33_bytes_little_endian():
    gid = bytes(range(16))
    att = wire.attachment(7, 1_700_000_000_123_456_789, gid)
    assert len(att) == 33
    assert struct.unpack_from("<q", att, 0)[0] == 7
    assert struct.unpack_from("<q", att, 8)[0] == 1_700_000_000_123_456_789
    assert att[16] == 0x10 and att[17:] == gid
    assert wire.parse_attachment(att) == (7, 1_700_000_000_123_456_789, gid)


@pytest.mark.parametrize("data", [None, b"", bytes(32), bytes(34), bytes(16) + b"\x0f" + bytes(16)])
def test_other_attachments_are_refused(data):
    with pytest.raises(InputError):
        wire.parse_attachment(data)
    with pytest.raises(ConfigError):
        wire.attachment(1, 2, bytes(15))


def test_a_gid_is_16_bytes_one_per_token():
    a, b = wire.gid("@ros2_lv/0/x/0/1/MP/%/%/n/%a/t/h/q"), wire.gid("@ros2_lv/0/x/0/2/MP/%/%/n/%a/t/h/q")
    assert len(a) == len(b) == 16 and a != b and a == wire.gid("@ros2_lv/0/x/0/1/MP/%/%/n/%a/t/h/q")


@pytest.mark.parametrize(("robot", "ns"), [
    ("robot1", "robot1"), ("mit-csail", "mit_csail"), ("1robot", "r1robot"), ("a.b-c", "a_b_c"),
    ("intel__lab", "intel_lab"), ("-x-", "_x_"), ("9", "r9"),
])
def test_the_namespace_rule(robot, ns):
    assert wire.namespace_of(robot) == ns


ROBOTS = st.from_regex(r"[A-Za-z0-9_\-.]{1,20}", fullmatch=True)   # what topics.check_robot accepts


@given(ROBOTS)
def test_every_robot_gets_a_valid_ros_name(robot):
    topics.check_robot(robot)
    ns = wire.namespace_of(robot)
    assert wire.is_ros_name(ns) and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", ns) and "__" not in ns
    assert wire.check_namespace(ns) == "/" + ns
    assert wire.namespace_of(ns) == ns   # the rule applied twice changes nothing


@given(st.from_regex(r"[A-Za-z][A-Za-z0-9]{0,8}(_[A-Za-z0-9]{1,8}){0,3}", fullmatch=True))
def test_a_valid_ros_name_is_its_own_namespace(robot):
    assert wire.namespace_of(robot) == robot


@given(st.lists(st.sampled_from("ab1"), min_size=1, max_size=6), st.data())
def test_robots_differing_only_in_forbidden_characters_collide(chars, data):
    """The documented collision: '-', '.' and '_' (and runs of them) give one namespace."""
    def spell():
        seps = data.draw(st.lists(st.sampled_from(["-", ".", "_", "-.", "__"]), min_size=len(chars),
                                  max_size=len(chars)))
        return "x" + "".join(s + c for s, c in zip(seps, chars, strict=True))
    assert wire.namespace_of(spell()) == wire.namespace_of(spell())


@pytest.mark.parametrize("bad", ["", "/", "1x", "a__b", "a-b", "/a//b", "a/"])
def test_a_given_namespace_must_be_a_ros_namespace(bad):
    with pytest.raises(ConfigError):
        wire.check_namespace(bad)


def test_a_given_namespace_is_fully_qualified():
    assert wire.check_namespace("fleet/robot_1") == "/fleet/robot_1"
