"""`tacf track`: follow one target through a video file or an image folder, write boxes and an annotated video;
and `tacf eval --videos`: a sequence's frames with every tracker's boxes and the ground truth."""
from __future__ import annotations

import itertools
import logging
import math
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import TextIO

import numpy as np

from ..boxes import check_box
from ..images import IMAGE_SUFFIXES, opencv_path
from . import metrics
from .datasets import Sequence
from .datasets.folders import frames_of
from .runner import read_frame
from .text_files import CannotWrite, drawable
from .trackers import BoxTracker

log = logging.getLogger(__name__)

BOXES_HEADER = ("# x,y,w,h,pme,ok - one line per frame, line 1 = the initial box; x,y,w,h in 0-based pixels "
                "(x,y = top-left corner); pme = peak-to-median energy of the response (nan when the tracker has "
                "none); ok = 1 tracked, 0 target lost")

# A container without a frame index gives a count estimated from its duration: exact in the formats measured (mp4,
# avi, mkv, mov at 7.3 to 29.97 fps), but a frame short is no reason to call a long run's video broken.
FRAME_COUNT_SLACK = 1


def open_source(source: Path) -> tuple[Iterator[tuple[str, np.ndarray]], float]:
    """((name, BGR frame) pairs, frame rate) of a video file or an image folder (its img/ subfolder if it has one,
    as a dataset's sequence folder: a stray image beside img/ is no sequence). A frame's name is its image file,
    or "frame N" (1-based) of a video, for the errors a frame can cause."""
    import cv2

    source = Path(source)
    if source.is_dir():
        paths = frames_of(source)
        if not paths:
            raise FileNotFoundError(f"{source}: no images ({', '.join(IMAGE_SUFFIXES)}) in the folder")
        return ((str(p), read_frame(p)) for p in paths), 10.0
    if not source.is_file():
        raise FileNotFoundError(f"{source}: no such video file or image folder")
    cap = cv2.VideoCapture(opencv_path(source))
    if not cap.isOpened():
        raise ValueError(f"{source}: OpenCV cannot open this video")
    fps = cap.get(cv2.CAP_PROP_FPS) or 0.0
    declared = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)

    def frames() -> Iterator[tuple[str, np.ndarray]]:
        try:
            for number in itertools.count(1):
                ok, frame = cap.read()
                if not ok:
                    # a file cut short (a copy interrupted, a recorder's power lost) reads as a shorter video
                    if number - 1 < declared:
                        log.warning("%s: the video ended after %d of the %d frames its header declares (cut short "
                                    "or damaged?)", source, number - 1, declared)
                    return
                yield f"{source} frame {number}", frame
        finally:
            cap.release()

    return frames(), fps if fps > 0 else 10.0


def draw(frame: np.ndarray, box, ok: bool, pme: float, index: int) -> np.ndarray:
    """The frame with the box (green tracked, red lost) and its PME written above it."""
    import cv2

    out = frame.copy()
    x, y = box[0], box[1]
    colour = (0, 200, 0) if ok else (0, 0, 255)
    _rectangle(out, box, colour)
    label = f"#{index} PME {pme:.1f}" if math.isfinite(pme) else f"#{index}"
    cv2.putText(out, label, (round(x), max(12, round(y) - 6)), cv2.FONT_HERSHEY_SIMPLEX, 0.5, colour, 1,
                cv2.LINE_AA)
    return out


def track_source(tracker: BoxTracker, source: Path, box, boxes_out: Path | None = None,
                 video_out: Path | None = None) -> int:
    """Track through `source`; write box lines to the file `boxes_out` (standard output if None) and, if asked, an
    mp4v video. Both are opened once the first frame is tracked, so a run that cannot start (no such source, a box
    outside the frame) leaves the files of an earlier run as they were.

    Every frame must have the first one's size: the trackers' boxes are in its pixels, and OpenCV's video writer
    drops a frame of another size with no more than a warning.

    Returns the number of frames processed.
    """
    frames, fps = open_source(source)
    lines = writer = None
    n = 0

    def write_line(text: str) -> None:
        try:
            lines.write(text)
        except OSError as exc:
            if boxes_out is None:   # standard output's as they are: a reader gone (BrokenPipeError) is no error
                raise
            raise CannotWrite.naming(exc, boxes_out) from None

    try:
        for name, frame in frames:
            if n > 0 and frame.shape[:2] != first_hw:
                raise ValueError(f"{name} is {frame.shape[1]}x{frame.shape[0]}, the first frame "
                                 f"{first_hw[1]}x{first_hw[0]}: a sequence's frames must all have one size")
            if n == 0:
                first_hw = frame.shape[:2]
                check_box(box, frame.shape)     # the library tracker's check, for OpenCV's peers too
                tracker.init(frame, box)
                cur, ok, pme = tuple(float(v) for v in box), True, math.nan
                if video_out is not None:
                    writer = _open_video(Path(video_out), fps, frame.shape[1::-1])
                lines = _open_boxes(boxes_out)
                write_line(BOXES_HEADER + "\n")
            else:
                cur = tracker.update(frame)
                ok, pme = bool(tracker.ok), float(tracker.pme)
            write_line(",".join(f"{v:.3f}" for v in cur) + f",{pme:.3f},{int(ok)}\n")
            if writer is not None:
                writer.write(draw(frame, cur, ok, pme, n))
            n += 1
    finally:
        if writer is not None:
            writer.release()
        if lines is not None and lines is not sys.stdout:
            try:
                lines.close()       # writes what its buffer holds: a full disk fails here
            except OSError as exc:
                raise CannotWrite.naming(exc, boxes_out) from None
    if n == 0:
        raise ValueError(f"{source}: no frames")
    if writer is not None:
        _check_video(Path(video_out), n)
    log.info("tracked %d frames of %s", n, source)
    return n


