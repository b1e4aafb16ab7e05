"""The public side of `tacf foxglove`: a WebSocket relay that lets Lichtblick in as well as Foxglove.

foxglove-sdk's server (0.30) accepts a client only if it offers the subprotocol `foxglove.sdk.v1`. Lichtblick, the
open fork of Foxglove, connects through @foxglove/ws-protocol's client, which offers only the protocol's older
name, `foxglove.websocket.v1`, and closes the connection unless it gets that name back (lichtblick#750): against
the SDK's server alone it never connects. The messages are the same under both names (that client library served
everything `tacf foxglove` offers once it was given the name it checks for; README "Foxglove and Lichtblick"). So
the SDK's server listens on a loopback address of its own, and this relay takes the public address: it accepts
either name, opens one connection to the SDK's server per client, and passes every message through unchanged both
ways, and the close code and reason when one side leaves (a connection that broke, with no close frame, as 1001).
It also terminates TLS (wss://), so the SDK's server never needs the certificate. The SDK's server checks no
Origin, so it must stay out of web pages' reach: FoxgloveBridge puts it on a random one of 127.0.0.0/8's 2**24
addresses, which no page can find, where 127.0.0.1's ports could be scanned.

Nothing queues without bound: the relay sends a message on before it reads the next, so a client that reads too
slowly fills the TCP buffers back to the SDK's server, which then drops that client's oldest messages, as it would
without the relay (its per-client backlog, FoxgloveBridge's MESSAGE_BACKLOG).

Web pages are let in only from known origins. A browser lets any page it shows open a WebSocket to any address,
127.0.0.1 included, and says which page asked in the Origin header; without this check any web site the operator
visits could watch the cameras and stop the sessions. Let in: no Origin (programs: the SDKs, Node.js), a page
served from this machine (a loopback host, any port), Foxglove's web app, desktop apps (origins that are no web
address: file://, app://...), and each origin given in `allow_origins` ("*" for any). `null` (sandboxed frames of
any site send it) only when given.
"""
from __future__ import annotations

import asyncio
import http
import logging
import ssl
import threading
import weakref
from urllib.parse import urlsplit

from websockets.asyncio.client import connect
from websockets.asyncio.server import ServerConnection, serve
from websockets.exceptions import ConnectionClosed, WebSocketException
from websockets.frames import CloseCode
from websockets.http11 import Request, Response

from tacf_clients.dashboard_access import is_loopback

log = logging.getLogger(__name__)

SDK_SUBPROTOCOL = "foxglove.sdk.v1"
SUBPROTOCOLS = (SDK_SUBPROTOCOL, "foxglove.websocket.v1")  # the SDK's name, then Lichtblick's
MAX_CLIENT_MESSAGE = 1 << 20   # subscriptions and service calls are small; the SDK's own limit is larger
UPSTREAM_QUEUE = 4             # messages read ahead from the SDK's server per client (images are ~0.1-0.5 MB)
CLOSE_TIMEOUT_S = 1.0          # a viewer that stopped reading never completes a close: don't wait 10 s for it
FOXGLOVE_WEB_APP = "https://app.foxglove.dev"
WEB_SCHEMES = ("http", "https", "ws", "wss")


def origin_allowed(origin: str | None, allow_origins=()) -> bool:
    """Whether a connection whose handshake carries this Origin header is let in (see the module's docstring)."""
    if origin is None or "*" in allow_origins or origin in allow_origins or origin == FOXGLOVE_WEB_APP:
        return True
    if origin == "null":
        return False
    parts = urlsplit(origin)
    if parts.scheme.lower() not in WEB_SCHEMES:
        return bool(parts.scheme)                     # a desktop app's own scheme; no web page can send it
    return parts.hostname is not None and is_loopback(parts.hostname)


