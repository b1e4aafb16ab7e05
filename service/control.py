"""The control queryable tacf/<node>/control/<op>.

One queryable on tacf/<node>/control/* (so `tacf/*/control/list` reaches every service). Its callback only admits
a query into one of two bounded lanes, never blocking: a full Zenoh FIFO handler would stall Zenoh's RX task for
the query's link (ZENOH.md §3.4), and over a router that link carries every client, frames and liveliness alike.
start/stop/reinit (up to seconds each) go to a lane served by CONTROL_THREADS threads, status/list and anything
else to a lane of their own, so that a flood of slow queries delays no status. A lane is full at QUERY_QUEUE queries
waiting, or when a query's payload would take the bytes it holds, waiting or being answered, past what its threads
could answer at once, each a query of the wire's largest size (a start may carry frames: 64 starts of 48 MiB each
waiting took 3.2 GB). A query that finds its lane full is answered at once with Error "unavailable" (busy; retry),
one larger than the wire allows with "invalid_request". Each query is answered inside `with query:`. Replies go
out on the concrete key tacf/<node>/control/<op> as the op's reply model; every failure is reply_err(Error) with a
code, never an exception escaping into Zenoh.
"""
from __future__ import annotations

import logging
import queue
import threading
import time

from tacf_schemas import (CONTROL_OPS, CONTROL_REQUESTS, MSGPACK_ENCODING, DecodeError, Error, ListRequest,
                          ReinitRequest, StartRequest, StatusRequest, StopRequest, control_key, decode, encode)
from tacf_schemas.limits import MAX_PAYLOAD_BYTES

from .errors import ServiceError
from .manager import SessionManager

log = logging.getLogger(__name__)

CONTROL_THREADS = 4        # serve the slow lane
QUICK_THREADS = 1          # serve the quick lane
QUERY_QUEUE = 64           # queries waiting in one lane; more are refused as busy
SLOW_OPS = frozenset({"start", "stop", "reinit"})
_EMPTY_MAP = b"\x80"        # msgpack {}: a query without payload is a request with default fields


class _Lane:
    """The queries waiting for a lane's threads, and the payload bytes of those the lane holds, waiting or being
    answered (the control server's admission lock guards `held`)."""

    def __init__(self, threads: int):
        self.queries: queue.Queue = queue.Queue()
        self.budget = threads * MAX_PAYLOAD_BYTES       # each thread may be answering a query of the largest size
        self.held = 0


class ControlServer:
    def __init__(self, zenoh_session, node: str, manager: SessionManager):
        import zenoh
        self.node = node
        self._manager = manager
        self._encoding = zenoh.Encoding(MSGPACK_ENCODING)
        # Unbounded queues: _admit bounds them (within a query or two when callbacks of several links race), so
        # that close() can always queue the end markers.
        self._slow = _Lane(CONTROL_THREADS)
        self._quick = _Lane(QUICK_THREADS)
        # A query admitted after the end markers would wait behind them unanswered: admitting and closing take
        # turns, and a closed server refuses at once.
        self._admission = threading.Lock()
        self._closed = False
        # Declared before the threads start (queries admitted meanwhile wait in their lane): a declaration that
        # fails leaves no thread behind to keep the process alive.
        self._queryable = zenoh_session.declare_queryable(control_key(node, "*"), self._admit)
        lanes = [(self._slow, f"control-{i}") for i in range(CONTROL_THREADS)]
        lanes += [(self._quick, f"control-quick-{i}") for i in range(QUICK_THREADS)]
        # Daemons: close() gives them `timeout` to finish; one stuck past it (a start waiting on a fork server that
        # hangs) must not keep the process alive after the service has closed.
        self._threads = [(lane, threading.Thread(target=self._serve, args=(lane,), name=name, daemon=True))
                         for lane, name in lanes]
        for _, thread in self._threads:
            thread.start()

    def close(self, timeout: float = 1.0) -> list[threading.Thread]:
        """Undeclare the queryable, let the threads answer what is queued and end, joining them within `timeout`
        in total. Returns those still answering, left behind."""
        try:
            self._queryable.undeclare()
        except Exception:
            pass
        with self._admission:
            self._closed = True
            for lane, _ in self._threads:
                lane.queries.put(None)
        deadline = time.monotonic() + timeout
        for _, thread in self._threads:
            thread.join(timeout=max(0.0, deadline - time.monotonic()))
        stuck = [thread for _, thread in self._threads if thread.is_alive()]
        if stuck:
            log.warning("control queries still being answered after %.1f s (%s): left behind", timeout,
                        ", ".join(thread.name for thread in stuck))
        return stuck

    def _admit(self, query) -> None:
        """On Zenoh's callback thread: queue the query in its lane, or refuse it at once when the lane is full."""
        op = str(query.key_expr).rsplit("/", 1)[-1]
        lane = self._slow if op in SLOW_OPS else self._quick
        size = len(query.payload) if query.payload is not None else 0
        with self._admission:
            closed, waiting, held = self._closed, lane.queries.qsize(), lane.held
            if not closed and size <= MAX_PAYLOAD_BYTES and waiting < QUERY_QUEUE and held + size <= lane.budget:
                lane.queries.put((query, size))
                lane.held += size
                return
        if closed:
            error = Error(code="unavailable", node=self.node, message=f"node {self.node!r} is shutting down")
        elif size > MAX_PAYLOAD_BYTES:          # decode refuses it: never held, and never "busy; retry"
            error = Error(code="invalid_request", node=self.node,
                          message=f"payload of {size} bytes exceeds {MAX_PAYLOAD_BYTES}")
        else:
            error = Error(code="unavailable", node=self.node,
                          message=f"node {self.node!r} is busy, {waiting} control queries waiting, "
                                  f"{held / 2**20:.0f} MiB of payload held; retry")
        with query:
            self._reply_err(query, error)

    def _serve(self, lane: _Lane) -> None:
        while True:
            item = lane.queries.get()
            if item is None:
                return                  # closed
            query, size = item
            with query:
                try:
                    self._answer(query)
                except Exception:
                    log.exception("control query %s failed", query.selector)
                    self._reply_err(query, Error(code="internal", message="internal error", node=self.node))
            with self._admission:
                lane.held -= size

    def _answer(self, query) -> None:
        op = str(query.key_expr).rsplit("/", 1)[-1]
        if op not in CONTROL_OPS:
            self._reply_err(query, Error(code="unknown_op", node=self.node,
                                         message=f"unknown control op {op[:64]!r}; use one of "
                                                 f"{', '.join(CONTROL_OPS)}"))
            return
        if op == "start" and str(query.key_expr) != control_key(self.node, op):
            # a wildcard reaches every service, and each would start the session: one target tracked once per box
            self._reply_err(query, Error(code="invalid_request", node=self.node,
                                         message=f"a start names its service: query {control_key(self.node, op)}, "
                                                 f"not {str(query.key_expr)[:128]}"))
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
