"""`tacf dashboard`, the web side: a stdlib ThreadingHTTPServer serving the page and its live data.

    GET  /                    the page (clients/static/index.html, dashboard.js, dashboard.css: no CDN, no internet)
    GET  /events              Server-Sent Events: every session's box, health and chart points, one stream
    GET  /api/state           the same as one JSON snapshot (the page loads it first)
    GET  /frame/<image key>   the newest frame of a watched key as JPEG (ETag: its seq and arrival; 304 when unchanged);
                              ?seq=N: the newest kept frame with seq <= N (the frame a box was computed on)
    GET  /mjpeg/<image key>   multipart/x-mixed-replace of the newest frames (a single view, e.g. VLC)
    POST /api/watch           {"key"}: watch an image key's frames
    POST /api/start           {"image_key", "box": [x, y, w, h], "seq"?, "sid"?, "profile"?, "overrides"?, "node"?}
    POST /api/stop            {"sid", "node"?}
    POST /api/reinit          {"sid", "box", "seq"?, "node"?}
    GET  /metrics             Prometheus text format (dashboard_metrics.py)
    GET  /healthz             200 {"status": "ok"} while the Zenoh side works, else 503
    HEAD                      as GET without the body, on every page but the two streams

Latest-only and rate-capped: each /events connection wakes at most `events_hz` times a second and sends only
what changed since its previous message (newest box and health per session, new chart points), read from the
Dashboard's slots; nothing is queued per browser. A browser that stops reading only blocks its own handler
thread until the socket write times out, then the connection is dropped. POSTs need a JSON content type (a
cross-site form cannot send one), so another web page cannot start or stop sessions through a user's browser;
every request first passes dashboard_access.py (the Host header on loopback, a token elsewhere).
"""
from __future__ import annotations

import io
import json
import logging
import math
import mimetypes
import selectors
import socket
import ssl
import sys
import threading
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path
from urllib.parse import parse_qs, unquote, urlencode, urlsplit

import pydantic

from tacf_clients import dashboard_metrics
from tacf_clients.dashboard import Dashboard
from tacf_clients.dashboard_access import DashboardAccess
from tacf_clients.errors import (AmbiguousNode, AmbiguousSession, DuplicateSession, InvalidRequest, NoService,
                                 RequestTimeout, ServiceUnavailable, TacfError, TooManySessions, UnknownSession)
from tacf_schemas.codec import RepeatedKeyError, unique_keys
from tacf_schemas.models import SEQ

log = logging.getLogger(__name__)

DEFAULT_PORT = 8080
EVENTS_HZ = 10.0                 # per /events connection, hence at most this rate per session
KEEPALIVE_S = 15.0               # an SSE comment when nothing changed for this long (proxies, dead peers)
WRITE_TIMEOUT_S = 10.0           # a browser that does not read for this long is dropped
# A request's line and headers (and a TLS handshake) must arrive whole within this: the socket timeout restarts on
# every byte, and a client sending one every few seconds held its thread for good, before any token check.
HEAD_TIMEOUT_S = 10.0
MAX_CONNECTIONS = 256            # open at once, a thread each; more are closed as they come (a busy page opens 3-4)
# A request's line and headers in all. http.client alone takes 100 header lines of 64 KiB each: a client without the
# token held 6.2 MiB per connection by stopping short of the blank line. This page's requests carry a key and a token
# of 256 characters at most; by default nginx refuses a header line over 8 KiB, Node a head over 16 KiB.
MAX_HEAD = 64 * 1024
HEAD_TOO_LARGE = f"a request's line and headers may take {MAX_HEAD} bytes in all"
# the fields each POST action takes (the module docstring's list)
ACTION_FIELDS = {"/api/start": {"image_key", "box", "seq", "sid", "profile", "overrides", "node"},
                 "/api/stop": {"sid", "node"}, "/api/reinit": {"sid", "box", "seq", "node"}, "/api/watch": {"key"}}
MAX_BODY = 64 * 1024
# Of a request refused unread (a body over MAX_BODY before its 413; what a client still sends after a refusal that
# closes the connection), read and dropped this much at most, so that its sender gets the refusal, not a reset.
MAX_DRAINED = 1 << 20
LINGER_S = 2.0                   # and, after the refusal, for this long at most: a client may not hold its thread
MJPEG_FPS = 10.0
MAX_SEQ_DIGITS = 20              # a seq is a 64-bit count (and int() refuses a string of over 4300 digits)

