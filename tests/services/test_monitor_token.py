"""The monitor's token beyond loopback: real servers on free ports, read with urllib and ``websockets``.

The dashboard (pages and WebSocket) and the Foxglove WebSocket (foxglove-sdk's server behind the
token relay) answer 401 without the token and 403 with a wrong one; with it they serve as without
a token. ``lrfslam monitor`` itself, as a process: beyond loopback it refuses to start without a
token or ``--insecure``, and with one it listens on every interface and asks for it.
"""

from __future__ import annotations

import asyncio
import json
import socket
import struct
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import websockets
from websockets.exceptions import InvalidStatus

from lrfslam.msgs import codec, topics
from lrfslam.msgs import types as t
from lrfslam.runtime.step import Message
from lrfslam.tools.dashboard import DashboardServer
from lrfslam.tools.monitor import FoxgloveServer
from lrfslam.tools.webserver import TokenGate
from lrfslam.viz import foxglove as fx

TOKEN = "s3cret-token_of.enough~length"
SUBPROTOCOLS = ["foxglove.websocket.v1", "foxglove.sdk.v1"]


def http_status(url: str, headers: dict[str, str] | None = None) -> tuple[int, dict, bytes]:
    try:
        with urllib.request.urlopen(urllib.request.Request(url, headers=headers or {}), timeout=10) as r:
            return r.status, dict(r.headers), r.read()
    except urllib.error.HTTPError as exc:
        return exc.code, dict(exc.headers), exc.read()


def ws_status(url: str, **kwargs) -> int | str:
    """The handshake's refusal status, or the first text frame when it is let in."""
    async def go():
        try:
            async with websockets.connect(url, open_timeout=10, **kwargs) as ws:
                return await asyncio.wait_for(ws.recv(), 10)
        except InvalidStatus as exc:
            return exc.response.status_code
    return asyncio.run(go())


def scan_message(seq: int) -> Message:
    n = 181
    scan = t.LaserScan(stamp_ns=seq * 100_000_000, seq=seq, ranges_m=np.full(n, 2.0), status=np.zeros(n, np.uint8),
                       angle_min_rad=-np.pi / 2, angle_increment_rad=np.pi / (n - 1))
    return Message(None, codec.LASER_SCAN.encode(scan), scan.stamp_ns, topics.SCAN.schema, topics.SCAN.name, seq)


@pytest.fixture
def dashboard():
    server = DashboardServer("127.0.0.1", 0, "lrfslam r1", period_s=0.05, gate=TokenGate(TOKEN))
    server.on_alive("slam", True)
    yield server
    server.close()


def test_the_dashboard_pages_need_the_token(dashboard):
    base = f"http://127.0.0.1:{dashboard.port}"
    for path in ("/", "/state.json", "/nothing"):
        status, headers, _ = http_status(base + path)
        assert status == 401 and headers["WWW-Authenticate"].startswith("Bearer"), path
        assert http_status(f"{base}{path}?token=wrong-token-of-enough-length")[0] == 403, path
    status, headers, page = http_status(f"{base}/?token={TOKEN}")
    assert status == 200 and b"<canvas" in page
    cookie = headers["Set-Cookie"]
    assert cookie == f"lrfslam_token_{dashboard.port}={TOKEN}; Path=/; HttpOnly; SameSite=Strict"
    # The cookie, as the browser sends it back, opens the rest; so does the header a script sends.
    sent = cookie.split(";")[0]
    status, headers, body = http_status(f"{base}/state.json", {"Cookie": f"other=1; {sent}"})
    assert status == 200 and json.loads(body)["title"] == "lrfslam r1" and "Set-Cookie" not in headers
    assert http_status(f"{base}/state.json", {"Authorization": f"Bearer {TOKEN}"})[0] == 200
    # Another monitor's cookie (another port) is not this one's.
    assert http_status(f"{base}/state.json", {"Cookie": f"lrfslam_token_1={TOKEN}"})[0] == 401


def test_the_dashboard_websocket_needs_the_token(dashboard):
    url = f"ws://127.0.0.1:{dashboard.port}/ws"
    assert ws_status(url) == 401
    assert ws_status(url + "?token=wrong-token-of-enough-length") == 403
    assert ws_status(url, additional_headers={"Cookie": f"lrfslam_token_{dashboard.port}=nope"}) == 403
    for frame in (ws_status(url + f"?token={TOKEN}"),
                  ws_status(url, additional_headers={"Cookie": f"lrfslam_token_{dashboard.port}={TOKEN}"})):
        assert json.loads(frame)["title"] == "lrfslam r1"


async def foxglove_scan(port: int, query: str, server: FoxgloveServer) -> tuple[str, set[str], int]:
    """As Foxglove connects through the relay: (subprotocol, the advertised topics, the stamp in
    0.1 s of the first scan view received after subscribing to it: it crossed the relay both ways)."""
    async with asyncio.timeout(20):
        async with websockets.connect(f"ws://127.0.0.1:{port}/{query}", subprotocols=SUBPROTOCOLS) as ws:
            channels, subscribed = {}, False
            while True:
                try:
                    frame = await asyncio.wait_for(ws.recv(), 0.2)
                except TimeoutError:   # until the subscription has reached the server, a scan finds none
                    if subscribed:
                        server.on_message(scan_message(7))
                    continue
                if isinstance(frame, str):
                    op = json.loads(frame)
                    if op["op"] == "advertise":
                        channels.update({c["id"]: c["topic"] for c in op["channels"]})
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                            {"id": cid, "channelId": cid} for cid, topic in channels.items() if topic == fx.SCAN]}))
                        subscribed = True
                elif frame[0] == 0x01:   # message data: subscription id (= channel id here), log time, payload
                    sub, log_time = struct.unpack_from("<IQ", frame, 1)
                    if channels[sub] == fx.SCAN:
                        return ws.subprotocol, set(channels.values()), log_time // 100_000_000


