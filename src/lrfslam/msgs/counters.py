"""The counters a service reports in its status (``ServiceStatus.counters``): every name in one place.

A counter is named by its kind's prefix and what it counts: ``in.scan``, ``drop.queue``,
``step.matched``. ``docs/monitoring.md`` says what each kind means to an operator.
"""

from __future__ import annotations

from collections.abc import Mapping

IN = "in."            #: inputs taken, per topic
OUT = "out."          #: outputs published, per topic
DROP = "drop."        #: inputs lost inside this service
SKIP = "skip."        #: stale inputs a stage that fell behind skipped, per topic (bridged, not lost)
GAP = "gap."          #: sequence numbers never received, per topic
DUP = "dup."          #: sequence numbers received again, per topic
RESTART = "restart."  #: a producer's sequence began again (it restarted), per topic
ERROR = "error."      #: inputs refused and writes that failed
STEP = "step."        #: the step's own counts (``step.matched``, ``step.closures_verified``, ...)
LATENCY = "latency."  #: percentiles (µs) from receiving an input to publishing what came of it
AGE = "age."          #: percentiles (µs) from the sensor scan's stamp to publishing

IN_RAW = IN + "raw"                     #: a raw subscriber's inputs (the recorder's, any topic)
DROP_QUEUE = DROP + "queue"             #: the input queue was full
DROP_STOP = DROP + "stop"               #: inputs still queued when the service stopped
DROP_UNWRITABLE = DROP + "unwritable"   #: the recorder could not write them (full disk)
ERROR_DECODE = ERROR + "decode"         #: a payload that does not decode
ERROR_SCHEMA = ERROR + "schema"         #: an unknown schema or version
ERROR_OVERSIZE = ERROR + "oversize"     #: a payload over the size limit
ERROR_INPUT = ERROR + "input"           #: a value the step refused
ERROR_HEALTH_FILE = ERROR + "health_file"  #: the health file could not be written
STEP_ERROR = STEP + "error"             #: the step's own errors, counted with ``error.*``
OUT_HEALTH = OUT + "health"             #: health statuses (not data)

# A resumable step's checkpoints, counted by the runtime among the step's own (``step.restored``;
# lrfslam/runtime/checkpoints.py).
CHECKPOINT_SAVED = "checkpoints"                  #: checkpoints written
CHECKPOINT_FAILED = "checkpoint_failed"           #: checkpoints that could not be written
CHECKPOINT_RESTORED = "restored"                  #: resumed from a checkpoint at start
CHECKPOINT_UNREADABLE = "checkpoint_unreadable"   #: a checkpoint found at start but not read


def total(counters: Mapping[str, int], *prefixes: str) -> int:
    """Sum of the counters whose names start with one of ``prefixes``."""
    return sum(v for k, v in counters.items() if k.startswith(prefixes))
