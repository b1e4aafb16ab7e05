"""Frame sources, the generated scene and the frame publisher over real Zenoh sessions on loopback; live streams
from a real HTTP MJPEG camera on loopback (the format of IP cameras and phone camera apps), read through OpenCV's
FFmpeg: a stream that ends, stalls or goes away is reopened, and the publisher's seq runs on across reconnections."""
from __future__ import annotations

import functools
import http.server
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
import types
from pathlib import Path

import cv2
import numpy as np
import pytest
import zenoh

from tacf.eval.metrics import box_iou
from tacf_clients.local_service import free_port
from tacf_clients.publisher import FramePublisher, publish
import tacf_clients.publisher as publisher_module
from tacf_clients.scene import Scene, SceneSource
import tacf_clients.sources as sources
from tacf_clients.sources import (CaptureSource, FrameSource, ImageFolderSource, Pacer, SourceError, SourceFrame,
                                   Thinner, never_stop, open_source, paced_frames)
from tacf_clients.zconfig import ZenohOptions, make_config
from tacf_schemas.codec import decode
from tacf_schemas.images import FrameError, decode_frame, encode_frame
from tacf_schemas.models import Frame
from tacf_service.loopback import wait_until

from mjpeg_camera import MjpegCamera, interrupted_while_a_stream_opens

KEY = "test/camera/front"


