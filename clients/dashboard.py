"""`tacf dashboard`, the data side: what the ground-station web page shows, gathered from Zenoh.

    with Dashboard(ZenohOptions.loopback(7447), image_keys=["uav1/camera/front"]) as board:
        board.snapshot()                 # sessions, their latest box and health, chart points, watched keys
        board.frame("uav1/camera/front") # the newest frame of that key, as JPEG

Everything is latest-only (ZENOH.md §3.4): boxes and health arrive through one latest-only ResultStream and
overwrite the session's slot; each watched image key has a RingChannel(1) subscriber whose worker reads at most
`max_frame_fps` frames a second and keeps the last few (so that a box is drawn on its own frame). Readers (the
HTTP side, dashboard_http.py; the Foxglove bridge) copy what they need under a lock and never block a Zenoh
thread, so a slow browser cannot slow the service.

A poller lists the sessions of every service once a second (a Zenoh query): that gives each session's image
key, state and node, and drops sessions that a service no longer lists, and the frames of a key that no session
uses any more (unless it was asked for). A service whose liveliness token goes (killed, or hung past the Zenoh
lease) has its sessions dropped at once, without waiting for the list to say so. The dashboard never imports the
tracker: it only talks to services through TrackingClient.
"""
from __future__ import annotations

import itertools
import logging
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace

import zenoh

from tacf_clients.client import LEAST_LOADED, NodeWatch, TrackingClient
from tacf_clients.errors import TacfError
from tacf_clients.stream import ResultStream
from tacf_clients.zconfig import ZenohOptions, open_session
from tacf_schemas.codec import DecodeError, decode
from tacf_schemas.images import FrameError, check_frame
from tacf_schemas.keys import validate_image_key
from tacf_schemas.limits import MAX_CARRIED_FRAMES
from tacf_schemas.models import BoxResult, Frame, Health, SessionInfo, catch_up_subset

log = logging.getLogger(__name__)

LIST_PERIOD_S = 1.0          # how often the session list is refreshed
LIST_TIMEOUT_S = 2.0         # reply timeout of that list query
SILENT_DROP_S = 30.0         # a session of a node that stopped answering (its token still up) is dropped after this
                             # long without news
REORDER_WINDOW_NS = 10**9    # a box published this much before the one shown crossed it on the way; further back,
                             # the edge box's clock was set back (NTP after boot), and it is news
TOMBSTONE_S = 5.0            # messages still in flight for a session stopped here or whose service's token went are
                             # ignored for this long (or until that service's token is back, or a list shows a new
                             # session under the stopped one's id)
MAX_IMAGE_KEYS = 32          # watched image keys (each one is a subscriber + a thread)
# A key asked for by watch() (the page's "watch" box) that no session uses is let go once no one has looked at its
# frames for this long: else a dashboard up for days reached MAX_IMAGE_KEYS, and new cameras were not shown.
ASKED_IDLE_S = 60.0
KEEP = 32                    # the last frames received, for a box to be drawn on its own frame; a 4K bgr8
KEEP_BYTES = 64 * 2**20      # frame is 25 MB, so the bytes are capped too
SHOWN_KEEP = 64              # frames shown to a browser, kept by seq: an operator may draw a box for seconds,
SHOWN_KEEP_BYTES = 64 * 2**20  # and the start carries the frame it was drawn on (the service may not hold it)
CARRY_BYTES = 32 * 2**20     # at most this much of frames carried by one start (the service takes 48 MiB)

_generations = itertools.count(1)


@dataclass
class ChartPoint:
    """One sample of a session's charts, taken from each Health (about 1 Hz)."""
    # when the dashboard received the health report, ms since the epoch: the page cuts the charts by the
    # dashboard's clock, and an edge box's (without NTP) may be minutes off it
    t_ms: int
    fps: float
    pme: float | None
    processing_ms: float
    frame_age_ms: float | None

    def to_json(self) -> dict:
        return {"t": self.t_ms, "fps": self.fps, "pme": self.pme, "proc": self.processing_ms,
                "age": self.frame_age_ms}


