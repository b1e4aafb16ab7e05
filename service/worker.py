"""The worker process of one tracking session.

Each session runs in its own process so that N cores serve N feeds at full speed, forked from a fork server, never
from the service, whose Zenoh runtime does not survive fork (worker_context). The worker opens its own Zenoh
session (client of the service), subscribes to the image key latest-only, runs the tracker on its main thread,
and publishes a BoxResult per processed frame and Health about once a second itself: frames never pass through
the service process.

Latest-only: the subscriber is a RingChannel(1): Zenoh itself overwrites a frame nobody has taken yet, without
needing the GIL, so a starved worker never builds a backlog (a callback subscriber would: its 256-deep FIFO
fills while Python is busy, and frames come out seconds late). A small pump thread moves the ring's frame into
a one-slot LatestFrame that the tracking loop waits on together with commands. Frames lost in the ring are
counted from seq gaps, frames overwritten in the slot directly. The tracker never runs in a Zenoh callback.

Workers are started ahead of need (warm spares, pool.WorkerPool: the process, the tracker's modules and the Zenoh
session are ready), so a start request gets a tracking worker in milliseconds; a worker started on demand tracks
within about 0.3 s when forked from the fork server, 1.5-3 s when spawned.

Parent <-> worker protocol over a multiprocessing Pipe (tuples):
    worker -> parent   ("idle",)                           warm and waiting for an assignment; repeated every
                                                           IDLE_HEARTBEAT_S until assigned, so that the service
                                                           can tell a wedged spare from a waiting one
                       ("ready",)                          assigned, subscribed, tracker built: send the init
                       ("result", seq, box, ok)            per processed frame (the parent keeps the last box)
                       ("health", health_msgpack)          about 1 Hz
                       ("failed", message, generation)     the tracker cannot be initialised: a bad box (the
                                                           generation of its init), its config (None: any init)
                       ("initialised", seq, generation)    the tracker was initialised on frame seq, by the init
                                                           of that generation
    parent -> worker   ("assign", Assignment)              become the worker of this session
                       ("init", box, [frame payloads], generation)
                                                           init on the first decodable payload, catch up through
                                                           the rest; [] = init on the next live frame. The
                                                           generation counts the session's inits, so that the
                                                           service can tell a reply to an init it has replaced
                       ("unserved", count)                 frames of the key that came while the session had no
                                                           worker, not among the init's: received and dropped
                       ("stop",)
The worker also stops when the pipe breaks (the service died), so no worker outlives its service.
"""
from __future__ import annotations

import contextlib
import logging
import math
import multiprocessing
import multiprocessing.context
import multiprocessing.forkserver
import multiprocessing.popen_forkserver
import multiprocessing.resource_tracker
import os
import signal
import threading
import time
from dataclasses import dataclass, field

from tacf.log_throttle import LogThrottle
from tacf.stop_signals import STOP_SIGNALS, hold_stop_signals, release_stop_signals, restore_signal_mask

from .config import ZenohOptions
from .trackers import DEFAULT_FACTORY

log = logging.getLogger(__name__)

HEALTH_PERIOD_S = 1.0
IDLE_HEARTBEAT_S = 1.0      # a spare repeats "idle" this often (pool.SPARE_SILENCE_S: silent longer, it is hung)
STALL_S = 2.0               # no frame for this long: health says the session is waiting for frames
NOTICE_HOLD_S = 5.0         # a rejected frame's reason stays in health this long after the last one: a session
                            # tracking well again is not shown with the problem of one frame minutes before
STALE_WINDOW = 64           # a frame up to this many seqs behind the last one used, and not newer, is stale
MAX_SEQ_GAP = 1000          # a larger seq jump is a publisher restart or a bogus seq, not frames lost in the ring
# Zenoh priorities, by name (Zenoh loads only after the fork): above the frames' DATA, so that on a link that also
# carries frames Zenoh sends boxes and health ahead of the frames queued for it (docs/thin_link.md).
BOX_PRIORITY, HEALTH_PRIORITY = "INTERACTIVE_HIGH", "DATA_HIGH"
CATCH_UP_BUDGET_S = 0.5     # after the init frame, catch-up frames are used only within this much time
RESIZE_ASPECT_TOLERANCE = 0.02   # a new frame size within this of the old aspect ratio shows the same view
REJECT_LOG_PERIOD_S = 60.0  # rejected frames are logged once in this long at most, with the count of those left out:
                            # a camera sending bad frames for days wrote a line every 100 of them to the edge's card
