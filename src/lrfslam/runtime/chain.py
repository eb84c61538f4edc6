"""The one in-process chain: read → decode → step → write, through any number of stages.

A :class:`Chain` holds service steps in pipeline order. Every message pushed in
goes to each step that takes its topic; each step's outputs come right after
the message that caused them and go on to the later steps, so the stream out of
the chain is the input stream with every stage's outputs inserted. Nothing
reads the clock: the same input gives the same outputs.

Three drivers use it: ``lrfslam <service> --replay`` (one stage, outputs only),
``lrfslam pipeline`` (several stages, input copied through), both by
:func:`replay_recording`; and in-memory callers (the Monte Carlo, tests) by
:meth:`Chain.push` and :meth:`Chain.feed`.

A configured stage is made one way, :func:`configure` — by name
:func:`lrfslam.services.stage`, or :func:`lrfslam.services.build_step` for the
step alone: defaults or the ``mode`` preset < config file < environment <
``sets``, as the service runner layers its flags.
"""

from __future__ import annotations

import logging
import sys
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Self

from tqdm import tqdm

from lrfslam.errors import InputError
from lrfslam.msgs import counters, topics
from lrfslam.runtime import checkpoints
from lrfslam.runtime import config as config_mod
from lrfslam.runtime.bus import BusConfig
from lrfslam.runtime.checkpoints import Checkpointer, Resumable
from lrfslam.runtime.decoding import LogOnce, decode_message
from lrfslam.runtime.outputs import atomic_output
from lrfslam.runtime.recording import (
    ReadReport,
    RecordedMessage,
    RecordingSource,
    RecordingWriter,
    describe_source,
    read_recording,
    recording_files,
)
from lrfslam.runtime.step import Message, Output, RunContext, ServiceSpec

log = logging.getLogger("lrfslam.chain")

DEFAULT_ROBOT: str = BusConfig.robot


@dataclass(frozen=True)
class Stage:
    """One service with its fully layered config."""

    spec: ServiceSpec
    config: Any

    def build(self, robot: str = DEFAULT_ROBOT) -> Any:
        """A fresh step of this service."""
        return self.spec.build(self.config, RunContext(robot))


def configure(spec: ServiceSpec, *, sets: Iterable[str] = (), config_file: str | Path | Mapping | None = None,
              env: Mapping[str, str] | None = None) -> Stage:
    """``spec`` configured as the runner would: defaults or preset < file < env < ``sets``.

    By name: :func:`lrfslam.services.stage` (the services room holds the registry).

    Parameters
    ----------
    sets : iterable of ``"name=value"``
        The service's own settings (``mode=paper``, ``ekf.gate_chi2=9``).
    config_file : path or mapping, optional
        A TOML file, or its already parsed tables; its ``[<name>]`` table is used.
    env : mapping, optional
        Environment (``LRFSLAM_<NAME>_*``); None leaves the environment out.
    """
    file = config_file if isinstance(config_file, Mapping) else config_mod.read_file(config_file)
    return Stage(spec, config_mod.service_config(spec, sets=sets, file=file, env=env))


@dataclass(frozen=True)
class Item:
    """A message in the chain.

    ``rec`` is set for one read from a recording; ``msg`` when some stage may
    consume it (decoded) or a stage made it; ``payload`` is a stage output's
    encoding (empty off the wire).
    """

    msg: Message | None
    rec: RecordedMessage | None = None
    payload: bytes = b""

    def raw(self) -> Message:
        """The undecoded message a raw-input service (the recorder) receives."""
        if self.rec is not None:
            r = self.rec
            return Message(None, r.data, r.stamp_ns, r.schema, r.topic, r.sequence)
        m = self.msg
        if m.topic is None:   # received raw off the bus
            return m
        return Message(None, self.payload or m.topic.codec.encode(m.value), m.stamp_ns, m.schema, m.name, m.seq)


class _Link:
    """One stage in the chain: its step, the topics it takes, its counters."""

    def __init__(self, st: Stage, step: Any, checkpoint_dir: Path | None, checkpoint_period_s: float) -> None:
        self.name = st.spec.name
        self.stage = st
        self.step = step
        self.checkpointer = None
        if checkpoint_dir is not None and isinstance(step, Resumable):
            self.checkpointer = Checkpointer(step, checkpoints.path_for(checkpoint_dir, self.name), checkpoint_period_s)
            self.checkpointer.restore()
        self.wanted = frozenset(tp.name for tp in st.spec.inputs)
        self.raw = st.spec.raw_inputs
        self.counts: Counter[str] = Counter()
        self.once = LogOnce(log)


