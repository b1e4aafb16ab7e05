"""SessionManager: the session table, its limits, and the supervision of one worker process per session.

Control operations (start, stop, reinit, list, status) run on the control threads; a supervisor thread reads
every worker's pipe, notices dead workers (process sentinels) and restarts them from their last box with a
backoff, kills the workers that went silent (pool.WORKER_SILENCE_S), keeps the pool of warm spares filled
(pool.WorkerPool: a session takes its worker from there) and saves the table when it changed.
A session whose worker keeps crashing (more than MAX_CRASHES within CRASH_WINDOW_S) stays `failed` until it is
re-initialised or stopped.
"""
from __future__ import annotations

import logging
import math
import multiprocessing
import multiprocessing.connection
import secrets
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from tacf_schemas import (MSGPACK_ENCODING, DecodeError, Frame, Health, ReinitRequest, SessionInfo, SessionList,
                          StartRequest, catch_up_subset, decode, encode, health_key)
from tacf_schemas import Health as HealthModel
from tacf_schemas.images import FrameError, check_frame
from tacf_schemas.keys import InvalidKeyError, validate_image_key

from .config import ZenohOptions
from .errors import ServiceError
from .frames import FrameHistory, StoredFrame, box_problem
from .health import COUNTERS
from .pool import WorkerHandle, WorkerPool, worker_is_silent
from .state import PersistedSession, StateStore
from .trackers import DEFAULT_FACTORY, checked_overrides, default_profile
from .worker import HEALTH_PRIORITY, Assignment, WorkerSpec, worker_context, worker_exit_message

log = logging.getLogger(__name__)

SUPERVISE_PERIOD_S = 0.2
SAVE_PERIOD_S = 1.0
# Each session's box frame is stored at a start, reinit or shutdown, and every this long between (tacf serve
# --state-frames-every): after a crash a restored tracker starts this far back at most.
FRAME_SAVE_PERIOD_S = 5.0
STOP_GRACE_S = 1.0
MAX_CRASHES = 5
CRASH_WINDOW_S = 60.0
RESTART_BACKOFF_S = (0.2, 0.5, 1.0, 2.0, 5.0)
CATCHUP_FRAMES = 6             # after the init frame, at most this many newer frames (evenly spaced) to catch up
REINIT_WRITE_WAIT_S = 0.2      # a reinit is answered once its init is written to the worker, or after this long


@dataclass
class Session:
    """One tracking session: what was asked, what the worker last reported, and the worker itself."""
    sid: str
    image_key: str
    profile: str
    overrides: dict
    box: tuple                          # the last box (initial box until the first result)
    created_ns: int
    init_seq: int | None = None         # the frame to (re)initialise on, then the one it was initialised on
    last_seq: int | None = None         # the frame `box` belongs to
    box_frame: StoredFrame | None = None   # that frame while it may be in no history (carried by a request)
    restarts: int = 0
    state: str = "starting"
    message: str | None = None
    health: Health | None = None
    # worker side
    process: multiprocessing.process.BaseProcess | None = None
    conn: multiprocessing.connection.Connection | None = None
    worker: WorkerHandle | None = None
    worker_ready: bool = False          # the worker said "ready": it can take an init
    heard_at: float = 0.0               # monotonic time of the worker's last message, or of its attachment
    init_pending: bool = False          # an init (init_box, init_seq) waits to be sent
    init_box: tuple | None = None
    init_frames: list = field(default_factory=list)   # frames pinned for the init: the init frame, then newer
    init_released: bool = False         # start validation is over: the pending init may go out
    awaiting_init: bool = False         # results older than the pending init are ignored until "initialised"
    init_generation: int = 0            # counts the inits queued: a reply to a replaced one is stale
    gave_up: bool = False               # failed for good (bad box or config, crash loop): no restart
    stopping: bool = False
    holds_history: bool = False         # holds a reference on its image key's frame history (released once)
    saved_frame_seq: int | None = None  # the seq of the frame stored with the persisted table,
    saved_frame_box: tuple | None = None    # the box computed on it,
    frame_saved_at: float = -math.inf       # and when it was stored (monotonic)
    started: bool = False               # its start was answered (or it was restored): only such are persisted
    restart_at: float | None = None
    crashes: deque = field(default_factory=deque)
    # FrameHistory.arrivals of its key when its worker died, or when it began to hold the key's history (a start, a
    # restore): the frames that come until a new worker subscribes are in no worker's counters (_unserved_frames)
    unserved_since: int | None = None

    def info(self, node: str) -> SessionInfo:
        return SessionInfo(node=node, sid=self.sid, image_key=self.image_key, profile=self.profile,
                           overrides=self.overrides, state=self.state, box=self.box, init_seq=self.init_seq,
                           last_seq=self.last_seq, created_ns=self.created_ns, restarts=self.restarts,
                           health=self.health)

    def persisted(self) -> PersistedSession:
        return PersistedSession(sid=self.sid, image_key=self.image_key, profile=self.profile,
                                overrides=self.overrides, box=self.box, last_seq=self.last_seq,
                                created_ns=self.created_ns, restarts=self.restarts,
                                frame_seq=self.saved_frame_seq, frame_box=self.saved_frame_box)


