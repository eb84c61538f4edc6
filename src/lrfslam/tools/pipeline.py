"""``lrfslam pipeline --replay IN.mcap --out OUT.mcap``: several services' steps in one process, offline.

Equivalent to replaying the services one after the other, each on a recording
holding its inputs, without the intermediate files and merges: every stage is
the service's own step (``services.spec(name).build``) driven by
:func:`~lrfslam.runtime.service.run_offline`, and each output is fed forward to
the later stages as soon as it is produced. The input is read once in log-time
order; nothing reads the clock, so the same input gives the same output bytes.

OUT.mcap holds the input's messages (raw, as recorded) and every stage's
outputs, except that input messages on a topic one of the stages produces are
dropped (that stage's outputs replace them, and they are not fed to later stages).
So ``lrfslam pipeline --replay intel.mcap --out run.mcap`` gives one file with
``scan``, ``odom``, ``scan/filtered``, ``features`` and ``slam/state``.

Configuration layers as for the services (defaults or preset < ``--config``
``[<service>]`` table < ``LRFSLAM_<SERVICE>_*`` < ``--set``), with ``--set``
naming the stage: ``--set feature.mode=paper --set slam.ekf.gate_chi2=9``.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections import Counter, deque
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tqdm import tqdm

from lrfslam import services
from lrfslam.errors import ConfigError, InputError, LrfSlamError
from lrfslam.runtime import config as config_mod
from lrfslam.runtime.bus import BusConfig
from lrfslam.runtime.decoding import LogOnce, decode_message
from lrfslam.runtime.recording import (
    ReadReport,
    RecordedMessage,
    RecordingWriter,
    read_recording,
)
from lrfslam.runtime.runner import service_config, setup_logging, step_close
from lrfslam.runtime.service import Message, RunContext, ServiceSpec, run_offline

log = logging.getLogger("lrfslam.pipeline")

DEFAULT_STAGES = ("denoise", "feature", "slam")


@dataclass(frozen=True)
class Stage:
    """One service to run: its spec and its fully layered config."""

    spec: ServiceSpec
    config: Any


@dataclass(frozen=True)
class _Item:
    """A message in the chain: ``rec`` is set for one read from the input file, ``msg``
    when some stage may consume it (decoded) or a stage produced it, ``payload`` (its
    encoding) for a stage's output."""

    msg: Message | None
    rec: RecordedMessage | None
    payload: bytes = b""


def stage_names(text: str) -> tuple[str, ...]:
    """Comma-separated service names, checked and put in pipeline order.

    Raises
    ------
    ConfigError
        A name is unknown, repeated, or a service without a replayable step
        (the sensor is a source; the recorder's job is done by OUT.mcap itself).
    """
    names = [n.strip() for n in text.split(",") if n.strip()]
    usable = [n for n in services.NAMES if n not in ("sensor", "recorder")]
    for name in names:
        if name not in usable:
            raise ConfigError(f"pipeline stage {name!r} must be one of {', '.join(usable)}")
    if not names or len(set(names)) != len(names):
        raise ConfigError(f"pipeline stages {text!r}: give each stage once")
    return tuple(n for n in services.NAMES if n in names)


def stage_sets(sets: Iterable[str], names: Iterable[str]) -> dict[str, list[str]]:
    """Split ``stage.field=value`` overrides by stage: ``{"feature": ["mode=paper"], ...}``."""
    names = tuple(names)
    out: dict[str, list[str]] = {n: [] for n in names}
    for item in sets:
        stage, dot, rest = item.partition(".")
        if not dot or stage not in out:
            raise ConfigError(f"--set {item!r}: prefix the setting with a stage ({', '.join(names)}), "
                              "e.g. feature.mode=paper")
        out[stage].append(rest)
    return out


def _stage(stage: Stage, robot: str, upstream: Iterator[_Item], counts: Counter) -> Iterator[_Item]:
    """Pass ``upstream`` through, with the stage's outputs right after the input that caused them."""
    once = LogOnce(log)
    step = stage.spec.build(stage.config, RunContext(robot, replay=True))
    wanted = {tp.name for tp in stage.spec.inputs}
    held: deque[_Item] = deque()

    def inputs() -> Iterator[Message]:
        # Everything goes to ``held`` so the stream keeps its order around the outputs.
        for item in upstream:
            held.append(item)
            if item.msg is not None and item.msg.name in wanted:
                counts[f"in.{item.msg.name}"] += 1
                yield item.msg

    def bad_input(msg: Message, exc: InputError) -> None:
        once.warning("error.input", type(exc).__name__, "%s: skipping bad input on %s: %s",
                     stage.spec.name, msg.name, exc)

    try:
        for out in run_offline(step, inputs(), counts, bad_input):
            while held:
                yield held.popleft()
            counts[f"out.{out.topic.name}"] += 1
            # Later stages get what the bus would deliver (e.g. float32 points), so a
            # pipeline run gives the same results as the live services and --replay.
            payload = out.topic.codec.encode(out.value)
            value = out.topic.codec.decode(payload)
            yield _Item(Message(out.topic, value, value.stamp_ns, out.topic.schema, out.topic.name, value.seq),
                        None, payload)
        while held:
            yield held.popleft()
    finally:
        step_close(step)
    counts.update({f"step.{k}": v for k, v in getattr(step, "counts", {}).items()})


