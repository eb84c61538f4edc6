"""The one registry of key expressions.

Every key lives under ``lrf/<robot>/`` so several robots share one Zenoh
network. The registry holds relative names; :func:`key` prefixes them. MCAP
channels use the relative name as topic and keep the robot in the file metadata.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Generic, TypeVar

from lrfslam.errors import ConfigError
from lrfslam.msgs import codec as c

T = TypeVar("T")

ROOT = "lrf"
_ROBOT_RE = re.compile(r"^[A-Za-z0-9_\-.]+$")


PRIORITIES = ("real_time", "interactive_high", "interactive_low", "data_high", "data", "data_low", "background")


@dataclass(frozen=True)
class Delivery:
    """How Zenoh carries a topic: the publisher's QoS (docs/delivery.md has the table and the measurements).

    ``congestion`` is what a publisher does when its transmit queue is full: ``"drop"`` the
    sample (the consumers count the gap in the sequence numbers) or ``"block"`` the put (Zenoh
    closes the link after 5 s of it). ``priority`` is a Zenoh priority name, highest first in
    :data:`PRIORITIES`; ``express`` sends at once instead of batching.
    """

    reliable: bool = True
    congestion: str = "drop"
    priority: str = "data"
    express: bool = False

    def __post_init__(self) -> None:
        if self.congestion not in ("drop", "block") or self.priority not in PRIORITIES:
            raise ConfigError(f"bad delivery policy {self}")


#: Sensor-rate streams: never stall a producer (the sensor's serial reader least of all); a
#: sample Zenoh cannot queue is dropped, and every consumer counts it as a gap.
STREAM = Delivery()
#: Low-rate, large, needed whole (the mapper's keyframes): wait for room rather than lose one,
#: below the streams' priority so a megabyte snapshot never delays a scan.
SNAPSHOT = Delivery(congestion="block", priority="data_low")
#: Health: small, once a second, needed most when the network is busiest: ahead of the data,
#: unbatched. Dropping one is harmless (the next follows in a second) and counted.
HEALTH = Delivery(priority="data_high", express=True)


@dataclass(frozen=True)
class Topic(Generic[T]):
    """A data stream: relative key, codec, and its delivery policy."""

    name: str
    codec: c.Codec[T]
    delivery: Delivery = STREAM

    @property
    def schema(self) -> str:
        return self.codec.schema


SCAN: Topic = Topic("scan", c.LASER_SCAN)
ODOM: Topic = Topic("odom", c.ODOMETRY)
SCAN_FILTERED: Topic = Topic("scan/filtered", c.FILTERED_SCAN)
FEATURES: Topic = Topic("features", c.FEATURES)
SLAM_STATE: Topic = Topic("slam/state", c.SLAM_STATE)
#: The whole landmark map, at a low rate (slam/state carries the changes): a replica heals on
#: the next one, so a lost one costs seconds of staleness, not a stalled filter.
SLAM_MAP: Topic = Topic("slam/map", c.LANDMARK_MAP)
TRUTH: Topic = Topic("truth", c.GROUND_TRUTH)
MAP_POSE: Topic = Topic("map/pose", c.MAP_POSE)
MAP_KEYFRAMES: Topic = Topic("map/keyframes", c.MAP_KEYFRAMES, SNAPSHOT)
#: The live occupancy grid's changed tiles, once a second of data at most; a lost one leaves
#: tiles stale until they change again, so it waits for room like the keyframes.
MAP_GRID: Topic = Topic("map/grid", c.MAP_GRID, SNAPSHOT)

#: Data topics in pipeline order.
DATA_TOPICS: tuple[Topic, ...] = (SCAN, ODOM, TRUTH, SCAN_FILTERED, FEATURES, SLAM_STATE, SLAM_MAP, MAP_POSE,
                                   MAP_KEYFRAMES, MAP_GRID)


def health(service: str) -> Topic:
    """Periodic status of ``service``."""
    return Topic(f"health/{service}", c.SERVICE_STATUS, HEALTH)


def is_health(name: str) -> bool:
    """Whether relative key ``name`` is a service's periodic status."""
    return name.startswith("health/")


