"""Docstrings and comments point only at files in this repository.

Every .py file under src/, services/ and tests/ is scanned for

* repository paths (``docs/<page>.md``, ``tests/data/<path>``, ``src/<path>.py``): each must
  exist, and a docs page followed by quoted section names (``docs/<page>.md, 'Name'``) must
  have a heading of each name;
* citations of notes that are not shipped with the project ("notes" or "note" followed by a
  section sign, a path into a notes folder, or a bare section sign with a number): there must
  be none.
  The SICK Telegram Listing ("TL") and the paper's own sections are public and allowed.

The section sign and the slash after "notes" are escaped in this file so that it does not
flag itself.
"""

from __future__ import annotations

import re
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SCANNED_DIRS = ("src", "services", "tests")

# A repository path, not the tail of a longer one (``../shared/docs/x.md`` is not ours).
_PATH = re.compile(r"(?<![\w./-])(docs/[\w./-]+?\.md|tests/data/[\w./*-]*|src/[\w./-]+?\.py)")
# Quoted section names right after a docs page: ``docs/<page>.md, 'A' and 'B'``.
_SECTIONS = re.compile(r"(docs/[\w./-]+?\.md)((?:\s*(?:,|and)\s*'[^'\n]+')+)")
_QUOTED = re.compile(r"'([^'\n]+)'")
_CITATIONS = (
    re.compile(r"\bnotes?\b[^\n\u00a7]{0,12}\u00a7"),  # "notes \u00a75.4", "reading notes (\u00a72)"
    re.compile(r"\bnotes\/"),                          # a notes folder
    re.compile(r"shared\/notes\b"),
    re.compile(r"(?<!TL )(?<!paper )\u00a7\s*\d"),     # a bare "(\u00a74.4)"
)

@cache
def headings(page: Path) -> frozenset[str]:
    """Heading texts of a markdown page (any level), code blocks skipped."""
    found = set()
    in_code = False
    for line in page.read_text(encoding="utf-8").splitlines():
        if line.startswith("```"):
            in_code = not in_code
        elif not in_code and line.startswith("#"):
            found.add(line.lstrip("#").strip())
    return frozenset(found)


def citation_problems(text: str) -> list[str]:
    """Citations of notes outside the repository found in ``text``."""
    return [f"cites notes outside the repository: {m.group(0)!r}"
            for pattern in _CITATIONS for m in pattern.finditer(text)]


def path_problems(text: str, root: Path = ROOT) -> list[str]:
    """Repository paths in ``text`` that do not exist, and section names a docs page lacks."""
    out = []
    for m in _PATH.finditer(text):
        ref = m.group(1).rstrip(".,")
        exists = any(root.glob(ref)) if "*" in ref else (root / ref).exists()
        if not exists:
            out.append(f"no such file in the repository: {ref}")
    for m in _SECTIONS.finditer(text):
        page = root / m.group(1)
        if not page.is_file():
            continue  # reported above
        for name in _QUOTED.findall(m.group(2)):
            if name not in headings(page):
                out.append(f"{m.group(1)} has no section {name!r}")
    return out


def scanned_files() -> list[Path]:
    return sorted(p for d in SCANNED_DIRS for p in (ROOT / d).rglob("*.py"))


def test_every_reference_points_into_the_repository():
    problems = []
    for path in scanned_files():
        rel = path.relative_to(ROOT).as_posix()
        text = path.read_text(encoding="utf-8")
        found = path_problems(text) + citation_problems(text)
        problems += [f"{rel}: {p}" for p in found]
    assert not problems, "\n".join(problems)


def test_the_scan_covers_the_code():
    rels = {p.relative_to(ROOT).as_posix() for p in scanned_files()}
    assert {"src/lrfslam/drivers/lms200/protocol.py", "tests/unit/test_docstring_references.py"} <= rels


@pytest.mark.parametrize("text", [
    "Forward searching (notes \u00a75.4): from each base point",
    "logically invalid command (note \u00a72.1).",
    "Definitions follow the reading notes (\u00a72): a corner is",
    "Section numbers refer to ``notes" + "/lms200-protocol.md``.",
    "copied from ../shared/no" + "tes/lms200-vectors",
    "The LMS acknowledges at the old rate, then switches (\u00a73).",
])
def test_planted_citation_is_caught(text):
    assert citation_problems(text)


@pytest.mark.parametrize("text", [
    "see " + "docs/" + "no-such-page.md, 'Framing'",
    "vectors in " + "tests/data/" + "lms200/V9_missing.hex",
    "as in " + "src/lrfslam/" + "nowhere.py",
    "docs/paper-reading.md, 'Forward searching' and " + "'No such section'",
    "docs/lms200-protocol.md, " + "'Framing and more'",
])
def test_planted_bad_path_is_caught(text):
    assert path_problems(text)


@pytest.mark.parametrize("text", [
    "SICK's CRC (docs/lms200-protocol.md, 'CRC'), TL p.107",
    "one mirror turn, 75 Hz (TL \u00a73.4); paper \u00a7IV",
    "docs/lms200-protocol.md, 'Baud rates and switching' and 'Operating modes (20h)'",
    "the copies in tests/data/lms200/ and tests/data/lms200/*.hex",
    "see src/lrfslam/algo/histogram.py.",
    "datasets under ../shared/datasets/intel/ stay outside",
])
def test_good_references_pass(text):
    assert not path_problems(text) and not citation_problems(text)
