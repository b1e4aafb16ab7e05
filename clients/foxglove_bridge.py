"""`tacf foxglove`: every tracking session in Foxglove (or its open fork Lichtblick), over Foxglove's WebSocket
protocol (foxglove-sdk's server behind a relay that also accepts Lichtblick's name for the protocol,
foxglove_relay.py; no ROS).

    tacf foxglove          # in Foxglove: Open connection > Foxglove WebSocket > ws://127.0.0.1:8765

Topics, for each watched image key K (the key of every listed session, plus the ones given; a session's key's
topics are withdrawn once no session uses it) and session N/S (withdrawn when it goes):
- `/K/image` (foxglove.CompressedImage): the newest frame of K, at most `image_hz` a second, only while someone
  subscribes; JPEG frames go as they came, raw ones are encoded once.
- `/K/tracks` (foxglove.ImageAnnotations): the newest box of every session on K, a rectangle (green while the
  tracker holds the target, red while it reports it lost; none from a failed worker's last box) labelled with the
  session id and PME; each rectangle and label, and the message when all its boxes are on one frame (else it has
  no stamp, which Foxglove would let override theirs), carries the stamp of the frame its box was computed on
  (images carry their frames' stamps too). Each rectangle's metadata carries node, sid, seq, ok and pme.
- `/tacf/N/S` (JSON, schema SESSION_SCHEMA): the session as the dashboard's /api/state shows it (box, PME, health:
  fps, latency, frame counts), on every change: a Plot panel plots e.g. `/tacf/N/S.health.fps`.
With `record` (`--record FILE.mcap`) everything published, images included at the same rate, is also written
to an MCAP file, which Foxglove opens to replay the flight.
Services (JSON, e.g. from the Service Call panel): `/tacf/start` (the fields of a start request: image_key, box,
and optionally seq, sid, profile, overrides, node), `/tacf/reinit` (sid, box, seq, node), `/tacf/stop` (sid, node)
and `/tacf/list`; replies are SessionInfo JSON (a list for /tacf/list), failures the service's error message.
Foxglove's protocol has no authentication, so the services are offered on a loopback address only, unless
`control=True`; web pages connect only from the origins the relay lets in (foxglove_relay.origin_allowed).
A viewer that subscribes to a topic is sent its newest message at once (a paused camera's last frame, the boxes
on it, a session that no longer changes), not only the next change.

The data side is the dashboard's (Dashboard: latest-only, never blocking a Zenoh thread); this module only turns
its state into Foxglove messages, from one thread.
"""
from __future__ import annotations

import json
import logging
import secrets
import ssl
import threading
import time
from collections import Counter
from pathlib import Path

import foxglove
from foxglove.channels import CompressedImageChannel, ImageAnnotationsChannel
from foxglove.messages import (Color, CompressedImage, ImageAnnotations, KeyValuePair, Point2, PointsAnnotation,
                               PointsAnnotationType, TextAnnotation, Timestamp)
from pydantic import ValidationError

from tacf_clients.dashboard import Dashboard
from tacf_clients.dashboard_access import is_loopback
from tacf_clients.foxglove_relay import SubprotocolRelay
from tacf_schemas.codec import RepeatedKeyError, unique_keys
from tacf_schemas.images import FrameError
from tacf_schemas.models import ReinitRequest, StartRequest, StopRequest

log = logging.getLogger(__name__)