def _open_boxes(path: Path | None) -> TextIO:
    """The box file at `path` (its folder made), or standard output."""
    if path is None:
        return sys.stdout
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return open(path, "w")


def _bgr(hex_colour: str) -> tuple[int, int, int]:
    red, green, blue = (int(hex_colour[i:i + 2], 16) for i in (1, 3, 5))
    return blue, green, red


def write_comparison_video(seq: Sequence, tracks: list[tuple[str, str, np.ndarray]], path: Path,
                           fps: float = 10.0) -> None:
    """An mp4v video of `seq`: its ground truth (white) and each track's boxes, tracks = (name, '#rrggbb' colour,
    0-based N x 4 boxes), under a band that names them with their IoU on the frame shown (the band sits above
    the frame, so that it hides nothing of small frames)."""
    import cv2

    overlaps = [metrics.iou(boxes, seq.gt) for _, _, boxes in tracks]
    present = metrics.valid_mask(seq.gt)
    white = (255, 255, 255)
    row_height = 18
    band = row_height * (len(tracks) + 2) + 6
    writer = None
    try:
        for index, frame_path in enumerate(seq.frames):
            frame = read_frame(frame_path)
            if writer is None:
                writer = _open_video(path, fps, (frame.shape[1], frame.shape[0] + band))
            rows = [(f"{drawable(seq.name)}  #{index + 1}/{len(seq)}", white),
                    ("ground truth" if present[index] else "ground truth: target absent", white)]
            if present[index]:
                _rectangle(frame, seq.gt[index], white)
            for (name, colour, boxes), overlap in zip(tracks, overlaps):
                if np.isfinite(boxes[index]).all():
                    _rectangle(frame, boxes[index], _bgr(colour))
                rows.append((f"{name}  IoU {overlap[index]:.2f}" if present[index] else name, _bgr(colour)))
            canvas = np.zeros((frame.shape[0] + band, frame.shape[1], 3), np.uint8)
            canvas[band:] = frame
            for row, (text, colour) in enumerate(rows):
                cv2.putText(canvas, text, (6, row_height * row + 17), cv2.FONT_HERSHEY_SIMPLEX, 0.5, colour, 1,
                            cv2.LINE_AA)
            writer.write(canvas)
    finally:
        if writer is not None:
            writer.release()
    _check_video(path, len(seq.frames))


def _open_video(path: Path, fps: float, width_height: tuple[int, int]):
    """An mp4v cv2.VideoWriter at `path` (its folder made); OSError if OpenCV cannot write it."""
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    writer = cv2.VideoWriter(opencv_path(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, width_height)
    if not writer.isOpened():
        raise OSError(f"cannot write video {path}")
    return writer


def _check_video(path: Path, frames: int) -> None:
    """CannotWrite unless the video at `path` opens with its `frames` frames: OpenCV's writer only prints "Failed to
    write frame" when the disk is full, and leaves a file no player opens (its index, the moov atom, missing)."""
    import cv2

    video = cv2.VideoCapture(opencv_path(path))
    opened = video.isOpened()
    written = int(video.get(cv2.CAP_PROP_FRAME_COUNT)) if opened else 0
    video.release()
    if written < frames - FRAME_COUNT_SLACK:
        found = f"it holds {written} of the {frames} frames" if opened else "it does not open"
        raise CannotWrite(None, f"OpenCV's video writer failed (a full disk?): {found}", str(path))


def _rectangle(frame: np.ndarray, box, colour) -> None:
    import cv2

    x, y, w, h = box
    cv2.rectangle(frame, (round(x), round(y)), (round(x + w), round(y + h)), colour, 2)
