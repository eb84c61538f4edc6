"""``lrfslam monitor --dashboard`` in a real browser: headless Chromium on the page of a live pipeline.

Router, the six services and the monitor run as processes on loopback Zenoh. The monitor is
started after the sensor has been stopped, so what it shows at once can only come from the
services' ``latest`` queryables and status replies (the late-joiner path); then the sensor starts
again and Chromium (driven over its DevTools protocol) loads the page: its DOM must show the six
services and a non-zero scan count, and the canvas in its screenshot must hold drawn pixels,
landmark red among them. Needs the Debian package ``chromium`` (deploy/setup-podman.sh installs
it); skipped without it, except under CI, where it fails.
"""

from __future__ import annotations

import asyncio
import base64
import io
import json
import os
import shutil
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import websockets
from conftest import free_port

from lrfslam import services
from lrfslam.tools.status import query_latest_states

pytestmark = [pytest.mark.slow, pytest.mark.integration]

STAGES = ("recorder", "mapper", "slam", "features", "denoise")
SENSOR = ("speedup=4", "seed=3", "source=sim")


def cluster_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "lrfslam.cli", *args]


def unavailable(reason: str) -> None:
    """Skip on a developer's machine; under CI (``CI`` set, as .ci/run does) a missing browser fails."""
    if os.environ.get("CI"):
        pytest.fail(f"{reason}; CI must run this test")
    pytest.skip(reason)


def get_json(url: str, timeout_s: float = 20.0):
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with urllib.request.urlopen(url, timeout=5) as r:
                return json.loads(r.read())
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def wait_state(url: str, predicate, timeout_s: float, what: str) -> dict:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        snap = get_json(url)
        if predicate(snap):
            return snap
        time.sleep(0.2)
    pytest.fail(f"timed out waiting for {what}: {snap}")


class DevTools:
    """One page of a running Chromium, over its DevTools protocol."""

    def __init__(self, ws) -> None:
        self.ws, self.next_id = ws, 0

    async def call(self, method: str, **params):
        self.next_id += 1
        await self.ws.send(json.dumps({"id": self.next_id, "method": method, "params": params}))
        while True:
            reply = json.loads(await self.ws.recv())
            if reply.get("id") == self.next_id:
                if "error" in reply:
                    raise RuntimeError(reply["error"])
                return reply["result"]

    async def evaluate(self, expression: str, await_promise: bool = False):
        result = await self.call("Runtime.evaluate", expression=expression, returnByValue=True,
                                 awaitPromise=await_promise)
        if "exceptionDetails" in result:
            raise RuntimeError(f"the page threw: {result['exceptionDetails'].get('exception', {}).get('description')}")
        return result["result"].get("value")


PAGE_FACTS = """JSON.stringify({
  rows: [...document.querySelectorAll('#services tbody tr')].map(r => [...r.cells].map(c => c.textContent)),
  scans: Number(document.getElementById('scans').textContent),
  states: Number(document.getElementById('states').textContent),
  trajectory: window.snapshot ? window.snapshot.trajectory.length : 0,
  landmarks: Number(document.getElementById('landmarks').textContent),
  conn: document.getElementById('conn').textContent,
  grid: gridImage ? [gridImage.naturalWidth, gridImage.naturalHeight] : null,
  canvas: document.getElementById('map').getBoundingClientRect().toJSON()})"""


async def look_at_page(debug_port: int, timeout_s: float) -> tuple[dict, dict, bytes, str]:
    """Wait until the page shows six services and scans, then until the map has grown;
    (first facts, later facts, screenshot PNG, the page's HTML)."""
    targets = get_json(f"http://127.0.0.1:{debug_port}/json/list")
    page = next(tg for tg in targets if tg["type"] == "page")
    async with websockets.connect(page["webSocketDebuggerUrl"], max_size=None) as ws:
        tools = DevTools(ws)
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                facts = json.loads(await tools.evaluate(PAGE_FACTS))
            except RuntimeError:   # the page is still loading
                facts = {"rows": [], "scans": 0, "landmarks": 0}
            if len(facts["rows"]) == len(services.NAMES) and facts["scans"] > 0 and facts["landmarks"] > 0:
                break
            if time.monotonic() > deadline:
                pytest.fail(f"the page never showed six services and scans: {facts}")
            await asyncio.sleep(0.3)
        first = facts
        while facts["states"] < first["states"] + 20 or facts["trajectory"] <= first["trajectory"] \
                or not facts["grid"]:
            if time.monotonic() > deadline:
                pytest.fail(f"the map on the page did not grow: {first} -> {facts}")
            await asyncio.sleep(0.3)
            facts = json.loads(await tools.evaluate(PAGE_FACTS))
        shot = await tools.call("Page.captureScreenshot", format="png")
        html = await tools.evaluate("document.documentElement.outerHTML")
        return first, facts, base64.b64decode(shot["data"]), html


