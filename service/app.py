"""TrackingService: one Zenoh session, the control queryable, the session manager, liveliness; and serve(),
the `tacf serve` main loop with SIGTERM/SIGINT/SIGHUP handling.

    with TrackingService(ServiceOptions(node="edge")) as service:   # in-process (tests)
        ...
    serve(options)                                                  # until SIGTERM/SIGINT/SIGHUP, then clean exit
"""
from __future__ import annotations

import contextlib
import logging
import math
import queue
import signal
import socket
import threading
import time
from dataclasses import dataclass, field

from tacf.stop_signals import STOP_SIGNALS, release_stop_signals
from tacf.zenoh_options import unreadable_file, zenoh_error_text
from tacf_schemas import LEAST_LOADED, sanitise_id, service_liveliness_key, validate_node_id

from .config import WorkerConnectError, ZenohOptions, own_endpoints, service_config, worker_config, worker_endpoints
from .control import ControlServer
from .frames import FrameHistory
from .manager import FRAME_SAVE_PERIOD_S, SessionManager
from .state import StateStore
from .trackers import DEFAULT_FACTORY
from .worker import stop_workers_and_fork_server

log = logging.getLogger(__name__)

SHUTDOWN_BUDGET_S = 1.3     # workers get this long in total; the whole exit stays under 2 s
NODE_CHECK_TIMEOUT_S = 1.0  # the liveliness query ends as soon as every linked node has answered
# The boxes gossip names link within ~10 ms of the open (measured); this long with no new link, all have
GOSSIP_SETTLE_S = 0.2


def default_node_id() -> str:
    node = sanitise_id(socket.gethostname(), fallback="edge")
    return "edge" if node == LEAST_LOADED else node


@dataclass
class ServiceOptions:
    node: str = field(default_factory=default_node_id)
    zenoh: ZenohOptions = field(default_factory=ZenohOptions)
    max_sessions: int = 8
    state_file: str | None = None
    tracker_factory: str = DEFAULT_FACTORY
    init_wait_s: float = 1.0
    spare_workers: int = 1
    state_frame_period_s: float = FRAME_SAVE_PERIOD_S
    log_level: int = logging.INFO


class TrackingService:
    def __init__(self, options: ServiceOptions) -> None:
        validate_node_id(options.node)
        if options.max_sessions < 1:
            raise ValueError("max_sessions must be >= 1")
        if not (math.isfinite(options.init_wait_s) and options.init_wait_s >= 0):     # NaN would wait for ever
            raise ValueError(f"init_wait_s must be finite and >= 0, not {options.init_wait_s}")
        if not (math.isfinite(options.state_frame_period_s) and options.state_frame_period_s >= 0):
            raise ValueError(f"state_frame_period_s must be finite and >= 0, not {options.state_frame_period_s}")
        if not 0 <= options.spare_workers <= options.max_sessions:
            # more could never all be in use, and each is a process started at once (with its own Zenoh session)
            raise ValueError(f"spare_workers must be 0 to max_sessions ({options.max_sessions}), "
                             f"not {options.spare_workers}")
        self.options = options
        self.node = options.node
        self._session = None
        self._token = None
        self._history: FrameHistory | None = None
        self._store: StateStore | None = None
        self.manager: SessionManager | None = None
        self._control: ControlServer | None = None
        self.queries_left_behind: list[threading.Thread] = []    # by close(): the threads still answering them

    def open(self) -> "TrackingService":
        import zenoh
        options = self.options
        # Zenoh checks the endpoints as the config is built: a malformed --listen is refused with its reason here,
        # where worker_endpoints, which skips what it cannot parse, would ask for a --listen as if none were given
        config = service_config(options.zenoh)
        endpoints = worker_endpoints(options.zenoh)
        if options.state_file:
            self._store = StateStore(options.state_file)
            self._store.lock()          # before the session: a service that cannot persist never goes live
        try:
            self._session = zenoh.open(config)          # names a file of its own it cannot read (listener, users)
            _check_worker_files(options.zenoh, endpoints)
            _refuse_a_taken_node(self._session, self.node)
            if own_endpoints(options.zenoh):    # a router the workers would reach instead may come up later
                _check_workers_can_connect(options.zenoh, endpoints)
            self._history = FrameHistory(self._session)
            self.manager = SessionManager(self._session, self.node, self._history, options.zenoh, endpoints,
                                          max_sessions=options.max_sessions, store=self._store,
                                          tracker_factory=options.tracker_factory, init_wait_s=options.init_wait_s,
                                          spare_workers=options.spare_workers,
                                          frame_save_period_s=options.state_frame_period_s, log_level=options.log_level)
            self.manager.restore()
            self.manager.start_supervisor()
            self._control = ControlServer(self._session, self.node, self.manager)
            self._token = self._session.liveliness().declare_token(service_liveliness_key(self.node))
        except BaseException:
            self.close()
            raise
        log.info("tacf service %r ready (workers connect to %s)", self.node, ", ".join(endpoints))
        return self

    def close(self) -> None:
        """Withdraw the service token, stop answering, stop the workers, close the session. Idempotent."""
        started = time.monotonic()
        was_ready = self._token is not None      # not after an open that failed, nor twice
        if self._token is not None:
            _quietly(self._token.undeclare)
            self._token = None
        if self.manager is not None:
            self.manager.begin_shutdown()
        if self._control is not None:
            self.queries_left_behind = self._control.close(timeout=0.5)
            self._control = None
        if self.manager is not None:
            self.manager.shutdown(timeout=SHUTDOWN_BUDGET_S - (time.monotonic() - started))
            self.manager = None
        if self._history is not None:
            self._history.close()
            self._history = None
        if self._session is not None:
            _quietly(self._session.close)
            self._session = None
        if self._store is not None:
            self._store.unlock()        # after the manager's last save
            self._store = None
        if was_ready:
            log.info("tacf service %r stopped in %.2f s", self.node, time.monotonic() - started)

    def __enter__(self) -> "TrackingService":
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()


