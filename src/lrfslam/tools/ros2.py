"""``lrfslam ros2``: the robot seen by ROS 2 over rmw_zenoh, and a ROS 2 robot's scans into the pipeline.

    lrfslam ros2 --connect tcp/ROBOT:7447 [--robot R] [--domain-id 0] [--namespace NS]
    lrfslam ros2 --subscribe [--scan-topic /NS/scan] [--odom-topic /NS/odom] ...

Joins the robot's Zenoh network as a client, as ``lrfslam monitor`` does, and speaks rmw_zenoh's
wire format there (src/lrfslam/ros2/wire.py), so a ROS 2 machine using ``rmw_zenoh_cpp`` on the same
router sees a node ``/<ns>/lrfslam`` and its topics (docs/ros2.md).

Publishing (the default): subscribes to the robot's ``scan``, ``scan/filtered``, ``odom``,
``slam/state``, ``slam/map``, ``map/pose`` and ``map/grid`` and publishes their ROS 2 views
(src/lrfslam/ros2/views.py): ``/<ns>/scan``, ``/<ns>/scan_filtered``, ``/<ns>/odom``, ``/<ns>/pose``,
``/<ns>/landmarks``, ``/tf``, and transient local ``/tf_static`` and ``/<ns>/map``, each on its data key with a CDR
payload and the 33-byte attachment (its sequence number, the data stamp as source timestamp, the
publisher's GID), after declaring the node's liveliness token and one per publisher. Joining late, it
asks the ``latest`` queryables for the current SLAM state, landmark map, map pose and whole grid first.

``--subscribe``: the other way. Declares the node with a subscription token for each topic (default
``/<ns>/scan``, ``sensor_msgs/msg/LaserScan``, and ``/<ns>/odom``, ``nav_msgs/msg/Odometry``), takes
their samples on the rmw_zenoh data keys, converts them (src/lrfslam/ros2/convert.py: any 2D laser)
and publishes them as the robot's ``scan`` and ``odom``, numbered 1, 2, 3, … under this process's
producer id, as the sensor or ``lrfslam play`` do; the recorder records them like any sensor's.
It refuses to start while a service of the robot publishing those topics (a sensor) is alive.

Counters (logged at the end): samples received, published, and what was dropped (the queue full)
or could not be converted, by kind (``error.decode``: not CDR of the type; ``error.input``: values
refused; ``attachment.other``: a sample without rmw_zenoh's 33-byte attachment, converted anyway);
each kind of bad input is logged once.

With ``--health-file`` it rewrites FILE every health period as a service does, for a container's
healthcheck (``lrfslam status --check-file FILE``).

Exit codes: 0 stopped by SIGTERM or Ctrl-C; 2 bad usage, a refused start, or the Zenoh session
could not start (one line).
"""

from __future__ import annotations

import argparse
import logging
import os
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass

import zenoh
import zenoh.ext

from lrfslam.errors import ConfigError, DecodeError, InputError, LrfSlamError
from lrfslam.msgs import counters, topics
from lrfslam.msgs import types as t
from lrfslam.ros2 import convert, wire
from lrfslam.ros2.views import PUBLISHED, SUBSCRIBED, RosTopic, RosViews
from lrfslam.runtime import health_file
from lrfslam.runtime.bus import (
    BusConfig,
    ZenohBus,
    closing,
    connected,
    open_session,
    zenoh_config,
)
from lrfslam.runtime.decoding import LogOnce
from lrfslam.runtime.runner import (
    install_signal_handlers,
    live_services,
    setup_logging,
    stopped_cleanly,
)
from lrfslam.runtime.step import Output
from lrfslam.tools.play import check_collisions
from lrfslam.tools.status import query_latest

log = logging.getLogger("lrfslam.ros2")

#: The ROS node's name (in the namespace): ``/<ns>/lrfslam``.
NODE_NAME = "lrfslam"
#: The robot's topics the publishing bridge takes.
INPUTS = (topics.SCAN, topics.SCAN_FILTERED, topics.ODOM, topics.SLAM_STATE, topics.SLAM_MAP, topics.MAP_POSE,
          topics.MAP_GRID)
#: The topics whose newest message a late bridge asks for (``topics.latest``; the grid: whole).
CATCH_UP = (topics.SLAM_MAP, topics.SLAM_STATE, topics.MAP_POSE, topics.MAP_GRID)
#: Samples taken from ROS 2 waiting to be converted, at most.
QUEUE_SIZE = BusConfig.queue_size


