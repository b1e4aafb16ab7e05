"""`tacf demo` end to end: a real service, publisher and session on loopback; it finishes and the boxes follow
the target's ground truth."""
from __future__ import annotations

import io
import subprocess
import sys
import threading
import time

import cv2
import pytest
import zenoh

from tacf_clients.demo import DemoOptions, GroundTruth, run_demo
from tacf_clients.local_service import free_port
from tacf_clients.scene import Scene
from tacf_clients.sources import FrameSource, SourceFrame, open_source
from tacf_clients.zconfig import ZenohOptions, make_config

pytestmark = pytest.mark.zenoh


def test_demo_on_the_generated_scene_follows_the_target():
    out = io.StringIO()
    report = run_demo(DemoOptions(seconds=3.0, fps=20, node="demotest"), out=out)
    text = out.getvalue()
    assert report.ok, text
    assert report.error is None
    assert report.service_exit == 0, "the service stops cleanly on SIGTERM"
    assert report.boxes >= 15, text
    assert report.followed is not None and report.followed >= 0.9, text
    assert report.mean_iou > 0.6, text
    assert report.last_health is not None and report.last_health.state in ("tracking", "lost")
    for expected in ("service ready", "session 'demo' started", "box ", "health ", "stopped", "done"):
        assert expected in text, text


def test_demo_command_on_a_sequence_folder(tmp_path):
    """SOURCE = an image sequence with a (1-based) groundtruth.txt, as in ../shared/data/sequences."""
    scene = Scene.from_spec("scene:320x240")
    (tmp_path / "seq" / "img").mkdir(parents=True)
    lines = []
    for i in range(40):
        cv2.imwrite(str(tmp_path / "seq" / "img" / f"{i + 1:06d}.jpg"), scene.frame(i))
        x, y, w, h = scene.box(i)
        lines.append(f"{x + 1:.0f},{y + 1:.0f},{w:.0f},{h:.0f}")
    (tmp_path / "seq" / "groundtruth.txt").write_text("\n".join(lines) + "\n")

    truth = GroundTruth.for_source(open_source(str(tmp_path / "seq")))
    assert truth is not None and truth.box(3) == scene.box(3)

    done = subprocess.run([sys.executable, "-m", "tacf.cli", "demo", str(tmp_path / "seq"), "--seconds", "20",
                           "--fps", "20"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "from ground truth" in done.stdout
    assert "the source ended" in done.stdout          # 40 frames: the demo stops before its 20 s
    assert "boxes on the target" in done.stdout and "done" in done.stdout


def test_demo_stops_cleanly_when_interrupted():
    out = io.StringIO()
    stop = threading.Event()
    timer = threading.Timer(0.5, stop.set)        # Ctrl-C while the service is still starting
    timer.start()
    report = run_demo(DemoOptions(seconds=30, node="demostop"), stop=stop, out=out)
    timer.join()
    assert report.service_exit is not None, out.getvalue()
    assert "service exited" in out.getvalue()


class BufferedCamera(FrameSource):
    """A live 30 fps camera whose frames queue up while nobody reads them, as a stream's buffers do: frame i is
    captured at `started + i / 30` and handed out in order, however late it is asked for."""

    name, fps, live = "buffered-camera", 30.0, True

    def __init__(self):
        self.started = time.monotonic()
        self.image = Scene.from_spec("scene:160x120").frame(0)

    def frames(self, should_stop=lambda: False):
        index = 0
        while not should_stop():
            time.sleep(max(0.0, self.started + index / self.fps - time.monotonic()))
            yield SourceFrame(index, self.image, time.time_ns())
            index += 1


def test_the_demo_keeps_up_with_a_live_camera_faster_than_its_rate():
    """The demo paced every source at its rate (20 fps) and held a live one unread until the first box: a 30 fps
    stream was then published 2.4 s late after a 2 s hold, and 0.33 s later every second. A live source is read
    as fast as it delivers (thinned to the rate), and drained while the first frame is held."""
    from tacf_clients.demo import HoldingPublisher

    camera = BufferedCamera()
    with zenoh.open(make_config(ZenohOptions(connect=(), listen=(f"tcp/127.0.0.1:{free_port()}",)))) as session:
        publisher = HoldingPublisher(session, camera, "test/demo/live", 20, "jpeg")
        publisher.start()
        try:
            time.sleep(1.0)                                  # the first frame held while the session starts
            assert publisher.index_of(publisher.last_seq) == 0
            publisher.hold.clear()
            time.sleep(2.0)
            index = publisher.index_of(publisher.last_seq)
            late = time.monotonic() - (camera.started + index / camera.fps)
            seqs = publisher.last_seq
        finally:
            publisher.close()
    assert late < 0.3, f"the frame published last was captured {late:.2f} s before"
    assert 40 <= seqs <= 75, "about 20 frames a second published"


def test_a_local_service_leaves_its_log_only_when_it_failed():
    """Every `tacf demo` (and test) left /tmp/tacf-serve-<node>-<port>.log behind: hundreds piled up. The log of a
    service that stopped cleanly goes; one that failed keeps it, since the error names it."""
    from tacf_clients.local_service import LocalService, LocalServiceError

    with LocalService(node="logtest") as service:
        with zenoh.open(make_config(service.options)) as session:
            service.wait_ready(session)
        assert service.log_path.exists()
    assert service.returncode == 0 and not service.log_path.exists()

    broken = LocalService(node="logtest", extra_args=("--no-such-option",)).start()
    with zenoh.open(make_config(broken.options)) as session, pytest.raises(LocalServiceError) as failed:
        broken.wait_ready(session)
    broken.stop()
    assert broken.returncode == 2 and broken.log_path.exists() and str(broken.log_path) in str(failed.value)
    broken.log_path.unlink()
