"""rmw_zenoh's wire format: data keys, liveliness tokens, QoS strings, the attachment, ROS names.

What a plain Zenoh program must send for ROS 2 nodes using rmw_zenoh (Jazzy ≥ 0.2.4, Kilted,
Rolling ≥ 0.6.0) to take its samples and list its node and topics (docs/ros2.md; the layout is
rmw_zenoh's design document, ``design.md``, and ``liveliness_utils.cpp``):

- data key ``<domain_id>/<topic without its leading '/'>/<DDS type name>/<RIHS01 type hash>``,
  e.g. ``0/robot1/scan/sensor_msgs::msg::dds_::LaserScan_/RIHS01_64c1…``;
- node token ``@ros2_lv/<domain>/<zid>/<node id>/<node id>/NN/<enclave>/<namespace>/<node>``, and
  per publisher (``MP``) or subscription (``MS``)
  ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/MP/<enclave>/<namespace>/<node>/<topic>/<type>/<hash>/<qos>``,
  names *mangled* (every ``/`` a ``%``; an empty one ``%``);
- a 33-byte attachment on every sample: sequence number (int64 LE), source timestamp (int64 LE,
  ns since the epoch), 0x10, the publisher's 16-byte GID. Samples without it are dropped.

Type hashes come from rosbags' Jazzy type store (``Typestore.hash_rihs01``); Humble's literal
``TypeHashNotSupported`` is not spoken.
"""

from __future__ import annotations

import functools
import hashlib
import re
import struct
from dataclasses import dataclass

from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from lrfslam.errors import ConfigError, InputError

#: The ROS 2 distribution whose message definitions (and so type hashes) are used.
STORE = Stores.ROS2_JAZZY

LASER_SCAN = "sensor_msgs/msg/LaserScan"
ODOMETRY = "nav_msgs/msg/Odometry"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"
POSE_WITH_COVARIANCE_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"

LIVELINESS_ROOT = "@ros2_lv"
NODE, PUBLISHER, SUBSCRIPTION = "NN", "MP", "MS"

#: rmw's QoS enum values (rmw/types.h).
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2

_ATTACHMENT = struct.Struct("<qqB16s")
GID_SIZE = 16
ATTACHMENT_SIZE = _ATTACHMENT.size   # 33

_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


@functools.cache
def typestore() -> Typestore:
    """rosbags' type store of :data:`STORE` (made once)."""
    return get_typestore(STORE)


def dds_type_name(msgtype: str) -> str:
    """``sensor_msgs::msg::dds_::LaserScan_`` for ``sensor_msgs/msg/LaserScan``."""
    package, kind, name = msgtype.split("/")
    return f"{package}::{kind}::dds_::{name}_"


@functools.cache
def type_hash(msgtype: str) -> str:
    """The type's RIHS01 hash (``RIHS01_`` and 64 hex digits), as rosidl makes it."""
    return typestore().hash_rihs01(msgtype)


def data_key(domain_id: int, topic: str, msgtype: str) -> str:
    """The key expression samples of ``topic`` (a fully qualified name, ``/robot1/scan``) travel on."""
    return f"{int(domain_id)}/{topic.strip('/')}/{dds_type_name(msgtype)}/{type_hash(msgtype)}"


def mangle(name: str) -> str:
    """A name as one key chunk: every ``/`` a ``%``; an empty name ``%``."""
    return name.replace("/", "%") or "%"


@dataclass(frozen=True)
class Qos:
    """A ROS 2 QoS profile as far as the liveliness token tells it (rmw enum values, depth in samples).

    ``keyexpr`` leaves a field empty where it equals rmw_zenoh's default (RELIABLE, VOLATILE,
    KEEP_LAST, depth 42); deadline, lifespan and liveliness are always the defaults here.
    """

    reliability: int = RELIABLE
    durability: int = VOLATILE
    history: int = KEEP_LAST
    depth: int = 42

    def keyexpr(self) -> str:
        """``rel:dur:hist,depth:dl_s,dl_ns:ls_s,ls_ns:liv,liv_s,liv_ns``, e.g. ``::,7:,:,:,,``."""
        default = Qos()

        def field(name: str) -> str:
            value = getattr(self, name)
            return "" if value == getattr(default, name) else str(value)
        return (f"{field('reliability')}:{field('durability')}:{field('history')},{field('depth')}"
                ":,:,:,,")


#: A stream: every sample to whoever listens now (RViz's and ``ros2 topic echo``'s defaults take it).
STREAM_QOS = Qos(depth=10)
#: The sensor-data profile (rclcpp's SensorDataQoS) for what this node subscribes to: takes
#: reliable and best-effort publishers alike.
SENSOR_QOS = Qos(reliability=BEST_EFFORT, depth=5)
#: Latched: the last sample kept for a late subscriber (``/tf_static``, ``/map``).
LATCHED_QOS = Qos(durability=TRANSIENT_LOCAL, depth=1)
#: ``/tf``: tf2's broadcaster depth.
TF_QOS = Qos(depth=100)