def test_the_foxglove_websocket_needs_the_token():
    server = FoxgloveServer("127.0.0.1", 0, "lrfslam r1", gate=TokenGate(TOKEN))
    try:
        # foxglove-sdk's own server is on another (loopback) port; the relay has the monitor's.
        assert server.server.port != server.port
        url = f"ws://127.0.0.1:{server.port}/"
        assert ws_status(url, subprotocols=SUBPROTOCOLS) == 401
        assert ws_status(url + "?token=wrong-token-of-enough-length", subprotocols=SUBPROTOCOLS) == 403
        subprotocol, advertised, seq = asyncio.run(foxglove_scan(server.port, f"?token={TOKEN}", server))
    finally:
        server.close()
    assert subprotocol == "foxglove.sdk.v1"
    assert advertised == set(fx.CHANNELS)
    assert seq == 7


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def monitor(*args: str, cwd: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "lrfslam.cli", "monitor", "--connect", "tcp/127.0.0.1:1",
                             "--log-level", "INFO", *args], cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)


def errors(err: str) -> list[str]:
    """The monitor's own error and warning lines (not the bus's, which retries the router)."""
    return [line for line in err.splitlines() if (" ERROR " in line or " WARNING " in line)
            and "lrfslam.monitor:" in line]


def test_beyond_loopback_the_monitor_refuses_to_start_without_a_token(tmp_path):
    proc = monitor("--host", "0.0.0.0", "--port", "0", "--dashboard", "--http-port", "0", cwd=tmp_path)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 2
    (line,) = errors(err)
    assert line.endswith("--host 0.0.0.0 is beyond loopback: whoever reaches it would see every stream; give a "
                         "token (--token-file FILE or LRFSLAM_MONITOR_TOKEN), or pass --insecure on a network "
                         "where everyone may see everything"), err
    assert "serving" not in err
    (tmp_path / "short").write_text("abc\n")
    proc = monitor("--host", "0.0.0.0", "--port", "0", "--token-file", "short", cwd=tmp_path)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 2
    (line,) = errors(err)
    assert "the token in --token-file short must be at least 16 characters" in line, err


def listening_addresses(port: int) -> set[str]:
    """The local addresses (hex, as /proc/net/tcp writes them) of the sockets listening on ``port``."""
    found = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for row in Path(table).read_text().splitlines()[1:]:
            local, state = row.split()[1], row.split()[3]
            address, hex_port = local.rsplit(":", 1)
            if state == "0A" and int(hex_port, 16) == port:
                found.add(address)
    return found


def wait_listening(port: int, proc: subprocess.Popen) -> None:
    deadline = time.monotonic() + 30
    while not listening_addresses(port):
        assert proc.poll() is None and time.monotonic() < deadline, "the monitor never listened"
        time.sleep(0.1)


LINUX = pytest.mark.skipif(not Path("/proc/net/tcp").exists(), reason="reads Linux's /proc/net/tcp")


@LINUX
def test_the_monitor_with_a_token_serves_every_interface_and_asks_for_it(tmp_path):
    (tmp_path / "token").write_text(TOKEN + "\n")
    port, http = free_port(), free_port()
    proc = monitor("--host", "0.0.0.0", "--port", str(port), "--dashboard", "--http-port", str(http),
                   "--token-file", "token", cwd=tmp_path)
    try:
        for p in (port, http):
            wait_listening(p, proc)
            assert listening_addresses(p) == {"00000000"}, "not on every interface (and only there)"
        assert http_status(f"http://127.0.0.1:{http}/state.json")[0] == 401
        assert http_status(f"http://127.0.0.1:{http}/state.json?token={TOKEN}")[0] == 200
        assert ws_status(f"ws://127.0.0.1:{port}/", subprotocols=SUBPROTOCOLS) == 401
        assert json.loads(ws_status(f"ws://127.0.0.1:{port}/?token={TOKEN}", subprotocols=SUBPROTOCOLS))["op"] \
            == "serverInfo"
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    assert not errors(err), err
    assert f"serving Foxglove on ws://0.0.0.0:{port}/?token=TOKEN" in err
    assert TOKEN not in err


@LINUX
def test_insecure_serves_every_interface_without_a_token_and_says_so(tmp_path):
    http = free_port()
    proc = monitor("--host", "0.0.0.0", "--port", "0", "--dashboard", "--http-port", str(http), "--insecure",
                   cwd=tmp_path)
    try:
        wait_listening(http, proc)
        assert http_status(f"http://127.0.0.1:{http}/state.json")[0] == 200
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=30)
    assert proc.returncode == 0, err
    (line,) = errors(err)
    assert "--host 0.0.0.0: beyond loopback without a token (--insecure)" in line