@dataclass
class SessionView:
    """What the dashboard knows of one session. `version` grows on every change; `points_total` counts every
    chart point ever added (the ring keeps the last ones), so a reader can ask for the points it has not seen;
    `generation` is new for each view, so that a reader sees a session stopped and started again with the same
    id as another session (its points and boxes are not the old one's)."""
    node: str
    sid: str
    image_key: str | None = None
    profile: str | None = None
    state: str = "starting"
    created_ns: int | None = None
    box: BoxResult | None = None
    box_received_ns: int | None = None
    health: Health | None = None
    health_received_ns: int | None = None
    points: deque[ChartPoint] = field(default_factory=deque)
    points_total: int = 0
    version: int = 0
    seen: float = field(default_factory=time.monotonic)   # last list entry, box or health
    generation: int = field(default_factory=lambda: next(_generations))
    # (seq, box) of a start or reinit sent from here, until a box on a later frame: the box to draw meanwhile
    # (on a still camera no box comes, and the box from before a reinit is no longer what the tracker follows)
    init: tuple[int, tuple[float, ...]] | None = None
    init_stamp_ns: int | None = None        # the stamp of the init frame, when this dashboard had it

    @property
    def id(self) -> str:
        return f"{self.node}/{self.sid}"

    def to_json(self, now_ns: int) -> dict:
        """The session as the page and /api/state show it (no chart points)."""
        box = self.box
        h = self.health
        return {
            "id": self.id, "node": self.node, "sid": self.sid, "image_key": self.image_key,
            "profile": self.profile, "state": self.state, "version": self.version, "generation": self.generation,
            "init": None if self.init is None else {"seq": self.init[0], "box": list(self.init[1])},
            "box": None if box is None else {
                "seq": box.seq, "stamp_ns": box.stamp_ns, "box": list(box.box), "ok": box.ok, "pme": box.pme,
                "score": box.score, "scale": box.scale, "processing_ms": box.processing_ms,
                # capture -> dashboard latency of the newest box, and how long ago it arrived
                "latency_ms": _ms(self.box_received_ns - box.stamp_ns) if self.box_received_ns else None,
                "age_ms": _ms(now_ns - self.box_received_ns) if self.box_received_ns else None,
            },
            "health": None if h is None else {
                "fps": h.fps, "processing_ms_mean": h.processing_ms_mean, "processing_ms_p95": h.processing_ms_p95,
                "frame_age_ms": h.frame_age_ms, "frames_received": h.frames_received,
                "frames_processed": h.frames_processed, "frames_dropped": h.frames_dropped,
                "frames_rejected": h.frames_rejected, "frames_lost": h.frames_lost, "pme": h.pme,
                "last_seq": h.last_seq,
                "restarts": h.restarts, "message": h.message, "age_ms": _ms(now_ns - h.stamp_ns),
                # by the dashboard's clock: a service's clock may be off by more than a staleness threshold
                "received_age_ms": _ms(now_ns - self.health_received_ns) if self.health_received_ns else None,
            },
        }


def _ms(ns: int) -> float:
    return round(ns / 1e6, 1)


@dataclass(frozen=True)
class FrameSnapshot:
    key: str
    seq: int
    stamp_ns: int
    width: int
    height: int
    jpeg: bytes
    received_ns: int


