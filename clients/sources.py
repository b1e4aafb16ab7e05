"""Frame sources for the publisher: video file, image folder, camera index, stream URL or the generated scene.

Every source yields `SourceFrame`s (BGR uint8 image, position in the source, capture time) and is a context
manager. `open_source(spec)` picks the kind from the spec string. Pacing (`paced_frames`) is separate: file-like
sources are replayed at their own rate or a given one; live sources (camera, URL) run at the device's rate and are
only thinned when a lower rate is asked for. A live source that fails (a radio link drops, a camera is unplugged, a
stream stalls) is reopened with growing pauses until it delivers again or the caller stops.
"""
from __future__ import annotations

import errno
import logging
import os
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import cv2
import numpy as np

from tacf.eval.datasets.folders import frames_of
from tacf.images import IMAGE_SUFFIXES, opencv_path, read_image
from tacf.log_throttle import LogThrottle

log = logging.getLogger(__name__)
T = TypeVar("T")

DEFAULT_FPS = 30.0
SCENE_SPEC = "scene"

# Stream URLs: give up opening after OPEN_TIMEOUT_MS and count a stream silent for READ_TIMEOUT_MS as failed
# (FFmpeg would otherwise wait on a dead RTSP/HTTP link for as long as the TCP connection lives).
OPEN_TIMEOUT_MS, READ_TIMEOUT_MS = 10_000, 5_000
# Pauses before each attempt to reopen a failed live source: doubling from the first, capped at the last.
RECONNECT_FIRST_S, RECONNECT_MAX_S = 0.5, 5.0
# Once they reach the cap, the failed attempts are logged once in this long, with their count: a camera switched
# off for hours wrote a line every 5 s.
REOPEN_LOG_PERIOD_S = 60.0


def never_stop() -> bool:
    return False


STOPPED = object()      # what call_unless_stopped returns when the caller stopped waiting


def call_unless_stopped(call: Callable[[], T], should_stop: Callable[[], bool] = never_stop,
                        poll_s: float = 0.1) -> T | object:
    """call() on a daemon thread, waited for until it returns (its value, or its exception raised here) or until
    `should_stop()` (then STOPPED). FFmpeg's blocking calls cannot be cut short: a stream that does not answer holds
    one for up to OPEN_TIMEOUT_MS or READ_TIMEOUT_MS, which a stop or Ctrl-C must not wait for; the call is left to
    end on its own thread."""
    return wait_unless_stopped(start_call(call), should_stop, poll_s)


def start_call(call: Callable[[], T]) -> Future:
    """call() on a daemon thread of its own; the Future of its value or exception."""
    result: Future = Future()

    def run() -> None:
        try:
            result.set_result(call())
        except BaseException as exc:        # raised in the thread that waits for it
            result.set_exception(exc)

    threading.Thread(target=run, name="tacf-capture", daemon=True).start()
    return result


def wait_unless_stopped(result: Future, should_stop: Callable[[], bool] = never_stop, poll_s: float = 0.1):
    """The value of `result` once it is there, or STOPPED as soon as `should_stop()` is true."""
    while True:
        try:
            return result.result(timeout=poll_s)
        except FutureTimeout:
            if should_stop():
                return STOPPED


def sleep_unless(seconds: float, should_stop: Callable[[], bool], slice_s: float = 0.1) -> bool:
    """Sleep `seconds` in slices, returning early (True) as soon as `should_stop()` is true."""
    deadline = time.monotonic() + seconds
    while (remaining := deadline - time.monotonic()) > 0:
        if should_stop():
            return True
        time.sleep(min(remaining, slice_s))
    return should_stop()


class SourceError(ValueError):
    """A source that opened but cannot deliver a frame (an image folder none of whose images can be read)."""


@dataclass(frozen=True)
class SourceFrame:
    index: int            # 0-based position in the source (restarts at 0 when a looping source wraps)
    image: np.ndarray     # HxWx3 BGR uint8 (or HxW uint8 grayscale)
    stamp_ns: int         # capture time, time.time_ns() when the frame was read or generated


class FrameSource:
    """Base class: iterate to get frames; `fps` is the native rate (None if unknown); `live` sources cannot loop;
    `reconnects` counts how often a live source was reopened after a failure."""

    name: str = "source"
    fps: float | None = None
    live: bool = False
    reconnects: int = 0

    def frames(self, should_stop: Callable[[], bool] = never_stop) -> Iterator[SourceFrame]:
        """The frames; a source that may wait (a live one reconnecting) returns once `should_stop()` is true."""
        raise NotImplementedError

    def __iter__(self) -> Iterator[SourceFrame]:
        return self.frames()

    def close(self) -> None:
        pass

    def __enter__(self) -> "FrameSource":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r})"


