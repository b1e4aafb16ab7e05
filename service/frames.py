"""FrameHistory: the last few frames of each image key that a session follows.

A start or reinit request may name the seq of the frame its box was drawn on; by the time the request
arrives, newer frames have come in. The service keeps the last `depth` frames of each subscribed key (as the
raw msgpack payloads, never decoded here) so that a worker is initialised on the frame the box belongs to
and then catches up through the newer ones, instead of applying the box to a frame where the target has moved.
A key is kept only while a session follows it: a request may carry its frame for when the service does not hold it.
"""
from __future__ import annotations

import logging
import threading
from collections import deque
from dataclasses import dataclass

from tacf.boxes import check_box
from tacf_schemas import DecodeError, Frame, decode

log = logging.getLogger(__name__)

DEFAULT_DEPTH = 24
MAX_BYTES_PER_KEY = 96 * 1024 * 1024


@dataclass(frozen=True, eq=False)     # compared by identity: a camera that restarts its seq count repeats seqs
class StoredFrame:
    seq: int
    stamp_ns: int
    width: int
    height: int
    payload: bytes          # the Frame's msgpack bytes as received
    arrival: int | None = None      # how many samples of its key came before it (FrameHistory.arrivals); None if
                                    # the service did not receive it on the key (carried by a request, or stored)

    @classmethod
    def from_frame(cls, frame: Frame, payload: bytes, arrival: int | None = None) -> "StoredFrame":
        return cls(frame.seq, frame.stamp_ns, frame.width, frame.height, payload, arrival)

    @classmethod
    def from_payload(cls, payload: bytes) -> "StoredFrame":
        """Parse a Frame payload (DecodeError if it is not one)."""
        return cls.from_frame(decode(payload, Frame), payload)


class _KeyHistory:
    def __init__(self, depth: int) -> None:
        self.frames: deque[StoredFrame] = deque(maxlen=depth)
        self.users = 0
        self.arrived = 0            # samples taken from the subscriber, frames or not
        self.subscriber = None
        self.pump: threading.Thread | None = None

    def add(self, frame: StoredFrame) -> None:
        self.frames.append(frame)
        while len(self.frames) > 1 and sum(len(f.payload) for f in self.frames) > MAX_BYTES_PER_KEY:
            self.frames.popleft()


