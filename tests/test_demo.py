"""`tacf demo` end to end: a real service, publisher and session on loopback; it finishes and the boxes follow
the target's ground truth."""
from __future__ import annotations

import io
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import zenoh

from tacf_clients import demo, local_service
from tacf_clients.demo import DemoOptions, GroundTruth, run_demo
from tacf_clients.local_service import ephemeral_range_start, free_port
from tacf_clients.scene import Scene
from tacf_clients.sources import FrameSource, SourceFrame, open_source
from tacf_clients.zconfig import ZenohOptions, make_config

from closed_pipe import head
from mjpeg_camera import MjpegCamera, interrupted_while_a_stream_opens

pytestmark = pytest.mark.zenoh
VOT_BAG = Path(__file__).resolve().parents[2] / "shared" / "data" / "sequences" / "VOT" / "bag"


def test_demo_on_the_generated_scene_follows_the_target():
    out = io.StringIO()
    report = run_demo(DemoOptions(seconds=3.0, fps=20, node="demotest"), out=out)
    text = out.getvalue()
    assert report.ok, text
    assert report.error is None
    assert report.service_exit == 0, "the service stops cleanly on SIGTERM"
    assert report.boxes >= 15, text
    # boxes on the held first frame, copied until the first box came, were counted too: 22 a second at 20 fps
    assert report.box_fps <= 20 * 1.05, text
    assert report.followed is not None and report.followed >= 0.9, text
    assert report.mean_iou > 0.6, text
    assert report.last_health is not None and report.last_health.state in ("tracking", "lost")
    for expected in ("service ready", "session 'demo' started", "box ", "health ", "stopped", "done"):
        assert expected in text, text


def test_a_first_run_s_slow_start_is_said(tmp_path, monkeypatch):
    """The first run after an install compiles the tracker's loops in the service before its session starts (numba's
    cache empty): the demo printed nothing for those 5-10 s (4.6 s here, 2026-12-07)."""
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "numba"))      # the service inherits it: nothing cached
    monkeypatch.setattr(demo, "SLOW_START_S", 0.5)                        # a fast machine compiles in 3 s or so
    out = io.StringIO()
    report = run_demo(DemoOptions(seconds=1.0, fps=20, node="demoslow"), out=out)
    text = out.getvalue()
    assert report.ok, text
    assert demo.SLOW_START_HINT in text and text.index(demo.SLOW_START_HINT) < text.index("session 'demo' started"), \
        text


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


@pytest.mark.skipif(not VOT_BAG.is_dir(), reason=f"benchmark sequences not found at {VOT_BAG}")
def test_a_sequence_s_polygon_ground_truth_gives_the_box_enclosing_it(tmp_path):
    """A VOT sequence (frames and groundtruth.txt in one folder) keeps its boxes as polygons x1,y1,...,x4,y4: the
    demo read their first four numbers as x,y,w,h and started on a box 438 px wide in a 480 px frame."""
    import shutil

    from tacf.eval.datasets.base import read_boxes

    for frame in sorted((VOT_BAG / "img").iterdir())[:3]:
        shutil.copy(frame, tmp_path)
    polygons = (VOT_BAG / "groundtruth_poly.txt").read_text().splitlines()[:3]
    (tmp_path / "groundtruth.txt").write_text("\n".join(polygons) + "\n")
    truth = GroundTruth.for_source(open_source(str(tmp_path)))
    assert truth is not None
    assert truth.box(2) == pytest.approx(tuple(read_boxes(VOT_BAG / "groundtruth.txt")[2]))   # their enclosing box


@pytest.mark.parametrize("lines", [2, 3])
def test_demo_read_by_head_ends_quietly(lines):
    """`tacf demo | head -3` ended with the publisher thread's traceback ("session closed"): its session was
    closed under it while it ran."""
    code, read, err = head(["demo"], lines)
    assert read[0].startswith("[  0.0s] starting the tracking service")
    assert (code, err) == (141, ""), err


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


