"""Fixtures shared by every test folder."""

from __future__ import annotations

import importlib

import pytest


@pytest.fixture(scope="session")
def soak_module():
    """``lrfslam.bench.soak``: its run, its memory levels and its process helpers."""
    return importlib.import_module("lrfslam.bench.soak")
