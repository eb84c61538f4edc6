"""Checkpoints: a stage that keeps state saves it, and a restarted one resumes.

A step that keeps state worth resuming (the slam's filter, the mapper's pose graph) is
:class:`Resumable`: it gives its state as named arrays (:meth:`Resumable.snapshot`) and takes them
back (:meth:`Resumable.restore`). Where the file lives and how often it is written belong to the
runtime, not to the step: :class:`Checkpointer` keeps ``<dir>/<service>.checkpoint.npz``, written
atomically every ``period_s`` of *data* time (the stamps of the inputs, so a replayed or sped-up
run saves as often per scan as a live one) and at a clean stop, and read back when the stage
starts. The live runner and the in-process chain both drive it (``bus.checkpoint_dir``,
``bus.checkpoint_period_s``); a replay writes none.

An unreadable file (damaged, another version's) is counted (``step.checkpoint_unreadable``) and the
stage starts afresh; it is never overwritten until the step has something to save.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Mapping
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from lrfslam.errors import InputError
from lrfslam.msgs import counters
from lrfslam.runtime import npz_file

log = logging.getLogger("lrfslam.checkpoints")

#: Data time between two saves by default (s): 50 scans of the LMS200 at 10 Hz.
PERIOD_S = 5.0
#: The file a service's checkpoint is kept in, under the checkpoint folder.
SUFFIX = ".checkpoint.npz"


@runtime_checkable
class Resumable(Protocol):
    """A step whose state a restarted process resumes."""

    def snapshot(self) -> dict[str, np.ndarray] | None:
        """The state as named arrays; None while there is nothing worth saving (no scan yet)."""

    def restore(self, arrays: Mapping[str, np.ndarray]) -> str:
        """Continue from ``arrays`` (as :meth:`snapshot` gave them); one line saying where it resumed.

        Raises
        ------
        InputError, ValueError, KeyError
            If the arrays are not a snapshot this version reads; the step is left as it was.
        """


def path_for(directory: str | Path, service: str) -> Path:
    """The checkpoint file of ``service`` in ``directory``."""
    return Path(directory) / f"{service}{SUFFIX}"


class Checkpointer:
    """Saves a :class:`Resumable` step to ``path`` every ``period_s`` of data time and at a clean stop.

    Parameters
    ----------
    step : Resumable
        Counted in its own ``counts`` where it has them (a :class:`~lrfslam.runtime.step.StepBase`):
        ``checkpoints``, ``checkpoint_failed``, ``restored``, ``checkpoint_unreadable``.
    path : Path
    period_s : float
        Data time (s) between two saves; the first comes ``period_s`` after the first input.
    """

    def __init__(self, step: Resumable, path: Path, period_s: float) -> None:
        self.step = step
        self.counts: Counter = getattr(step, "counts", Counter())
        self.path = path
        self._period_ns = int(period_s * 1e9)
        self._last_ns: int | None = None

    def restore(self) -> None:
        """Resume the step from the file, if there is one."""
        if not self.path.exists():
            return
        try:
            where = self.step.restore(npz_file.read(self.path))
        except (OSError, ValueError, KeyError, InputError) as exc:
            log.warning("ignoring unreadable checkpoint %s: %s", self.path, exc)
            self.counts[counters.CHECKPOINT_UNREADABLE] += 1
            return
        log.info("resumed from %s: %s", self.path, where)
        self.counts[counters.CHECKPOINT_RESTORED] += 1

    def after(self, stamp_ns: int) -> None:
        """An input stamped ``stamp_ns`` was handled: save if ``period_s`` of data time has passed.

        Data time going back (another run, a replayed loop) starts the period afresh.
        """
        if self._last_ns is None or stamp_ns < self._last_ns or stamp_ns - self._last_ns >= self._period_ns and self.save():
            self._last_ns = stamp_ns

    def save(self) -> bool:
        """Write the step's snapshot now; False if it has nothing to save yet.

        A failed write (a full disk) leaves the previous file whole; it is counted and logged, and
        the stage goes on (the next try one period later): a checkpoint is worth less than the run.
        """
        arrays = self.step.snapshot()
        if arrays is None:
            return False
        try:
            npz_file.write_atomic(self.path, arrays)
        except OSError as exc:
            if not self.counts[counters.CHECKPOINT_FAILED]:
                log.warning("cannot write the checkpoint %s: %s", self.path, exc)
            self.counts[counters.CHECKPOINT_FAILED] += 1
            return True
        self.counts[counters.CHECKPOINT_SAVED] += 1
        return True