class SubprotocolRelay:
    """Serves ws://host:port (wss:// with `tls`) and relays every connection to ws://upstream_host:upstream_port.

    Runs its own asyncio loop on a daemon thread; close() stops it and drops every connection."""

    def __init__(self, upstream_port: int, *, upstream_host: str = "127.0.0.1", host: str, port: int,
                 tls: ssl.SSLContext | None = None, allow_origins=()):
        self.upstream = f"ws://{upstream_host}:{upstream_port}"
        self.allow_origins = frozenset(allow_origins)
        # every connection, those still in their handshake too (a port scan, a half-sent request): close() drops
        # them all after CLOSE_TIMEOUT_S, where the server would wait out the handshake's 10 s
        self._connections: weakref.WeakSet[ServerConnection] = weakref.WeakSet()
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, name="foxglove-relay", daemon=True)
        self._thread.start()
        try:
            self._server = asyncio.run_coroutine_threadsafe(self._listen(host, port, tls), self._loop).result()
        except BaseException:
            self._stop_loop()
            raise
        self.port = self._server.sockets[0].getsockname()[1]

    async def _listen(self, host: str, port: int, tls: ssl.SSLContext | None):
        return await serve(self._relay, host, port, ssl=tls, subprotocols=list(SUBPROTOCOLS),
                           compression=None, max_size=MAX_CLIENT_MESSAGE, close_timeout=CLOSE_TIMEOUT_S,
                           process_request=self._check_origin, create_connection=self._connection)

    def _connection(self, *args, **kwargs) -> ServerConnection:
        connection = ServerConnection(*args, **kwargs)
        self._connections.add(connection)
        return connection

    def _check_origin(self, connection: ServerConnection, request: Request) -> Response | None:
        origin = request.headers.get("Origin")
        if origin_allowed(origin, self.allow_origins):
            return None
        log.warning("foxglove relay: refused a page at %s (tacf foxglove --allow-origin %s lets it in)", origin, origin)
        return connection.respond(http.HTTPStatus.FORBIDDEN, f"pages at {origin} are not let in\n")

    async def _relay(self, client: ServerConnection) -> None:
        try:
            async with connect(self.upstream, subprotocols=[SDK_SUBPROTOCOL], compression=None, max_size=None,
                               max_queue=UPSTREAM_QUEUE, open_timeout=5, close_timeout=CLOSE_TIMEOUT_S) as server:
                forward = asyncio.create_task(_pass_on(client, server))
                back = asyncio.create_task(_pass_on(server, client))
                await asyncio.wait((forward, back), return_when=asyncio.FIRST_COMPLETED)
                for task in (forward, back):
                    task.cancel()
                await asyncio.gather(forward, back, return_exceptions=True)
        # asyncio.TimeoutError: before Python 3.11 it is not the builtin TimeoutError (an OSError);
        # WebSocketException: a closed connection, or the SDK's server refusing the handshake
        except (OSError, asyncio.TimeoutError, WebSocketException) as exc:
            log.info("foxglove relay: %s closed: %s", client.remote_address, exc)

    def close(self) -> None:
        if self._loop.is_closed():
            return
        try:
            asyncio.run_coroutine_threadsafe(self._shut_down(), self._loop).result(timeout=10)
        finally:
            self._stop_loop()

    async def _shut_down(self) -> None:
        self._server.close()          # also closes every open connection, politely
        try:
            await asyncio.wait_for(self._server.wait_closed(), CLOSE_TIMEOUT_S)
        except asyncio.TimeoutError:  # a viewer that stopped reading, or a handshake never finished: drop them
            for connection in list(self._connections):
                transport = getattr(connection, "transport", None)    # none yet while a TLS handshake runs
                if transport is not None:
                    transport.abort()
            await self._server.wait_closed()

    def _stop_loop(self) -> None:
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=10)
        # what is left (asyncio's own TLS handshake of a client that never sent a ClientHello) is cancelled and
        # run to its end, as asyncio.run does, rather than destroyed pending with a warning
        if leftover := asyncio.all_tasks(self._loop):
            for task in leftover:
                task.cancel()
            self._loop.run_until_complete(asyncio.gather(*leftover, return_exceptions=True))
        self._loop.close()


async def _pass_on(source, sink) -> None:
    """Every message of source to sink, text as text and binary as binary, until either side closes; then closes
    sink with the code and reason source was closed with, so that each end learns why the other left."""
    try:
        async for message in source:
            await sink.send(message)
    except ConnectionClosed:
        pass
    finally:
        await sink.close(*_close_to_pass_on(source))


def _close_to_pass_on(source) -> tuple[int, str]:
    """The close code and reason source got, as they may be sent on: websockets refuses on receipt every code that
    may not be sent, except the two it reports itself (RFC 6455 7.1.5, 7.4.1), which no frame may carry."""
    code, reason = source.protocol.close_code, source.protocol.close_reason   # on the connection from websockets 15
    sent = source.protocol.close_sent
    if code == CloseCode.ABNORMAL_CLOSURE and sent is not None and sent.code == CloseCode.MESSAGE_TOO_BIG:
        # the relay itself closed a viewer whose message was over the limit, before the viewer answered: say so
        return sent.code, sent.reason
    if code is None or code == CloseCode.NO_STATUS_RCVD:   # still open (sink failed first), or closed with no code
        return CloseCode.NORMAL_CLOSURE, ""
    if code == CloseCode.ABNORMAL_CLOSURE:
        # no close frame: the connection broke (a crash, a network cut). 1001 says the peer went away, which is
        # all the relay knows; 1011 would blame the server for what may have been the viewer's network.
        return CloseCode.GOING_AWAY, "connection lost"
    return code, reason
