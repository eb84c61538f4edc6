"""deploy/compose.lms200.yaml's sensor against the project's LMS200 emulator on a pseudo-terminal.

The sensor's command line and device mapping are read from the compose files (the override's
``command`` replaces the base file's, its ``devices`` maps the host's serial port to the
container path that ``--device`` names). The emulator (``lrfslam emulate-lms200``) plays the
LMS200 on a pty; the router (with compose's mutual TLS and access-control list, certificates by
``lrfslam certs``) and a recorder run in a network namespace of their own, so the command's
``tls/zenohd:7447`` is theirs and no port of this host is taken. Two ways:

``podman``
    the image (deploy/podman-build.sh) with the pty at the container path (bind-mounted: a pty
    passed as ``--device`` answers EIO in the container, a real serial port does not), the
    compose file's config, Zenoh config and certificate mounts, ``zenohd`` resolving to the
    router: the argv unchanged.
``host``
    the same argv as a host process in the namespace, the container paths (device, config,
    Zenoh config) replaced by the host's.

Every recorded scan must be one the emulator sent (its ``--dump-ranges`` log). Needs root for
the namespace; skips without it or without podman, and fails instead under CI.
"""

from __future__ import annotations

import json
import os
import select
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from lrfslam.msgs import codec, topics
from lrfslam.runtime.recording import read_recording
from lrfslam.tools.certs import main as certs_main

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy"
IMAGE = "lrfslam:test"
SCANS = 20               # the emulator's scans to wait for before stopping
HANG_GUARD_S = 120.0
CONTAINER_ZENOH, CONTAINER_TLS = "/etc/lrfslam/zenoh", "/etc/lrfslam/tls"   # compose.yaml's mounts


def unavailable(reason: str) -> None:
    """Skip on a developer's machine; under CI (``CI`` set, as .ci/run does) it fails."""
    if os.environ.get("CI"):
        pytest.fail(f"{reason}; CI must run this test")
    pytest.skip(reason)


def sensor_service() -> dict:
    """compose.yaml's sensor with compose.lms200.yaml applied (command replaced, devices added)."""
    base = yaml.safe_load((DEPLOY / "compose.yaml").read_text())["services"]["sensor"]
    override = yaml.safe_load((DEPLOY / "compose.lms200.yaml").read_text())["services"]["sensor"]
    merged = dict(base)
    merged["command"] = override["command"]
    merged["devices"] = [*base.get("devices", []), *override["devices"]]
    return merged


def config_mount(svc: dict) -> tuple[Path, str]:
    """(host file, container path) of the config.toml bind mount (compose.yaml's anchor)."""
    base = yaml.safe_load((DEPLOY / "compose.yaml").read_text())
    for volume in svc.get("volumes") or base["x-lrfslam"]["volumes"]:
        host, container, *_ = volume.split(":")
        if container.endswith("config.toml"):
            return (DEPLOY / host).resolve(), container
    raise AssertionError("no config.toml mount")


def tls_configs(tmp: Path) -> tuple[Path, dict[str, Path]]:
    """Certificates (as compose's certs service makes them) in ``tmp``/tls, and the router's and a
    service's Zenoh configs of deploy/zenoh with their certificate paths moved there."""
    tls = tmp / "tls"
    assert certs_main([str(tls), "--if-absent"]) == 0
    confs = {}
    for name in ("router-tls-acl", "service-tls"):
        confs[name] = tmp / f"{name}.json5"
        confs[name].write_text((DEPLOY / "zenoh" / f"{name}.json5").read_text().replace(f"{CONTAINER_TLS}/", f"{tls}/"))
    return tls, confs


def read_dump(path: Path) -> dict[bytes, str]:
    """Ranges (rounded to mm, as bytes) -> fault of every scan the emulator sent."""
    sent = {}
    for line in path.read_text().splitlines():
        _, fault, *values = line.split()
        sent[np.round(np.array([float(v) for v in values]), 3).tobytes()] = fault
    return sent


@pytest.fixture
def netns():
    if shutil.which("ip") is None or os.geteuid() != 0:
        unavailable("needs root and the ip command (Debian package iproute2) for a network namespace")
    name = f"lrf{os.getpid() % 100000}lms"
    made = subprocess.run(["ip", "netns", "add", name], capture_output=True, text=True, check=False)
    if made.returncode != 0:
        unavailable(f"ip netns add failed: {made.stderr.strip()}")
    try:
        subprocess.run(["ip", "-n", name, "link", "set", "lo", "up"], check=True)
        yield name
    finally:
        subprocess.run(["ip", "netns", "del", name], capture_output=True, check=False)