DEFAULT_PORT = 8765                 # Foxglove's default WebSocket port
DEFAULT_IMAGE_HZ = 10.0             # viewers keep every image they get: a cap keeps a long session's memory bounded
MESSAGE_BACKLOG = 64                # messages queued per client before the oldest are dropped (SDK default: 1024)
MAX_STAMP_NS = (2**32 - 1) * 1_000_000_000 + 999_999_999    # Foxglove's Timestamp: seconds in 32 bits (2106)
TRACKING, LOST = Color(r=0.2, g=0.9, b=0.3, a=1.0), Color(r=1.0, g=0.25, b=0.2, a=1.0)
LABEL_BACKGROUND = Color(r=0.0, g=0.0, b=0.0, a=0.6)
# The fields of each service's JSON request, as JSON schemas in the subset Lichtblick parses (plain types: no null,
# no anyOf). Lichtblick builds a request writer from the request's schema and offers no service that has none.
_TEXT, _WHOLE = {"type": "string"}, {"type": "integer"}
_BOX = {"type": "array", "items": {"type": "number"}, "description": "x, y, w, h: pixels of the frame `seq`"}
_NODE = {"type": "string", "description": "the service to ask, when several are on the network"}
REQUEST_FIELDS = {
    "start": {"image_key": _TEXT, "box": _BOX, "seq": _WHOLE, "sid": _TEXT, "profile": _TEXT,
              "overrides": {"type": "object", "properties": {}, "description": "TrackerConfig fields"},
              "node": _NODE},
    "reinit": {"sid": _TEXT, "box": _BOX, "seq": _WHOLE, "node": _NODE},
    "stop": {"sid": _TEXT, "node": _NODE},
    "list": {"node": _NODE},
}
# The session topic's JSON (Dashboard's SessionView.to_json), in the same subset: the viewers' Plot and Raw
# Messages panels take field names and types from it (`.health.fps`); box and health are null until they arrive,
# box again after a start or reinit from the dashboard until the tracker's next box (init holds the box given).
_NUMBER = {"type": "number"}
SESSION_SCHEMA = {"type": "object", "properties": {
    "id": _TEXT, "node": _TEXT, "sid": _TEXT, "image_key": _TEXT, "profile": _TEXT, "state": _TEXT,
    "version": _WHOLE, "generation": _WHOLE,
    "init": {"type": "object", "properties": {"seq": _WHOLE, "box": _BOX}},
    "box": {"type": "object", "properties": {
        "seq": _WHOLE, "stamp_ns": _WHOLE, "box": _BOX, "ok": {"type": "boolean"}, "pme": _NUMBER,
        "score": _NUMBER, "scale": _NUMBER, "processing_ms": _NUMBER, "latency_ms": _NUMBER, "age_ms": _NUMBER}},
    "health": {"type": "object", "properties": {
        "fps": _NUMBER, "processing_ms_mean": _NUMBER, "processing_ms_p95": _NUMBER, "frame_age_ms": _NUMBER,
        "frames_received": _WHOLE, "frames_processed": _WHOLE, "frames_dropped": _WHOLE, "frames_rejected": _WHOLE,
        "frames_lost": _WHOLE, "pme": _NUMBER, "last_seq": _WHOLE, "restarts": _WHOLE, "message": _TEXT,
        "age_ms": _NUMBER, "received_age_ms": _NUMBER}},
}}


def _internal_host() -> str:
    """A random address of 127.0.0.0/8 for the SDK's own server. That server checks no Origin: a web page that found
    its address could watch the cameras and call the services past the relay's check. On one of 2**24 addresses
    (and an ephemeral port) no page can find it; on 127.0.0.1 a page could scan the ports in minutes."""
    return "127." + ".".join(str(secrets.randbelow(254) + 1) for _ in range(3))


def _timestamp(ns: int) -> Timestamp:
    """A frame's stamp as Foxglove's Timestamp; the wire allows stamps past 2106, which it cannot hold (a
    camera with a garbage clock): those are shown at its last second rather than failing every message."""
    ns = min(ns, MAX_STAMP_NS)
    return Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


