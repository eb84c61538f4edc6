"""A service's health in a local file, for container healthchecks (``lrfslam status --check-file``).

A healthcheck that asks the router runs a new Zenoh client inside the container, and so
depends on the container resolving the router's name: under podman that lookup has been
seen to time out (10 s) for one container while its service itself stayed connected. The
service's own view is what the check should report anyway: its main loop rewrites this
file every ``bus.health_period_s`` with its health level and whether its session has a
router or peer, and the check reads it without any network.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

from lrfslam.msgs import types as t

#: A file older than this, in health periods, belongs to a main loop that stopped turning.
STALE_PERIODS = 10


@dataclass(frozen=True)
class HealthRecord:
    """What one service writes; ``wall_stamp_ns`` is the host's wall clock at the write."""

    service: str
    robot: str
    level: int                 # HEALTH_* (lrfslam.msgs.types)
    message: str
    wall_stamp_ns: int
    health_period_s: float
    connected: bool            # the Zenoh session has at least one router or peer
    pid: int


def write(path: str | Path, record: HealthRecord) -> None:
    """Replace ``path`` with ``record`` as JSON (a reader never sees half a file).

    Raises
    ------
    OSError
        The file cannot be written.
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(asdict(record)))
    os.replace(tmp, path)


def problems(path: str | Path, now_ns: int) -> list[str]:
    """Why the service that writes ``path`` is not healthy (empty when it is).

    Healthy: the file is there, parses, is newer than ``STALE_PERIODS`` health periods,
    says the session is connected, and its level is not ERROR (WARN and STALE pass, as
    in :func:`lrfslam.tools.status.check`).
    """
    try:
        record = HealthRecord(**json.loads(Path(path).read_text()))
    except FileNotFoundError:
        return [f"{path}: no health file (is the service started with --health-file {path}?)"]
    except (OSError, ValueError, TypeError) as exc:
        return [f"{path}: unreadable health file: {exc}"]
    found = []
    age_s = (now_ns - record.wall_stamp_ns) / 1e9
    if age_s > STALE_PERIODS * record.health_period_s:
        found.append(f"{record.service}: health file written {age_s:.0f} s ago (main loop stuck or process gone)")
    if not record.connected:
        found.append(f"{record.service}: no router or peer connected")
    if record.level == t.HEALTH_ERROR:
        found.append(f"{record.service}@{record.robot}: ERROR {record.message}")
    return found
