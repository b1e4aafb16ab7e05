"""Ground-station API: start, stop, re-initialise, list and watch tracking sessions on any service.

    with TrackingClient() as client:                       # loopback: tcp/127.0.0.1:7447, scouting off
        info = client.start("uav1/camera/front", (410, 220, 60, 40))
        with client.subscribe(info.sid, on_box=print, on_health=print):
            time.sleep(10)
        client.stop(info.sid)

Every call is one Zenoh query on tacf/<node>/control/<op> (a wildcard node when none is given) with a timeout;
error replies raise the exception class of their code (tacf_clients.errors), a silent service raises
RequestTimeout, no service at all raises NoService, a bad id InvalidId, a session that cannot open (a Zenoh
client with no node reachable) ZenohUnavailable, and a call after close() ClientClosed.

Several services (edge boxes) on one network: `start(..., node=LEAST_LOADED)` picks one (see `least_loaded`),
and `watch_nodes()` reports services appearing and disappearing through their liveliness tokens.
"""
from __future__ import annotations

import logging
import numbers
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import pydantic
import zenoh

from tacf.log_throttle import LogThrottle
from tacf_clients.errors import (AmbiguousNode, AmbiguousSession, ClientClosed, InvalidBox, InvalidId, InvalidKey,
                                 InvalidRequest, NoService, ProtocolError, RequestTimeout, TacfError, TooManySessions,
                                 UnknownSession, as_invalid_id, error_from_wire)
from tacf_clients.stream import ResultStream
from tacf_clients.zconfig import ZenohOptions, open_session
from tacf_schemas import keys
from tacf_schemas.codec import MSGPACK_ENCODING, DecodeError, decode, decode_error_reply, encode, is_deadline_reply
from tacf_schemas.models import (BoxResult, Error, Frame, Health, ListRequest, ReinitRequest, SessionInfo,
                                 SessionList, StartRequest, StatusRequest, StopRequest, WireModel)

log = logging.getLogger(__name__)

DEFAULT_TIMEOUT = 5.0
# A start is answered once its worker process is forked, and the service's first start waits for the fork server
# that forks them to load the tracker: 5.7 s with numba's cache empty (a fresh install; 2-core VM, 2026-12-07), and
# more on a busier machine. With DEFAULT_TIMEOUT it failed there, while the session was created all the same.
START_TIMEOUT = 30.0
SETTLE_POLL_S = 0.005   # how often a lookup that may end early looks for replies
BoxLike = Sequence[float]
#: `start(..., node=LEAST_LOADED)` runs the session on the least-loaded service ("auto", an id no service takes).
LEAST_LOADED = keys.LEAST_LOADED
# Read by API callers and, through the command line's error line, by people at a shell.
SAY_WHICH_NODE = "pass node=... (--node on the command line)"


@dataclass(frozen=True)
class _Reply:
    node: str | None
    model: WireModel | None      # the decoded ok reply
    error: TacfError | None      # or the error


