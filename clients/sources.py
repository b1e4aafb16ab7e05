"""Frame sources for the publisher: video file, image folder, camera index, stream URL or the generated scene.

Every source yields `SourceFrame`s (BGR uint8 image, position in the source, capture time) and is a context
manager. `open_source(spec)` picks the kind from the spec string. Pacing (`Pacer`) is separate: file-like sources
are replayed at their own rate or a given one; live sources (camera, URL) run at the device's rate and are only
thinned when a lower rate is asked for.
"""
from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".ppm", ".pgm")
DEFAULT_FPS = 30.0
SCENE_SPEC = "scene"


@dataclass(frozen=True)
class SourceFrame:
    index: int            # 0-based position in the source (restarts at 0 when a looping source wraps)
    image: np.ndarray     # HxWx3 BGR uint8 (or HxW uint8 grayscale)
    stamp_ns: int         # capture time, time.time_ns() when the frame was read or generated


class FrameSource:
    """Base class: iterate to get frames; `fps` is the native rate (None if unknown); `live` sources cannot loop."""

    name: str = "source"
    fps: float | None = None
    live: bool = False

    def frames(self) -> Iterator[SourceFrame]:
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
    """Sorted images of a folder. A sequence folder (`<seq>/img/*.jpg`) may be given as `<seq>` too."""

    def __init__(self, folder: str | Path, loop: bool = False, fps: float | None = None):
        folder = Path(folder)
        if not any(_is_image(p) for p in folder.iterdir()) and (folder / "img").is_dir():
            folder = folder / "img"
        self.paths = sorted(p for p in folder.iterdir() if _is_image(p))
        if not self.paths:
            raise ValueError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in {folder}")
        self.folder, self.name, self.loop, self.fps = folder, str(folder), loop, fps

    def __len__(self) -> int:
        return len(self.paths)

    def frames(self) -> Iterator[SourceFrame]:
        while True:
            for index, path in enumerate(self.paths):
                image = cv2.imread(str(path), cv2.IMREAD_COLOR)
                if image is None:
                    log.warning("cannot read %s, skipped", path)
                    continue
                yield SourceFrame(index, image, time.time_ns())
            if not self.loop:
                return


class CaptureSource(FrameSource):
    """cv2.VideoCapture: a video file (replayable, loops by reopening), a camera index or a stream URL (live)."""

    def __init__(self, spec: str | int, loop: bool = False, live: bool | None = None):
        self.spec, self.name = spec, str(spec)
        self.live = isinstance(spec, int) if live is None else live
        self.loop = loop and not self.live
        self._cap = self._open()
        fps = self._cap.get(cv2.CAP_PROP_FPS)
        self.fps = float(fps) if fps and 0 < fps < 1000 else None

    def _open(self) -> cv2.VideoCapture:
        cap = cv2.VideoCapture(self.spec)
        if not cap.isOpened():
            cap.release()
            raise ValueError(f"cannot open video source {self.spec!r}")
        return cap

    def frames(self) -> Iterator[SourceFrame]:
        index = 0
        while True:
            ok, image = self._cap.read()
            if ok and image is not None:
                yield SourceFrame(index, image, time.time_ns())
                index += 1
                continue
            if not self.loop or index == 0:
                if self.live:
                    log.warning("video source %s ended or failed after %d frames", self.name, index)
                return
            self._cap.release()
            self._cap = self._open()
            index = 0

    def close(self) -> None:
        self._cap.release()


def _is_image(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in IMAGE_SUFFIXES


def open_source(spec: str | int | Path, loop: bool = False) -> FrameSource:
    """Open SOURCE as given on the command line.

    - ``scene`` (or ``scene:WxH``): the generated demo scene (endless, deterministic);
    - a digit string or an int: camera index;
    - a string with ``://`` (rtsp://, http://, udp://...): stream URL;
    - an existing folder: image folder (or a sequence folder containing ``img/``);
    - an existing file: video file.
    """
    if isinstance(spec, int) or (isinstance(spec, str) and spec.isdigit()):
        return CaptureSource(int(spec), live=True)
    text = str(spec)
    if text == SCENE_SPEC or text.startswith(SCENE_SPEC + ":"):
        from tacf_clients.scene import Scene, SceneSource

        return SceneSource(Scene.from_spec(text))
    if "://" in text:
        return CaptureSource(text, live=True)
    path = Path(text).expanduser()
    if path.is_dir():
        return ImageFolderSource(path, loop=loop)
    if path.is_file():
        return CaptureSource(str(path), loop=loop, live=False)
    raise FileNotFoundError(f"source {text!r} is neither a file, a folder, a camera index, a URL nor 'scene'")


class Pacer:
    """Paces a loop at `fps` frames per second without drift; when late by more than a period, it re-anchors
    instead of bursting to catch up. fps None or <= 0: no pacing."""

    def __init__(self, fps: float | None):
        self.period = 1.0 / fps if fps and fps > 0 else 0.0
        self._next: float | None = None

    def wait(self, stop_check_s: float = 0.1, should_stop=lambda: False) -> None:
        """Sleep until the next tick (in slices of `stop_check_s`, returning early if `should_stop()`)."""
        if not self.period:
            return
        now = time.monotonic()
        if self._next is None or now - self._next > self.period:
            self._next = now
        while (remaining := self._next - time.monotonic()) > 0 and not should_stop():
            time.sleep(min(remaining, stop_check_s))
        self._next += self.period


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
