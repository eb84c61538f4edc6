"""``python -m lrfslam.evaluation.ros2_roundtrip RECORDING -o OUT``: a log as a ROS 2 robot's would reach the pipeline.

Every scan and odometry message of RECORDING (a log imported with ``lrfslam import carmen``)
goes the way ``lrfslam ros2 --subscribe`` takes a ROS 2 robot's: converted to
``sensor_msgs/msg/LaserScan`` and ``nav_msgs/msg/Odometry`` (ranges become float32), serialized
to CDR, read back and converted to ours. OUT keeps RECORDING's metadata, so that

    lrfslam eval relations OUT RELATIONS

scores mapping from a ROS 2 robot's stream beside the log read directly (docs/ros2.md). The
transport itself carries the CDR bytes unchanged (tests/integration/test_ros2_bridge.py): the
conversion is all that could differ.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterable, Iterator
from pathlib import Path

from lrfslam.msgs import topics
from lrfslam.ros2 import convert, wire
from lrfslam.runtime.outputs import atomic_output
from lrfslam.runtime.recording import (
    TIMES,
    RecordedMessage,
    RecordingWriter,
    read_metadata,
    read_recording,
)

#: The ROS namespace the messages are converted under (and stripped of again).
NAMESPACE = "robot1"


def through_ros2(messages: Iterable[RecordedMessage]) -> Iterator[tuple[str, str, bytes, int, int]]:
    """``(topic, schema, payload, stamp ns, sequence)`` of each message, scans and odometry through
    ROS 2's messages and CDR and back, numbered afresh as the bridge numbers them; others as they are."""
    seq = {topics.SCAN.name: 0, topics.ODOM.name: 0}
    for m in messages:
        if m.topic not in seq:
            yield m.topic, m.schema, m.data, m.stamp_ns, m.sequence
            continue
        topic = topics.by_name(m.topic)
        value = topic.codec.decode(m.data, m.schema)
        seq[m.topic] += 1
        if topic is topics.SCAN:
            msg = convert.deserialize(convert.serialize(convert.laser_scan(value, NAMESPACE)), wire.LASER_SCAN)
            back = convert.scan_from_ros(msg, seq[m.topic], NAMESPACE, value.source)
        else:
            msg = convert.deserialize(convert.serialize(convert.odometry(value, NAMESPACE)), wire.ODOMETRY)
            back = convert.odometry_from_ros(msg, seq[m.topic], NAMESPACE)
        yield m.topic, topic.schema, topic.codec.encode(back), back.stamp_ns, seq[m.topic]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m lrfslam.evaluation.ros2_roundtrip",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("recording", type=Path)
    parser.add_argument("-o", "--out", type=Path, required=True, help="the recording to write (never overwritten)")
    args = parser.parse_args(argv)
    if args.out.exists():
        parser.error(f"{args.out} exists; not overwriting it")
    # The source's metadata but its time layout, which the writer states for the file it writes.
    metadata = {name: record for name, record in read_metadata(args.recording).items() if name != TIMES}
    with atomic_output(args.out) as partial, RecordingWriter(partial, metadata) as writer:
        for topic, schema, payload, stamp_ns, sequence in through_ros2(read_recording(args.recording)):
            writer.write(topic, schema, payload, stamp_ns, stamp_ns, sequence)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