class FrameHistory:
    """Per-key frame rings, fed from RingChannel subscribers on the service's session by one pump thread per
    key (parsing only). A ring never blocks Zenoh's receive path, even when this process is starved of CPU,
    so the frames the service routes to its workers never wait behind this history."""

    def __init__(self, session, depth: int = DEFAULT_DEPTH) -> None:
        self._session = session
        self._depth = depth
        self._keys: dict[str, _KeyHistory] = {}
        self._cond = threading.Condition()

    def acquire(self, key: str) -> None:
        """Start keeping frames of `key` (reference counted: one per session on that key)."""
        with self._cond:
            history = self._keys.get(key)
            if history is None:
                import zenoh
                history = self._keys[key] = _KeyHistory(self._depth)
                history.subscriber = self._session.declare_subscriber(key, zenoh.handlers.RingChannel(self._depth))
                history.pump = threading.Thread(target=self._pump, args=(key, history.subscriber.handler),
                                                name=f"history-{key}", daemon=True)
                history.pump.start()
            history.users += 1

    def release(self, key: str) -> None:
        with self._cond:
            history = self._keys.get(key)
            if history is None:
                return
            history.users -= 1
            if history.users > 0:
                return
            del self._keys[key]
            _undeclare(history.subscriber)
        history.pump.join(timeout=0.5)

    def wake_all(self) -> None:
        """Wake every wait_for (they re-check their cancel event)."""
        with self._cond:
            self._cond.notify_all()

    def close(self) -> None:
        with self._cond:
            histories = list(self._keys.values())
            for history in histories:
                _undeclare(history.subscriber)          # ends the pump's recv()
            self._keys.clear()
            self._cond.notify_all()
        for history in histories:
            history.pump.join(timeout=0.5)

    def _pump(self, key: str, ring) -> None:
        import zenoh
        while True:
            try:
                sample = ring.recv()
            except zenoh.ZError:
                return                      # undeclared or session closed
            payload = sample.payload.to_bytes()
            try:
                frame = decode(payload, Frame)      # outside the lock: the readers of the history wait on it
            except DecodeError:
                frame = None                # an arrival all the same; the workers count rejected frames
            with self._cond:
                history = self._keys.get(key)
                if history is None:
                    continue
                arrival, history.arrived = history.arrived, history.arrived + 1
                if frame is not None:
                    history.add(StoredFrame.from_frame(frame, payload, arrival))
                    self._cond.notify_all()

    def _kept(self, key: str) -> list[StoredFrame]:
        with self._cond:
            history = self._keys.get(key)
            return list(history.frames) if history else []

    def arrivals(self, key: str) -> int:
        """How many samples of `key` have come since it is kept (0 if it is not): the frames that came between two
        readings, for a session that had no worker to count them."""
        with self._cond:
            history = self._keys.get(key)
            return history.arrived if history else 0

    def frames_from(self, key: str, seq: int | None) -> list[StoredFrame]:
        """The frame with `seq` (the latest to arrive, should a camera have restarted its count) and every one kept
        after it, in arrival order. With `seq` no longer kept, the frames that arrived last with higher seqs: a box
        whose frame has left the ring (a restart that waited for a new worker) is then followed from the nearest
        frame after it, not from the newest, where the target may have moved out of reach. With seq None or nothing
        after it, just the newest frame; [] when none has arrived."""
        frames = self._kept(key)
        if seq is not None:
            for i in range(len(frames) - 1, -1, -1):
                if frames[i].seq == seq:
                    return frames[i:]
            after = len(frames)
            while after > 0 and frames[after - 1].seq > seq:
                after -= 1
            if after < len(frames):
                return frames[after:]
        return frames[-1:]

    def frames_after(self, key: str, frame: StoredFrame) -> list[StoredFrame]:
        """The frames of `key` kept after `frame`, in arrival order. A frame not kept (sent with a request, or gone
        from the history) is placed by seq and stamp: the kept frames after it have a higher seq and a stamp no
        older (a camera that restarted its count sent the higher seqs of the frames before it)."""
        frames = self._kept(key)
        for i, kept in enumerate(frames):
            if kept is frame:
                return frames[i + 1:]
        return [f for f in frames if f.seq > frame.seq and f.stamp_ns >= frame.stamp_ns]

    def frame(self, key: str, seq: int) -> StoredFrame | None:
        """The kept frame of `key` with `seq`, if any."""
        frames = self.frames_from(key, seq)
        return frames[0] if frames and frames[0].seq == seq else None

    def wait_for(self, key: str, seq: int | None, timeout: float, cancel: threading.Event | None = None) -> None:
        """Wait up to `timeout` s for a first frame of `key` (and, when seq is given, for that seq when it is
        newer than anything kept)."""
        def satisfied() -> bool:
            if cancel is not None and cancel.is_set():
                return True
            history = self._keys.get(key)
            if history is None or not history.frames:
                return False
            if seq is None:
                return True
            newest = history.frames[-1].seq
            return newest >= seq or any(f.seq == seq for f in history.frames)
        with self._cond:
            self._cond.wait_for(satisfied, timeout)


def box_problem(box: tuple, width: int, height: int) -> str | None:
    """Why `box` cannot initialise a tracker on a width x height frame (tacf.boxes.check_box: finite, w and h at
    least a pixel, overlapping the frame and no larger than it), or None."""
    try:
        check_box(box, (height, width))
    except ValueError as exc:
        return str(exc)
    return None


def _undeclare(entity) -> None:
    try:
        entity.undeclare()
    except Exception:  # already closed with the session
        pass