def session_annotations(sessions: list[dict], empty_stamp_ns: int) -> ImageAnnotations:
    """The boxes of the given sessions (as Dashboard.sessions_json gives them) as one ImageAnnotations. Each
    rectangle and label carries the stamp of its own box's frame. Foxglove lets a message's stamp override them all,
    so the message has one only when every box is on the same frame (sessions on one key at different rates are
    not), or none is: the empty message that takes the last boxes off is stamped `empty_stamp_ns`."""
    rectangles, labels, stamps = [], [], set()
    for session in sessions:
        result = session["box"]
        if result is None:
            continue
        x, y, w, h = result["box"]
        colour = TRACKING if result["ok"] else LOST
        stamp = _timestamp(result["stamp_ns"])
        corners = [Point2(x=x, y=y), Point2(x=x + w, y=y), Point2(x=x + w, y=y + h), Point2(x=x, y=y + h)]
        metadata = {"node": session["node"], "sid": session["sid"], "seq": str(result["seq"]),
                    "ok": str(result["ok"]).lower(), "pme": f"{result['pme']:.2f}"}
        rectangles.append(PointsAnnotation(timestamp=stamp, type=PointsAnnotationType.LineLoop, points=corners,
                                           outline_color=colour, thickness=2.0, metadata=_key_values(metadata)))
        labels.append(TextAnnotation(timestamp=stamp, position=Point2(x=x, y=max(y - 2.0, 12.0)), font_size=12.0,
                                     text=f"{session['sid']}  pme {result['pme']:.1f}", text_color=colour,
                                     background_color=LABEL_BACKGROUND))
        stamps.add(result["stamp_ns"])
    if len(stamps) > 1:
        return ImageAnnotations(points=rectangles, texts=labels)
    stamp = _timestamp(stamps.pop() if stamps else empty_stamp_ns)
    return ImageAnnotations(timestamp=stamp, points=rectangles, texts=labels)


def _key_values(pairs: dict[str, str]) -> list[KeyValuePair]:
    return [KeyValuePair(key=k, value=v) for k, v in pairs.items()]


class _Subscriptions(foxglove.websocket.ServerListener):
    """How many client subscriptions each topic has, and which got a new one (the server calls these from its
    own threads)."""

    def __init__(self):
        self._lock = threading.Lock()
        self._count: Counter[str] = Counter()
        self._new: set[str] = set()

    def on_subscribe(self, client, channel) -> None:
        with self._lock:
            self._count[channel.topic] += 1
            self._new.add(channel.topic)

    def take_new(self, topic: str) -> bool:
        """Whether `topic` got a subscriber since the last call: it is owed the newest message, even unchanged. It
        goes to every subscriber and the recording: the SDK's Python API gives no client's sink id (README)."""
        with self._lock:
            if topic not in self._new:
                return False
            self._new.discard(topic)
            return True

    def on_unsubscribe(self, client, channel) -> None:   # also on disconnect and on a channel's removal
        with self._lock:
            self._count[channel.topic] = max(0, self._count[channel.topic] - 1)
            if not self._count[channel.topic]:
                self._new.discard(channel.topic)     # nobody left to owe it to (and a removed topic goes)

    def __contains__(self, topic: str) -> bool:
        with self._lock:
            return self._count[topic] > 0


