"""Named arrays in an ``.npz`` file, written atomically (the checkpoints' storage)."""

from __future__ import annotations

import os
import zipfile
from pathlib import Path

import numpy as np


def write_atomic(path: Path, arrays: dict) -> None:
    """Write ``arrays`` to ``path``: a crash mid-write leaves the previous file intact.

    The data goes to ``<path>.tmp``, is synced to disk, then renamed over ``path``.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        np.savez(f, **arrays)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def read(path: Path) -> dict[str, np.ndarray]:
    """The arrays of ``path``, loaded (no pickles).

    Raises
    ------
    OSError, ValueError
        If the file cannot be read or is no ``.npz`` of plain arrays.
    """
    try:
        with np.load(path) as data:
            return {k: data[k] for k in data.files}
    except zipfile.BadZipFile as exc:
        raise ValueError(f"{path}: {exc}") from None