_ERROR_STATUS = (                # most specific first
    (UnknownSession, HTTPStatus.NOT_FOUND),
    (DuplicateSession, HTTPStatus.CONFLICT),
    (InvalidRequest, HTTPStatus.BAD_REQUEST),
    ((AmbiguousNode, AmbiguousSession), HTTPStatus.CONFLICT),
    (TooManySessions, HTTPStatus.TOO_MANY_REQUESTS),
    ((NoService, ServiceUnavailable), HTTPStatus.SERVICE_UNAVAILABLE),
    (RequestTimeout, HTTPStatus.GATEWAY_TIMEOUT),
    (TacfError, HTTPStatus.BAD_GATEWAY),
)

# the error codes of http.server's own refusals (send_error), as the dashboard names its own
_STDLIB_ERRORS = {HTTPStatus.BAD_REQUEST: "invalid_request", HTTPStatus.REQUEST_URI_TOO_LONG: "head_too_large",
                  HTTPStatus.REQUEST_HEADER_FIELDS_TOO_LARGE: "head_too_large"}


def tls_context(certfile: str, keyfile: str | None = None) -> ssl.SSLContext:
    """A server context for HTTPS from a PEM certificate (chain) and its key (TLS 1.2 or newer)."""
    context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    context.load_cert_chain(certfile, keyfile)
    return context


def static_dir() -> Path:
    """clients/static (installed as tacf_clients/static)."""
    return Path(str(resources.files("tacf_clients") / "static"))


class DashboardServer(ThreadingHTTPServer):
    """One thread per connection (daemon threads: a hanging browser never blocks shutdown), at most
    `max_connections` of them; a connection whose request head takes over `head_timeout_s` is cut."""

    daemon_threads = True
    max_connections = MAX_CONNECTIONS
    head_timeout_s = HEAD_TIMEOUT_S
    linger_s = LINGER_S
    allow_reuse_address = True
    # the stdlib's 5: the connections of many viewers (re)connecting at once, beyond it, waited 1 s, 3 s... for
    # their SYN to be sent again
    request_queue_size = socket.SOMAXCONN

    def __init__(self, address: tuple[str, int], dashboard: Dashboard, *, events_hz: float = EVENTS_HZ,
                 access: DashboardAccess | None = None, tls: ssl.SSLContext | None = None):
        self.dashboard = dashboard
        self.access = access or DashboardAccess.for_address(address[0])
        self.tls = tls
        self.events_hz = events_hz
        self.static = static_dir()
        self.event_clients = 0
        self.connections = 0
        self.connections_refused = 0
        self._refusal_logged = -math.inf
        self._heads: dict[socket.socket, float] = {}      # connection -> when its request head must have come
        self._clients_lock = threading.Lock()
        self.stopping = threading.Event()
        if ":" in address[0]:                      # an IPv6 address: the class binds IPv4 only
            self.address_family = socket.AF_INET6
        super().__init__(address, DashboardHandler)
        if tls is not None:     # the handshake runs in each connection's own thread, so a slow one stalls no other
            self.socket = tls.wrap_socket(self.socket, server_side=True, do_handshake_on_connect=False)

    def server_bind(self) -> None:
        if self.address_family == socket.AF_INET6 and self.server_address[0] == "::":
            # both stacks whatever net.ipv6.bindv6only says: as for 0.0.0.0, the address printed is 127.0.0.1
            self.socket.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 0)
        super().server_bind()

    def process_request(self, request, client_address) -> None:
        with self._clients_lock:
            admitted = self.connections < self.max_connections
            self.connections += admitted
            self.connections_refused += not admitted
        if admitted:
            try:
                super().process_request(request, client_address)
                return
            except Exception as exc:    # its thread did not start (none left): process_request_thread never runs
                with self._clients_lock:
                    self.connections -= 1
                    self.connections_refused += 1
                reason = f"cannot start a thread for a connection ({exc}): refusing it"
        else:
            reason = f"{self.max_connections} connections open, the most this dashboard serves: refusing new ones"
        self.shutdown_request(request)        # no reply: a TLS connection could not even be answered unread
        if time.monotonic() - self._refusal_logged > 10.0:
            self._refusal_logged = time.monotonic()
            log.warning("%s (%d so far)", reason, self.connections_refused)

    def process_request_thread(self, request, client_address) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            with self._clients_lock:
                self.connections -= 1

    def expect_head(self, connection: socket.socket, waiting: bool) -> None:
        """Mark `connection` as waiting for a request head or a POST's body (from now on, head_timeout_s at most),
        or not."""
        with self._clients_lock:
            if waiting:
                self._heads[connection] = time.monotonic() + self.head_timeout_s
            else:
                self._heads.pop(connection, None)

    def service_actions(self) -> None:
        """Between two polls of serve_forever: cut the connections whose request head is late (their thread's
        read then returns at once)."""
        now = time.monotonic()
        with self._clients_lock:
            late = [connection for connection, deadline in self._heads.items() if deadline < now]
            for connection in late:
                del self._heads[connection]
        for connection in late:
            try:
                connection.shutdown(socket.SHUT_RDWR)
            except OSError:                    # closed meanwhile
                pass

    def handle_error(self, request, client_address) -> None:
        """A connection that fails its TLS handshake (plain HTTP on the HTTPS port, say), or that its client resets
        (a flaky radio link, a phone changing networks), is a line, not a trace."""
        exc = sys.exc_info()[1]
        if isinstance(exc, ssl.SSLError):
            log.info("%s: TLS failed: %s", client_address[0], exc)
        elif isinstance(exc, ConnectionError):
            log.info("%s: connection lost: %s", client_address[0], exc)
        else:
            super().handle_error(request, client_address)

    @property
    def base_url(self) -> str:
        host, port = self.server_address[:2]
        host = "127.0.0.1" if host in ("0.0.0.0", "", "::") else f"[{host}]" if ":" in host else host
        return f"{'https' if self.tls else 'http'}://{host}:{port}/"

    @property
    def url(self) -> str:
        """The address to open in a browser: base_url, with the token when one is needed."""
        token = self.access.token
        return self.base_url if token is None else f"{self.base_url}?{urlencode({'token': token})}"

    def count_client(self, delta: int) -> None:
        with self._clients_lock:
            self.event_clients += delta

    def stop(self) -> None:
        """Stop serving (call from another thread than serve_forever's); open streams end within a tick."""
        self.stopping.set()
        self.shutdown()
        self.server_close()


