"""The one in-process chain (lrfslam.runtime.chain): stream order, configuration layers, wire round trip."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from lrfslam.services import build_step, stage

from lrfslam.errors import ConfigError, InputError
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.runtime.chain import Chain, Item, Stage
from lrfslam.runtime.step import Message, Output, ServiceSpec, StepBase


@dataclass(frozen=True)
class ToyConfig:
    fan_out: int = 1


class Splitter(StepBase):
    """scan -> ``fan_out`` odometry messages (seq 10 * scan seq + k); a 1-beam scan is bad input."""

    def __init__(self, cfg: ToyConfig) -> None:
        super().__init__()
        self.cfg = cfg

    def on_message(self, msg: Message):
        if msg.value.ranges_m.size < 2:
            raise InputError("one beam")
        self.made = [Output(topics.ODOM, t.Odometry(stamp_ns=msg.stamp_ns, seq=10 * msg.seq + k,
                                                    pose=[0.1 * k, 0.0, 0.0]))
                     for k in range(self.cfg.fan_out)]
        return self.made

    def finish(self):
        return [Output(topics.ODOM, t.Odometry(stamp_ns=99, seq=999, pose=[0.0, 0.0, 0.0]))]


class Marker(StepBase):
    """odometry -> truth with the same seq; remembers what it was given."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: list[Message] = []

    def on_message(self, msg: Message):
        self.seen.append(msg)
        return [Output(topics.TRUTH, t.GroundTruth(stamp_ns=msg.stamp_ns, seq=msg.seq, pose=msg.value.pose,
                                                   corner_ids=[], corners_xy_m=np.zeros((0, 2))))]

    def finish(self):
        return [Output(topics.TRUTH, t.GroundTruth(stamp_ns=100, seq=1000, pose=[0.0, 0.0, 0.0], corner_ids=[],
                                                   corners_xy_m=np.zeros((0, 2))))]


class Raw(StepBase):
    def __init__(self) -> None:
        super().__init__()
        self.seen: list[Message] = []

    def on_message(self, msg: Message):
        self.seen.append(msg)
        return ()


def spec(name, inputs, outputs, build, raw=False) -> ServiceSpec:
    return ServiceSpec(name, name, ToyConfig, inputs, outputs, build, raw_inputs=raw)


SPLITTER = spec("splitter", (topics.SCAN,), (topics.ODOM,), lambda cfg, ctx: Splitter(cfg))
MARKER = spec("marker", (topics.ODOM,), (topics.TRUTH,), lambda cfg, ctx: Marker())
RAW = spec("raw", (), (), lambda cfg, ctx: Raw(), raw=True)


def scan(seq: int, beams: int = 3) -> Message:
    return Message.of(Output(topics.SCAN, t.LaserScan.from_ranges(seq, seq, np.ones(beams), 0.0, 0.1)))


def names(msgs) -> list[tuple[str, int]]:
    return [(m.name, m.seq) for m in msgs]


def test_outputs_follow_their_cause_through_every_stage():
    chain = Chain([Stage(SPLITTER, ToyConfig(fan_out=2)), Stage(MARKER, ToyConfig())])
    first = Item(scan(1))
    items = chain.push_item(first)
    assert items[0] is first
    # Each output comes right after its cause, and what a later stage made of it right after it.
    assert names(it.msg for it in items) == [("scan", 1), ("odom", 10), ("truth", 10), ("odom", 11), ("truth", 11)]
    # The final outputs of a stage go through the later stages before their own final outputs.
    assert names(it.msg for it in chain.finish_items()) == [
        ("odom", 999), ("truth", 999), ("truth", 1000)]


def test_feed_gives_outputs_only_and_counts_per_stage():
    chain = Chain([Stage(SPLITTER, ToyConfig()), Stage(MARKER, ToyConfig())])
    out = list(chain.feed([scan(1), scan(2, beams=1), scan(3)]))
    assert names(out) == [("odom", 10), ("truth", 10), ("odom", 30), ("truth", 30),
                          ("odom", 999), ("truth", 999), ("truth", 1000)]
    counts = chain.counts()
    # The bad scan is counted and skipped; it does not stop the chain.
    assert counts["splitter"] == {"in.scan": 3, "error.input": 1, "out.odom": 3}
    assert counts["marker"] == {"in.odom": 3, "out.truth": 4}


@pytest.mark.parametrize("wire", [True, False])
def test_wire_round_trip_between_stages(wire):
    chain = Chain([Stage(SPLITTER, ToyConfig()), Stage(MARKER, ToyConfig())], wire=wire)
    chain.push(scan(4))
    (made,) = chain.step("splitter").made
    (seen,) = chain.step("marker").seen
    # On the wire the later stage gets a decoded copy, as a subscriber would; in memory, the very value.
    assert (seen.value is made.value) != wire
    np.testing.assert_array_equal(seen.value.pose, made.value.pose)