class Chain:
    """Service steps in pipeline order, driven synchronously.

    Parameters
    ----------
    stages : iterable of Stage
        In pipeline order; a stage sees the outputs of the stages before it.
    robot : str
        Given to the steps.
    checkpoint_dir : Path, optional
        Where the stages that keep state save it and resume from (:mod:`lrfslam.runtime.checkpoints`),
        as a live service does with ``bus.checkpoint_dir``; None: no checkpoints (a replay).
    checkpoint_period_s : float
        Data time between two saves.
    wire : bool
        True: a stage's outputs reach the later stages encoded and decoded, as
        the bus delivers them (float32 points), so results equal the live
        services'. False: the values as the step made them, at full precision
        (the Monte Carlo measures the algorithms so).
    emit : callable, optional
        ``emit(stage_name, item)`` for every output as its step yields it, before the step goes on:
        the live runner puts each on the bus so (a step that yields its answer before further work
        has it out before that work).
    """

    def __init__(self, stages: Iterable[Stage], *, robot: str = DEFAULT_ROBOT, checkpoint_dir: Path | None = None,
                 checkpoint_period_s: float = checkpoints.PERIOD_S, wire: bool = True,
                 emit: Callable[[str, Item], None] | None = None) -> None:
        self.wire = wire
        self._emit = emit
        self._links = [_Link(st, st.build(robot), checkpoint_dir, checkpoint_period_s) for st in stages]
        # Topics some stage after the i-th decodes: only those outputs need decoding again
        # (a raw stage takes the payload).
        self._later = [frozenset().union(*(lk.wanted for lk in self._links[i + 1:]))
                       for i in range(len(self._links))]
        self._closed = False

    @property
    def stages(self) -> tuple[Stage, ...]:
        return tuple(lk.stage for lk in self._links)

    def step(self, name: str) -> Any:
        """The step of stage ``name``."""
        for lk in self._links:
            if lk.name == name:
                return lk.step
        raise KeyError(name)

    def counts(self) -> dict[str, Counter]:
        """Per stage: ``in.<topic>``, ``out.<topic>``, ``error.input`` and the step's ``step.*``."""
        out = {}
        for lk in self._links:
            c = Counter(lk.counts)
            c.update({f"{counters.STEP}{k}": v for k, v in lk.step.counts.items()})
            out[lk.name] = c
        return out

    # -- driving

    def push_item(self, item: Item) -> list[Item]:
        """``item`` and, right after it, everything the stages made from it, in stream order."""
        stream = [item]
        for i, lk in enumerate(self._links):
            stream = self._through(i, lk, stream)
        return stream

    def finish_items(self) -> list[Item]:
        """Every stage's final outputs (each passed through the stages after it)."""
        stream: list[Item] = []
        for i, lk in enumerate(self._links):
            stream = self._through(i, lk, stream)
            stream += [self._item(i, out) for out in lk.step.finish()]
        return stream

    def push_outputs(self, name: str, outputs: Iterable[Output]) -> list[Item]:
        """What stage ``name`` made outside an input (a source's poll), each passed through the stages after it."""
        i = next(i for i, lk in enumerate(self._links) if lk.name == name)
        stream = [self._item(i, out) for out in outputs]
        for j in range(i + 1, len(self._links)):
            stream = self._through(j, self._links[j], stream)
        return stream

    def push(self, msg: Message) -> list[Message]:
        """Feed one message; the outputs of every stage it caused, in stream order."""
        return [it.msg for it in self.push_item(Item(msg))[1:]]

    def feed(self, messages: Iterable[Message]) -> Iterator[Message]:
        """Every output for ``messages``, in order, then the stages' final outputs."""
        for msg in messages:
            yield from self.push(msg)
        yield from (it.msg for it in self.finish_items())

    def close(self, save: bool = True) -> None:
        """Save every checkpoint (unless not ``save``: after a failure) and close every step, once (a chain
        never closed is a killed process: its last periodic checkpoints stay)."""
        if not self._closed:
            self._closed = True
            for lk in self._links:
                if save and lk.checkpointer is not None:
                    lk.checkpointer.save()
                lk.step.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _through(self, i: int, lk: _Link, stream: list[Item]) -> list[Item]:
        out: list[Item] = []
        for item in stream:
            out.append(item)
            if lk.raw:
                msg = item.raw()
                lk.counts[counters.IN_RAW] += 1
            elif item.msg is not None and item.msg.name in lk.wanted:
                msg = item.msg
                lk.counts[f"{counters.IN}{msg.name}"] += 1
            else:
                continue
            try:
                for o in lk.step.on_message(msg):   # what a step yielded before a bad input stays
                    out.append(self._item(i, o))
            except InputError as exc:
                lk.counts[counters.ERROR_INPUT] += 1
                lk.once.warning(counters.ERROR_INPUT, type(exc).__name__, "%s: skipping bad input on %s: %s",
                                lk.name, msg.name, exc)
            else:
                if lk.checkpointer is not None:
                    lk.checkpointer.after(msg.stamp_ns)
        return out

    def _item(self, i: int, out: Output) -> Item:
        lk = self._links[i]
        lk.counts[f"{counters.OUT}{out.topic.name}"] += 1
        if not self.wire:
            item = Item(Message.of(out))
        else:
            payload = out.topic.codec.encode(out.value)
            if out.topic.name in self._later[i]:
                out = Output(out.topic, out.topic.codec.decode(payload))
            item = Item(Message.of(out), None, payload)
        if self._emit is not None:
            self._emit(lk.name, item)
        return item


