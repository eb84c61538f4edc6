"""Pure algorithm modules stay apart from transport, the clock, the environment and the console.

Every module listed here is numpy in, numpy out: it may import only the standard
library's data-structure and maths modules, numpy/scipy/filterpy, numba (a compiler of
numpy code: the scan matcher's kernels), and other pure lrfslam modules. A new module under algo/ or sim/ is covered automatically.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[2] / "src" / "lrfslam"
PURE = sorted(
    [*SRC.glob("algo/*.py"), *SRC.glob("sim/*.py"), SRC / "io" / "carmen.py", SRC / "evaluation" / "relations.py",
     SRC / "runtime" / "pacing.py"]
    # The LMS200 driver: everything but the serial port and the emulator process is protocol.
    + [p for p in SRC.glob("drivers/lms200/*.py") if p.stem not in ("port", "emulator", "__init__")]
)
IMPURE = ("lrfslam.drivers.lms200.port", "lrfslam.drivers.lms200.emulator")

ALLOWED_ROOTS = {"__future__", "collections", "dataclasses", "typing", "math", "enum", "functools",
                 "itertools", "heapq", "operator", "struct", "zlib", "decimal", "numpy", "scipy", "filterpy", "numba",
                 "lrfslam"}
ALLOWED_LRFSLAM_PREFIXES = ("lrfslam.errors", "lrfslam.algo", "lrfslam.sim", "lrfslam.drivers.lms200")
FORBIDDEN_CALLS = {"print", "open", "input", "exec", "eval", "breakpoint"}


def imported_modules(tree: ast.Module) -> list[str]:
    names = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            names.append(node.module or "")
    return names


def test_the_list_is_not_empty():
    assert len([p for p in PURE if p.exists()]) >= 8


@pytest.mark.parametrize("path", [p for p in PURE if p.exists()], ids=lambda p: str(p.relative_to(SRC)))
def test_pure_module_imports_and_calls(path):
    tree = ast.parse(path.read_text(encoding="utf-8"))
    for name in imported_modules(tree):
        assert name.split(".")[0] in ALLOWED_ROOTS, f"{path.name} imports {name}"
        if name.startswith("lrfslam"):
            assert name.startswith(ALLOWED_LRFSLAM_PREFIXES) and not name.startswith(IMPURE), \
                f"{path.name} imports {name}"
    calls = {n.func.id for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)}
    assert not calls & FORBIDDEN_CALLS, f"{path.name} calls {calls & FORBIDDEN_CALLS}"


def test_checker_catches_a_violation(tmp_path):
    bad = ast.parse("import zenoh\nfrom time import monotonic\nprint(1)\n")
    names = imported_modules(bad)
    assert [n for n in names if n.split(".")[0] not in ALLOWED_ROOTS] == ["zenoh", "time"]


#: The views for viewers (lrfslam/viz) are pure too: lrfslam messages in, foxglove-sdk's message
#: objects out (``foxglove.messages`` only: never its server, channels or files).
VIEWS = sorted(SRC.glob("viz/*.py"))


@pytest.mark.parametrize("path", VIEWS, ids=lambda p: str(p.relative_to(SRC)))
def test_views_import_no_transport_and_call_no_console(path):
    tree = ast.parse(path.read_text(encoding="utf-8"))
    for name in imported_modules(tree):
        if name.split(".")[0] == "foxglove":
            assert name == "foxglove.messages", f"{path.name} imports {name}"
            continue
        assert name.split(".")[0] in ALLOWED_ROOTS, f"{path.name} imports {name}"
        if name.startswith("lrfslam"):
            assert name.startswith((*ALLOWED_LRFSLAM_PREFIXES, "lrfslam.msgs", "lrfslam.viz")), \
                f"{path.name} imports {name}"
    calls = {n.func.id for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)}
    assert not calls & FORBIDDEN_CALLS, f"{path.name} calls {calls & FORBIDDEN_CALLS}"


def test_the_views_are_checked():
    assert SRC / "viz" / "foxglove.py" in VIEWS