def _frames(n: int, width: int = 96, height: int = 64) -> list[np.ndarray]:
    """Distinct, textured frames: frame i has a bright square at x = 4 i."""
    rng = np.random.default_rng(1)
    noise = rng.integers(0, 120, (height // 8, width // 8, 3), dtype=np.uint8)
    base = cv2.resize(noise, (width, height), interpolation=cv2.INTER_CUBIC)   # smooth: survives MJPG
    frames = []
    for i in range(n):
        image = base.copy()
        image[10:30, 4 * i:4 * i + 20] = (255, 255, 255)
        frames.append(image)
    return frames


def _write_folder(folder: Path, images: list[np.ndarray]) -> Path:
    folder.mkdir(parents=True)
    for i, image in enumerate(images):
        cv2.imwrite(str(folder / f"{i + 1:06d}.png"), image)
    (folder / "notes.txt").write_text("not an image")
    return folder


def _write_video(path: Path, images: list[np.ndarray], fps: float = 25.0) -> Path:
    height, width = images[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (width, height))
    assert writer.isOpened()
    for image in images:
        writer.write(image)
    writer.release()
    return path


class Collector:
    """A listening session that collects the Frames published on KEY."""

    def __init__(self):
        self.port = free_port()
        self.session = zenoh.open(make_config(ZenohOptions.listener(f"tcp/127.0.0.1:{self.port}")))
        self.frames: list[Frame] = []
        self._lock = threading.Lock()
        self._sub = self.session.declare_subscriber(KEY, self._on_sample)

    def _on_sample(self, sample):
        frame = decode(sample.payload.to_bytes(), Frame)
        with self._lock:
            self.frames.append(frame)

    def wait(self, n: int, timeout: float = 10.0) -> list[Frame]:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self._lock:
                if len(self.frames) >= n:
                    return list(self.frames)
            time.sleep(0.01)
        return list(self.frames)

    def close(self):
        self.session.close()


@pytest.fixture
def collector():
    c = Collector()
    yield c
    c.close()


def _publisher_session(port: int) -> zenoh.Session:
    return zenoh.open(make_config(ZenohOptions.loopback(port)))


def _wait_matched(session: zenoh.Session, timeout: float = 5.0) -> None:
    """Publications before the subscriber is matched go nowhere (ZENOH.md §2.2)."""
    with FramePublisher(session, KEY) as probe:
        assert probe.wait_matched(timeout), "the collector's subscriber never matched"


# ----------------------------------------------------------------------------------------------- sources


def test_scene_is_deterministic_and_the_target_stays_inside():
    scene = Scene()
    assert np.array_equal(scene.frame(17), Scene().frame(17))
    for i in range(0, 2 * scene.period, 7):
        x, y, w, h = scene.box(i)
        assert 0 <= x and 0 <= y and x + w <= scene.width and y + h <= scene.height
    steps = [np.hypot(scene.box(i + 1)[0] - scene.box(i)[0], scene.box(i + 1)[1] - scene.box(i)[1])
             for i in range(scene.period)]
    assert 0 < max(steps) < 8, "the target must move, but slowly enough to track"
    # the ground-truth box holds the (red) target: its mean colour is far from the terrain's
    image = scene.frame(40)
    x, y, w, h = (int(v) for v in scene.box(40))
    inside = image[y:y + h, x:x + w].reshape(-1, 3).mean(0)
    assert inside[2] > inside[1] + 40
    assert box_iou(scene.box(5), scene.box(5)) == 1.0 and box_iou((0, 0, 1, 1), (5, 5, 1, 1)) == 0.0
    assert Scene.from_spec("scene:320x240").width == 320
    with pytest.raises(ValueError):
        Scene.from_spec("scene:big")


def test_a_scene_larger_than_a_frame_may_be_is_refused_at_once():
    """scene:100000x100000 went on to build its terrain and died of a MemoryError (83.8 GiB) in a traceback; no
    service would take frames over the wire limits anyway."""
    for spec in ("scene:100000x100000", "scene:9000x200", "scene:5000x5000"):
        with pytest.raises(ValueError, match="exceeds the limits"):
            Scene.from_spec(spec)
    assert Scene.from_spec("scene:8192x2048").width == 8192
    done = subprocess.run([sys.executable, "-m", "tacf.cli", "publish", "scene:100000x100000", "--key", KEY,
                           "--connect", f"tcp/127.0.0.1:{free_port()}"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and done.stderr.startswith("tacf publish: frame size 100000x100000 exceeds"), \
        done.stderr


def test_image_folder_source_sorted_skips_non_images_and_loops(tmp_path):
    images = _frames(4)
    folder = _write_folder(tmp_path / "seq" / "img", images)
    source = open_source(str(tmp_path / "seq"))           # a sequence folder: its img/ is used
    assert isinstance(source, ImageFolderSource) and len(source) == 4
    got = [f.image for f in source]
    assert all(np.array_equal(a, b) for a, b in zip(got, images)) and len(got) == 4
    looped = ImageFolderSource(folder, loop=True).frames()
    indices = [next(looped).index for _ in range(10)]
    assert indices == [0, 1, 2, 3, 0, 1, 2, 3, 0, 1]
    with pytest.raises(ValueError):
        ImageFolderSource(tmp_path / "seq" / "img" / ".." / "..")   # no images anywhere


def test_a_sequence_folder_plays_its_img_not_a_stray_image_beside_it(tmp_path):
    # as tacf track and tacf eval read it (publish and demo played the preview alone, demo with the sequence's box)
    images = _frames(4)
    _write_folder(tmp_path / "seq" / "img", images)
    cv2.imwrite(str(tmp_path / "seq" / "preview.png"), images[3])
    with open_source(str(tmp_path / "seq")) as source:
        assert source.folder == tmp_path / "seq" / "img" and len(source) == 4
        assert all(np.array_equal(f.image, image) for f, image in zip(source, images))


def test_a_folder_of_unreadable_images_is_an_error_even_looping(tmp_path):
    folder = tmp_path / "garbage"
    folder.mkdir()
    for name in ("a.jpg", "b.jpg"):
        (folder / name).write_bytes(b"not a jpeg")
    source = ImageFolderSource(folder, loop=True)
    assert list(source.frames(should_stop=lambda: True)) == []      # the stop flag is seen between images
    with pytest.raises(SourceError, match="none of the 2 images"):
        next(source.frames())


def test_video_file_source_reads_every_frame_and_loops(tmp_path):
    images = _frames(6)
    path = _write_video(tmp_path / "clip.avi", images, fps=25)
    with open_source(str(path)) as source:
        assert isinstance(source, CaptureSource) and not source.live
        assert source.fps == pytest.approx(25)
        frames = list(source)
    assert [f.index for f in frames] == list(range(6))
    assert frames[0].image.shape == (64, 96, 3)
    # MJPG is lossy: the bright square must still be where it was written
    for i, (f, image) in enumerate(zip(frames, images)):
        assert np.abs(f.image.astype(int) - image).mean() < 6
        assert f.image[20, 4 * i + 10].min() > 200        # the bright square of frame i
    with open_source(str(path), loop=True) as source:
        it = source.frames()
        assert [next(it).index for _ in range(8)] == [0, 1, 2, 3, 4, 5, 0, 1]


def test_a_looping_video_that_cannot_be_reopened_is_a_source_error(tmp_path):
    """The file removed while it plays: the reopen at its end raised a bare ValueError, a traceback in
    `tacf publish`; it is now the SourceError the command reports in one line (exit 2)."""
    path = _write_video(tmp_path / "clip.avi", _frames(3), fps=25)
    with open_source(str(path), loop=True) as source:
        frames = source.frames()
        assert [next(frames).index for _ in range(3)] == [0, 1, 2]
        path.unlink()
        with pytest.raises(SourceError, match="cannot reopen .*clip.avi to play it again"):
            next(frames)


def test_open_source_rejects_what_does_not_exist(tmp_path):
    with pytest.raises(FileNotFoundError):
        open_source(str(tmp_path / "missing.mp4"))
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(b"not a video")
    with pytest.raises(ValueError):
        open_source(str(bad))
    assert isinstance(open_source("scene"), SceneSource)


def test_scene_with_a_folder_of_that_name_here_is_the_generated_scene_and_says_how_to_get_the_folder(
        tmp_path, monkeypatch, caplog):
    """A folder named `scene` in the current folder was passed over for the generated scene without a word."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "scene").mkdir()
    cv2.imwrite(str(tmp_path / "scene" / "000001.png"), np.zeros((48, 64, 3), np.uint8))
    assert isinstance(open_source("scene"), SceneSource)
    assert "'scene' is the generated scene; give ./scene for the folder of that name here" in caplog.text
    assert isinstance(open_source("./scene"), ImageFolderSource)


def test_a_folder_of_16_bit_images_is_stretched_to_8_bits(tmp_path):
    """12-bit thermal data in 16-bit PNGs: cv2.IMREAD_COLOR kept the high byte; frames of 0..4095 came out 0..15."""
    folder = tmp_path / "thermal"
    folder.mkdir()
    ramp = np.tile(np.linspace(0, 4095, 64).astype(np.uint16), (48, 1))
    cv2.imwrite(str(folder / "000001.png"), ramp)
    image = next(iter(open_source(str(folder)))).image
    assert image.dtype == np.uint8 and image.shape == (48, 64, 3)
    assert image.min() == 0 and image.max() == 255


@pytest.mark.parametrize("pixels", [np.float32, np.uint16, np.float64, np.int16, np.int32])
def test_a_folder_of_one_channel_tiffs_is_stretched_to_8_bits(tmp_path, pixels):
    """A radiometric thermal export: one channel of floats (NaN where nothing was measured), which IMREAD_COLOR
    cannot read: every image was skipped and the folder refused. Doubles and signed or 32-bit integers (degrees
    Celsius x 100) ended `tacf publish` with OpenCV's traceback: cvtColor takes 8-bit, 16-bit unsigned and float32
    pixels only."""
    folder = tmp_path / "radiometric"
    folder.mkdir()
    kelvin = np.tile(np.linspace(250, 320, 64), (48, 1)).astype(pixels)
    if pixels == np.float32:
        kelvin[0, :8] = np.nan
        kelvin[1, :2] = np.inf, -np.inf   # saturated and dead pixels: an inf left the rest of the image black
    cv2.imwrite(str(folder / "000001.tiff"), kelvin)
    image = next(iter(open_source(str(folder)))).image
    assert image.dtype == np.uint8 and image.shape == (48, 64, 3)
    assert image.min() == 0 and image.max() == 255 and image[47, 63].tolist() == [255, 255, 255]
    assert 120 < image[47, 32, 0] < 135   # half way up the ramp


def test_an_image_beyond_the_wire_s_limits_is_skipped_once_frames_went_out(tmp_path, collector):
    """One odd image in a folder (a panorama 9000 px wide) ended the whole run with its FrameError."""
    images = _frames(3)
    folder = _write_folder(tmp_path / "img", images)
    cv2.imwrite(str(folder / "000002.png"), np.zeros((16, 9000, 3), np.uint8))
    with _publisher_session(collector.port) as session:
        _wait_matched(session)
        with open_source(str(folder)) as source:
            assert publish(session, source, KEY, fps=40, encoding="png").frames == len(images) - 1
        (folder / "000001.png").unlink()
        with open_source(str(folder)) as source, pytest.raises(FrameError):       # the first: an error, as before
            publish(session, source, KEY, fps=40)


def test_a_folder_named_by_digits_is_a_folder_not_a_camera(tmp_path, monkeypatch):
    """`tacf publish 7` with a folder ./7 tried camera 7 ("cannot open video source 7")."""
    _write_folder(tmp_path / "7", _frames(2))
    monkeypatch.chdir(tmp_path)
    assert isinstance(open_source("7"), ImageFolderSource)


def test_a_named_pipe_is_read_as_a_live_source(tmp_path):
    """A camera device (/dev/video0) or a named pipe is neither a file nor a folder: it was refused as "neither a
    file, a folder, a camera index, a URL nor 'scene'"."""
    clip = _write_video(tmp_path / "clip.avi", _frames(6), fps=25)
    pipe = tmp_path / "video.pipe"
    os.mkfifo(pipe)
    writer = threading.Thread(target=lambda: pipe.write_bytes(clip.read_bytes()), daemon=True)
    writer.start()
    with open_source(str(pipe), reconnect=False) as source:
        assert isinstance(source, CaptureSource) and source.live
        assert [f.index for f in source] == list(range(6))
    writer.join(5)


@pytest.fixture
def web_folder(tmp_path):
    """An HTTP server on loopback serving tmp_path's files."""
    handler = functools.partial(_QuietFileHandler, directory=str(tmp_path))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}"
    server.shutdown()
    server.server_close()


class _QuietFileHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


def test_a_recorded_clip_given_by_url_plays_as_a_file(tmp_path, web_folder):
    """A video file's URL (http://, file://) was taken for a live camera: sent unpaced, its end taken for a failure
    and reopened forever, --loop ignored. Now it plays once at its own rate, or loops."""
    _write_video(tmp_path / "clip.avi", _frames(5), fps=10)
    for url in (f"{web_folder}/clip.avi", (tmp_path / "clip.avi").as_uri()):
        with open_source(url) as source:
            assert isinstance(source, CaptureSource) and not source.live and source.fps == pytest.approx(10)
            assert [f.index for f in source] == list(range(5)) and source.reconnects == 0
        with open_source(url, loop=True) as source:
            frames = source.frames()
            assert [next(frames).index for _ in range(7)] == [0, 1, 2, 3, 4, 0, 1]


def test_pacer_keeps_the_rate_without_bursting():
    pacer = Pacer(50)
    start = time.monotonic()
    for _ in range(10):
        pacer.wait()
    assert 0.17 <= time.monotonic() - start < 0.4
    time.sleep(0.1)                     # late by 5 periods: no burst of catch-up ticks afterwards
    t0 = time.monotonic()
    for _ in range(3):
        pacer.wait()
    assert time.monotonic() - t0 >= 0.03


def test_a_pacer_stalled_in_its_sleep_ticks_once_then_keeps_the_period(monkeypatch):
    """A stall inside the wait (a GC pause, SIGSTOP) made the late tick and the next one go out back to back."""
    pacer = Pacer(50)
    pacer.wait()
    real_sleep_unless = sources.sleep_unless

    def stalled(seconds, should_stop, slice_s=0.1):
        time.sleep(0.1)
        return real_sleep_unless(seconds, should_stop, slice_s)

    monkeypatch.setattr(sources, "sleep_unless", stalled)
    pacer.wait()                        # the tick due 20 ms after the first comes 100 ms late
    monkeypatch.setattr(sources, "sleep_unless", real_sleep_unless)
    t0 = time.monotonic()
    pacer.wait()
    assert time.monotonic() - t0 >= 0.015


def test_thinner_keeps_every_third_frame_of_a_30fps_camera():
    thinner = Thinner(10)
    admitted = []
    started = time.monotonic()
    for i in range(30):
        admitted.append(thinner.admit())
        time.sleep(1 / 30)
    expected = (time.monotonic() - started) * 10        # about 10 a second, whatever the sleeps really took
    assert expected - 2 <= sum(admitted) <= expected + 1.5
    assert sum(admitted) < 20
    assert all(Thinner(None).admit() for _ in range(5))


def test_thinner_keeps_every_third_frame_of_a_camera_whose_frames_come_a_little_early(monkeypatch):
    """A camera's frames come a few ms either side of its period: a frame due 0.1 s after the last one kept, coming
    at 0.098 s, must pass, or a 30 fps camera thinned to 10 fps gives every fourth frame (7.5 fps)."""
    clock = [0.0]
    monkeypatch.setattr(sources, "time", types.SimpleNamespace(monotonic=lambda: clock[0]))
    thinner = Thinner(10)
    admitted = []
    for i in range(30):
        clock[0] = i / 30 - (0.002 if i % 3 == 0 else 0.0)
        admitted.append(thinner.admit())
    assert admitted == [True, False, False] * 10


def test_a_pacer_whose_sleeps_overshoot_keeps_its_rate(monkeypatch):
    """Every sleep ends a little late (the timer's slack, a busy machine): ticks keep to the schedule, or a replay
    plays ever slower than asked, by as much per frame as a sleep overshoots."""
    clock = [0.0]

    def oversleeping(seconds, should_stop, slice_s=0.1):
        clock[0] += max(seconds, 0.0) + 0.001
        return False

    monkeypatch.setattr(sources, "time", types.SimpleNamespace(monotonic=lambda: clock[0]))
    monkeypatch.setattr(sources, "sleep_unless", oversleeping)
    pacer, ticks = Pacer(50), []
    for _ in range(11):
        pacer.wait()
        ticks.append(clock[0])
    assert ticks[-1] - ticks[0] == pytest.approx(10 / 50)


class CountingLiveSource(FrameSource):
    """A live source that delivers frame after frame as fast as it is read; each frame's index is its count."""
    live = True

    def __init__(self, image: np.ndarray):
        self.image, self.read = image, 0

    def frames(self, should_stop=never_stop):
        while not should_stop():
            self.read += 1
            yield SourceFrame(self.read - 1, self.image, time.time_ns())


def test_paced_frames_hold_the_first_frame_then_go_on(tmp_path):
    """While held, a replayed source stands still (it goes on from its second frame once released), and a live
    one is read on and dropped (released, it goes on from its newest frame, not from a stale buffer)."""
    for i, image in enumerate(_frames(5)):
        cv2.imwrite(str(tmp_path / f"{i:04d}.png"), image)
    stop, hold = threading.Event(), threading.Event()
    hold.set()
    replayed = paced_frames(ImageFolderSource(tmp_path), 200.0, stop, hold)
    indices = [next(replayed).index for _ in range(4)]
    hold.clear()
    indices += [frame.index for frame in replayed]
    assert indices == [0, 0, 0, 0, 1, 2, 3, 4]

    hold.set()
    source = CountingLiveSource(_frames(1)[0])
    live = paced_frames(source, 50.0, stop, hold)       # thinned to 50 fps from a source that never waits
    held = [next(live).index for _ in range(3)]         # the newest frame when the first was taken
    assert held == held[:1] * 3
    hold.clear()
    released = next(live).index
    assert held[0] + 3 < released <= source.read - 1, (held, released, source.read)
    stop.set()
    assert list(live) == []


# ----------------------------------------------------------------------------------------------- publisher


def test_publish_video_file_bgr8_matches_the_decoded_video(tmp_path, collector):
    images = _frames(8)
    path = _write_video(tmp_path / "clip.avi", images)
    with _publisher_session(collector.port) as session:
        _wait_matched(session)
        with open_source(str(path)) as source:
            stats = publish(session, source, KEY, fps=100, encoding="bgr8")
    assert stats.frames == 8 and stats.last_seq == 7
    frames = collector.wait(8)
    assert [f.seq for f in frames] == list(range(8))
    stamps = [f.stamp_ns for f in frames]
    assert stamps == sorted(stamps) and abs(stamps[-1] - time.time_ns()) < 10e9
    with open_source(str(path)) as source:
        expected = [f.image for f in source]
    for frame, image in zip(frames, expected):
        assert (frame.encoding, frame.width, frame.height) == ("bgr8", 96, 64)
        assert np.array_equal(decode_frame(frame), image)


def test_the_rate_reported_is_the_rate_the_frames_went_out_at(collector):
    """It was frames / (set-up + (n - 1) periods): five frames at 10 fps read 11.3 fps."""
    with _publisher_session(collector.port) as session, open_source("scene") as source:
        stats = publish(session, source, KEY, fps=10, max_frames=5)
    assert stats.frames == 5 and stats.fps == pytest.approx(10, rel=0.05), stats


def test_publish_image_folder_jpeg_loops_with_increasing_seq(tmp_path, collector):
    images = _frames(3)
    folder = _write_folder(tmp_path / "img", images)
    with _publisher_session(collector.port) as session:
        _wait_matched(session)
        with open_source(str(folder), loop=True) as source:
            started = time.monotonic()
            stats = publish(session, source, KEY, fps=40, encoding="jpeg", quality=95, max_frames=7)
            elapsed = time.monotonic() - started
    assert stats.frames == 7
    assert elapsed >= 6 / 40 * 0.9, "fps=40 paces the replay"
    frames = collector.wait(7)
    assert [f.seq for f in frames] == list(range(7))
    for frame in frames:
        assert frame.encoding == "jpeg" and frame.data[:2] == b"\xff\xd8"
        image = decode_frame(frame)
        expected = images[frame.seq % 3]
        assert np.abs(image.astype(int) - expected).mean() < 4


def test_publish_stop_event_and_encodings(tmp_path, collector):
    with _publisher_session(collector.port) as session:
        _wait_matched(session)
        with FramePublisher(session, KEY, encoding="mono8", first_seq=100) as pub:
            frame = pub.put(_frames(1)[0])
            assert (frame.encoding, len(frame.data), frame.seq) == ("mono8", 96 * 64, 100)
        with pytest.raises(ValueError):
            FramePublisher(session, "bad/*/key")
        stop = threading.Event()
        timer = threading.Timer(0.3, stop.set)
        timer.start()
        stats = publish(session, SceneSource(Scene.from_spec("scene:320x240")), KEY, fps=30, stop=stop)
        timer.join()
    assert 4 <= stats.frames <= 15
    frames = collector.wait(1 + stats.frames)
    assert frames[1].width == 320 and frames[1].height == 240


@pytest.mark.parametrize("fps, encoding_s, warned", [(40, 0.05, True), (10, 0.0, False)])
def test_a_replay_sent_slower_than_asked_is_told(collector, monkeypatch, caplog, fps, encoding_s, warned):
    """A replayed source whose frames took longer to read and encode than the period asked played in slow motion,
    the rate known only from the final count."""
    monkeypatch.setattr(publisher_module, "SHORTFALL_AFTER_S", 0.5)
    with _publisher_session(collector.port) as session:
        _wait_matched(session)
        stats = publish(session, SceneSource(Scene.from_spec("scene:320x240")), KEY, fps=fps, max_frames=12,
                        on_frame=lambda *_: time.sleep(encoding_s))
    told = [r.getMessage() for r in caplog.records if "below the" in r.getMessage()]
    assert stats.frames == 12 and bool(told) == warned, (stats.fps, told)
    if warned:
        assert told[0].startswith("sending ") and "below the 40 asked: a frame takes longer" in told[0], told


class StampedSource(FrameSource):
    """One image over and over, every frame stamped `stamp_ns` (the capture time the source gives it)."""

    def __init__(self, image: np.ndarray, stamp_ns: int, live: bool):
        self.image, self.stamp_ns, self.live = image, stamp_ns, live

    def frames(self, should_stop=never_stop):
        index = 0
        while not should_stop():
            yield SourceFrame(index, self.image, self.stamp_ns)
            index += 1


def test_a_live_frame_is_stamped_when_captured_and_a_replayed_one_when_sent(collector):
    """The frame age a session reports is its stamp's: a live frame carries the time the camera delivered it, not
    the later one it went out at; a replayed one (read ahead, or held) the time it is sent, its "capture"."""
    captured = time.time_ns() - 2_000_000_000
    image = _frames(1)[0]
    with _publisher_session(collector.port) as session:
        _wait_matched(session)
        publish(session, StampedSource(image, captured, live=True), KEY, encoding="bgr8", max_frames=3)
        replay_started = time.time_ns()
        publish(session, StampedSource(image, captured, live=False), KEY, fps=100, encoding="bgr8", max_frames=3)
        replay_ended = time.time_ns()
    frames = collector.wait(6)
    assert [f.stamp_ns for f in frames[:3]] == [captured] * 3
    assert all(replay_started <= f.stamp_ns <= replay_ended for f in frames[3:6]), frames[3:]


class FailingLiveSource(FrameSource):
    """A live source that delivers two frames, then fails."""
    live = True

    def frames(self, should_stop=never_stop):
        for index in range(2):
            yield SourceFrame(index, _frames(1)[0], time.time_ns())
        raise SourceError("the capture card stopped answering")


def test_a_live_source_s_failure_ends_the_frames_with_its_error():
    """A live source is read on a thread of its own: its error is raised where its frames are taken, so that
    `tacf publish` reports it (exit 2), not a source that merely ended."""
    frames = paced_frames(FailingLiveSource(), None, threading.Event())
    with pytest.raises(SourceError, match="the capture card stopped answering"):
        for _ in frames:
            pass


def test_a_subscriber_that_left_before_the_end_counts_as_having_listened():
    """A session stopped before the feed ends: the frames reached it, and `tacf publish` must not say at the end
    that they reached nobody."""
    port = free_port()
    with zenoh.open(make_config(ZenohOptions.listener(f"tcp/127.0.0.1:{port}"))) as listener, \
            _publisher_session(port) as session, FramePublisher(session, KEY) as probe:
        subscriber = listener.declare_subscriber(KEY, lambda sample: None)
        assert probe.wait_matched(5)

        def leave_after_the_first(frame: Frame, src: SourceFrame) -> None:
            if frame.seq == 0:
                subscriber.undeclare()
                assert wait_until(lambda: not probe.matched, timeout=5)

        stats = publish(session, SceneSource(Scene.from_spec("scene:320x240")), KEY, fps=50, max_frames=3,
                        on_frame=leave_after_the_first)
    assert stats.frames == 3 and stats.matched


def test_frames_that_reached_nobody_are_said_so():
    """A camera publishing where no subscriber ever listened (no session on the key, or access control keeping its
    frames from the network: the README's viewer.json5 on a camera) was told "published 20 frames" and nothing
    else."""
    cmd = [sys.executable, "-m", "tacf.cli", "publish", "scene", "--frames", "5", "--key", "nobody/listens",
           "--connect", f"tcp/127.0.0.1:{free_port()}"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert "published 5 frames" in done.stdout
    assert done.stderr.splitlines()[-1] == "tacf publish: no subscriber ever listened on nobody/listens: the frames " \
        "reached nobody (no session follows the key, or access control keeps them from the network)", done.stderr


def test_publish_command_line_on_an_image_folder(tmp_path, collector):
    folder = _write_folder(tmp_path / "img", _frames(5))
    cmd = [sys.executable, "-m", "tacf.cli", "publish", str(folder), "--key", KEY, "--fps", "50",
           "--encoding", "png", "--connect", f"tcp/127.0.0.1:{collector.port}", "--wait-subscriber", "5"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert "no subscriber ever listened" not in done.stderr
    frames = collector.wait(5)
    assert [f.seq for f in frames] == list(range(5)) and frames[0].encoding == "png"
    assert "published 5 frames" in done.stderr + done.stdout


def test_publish_reads_a_video_and_a_folder_whose_names_are_not_utf8(tmp_path, collector):
    """A folder unzipped from an archive made on a Chinese Windows has GBK names ("数据" here), which Python decodes
    to lone surrogates: OpenCV's imread and VideoCapture crashed `tacf publish` on them (SIGSEGV, no message)."""
    written = tmp_path / "written"               # by OpenCV too, then renamed
    _write_folder(written / "img", _frames(3))
    _write_video(written / "clip.avi", _frames(3))
    folder = written.rename(tmp_path / os.fsdecode("数据".encode("gbk")))
    for source in (folder / "clip.avi", folder / "img"):
        cmd = [sys.executable, "-m", "tacf.cli", "publish", str(source), "--key", KEY, "--fps", "50",
               "--connect", f"tcp/127.0.0.1:{collector.port}", "--wait-subscriber", "5"]
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
        assert done.returncode == 0, f"exit {done.returncode}: {done.stderr}"
        assert "published 3 frames" in done.stderr + done.stdout
    assert len(collector.wait(6)) == 6


def test_an_image_folder_plays_in_natural_order(tmp_path):
    """FFmpeg's %d.jpg names frames 1, 2, ... 10: sorted as text, 10.png came before 2.png."""
    for i in (1, 2, 10, 11, 3):
        cv2.imwrite(str(tmp_path / f"{i}.png"), np.full((8, 8, 3), i, np.uint8))
    assert [p.stem for p in ImageFolderSource(tmp_path).paths] == ["1", "2", "3", "10", "11"]


def test_an_image_named_with_a_superscript_digit_is_listed(tmp_path):
    # '²' is a digit to str.isdigit but not to the \d that splits the names: int('²') failed the whole folder
    png = cv2.imencode(".png", np.zeros((8, 8, 3), np.uint8))[1].tobytes()
    for name in ("1.png", "²2.png", "3.png"):
        (tmp_path / name).write_bytes(png)
    assert [p.name for p in ImageFolderSource(tmp_path).paths] == ["1.png", "3.png", "²2.png"]


@pytest.mark.parametrize("loop", [(), ("--loop",)], ids=["once", "looped"])
def test_publish_command_line_fails_on_a_video_without_frames(tmp_path, collector, loop):
    """A video whose headers survive but whose frames were cut off opens, then yields nothing: that is no success;
    looped, it would play its nothing again and again."""
    clip = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(clip), cv2.VideoWriter_fourcc(*"MJPG"), 25, (64, 48))
    for i in range(5):
        writer.write(np.full((48, 64, 3), i * 10, np.uint8))
    writer.release()
    data = clip.read_bytes()
    cut = tmp_path / "headers_only.avi"
    cut.write_bytes(data[:data.index(b"movi") + 4])
    cmd = [sys.executable, "-m", "tacf.cli", "publish", str(cut), *loop, "--key", KEY,
           "--connect", f"tcp/127.0.0.1:{collector.port}"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stdout + done.stderr
    assert f"tacf publish: {cut}: no frame could be read" in done.stderr


def test_publish_command_line_ends_on_a_looped_folder_it_cannot_read(tmp_path, collector):
    for name in ("a.jpg", "b.jpg"):
        (tmp_path / name).write_bytes(b"not a jpeg")
    cmd = [sys.executable, "-m", "tacf.cli", "publish", str(tmp_path), "--loop", "--key", KEY,
           "--connect", f"tcp/127.0.0.1:{collector.port}"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=30)
    assert done.returncode == 2
    assert done.stderr.splitlines()[-1] == f"tacf publish: none of the 2 images in {tmp_path} can be read"
    assert done.stderr.count("cannot read") == 2 and "Traceback" not in done.stderr


def _locked_source(kind: str, tmp_path: Path) -> tuple[Path, Path]:
    """A source of this kind that may not be read: (the path given to publish, the path the error should name)."""
    images = _frames(2)
    if kind == "image folder":
        source = locked = _write_folder(tmp_path / "folder", images)
    elif kind == "sequence folder":                         # <seq>/img/*.png, given as <seq>
        source, locked = tmp_path / "seq", _write_folder(tmp_path / "seq" / "img", images)
    elif kind == "video file":
        source = locked = _write_video(tmp_path / "clip.avi", images)
    elif kind == "single image":
        source = locked = tmp_path / "one.png"
        cv2.imwrite(str(source), images[0])
    else:                                                   # a video in a folder that may not be entered
        locked = tmp_path / "private"
        locked.mkdir()
        source = _write_video(locked / "clip.avi", images)
        locked.chmod(0)
        return source, source                               # stat() of the video itself is what fails
    locked.chmod(0)
    return source, locked


@pytest.mark.parametrize("kind", ["image folder", "sequence folder", "video file", "single image",
                                  "video in a locked folder"])
def test_publish_says_which_source_it_may_not_read(kind, tmp_path, unprivileged):
    """A folder it could not list ended `tacf publish` with a PermissionError traceback, a video file or image with
    OpenCV's "cannot open video source" (no reason given): one line naming the path, exit 2, as for other bad
    sources."""
    source, named = _locked_source(kind, tmp_path)
    cmd = unprivileged + [sys.executable, "-m", "tacf.cli", "publish", str(source), "--key", KEY, "--frames", "1",
                          "--connect", f"tcp/127.0.0.1:{free_port()}"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stdout + done.stderr
    assert done.stderr.splitlines()[-1] == f"tacf publish: cannot read {named}: permission denied", done.stderr
    assert "Traceback" not in done.stderr


def test_publish_refuses_frames_beyond_the_wire_limits(tmp_path, collector):
    with pytest.raises(FrameError, match="exceeds the limits"):                 # 16.8 Mpx at most
        encode_frame(np.zeros((4097, 4097), np.uint8), 0, "mono8")
    folder = _write_folder(tmp_path / "wide", [np.zeros((100, 9000, 3), np.uint8)])     # wider than 8192 px
    cmd = [sys.executable, "-m", "tacf.cli", "publish", str(folder), "--key", KEY,
           "--connect", f"tcp/127.0.0.1:{collector.port}", "--wait-subscriber", "5"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stderr
    assert done.stderr.splitlines()[-1] == ("tacf publish: frame size 9000x100 exceeds the limits (8192x8192, "
                                            "16777216 pixels)")
    assert collector.wait(1, timeout=0.5) == []


def test_an_image_of_the_right_shape_but_not_uint8_is_refused_naming_its_type(collector):
    """FramePublisher.put() of a 16-bit or float image said only "expected an HxWx3 (BGR) or HxW uint8 image, got
    (64, 96, 3)": the shape it named was right, and the type that was wrong went unsaid."""
    with _publisher_session(collector.port) as session, FramePublisher(session, KEY) as publisher:
        for image, named in ((np.zeros((64, 96, 3), np.float32), "float32 (64, 96, 3)"),
                             (np.zeros((64, 96), np.uint16), "uint16 (64, 96)"), ([[0, 1], [2, 3]], "list")):
            with pytest.raises(ValueError, match=rf"uint8 image, got {re.escape(named)}$"):
                publisher.put(image)
        assert publisher.next_seq == 0
    assert collector.wait(1, timeout=0.5) == []


def test_ctrl_c_ends_the_wait_for_a_subscriber_without_publishing():
    cmd = [sys.executable, "-m", "tacf.cli", "publish", "scene", "--key", KEY, "--wait-subscriber", "30",
           "--connect", f"tcp/127.0.0.1:{free_port()}"]      # nobody there: no subscriber ever comes
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert any("waiting up to 30 s" in line for line in proc.stderr)    # stops reading at that line
        time.sleep(0.2)
        proc.send_signal(signal.SIGINT)
        started = time.monotonic()
        out, err = proc.communicate(timeout=10)
    finally:
        proc.kill()
    assert time.monotonic() - started < 3
    assert proc.returncode == 130, err
    assert "nothing published" in err and "publishing anyway" not in err and "published" not in out


@pytest.mark.parametrize("stop_signal", [signal.SIGINT, signal.SIGTERM])
def test_a_stop_signal_ends_publish_with_128_plus_its_number_after_closing_its_session(collector, stop_signal):
    """`tacf publish` exited 0 on Ctrl-C, where `tacf demo` and `tacf bench` exit 130: a script could not tell a
    run cut short from a source played to its end. SIGTERM then exited 130 too, where shells report 143."""
    cmd = [sys.executable, "-m", "tacf.cli", "publish", "scene", "--key", KEY, "--fps", "20",
           "--connect", f"tcp/127.0.0.1:{collector.port}"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert len(collector.wait(3, timeout=30)) >= 3, "the publisher's frames arrived"
        proc.send_signal(stop_signal)
        started = time.monotonic()
        out, err = proc.communicate(timeout=10)
    finally:
        proc.kill()
    assert time.monotonic() - started < 3, "no hang at exit (ZENOH.md 8): the session was closed first"
    assert proc.returncode == 128 + stop_signal, err    # not -2 (killed by the signal) nor 134/139 (a crash at exit)
    assert out.startswith("published ") and err.splitlines()[-1] == "tacf publish: interrupted", out + err
    assert "Traceback" not in err


# ----------------------------------------------------------------------------------------------- live streams


@pytest.fixture
def camera():
    cameras = []

    def make(**kwargs) -> MjpegCamera:
        cameras.append(MjpegCamera(**kwargs))
        return cameras[-1]

    yield make
    for cam in cameras:
        cam.close()


def _take(source: CaptureSource, n: int, should_stop=never_stop) -> list[SourceFrame]:
    frames = []
    for frame in source.frames(should_stop):
        frames.append(frame)
        if len(frames) == n:
            break
    return frames


def test_a_stream_that_ends_is_reopened_and_its_frames_go_on(camera):
    cam = camera(frames_per_connection=4)
    with open_source(cam.url) as source:
        assert isinstance(source, CaptureSource) and source.live
        frames = _take(source, 10)
        assert source.reconnects >= 2
    assert [f.index for f in frames] == list(range(10))
    assert [MjpegCamera.connection_of(f.image) for f in frames] == [1] * 4 + [2] * 4 + [3] * 2
    assert frames[5].image[50, 8:16].min() > 200  # the second connection's frame 1: its bar at x = 8


def test_a_stalled_stream_counts_as_failed_after_the_read_timeout(camera, monkeypatch):
    monkeypatch.setattr(sources, "READ_TIMEOUT_MS", 1000)
    cam = camera(frames_per_connection=3, stall=True)
    with open_source(cam.url) as source:
        started = time.monotonic()
        frames = _take(source, 5)
        elapsed = time.monotonic() - started
    assert [MjpegCamera.connection_of(f.image) for f in frames] == [1, 1, 1, 2, 2]
    assert 0.9 < elapsed < 6, "silence for the read timeout, then a reconnection"


def test_a_camera_that_goes_away_is_retried_until_it_is_back(camera, monkeypatch):
    cam = camera(frames_per_connection=3)
    pauses = []
    real_sleep_unless = sources.sleep_unless

    def recorded(seconds, should_stop, slice_s=0.1):
        pauses.append(seconds)
        return real_sleep_unless(seconds, should_stop, slice_s)

    monkeypatch.setattr(sources, "sleep_unless", recorded)
    with open_source(cam.url) as source:
        frames = source.frames()
        first = [next(frames) for _ in range(3)]
        cam.down()  # connection refused from now on
        threading.Timer(2.0, cam.up).start()
        started = time.monotonic()
        after = next(frames)
        waited = time.monotonic() - started
    assert [MjpegCamera.connection_of(f.image) for f in first] == [1, 1, 1]
    assert MjpegCamera.connection_of(after.image) == 2 and after.index == 3
    assert 1.9 < waited < 6
    assert pauses[:3] == [0.5, 1.0, 2.0], "the pauses double while the camera is away"
    assert source.reconnects == 1


def test_a_camera_away_for_long_is_logged_once_a_period_once_the_pauses_are_capped(camera, monkeypatch, caplog):
    """Every failed reopen was logged: a camera switched off for hours wrote a line every 5 s. The doubling pauses
    are still told one by one; at the cap, once in REOPEN_LOG_PERIOD_S, with the count of the attempts since."""
    monkeypatch.setattr(sources, "RECONNECT_FIRST_S", 0.05)
    monkeypatch.setattr(sources, "RECONNECT_MAX_S", 0.2)
    monkeypatch.setattr(sources, "REOPEN_LOG_PERIOD_S", 1.0)
    cam = camera(frames_per_connection=3)
    with caplog.at_level("WARNING", logger="tacf_clients.sources"), open_source(cam.url) as source:
        frames = source.frames()
        assert len([next(frames) for _ in range(3)]) == 3
        cam.down()
        threading.Timer(3.0, cam.up).start()
        next(frames)
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("cannot reopen")]
    assert [line.split("next attempt in ")[1][:3] for line in lines[:3]] == ["0.1", "0.2", "0.2"], lines
    assert re.search(r"\((\d+) failed attempts since the last line\)$", lines[2]), lines
    assert 3 <= len(lines) <= 5, lines      # not one for each of the 10 or more attempts of 3 s


def test_stopping_ends_a_reconnecting_source_promptly(camera):
    cam = camera(frames_per_connection=3)  # FFmpeg reads two or three frames to open a stream
    stop = threading.Event()
    with open_source(cam.url) as source:
        frames = source.frames(should_stop=stop.is_set)
        cam.down()
        assert len([next(frames) for _ in range(3)]) == 3
        threading.Timer(0.8, stop.set).start()
        started = time.monotonic()
        assert next(frames, None) is None
        assert time.monotonic() - started < 1.5


def test_stopping_ends_a_stalled_stream_without_waiting_for_ffmpeg(camera):
    """A read of a stream gone silent blocks in FFmpeg until READ_TIMEOUT_MS (5 s): a stop used to wait for it."""
    cam = camera(frames_per_connection=3, stall=True)
    stop = threading.Event()
    with open_source(cam.url) as source:
        frames = source.frames(should_stop=stop.is_set)
        assert len([next(frames) for _ in range(3)]) == 3
        threading.Timer(0.5, stop.set).start()
        started = time.monotonic()
        assert next(frames, None) is None
        assert time.monotonic() - started < 1.5


def test_a_stop_during_a_slow_camera_s_read_loses_it_no_frame(camera):
    """--wait-subscriber stops reading when a subscriber comes, mostly in the middle of a read for a camera under
    10 fps: the source gave no frame any more, and `tacf publish` published nothing (exit 2)."""
    cam = camera(frames_per_connection=40, fps=4)
    with open_source(cam.url) as source:
        assert len(_take(source, 5)) == 5                   # what FFmpeg read ahead while opening is taken
        stop_at = time.monotonic() + 0.1                    # within the 0.25 s the next frame takes
        _take(source, 1, should_stop=lambda: time.monotonic() > stop_at)
        assert len(_take(source, 2)) == 2


def test_ctrl_c_ends_publish_while_a_stream_does_not_answer():
    """A server that accepts and never answers holds FFmpeg's open for OPEN_TIMEOUT_MS (10 s): Ctrl-C used to wait
    for it, then reported "cannot open video source" (exit 2)."""
    done, seconds = interrupted_while_a_stream_opens(
        lambda url: [sys.executable, "-m", "tacf.cli", "publish", url, "--key", KEY,
                     "--connect", f"tcp/127.0.0.1:{free_port()}"])
    assert done.returncode == 130 and seconds < 2, (seconds, done.stderr)


def test_without_reconnect_a_stream_ends_with_its_connection(camera):
    cam = camera(frames_per_connection=3)
    with open_source(cam.url, reconnect=False) as source:
        frames = list(source)
    assert len(frames) == 3 and source.reconnects == 0 and cam.connections == 1


def test_a_camera_that_is_not_there_is_a_clear_error_at_start(camera):
    cam = camera()
    cam.down()
    with pytest.raises(ValueError, match="cannot open video source"):
        open_source(cam.url)


def test_stopping_ends_a_reconnection_while_the_stream_does_not_answer(camera):
    """The camera back on its port but silent (a server up before its stream): FFmpeg holds the reopen for up to
    OPEN_TIMEOUT_MS (10 s), and a stop, Ctrl-C, waited for it."""
    cam = camera(frames_per_connection=3)
    stop = threading.Event()
    stopped_at = []

    def stop_once_reopening(silent: socket.socket) -> None:
        connection, _ = silent.accept()                 # FFmpeg opens the stream again
        stopped_at.append(time.monotonic())
        stop.set()
        time.sleep(3)
        connection.close()

    with open_source(cam.url) as source:
        frames = source.frames(should_stop=stop.is_set)
        cam.down()
        with socket.create_server(("127.0.0.1", cam.port)) as silent:
            silent.settimeout(10)
            threading.Thread(target=stop_once_reopening, args=(silent,), daemon=True).start()
            assert len([next(frames) for _ in range(3)]) == 3
            assert next(frames, None) is None
            assert stopped_at and time.monotonic() - stopped_at[0] < 1.5


def test_publish_runs_on_through_reconnections_with_one_seq_count(camera, collector):
    cam = camera(frames_per_connection=4)
    with _publisher_session(collector.port) as session:
        _wait_matched(session)
        with open_source(cam.url) as source:
            stats = publish(session, source, KEY, encoding="bgr8", max_frames=9)
    frames = collector.wait(9)
    assert stats.frames == 9 and stats.last_seq == 8 and source.reconnects == 2
    # Frames are published with CongestionControl.DROP, so a loaded machine may lose one on the way (seen once in a
    # full suite: seq 2); the count is what is tested: one seq run over the three connections, 4 frames each, the
    # connections following each other along it. A live source sends its newest frame, so one of a connection may
    # be passed over too (seen once: seq 7 was the third connection's first frame).
    seqs = [f.seq for f in frames]
    assert len(frames) >= 7 and seqs == sorted(set(seqs)) and set(seqs) <= set(range(9)), seqs
    connections = [MjpegCamera.connection_of(decode_frame(frame)) for frame in frames]
    assert connections == sorted(connections) and len(set(connections)) >= 2, (seqs, connections)
    assert set(connections) <= {1, 2, 3}, (seqs, connections)


class CountingCamera(MjpegCamera):
    """An MjpegCamera whose frame i carries i in binary (8 blocks of 16 px, white for 1) and which remembers the
    index it sent last."""

    latest = -1

    def frame(self, connection: int, index: int) -> np.ndarray:
        self.latest = index
        image = np.zeros((96, 128, 3), np.uint8)
        for bit in range(8):
            if index >> bit & 1:
                image[32:64, 16 * bit + 2:16 * bit + 14] = 255
        return image

    @staticmethod
    def index_of(image: np.ndarray) -> int:
        return sum(1 << bit for bit in range(8) if image[48, 16 * bit + 8].mean() > 128)


def test_a_live_source_is_read_on_while_waiting_for_a_subscriber():
    """--wait-subscriber left a live stream unread: its buffers kept the frames of the wait, and the first frames
    published when a subscriber came were as old as the wait (8 s after an 8 s wait), then sent in a burst."""
    cam = CountingCamera(frames_per_connection=250)         # 20 fps for 12.5 s
    port = free_port()
    try:
        with zenoh.open(make_config(ZenohOptions.listener(f"tcp/127.0.0.1:{port}"))) as session:
            cmd = [sys.executable, "-m", "tacf.cli", "publish", cam.url, "--key", KEY, "--wait-subscriber", "30",
                   "--encoding", "bgr8", "--connect", f"tcp/127.0.0.1:{port}"]
            proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
            try:
                assert any("waiting up to 30 s" in line for line in proc.stderr)    # stops reading at that line
                time.sleep(3)
                first: list[tuple[int, int]] = []                   # (index shown, index the camera is at)
                subscriber = session.declare_subscriber(KEY, lambda sample: first or first.append(
                    (CountingCamera.index_of(decode_frame(decode(sample.payload.to_bytes(), Frame))), cam.latest)))
                assert wait_until(lambda: first, timeout=10)
                subscriber.undeclare()
            finally:
                proc.kill()
                proc.wait()
    finally:
        cam.close()
    shown, at = first[0]
    assert at - shown <= 5, f"the first frame published was {at - shown} frames old ({shown}; the camera at {at})"


def test_a_camera_slower_than_the_fps_asked_is_told(collector, monkeypatch, caplog):
    monkeypatch.setattr(publisher_module, "SHORTFALL_AFTER_S", 0.5)
    cam = CountingCamera(frames_per_connection=250)         # 20 fps
    try:
        with _publisher_session(collector.port) as session, open_source(cam.url) as source:
            _wait_matched(session)
            stats = publish(session, source, KEY, fps=30, encoding="bgr8", max_frames=16)
    finally:
        cam.close()
    told = [r.getMessage() for r in caplog.records if "below the" in r.getMessage()]
    assert stats.frames == 16 and len(told) == 1 and "below the 30 asked: the camera delivers no more" in told[0], told


def test_a_sender_slower_than_a_live_source_sends_its_newest_frames(collector):
    """A live source was read in turn with the sending: an encoding slower than the camera left the other frames in
    the stream's buffers, and the publisher sent ever older frames (2.5 s behind a 30 fps MJPEG camera after 20 s
    of PNG at 1080p) under stamps of when they were read. The sender now gets the newest frame when it is ready."""
    cam = CountingCamera(frames_per_connection=250)         # 20 fps
    behind = []                                             # frames the camera is ahead of the one just sent

    def slow_encoding(frame: Frame, src: SourceFrame) -> None:
        behind.append(cam.latest - CountingCamera.index_of(src.image))
        time.sleep(0.25)                                    # 5 camera frames per frame sent

    try:
        with _publisher_session(collector.port) as session, open_source(cam.url) as source:
            _wait_matched(session)
            stats = publish(session, source, KEY, encoding="bgr8", max_frames=10, on_frame=slow_encoding)
    finally:
        cam.close()
    assert stats.frames == 10
    assert max(behind[3:]) <= 3, f"frames sent were this many camera frames old: {behind}"