def test_a_live_camera_s_frames_carry_when_they_were_read_and_the_held_first_frame_when_sent_again():
    """As `tacf publish` stamps them: the demo stamped every frame when it sent it, so the frame age the service
    reports left out the time spent encoding it (a JPEG of a 1080p frame takes milliseconds). The first frame,
    sent again while the session starts, is stamped anew each time: it is not a frame read that long ago."""
    from tacf_clients.demo import HoldingPublisher
    from tacf_schemas import Frame, decode

    camera, sent = BufferedCamera(), []
    read_at = {}                                     # index -> stamp the camera gave, 50 ms before it handed it out
    frames = camera.frames

    def early_frames(should_stop=lambda: False):
        for frame in frames(should_stop):
            read_at[frame.index] = frame.stamp_ns - 50_000_000
            yield SourceFrame(frame.index, frame.image, read_at[frame.index])

    camera.frames = early_frames
    with zenoh.open(make_config(ZenohOptions(connect=(), listen=(f"tcp/127.0.0.1:{free_port()}",)))) as session:
        publisher = HoldingPublisher(session, camera, "test/demo/stamps", 20, "jpeg")
        subscriber = session.declare_subscriber(
            "test/demo/stamps", lambda sample: sent.append((decode(sample.payload.to_bytes(), Frame), time.time_ns())))
        publisher.start()
        try:
            time.sleep(0.5)                                  # the first frame held while the session starts
            publisher.hold.clear()
            time.sleep(0.5)
        finally:
            publisher.close()
            subscriber.undeclare()
    indices = [publisher.index_of(frame.seq) for frame, _ in sent]
    held = [(frame, arrived) for (frame, arrived), index in zip(sent, indices) if index == 0]
    fresh = [(frame, index) for (frame, _), index in zip(sent, indices) if index not in (None, 0)]
    assert len(held) >= 5 and len(fresh) >= 5, indices
    assert held[0][0].stamp_ns == read_at[0]
    assert all(0 <= arrived - frame.stamp_ns < 90_000_000 for frame, arrived in held[1:]), "repeats stamped anew"
    assert all(frame.stamp_ns == read_at[index] for frame, index in fresh)


def test_a_frame_s_source_index_is_known_before_it_can_be_answered():
    """The publisher noted which source frame a seq carried after put() returned; a box can come back sooner (on a
    machine where the publishing thread lost the CPU right after sending), and the demo printed such boxes
    without their IoU."""
    from tacf_clients.demo import HoldingPublisher
    from tacf_schemas import Frame, decode

    known = []
    with zenoh.open(make_config(ZenohOptions(connect=(), listen=(f"tcp/127.0.0.1:{free_port()}",)))) as session:
        publisher = HoldingPublisher(session, BufferedCamera(), "test/demo/known", 20, "bgr8")
        put = publisher.publisher.put
        publisher.publisher.put = lambda *frame: (put(*frame), time.sleep(0.02))[0]  # a busy machine, after sending
        subscriber = session.declare_subscriber(
            "test/demo/known", lambda sample: known.append(publisher.index_of(decode(sample.payload.to_bytes(),
                                                                                     Frame).seq)))
        publisher.start()
        try:
            time.sleep(0.3)
            publisher.hold.clear()
            time.sleep(0.5)
        finally:
            publisher.close()
            subscriber.undeclare()
    assert len(known) >= 10 and None not in known, known


def test_a_frame_beyond_the_wire_s_limits_is_skipped_once_frames_went_out(tmp_path):
    """As `tacf publish` skips it: the demo ended there, exit 2 with the frame's error, its summary never printed."""
    from tacf_clients.demo import HoldingPublisher
    from tacf_schemas import Frame, decode

    scene = Scene.from_spec("scene:160x120")
    for i in range(4):
        cv2.imwrite(str(tmp_path / f"{i + 1}.png"), scene.frame(i) if i != 2 else np.zeros((8, 8200, 3), np.uint8))
    sent = []
    with zenoh.open(make_config(ZenohOptions(connect=(), listen=(f"tcp/127.0.0.1:{free_port()}",)))) as session:
        publisher = HoldingPublisher(session, open_source(str(tmp_path)), "test/demo/wide", 50, "jpeg")
        subscriber = session.declare_subscriber(
            "test/demo/wide", lambda sample: sent.append(publisher.index_of(decode(sample.payload.to_bytes(),
                                                                                    Frame).seq)))
        publisher.hold.clear()
        publisher.start()
        try:
            assert publisher.ended.wait(5)
            time.sleep(0.2)                                  # the last frame's delivery
        finally:
            publisher.close()
            subscriber.undeclare()
    assert publisher.error is None
    assert sent == [0, 1, 3]


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
    assert "tacf serve exited with code 2" in str(failed.value), "said at once, not after the ready timeout"
    broken.log_path.unlink()


def test_free_ports_come_from_below_the_ephemeral_range_and_never_twice():
    """A port 0 bind comes from the kernel's ephemeral range, where every outgoing connection takes its local port
    too: one took a test service's port between free_port() and the service's bind (CI, "Address already in use")."""
    ports = [free_port() for _ in range(200)]
    assert len(set(ports)) == len(ports)
    assert all(1024 <= port < ephemeral_range_start() for port in ports), ports


