"""Recordings compared as decoded messages, field by field, with stated tolerances.

Byte-identity of a replay holds within one machine (run twice, compare the files). Across
machines numpy's SIMD kernels and OpenBLAS's kernels round the last bit differently (another
CPU, or ``NPY_DISABLE_CPU_FEATURES`` / ``OPENBLAS_CORETYPE`` on this one), so outputs made
elsewhere — the golden recordings — are compared here: topics, schemas, stamps and sequence
numbers exactly; integers, strings and flags exactly; floats within ``atol + rtol * |expected|``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from lrfslam.msgs import topics
from lrfslam.runtime.recording import read_metadata, read_recording

#: A stage's own output from the same input: round-off only (seen: 1e-16 on ``wall_direction_rad``).
ROUND_OFF = (1e-9, 1e-9)
#: The EKF carried over the golden recordings' 80-150 scans: round-off the filter carries on
#: (seen: 1e-15 m); a changed association or match would move a pose by centimetres.
SHORT_SLAM_RUN = (1e-6, 1e-6)


def decoded(path: Path) -> list[tuple]:
    """Every message of a recording as (topic, schema, stamp ns, receive ns, sequence, decoded value)."""
    out = []
    for m in read_recording(path):
        value = topics.by_name(m.topic).codec.decode(m.data, m.schema)
        out.append((m.topic, m.schema, m.stamp_ns, m.receive_ns, m.sequence, value))
    return out


def _fields(value, where: str) -> Iterable[tuple[str, object]]:
    if dataclasses.is_dataclass(value):
        for f in dataclasses.fields(value):
            yield from _fields(getattr(value, f.name), f"{where}.{f.name}")
    elif isinstance(value, dict):
        yield f"{where}{{keys}}", tuple(sorted(value))
        for k in sorted(value):
            yield from _fields(value[k], f"{where}[{k!r}]")
    elif isinstance(value, tuple | list):
        yield f"{where}(len)", len(value)
        for i, v in enumerate(value):
            yield from _fields(v, f"{where}[{i}]")
    else:
        yield where, value


def differences(actual, expected, atol: float, rtol: float, where: str = "") -> list[str]:
    """Where two decoded values differ beyond the tolerance: one line each (empty: equal)."""
    got, want = list(_fields(actual, where)), list(_fields(expected, where))
    if [name for name, _ in got] != [name for name, _ in want]:
        return [f"{where}: a different structure"]
    found = []
    for (name, a), (_, b) in zip(got, want, strict=True):
        if isinstance(a, float | np.floating) or (isinstance(a, np.ndarray) and a.dtype.kind == "f"):
            a, b = np.asarray(a, float), np.asarray(b, float)
            if a.shape != b.shape:
                found.append(f"{name}: shape {a.shape} against {b.shape}")
            elif not np.allclose(a, b, atol=atol, rtol=rtol, equal_nan=True):
                with np.errstate(invalid="ignore"):
                    gap = np.abs(a - b)
                worst = np.nanmax(gap) if np.isfinite(gap).any() else float("nan")
                found.append(f"{name}: differs by up to {worst:.3g} (tolerance {atol:g} + {rtol:g} x)")
        elif isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
            if not np.array_equal(a, b):
                found.append(f"{name}: {a!r} against {b!r}")
        elif a != b:
            found.append(f"{name}: {a!r} against {b!r}")
    return found


def assert_same_messages(actual: Path, expected: Path, tolerance: dict[str, tuple[float, float]],
                         metadata: bool = True) -> None:
    """``actual`` holds ``expected``'s messages, within ``tolerance``: topic -> (atol, rtol),
    :data:`ROUND_OFF` for topics it does not name; and its metadata records, unless not ``metadata``."""
    if metadata:
        assert read_metadata(actual) == read_metadata(expected)
    got, want = decoded(actual), decoded(expected)
    assert [m[:5] for m in got] == [m[:5] for m in want], "topics, schemas, stamps or sequence numbers differ"
    problems = []
    for a, b in zip(got, want, strict=True):
        atol, rtol = tolerance.get(a[0], ROUND_OFF)
        problems += differences(a[5], b[5], atol, rtol, f"{a[0]} #{a[4]}")
    assert not problems, "\n".join(problems[:20])
