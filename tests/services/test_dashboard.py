"""The web dashboard's model and server: a simulated run in, the snapshot the page draws out.

The model is fed a simulated run through every stage as the monitor receives it (encoded on
the wire); its snapshot is checked against the messages themselves (scan points moved by the
state's pose, the 95 % ellipses, counts). The server is started for real on a free port and
read with urllib and a ``websockets`` client.
"""

from __future__ import annotations

import asyncio
import io
import json
import logging
import math
import socket
import urllib.request

import numpy as np
import pytest
import websockets
from lrfslam.services import stage
from PIL import Image
from test_steps import sim_outputs
from websockets.sync.client import connect

from lrfslam.errors import StartupError
from lrfslam.msgs import topics
from lrfslam.msgs import types as t
from lrfslam.msgs.grid_replica import GridReplica
from lrfslam.msgs.landmark_map import LandmarkMapReplica
from lrfslam.runtime.chain import Chain
from lrfslam.runtime.step import Message
from lrfslam.tools.dashboard import DashboardServer
from lrfslam.viz import dashboard as dash

CHI2_2D_95 = 5.991464547107979


@pytest.fixture(scope="module")
def wire():
    """(name, schema, payload, decoded) of a simulated run through every stage, health included."""
    stream = []
    with Chain([stage(n) for n in ("denoise", "features", "slam", "mapper")], robot="r1") as ch:
        for out in sim_outputs(80):
            m = Message.of(out)
            stream += [m, *ch.push(m)]
    out = []
    for m in stream:
        tp = topics.by_name(m.name)
        data = tp.codec.encode(m.value)
        out.append((m.name, tp.schema, data, tp.codec.decode(data)))
    return out


def feed(model, wire):
    for name, schema, data, _ in wire:
        model.from_payload(name, schema, data)


def status(service, wall_s, pid=7, **counters):
    return t.ServiceStatus(service=service, robot="r1", level=t.HEALTH_OK, message="ok",
                           wall_stamp_ns=int(wall_s * 1e9), uptime_s=wall_s, counters=counters, pid=pid, host="h")


def test_the_snapshot_draws_the_newest_state_at_its_pose(wire):
    model = dash.DashboardModel()
    feed(model, wire)
    snap = json.loads(json.dumps(model.snapshot()))
    scans = [v for n, _, _, v in wire if n == "scan"]
    states = [v for n, _, _, v in wire if n == "slam/state"]
    assert snap["scans"] == len(scans) == 80 and snap["states"] == len(states) > 0
    last = states[-1]
    np.testing.assert_allclose(snap["pose"], last.pose, atol=1e-4)
    # The scan of the newest state, moved from the laser frame by its pose (oracle: plain trigonometry).
    scan = next(s for s in scans if s.stamp_ns == last.stamp_ns)
    ok = np.isfinite(scan.ranges_m)
    a = scan.angles_rad[ok] + last.pose[2]
    expected = np.column_stack([last.pose[0] + scan.ranges_m[ok] * np.cos(a), last.pose[1] + scan.ranges_m[ok] * np.sin(a)])
    np.testing.assert_allclose(snap["scan"], expected, atol=1e-3)
    kept = next(v for n, _, _, v in wire if n == "scan/filtered" and v.stamp_ns == last.stamp_ns)
    assert len(snap["kept"]) == kept.kept_beams.size > 0
    # Landmarks: ids, and the 95 % ellipse's axes square to chi2 × the covariance's eigenvalues.
    replica = LandmarkMapReplica()
    for n, _, _, v in wire:
        if n in ("slam/state", "slam/map"):
            replica.apply_message(v)
    lms = replica.landmarks
    assert [lm[5] for lm in snap["landmarks"]] == lms.ids.tolist() and snap["landmarks"]
    for lm, cov in zip(snap["landmarks"], lms.cov_m2):
        np.testing.assert_allclose(sorted([lm[2] ** 2, lm[3] ** 2]),
                                   CHI2_2D_95 * np.linalg.eigvalsh(cov), rtol=1e-2, atol=1e-7)
    # The trajectory ends within a thinning step of the pose; the truth is tied to the estimate
    # at the first state, so both start together.
    assert math.dist(snap["trajectory"][-1], last.pose[:2]) <= dash.DashboardConfig().path_step_m
    assert snap["truth"] and math.dist(snap["truth"][0], snap["trajectory"][0]) < 0.05
    assert snap["map_trajectory"]


def test_a_late_joiner_draws_the_state_and_map_it_is_given(wire):
    model = dash.DashboardModel()
    last_state = [(n, s, d) for n, s, d, _ in wire if n == "slam/state"][-1]
    keyframes = [(n, s, d) for n, s, d, _ in wire if n == "map/keyframes"]
    for n, s, d in keyframes[-1:] + [last_state]:
        model.from_payload(n, s, d)
    snap = model.snapshot()
    assert snap["landmarks"] and snap["pose"] and snap["scans"] == 0
    if keyframes:
        assert len(snap["map_trajectory"]) > 1


def test_rates_come_from_the_services_own_stamps():
    a = status("denoise", 10.0, **{"in.scan": 100, "out.scan/filtered": 100, "out.health": 9})
    b = status("denoise", 12.0, **{"in.scan": 180, "out.scan/filtered": 170, "out.health": 11, "drop.queue": 3})
    assert dash.rates(a, b) == (40.0, 35.0)
    assert dash.rates(None, b) is None
    assert dash.rates(status("denoise", 11.0, pid=8), b) is None     # a restarted process counts from zero
    assert dash.counter_figures(b.counters) == {"in": 180, "out": 170, "dropped": 3, "gaps": 0, "skipped": 0,
                                                 "errors": 0}
    model = dash.DashboardModel()
    model.add("health/denoise", a)
    model.add("health/denoise", b)
    model.set_alive("denoise", True)
    model.set_alive("slam", True)
    rows = {r["service"]: r for r in model.services()}
    assert rows["denoise"]["in_hz"] == 40.0 and rows["denoise"]["alive"] and rows["denoise"]["dropped"] == 3
    assert rows["slam"] == {"service": "slam", "alive": True}


