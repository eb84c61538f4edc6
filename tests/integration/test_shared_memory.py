"""Zenoh's shared memory is off unless a config file asks for it (``bus.base_config``).

Real sessions over loopback TCP: a router, a publisher and a subscriber made as the services
and tools make theirs. A 10 KB message (over Zenoh's 3 KB threshold) arrives without any
16 MiB pool mapped from /dev/shm; a config file that enables shared memory gets it. Only the files
this process maps (``/proc/self/maps``) are looked at and removed.
"""

from __future__ import annotations

import json
import threading
from pathlib import Path

import pytest
import zenoh
from conftest import free_port

from lrfslam.runtime.bus import base_config

pytestmark = pytest.mark.integration

SHM = Path("/dev/shm")
POOL_BYTES = 16 * 2**20


MAPS = Path("/proc/self/maps")


def own_zenoh_files() -> dict[str, int]:
    """The Zenoh shared-memory files this process has mapped now: name -> size (bytes). Only
    these are looked at and removed: other processes' files in /dev/shm are none of the test's."""
    names = set()
    for line in MAPS.read_text().splitlines():
        path = line.split(maxsplit=5)[5] if len(line.split(maxsplit=5)) == 6 else ""
        if path.startswith(f"{SHM}/") and path.endswith(".zenoh"):
            names.add(Path(path).name)
    return {name: (SHM / name).stat().st_size for name in names if (SHM / name).exists()}


def send_big_message(port: int, zenoh_config: str | None) -> set[str]:
    """Router, subscriber and publisher as lrfslam makes them; one 10 KB put; the pools that appeared."""
    router = base_config("router", [], zenoh_config)
    router.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    got = threading.Event()
    with zenoh.open(router), zenoh.open(base_config("client", [f"tcp/127.0.0.1:{port}"], zenoh_config)) as sub_s, \
            zenoh.open(base_config("client", [f"tcp/127.0.0.1:{port}"], zenoh_config)) as pub_s:
        sub = sub_s.declare_subscriber("lrf/shm_test/big", lambda s: got.set() if len(s.payload.to_bytes()) == 10_000 else None)
        pub = pub_s.declare_publisher("lrf/shm_test/big")
        for _ in range(50):   # until the subscription has reached the publisher
            pub.put(b"x" * 10_000)
            if got.wait(0.1):
                break
        appeared = own_zenoh_files()
        sub.undeclare()
    for name in appeared:   # Zenoh leaves a closed session's files for the next session to clean
        (SHM / name).unlink(missing_ok=True)
    assert got.is_set(), "the 10 KB message never arrived"
    return {name for name, size in appeared.items() if size >= POOL_BYTES}


@pytest.mark.skipif(not (SHM.is_dir() and MAPS.is_file()), reason="no /dev/shm or /proc on this system")
def test_no_shared_memory_pool_without_a_config_file():
    assert send_big_message(free_port(), None) == set()


@pytest.mark.skipif(not (SHM.is_dir() and MAPS.is_file()), reason="no /dev/shm or /proc on this system")
def test_a_config_file_can_turn_shared_memory_on(tmp_path):
    conf = tmp_path / "shm.json5"
    conf.write_text("{ transport: { shared_memory: { enabled: true } } }")
    assert base_config("client", [], str(conf)).get_json("transport/shared_memory/enabled") == "true"
    assert len(send_big_message(free_port(), str(conf))) >= 1
