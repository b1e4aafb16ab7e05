"""`tacf demo`: the whole loop on one machine, for a newcomer's first minute.

1. start `tacf serve` as a child process on a free loopback port and wait until it answers;
2. publish SOURCE (default: the generated scene) on an image key: the "camera" holds its first frame until the
   session has its first box (like an operator drawing a box on a paused image), then plays;
3. start a session on the target's box (the scene's ground truth, a sequence's groundtruth.txt, --box, or a
   centred box), print boxes and health as they arrive, and how well the boxes follow the ground truth;
4. stop the session, the publisher and the service, cleanly, in that order.
"""
from __future__ import annotations

import logging
import math
import sys
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import TextIO

from tacf.boxes import check_box
from tacf.eval.datasets.base import read_boxes
from tacf.eval.metrics import box_iou
from tacf_clients.client import TrackingClient
from tacf_clients.errors import TacfError
from tacf_clients.local_service import LocalService, LocalServiceError
from tacf_clients.publisher import FramePublisher
from tacf_clients.scene import Scene, SceneSource
from tacf_clients.sources import (CaptureSource, FrameSource, ImageFolderSource, SourceError, SourceFrame,
                                  open_source, paced_frames)
from tacf_clients.zconfig import open_session
from tacf_schemas.images import FrameError
from tacf_schemas.models import BoxResult, Health

log = logging.getLogger(__name__)

Box = tuple[float, float, float, float]
# The rate of every source but a video file with its own (a camera or URL is thinned to it): real time for the
# tracker on one core.
DEMO_FPS = 20.0
FAILED_GRACE_S = 5.0      # a session reported "failed" for this long (the service restarts workers) ends the demo
FOLLOW_IOU = 0.3          # a box "follows" the target when its IoU with the ground truth exceeds this
LAST_BOX_WAIT_S = 2.0     # once the source ends, how long the box of its last frame is waited for
# A start still unanswered after this long is most likely the first after an install, whose worker compiles the
# tracker's loops (numba; cached on disk for later runs): said, so that a newcomer's first run is not silent. A start
# took 1.2-1.4 s cached on an idle 2-core VM, up to about 3 s under load, and 4.6-9.5 s with nothing cached.
SLOW_START_S = 4.0
SLOW_START_HINT = "still starting (the first run after an install compiles the tracker's loops: 5-10 s, once)"


@dataclass(frozen=True)
class DemoOptions:
    source: str = "scene"
    box: Box | None = None
    seconds: float = 10.0
    fps: float | None = None
    encoding: str = "jpeg"
    profile: str | None = None
    every: int | None = None              # print every Nth box (None: about 3 lines a second)
    node: str = "demo"
    image_key: str = "demo/camera/front"
    start_timeout: float = 60.0           # service start-up (imports, worker spawn) on a slow machine


@dataclass
class DemoReport:
    """What the demo saw. boxes, lost, seconds and ious count the boxes on frames published once the camera
    moved: those on the held first frame, which is copied until the first box comes, would inflate the rate and
    the overlap."""
    ok: bool = False
    sid: str | None = None
    boxes: int = 0
    lost: int = 0
    seconds: float = 0.0                  # from the first box counted to the last
    ious: list[float] = field(default_factory=list)
    last_health: Health | None = None
    service_exit: int | None = None
    error: str | None = None
    interrupted: bool = False             # `stop` was set (Ctrl-C): not an error

    @property
    def box_fps(self) -> float:
        return (self.boxes - 1) / self.seconds if self.seconds > 0 else 0.0

    @property
    def mean_iou(self) -> float | None:
        return sum(self.ious) / len(self.ious) if self.ious else None

    @property
    def followed(self) -> float | None:
        """Fraction of boxes with IoU > FOLLOW_IOU against the ground truth (None without ground truth)."""
        return sum(v > FOLLOW_IOU for v in self.ious) / len(self.ious) if self.ious else None


