"""The relay in front of foxglove-sdk's server on its own, against a real WebSocket server that stands in for the
SDK's (tests/test_foxglove.py runs it in front of the real one): names, messages both ways, the web pages it lets
in, and shutting down with a viewer that has stopped reading or a connection that never finished its handshake."""
from __future__ import annotations

import asyncio
import socket
import threading
import time
from collections import Counter
from contextlib import contextmanager

import pytest

pytest.importorskip("websockets", reason="pip install -e '.[test]' installs websockets")
from websockets.asyncio.server import serve  # noqa: E402
from websockets.exceptions import ConnectionClosed, InvalidStatus  # noqa: E402
from websockets.sync.client import connect  # noqa: E402

from tacf_clients.foxglove_relay import SubprotocolRelay, origin_allowed  # noqa: E402

BLOCK = bytes(256 * 1024)
FLOOD_BLOCKS = 400          # 100 MB: what a flood costs a relay that reads ahead without bound, not all memory


@contextmanager
def upstream_server(flood: bool, closes: list | None = None, sent: list | None = None):
    """A WebSocket server on a free loopback port that speaks foxglove.sdk.v1 only: it echoes what it gets, and
    with `flood` first sends FLOOD_BLOCKS messages of 256 KB as fast as the connection takes them, appending the
    connection's id to `sent` for each. Told "close CODE REASON" it closes with them, told "drop" it drops the TCP
    connection without a close frame (a crash); the close code and reason each connection got are appended to
    `closes`. Yields its port."""
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()

    async def handler(connection):
        try:
            for _ in range(FLOOD_BLOCKS if flood else 0):
                await connection.send(BLOCK)
                if sent is not None:
                    sent.append(connection.id)
            async for message in connection:
                if message == "drop":
                    connection.transport.abort()
                elif isinstance(message, str) and message.startswith("close "):
                    _, code, reason = message.split(" ", 2)
                    await connection.close(int(code), reason)
                else:
                    await connection.send(message)
        except ConnectionClosed:
            pass
        finally:
            if closes is not None:
                closes.append((connection.protocol.close_code, connection.protocol.close_reason))

    async def start():
        return await serve(handler, "127.0.0.1", 0, subprotocols=["foxglove.sdk.v1"], compression=None,
                           max_size=None)       # as the SDK's server, whose limit is larger than the relay's

    server = asyncio.run_coroutine_threadsafe(start(), loop).result(timeout=5)
    try:
        yield server.sockets[0].getsockname()[1]
    finally:
        server.close()
        asyncio.run_coroutine_threadsafe(server.wait_closed(), loop).result(timeout=10)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(timeout=5)


def test_either_name_is_accepted_and_messages_pass_unchanged_both_ways():
    with upstream_server(flood=False) as upstream_port:
        relay = SubprotocolRelay(upstream_port, host="127.0.0.1", port=0)
        try:
            for name in ("foxglove.websocket.v1", "foxglove.sdk.v1"):
                with connect(f"ws://127.0.0.1:{relay.port}", subprotocols=[name], open_timeout=5) as ws:
                    assert ws.subprotocol == name
                    ws.send('{"op": "subscribe"}')
                    assert ws.recv(timeout=5) == '{"op": "subscribe"}'      # text stays text
                    ws.send(b"\x02binary")
                    assert ws.recv(timeout=5) == b"\x02binary"              # binary stays binary
            with pytest.raises(InvalidStatus):                              # neither name: refused
                with connect(f"ws://127.0.0.1:{relay.port}", subprotocols=["other"], open_timeout=5):
                    pass
        finally:
            relay.close()


def test_a_viewer_that_stopped_reading_holds_up_neither_the_relay_nor_its_shutdown():
    sent: list = []
    with upstream_server(flood=True, sent=sent) as upstream_port:
        relay = SubprotocolRelay(upstream_port, host="127.0.0.1", port=0)
        try:
            with connect(f"ws://127.0.0.1:{relay.port}", subprotocols=["foxglove.websocket.v1"], open_timeout=5,
                         max_size=None) as stalled:
                assert stalled.recv(timeout=5) == BLOCK
                with connect(f"ws://127.0.0.1:{relay.port}", subprotocols=["foxglove.sdk.v1"], open_timeout=5,
                             max_size=None) as reader:                      # another viewer is served meanwhile
                    assert all(reader.recv(timeout=5) == BLOCK for _ in range(20))
                time.sleep(1.0)                                             # the stalled pipe fills up
                # and the server is held up too, rather than the relay reading on into its memory (measured: 61
                # blocks in the socket buffers and queues; without a bound the relay took all 400 at once)
                blocks = Counter(sent)
                assert max(blocks.values()) < FLOOD_BLOCKS / 2, blocks
                time.sleep(0.5)
                assert Counter(sent) == blocks
                started = time.monotonic()
                relay.close()
                assert time.monotonic() - started < 5, "close() does not wait on a viewer that reads nothing"
                with pytest.raises(ConnectionClosed):
                    while True:
                        stalled.recv(timeout=5)
        finally:
            relay.close()


@pytest.mark.parametrize("origin, allowed", [
    (None, True),                                   # a program (the SDKs, Node.js): browsers always send one
    ("http://127.0.0.1:8080", True), ("http://localhost:3000", True), ("https://[::1]", True),
    ("https://app.foxglove.dev", True),             # Foxglove's web app, connecting to ws://127.0.0.1:8765
    ("file://", True), ("app://lichtblick", True),  # desktop apps: no web page sends these
    ("https://evil.example", False), ("http://127.0.0.1.evil.example", False), ("http://localhost.evil.example", False),
    ("http://10.0.0.2:8080", False),                # a Lichtblick served elsewhere: only with --allow-origin
    ("null", False),                                # any site's sandboxed frame
])
def test_which_web_pages_are_let_in(origin, allowed):
    assert origin_allowed(origin) is allowed
    assert origin_allowed(origin, ["*"])
    assert origin_allowed(origin, [origin]) if origin else True


