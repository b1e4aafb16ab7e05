"""Frame publisher: encode images as `Frame` messages (jpeg, png, bgr8 or mono8) and put them on an image key.

    with open_session(options) as session, open_source("clip.mp4") as source:
        stats = publish(session, source, "uav1/camera/front", fps=15, encoding="jpeg", quality=85)

Frames carry a seq that increases by one per published frame (also across loops of the source) and the capture
time `stamp_ns`: time.time_ns() when a live source's frame was read, when a replayed one's is sent. Publishing uses
CongestionControl.DROP: a camera stream never blocks on a slow network (ZENOH.md §3.4).
"""
from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
import zenoh

from tacf_clients.sources import FrameSource, SourceFrame, paced_frames, paced_rate
from tacf_schemas.codec import MSGPACK_ENCODING, encode
from tacf_schemas.images import FrameError, encode_frame
from tacf_schemas.keys import validate_image_key
from tacf_schemas.models import ENCODINGS, Frame

log = logging.getLogger(__name__)

# A rate below the one asked is told once, after this long: a replayed source whose frames take longer to read and
# encode than a period played slower than it was filmed, without a word until the final count.
SHORTFALL_AFTER_S = 5.0
SHORTFALL_FRACTION = 0.9


@dataclass(frozen=True)
class PublishStats:
    frames: int             # frames published
    bytes: int              # payload bytes published
    seconds: float          # wall time of the run
    last_seq: int | None    # seq of the last frame published
    span: float = 0.0       # from the first frame put to the last
    matched: bool = False   # a subscriber listened on the key at some point (else the frames reached nobody)

    @property
    def fps(self) -> float:
        """Frames per second between the first frame and the last (not over the set-up before the first)."""
        return (self.frames - 1) / self.span if self.span > 0 else 0.0


def to_channels(image: np.ndarray, encoding: str) -> np.ndarray:
    """`image` with the channel count `encoding` needs: gray for mono8, BGR for bgr8, as is for jpeg/png."""
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim not in (2, 3) or (
            image.ndim == 3 and image.shape[2] != 3):
        # the dtype too: a float or 16-bit image of the right shape was refused with its shape alone, as if wrong
        got = f"{image.dtype} {image.shape}" if isinstance(image, np.ndarray) else type(image).__name__
        raise ValueError(f"expected an HxWx3 (BGR) or HxW uint8 image, got {got}")
    if encoding == "mono8" and image.ndim == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if encoding == "bgr8" and image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    return image


class FramePublisher:
    """Puts images on one image key as Frame messages; seq counts from `first_seq`. Close it (or use `with`)."""

    def __init__(self, session: zenoh.Session, key: str, encoding: str = "jpeg", quality: int = 90,
                 first_seq: int = 0):
        self.key = validate_image_key(key)
        if encoding not in ENCODINGS:
            raise ValueError(f"unknown encoding {encoding!r}; expected one of {', '.join(ENCODINGS)}")
        self.encoding, self.quality, self.next_seq = encoding, quality, first_seq
        self._pub = session.declare_publisher(key, encoding=zenoh.Encoding(MSGPACK_ENCODING),
                                              congestion_control=zenoh.CongestionControl.DROP)

    def make_frame(self, image: np.ndarray, seq: int, stamp_ns: int) -> Frame:
        return encode_frame(to_channels(image, self.encoding), seq, self.encoding, quality=self.quality,
                            stamp_ns=stamp_ns)

    def put(self, image: np.ndarray, stamp_ns: int | None = None) -> Frame:
        """Encode and publish one image with the next seq; returns the Frame sent. FrameError (nothing sent) for
        an image beyond the wire limits (tacf_schemas.limits), which every service would refuse."""
        frame = self.make_frame(image, self.next_seq, time.time_ns() if stamp_ns is None else stamp_ns)
        self._pub.put(encode(frame))
        self.next_seq += 1
        return frame

    @property
    def matched(self) -> bool:
        """True when at least one subscriber (e.g. a tracking session) listens on the key."""
        return bool(self._pub.matching_status.matching)

    def wait_matched(self, timeout: float, stop: threading.Event | None = None) -> bool:
        """Wait up to `timeout` seconds for a subscriber; False on timeout, or at once when `stop` is set."""
        stop = stop or threading.Event()
        deadline = time.monotonic() + timeout
        while not self.matched:
            if stop.is_set() or time.monotonic() >= deadline:
                return False
            stop.wait(0.02)
        return True

    def close(self) -> None:
        try:
            self._pub.undeclare()
        except zenoh.ZError:
            pass  # the session is already closed

    def __enter__(self) -> "FramePublisher":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def publish(session: zenoh.Session, source: FrameSource, key: str, *, fps: float | None = None,
            encoding: str = "jpeg", quality: int = 90, max_frames: int | None = None,
            stop: threading.Event | None = None,
            on_frame: Callable[[Frame, SourceFrame], None] | None = None) -> PublishStats:
    """Publish `source` on `key` until it ends, `max_frames` (>= 1) were sent or `stop` is set.

    Replayable sources (files, folders, the scene) are paced at `fps`, else at their own rate, else 30 fps;
    live sources (camera, URL) run at the device's rate, thinned to `fps` when given, and go on through their
    reconnections with the same seq count. `on_frame(frame, src)` is called after each put (keep it quick).
    A frame that cannot be sent (beyond the wire's limits) raises FrameError if it is the first; after frames went
    out it is skipped with a warning (one odd image in a folder ended the whole run).
    """
    if max_frames is not None and max_frames < 1:
        raise ValueError(f"max_frames must be at least 1, got {max_frames}")
    stop = stop or threading.Event()
    frames = nbytes = 0
    last_seq = first_put = None
    matched = shortfall_told = False
    started = last_put = time.monotonic()
    rate = paced_rate(source, fps)
    log.info("publishing %s on %r as %s at %s fps", source.name, key, encoding,
             "device" if rate is None else f"{rate:.3g}")
    with FramePublisher(session, key, encoding, quality) as publisher:
        for src in paced_frames(source, fps, stop):
            # Live sources: the time the device delivered the frame; replayed ones: now, their "capture" time.
            try:
                frame = publisher.put(src.image, src.stamp_ns if source.live else None)
            except FrameError as exc:
                if not frames:
                    raise
                log.warning("frame %d of %s skipped: %s", src.index, source.name, exc)
                continue
            last_put = time.monotonic()
            first_put = first_put or last_put
            matched = matched or publisher.matched
            frames, nbytes, last_seq = frames + 1, nbytes + len(frame.data), frame.seq
            if on_frame is not None:
                on_frame(frame, src)
            if frames == 1:
                log.info("first frame: %dx%d, %d bytes", frame.width, frame.height, len(frame.data))
            if rate and not shortfall_told and last_put - first_put >= SHORTFALL_AFTER_S:
                shortfall_told = True
                sent = (frames - 1) / (last_put - first_put)
                if sent < SHORTFALL_FRACTION * rate:
                    log.warning("sending %.1f fps, below the %.3g asked: %s", sent, rate, "the camera delivers no more"
                                if source.live else "a frame takes longer to read and encode than a period, and the "
                                "replay runs slower than it was filmed (a lighter --encoding or --quality keeps up)")
            if frames == max_frames:
                break
    stats = PublishStats(frames, nbytes, time.monotonic() - started, last_seq, last_put - (first_put or last_put),
                         matched)
    log.info("published %d frames (%.1f fps, %.1f MB)", stats.frames, stats.fps, stats.bytes / 1e6)
    return stats