class TrackingClient:
    """Control and observe tracking sessions.

    session: an open zenoh.Session to use (not closed by the client); otherwise the client opens one from
    `options` (ZenohOptions; None = loopback defaults) and closes it in `close()`.
    node: the service to address by default; None = whichever service holds the session (and, for `start`,
    the only service on the network). LEAST_LOADED is refused here: it is a choice for `start` only.
    timeout: seconds each call may take, however many queries it makes (a start with no node lists the services
    first; a session whose service is not known yet is looked for first). None: DEFAULT_TIMEOUT, and START_TIMEOUT
    for a start.
    """

    def __init__(self, options: ZenohOptions | None = None, *, session: zenoh.Session | None = None,
                 node: str | None = None, timeout: float | None = None):
        if node == LEAST_LOADED:
            raise ValueError(f"node={LEAST_LOADED!r} is for start(); leave the client's node unset")
        with as_invalid_id():
            self.node = keys.validate_id(node, "node id") if node is not None else None
        self.timeout = DEFAULT_TIMEOUT if timeout is None else timeout
        self.start_timeout = START_TIMEOUT if timeout is None else timeout
        self._own_session = session is None
        self.session = session if session is not None else open_session(options)
        self._nodes_of_sid: dict[str, str] = {}
        self._lock = threading.Lock()

    # --- lifetime ---------------------------------------------------------------------------------------------
    def close(self) -> None:
        if self._own_session:
            self.session.close()

    def __enter__(self) -> "TrackingClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _open_session(self) -> zenoh.Session:
        """The Zenoh session, to make a call on. Once closed, Zenoh raised its own ZError ("session closed"), which
        callers catching TacfError did not expect."""
        if self.session.is_closed():
            raise ClientClosed("client is closed" if self._own_session else
                               "client is closed: the Zenoh session it was given is closed")
        return self.session

    # --- control ops --------------------------------------------------------------------------------------------
    def start(self, image_key: str, box: BoxLike, seq: int | None = None, profile: str | None = None, *,
              sid: str | None = None, overrides: dict[str, bool | int | float] | None = None,
              node: str | None = None, frames: Sequence[Frame] = ()) -> SessionInfo:
        """Start following the target in `box` (x, y, w, h pixels) on the frames of `image_key`.

        seq: the frame the box was drawn on (the service applies it to that frame if it still holds it).
        frames: that Frame itself, when you have it, then up to 7 newer ones (oldest first): the service then
        initialises on it and catches up through them even when it does not hold them (it keeps a feed's frames
        only while a session follows it).
        sid: a session id of your choice (else the service makes one). node: the service to run it on; needed
        only when several services are on the network; LEAST_LOADED picks one (see `least_loaded`).
        """
        request = _build(StartRequest, image_key=_image_key(image_key), box=_box(box), seq=seq, frames=list(frames),
                         sid=sid, profile=profile, overrides=dict(overrides or {}))
        deadline, target = self._deadline(self.start_timeout), node or self.node
        # Finding the service is a list: it gets a list's time, not the start's (given the start's 30 s, with zenoh
        # 1.5, the oldest we take, a start by the Foxglove bridge was not answered within 15 s)
        lookup_deadline = min(deadline, self._deadline())
        if target == LEAST_LOADED:                                       # every service, even with self.node set
            listings = self._services(None, lookup_deadline, settle=True)
            target = least_loaded(listings)
            _refuse_twins([listing.node for listing in listings if listing.node == target])
        elif target is None:
            target = self._single_node(lookup_deadline)
        # The service goes on with a start it answers too late: a retry then met duplicate_session, or, without a sid,
        # started a second session on the same target.
        late = (f"; service {target!r} may still start the session: check with status"
                f"{f' {sid!r}' if sid else ''} or list before starting it again")
        info = self._call_one(target, "start", request, SessionInfo, deadline, late)
        self._remember(info)
        return info

    def stop(self, sid: str, *, node: str | None = None) -> SessionInfo:
        """Stop session `sid`; returns its final SessionInfo (state "stopped")."""
        info = self._call_session(sid, node, "stop", _build(StopRequest, sid=_sid(sid)))
        with self._lock:
            self._nodes_of_sid.pop(sid, None)
        return info

    def reinit(self, sid: str, box: BoxLike, seq: int | None = None, *, node: str | None = None,
               frames: Sequence[Frame] = ()) -> SessionInfo:
        """Re-initialise session `sid` on a new box (drawn on frame `seq`, if given; `frames` as for start)."""
        return self._call_session(sid, node, "reinit", _build(ReinitRequest, sid=_sid(sid), box=_box(box), seq=seq,
                                                              frames=list(frames)))

    def status(self, sid: str, *, node: str | None = None) -> SessionInfo:
        """The session's current SessionInfo (state, last box, latest health)."""
        return self._call_session(sid, node, "status", _build(StatusRequest, sid=_sid(sid)))

    def list(self, *, node: str | None = None) -> list[SessionInfo]:
        """Every session on every service that answers (or on `node` only), sorted by node then sid."""
        sessions = [info for listing in self.services(node=node) for info in listing.sessions]
        return sorted(sessions, key=lambda info: (info.node, info.sid))

    def services(self, *, node: str | None = None) -> list[SessionList]:
        """One SessionList per service that answers (a wildcard query on tacf/*/control/list)."""
        return self._services(node or self.node, self._deadline())

    def nodes(self) -> list[str]:
        """Ids of the services that answer a list query."""
        return [listing.node for listing in self.services()]

    def _services(self, node: str | None, deadline: float, settle: bool = False) -> list[SessionList]:
        replies = self._query(node or keys.WILDCARD, "list", ListRequest(), SessionList, deadline, settle)
        listings = [r.model for r in replies if r.model is not None]
        errors = [r.error for r in replies if r.error is not None]
        if not listings and errors:
            raise errors[0]
        if not listings and node:
            raise NoService(f"service {node!r} did not answer")
        seen: dict[str, set[str]] = {}
        for listing in listings:
            for info in listing.sessions:
                seen.setdefault(info.sid, set()).add(info.node)
        with self._lock:                 # remember where each sid lives, unless it lives on several services
            for sid, nodes in seen.items():
                if len(nodes) == 1:
                    self._nodes_of_sid[sid] = next(iter(nodes))
                else:
                    self._nodes_of_sid.pop(sid, None)
        return sorted(listings, key=lambda lst: lst.node)

    def alive_nodes(self) -> list[str]:
        """Ids of the services whose liveliness token is up, whether or not they answer queries."""
        replies = self._open_session().liveliness().get(keys.service_liveliness_key(keys.WILDCARD),
                                                        timeout=self.timeout)
        return sorted({node for r in replies if r.ok is not None and (node := _node_of_token(r.ok.key_expr))})

    def watch_nodes(self, on_change: Callable[[str, bool], None] | None = None) -> "NodeWatch":
        """Follow services appearing (on_change(node, True)) and disappearing (on_change(node, False)), starting
        with those up now. Close the returned watch (or use `with`) to stop."""
        return NodeWatch(self._open_session(), on_change)

    # --- results ------------------------------------------------------------------------------------------------
    def subscribe(self, sid: str = keys.WILDCARD, on_box: Callable[[BoxResult], None] | None = None,
                  on_health: Callable[[Health], None] | None = None, *, node: str | None = None,
                  latest_only: bool = False) -> ResultStream[BoxResult | Health]:
        """Boxes and health of session `sid` ("*" = every session) handed to the callbacks on a worker thread.

        Returns the stream: close it to stop (or use `with`). Without callbacks, iterate the stream instead
        (see `results`).
        """
        def dispatch(item: BoxResult | Health) -> None:
            if isinstance(item, BoxResult):
                if on_box is not None:
                    on_box(item)
            elif on_health is not None:
                on_health(item)

        callback = dispatch if (on_box or on_health) else None
        return self._stream(sid, node, latest_only, callback)

    def results(self, sid: str = keys.WILDCARD, *, node: str | None = None,
                latest_only: bool = False) -> ResultStream[BoxResult | Health]:
        """Iterator form of `subscribe`, yielding BoxResult and Health: `with client.results(sid) as stream: for item
        in stream: ...`. Close the stream (the `with`) when done: a loop that breaks out leaves it open, and its Zenoh
        subscriber and callback thread live on until its Zenoh session closes (300 left open: 300 threads)."""
        return self._stream(sid, node, latest_only, None)

    def iter_boxes(self, sid: str, *, node: str | None = None, timeout: float | None = None) -> Iterator[BoxResult]:
        """Yield the session's BoxResults until `timeout` seconds pass without one (None: forever)."""
        with self._stream(sid, node, False, None, leaf="box") as stream:
            while (item := stream.get(timeout)) is not None:
                yield item

    def _stream(self, sid: str, node: str | None, latest_only: bool, callback, leaf: str = "*"):
        if sid != keys.WILDCARD:
            _sid(sid)
        node = node or self.node or (self._nodes_of_sid.get(sid) if sid != keys.WILDCARD else None)
        with as_invalid_id():
            key_expr = f"{keys.session_key(node or keys.WILDCARD, sid)}/{leaf}"
        return ResultStream(self._open_session(), key_expr, _ResultDecoder(), latest_only=latest_only,
                            slot_of=lambda item: (item.node, item.sid, type(item).__name__),
                            callback=callback, name=f"tacf-subscribe-{sid}")

    # --- plumbing -------------------------------------------------------------------------------------------------
    def _remember(self, info: SessionInfo) -> None:
        self._remember_node(info.sid, info.node)

    def _remember_node(self, sid: str, node: str) -> None:
        with self._lock:
            self._nodes_of_sid[sid] = node

    def _deadline(self, timeout: float | None = None) -> float:
        """When the call starting now must end: every query it makes shares its timeout (`self.timeout` if None)."""
        return time.monotonic() + (self.timeout if timeout is None else timeout)

    def _single_node(self, deadline: float) -> str:
        nodes = [listing.node for listing in self._services(None, deadline)]
        if not nodes:
            raise NoService("no tracking service answered on tacf/*/control/list")
        _refuse_twins(nodes)
        if len(nodes) > 1:
            raise AmbiguousNode(f"{len(nodes)} services on the network ({', '.join(nodes)}): {SAY_WHICH_NODE}")
        return nodes[0]

    def _call_session(self, sid: str, node: str | None, op: str, request: WireModel) -> SessionInfo:
        """Call `op` on the service holding `sid`. A node remembered from an earlier reply may be out of date
        (the session was stopped and started elsewhere): then look it up again once."""
        deadline = self._deadline()
        if node or self.node:
            return self._call_one(node or self.node, op, request, SessionInfo, deadline)
        with self._lock:
            cached = self._nodes_of_sid.get(sid)
        if cached is not None:
            try:
                return self._call_one(cached, op, request, SessionInfo, deadline)
            except (UnknownSession, NoService):
                with self._lock:
                    self._nodes_of_sid.pop(sid, None)
        return self._call_one(self._find_node(sid, deadline), op, request, SessionInfo, deadline)

    def _find_node(self, sid: str, deadline: float) -> str:
        """The node holding session `sid`, found by a wildcard status query."""
        replies = self._query(keys.WILDCARD, "status", StatusRequest(sid=sid), SessionInfo, deadline, settle=True)
        found = sorted({r.model.node for r in replies if r.model is not None})
        if len(found) > 1:
            raise AmbiguousSession(f"session {sid!r} exists on {', '.join(found)}: {SAY_WHICH_NODE}")
        if found:
            self._remember_node(sid, found[0])
            return found[0]
        if not replies:
            raise NoService("no tracking service answered on tacf/*/control/status")
        # Prefer an error that says more than "not here" (e.g. a timeout of the one service that has it).
        errors = sorted((r.error for r in replies if r.error is not None),
                        key=lambda e: isinstance(e, UnknownSession))
        raise errors[0] if errors else UnknownSession(f"unknown session {sid!r}")

    def _call_one(self, node: str, op: str, request: WireModel, reply_model: type[WireModel], deadline: float,
                  late: str = ""):
        """`op` on one service: `node` is an id, never "*" (a start or stop on every service at once). `late` is
        added to the message of a RequestTimeout for a query sent and not answered in time."""
        with as_invalid_id():
            keys.validate_id(node, "node id")
        replies = self._query(node, op, request, reply_model, deadline, late=late)
        if not replies:
            raise NoService(f"no tracking service {node!r} answered on {keys.control_key(node, op)}")
        for reply in replies:
            if reply.model is not None:
                return reply.model
        raise replies[0].error

    def _query(self, node: str, op: str, request: WireModel, reply_model: type[WireModel], deadline: float,
               settle: bool = False, late: str = "") -> list[_Reply]:
        """The replies to `op` on `node` (a wildcard asks every service) until `deadline`. A lookup before the
        call itself (which service, where a session is) passes `settle`: once half the time is gone and a service
        has answered, it waits no longer for one that does not answer (hung, or going out of reach until its lease
        ends, 10 s), which took the call's whole time and failed every call without a node."""
        with as_invalid_id():
            key = keys.control_key(node, op)
        now = time.monotonic()
        remaining = deadline - now
        if remaining <= 0:                       # the queries before this one took the call's whole timeout
            raise RequestTimeout(f"no time left for {key}: the queries before it took the call's whole timeout")
        log.debug("query %s %s", key, request)
        handler = self._open_session().get(key, payload=encode(request), encoding=zenoh.Encoding(MSGPACK_ENCODING),
                                           target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE,
                                           timeout=remaining)
        late_message = f"no reply on {key} within {remaining:.3g} s{late}"
        if not settle:
            return [_parse_reply(reply, reply_model, key, late_message) for reply in handler]
        settle_at, replies = now + remaining / 2, []
        while True:
            try:
                reply = handler.try_recv()
            except zenoh.ZError:                 # every service answered, or the deadline passed
                return replies
            if reply is not None:
                replies.append(_parse_reply(reply, reply_model, key, late_message))
            elif time.monotonic() >= deadline or (time.monotonic() >= settle_at
                                                  and any(r.model is not None for r in replies)):
                return replies      # at the deadline too: with zenoh 1.5, try_recv() never raised after the replies
            else:
                time.sleep(SETTLE_POLL_S)