class GroundTruth:
    """Ground-truth box by source frame index: the scene's, or a sequence's groundtruth.txt (1-based x,y)."""

    def __init__(self, scene: Scene | None = None, boxes: list[Box] | None = None):
        self.scene, self.boxes = scene, boxes

    @classmethod
    def for_source(cls, source: FrameSource) -> "GroundTruth | None":
        if isinstance(source, SceneSource):
            return cls(scene=source.scene)
        if isinstance(source, ImageFolderSource):
            for candidate in (source.folder / "groundtruth.txt", source.folder.parent / "groundtruth.txt",
                              source.folder / "groundtruth_rect.txt", source.folder.parent / "groundtruth_rect.txt"):
                if candidate.is_file():
                    try:        # the eval toolkit's reader: a VOT polygon x1,y1,...,x4,y4 is the box enclosing it
                        boxes = [tuple(box) for box in read_boxes(candidate).tolist()]
                    except ValueError as exc:
                        log.warning("ground truth not used: %s", exc)
                        return None
                    return cls(boxes=boxes) if boxes else None
        return None

    def box(self, index: int) -> Box | None:
        if self.scene is not None:
            return self.scene.box(index)
        if self.boxes is not None and 0 <= index < len(self.boxes):
            box = self.boxes[index]
            return box if all(math.isfinite(v) for v in box) and box[2] > 0 and box[3] > 0 else None
        return None


class HoldingPublisher:
    """Publishes a source on a thread, paced as publish() paces it; while `hold` is set it republishes the first
    frame (new seq each time). Remembers which source frame each recent seq carried, for the ground-truth
    comparison."""

    def __init__(self, session, source: FrameSource, key: str, fps: float, encoding: str):
        self.source, self.fps = source, fps
        self.publisher = FramePublisher(session, key, encoding=encoding, quality=90)
        self.hold, self.stop, self.ended = threading.Event(), threading.Event(), threading.Event()
        self.hold.set()
        self._index_of_seq: OrderedDict[int, int] = OrderedDict()
        self._last_sent = -1
        self._lock = threading.Lock()
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="tacf-demo-publisher")

    def start(self) -> None:
        self._thread.start()

    def index_of(self, seq: int) -> int | None:
        with self._lock:
            return self._index_of_seq.get(seq)

    @property
    def last_seq(self) -> int:
        """The seq of the last frame sent (-1 before the first)."""
        with self._lock:
            return self._last_sent

    def _put(self, frame: SourceFrame, stamp_ns: int | None) -> None:
        # Noted before the frame goes: its box can come back before put() returns (on a busy machine it did, and
        # the demo printed that box without its IoU). A frame that fails to encode leaves its seq to the next.
        with self._lock:
            self._index_of_seq[self.publisher.next_seq] = frame.index
            while len(self._index_of_seq) > 4096:
                self._index_of_seq.popitem(last=False)
        sent = self.publisher.put(frame.image, stamp_ns)
        with self._lock:
            self._last_sent = sent.seq

    def _run(self) -> None:
        try:
            previous = None
            for frame in paced_frames(self.source, self.fps, self.stop, hold=self.hold):
                # As publish() stamps them: a live frame when it was read (its age then counts the encoding), the
                # rest when sent, the held first frame's repeats among them (not a frame read long ago).
                stamp_ns = frame.stamp_ns if self.source.live and frame is not previous else None
                previous = frame
                try:
                    self._put(frame, stamp_ns)
                except FrameError as exc:
                    if self.last_seq < 0:
                        raise
                    # as publish() does: one odd image in a folder ended the whole demo with its error
                    log.warning("frame %d of %s skipped: %s", frame.index, self.source.name, exc)
        except (FrameError, SourceError) as exc:     # what the source gives cannot be sent: the demo says so
            self.error = exc
        except BaseException as exc:  # reported by the demo, never lost on this thread
            self.error = exc
            log.exception("demo publisher failed")
        finally:
            self.ended.set()

    def close(self) -> None:
        self.stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5)
        self.publisher.close()


class Printer:
    """The demo's console output (it is CLI output, hence print rather than logging): progress to `out`,
    errors to `err`."""

    def __init__(self, out: TextIO, err: TextIO, every: int):
        self.out, self.err, self.every, self.t0 = out, err, max(1, every), time.monotonic()

    def line(self, text: str, error: bool = False) -> None:
        print(f"[{time.monotonic() - self.t0:5.1f}s] {text}", file=self.err if error else self.out, flush=True)

    def box(self, result: BoxResult, count: int, overlap: float | None) -> None:
        if count % self.every != 1 and self.every > 1:
            return
        x, y, w, h = result.box
        status = "ok  " if result.ok else "LOST"
        score = f"  iou {overlap:4.2f}" if overlap is not None else ""
        self.line(f"box    seq {result.seq:5d}  ({x:6.1f}, {y:6.1f}, {w:5.1f}, {h:5.1f})  {status}  "
                  f"pme {result.pme:6.1f}{score}  {result.processing_ms:5.1f} ms")

    def health(self, h: Health) -> None:
        age = f"{h.frame_age_ms:.0f} ms" if h.frame_age_ms is not None else "-"
        self.line(f"health {h.state:<8}  {h.fps:5.1f} fps  proc {h.processing_ms_mean:.1f}/{h.processing_ms_p95:.1f}"
                  f" ms (mean/p95)  age {age}  received {h.frames_received}  processed {h.frames_processed}  "
                  f"dropped {h.frames_dropped}" + (f"  ({h.message})" if h.message else ""))