def test_another_web_site_in_the_operators_browser_is_refused():
    """Any page a browser shows may open a WebSocket to 127.0.0.1: it used to be let in, and could watch the
    cameras and stop the sessions (the dashboard refuses such pages; the relay did not)."""
    with upstream_server(flood=False) as upstream_port:
        relay = SubprotocolRelay(upstream_port, host="127.0.0.1", port=0, allow_origins=["http://10.0.0.2:8080"])
        url = f"ws://127.0.0.1:{relay.port}"
        try:
            for headers in ({}, {"Host": "evil.example:8765"}):              # the second: after DNS rebinding
                with pytest.raises(InvalidStatus, match="403"):
                    with connect(url, subprotocols=["foxglove.websocket.v1"], origin="https://evil.example",
                                 additional_headers=headers, open_timeout=5):
                        pass
            for origin in ("http://localhost:5173", "http://10.0.0.2:8080", None):
                with connect(url, subprotocols=["foxglove.websocket.v1"], origin=origin, open_timeout=5) as ws:
                    ws.send("hello")
                    assert ws.recv(timeout=5) == "hello"
        finally:
            relay.close()


def test_a_viewer_s_message_over_the_limit_ends_its_connection_and_never_reaches_the_server():
    """Viewers send subscriptions and service calls, all small: a bigger message (the relay would hold it whole in
    memory, and the SDK's server after it) closes the connection with 1009, message too big: the server's echo
    of it never comes."""
    from tacf_clients.foxglove_relay import MAX_CLIENT_MESSAGE

    closes: list = []
    with upstream_server(flood=False, closes=closes) as upstream_port:
        relay = SubprotocolRelay(upstream_port, host="127.0.0.1", port=0)
        try:
            with connect(f"ws://127.0.0.1:{relay.port}", subprotocols=["foxglove.sdk.v1"], open_timeout=5,
                         max_size=None) as ws:                              # the server's echo would be taken
                ws.send(bytes(MAX_CLIENT_MESSAGE + 1))
                with pytest.raises(ConnectionClosed):
                    ws.recv(timeout=5)
                assert ws.protocol.close_code == 1009
            assert wait_for(lambda: closes), "the server's side was closed"
            assert closes[0][0] == 1009, closes        # the reason, not "connection lost"
        finally:
            relay.close()


def test_a_connection_that_never_finished_its_handshake_does_not_hold_up_the_shutdown():
    """A port scan, a TCP health check or a half-sent request: the server waited out the handshake's 10 s on
    close (and the bridge's close, given 10 s, failed before finishing its recording)."""
    with upstream_server(flood=False) as upstream_port:
        relay = SubprotocolRelay(upstream_port, host="127.0.0.1", port=0)
        try:
            idle = socket.create_connection(("127.0.0.1", relay.port))
            half = socket.create_connection(("127.0.0.1", relay.port))
            half.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n")
            time.sleep(0.3)
            started = time.monotonic()
            relay.close()
            assert time.monotonic() - started < 3
            for sock in (idle, half):
                sock.settimeout(5)
                try:
                    assert sock.recv(1) == b"", "the connection was dropped"
                except ConnectionResetError:
                    pass                                                    # dropped with a reset: as good
                sock.close()
        finally:
            relay.close()


def wait_for(condition, timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.02)
    return condition()


@pytest.mark.parametrize("how, code, reason", [
    ("close 4002 session limit reached", 4002, "session limit reached"),  # an application's own code
    ("close 1011 internal error", 1011, "internal error"),
    ("drop", 1001, "connection lost"),      # no close frame (1006): may not be sent on, the peer went away
])
def test_the_servers_close_code_and_reason_reach_the_viewer(how, code, reason):
    """The relay used to close the viewer's side with 1000 whatever the SDK's server closed with: a viewer could not
    tell a refusal or a server error from a normal end."""
    with upstream_server(flood=False) as upstream_port:
        relay = SubprotocolRelay(upstream_port, host="127.0.0.1", port=0)
        try:
            with connect(f"ws://127.0.0.1:{relay.port}", subprotocols=["foxglove.websocket.v1"],
                         open_timeout=5) as ws:
                ws.send(how)
                with pytest.raises(ConnectionClosed):
                    ws.recv(timeout=5)
                assert (ws.protocol.close_code, ws.protocol.close_reason) == (code, reason)
        finally:
            relay.close()


@pytest.mark.parametrize("close, code, reason", [
    ((4001, "viewer closed the layout"), 4001, "viewer closed the layout"),
    ((1001, ""), 1001, ""),                  # a browser tab that navigates away
    ((None, ""), 1000, ""),                  # a close frame with no code (1005): may not be sent on; a normal end
    ("drop", 1001, "connection lost"),       # no close frame (1006)
])
def test_the_viewers_close_code_and_reason_reach_the_server(close, code, reason):
    closes: list = []
    with upstream_server(flood=False, closes=closes) as upstream_port:
        relay = SubprotocolRelay(upstream_port, host="127.0.0.1", port=0)
        try:
            with connect(f"ws://127.0.0.1:{relay.port}", subprotocols=["foxglove.sdk.v1"], open_timeout=5) as ws:
                ws.send("hello")
                assert ws.recv(timeout=5) == "hello"                        # relayed: the upstream side is open
                if close == "drop":
                    ws.socket.shutdown(socket.SHUT_RDWR)
                else:
                    ws.close(*close)
                assert wait_for(lambda: closes), "the server's side was closed"
            assert closes == [(code, reason)]
        finally:
            relay.close()