class NodeWatch:
    """The services on the network, from their liveliness tokens (@tacf/<node>), with a callback on changes.

    A killed service's token goes as soon as the kernel closes its sockets (milliseconds); a hung one's only
    when the Zenoh lease expires (transport/link/tx/lease, 10 s by default; ZENOH.md section 6).
    `on_change` runs on a Zenoh callback thread: keep it short.
    """

    def __init__(self, session: zenoh.Session, on_change: Callable[[str, bool], None] | None = None):
        self._on_change = on_change
        self._alive: set[str] = set()
        self._lock = threading.Lock()
        self._subscriber = session.liveliness().declare_subscriber(
            keys.service_liveliness_key(keys.WILDCARD), self._on_sample, history=True)

    @property
    def nodes(self) -> list[str]:
        with self._lock:
            return sorted(self._alive)

    def close(self) -> None:
        """Undeclare the subscriber: a callback subscriber left declared can hang interpreter exit (ZENOH.md 8)."""
        self._subscriber.undeclare()

    def __enter__(self) -> "NodeWatch":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _on_sample(self, sample: zenoh.Sample) -> None:
        node = _node_of_token(sample.key_expr)
        if node is None:
            return
        alive = sample.kind == zenoh.SampleKind.PUT
        with self._lock:
            if (node in self._alive) == alive:     # the history and the live stream may both report a token
                return
            (self._alive.add if alive else self._alive.discard)(node)
        if self._on_change is not None:
            try:
                self._on_change(node, alive)
            except Exception:                      # zenoh would only log it to "zenoh.handlers"
                log.exception("node watch callback failed on %s %s", node, "up" if alive else "down")


