"""Outbox: the messages to one worker process, written to its pipe by a thread of its own.

A worker that does not read its pipe for a while (busy, starved of CPU, stopped, wedged) makes a write larger than
what the pipe holds block until it reads: an init carries whole frames. Only this thread waits then, never a
control thread (a reply, and the queries queued behind it, other sessions' included) nor the supervisor. A new
init replaces one not written yet: only the latest box matters. Inits carry their generation last; two reinits at
once can queue them out of order, and the older one is then dropped, not the newer.
"""
from __future__ import annotations

import threading
from collections import deque


class Outbox:
    def __init__(self, conn, name: str) -> None:
        self._conn = conn
        self._cond = threading.Condition()
        self._queue: deque[tuple[tuple, threading.Event]] = deque()
        self._closed = False
        self._thread = threading.Thread(target=self._write, name=name, daemon=True)
        self._thread.start()

    def put(self, message: tuple) -> threading.Event:
        """Queue `message`; the event returned is set once it is written, or once it never will be (replaced by a
        newer init, the outbox closed, the pipe broken)."""
        done = threading.Event()
        with self._cond:
            if self._closed:
                done.set()
                return done
            if message[0] == "init":
                queued_inits = [q for q in self._queue if q[0][0] == "init"]
                if any(queued[0][-1] > message[-1] for queued in queued_inits):
                    done.set()
                    return done
                for queued in queued_inits:
                    self._queue.remove(queued)
                    queued[1].set()
            self._queue.append((message, done))
            self._cond.notify()
        return done

    def close(self, timeout: float) -> bool:
        """Drop what is not written and end the thread. False when it is still inside a write after `timeout` (the
        worker alive and not reading): the pipe must then not be closed under it."""
        with self._cond:
            self._closed = True
            for _, done in self._queue:
                done.set()
            self._queue.clear()
            self._cond.notify()
        self._thread.join(timeout)
        return not self._thread.is_alive()

    def _write(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._queue or self._closed)
                if self._closed:
                    return
                message, done = self._queue.popleft()
            try:
                self._conn.send(message)
            except (BrokenPipeError, EOFError, OSError):
                pass            # the worker is gone; the supervisor reports it
            finally:
                done.set()
