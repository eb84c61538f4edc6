"""What a service is: a config type, its input and output topics, and a step.

A *step* turns one input message into zero or more outputs; a *source* (the
sensor) produces outputs when polled. The runner drives the same step live on
Zenoh; :class:`lrfslam.runtime.chain.Chain` drives it over a recording
(``--replay``, ``lrfslam pipeline``), in the Monte Carlo and in tests, so they
can never disagree about what a stage does.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

from lrfslam.msgs.topics import Topic


@dataclass(frozen=True)
class Message:
    """One received sample: decoded value (or raw bytes for raw services), data stamp and schema."""

    topic: Topic | None
    value: Any
    stamp_ns: int
    schema: str
    name: str = ""      # relative key; the only way a raw service knows what it got
    seq: int = 0
    received_wall_ns: int = 0   # wall clock (ns) when the bus received it, for raw services; 0: not received live

    @classmethod
    def of(cls, out: Output) -> Message:
        """``out`` as a later stage receives it: stamp and seq from the value's header."""
        return cls(out.topic, out.value, out.value.stamp_ns, out.topic.schema, out.topic.name, out.value.seq)


@dataclass(frozen=True)
class Output:
    """A value to publish on ``topic``; the stamp and seq come from the value's header."""

    topic: Topic
    value: Any


@runtime_checkable
class Step(Protocol):
    """Processing stage: called once per input message, in arrival order.

    ``on_message`` may be a generator: live, each output is put as it is yielded, so a step that yields
    its answer before work that need not delay it (the mapper's keyframes) answers first; every
    driver consumes it whole.
    """

    def on_message(self, msg: Message) -> Iterable[Output]: ...


@runtime_checkable
class Source(Protocol):
    """Producing stage: ``poll`` blocks at most ``timeout_s`` and returns what is ready."""

    def poll(self, timeout_s: float) -> Iterable[Output]: ...


class StepBase:
    """Defaults for the optional hooks, and a counter the status reply shows."""

    def __init__(self) -> None:
        self.counts: Counter[str] = Counter()

    def finish(self) -> Iterable[Output]:
        """Called once at the end of input (replay end or shutdown): flush pending outputs."""
        return ()

    def tick(self) -> None:
        """Called by the live runner about every 100 ms of wall time (e.g. to flush a file)."""

    def close(self) -> None:
        """Release resources; called once, last."""

    def health(self) -> tuple[int, str]:
        """(HEALTH_* level, message) for the status reply."""
        return 0, "ok"

    def latest(self, topic: Topic) -> Any | None:
        """The value to answer a late joiner's query on ``topic`` (one of the spec's ``latest``), built now;
        None: the newest published one."""
        return None


@dataclass(frozen=True)
class ServiceSpec:
    """Everything the runner needs to know about one service."""

    name: str
    summary: str
    config_type: type
    inputs: tuple[Topic, ...]
    outputs: tuple[Topic, ...]
    build: Callable[[Any, RunContext], Any]
    raw_inputs: bool = False   # receive every key under the robot undecoded (the recorder)
    #: Given the configured ``mode``, the config whose values the layers then override
    #: (the "paper" or "default" parameter preset).
    preset: Callable[[str], Any] | None = None
    #: Service-specific flags: (flag, config field, help), e.g. ("--device", "device", "serial port").
    flags: tuple[tuple[str, str, str], ...] = ()
    #: Outputs whose newest message the live service keeps and answers for on ``topics.latest``
    #: (the state a late viewer needs at once, e.g. the slam's landmarks).
    latest: tuple[Topic, ...] = ()
    #: Inputs the live service skips when it falls behind, the last of them the lead (a newer one
    #: of it waiting makes older inputs stale; lrfslam/runtime/bus.py). Its step bridges a skipped
    #: input as a lost one. Empty: every input is handled, however late (the recorder).
    skippable: tuple[Topic, ...] = ()
    #: How old (s, wall clock) a skippable input may be before a newer lead input makes it stale.
    max_lag_s: float = 0.25
    #: A consumer that need not answer at once (the recorder): it takes its inputs in batches,
    #: about every 0.1 s, rather than being woken for each (lrfslam/runtime/bus.py).
    batched: bool = False


@dataclass(frozen=True)
class RunContext:
    """Deployment facts a step may need: which robot."""

    robot: str
    extra: dict = field(default_factory=dict)