def by_name(name: str) -> Topic:
    """Topic for a relative key (data topics and ``health/<service>``)."""
    for topic in DATA_TOPICS:
        if topic.name == name:
            return topic
    if is_health(name):
        return health(name.split("/", 1)[1])
    raise KeyError(name)


#: MCAP topics (and WebSocket channels) of Foxglove's views of the topics above: Foxglove's
#: well-known schemas made from the lrfslam messages (lrfslam/viz/foxglove.py, docs/monitoring.md).
#: They never travel on Zenoh; the lrfslam channels stay the source of truth.
FOXGLOVE_PREFIX = "/foxglove/"
#: The view of the services' health: stamped, like it, by the wall clock.
FOXGLOVE_LOG = FOXGLOVE_PREFIX + "log"


def is_foxglove(name: str) -> bool:
    """Whether MCAP topic ``name`` is one of Foxglove's views (derived, not a key of the robot)."""
    return name.startswith(FOXGLOVE_PREFIX)


def on_wall_clock(name: str) -> bool:
    """Whether MCAP topic ``name`` is stamped by the wall clock (health and its view), not by the data."""
    return is_health(name) or name == FOXGLOVE_LOG


def check_robot(robot: str) -> str:
    """Return ``robot`` if it is a single key chunk, else raise ConfigError."""
    if not _ROBOT_RE.match(robot or ""):
        raise ConfigError(f"robot name {robot!r} must be one key chunk of letters, digits, '_', '-', '.'")
    return robot


def key(robot: str, name: str) -> str:
    """Absolute key expression of relative ``name`` for ``robot``."""
    return f"{ROOT}/{robot}/{name}"


def relative(robot: str, key_expr: str) -> str:
    """Relative name of an absolute key of ``robot``."""
    prefix = f"{ROOT}/{robot}/"
    if not key_expr.startswith(prefix):
        raise KeyError(key_expr)
    return key_expr[len(prefix):]


def everything(robot: str) -> str:
    """Key expression matching every data and health key of ``robot``."""
    return f"{ROOT}/{robot}/**"


#: Stands for "every service" (or "every robot") in the key expressions below.
ANY = "*"


def alive(robot: str, service: str) -> str:
    """Liveliness token of a running service (``service=ANY``: every service's)."""
    return f"{ROOT}/{robot}/alive/{service}"


def status(robot: str, service: str) -> str:
    """Status queryable of a running service (``service=ANY``: every service's)."""
    return f"{ROOT}/{robot}/svc/{service}/status"


def latest(robot: str, name: str) -> str:
    """Queryable of the newest message on relative key ``name`` (e.g. ``slam/state``), answered by its
    producer so a viewer that joins late draws the current state at once (``name="**"``: every one).

    Not under ``lrf/<robot>/<name>``: a subscriber to the robot's data (the recorder's ``**``) must never
    see these replies as a second copy of the stream.
    """
    return f"{ROOT}/{robot}/latest/{name}"


def health_key(robot: str, service: str) -> str:
    """Absolute key of ``service``'s periodic status (``service=ANY``: every service's)."""
    return key(robot, health(service).name)


def robot_and_service(key_expr: str) -> tuple[str, str]:
    """``(robot, service)`` of an :func:`alive`, :func:`status` or :func:`health_key` key.

    Raises
    ------
    KeyError
        ``key_expr`` is none of those.
    """
    parts = str(key_expr).split("/")
    if len(parts) == 4 and parts[0] == ROOT and parts[2] in ("alive", "health"):
        return parts[1], parts[3]
    if len(parts) == 5 and parts[0] == ROOT and parts[2] == "svc" and parts[4] == "status":
        return parts[1], parts[3]
    raise KeyError(key_expr)
