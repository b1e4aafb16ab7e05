"""The relay in front of foxglove-sdk's server on its own, against a real WebSocket server that stands in for the
SDK's (tests/test_foxglove.py runs it in front of the real one): names, messages both ways, and shutting down with
a viewer that has stopped reading."""
from __future__ import annotations

import asyncio
import threading
import time
from contextlib import contextmanager

import pytest

pytest.importorskip("websockets", reason="pip install -e '.[test]' installs websockets")
from websockets.asyncio.server import serve  # noqa: E402
from websockets.exceptions import ConnectionClosed, InvalidStatus  # noqa: E402
from websockets.sync.client import connect  # noqa: E402

from tacf_clients.foxglove_relay import SubprotocolRelay  # noqa: E402

BLOCK = bytes(256 * 1024)


@contextmanager
def upstream_server(flood: bool):
    """A WebSocket server on a free loopback port that speaks foxglove.sdk.v1 only: it echoes what it gets, and
    with `flood` also sends 256 KB messages as fast as the connection takes them. Yields its port."""
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()

    async def handler(connection):
        if flood:
            while True:
                await connection.send(BLOCK)
        async for message in connection:
            await connection.send(message)

    async def start():
        return await serve(handler, "127.0.0.1", 0, subprotocols=["foxglove.sdk.v1"], compression=None)

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
    with upstream_server(flood=True) as upstream_port:
        relay = SubprotocolRelay(upstream_port, host="127.0.0.1", port=0)
        try:
            with connect(f"ws://127.0.0.1:{relay.port}", subprotocols=["foxglove.websocket.v1"], open_timeout=5,
                         max_size=None) as stalled:
                assert stalled.recv(timeout=5) == BLOCK
                with connect(f"ws://127.0.0.1:{relay.port}", subprotocols=["foxglove.sdk.v1"], open_timeout=5,
                             max_size=None) as reader:                      # another viewer is served meanwhile
                    assert all(reader.recv(timeout=5) == BLOCK for _ in range(20))
                time.sleep(1.0)                                             # the stalled pipe fills up
                started = time.monotonic()
                relay.close()
                assert time.monotonic() - started < 5, "close() does not wait on a viewer that reads nothing"
                with pytest.raises(ConnectionClosed):
                    while True:
                        stalled.recv(timeout=5)
        finally:
            relay.close()