def test_a_raw_stage_gets_inputs_and_outputs_as_payloads():
    chain = Chain([Stage(SPLITTER, ToyConfig()), Stage(RAW, ToyConfig())])
    chain.push(scan(5))
    seen = chain.step("raw").seen
    assert names(seen) == [("scan", 5), ("odom", 50)]
    assert all(m.topic is None and isinstance(m.value, bytes) for m in seen)
    assert topics.ODOM.codec.decode(seen[1].value).seq == 50


def test_build_step_layers_preset_file_environment_and_sets(tmp_path):
    cfg = stage("denoise", config_file={"denoise": {"mode": "paper", "histogram": {"bin_deg": 5.0}}},
                env={"LRFSLAM_DENOISE_HISTOGRAM__BIN_DEG": "15"}, sets=["histogram.keep_frac=0.2"]).config
    # mode=paper picks the paper preset (period 180°); env beats the file; sets add on top.
    assert (cfg.mode, cfg.histogram.period_deg, cfg.histogram.bin_deg) == ("paper", 180.0, 15.0)
    assert cfg.histogram.keep_frac == 0.2
    path = tmp_path / "c.toml"
    path.write_text('[features]\nmode = "paper"\n')
    step = build_step("features", config_file=path)
    assert step.cfg.mode == "paper" and step.cfg.wall_direction is False
    # No environment unless given: the process environment never leaks into a test.
    assert stage("denoise").config == stage("denoise", env={}).config
    with pytest.raises(ConfigError):
        stage("denoise", sets=["nonsense=1"])


class Answering(StepBase):
    """scan -> odometry yielded at once, then (a 1-beam scan: bad input found by the later work) an error."""

    def on_message(self, msg: Message):
        yield Output(topics.ODOM, t.Odometry(stamp_ns=msg.stamp_ns, seq=msg.seq, pose=[0.0, 0.0, 0.0]))
        if msg.value.ranges_m.size < 2:
            raise InputError("one beam")
        yield Output(topics.ODOM, t.Odometry(stamp_ns=msg.stamp_ns, seq=100 + msg.seq, pose=[1.0, 0.0, 0.0]))


def test_a_generator_step_keeps_what_it_yielded_before_a_bad_input():
    # Live, the runner has put an output the moment it was yielded; the chain keeps it too, so replay equals live.
    answering = spec("answering", (topics.SCAN,), (topics.ODOM,), lambda cfg, ctx: Answering())
    chain = Chain([Stage(answering, ToyConfig()), Stage(MARKER, ToyConfig())])
    out = list(chain.feed([scan(1), scan(2, beams=1), scan(3)]))
    assert names(out) == [("odom", 1), ("truth", 1), ("odom", 101), ("truth", 101), ("odom", 2), ("truth", 2),
                          ("odom", 3), ("truth", 3), ("odom", 103), ("truth", 103), ("truth", 1000)]
    assert chain.counts()["answering"] == {"in.scan": 3, "error.input": 1, "out.odom": 5}


def test_emit_gets_each_output_as_its_step_yields_it():
    # The live runner puts what ``emit`` gets: an output must be out before its step goes on. A stage takes
    # the whole stream before the next, so across stages emission is by stage; each topic keeps its order.
    emitted: list[tuple[str, str, int]] = []
    seen_by_step: list[int] = []

    class Watching(Answering):
        def on_message(self, msg):
            for out in super().on_message(msg):
                yield out
                seen_by_step.append(len(emitted))   # how many were out when the step resumed

    watching = spec("answering", (topics.SCAN,), (topics.ODOM,), lambda cfg, ctx: Watching())
    chain = Chain([Stage(watching, ToyConfig()), Stage(MARKER, ToyConfig())],
                  emit=lambda name, item: emitted.append((name, item.msg.name, item.msg.seq)))
    out = list(chain.feed([scan(1), scan(2, beams=1)]))
    assert emitted[:4] == [("answering", "odom", 1), ("answering", "odom", 101), ("marker", "truth", 1),
                           ("marker", "truth", 101)]
    assert seen_by_step == [1, 2, 5]   # after odom 1, odom 101, odom 2 (then scan 2 raised)
    assert sorted((m.name, m.seq) for m in out) == sorted((n, q) for _, n, q in emitted)
    assert emitted[-1] == ("marker", "truth", 1000)   # finish() outputs are emitted too

