"""`tacf mavlink`: a MAVLink camera component for one image key, so that a ground station that speaks MAVLink's
camera tracking protocol (QGroundControl) starts and stops tracking on it and is shown the box.

    tacf mavlink --key uav1/camera/front --link udpout:10.0.0.2:14550      # the ground station's address

It announces itself with a HEARTBEAT (MAV_TYPE_CAMERA, component 100 by default) once a second and answers these
commands, sent as COMMAND_LONG or COMMAND_INT:
- MAV_CMD_CAMERA_TRACK_RECTANGLE: starts a session on the image key with that rectangle (normalised 0..1,
  converted with the size of the newest frame on the key and applied to that frame), or re-initialises the
  running one. ACCEPTED once the service has the session; TEMPORARILY_REJECTED while no frame has been seen on
  the key; DENIED for a rectangle that is not inside 0..1 or is empty; FAILED with the service's refusal.
- MAV_CMD_CAMERA_TRACK_POINT (a click rather than a drag): the same with the square of half-side radius around
  the point, cut to the frame (point_box: x, y normalised to the frame, the radius to its width, 0 one pixel);
  DENIED for values outside 0..1. Its statuses are in point mode, with the box's half-side as their radius
  (point_radius, at most 1).
- MAV_CMD_CAMERA_STOP_TRACKING: stops it (ACCEPTED also when nothing runs), and clears a failed session.
Calls to the service run on one thread of their own, in the order the commands came, so that the loop goes on
answering (heartbeats, statuses, other commands) meanwhile: such a command is answered IN_PROGRESS at once and
every second, then with its result, as MAVLink's command protocol has it. A command repeated while it is in
progress (a ground station that got no answer in time retransmits it) is answered IN_PROGRESS again, not run
twice; the same command with other parameters meanwhile is TEMPORARILY_REJECTED.
- MAV_CMD_SET_MESSAGE_INTERVAL for CAMERA_TRACKING_IMAGE_STATUS: its rate (-1 off, 0 the default 10 Hz).
- MAV_CMD_REQUEST_MESSAGE (and the older MAV_CMD_REQUEST_CAMERA_INFORMATION) for CAMERA_INFORMATION, whose
  flags say CAMERA_CAP_FLAGS_HAS_TRACKING_RECTANGLE and _POINT, or for one CAMERA_TRACKING_IMAGE_STATUS.
- any other command addressed to it: UNSUPPORTED. Commands for other components are left alone, and so are
  broadcast ones (component 0) it does not handle, as a MAVSDK component's are: the autopilot or another component
  answers those, and an UNSUPPORTED from the camera could reach the ground station before their ACCEPTED.
While a session runs it streams CAMERA_TRACKING_IMAGE_STATUS with the newest box (rectangle and centre, target
data IN_STATUS): ACTIVE, plus COASTING while the tracker reports the target lost; one IDLE status follows a stop.
A box older than STALE_BOX_S is not shown (ACTIVE | COASTING, no target data): a frozen box over the video would
say the target stands still. A service that has not answered SERVICE_LOST_CHECKS session checks in a row (killed,
hung, out of reach) turns the status to ERROR; the checks go on, and the status is ACTIVE again once the service
answers that the session runs (a service restarted with --state brings it back).
A session that could not start stays `failed`: its status says ERROR, at the same rate, until a stop clears it or
a new rectangle or point starts it again. So does one that failed on the service, whose checks go on: once the
service runs it again (it restarts a crashed worker) the status is ACTIVE again.
The video itself stays the camera's own (QGroundControl shows its RTSP/UDP stream); only the box travels here.
"""
from __future__ import annotations

import hashlib
import logging
import math
import os
import queue
import re
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import zenoh

from tacf_clients.client import TrackingClient
from tacf_clients.consumer import BoxConsumer, TrackedBox
from tacf_clients.errors import DuplicateSession, RequestTimeout, TacfError, UnknownSession
from tacf_clients.zconfig import ZenohOptions, open_session, zenoh_error_text
from tacf_schemas import keys
from tacf_schemas.codec import DecodeError, decode
from tacf_schemas.models import Frame

os.environ.setdefault("MAVLINK20", "1")             # MAVLink 2: CAMERA_TRACKING_IMAGE_STATUS has a 2-only id
from pymavlink import mavutil  # noqa: E402  (after MAVLINK20 is set)
from pymavlink.dialects.v20 import common as mav  # noqa: E402

