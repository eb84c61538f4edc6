"""The CLF parser and the relation metric stay pure: stdlib data types + numpy only."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[2] / "src" / "lrfslam"
PURE = [SRC / "io" / "carmen.py", SRC / "evaluation" / "relations.py"]

ALLOWED_ROOTS = {"__future__", "collections", "dataclasses", "typing", "math", "numpy", "lrfslam"}
ALLOWED_LRFSLAM = {"lrfslam.errors", "lrfslam.algo.geometry"}
FORBIDDEN_CALLS = {"print", "open", "input", "exec", "eval"}


def imported_modules(tree: ast.Module) -> list[str]:
    names = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            names.append(node.module or "")
    return names


@pytest.mark.parametrize("path", PURE, ids=lambda p: p.name)
def test_pure_module_imports_and_calls(path):
    tree = ast.parse(path.read_text(encoding="utf-8"))
    for name in imported_modules(tree):
        assert name.split(".")[0] in ALLOWED_ROOTS, f"{path.name} imports {name}"
        if name.startswith("lrfslam"):
            assert name in ALLOWED_LRFSLAM, f"{path.name} imports {name}"
    calls = {n.func.id for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)}
    assert not calls & FORBIDDEN_CALLS, f"{path.name} calls {calls & FORBIDDEN_CALLS}"