class FoxgloveBridge:
    """Serves `board`'s sessions to Foxglove clients on ws://host:port (port 0: any free port; see `port`).

    `serve(stop)` publishes until `stop` is set; close() stops the WebSocket server (the board is not closed
    here). control: offer the start/stop/reinit/list services (default: only on a loopback host). tls: a server
    context to serve wss:// only. record: an MCAP file to write everything to (it must not exist yet).
    allow_origins: web page origins let in besides the default ones (SubprotocolRelay).
    The SDK's server listens on a random loopback address of its own (_internal_host); the public address is a
    SubprotocolRelay's, which also lets in Lichtblick and checks web pages' origins (foxglove_relay.py).
    """

    def __init__(self, board: Dashboard, *, host: str = "127.0.0.1", port: int = DEFAULT_PORT,
                 image_hz: float = DEFAULT_IMAGE_HZ, control: bool | None = None,
                 tls: ssl.SSLContext | None = None, record: str | Path | None = None, name: str = "tacf",
                 allow_origins=()):
        if image_hz <= 0:
            raise ValueError(f"image_hz must be positive, got {image_hz}")
        if record is not None:
            _check_recording_path(record)      # before the servers start, which would log as if all were well
        self.board = board
        self.image_period_s = 1.0 / image_hz
        self.control = is_loopback(host) if control is None else control
        self.context = foxglove.Context()         # our own: other Foxglove users in the process are not mixed in
        self._subscriptions = _Subscriptions()
        services = self._services() if self.control else []
        self.server = self.relay = self._recording = None
        try:
            self.internal_host = _internal_host()
            try:
                self.server = self._start_sdk_server(name, services)
            except RuntimeError:    # only 127.0.0.1 is loopback here (macOS): 127.0.0.0/8's others cannot be bound
                log.warning("foxglove: cannot listen on %s; the SDK's server takes a port of 127.0.0.1, which web "
                            "pages on this machine's browser could find by scanning", self.internal_host)
                self.internal_host = "127.0.0.1"
                self.server = self._start_sdk_server(name, services)
            self.relay = SubprotocolRelay(self.server.port, upstream_host=self.internal_host, host=host, port=port,
                                          tls=tls, allow_origins=allow_origins)
            log.info("viewers connect to %s:%d; the SDK's server on %s:%d is internal, behind the relay",
                     host, self.relay.port, self.internal_host, self.server.port)
            # last: a bridge that cannot serve leaves no empty recording behind, which a retry could not overwrite
            if record is not None:
                self._recording = _open_recording(record, self.context)
        except Exception:
            self.close()
            raise
        self._images: dict[str, CompressedImageChannel] = {}
        self._tracks: dict[str, ImageAnnotationsChannel] = {}
        self._session_channels: dict[str, foxglove.Channel] = {}
        self._sent_versions: dict[str, tuple[int, int]] = {}
        self._sent_frames: dict[str, tuple[int, int]] = {}       # key -> (seq, received_ns) last sent
        self._unshowable: set[str] = set()                        # keys whose newest frame is no image
        self._sent_boxes: dict[str, tuple] = {}          # key -> (sid id, seq, ok, stamp_ns) of the boxes last sent
        self._failed_boxes: dict[str, tuple[int, int]] = {}   # sid id -> (seq, stamp_ns) of its box when it failed

    def _start_sdk_server(self, name: str, services: list) -> foxglove.WebSocketServer:
        return foxglove.start_server(
            name=name, host=self.internal_host, port=0, context=self.context, server_listener=self._subscriptions,
            services=services, capabilities=[foxglove.Capability.Services] if services else [],
            supported_encodings=["json"], message_backlog_size=MESSAGE_BACKLOG)

    @property
    def port(self) -> int:
        return self.relay.port

    def close(self) -> None:
        try:
            if self.relay is not None:
                self.relay.close()
        finally:
            if self.server is not None:
                self.server.stop()
            if self._recording is not None:
                self._recording.close()    # writes the MCAP summary: without it the file is read only slowly

    def __enter__(self) -> "FoxgloveBridge":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- publishing -----------------------------------------------------------------------------------------
    def serve(self, stop: threading.Event) -> None:
        next_images = 0.0
        while not stop.is_set() and not self.board.closed.is_set():
            now = time.monotonic()
            try:
                self.publish_sessions()
                if now >= next_images:
                    next_images = now + self.image_period_s
                    self.publish_images()
            except Exception:  # a viewer bridge that stops silently would look like a tracker that stopped
                log.exception("publishing to Foxglove failed")
            self.board.wait_changed(timeout=max(0.0, min(next_images - time.monotonic(), 0.25)))

    def publish_sessions(self) -> None:
        """Each changed session on `/tacf/N/S`, and the boxes of every image key one of them is on."""
        versions = self.board.versions()
        changed = {sid_id for sid_id, version in versions.items() if self._sent_versions.get(sid_id) != version}
        changed |= {sid_id for sid_id in self._session_channels if self._subscriptions.take_new(f"/tacf/{sid_id}")}
        owed_tracks = {key for key in self._tracks if self._subscriptions.take_new(f"/{key}/tracks")}
        gone = self._sent_versions.keys() - versions.keys()
        if not changed and not gone and not owed_tracks:
            return
        sessions, _ = self.board.sessions_json(points_after={k: v[1] for k, v in versions.items()})
        now_ns = time.time_ns()
        for session in sessions:
            if session["id"] in changed:
                self._channel_of(session["id"]).log(session, log_time=now_ns)
        for sid_id in gone:
            channel = self._session_channels.pop(sid_id, None)
            if channel is not None:
                channel.close()
            self._failed_boxes.pop(sid_id, None)
        self._sent_versions = versions
        by_key: dict[str, list[dict]] = {key: [] for key in self._sent_boxes}
        for session in sessions:
            if session["image_key"] is not None and session["state"] != "stopped":
                by_key.setdefault(session["image_key"], []).append(self._without_failed_box(session))
        for key, on_key in by_key.items():
            # a key's annotations change with its boxes (not with health); a key whose last session went away
            # gets one empty message, so that the last rectangle disappears
            boxes = tuple((s["id"], s["box"]["seq"], s["box"]["ok"], s["box"]["stamp_ns"])
                          for s in on_key if s["box"] is not None)
            sent = self._sent_boxes.get(key)
            if sent == boxes and key not in owed_tracks:
                continue
            self._sent_boxes[key] = boxes
            if key not in self._tracks:
                self._tracks[key] = ImageAnnotationsChannel(f"/{key}/tracks", context=self.context)
            # no boxes left: the empty message belongs to the key's newest frame (else to its last boxes' frame)
            empty_stamp_ns = self.board.frame_stamp_ns(key)
            if empty_stamp_ns is None:
                empty_stamp_ns = max((stamp_ns for *_, stamp_ns in sent or ()), default=now_ns)
            self._tracks[key].log(session_annotations(on_key, empty_stamp_ns), log_time=now_ns)
        for key in self._tracks.keys() - self._images.keys():
            if not by_key[key]:          # no session left on a key the board does not watch (it watches 32 at most)
                self._withdraw_tracks(key)

    def _without_failed_box(self, session: dict) -> dict:
        """The session, its box left out while it is the one it had when its worker failed: no tracker is behind
        it, and it sat on the live picture as if tracking until the restarted worker's first box on a new frame."""
        box = session["box"]
        if box is None:
            return session
        mark = (box["seq"], box["stamp_ns"])
        if session["state"] == "failed":
            self._failed_boxes[session["id"]] = mark
        return {**session, "box": None} if self._failed_boxes.get(session["id"]) == mark else session

    def publish_images(self) -> None:
        """The newest frame of each watched key whose image topic somebody subscribes to (or all, recording)."""
        watched = self.board.image_keys()
        for key in self._images.keys() - set(watched):
            self._withdraw(key)
        for key in watched:
            topic = f"/{key}/image"
            if key not in self._images:
                self._images[key] = CompressedImageChannel(topic, context=self.context)
            if topic not in self._subscriptions and self._recording is None:
                continue
            try:
                snap = self.board.frame(key)
            except FrameError as exc:     # a camera sending frames that are no images holds up no other key's
                if key not in self._unshowable:
                    log.warning("cannot show the frames of %s: %s", key, exc)
                    self._unshowable.add(key)
                continue
            self._unshowable.discard(key)
            owed = self._subscriptions.take_new(topic)
            if snap is None or (self._sent_frames.get(key) == (snap.seq, snap.received_ns) and not owed):
                continue
            self._sent_frames[key] = (snap.seq, snap.received_ns)
            self._images[key].log(CompressedImage(timestamp=_timestamp(snap.stamp_ns), frame_id=key,
                                                  data=snap.jpeg, format="jpeg"), log_time=snap.received_ns)

    def _withdraw(self, key: str) -> None:
        """Withdraw the topics of a key no longer watched (no session uses it any more), once its rectangles are
        taken off: the last of its tracks messages, sent by publish_sessions, is an empty one."""
        if self._sent_boxes.get(key, ()) != ():
            return
        self._images.pop(key).close()
        self._sent_frames.pop(key, None)
        self._unshowable.discard(key)
        self._withdraw_tracks(key)

    def _withdraw_tracks(self, key: str) -> None:
        self._sent_boxes.pop(key, None)
        tracks = self._tracks.pop(key, None)
        if tracks is not None:
            tracks.close()

    def _channel_of(self, sid_id: str) -> foxglove.Channel:
        channel = self._session_channels.get(sid_id)
        if channel is None:
            channel = foxglove.Channel(f"/tacf/{sid_id}", message_encoding="json", context=self.context,
                                       schema=foxglove.Schema(name="tacf.Session", encoding="jsonschema",
                                                              data=json.dumps(SESSION_SCHEMA).encode()))
            self._session_channels[sid_id] = channel
        return channel

    # --- control services -------------------------------------------------------------------------------------
    def _services(self) -> list[foxglove.Service]:
        def service(name: str, handler) -> foxglove.Service:
            request_schema = json.dumps({"type": "object", "properties": REQUEST_FIELDS[name]}).encode()
            # replies are SessionInfo JSON (a list of them for list): no schema, so viewers show them as they are
            schema = foxglove.ServiceSchema(
                name=f"tacf.{name}",
                request=foxglove.MessageSchema(encoding="json", schema=foxglove.Schema(
                    name=f"tacf.{name}_Request", encoding="jsonschema", data=request_schema)),
                response=foxglove.MessageSchema(encoding="json", schema=foxglove.Schema(
                    name=f"tacf.{name}_Response", encoding="jsonschema", data=b"")))
            return foxglove.Service(f"/tacf/{name}", schema=schema, handler=lambda request: _call(handler, request))
        return [service("start", self._start), service("reinit", self._reinit), service("stop", self._stop),
                service("list", self._list)]

    def _start(self, fields: dict) -> bytes:
        node = fields.pop("node", None)
        request = StartRequest.from_wire(fields)
        info = self.board.start(request.image_key, request.box, request.seq, sid=request.sid,
                                profile=request.profile, overrides=request.overrides, node=node)
        return info.model_dump_json().encode()

    def _reinit(self, fields: dict) -> bytes:
        node = fields.pop("node", None)
        request = ReinitRequest.from_wire(fields)
        return self.board.reinit(request.sid, request.box, request.seq, node=node).model_dump_json().encode()

    def _stop(self, fields: dict) -> bytes:
        node = fields.pop("node", None)
        request = StopRequest.from_wire(fields)
        return self.board.stop(request.sid, node=node).model_dump_json().encode()

    def _list(self, fields: dict) -> bytes:
        if set(fields) - {"node"}:
            raise ValueError(f"bad request: unknown fields {sorted(set(fields) - {'node'})}; only node is taken")
        infos = self.board.client.list(node=fields.get("node"))
        return json.dumps([info.model_dump(mode="json") for info in infos]).encode()


