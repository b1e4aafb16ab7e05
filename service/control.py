"""The control queryable tacf/<node>/control/<op>.

One queryable on tacf/<node>/control/* (so `tacf/*/control/list` reaches every service) feeds a FIFO channel;
a few threads take queries from it and answer each inside `with query:`. Replies go out on the concrete key
tacf/<node>/control/<op> as the op's reply model; every failure is reply_err(Error) with a code, never an
exception escaping into Zenoh.
"""
from __future__ import annotations

import logging
import threading
import time

from tacf_schemas import (CONTROL_OPS, CONTROL_REQUESTS, MSGPACK_ENCODING, DecodeError, Error, ListRequest,
                          ReinitRequest, StartRequest, StatusRequest, StopRequest, control_key, decode, encode)

from .errors import ServiceError
from .manager import SessionManager

log = logging.getLogger(__name__)

CONTROL_THREADS = 4
QUERY_QUEUE = 64
_EMPTY_MAP = b"\x80"        # msgpack {}: a query without payload is a request with default fields


class ControlServer:
    def __init__(self, zenoh_session, node: str, manager: SessionManager, threads: int = CONTROL_THREADS):
        import zenoh
        self.node = node
        self._manager = manager
        self._encoding = zenoh.Encoding(MSGPACK_ENCODING)
        self._queryable = zenoh_session.declare_queryable(control_key(node, "*"),
                                                          zenoh.handlers.FifoChannel(QUERY_QUEUE))
        self._threads = [threading.Thread(target=self._serve, name=f"control-{i}") for i in range(threads)]
        for thread in self._threads:
            thread.start()

    def close(self, timeout: float = 1.0) -> None:
        """Undeclare the queryable (ends the serving loops) and join the threads within `timeout` in total."""
        try:
            self._queryable.undeclare()
        except Exception:
            pass
        deadline = time.monotonic() + timeout
        for thread in self._threads:
            thread.join(timeout=max(0.0, deadline - time.monotonic()))

    def _serve(self) -> None:
        import zenoh
        channel = self._queryable.handler      # recv() on the queryable itself cannot run in several threads
        while True:
            try:
                query = channel.recv()
            except zenoh.ZError:
                return                  # undeclared or session closed
            with query:
                try:
                    self._answer(query)
                except Exception:
                    log.exception("control query %s failed", query.selector)
                    self._reply_err(query, Error(code="internal", message="internal error", node=self.node))

    def _answer(self, query) -> None:
        op = str(query.key_expr).rsplit("/", 1)[-1]
        if op not in CONTROL_OPS:
            self._reply_err(query, Error(code="unknown_op", node=self.node,
                                         message=f"unknown control op {op[:64]!r}; use one of "
                                                 f"{', '.join(CONTROL_OPS)}"))
            return
        payload = query.payload.to_bytes() if query.payload is not None else _EMPTY_MAP
        try:
            request = decode(payload or _EMPTY_MAP, CONTROL_REQUESTS[op])
        except DecodeError as exc:
            self._reply_err(query, Error(code="invalid_request", message=exc.message[:1024], node=self.node))
            return
        try:
            reply = self._dispatch(op, request)
        except ServiceError as exc:
            log.info("control %s refused: %s: %s", op, exc.code, exc.message)
            self._reply_err(query, exc.to_error(self.node))
            return
        query.reply(control_key(self.node, op), encode(reply), encoding=self._encoding)

    def _dispatch(self, op: str, request):
        manager = self._manager
        if op == "start":
            assert isinstance(request, StartRequest)
            return manager.start(request)
        if op == "stop":
            assert isinstance(request, StopRequest)
            return manager.stop(request.sid)
        if op == "reinit":
            assert isinstance(request, ReinitRequest)
            return manager.reinit(request)
        if op == "status":
            assert isinstance(request, StatusRequest)
            return manager.status(request.sid)
        assert isinstance(request, ListRequest)
        return manager.list()

    def _reply_err(self, query, error: Error) -> None:
        try:
            query.reply_err(encode(error), encoding=self._encoding)
        except Exception as exc:
            log.debug("reply_err failed: %s", exc)