class ImageFolderSource(FrameSource):
    """Sorted images of a folder (2.png before 10.png). A sequence folder (`<seq>/img/*.jpg`, VOT's
    `<seq>/color/`) may be given as `<seq>` too, and reads as in `tacf track` and `tacf eval`: its img/, not a
    stray image beside it."""

    def __init__(self, folder: str | Path, loop: bool = False):
        folder = Path(folder)
        self.paths = frames_of(folder)
        if not self.paths:
            raise ValueError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in {folder}")
        folder = self.paths[0].parent
        self.folder, self.name, self.loop = folder, str(folder), loop

    def __len__(self) -> int:
        return len(self.paths)

    def frames(self, should_stop: Callable[[], bool] = never_stop) -> Iterator[SourceFrame]:
        """The images in order (skipping unreadable ones); SourceError when a whole pass reads none."""
        while True:
            read = 0
            for index, path in enumerate(self.paths):
                if should_stop():          # a pass over unreadable images yields nothing to stop at
                    return
                image = read_image(path)
                if image is None:
                    log.warning("cannot read %s, skipped", path)
                    continue
                read += 1
                yield SourceFrame(index, image, time.time_ns())
            if not read:
                raise SourceError(f"none of the {len(self.paths)} images in {self.folder} can be read")
            if not self.loop:
                return


class CaptureSource(FrameSource):
    """cv2.VideoCapture: a video file (replayable, loops by reopening), a camera index or a stream URL (live).

    A live source reconnects after a failure unless `reconnect` is False; `reconnects` counts the reopenings.
    Whatever may block (opening anything, reading anything but a local file) runs through call_unless_stopped, so
    that a stop or Ctrl-C ends the source at once.
    """

    def __init__(self, spec: str | int, loop: bool = False, live: bool | None = None, reconnect: bool = True,
                 should_stop: Callable[[], bool] = never_stop):
        """live None: a camera index is live; a URL is, unless it names a recorded clip (a file:// path, a video
        served over HTTP), which FFmpeg gives a frame count. A stop while opening raises SourceError."""
        self.spec, self.name = spec, str(spec)
        self._cap = call_unless_stopped(self._open, should_stop)
        if self._cap is STOPPED:
            raise SourceError(f"stopped while opening {self.name}")
        self._pending_read: Future | None = None    # a read a stop left running: the next frames() takes its frame
        if live is None:
            live = isinstance(spec, int) or not self._cap.get(cv2.CAP_PROP_FRAME_COUNT) > 0
        self.live = live
        self.loop = loop and not self.live
        self.reconnect = reconnect and self.live
        self.reconnects = 0
        self._reads_may_block = self.live or "://" in self.name
        fps = self._cap.get(cv2.CAP_PROP_FPS)
        self.fps = float(fps) if fps and 0 < fps < 1000 else None

    def _open(self) -> cv2.VideoCapture:
        if isinstance(self.spec, str) and "://" in self.spec:
            cap = cv2.VideoCapture(self.spec, cv2.CAP_ANY, [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, OPEN_TIMEOUT_MS,
                                                             cv2.CAP_PROP_READ_TIMEOUT_MSEC, READ_TIMEOUT_MS])
        else:
            cap = cv2.VideoCapture(opencv_path(self.spec) if isinstance(self.spec, str) else self.spec)
        if not cap.isOpened():
            cap.release()
            raise ValueError(f"cannot open video source {self.spec!r}")
        return cap

    def frames(self, should_stop: Callable[[], bool] = never_stop) -> Iterator[SourceFrame]:
        """The frames. A stop during a read that may block leaves the read running; the next call of frames()
        waits for it and yields its frame (`publish --wait-subscriber` stops reading once a subscriber comes, in
        the middle of a slow camera's read: its frames were lost for good)."""
        index = 0
        while not should_stop():
            read = self._read(should_stop)
            if read is STOPPED:
                return
            ok, image = read
            if ok and image is not None:
                yield SourceFrame(index, image, time.time_ns())
                index += 1
                continue
            if self.live:
                log.warning("video source %s ended or failed after %d frames", self.name, index)
                if not self.reconnect or not self._reopen(should_stop):
                    return
            elif self.loop and index > 0:
                self._cap.release()
                try:
                    self._cap = call_unless_stopped(self._open)
                except ValueError:                   # the file went away or changed under the loop
                    raise SourceError(f"cannot reopen {self.name} to play it again") from None
                index = 0
            else:
                return

    def _read(self, should_stop: Callable[[], bool]):
        """cap.read()'s (ok, image), or STOPPED with the read still running (kept in _pending_read)."""
        if not self._reads_may_block:
            return self._cap.read()
        self._pending_read = self._pending_read or start_call(self._cap.read)
        try:
            read = wait_unless_stopped(self._pending_read, should_stop)
        except BaseException:
            self._pending_read = None
            raise
        if read is not STOPPED:
            self._pending_read = None
        return read

    def _reopen(self, should_stop: Callable[[], bool]) -> bool:
        """Reopen a failed live source, pausing longer after each failed attempt; False once stopped."""
        self._cap.release()
        pause, failures = RECONNECT_FIRST_S, LogThrottle()
        while not sleep_unless(pause, should_stop):
            try:
                cap = call_unless_stopped(self._open, should_stop)
            except ValueError:
                period_s = REOPEN_LOG_PERIOD_S if pause == RECONNECT_MAX_S else 0.0   # each doubling is told
                pause = min(2 * pause, RECONNECT_MAX_S)
                if (admitted := failures.admit(period_s)) is not None:
                    held_back = admitted.held_back
                    more = f" ({held_back + 1} failed attempts since the last line)" if held_back else ""
                    log.warning("cannot reopen %s, next attempt in %.1f s%s", self.name, pause, more)
                continue
            if cap is STOPPED:                  # the capture, if it ever opens, is released when collected
                break
            self._cap = cap
            self.reconnects += 1
            log.info("video source %s reopened (reconnection %d)", self.name, self.reconnects)
            return True
        return False

    def close(self) -> None:
        """Release the capture, once a read still running on it has ended (a slow camera's, within a frame; a
        silent stream's within READ_TIMEOUT_MS): that read, returning into an interpreter shutting down, crashed
        `tacf publish` on a Ctrl-C (exit 134 or 139). One that outlasts its timeout is left to it."""
        if self._pending_read is not None:
            try:
                self._pending_read.result(timeout=READ_TIMEOUT_MS / 1000 + 1.0)
            except FutureTimeout:
                return
            except Exception:
                pass                                # its error does not matter any more: the source is closing
        self._cap.release()


