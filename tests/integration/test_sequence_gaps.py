"""Sequence gaps over real Zenoh: a publisher that skips numbers, a restarted publisher, and consumers counting.

One router session and client sessions on loopback in this process (each session is what one
service process has). The publisher's skipped numbers stand for samples lost on the way; the
consumers must count exactly those, and a second publisher starting again from 1 is a restart,
not a gap. The samples also show the delivery policy of ``msgs/topics.py`` applied by the bus.
"""

from __future__ import annotations

import threading
import time
from collections import Counter

import pytest
import zenoh

from lrfslam.msgs import codec, topics
from lrfslam.msgs import types as t
from lrfslam.runtime.bus import ZenohBus, parse_attachment, producer_id
from lrfslam.tools.status import client_config

pytestmark = pytest.mark.integration

ROBOT = "gaps"


def odom(i: int) -> bytes:
    return codec.ODOMETRY.encode(t.Odometry(stamp_ns=i * 1000, seq=i, pose=(0.0, 0.0, 0.0)))


def wait_until(predicate, what: str, timeout_s: float = 10.0):
    deadline = time.monotonic() + timeout_s
    while not (value := predicate()):
        assert time.monotonic() < deadline, what
        time.sleep(0.02)
    return value


def publish(endpoint: str, seqs: list[int], consumers: list[ZenohBus]) -> bytes:
    """Publish odometry numbered ``seqs`` from a new session (a new producer) until every consumer
    has taken the last one from its queue; the producer's id."""
    with zenoh.open(client_config([endpoint])) as session:
        bus = ZenohBus(session, ROBOT, (), False, 16, Counter())
        pub = bus.publisher(topics.ODOM)
        wait_until(lambda: pub.matching_status.matching, "no subscriber matched")
        for i in seqs:
            bus.put(topics.ODOM, odom(i), i * 1000, i)
        for consumer in consumers:
            wait_until(lambda c=consumer: last_seq(c) == seqs[-1], "a consumer never got the last sample")
        bus.close()
        return producer_id(session)


def last_seq(consumer: ZenohBus) -> int | None:
    """The sequence number of the last message waiting in ``consumer``'s queue (None if empty)."""
    last = None
    while (msg := consumer.get(0.01)) is not None:
        last = msg.seq
    return last


def test_consumers_count_what_a_producer_skipped_and_recognise_a_restart(router):
    with zenoh.open(client_config([router])) as decoded_s, zenoh.open(client_config([router])) as raw_s:
        stage = ZenohBus(decoded_s, ROBOT, (topics.ODOM,), False, 1000, Counter())
        recorder = ZenohBus(raw_s, ROBOT, (), True, 1000, Counter())
        consumers = [stage, recorder]
        skipped = {10, 20, 21, 22, 49}
        first = publish(router, [i for i in range(1, 51) if i not in skipped] + [51], consumers)
        second = publish(router, list(range(1, 11)), consumers)   # a restarted producer: new id, from 1
        assert first != second
        for consumer in consumers:
            assert consumer.receive_counts() == Counter({"gap.odom": len(skipped), "restart.odom": 1})
        stage.close()
        recorder.close()


def test_each_topic_is_published_with_its_delivery_policy(router):
    samples: dict[str, zenoh.Sample] = {}
    with zenoh.open(client_config([router])) as sub_s, zenoh.open(client_config([router])) as pub_s:
        sub = sub_s.declare_subscriber(topics.everything(ROBOT), lambda s: samples.setdefault(str(s.key_expr), s))
        bus = ZenohBus(pub_s, ROBOT, (), False, 16, Counter())
        health = topics.health("sensor")
        for topic in (topics.SCAN, topics.MAP_KEYFRAMES, health):
            pub = bus.publisher(topic)
            wait_until(lambda pub=pub: pub.matching_status.matching, "no subscriber matched")
            bus.put(topic, b"x", 7, 1)
        wait_until(lambda: len(samples) == 3, "not every sample arrived")
        sub.undeclare()
        bus.close()
        got = {topics.relative(ROBOT, k): s for k, s in samples.items()}
        assert got["scan"].congestion_control == zenoh.CongestionControl.DROP
        assert got["scan"].priority == zenoh.Priority.DATA and not got["scan"].express
        assert got["map/keyframes"].congestion_control == zenoh.CongestionControl.BLOCK
        assert got["map/keyframes"].priority == zenoh.Priority.DATA_LOW
        assert got[health.name].priority == zenoh.Priority.DATA_HIGH and got[health.name].express
        att = parse_attachment(got["scan"].attachment.to_bytes())
        assert (att.seq, att.stamp_ns, att.producer) == (1, 7, producer_id(pub_s))


def test_a_batched_consumer_gets_every_message_in_order_stamped_on_arrival(router):
    """The recorder's bus: not woken per message, yet nothing lost or reordered, and each
    message carries the wall-clock time it arrived (the recording's log_time), not when taken."""
    with zenoh.open(client_config([router])) as raw_s, zenoh.open(client_config([router])) as pub_s:
        recorder = ZenohBus(raw_s, ROBOT, (), True, 8, Counter(), batched=True)
        producer = ZenohBus(pub_s, ROBOT, (), False, 16, Counter())
        pub = producer.publisher(topics.ODOM)
        wait_until(lambda: pub.matching_status.matching, "no subscriber matched")
        before = time.time_ns()
        for i in range(1, 7):
            producer.put(topics.ODOM, odom(i), i * 1000, i)
        got = []
        while len(got) < 6:
            msg = recorder.get(1.0)
            assert msg is not None, f"only {len(got)} of 6 messages arrived"
            got.append(msg)
        assert [m.seq for m in got] == list(range(1, 7))
        arrived = [m.received_wall_ns for m in got]
        assert arrived == sorted(arrived) and before <= arrived[0]
        assert arrived[-1] <= time.time_ns()
        # A quarter of the queue (2 of 8) waiting wakes the consumer before its timeout ends.
        waiter = threading.Thread(target=lambda: got.append(recorder.get(600.0)))
        waiter.start()
        for i in range(7, 9):
            producer.put(topics.ODOM, odom(i), i * 1000, i)
        waiter.join(60.0)
        assert not waiter.is_alive() and got[-1].seq == 7
        assert recorder.receive_counts() == Counter()
        recorder.close()
        producer.close()