def node_load(listing: SessionList) -> float:
    """Tracking seconds per second on a service: the sum over its sessions of fps x mean processing time (from
    their latest Health), i.e. about how many CPU cores its trackers keep busy."""
    return sum(h.fps * h.processing_ms_mean / 1000 for info in listing.sessions if (h := info.health) is not None)


def least_loaded(listings: list[SessionList]) -> str:
    """The service to start a new session on: among those with a free slot, the fewest sessions; ties go to
    the lowest `node_load` (sessions on large or fast frames weigh more), then to the node id (deterministic)."""
    if not listings:
        raise NoService("no tracking service answered on tacf/*/control/list")
    free = [lst for lst in listings if len(lst.sessions) < lst.max_sessions]
    if not free:
        raise TooManySessions(f"every service is full ({', '.join(lst.node for lst in listings)})")
    return min(free, key=lambda lst: (len(lst.sessions), node_load(lst), lst.node)).node


def _refuse_twins(nodes: list[str]) -> None:
    """AmbiguousNode if several of the services that answered have one node id: node=... cannot tell them apart,
    and every query to that node reaches all of them."""
    if twins := sorted({node for node in nodes if nodes.count(node) > 1}):
        raise AmbiguousNode(f"several services answer as node {', '.join(map(repr, twins))}: give each its own "
                            "node id (tacf serve --node); a session started there would run on each of them")


