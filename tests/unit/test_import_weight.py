"""The stages that need no sparse algebra do not import scipy.

scipy.sparse and its solvers add ~38 MB to a process's resident memory. The hour's soak at
50c8c80 found the recorder 33 MB heavier from the start when a display helper imported the
mapper's module for one function (docs/operations.md, "Soak").
"""

from __future__ import annotations

import subprocess
import sys

import pytest


@pytest.mark.parametrize("service", ["sensor", "denoise", "features", "recorder"])
def test_a_light_stage_does_not_import_scipy(service):
    code = (f"import importlib, sys; importlib.import_module('lrfslam.services.{service}'); "
            "import lrfslam.viz.dashboard; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] == 'scipy')[:5])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]", f"{service} imports {out.strip()}"