class FrameWatcher:
    """The newest frames of one image key: a RingChannel(1) subscriber drained by one worker thread that reads
    at most `max_fps` frames a second (the ring keeps only the newest meanwhile). The last KEEP frames stay (at
    most KEEP_BYTES of them, but always the newest), so that a box can be drawn on the very frame it was computed
    on, and the frames shown lately (`SHOWN_KEEP`), so that a box drawn on one can be sent with it. Non-JPEG
    frames are turned into JPEG when someone asks for them."""

    def __init__(self, session: zenoh.Session, key: str, max_fps: float = 30.0):
        self.key = key
        self.received = self.rejected = 0
        self._min_period = 1.0 / max_fps if max_fps > 0 else 0.0
        self._lock = threading.Lock()
        self._frames: deque[tuple[Frame, int]] = deque()   # (frame, received_ns), oldest first
        self._frames_bytes = 0
        self._jpeg: FrameSnapshot | None = None          # the last non-JPEG frame converted
        self._shown: OrderedDict[int, Frame] = OrderedDict()   # seq -> frame, the frames snapshot() returned
        self.viewed_at = time.monotonic()                 # the last snapshot() (a page or viewer showing it)
        self._closed = threading.Event()
        self._sub = session.declare_subscriber(key, zenoh.handlers.RingChannel(1))
        self._thread = threading.Thread(target=self._run, name=f"tacf-dashboard-frames-{key}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            for sample in self._sub:                       # ends when the subscriber is undeclared
                started = time.monotonic()
                try:
                    frame = decode(sample.payload.to_bytes(), Frame)
                    check_frame(frame)                 # its size and header: a raw frame too short is no image
                except (DecodeError, FrameError) as exc:
                    self.rejected += 1
                    log.debug("dropped a malformed frame on %s: %s", self.key, exc)
                    continue
                with self._lock:
                    if self._frames and frame.seq < self._frames[-1][0].seq:
                        self._frames.clear()               # the camera restarted its seq
                        self._frames_bytes = 0
                        self._shown.clear()
                    self._frames.append((frame, time.time_ns()))
                    self._frames_bytes += len(frame.data)
                    while len(self._frames) > 1 and (len(self._frames) > KEEP
                                                     or self._frames_bytes > KEEP_BYTES):
                        self._frames_bytes -= len(self._frames.popleft()[0].data)
                    self.received += 1
                if self._closed.wait(max(0.0, self._min_period - (time.monotonic() - started))):
                    return
        except zenoh.ZError:
            pass                                           # the session closed under us

    @property
    def newest_stamp_ns(self) -> int | None:
        with self._lock:
            return self._frames[-1][0].stamp_ns if self._frames else None

    def snapshot(self, seq: int | None = None) -> FrameSnapshot | None:
        """The newest frame (with seq <= `seq` when given, else the oldest kept) as JPEG; None before the first."""
        self.viewed_at = time.monotonic()
        with self._lock:
            if not self._frames:
                return None
            frame, received_ns = self._frames[-1]
            if seq is not None:
                frame, received_ns = next(((f, r) for f, r in reversed(self._frames) if f.seq <= seq),
                                          self._frames[0])
            self._remember_shown(frame)
            cached = self._jpeg
        if frame.encoding == "jpeg":
            jpeg = frame.data
        elif cached is not None and cached.seq == frame.seq and cached.received_ns == received_ns:
            return cached
        else:
            jpeg = _to_jpeg(frame)
        snap = FrameSnapshot(self.key, frame.seq, frame.stamp_ns, frame.width, frame.height, jpeg, received_ns)
        if frame.encoding != "jpeg":
            with self._lock:
                self._jpeg = snap
        return snap

    def frames_since(self, seq: int) -> list[Frame]:
        """What a start carries for a box drawn on frame `seq`: that frame, then up to MAX_CARRIED_FRAMES - 1
        newer ones evenly spaced, ending on the newest, all from the last frames received and those shown lately
        ([] when frame `seq` is in neither)."""
        with self._lock:
            known = {f.seq: f for f in self._shown.values()}
            known.update((f.seq, f) for f, _ in self._frames)
        if seq not in known:
            return []
        frames = [known[s] for s in sorted(s for s in known if s >= seq)]
        carried = catch_up_subset(frames, MAX_CARRIED_FRAMES - 1)
        while len(carried) > 1 and sum(len(f.data) for f in carried) > CARRY_BYTES:
            carried = catch_up_subset(frames, len(carried) - 2)
        return carried

    def _remember_shown(self, frame: Frame) -> None:
        self._shown[frame.seq] = frame
        self._shown.move_to_end(frame.seq)
        while len(self._shown) > 1 and (len(self._shown) > SHOWN_KEEP or
                                        sum(len(f.data) for f in self._shown.values()) > SHOWN_KEEP_BYTES):
            self._shown.popitem(last=False)

    def close(self) -> None:
        self._closed.set()
        try:
            self._sub.undeclare()
        except zenoh.ZError:
            pass
        self._thread.join(timeout=5.0)


def _to_jpeg(frame: Frame) -> bytes:
    import cv2

    from tacf_schemas.images import decode_frame

    ok, buf = cv2.imencode(".jpg", decode_frame(frame), [cv2.IMWRITE_JPEG_QUALITY, 85])
    if not ok:
        raise ValueError(f"cannot encode frame {frame.seq} as JPEG")
    return buf.tobytes()


class Dashboard:
    """The dashboard's live state: sessions (from list replies, boxes and health), chart history and the newest
    frame of each watched image key; control calls go through TrackingClient.

    options / session: how to reach the Zenoh network (a given session is not closed here).
    image_keys: keys to watch from the start, for good (the key of a session is watched while a session uses it).
    node: only this service (None: every service that answers).
    history_s: how many seconds of chart points each session keeps.
    timeout: of each call to a service, as TrackingClient's (None: 5 s, 30 s for a start, which a cold service's
    first takes seconds to answer).
    """

    def __init__(self, options: ZenohOptions | None = None, *, session: zenoh.Session | None = None,
                 image_keys: Iterable[str] = (), node: str | None = None, history_s: float = 300.0,
                 max_frame_fps: float = 30.0, timeout: float | None = None):
        self._own_session = session is None
        self.session = session if session is not None else open_session(options)
        self.node = node
        self.history_s = history_s
        self.max_frame_fps = max_frame_fps
        self.client = TrackingClient(session=self.session, node=node, timeout=timeout)
        self._list_client = TrackingClient(session=self.session, node=node, timeout=LIST_TIMEOUT_S)
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._sessions: dict[str, SessionView] = {}
        # node/sid -> (when, created_ns of the session stopped here, None when its service's token went)
        self._tombstones: dict[str, tuple[float, int | None]] = {}
        self._watchers: dict[str, FrameWatcher] = {}
        self._pinned: set[str] = set()                    # image_keys: watched for good
        self._asked: dict[str, float] = {}                # key -> when watch() asked for it (monotonic)
        self._nodes: dict[str, int] = {}                  # node -> max_sessions, from the last list round
        self.list_ok_at: float | None = None              # monotonic time of the last list round that ran
        self.list_error: str | None = None
        self.messages = 0                                 # boxes + health received
        self.closed = threading.Event()
        self.started = time.monotonic()
        try:
            self._pinned = {validate_image_key(key) for key in image_keys}
            for key in self._pinned:
                self._watch(key, asked=False)
            self._stream = self.client.subscribe(on_box=self._on_result, on_health=self._on_result,
                                                 latest_only=True)
            self._node_watch = self.client.watch_nodes(self._on_node)
        except Exception:
            self.close()
            raise
        self._poller = threading.Thread(target=self._poll, name="tacf-dashboard-list", daemon=True)
        self._poller.start()

    # --- lifetime -------------------------------------------------------------------------------------------
    def close(self) -> None:
        if self.closed.is_set():
            return
        self.closed.set()
        with self._changed:
            self._changed.notify_all()
        node_watch: NodeWatch | None = getattr(self, "_node_watch", None)
        if node_watch is not None:
            node_watch.close()         # before the session closes: a callback subscriber can hang exit (ZENOH.md 8)
        stream: ResultStream | None = getattr(self, "_stream", None)
        if stream is not None:
            stream.close()
        poller = getattr(self, "_poller", None)
        if poller is not None:
            poller.join(timeout=LIST_TIMEOUT_S + 3)
        with self._lock:
            watchers, self._watchers = list(self._watchers.values()), {}
        for watcher in watchers:
            watcher.close()
        if self._own_session:
            self.session.close()

    def __enter__(self) -> "Dashboard":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- image keys -----------------------------------------------------------------------------------------
    def watch(self, key: str) -> bool:
        """Subscribe to the frames of image key `key` (idempotent), until a session uses it or for as long as
        its frames are looked at (ASKED_IDLE_S). True if it is (now) watched; ValueError for an invalid key or
        when MAX_IMAGE_KEYS are watched already."""
        return self._watch(key, asked=True)

    def _watch(self, key: str, asked: bool) -> bool:
        """watch(); asked=False for a session's key, which is dropped once no session uses it, or a pinned one."""
        key = validate_image_key(key)
        with self._lock:
            if key not in self._watchers:
                if len(self._watchers) >= MAX_IMAGE_KEYS:
                    raise ValueError(f"already watching {MAX_IMAGE_KEYS} image keys")
                if self.closed.is_set():
                    return False
                self._watchers[key] = FrameWatcher(self.session, key, self.max_frame_fps)
                self._changed.notify_all()
                log.info("watching frames on %s", key)
            if asked:
                self._asked[key] = time.monotonic()
        return True

    def frame(self, key: str, seq: int | None = None) -> FrameSnapshot | None:
        """The newest frame of `key` (the newest with seq <= `seq`, when given: the frame a box belongs to)."""
        with self._lock:
            watcher = self._watchers.get(key)
        return None if watcher is None else watcher.snapshot(seq)

    def frame_stamp_ns(self, key: str) -> int | None:
        """The stamp of the newest frame of `key` (None before its first, or when it is not watched)."""
        with self._lock:
            watcher = self._watchers.get(key)
        return None if watcher is None else watcher.newest_stamp_ns

    def image_keys(self) -> list[str]:
        with self._lock:
            return sorted(self._watchers)

    def _drawn_on(self, key: str | None, seq: int | None) -> list[Frame]:
        """The frames to send with a box drawn on frame `seq` of `key` (FrameWatcher.frames_since)."""
        with self._lock:
            watcher = self._watchers.get(key) if key is not None and seq is not None else None
        return [] if watcher is None else watcher.frames_since(seq)

    def frame_counts(self) -> dict[str, tuple[int, int]]:
        """key -> (frames received, frames rejected) by the dashboard's own frame subscribers."""
        with self._lock:
            return {key: (w.received, w.rejected) for key, w in self._watchers.items()}

    # --- results (ResultStream worker thread) ------------------------------------------------------------------
    def _on_result(self, item: BoxResult | Health) -> None:
        sid_id = f"{item.node}/{item.sid}"
        with self._changed:
            self.messages += 1
            if sid_id in self._tombstones or (isinstance(item, Health) and item.state == "stopped"):
                return
            view = self._sessions.get(sid_id)
            if view is None:
                view = self._sessions[sid_id] = SessionView(item.node, item.sid)
            if isinstance(item, BoxResult):
                if view.box is not None and 0 < view.box.published_ns - item.published_ns <= REORDER_WINDOW_NS:
                    return      # reordered: keep the newest (further back is the edge box's clock set back)
                if view.init is not None:
                    # computed before the start or reinit: on an earlier frame, unless the camera restarted its
                    # seq count meanwhile (a later stamp)
                    if item.seq <= view.init[0] and (view.init_stamp_ns is None or
                                                     item.stamp_ns <= view.init_stamp_ns):
                        return
                    view.init = None
                view.box, view.box_received_ns = item, time.time_ns()
            else:
                view.health, view.state, view.health_received_ns = item, item.state, time.time_ns()
                pme = item.pme if item.pme is not None else (view.box.pme if view.box is not None else None)
                received_ms = view.health_received_ns // 1_000_000
                view.points.append(ChartPoint(received_ms, item.fps, pme, item.processing_ms_mean,
                                              item.frame_age_ms))
                view.points_total += 1
                horizon_ms = received_ms - self.history_s * 1000
                while view.points and view.points[0].t_ms < horizon_ms:
                    view.points.popleft()
            view.version += 1
            view.seen = time.monotonic()
            self._changed.notify_all()

    # --- services' liveliness tokens (NodeWatch callback thread) -----------------------------------------------
    def _on_node(self, node: str, alive: bool) -> None:
        """A service's token went: its sessions go now (a killed service says no goodbye, and the list alone would
        keep them SILENT_DROP_S), tombstoned so that a box, health or list reply still in flight does not bring
        them back. Its token back: the tombstones go, so that a service restarted with its --state file shows its
        restored sessions again as soon as it lists them or publishes for them."""
        with self._changed:
            if alive:
                self._tombstones = {k: v for k, v in self._tombstones.items() if not k.startswith(f"{node}/")}
                return
            now = time.monotonic()
            for sid_id in [k for k, view in self._sessions.items() if view.node == node]:
                del self._sessions[sid_id]
                self._tombstones[sid_id] = (now, None)
            self._nodes.pop(node, None)
            self._changed.notify_all()

    # --- session list (poller thread) ------------------------------------------------------------------------
    def _poll(self) -> None:
        while not self.closed.is_set():
            started = time.monotonic()
            try:
                listings = self._list_client.services()
                self._apply_listings(listings)
                self.list_error = None
            except TacfError as exc:
                # NoService and timeouts are normal while no service runs: the dashboard keeps serving.
                self._apply_listings([])
                self.list_error = f"{type(exc).__name__}: {exc}"
            except zenoh.ZError as exc:
                if self.closed.is_set():
                    return
                self.list_error = f"zenoh: {exc}"
            except Exception as exc:  # never let the poller die silently
                log.exception("session list failed")
                self.list_error = f"{type(exc).__name__}: {exc}"
            self.list_ok_at = time.monotonic()
            self.closed.wait(max(0.05, LIST_PERIOD_S - (time.monotonic() - started)))

    def _apply_listings(self, listings) -> None:
        now = time.monotonic()
        answered = {listing.node for listing in listings}
        listed: dict[str, SessionInfo] = {f"{info.node}/{info.sid}": info
                                          for listing in listings for info in listing.sessions}
        to_watch = set()
        with self._changed:
            self._nodes = {listing.node: listing.max_sessions for listing in listings}
            self._tombstones = {k: v for k, v in self._tombstones.items() if now - v[0] < TOMBSTONE_S}
            for sid_id, info in listed.items():
                if sid_id in self._tombstones:
                    stopped_created_ns = self._tombstones[sid_id][1]
                    if stopped_created_ns is None or info.created_ns == stopped_created_ns:
                        continue
                    del self._tombstones[sid_id]           # started again under its id (by another client)
                self._update_from_info(info)
                to_watch.add(info.image_key)
            for sid_id, view in list(self._sessions.items()):
                if sid_id in listed:
                    continue
                gone = view.node in answered and now - view.seen > LIST_PERIOD_S   # its service says it is gone
                silent = now - view.seen > SILENT_DROP_S                            # its service went quiet
                if gone or silent:
                    del self._sessions[sid_id]
            # sessions come and go, and keys asked for are looked at for a while: without this the keys of past
            # ones would use up MAX_IMAGE_KEYS
            self._asked = {key: at for key, at in self._asked.items()
                           if key in self._watchers and now - max(at, self._watchers[key].viewed_at) < ASKED_IDLE_S}
            used = self._pinned | set(self._asked) | {view.image_key for view in self._sessions.values()}
            unused = [self._watchers.pop(key) for key in list(self._watchers) if key not in used]
            self._changed.notify_all()
        for watcher in unused:
            log.info("no session uses %s any more: not watching its frames", watcher.key)
            watcher.close()
        for key in to_watch:
            try:
                self._watch(key, asked=False)
            except ValueError as exc:
                log.debug("not watching %s: %s", key, exc)

    def _update_from_info(self, info: SessionInfo) -> SessionView:
        """Merge a SessionInfo (list, start, reinit reply) into the views; call with the lock held."""
        sid_id = f"{info.node}/{info.sid}"
        view = self._sessions.get(sid_id)
        if view is None or view.created_ns not in (None, info.created_ns):   # stopped and started again elsewhere
            view = self._sessions[sid_id] = SessionView(info.node, info.sid)
        changed = (view.image_key, view.profile, view.state) != (info.image_key, info.profile, info.state)
        view.image_key, view.profile, view.created_ns = info.image_key, info.profile, info.created_ns
        view.state = info.state
        if view.health is None and info.health is not None:
            view.health = info.health
            changed = True
        view.seen = time.monotonic()
        if changed:
            view.version += 1
        return view

    # --- control ----------------------------------------------------------------------------------------------
    def start(self, image_key: str, box: Sequence[float], seq: int | None = None, *, sid: str | None = None,
              profile: str | None = None, overrides: dict | None = None, node: str | None = None) -> SessionInfo:
        """Start a session on `node`; with none (or 'auto'), on this dashboard's service if it has one, else on
        the least-loaded service: an operator's start must not fail because a second service came up."""
        if node in (None, LEAST_LOADED):
            node = self.node or LEAST_LOADED
        frames = self._drawn_on(image_key, seq)
        info = self.client.start(image_key, box, seq=seq, sid=sid, profile=profile, overrides=overrides, node=node,
                                 frames=frames)
        with self._changed:
            self._tombstones.pop(f"{info.node}/{info.sid}", None)
            self._set_init(self._update_from_info(info), info, frames)
            self._changed.notify_all()
        try:
            self._watch(info.image_key, asked=False)
        except ValueError as exc:      # the session runs all the same: a 400 would tell the operator it does not
            log.warning("session %s started, but its frames are not shown: %s", info.sid, exc)
        return info

    def stop(self, sid: str, *, node: str | None = None) -> SessionInfo:
        info = self.client.stop(sid, node=node)
        with self._changed:
            sid_id = f"{info.node}/{info.sid}"
            self._tombstones[sid_id] = (time.monotonic(), info.created_ns)
            self._sessions.pop(sid_id, None)
            self._changed.notify_all()
        return info

    def reinit(self, sid: str, box: Sequence[float], seq: int | None = None, *,
               node: str | None = None) -> SessionInfo:
        with self._lock:
            key = next((v.image_key for v in self._sessions.values()
                        if v.sid == sid and (node is None or v.node == node)), None)
        frames = self._drawn_on(key, seq)
        info = self.client.reinit(sid, box, seq=seq, node=node, frames=frames)
        with self._changed:
            self._set_init(self._update_from_info(info), info, frames)
            self._changed.notify_all()
        return info

    @staticmethod
    def _set_init(view: SessionView, info: SessionInfo, frames: list[Frame]) -> None:
        """The box of a start or reinit reply replaces the view's last box (call with the lock held); `frames`
        are those the request carried, the init frame's stamp among them when the service used one."""
        view.box = view.box_received_ns = None
        view.init = None if info.init_seq is None else (info.init_seq, tuple(info.box))
        view.init_stamp_ns = next((f.stamp_ns for f in frames if f.seq == info.init_seq), None)
        view.version += 1

    # --- readers ----------------------------------------------------------------------------------------------
    def wait_changed(self, timeout: float) -> None:
        """Block until something changes (or `timeout` seconds pass, or the dashboard closes)."""
        with self._changed:
            if not self.closed.is_set():
                self._changed.wait(timeout)

    def versions(self) -> dict[str, tuple[int, int, int]]:
        """sid id -> (version, points_total, generation): cheap, for a reader to see what changed since it last
        looked (another generation: the session was replaced by a new one with the same id)."""
        with self._lock:
            return {k: (v.version, v.points_total, v.generation) for k, v in self._sessions.items()}

    def sessions_json(self, ids: Iterable[str] | None = None, points_after: dict[str, int] | None = None
                      ) -> tuple[list[dict], dict[str, list[dict]]]:
        """(sessions, new chart points by sid id). ids: only these sessions (None: all). points_after: per sid
        id, the points_total the reader already has (only newer points are returned; absent = all kept)."""
        now_ns = time.time_ns()
        points_after = points_after or {}
        with self._lock:
            views = [v for k, v in sorted(self._sessions.items()) if ids is None or k in ids]
            sessions = [v.to_json(now_ns) for v in views]
            points = {}
            for v in views:
                new = v.points_total - points_after.get(v.id, 0)
                if new > 0:
                    kept = list(v.points)[-new:] if new < len(v.points) else list(v.points)
                    points[v.id] = [p.to_json() for p in kept]
        return sessions, points

    def snapshot(self) -> dict:
        """Everything the page needs to draw itself from scratch (GET /api/state)."""
        sessions, points = self.sessions_json()
        with self._lock:
            nodes = dict(self._nodes)
        return {"t": time.time_ns() // 1_000_000, "sessions": sessions, "points": points,
                "keys": self.image_keys(), "nodes": nodes, "history_s": self.history_s,
                "list_error": self.list_error}

    def nodes(self) -> dict[str, int]:
        with self._lock:
            return dict(self._nodes)

    def session_views(self) -> list[SessionView]:
        """Copies of the session views (for /metrics)."""
        with self._lock:
            return [replace(v, points=deque()) for _, v in sorted(self._sessions.items())]

    def healthy(self) -> tuple[bool, str]:
        """(ok, reason): the Zenoh side is open and the session poller ran within the last few periods."""
        if self.closed.is_set():
            return False, "closing"
        if not self._poller.is_alive():
            return False, "session poller stopped"
        if self.list_ok_at is None:
            if time.monotonic() - self.started > 3 * LIST_PERIOD_S + LIST_TIMEOUT_S:
                return False, "no session list round yet"
            return True, "starting"
        age = time.monotonic() - self.list_ok_at
        if age > 3 * LIST_PERIOD_S + LIST_TIMEOUT_S:
            return False, f"session list stalled for {age:.0f} s"
        return True, "ok"
