"""Open a text log that may be bzip2- or gzip-compressed; find the CARMEN logs in a folder.

Kept apart from the pure parsers (:mod:`lrfslam.io.carmen`,
:mod:`lrfslam.evaluation.relations`), which only ever see lines of text.
"""

from __future__ import annotations

import bz2
import gzip
import os
from pathlib import Path
from typing import TextIO

#: How a CARMEN log file's name ends (plain or compressed).
CARMEN_SUFFIXES = (".clf", ".clf.gz", ".clf.bz2")

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


def carmen_logs(folder: str | Path) -> list[Path]:
    """Every CARMEN log file under ``folder`` (``*.clf``, ``.clf.gz``, ``.clf.bz2``, at any depth), in path order.

    Symbolic links to folders are followed (a datasets folder of links to where the logs are
    kept), each real folder once, so a link back up the tree does not loop; of two paths to one
    folder, the first in name order is the one given.
    """
    found, seen = [], set()
    for here, subfolders, files in os.walk(folder, followlinks=True):
        real = os.path.realpath(here)
        if real in seen:
            subfolders.clear()
            continue
        seen.add(real)
        subfolders.sort()   # walked in name order, whatever order the file system lists them in
        found += [Path(here, f) for f in files if f.endswith(CARMEN_SUFFIXES) and Path(here, f).is_file()]
    return sorted(found)


def log_name(path: str | Path) -> str:
    """A CARMEN log's file name without its suffix: ``intel.clf.bz2`` -> ``intel``."""
    name = Path(path).name
    for suffix in CARMEN_SUFFIXES:
        name = name.removesuffix(suffix)
    return name
