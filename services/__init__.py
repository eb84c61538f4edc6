"""The processes of the pipeline, one module each (installed as ``lrfslam.services``).

Each module defines ``SPEC``: its config dataclass, input and output topics and
step. :data:`NAMES` is the pipeline order: each service takes its inputs from services before
it, the recorder (last) everything (``tests/unit/test_services.py`` holds the specs to it).
``lrfslam up`` starts them in the reverse order, so every consumer listens before its producer
sends, and stops them in this order, so each drains what the one before it sent.
:func:`spec` imports one lazily so a service never loads the algorithms of another.
"""

from __future__ import annotations

import importlib
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from lrfslam.runtime.chain import DEFAULT_ROBOT, Stage, configure
from lrfslam.runtime.step import ServiceSpec

NAMES: tuple[str, ...] = ("sensor", "denoise", "features", "slam", "mapper", "recorder")

#: The tables a config file may hold: the bus's and one per service.
CONFIG_TABLES: tuple[str, ...] = ("bus", *NAMES)


def spec(name: str) -> ServiceSpec:
    """The ServiceSpec of service ``name``."""
    if name not in NAMES:
        raise KeyError(name)
    return importlib.import_module(f"lrfslam.services.{name}").SPEC


def stage(name: str, *, sets: Iterable[str] = (), config_file: str | Path | Mapping | None = None,
          env: Mapping[str, str] | None = None) -> Stage:
    """Service ``name`` configured as the runner would (see :func:`lrfslam.runtime.chain.configure`)."""
    return configure(spec(name), sets=sets, config_file=config_file, env=env)


def build_step(name: str, *, sets: Iterable[str] = (), config_file: str | Path | Mapping | None = None,
               env: Mapping[str, str] | None = None, robot: str = DEFAULT_ROBOT) -> Any:
    """The step of service ``name``, configured by :func:`stage`: the one way to make a step in code."""
    return stage(name, sets=sets, config_file=config_file, env=env).build(robot)