class DashboardHandler(BaseHTTPRequestHandler):
    server: DashboardServer
    protocol_version = "HTTP/1.1"
    timeout = WRITE_TIMEOUT_S
    server_version = "tacf-dashboard"

    # the connection ends with its request maybe not read whole: what its client still sends is drained first
    unread_input = False

    def log_message(self, fmt: str, *args) -> None:
        log.debug("%s %s", self.address_string(), fmt % args)

    def handle(self) -> None:
        super().handle()
        if self.unread_input:
            self._linger()

    def _linger(self) -> None:
        """Close as web servers do after a refusal ("lingering close"): the reply sent and the write side shut, read
        and drop what the client still sends until it closes its end (linger_s and MAX_DRAINED at most). Closed
        with input unread, the connection was reset: a client still writing its head or body (a line per send, or
        more than the socket buffers hold) failed with a broken pipe or a reset, never reading the refusal."""
        deadline, left = time.monotonic() + self.server.linger_s, MAX_DRAINED
        try:
            self.connection.shutdown(socket.SHUT_WR)
            while left > 0 and (timeout := deadline - time.monotonic()) > 0:
                self.connection.settimeout(timeout)
                chunk = self.connection.recv(min(left, 65536))
                if not chunk:
                    break
                left -= len(chunk)
        except OSError:                       # reset, or the time is up
            pass

    def handle_one_request(self) -> None:
        self.server.expect_head(self.connection, True)
        try:
            super().handle_one_request()
        finally:
            self.server.expect_head(self.connection, False)

    def parse_request(self) -> bool:
        if self.server.stopping.is_set():
            # a browser's kept-alive connection outlives a stopped server (its threads are daemons): left unanswered,
            # the browser asks again on a new connection, of the dashboard started on this port in its place; served,
            # it had the closed dashboard's empty state (no image keys)
            self.close_connection = True
            return False
        # a request line without a version ("GET /") is HTTP/0.9's, which has no headers: none is waited for
        versionless = len(str(self.raw_requestline, "iso-8859-1").split()) == 2
        head = io.BytesIO() if versionless else _HeadBudget(self.rfile, MAX_HEAD - len(self.raw_requestline))
        rfile, self.rfile = self.rfile, head
        try:
            parsed = super().parse_request()                # reads the headers
        except HeadTooLarge:
            self.send_error(HTTPStatus.REQUEST_HEADER_FIELDS_TOO_LARGE, HEAD_TOO_LARGE)
            return False
        finally:
            self.rfile = rfile
        if parsed and versionless:
            # http.server would serve a GET's reply as HTTP/0.9's bare body, with no status, Content-Type or
            # X-Frame-Options, which curl and browsers refuse; nor could a request without headers pass the Host
            # check or carry the token. Refused, in HTTP/1.1 like every other refusal.
            self.send_error(HTTPStatus.BAD_REQUEST, "a request line needs its HTTP version (HTTP/1.0 or HTTP/1.1)")
            return False
        self.server.expect_head(self.connection, False)     # the head came: streams (/events, /mjpeg) run on
        if parsed and self.command != "POST" and (self.headers.get("Transfer-Encoding") is not None
                                                  or body_length(self.headers) != 0):
            # only a POST's body is ever read: another's would pass for the next request on this connection
            # (behind a proxy that reuses its connections, a request smuggled past the proxy's own checks)
            self.close_connection = self.unread_input = True
        return parsed

    def send_error(self, code: int, message: str | None = None, explain: str | None = None) -> None:
        """The refusals http.server makes itself (a request line over 64 KiB, over 100 header lines, a malformed
        request line, a method with no do_ method) in JSON like the dashboard's own: they came as an HTML page.
        Each may come before the request was read whole, so the connection is drained, then closed."""
        status = HTTPStatus(code)
        if status == HTTPStatus.REQUEST_URI_TOO_LONG:      # the stdlib's limit on the line alone: MAX_HEAD's 64 KiB
            message = HEAD_TOO_LARGE
        if self.request_version == "HTTP/0.9":
            # no valid version read from the request line (HTTP/9.9, HTTP/1.x, none): http.server's default, under
            # which a reply is a bare body, no status line nor headers, which a client cannot read as a refusal
            self.request_version = "HTTP/1.0"
        self.unread_input = True
        self._error(status, _STDLIB_ERRORS.get(status, status.name.lower()), message or status.description,
                    {"Connection": "close"})

    def handle_expect_100(self) -> bool:
        """A client that waits for "100 Continue" before sending its body (curl since 7.69, for a body over 1 MiB, so
        not for one of MAX_BODY; `-H "Expect: 100-continue"` asks for it) is refused first when it is not let in: it
        was invited to send the body before the token was looked at."""
        return self._admitted() and super().handle_expect_100()

    # --- routing --------------------------------------------------------------------------------------------
    def do_GET(self) -> None:
        path = urlsplit(self.path).path
        try:
            if not self._admitted():
                return
            if path in ("/", "/index.html"):
                self._static("index.html")
            elif path.startswith("/static/"):
                self._static(path[len("/static/"):])
            elif path == "/events":
                self._events()
            elif path == "/api/state":
                self._json(HTTPStatus.OK, self.server.dashboard.snapshot())
            elif path.startswith("/frame/"):
                self._frame(unquote(path[len("/frame/"):]), parse_qs(urlsplit(self.path).query))
            elif path.startswith("/mjpeg/"):
                self._mjpeg(unquote(path[len("/mjpeg/"):]))
            elif path == "/metrics":
                self._metrics()
            elif path == "/healthz":
                self._healthz()
            else:
                self._error(HTTPStatus.NOT_FOUND, "not_found", f"no such page: {path}")
        except (BrokenPipeError, ConnectionResetError, TimeoutError):
            self.close_connection = True

    def _not_allowed(self) -> None:
        """A 405 in JSON like every other refusal (the stdlib answers PUT and the like with a 501 HTML page)."""
        if self.command != "HEAD":                           # a body left unread is not the next request
            self.close_connection = self.unread_input = True
        self._error(HTTPStatus.METHOD_NOT_ALLOWED, "method_not_allowed", "use GET or POST", {"Allow": "GET, POST"})

    do_PUT = do_DELETE = do_PATCH = do_OPTIONS = _not_allowed

    def do_HEAD(self) -> None:
        """GET's status and headers without its body (uptime monitors and `curl -I` probe with it); not on the streams,
        whose headers promise a body that never ends."""
        path = urlsplit(self.path).path
        if path == "/events" or path.startswith("/mjpeg/"):
            self._not_allowed()
        else:
            self.do_GET()

    def do_POST(self) -> None:
        path = urlsplit(self.path).path
        actions = {"/api/start": self._start, "/api/stop": self._stop, "/api/reinit": self._reinit,
                   "/api/watch": self._watch}
        action = actions.get(path)
        try:
            body = None
            if self._admitted():
                if action is None:
                    self._error(HTTPStatus.NOT_FOUND, "not_found", f"no such action: {path}")
                else:
                    body = self._read_json()
            if body is None:                        # refused, maybe with the body unread: it is not a request
                self.close_connection = self.unread_input = True
                return
            unknown = sorted(set(body) - ACTION_FIELDS[path])
            if unknown:         # a misspelt field ("overide") was ignored: refused, as the wire protocol does
                self._error(HTTPStatus.BAD_REQUEST, "invalid_request", f"unknown field(s) {', '.join(unknown)}; "
                            f"{path} takes {', '.join(sorted(ACTION_FIELDS[path]))}")
                return
            self._act(action, body)
        except (BrokenPipeError, ConnectionResetError, TimeoutError):      # the error replies' writes too
            self.close_connection = True

    def _act(self, action, body: dict) -> None:
        """Run a POST's action and send its reply: the service's errors and invalid fields as 4xx/5xx JSON."""
        try:
            reply = action(body)
        except TacfError as exc:
            status = next(s for cls, s in _ERROR_STATUS if isinstance(exc, cls))
            self._error(status, getattr(exc, "code", type(exc).__name__), str(exc))
        except (ValueError, TypeError, KeyError) as exc:
            self._error(HTTPStatus.BAD_REQUEST, "invalid_request", str(exc) or type(exc).__name__)
        else:
            self._json(HTTPStatus.OK, reply)

    def _admitted(self) -> bool:
        """Whether dashboard_access lets this request in; if not, the refusal (or the token's login) is sent."""
        access, port = self.server.access, self.server.server_address[1]
        host = self.headers.get("Host")
        if not access.host_allowed(host):
            self._error(HTTPStatus.FORBIDDEN, "host_not_allowed",
                        f"this dashboard does not answer to the host name {host!r} (see tacf dashboard --allow-host)",
                        {"Connection": "close"})
            return False
        url = urlsplit(self.path)
        query = parse_qs(url.query)
        url_token = (query.pop("token", None) or [None])[-1] if self.command in ("GET", "HEAD") else None
        if access.token is not None and url.path in ("/", "/index.html") and access.is_token(url_token):
            # a browser's visit, logged in already or not: keep the token as a cookie, and out of the address bar
            # and history
            rest = urlencode(query, doseq=True)
            self._send(HTTPStatus.SEE_OTHER, b"", None,
                       {"Location": url.path + (f"?{rest}" if rest else ""),
                        "Set-Cookie": access.cookie(port, secure=self.server.tls is not None)})
            return False
        if access.is_token(access.presented(self.headers, port)) or access.is_token(url_token):
            return True                              # the URL's: a program that cannot send headers (VLC on /mjpeg/)
        self._error(HTTPStatus.UNAUTHORIZED, "unauthorized", "open the address tacf dashboard printed (it carries "
                    "?token=...), or send Authorization: Bearer TOKEN",
                    # closed: kept open for the idle timeout, clients without the token held the connection cap
                    {"WWW-Authenticate": 'Bearer realm="tacf dashboard"', "Connection": "close"})
        return False

    # --- actions ----------------------------------------------------------------------------------------------
    def _start(self, body: dict) -> dict:
        info = self.server.dashboard.start(_str(body, "image_key"), _box(body), _seq(body),
                                           sid=_opt_str(body, "sid"), profile=_opt_str(body, "profile"),
                                           overrides=_opt_dict(body, "overrides"), node=_opt_str(body, "node"))
        return json.loads(info.model_dump_json())

    def _stop(self, body: dict) -> dict:
        info = self.server.dashboard.stop(_str(body, "sid"), node=_opt_str(body, "node"))
        return json.loads(info.model_dump_json())

    def _reinit(self, body: dict) -> dict:
        info = self.server.dashboard.reinit(_str(body, "sid"), _box(body), _seq(body), node=_opt_str(body, "node"))
        return json.loads(info.model_dump_json())

    def _watch(self, body: dict) -> dict:
        key = _str(body, "key")
        self.server.dashboard.watch(key)
        return {"key": key, "keys": self.server.dashboard.image_keys()}

    # --- pages ------------------------------------------------------------------------------------------------
    def _static(self, name: str) -> None:
        root = self.server.static.resolve()
        try:
            target = (root / unquote(name)).resolve()
            found = root in target.parents and target.is_file()
        except (ValueError, OSError):              # a NUL byte, a name too long for the file system
            found = False
        if not found:
            self._error(HTTPStatus.NOT_FOUND, "not_found", f"no such file: {name}")
            return
        body = target.read_bytes()
        ctype = mimetypes.guess_type(target.name)[0] or "application/octet-stream"
        if ctype.startswith("text/") or ctype in ("application/javascript", "text/javascript"):
            ctype += "; charset=utf-8"
        self._send(HTTPStatus.OK, body, ctype, {"Cache-Control": "no-cache"})

    def _frame(self, key: str, query: dict[str, list[str]]) -> None:
        seq = query.get("seq", [None])[0]
        if seq is not None and not (seq.isascii() and seq.isdigit() and len(seq) <= MAX_SEQ_DIGITS):
            self._error(HTTPStatus.BAD_REQUEST, "invalid_request", "seq: expected a frame seq")
            return
        try:
            snap = self.server.dashboard.frame(key, None if seq is None else int(seq))
        except ValueError as exc:                  # FrameError: the camera sends frames that are no images
            self._error(HTTPStatus.BAD_GATEWAY, "bad_frame", f"the newest frame on {key!r} cannot be shown: {exc}")
            return
        if snap is None:
            watched = key in self.server.dashboard.image_keys()
            self._error(HTTPStatus.NOT_FOUND, "no_frame",
                        f"no frame yet on {key!r}" if watched else f"{key!r} is not watched: POST /api/watch")
            return
        etag = f'"{snap.seq}-{snap.received_ns}"'
        headers = {"ETag": etag, "Cache-Control": "no-cache", "X-Seq": str(snap.seq),
                   "X-Stamp-Ns": str(snap.stamp_ns), "X-Width": str(snap.width), "X-Height": str(snap.height)}
        if self.headers.get("If-None-Match") == etag:
            self._send(HTTPStatus.NOT_MODIFIED, b"", None, headers)
            return
        self._send(HTTPStatus.OK, snap.jpeg, "image/jpeg", headers)

    def _mjpeg(self, key: str) -> None:
        dashboard = self.server.dashboard
        if key not in dashboard.image_keys():
            self._error(HTTPStatus.NOT_FOUND, "not_watched", f"{key!r} is not watched: POST /api/watch")
            return
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=tacfframe")
        self.send_header("Cache-Control", "no-cache")
        self.send_header("Connection", "close")
        self.end_headers()
        self.close_connection = True
        last = None
        while not self._ending():
            if key not in dashboard.image_keys():
                return                             # its last session stopped: the stream ends, not freezes
            try:
                snap = dashboard.frame(key)
            except ValueError:                     # FrameError: a frame that is no image is left out
                snap = None
            if snap is not None and (snap.seq, snap.received_ns) != last:
                last = (snap.seq, snap.received_ns)
                self.wfile.write(b"--tacfframe\r\nContent-Type: image/jpeg\r\nContent-Length: "
                                 + str(len(snap.jpeg)).encode() + b"\r\nX-Seq: " + str(snap.seq).encode()
                                 + b"\r\n\r\n" + snap.jpeg + b"\r\n")
                self.wfile.flush()
            if self._client_left(1.0 / MJPEG_FPS):     # seen here, not by a write, while no new frame comes
                return

    def _events(self) -> None:
        """One SSE stream per browser: `state` once, then `update` events with what changed, at most
        events_hz a second; a comment line as keep-alive."""
        dashboard = self.server.dashboard
        self.send_response(HTTPStatus.OK)
        self.send_header("Content-Type", "text/event-stream; charset=utf-8")
        self.send_header("Cache-Control", "no-cache")
        self.send_header("Connection", "close")
        self.send_header("X-Accel-Buffering", "no")
        self.end_headers()
        self.close_connection = True
        self.server.count_client(+1)
        try:
            period = 1.0 / self.server.events_hz
            sent = dashboard.versions()        # before the snapshot: a change in between is sent twice, never lost
            snapshot = dashboard.snapshot()
            sent_keys, sent_nodes = snapshot["keys"], snapshot["nodes"]
            self._sse("state", snapshot, retry_ms=2000)
            last_write = time.monotonic()
            next_tick = time.monotonic() + period
            while not self._ending():
                dashboard.wait_changed(timeout=min(1.0, KEEPALIVE_S))
                # a browser gone is seen here: with nothing to send, a write fails only at the second keep-alive
                if self._client_left(0.0):
                    break
                delay = next_tick - time.monotonic()
                if delay > 0 and self.server.stopping.wait(delay) or self._ending():       # the rate cap
                    break               # a closing dashboard's empty key list is no news: it had the page drop its key
                next_tick = time.monotonic() + period
                versions = dashboard.versions()
                changed = [k for k, v in versions.items() if sent.get(k) != v]
                # a session replaced by another with the same id (a new generation): removed, then added whole
                replaced = [k for k in changed if k in sent and sent[k][2] != versions[k][2]]
                removed = [k for k in sent if k not in versions] + replaced
                keys, nodes = dashboard.image_keys(), dashboard.nodes()
                if changed or removed or keys != sent_keys or nodes != sent_nodes:
                    sessions, points = dashboard.sessions_json(
                        changed, {k: sent[k][1] for k in changed if k in sent and k not in replaced})
                    self._sse("update", {"t": time.time_ns() // 1_000_000, "sessions": sessions,
                                         "points": points, "removed": removed, "keys": keys, "nodes": nodes})
                    sent, sent_keys, sent_nodes, last_write = versions, keys, nodes, time.monotonic()
                elif time.monotonic() - last_write > KEEPALIVE_S:
                    self.wfile.write(b": keep-alive\n\n")
                    self.wfile.flush()
                    last_write = time.monotonic()
        finally:
            self.server.count_client(-1)

    def _ending(self) -> bool:
        return self.server.stopping.is_set() or self.server.dashboard.closed.is_set()

    def _client_left(self, timeout: float) -> bool:
        """Whether the client of a stream (/events, /mjpeg) closed its end, waiting up to `timeout` s to see it. It
        never sends more (Connection: close), so anything readable is its end (b"") or bytes that nobody will read."""
        with selectors.DefaultSelector() as selector:      # not select(): it refuses descriptors over 1023
            selector.register(self.connection, selectors.EVENT_READ)
            readable = bool(selector.select(timeout))
        return readable and not self.connection.recv(4096)

    def _sse(self, event: str, data: dict, retry_ms: int | None = None) -> None:
        text = (f"retry: {retry_ms}\n" if retry_ms else "") + f"event: {event}\ndata: {json.dumps(data)}\n\n"
        self.wfile.write(text.encode())
        self.wfile.flush()

    def _metrics(self) -> None:
        dashboard = self.server.dashboard
        ok, _ = dashboard.healthy()
        body = dashboard_metrics.render(dashboard.session_views(), frame_counts=dashboard.frame_counts(),
                                        nodes=dashboard.nodes(), event_clients=self.server.event_clients,
                                        connections_refused=self.server.connections_refused, up=ok)
        self._send(HTTPStatus.OK, body.encode(), dashboard_metrics.CONTENT_TYPE, {"Cache-Control": "no-cache"})

    def _healthz(self) -> None:
        dashboard = self.server.dashboard
        ok, reason = dashboard.healthy()
        body = {"status": "ok" if ok else "unavailable", "reason": reason, "services": sorted(dashboard.nodes()),
                "sessions": len(dashboard.versions()), "image_keys": dashboard.image_keys(),
                "list_error": dashboard.list_error}
        self._json(HTTPStatus.OK if ok else HTTPStatus.SERVICE_UNAVAILABLE, body)

    # --- plumbing ---------------------------------------------------------------------------------------------
    def _read_json(self) -> dict | None:
        ctype = (self.headers.get("Content-Type") or "").split(";")[0].strip().lower()
        if ctype != "application/json":
            self._error(HTTPStatus.UNSUPPORTED_MEDIA_TYPE, "invalid_request", "send Content-Type: application/json")
            return None
        length = body_length(self.headers)
        if length is None or self.headers.get("Transfer-Encoding") is not None:
            # where the body ends is read another way by a proxy in front: the rest would be a request of its own
            self._error(HTTPStatus.BAD_REQUEST, "invalid_request", "send the body with one Content-Length of digits "
                        "and no Transfer-Encoding")
            return None
        # the body too must come whole within head_timeout_s: the socket timeout restarts on every byte, and a body
        # sent a byte every few seconds held the connection's thread for good
        self.server.expect_head(self.connection, True)
        try:
            if length > MAX_BODY:
                self._discard(min(length, MAX_DRAINED))
            data = self.rfile.read(length) if 0 < length <= MAX_BODY else b""
        finally:
            self.server.expect_head(self.connection, False)
        if not 0 < length <= MAX_BODY:
            self._error(HTTPStatus.REQUEST_ENTITY_TOO_LARGE if length > MAX_BODY else HTTPStatus.BAD_REQUEST,
                        "invalid_request", f"a JSON body of 1 to {MAX_BODY} bytes is needed")
            return None
        if len(data) < length:                     # the client gave up (or was cut): not the request it meant
            return None
        try:
            body = json.loads(data, object_pairs_hook=unique_keys)
        except RepeatedKeyError as exc:                  # json would keep the last value and drop the first unseen
            self._error(HTTPStatus.BAD_REQUEST, "invalid_request", f"{exc}: give each field once")
            return None
        except (ValueError, RecursionError) as exc:      # also a 5000-digit number, and [[[[... too deep
            self._error(HTTPStatus.BAD_REQUEST, "invalid_request", f"not JSON: {exc}")
            return None
        if not isinstance(body, dict):
            self._error(HTTPStatus.BAD_REQUEST, "invalid_request", "expected a JSON object")
            return None
        return body

    def _discard(self, length: int) -> None:
        """Read and drop `length` bytes of the request (fewer if the client stops sending first)."""
        while length > 0 and (chunk := self.rfile.read(min(length, 65536))):
            length -= len(chunk)

    def _json(self, status: HTTPStatus, body: dict, headers: dict[str, str] | None = None) -> None:
        self._send(status, json.dumps(body).encode(), "application/json",
                   {"Cache-Control": "no-cache", **(headers or {})})

    def _error(self, status: HTTPStatus, code: str, message: str, headers: dict[str, str] | None = None) -> None:
        self._json(status, {"error": code, "message": message}, headers)

    def _send(self, status: HTTPStatus, body: bytes, ctype: str | None, headers: dict[str, str]) -> None:
        self.send_response(status)
        if ctype:
            self.send_header("Content-Type", ctype)
        for name, value in headers.items():
            self.send_header(name, value)
        self.send_header("X-Content-Type-Options", "nosniff")
        # no other site may show the page in a frame, with a decoy over its Stop button (clickjacking)
        self.send_header("X-Frame-Options", "DENY")
        self.send_header("Content-Security-Policy", "frame-ancestors 'none'")
        if status != HTTPStatus.NOT_MODIFIED:
            self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        if body and self.command != "HEAD":    # a body after a HEAD reply would be read as the next reply
            self.wfile.write(body)