class SessionManager:
    def __init__(self, zenoh_session, node: str, history: FrameHistory, zenoh_options: ZenohOptions,
                 endpoints: list[str], *, max_sessions: int = 8, store: StateStore | None = None,
                 tracker_factory: str = DEFAULT_FACTORY, init_wait_s: float = 1.0, spare_workers: int = 1,
                 frame_save_period_s: float = FRAME_SAVE_PERIOD_S, log_level: int = logging.INFO) -> None:
        self.node = node
        self.max_sessions = max_sessions
        self._zenoh = zenoh_session
        self._history = history
        self._store = store
        self._frame_save_period_s = frame_save_period_s
        self._init_wait_s = init_wait_s
        self._lock = threading.RLock()
        self._sessions: dict[str, Session] = {}
        self._stopping: set[str] = set()    # ids of sessions being stopped: not free for a start until stopped
        # Saved sessions a restore left out (beyond --max-sessions, or refused by this version's checks): written
        # back with every table until a start takes their id, so that a restart with room for them brings them back.
        self._not_restored: dict[str, PersistedSession] = {}
        self._closing = threading.Event()
        worker_spec = WorkerSpec(node=node, zenoh=zenoh_options, endpoints=tuple(endpoints),
                                 tracker_factory=tracker_factory, log_level=log_level)
        self.pool = WorkerPool(worker_context(), worker_spec, spare_workers, lock=self._lock, closing=self._closing,
                               deliver=self._on_message)
        self._dirty = False
        # The files the last save could not write (the table, sessions' frames), each logged once while it fails:
        # a frame failing hid the table's failure after it (a full disk), and a session started then was lost unsaid.
        self._save_failures: set[Path] = set()
        # Held from a save's snapshot to its rename: saves from the control threads and the supervisor would
        # otherwise land in any order, an older table last (a stopped session back after a restart).
        self._save_lock = threading.Lock()
        self._saves_closed = False          # shutdown's last save is written: none after it (the file is unlocked)
        self._supervisor = threading.Thread(target=self._supervise, name="supervisor", daemon=True)

    # ------------------------------------------------------------------ lifecycle

    def start_supervisor(self) -> None:
        self._supervisor.start()

    def restore(self) -> int:
        """Bring back the sessions of the state file, each re-initialised from its last box."""
        if self._store is None:
            return 0
        restored = 0
        table = []
        for saved in self._store.load():
            try:            # as a start checks them: a hand-edited file, or one from a version with other profiles
                validate_image_key(saved.image_key)
                table.append((saved, checked_overrides(saved.profile, dict(saved.overrides))))
            except (InvalidKeyError, ValueError, TypeError) as exc:
                log.warning("not restoring session %s: %s (kept in the file)", saved.sid, exc)
                self._not_restored[saved.sid] = saved
        # counted after those left out: a session not restored takes no slot from one that would be
        if len(table) > self.max_sessions:
            log.warning("not restoring %d session(s) of %s beyond --max-sessions %d: %s (kept in the file: a restart "
                        "with room for them restores them)", len(table) - self.max_sessions, self._store.path,
                        self.max_sessions, ", ".join(saved.sid for saved, _ in table[self.max_sessions:]))
            self._not_restored.update((saved.sid, saved) for saved, _ in table[self.max_sessions:])
        for saved, overrides in table[: self.max_sessions]:
            session = Session(sid=saved.sid, image_key=saved.image_key, profile=saved.profile,
                              overrides=overrides, box=tuple(saved.box), created_ns=saved.created_ns,
                              init_seq=saved.last_seq, last_seq=saved.last_seq, restarts=saved.restarts,
                              started=True)
            with self._lock:
                self._sessions[session.sid] = session
            self._hold_history(session)
            box, seq, saved_frame = self._saved_frame(saved)      # init on the frame of a box, then catch up
            carried = [saved_frame] if saved_frame is not None else []
            frames = self._init_frames(session.image_key, seq, carried)
            self._queue_init(session, box, seq, released=True, frames=frames)
            if saved_frame is not None:
                session.saved_frame_seq, session.saved_frame_box = saved_frame.seq, tuple(box)
            try:
                self._spawn(session)
            except Exception as exc:    # no process to be had: tried again as a restart is, the session kept
                self._no_worker_yet(session, exc)
            restored += 1
        if restored:
            log.info("restored %d session(s) from %s", restored, self._store.path)
        return restored

    def begin_shutdown(self) -> None:
        """Refuse new work and wake any start waiting for a frame (call before closing the control server)."""
        self._closing.set()
        self._history.wake_all()

    def _saved_frame(self, saved: PersistedSession) -> tuple[tuple, int | None, StoredFrame | None]:
        """(box, seq, frame) to restore `saved` on: its last box with the frame it was computed on when stored,
        else the stored frame's own box (up to a frame save period older), else the last box alone."""
        last = tuple(saved.box), saved.last_seq, None
        payload = self._store.load_frame(saved.sid) if self._store else None
        if payload is None or saved.last_seq is None:
            return last
        try:
            frame = StoredFrame.from_payload(payload)
        except DecodeError as exc:
            log.warning("ignoring the saved frame of session %s: %s", saved.sid, exc)
            return last
        if frame.seq == saved.last_seq:
            return tuple(saved.box), frame.seq, frame
        if frame.seq == saved.frame_seq and saved.frame_box is not None:
            return tuple(saved.frame_box), frame.seq, frame
        return last

    def shutdown(self, timeout: float = 1.5) -> None:
        """Stop every worker (stop command, then SIGTERM, then SIGKILL) within `timeout`; keep the table saved
        so that the sessions come back on the next start."""
        deadline = time.monotonic() + max(0.1, timeout - 0.7)     # then SIGTERM, then SIGKILL
        self._closing.set()
        with self._lock:
            sessions = list(self._sessions.values())
        if self._supervisor.is_alive():
            self._supervisor.join(timeout=SUPERVISE_PERIOD_S * 2)
        for session in sessions:
            session.stopping = True
            self._send(session, ("stop",))
        spares = self.pool.retire()
        _reap([s.process for s in sessions if s.process] + [w.process for w in spares], deadline)
        self._save(force=True, last=True)
        for session in sessions:
            _close_conn(session)
        for spare in spares:
            spare.close()

    # ------------------------------------------------------------------ control operations

    def start(self, request: StartRequest) -> SessionInfo:
        try:
            image_key = validate_image_key(request.image_key)
            _zenoh_key(image_key)
        except InvalidKeyError as exc:
            raise ServiceError("invalid_key", str(exc)) from None
        profile = request.profile or default_profile()
        try:
            overrides = checked_overrides(profile, dict(request.overrides))
        except (ValueError, TypeError) as exc:
            raise ServiceError("invalid_config", str(exc)) from None
        carried = _carried_frames(request.frames)
        sid = request.sid or _new_sid()
        session = Session(sid=sid, image_key=image_key, profile=profile, overrides=overrides,
                          box=tuple(request.box), created_ns=time.time_ns())
        with self._lock:
            self._check_open()
            if sid in self._sessions:
                raise ServiceError("duplicate_session", f"session {sid!r} already exists on node {self.node!r}")
            if sid in self._stopping:
                raise ServiceError("duplicate_session", f"session {sid!r} is still being stopped on node "
                                                        f"{self.node!r}; retry")
            if len(self._sessions) >= self.max_sessions:
                raise ServiceError("too_many_sessions", f"node {self.node!r} already runs {len(self._sessions)} "
                                                        f"session(s) (--max-sessions {self.max_sessions})")
            self._sessions[sid] = session                      # reserved: the id and the slot
        try:
            self._hold_history(session)
            if not carried:
                self._history.wait_for(image_key, request.seq, self._init_wait_s, cancel=self._closing)
            self._check_open()
            frames = self._init_frames(image_key, request.drawn_on, carried)
            if frames:
                _check_box_in_frame(session.box, frames[0])
            self._queue_init(session, session.box, request.drawn_on, released=False, frames=frames)
            try:
                self._spawn(session)
            except OSError as exc:      # no process or descriptors to be had (a small edge box): try later
                raise ServiceError("unavailable", f"cannot start a worker process: {exc}") from None
        except BaseException:
            self._discard(session)
            raise
        self._release_init(session)
        with self._lock:
            session.started = True
            replaced = self._not_restored.pop(sid, None)     # in the table a session of this id is the new one
        if replaced is not None:
            log.warning("session %s replaces the one of that id kept, not restored, in %s", sid, self._store.path)
        self._save(force=True)
        log.info("started session %s on %s (profile %s, box %s, asked seq %s, init seq %s)", sid, image_key,
                 profile, session.box, request.drawn_on, session.init_seq)
        return session.info(self.node)

    def stop(self, sid: str) -> SessionInfo:
        with self._lock:
            self._check_open()                  # shutdown stops every worker and keeps the table for the restart
            kept = None if sid in self._sessions else self._not_restored.pop(sid, None)
            if kept is None:
                session = self._get(sid)
                del self._sessions[sid]
                self._stopping.add(sid)         # until its "stopped" is out, the id is not free for a new session
                session.stopping = True
                process = session.process       # _spawn attaches a worker under the lock, or not at all now
        if kept is not None:
            return self._forget_kept(kept)
        try:
            self._send(session, ("stop",))
            _reap([process] if process else [], time.monotonic() + STOP_GRACE_S)
            self._drain(session)                # the worker's last Health: the counters the "stopped" one carries
            _close_conn(session)
            unserved = self._unserved_frames(session, sent=[])      # stopped before a new worker served it
            self._release_history(session)
            session.state = "stopped"
            self._publish_health(session, "stopped", "stopped by request", unserved)
        finally:
            with self._lock:
                self._stopping.discard(sid)
        self._save(force=True)
        log.info("stopped session %s", sid)
        return session.info(self.node)

    def _forget_kept(self, kept: PersistedSession) -> SessionInfo:
        """Stop a session the restore left out: it has no worker, so stopping it takes it out of the state file."""
        self._save(force=True)
        log.info("stopped session %s, kept, not restored, in %s: removed from the file", kept.sid, self._store.path)
        return SessionInfo(node=self.node, sid=kept.sid, image_key=kept.image_key, profile=kept.profile,
                           overrides=kept.overrides, state="stopped", box=kept.box, last_seq=kept.last_seq,
                           created_ns=kept.created_ns, restarts=kept.restarts)

    def reinit(self, request: ReinitRequest) -> SessionInfo:
        with self._lock:
            self._check_open()
            session = self._get(request.sid)
        carried = _carried_frames(request.frames)
        frames = self._init_frames(session.image_key, request.drawn_on, carried)
        if frames:
            _check_box_in_frame(tuple(request.box), frames[0])
        with self._lock:
            session.gave_up, session.crashes = False, deque()
            session.state, session.message = "starting", None
            self._queue_init(session, request.box, request.drawn_on, released=True, frames=frames)  # sets box
            needs_worker = not _has_live_worker(session)
            reply = session.info(self.node)
        if needs_worker:
            self._spawn(session)
        else:
            written = self._flush_init(session)
            if written is not None:             # the common case: answered once the worker has the new box
                written.wait(REINIT_WRITE_WAIT_S)
        self._save(force=True)
        log.info("re-initialised session %s with box %s (seq %s)", session.sid, request.box, request.drawn_on)
        return reply

    def list(self) -> SessionList:
        with self._lock:
            infos = [s.info(self.node) for s in self._sessions.values()]
        return SessionList(node=self.node, max_sessions=self.max_sessions, sessions=infos)

    def status(self, sid: str) -> SessionInfo:
        with self._lock:
            return self._get(sid).info(self.node)

    def idle_spares(self) -> int:
        """How many warm workers wait for a session (tests wait for one before timing a start)."""
        return self.pool.warm_count()

    def worker_pids(self) -> dict[str, int]:
        """Worker process ids by session id (for tests and diagnostics)."""
        with self._lock:
            return {s.sid: s.process.pid for s in self._sessions.values() if s.process and s.process.pid}

    # ------------------------------------------------------------------ helpers of the control operations

    def _check_open(self) -> None:
        if self._closing.is_set():
            raise ServiceError("unavailable", f"node {self.node!r} is shutting down")

    def _get(self, sid: str) -> Session:
        session = self._sessions.get(sid)
        if session is None:
            raise ServiceError("unknown_session", f"no session {sid!r} on node {self.node!r}")
        return session

    def _discard(self, session: Session) -> None:
        with self._lock:
            if self._sessions.get(session.sid) is session:
                del self._sessions[session.sid]
        session.stopping = True
        self._send(session, ("stop",))
        if session.process is not None:
            _reap([session.process], time.monotonic() + STOP_GRACE_S)
        _close_conn(session)
        self._release_history(session)

    def _hold_history(self, session: Session) -> None:
        """Keep the frames of the session's key (a start, a restore): from here on they are the session's, and those
        that come before its first worker subscribes are counted as a dead worker's successor counts them."""
        self._history.acquire(session.image_key)
        with self._lock:
            session.holds_history = True
            session.unserved_since = self._history.arrivals(session.image_key)

    def _release_history(self, session: Session) -> None:
        """Release the session's reference on its frame history, once: a stop and a failing start may both try."""
        with self._lock:
            held, session.holds_history = session.holds_history, False
        if held:
            self._history.release(session.image_key)

    def _is_gone(self, session: Session) -> bool:
        """Stopped, or replaced in the table: a start, reinit or restart still running for it must not go on."""
        return session.stopping or self._sessions.get(session.sid) is not session

    # ------------------------------------------------------------------ workers

    def _spawn(self, session: Session) -> None:
        """Give the session a worker: a warm spare when there is one, else a new process. A session stopped in
        the meantime (a stop while a start waited for a frame) gets none: ServiceError unknown_session. The
        check and the attachment are one step under the lock, and stop() reads the worker under it, so a worker
        is either attached before the stop, which then stops it, or never. A session given a live worker
        meanwhile (a reinit while its start waited for a frame, two reinits after a crash) keeps that one, which
        takes the pending init: a second worker would serve it unseen and outlive its stop."""
        earlier = session.health.model_dump(include=set(COUNTERS)) if session.health is not None else {}
        assignment = Assignment(sid=session.sid, image_key=session.image_key, profile=session.profile,
                                overrides=session.overrides, restarts=session.restarts, earlier_counts=earlier)
        with self._lock:
            if self._is_gone(session):
                raise _stopped_meanwhile(session, self.node)
            handle = self.pool.take_warm()
        warm = handle is not None
        if handle is None:
            handle = self.pool.new_worker()
        with self._lock:
            # shutdown() stops the workers and spares it found: one attached or put back after that would outlive it
            closing = self._closing.is_set()
            gone = closing or self._is_gone(session)
            served = not gone and _has_live_worker(session)
            returned = (gone or served) and warm and not closing
            replaced = None
            if returned:
                self.pool.put_back(handle)      # still a warm, unassigned spare
            elif not (gone or served):
                replaced = session.worker       # a dead worker's pipe, not yet closed by the supervisor
                session.worker = handle
                session.process, session.conn, session.worker_ready = handle.process, handle.conn, False
                session.heard_at = time.monotonic()     # silent from now on, it is hung even before "ready"
                session.restart_at = None
                if session.state == "failed" and not session.gave_up:
                    session.state = "starting"
        if gone or served:
            if not returned:
                handle.discard()
        if served:
            self._flush_init(session)
            return
        if gone:
            self._check_open()
            raise _stopped_meanwhile(session, self.node)
        if replaced is not None:
            replaced.close()
        with handle.recv_lock:
            handle.owner = session
        self._send(session, ("assign", assignment))
        log.debug("worker pid %d serves session %s%s", handle.process.pid, session.sid,
                  " (warm spare)" if warm else "")

    def _init_frames(self, key: str, seq: int | None, carried: Sequence[StoredFrame]) -> list[StoredFrame]:
        """The frames to initialise on: frame `seq` and the newer ones kept; else the carried frames (the one the
        box was drawn on, then newer ones, sent with the request) and the newer ones kept; else those kept after
        `seq` (FrameHistory.frames_from), else the newest kept."""
        frames = self._history.frames_from(key, seq)
        if carried and not (frames and frames[0].seq == seq):
            return list(carried) + self._history.frames_after(key, carried[-1])
        return frames

    def _queue_init(self, session: Session, box: tuple, seq: int | None, released: bool,
                    frames: list[StoredFrame]) -> None:
        """Pin `frames`, those to initialise on (_init_frames: the ones the box was checked against), so that they
        are still there when the worker is ready."""
        if seq is not None and frames and frames[0].seq != seq:
            log.warning("session %s: frame seq %d is not held (no longer, or never); initialising on seq %d",
                        session.sid, seq, frames[0].seq)
        session.init_box, session.init_frames = tuple(box), frames
        session.init_seq = frames[0].seq if frames else seq
        # The box now belongs to the init frame: a restart or a restored service initialises there, not on the
        # frame the last result came from.
        session.box, session.last_seq = tuple(box), session.init_seq
        session.box_frame = frames[0] if frames else None
        session.init_pending, session.init_released = True, released
        session.awaiting_init = True
        session.init_generation += 1

    def _release_init(self, session: Session) -> None:
        session.init_released = True
        self._flush_init(session)

    def _flush_init(self, session: Session) -> threading.Event | None:
        """Send the pending init once the worker is ready: the box and the frames from init_seq on. The event
        returned is set once the init is written (None: nothing sent)."""
        with self._lock:
            if not (session.init_pending and session.init_released and session.worker_ready):
                return None
            session.init_pending = False
            box, pinned, session.init_frames = session.init_box, session.init_frames, []
            generation = session.init_generation
        if pinned:
            frames = pinned + self._history.frames_after(session.image_key, pinned[-1])
        else:
            frames = self._history.frames_from(session.image_key, None)
        frames = catch_up_subset(frames, CATCHUP_FRAMES)
        if unserved := self._unserved_frames(session, sent=frames):
            self._send(session, ("unserved", unserved))
        return self._send(session, ("init", box, [f.payload for f in frames], generation))

    def _unserved_frames(self, session: Session, sent: Sequence[StoredFrame]) -> int:
        """The frames of the session's key that came while it had no worker subscribed (from its worker's death to
        now, its new worker's "ready" or its stop), less those `sent` to the new worker, which counts them itself:
        no worker counted them, and they go into its received and dropped counters. Counted once."""
        with self._lock:
            since, session.unserved_since = session.unserved_since, None
        if since is None:
            return 0
        now = self._history.arrivals(session.image_key)
        caught_up = sum(1 for f in sent if f.arrival is not None and since <= f.arrival < now)
        return max(0, now - since - caught_up)

    def _send(self, session: Session, message: tuple) -> threading.Event | None:
        """Queue a message to the session's worker (Outbox); the event is set once it is written."""
        worker = session.worker
        return worker.outbox.put(message) if worker is not None else None

    # ------------------------------------------------------------------ supervision

    def _supervise(self) -> None:
        while not self._closing.is_set():
            try:
                self._supervise_once()
            except Exception:
                log.exception("supervisor iteration failed")
                time.sleep(SUPERVISE_PERIOD_S)

    def _supervise_once(self) -> None:
        # Spares start here, not in open(): the first worker waits for the fork server to load the tracker, and
        # the service answers in the meantime.
        self.pool.replenish()
        with self._lock:
            sessions = [s for s in self._sessions.values() if s.process is not None]
        waitables = [s.conn for s in sessions if s.conn is not None] + [s.process.sentinel for s in sessions]
        waitables += self.pool.waitables()
        try:
            if waitables:
                multiprocessing.connection.wait(waitables, timeout=SUPERVISE_PERIOD_S)
            else:
                self._closing.wait(SUPERVISE_PERIOD_S)
        except (OSError, ValueError):
            pass                # a connection closed under us by stop(); the next round has a fresh list
        for session in sessions:
            self._drain(session)
            process = session.process
            if process is not None and process.exitcode is not None and not session.stopping:
                self._on_worker_exit(session, process)
            elif (process is not None and not session.stopping
                  and worker_is_silent(session.heard_at, time.monotonic())):
                log.warning("session %s: worker pid %d silent for %.0f s: killing it", session.sid, process.pid,
                            time.monotonic() - session.heard_at)
                process.kill()          # the exit is handled (failed, restart) on the next round
                session.heard_at = time.monotonic()
        now = time.monotonic()
        with self._lock:
            due = [s for s in self._sessions.values()
                   if s.restart_at is not None and s.restart_at <= now and not s.stopping]
        for session in due:
            if not self._closing.is_set():
                self._restart(session)
        self.pool.drain()
        self._save()

    def _drain(self, session: Session) -> None:
        worker = session.worker
        if worker is not None:
            worker.drain(self._on_message)

    def _on_message(self, session: Session, message: tuple) -> None:
        kind = message[0]
        session.heard_at = time.monotonic()
        if kind == "result":
            _, seq, box, ok = message
            with self._lock:
                if session.awaiting_init:
                    return              # computed before the new init reached the worker: stale
                session.last_seq, session.box, session.box_frame = seq, tuple(box), None
                if not session.gave_up:
                    session.state = "tracking" if ok else "lost"
            self._dirty = True
        elif kind == "health":
            try:
                health = decode(message[1], HealthModel)
            except Exception:
                return
            with self._lock:
                session.health = health
                if not session.gave_up and session.state != "failed":
                    session.state = health.state
        elif kind == "ready":
            session.worker_ready = True
            self._flush_init(session)
        elif kind == "initialised":
            with self._lock:
                if message[2] != session.init_generation:
                    return              # of an init a reinit has replaced: its results are still of the old box
                session.awaiting_init = False
                session.init_seq = message[1]
                session.state, session.message = "tracking", None
        elif kind == "failed":
            with self._lock:
                if message[2] is not None and message[2] != session.init_generation:
                    return              # the box of a replaced init did not fit; the new one may
                session.state, session.message, session.gave_up = "failed", message[1], True
            log.warning("session %s failed: %s", session.sid, message[1])
            if message[2] is None:          # its tracker could not be built: the worker publishes no Health at all
                self._publish_health(session, "failed", message[1])

    def _on_worker_exit(self, session: Session, process) -> None:
        with self._lock:
            if session.process is not process or self._is_gone(session):
                # a reinit gave it a new worker meanwhile and closed this one's pipe, or a stop, whose "stopped"
                # must stay the session's last Health, is reaping it
                return
            worker, session.worker, session.conn, session.process = session.worker, None, None, None
            if session.unserved_since is None:      # else a worker that died before it was ready: counting on
                session.unserved_since = self._history.arrivals(session.image_key)
        message = worker_exit_message(process)     # before the close below stops a worker its fork server left
        if worker is not None:
            worker.close()
        with self._lock:
            if session.gave_up or self._is_gone(session):
                return
            session.state = "failed"
            session.message = message
            now = time.monotonic()
            session.crashes.append(now)
            while session.crashes and now - session.crashes[0] > CRASH_WINDOW_S:
                session.crashes.popleft()
            if len(session.crashes) > MAX_CRASHES:
                session.gave_up = True
                session.message += f"; {len(session.crashes)} crashes in {CRASH_WINDOW_S:.0f} s, not restarting"
            else:
                backoff = RESTART_BACKOFF_S[min(len(session.crashes), len(RESTART_BACKOFF_S)) - 1]
                session.restart_at = now + backoff
                # The restart comes after the backoff, or later when it waits for a fork server started again: the
                # last box's frame may have left the history by then (24 frames, 2.4 s at 10 fps), and the box would
                # go on a later frame, where the target has moved. Kept from now on, as a frame a request carries.
                if session.box_frame is None and session.last_seq is not None:
                    session.box_frame = self._history.frame(session.image_key, session.last_seq)
            # Under the lock, as the check above: a stop that came in between published "stopped" first, and this
            # "failed" became the last word on a stopped session.
            self._publish_health(session, "failed", session.message)
        log.warning("session %s: %s", session.sid, session.message)

    def _restart(self, session: Session) -> None:
        with self._lock:
            if self._is_gone(session) or session.restart_at is None:
                return                          # stopped, or given a worker by a reinit since it was due
            session.restarts += 1
            carried = [session.box_frame] if session.box_frame is not None else []
            self._queue_init(session, session.box, session.last_seq, released=True,
                             frames=self._init_frames(session.image_key, session.last_seq, carried))
        log.info("restarting session %s from box %s (seq %s), restart #%d", session.sid, session.box,
                 session.last_seq, session.restarts)
        try:
            self._spawn(session)
        except ServiceError:
            return                              # stopped meanwhile
        except Exception as exc:
            self._no_worker_yet(session, exc)
            return
        self._dirty = True

    def _no_worker_yet(self, session: Session, exc: Exception) -> None:
        """A worker could not be started for the session (a fork failing for memory, the process limit): it is
        `failed` and tried again after the longest backoff, not on every round."""
        with self._lock:
            session.restart_at = time.monotonic() + RESTART_BACKOFF_S[-1]
            session.state = "failed"
            session.message = f"cannot start a worker process: {exc}; trying again in {RESTART_BACKOFF_S[-1]:.0f} s"
            if not self._is_gone(session):
                self._publish_health(session, "failed", session.message)
        log.warning("session %s: %s", session.sid, session.message)

    def _publish_health(self, session: Session, state: str, message: str | None, unserved: int = 0) -> None:
        """Health on behalf of a session whose worker cannot publish it (dead or stopped), with `unserved` frames
        (_unserved_frames) added to the last one's counters."""
        import zenoh

        last = session.health
        counters = last.model_dump(include={*COUNTERS, "pme", "last_seq"}) if last else {}
        if unserved:
            for name in ("frames_received", "frames_dropped"):
                counters[name] = counters.get(name, 0) + unserved
        health = Health(node=self.node, sid=session.sid, state=state, stamp_ns=time.time_ns(), fps=0.0,
                        processing_ms_mean=0.0, processing_ms_p95=0.0, restarts=session.restarts,
                        message=(message or "")[:1024] or None, **counters)
        session.health = health
        priority = getattr(zenoh.Priority, HEALTH_PRIORITY)
        try:
            self._zenoh.put(health_key(self.node, session.sid), encode(health),
                            encoding=zenoh.Encoding(MSGPACK_ENCODING), priority=priority)
        except Exception as exc:
            log.debug("cannot publish health of %s: %s", session.sid, exc)

    # ------------------------------------------------------------------ persistence

    def _save(self, force: bool = False, last: bool = False) -> None:
        """Write the table (and each session's box frame) when it changed, at most every SAVE_PERIOD_S unless
        `force`; `last`: shutdown's save, after which none is written."""
        if self._store is None or not (self._dirty or force):
            return
        with self._save_lock:
            if self._saves_closed:
                return
            self._saves_closed = last
            self._write_table(force, last)

    def _write_table(self, force: bool, last: bool = False) -> None:
        now = time.monotonic()
        if not force and now - getattr(self, "_saved_at", 0.0) < SAVE_PERIOD_S:
            return
        with self._lock:
            # a start still running is left out: if shutdown cuts it off, its client is told it failed
            sessions = [s for s in self._sessions.values() if s.started]
            table = [s.persisted() for s in sessions]
            box_frames = [s.box_frame for s in sessions]
            not_restored = list(self._not_restored.values())
            self._dirty = False
        self._saved_at = now
        failures: dict[Path, str] = {}
        written: set[Path] = set()
        for i, (session, entry, box_frame) in enumerate(zip(sessions, table, box_frames)):
            due = force or now - session.frame_saved_at >= self._frame_save_period_s
            # the box too: a reinit drawn on the frame already stored changes the box, not the seq
            stored = (session.saved_frame_seq, session.saved_frame_box)
            if due and entry.last_seq is not None and (entry.last_seq, tuple(entry.box)) != stored:
                frame = self._history.frame(session.image_key, entry.last_seq)
                if frame is None and box_frame is not None and box_frame.seq == entry.last_seq:
                    frame = box_frame           # carried by a start or reinit: in no history
                if frame is not None:
                    try:
                        self._store.save_frame(session.sid, frame.payload)
                    except OSError as exc:
                        # The table goes on without it: a disk with no room for a frame (a megabyte) may still
                        # have it for the table (a kilobyte), and a stop must reach the file. The entry keeps the
                        # frame stored before, and its box.
                        failures[self._store.frame_path(session.sid)] = \
                            f"the box frame of session {session.sid} in {self._store.frames_dir}: {exc}"
                    else:
                        written.add(self._store.frame_path(session.sid))
                        session.saved_frame_seq, session.saved_frame_box = entry.last_seq, entry.box
                        session.frame_saved_at = now
            table[i] = entry.model_copy(update={"frame_seq": session.saved_frame_seq,
                                                "frame_box": session.saved_frame_box})
        try:
            self._store.save(table + not_restored)
            self._store.prune_frames({s.sid for s in [*sessions, *not_restored]})
            written.add(self._store.path)
        except OSError as exc:
            failures[self._store.path] = f"the session table to {self._store.path}: {exc}"
        if failures:
            # Saved again every SAVE_PERIOD_S until it works (disk full, say): a stop must reach the file even
            # when nothing else changes after it.
            self._dirty = True
        for path, failure in failures.items():
            if last:        # the file keeps the table saved before: what changed since is lost, so say it again
                log.error("cannot save %s; shutting down, not retried", failure)
            elif path not in self._save_failures:
                log.error("cannot save %s; retrying every %.0f s", failure, SAVE_PERIOD_S)
        if self._store.path in self._save_failures and self._store.path not in failures:
            log.info("session table saved to %s again", self._store.path)
        # a frame not tried this time (no new box) fails still; one of a session gone is forgotten
        files = {self._store.path, *(self._store.frame_path(s.sid) for s in sessions)}
        self._save_failures = ((self._save_failures - written) | failures.keys()) & files


