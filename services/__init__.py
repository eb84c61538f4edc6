"""The five processes of the pipeline, one module each (installed as ``lrfslam.services``).

Each module defines ``SPEC``: its config dataclass, input and output topics and
step. :data:`NAMES` is the pipeline order; :func:`spec` imports one lazily so a
service never loads the algorithms of another.
"""

from __future__ import annotations

import importlib

from lrfslam.runtime.step import ServiceSpec

NAMES: tuple[str, ...] = ("sensor", "denoise", "feature", "slam", "recorder")


def spec(name: str) -> ServiceSpec:
    """The ServiceSpec of service ``name``."""
    if name not in NAMES:
        raise KeyError(name)
    return importlib.import_module(f"lrfslam.services.{name}").SPEC
