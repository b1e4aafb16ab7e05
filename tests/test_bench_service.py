"""`tacf bench service` end to end: a real `tacf serve` child, generated 1280x720 JPEG sequences, real Zenoh."""
from __future__ import annotations

import json
import logging
import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh

from tacf.cli import main
from tacf_clients import bench, local_service
from tacf_clients.bench import Feed, FeedPublisher, _percentile
from tacf_clients.local_service import free_port
from tacf_clients.zconfig import ZenohOptions, make_config, open_session
import busy_tracker

TESTS = Path(__file__).resolve().parent


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    """A dataset folder as the benchmark reads it: two 1280x720 JPEG sequences of a moving target (the benchmark's
    feeds, generated: these tests are of the tool, not of the shared sequences) and one of another size it passes
    over."""
    import cv2
    from tacf_service.scene import MovingTargetScene

    root = tmp_path_factory.mktemp("bench-data")
    for name, (width, height) in (("UAV123_10fps/scene1", (1280, 720)), ("UAV123_10fps/scene2", (1280, 720)),
                                  ("small/scene3", (640, 360))):
        scene, folder = MovingTargetScene(width, height, target=96), root / name / "img"
        folder.mkdir(parents=True)
        boxes = []
        for i in range(30):
            image, box = scene.frame(i)
            cv2.imwrite(str(folder / f"{i + 1:06d}.jpg"), image, [cv2.IMWRITE_JPEG_QUALITY, 85])
            boxes.append(",".join(f"{v:g}" for v in box))
        (folder.parent / "groundtruth.txt").write_text("\n".join(boxes) + "\n")
    return root


def test_percentiles_are_nearest_rank():
    """int(q n) as the index was a rank too high: p99 of 100 latencies was their maximum."""
    values = [float(v) for v in range(1, 101)]
    assert (_percentile(values, 0.5), _percentile(values, 0.95), _percentile(values, 0.99)) == (50, 95, 99)
    assert _percentile(values, 1.0) == 100 and _percentile([7.0], 0.99) == 7 and _percentile([], 0.5) is None
    assert _percentile([float(v) for v in range(1, 21)], 0.95) == 19


def test_only_jpeg_sequences_feed_the_benchmark(tmp_path):
    """Frames go out labelled JPEG as read from disk: a 1280x720 PNG sequence was sent as 'jpeg'."""
    import cv2
    import numpy as np

    for name, suffix in (("png", ".png"), ("jpeg", ".jpg")):
        folder = tmp_path / "data" / "bench" / name / "img"
        folder.mkdir(parents=True)
        for i in range(1, 3):
            cv2.imwrite(str(folder / f"{i:06d}{suffix}"), np.full((720, 1280, 3), 40 * i, np.uint8))
        (folder.parent / "groundtruth.txt").write_text("100,100,50,50\n100,100,50,50\n")
    feeds = bench.load_feeds(tmp_path / "data", 2)
    assert [feed.name for feed in feeds] == ["bench/jpeg", "bench/jpeg"]


def _hold_the_gil(seconds: float) -> None:
    """Stall every other Python thread for `seconds`, as a long GC pause or a SIGSTOP would: a busy loop that never
    lets the GIL go (no blocking call, and a switch interval longer than the loop)."""
    interval = sys.getswitchinterval()
    sys.setswitchinterval(seconds + 5)
    try:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            pass
    finally:
        sys.setswitchinterval(interval)