@dataclass(frozen=True)
class Ros2Config:
    """What the bridge speaks: ROS domain ``domain_id``, namespace ``namespace`` (fully qualified,
    ``/robot1``), and with ``subscribe`` the ROS topics (fully qualified) of the scans and odometry."""

    domain_id: int = 0
    namespace: str = ""
    subscribe: bool = False
    scan_topic: str = ""
    odom_topic: str = ""

    def __post_init__(self) -> None:
        if not 0 <= self.domain_id <= 232:
            raise ConfigError(f"--domain-id must be 0..232 (ROS 2's range), got {self.domain_id}")


class RosNode:
    """A ROS 2 node as rmw_zenoh announces it: its liveliness token, and a token and a GID per
    publisher or subscription, all undeclared by :meth:`close`."""

    def __init__(self, session: zenoh.Session, cfg: Ros2Config) -> None:
        self.session, self.cfg = session, cfg
        self.zid = str(session.zid())
        self._next_id = 1
        self._tokens = [session.liveliness().declare_token(
            wire.node_token(cfg.domain_id, self.zid, 0, cfg.namespace, NODE_NAME))]

    def entity(self, kind: str, topic: str, msgtype: str, qos: wire.Qos) -> bytes:
        """Declare a publisher's or subscription's token on fully qualified ``topic``; its GID."""
        token = wire.entity_token(self.cfg.domain_id, self.zid, 0, self._next_id, kind, self.cfg.namespace,
                                  NODE_NAME, topic, msgtype, qos)
        self._next_id += 1
        self._tokens.append(self.session.liveliness().declare_token(token))
        return wire.gid(token)

    def close(self) -> None:
        for token in self._tokens:
            token.undeclare()


class RosPublisher:
    """One ROS 2 publisher: its data key, its token, and the attachment's sequence numbers.

    A latched topic (transient local) is a zenoh-ext advanced publisher keeping its last sample
    for late subscribers, as rmw_zenoh makes one.
    """

    def __init__(self, node: RosNode, topic: RosTopic) -> None:
        self.name = topic.qualified(node.cfg.namespace)
        self.gid = node.entity(wire.PUBLISHER, self.name, topic.msgtype, topic.qos)
        key = wire.data_key(node.cfg.domain_id, self.name, topic.msgtype)
        if topic.latched:
            self._pub = zenoh.ext.declare_advanced_publisher(
                node.session, key, cache=zenoh.ext.CacheConfig(max_samples=topic.qos.depth), publisher_detection=True)
        else:
            self._pub = node.session.declare_publisher(key)
        self.seq = 0

    def put(self, message, stamp_ns: int) -> None:
        self.seq += 1
        self._pub.put(convert.serialize(message), attachment=wire.attachment(self.seq, stamp_ns, self.gid))

    def close(self) -> None:
        self._pub.undeclare()


class Publishing:
    """The robot's messages as ROS 2 topics (the module's docstring)."""

    def __init__(self, session: zenoh.Session, bus_cfg: BusConfig, cfg: Ros2Config, counts: Counter) -> None:
        self.session, self.robot, self.counts = session, bus_cfg.robot, counts
        self.views = RosViews(cfg.namespace)
        self.node = RosNode(session, cfg)
        self.publishers = {topic.name: RosPublisher(self.node, topic) for topic in PUBLISHED}
        self.bus = ZenohBus(session, self.robot, INPUTS, False, bus_cfg.queue_size, counts)
        self._once = LogOnce(log)

    def catch_up(self, timeout_s: float = 2.0) -> None:
        """The newest landmark map, SLAM state and map pose, and the whole grid, that the services keep for late joiners."""
        for topic in CATCH_UP:
            for _, value in query_latest(self.session, self.robot, topic, timeout_s):
                if isinstance(value, DecodeError):
                    self.counts["catch_up.undecodable"] += 1
                    self._once.warning("catch_up", topic.name, "the newest %s does not decode: %s", topic.name, value)
                    continue
                self.counts["catch_up"] += 1
                self.hand_on(topic.name, value)

    def hand_on(self, name: str, value) -> None:
        for pub in self.views.on_message(name, value):
            self.publishers[pub.topic.name].put(pub.message, pub.stamp_ns)
            self.counts[f"{counters.OUT}{pub.topic.qualified(self.views.namespace)}"] += 1

    def step(self, timeout_s: float) -> None:
        msg = self.bus.get(timeout_s)
        if msg is not None:
            self.hand_on(msg.topic.name, msg.value)

    def close(self) -> None:
        self.counts.update(self.bus.receive_counts())
        self.bus.close()
        for pub in self.publishers.values():
            pub.close()
        self.node.close()