def _node_of_token(key_expr) -> str | None:
    """The node of a service token @tacf/<node> (the only tokens @tacf/* matches); None if malformed."""
    try:
        return keys.parse_liveliness_key(str(key_expr))[0]
    except ValueError:
        log.warning("ignored a malformed liveliness token %r", str(key_expr))     # %r: see _ResultDecoder._warn
        return None


def _parse_reply(reply: zenoh.Reply, reply_model: type[WireModel], key: str, late: str) -> _Reply:
    """The reply decoded, or the error it stands for; `late` is the message of a RequestTimeout."""
    if reply.ok is not None:
        sample = reply.ok
        node = _node_from_key(str(sample.key_expr))
        try:
            return _Reply(node, decode(sample.payload.to_bytes(), reply_model), None)
        except DecodeError as exc:
            return _Reply(node, None, ProtocolError(f"bad {reply_model.__name__} reply on {key}: {exc}", node))
    error = decode_error_reply(reply.err.payload.to_bytes())
    if isinstance(error, Error):
        return _Reply(error.node, None, error_from_wire(error.code, error.message, error.node))
    if is_deadline_reply(error):
        return _Reply(None, None, RequestTimeout(late))
    return _Reply(None, None, ProtocolError(f"undecodable error reply on {key}: {error[:200]!r}"))