@pytest.mark.zenoh
def test_the_feed_publisher_starts_its_schedule_again_after_a_stall():
    """Frame k of the run was due at start + k / (N fps) whatever happened: after a stall every overdue frame went
    out back to back, a burst the service's latest-only slots turned into drops (20 frames after 1 s at 2 x 10
    fps). After a stall the schedule starts again from then."""
    feeds = [Feed(f"feed{i}", (b"jpeg",), (0.0, 0.0, 8.0, 8.0)) for i in range(2)]
    with zenoh.open(make_config(ZenohOptions(connect=(), listen=(f"tcp/127.0.0.1:{free_port()}",)))) as session:
        publisher = FeedPublisher(session, feeds, fps=10).start()
        time.sleep(0.5)
        _hold_the_gil(1.0)
        time.sleep(1.0)
        publisher.stop()
    stamps = sorted(stamp for sent in publisher.sent for stamp in sent)
    gaps = [(later - earlier) / 1e6 for earlier, later in zip(stamps, stamps[1:])]      # ms
    stall = gaps.index(max(gaps))
    assert gaps[stall] > 900, gaps
    # the frame held up and the next one (the other feed's) go at once, then one every 50 ms again (a loaded
    # machine may add a late one)
    assert sum(gap < 10 for gap in gaps[stall + 1:]) <= 3, [round(gap) for gap in gaps]
    assert abs(len(publisher.sent[0]) - len(publisher.sent[1])) <= 1, "the feeds take turns"


@pytest.mark.zenoh
def test_bench_service_reports_latency_drops_memory_and_cpu(data, tmp_path, capsys):
    out = tmp_path / "bench.json"
    assert main(["bench", "service", str(data), "--feeds", "2", "--fps", "5", "--seconds", "4", "--warmup", "1",
                 "--json", str(out), "--no-progress"]) == 0
    assert "2 feeds:" not in capsys.readouterr().err
    report = json.loads(out.read_text())
    assert report["feeds"] == 2 and report["fps_in"] == 5.0
    assert 2 * 5 * 4 * 0.7 <= report["frames_sent"] <= 2 * 5 * 4 * 1.3   # paced, not flooded
    # every frame got a box or is counted as dropped; at 10 frames/s in all, most get one even on a loaded box
    assert report["boxes_received"] + report["dropped"] == report["frames_sent"]
    assert report["boxes_received"] >= report["frames_sent"] // 2
    latency = report["latency_ms"]
    assert 0 < latency["p50"] <= latency["p95"] <= latency["p99"] <= latency["max"]
    assert report["rss_mb_per_session"] > 50 and report["pss_mb_per_session"] > 10
    assert report["pss_mb_total"] > 2 * report["pss_mb_per_session"]   # the service and its fork server besides
    assert 0 < report["cpu_percent"] <= 100 * report["cpus"] and report["worker_restarts"] == 0
    over_time = report["over_time"]
    assert len(over_time["seconds"]) == len(over_time["rss_mb"]) == len(over_time["pss_mb"]) == \
        len(over_time["open_fds"]) >= 10
    assert min(over_time["open_fds"]) > 0 and min(over_time["rss_mb"]) > 100
    assert 0 < max(over_time["pss_mb"]) < max(over_time["rss_mb"])
    assert sorted(report["sequences"]) == ["UAV123_10fps/scene1", "UAV123_10fps/scene2"]   # the 1280x720 ones


def test_bench_service_without_sequences_is_a_clear_error(tmp_path, caplog):
    assert main(["bench", "service", str(tmp_path / "nowhere")]) == 2
    assert "does not exist" in caplog.text


def test_bench_service_refuses_a_bad_warmup_or_profile_before_starting_a_service(tmp_path):
    a_file = tmp_path / "a-file"
    a_file.write_text("")
    for bad in (["--warmup", "-1"], ["--fps", "nan"], ["--profile", "bogus"], ["--json", str(tmp_path)],
                ["--json", str(a_file / "out.json")]):       # written only after the run, lost with it
        # argparse: a usage error naming what is wrong (a NaN --fps passed a `<= 0` check and ran)
        with pytest.raises(SystemExit) as refused:
            main(["bench", "service", str(tmp_path), *bad])
        assert refused.value.code == 2


