"""A Zenoh subscription delivering decoded, typed items by iteration or to a callback on a worker thread.

The Zenoh callback only decodes a small msgpack message and drops it into a mailbox (never user code, never a
blocking call: ZENOH.md §7). The mailbox is either a bounded FIFO (oldest dropped when full, counted) or
latest-only: one slot per `slot_of(item)` (e.g. per session), a newer item replacing an unread older one.
User callbacks run on the stream's own thread, so a slow callback never stalls Zenoh's network threads.
"""
from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Hashable, Iterator
from typing import Generic, TypeVar

import zenoh

log = logging.getLogger(__name__)

T = TypeVar("T")


class ResultStream(Generic[T]):
    """Subscribe to `key_expr`; `decode(sample)` returns an item or None (ignored, counted as rejected).

    Iterate (`for item in stream`, ends when closed) or `get(timeout)`; or pass `callback` to have every item
    handed to it on a worker thread. Close it (or use `with`): that undeclares the subscriber and joins the
    thread. Closing the Zenoh session ends the stream too (the items already received are still read).
    """

    def __init__(self, session: zenoh.Session, key_expr: str, decode: Callable[[zenoh.Sample], T | None], *,
                 latest_only: bool = False, slot_of: Callable[[T], Hashable] = lambda item: None,
                 queue_size: int = 256, callback: Callable[[T], None] | None = None, name: str = "tacf-stream"):
        self.key_expr = key_expr
        self.received = self.rejected = self.dropped = 0
        self._decode, self._latest_only, self._slot_of = decode, latest_only, slot_of
        self._fifo: deque[T] = deque(maxlen=max(1, queue_size))
        self._latest: OrderedDict[Hashable, T] = OrderedDict()
        self._cond = threading.Condition()
        self._closed = False
        self._thread: threading.Thread | None = None
        # The drop hook runs when the subscriber goes, also when its session closes first (TrackingClient.close(),
        # the end of its `with`): the stream then ends, instead of iterators and the callback thread (which keeps
        # the interpreter from exiting) waiting for items that will never come.
        self._sub = session.declare_subscriber(key_expr, zenoh.handlers.Callback(self._on_sample, self._on_drop))
        if callback is not None:
            self._thread = threading.Thread(target=self._run_callback, args=(callback,), name=name)
            self._thread.start()

    # --- Zenoh side (runs on Zenoh's callback thread: keep it short) -----------------------------------------
    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            item = self._decode(sample)
        except Exception:  # a decoder bug must not kill the subscription
            log.exception("cannot decode sample on %r", str(sample.key_expr))   # %r: a key may hold escapes
            item = None
        with self._cond:
            if self._closed:        # decoded while close() emptied the mailbox: nothing is handed out after it
                return
            if item is None:
                self.rejected += 1
                return
            self.received += 1
            if self._latest_only:
                slot = self._slot_of(item)
                if slot in self._latest:
                    self.dropped += 1
                    del self._latest[slot]
                self._latest[slot] = item
            else:
                if len(self._fifo) == self._fifo.maxlen:
                    self.dropped += 1
                self._fifo.append(item)
            self._cond.notify_all()

    def _on_drop(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    # --- consumer side ---------------------------------------------------------------------------------------
    def get(self, timeout: float | None = None) -> T | None:
        """The next item, or None after `timeout` seconds (None: wait until one arrives or the stream closes)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            while True:
                if self._latest:
                    return self._latest.popitem(last=False)[1]
                if self._fifo:
                    return self._fifo.popleft()
                if self._closed:
                    return None
                remaining = None if deadline is None else deadline - time.monotonic()
                if remaining is not None and remaining <= 0:
                    return None
                # Wake up regularly so that Ctrl-C reaches a main thread waiting here.
                self._cond.wait(0.2 if remaining is None else min(remaining, 0.2))

    def __iter__(self) -> Iterator[T]:
        while True:
            item = self.get()
            if item is None:
                return
            yield item

    def _run_callback(self, callback: Callable[[T], None]) -> None:
        for item in self:
            try:
                callback(item)
            except Exception:
                log.exception("callback for %s failed", self.key_expr)

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        # Also after the session closed first (which only ends the stream): the items still queued are dropped and
        # the thread joined, else the callback went on with them after close() returned.
        with self._cond:
            self._closed = True
            self._latest.clear()
            self._fifo.clear()
            self._cond.notify_all()
        try:
            self._sub.undeclare()
        except zenoh.ZError:
            pass  # the session was closed first, or this is a second close(): the subscriber is gone already
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)

    def __enter__(self) -> "ResultStream[T]":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
