"""Onboard consumer: a light subscriber for the boxes of one session or of all, for a gimbal or flight controller.

    with BoxConsumer(session, sid="cam1-target", latest_only=True) as boxes:
        for b in boxes:                          # TrackedBox; a slow consumer skips to the newest one
            gimbal.point_at(b.center_norm) if b.ok else gimbal.hold()

Boxes come in pixels (x, y, w, h, 0-based, top-left origin) and, with the frame size every result carries,
normalised to 0..1 as (x, y, w, h) and as top-left + bottom-right corners: the form MAVLink's camera tracking messages
(CAMERA_TRACKING_IMAGE_STATUS, MAV_CMD_CAMERA_TRACK_RECTANGLE) and most gimbal SDKs use.
"""
from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import zenoh

from tacf_clients.errors import ClientClosed, as_invalid_id
from tacf_clients.stream import ResultStream
from tacf_clients.zconfig import ZenohOptions, open_session
from tacf_schemas import keys
from tacf_schemas.codec import DecodeError, decode
from tacf_schemas.models import BoxResult

Box = tuple[float, float, float, float]


@dataclass(frozen=True)
class TrackedBox:
    """One tracker output as an onboard consumer needs it."""

    node: str
    sid: str
    seq: int                         # the frame's seq
    stamp_ns: int                    # the frame's capture time
    box: Box                         # pixels: x, y, w, h
    ok: bool                         # False: target lost, do not steer on this box
    pme: float
    frame_size: tuple[int, int]      # (width, height) of the frame the box was found in
    received_ns: int                 # when this consumer received it

    @property
    def age_ms(self) -> float:
        """Capture-to-receipt latency (needs synchronised clocks across hosts)."""
        return (self.received_ns - self.stamp_ns) / 1e6

    @property
    def center(self) -> tuple[float, float]:
        x, y, w, h = self.box
        return x + w / 2, y + h / 2

    @property
    def normalised(self) -> Box:
        """(x, y, w, h) in 0..1 of the frame width and height (clipped)."""
        x1, y1, x2, y2 = self.corners_normalised
        return x1, y1, x2 - x1, y2 - y1

    @property
    def corners_normalised(self) -> Box:
        """(top_left_x, top_left_y, bottom_right_x, bottom_right_y) in 0..1, clipped (MAVLink's rectangle)."""
        width, height = self.frame_size
        x, y, w, h = self.box
        return (_clip01(x / width), _clip01(y / height), _clip01((x + w) / width), _clip01((y + h) / height))

    @property
    def center_norm(self) -> tuple[float, float]:
        """Centre in 0..1 (MAVLink's point form)."""
        cx, cy = self.center
        return _clip01(cx / self.frame_size[0]), _clip01(cy / self.frame_size[1])


def _clip01(value: float) -> float:
    return min(1.0, max(0.0, value))


def tracked_box(result: BoxResult, received_ns: int | None = None) -> TrackedBox:
    """A TrackedBox from a wire BoxResult."""
    return TrackedBox(result.node, result.sid, result.seq, result.stamp_ns, tuple(result.box), result.ok,
                      result.pme, (result.width, result.height),
                      time.time_ns() if received_ns is None else received_ns)


class BoxConsumer:
    """Subscribe to the boxes of session `sid` on service `node` ("*" = all sessions / all services).

    session: a zenoh.Session to use (not closed here), or None to open one from `options` (closed on close()).
    latest_only: keep only the newest unread box per session (a slow consumer always gets the freshest box);
    otherwise a FIFO of `queue_size` (oldest dropped when full).
    on_box: a callback, called on a worker thread; without it, iterate the consumer.
    """

    def __init__(self, session: zenoh.Session | None = None, sid: str = keys.WILDCARD, node: str = keys.WILDCARD,
                 *, latest_only: bool = False, on_box: Callable[[TrackedBox], None] | None = None,
                 options: ZenohOptions | None = None, queue_size: int = 64):
        with as_invalid_id():                   # a TacfError, as TrackingClient raises it
            key_expr = keys.box_key(node, sid)
        if session is not None and session.is_closed():     # zenoh's own ZError, which a TacfError handler missed
            raise ClientClosed("the Zenoh session given to the consumer is closed")
        self._own_session = session is None
        self.session = session if session is not None else open_session(options)
        try:
            self._stream: ResultStream[TrackedBox] = ResultStream(
                self.session, key_expr, self._decode, latest_only=latest_only,
                slot_of=lambda b: (b.node, b.sid), queue_size=queue_size, callback=on_box,
                name=f"tacf-boxes-{sid}")
        except Exception:
            self.close()
            raise

    def _decode(self, sample: zenoh.Sample) -> TrackedBox | None:
        received = time.time_ns()
        try:
            result = decode(sample.payload.to_bytes(), BoxResult)
        except DecodeError:
            return None
        return tracked_box(result, received)

    def get(self, timeout: float | None = None) -> TrackedBox | None:
        """The next box, or None after `timeout` seconds or when closed."""
        return self._stream.get(timeout)

    def __iter__(self) -> Iterator[TrackedBox]:
        return iter(self._stream)

    @property
    def received(self) -> int:
        return self._stream.received

    @property
    def dropped(self) -> int:
        """Boxes replaced by a newer one (latest_only) or pushed out of a full queue before being read."""
        return self._stream.dropped

    def close(self) -> None:
        stream = getattr(self, "_stream", None)
        if stream is not None:
            stream.close()
        if self._own_session:
            self.session.close()

    def __enter__(self) -> "BoxConsumer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