@pytest.mark.parametrize("where", ["host", "podman"])
def test_compose_lms200_sensor_publishes_the_emulators_scans(where, netns, tmp_path):
    svc = sensor_service()
    argv = list(svc["command"])
    device = argv[argv.index("--device") + 1]
    # "${LRFSLAM_LMS200_DEVICE:-/dev/ttyUSB0}:/dev/lms200": the container path is the last part.
    (mapping,) = [d for d in svc["devices"] if d.rsplit(":", 1)[1] == device]
    host_config, container_config = config_mount(svc)
    endpoint = argv[argv.index("--connect") + 1]
    port = endpoint.rsplit(":", 1)[1]
    if where == "podman":
        if shutil.which("podman") is None:
            unavailable("podman is not installed (Debian: sudo deploy/setup-podman.sh)")
        build = subprocess.run([str(DEPLOY / "podman-build.sh"), "-q"], capture_output=True, text=True,
                               timeout=1200, env=dict(os.environ, LRFSLAM_IMAGE=IMAGE), check=False)
        assert build.returncode == 0, build.stdout[-2000:] + build.stderr[-2000:]

    procs: list[subprocess.Popen] = []
    container = f"lrfslam-lms200-test-{os.getpid()}"
    dump = tmp_path / "sent.txt"
    try:
        emu = subprocess.Popen([sys.executable, "-m", "lrfslam.cli", "emulate-lms200", "--seed", "4",
                                "--dump-ranges", str(dump)], stdout=subprocess.PIPE, text=True)
        procs.append(emu)
        ready, _, _ = select.select([emu.stdout], [], [], HANG_GUARD_S)
        assert ready, "the emulator did not print its pty"
        pty = emu.stdout.readline().strip()
        assert pty.startswith("/dev/")

        def in_ns(*args: str) -> subprocess.Popen:
            proc = subprocess.Popen(["ip", "netns", "exec", netns, *args], cwd=tmp_path)
            procs.append(proc)
            return proc

        lrfslam = [sys.executable, "-m", "lrfslam.cli"]
        tls, confs = tls_configs(tmp_path)
        in_ns(*lrfslam, "router", "--zenoh-config", str(confs["router-tls-acl"]), "--listen", f"tls/127.0.0.1:{port}",
              "--log-level", "WARNING")
        recorder = in_ns(*lrfslam, "recorder", "--mode", "client", "--connect", f"tls/127.0.0.1:{port}",
                         "--zenoh-config", str(confs["service-tls"]),
                         "--config", str(host_config), "--set", f"directory={tmp_path / 'recordings'}")
        if where == "podman":
            # podman itself runs outside (under `ip netns exec` it fails); its container joins the namespace.
            # A pty cannot go in as `--device` (the container's copy of the node answers EIO: a pty
            # opens only through its own devpts mount), so it is bind-mounted where the device would be.
            sensor = subprocess.Popen(["podman", "run", "--rm", "--init", "--name", container, "--network", f"ns:/run/netns/{netns}",
                           "--add-host", f"{endpoint.split('/')[1].split(':')[0]}:127.0.0.1",
                           "-v", f"{pty}:{device}", "-v", f"{host_config}:{container_config}:ro",
                           "-v", f"{DEPLOY / 'zenoh'}:{CONTAINER_ZENOH}:ro", "-v", f"{tls}:{CONTAINER_TLS}:ro",
                           IMAGE, *argv])
            procs.append(sensor)
        else:
            host_argv = [{device: pty, container_config: str(host_config)}.get(a, a) for a in argv]
            host_argv[host_argv.index("--connect") + 1] = f"tls/127.0.0.1:{port}"
            zenoh_config = host_argv.index("--zenoh-config") + 1
            assert host_argv[zenoh_config] == f"{CONTAINER_ZENOH}/service-tls.json5"
            host_argv[zenoh_config] = str(confs["service-tls"])
            host_argv[host_argv.index("--health-file") + 1] = str(tmp_path / "health.json")
            sensor = in_ns(*lrfslam, *host_argv)

        deadline = time.monotonic() + HANG_GUARD_S
        while not (dump.exists() and len(dump.read_text().splitlines()) >= SCANS):
            assert time.monotonic() < deadline and sensor.poll() is None, "the sensor never read the emulator"
            time.sleep(0.5)
        time.sleep(2)    # the last scans on their way to the recorder
        if where == "podman":
            subprocess.run(["podman", "stop", "-t", "15", container], capture_output=True, check=False)
        else:
            sensor.terminate()
        assert sensor.wait(30) == 0
        recorder.terminate()
        assert recorder.wait(30) == 0
    finally:
        if where == "podman":
            subprocess.run(["podman", "rm", "-f", container], capture_output=True, check=False)
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
            proc.wait()

    (recording,) = (tmp_path / "recordings").iterdir()
    sent = read_dump(dump)
    scans = [codec.LASER_SCAN.decode(m.data) for m in read_recording(recording, [topics.SCAN.name])]
    assert len(scans) >= SCANS // 2, len(scans)
    for scan in scans:
        assert scan.source == "lms200" and scan.ranges_m.size == 181
        assert np.round(scan.ranges_m, 3).tobytes() in sent, "a recorded scan the emulator never sent"
    health = [codec.SERVICE_STATUS.decode(m.data) for m in read_recording(recording, ["health/sensor"])]
    config = json.loads(health[-1].config_json)
    assert (config["source"], config["device"]) == ("lms200", device if where == "podman" else pty)
    print(f"\n{where}: {len(scans)} scans recorded, all the emulator's; host device {pty} mapped as {mapping}")