log = logging.getLogger(__name__)


def _pymavlink_print(*args, **_) -> None:
    log.debug("pymavlink: %s", " ".join(map(str, args)))


# pymavlink tells each attempt to reconnect a TCP ground station, or a serial device, with print() on stdout: 1.5
# lines a second while the ground station is away, for hours. Debug lines instead; the loop below says it once.
mavutil.print = _pymavlink_print

DEFAULT_STATUS_HZ = 10.0
HEARTBEAT_S = 1.0
SESSION_CHECK_S = 2.0       # how often a running session is asked whether it still runs
SERVICE_LOST_CHECKS = 2     # session checks unanswered in a row before the status says ERROR (one may be a blip)
STALE_BOX_S = 1.0           # a box not followed by a newer one within this long is no longer shown
PROGRESS_S = 1.0            # how often a command in progress is answered IN_PROGRESS again
PROGRESS_UNKNOWN = 255      # COMMAND_ACK.progress when the percentage is not known
LINK_RETRY_S = 1.0          # pause between reconnections to a TCP ground station that went away
VENDOR, MODEL = b"tacf", b"TACF tracker"
TRACKING_CAPABILITIES = mav.CAMERA_CAP_FLAGS_HAS_TRACKING_RECTANGLE | mav.CAMERA_CAP_FLAGS_HAS_TRACKING_POINT
_TRACKING_COMMANDS = {mav.CAMERA_TRACKING_MODE_RECTANGLE: "TRACK_RECTANGLE",
                      mav.CAMERA_TRACKING_MODE_POINT: "TRACK_POINT"}
# A ground station may send any command in either message; the commands answered here read param1-4, which both
# carry as floats, and the target camera id of the tracking commands (param5 of TRACK_RECTANGLE, which
# COMMAND_INT carries as x; param4 of TRACK_POINT; param1 of STOP_TRACKING).
COMMAND_MESSAGES = ["COMMAND_LONG", "COMMAND_INT"]
# pymavlink's network links, each HOST:PORT after its prefix ("udp:" and no prefix at all: UDP as well)
NETWORK_LINKS = ("tcp:", "tcpin:", "udpin:", "udpout:", "udpbcast:", "udp:")
# pymavlink's links that are no HOST:PORT to check: multicast (mcast:[IP:]PORT, or none for its default group) and
# Unix sockets (unix:PATH, uds:PATH)
UNCHECKED_LINKS = ("mcast:", "unix:", "uds:")
# pymavlink's UDP links (udpin, udpout, udpbcast, udp, mcast), whose datagrams each hold whole messages; serial, TCP
# and Unix socket links are byte streams
DATAGRAM_LINKS = (mavutil.mavudp, mavutil.mavmcast)


def signing_key_from_passphrase(passphrase: str) -> bytes:
    """The 32-byte MAVLink 2 signing key of a passphrase: its SHA-256, as MAVProxy's `signing setup` makes it."""
    if not passphrase:
        raise ValueError("the signing passphrase is empty")
    return hashlib.sha256(passphrase.encode()).digest()


def _ascii_field(text: bytes, size: int = 32) -> list[int]:
    return list(text[:size].ljust(size, b"\0"))


def _message_id(param: float) -> int | None:
    return int(param) if math.isfinite(param) else None


def check_link(link: str) -> None:
    """Refuse a network link whose port is not one or whose host does not resolve (ValueError), before it is
    opened: pymavlink's udpout sends to it in silence for ever, and a port over 65535 fails in the loop."""
    prefix = next((p for p in NETWORK_LINKS if link.startswith(p)), None)
    if prefix is None:
        if ":" not in link or link.startswith(("/", *UNCHECKED_LINKS)):
            return                                   # a serial device, or a link pymavlink opens as given
        prefix = ""                                  # pymavlink takes HOST:PORT as UDP
    host, _, port = link[len(prefix):].rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"--link {link!r}: expected {prefix or 'udp:'}HOST:PORT with a port of 1 to 65535")
    try:
        socket.getaddrinfo(host, int(port))
    except (socket.gaierror, UnicodeError) as exc:
        reason = exc.strerror if isinstance(exc, socket.gaierror) else str(exc)
        raise ValueError(f"--link {link!r}: cannot resolve host {host!r} ({reason})") from None


