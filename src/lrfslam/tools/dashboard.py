"""``lrfslam monitor --dashboard``: a web page of the robot's map and services, served by the monitor.

One sink of the monitor (src/lrfslam/tools/monitor.py): every message updates a
:class:`~lrfslam.viz.dashboard.DashboardModel`, and an HTTP + WebSocket server (the ``websockets``
package's, on its own thread: src/lrfslam/tools/webserver.py) serves

* ``/``: the page (src/lrfslam/tools/dashboard.html), a canvas and a table of the services;
* ``/ws``: a WebSocket on which the page gets the model's snapshot as JSON, at most every
  ``period_s`` and only when it changed;
* ``/state.json``: the same snapshot once (for scripts and ``curl``);
* ``/map.png``: the mapper's live grid as a picture (404 before the first ``map/grid``), which the
  page loads again when the snapshot's ``grid.version`` changes.

With a token (the monitor requires one beyond loopback) every one of them answers only a request
that presents it: ``http://HOST:PORT/?token=TOKEN`` opens the page, whose answer sets a cookie
that its WebSocket and a reload present in its place.
"""

from __future__ import annotations

import asyncio
import json
import logging
import threading
from http import HTTPStatus
from importlib import resources

from websockets.asyncio.server import ServerConnection
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response

from lrfslam.errors import DecodeError
from lrfslam.runtime.decoding import LogOnce
from lrfslam.runtime.step import Message
from lrfslam.tools.webserver import ServerThread, TokenGate, response
from lrfslam.viz.dashboard import DashboardModel

log = logging.getLogger("lrfslam.monitor.dashboard")

DEFAULT_HTTP_PORT = 8080
#: The page redraws at most this often, s.
PUSH_PERIOD_S = 0.2
PAGE = resources.files("lrfslam.tools").joinpath("dashboard.html")


class DashboardServer:
    """Sink: the dashboard's model, served over HTTP and WebSocket on ``host``:``port`` (0: any free port).

    Raises
    ------
    StartupError
        The server cannot listen there.
    """

    def __init__(self, host: str, port: int, title: str, period_s: float = PUSH_PERIOD_S,
                 gate: TokenGate | None = None) -> None:
        self.model = DashboardModel()
        self.title = title
        self.period_s = period_s
        self.counts = {"undecodable": 0}
        self._lock = threading.Lock()
        self._once = LogOnce(log)
        self._page = PAGE.read_bytes()
        self._gate = gate
        self.server = ServerThread("the dashboard", host, port, self._client, self._http, "(pass another --http-port)")
        self.port = self.server.port

    # -- the sink, on the monitor's thread

    def on_message(self, msg: Message) -> None:
        try:
            with self._lock:
                self.model.from_payload(msg.name, msg.schema, msg.value)
        except DecodeError as exc:
            self.counts["undecodable"] += 1
            self._once.warning("undecodable", f"{msg.name}:{msg.schema}", "dashboard: cannot decode %s: %s",
                               msg.name, exc)

    def on_alive(self, service: str, alive: bool) -> None:
        with self._lock:
            self.model.set_alive(service, alive)

    def snapshot(self) -> tuple[int, bytes]:
        """(model version, the snapshot as JSON)."""
        with self._lock:
            snap = self.model.snapshot()
        snap["title"] = self.title
        return snap["version"], json.dumps(snap, separators=(",", ":")).encode()

    def close(self) -> None:
        self.server.close()

    # -- the server, on its own thread

    def _http(self, connection: ServerConnection, request: Request) -> Response | None:
        if self._gate is not None and (refusal := self._gate.refusal(connection, request)) is not None:
            return refusal
        cookie = self._gate.cookie(connection, request) if self._gate is not None else {}
        path = request.path.split("?", 1)[0]
        if path == "/ws":
            return None   # the WebSocket handshake goes on
        if path in ("/", "/index.html"):
            return response(HTTPStatus.OK, "text/html; charset=utf-8", self._page, **cookie)
        if path == "/state.json":
            return response(HTTPStatus.OK, "application/json", self.snapshot()[1], **cookie)
        if path == "/map.png":
            with self._lock:
                png = self.model.grid_png()
            if png is not None:
                return response(HTTPStatus.OK, "image/png", png, **cookie)
        return response(HTTPStatus.NOT_FOUND, "text/plain", b"not found\n")

    async def _client(self, ws: ServerConnection) -> None:
        sent = -1
        try:
            while True:
                version, data = self.snapshot()
                if version != sent:
                    await ws.send(data.decode())
                    sent = version
                # Waiting on the connection, not a plain sleep: a handler that never sees its
                # browser go would keep the server's close waiting.
                try:
                    await asyncio.wait_for(ws.wait_closed(), self.period_s)
                    return
                except TimeoutError:
                    pass
        except ConnectionClosed:
            return
