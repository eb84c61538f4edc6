"""Validation shared by the algorithms' parameter dataclasses."""

from __future__ import annotations

import math
from collections.abc import Iterable

from lrfslam.errors import ConfigError


def require_finite(params: object, names: Iterable[str], *, positive: bool, what: str = "") -> None:
    """Raise ConfigError unless every named field of ``params`` is finite and > 0 (``positive``) or >= 0.

    ``what`` prefixes the message (e.g. "scan matching ") so the user knows which table it belongs to.
    """
    for name in names:
        value = getattr(params, name)
        ok = isinstance(value, (int, float)) and math.isfinite(value) and (value > 0 if positive else value >= 0)
        if not ok:
            raise ConfigError(f"{what}{name} must be finite and {'>' if positive else '>='} 0, got {value!r}")
