"""Fixtures shared by every test folder."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def soak_module():
    """benchmarks/soak.py as a module: its run, its memory levels and its process helpers."""
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "soak.py"
    spec = importlib.util.spec_from_file_location("soak", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules["soak"] = module   # dataclasses look their module up by name
    spec.loader.exec_module(module)
    return module