def serve(options: ServiceOptions) -> int:
    """Run until one of STOP_SIGNALS (SIGHUP too: a closed terminal or ssh session would otherwise end the service
    without saving its table); return the exit code."""
    # Not a threading.Event: a handler runs in the main thread wherever it is, and Event.set() there deadlocked when
    # the main thread was inside Event.wait() holding the lock set() takes. SimpleQueue.put() never waits.
    signalled = queue.SimpleQueue()
    previous = {sig: signal.signal(sig, lambda signum, _: signalled.put(signum)) for sig in STOP_SIGNALS}
    release_stop_signals()      # one that came while `tacf serve` started (tacf.cli held it) stops it as a later one
    import zenoh

    try:
        service = TrackingService(options)
    except ValueError as exc:       # a setting out of its range (InvalidIdError is one): a usage error
        log.error("cannot start the service: %s", exc)
        return 2
    try:
        service.open()
    except zenoh.ZError as exc:     # settings Zenoh refused (a malformed endpoint, a port taken): a usage error
        log.error("cannot start the service: Zenoh%s", options.zenoh.refusal(exc))
        return 2
    except WorkerConnectError as exc:
        log.error("cannot start the service: %s", exc)
        return 2
    except Exception as exc:
        log.error("cannot start the service: %s", exc)
        return 1
    try:
        signum = None
        while signum is None:
            with contextlib.suppress(queue.Empty):     # a timeout: a signal delivered to another thread wakes none
                signum = signalled.get(timeout=0.5)
        log.info("%s received: shutting down", signal.Signals(signum).name)
    finally:
        service.close()
        if service.queries_left_behind:
            # One may wait on a hung fork server, which with the resource tracker it holds would outlive this
            # process. Only here, where nothing else uses the server: a library's process may share it.
            stop_workers_and_fork_server()
            # Woken by that, a thread must end before the interpreter does: one finalised inside a Zenoh call
            # aborts the process ("FATAL: exception not rethrown", exit -6).
            for thread in service.queries_left_behind:
                thread.join(timeout=1.0)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    return 0


def _refuse_a_taken_node(session, node: str) -> None:
    """Two services under one node id both answer every query to it: a start there starts the session on both, whose
    boxes then interleave on one key. Boxes flashed from one SD-card image share a hostname, the default id. The
    check sees the nodes linked as the session opens (those of --connect, and the ones gossip names through them),
    not one found later by multicast scouting; clients name such a clash when they meet it (AmbiguousNode)."""
    _wait_for_gossip_links(session, NODE_CHECK_TIMEOUT_S)
    replies = session.liveliness().get(service_liveliness_key(node), timeout=NODE_CHECK_TIMEOUT_S)
    if any(reply.ok is not None for reply in replies):
        raise RuntimeError(f"another tacf service already runs as node {node!r} on this network; give this one its "
                           "own --node (a service that has just died keeps its token until its link drops: up to "
                           "10 s on a lost network)")


def _check_worker_files(zenoh_options: ZenohOptions, endpoints: list[str]) -> None:
    """WorkerConnectError naming a file of the workers' settings that is not there or that this user may not read:
    the CA that checks the service's certificate, their mutual-TLS certificate or key failed the worker check only
    after its 5 s connect timeout, as "Unable to connect ... Timeout!", naming no file."""
    if problem := unreadable_file(worker_config(zenoh_options, endpoints)):
        raise WorkerConnectError(f"its worker processes cannot use the settings of {zenoh_options.config_file}: "
                                 f"{problem}")


def _wait_for_gossip_links(session, budget_s: float) -> None:
    """Wait until no new Zenoh node has linked for GOSSIP_SETTLE_S (at most `budget_s`). The open returns once the
    --connect nodes are linked, and those answer a liveliness query for their own tokens only (peers do not relay
    for peers): a twin linked to the same box was met through gossip only after the check, and went live."""
    def linked() -> set[str]:
        return {str(zid) for zid in [*session.info.peers_zid(), *session.info.routers_zid()]}

    seen = linked()
    if not seen:                # nothing to gossip with: no node will link through one
        return
    deadline = time.monotonic() + budget_s
    quiet_until = time.monotonic() + GOSSIP_SETTLE_S
    while time.monotonic() < min(deadline, quiet_until):
        time.sleep(0.01)
        if not (now_linked := linked()) <= seen:
            seen |= now_linked
            quiet_until = time.monotonic() + GOSSIP_SETTLE_S


def _check_workers_can_connect(zenoh_options: ZenohOptions, endpoints: list[str]) -> None:
    """Open a session as a worker does, then close it. The settings only workers use (the CA that checks the
    service's certificate, their mutual-TLS certificate, the password they present) used to fail in every worker,
    again and again, while the service said it was ready and accepted starts."""
    import zenoh

    try:
        zenoh.open(worker_config(zenoh_options, endpoints)).close()
    except zenoh.ZError as exc:
        where = f" with the settings of {zenoh_options.config_file}" if zenoh_options.config_file else ""
        raise WorkerConnectError(f"its worker processes cannot connect to it at {', '.join(endpoints)}{where}: "
                                 f"{zenoh_error_text(exc)}") from None


def _quietly(fn) -> None:
    try:
        fn()
    except Exception as exc:
        log.debug("%s: %s", getattr(fn, "__name__", fn), exc)