@dataclass
class _Call:
    """A command run on the service thread: `run` returns its MAV_RESULT. `key` is (system, component, command)
    of the ground station's command, None for the component's own session check (no ACK)."""
    run: Callable[[], int]
    key: tuple[int, int, int] | None = None
    params: tuple[float, ...] = ()
    result: int | None = None
    next_progress: float = field(default_factory=lambda: time.monotonic() + PROGRESS_S)


def _precedes(box: TrackedBox, frame: tuple[int, int]) -> bool:
    """Whether `box` was computed on a frame older than `frame` (seq, stamp_ns), i.e. before the session was
    (re)started on it: lower in both seq and stamp, as the service judges stale frames. A camera that restarted
    counts seq from 0 again but stamps its frames later."""
    seq, stamp_ns = frame
    return box.seq < seq and box.stamp_ns < stamp_ns


class MavlinkCamera:
    """The camera component: `serve(stop)` runs it until `stop` is set; close() ends the session it holds.

    link: a pymavlink connection string (`udpout:HOST:PORT` towards a ground station, `udpin:0.0.0.0:PORT`,
    `tcp:HOST:PORT`, or a serial device `/dev/ttyUSB0` with `baud`). session: a zenoh.Session to use (not
    closed here), else one is opened from `options`. signing_key: 32 bytes (signing_key_from_passphrase) to sign
    what it sends and to accept only commands signed with the same key. timeout: of each call to the service, as
    TrackingClient's (None: 5 s, 30 s for a start, which a cold service's first takes seconds to answer).
    """

    def __init__(self, link: str, image_key: str, *, options: ZenohOptions | None = None,
                 session: zenoh.Session | None = None, sid: str | None = None, node: str | None = None,
                 profile: str | None = None, system: int = 1, component: int = mav.MAV_COMP_ID_CAMERA,
                 baud: int = 57600, signing_key: bytes | None = None, timeout: float | None = None):
        self.image_key = keys.validate_image_key(image_key)
        self.sid = keys.validate_id(default_sid(image_key) if sid is None else sid, "session id")
        check_link(link)
        self.profile = profile
        self.component = component
        self.status_interval_s = 1.0 / DEFAULT_STATUS_HZ
        self._own_session = session is None
        self.session = session if session is not None else open_session(options)
        self._frames = self._boxes = None
        try:
            self.client = TrackingClient(session=self.session, node=node, timeout=timeout)
            self._frames = self.session.declare_subscriber(self.image_key, zenoh.handlers.RingChannel(1))
            self._boxes = BoxConsumer(self.session, sid=self.sid, latest_only=True)
            self.mav = mavutil.mavlink_connection(link, baud=baud, source_system=system, source_component=component,
                                                  dialect="common", autoreconnect=True)
            if signing_key is not None:              # MAVLink 2 signing: unsigned or wrongly signed packets are dropped
                self.mav.setup_signing(signing_key, sign_outgoing=True)
        except Exception:
            self.close()
            raise
        self.state = "idle"                          # idle | tracking | failed
        self._mode = mav.CAMERA_TRACKING_MODE_RECTANGLE     # of the last tracking command the service took
        self._held = False                           # the service has a session of ours (to stop on a stop)
        self._lock = threading.Lock()                # state, box and start frame: set by the service thread
        self._calls: queue.Queue[_Call | None] = queue.Queue()
        self._done: queue.Queue[_Call] = queue.Queue()
        self._pending: dict[tuple[int, int, int], _Call] = {}    # commands in progress (the loop's alone)
        self._checking = False                       # a session check is queued or runs
        self._service_thread = threading.Thread(target=self._run_calls, name="tacf-mavlink-service", daemon=True)
        self._service_thread.start()
        self._newest_frame: zenoh.Sample | None = None
        self._box: TrackedBox | None = None
        self._box_arrived = 0.0                      # monotonic time the box arrived
        self._unanswered_checks = 0                  # session checks in a row the service did not answer
        # (seq, stamp_ns) of the frame the session was last (re)started on, until a box of the new start arrives
        self._started_on: tuple[int, int] | None = None
        self._started = time.monotonic()

    @property
    def tracking(self) -> bool:
        return self.state == "tracking"

    # --- the loop ----------------------------------------------------------------------------------------------
    def serve(self, stop: threading.Event) -> None:
        next_heartbeat = next_check = 0.0
        last_status = -math.inf
        link_down = False
        while not stop.is_set():
            try:
                now = time.monotonic()
                if now >= next_heartbeat:
                    self.mav.mav.heartbeat_send(mav.MAV_TYPE_CAMERA, mav.MAV_AUTOPILOT_INVALID, 0, 0,
                                                mav.MAV_STATE_ACTIVE)
                    next_heartbeat = now + HEARTBEAT_S
                # a failed session the service keeps is checked too: it restarts a crashed worker
                checked = self.tracking or (self.state == "failed" and self._held)
                if checked and now >= next_check and not self._checking:
                    self._checking = True
                    self._calls.put(_Call(self._check_session))
                    next_check = now + SESSION_CHECK_S
                self._answer_calls(now)
                self._newest_frame = self._frames.try_recv() or self._newest_frame
                while (box := self._boxes.get(timeout=0)) is not None:
                    with self._lock:
                        if self._started_on is None or not _precedes(box, self._started_on):
                            # boxes arrive in order: once one is from after the (re)start, later ones are too,
                            # even with the seq of a camera that restarted from 0
                            self._box, self._box_arrived, self._started_on = box, now, None
                # timed from the last status with the interval in force now: a faster rate applies at once
                if self.state != "idle" and self.status_interval_s > 0 and now >= last_status + self.status_interval_s:
                    self._send_status()
                    last_status = now
                for message in self._receive_commands(timeout=0.02):
                    self._command(message)
                if link_down:
                    log.info("MAVLink link %s is up again", self.mav.address)
                    link_down = False
            except OSError as exc:
                # a TCP ground station went away, met by a send or a receive: pymavlink connects again on the next.
                # Said once: a ground station switched off for hours failed here every few seconds.
                if not link_down:
                    log.warning("MAVLink link %s is down: %s; reconnecting", self.mav.address, exc)
                    link_down = True
                stop.wait(LINK_RETRY_S)

    def _receive_commands(self, timeout: float) -> list[mav.MAVLink_message]:
        """The commands received within `timeout`: the next one on a stream link, those of the next datagram on a
        UDP link."""
        if not isinstance(self.mav, DATAGRAM_LINKS):
            message = self.mav.recv_match(type=COMMAND_MESSAGES, blocking=True, timeout=timeout)
            return [] if message is None else [message]
        if not self.mav.select(timeout):
            return []
        # pymavlink parses a UDP link as one stream: a datagram that ends inside a message (a stray 0xFD, a
        # truncated packet) kept its parser waiting for the rest, which the next datagrams' commands then made up
        # (6 commands lost to a lone 0xFD). A parser of its own for each datagram starts clean (1 us to make); it
        # skips garbage as BAD_DATA, as the link's does, and shares the link's signing key and replay checks.
        parser = mav.MAVLink(None)
        parser.robust_parsing, parser.signing = True, self.mav.mav.signing
        messages = parser.parse_buffer(self.mav.recv()) or []   # recv(): also how udpin learns its ground station
        for message in messages:
            self.mav.post_message(message)           # pymavlink's bookkeeping, as recv_match does it
        return [m for m in messages if m.get_type() in COMMAND_MESSAGES]

    def _run_calls(self) -> None:
        """The service thread: each call in turn, until close() puts None."""
        for call in iter(self._calls.get, None):
            try:
                call.result = call.run()
            except Exception:                        # a command never ends the component: FAILED, and on we go
                log.exception("a call to the service failed")
                call.result = mav.MAV_RESULT_FAILED
            self._done.put(call)

    def _answer_calls(self, now: float) -> None:
        """Final ACKs of the calls done (and what follows them), IN_PROGRESS again for those still running."""
        while True:
            try:
                call = self._done.get_nowait()
            except queue.Empty:
                break
            if call.key is None:                     # the session check
                self._checking = False
                if call.result != mav.MAV_RESULT_ACCEPTED:
                    self._send_status()              # it changed: IDLE, ERROR, or ACTIVE once the service is back
                continue
            del self._pending[call.key]
            self._ack(call.key, call.result)
            if call.key[2] == mav.MAV_CMD_CAMERA_STOP_TRACKING and call.result == mav.MAV_RESULT_ACCEPTED:
                self._send_status()                  # IDLE, so that the ground station clears its box
        for call in self._pending.values():
            if now >= call.next_progress:
                self._ack(call.key, mav.MAV_RESULT_IN_PROGRESS)
                call.next_progress = now + PROGRESS_S

    def _ack(self, key: tuple[int, int, int], result: int) -> None:
        system, component, command = key
        progress = PROGRESS_UNKNOWN if result == mav.MAV_RESULT_IN_PROGRESS else 0
        self.mav.mav.command_ack_send(command, result, progress, target_system=system, target_component=component)

    def _command(self, message) -> None:
        if message.target_system not in (0, self.mav.mav.srcSystem) or \
                message.target_component not in (0, self.component):
            return                                   # for another system or component
        command, requested = message.command, None
        if message.target_component == 0 and _target_camera(message) not in (0, self.component):
            return                                   # broadcast for another camera, which answers it
        key = (message.get_srcSystem(), message.get_srcComponent(), command)
        params = (message.param1, message.param2, message.param3, message.param4)
        if key in self._pending:
            same = all(a == b or (math.isnan(a) and math.isnan(b)) for a, b in zip(params, self._pending[key].params))
            # a retransmission is answered, not queued again; another command of the kind waits for the first
            self._ack(key, mav.MAV_RESULT_IN_PROGRESS if same else mav.MAV_RESULT_TEMPORARILY_REJECTED)
            return
        try:
            if command == mav.MAV_CMD_CAMERA_TRACK_RECTANGLE:
                result = self._track_rectangle(message)
            elif command == mav.MAV_CMD_CAMERA_TRACK_POINT:
                result = self._track_point(message)
            elif command == mav.MAV_CMD_CAMERA_STOP_TRACKING:
                result = self._stop_tracking()
            elif command == mav.MAV_CMD_SET_MESSAGE_INTERVAL:
                result = self._set_interval(message)
            elif command in (mav.MAV_CMD_REQUEST_MESSAGE, mav.MAV_CMD_REQUEST_CAMERA_INFORMATION):
                requested = (mav.MAVLINK_MSG_ID_CAMERA_INFORMATION
                             if command == mav.MAV_CMD_REQUEST_CAMERA_INFORMATION else _message_id(message.param1))
                known = (mav.MAVLINK_MSG_ID_CAMERA_INFORMATION, mav.MAVLINK_MSG_ID_CAMERA_TRACKING_IMAGE_STATUS)
                result = mav.MAV_RESULT_ACCEPTED if requested in known else mav.MAV_RESULT_UNSUPPORTED
            else:
                result = mav.MAV_RESULT_UNSUPPORTED
        except Exception:                            # a command never ends the component: FAILED, and on we go
            log.exception("command %d failed", command)
            result = mav.MAV_RESULT_FAILED
        if result == mav.MAV_RESULT_UNSUPPORTED and message.target_component == 0:
            return                                   # a broadcast command for some other component
        if isinstance(result, _Call):                # to be run on the service thread
            result.key, result.params = key, params
            self._pending[key] = result
            self._calls.put(result)
            result = mav.MAV_RESULT_IN_PROGRESS
        self._ack(key, result)
        if result != mav.MAV_RESULT_ACCEPTED:
            return
        if requested == mav.MAVLINK_MSG_ID_CAMERA_INFORMATION:
            self._send_camera_information()
        elif requested is not None or command == mav.MAV_CMD_CAMERA_STOP_TRACKING:
            self._send_status()                      # after a stop: IDLE, so that the ground station clears its box

    # --- commands (checked on the loop; what calls the service runs on the service thread) ---------------------
    def _track_rectangle(self, message) -> int | _Call:
        corners = (message.param1, message.param2, message.param3, message.param4)
        x1, y1, x2, y2 = corners
        if not all(math.isfinite(c) and 0.0 <= c <= 1.0 for c in corners) or not (x1 < x2 and y1 < y2):
            log.warning("refused TRACK_RECTANGLE %s: not a rectangle inside 0..1", corners)
            return mav.MAV_RESULT_DENIED
        frame = self._frame_header()
        if frame is None:
            return mav.MAV_RESULT_TEMPORARILY_REJECTED
        box = (x1 * frame.width, y1 * frame.height, (x2 - x1) * frame.width, (y2 - y1) * frame.height)
        return _Call(lambda: self._track(box, frame, mav.CAMERA_TRACKING_MODE_RECTANGLE))

    def _track_point(self, message) -> int | _Call:
        """A point and its radius (QGroundControl sends one for a click rather than a drag): the square of that
        half-side around the point, cut to the frame, is the target's box."""
        point = (message.param1, message.param2, message.param3)
        if not all(math.isfinite(v) and 0.0 <= v <= 1.0 for v in point):
            log.warning("refused TRACK_POINT %s: not a point and a radius inside 0..1", point)
            return mav.MAV_RESULT_DENIED
        frame = self._frame_header()
        if frame is None:
            return mav.MAV_RESULT_TEMPORARILY_REJECTED
        box = point_box(point, frame.width, frame.height)
        return _Call(lambda: self._track(box, frame, mav.CAMERA_TRACKING_MODE_POINT))

    def _track(self, box: tuple[float, float, float, float], frame: Frame, mode: int) -> int:
        try:
            if self.tracking:
                self._reinit_or_start(box, frame.seq)
            else:
                self._start_or_take_over(box, frame.seq)
        except TacfError as exc:
            log.warning("%s: the service refused: %s", _TRACKING_COMMANDS[mode], exc)
            if not self.tracking:                    # a re-target refused leaves the session tracking as it was
                # a refusal leaves nothing of ours running, and a stop clears the failure alone; a start not
                # answered in time may have started it: a stop asks the service
                self._held = isinstance(exc, RequestTimeout)
                self._set_state("failed", mode=mode)
            return mav.MAV_RESULT_FAILED
        self._held = True
        self._set_state("tracking", started_on=(frame.seq, frame.stamp_ns), mode=mode)
        log.info("tracking %s on %s from box %s (frame %d)", self.sid, self.image_key, box, frame.seq)
        return mav.MAV_RESULT_ACCEPTED

    def _start_or_take_over(self, box: tuple[float, float, float, float], seq: int) -> None:
        """Start the session, or re-target it when it already runs: the sid is this component's, so a session
        under it on this key is one an earlier run of the component left behind (killed before it could stop it)."""
        try:
            self.client.start(self.image_key, box, seq=seq, profile=self.profile, sid=self.sid)
        except DuplicateSession:
            running = self.client.status(self.sid)
            if running.image_key != self.image_key:
                raise TacfError(f"session {self.sid!r} runs on {running.image_key}, not on {self.image_key}") \
                    from None
            log.info("session %s already runs: taking it over", self.sid)
            self.client.reinit(self.sid, box, seq=seq)

    def _reinit_or_start(self, box: tuple[float, float, float, float], seq: int) -> None:
        """Re-target the running session, or start it again when it was stopped elsewhere (the dashboard, `tacf
        stop`) since _check_session last looked."""
        try:
            self.client.reinit(self.sid, box, seq=seq)
        except UnknownSession:
            log.info("session %s was stopped elsewhere: starting it again", self.sid)
            self._start_or_take_over(box, seq)

    def _stop_tracking(self) -> int | _Call:
        if self.state == "idle" and not self._pending:
            return mav.MAV_RESULT_ACCEPTED           # nothing runs, nor is about to
        return _Call(self._stop)

    def _stop(self) -> int:
        if self._held:
            try:
                self.client.stop(self.sid)
            except UnknownSession:
                log.info("session %s is not on the service (stopped elsewhere, or it never started)", self.sid)
            except TacfError as exc:
                log.warning("STOP_TRACKING: %s", exc)
                return mav.MAV_RESULT_FAILED
            self._held = False
        self._set_state("idle")
        return mav.MAV_RESULT_ACCEPTED

    def _check_session(self) -> int:
        """A session stopped elsewhere (the dashboard, `tacf stop`) ends the tracking here too, one that failed on
        the service is failed here until the service runs it again (a crashed worker is restarted, a reinit from
        elsewhere revives it), and a service that stopped answering is lost (ERROR) until it answers again.
        ACCEPTED when the status to send is unchanged, FAILED when it changed."""
        try:
            state = self.client.status(self.sid).state
        except UnknownSession:
            state = "stopped"
        except TacfError as exc:                     # no answer: killed, hung or out of reach; ask again later
            with self._lock:
                self._unanswered_checks += 1
                lost_now = self._unanswered_checks == SERVICE_LOST_CHECKS
            if lost_now:
                log.warning("the service has not answered %d checks of %s (%s): status ERROR until it answers",
                            SERVICE_LOST_CHECKS, self.sid, exc)
            return mav.MAV_RESULT_FAILED if lost_now else mav.MAV_RESULT_ACCEPTED
        with self._lock:
            was_lost, self._unanswered_checks = self._unanswered_checks >= SERVICE_LOST_CHECKS, 0
        seen = {"stopped": "idle", "failed": "failed"}.get(state, "tracking")
        # unchanged, or a command changed it meanwhile (a stop; a refused start, which holds nothing to check)
        if seen == self.state or self.state == "idle" or (self.state == "failed" and not self._held):
            if was_lost:
                log.info("the service answers again: %s is %s", self.sid, state)
            return mav.MAV_RESULT_FAILED if was_lost else mav.MAV_RESULT_ACCEPTED     # back to ACTIVE if lost
        log.info("session %s is %s: %s", self.sid, state, "tracking again" if seen == "tracking" else "tracking ended")
        self._held = seen != "idle"                  # the service keeps a failed session until it is stopped
        self._set_state(seen)
        return mav.MAV_RESULT_FAILED

    def _set_state(self, state: str, started_on: tuple[int, int] | None = None, mode: int | None = None) -> None:
        """Called after the service answered: it is not lost. `mode`: that of a tracking command it took."""
        with self._lock:
            self.state, self._box, self._started_on = state, None, started_on
            self._mode = self._mode if mode is None else mode
            self._unanswered_checks = 0

    def _set_interval(self, message) -> int:
        if _message_id(message.param1) != mav.MAVLINK_MSG_ID_CAMERA_TRACKING_IMAGE_STATUS:
            return mav.MAV_RESULT_UNSUPPORTED
        interval_us = message.param2
        if not math.isfinite(interval_us) or interval_us < 0 and interval_us != -1:
            return mav.MAV_RESULT_DENIED                # MAVLink defines -1 (off), 0 (default) and intervals only
        self.status_interval_s = (0.0 if interval_us == -1 else
                                  1.0 / DEFAULT_STATUS_HZ if interval_us == 0 else interval_us / 1e6)
        return mav.MAV_RESULT_ACCEPTED

    # --- messages -----------------------------------------------------------------------------------------------
    def _send_camera_information(self) -> None:
        frame = self._frame_header()
        width, height = (frame.width, frame.height) if frame is not None else (0, 0)
        nan = float("nan")
        boot_ms = int((time.monotonic() - self._started) * 1000) & 0xFFFFFFFF
        self.mav.mav.camera_information_send(boot_ms, _ascii_field(VENDOR), _ascii_field(MODEL), 0, nan, nan, nan,
                                             width, height, 0, TRACKING_CAPABILITIES, 0, b"")

    def _send_status(self) -> None:
        nan = float("nan")
        status, mode, target_data = mav.CAMERA_TRACKING_STATUS_FLAGS_IDLE, mav.CAMERA_TRACKING_MODE_NONE, 0
        point, radius, corners = (nan, nan), nan, (nan, nan, nan, nan)
        with self._lock:
            state, box, box_age = self.state, self._box, time.monotonic() - self._box_arrived
            lost, tracking_mode = self._unanswered_checks >= SERVICE_LOST_CHECKS, self._mode
        if state == "failed" or (state == "tracking" and lost):
            status, mode = mav.CAMERA_TRACKING_STATUS_FLAGS_ERROR, tracking_mode
        elif state == "tracking":
            status, mode = mav.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE, tracking_mode
            if box is not None and box_age > STALE_BOX_S:
                status |= mav.CAMERA_TRACKING_STATUS_FLAGS_COASTING      # no box lately: none to show
            elif box is not None:
                target_data = mav.CAMERA_TRACKING_TARGET_DATA_IN_STATUS
                point, corners = box.center_norm, box.corners_normalised
                if mode == mav.CAMERA_TRACKING_MODE_POINT:      # the box's half-side, in image widths
                    radius = point_radius(box.box[2], box.box[3], box.frame_size[0])
                if not box.ok:
                    status |= mav.CAMERA_TRACKING_STATUS_FLAGS_COASTING
        self.mav.mav.camera_tracking_image_status_send(status, mode, target_data, *point, radius, *corners)

    def _frame_header(self) -> Frame | None:
        """The newest frame seen on the image key (its seq and size), or None."""
        if self._newest_frame is None:
            return None
        try:
            return decode(self._newest_frame.payload.to_bytes(), Frame)
        except DecodeError as exc:
            log.warning("the newest frame on %s is malformed: %s", self.image_key, exc)
            return None

    # --- lifetime ------------------------------------------------------------------------------------------------
    def close(self) -> None:
        """Stop the session this component started, and let go of everything."""
        service_thread = getattr(self, "_service_thread", None)
        if service_thread is not None:
            self._calls.put(None)                    # after the calls queued: a start still running ends first
            service_thread.join(timeout=self.client.timeout)
        if getattr(self, "_held", False):
            if (service_thread is not None and service_thread.is_alive()) or self._unanswered_checks:
                # a stop would wait out its timeout too: Ctrl-C took 17 s against a hung service
                log.warning("the service does not answer: %s is left to it (a new tacf mavlink on %s takes it "
                            "over; tacf stop %s ends it)", self.sid, self.image_key, self.sid)
            else:
                try:
                    self.client.stop(self.sid)
                except TacfError as exc:
                    log.warning("could not stop %s: %s", self.sid, exc)
            self._held, self.state = False, "idle"
        # a TCP link whose reconnection failed has no port, and pymavlink's close() would fail on it
        if getattr(self, "mav", None) is not None and self.mav.port is not None:
            self.mav.close()
        if isinstance(getattr(self, "mav", None), mavutil.mavtcpin):
            # pymavlink's close() of a tcpin link closes only its ground station's connection: the listening
            # socket kept the port, and a component opened on it again was refused (Address already in use)
            self.mav.listen.close()
        if self._boxes is not None:
            self._boxes.close()
        if self._frames is not None:
            self._frames.undeclare()
        if self._own_session:
            # Zenoh waits up to 10 s to flush a link whose peer does not read (a hung service), then gives up
            # (measured: 12.6 s with puts queued to a SIGSTOPped peer; zenoh#2675): closed anyway
            try:
                self.session.close()
            except zenoh.ZError as exc:
                log.warning("the Zenoh session did not close cleanly: %s", zenoh_error_text(exc))

    def __enter__(self) -> "MavlinkCamera":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def default_sid(image_key: str) -> str:
    """mavlink-<image key>, made an id, '/' read as '-'. A key of other characters than letters, digits, '_' and
    '/' (uav1/cam-front, uav1/cam.front and uav1/cam/front would all read mavlink-uav1-cam-front) or too long for
    an id (64 characters at most, so cut) ends in a digest of the whole key: two cameras never share a session."""
    sid = "mavlink-" + keys.sanitise_id(image_key)
    if len(sid) <= 64 and re.fullmatch(r"[A-Za-z0-9_/]+", image_key):
        return sid
    return sid[:55] + "-" + hashlib.sha256(image_key.encode()).hexdigest()[:8]


