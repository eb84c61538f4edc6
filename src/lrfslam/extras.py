"""Optional dependencies: import one, or say in one line which extra installs it.

Heavy packages that only some commands need (plotting) are extras of the
distribution (``pip install 'lrfslam[plot]'``), not requirements of the pipeline.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from lrfslam.errors import MissingExtraError


def require(module: str, extra: str, purpose: str) -> ModuleType:
    """Import ``module``, or raise :class:`MissingExtraError` naming ``extra``.

    Raises
    ------
    MissingExtraError
        ``module`` is not installed.
    """
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if exc.name != module.partition(".")[0]:
            raise   # the package is there but broken: a real error, not a missing extra
        raise MissingExtraError(f"{purpose} needs {module}, which is not installed: "
                                f"pip install 'lrfslam[{extra}]'") from None
