"""Fixtures of the deployment tests."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"


@pytest.fixture(scope="session")
def make_certs():
    """``deploy/zenoh/make-certs.sh OUT ROBOT_HOST`` run as a user runs it. The script calls ``lrfslam
    certs``, so this interpreter's scripts folder goes first on PATH, as an activated venv puts it."""
    env = dict(os.environ, PATH=os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")]))

    def make(out: Path, host: str = "robot.test") -> subprocess.CompletedProcess:
        return subprocess.run([str(DEPLOY / "zenoh" / "make-certs.sh"), str(out), host], check=True,
                              capture_output=True, text=True, timeout=60, env=env)
    return make