async def ask_page(debug_port: int, expression: str):
    """What ``expression`` (awaited, if a promise) gives in the browser's page."""
    targets = get_json(f"http://127.0.0.1:{debug_port}/json/list")
    page = next(tg for tg in targets if tg["type"] == "page")
    async with websockets.connect(page["webSocketDebuggerUrl"], max_size=None) as ws:
        return json.loads(await DevTools(ws).evaluate(expression, await_promise=True))


def open_chromium(chromium: str, profile: Path, url: str) -> tuple[subprocess.Popen, int]:
    """Headless Chromium on ``url``: the process and its DevTools port."""
    browser = subprocess.Popen(
        [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
         "--remote-debugging-port=0", f"--user-data-dir={profile}", "--window-size=1280,900",
         "--no-first-run", url], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    port_file = profile / "DevToolsActivePort"
    deadline = time.monotonic() + 30
    while not port_file.exists() or not port_file.read_text().strip():
        if browser.poll() is not None or time.monotonic() > deadline:
            browser.kill()
            pytest.fail("chromium did not start")
        time.sleep(0.2)
    return browser, int(port_file.read_text().split()[0])


def find_chromium() -> str:
    """The browser's path; the test stops (fails under CI) where there is none."""
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        unavailable("chromium is not installed (Debian: apt-get install chromium; deploy/setup-podman.sh does)")
    return chromium


def start_stages(cluster):
    """Every stage but the sensor started and alive; returns the open session to the router."""
    for name in STAGES:
        cluster.start(name, *(("name=run",) if name == "recorder" else ()))
    session = cluster.session()
    cluster.wait_for(session, lambda alive, st: {s for _, s in alive} >= set(STAGES), 30, "liveliness")
    return session


def test_a_late_monitor_and_a_browser_see_the_map_and_the_services(cluster, tmp_path):
    chromium = find_chromium()
    from matplotlib import image

    session = start_stages(cluster)
    with session:
        cluster.start("sensor", *SENSOR)
        cluster.wait_for(session, lambda a, st: st.get("slam") and st["slam"].counters.get(
            "out.slam/state", 0) >= 40, 60, "40 SLAM states")
        assert cluster.stop("sensor") == 0

        # Joining late, with no data flowing: the map comes from the latest-state queryables.
        http = free_port()
        cluster.procs["monitor"] = subprocess.Popen(cluster.cmd(
            "monitor", "--connect", cluster.endpoint, "--robot", cluster.robot, "--port", "0", "--dashboard",
            "--http-port", str(http), "--log-level", "WARNING"), cwd=cluster.tmp)
        url = f"http://127.0.0.1:{http}/state.json"
        snap = wait_state(url, lambda s: s["states"] >= 1, 30, "the slam's latest state")
        assert snap["scans"] == 0 and snap["landmarks"] and snap["pose"] and snap["map_trajectory"]
        # The whole map, from the slam's latest/slam/map: every landmark its newest state counts.
        (newest,) = query_latest_states(session, cluster.robot, 5.0).values()
        assert len(snap["landmarks"]) == newest.n_landmarks
        assert {r["service"] for r in snap["services"]} >= set(STAGES)

        cluster.start("sensor", *SENSOR)
        wait_state(url, lambda s: s["scans"] >= 20, 60, "scans")
        browser, debug_port = open_chromium(chromium, tmp_path / "chromium", f"http://127.0.0.1:{http}/")
        try:
            first, facts, png, html = asyncio.run(look_at_page(debug_port, 60))
        finally:
            browser.terminate()
            browser.wait(15)
    for name in ("sensor", *reversed(STAGES), "monitor"):
        assert cluster.stop(name) == 0, f"{name} did not exit cleanly on SIGTERM"

    Path(tmp_path / "dashboard.png").write_bytes(png)
    # The DOM: a row per service, each alive, with its health; the header's scan count.
    assert sorted(row[0] for row in facts["rows"]) == sorted(services.NAMES)
    assert all(row[1] == "yes" and row[2] in ("OK", "WARN") for row in facts["rows"]), facts["rows"]
    assert facts["conn"] == "live" and facts["scans"] > first["scans"] > 0
    # Live data keeps coming and the map grows: more states, a longer trajectory (look_at_page).
    assert facts["states"] >= first["states"] + 20 and facts["trajectory"] > first["trajectory"]
    assert 'id="services"' in html and "<canvas" in html
    # The screenshot: the canvas holds drawn pixels, landmark red among them.
    rgb = image.imread(io.BytesIO(png))[..., :3]
    box = facts["canvas"]
    crop = rgb[int(box["top"]) + 2:int(box["bottom"]) - 2, int(box["left"]) + 2:int(box["right"]) - 2]
    drawn = np.any(crop < 0.95, axis=-1)
    red = (crop[..., 0] > 0.7) & (crop[..., 1] < 0.3) & (crop[..., 2] < 0.3)
    assert drawn.sum() > 500, f"{drawn.sum()} drawn pixels"
    assert red.sum() > 10, f"{red.sum()} landmark-red pixels"
    # The mapper's grid, loaded as a picture and drawn under the rest: its walls grey (black at 60 %).
    assert facts["grid"][0] > 0 and facts["grid"][1] > 0
    grey = (np.ptp(crop, axis=-1) < 0.06) & (crop.max(axis=-1) < 0.5)
    assert grey.sum() > 200, f"{grey.sum()} wall-grey pixels"


TOKEN = "browser-test-token-0123456789"
#: In the page: the address bar without the token, no cookie its scripts can read (HttpOnly), and
#: the snapshot fetched with the cookie the first answer set, and without it.
TOKEN_FACTS = """(async () => JSON.stringify({
  search: location.search,
  cookie: document.cookie,
  with_cookie: (await fetch('/state.json')).status,
  without: (await fetch('/state.json', {credentials: 'omit'})).status}))()"""


def test_beyond_loopback_the_page_opened_with_the_token_shows_the_live_map(cluster, tmp_path):
    """The monitor on every interface with a token: Chromium opens ``/?token=...`` once, and the page
    and its WebSocket then go on with the cookie that answer set; without it the pages answer 401."""
    chromium = find_chromium()
    with start_stages(cluster):
        pass
    cluster.start("sensor", *SENSOR)
    (tmp_path / "token").write_text(TOKEN + "\n")
    http = free_port()
    cluster.procs["monitor"] = subprocess.Popen(cluster.cmd(
        "monitor", "--connect", cluster.endpoint, "--robot", cluster.robot, "--host", "0.0.0.0", "--port", "0",
        "--dashboard", "--http-port", str(http), "--token-file", str(tmp_path / "token"), "--log-level", "WARNING"),
        cwd=cluster.tmp)
    wait_state(f"http://127.0.0.1:{http}/state.json?token={TOKEN}", lambda s: s["scans"] >= 20, 60, "scans")
    browser, debug_port = open_chromium(chromium, tmp_path / "chromium", f"http://127.0.0.1:{http}/?token={TOKEN}")
    try:
        first, facts, _, _ = asyncio.run(look_at_page(debug_port, 60))
        token_facts = asyncio.run(ask_page(debug_port, TOKEN_FACTS))
    finally:
        browser.terminate()
        browser.wait(15)
    for name in ("sensor", *reversed(STAGES), "monitor"):
        assert cluster.stop(name) == 0, f"{name} did not exit cleanly on SIGTERM"
    assert sorted(row[0] for row in facts["rows"]) == sorted(services.NAMES)
    assert facts["conn"] == "live" and facts["scans"] > first["scans"] > 0
    assert facts["states"] >= first["states"] + 20 and facts["trajectory"] > first["trajectory"]
    assert token_facts == {"search": "", "cookie": "", "with_cookie": 200, "without": 401}


def test_up_with_monitor_serves_the_dashboard_and_quiet_prints_no_live_line(tmp_path):
    http, port = free_port(), free_port()
    up = subprocess.Popen(cluster_cmd("up", "--duration", "10", "--speedup", "4", "--port", str(port), "--robot",
                                      "r8", "--monitor", "--monitor-port", "0", "--http-port", str(http), "--quiet"),
                          cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        snap = wait_state(f"http://127.0.0.1:{http}/state.json", lambda s: s["scans"] > 0 and s["landmarks"], 60,
                          "the dashboard of up's pipeline")
        out, err = up.communicate(timeout=120)
    finally:
        if up.poll() is None:
            up.kill()
    assert up.returncode == 0, err[-3000:]
    assert {r["service"] for r in snap["services"]} == set(services.NAMES)
    assert "lrfslam up: ran" in out and " scans " not in out.split("lrfslam up: ran")[0], out
    assert "restarts: monitor" not in out


LOCALIZATION_FACTS = """JSON.stringify({
  shown: !document.getElementById('localization-box').hidden,
  text: document.getElementById('localization').textContent,
  canvas: document.getElementById('map').getBoundingClientRect().toJSON()})"""


def test_on_a_saved_map_the_page_says_not_localized_then_how_sure(tmp_path):
    """The dashboard's header and canvas, in Chromium, as the mapper on a saved map reports the robot
    not localized, then localized (its pose's covariance as a 1-sigma error)."""
    from matplotlib import image

    from lrfslam.msgs import topics
    from lrfslam.msgs import types as t
    from lrfslam.runtime.step import Message
    from lrfslam.tools.dashboard import DashboardServer

    chromium = find_chromium()
    server = DashboardServer("127.0.0.1", 0, "lrfslam r1", period_s=0.05)

    def send(topic, value):
        server.on_message(Message(None, topic.codec.encode(value), 0, topic.schema, topic.name))

    def map_pose(localization, cov=None):
        return t.MapPose(stamp_ns=10**9, seq=1, scan_seq=1, pose=np.array([1.0, 2.0, 0.3]), map_from_slam=np.zeros(3),
                         keyframes=5, local_pose=np.zeros(3), localization=localization, pose_cov=cov)

    async def facts_when(debug_port, predicate):
        targets = get_json(f"http://127.0.0.1:{debug_port}/json/list")
        page = next(tg for tg in targets if tg["type"] == "page")
        async with websockets.connect(page["webSocketDebuggerUrl"], max_size=None) as ws:
            tools = DevTools(ws)
            deadline = time.monotonic() + 30
            while True:
                try:
                    facts = json.loads(await tools.evaluate(LOCALIZATION_FACTS))
                except RuntimeError:   # the page is still loading
                    facts = None
                if facts is not None and predicate(facts):
                    shot = await tools.call("Page.captureScreenshot", format="png")
                    return facts, base64.b64decode(shot["data"])
                if time.monotonic() > deadline:
                    pytest.fail(f"the page never showed it: {facts}")
                await asyncio.sleep(0.2)

    try:
        send(topics.SLAM_STATE, t.SlamState(stamp_ns=10**9, seq=1, scan_seq=1, pose=np.array([1.0, 2.0, 0.3]),
                                            pose_cov=np.eye(3) * 1e-4))
        send(topics.MAP_POSE, map_pose(t.NOT_LOCALIZED))
        browser, debug_port = open_chromium(chromium, tmp_path / "chromium", f"http://127.0.0.1:{server.port}/")
        try:
            lost, png = asyncio.run(facts_when(debug_port, lambda f: f["shown"] and f["text"] != "–"))
            cov = np.diag([0.03 ** 2, 0.04 ** 2, np.radians(0.5) ** 2])
            send(topics.MAP_POSE, map_pose(t.LOCALIZED, cov))
            found, png_found = asyncio.run(facts_when(debug_port, lambda f: f["text"].startswith("localized")))
        finally:
            browser.terminate()
            browser.wait(15)
    finally:
        server.close()
    assert lost["text"] == "NOT LOCALIZED"
    assert found["text"] == "localized (σ 0.050 m, 0.50°)"

    def red_pixels(shot: bytes, box: dict) -> int:
        rgb = image.imread(io.BytesIO(shot))[..., :3]
        crop = rgb[int(box["top"]) + 2:int(box["bottom"]) - 2, int(box["left"]) + 2:int(box["right"]) - 2]
        return int(((crop[..., 0] > 0.6) & (crop[..., 1] < 0.3) & (crop[..., 2] < 0.3)).sum())
    # Not localized: the canvas says so in red (and rings the robot); localized, no red on it.
    assert red_pixels(png, lost["canvas"]) > 100 and red_pixels(png_found, found["canvas"]) == 0