class HeadTooLarge(Exception):
    """A request's line and headers passed MAX_HEAD bytes."""


class _HeadBudget:
    """The connection's rfile as http.client.parse_headers reads it (line by line), up to `left` bytes: the lines
    read are kept until the blank line ends them."""

    def __init__(self, rfile, left: int):
        self.rfile, self.left = rfile, left

    def readline(self, limit: int) -> bytes:
        line = self.rfile.readline(min(limit, self.left + 1))
        self.left -= len(line)
        if self.left < 0:
            raise HeadTooLarge
        return line


# --- request fields ------------------------------------------------------------------------------------------------
def body_length(headers) -> int | None:
    """A request's Content-Length as RFC 9112 has it, 0 when there is none; None when it is not ASCII digits, or is
    given twice with different values. int() also took `+5`, `1_0` and other digits than ASCII's, which a proxy in
    front may read otherwise (or not at all), as it may pick another of two values."""
    values = {value.strip() for value in headers.get_all("Content-Length") or ()}
    if not values:
        return 0
    value = values.pop()
    if values or not (value.isascii() and value.isdigit()):
        return None
    return int(value) if len(value) <= 18 else 10 ** 18     # int() refuses over 4300 digits; any such is too long


def _str(body: dict, name: str) -> str:
    value = body.get(name)
    if not isinstance(value, str) or not value:
        raise ValueError(f"{name!r}: a non-empty string is needed")
    return value


