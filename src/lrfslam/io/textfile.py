"""Open a text log that may be bzip2- or gzip-compressed.

Kept apart from the pure parsers (:mod:`lrfslam.io.carmen`,
:mod:`lrfslam.evaluation.relations`), which only ever see lines of text.
"""

from __future__ import annotations

import bz2
import gzip
from pathlib import Path
from typing import TextIO

# Detect compression from the content, not the name: datasets get renamed.
_BZIP2_MAGIC = b"BZh"
_GZIP_MAGIC = b"\x1f\x8b"


def open_log(path: str | Path) -> TextIO:
    """Open a plain, ``.bz2`` or ``.gz`` text file for reading.

    Parameters
    ----------
    path : str or Path
        File to open; compression is recognised by its magic bytes.

    Returns
    -------
    TextIO
        Text stream yielding lines; use it as a context manager. Undecodable
        bytes become U+FFFD so that a damaged line surfaces as a parser issue
        instead of aborting the read.
    """
    path = Path(path)
    with path.open("rb") as probe:
        magic = probe.read(3)
    if magic.startswith(_BZIP2_MAGIC):
        return bz2.open(path, "rt", encoding="utf-8", errors="replace")
    if magic.startswith(_GZIP_MAGIC):
        return gzip.open(path, "rt", encoding="utf-8", errors="replace")
    return path.open("r", encoding="utf-8", errors="replace")
