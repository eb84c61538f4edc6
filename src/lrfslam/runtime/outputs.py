"""Files an offline command writes are complete or absent.

``lrfslam pipeline``, ``<service> --replay``, ``import``, ``export`` and ``eval`` write
each output to a hidden file next to it (``.<stem>.<pid>.partial<suffix>``) and rename
it over the output only once the command has finished (:func:`atomic_output`). An
error, Ctrl-C or SIGTERM removes the partial file instead, so an output either holds
the whole result or does not exist, and a previous file of that name is left as it
was. SIGTERM does that by being raised in the main thread like Ctrl-C
(:func:`raise_on_signals`), so every ``finally`` runs.
"""

from __future__ import annotations

import os
import signal
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


class Interrupted(KeyboardInterrupt):
    """SIGTERM or SIGINT received; ``signum`` says which (the exit code is 128 + signum)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def raise_on_signals() -> None:
    """Make SIGTERM and SIGINT raise :class:`Interrupted` in the main thread.

    The first signal raises; the handlers then go back to the defaults, so a second
    signal ends a clean-up that hangs.
    """
    def handler(signum: int, _frame) -> None:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        raise Interrupted(signum)
    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGINT, handler)


def _partial_path(path: str | Path) -> Path:
    """Where :func:`atomic_output` writes ``path`` until it is complete (same folder, hidden)."""
    path = Path(path)
    return path.with_name(f".{path.stem}.{os.getpid()}.partial{path.suffix}")


@contextmanager
def atomic_output(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path to write ``path`` to; on success it becomes ``path``.

    The folder of ``path`` is created. If the body raises (including
    :class:`KeyboardInterrupt` and :class:`Interrupted`), the temporary file is
    removed and ``path`` is untouched. The temporary file keeps the suffix of
    ``path``, so writers that pick a format by it (matplotlib) still do.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _partial_path(path)
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