def run_pipeline(stages: Iterable[Stage], robot: str, in_path: str | Path, out_path: str | Path | None,
                 progress: bool = False) -> dict[str, Counter]:
    """Run ``stages`` (in pipeline order) over the recording ``in_path``; write ``out_path``.

    Returns
    -------
    dict of str to Counter
        Per stage name: ``in.<topic>``, ``out.<topic>``, ``error.input`` and the
        step's own ``step.*`` counters; under ``"input"``: messages read, copied,
        dropped (replaced by a stage's outputs) and undecodable.
    """
    stages = tuple(stages)
    in_path = Path(in_path)
    produced = {tp.name for s in stages for tp in s.spec.outputs}
    consumed = {tp.name: tp for s in stages for tp in s.spec.inputs if tp.name not in produced}
    counts: dict[str, Counter] = {"input": Counter(), **{s.spec.name: Counter() for s in stages}}
    read = counts["input"]
    once = LogOnce(log)
    report = ReadReport()

    def source() -> Iterator[_Item]:
        for rec in tqdm(read_recording(in_path, report=report), desc=f"pipeline {in_path.name}",
                        unit=" msgs", disable=not progress, file=sys.stderr):
            read["read"] += 1
            if rec.topic in produced:
                read["dropped"] += 1
                continue
            topic = consumed.get(rec.topic)
            msg = None
            if topic is not None:
                msg = decode_message(topic, rec.data, rec.schema, read, once, f"{in_path.name}:{rec.topic}")
            yield _Item(msg, rec)

    stream: Iterator[_Item] = source()
    for stage in stages:
        stream = _stage(stage, robot, stream, counts[stage.spec.name])
    metadata = {"lrfslam": {"robot": robot, "service": "pipeline", "replay_of": in_path.name,
                            "stages": ",".join(s.spec.name for s in stages),
                            **{f"config.{s.spec.name}": config_mod.to_json(s.config) for s in stages}}}
    writer = RecordingWriter(out_path, metadata) if out_path is not None else None
    try:
        for item in stream:
            if writer is None:
                continue
            if item.rec is not None:
                rec = item.rec
                read["copied"] += 1
                writer.write(rec.topic, rec.schema, rec.data, rec.log_time_ns, rec.publish_time_ns, rec.sequence)
            else:
                msg = item.msg
                writer.write(msg.name, msg.schema, item.payload, msg.stamp_ns, msg.stamp_ns, msg.seq)
    finally:
        if writer is not None:
            writer.close()
    if report.truncated:
        read["truncated"] = 1
    return counts


def build_stages(names: Iterable[str], sets: Iterable[str], file: Mapping, env: Mapping[str, str]) -> list[Stage]:
    """The stages ``names`` with their configs layered as :func:`runner.service_config` does."""
    names = tuple(names)
    per_stage = stage_sets(sets, names)
    stages = []
    for name in names:
        spec = services.spec(name)
        stages.append(Stage(spec, service_config(spec, argparse.Namespace(sets=per_stage[name]), file, env)))
    return stages


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="lrfslam pipeline", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--replay", required=True, metavar="IN.mcap", help="recording to run on")
    parser.add_argument("--out", metavar="OUT.mcap", help="write the input and every stage's outputs here")
    parser.add_argument("--stages", default=",".join(DEFAULT_STAGES),
                        help=f"comma-separated services, run in pipeline order (default {','.join(DEFAULT_STAGES)})")
    parser.add_argument("--config", metavar="FILE", help="TOML config file ([bus] robot and [<service>] tables)")
    parser.add_argument("--set", dest="sets", action="append", default=[], metavar="STAGE.NAME=VALUE",
                        help="override one setting of a stage, e.g. feature.mode=paper (repeatable)")
    parser.add_argument("--robot", help="robot namespace given to the steps and stored in the metadata")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--log-level", default=None, help="DEBUG, INFO, WARNING, ERROR")
    args = parser.parse_args(argv)
    setup_logging("pipeline", args.log_level)
    try:
        file = config_mod.read_file(args.config)
        robot = config_mod.load(BusConfig, table=file.get("bus", {}), env=os.environ,
                                env_prefix=f"{config_mod.ENV_PREFIX}_BUS",
                                sets=[f"robot={args.robot}"] if args.robot else []).robot
        stages = build_stages(stage_names(args.stages), args.sets, file, os.environ)
        for stage in stages:
            log.info("%s config %s", stage.spec.name, config_mod.to_json(stage.config))
        counts = run_pipeline(stages, robot, Path(args.replay), Path(args.out) if args.out else None,
                              progress=not args.quiet and sys.stderr.isatty())
    except LrfSlamError as exc:
        log.error("%s", exc)
        return 2
    for name, c in counts.items():
        log.info("%s: %s", name, ", ".join(f"{k}={v}" for k, v in sorted(c.items())) or "nothing")
    return 0
