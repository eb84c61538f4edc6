"""The compiled kernels, made ready in one call.

Numba compiles a kernel on its first call and caches the result beside its module; the first
process after an install pays the compilation (seconds), later ones load it (under a second).
:func:`prepare` does that before a live stage takes inputs, so its first scans do not wait
behind the compiler, and an image build runs it once so no container compiles.
"""

from __future__ import annotations

from lrfslam.algo import (
    correlative_kernel,
    free_space_kernel,
    grid_kernel,
    scan_match_kernel,
)


def prepare() -> None:
    """Compile (or load from numba's cache) the scan matcher's, the free-space check's, the correlative
    search's and the live grid's kernels."""
    scan_match_kernel.warm_up()
    free_space_kernel.warm_up()
    correlative_kernel.warm_up()
    grid_kernel.warm_up()