def replay_recording(stages: Iterable[Stage], robot: str, in_path: RecordingSource, out_path: str | Path | None, *,
                     copy_inputs: bool, metadata: dict[str, dict[str, str]], progress: bool = False
                     ) -> dict[str, Counter]:
    """Run ``stages`` over the recording ``in_path`` (file, folder or files), in data-stamp order; write ``out_path``.

    Input messages on a topic one of the stages produces are dropped (that
    stage's outputs replace them, and they are not fed to later stages), and so
    are Foxglove's views (``/foxglove/...``, made from the inputs: ``lrfslam export
    --foxglove`` makes new ones). With
    ``copy_inputs`` the other input messages are written too, as recorded but for their times:
    the output is an offline file, every message's ``log_time`` and ``publish_time`` its data
    stamp (lrfslam/runtime/recording.py). Deterministic: nothing reads the clock and the output carries no wall-clock
    metadata, so two runs give the same bytes. ``out_path`` appears only when the
    run has finished (:func:`~lrfslam.runtime.outputs.atomic_output`).

    Returns
    -------
    dict of str to Counter
        Per stage, :meth:`Chain.counts`; under ``"input"``: messages ``read``,
        ``copied``, ``dropped``, undecodable (``error.decode``/``error.schema``)
        and ``truncated``.

    Raises
    ------
    RecordingError
        ``in_path`` is no MCAP recording (checked before anything is written).
    """
    recording_files(in_path)
    if out_path is None:
        return _replay(stages, robot, in_path, None, copy_inputs, metadata, progress)
    with atomic_output(out_path) as partial:
        return _replay(stages, robot, in_path, partial, copy_inputs, metadata, progress)


def _replay(stages: Iterable[Stage], robot: str, in_path: RecordingSource, out_path: Path | None,
            copy_inputs: bool, metadata: dict[str, dict[str, str]], progress: bool) -> dict[str, Counter]:
    name = describe_source(in_path)
    chain = Chain(stages, robot=robot)
    specs = [st.spec for st in chain.stages]
    produced = {tp.name for sp in specs for tp in sp.outputs}
    consumed = {tp.name: tp for sp in specs for tp in sp.inputs if tp.name not in produced}
    everything = copy_inputs or any(sp.raw_inputs for sp in specs)
    read: Counter[str] = Counter()
    once = LogOnce(log)
    report = ReadReport()
    writer = RecordingWriter(out_path, metadata) if out_path is not None else None

    def write(items: list[Item]) -> None:
        if writer is None:
            return
        for item in items:
            if item.rec is None:
                m = item.msg
                writer.write(m.name, m.schema, item.payload, m.stamp_ns, sequence=m.seq)
            elif copy_inputs:
                r = item.rec
                read["copied"] += 1
                writer.write(r.topic, r.schema, r.data, r.stamp_ns, sequence=r.sequence)

    try:
        records = read_recording(in_path, None if everything else list(consumed), report)
        for rec in tqdm(records, desc=name, unit=" msgs", disable=not progress, file=sys.stderr):
            read["read"] += 1
            if rec.topic in produced or topics.is_foxglove(rec.topic):
                read["dropped"] += 1
                continue
            topic = consumed.get(rec.topic)
            msg = None
            if topic is not None:
                msg = decode_message(topic, rec.data, rec.schema, read, once, f"{name}:{rec.topic}")
            write(chain.push_item(Item(msg, rec)))
        write(chain.finish_items())
    finally:
        chain.close()
        if writer is not None:
            writer.close()
    if report.truncated:
        read["truncated"] = 1
    return {"input": read, **chain.counts()}
