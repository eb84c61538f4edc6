"""The monitor's web servers: one ``websockets`` server per port, on its own thread, and the token they require.

Beyond loopback ``lrfslam monitor`` serves only to whoever presents its token
(src/lrfslam/tools/monitor.py): in the URL's query (``?token=``, what a browser's first page load
and the Foxglove app can carry), in the cookie the dashboard's page gets on that first load (so
that its WebSocket and a reload need nothing more), or as ``Authorization: Bearer`` (scripts). A
request without it is answered 401, with a wrong one 403, before any page or WebSocket.

foxglove-sdk's WebSocket server cannot check a token: no callback of its sees the handshake's URL
or headers, and it has no way to refuse or drop a client. So with a token it listens on loopback
only, and :class:`FoxgloveRelay` stands on the monitor's address and port in its place, letting a
client through to it once the token checks out, frames passed on unchanged both ways.
"""

from __future__ import annotations

import asyncio
import hmac
import logging
import threading
from collections.abc import Awaitable, Callable
from http import HTTPStatus
from urllib.parse import parse_qs, urlsplit

from websockets.asyncio.client import connect
from websockets.asyncio.server import ServerConnection, serve
from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed, InvalidHandshake
from websockets.http11 import Request, Response

from lrfslam.errors import StartupError

ProcessRequest = Callable[[ServerConnection, Request], Response | None]
log = logging.getLogger(__name__)
#: s a server's thread gets to close its connections and end (its handlers must notice the close).
CLOSE_WAIT_S = 5.0


def response(status: HTTPStatus, content_type: str, body: bytes, **headers: str) -> Response:
    """An HTTP response that no cache keeps."""
    return Response(status.value, status.phrase, Headers({"Content-Type": content_type,
                                                          "Content-Length": str(len(body)),
                                                          "Cache-Control": "no-store", **headers}), body)


class ServerThread:
    """A ``websockets`` server (plain HTTP answers and WebSockets) on its own thread and event loop,
    listening on ``host``:``port`` (0: any free port, then :attr:`port`) when the constructor returns.

    Raises
    ------
    StartupError
        It cannot listen there: one line naming ``what``, with ``hint`` when the port is taken.
    """

    def __init__(self, what: str, host: str, port: int, handler: Callable[[ServerConnection], Awaitable[None]],
                 process_request: ProcessRequest, hint: str, **options) -> None:
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Future | None = None
        self.port = 0
        self._thread = threading.Thread(target=self._serve_forever, name=what, daemon=True,
                                        args=(host, port, handler, process_request, options))
        self._thread.start()
        self._ready.wait()
        if self._error is not None:
            reason = getattr(self._error, "strerror", None) or str(self._error)
            raise StartupError(f"cannot serve {what} on {host}:{port}: {reason}"
                               + (f" {hint}" if "in use" in reason else ""))

    def close(self) -> None:
        if self._loop is not None and self._stop is not None:
            self._loop.call_soon_threadsafe(lambda: self._stop.done() or self._stop.set_result(None))
        self._thread.join(CLOSE_WAIT_S)
        if self._thread.is_alive():
            log.warning("%s did not stop within %g s (a connection's handler still runs); left behind",
                        self._thread.name, CLOSE_WAIT_S)

    def _serve_forever(self, host: str, port: int, handler, process_request: ProcessRequest, options: dict) -> None:
        try:
            asyncio.run(self._main(host, port, handler, process_request, options))
        except OSError as exc:   # reported by the constructor, in one line
            self._error = exc
        finally:
            if not self._ready.is_set():
                self._error = self._error or OSError("the server stopped while starting")
                self._ready.set()

    async def _main(self, host: str, port: int, handler, process_request: ProcessRequest, options: dict) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop = self._loop.create_future()
        async with serve(handler, host, port, process_request=process_request, **options) as server:
            self.port = server.sockets[0].getsockname()[1]
            self._ready.set()
            await self._stop


class TokenGate:
    """The check every request passes when the monitor has a token (see the module's docstring)."""

    def __init__(self, token: str) -> None:
        self._token = token.encode()

    @staticmethod
    def cookie_name(connection: ServerConnection) -> str:
        """The cookie's name carries the server's port: a browser keeps cookies per host, not per port,
        and two monitors on one host must not overwrite each other's."""
        return f"lrfslam_token_{connection.local_address[1]}"

    def presented(self, connection: ServerConnection, request: Request) -> tuple[str | None, str]:
        """(the token the request presents, how: "query", "cookie", "header" or "" for none)."""
        if values := parse_qs(urlsplit(request.path).query).get("token"):
            return values[0], "query"
        name = self.cookie_name(connection)
        for header in request.headers.get_all("Cookie"):
            for part in header.split(";"):
                key, _, value = part.strip().partition("=")
                if key == name:
                    return value, "cookie"
        scheme, _, value = request.headers.get("Authorization", "").partition(" ")
        if scheme.lower() == "bearer" and value:
            return value.strip(), "header"
        return None, ""

    def refusal(self, connection: ServerConnection, request: Request) -> Response | None:
        """401 without a token, 403 with a wrong one; None when the right one came."""
        given, _ = self.presented(connection, request)
        if given is None:
            return response(HTTPStatus.UNAUTHORIZED, "text/plain", b"a token is required: add ?token=TOKEN to the "
                            b"URL (lrfslam monitor --token-file)\n", **{"WWW-Authenticate": 'Bearer realm="lrfslam"'})
        if not hmac.compare_digest(given.encode(), self._token):
            return response(HTTPStatus.FORBIDDEN, "text/plain", b"wrong token\n")
        return None

    def cookie(self, connection: ServerConnection, request: Request) -> dict[str, str]:
        """The header that lets a browser that came with ``?token=`` in as it is on (none otherwise).
        HttpOnly: the page's scripts never see it; SameSite=Strict: another site's page cannot use it."""
        given, how = self.presented(connection, request)
        if how != "query" or given is None:
            return {}
        return {"Set-Cookie": f"{self.cookie_name(connection)}={given}; Path=/; HttpOnly; SameSite=Strict"}


async def _pump(source: ServerConnection, sink) -> None:
    try:
        async for frame in source:
            await sink.send(frame)
    except ConnectionClosed:
        pass


class FoxgloveRelay:
    """Foxglove's WebSocket on ``host``:``port`` behind ``gate``: each client let in gets its own
    connection to foxglove-sdk's server on loopback ``upstream_port``, with the subprotocol it agreed.

    Raises
    ------
    StartupError
        It cannot listen there.
    """

    #: What foxglove-sdk's server speaks, in its order of preference.
    SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")

    def __init__(self, host: str, port: int, upstream_port: int, gate: TokenGate) -> None:
        self.upstream = f"ws://127.0.0.1:{upstream_port}"
        self.server = ServerThread("Foxglove", host, port, self._relay, gate.refusal,
                                   "(another monitor has it: pass another --port)",
                                   subprotocols=list(self.SUBPROTOCOLS), compression=None)

    @property
    def port(self) -> int:
        return self.server.port

    async def _relay(self, client: ServerConnection) -> None:
        try:
            # No size limit: the views (a map, a long trajectory) may be large, and they come from our server.
            async with connect(self.upstream, subprotocols=[client.subprotocol], max_size=None,
                               compression=None) as upstream:
                tasks = [asyncio.create_task(_pump(client, upstream)), asyncio.create_task(_pump(upstream, client))]
                await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
                for task in tasks:
                    task.cancel()
        except (OSError, InvalidHandshake):
            await client.close(1011, "the Foxglove server is not answering")

    def close(self) -> None:
        self.server.close()