def _check_recording_path(path: str | Path) -> None:
    """The errors opening a recording would raise, found before anything starts. _open_recording stays the
    real check (the file could appear in between)."""
    path = Path(path)
    if path.exists():
        raise FileExistsError(f"cannot record to {path}: File exists (a recording is never overwritten)")
    if not path.parent.is_dir():
        raise FileNotFoundError(f"cannot record to {path}: no folder {path.parent}")


def _open_recording(path: str | Path, context: foxglove.Context):
    try:
        return foxglove.open_mcap(path, context=context)
    except OSError as exc:     # the SDK's has no errno: str() of a rebuilt OSError(errno, ...) would say "[Errno None]"
        raise type(exc)(f"cannot record to {path}: {exc}") from None


def _call(handler, request) -> bytes:
    """Run a service handler on a request's JSON payload (the server refuses other encodings). An exception's
    text is what the Foxglove client is shown (the SDK replies serviceCallFailure with it); nothing a client
    sends gets further than that."""
    try:
        fields = json.loads(request.payload or b"{}", object_pairs_hook=unique_keys)
    except RepeatedKeyError as exc:             # json would keep the last value and drop the first unseen
        raise ValueError(f"bad request: {exc}: give each field once") from None
    except (ValueError, RecursionError) as exc:      # also a 5000-digit number, and [[[[... too deep
        raise ValueError(f"the request is not JSON: {exc}") from None
    if not isinstance(fields, dict):
        raise ValueError("the request must be a JSON object")
    try:
        return handler(fields)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc'])) or 'request'}: {e['msg']}" for e in exc.errors())
        raise ValueError(f"bad request: {problems}") from None
    except Exception as exc:
        log.info("%s failed: %s", request.service_name, exc)
        raise ValueError(f"{type(exc).__name__}: {exc}") from None