def point_box(point: tuple[float, float, float], width: int, height: int) -> tuple[float, float, float, float]:
    """TRACK_POINT's (x, y, radius) as a box in pixels: the square of half-side radius around the point, cut to the
    frame. MAVLink normalises x and y to the frame, the radius to its width, 0 being one pixel."""
    x, y, radius = point
    cx, cy, half = x * width, y * height, max(1.0, radius * width)
    left, top = max(0.0, cx - half), max(0.0, cy - half)
    return left, top, min(float(width), cx + half) - left, min(float(height), cy + half) - top


def point_radius(box_width: float, box_height: float, width: int) -> float:
    """A point-mode status's radius for a box: its half-side in image widths, the inverse of point_box's, at most 1
    (the whole width), as MAVLink bounds it: a box over twice the width tall (a portrait frame) went past it."""
    return min(1.0, max(box_width, box_height) / 2 / width)


def _target_camera(message) -> int:
    """The camera a tracking command is for (0: any; 1-6 attached to the autopilot, 7-255 a camera component's
    id); 0 for other commands and for values no camera id can be."""
    if message.command == mav.MAV_CMD_CAMERA_TRACK_RECTANGLE:
        value = message.x if message.get_type() == "COMMAND_INT" else message.param5
    elif message.command == mav.MAV_CMD_CAMERA_TRACK_POINT:
        value = message.param4
    elif message.command == mav.MAV_CMD_CAMERA_STOP_TRACKING:
        value = message.param1
    else:
        return 0
    return int(value) if math.isfinite(value) and 1 <= value <= 255 and value == int(value) else 0