class Subscribing:
    """A ROS 2 robot's scans and odometry into the pipeline (the module's docstring)."""

    def __init__(self, session: zenoh.Session, bus_cfg: BusConfig, cfg: Ros2Config, counts: Counter) -> None:
        self.cfg, self.counts = cfg, counts
        scan_topic, odom_topic = SUBSCRIBED
        self.wanted = {cfg.scan_topic or scan_topic.qualified(cfg.namespace): (scan_topic, topics.SCAN),
                       cfg.odom_topic or odom_topic.qualified(cfg.namespace): (odom_topic, topics.ODOM)}
        self.bus = ZenohBus(session, bus_cfg.robot, (), False, 1, counts)
        self.node = RosNode(session, cfg)
        self._queue: deque[tuple[str, bytes, bytes | None]] = deque()
        self._ready = threading.Condition(threading.Lock())
        self._dropped = 0
        self._seq: Counter = Counter()
        self._once = LogOnce(log)
        self._subs = []
        for name, (ros, _) in self.wanted.items():
            self.node.entity(wire.SUBSCRIPTION, name, ros.msgtype, ros.qos)
            self._subs.append(session.declare_subscriber(wire.data_key(cfg.domain_id, name, ros.msgtype),
                                                         self._receiver(name)))
        for ours in (topics.SCAN, topics.ODOM):
            self.bus.publisher(ours)

    def _receiver(self, name: str):
        def on_sample(sample: zenoh.Sample) -> None:   # Zenoh's thread: queue only
            att = sample.attachment
            item = (name, sample.payload.to_bytes(), att.to_bytes() if att is not None else None)
            with self._ready:
                if len(self._queue) >= QUEUE_SIZE:
                    self._dropped += 1
                    return
                self._queue.append(item)
                self._ready.notify()
        return on_sample

    def step(self, timeout_s: float) -> None:
        with self._ready:
            if not self._queue and not self._ready.wait_for(lambda: self._queue, timeout_s):
                return
            name, payload, att = self._queue.popleft()
        ros, ours = self.wanted[name]
        self.counts[f"{counters.IN}{name}"] += 1
        try:
            wire.parse_attachment(att)
        except InputError as exc:
            self.counts["attachment.other"] += 1
            self._once.warning("attachment", name, "samples on %s: %s (converted anyway)", name, exc)
        try:
            msg = convert.deserialize(payload, ros.msgtype)
        except InputError as exc:
            self.counts[counters.ERROR_DECODE] += 1
            self._once.warning(counters.ERROR_DECODE, name, "skipping samples on %s: %s", name, exc)
            return
        self._seq[ours.name] += 1
        try:
            value = (convert.scan_from_ros(msg, self._seq[ours.name], self.cfg.namespace, f"ros2:{name}")
                     if ours is topics.SCAN else convert.odometry_from_ros(msg, self._seq[ours.name], self.cfg.namespace))
        except InputError as exc:
            self._seq[ours.name] -= 1
            self.counts[counters.ERROR_INPUT] += 1
            self._once.warning(counters.ERROR_INPUT, name, "skipping samples on %s: %s", name, exc)
            return
        self.bus.publish(Output(ours, value))

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
        with self._ready:
            if self._dropped:
                self.counts[counters.DROP_QUEUE] += self._dropped
        self.bus.close()
        self.node.close()