def _serve_processes(node: str) -> list[int]:
    """Pids of `tacf serve ... --node NODE` processes on this machine."""
    found = []
    for entry in Path("/proc").iterdir():
        try:
            command = (entry / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"serve" in command and b"--node" in command and command[command.index(b"--node") + 1] == node.encode():
            found.append(int(entry.name))
    return found


@pytest.mark.zenoh
def test_bench_service_stops_its_service_on_sigterm_and_sighup(data):
    """The service runs in a session of its own: only the bench can stop it. Only Ctrl-C used to reach the
    bench's clean-up; SIGTERM (a CI job's timeout) and SIGHUP (the terminal closed) left `tacf serve`, its fork
    server and its workers running."""
    assert not _serve_processes("bench"), "a bench service is already running"
    for sig in (signal.SIGTERM, signal.SIGHUP):
        bench = subprocess.Popen([sys.executable, "-m", "tacf.cli", "bench", "service", str(data), "--seconds", "60",
                                  "--no-progress"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        try:
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline and not _serve_processes("bench"):
                time.sleep(0.2)
            assert _serve_processes("bench"), "the bench started its service"
            time.sleep(1.0)
            bench.send_signal(sig)
            _, err = bench.communicate(timeout=30)
            assert bench.returncode == 128 + sig and "interrupted" in err, (sig, bench.returncode, err[-500:])
            assert not _serve_processes("bench"), f"{sig.name}: the service outlived the bench"
        finally:
            if bench.poll() is None:
                bench.kill()
                bench.wait()
            for pid in _serve_processes("bench"):          # what a failure left behind
                os.kill(pid, signal.SIGKILL)


def _errors(caplog) -> list[str]:
    """The ERROR records logged; the logs they name (kept by LocalService after a failure) are removed."""
    errors = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    for error in errors:
        if found := re.search(r"; log: (\S+)", error):
            Path(found[1]).unlink(missing_ok=True)
    return errors


@pytest.mark.zenoh
def test_a_service_that_cannot_start_is_one_error_with_its_cause(data, monkeypatch, caplog):
    """A failure in a run (here the service's port taken, as a race after free_port() can do) was a traceback, and
    the reports of the feed counts already run were lost. Then it was the first line of the error only, without
    the cause the service's log gives."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        monkeypatch.setattr(local_service, "free_port", lambda: taken.getsockname()[1])
        assert main(["bench", "service", str(data), "--seconds", "1", "--no-progress"]) == 1
    errors = _errors(caplog)
    assert len(errors) == 1 and errors[0].startswith("1 feeds: tacf serve exited with code"), errors
    assert "Address already in use" in errors[0], errors


@pytest.mark.zenoh
def test_a_service_killed_during_the_run_is_reported_as_exited_at_once(data, caplog):
    """A service killed mid-run was measured dead for the rest of the window, then reported as "no tracking service
    'bench' answered"."""
    killed_at = []

    def kill_the_service() -> None:
        deadline = time.monotonic() + 60
        while not (pids := _serve_processes("bench")) and time.monotonic() < deadline:
            time.sleep(0.1)
        time.sleep(4.0)                     # its session tracking by now
        killed_at.append(time.monotonic())
        for pid in pids:
            os.kill(pid, signal.SIGKILL)

    assert not _serve_processes("bench"), "a bench service is already running"
    killer = threading.Thread(target=kill_the_service)
    killer.start()
    try:
        status = main(["bench", "service", str(data), "--fps", "5", "--seconds", "60", "--warmup", "0",
                       "--no-progress"])
    finally:
        killer.join()
    reported_after = time.monotonic() - killed_at[0]
    errors = _errors(caplog)
    assert status == 1 and len(errors) == 1, errors
    assert errors[0].startswith("1 feeds: tacf serve exited with code -9"), errors
    assert reported_after < 10, f"reported {reported_after:.0f} s after the service was killed"


# The fork server of `tacf serve` (named in its command line): every worker it forks after its first hangs before
# running, a worker that never starts.
HANG_WORKERS_AFTER_THE_FIRST = """
import os, time
if b"forkserver" in open("/proc/self/cmdline", "rb").read():
    forks = []
    os.register_at_fork(before=lambda: forks.append(1), after_in_child=lambda: len(forks) > 1 and time.sleep(600))
"""


@pytest.mark.zenoh
def test_a_session_that_sends_no_box_fails_the_run_and_names_it(data, tmp_path, monkeypatch, caplog):
    """A session that never sent a box (its worker hung) made the bench wait 120 s in silence, then report an
    empty measurement with exit code 0."""
    caplog.set_level(logging.INFO)
    (tmp_path / "sitecustomize.py").write_text(HANG_WORKERS_AFTER_THE_FIRST)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(tmp_path), os.environ.get("PYTHONPATH")])))
    monkeypatch.setattr(bench, "FIRST_BOX_TIMEOUT_S", 8.0)
    out = tmp_path / "bench.json"
    assert main(["bench", "service", str(data), "--feeds", "1", "2", "--fps", "5", "--seconds", "1", "--warmup",
                 "0", "--json", str(out), "--no-progress"]) == 1
    [report] = json.loads(out.read_text())      # a list, as for every run of several counts
    assert report["feeds"] == 1, "the report of the count run before is written"
    assert "2 feeds: waiting up to 8 s for the first box of every session" in caplog.text
    errors = _errors(caplog)
    assert errors == ["2 feeds: no box within 8 s from feed1 (starting)"], errors