def _opt_str(body: dict, name: str) -> str | None:
    value = body.get(name)
    if value in (None, ""):
        return None
    if not isinstance(value, str):
        raise ValueError(f"{name!r}: expected a string")
    return value


def _opt_dict(body: dict, name: str) -> dict | None:
    value = body.get(name)
    if value is not None and not isinstance(value, dict):
        raise ValueError(f"{name!r}: expected a JSON object")
    return value


def _box(body: dict) -> tuple[float, float, float, float]:
    box = body.get("box")
    if not isinstance(box, list) or len(box) != 4 or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                             for v in box):
        raise ValueError("'box': expected [x, y, w, h] numbers")
    try:
        return tuple(float(v) for v in box)  # type: ignore[return-value]
    except OverflowError:                          # a JSON integer of hundreds of digits
        raise ValueError("'box': a number too large") from None


def _seq(body: dict) -> int | None:
    seq = body.get("seq")
    if seq is None:
        return None
    try:
        return SEQ.validate_python(seq, strict=True)      # as the wire takes it: 5.0 is 5, true is no seq
    except pydantic.ValidationError:
        raise ValueError("'seq': expected a frame seq (integer >= 0 and < 2**63)") from None


# --- running it ----------------------------------------------------------------------------------------------------
class DashboardApp:
    """A Dashboard plus its HTTP server on a thread: `with DashboardApp(options, port=0) as app: app.url`."""

    def __init__(self, options=None, *, host: str = "127.0.0.1", port: int = DEFAULT_PORT, session=None,
                 image_keys=(), node: str | None = None, history_s: float = 300.0, events_hz: float = EVENTS_HZ,
                 access: DashboardAccess | None = None, tls: ssl.SSLContext | None = None):
        self.dashboard = Dashboard(options, session=session, image_keys=image_keys, node=node, history_s=history_s)
        try:
            self.server = DashboardServer((host, port), self.dashboard, events_hz=events_hz, access=access, tls=tls)
        except Exception:
            self.dashboard.close()
            raise
        self._thread = threading.Thread(target=self.server.serve_forever, kwargs={"poll_interval": 0.2},
                                        name="tacf-dashboard-http", daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        return self.server.url

    def close(self) -> None:
        self.server.stop()
        self._thread.join(timeout=5)
        self.dashboard.close()

    def __enter__(self) -> "DashboardApp":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def serve(options=None, *, host: str = "127.0.0.1", port: int = DEFAULT_PORT, image_keys=(), node: str | None = None,
          history_s: float = 300.0, access: DashboardAccess | None = None, tls: ssl.SSLContext | None = None,
          stop: threading.Event, on_ready=None) -> int:
    """Run the dashboard until `stop` is set (tacf dashboard). on_ready(url) is called once it serves."""
    with DashboardApp(options, host=host, port=port, image_keys=image_keys, node=node, history_s=history_s,
                      access=access, tls=tls) as app:
        if on_ready is not None:
            on_ready(app.url)
        while not stop.wait(0.5):
            pass
    return 0