COMMAND_POLL_S = 0.1
# A SIGTERM the service did not send (it had not asked to stop) ends a worker or the fork server this much later, unless
# the service asks them to stop first, as it does within its shutdown after a signal to the whole process group.
SIGTERM_GRACE_S = 3.0


@dataclass(frozen=True)
class WorkerSpec:
    """What every worker process of a service shares, pickled across the spawn boundary."""
    node: str
    zenoh: ZenohOptions = field(default_factory=ZenohOptions)
    endpoints: tuple[str, ...] = ()
    tracker_factory: str = DEFAULT_FACTORY
    log_level: int = logging.INFO


@dataclass(frozen=True)
class Assignment:
    """The session a worker serves."""
    sid: str
    image_key: str
    profile: str
    overrides: dict = field(default_factory=dict)
    restarts: int = 0
    earlier_counts: dict = field(default_factory=dict)     # the frame counters of the session's earlier workers


class LatestFrame:
    """A one-slot mailbox: put() replaces the held payload (counting it as dropped), take() waits for one.

    A payload put with fills_gap has a seq the ring's gap count already counted as received and dropped. Dropped
    here too it was counted twice: overwritten, it adds to gap_fills_dropped, which the counts take off again."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._payload: bytes | None = None
        self._fills_gap = False
        self._woken = False
        self.received = 0
        self.overwritten = 0
        self.gap_fills_dropped = 0
        self.last_put = time.monotonic()

    def put(self, payload: bytes, fills_gap: bool = False) -> None:
        with self._cond:
            self._drop_held()
            self._payload, self._fills_gap = payload, fills_gap
            self.received += 1
            self.last_put = time.monotonic()
            self._cond.notify()

    def wake(self) -> None:
        with self._cond:
            self._woken = True
            self._cond.notify()

    def take(self, timeout: float) -> tuple[bytes | None, bool]:
        """(payload, whether it fills a counted seq gap), or (None, False) on a timeout or wake()."""
        with self._cond:
            self._cond.wait_for(lambda: self._payload is not None or self._woken, timeout)
            taken = self._payload, self._fills_gap
            self._payload, self._fills_gap, self._woken = None, False, False
            return taken

    def discard(self) -> None:
        with self._cond:
            self._drop_held()
            self._payload = None

    def _drop_held(self) -> None:
        if self._payload is not None:
            self.overwritten += 1
            self.gap_fills_dropped += self._fills_gap

    def counts(self) -> tuple[int, int, int]:
        """(received, overwritten, gap_fills_dropped), read together, the payload still waiting left out of
        received: it is neither processed nor dropped yet, and a Health that counted it received did not add up
        (under a feed faster than the tracker, nearly every one)."""
        with self._cond:
            return self.received - (self._payload is not None), self.overwritten, self.gap_fills_dropped


if "forkserver" in multiprocessing.get_all_start_methods():       # its classes are not there on Windows
    class _ForkServerPopen(multiprocessing.popen_forkserver.Popen):
        """The fork server's Popen, whose poll one thread at a time reads. Its exit status comes once, as bytes on the
        sentinel: of two threads polling at once (the supervisor, and Process.start's clean-up of every child in
        another), the second read nothing and took the worker for exited with code 255, over the first's -9 (1 poll
        pair in 8 for a killed process here). Holding the lock never waits: poll reads only a sentinel that is ready."""

        def __init__(self, process_obj):
            self._poll_lock = threading.Lock()
            super().__init__(process_obj)

        def poll(self, flag=os.WNOHANG):
            with self._poll_lock:
                return super().poll(flag)


    class _ForkServerProcess(multiprocessing.context.ForkServerProcess):
        @staticmethod
        def _Popen(process_obj):        # how each context names its Popen (private, the same from 3.4 on)
            return _ForkServerPopen(process_obj)


    class _ForkServerContext(multiprocessing.context.ForkServerContext):
        Process = _ForkServerProcess


def worker_context():
    """Where workers are started. A fork server where the platform has one (Linux, macOS): a process that imported
    numpy, OpenCV and the tracker once (tacf_service.warm), from which each worker is forked, so a worker starts
    without importing anything and shares that memory with the others. Elsewhere a fresh interpreter per worker.
    Never a plain fork of the service, whose Zenoh runtime a child would inherit broken (ZENOH.md 2.5)."""
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return multiprocessing.get_context("spawn")
    context = _ForkServerContext()
    context.set_forkserver_preload(["tacf_service.warm"])
    return context


def stop_workers_and_fork_server() -> None:
    """Kill this process's worker processes, then the workers' fork server if one runs. Workers first: with the
    server dead, multiprocessing takes every worker for exited and would not stop one at exit. Not joined: a hung
    server, their parent, would never report them."""
    for child in multiprocessing.active_children():
        child.kill()
    pid = getattr(multiprocessing.forkserver._forkserver, "_forkserver_pid", None)    # private, the same from 3.4 on
    if pid is not None:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)


def hold_blas_to_one_thread() -> None:
    """One core per session, the service scales by processes: BLAS reads these when numpy loads, so call it first."""
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")


def start_with_stop_signals_held(process) -> None:
    """Start a worker process with STOP_SIGNALS held in this thread. The start may launch the fork server, which then
    holds them from its first instruction until tacf_service.warm takes them over: a Ctrl-C to the whole process
    group as it started ended it with a KeyboardInterrupt traceback, and the service's first worker with it.
    multiprocessing holds them so for its resource tracker (bpo-33613), but unblocks SIGINT and SIGTERM in this
    thread once that one is up: it is started first."""
    if hasattr(signal, "pthread_sigmask"):      # where there is a fork server (not Windows)
        multiprocessing.resource_tracker.ensure_running()
    mask = hold_stop_signals()
    try:
        process.start()
    finally:
        restore_signal_mask(mask)


def take_group_signals(on_sigterm) -> None:
    """Ignore SIGINT and SIGHUP, and give SIGTERM to `on_sigterm`, then release STOP_SIGNALS if they were held (the
    fork server starts with them held). These are the signals a whole process group gets (a terminal's Ctrl-C or
    hangup, systemd's SIGTERM to every process of the unit, `timeout`'s): the service, which gets them too, stops
    its workers and the fork server itself, and a session ends "stopped"; a worker that left first made the service
    report it failed. SIGTERM is also what `kill PID` sends to one process: `on_sigterm` tells the two apart."""
    for sig in STOP_SIGNALS:
        signal.signal(sig, on_sigterm if sig == signal.SIGTERM else signal.SIG_IGN)
    release_stop_signals()


def end_after_grace(*_) -> None:
    """SIGTERM handler of the fork server, and of a worker not asked to stop: end this process SIGTERM_GRACE_S from
    now unless the service asks it to stop first (cancel_grace). A kernel timer, whose SIGALRM's default action
    ends the process even if its main thread is stuck; the fork server may start no thread; a forked child does not
    inherit the timer."""
    if hasattr(signal, "setitimer"):            # not on Windows, whose SIGTERM comes only from the process itself
        signal.setitimer(signal.ITIMER_REAL, SIGTERM_GRACE_S)


def cancel_grace() -> None:
    if hasattr(signal, "setitimer"):
        signal.setitimer(signal.ITIMER_REAL, 0)


def worker_exit_message(process) -> str:
    """A worker's exit, as its session's health says it."""
    code = process.exitcode
    if hasattr(signal, "SIGALRM") and code == -signal.SIGALRM:     # end_after_grace's timer
        return f"worker ended {SIGTERM_GRACE_S:.0f} s after a SIGTERM not from the service"
    if code == 255 and "forkserver" in multiprocessing.get_all_start_methods() and _exists(process.pid):
        # The fork server sends a worker's status once it has reaped it; a server that died sent none, and its
        # Popen says 255 while the worker runs on: "worker exited with code 255" named the wrong process. Only where
        # a fork server can be: on Windows, os.kill(pid, 0) would end the process it asks about.
        return "the workers' fork server died, taking this worker's status with it; the worker is stopped"
    return f"worker exited with code {code}"


def _exists(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except OSError:             # none, or another user's that took the pid over
        return False
    return True


def worker_log_format(sid: str | None = None) -> str:
    """The worker's log lines name its session once it has one: its pid alone named none at INFO, and a restore
    starts several sessions in the same few milliseconds."""
    session = "" if sid is None else f" session {sid}"
    return f"%(asctime)s %(levelname)s worker[{os.getpid()}]{session} %(name)s: %(message)s"


def run_worker(spec: WorkerSpec, conn) -> None:
    """Process entry point (the target of the worker's Process)."""
    hold_blas_to_one_thread()
    logging.basicConfig(level=spec.log_level, format=worker_log_format())
    worker = Worker(spec, conn)
    take_group_signals(worker.on_sigterm)
    try:
        worker.run()
    except Exception:
        log.exception("worker crashed")
        raise SystemExit(1)


class Worker:
    def __init__(self, spec: WorkerSpec, conn) -> None:
        self.spec = spec
        self._conn = conn
        self._send_lock = threading.Lock()
        self._stop = threading.Event()
        self._slot = LatestFrame()
        self._pending_lock = threading.Lock()
        self._pending_init: tuple | None = None
        self._init_generation = 0                # of the init last applied: echoed in "initialised" and "failed"
        self._newest_init_generation = -1        # of the inits received: an older one written after it is stale
        self._tracker = None
        self._init_box: tuple | None = None      # box to initialise on the next frame
        self._image_shape: tuple | None = None   # shape of the frame the tracker was initialised on
        self._last_box: tuple | None = None      # the box of the last frame tracked (or initialised on)
        self._state = "starting"
        self._message: str | None = None         # why the session failed
        self._notice: str | None = None          # the last rejected frame's reason, or a re-initialisation's
        self._notice_until = 0.0                 # monotonic time it leaves health (NOTICE_HOLD_S)
        self._reject_lines = LogThrottle()       # once a REJECT_LOG_PERIOD_S
        self._stats = None
        self._pump: threading.Thread | None = None
        self.job: Assignment | None = None
        self._assigned = _Flag()
        self._connected = False         # the Zenoh session is open
        self._last_frame_id: tuple[int, int] | None = None   # (seq, stamp_ns) of the last frame used
        self._extra_received = 0        # catch-up frames handed over by the service
        self._catching_up = False       # while they are tracked: back to back, not at the feed's rate
        self._skipped = 0               # frames not used: duplicates, no box to track yet, or a reinit came
        self._unserved = 0              # frames that came while the session had no worker (told by the service)
        self._ring_dropped = 0          # frames overwritten in the RingChannel(1) (seq gaps)
        self._gap_fills_skipped = 0     # skipped frames whose seq _ring_dropped had counted (counted twice)

    def on_sigterm(self, *_) -> None:
        """Once the service has asked to stop (a stop command, or its pipe closed), SIGTERM is its own and means now:
        leave at once, even from inside a tracker update. Leaving the `with zenoh.open(...)` block still closes the
        session, which withdraws the session's liveliness token. Before that, the SIGTERM came to the whole process
        group (systemd stopping the unit, `timeout`), and the service, which got it too, asks this worker to stop
        within its shutdown: the session ends "stopped". Or it came by hand (`kill PID`), and nothing follows: the
        worker ends SIGTERM_GRACE_S later, and the service restarts its session as after a crash."""
        if self._stop.is_set():
            raise SystemExit(0)
        end_after_grace()

    def request_stop(self) -> None:
        cancel_grace()
        self._stop.set()
        self._slot.wake()

    # ------------------------------------------------------------------ main loop

    def run(self) -> None:
        import cv2
        import zenoh

        from .config import worker_config
        from .trackers import load_factory, preload

        cv2.setNumThreads(1)
        preload(self.spec.tracker_factory)
        commands = threading.Thread(target=self._read_commands, name="commands", daemon=True)
        commands.start()
        conf = worker_config(self.spec.zenoh, list(self.spec.endpoints))
        try:
            with zenoh.open(conf) as session:
                self._connected = True
                assigned = False
                while not assigned and not self._stop.is_set():
                    self._send(("idle",))
                    assigned = self._assigned.wait_until(self._stop, IDLE_HEARTBEAT_S)
                if assigned:
                    for handler in logging.getLogger().handlers:
                        handler.setFormatter(logging.Formatter(worker_log_format(self.job.sid)))
                    try:
                        self._tracker = load_factory(self.spec.tracker_factory)(self.job.profile,
                                                                                self.job.overrides)
                    except (ValueError, TypeError) as exc:
                        self._state = "failed"
                        self._send(("failed", f"tracker config: {exc}", None))
                    else:
                        self._serve(session, zenoh)
        finally:
            # the session is closed: the pump's recv() has ended; join so no thread is inside zenoh at exit
            if self._pump is not None:
                self._pump.join(timeout=0.5)
            commands.join(timeout=0.5)

    def _serve(self, session, zenoh) -> None:
        """Track the assigned session until stopped."""
        from tacf_schemas import MSGPACK_ENCODING, box_key, health_key, session_liveliness_key

        from .health import HealthStats

        self._stats = HealthStats(self.job.earlier_counts)
        encoding = zenoh.Encoding(MSGPACK_ENCODING)
        node, sid = self.spec.node, self.job.sid
        token = session.liveliness().declare_token(session_liveliness_key(node, sid))
        self._box_pub = session.declare_publisher(box_key(node, sid), encoding=encoding, express=True,
                                                  priority=getattr(zenoh.Priority, BOX_PRIORITY))
        self._health_pub = session.declare_publisher(health_key(node, sid), encoding=encoding,
                                                     priority=getattr(zenoh.Priority, HEALTH_PRIORITY))
        frames = session.declare_subscriber(self.job.image_key, zenoh.handlers.RingChannel(1))
        # The stall clock (STALL_S) runs from here, not from the process's start: a spare waited for no frames.
        self._slot.last_put = time.monotonic()
        self._pump = threading.Thread(target=self._pump_frames, args=(frames.handler,), name="frames", daemon=True)
        self._pump.start()
        self._send(("ready",))
        next_health = time.monotonic()
        while not self._stop.is_set():
            self._apply_pending_init()
            payload, fills_gap = self._slot.take(timeout=0.2)
            if payload is not None:
                if self._stop.is_set():
                    self._skip(fills_gap)   # taken as the stop came: dropped, so that the counts add up
                else:
                    self._process(payload, fills_gap)
            if time.monotonic() >= next_health:
                self._publish_health()
                next_health = time.monotonic() + HEALTH_PERIOD_S
        self._state = "stopped"
        frames.undeclare()                  # ends the pump's recv(): no frame comes after the last counts
        self._pump.join(timeout=0.5)
        self._slot.discard()                # a frame still waiting is dropped
        self._publish_health()
        token.undeclare()

    def _pump_frames(self, ring) -> None:
        """Move frames from the RingChannel(1) into the slot; count frames the ring dropped from seq gaps."""
        import zenoh
        last_seq = None
        missing: set[int] = set()           # the recent seqs counted as dropped by the ring
        while True:
            try:
                sample = ring.recv()
            except zenoh.ZError:
                return                      # undeclared or session closed
            payload = sample.payload.to_bytes()
            seq = _peek_seq(payload)
            fills_gap = False
            if seq is not None:
                # only plausible gaps count: a bogus seq must not inflate the counters (past 2**64 msgpack cannot
                # encode the Health and the worker died); a reordered frame does not move last_seq back. One that
                # fills a gap stays in the ring's count, and is taken off it only with its own drop (LatestFrame,
                # _skip): taken off at once, frames_dropped went down when the frame was then used (a camera that
                # restarts its count within STALE_WINDOW seqs sends a new frame with the missing seq). One used
                # counts as a frame of its own: right for a restarted count; a late frame used because it
                # replaced the one after the gap in the slot is then counted twice, which a counter must accept.
                if seq in missing:
                    missing.discard(seq)
                    fills_gap = True
                elif last_seq is not None and 0 < seq - last_seq - 1 <= MAX_SEQ_GAP:
                    self._ring_dropped += seq - last_seq - 1
                    missing = {s for s in missing if s > seq - STALE_WINDOW}
                    missing.update(range(max(last_seq + 1, seq - STALE_WINDOW), seq))
                if last_seq is None or seq > last_seq or last_seq - seq > STALE_WINDOW:
                    if last_seq is not None and seq < last_seq:
                        missing.clear()     # a restarted seq count: the old gaps are not this count's
                    last_seq = seq
            self._slot.put(payload, fills_gap)

    # ------------------------------------------------------------------ commands from the service

    def _read_commands(self) -> None:
        while not self._stop.is_set():
            try:
                if not self._conn.poll(COMMAND_POLL_S):
                    continue
                message = self._conn.recv()
            except (EOFError, OSError):
                self.request_stop()
                if not self._connected:
                    # Still in zenoh.open, which tries to reach the gone service for seconds: end now. A worker the
                    # fork server made after the service had exited lands here, after a stop right after the
                    # service's start: it served nothing, and a warning would be the only trace of that stop.
                    log.debug("service pipe closed before this worker connected: exiting")
                    os._exit(0)
                log.warning("service pipe closed: stopping")
                return
            if message[0] == "assign":
                self.job = message[1]
                self._assigned.set()
            elif message[0] == "init":
                with self._pending_lock:
                    # two reinits at once can be written out of order: the service waits for the newer one
                    if message[3] < self._newest_init_generation:
                        continue
                    self._newest_init_generation = message[3]
                    self._pending_init = (tuple(message[1]), list(message[2]), message[3])
                self._slot.wake()
            elif message[0] == "unserved":
                self._unserved += message[1]
            elif message[0] == "stop":
                self.request_stop()

    def _send(self, message: tuple) -> None:
        try:
            with self._send_lock:
                self._conn.send(message)
        except (BrokenPipeError, EOFError, OSError):
            self.request_stop()

    # ------------------------------------------------------------------ tracking

    def _apply_pending_init(self) -> None:
        with self._pending_lock:
            pending, self._pending_init = self._pending_init, None
        if pending is None:
            return
        box, payloads, self._init_generation = pending
        self._init_box, self._image_shape = box, None
        self._last_frame_id = None          # the init frame may be older than the last frame tracked
        self._stats.last_pme = None         # the replaced target's: none until a frame of the new one is tracked
        self._state, self._message, self._notice = "starting", None, None
        # init on the first decodable payload, then catch up through the newer ones while the budget lasts
        # (a slow tracker would otherwise spend seconds on stale frames); the live feed takes over after
        budget_ends = None
        self._catching_up = True
        try:
            for payload in payloads:
                self._extra_received += 1
                out_of_budget = budget_ends is not None and time.monotonic() > budget_ends
                # after a stop or a newer init the rest is of no use: it delayed them, on CPU other sessions lacked
                if out_of_budget or self._stop.is_set() or self._init_arrived():
                    self._skipped += 1
                    continue
                self._process(payload)
                if budget_ends is None and self._image_shape is not None:
                    budget_ends = time.monotonic() + CATCH_UP_BUDGET_S
        finally:
            self._catching_up = False

    def _init_arrived(self) -> bool:
        """Whether a reinit came in while this frame was being tracked (it is applied before the next one)."""
        with self._pending_lock:
            return self._pending_init is not None

    def _skip(self, fills_gap: bool = False) -> None:
        """Count a frame taken but not used as dropped; one that fills a counted seq gap is dropped already."""
        self._skipped += 1
        self._gap_fills_skipped += fills_gap

    def _process(self, payload: bytes, fills_gap: bool = False) -> None:
        from tacf_schemas import DecodeError, Frame, decode
        from tacf_schemas.images import FrameError, decode_frame

        if self._init_box is None and self._image_shape is None:
            self._skip(fills_gap)                       # not told what to track yet (waiting for init)
            return
        started = time.perf_counter()
        try:
            frame = decode(payload, Frame)
        except DecodeError as exc:
            self._reject(str(exc))
            return
        if _is_stale(frame, self._last_frame_id):
            self._skip(fills_gap)           # a duplicate (e.g. the live copy of the last catch-up frame) or reordered
            return
        try:
            image = decode_frame(frame)
        except FrameError as exc:
            self._reject(str(exc))
            return
        self._last_frame_id = (frame.seq, frame.stamp_ns)
        if self._image_shape is None:
            self._initialise(image, frame)
            return
        if image.shape != self._image_shape:
            self._follow_new_size(image, frame)
            return
        # A tracker with locate() and learn() (tacf.Tracker) gives the box before it learns from the frame: the
        # box is sent in between, so its latency excludes the model update.
        learns_after = hasattr(self._tracker, "locate") and hasattr(self._tracker, "learn")
        try:
            result = self._tracker.locate(image) if learns_after else self._tracker.update(image)
        except Exception as exc:                        # a tracker bug must not kill the session
            log.exception("tracker update failed on seq %d", frame.seq)
            self._reject(f"tracker update failed: {exc}")
            return
        if self._init_arrived():
            self._skip(fills_gap)           # the box is of the target the reinit replaces: never show it
            return
        if not all(math.isfinite(c) for c in result.box):     # a plug-in tracker's bug: no BoxResult can carry it
            self._reject(f"the tracker gave a box that is not finite on seq {frame.seq}: {tuple(result.box)}")
            return
        self._state = "tracking" if result.ok else "lost"
        self._publish_box(frame, result, (time.perf_counter() - started) * 1e3)
        if learns_after:
            try:
                self._tracker.learn()
            except Exception as exc:
                log.exception("tracker learning failed on seq %d", frame.seq)
                self._reject(f"tracker learning failed: {exc}")
                return
        self._stats.processed(frame.seq, frame.stamp_ns, (time.perf_counter() - started) * 1e3, _finite(result.pme),
                              bool(result.ok), live=not self._catching_up)

    def _initialise(self, image, frame) -> None:
        """Initialise the tracker on this frame; counted as processed (no box is published for it), or as rejected
        when the box does not fit it, so that received = processed + dropped + rejected."""
        box = self._init_box
        problem = self._init_problem(image, box)
        if problem is not None:     # a bad box, or a tracker bug on a hostile one: fail the session, not the worker
            self._init_box = None
            self._state, self._message = "failed", f"cannot initialise on seq {frame.seq}: {problem}"
            self._stats.rejected()
            log.warning("%s", self._message)
            self._send(("failed", self._message, self._init_generation))
            self._publish_health()
            return
        self._initialised(image, frame, box)

    def _init_problem(self, image, box: tuple) -> str | None:
        """Initialise the tracker on `image` with `box`; why it cannot, or None (tacf's Tracker refuses before any of
        its state changes: it keeps its target)."""
        from .frames import box_problem
        problem = box_problem(box, image.shape[1], image.shape[0])
        if problem is not None:
            return problem
        try:
            self._tracker.init(image, box)
        except Exception as exc:
            return str(exc)
        return None

    def _initialised(self, image, frame, box: tuple) -> None:
        self._image_shape, self._last_box = image.shape, tuple(box)
        self._init_box = None
        self._state = "tracking"
        self._stats.processed(frame.seq, frame.stamp_ns, None, None, True, live=False)
        self._send(("initialised", frame.seq, self._init_generation))
        log.info("initialised on seq %d with box %s", frame.seq, box)

    def _follow_new_size(self, image, frame) -> None:
        """A feed whose frame size changes (a stream adapting its resolution to the link, a camera reopened, a
        colour camera switching to grey) mostly shows the same view: the tracker starts again on this frame from
        the last box, scaled. A different aspect ratio is a different view (a crop) that no scaling maps: the
        session is then lost until a reinit gives it a box on the new frames."""
        (old_height, old_width), (height, width) = self._image_shape[:2], image.shape[:2]
        scale_x, scale_y = width / old_width, height / old_height
        change = f"frame size {old_width}x{old_height} -> {width}x{height}"
        if abs(scale_x / scale_y - 1.0) > RESIZE_ASPECT_TOLERANCE:
            self._state = "lost"
            self._reject(f"{change} changes the aspect ratio; reinit the session with a box on the new frames")
            return
        x, y, w, h = self._last_box
        box = (x * scale_x, y * scale_y, w * scale_x, h * scale_y)
        log.info("%s: re-initialising from the last box, scaled", change)
        problem = self._init_problem(image, box)
        if problem is not None:     # a frame too small for the tracker: frames of the old size still are not
            self._state = "lost"
            self._reject(f"{change}: cannot re-initialise from the last box, scaled: {problem}; reinit the session "
                         f"with a box on the new frames")
            return
        self._initialised(image, frame, box)
        self._note(f"{change}: re-initialised on seq {frame.seq} from the last box, scaled")

    def _reject(self, reason: str) -> None:
        self._stats.rejected()
        self._note(reason)
        if (admitted := self._reject_lines.admit(REJECT_LOG_PERIOD_S)) is None:
            return
        more = f" ({admitted.held_back} more in the last {admitted.since_s:.0f} s)" if admitted.held_back else ""
        log.warning("rejected frame (%d so far): %s%s", self._stats.frames_rejected, reason, more)

    def _note(self, notice: str) -> None:
        self._notice, self._notice_until = notice, time.monotonic() + NOTICE_HOLD_S

    def _publish_box(self, frame, result, processing_ms: float) -> None:
        from tacf_schemas import BoxResult, encode
        box = tuple(float(c) for c in result.box)
        self._last_box = box
        message = BoxResult(node=self.spec.node, sid=self.job.sid, seq=frame.seq, stamp_ns=frame.stamp_ns,
                            box=box, width=frame.width, height=frame.height, ok=bool(result.ok),
                            pme=_finite(result.pme), score=_finite(result.score), scale=_finite(result.scale),
                            processing_ms=processing_ms, published_ns=time.time_ns())
        self._box_pub.put(encode(message))
        self._send(("result", frame.seq, box, bool(result.ok)))

    def _publish_health(self) -> None:
        from tacf_schemas import encode
        stats = self._stats
        # each read once: the commands thread adds to _unserved, the pump thread to the others meanwhile
        unserved, ring_dropped = self._unserved, self._ring_dropped
        received, overwritten, gap_fills_dropped = self._slot.counts()
        counted_twice = gap_fills_dropped + self._gap_fills_skipped     # both in a seq gap and dropped here
        stats.frames_received = received + ring_dropped + self._extra_received + unserved - counted_twice
        stats.frames_dropped = overwritten + ring_dropped + self._skipped + unserved - counted_twice
        now = time.monotonic()
        message = self._message or (self._notice if now < self._notice_until else None)
        idle_s = now - self._slot.last_put
        if idle_s > STALL_S and self._state not in ("failed", "stopped"):     # a stopped session waits for nothing
            message = f"waiting for frames: none for {idle_s:.0f} s"
        health = stats.snapshot(self.spec.node, self.job.sid, self._state, self.job.restarts, message)
        payload = encode(health)
        try:
            self._health_pub.put(payload)
        except Exception as exc:     # session closing
            log.debug("health put failed: %s", exc)
        self._send(("health", payload))


def _is_stale(frame, last: tuple[int, int] | None) -> bool:
    """Whether `frame` duplicates or precedes the last frame used, `last` = (seq, stamp_ns): a seq at most
    STALE_WINDOW behind and a stamp no newer. A publisher that restarts its seq count has newer stamps, and a
    single frame with a bogus seq or stamp holds the session back for at most STALE_WINDOW frames."""
    if last is None:
        return False
    seq, stamp_ns = last
    return seq - STALE_WINDOW < frame.seq <= seq and frame.stamp_ns <= stamp_ns


def _peek_seq(payload: bytes) -> int | None:
    """A Frame's seq without validating the whole message (None if there is no valid seq): valid as the decoder
    takes it (an integral float is the int, as from a JavaScript publisher), so gaps count for every feed."""
    import msgpack
    from tacf_schemas.models import SEQ
    try:
        unpacker = msgpack.Unpacker(max_buffer_size=len(payload) + 1, max_bin_len=0, max_str_len=64,
                                    max_array_len=0, max_map_len=16)
        unpacker.feed(payload[:256])
        n = unpacker.read_map_header()
        for _ in range(n):
            key = unpacker.unpack()
            if key == "seq":
                return SEQ.validate_python(unpacker.unpack(), strict=True)
            unpacker.skip()
    except Exception:    # msgpack's several error types, pydantic's ValidationError
        return None
    return None


class _Flag:
    """A one-shot event that can also be abandoned by a stop event."""

    def __init__(self) -> None:
        self._event = threading.Event()

    def set(self) -> None:
        self._event.set()

    def wait_until(self, stop: threading.Event, timeout: float) -> bool:
        """True once set; False when `stop` is set or `timeout` seconds passed first."""
        deadline = time.monotonic() + timeout
        while not stop.is_set() and time.monotonic() < deadline:
            if self._event.wait(min(0.1, max(0.0, deadline - time.monotonic()))):
                return True
        return False


def _finite(value) -> float:
    value = float(value)
    return value if value == value and abs(value) != float("inf") else 0.0