def initial_box(options: DemoOptions, source: FrameSource, truth: GroundTruth | None,
                stop: threading.Event) -> tuple[Box, str]:
    """(box, where it came from) for the first frame; --box checked against it (a box the tracker cannot start on
    was refused by the service seconds later, after its start). A live source that opened and gives no frame is
    reopened until it does, or until `stop` (Ctrl-C: it was not heard there)."""
    if options.box is None and truth is not None and (box := truth.box(0)) is not None:
        return box, "ground truth"
    first = next(source.frames(should_stop=stop.is_set), None)
    if first is None:
        raise ValueError(f"source {options.source!r} has no frames")
    height, width = first.image.shape[:2]
    if options.box is not None:
        try:
            check_box(options.box, (height, width))
        except ValueError as exc:
            raise ValueError(f"cannot start a session with --box on the first frame: {exc}") from None
        return options.box, "--box"
    w, h = max(8.0, width / 5), max(8.0, height / 5)
    return ((width - w) / 2, (height - h) / 2, w, h), "centre of the frame (pass --box x,y,w,h to choose)"


def run_demo(options: DemoOptions | None = None, stop: threading.Event | None = None,
             out: TextIO | None = None, err: TextIO | None = None) -> DemoReport:
    """Run the demo until done or `stop` is set; progress on `out`, errors on `err` (default stdout, stderr).

    A source that cannot be opened or has no frames raises ValueError or FileNotFoundError before anything
    starts: an error of the caller's, not of the demo."""
    options, stop = options or DemoOptions(), stop or threading.Event()
    report = DemoReport()
    printer = Printer(out or sys.stdout, err or sys.stderr, options.every or 10)
    source = open_source(options.source, should_stop=stop.is_set)
    with source:
        truth = GroundTruth.for_source(source)
        box, origin = initial_box(options, source, truth, stop)
        if isinstance(source, CaptureSource) and not source.live:
            # A video file starts again at frame 0, which the box is on; a camera or stream is not opened twice
            # (one may take a single client), folders and the scene start again by themselves.
            source.close()
            source = open_source(options.source, should_stop=stop.is_set)
        fps = options.fps or (None if source.live or isinstance(source, SceneSource) else source.fps) or DEMO_FPS
        if options.every is None:
            printer.every = max(1, round(fps / 3))
        service = LocalService(node=options.node, ready_timeout=options.start_timeout)
        printer.line(f"starting the tracking service (tacf serve, node {options.node!r}) on {service.endpoint}")
        try:
            with service:
                _run_loop(options, source, truth, box, origin, fps, service, printer, report, stop)
                printer.line("stopping the service")
        except LocalServiceError as exc:
            report.error = str(exc)
            printer.line(f"the service failed: {exc}", error=True)
        finally:
            source.close()
        report.service_exit = service.returncode
    report.interrupted = stop.is_set()
    _summary(printer, report, truth is not None)
    return report