def run(bus_cfg: BusConfig, cfg: Ros2Config, stop: threading.Event, counts: Counter) -> int:
    """The bridge until ``stop`` is set; waits for the router while it is unreachable.

    Raises
    ------
    ConfigError
        ``--subscribe`` while a live service of the robot publishes ``scan`` or ``odom``.
    """
    zenoh.init_log_from_env_or("error")
    conf = zenoh_config(bus_cfg)
    # A transient-local publisher (zenoh-ext's advanced one, as rmw_zenoh makes it) stamps its samples.
    conf.insert_json5("timestamping/enabled", "true")
    session = open_session(conf, stop, bus_cfg.connect)
    if session is None:
        return 0
    with closing(session):
        if cfg.subscribe:
            check_collisions((topics.SCAN, topics.ODOM), live_services(session, bus_cfg.robot))
            bridge: Publishing | Subscribing = Subscribing(session, bus_cfg, cfg, counts)
            log.info("node %s/%s on ROS domain %d: %s into robot %s's scan and odom", cfg.namespace, NODE_NAME,
                     cfg.domain_id, " and ".join(bridge.wanted), bus_cfg.robot)
        else:
            bridge = Publishing(session, bus_cfg, cfg, counts)
            log.info("node %s/%s on ROS domain %d: robot %s's topics as %s", cfg.namespace, NODE_NAME,
                     cfg.domain_id, bus_cfg.robot, ", ".join(bridge.publishers[t.name].name for t in PUBLISHED))
            bridge.catch_up()
        next_health = 0.0
        try:
            while not stop.is_set():
                bridge.step(0.1)
                if bus_cfg.health_file and (now := time.monotonic()) >= next_health:
                    next_health = now + bus_cfg.health_period_s
                    write_health(session, bus_cfg, counts)
        finally:
            bridge.close()
    return 0


def write_health(session: zenoh.Session, bus_cfg: BusConfig, counts: Counter) -> None:
    """The health file (``--health-file``), as a service writes it: rewritten while the loop turns, and
    whether the session still has its router. One that cannot be written is counted and logged once."""
    try:
        health_file.write(bus_cfg.health_file, health_file.HealthRecord(
            "ros2", bus_cfg.robot, t.HEALTH_OK, f"{sum(v for k, v in counts.items() if k.startswith(counters.OUT))} "
            "messages published", time.time_ns(), bus_cfg.health_period_s, connected(session), os.getpid()))
    except OSError as exc:
        if not counts[counters.ERROR_HEALTH_FILE]:
            log.warning("cannot write the health file: %s", exc)
        counts[counters.ERROR_HEALTH_FILE] += 1


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="lrfslam ros2", description=__doc__.splitlines()[0])
    p.add_argument("-e", "--connect", action="append", metavar="ENDPOINT",
                   help="the robot's Zenoh router, which the ROS 2 machines use too (repeatable; default "
                        "tcp/127.0.0.1:7447)")
    p.add_argument("--robot", default=BusConfig.robot, help="robot namespace (keys lrf/<robot>/...)")
    p.add_argument("--domain-id", type=int, default=0, help="ROS_DOMAIN_ID of the ROS 2 side (default 0)")
    p.add_argument("--namespace", help="ROS namespace (default: from the robot name: characters other than letters, "
                                       "digits and _ become _, runs of _ one, a leading digit gets an r)")
    p.add_argument("--subscribe", action="store_true",
                   help="the other way: a ROS 2 robot's LaserScan and Odometry into this robot's scan and odom")
    p.add_argument("--scan-topic", help="with --subscribe: the LaserScan topic (default /<ns>/scan)")
    p.add_argument("--odom-topic", help="with --subscribe: the Odometry topic (default /<ns>/odom)")
    p.add_argument("--zenoh-config", metavar="FILE", help="Zenoh JSON5 config applied first (TLS, ...)")
    p.add_argument("--health-file", metavar="FILE",
                   help="also write the bridge's health to FILE every second, for a container healthcheck: "
                        "lrfslam status --check-file FILE")
    p.add_argument("--log-level", default=None, help="DEBUG, INFO, WARNING, ERROR")
    return p


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    setup_logging("ros2", args.log_level)
    stop = threading.Event()
    install_signal_handlers(stop)
    counts: Counter = Counter()
    try:
        if (args.scan_topic or args.odom_topic) and not args.subscribe:
            raise ConfigError("--scan-topic and --odom-topic are for --subscribe")
        robot = topics.check_robot(args.robot)
        cfg = Ros2Config(domain_id=args.domain_id, subscribe=args.subscribe,
                         namespace=wire.check_namespace(args.namespace or wire.namespace_of(robot)),
                         scan_topic=wire.check_namespace(args.scan_topic) if args.scan_topic else "",
                         odom_topic=wire.check_namespace(args.odom_topic) if args.odom_topic else "")
        bus_cfg = BusConfig(robot=robot, mode="client", connect=tuple(args.connect or BusConfig.connect),
                            zenoh_config=args.zenoh_config or "", health_file=args.health_file or "")
        run(bus_cfg, cfg, stop, counts)
    except LrfSlamError as exc:
        log.error("%s", exc)
        return 2
    if counts:
        log.info("counts: %s", ", ".join(f"{k} {v}" for k, v in sorted(counts.items())))
    stopped_cleanly("ros2")
    return 0
