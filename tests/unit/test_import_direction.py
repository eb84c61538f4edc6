"""Rooms import only downward: the table in docs/architecture.md, checked on every module.

A room is a top-level package of ``lrfslam`` (``algo``, ``msgs``, ``runtime`` …; ``services``
is the top-level ``services/`` folder). Imports inside functions count too: a lazy import
is still a dependency.
"""

from __future__ import annotations

import ast
import re
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SRC = ROOT / "src" / "lrfslam"

# Each room and the rooms it may import (besides itself and the package root ``lrfslam``).
BASE = {"errors"}
MAY_IMPORT: dict[str, set[str]] = {
    "errors": set(),
    "extras": BASE,
    "algo": BASE,
    "io": BASE,
    "msgs": BASE,
    "sim": BASE | {"algo"},
    "drivers": BASE | {"sim", "algo"},
    "runtime": BASE | {"msgs", "extras"},
    "viz": BASE | {"msgs", "algo"},
    "ros2": BASE | {"msgs", "algo"},
    "services": BASE | {"runtime", "viz", "msgs", "algo", "sim", "drivers", "io", "extras"},
    "evaluation": BASE | {"services", "runtime", "ros2", "msgs", "algo", "sim", "io", "extras"},
    "tools": BASE | {"evaluation", "services", "runtime", "viz", "ros2", "msgs", "algo", "sim", "drivers", "io", "extras"},
    "bench": BASE | {"tools", "evaluation", "services", "runtime", "viz", "ros2", "msgs", "algo", "sim", "drivers", "io",
                     "extras"},
    "cli": BASE | {"services", "runtime", "tools", "bench"},
}


def modules() -> list[tuple[str, Path]]:
    """(room, path) of every module of the distribution."""
    found = [(p.relative_to(SRC).parts[0].removesuffix(".py"), p) for p in SRC.rglob("*.py")
             if p.parent != SRC or p.stem != "__init__"]
    return found + [("services", p) for p in (ROOT / "services").glob("*.py")]


def rooms_imported(source: str) -> set[str]:
    """Rooms of ``lrfslam`` that ``source`` imports (absolute imports only; the package uses no others)."""
    rooms = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names = [node.module] + ([f"{node.module}.{a.name}" for a in node.names] if node.module == "lrfslam"
                                     else [])
        else:
            continue
        rooms |= {name.split(".")[1] for name in names if name.startswith("lrfslam.")}
    return rooms - {"__name__", "__version__"}


def test_every_room_is_in_the_table():
    assert {room for room, _ in modules()} <= set(MAY_IMPORT)


@pytest.mark.parametrize(("room", "path"), modules(), ids=lambda v: v if isinstance(v, str) else v.name)
def test_imports_go_downward(room, path):
    wrong = rooms_imported(path.read_text(encoding="utf-8")) - MAY_IMPORT[room] - {room}
    assert not wrong, f"{path.relative_to(ROOT)} ({room}) imports {sorted(wrong)}"


def test_the_checker_sees_lazy_and_package_imports():
    source = ("from lrfslam import services\n"
              "def f():\n    import lrfslam.tools.up\n"
              "from lrfslam.msgs import topics\n")
    assert rooms_imported(source) == {"services", "tools", "msgs"}


def module_name(path: Path) -> str:
    """``lrfslam.runtime.recording.reader`` for src/lrfslam/runtime/recording/reader.py (services/ too)."""
    parts = (path.relative_to(SRC).with_suffix("").parts if path.is_relative_to(SRC)
             else ("services", path.stem))
    return ".".join(("lrfslam", *parts)).removesuffix(".__init__")


def module_imports(source: str, known: set[str]) -> set[str]:
    """The modules of ``known`` that ``source`` imports at run time (not for type checking only),
    a name imported from a module counted as it."""
    tree = ast.parse(source)
    typing_only = {id(n) for block in ast.walk(tree) if isinstance(block, ast.If)
                   and isinstance(block.test, ast.Name) and block.test.id == "TYPE_CHECKING"
                   for n in ast.walk(block)}
    found = set()
    for node in ast.walk(tree):
        if id(node) in typing_only:
            continue
        elif isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found |= {node.module} | {f"{node.module}.{a.name}" for a in node.names}
    return found & known


def test_no_module_imports_itself_back_through_others():
    """No import cycle: a cycle (eval_logs <-> evaluate once) means two modules share one idea.
    A package's own ``__init__`` re-exporting its modules is not one."""
    paths = {module_name(p): p for _, p in modules()}
    known = set(paths) | {module_name(p) for p in SRC.rglob("__init__.py")}
    graph = {name: {m for m in module_imports(path.read_text(encoding="utf-8"), known)
                    if m != name and not name.startswith(m + ".")}
             for name, path in paths.items()}
    state: dict[str, int] = {}

    def visit(name: str, trail: list[str]) -> None:
        state[name] = 1
        for nxt in sorted(graph.get(name, ())):
            assert state.get(nxt) != 1, f"import cycle: {' -> '.join([*trail[trail.index(nxt):], nxt])}"
            if nxt not in state:
                visit(nxt, [*trail, nxt])
        state[name] = 2

    for name in sorted(graph):
        if name not in state:
            visit(name, [name])


def test_every_package_is_installed():
    """pyproject.toml lists the packages by hand: one left out imports from a checkout
    (an editable install) and fails from a wheel or the container image."""
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {module_name(p) for p in SRC.rglob("__init__.py")} | {"lrfslam.services"}
    assert listed == found


def test_docs_architecture_names_every_module():
    """docs/architecture.md's "Every module" lists each module once (generated protobuf modules aside)."""
    text = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    listed = re.findall(r"^- `([\w/]+\.py)`:", text.split("## Every module", 1)[1], flags=re.MULTILINE)
    present = [str(p.relative_to(SRC)) for p in SRC.rglob("*.py")
               if not p.name.endswith("_pb2.py") and p != SRC / "__init__.py"
               and (p.name != "__init__.py" or p.parent.name in ("recording", "loop_closure"))]
    present += [f"services/{p.name}" for p in (ROOT / "services").glob("*.py")]
    assert sorted(listed) == sorted(present)