def open_source(spec: str | int | Path, loop: bool = False, reconnect: bool = True,
                should_stop: Callable[[], bool] = never_stop) -> FrameSource:
    """Open SOURCE as given on the command line; a live one (camera, URL) reconnects after failures if `reconnect`.
    A stop while a camera or stream opens raises SourceError.

    - ``scene`` (or ``scene:WxH``): the generated demo scene (endless, deterministic);
    - an int, or a digit string that names no file or folder here: camera index;
    - a string with ``://`` (rtsp://, http://, udp://...): stream URL (a recorded clip's URL plays as a file);
    - an existing folder: image folder (or a sequence folder containing ``img/``);
    - an existing file: video file;
    - any other existing path (a camera device such as /dev/video0, a named pipe): live source.

    A path this user may not read (the file or folder, one above it, a sequence's img/) raises ValueError naming it.
    """
    try:
        return _open_source(spec, loop, reconnect, should_stop)
    except PermissionError as exc:  # a traceback from a folder's listing, or OpenCV's "cannot open" without a reason
        raise ValueError(f"cannot read {exc.filename or spec}: permission denied") from None


def _open_source(spec: str | int | Path, loop: bool, reconnect: bool,
                 should_stop: Callable[[], bool]) -> FrameSource:
    text = str(spec)
    path = Path(text).expanduser()
    if isinstance(spec, int) or (text.isdigit() and not path.exists()):
        return CaptureSource(int(text), live=True, reconnect=reconnect, should_stop=should_stop)
    if text == SCENE_SPEC or text.startswith(SCENE_SPEC + ":"):
        from tacf_clients.scene import Scene, SceneSource

        if path.exists():               # the user's own `scene` folder may be what they meant
            log.warning("%r is the generated scene; give ./%s for the %s of that name here", text, text,
                        "folder" if path.is_dir() else "file")
        return SceneSource(Scene.from_spec(text))
    if "://" in text:
        return CaptureSource(text, loop=loop, reconnect=reconnect, should_stop=should_stop)
    if path.exists() and not os.access(path, os.R_OK):    # checked, not tried: opening a named pipe waits for a writer
        raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(path))
    if path.is_dir():
        return ImageFolderSource(path, loop=loop)
    if path.is_file():
        return CaptureSource(str(path), loop=loop, live=False)
    if path.exists():
        return CaptureSource(str(path), live=True, reconnect=reconnect, should_stop=should_stop)
    raise FileNotFoundError(f"source {text!r} is neither a file, a folder, a camera index, a URL nor 'scene'")


