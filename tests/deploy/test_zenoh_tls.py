"""deploy/zenoh/: mutual TLS for remote monitoring, with real processes on loopback.

The committed JSON5 files and make-certs.sh are used as shipped (only the certificate folder is
moved into a temporary directory): a monitor with the issued certificate sees the services, one
without a certificate or with a certificate from another CA is refused; the same with the router
of ``lrfslam up --zenoh-config router-tls.json5 --listen tls/...``.
"""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from lrfslam.tools.router import main as router_main
from lrfslam.tools.status import main as status

pytestmark = pytest.mark.integration

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def tls(tmp_path, make_certs):
    certs = tmp_path / "tls"
    make_certs(certs)
    router_conf = tmp_path / "router.json5"
    router_conf.write_text((DEPLOY / "zenoh" / "router-tls.json5").read_text()
                           .replace("/etc/lrfslam/tls/", f"{certs}/"))
    monitor_conf = tmp_path / "monitor.json5"
    monitor_conf.write_text((DEPLOY / "zenoh" / "monitor-tls.json5").read_text().replace('"tls/', f'"{certs}/'))
    # Both impostors trust the robot's CA, so only the router's demand for a client
    # certificate can turn them away: one presents none, one presents another CA's.
    no_cert_conf = tmp_path / "no-cert.json5"
    no_cert_conf.write_text(json.dumps({"transport": {"link": {"tls": {"root_ca_certificate": f"{certs}/ca.pem"}}}}))
    rogue = tmp_path / "rogue"
    make_certs(rogue)
    rogue_conf = tmp_path / "rogue.json5"
    rogue_conf.write_text(monitor_conf.read_text().replace(f"{certs}/monitor", f"{rogue}/monitor"))
    return router_conf, monitor_conf, no_cert_conf, rogue_conf


def test_monitor_needs_a_certificate_from_the_robots_ca(tls):
    router_conf, monitor_conf, no_cert_conf, rogue_conf = tls
    tcp, tls_port = free_port(), free_port()
    cli = [sys.executable, "-m", "lrfslam.cli"]
    procs = [subprocess.Popen([*cli, "router", "--zenoh-config", str(router_conf), "--log-level", "WARNING",
                               "--listen", f"tcp/127.0.0.1:{tcp}", "--listen", f"tls/127.0.0.1:{tls_port}"])]
    try:
        procs.append(subprocess.Popen([*cli, "denoise", "--mode", "client", "--connect", f"tcp/127.0.0.1:{tcp}",
                                       "--log-level", "WARNING"]))
        endpoint = f"tls/127.0.0.1:{tls_port}"
        deadline = time.monotonic() + 30
        while status(["--zenoh-config", str(monitor_conf), "-e", endpoint, "--check", "-s", "denoise"]) != 0:
            assert time.monotonic() < deadline, "the monitor never saw denoise over TLS"
            time.sleep(0.5)
        assert status(["--zenoh-config", str(no_cert_conf), "-e", endpoint, "--check"]) == 2
        assert status(["--zenoh-config", str(rogue_conf), "-e", endpoint, "--check"]) == 2
        assert status(["-e", endpoint, "--check"]) == 2  # does not even trust the router
        assert status(["-e", f"tcp/127.0.0.1:{tls_port}", "--check"]) == 2             # plain TCP
    finally:
        for proc in procs:
            proc.terminate()
        for proc in procs:
            proc.wait(10)


def test_up_listens_for_other_hosts_over_tls_and_plain_only_when_insecure(tls, tmp_path):
    """up's router takes the TLS config; a plain endpoint on every interface runs with --insecure,
    and up says so in one warning line."""
    router_conf, monitor_conf, no_cert_conf, _ = tls
    port, tls_port, plain = free_port(), free_port(), free_port()
    up = subprocess.Popen([sys.executable, "-m", "lrfslam.cli", "up", "--port", str(port), "--robot", "r9",
                           "--zenoh-config", str(router_conf), "--listen", f"tls/0.0.0.0:{tls_port}",
                           "--listen", f"tcp/0.0.0.0:{plain}", "--insecure", "--skip", "sensor", "--skip", "mapper",
                           "--duration", "120", "--quiet"],
                          cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        endpoint = f"tls/127.0.0.1:{tls_port}"
        deadline = time.monotonic() + 60
        while status(["--zenoh-config", str(monitor_conf), "-e", endpoint, "--robot", "r9", "--check",
                      "-s", "slam"]) != 0:
            assert up.poll() is None and time.monotonic() < deadline, "up's slam never answered over TLS"
            time.sleep(0.5)
        assert status(["-e", f"tcp/127.0.0.1:{plain}", "--robot", "r9", "--check", "-s", "slam"]) == 0
        assert status(["--zenoh-config", str(no_cert_conf), "-e", endpoint, "--check"]) == 2
    finally:
        up.terminate()
        _, err = up.communicate(timeout=60)
    assert up.returncode == 0, err[-3000:]
    warnings = [line for line in err.splitlines() if "--insecure" in line]
    assert len(warnings) == 1 and f"--listen tcp/0.0.0.0:{plain}: plain, beyond loopback" in warnings[0], err


def test_the_router_refuses_a_plain_endpoint_beyond_loopback_unless_insecure(caplog):
    port = free_port()
    assert router_main(["--listen", f"tcp/0.0.0.0:{port}"]) == 2
    (line,) = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert line.startswith(f"--listen tcp/0.0.0.0:{port} is plain (no TLS) beyond loopback") and "--insecure" in line
    with socket.socket() as s:   # nothing was bound
        s.bind(("0.0.0.0", port))