def _run_loop(options: DemoOptions, source: FrameSource, truth: GroundTruth | None, box: Box, origin: str,
              fps: float, service: LocalService, printer: Printer, report: DemoReport,
              stop: threading.Event) -> None:
    with open_session(service.options) as session:
        started = time.monotonic()
        if not service.wait_ready(session, cancel=stop):
            return
        printer.line(f"service ready in {time.monotonic() - started:.1f} s")
        client = TrackingClient(session=session, node=options.node, timeout=10.0)
        publisher = HoldingPublisher(session, source, options.image_key, fps, options.encoding)
        publisher.start()
        try:
            printer.line(f"publishing {source.name} on {options.image_key!r} at {fps:.0f} fps ({options.encoding})")
            while publisher.last_seq < 0 and not publisher.ended.is_set() and not stop.is_set():
                time.sleep(0.01)
            if publisher.last_seq < 0:
                return                   # stopped, or no frame could be sent: the publisher's error says why
            with client.results(node=options.node) as results:
                hint = threading.Timer(SLOW_START_S, printer.line, [SLOW_START_HINT])
                hint.start()
                try:
                    info = client.start(options.image_key, box, seq=publisher.last_seq, profile=options.profile,
                                        sid="demo")
                finally:
                    hint.cancel()
                report.sid = info.sid
                printer.line(f"session {info.sid!r} started (profile {info.profile}) on box "
                             f"({box[0]:.0f}, {box[1]:.0f}, {box[2]:.0f}, {box[3]:.0f}) from {origin}")
                printer.line("waiting for the first box (the service starts a worker process for the session)")
                _follow(options, publisher, results, truth, printer, report, stop)
                final = client.stop(info.sid)
                printer.line(f"session {final.sid!r} stopped ({final.state})")
            report.ok = report.boxes > 0 and publisher.error is None
        except (TacfError, TimeoutError) as exc:
            report.error = f"{type(exc).__name__}: {exc}"
            printer.line(f"error: {report.error}", error=True)
        finally:
            publisher.close()
            if isinstance(publisher.error, (FrameError, SourceError)):     # the source is at fault, not the demo
                raise publisher.error
            if publisher.error is not None and report.error is None:
                report.error = f"publisher: {publisher.error}"


def _follow(options: DemoOptions, publisher: HoldingPublisher, results, truth: GroundTruth | None,
            printer: Printer, report: DemoReport, stop: threading.Event) -> None:
    """Print results until the time is up, the source ends or `stop` is set."""
    deadline = counted_from = first_counted = failed_since = last_box_deadline = None
    seen, newest_seq = 0, -1
    first_box_timeout = time.monotonic() + options.start_timeout
    while not stop.is_set():
        now = time.monotonic()
        if deadline is not None and now >= deadline:
            break
        if deadline is None and now >= first_box_timeout:
            raise TimeoutError("no box from the session")
        if publisher.ended.is_set() and deadline is not None:
            # the last frames sent are still being tracked: stopping at once lost their boxes (a 12-frame folder
            # counted 10 boxes; a slow tracker lost the last box every time)
            last_box_deadline = last_box_deadline or now + LAST_BOX_WAIT_S
            if newest_seq >= publisher.last_seq or now >= last_box_deadline:
                printer.line("the source ended")
                break
        item = results.get(timeout=0.2)
        if isinstance(item, Health) and item.sid == report.sid:
            report.last_health = item
            printer.health(item)
            if item.state != "failed":
                failed_since = None
            elif failed_since is None:
                failed_since = now
            elif now - failed_since > FAILED_GRACE_S:
                raise TimeoutError(f"the session failed: {item.message or 'no message'}")
        elif isinstance(item, BoxResult) and item.sid == report.sid:
            newest_seq = max(newest_seq, item.seq)
            if deadline is None:             # first box: the camera starts moving
                publisher.hold.clear()
                counted_from = publisher.last_seq + 1
                deadline = time.monotonic() + options.seconds
            overlap = None
            index = publisher.index_of(item.seq)
            if truth is not None and index is not None and (gt := truth.box(index)) is not None:
                overlap = box_iou(tuple(item.box), gt)
            if item.seq >= counted_from:
                if first_counted is None:
                    first_counted = now
                report.boxes += 1
                report.lost += not item.ok
                report.seconds = now - first_counted
                if overlap is not None:
                    report.ious.append(overlap)
            seen += 1
            printer.box(item, seen, overlap)


def _summary(printer: Printer, report: DemoReport, has_truth: bool) -> None:
    if report.boxes:
        text = f"{report.boxes} boxes in {report.seconds:.1f} s ({report.box_fps:.1f} per second), {report.lost} lost"
        if has_truth and report.ious:
            text += (f"; boxes on the target (IoU > {FOLLOW_IOU}) in {100 * report.followed:.0f}% of frames, "
                     f"mean IoU {report.mean_iou:.2f}")
        printer.line(text)
    if report.service_exit is not None:
        printer.line(f"service exited with code {report.service_exit}")
    if report.interrupted:
        printer.line("interrupted")
    elif report.ok:
        printer.line("done")
    else:
        printer.line(f"demo failed: {report.error or 'no boxes received'}", error=True)