def node_token(domain_id: int, zid: str, node_id: int, namespace: str, node: str, enclave: str = "") -> str:
    """The liveliness token that makes ``node`` appear in ``ros2 node list``.

    ``zid``: the session's Zenoh id (hex); ``namespace``: ``/robot1`` or ``""`` (the root).
    """
    return (f"{LIVELINESS_ROOT}/{int(domain_id)}/{zid}/{node_id}/{node_id}/{NODE}/{mangle(enclave)}/"
            f"{mangle(namespace)}/{node}")


def entity_token(domain_id: int, zid: str, node_id: int, entity_id: int, kind: str, namespace: str, node: str,
                 topic: str, msgtype: str, qos: Qos, enclave: str = "") -> str:
    """The liveliness token of a publisher (``kind`` :data:`PUBLISHER`) or subscription
    (:data:`SUBSCRIPTION`) of ``node`` on ``topic`` (fully qualified): what ``ros2 topic list`` reads."""
    if kind not in (PUBLISHER, SUBSCRIPTION):
        raise ConfigError(f"entity kind must be {PUBLISHER} or {SUBSCRIPTION}, got {kind!r}")
    return (f"{LIVELINESS_ROOT}/{int(domain_id)}/{zid}/{node_id}/{entity_id}/{kind}/{mangle(enclave)}/"
            f"{mangle(namespace)}/{node}/{mangle(topic)}/{dds_type_name(msgtype)}/{type_hash(msgtype)}/"
            f"{qos.keyexpr()}")


def gid(token: str) -> bytes:
    """A 16-byte GID for the entity of liveliness token ``token``.

    rmw_zenoh hashes the token with XXH3-128; this uses BLAKE2b-128 (the standard library's),
    so the bytes differ from what rmw_zenoh would compute for the same token. Subscribers use the
    GID only to tell publishers apart (``message_info.publisher_gid``), never check it.
    """
    return hashlib.blake2b(token.encode(), digest_size=GID_SIZE).digest()


def attachment(seq: int, stamp_ns: int, publisher_gid: bytes) -> bytes:
    """The 33-byte attachment of a sample: ``seq`` (the publisher's count, from 1), ``stamp_ns`` (the
    source timestamp, ns since the epoch), 0x10 and ``publisher_gid`` (16 bytes)."""
    if len(publisher_gid) != GID_SIZE:
        raise ConfigError(f"a GID is {GID_SIZE} bytes, got {len(publisher_gid)}")
    return _ATTACHMENT.pack(int(seq), int(stamp_ns), GID_SIZE, publisher_gid)


def parse_attachment(data: bytes | None) -> tuple[int, int, bytes]:
    """``(seq, stamp_ns, gid)`` of a 33-byte attachment.

    Raises
    ------
    InputError
        None, another length (an rmw_zenoh before Jazzy 0.2.4 sends a labelled, longer
        layout) or a GID length byte other than 16.
    """
    if data is None or len(data) != ATTACHMENT_SIZE:
        raise InputError(f"attachment of {0 if data is None else len(data)} bytes, not the {ATTACHMENT_SIZE} of "
                         "rmw_zenoh >= 0.2.4")
    seq, stamp_ns, size, publisher_gid = _ATTACHMENT.unpack(data)
    if size != GID_SIZE:
        raise InputError(f"attachment GID length {size}, not {GID_SIZE}")
    return seq, stamp_ns, publisher_gid


def namespace_of(robot: str) -> str:
    """The ROS namespace token for robot name ``robot`` (``lrf/<robot>/...``).

    The rule: every character other than ``A-Z a-z 0-9 _`` becomes ``_``, runs of ``_``
    become one, and a name that then starts with a digit gets an ``r`` in front
    (``mit-csail`` -> ``mit_csail``, ``1robot`` -> ``r1robot``). A valid ROS name without a
    double underscore stays as it is. Robots whose names differ only in the characters replaced
    (``mit-csail``, ``mit.csail``, ``mit_csail``), or by that ``r`` (``1robot``, ``r1robot``),
    get one namespace: two of them on one router need ``--namespace``.
    """
    out = re.sub(r"_+", "_", re.sub(r"[^A-Za-z0-9_]", "_", robot))
    if not out:
        raise ConfigError("a robot name cannot be empty")
    return "r" + out if out[0].isdigit() else out


def check_namespace(namespace: str) -> str:
    """``namespace`` as a fully qualified ROS namespace (``/robot1``, ``/fleet/robot1``).

    Raises
    ------
    ConfigError
        A token is empty, starts with a digit, holds a character other than ``A-Z a-z 0-9 _``,
        or a double underscore.
    """
    tokens = namespace.removeprefix("/").split("/")
    for token in tokens:
        if not is_ros_name(token):
            raise ConfigError(f"namespace {namespace!r}: {token!r} is not a ROS name (letters, digits and single "
                              "underscores, not starting with a digit)")
    return "/" + "/".join(tokens)


def is_ros_name(token: str) -> bool:
    """Whether ``token`` is one valid ROS name token without a double underscore."""
    return bool(_TOKEN.fullmatch(token)) and "__" not in token
