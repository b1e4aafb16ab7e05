"""WorkerPool: the service's worker processes, and the warm spares it keeps ahead of need.

A spare is a worker started before any session needs it: once its tracker's modules are loaded and its Zenoh
session is open it says "idle", and repeats it every worker.IDLE_HEARTBEAT_S until a session takes it, so that a
start gets a tracking worker in milliseconds. The supervisor keeps `spare_workers` spares (replenish): a spare
not warm WORKER_SILENCE_S after it started, or warm but silent for SPARE_SILENCE_S, is hung: it is handed no
session, killed and replaced; a spare that dies, or could not be started, is replaced at most every
SPARE_RESPAWN_MIN_S.

The pool shares the SessionManager's lock and closing event: the manager takes a spare, or puts one back, in the
same step as its check of the session under that lock, and no worker enters the pool once the service closes,
so no worker outlives a stopped session or a shutdown.
"""
from __future__ import annotations

import errno
import logging
import multiprocessing
import multiprocessing.connection
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from .outbox import Outbox
from .worker import WorkerSpec, run_worker, start_with_stop_signals_held

if TYPE_CHECKING:
    from .manager import Session

log = logging.getLogger(__name__)

SPARE_RESPAWN_MIN_S = 2.0      # a spare that dies is replaced at most this often (no spawn storm)
WORKER_SILENCE_S = 15.0        # a worker silent this long (no health; no "ready" or "idle" once started) is hung
SPARE_SILENCE_S = 5.0          # a warm spare repeats "idle" every second (worker.IDLE_HEARTBEAT_S): silent this
                               # long, it is hung: handed no session, killed and replaced
WRITER_JOIN_S = 1.0            # closing a worker's pipe waits this long for a write in progress (the worker is gone)
# Descriptors a worker's start leaves free: Zenoh takes one for each client's link (a query to this service), and a
# start that ran out of them half-way ended the fork server, whose every worker the service then took for dead.
FD_RESERVE = 16

Deliver = Callable[["Session", tuple], None]


@dataclass
class WorkerHandle:
    """A worker process and the parent's end of its pipe. Only drain() reads the pipe, under recv_lock, and
    routes each message to the owning session (none while the worker is a spare); only the outbox's thread
    writes to it."""
    process: multiprocessing.process.BaseProcess
    conn: multiprocessing.connection.Connection
    outbox: Outbox
    started_at: float = field(default_factory=time.monotonic)
    idle: bool = False              # said "idle": warm and waiting for an assignment
    idle_at: float = 0.0            # monotonic time of its last "idle" (the heartbeat of a spare)
    owner: "Session | None" = None
    recv_lock: threading.Lock = field(default_factory=threading.Lock)

    def is_warm(self, now: float) -> bool:
        """A spare that can take a session: alive, said "idle", and said it again lately."""
        return self.idle and self.process.exitcode is None and now - self.idle_at <= SPARE_SILENCE_S

    def drain(self, deliver: Deliver) -> None:
        """Read every pending message and route it: to its session through `deliver`, or (a spare) note "idle"."""
        with self.recv_lock:
            try:
                while self.conn.poll():
                    message = self.conn.recv()
                    if self.owner is not None:
                        deliver(self.owner, message)
                    elif message[0] == "idle":
                        self.idle, self.idle_at = True, time.monotonic()
            except (EOFError, OSError):
                pass

    def discard(self) -> None:
        """End a worker that serves nothing: close its pipe, which stops it, then SIGTERM, which ends it at once
        if it has read that end (else the pipe's end stops it all the same, worker.Worker.on_sigterm)."""
        self.close()
        self.process.terminate()

    def close(self) -> None:
        """End the writer thread, then close the pipe, never under the reader nor under a write. A write still in
        progress (to a worker alive and not reading) keeps the pipe, closed when that write ends and it is freed."""
        if not self.outbox.close(WRITER_JOIN_S):
            log.warning("worker pid %s: a write to its pipe is still in progress; the pipe is closed once it ends",
                        self.process.pid)
            return
        with self.recv_lock:
            _quiet_close(self.conn)