def test_a_range_with_no_room_below_it_still_gives_a_port(tmp_path, monkeypatch):
    squeezed = tmp_path / "ip_local_port_range"
    squeezed.write_text("1024\t60999\n")
    monkeypatch.setattr(local_service, "EPHEMERAL_RANGE_FILE", squeezed)
    port = free_port()
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", port))
    monkeypatch.setattr(local_service, "EPHEMERAL_RANGE_FILE", tmp_path / "absent")
    assert local_service.ephemeral_range_start() == local_service.EPHEMERAL_LOW_ELSEWHERE


def _demo(*argv: str) -> list[str]:
    return [sys.executable, "-m", "tacf.cli", "demo", *argv]


@pytest.mark.parametrize("source, reason", [("/nonexistent/clip.mp4", "is neither a file, a folder"),
                                            ("http://127.0.0.1:9/none.mjpg", "cannot open video source")])
def test_demo_on_a_bad_source_is_a_usage_error_on_stderr(source, reason):
    """A source that does not exist was reported on standard output, with exit code 1 as for a demo that ran and
    failed: it is one line on stderr and exit code 2, before any service starts."""
    done = subprocess.run(_demo(source), capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and done.stdout == "", done.stdout + done.stderr
    last = done.stderr.splitlines()[-1]         # (FFmpeg says first, on its own, why it could not connect)
    assert last.startswith("tacf demo: ") and reason in last and "Traceback" not in done.stderr, done.stderr


def test_ctrl_c_while_a_stream_opens_ends_the_demo_with_130():
    """Ctrl-C while FFmpeg waited for a stream that does not answer ended the demo once FFmpeg gave up (10 s), with
    exit code 2 and "cannot open video source", as for a bad source."""
    done, seconds = interrupted_while_a_stream_opens(_demo)
    assert done.returncode == 130, done.stdout + done.stderr
    assert seconds < 3, "the open is left to FFmpeg's timeout (10 s) on a thread of its own"
    last_line = done.stderr.splitlines()[-1]
    assert last_line == "tacf demo: interrupted" and "cannot open" not in done.stderr, done.stderr


def test_the_first_frame_of_a_live_source_is_waited_for_only_until_a_stop():
    """A camera that opened and then gave no frame (unplugged, a stream dead after its probe) was read for a first
    box without the stop: Ctrl-C and SIGTERM went unheard while it reconnected for ever."""
    from tacf_clients.demo import initial_box

    camera, stop = MjpegCamera(frames_per_connection=100), threading.Event()
    try:
        with open_source(camera.url, should_stop=stop.is_set) as source:
            stop.set()
            with pytest.raises(ValueError, match="has no frames"):
                initial_box(DemoOptions(source=camera.url), source, None, stop)
    finally:
        camera.close()


def test_a_source_whose_frames_cannot_be_sent_is_a_usage_error_and_no_session_starts(tmp_path):
    """A frame beyond the wire's limits: the publisher failed with a traceback, the demo started a session on
    frame -1 anyway and reported the service's refusal of that, exit 1."""
    folder = tmp_path / "wide"
    folder.mkdir()
    cv2.imwrite(str(folder / "1.png"), np.zeros((16, 8200, 3), np.uint8))
    done = subprocess.run(_demo(str(folder)), capture_output=True, text=True, timeout=120)
    assert done.returncode == 2, done.stdout + done.stderr
    assert done.stderr.splitlines()[-1] == "tacf demo: frame size 8200x16 exceeds the limits (8192x8192, " \
        "16777216 pixels)", done.stderr
    assert "Traceback" not in done.stderr and "session" not in done.stdout, done.stdout + done.stderr


def test_an_unknown_profile_is_refused_before_a_service_starts():
    done = subprocess.run(_demo("--profile", "bogus"), capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "invalid choice: 'bogus'" in done.stderr and done.stdout == "", done.stderr


def test_ctrl_c_ends_the_demo_quietly_with_130():
    """Ctrl-C ended the demo with 'demo failed: no boxes received' and exit code 1, as an error would. A terminal
    sends SIGINT to the whole foreground process group: the service the demo started must not take it for itself
    (it stopped under the demo, whose stop of the session then failed), the demo stops it in order."""
    proc = subprocess.Popen(_demo("--seconds", "60"), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)         # a process group of its own, as a shell gives it
    try:
        for line in proc.stdout:
            if "waiting for the first box" in line:            # the session is starting
                break
        os.killpg(proc.pid, signal.SIGINT)                     # Ctrl-C in its terminal
        out, err = proc.communicate(timeout=30)
    finally:
        proc.kill()
    assert proc.returncode == 130, out + err
    assert "Traceback" not in err and "failed" not in out + err, out + err
    assert "interrupted" in out and "service exited with code 0" in out, out


def test_a_stream_url_is_opened_once():
    """The demo read the first frame of the source for the centred box, then closed the source and opened it
    again for the publisher: a camera or stream was connected to twice (an RTSP camera that takes one client
    refused the second). A live source is opened once; a file still starts again from its first frame."""
    camera = MjpegCamera(frames_per_connection=10_000)
    try:
        out = io.StringIO()
        report = run_demo(DemoOptions(source=camera.url, seconds=1.0, node="demourl"), out=out)
    finally:
        camera.close()
    assert report.ok, out.getvalue()
    assert camera.connections == 1, out.getvalue()


def test_the_boxes_of_the_last_frames_are_waited_for_when_the_source_ends(tmp_path, monkeypatch):
    """The demo stopped listening as soon as the source had sent its last frame: the boxes of the frames still
    being tracked were lost (a 12-frame folder counted 10 boxes at 20 fps; with a tracker taking 0.3 s a frame, as
    here, on a real service, every box after the held first frame's: "demo failed: no boxes received")."""
    from tacf_clients import demo

    env = {**os.environ, "SLOW_TRACKER_LOCATE_S": "0.3",
           "PYTHONPATH": os.pathsep.join(filter(None, [str(Path(__file__).parent), os.environ.get("PYTHONPATH")]))}

    class SlowService(local_service.LocalService):
        def __init__(self, **kwargs):
            super().__init__(extra_args=("--tracker-factory", "slow_tracker:slow_tracker"), env=env, **kwargs)

    last_sent = []

    class RecordingPublisher(demo.HoldingPublisher):
        def close(self) -> None:
            super().close()
            last_sent.append(self.last_seq)

    monkeypatch.setattr(demo, "LocalService", SlowService)
    monkeypatch.setattr(demo, "HoldingPublisher", RecordingPublisher)
    scene = Scene.from_spec("scene:320x240")
    for i in range(6):
        cv2.imwrite(str(tmp_path / f"{i + 1}.png"), scene.frame(i))
    out = io.StringIO()
    report = run_demo(DemoOptions(source=str(tmp_path), box=scene.box(0), seconds=30, fps=20, every=1,
                                  node="demolast"), out=out)
    text = out.getvalue()
    assert report.ok and "the source ended" in text, text
    newest_box = max(int(seq) for seq in re.findall(r"box +seq +(\d+)", text))
    assert last_sent and newest_box == last_sent[0], text


def test_a_video_without_frames_is_a_usage_error_with_a_box_given_too(tmp_path):
    """A video file that opens and holds no frame is refused ("has no frames", exit 2) when the demo reads its first
    frame for a box; with --box it was read by the publisher only, and the demo ended with "demo failed: no boxes
    received", exit 1, as for a service that failed."""
    video = tmp_path / "empty.avi"
    cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, (320, 240)).release()
    assert cv2.VideoCapture(str(video)).isOpened()
    done = subprocess.run(_demo(str(video), "--box", "10,10,40,30", "--seconds", "2"), capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 2, done.stdout + done.stderr
    assert done.stderr.splitlines()[-1] == f"tacf demo: source {str(video)!r} has no frames", done.stderr
    assert "Traceback" not in done.stderr and "session" not in done.stdout, done.stdout + done.stderr


def test_a_box_the_tracker_cannot_start_on_is_a_usage_error_before_the_service_starts(tmp_path):
    """A --box outside the first frame was refused by the service only after it had started (about 2 s in), and
    printed twice: as the failed start's error line and again in the "demo failed" summary, exit 1."""
    folder = tmp_path / "clip"
    folder.mkdir()
    for i in range(3):
        cv2.imwrite(str(folder / f"{i:04d}.jpg"), np.full((120, 160, 3), 40 * i, np.uint8))
    done = subprocess.run(_demo(str(folder), "--box", "200,10,20,20"), capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and done.stdout == "", done.stdout + done.stderr
    assert done.stderr.splitlines() == ["tacf demo: cannot start a session with --box on the first frame: "
                                        "box (200.0, 10.0, 20.0, 20.0) lies outside the 160x120 image"], done.stderr