class Pacer:
    """Paces a loop at `fps` frames per second without drift; when late by more than a period, it re-anchors
    instead of bursting to catch up. fps None or <= 0: no pacing."""

    def __init__(self, fps: float | None):
        self.period = 1.0 / fps if fps and fps > 0 else 0.0
        self._next: float | None = None

    def wait(self, should_stop: Callable[[], bool] = never_stop) -> None:
        """Sleep until the next tick, returning early if `should_stop()`."""
        if not self.period:
            return
        if self._next is None:
            self._next = time.monotonic()
        sleep_unless(self._next - time.monotonic(), should_stop)
        # Late by more than a period (a stall in the caller or in this very sleep): this tick goes now and the
        # schedule starts again from it; re-anchoring only on the next call would give two ticks back to back.
        now = time.monotonic()
        self._next = (now if now - self._next > self.period else self._next) + self.period


class Thinner:
    """For live sources: lets frames through at about `fps` (a schedule with a quarter-period tolerance, so a
    30 fps camera thinned to 10 fps gives every third frame, not every fourth). fps None or <= 0: all frames."""

    def __init__(self, fps: float | None):
        self.period = 1.0 / fps if fps and fps > 0 else 0.0
        self._next: float | None = None

    def admit(self) -> bool:
        if not self.period:
            return True
        now = time.monotonic()
        if self._next is not None and now < self._next - self.period / 4:
            return False
        self._next = now + self.period if self._next is None or now - self._next > self.period else \
            self._next + self.period
        return True


def paced_rate(source: FrameSource, fps: float | None) -> float | None:
    """The rate `paced_frames` sends `source` at: a replayed one at `fps`, else its own, else DEFAULT_FPS; a live
    one at `fps` when given, else None (the device's rate)."""
    return fps if source.live else (fps or source.fps or DEFAULT_FPS)


class NewestFrames:
    """The frames of a live source, read on a thread of its own as fast as the source delivers them; iterating
    gives the newest frame not yet taken (waiting for one), the older ones are skipped (`skipped` counts them).
    A sender slower than the device (an encoding slower than the frame rate, a busy machine) that read the frames
    in turn left the others in the stream's buffers: it sent ever older frames, 2.5 s behind the camera after 20 s
    (PNG at 1080p from a 30 fps MJPEG camera), stamped with the time they were read. Close it to end the thread."""

    def __init__(self, source: FrameSource, stop: threading.Event):
        self.source, self.skipped = source, 0
        self._stop, self._closing = stop, threading.Event()
        self._cond = threading.Condition()
        self._newest: SourceFrame | None = None
        self._ended = False
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._read, name="tacf-reader", daemon=True)
        self._thread.start()

    def _should_stop(self) -> bool:
        return self._stop.is_set() or self._closing.is_set()

    def _read(self) -> None:
        try:
            for frame in self.source.frames(should_stop=self._should_stop):
                with self._cond:
                    self.skipped += self._newest is not None
                    self._newest = frame
                    self._cond.notify_all()
                if self._should_stop():         # a source that does not ask should_stop itself
                    break
        except BaseException as exc:            # raised where the frames are taken
            self._error = exc
        finally:
            with self._cond:
                self._ended = True
                self._cond.notify_all()

    def __iter__(self) -> "NewestFrames":
        return self

    def __next__(self) -> SourceFrame:
        with self._cond:
            while self._newest is None and not self._ended and not self._stop.is_set():
                self._cond.wait(0.1)            # a stop is an Event of its own: looked at in slices
            frame, self._newest = self._newest, None
        if frame is not None:
            return frame
        if self._ended and self._error is not None:
            raise self._error
        raise StopIteration

    def close(self) -> None:
        """End the reading (within a read's poll: a read left running is the source's to wait for on close)."""
        self._closing.set()
        self._thread.join()
        if self.skipped:
            log.info("%s: frames skipped as newer ones came before the sender was ready: %d", self.source.name,
                     self.skipped)


def paced_frames(source: FrameSource, fps: float | None, stop: threading.Event,
                 hold: threading.Event | None = None) -> Iterator[SourceFrame]:
    """The frames of `source` to send, each yielded when it is due (paced_rate), until the source ends or `stop` is
    set. While `hold` is set the first frame is yielded in place of the others: a replayed source stands still; a
    live one is read on and its frames dropped, since its buffers would otherwise hand out ever older frames. A live
    source is read on all the time (NewestFrames): a caller slower than the device gets its newest frame."""
    hold = hold or threading.Event()
    rate = paced_rate(source, fps)
    pacer, thinner = Pacer(None if source.live else rate), Thinner(rate if source.live else None)
    frames = NewestFrames(source, stop) if source.live else source.frames(should_stop=stop.is_set)
    try:
        first = current = next(frames, None)
        while current is not None and not stop.is_set():
            if thinner.admit():
                pacer.wait(should_stop=stop.is_set)
                if stop.is_set():
                    return
                yield first if hold.is_set() else current
            if source.live or not hold.is_set():
                current = next(frames, None)
    finally:
        frames.close()