def test_a_long_trajectory_stays_bounded_and_keeps_its_ends():
    path = dash.Path(dash.DashboardConfig(path_step_m=0.0, max_path_poses=100))
    for i in range(10_001):
        path.add(float(i), 0.0)
    assert len(path.xy) <= 100 and path.xy[0] == (0.0, 0.0) and path.xy[-1] == (10_000.0, 0.0)


def test_the_server_serves_the_page_the_snapshot_and_a_websocket(wire):
    server = DashboardServer("127.0.0.1", 0, "lrfslam r1", period_s=0.05)
    try:
        for name, schema, data, _ in wire:
            server.on_message(Message(None, data, 0, schema, name))
        server.on_alive("slam", True)
        base = f"http://127.0.0.1:{server.port}"
        with urllib.request.urlopen(base + "/") as r:
            assert r.headers["Content-Type"].startswith("text/html") and b"<canvas" in r.read()
        with urllib.request.urlopen(base + "/state.json") as r:
            snap = json.loads(r.read())
        assert snap["scans"] == 80 and snap["title"] == "lrfslam r1"
        # The mapper's grid as a picture: walls black, free space white, unknown transparent, top row the highest y.
        replica = GridReplica()
        for name, _, _, value in wire:
            if name == topics.MAP_GRID.name:
                replica.apply(value)
        cells = replica.image().cells
        grid = snap["grid"]
        assert (grid["height"], grid["width"]) == cells.shape and grid["resolution"] == replica.resolution_m
        with urllib.request.urlopen(base + "/map.png") as r:
            assert r.headers["Content-Type"] == "image/png"
            picture = np.asarray(Image.open(io.BytesIO(r.read())).convert("LA"))
        want = np.flipud(cells)
        np.testing.assert_array_equal(picture[..., 1], np.where(want == -1, 0, 255))
        known = want != -1
        np.testing.assert_array_equal(picture[..., 0][known], np.where(want[known] == 100, 0, 255))
        assert {0, 100, -1} <= set(np.unique(cells).tolist())

        async def first_frame():
            async with websockets.connect(f"ws://127.0.0.1:{server.port}/ws") as ws:
                return json.loads(await asyncio.wait_for(ws.recv(), 10))
        assert asyncio.run(first_frame()) == snap
        with pytest.raises(urllib.error.HTTPError):
            urllib.request.urlopen(base + "/nothing")
        # The port is taken: one line, with what to do.
        with pytest.raises(StartupError, match=r"cannot serve the dashboard on 127\.0\.0\.1:\d+: .*--http-port"):
            DashboardServer("127.0.0.1", server.port, "x")
    finally:
        server.close()
    with socket.socket() as s:     # closed: the port is free again (as a server takes it, past TIME_WAIT)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind(("127.0.0.1", server.port))


def test_the_server_closes_at_once_while_a_page_is_open_and_idle(caplog):
    # A browser left open on an unchanging dashboard: its handler waits for news, and must
    # still notice the close (a server that waits for it stops seconds late, or never).
    server = DashboardServer("127.0.0.1", 0, "lrfslam r1", period_s=0.05)
    with connect(f"ws://127.0.0.1:{server.port}/ws") as ws:
        assert json.loads(ws.recv(timeout=10))["title"] == "lrfslam r1"
        with caplog.at_level(logging.WARNING, logger="lrfslam.tools.webserver"):
            server.close()
        assert not caplog.records


def map_pose(stamp_s: float, x_m: float, localization: int, cov=None) -> t.MapPose:
    return t.MapPose(stamp_ns=int(stamp_s * 1e9), seq=int(stamp_s * 10), scan_seq=int(stamp_s * 10),
                     pose=np.array([x_m, 0.0, 0.0]), map_from_slam=np.zeros(3), keyframes=5, local_pose=np.zeros(3),
                     localization=localization, pose_cov=cov)


def test_on_a_saved_map_the_snapshot_says_whether_and_how_surely_the_robot_is_localized():
    model = dash.DashboardModel(dash.DashboardConfig(path_step_m=0.0))
    model.add("map/pose", map_pose(1.0, 0.0, t.MAPPING))
    assert model.snapshot()["localization"] is None          # mapping: nothing to say
    model.add("map/pose", map_pose(1.1, 1.0, t.NOT_LOCALIZED))
    snap = json.loads(json.dumps(model.snapshot()))
    assert snap["localization"] == {"localized": False, "sigma_m": None, "sigma_deg": None}
    assert len(snap["map_trajectory"]) == 1                  # a pose not placed on the map is not drawn on it
    cov = np.diag([0.03 ** 2, 0.04 ** 2, math.radians(0.5) ** 2])
    model.add("map/pose", map_pose(1.2, 2.0, t.LOCALIZED, cov))
    snap = json.loads(json.dumps(model.snapshot()))
    assert snap["localization"]["localized"] and snap["localization"]["sigma_m"] == pytest.approx(0.05, abs=1e-4)
    assert snap["localization"]["sigma_deg"] == pytest.approx(0.5, abs=1e-3)
    assert [p[0] for p in snap["map_trajectory"]] == [0.0, 2.0]
