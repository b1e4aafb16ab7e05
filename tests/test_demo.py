"""`tacf demo` end to end: a real service, publisher and session on loopback; it finishes and the boxes follow
the target's ground truth."""
from __future__ import annotations

import io
import subprocess
import sys
import threading

import cv2
import pytest

from tacf_clients.demo import DemoOptions, GroundTruth, run_demo
from tacf_clients.scene import Scene
from tacf_clients.sources import open_source

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