@pytest.mark.zenoh
def test_ctrl_c_writes_the_reports_of_the_feed_counts_already_run(data, tmp_path):
    """Ctrl-C during the second feed count threw the report of the first away. That report was then written as one
    object, where a run of both counts writes a list of two: a script reading the file had to handle both."""
    out = tmp_path / "bench.json"
    bench_run = subprocess.Popen([sys.executable, "-m", "tacf.cli", "bench", "service", str(data), "--feeds", "1",
                                  "2", "--fps", "5", "--seconds", "1", "--warmup", "0", "--json", str(out),
                                  "--no-progress"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        for line in bench_run.stderr:
            if "1 feeds: p95" in line:          # the second count starts
                break
        bench_run.send_signal(signal.SIGINT)
        _, err = bench_run.communicate(timeout=30)
    finally:
        if bench_run.poll() is None:
            bench_run.kill()
            bench_run.wait()
    assert bench_run.returncode == 130 and "interrupted" in err, err[-500:]
    assert [report["feeds"] for report in json.loads(out.read_text())] == [1]
    assert not _serve_processes("bench"), "the service outlived the bench"


@pytest.mark.zenoh
def test_a_stop_signal_after_the_window_closed_keeps_that_count_s_report(data, tmp_path, monkeypatch, capsys):
    """A Ctrl-C during the 2 s wait for the boxes of the window's last frames threw that count's report away,
    although its window was complete. The wait now runs its course, the report is made, and the exit code is
    130. The Ctrl-C comes 0.5 s after the window's end (when the session workers are looked up)."""
    workers = bench._workers

    def workers_then_ctrl_c(service_pid: int) -> list[int]:
        threading.Timer(0.5, os.kill, (os.getpid(), signal.SIGINT)).start()
        return workers(service_pid)

    monkeypatch.setattr(bench, "_workers", workers_then_ctrl_c)
    out = tmp_path / "bench.json"
    assert main(["bench", "service", str(data), "--feeds", "1", "2", "--fps", "5", "--seconds", "1", "--warmup", "0",
                 "--json", str(out), "--no-progress"]) == 130
    assert "tacf bench: interrupted" in capsys.readouterr().err
    [report] = json.loads(out.read_text())      # the second count is not run
    assert report["feeds"] == 1 and report["boxes_received"] > 0
    assert not _serve_processes("bench"), "the service outlived the bench"


@pytest.mark.zenoh
def test_a_stop_signal_while_the_last_count_stops_its_service_exits_130(data, tmp_path, monkeypatch, capsys):
    """A Ctrl-C while the last feed count shut down (the sessions stopped, the service stopping) was lost: the
    bench exited 0 as if it had not been stopped."""
    class CtrlCOnStop(local_service.LocalService):
        def stop(self, *args, **kwargs):
            if self.process is not None:
                signal.raise_signal(signal.SIGINT)
            return super().stop(*args, **kwargs)

    monkeypatch.setattr(local_service, "LocalService", CtrlCOnStop)
    out = tmp_path / "bench.json"
    assert main(["bench", "service", str(data), "--fps", "5", "--seconds", "1", "--warmup", "0", "--json", str(out),
                 "--no-progress"]) == 130
    assert "tacf bench: interrupted" in capsys.readouterr().err
    assert json.loads(out.read_text())["feeds"] == 1
    assert not _serve_processes("bench"), "the service outlived the bench"


def _forked_workers(service_pid: int) -> list[int]:
    """The children of the service's fork server: its session workers."""
    servers = [pid for pid in bench._children(service_pid)
               if b"forkserver" in Path(f"/proc/{pid}/cmdline").read_bytes()]
    return [pid for server in servers for pid in bench._children(server)]


@pytest.mark.zenoh
def test_a_worker_restarted_in_the_window_is_measured_with_the_one_it_replaced(data, tmp_path, monkeypatch):
    """The benchmark listed the service's processes once, as the window opened. A worker killed in the window
    took the CPU time it had used before the window off the total (the run reported less than nothing), and the
    worker the service started in its place was measured for neither CPU nor memory (with one feed, no session
    memory at all). Each frame costs the busy tracker a known CPU time, so the boxes give a floor for the CPU
    used in the window whatever the machine's load."""
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(TESTS), os.environ.get("PYTHONPATH")])))
    services = []

    class BusyService(local_service.LocalService):        # the bench's service, with the busy tracker
        def __init__(self, *args, extra_args=(), **kwargs):
            super().__init__(*args, extra_args=(*extra_args, "--tracker-factory", "busy_tracker:busy_tracker"),
                             **kwargs)
            services.append(self)

    monkeypatch.setattr(local_service, "LocalService", BusyService)
    warmup, seconds, killed = 1.0, 6.0, []

    def kill_the_worker_in_the_window() -> None:
        deadline = time.monotonic() + 60
        while not (services and services[0].process and _forked_workers(services[0].process.pid)):
            if time.monotonic() > deadline:
                return
            time.sleep(0.1)
        first_box = threading.Event()
        with open_session(services[0].options) as session:
            session.declare_subscriber(f"tacf/{bench.NODE}/sessions/feed0/box", lambda _: first_box.set())
            if not first_box.wait(60):
                return
        time.sleep(warmup + seconds / 3)        # the window opens about `warmup` after the first box
        worker, = _forked_workers(services[0].process.pid)
        os.kill(worker, signal.SIGKILL)
        killed.append(worker)

    killer = threading.Thread(target=kill_the_worker_in_the_window)
    killer.start()
    out = tmp_path / "bench.json"
    try:
        status = main(["bench", "service", str(data), "--fps", "5", "--seconds", str(seconds), "--warmup",
                       str(warmup), "--json", str(out), "--no-progress"])
    finally:
        killer.join()
    assert status == 0 and killed, "the worker was killed during the run"
    report = json.loads(out.read_text())
    cpu_seconds = report["cpu_percent"] / 100 * seconds
    # the boxes of the last frame or two can come after the window's last CPU reading; clock ticks are 10 ms
    floor = 0.9 * busy_tracker.CPU_S * (report["boxes_received"] - 2)
    assert cpu_seconds >= floor, (cpu_seconds, floor, report)
    assert report["rss_mb_per_session"] is not None and report["rss_mb_per_session"] > 20, report
    rss = report["over_time"]["rss_mb"]
    assert rss[-1] > rss[0] - report["rss_mb_per_session"] / 2, rss       # the new worker is in the last sample
    assert report["worker_restarts"] == 1