def _zenoh_key(key: str) -> None:
    """Zenoh's own validation on top of the whitelist (raises InvalidKeyError)."""
    import zenoh
    try:
        zenoh.KeyExpr(key)
    except zenoh.ZError as exc:
        raise InvalidKeyError(f"invalid image key {key!r}: {exc}") from None


def _new_sid() -> str:
    return "s" + secrets.token_hex(4)


def _carried_frames(frames: list[Frame]) -> list[StoredFrame]:
    """The frames a start or reinit request carries, each checked as far as it can be without decoding its pixels
    (encoding, sizes, the image's header; else the request is refused), so that this process never loads OpenCV.
    A frame corrupt beyond its header is counted as rejected by the worker, which goes on to the next."""
    for frame in frames:
        try:
            check_frame(frame)
        except FrameError as exc:
            raise ServiceError("frame_rejected", f"the request's frame {frame.seq} is not an image: {exc}") from None
    return [StoredFrame.from_frame(frame, encode(frame)) for frame in frames]


def _has_live_worker(session: Session) -> bool:
    return session.process is not None and session.process.exitcode is None


def _stopped_meanwhile(session: Session, node: str) -> ServiceError:
    return ServiceError("unknown_session", f"session {session.sid!r} on node {node!r} was stopped meanwhile")


def _check_box_in_frame(box: tuple, frame: StoredFrame) -> None:
    problem = box_problem(box, frame.width, frame.height)
    if problem is not None:
        raise ServiceError("invalid_box", f"{problem} (seq {frame.seq})")


def _reap(processes: list, deadline: float, kill_after: float = 0.3) -> None:
    """Wait for processes until `deadline`, then SIGTERM them, then SIGKILL what is left `kill_after` s later."""
    for process in processes:
        process.join(timeout=max(0.0, deadline - time.monotonic()))
    alive = [p for p in processes if p.exitcode is None]
    for process in alive:
        process.terminate()
    kill_at = time.monotonic() + kill_after
    for process in alive:
        process.join(timeout=max(0.0, kill_at - time.monotonic()))
    for process in alive:
        if process.exitcode is None:
            process.kill()
            process.join(timeout=0.5)


def _close_conn(session: Session) -> None:
    worker = session.worker
    session.worker, session.conn = None, None
    if worker is not None:
        worker.close()
