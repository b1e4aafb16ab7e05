"""Frame sources, the generated scene and the frame publisher over real Zenoh sessions on loopback."""
from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import zenoh

from tacf.eval.metrics import box_iou
from tacf_clients.local_service import free_port
from tacf_clients.publisher import FramePublisher, publish
from tacf_clients.scene import Scene, SceneSource
from tacf_clients.sources import CaptureSource, ImageFolderSource, Pacer, Thinner, open_source
from tacf_clients.zconfig import ZenohOptions, make_config
from tacf_schemas.codec import decode
from tacf_schemas.images import decode_frame
from tacf_schemas.models import Frame

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


def test_open_source_rejects_what_does_not_exist(tmp_path):
    with pytest.raises(FileNotFoundError):
        open_source(str(tmp_path / "missing.mp4"))
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(b"not a video")
    with pytest.raises(ValueError):
        open_source(str(bad))
    assert isinstance(open_source("scene"), SceneSource)


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
        with FramePublisher(session, KEY, encoding="mono8") as pub:
            frame = pub.put(_frames(1)[0])
            assert (frame.encoding, len(frame.data)) == ("mono8", 96 * 64)
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


def test_publish_command_line_on_an_image_folder(tmp_path, collector):
    folder = _write_folder(tmp_path / "img", _frames(5))
    cmd = [sys.executable, "-m", "tacf.cli", "publish", str(folder), "--key", KEY, "--fps", "50",
           "--encoding", "png", "--connect", f"tcp/127.0.0.1:{collector.port}", "--wait-subscriber", "5"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    frames = collector.wait(5)
    assert [f.seq for f in frames] == list(range(5)) and frames[0].encoding == "png"
    assert "published 5 frames" in done.stderr + done.stdout
