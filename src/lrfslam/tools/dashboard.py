"""``lrfslam monitor --dashboard``: a web page of the robot's map and services, served by the monitor.

One sink of the monitor (src/lrfslam/tools/monitor.py): every message updates a
:class:`~lrfslam.viz.dashboard.DashboardModel`, and an HTTP + WebSocket server (the ``websockets``
package's, on its own thread) serves

* ``/``: the page (src/lrfslam/tools/dashboard.html), a canvas and a table of the services;
* ``/ws``: a WebSocket on which the page gets the model's snapshot as JSON, at most every
  ``period_s`` and only when it changed;
* ``/state.json``: the same snapshot once (for scripts and ``curl``).

No authentication: the server listens on loopback unless told otherwise.
"""

from __future__ import annotations

import asyncio
import json
import logging
import threading
from http import HTTPStatus
from importlib import resources

from websockets.asyncio.server import ServerConnection, serve
from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response

from lrfslam.errors import DecodeError, StartupError
from lrfslam.runtime.decoding import LogOnce
from lrfslam.runtime.step import Message
from lrfslam.viz.dashboard import DashboardModel

log = logging.getLogger("lrfslam.monitor.dashboard")

DEFAULT_HTTP_PORT = 8080
#: The page redraws at most this often, s.
PUSH_PERIOD_S = 0.2
PAGE = resources.files("lrfslam.tools").joinpath("dashboard.html")


def _response(status: HTTPStatus, content_type: str, body: bytes) -> Response:
    return Response(status.value, status.phrase, Headers({"Content-Type": content_type,
                                                          "Content-Length": str(len(body)),
                                                          "Cache-Control": "no-store"}), body)


class DashboardServer:
    """Sink: the dashboard's model, served over HTTP and WebSocket on ``host``:``port`` (0: any free port).

    Raises
    ------
    StartupError
        The server cannot listen there.
    """

    def __init__(self, host: str, port: int, title: str, period_s: float = PUSH_PERIOD_S) -> None:
        self.model = DashboardModel()
        self.title = title
        self.period_s = period_s
        self.counts = {"undecodable": 0}
        self._lock = threading.Lock()
        self._once = LogOnce(log)
        self._page = PAGE.read_bytes()
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Future | None = None
        self.port = 0
        self._thread = threading.Thread(target=self._serve_forever, args=(host, port), name="dashboard", daemon=True)
        self._thread.start()
        self._ready.wait()
        if self._error is not None:
            reason = getattr(self._error, "strerror", None) or str(self._error)
            hint = " (pass another --http-port)" if "in use" in reason else ""
            raise StartupError(f"cannot serve the dashboard on {host}:{port}: {reason}{hint}")

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
        if self._loop is not None and self._stop is not None:
            self._loop.call_soon_threadsafe(lambda: self._stop.done() or self._stop.set_result(None))
        self._thread.join(5)

    # -- the server, on its own thread

    def _serve_forever(self, host: str, port: int) -> None:
        try:
            asyncio.run(self._main(host, port))
        except OSError as exc:   # reported by the constructor, in one line
            self._error = exc
        finally:
            if not self._ready.is_set():
                self._error = self._error or OSError("the server stopped while starting")
                self._ready.set()

    async def _main(self, host: str, port: int) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop = self._loop.create_future()
        async with serve(self._client, host, port, process_request=self._http) as server:
            self.port = server.sockets[0].getsockname()[1]
            self._ready.set()
            await self._stop

    def _http(self, _connection: ServerConnection, request: Request) -> Response | None:
        path = request.path.split("?", 1)[0]
        if path == "/ws":
            return None   # the WebSocket handshake goes on
        if path in ("/", "/index.html"):
            return _response(HTTPStatus.OK, "text/html; charset=utf-8", self._page)
        if path == "/state.json":
            return _response(HTTPStatus.OK, "application/json", self.snapshot()[1])
        return _response(HTTPStatus.NOT_FOUND, "text/plain", b"not found\n")

    async def _client(self, ws: ServerConnection) -> None:
        sent = -1
        try:
            while True:
                version, data = self.snapshot()
                if version != sent:
                    await ws.send(data.decode())
                    sent = version
                await asyncio.sleep(self.period_s)
        except ConnectionClosed:
            return