class WorkerPool:
    """Starts workers and keeps `spare_target` of them as spares. `lock` and `closing` are the SessionManager's:
    every method that reads or changes the spares takes `lock`, so that the manager can combine them with its own
    checks under it."""

    def __init__(self, mp_context, spec: WorkerSpec, spare_target: int, *, lock: threading.RLock,
                 closing: threading.Event, deliver: Deliver) -> None:
        self._mp = mp_context
        self._spec = spec
        self._spare_target = spare_target
        self._lock = lock
        self._closing = closing
        self._deliver = deliver             # a message of a worker taken from the pool while it was drained
        self._spares: list[WorkerHandle] = []
        self._spawned_at = 0.0
        self._start_failed = False          # the last spare could not be started: held back as after a death

    def new_worker(self) -> WorkerHandle:
        """Start a worker process (not a spare: the caller owns it)."""
        _check_fd_headroom()
        parent_conn, child_conn = self._mp.Pipe(duplex=True)
        process = self._mp.Process(target=run_worker, args=(self._spec, child_conn), name="tacf-worker",
                                   daemon=True)
        start_with_stop_signals_held(process)
        child_conn.close()
        return WorkerHandle(process, parent_conn, Outbox(parent_conn, f"outbox-{process.pid}"))

    def take_warm(self) -> WorkerHandle | None:
        """Take a warm spare out of the pool, if there is one."""
        with self._lock:
            now = time.monotonic()
            handle = next((w for w in self._spares if w.is_warm(now)), None)
            if handle is not None:
                self._spares.remove(handle)
            return handle

    def put_back(self, handle: WorkerHandle) -> None:
        """Return a spare taken by take_warm() and assigned nothing (the caller checks, under the lock, that the
        service is not closing)."""
        with self._lock:
            self._spares.append(handle)

    def replenish(self) -> None:
        """Kill the spares that are hung, forget the dead ones, and start new ones up to the target (supervisor)."""
        with self._lock:
            now = time.monotonic()
            for handle in self._spares:
                if handle.process.exitcode is not None:
                    continue
                if not handle.idle and worker_is_silent(handle.started_at, now):
                    log.warning("spare worker pid %d not warm %.0f s after it started: killing it", handle.process.pid,
                                now - handle.started_at)
                    handle.process.kill()       # replaced once its exit shows, like a spare that died
                elif handle.idle and not handle.is_warm(now):     # alive, said "idle", then went silent
                    log.warning("spare worker pid %d silent for %.0f s: killing it", handle.process.pid,
                                now - handle.idle_at)
                    handle.process.kill()
            dead = [w for w in self._spares if w.process.exitcode is not None]
            for handle in dead:
                self._spares.remove(handle)
                handle.close()
            missing = self._spare_target - len(self._spares)
            held_back = (dead or self._start_failed) and now - self._spawned_at < SPARE_RESPAWN_MIN_S
            if missing <= 0 or self._closing.is_set() or held_back:
                return
            self._spawned_at, self._start_failed = now, False
        for _ in range(missing):
            try:
                handle = self.new_worker()
            except Exception as exc:    # no process to be had (a fork failing for memory, the process limit)
                # The supervisor's round goes on to the sessions' workers; the spares are tried again after
                # SPARE_RESPAWN_MIN_S, as after a spare's death.
                with self._lock:
                    self._start_failed = True
                log.warning("cannot start a spare worker: %s; trying again in %.0f s", exc, SPARE_RESPAWN_MIN_S)
                return
            with self._lock:
                if not self._closing.is_set():
                    self._spares.append(handle)
                    continue
            # The service began closing while the worker started (the first can wait ~1 s for the fork server),
            # and shutdown() has already retired the spares it stops: this one is stopped here.
            handle.discard()

    def drain(self) -> None:
        """Read the spares' pipes (their "idle" heartbeats)."""
        for handle in self.spares():
            handle.drain(self._deliver)

    def waitables(self) -> list:
        """The pipes of the spares not warm yet, for the supervisor to wait on: their first "idle" wakes it (a warm
        spare's heartbeats are read on each round, by drain())."""
        with self._lock:
            return [w.conn for w in self._spares if not w.idle]

    def warm_count(self) -> int:
        """How many warm spares wait for a session."""
        self.drain()
        with self._lock:
            now = time.monotonic()
            return sum(1 for w in self._spares if w.is_warm(now))

    def spares(self) -> list[WorkerHandle]:
        """The spares, warm or not (a copy)."""
        with self._lock:
            return list(self._spares)

    def retire(self) -> list[WorkerHandle]:
        """Empty the pool for a shutdown and ask every spare to stop (a SIGTERM before that, as one sent to the
        whole process group, waits for it, worker.Worker.on_sigterm). The caller reaps their processes and closes
        them."""
        with self._lock:
            spares, self._spares = self._spares, []
        for spare in spares:
            spare.outbox.put(("stop",))
        return spares


def worker_is_silent(heard_at: float, now: float) -> bool:
    """A worker last heard from at ``heard_at`` (monotonic) is hung: silent for longer than WORKER_SILENCE_S, read
    here at each call so that a test can shorten it."""
    return now - heard_at > WORKER_SILENCE_S


def _quiet_close(conn) -> None:
    try:
        conn.close()
    except OSError:
        pass


def _check_fd_headroom() -> None:
    """OSError(EMFILE) when fewer than FD_RESERVE descriptors would be left to this process (checked where /proc
    lists them: Linux)."""
    try:
        used = len(os.listdir("/proc/self/fd"))     # EMFILE too when none is left
    except FileNotFoundError:
        return
    import resource

    limit = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
    if limit != resource.RLIM_INFINITY and used + FD_RESERVE > limit:
        raise OSError(errno.EMFILE, f"too many open files: {used} of the {limit} allowed (ulimit -n) are open, and "
                                    f"{FD_RESERVE} are kept free")