def _node_from_key(key: str) -> str | None:
    parts = key.split("/")
    return parts[1] if len(parts) >= 2 and parts[0] == keys.PREFIX else None


MALFORMED_WARNING_PERIOD_S = 10.0


class _ResultDecoder:
    """A results stream's decoder: BoxResult or Health by the key's leaf, None for anything else or a malformed
    payload. It warns of malformed ones at most once per MALFORMED_WARNING_PERIOD_S, with the count held back: a
    service on another schema version sends a box and a health per frame and session, and a warning each (30 lines
    a second) scrolled `tacf watch`'s table away."""

    def __init__(self) -> None:
        self._warnings = LogThrottle()

    def __call__(self, sample: zenoh.Sample) -> BoxResult | Health | None:
        leaf = str(sample.key_expr).rsplit("/", 1)[-1]
        model = {"box": BoxResult, "health": Health}.get(leaf)
        if model is None:
            return None
        try:
            return decode(sample.payload.to_bytes(), model)
        except DecodeError as exc:
            self._warn(leaf, str(sample.key_expr), exc)
            return None

    def _warn(self, leaf: str, key: str, exc: DecodeError) -> None:
        if (admitted := self._warnings.admit(MALFORMED_WARNING_PERIOD_S)) is None:
            return
        held_back = admitted.held_back
        more = f" ({held_back} more malformed results dropped since the last such warning)" if held_back else ""
        # %r: a key may hold any character but # ? * $, so anyone on the network could write terminal escapes
        # (screen clear, window title) and forged log lines to the terminal of `tacf watch`
        log.warning("dropped a malformed %s on %r: %s%s", leaf, key, exc, more)


# --- request validation: the same exception classes as an error reply from the service ---------------------------
def _build(model: type[WireModel], **fields) -> WireModel:
    try:
        return model(**fields)
    except pydantic.ValidationError as exc:
        first = exc.errors(include_url=False, include_input=False)[0]
        where = str(first["loc"][0]) if first["loc"] else ""
        cls = {"box": InvalidBox, "image_key": InvalidKey, "sid": InvalidId}.get(where, InvalidRequest)
        raise cls(f"invalid {model.__name__}: {where or '<root>'}: {first['msg']}") from None


def _box(box: BoxLike) -> tuple[float, float, float, float]:
    # Numbers only (numpy's included): float() would also take "12" or True, which the wire refuses.
    try:
        values = tuple(box)
    except TypeError:
        values = ()
    if len(values) != 4 or not all(isinstance(v, numbers.Real) and not isinstance(v, bool) for v in values):
        raise InvalidBox(f"box must be 4 numbers (x, y, w, h), got {box!r}")
    try:
        return tuple(float(v) for v in values)  # type: ignore[return-value]
    except OverflowError:       # an int past the float range (10**400); not printed: str() of 4,300 digits raises
        raise InvalidBox("box must be 4 numbers (x, y, w, h) a float holds, got one past its range") from None


def _image_key(key: str) -> str:
    try:
        return keys.validate_image_key(key)
    except keys.InvalidKeyError as exc:
        raise InvalidKey(str(exc)) from None


def _sid(sid: object) -> str:
    if not keys.is_valid_id(sid):
        raise InvalidId(f"invalid session id {sid!r}: expected 1-64 characters of [A-Za-z0-9_-]")
    return sid  # type: ignore[return-value]
