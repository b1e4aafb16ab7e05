"""`tacf eval`, `tacf track`, `tacf bench tracker` end to end, the tracker registry and adapters."""
from __future__ import annotations

import contextlib
import importlib.util
import json
import logging
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
import weakref
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

import tacf
from tacf.cli import main
from tacf.config import TrackerConfig
from tacf.eval import metrics, trackers
from tacf.eval.cli import _names
from tacf.eval.datasets import load_sequences
from tacf.eval.runner import read_frame, read_run, run_job, times_path, track_frames, write_run

from closed_pipe import head

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
SEQUENCES = DATA / "sequences"
needs_data = pytest.mark.skipif(not SEQUENCES.is_dir(), reason="../shared/data is absent")
HAS_TACF = importlib.util.find_spec("tacf.tracker") is not None
needs_tacf = pytest.mark.skipif(not HAS_TACF, reason="tacf/tracker.py does not exist yet")

EVAL_SEQS = "UAV123_10fps/wakeboard7,UAVDT/S0601"
EVAL_TRACKERS = ["opencv-csrt", "opencv-kcf", "opencv-mosse"]
ENTRY_KEYS = {"auc", "precision20", "fps", "frames"}


def synthetic_frames(n: int = 20, size=(160, 120)) -> tuple[list[np.ndarray], tuple]:
    """A textured square drifting right over a noisy background; returns frames and the first box."""
    rng = np.random.default_rng(0)
    w, h = size
    background = rng.integers(0, 80, (h, w, 3), dtype=np.uint8)
    patch = rng.integers(60, 255, (24, 24, 3), dtype=np.uint8)
    background, patch = cv2.GaussianBlur(background, (0, 0), 2), cv2.GaussianBlur(patch, (0, 0), 1.5)
    frames = []
    for i in range(n):
        f = background.copy()
        x, y = 30 + 2 * i, 40 + i
        f[y:y + 24, x:x + 24] = patch
        frames.append(f)
    return frames, (30.0, 40.0, 24.0, 24.0)


# --- registry and adapters -------------------------------------------------------------------------------------
def test_registry_names():
    for name in ["tacf", "tacf-paper", "tacf-authors", "kcc", "kcc+sa", "kcc+da+ca", "identity",
                 *trackers.OPENCV_TRACKERS]:
        assert trackers.check_name(name) == name
    for bad in ["kcc+xx", "kcc+sa+sa", "opencv-goturn", "tacf-fast", "sa"]:
        with pytest.raises(ValueError):
            trackers.check_name(bad)
    cfg = trackers.tacf_config("kcc+sa+da")
    assert cfg.profile_name == "kcc" and cfg.spatiotemporal_attention and cfg.dimensional_attention
    assert not cfg.context_attention
    only_ca = trackers.tacf_config("kcc+ca")
    assert only_ca.context_attention and not only_ca.dimensional_attention and not only_ca.spatiotemporal_attention
    assert trackers.tacf_config("tacf-paper").profile_name == "paper"


def test_tracker_names_are_split_at_commas_and_spaces_quoted_or_not():
    assert _names(["tacf kcc", "kcc,identity", " staple ,"], "tacf") == ["tacf", "kcc", "identity", "staple"]
    assert _names(None, "tacf,kcc") == ["tacf", "kcc"]


def test_names_with_settings():
    heavy = trackers.tacf_config("kcc+ca@context_lambda2=16@context_interval=2@fast_resize=false")
    assert heavy.context_attention and not heavy.dimensional_attention and heavy.profile_name == "kcc"
    assert (heavy.context_lambda2, heavy.context_interval, heavy.fast_resize) == (16.0, 2, False)
    assert type(heavy.context_interval) is int and type(heavy.context_lambda2) is float
    paper = trackers.tacf_config("tacf-paper@lambda1=1e-4")
    assert paper.profile_name == "paper" and paper.lambda1 == 1e-4 and paper.context_lambda2 == 0.0625
    assert trackers.tacf_config("tacf@use_colour_names=False") == TrackerConfig.profile(use_colour_names=False)
    assert not trackers.tacf_config("kcc+ca@context_attention=false").context_attention     # the setting wins
    for bad, says in [("tacf@nonsense=1", "bad setting"), ("tacf@lambda1", "bad setting"),
                      ("tacf@lambda1=", "bad setting"), ("tacf@profile_name=paper", "bad setting"),
                      ("kcc@fast_fft=yes", "true or false"), ("kcc@num_scales=3.5", "an integer"),
                      ("kcc@lambda1=1@lambda1=2", "set twice"), ("kcc@num_scales=4", "must be odd"),
                      ("kcc@lambda1=nan", "finite"), ("kcc+xx@lambda1=1", "module list")]:
        with pytest.raises(ValueError, match=says):
            trackers.check_name(bad)


@pytest.mark.parametrize("name", trackers.OPENCV_TRACKERS + ("identity",))
def test_adapters_follow_the_interface(name):
    frames, box = synthetic_frames(8)
    t = trackers.make_tracker(name)
    run = track_frames(t, frames, box)
    assert run.boxes.shape == (8, 4) and run.times.shape == (8,) and (run.times >= 0).all()
    np.testing.assert_array_equal(run.boxes[0], box)
    assert np.isfinite(run.boxes).all() and run.ok.dtype == bool
    if name not in ("identity", "opencv-mosse"):   # OpenCV's MOSSE gives up (PSR < 5.7) on small targets
        assert run.boxes[-1, 0] > box[0] + 4      # followed the drift to the right
    with pytest.raises(RuntimeError, match="call init"):  # as tacf's: not AttributeError, nor a None box
        trackers.make_tracker(name).update(frames[0])


def test_opencv_names_this_opencv_lacks_are_refused_up_front(monkeypatch):
    """opencv-python-headless (installed in place of the contrib build) has no CSRT, KCF or MOSSE: the names were
    accepted, then every sequence failed with "module 'cv2' has no attribute 'TrackerCSRT'"."""
    monkeypatch.delattr(cv2, "TrackerCSRT")
    monkeypatch.delattr(cv2, "legacy")
    for name in ("opencv-csrt", "opencv-mosse"):
        with pytest.raises(ValueError, match="needs OpenCV's contrib modules.*opencv-contrib-python-headless"):
            trackers.check_name(name)
        with pytest.raises(ValueError, match="contrib"):
            trackers.make_tracker(name)
    assert trackers.check_name("opencv-kcf") == "opencv-kcf"


def test_opencv_mil_refuses_a_box_too_small_for_its_features():
    """OpenCV's MIL draws Haar features in the box until each fits; on a 4x4 box none can, and its init spun for
    ever (an eval job that never ended). Sizes measured with OpenCV 5.1: those that hung, then those that started."""
    for width, height in [(1, 30), (30, 1), (2, 10), (10, 2), (3, 5), (5, 3), (4, 4), (3, 4)]:
        assert not trackers.mil_features_fit(width, height)
    for width, height in [(2, 11), (11, 2), (3, 6), (7, 3), (4, 5), (5, 4), (5, 5), (2, 30)]:
        assert trackers.mil_features_fit(width, height)
    frames, _ = synthetic_frames(2)
    mil = trackers.make_tracker("opencv-mil")
    with pytest.raises(ValueError, match="opencv-mil cannot start on a 4x4 box"):
        mil.init(frames[0], (50.0, 50.0, 4.2, 3.6))
    mil.init(frames[0], (50.0, 50.0, 2.0, 11.0))
    assert mil.update(frames[1])[2:] == (2.0, 11.0)


@needs_data
def test_opencv_mil_gives_the_same_boxes_whatever_ran_before_in_the_process():
    """MIL draws its features with libc's rand(), whose state is the process's: the boxes of a pair depended on the
    pairs before it (person12_1's AUC 0.15, 0.38 or 0.56 by --workers and --sequences alone)."""
    import ctypes
    import ctypes.util

    from tacf.eval.runner import track_sequence

    libc = ctypes.CDLL(ctypes.util.find_library("c"))
    seq = load_sequences(SEQUENCES, "UAV123_10fps/wakeboard7")[0]
    seq = replace(seq, frames=seq.frames[:30], gt=seq.gt[:30])
    runs = []
    for draws in (0, 7, 1000):
        for _ in range(draws):               # what earlier pairs would have drawn
            libc.rand()
        runs.append(track_sequence(trackers.make_tracker("opencv-mil"), seq).boxes)
    assert all(np.array_equal(runs[0], boxes) for boxes in runs[1:])


# --- tacf eval ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def evaluated(tmp_path_factory):
    if not SEQUENCES.is_dir():
        pytest.skip("../shared/data is absent")
    out = tmp_path_factory.mktemp("eval")
    rc = main(["eval", str(SEQUENCES), "--sequences", EVAL_SEQS, "--trackers", ",".join(EVAL_TRACKERS),
               "--out", str(out), "--no-progress"])
    assert rc == 0
    return out


def got10k_auc(result_file: Path, gt_file: Path) -> float:
    """got10k's ExperimentOTB formula on the raw (1-based) files, as got10k reads them."""
    boxes = np.loadtxt(result_file, delimiter=",")
    anno = np.loadtxt(gt_file, delimiter=",")
    x1 = np.maximum(boxes[:, 0], anno[:, 0])
    y1 = np.maximum(boxes[:, 1], anno[:, 1])
    x2 = np.minimum(boxes[:, 0] + boxes[:, 2], anno[:, 0] + anno[:, 2])
    y2 = np.minimum(boxes[:, 1] + boxes[:, 3], anno[:, 1] + anno[:, 3])
    inter = np.maximum(x2 - x1, 0) * np.maximum(y2 - y1, 0)
    ious = inter / (boxes[:, 2] * boxes[:, 3] + anno[:, 2] * anno[:, 3] - inter + np.finfo(float).eps)
    return float(np.mean(np.mean(ious[:, None] > np.linspace(0, 1, 21)[None, :], axis=0)))


def test_eval_summary_shape_and_values(evaluated):
    summary = json.loads((evaluated / "summary.json").read_text())
    assert set(summary) == {"trackers", "protocol", "lost_flag", "attributes", "run"}
    assert sorted(summary["trackers"]) == sorted(EVAL_TRACKERS)
    run = summary["run"]      # where the numbers came from
    assert run["arguments"]["trackers"] == [",".join(EVAL_TRACKERS)]
    assert run["arguments"]["root"] == str(SEQUENCES.resolve())
    assert (run["pairs_run"], run["pairs_recorded_before"]) == (6, 0)
    assert run["tacf"] == tacf.__version__ and run["numpy"] == np.__version__ and run["cpus"] >= 1
    assert run["commit"] is None or re.fullmatch(r"[0-9a-f]{40}(\+dirty)?", run["commit"])
    for name, t in summary["trackers"].items():
        assert set(t) == ENTRY_KEYS | {"sequences"}
        assert sorted(t["sequences"]) == ["UAV123_10fps/wakeboard7", "UAVDT/S0601"]
        assert t["frames"] == 67 + 82
        for seq, s in t["sequences"].items():
            assert set(s) == ENTRY_KEYS and 0 <= s["auc"] <= 1 and 0 <= s["precision20"] <= 1 and s["fps"] > 0
            gt_file = SEQUENCES / seq / "groundtruth.txt"
            assert s["auc"] == pytest.approx(got10k_auc(evaluated / name / f"{seq}.txt", gt_file), abs=1e-9)
        seqs = t["sequences"].values()
        assert t["auc"] == pytest.approx(np.mean([s["auc"] for s in seqs]))
        assert t["precision20"] == pytest.approx(np.mean([s["precision20"] for s in seqs]))
        times = np.concatenate([np.loadtxt(evaluated / name / "times" / f"{s}_time.txt") for s in t["sequences"]])
        assert t["fps"] == pytest.approx(len(times) / times.sum(), rel=1e-3)
    # CSRT follows the car of S0601 for a good part of the sequence; MOSSE stays put on wakeboard7's fast target
    assert summary["trackers"]["opencv-csrt"]["sequences"]["UAVDT/S0601"]["auc"] > 0.2


def test_eval_result_files_are_one_based_got10k_format(evaluated):
    lines = (evaluated / "opencv-kcf" / "UAV123_10fps" / "wakeboard7.txt").read_text().splitlines()
    assert len(lines) == 67
    assert lines[0] == "623.000,299.000,11.000,38.000"      # = groundtruth.txt line 1 (1-based)
    assert all(len(line.split(",")) == 4 for line in lines)
    times = np.loadtxt(evaluated / "opencv-kcf" / "times" / "UAV123_10fps" / "wakeboard7_time.txt")
    assert times.shape == (67,) and (times > 0).all()


def test_eval_records_and_judges_each_tracker_s_lost_flag(evaluated):
    summary = json.loads((evaluated / "summary.json").read_text())
    flags = summary["lost_flag"]
    assert (flags["failure_iou"], flags["tracked_iou"]) == (0.1, 0.5)
    assert sorted(flags["trackers"]) == sorted(EVAL_TRACKERS)
    gt = {seq: np.loadtxt(SEQUENCES / seq / "groundtruth.txt", delimiter=",") for seq in ("UAV123_10fps/wakeboard7",
                                                                                      "UAVDT/S0601")}
    for name, judged in flags["trackers"].items():
        lost, overlaps = [], []
        for seq, truth in gt.items():
            rows = np.loadtxt(evaluated / name / "confidence" / f"{seq}.txt", delimiter=",")
            assert rows.shape == (len(truth), 2) and set(rows[:, 1]) <= {0.0, 1.0}
            assert np.isnan(rows[:, 0]).all()  # OpenCV's trackers have no PME
            boxes = np.loadtxt(evaluated / name / f"{seq}.txt", delimiter=",")
            lost.append(rows[1:, 1] == 0)
            overlaps.append(metrics.iou(boxes[1:], truth[1:]))  # the init frame is not judged
        lost, overlaps = np.concatenate(lost), np.concatenate(overlaps)
        assert judged["frames"] == 66 + 81 and judged["flagged"] == pytest.approx(lost.mean())
        assert judged["failures_flagged"] == pytest.approx(lost[overlaps < 0.1].mean())
    # MOSSE gives up on wakeboard7's fast little target and says so
    assert flags["trackers"]["opencv-mosse"]["failures_flagged"] > 0.5
    assert "| opencv-csrt | 147 |" in (evaluated / "summary.md").read_text()
    assert (evaluated / "lost_flag_plot.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_eval_reports_plots_and_markdown(evaluated):
    for png in ("success_plot.png", "precision_plot.png"):
        data = (evaluated / png).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000
    for seq in ("UAV123_10fps/wakeboard7", "UAVDT/S0601"):  # one IoU-over-frames plot per sequence
        data = (evaluated / "overlap" / f"{seq}.png").read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000
    md = (evaluated / "summary.md").read_text()
    assert md.startswith("| tracker | AUC | precision@20 | FPS |")
    assert all(name in md for name in EVAL_TRACKERS) and "UAVDT/S0601" in md


def test_eval_scores_each_attribute_of_the_sequences(evaluated, tmp_path, capsys):
    summary = json.loads((evaluated / "summary.json").read_text())
    attributes = summary["attributes"]
    # without labels they are derived from the ground truth: wakeboard7's target grows, changes shape and moves
    # fast at 10 fps; S0601's car does none of that
    assert attributes["source"] == "derived"
    assert {a: v["sequences"] for a, v in attributes["attributes"].items()} == {
        "SV": ["UAV123_10fps/wakeboard7"], "ARC": ["UAV123_10fps/wakeboard7"], "FM": ["UAV123_10fps/wakeboard7"]}
    for name, t in summary["trackers"].items():
        assert attributes["attributes"]["FM"]["trackers"][name] == {
            "auc": t["sequences"]["UAV123_10fps/wakeboard7"]["auc"],
            "precision20": t["sequences"]["UAV123_10fps/wakeboard7"]["precision20"], "sequences": 1}
    assert "| FM (fast motion) | 1 |" in (evaluated / "summary.md").read_text()
    assert (evaluated / "attributes_plot.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    # a table instead: nothing runs again, the attributes come from it
    out = tmp_path / "out"
    shutil.copytree(evaluated, out)
    table = tmp_path / "attributes.txt"
    table.write_text("S0601 LR POC\nUAV123_10fps/wakeboard7 LR\n")
    assert main(["eval", str(SEQUENCES), "--sequences", EVAL_SEQS, "--trackers", ",".join(EVAL_TRACKERS),
                 "--out", str(out), "--attributes", str(table), "--no-progress"]) == 0
    attributes = json.loads((out / "summary.json").read_text())["attributes"]
    assert attributes["source"] == "table"
    assert {a: v["sequences"] for a, v in attributes["attributes"].items()} == {
        "LR": ["UAV123_10fps/wakeboard7", "UAVDT/S0601"], "POC": ["UAVDT/S0601"]}
    lr = attributes["attributes"]["LR"]["trackers"]["opencv-csrt"]
    assert lr["auc"] == pytest.approx(summary["trackers"]["opencv-csrt"]["auc"]) and lr["sequences"] == 2
    assert "Success AUC per attribute (from the --attributes table)" in capsys.readouterr().out
    table.write_text("S0601 LR\nS0601 FM\n")
    assert main(["eval", str(SEQUENCES), "--sequences", EVAL_SEQS, "--trackers", "opencv-csrt",
                 "--out", str(out), "--attributes", str(table), "--no-progress"]) == 2


def test_eval_resumes_and_force_reruns(evaluated, capsys):
    result = evaluated / "opencv-mosse" / "UAVDT" / "S0601.txt"
    before = result.stat().st_mtime_ns
    assert main(["eval", str(SEQUENCES), "--sequences", EVAL_SEQS, "--trackers", "opencv-mosse",
                 "--out", str(evaluated / "."), "--no-progress"]) == 0
    assert result.stat().st_mtime_ns == before
    os.utime(result, ns=(before - 10**9, before - 10**9))
    assert main(["eval", str(SEQUENCES), "--sequences", "UAVDT/S0601", "--trackers", "opencv-mosse",
                 "--out", str(evaluated), "--force", "--no-progress"]) == 0
    assert result.stat().st_mtime_ns > before - 10**9
    assert "opencv-mosse" in capsys.readouterr().out


def test_a_pair_that_fails_is_not_scored_from_what_an_earlier_run_left(tmp_path, caplog):
    """A --force run whose frame had become unreadable named the pair as failed, then scored it from the result
    file of the run before."""
    data = write_synthetic_dataset(tmp_path, 6)
    out = tmp_path / "out"
    args = ["eval", str(data), "--trackers", "opencv-mosse", "--out", str(out), "--no-progress"]
    assert main(args) == 0
    (data / "synthetic" / "drift" / "img" / "000003.png").write_bytes(b"not a png")
    assert main([*args, "--force"]) == 1
    assert "opencv-mosse on synthetic/drift failed" in caplog.text
    assert json.loads((out / "summary.json").read_text())["trackers"]["opencv-mosse"]["sequences"] == {}
    assert not (out / "opencv-mosse" / "synthetic" / "drift.txt").exists()


def test_a_result_recorded_with_other_settings_is_run_again(tmp_path, caplog):
    """`tacf` names the default profile, whose boxes change with it: a resumed run kept an older version's results
    under that name, and summary.json credited them to the current commit. Here another tracker's results stand in
    for them."""
    caplog.set_level("INFO", logger="tacf.eval.runner")
    data = write_synthetic_dataset(tmp_path, 6)
    out = tmp_path / "out"
    args = ["eval", str(data), "--out", str(out), "--no-progress", "--trackers"]

    def pairs_run() -> int:
        return json.loads((out / "summary.json").read_text())["run"]["pairs_run"]
    assert main([*args, "identity,opencv-mosse"]) == 0 and pairs_run() == 2
    shutil.rmtree(out / "opencv-mosse")
    shutil.copytree(out / "identity", out / "opencv-mosse")
    assert main([*args, "opencv-mosse"]) == 0 and pairs_run() == 1
    assert "recorded with other settings of opencv-mosse" in caplog.text
    assert main([*args, "opencv-mosse"]) == 0 and pairs_run() == 0         # resumed, now that they are its own


def test_eval_reruns_a_result_of_another_length_and_scores_the_first_frames_of_a_longer_one(tmp_path):
    out = tmp_path / "out"
    args = ["eval", str(write_synthetic_dataset(tmp_path, 12)), "--trackers", "identity", "--out", str(out),
            "--no-progress"]
    result = out / "identity" / "synthetic" / "drift.txt"

    def frames_scored() -> int:
        return json.loads((out / "summary.json").read_text())["trackers"]["identity"]["frames"]

    assert main(args + ["--max-frames", "5"]) == 0 and frames_scored() == 5
    assert main(args) == 0 and frames_scored() == 12     # the 5-row smoke result runs again
    assert len(result.read_text().splitlines()) == 12
    before = result.stat().st_mtime_ns
    assert main(args + ["--max-frames", "5"]) == 0 and frames_scored() == 5
    assert result.stat().st_mtime_ns == before           # the whole run's first 5 boxes are scored, not rerun
    result.write_text(result.read_text() + "garbage\n")  # edited by hand, say
    assert main(args) == 0 and frames_scored() == 12     # runs again, instead of a traceback


@needs_data
def test_eval_with_two_worker_processes(evaluated, tmp_path):
    rc = main(["eval", str(SEQUENCES), "--sequences", EVAL_SEQS, "--trackers", "opencv-mosse", "identity",
               "--out", str(tmp_path), "--workers", "2", "--no-progress"])
    assert rc == 0
    for seq in ("UAV123_10fps/wakeboard7", "UAVDT/S0601"):
        assert (tmp_path / "opencv-mosse" / f"{seq}.txt").read_text() == \
            (evaluated / "opencv-mosse" / f"{seq}.txt").read_text()
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert sorted(summary["trackers"]) == ["identity", "opencv-mosse"]


@needs_data
@pytest.mark.parametrize("stop_signal, whole_group, exit_code", [
    (signal.SIGINT, True, 130),         # Ctrl-C in a terminal: the whole foreground group
    (signal.SIGTERM, False, 143),       # `kill PID`, a container's stop: the command alone; its workers outlived it
])
def test_a_stop_signal_stops_an_eval_and_its_workers_quietly(tmp_path, stop_signal, whole_group, exit_code):
    command = [sys.executable, "-m", "tacf.cli", "eval", str(SEQUENCES), "--sequences", "UAV123_10fps/*",
               "--trackers", "opencv-csrt", "--out", str(tmp_path), "--workers", "2", "--no-progress"]
    # a process group of its own, as a terminal's foreground job, with SIGINT not ignored
    proc = subprocess.Popen(command, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))

    def group() -> list[str]:
        return subprocess.run(["pgrep", "-g", str(proc.pid)], capture_output=True, text=True).stdout.split()

    try:
        deadline = time.monotonic() + 60
        while len(group()) < 4 and time.monotonic() < deadline:  # this process, the resource tracker, two workers
            time.sleep(0.2)
        time.sleep(1.0)
        if whole_group:
            os.killpg(proc.pid, stop_signal)
        else:
            proc.send_signal(stop_signal)
        _, err = proc.communicate(timeout=60)
        assert proc.returncode == exit_code, err
        assert "Traceback" not in err and "interrupted: the pairs finished are recorded" in err
        deadline = time.monotonic() + 5                          # the resource tracker ends once it sees the end
        while group() and time.monotonic() < deadline:
            time.sleep(0.1)
        assert group() == []                                     # no worker left behind
        assert not list(tmp_path.rglob("*.part"))
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)


def run_job_or_die(job):
    """run_job, in a worker that dies as the out-of-memory killer ends a process when its job is sequence `die`."""
    if job.seq.name == "die":
        os.kill(os.getpid(), signal.SIGKILL)
    return run_job(job)


def test_eval_runs_the_pairs_a_dead_worker_left_again_and_fails_only_its_own(tmp_path, monkeypatch, caplog):
    """A pool worker killed in the middle of a job made `tacf eval --workers 2` wait for ever; then it failed every
    pair not done with it. They now run again, and only the pair that killed its worker fails."""
    from tacf.eval import runner

    data = write_synthetic_dataset(tmp_path, 4)
    for name in ("die", "live"):
        shutil.copytree(data / "synthetic" / "drift", data / name)
    monkeypatch.setattr(runner, "run_job", run_job_or_die)   # the workers unpickle it from this module
    rcs = []
    run = threading.Thread(target=lambda: rcs.append(main(["eval", str(data), "--trackers", "identity", "--workers",
                                                            "2", "--out", str(tmp_path / "out"), "--no-progress"])),
                           daemon=True)
    run.start()
    run.join(timeout=120)
    assert not run.is_alive(), "the run waits for ever for the job of the worker that died"
    assert rcs == [1]
    assert f"identity on die failed: {runner.WORKER_DIED}" in caplog.text
    assert "pair(s) it left undone run again" in caplog.text
    for name in ("live", "synthetic/drift"):
        assert (tmp_path / "out" / "identity" / f"{name}.txt").is_file(), caplog.text
        assert f"identity on {name} failed" not in caplog.text


def test_times_keep_a_fast_tracker_s_precision_and_files_of_6_decimals_still_read(tmp_path):
    """Times were written with 6 decimals: 0.25 us a frame was recorded as 0, 1.234567 us as 1 us."""
    frames, box = synthetic_frames(4)
    times = np.array([1.234567e-6, 2.5e-7, 0.0123456789, 3.0])
    run = replace(track_frames(trackers.IdentityTracker(), frames, box), times=times)
    write_run(tmp_path, "identity", "seq", run)
    np.testing.assert_allclose(read_run(tmp_path, "identity", "seq")[1], times, rtol=1e-8)
    times_path(tmp_path, "identity", "seq").write_text("0.000002\n0.000001\n0.012346\n3.000000\n")
    np.testing.assert_array_equal(read_run(tmp_path, "identity", "seq")[1], [2e-6, 1e-6, 0.012346, 3.0])


def test_eval_bad_input_exits_2(tmp_path):
    assert main(["eval", str(tmp_path), "--trackers", "opencv-kcf", "--out", str(tmp_path / "o")]) == 2
    assert main(["eval", str(tmp_path), "--trackers", "nope", "--out", str(tmp_path / "o")]) == 2


def test_a_glob_that_matches_nothing_is_refused_with_the_names_there_are(tmp_path, caplog):
    data = write_synthetic_dataset(tmp_path, 4)
    for command in (["eval", str(data), "--out", str(tmp_path / "out")], ["bench", "tracker", str(data)]):
        caplog.clear()
        assert main([*command, "--trackers", "identity", "--sequences", "drif"]) == 2
        assert f"no sequences in {data} matching 'drif'; it has synthetic/drift" in caplog.text
    assert not (tmp_path / "out").exists()


def test_a_ground_truth_that_cannot_be_read_is_an_error_naming_it(tmp_path, caplog):
    """`tacf bench tracker` caught only FileNotFoundError: a ground truth that was a folder was a traceback."""
    data = write_synthetic_dataset(tmp_path, 4)
    ground_truth = data / "synthetic" / "drift" / "groundtruth.txt"
    ground_truth.unlink()
    ground_truth.mkdir()
    for command in (["eval", str(data), "--out", str(tmp_path / "out")], ["bench", "tracker", str(data)]):
        caplog.clear()
        assert main([*command, "--trackers", "identity", "--sequences", "*"]) == 2
        assert f"Is a directory: '{ground_truth}'" in caplog.text


def test_eval_refuses_ranges_for_a_root_not_in_the_uav123_layout(tmp_path, caplog):
    """--ranges was ignored, without a word, unless the root was in the UAV123 layout."""
    ranges = tmp_path / "ranges.txt"
    ranges.write_text("drift drift 1 4\n")
    assert main(["eval", str(write_synthetic_dataset(tmp_path, 4)), "--trackers", "identity", "--ranges", str(ranges),
                 "--out", str(tmp_path / "out"), "--no-progress"]) == 2
    assert f"--ranges {ranges}: frame-range tables are for the UAV123 layout" in caplog.text
    assert "is in the generic layout" in caplog.text and not (tmp_path / "out").exists()


def test_eval_refuses_an_out_folder_it_cannot_make_before_running(tmp_path, caplog):
    data = write_synthetic_dataset(tmp_path, 4)
    (tmp_path / "a_file").write_text("")
    for out in (tmp_path / "a_file", tmp_path / "a_file" / "below"):
        caplog.clear()
        assert main(["eval", str(data), "--trackers", "identity", "--out", str(out), "--no-progress"]) == 2
        assert f"--out {out}: cannot make this folder" in caplog.text and "failed" not in caplog.text


def run_with_file_size_limit(args: list[str], limit: int) -> subprocess.CompletedProcess:
    """`tacf ARGS` in a process that may write files of `limit` bytes at most, as on a disk that fills up: a write
    past it fails with EFBIG (SIGXFSZ ignored), as one fails with ENOSPC on a full disk."""
    import resource

    def limit_file_size() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
    return subprocess.run([sys.executable, "-m", "tacf.cli", *args], capture_output=True, text=True, timeout=120,
                          preexec_fn=limit_file_size)


def test_eval_names_a_report_it_has_no_room_for_and_keeps_the_earlier_one(tmp_path):
    """A disk that filled up as `tacf eval` wrote its reports ended it with an OSError traceback that named no file,
    and left summary.json cut (0 bytes on a full tmpfs). One line now names the file and the reason, exit 1, and
    the earlier run's summary.json is left whole."""
    data, out = write_synthetic_dataset(tmp_path, 6), tmp_path / "out"
    args = ["eval", str(data), "--trackers", "identity", "--out", str(out), "--no-progress"]
    assert main(args) == 0
    earlier = (out / "summary.json").read_bytes()
    assert len(earlier) > 1000                          # the result files fit in 1000 bytes, summary.json not
    done = run_with_file_size_limit(args + ["--force"], 1000)
    assert done.returncode == 1, done.stderr
    assert "Traceback" not in done.stderr
    assert f"ERROR tacf.eval.cli: cannot write {out / 'summary.json'}: File too large; the results of the pairs " \
           f"are recorded in {out}" in done.stderr
    assert (out / "summary.json").read_bytes() == earlier and not list(out.rglob("*.part"))


@pytest.mark.parametrize("workers", [1, 2])
def test_eval_stops_at_the_first_result_it_has_no_room_for(tmp_path, workers):
    """On a full disk `tacf eval` tracked every pair and failed to record each in turn (minutes each on a real
    dataset), each with a traceback that named no file. It now stops at the first, with one line naming the file
    and the reason, exit 1, and leaves no .part file."""
    data, out = write_synthetic_dataset(tmp_path, 6), tmp_path / "out"
    done = run_with_file_size_limit(["eval", str(data), "--trackers", "identity,opencv-mosse,opencv-kcf,opencv-csrt",
                                     "--out", str(out), "--workers", str(workers), "--no-progress"],
                                    100)            # the confidence file's header alone is longer
    assert done.returncode == 1, done.stderr
    assert "Traceback" not in done.stderr
    errors = [line for line in done.stderr.splitlines() if " ERROR " in line]
    assert len(errors) == 1, done.stderr
    assert re.search(rf"ERROR tacf.eval.cli: (\S+) on synthetic/drift failed: cannot write {re.escape(str(out))}/\1/"
                     r"confidence/synthetic/drift.txt: File too large; stopped, with \d of the 4 pairs not done",
                     errors[0]), errors[0]
    if workers == 1:
        assert "with 3 of the 4 pairs not done" in errors[0] and [p.name for p in out.iterdir()] == ["identity"]
    assert not list(out.rglob("*.part")) and not (out / "summary.json").exists()


def test_bench_puts_a_report_it_has_no_room_for_on_standard_output(tmp_path):
    """`tacf bench tracker --json` on a full disk ended minutes of timing with an OSError traceback, the report
    lost."""
    data, report = write_synthetic_dataset(tmp_path, 4), tmp_path / "bench.json"
    done = run_with_file_size_limit(["bench", "tracker", str(data), "--sequences", "*", "--trackers", "identity",
                                     "--no-progress", "--json", str(report)], 1000)
    assert done.returncode == 1, done.stderr
    assert f"cannot write {report}: File too large; the report follows on standard output" in done.stderr
    assert json.loads(done.stdout)["tracker"] == "identity" and not report.exists()


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no named pipes")
def test_a_report_to_a_pipe_or_device_is_written_to_it_not_replaced(tmp_path):
    """Written whole by a rename, `--json /dev/stdout` (a pipe) was replaced by a file, as root /dev/stdout itself."""
    from tacf.eval.text_files import write_atomically

    pipe = tmp_path / "pipe"
    os.mkfifo(pipe)
    reader = os.open(pipe, os.O_RDONLY | os.O_NONBLOCK)     # a reader there, so that the writer does not wait
    try:
        write_atomically(pipe, '{"fps": 1}')
        assert pipe.is_fifo() and not list(tmp_path.glob("*.part"))
        assert os.read(reader, 100) == b'{"fps": 1}'
    finally:
        os.close(reader)



def test_a_write_interrupted_by_ctrl_c_leaves_no_part_file(tmp_path, monkeypatch):
    """A Ctrl-C while a result was being written left RESULT.part beside the results; the earlier file stays."""
    from tacf.eval.text_files import write_atomically

    result = tmp_path / "person1.txt"
    result.write_text("1,2,3,4\n")

    def cut_short(path, data):
        with open(path, "wb") as file:
            file.write(data[:3])
        raise KeyboardInterrupt

    monkeypatch.setattr(Path, "write_bytes", cut_short)
    with pytest.raises(KeyboardInterrupt):
        write_atomically(result, "5,6,7,8\n" * 100)
    assert result.read_text() == "1,2,3,4\n" and not list(tmp_path.glob("*.part"))

# --- tacf track ---------------------------------------------------------------------------------------------
def check_boxes_file(path: Path, n: int, box) -> np.ndarray:
    lines = path.read_text().splitlines()
    assert lines[0].startswith("# x,y,w,h,pme,ok")
    rows = np.array([[float(v) for v in line.split(",")] for line in lines[1:]])
    assert rows.shape == (n, 6)
    np.testing.assert_array_equal(rows[0, :4], box)
    assert set(rows[:, 5]) <= {0.0, 1.0}
    return rows


def test_track_image_folder_and_video(tmp_path):
    frames, box = synthetic_frames(20)
    folder = tmp_path / "frames"
    folder.mkdir()
    for i, f in enumerate(frames, 1):
        cv2.imwrite(str(folder / f"{i:06d}.png"), f)
    rc = main(["track", str(folder), "--box", ",".join(str(v) for v in box), "--tracker", "opencv-kcf",
               "--out", str(tmp_path / "boxes.txt"), "--video", str(tmp_path / "out.mp4")])
    assert rc == 0
    rows = check_boxes_file(tmp_path / "boxes.txt", 20, box)
    assert rows[-1, 0] == pytest.approx(box[0] + 38, abs=3)
    # a dataset's sequence folder: its img/, not a preview image beside it
    (tmp_path / "seq").mkdir()
    folder.rename(tmp_path / "seq" / "img")
    cv2.imwrite(str(tmp_path / "seq" / "preview.jpg"), frames[0])
    assert main(["track", str(tmp_path / "seq"), "--box", ",".join(str(v) for v in box), "--tracker", "opencv-kcf",
                 "--out", str(tmp_path / "seq_boxes.txt")]) == 0
    check_boxes_file(tmp_path / "seq_boxes.txt", 20, box)
    cap = cv2.VideoCapture(str(tmp_path / "out.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 20
    cap.release()

    mp4 = tmp_path / "input.mp4"
    writer = cv2.VideoWriter(str(mp4), cv2.VideoWriter_fourcc(*"mp4v"), 10, (160, 120))
    for f in frames:
        writer.write(f)
    writer.release()
    rc = main(["track", str(mp4), "--box", "30,40,24,24", "--tracker", "opencv-csrt",
               "--out", str(tmp_path / "boxes_mp4.txt")])
    assert rc == 0
    rows = check_boxes_file(tmp_path / "boxes_mp4.txt", 20, box)
    assert rows[-1, 0] == pytest.approx(box[0] + 38, abs=4)


def test_track_reads_a_folder_of_thermal_tiffs_as_tacf_publish_does(tmp_path):
    """`tacf track` listed .jpg, .jpeg, .png and .bmp only: a folder of TIFFs that `tacf publish` and `tacf demo`
    take was "no images". 12-bit thermal frames in one-channel 16-bit TIFFs are stretched to 8 bits as there."""
    frames, box = synthetic_frames(20)
    folder = tmp_path / "thermal"
    folder.mkdir()
    for i, frame in enumerate(frames, 1):
        cv2.imwrite(str(folder / f"{i:06d}.tiff"), cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY).astype(np.uint16) * 16)
    assert main(["track", str(folder), "--box", ",".join(str(v) for v in box), "--tracker", "tacf",
                 "--out", str(tmp_path / "boxes.txt")]) == 0
    rows = check_boxes_file(tmp_path / "boxes.txt", 20, box)
    assert rows[-1, 0] == pytest.approx(box[0] + 38, abs=3) and rows[-1, 1] == pytest.approx(box[1] + 19, abs=3)
    assert read_frame(folder / "000001.tiff").max() == 255          # read with cv2.IMREAD_COLOR: under 16


def test_track_leaves_out_the_hidden_files_a_mac_puts_beside_each_frame(tmp_path):
    """A folder copied from a Mac to a FAT or exFAT drive holds `._000001.jpg` (AppleDouble metadata, not an image)
    beside each frame: they were listed as frames after the real ones, and `tacf track` tracked every frame, then
    failed on the first of them ("cannot read image"), exit 2."""
    frames, box = synthetic_frames(10)
    for i, frame in enumerate(frames, 1):
        cv2.imwrite(str(tmp_path / f"{i:06d}.jpg"), frame)
        (tmp_path / f"._{i:06d}.jpg").write_bytes(b"\x00\x05\x16\x07" + bytes(4092))
    assert main(["track", str(tmp_path), "--box", ",".join(str(v) for v in box), "--tracker", "identity",
                 "--out", str(tmp_path / "boxes.txt")]) == 0
    check_boxes_file(tmp_path / "boxes.txt", 10, box)


def test_track_and_eval_read_and_write_paths_whose_names_are_not_utf8(tmp_path):
    """A folder unzipped from an archive made on a Chinese Windows has GBK names ("数据" here), which Python decodes
    to lone surrogates: OpenCV's imread, VideoWriter and VideoCapture, and its putText on the sequence's name,
    crashed the process (SIGSEGV, no message) and matplotlib and summary.md refused the name with a traceback. In
    a child process, as a crash would end pytest's own."""
    gbk = os.fsdecode("数据".encode("gbk"))
    data = write_synthetic_dataset(tmp_path, 6)
    seq = (data / "synthetic" / "drift").rename(data / "synthetic" / f"{gbk} drift")
    video, out = tmp_path / f"{gbk}.mp4", tmp_path / "out"

    def tacf_cli(*args: str) -> None:
        done = subprocess.run([sys.executable, "-m", "tacf.cli", *args], capture_output=True, timeout=120)
        assert done.returncode == 0, f"exit {done.returncode}: {done.stderr.decode(errors='replace')[-2000:]}"

    tacf_cli("track", str(seq), "--tracker", "identity", "--box", "31,41,24,24", "--out", str(tmp_path / "b.txt"),
             "--video", str(video))
    tacf_cli("track", str(video), "--tracker", "identity", "--box", "31,41,24,24", "--out", str(tmp_path / "c.txt"))
    assert len((tmp_path / "c.txt").read_text().splitlines()) == 1 + 6
    tacf_cli("eval", str(data), "--trackers", "identity", "--out", str(out), "--no-progress", "--videos")
    assert f"| synthetic/{gbk} drift |".encode(errors="surrogateescape") in (out / "summary.md").read_bytes()
    for made in ("identity/synthetic/{} drift.txt", "overlap/synthetic/{} drift.png", "videos/synthetic/{} drift.mp4"):
        assert (out / made.format(gbk)).stat().st_size > 0


def test_track_warns_of_a_video_cut_short(tmp_path, caplog):
    """A video cut in half (a copy interrupted, a recorder's power lost) was tracked to where it broke, the box file
    as for a whole video, without a word that frames were missing."""
    frames, box = synthetic_frames(30)
    whole, cut = tmp_path / "whole.avi", tmp_path / "cut.avi"
    writer = cv2.VideoWriter(str(whole), cv2.VideoWriter_fourcc(*"MJPG"), 10, (160, 120))
    for frame in frames:
        writer.write(frame)
    writer.release()
    cut.write_bytes(whole.read_bytes()[:whole.stat().st_size // 2])
    track = ["--box", ",".join(str(v) for v in box), "--tracker", "identity", "--out", str(tmp_path / "boxes.txt")]
    assert main(["track", str(whole), *track]) == 0 and "declares" not in caplog.text
    assert main(["track", str(cut), *track]) == 0
    lines = (tmp_path / "boxes.txt").read_text().splitlines()[1:]
    assert 0 < len(lines) < 30
    assert f"cut.avi: the video ended after {len(lines)} of the 30 frames its header declares" in caplog.text


def test_track_read_by_head_ends_quietly(tmp_path):
    """`tacf track ... | head` logged "ERROR ... Broken pipe" and exited 2, as for a source it could not read: it
    ends as Unix filters do, silent, with the status of a filter the pipe stopped."""
    frame = np.random.default_rng(0).integers(0, 256, (32, 32, 3), np.uint8)
    for i in range(1, 3001):            # more lines than a pipe holds (64 KB): the command cannot be done first
        cv2.imwrite(str(tmp_path / f"{i:06d}.png"), frame)
    code, lines, err = head(["track", str(tmp_path), "--box", "8,8,10,10", "--tracker", "identity"], 2)
    assert lines[0].startswith("# x,y,w,h,pme,ok") and lines[1].startswith("8.000,8.000,10.000,10.000,")
    assert (code, err) == (141, ""), err


def test_track_bad_arguments(tmp_path, capsys):
    with pytest.raises(SystemExit) as refused:      # a usage error, as for every command taking a box
        main(["track", str(tmp_path), "--box", "1,2,3", "--tracker", "opencv-kcf"])
    assert refused.value.code == 2 and "argument --box: '1,2,3': expected x,y,w,h" in capsys.readouterr().err
    assert main(["track", str(tmp_path / "missing.mp4"), "--box", "1,2,3,4", "--tracker", "opencv-kcf"]) == 2
    assert main(["track", str(tmp_path), "--box", "1,2,3,4", "--tracker", "opencv-kcf"]) == 2   # empty folder


def test_track_that_cannot_start_leaves_an_existing_box_file_alone(tmp_path):
    """--out was opened (emptied) before anything was checked: a mistyped source or a box outside the frame wiped
    the boxes of an earlier run. The outputs are now opened once the first frame is tracked. A box outside the
    frame is refused alike for every tracker."""
    frames, box = synthetic_frames(5)
    folder = tmp_path / "frames"
    folder.mkdir()
    for i, f in enumerate(frames, 1):
        cv2.imwrite(str(folder / f"{i:06d}.png"), f)
    out, video = tmp_path / "boxes.txt", tmp_path / "tracked.mp4"
    out.write_text("the boxes of an earlier run\n")
    for source, bad_box, tracker in ((tmp_path / "frames-typo", "30,40,24,24", "opencv-kcf"),
                                     (folder, "500,500,24,24", "tacf-kcc"),
                                     (folder, "500,500,24,24", "opencv-kcf"),      # was a cv2.error traceback
                                     (folder, "500,500,24,24", "opencv-mosse")):   # was tracked, exit 0
        assert main(["track", str(source), "--box", bad_box, "--tracker", tracker, "--out", str(out),
                     "--video", str(video)]) == 2
        assert out.read_text() == "the boxes of an earlier run\n" and not video.exists()
    assert main(["track", str(folder), "--box", "30,40,24,24", "--tracker", "opencv-kcf", "--out", str(out)]) == 0
    check_boxes_file(out, 5, box)


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="no /dev/full, whose writes fail as on a full disk")
def test_track_names_the_box_file_it_has_no_room_for(tmp_path, caplog):
    """`tacf track --out` on a full disk said only "[Errno 28] No space left on device"."""
    sequence = write_synthetic_dataset(tmp_path, 4) / "synthetic" / "drift"
    assert main(["track", str(sequence), "--box", "31,41,24,24", "--tracker", "identity", "--out", "/dev/full"]) == 2
    assert "cannot write /dev/full: No space left on device" in caplog.text


def test_track_fails_when_its_video_could_not_be_written_whole(tmp_path):
    """A disk that filled up under `tacf track --video` ended it with exit 0 and "video in OUT.mp4", an mp4 without
    its index that no player opens: OpenCV's writer printed "Failed to write frame" at most."""
    sequence = write_synthetic_dataset(tmp_path, 20) / "synthetic" / "drift"
    boxes, video = tmp_path / "boxes.txt", tmp_path / "tracked.mp4"
    done = run_with_file_size_limit(["track", str(sequence), "--box", "31,41,24,24", "--tracker", "identity",
                                     "--out", str(boxes), "--video", str(video)],
                                    4000)           # the boxes fit, not the video (10 KB)
    assert done.returncode == 2, done.stderr
    assert f"ERROR tacf.eval.cli: cannot write {video}: OpenCV's video writer failed (a full disk?): it does not " \
           "open" in done.stderr and "video in" not in done.stderr
    check_boxes_file(boxes, 20, (31, 41, 24, 24))    # written all the same


@pytest.mark.parametrize("text", ["-5,40,24,24", "-.5,-3.5,24,24", "-1e1,40,24,24"])
def test_track_takes_a_box_across_the_left_or_top_border_as_written(tmp_path, text):
    """`--box -5,40,24,24`, a target half out of view: argparse before Python 3.14 took the value for an option,
    and the command refused it ("argument --box: expected one argument"); only `--box=-5,...` went through."""
    frames, _ = synthetic_frames(3)
    for i, f in enumerate(frames, 1):
        cv2.imwrite(str(tmp_path / f"{i:06d}.png"), f)
    out = tmp_path / "boxes.txt"
    assert main(["track", str(tmp_path), "--box", text, "--tracker", "identity", "--out", str(out)]) == 0
    check_boxes_file(out, 3, [float(v) for v in text.split(",")])


def test_track_refuses_a_negative_box_that_is_no_box(capsys):
    with pytest.raises(SystemExit) as refused:      # still a usage error naming --box, not an option
        main(["track", "frames", "--box", "-5,40,24"])
    assert refused.value.code == 2 and "argument --box: '-5,40,24': expected x,y,w,h" in capsys.readouterr().err


@pytest.mark.parametrize("tracker, box", [("opencv-csrt", "159,119,1,1"), ("opencv-csrt", "-0.5,-0.5,1,1"),
                                          ("opencv-mosse", "159,119,1,1"), ("opencv-mil", "-5,0,10,10"),
                                          ("opencv-mil", "150,30,20,20")])
def test_track_with_a_box_opencv_cannot_start_on_is_an_error_naming_the_tracker(tmp_path, caplog, tracker, box):
    """Boxes the library tracker takes (across a border, a pixel in a corner) that OpenCV's trackers fail on in
    init: `tacf track` ended with a cv2.error traceback (MIL: "std::bad_alloc"). Now exit 2 and one line naming
    the tracker and the box; an init refused keeps the target the adapter followed."""
    frames, start = synthetic_frames(3)
    for i, f in enumerate(frames, 1):
        cv2.imwrite(str(tmp_path / f"{i:06d}.png"), f)
    assert main(["track", str(tmp_path), f"--box={box}", "--tracker", tracker]) == 2
    assert f"{tracker} cannot start on the box ({', '.join(str(float(v)) for v in box.split(','))}) in the " \
           f"160x120 image (OpenCV: " in caplog.text
    adapter = trackers.make_tracker(tracker)
    adapter.init(frames[0], start)
    with pytest.raises(ValueError, match="cannot start"):
        adapter.init(frames[0], tuple(float(v) for v in box.split(",")))
    assert adapter.update(frames[1])[2:] == start[2:]


def test_track_refuses_a_frame_of_another_size_and_names_it(tmp_path, caplog):
    """A folder whose third image is smaller: OpenCV's trackers went on (exit 0) while the video writer dropped
    that frame with a warning, and TACF's error named no file and told the user to call init()."""
    frames, box = synthetic_frames(5)
    for i, f in enumerate(frames, 1):
        cv2.imwrite(str(tmp_path / f"{i:06d}.png"), f if i != 3 else cv2.resize(f, (80, 60)))
    for tracker in ("opencv-csrt", "identity", "tacf"):
        caplog.clear()
        assert main(["track", str(tmp_path), "--box", ",".join(str(v) for v in box), "--tracker", tracker,
                     "--out", str(tmp_path / "boxes.txt"), "--video", str(tmp_path / "out.mp4")]) == 2, tracker
        assert f"{tmp_path / '000003.png'} is 80x60, the first frame 160x120" in caplog.text, (tracker, caplog.text)
        assert "init()" not in caplog.text
        assert len((tmp_path / "boxes.txt").read_text().splitlines()) == 3      # the header and frames 1-2


@pytest.mark.parametrize("stop_signal, exit_code", [(signal.SIGINT, 130), (signal.SIGTERM, 143), (signal.SIGHUP, 129)])
def test_a_stop_signal_ends_a_command_with_one_line_not_a_traceback(tmp_path, stop_signal, exit_code):
    """Ctrl-C, SIGTERM (`timeout`, a supervisor) or a closed terminal's SIGHUP in a command that does not handle them
    itself (here `tacf track` half way through a long video): exit code 128 + the signal and one line on stderr; the
    boxes tracked so far stay in the --out file, and the --video file plays them. SIGTERM and SIGHUP used to end it
    on the spot: the box file lost the lines still in its buffer (all of them, here) and the mp4 had no index."""
    frames, box = synthetic_frames(20)
    video = tmp_path / "long.mp4"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), 10, (160, 120))
    for i in range(3000):
        writer.write(frames[i % len(frames)])
    writer.release()
    out, annotated = tmp_path / "boxes.txt", tmp_path / "annotated.mp4"
    # SIGINT not ignored: a shell's background job (a suite run with `&`) hands its children SIGINT ignored
    process = subprocess.Popen([sys.executable, "-m", "tacf.cli", "track", str(video), "--box",
                                ",".join(str(v) for v in box), "--out", str(out), "--video", str(annotated)],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and process.poll() is None and \
                (not out.exists() or out.read_text().count("\n") < 10):
            time.sleep(0.05)
        process.send_signal(stop_signal)
        _, err = process.communicate(timeout=20)
    finally:
        process.kill()
    assert process.returncode == exit_code, err
    assert "Traceback" not in err and err.splitlines()[-1] == "tacf track: interrupted"
    lines = out.read_text().count("\n")
    assert 10 <= lines < 3001
    # the header, then a line per frame drawn; the signal may fall between the last frame's line and its drawing
    assert cv2.VideoCapture(str(annotated)).get(cv2.CAP_PROP_FRAME_COUNT) in (lines - 1, lines - 2)


def test_the_commit_recorded_is_the_checkout_s_and_says_when_it_was_changed(tmp_path):
    from tacf.eval.provenance import source_commit

    assert source_commit(tmp_path) is None                          # not a checkout (an installed wheel)
    (tmp_path / "tacf").mkdir()
    (tmp_path / "tacf" / "a.py").write_text("x = 1\n")
    git = ["git", "-C", str(tmp_path), "-c", "user.name=t", "-c", "user.email=t@t"]
    subprocess.run(git + ["init", "-q"], check=True)
    subprocess.run(git + ["add", "."], check=True)
    subprocess.run(git + ["commit", "-q", "-m", "a"], check=True)
    head = subprocess.run(git + ["rev-parse", "HEAD"], check=True, capture_output=True, text=True).stdout.strip()
    assert source_commit(tmp_path) == head
    (tmp_path / "notes.txt").write_text("untracked files do not count\n")
    assert source_commit(tmp_path) == head
    (tmp_path / "tacf" / "a.py").write_text("x = 2\n")
    assert source_commit(tmp_path) == head + "+dirty"


# --- tacf bench tracker -------------------------------------------------------------------------------------
def test_bench_tracker_names_an_image_it_cannot_read(tmp_path, caplog):
    data = write_synthetic_dataset(tmp_path, 4)
    broken = sorted((data / "synthetic" / "drift" / "img").iterdir())[2]
    broken.write_text("not a PNG")
    assert main(["bench", "tracker", str(data), "--sequences", "*", "--trackers", "identity"]) == 1
    assert f"identity on synthetic/drift failed: FileNotFoundError: cannot read image {broken}" in caplog.text


def test_bench_tracker_records_a_pair_that_fails_and_measures_the_others(tmp_path, caplog):
    """A sequence no tracker can start on (a NaN first box) ended the benchmark with a traceback."""
    data = write_synthetic_dataset(tmp_path, 4)
    shutil.copytree(data / "synthetic" / "drift", data / "nan_first")
    truth = data / "nan_first" / "groundtruth.txt"
    truth.write_text("nan,nan,nan,nan\n" + "".join(truth.read_text().splitlines(keepends=True)[1:]))
    out = tmp_path / "bench.json"
    assert main(["bench", "tracker", str(data), "--sequences", "*", "--trackers", "identity", "--json", str(out),
                 "--no-progress"]) == 1
    report = json.loads(out.read_text())
    assert report["interrupted"] is False
    for tracker in (report, report["peers"]["opencv-csrt"]):
        assert list(tracker["sequences"]) == ["synthetic/drift"] and tracker["frames"] == 4
        assert tracker["failed"] == {"nan_first": "ValueError: nan_first: the first ground-truth box "
                                                  "[nan, nan, nan, nan] cannot start a track"}
    assert "identity on nan_first failed: ValueError" in caplog.text
    assert "2 (tracker, sequence) pairs failed" in caplog.text


def _bench_on_two_sequences(tmp_path, monkeypatch, make) -> tuple[int, dict]:
    """`tacf bench tracker --trackers identity --json` on two synthetic sequences, each tracker (CSRT too) made by
    `make`; its exit code and report."""
    from tacf.eval import bench, runner

    data = write_synthetic_dataset(tmp_path, 4)
    shutil.copytree(data / "synthetic" / "drift", data / "synthetic" / "second")
    for module in (bench, runner):
        monkeypatch.setattr(module, "make_tracker", make)
    monkeypatch.setattr(runner, "_warmed_up", set())
    out = tmp_path / "bench.json"
    code = main(["bench", "tracker", str(data), "--sequences", "*", "--trackers", "identity", "--json", str(out),
                 "--no-progress"])
    return code, json.loads(out.read_text())


def test_ctrl_c_in_bench_tracker_writes_the_report_of_the_pairs_finished(tmp_path, monkeypatch, capsys):
    """A Ctrl-C on the second sequence threw away the first one's measurement (no report at all, exit 130)."""
    made = []

    class CtrlCOnItsThirdRun(trackers.IdentityTracker):   # the warm-up, the first sequence, then the second
        def update(self, frame):
            if len(made) == 3:
                signal.raise_signal(signal.SIGINT)
            return super().update(frame)

    def make(name):
        if name != "identity":
            return trackers.make_tracker(name)
        made.append(name)
        return CtrlCOnItsThirdRun(name)

    code, report = _bench_on_two_sequences(tmp_path, monkeypatch, make)
    assert code == 130 and "tacf bench: interrupted" in capsys.readouterr().err
    assert report["interrupted"] is True and len(made) == 3
    for tracker in (report, report["peers"]["opencv-csrt"]):
        assert list(tracker["sequences"]) == ["synthetic/drift"] and tracker["frames"] == 4
    assert report["ratio_to_opencv-csrt"] > 0


def test_bench_tracker_puts_side_by_side_the_speeds_over_the_same_sequences(tmp_path, monkeypatch, caplog):
    """A Ctrl-C during CSRT's second sequence: the subject's fps covered both sequences, CSRT's the first only, and
    the log printed the two side by side, while the ratio divided the speeds over the first only. Here the
    subject is slow on the second sequence, so its fps over both is not its fps over the first."""
    caplog.set_level(logging.INFO)
    made = []

    class SlowOnTheSecond(trackers.IdentityTracker):   # the warm-up, the first sequence, then the second
        def update(self, frame):
            time.sleep(0.02 if made.count("identity") == 3 else 0.002)
            return super().update(frame)

    class CtrlCOnTheSecond(trackers.IdentityTracker):
        def update(self, frame):
            if made.count("opencv-csrt") == 3:
                signal.raise_signal(signal.SIGINT)
            return super().update(frame)

    def make(name):
        made.append(name)
        return (SlowOnTheSecond if name == "identity" else CtrlCOnTheSecond)(name)

    code, report = _bench_on_two_sequences(tmp_path, monkeypatch, make)
    assert code == 130
    assert list(report["sequences"]) == ["synthetic/drift", "synthetic/second"]
    assert list(report["peers"]["opencv-csrt"]["sequences"]) == ["synthetic/drift"]
    over = report["ratio_over"]
    assert over["sequences"] == ["synthetic/drift"] and over["fps"] == report["sequences"]["synthetic/drift"]["fps"]
    assert over["peer_fps"] == report["peers"]["opencv-csrt"]["fps"]
    assert report["ratio_to_opencv-csrt"] == pytest.approx(over["fps"] / over["peer_fps"])
    assert report["fps"] < over["fps"] / 2, "the second sequence is slower"
    assert (f"identity: {report['fps']:.1f} fps on {report['cores']:.2f} cores over its 2 sequences; over the 1 it "
            f"and opencv-csrt both finished, {over['fps']:.1f} against {over['peer_fps']:.1f} fps "
            f"({report['ratio_to_opencv-csrt']:.2f}x)") in caplog.text


@pytest.mark.parametrize("interrupted", ["identity", "opencv-csrt"])
def test_bench_tracker_log_gives_no_nan_speed_when_a_tracker_finished_nothing(tmp_path, monkeypatch, caplog,
                                                                              interrupted):
    """A Ctrl-C in the first sequence timed (a newcomer stopping a long bench early) logged "tacf: nan fps on nan
    cores (opencv-csrt nan fps, nanx)": speeds and a ratio where nothing was measured."""
    caplog.set_level(logging.INFO)
    made = []

    class CtrlCOnItsFirstTimedRun(trackers.IdentityTracker):   # after its warm-up run
        def update(self, frame):
            if made.count(interrupted) == 2:
                signal.raise_signal(signal.SIGINT)
            return super().update(frame)

    def make(name):
        made.append(name)
        return CtrlCOnItsFirstTimedRun(name)

    code, report = _bench_on_two_sequences(tmp_path, monkeypatch, make)
    assert code == 130 and report["ratio_to_opencv-csrt"] is None
    line = next(r.getMessage() for r in caplog.records if "wrote" in r.getMessage())
    assert "nan" not in line and "no ratio to opencv-csrt" in line, line
    assert ("identity: no sequence finished" in line) == (interrupted == "identity"), line


@needs_data
def test_sigterm_in_bench_tracker_writes_the_report_of_the_pairs_finished(tmp_path):
    """`timeout 300 tacf bench tracker --json OUT`: its SIGTERM ended the command on the spot, without a report (the
    sequences measured so far lost, as they were on Ctrl-C); now as on Ctrl-C, with exit code 143."""
    out, log_file = tmp_path / "bench.json", tmp_path / "stderr.txt"
    with log_file.open("w") as err:
        process = subprocess.Popen([sys.executable, "-m", "tacf.cli", "bench", "tracker", str(SEQUENCES),
                                    "--max-frames", "30", "--json", str(out), "--no-progress"], stderr=err)
    try:
        deadline = time.monotonic() + 120
        while "opencv-csrt" not in log_file.read_text() and process.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)    # until both trackers have timed the first sequence
        process.send_signal(signal.SIGTERM)
        process.wait(timeout=30)
    finally:
        process.kill()
    assert process.returncode == 143, log_file.read_text()
    assert "tacf bench: interrupted" in log_file.read_text()
    report = json.loads(out.read_text())
    assert report["interrupted"] is True and 1 <= len(report["peers"]["opencv-csrt"]["sequences"]) < 10


def test_bench_tracker_json_is_strict_json_when_a_tracker_has_no_speed(tmp_path):
    """A tracker that failed on every sequence has no fps nor cores, and the ratio none either: they were written
    as NaN, which json.loads takes but strict readers (jq, JavaScript's JSON.parse) refuse; summary.json writes
    null there."""
    data = write_synthetic_dataset(tmp_path, 6)
    truth = data / "synthetic" / "drift" / "groundtruth.txt"
    rows = truth.read_text().splitlines(keepends=True)
    truth.write_text("NaN,NaN,NaN,NaN\n" + "".join(rows[1:]))    # UAV123's absent target
    out = tmp_path / "bench.json"
    assert main(["bench", "tracker", str(data), "--sequences", "*", "--trackers", "identity", "--max-frames", "3",
                 "--json", str(out), "--no-progress"]) == 1

    def refuse(constant):
        raise ValueError(f"{constant} is not JSON")

    report = json.loads(out.read_text(), parse_constant=refuse)
    assert report["fps"] is None and report["cores"] is None and report["ratio_to_opencv-csrt"] is None
    assert list(report["failed"]) == ["synthetic/drift"]


def test_bench_tracker_reports_a_tracker_that_finished_nothing_with_the_same_keys(tmp_path, monkeypatch):
    """A tracker with no sequence finished was reported as {"fps": null, "frames": 0} and no `ms_per_frame` nor
    `seconds`: a script reading every tracker's p95 met a KeyError on that one."""
    from tacf.eval import bench, runner

    class CannotStart(trackers.IdentityTracker):
        def init(self, frame, box):
            raise ValueError("cannot start")

    def make(name):
        return CannotStart(name) if name == "identity" else trackers.make_tracker(name)

    for module in (bench, runner):
        monkeypatch.setattr(module, "make_tracker", make)
    monkeypatch.setattr(runner, "_warmed_up", set())
    out = tmp_path / "bench.json"
    assert main(["bench", "tracker", str(write_synthetic_dataset(tmp_path, 4)), "--sequences", "*", "--trackers",
                 "identity", "--json", str(out), "--no-progress"]) == 1
    report = json.loads(out.read_text())
    csrt = report["peers"]["opencv-csrt"]
    assert csrt["frames"] == 4 and set(csrt) <= set(report), (set(csrt) - set(report))
    assert report["frames"] == 0 and report["seconds"] == 0 and report["fps"] is None
    assert report["ms_per_frame"] == {"p50": None, "p95": None, "mean": None}
    assert list(report["failed"]) == ["synthetic/drift"] and report["sequences"] == {}


def test_bench_tracker_decodes_a_frame_when_the_tracker_needs_it(tmp_path, monkeypatch):
    """Each sequence was decoded whole before it was timed: 2.7 MB a 720p frame, 5,000 frames in a UAV20L one.
    Here the frames alive (decoded, not yet freed) are counted at every tracker call."""
    from tacf.eval import bench, runner

    decoded = []   # weak references to every frame decoded
    imread = cv2.imread
    monkeypatch.setattr(cv2, "imread", lambda *args: decoded.append(weakref.ref(frame := imread(*args))) or frame)
    alive_at_calls = []

    class CountsFramesAlive(trackers.IdentityTracker):
        def init(self, frame, box):
            alive_at_calls.append(sum(ref() is not None for ref in decoded))
            super().init(frame, box)

        def update(self, frame):
            alive_at_calls.append(sum(ref() is not None for ref in decoded))
            return super().update(frame)

    for module in (bench, runner):
        monkeypatch.setattr(module, "make_tracker", CountsFramesAlive)
    sequences = load_sequences(write_synthetic_dataset(tmp_path, 12))
    report = bench.bench(["identity"], sequences, progress=False)
    assert report["frames"] == 12 and len(decoded) >= 12
    assert max(alive_at_calls) <= 3   # the first frame (the init's), the one before, the one tracked


def test_bench_tracker_on_a_root_without_uav_names_says_how_to_choose_its_sequences(tmp_path, caplog):
    data = write_synthetic_dataset(tmp_path, 4)          # as the official DTB70 root: its names lack "DTB70/"
    assert main(["bench", "tracker", str(data), "--trackers", "identity"]) == 2
    assert "none of the 1 sequences of" in caplog.text and "--sequences chooses others" in caplog.text
    assert main(["bench", "tracker", str(data), "--trackers", "identity", "--sequences", "*",
                 "--json", str(tmp_path / "b.json")]) == 0
    with pytest.raises(SystemExit) as refused:          # a folder, refused before the run it would lose
        main(["bench", "tracker", str(data), "--sequences", "*", "--json", str(tmp_path)])
    assert refused.value.code == 2


def test_cores_count_the_cpu_time_of_the_tracker_calls_only():
    """Frames are decoded between the tracker calls now: that CPU time is no tracker's."""
    def decoded_at_a_cpu_cost(frames):
        for frame in frames:
            end = time.process_time() + 0.02
            while time.process_time() < end:
                pass
            yield frame

    class Sleeps(trackers.IdentityTracker):   # wall time, next to no CPU time
        def update(self, frame):
            time.sleep(0.02)
            return super().update(frame)

    frames, box = synthetic_frames(6)
    run = track_frames(Sleeps(), decoded_at_a_cpu_cost(frames), box)
    assert run.cpu_seconds < 0.3 * run.times.sum()


@pytest.mark.parametrize("frames", ["0", "-5"])
def test_bench_tracker_refuses_max_frames_under_one(frames, capsys, tmp_path):
    with pytest.raises(SystemExit) as refused:
        main(["bench", "tracker", str(write_synthetic_dataset(tmp_path, 6)), "--sequences", "*",
              "--trackers", "identity", "--max-frames", frames])
    assert refused.value.code == 2
    captured = capsys.readouterr()
    assert captured.out == ""                            # no report of 1 (= 6 - 5) frame at a negative fps
    assert f"argument --max-frames: '{frames}': expected an integer >= 1" in captured.err


@needs_data
def test_bench_tracker_json(tmp_path, capsys):
    out = tmp_path / "bench.json"
    rc = main(["bench", "tracker", str(SEQUENCES), "--sequences", "UAV123_10fps/wakeboard7",
               "--trackers", "opencv-kcf", "--max-frames", "10", "--json", str(out)])
    assert rc == 0 and "bench: 100%" in capsys.readouterr().err
    assert main(["bench", "tracker", str(SEQUENCES), "--sequences", "UAV123_10fps/wakeboard7",
                 "--trackers", "opencv-kcf", "--max-frames", "10", "--json", str(out), "--no-progress"]) == 0
    assert "bench:" not in capsys.readouterr().err
    r = json.loads(out.read_text())
    assert r["tracker"] == "opencv-kcf" and r["fps"] > 0 and r["frames"] == 10
    assert set(r["ms_per_frame"]) >= {"p50", "p95"} and r["ms_per_frame"]["p95"] >= r["ms_per_frame"]["p50"]
    assert r["peers"]["opencv-csrt"]["fps"] > 0 and r["peers"]["opencv-csrt"]["frames"] == 10
    assert r["sequences"]["UAV123_10fps/wakeboard7"]["frames"] == 10
    assert r["opencv"] == r["run"]["opencv"] == cv2.__version__
    assert r["run"]["arguments"]["trackers"] == ["opencv-kcf"] and r["run"]["arguments"]["max_frames"] == 10
    assert 0 < r["cores"] < 1.5 and 0 < r["peers"]["opencv-csrt"]["cores"] < 1.5, "one core each"


@pytest.fixture
def slow_first_init(monkeypatch):
    """The tracker factory of bench and eval makes, for any name, a tracker whose first init in the process is
    slow (a JIT loading, say); no tracker counts as run in this process yet."""
    from tacf.eval import bench, runner

    class FirstInitIsSlow(trackers.IdentityTracker):
        process_started = False

        def init(self, frame, box):
            if not FirstInitIsSlow.process_started:
                FirstInitIsSlow.process_started = True
                time.sleep(0.5)
            super().init(frame, box)

    for module in (bench, runner):
        monkeypatch.setattr(module, "make_tracker", lambda name: FirstInitIsSlow(name))
    monkeypatch.setattr(runner, "_warmed_up", set(), raising=False)


def test_bench_tracker_does_not_charge_a_process_s_first_init_to_a_sequence(slow_first_init, tmp_path):
    """A tracker whose first init in the process is slow is timed at its per-stream speed."""
    from tacf.eval import bench

    sequences = load_sequences(write_synthetic_dataset(tmp_path, 8))
    report = bench.bench(["slow-start"], sequences, max_frames=5)
    assert report["frames"] == 5 and report["seconds"] < 0.1


def test_eval_does_not_charge_a_process_s_first_init_to_a_sequence(slow_first_init, tmp_path):
    """The first sequence of each tracker in an eval process was charged what the process pays once: tacf's
    first init there took 1.06 s (numba loading the compiled fHOG), and truck2 scored 46.5 fps beside
    wakeboard7's 100.8."""
    from tacf.eval.runner import pending_jobs, run_jobs

    sequences = load_sequences(write_synthetic_dataset(tmp_path, 20))
    [outcome] = run_jobs(pending_jobs(["slow-start"], sequences, tmp_path / "out"), progress=False)
    assert outcome.error is None and outcome.frames == 20 and outcome.seconds < 0.25


def test_console_script_lists_subcommands():
    out = subprocess.run([sys.executable, "-m", "tacf.cli", "--help"], capture_output=True, text=True, check=True)
    assert all(cmd in out.stdout for cmd in ("eval", "track", "bench"))


# --- the TACF path ------------------------------------------------------------------------------------------
@needs_tacf
@pytest.mark.parametrize("name", ["tacf", "kcc", "kcc+sa+da"])
def test_tacf_adapter(name):
    frames, box = synthetic_frames(8)
    run = track_frames(trackers.make_tracker(name), frames, box)
    assert run.boxes.shape == (8, 4) and np.isfinite(run.boxes).all()
    assert np.isfinite(run.pme[1:]).all()
    assert run.boxes[-1, 0] == pytest.approx(box[0] + 14, abs=4)


@needs_tacf
@needs_data
def test_eval_and_track_with_tacf(tmp_path):
    rc = main(["eval", str(SEQUENCES), "--sequences", "UAV123_10fps/wakeboard7", "--trackers", "tacf,kcc",
               "--max-frames", "15", "--out", str(tmp_path), "--no-progress"])
    assert rc == 0
    summary = json.loads((tmp_path / "summary.json").read_text())
    for name in ("tacf", "kcc"):
        t = summary["trackers"][name]
        assert t["frames"] == 15 and 0.3 <= t["auc"] <= 1 and t["fps"] > 0
    folder = tmp_path / "img"
    folder.mkdir()
    for p in sorted((SEQUENCES / "UAV123_10fps" / "wakeboard7" / "img").iterdir())[:10]:
        (folder / p.name).symlink_to(p)
    rc = main(["track", str(folder), "--box", "622,298,11,38", "--profile", "kcc", "--out", str(tmp_path / "b.txt")])
    assert rc == 0
    rows = check_boxes_file(tmp_path / "b.txt", 10, (622, 298, 11, 38))
    assert np.isfinite(rows[1:, 4]).all()


# --- the ablation table ---------------------------------------------------------------------------------------
def test_ablation_table_rows_and_gains():
    from tacf.eval.report import ablation_table

    def entry(*aucs):
        return {"auc": float(np.mean(aucs)), "precision20": 0.5, "fps": 100.0, "frames": 10,
                "sequences": {f"s{i}": {"auc": a} for i, a in enumerate(aucs)}}

    summary = {"trackers": {"kcc": entry(*[0.40] * 5), "kcc+sa": entry(0.44, 0.46), "kcc+da": entry(*[0.38] * 5),
                            "kcc+ca": entry(*[0.42] * 5), "tacf-authors": entry(0.60, 0.40, 0.40, 0.40, 0.40),
                            "tacf": entry(*[0.45] * 5)}}
    lines = ablation_table(summary).splitlines()
    assert [line.split("|")[2].strip() for line in lines[2:]] == list(trackers.ABLATION)
    assert "| +0.050 | +12.5% (no interval: under 5 sequences) |" in lines[3], lines[3]   # s0, s1 only
    assert "| -0.020 | -5.0% (-5.0% to -5.0%) |" in lines[4], lines[4]
    # all of it from s0: none in 33 % of the resamples, three or more times in 5.8 %
    assert "| +0.040 | +10.0% (+0.0% to +30.0%) |" in lines[6], lines[6]
    assert "| +0.050 | +12.5% (+12.5% to +12.5%) |" in lines[7], lines[7]


def test_relative_gain_and_its_interval():
    from tacf.eval.report import relative_gain

    assert relative_gain([0.5] * 5, [0.4] * 5) == pytest.approx((0.25, 0.25, 0.25))
    gain, low, high = relative_gain([0.9, 0.4, 0.4, 0.4, 0.4], [0.4] * 5)
    assert gain == pytest.approx(0.25) and low == pytest.approx(0.0) and high > 0.6   # one sequence carries it
    # over four sequences a bootstrap has too few resamples to tell anything: no interval
    gain, low, high = relative_gain([0.9, 0.4, 0.4, 0.4], [0.4] * 4)
    assert gain == pytest.approx(0.3125) and np.isnan(low) and np.isnan(high)


def test_robustness_of_hand_made_scores():
    from tacf.eval.report import robustness, robustness_table

    def summary(aucs_a, aucs_b):
        sequences = lambda aucs: {"sequences": {f"s{i}": {"auc": a} for i, a in enumerate(aucs)}}  # noqa: E731
        return {"trackers": {"a": sequences(aucs_a), "b": sequences(aucs_b)}}

    aucs = {"+0,+0": ([0.5, 0.6, 0.7], [0.4, 0.6, 0.9]),
            "+1,+0": ([0.2, 0.6, 0.7], [0.2, 0.5, 0.8]),
            "-1,+0": ([0.5, 0.3, 0.7], [0.5, 0.3, 0.7])}
    per_start = {start: summary(a, b) for start, (a, b) in aucs.items()}
    result = robustness(per_start, ["a", "b"])
    assert result["starts"] == ["+0,+0", "+1,+0", "-1,+0"] and result["sequences"] == 3
    a, b = result["trackers"]["a"], result["trackers"]["b"]
    np.testing.assert_allclose(a["auc_per_start"], [0.6, 0.5, 0.5])
    assert (a["mean"], a["min"], a["max"]) == pytest.approx((1.6 / 3, 0.5, 0.6)) and "difference" not in a
    # b - a per sequence, over the starts: (-0.1 + 0 + 0) / 3, (0 - 0.1 + 0) / 3, (0.2 + 0.1 + 0) / 3
    assert b["difference"]["to"] == "a" and b["difference"]["mean"] == pytest.approx(0.1 / 9)
    assert np.isnan(b["difference"]["ci95"]).all()   # three sequences are too few for an interval
    table = robustness_table(result)
    assert table.startswith("Robustness: first box moved by (dx,dy) = (+0,+0), (+1,+0), (-1,+0) pixels; 3 seq")
    assert "| b | 0.633 | 0.544 | 0.500 - 0.633 | +0.011 (no interval: under 5 sequences) |" in table
    # five sequences: an interval, within the range of the per-sequence differences (-0.1 / 3 to +0.1)
    five = {start: summary(a + [a[0], a[2]], b + [b[0], b[2]]) for start, (a, b) in aucs.items()}
    low, high = robustness(five, ["a", "b"])["trackers"]["b"]["difference"]["ci95"]
    assert -0.1 / 3 - 1e-12 <= low < high <= 0.1 + 1e-12
    assert f"({low:+.3f} to {high:+.3f}) |" in robustness_table(robustness(five, ["a", "b"]))
    # each sequence's mean over the starts, in summary.json and as a table after the trackers'
    assert b["per_sequence"] == pytest.approx({"s0": 1.1 / 3, "s1": 1.4 / 3, "s2": 2.4 / 3})
    assert table.split("Success AUC per sequence, the mean over the 3 starts:\n\n")[1].splitlines() == [
        "| sequence | a | b |", "|---|---|---|", "| s0 | 0.400 | 0.367 |", "| s1 | 0.500 | 0.467 |",
        "| s2 | 0.700 | 0.800 |"]
    temporal = robustness_table(robustness({"0/3": per_start["+0,+0"], "1/3": per_start["+1,+0"]}, ["a"], "tre"))
    assert temporal.startswith("Temporal robustness: runs started at (0/3), (1/3) of each sequence; 3 sequences")


def test_temporal_starts_begin_at_the_segments_first_usable_box():
    from tacf.eval.datasets import Sequence
    from tacf.eval.runner import Start, temporal_starts

    gt = np.tile([10.0, 10.0, 5.0, 5.0], (20, 1))
    gt[10:13] = np.nan                      # target absent at frames 10-12
    gt[15, 2] = 0.0                         # a zero-width box cannot start a track
    seq = Sequence("s", [Path(f"{i}.jpg") for i in range(20)], gt)
    starts = temporal_starts(4)
    assert [s.label for s in starts] == ["0/4", "1/4", "2/4", "3/4"] and starts[0] == Start(segment=0, segments=4)
    parts = [s.sequence(seq) for s in starts]
    assert parts[0] is seq
    # frames 0, 5, 10 -> 13 (the first box after the gap), 15 -> 16
    assert [p.frames[0].name for p in parts] == ["0.jpg", "5.jpg", "13.jpg", "16.jpg"]
    assert [len(p) for p in parts] == [20, 15, 7, 4] and np.array_equal(parts[2].gt, gt[13:])
    # no frame to track after frame 19: from the last box that leaves two frames, so that s stays in the report
    assert Start(segment=19, segments=20).sequence(seq).frames[0].name == "18.jpg"
    tail_absent = Sequence("t", seq.frames, np.vstack([gt[:14], np.full((6, 4), np.nan)]))
    assert [p.frames[0].name for p in map(lambda s: s.sequence(tail_absent), starts)] == ["0.jpg", "5.jpg", "13.jpg",
                                                                                          "13.jpg"]
    assert Start(segment=1, segments=4).sequence(Sequence("u", seq.frames[:1], gt[:1])) is None
    assert Start(segment=1, segments=4).directory(Path("out")) == Path("out/tre/1of4")
    assert starts[0].directory(Path("out")) == Path("out")


def write_synthetic_dataset(root: Path, n: int) -> Path:
    """synthetic_frames as a generic-layout dataset under root/data: one sequence, synthetic/drift."""
    frames, _ = synthetic_frames(n)
    seq = root / "data" / "synthetic" / "drift"
    (seq / "img").mkdir(parents=True)
    for i, f in enumerate(frames, 1):
        cv2.imwrite(str(seq / "img" / f"{i:06d}.png"), f)
    (seq / "groundtruth.txt").write_text("".join(f"{31 + 2 * i},{41 + i},24,24\n" for i in range(n)))
    return root / "data"


def test_eval_shifts_command(tmp_path, capsys):
    out = tmp_path / "out"
    args = ["eval", str(write_synthetic_dataset(tmp_path, 6)), "--trackers", "identity,opencv-mosse",
            "--out", str(out), "--no-progress"]
    with pytest.raises(SystemExit) as refused:          # a usage error, before the sequences are loaded
        main(args + ["--shifts", "-1"])
    assert refused.value.code == 2 and "argument --shifts: '-1': expected an integer >= 0" in capsys.readouterr().err
    assert main(args + ["--shifts", "2"]) == 0
    first_lines = {start.name: (start / "identity" / "synthetic" / "drift.txt").read_text().splitlines()[0]
                   for start in (out / "shifted").iterdir()}
    assert len(first_lines) == 8 and first_lines["+2+0"] == "33.000,41.000,24.000,24.000"
    assert first_lines["-2+2"] == "29.000,43.000,24.000,24.000"
    assert (out / "identity" / "synthetic" / "drift.txt").read_text().startswith("31.000,41.000,")
    robust = json.loads((out / "summary.json").read_text())["robustness"]
    assert len(robust["starts"]) == 9 and robust["sequences"] == 1
    assert robust["trackers"]["opencv-mosse"]["difference"]["to"] == "identity"
    table = "Robustness: first box moved by (dx,dy) = (+0,+0), (-2,-2),"
    assert table in capsys.readouterr().out and table in (out / "summary.md").read_text()
    assert (out / "robustness_plot.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_eval_tre_command(tmp_path, capsys):
    out = tmp_path / "out"
    args = ["eval", str(write_synthetic_dataset(tmp_path, 8)), "--trackers", "identity,opencv-mosse",
            "--out", str(out), "--no-progress"]
    with pytest.raises(SystemExit) as refused:          # a usage error: one segment is the one-pass run
        main(args + ["--tre", "1"])
    assert refused.value.code == 2
    assert main(args + ["--tre", "4", "--shifts", "1"]) == 0
    # segment i of 4 starts at frame 2 i, from the ground-truth box there: 31 + 2 * 2 i, 41 + 2 i
    for i in (1, 2, 3):
        rows = (out / "tre" / f"{i}of4" / "identity" / "synthetic" / "drift.txt").read_text().splitlines()
        assert len(rows) == 8 - 2 * i and rows[0] == f"{31 + 4 * i:.3f},{41 + 2 * i:.3f},24.000,24.000"
    assert len(list((out / "shifted").iterdir())) == 8     # both protocols; the one-pass runs serve both
    summary = json.loads((out / "summary.json").read_text())
    temporal = summary["temporal_robustness"]
    assert temporal["protocol"] == "tre" and temporal["starts"] == ["0/4", "1/4", "2/4", "3/4"]
    assert summary["robustness"]["protocol"] == "shifts" and len(summary["robustness"]["starts"]) == 9
    # identity keeps the start box: its AUC only falls with the time left to drift away in
    identity = temporal["trackers"]["identity"]["auc_per_start"]
    assert identity == sorted(identity) and identity[0] == summary["trackers"]["identity"]["auc"]
    # OTB's TRE weighs each start by the frames it scored: 8, 6, 4 and 2 of the one sequence
    assert temporal["trackers"]["identity"]["otb_pooled"]["auc"] == pytest.approx(np.dot(identity, [8, 6, 4, 2]) / 20)
    assert "otb_pooled" not in summary["robustness"]["trackers"]["identity"]
    printed = capsys.readouterr().out
    for text in (printed, (out / "summary.md").read_text()):
        assert "Temporal robustness: runs started at (0/4), (1/4), (2/4), (3/4)" in text and "Robustness: first" in text
        assert "OTB's TRE, pooled: AUC / precision@20" in text
    assert (out / "temporal_robustness_plot.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / "robustness_plot.png").is_file()
    # 7 frames start the segments at frames 1, 3, 5: the results of 6, 4 and 2 rows from frames 2, 4, 6 are not theirs
    assert main(args + ["--tre", "4", "--max-frames", "7"]) == 0
    for i in (1, 2, 3):
        first = 2 * i - 1
        rows = (out / "tre" / f"{i}of4" / "identity" / "synthetic" / "drift.txt").read_text().splitlines()
        assert len(rows) == 7 - first and rows[0] == f"{31 + 2 * first:.3f},{41 + first:.3f},24.000,24.000"


def test_shifted_start_boxes_stay_in_the_frame():
    from tacf.eval.runner import shifted_box

    assert shifted_box([5.0, 3.0, 10.0, 8.0], (1, -1), (20, 30)).tolist() == [6.0, 2.0, 10.0, 8.0]
    assert shifted_box([0.5, 0.0, 10.0, 8.0], (-1, -1), (20, 30)).tolist() == [0.0, 0.0, 10.0, 8.0]
    assert shifted_box([25.0, 15.0, 10.0, 8.0], (1, 1), (20, 30)).tolist() == [26.0, 16.0, 4.0, 4.0]
    with pytest.raises(ValueError, match=r"moved by \(6, 0\) lies outside the 30x20 frame"):
        shifted_box([25.0, 15.0, 10.0, 8.0], (6, 0), (20, 30))


@needs_tacf
def test_eval_shifts_off_the_image_fail_clearly(tmp_path, caplog):
    data = write_synthetic_dataset(tmp_path, 3)
    rc = main(["eval", str(data), "--trackers", "kcc", "--out", str(tmp_path / "out"), "--shifts", "500",
               "--no-progress"])
    assert rc == 1  # 7 shifted starts leave the 160 x 120 frames; the given start still runs
    assert "moved by (500, 500) lies outside the 160x120 frame" in caplog.text
    # (-500, -500) is kept in the frame, at its top left corner, as OTB's shiftInitBB keeps it
    assert (tmp_path / "out" / "shifted" / "-500-500" / "kcc" / "synthetic" / "drift.txt").read_text().startswith(
        "1.000,1.000,24.000,24.000")
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["trackers"]["kcc"]["sequences"] and summary["robustness"]["sequences"] == 0


@needs_tacf
def test_eval_ablation_command(tmp_path, capsys):
    data = write_synthetic_dataset(tmp_path, 8)
    rc = main(["eval", "--ablation", str(data), "--out", str(tmp_path / "out"), "--no-progress"])
    assert rc == 0
    out = capsys.readouterr().out
    assert "KCC (baseline)" in out and "TACF (SA + DA + CA)" in out
    assert out.startswith((tmp_path / "out" / "ablation.md").read_text())  # then the lost-flag table
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert sorted(summary["trackers"]) == sorted(trackers.ABLATION) == sorted(summary["lost_flag"]["trackers"])
    assert all(t["sequences"]["synthetic/drift"]["auc"] > 0.5 for t in summary["trackers"].values())


# --- tacf eval --results: result folders other toolkits wrote ----------------------------------------------------
def test_eval_scores_result_folders_in_other_toolkits_layouts(tmp_path, capsys):
    n = 6
    data = write_synthetic_dataset(tmp_path, n)
    gt_lines = (data / "synthetic" / "drift" / "groundtruth.txt").read_text()
    gt = np.loadtxt(data / "synthetic" / "drift" / "groundtruth.txt", delimiter=",")
    ours = tmp_path / "ours"  # our layout and got10k's: the sequence's path, times/ beside
    (ours / "synthetic").mkdir(parents=True)
    (ours / "synthetic" / "drift.txt").write_text(gt_lines)
    (ours / "times" / "synthetic").mkdir(parents=True)
    (ours / "times" / "synthetic" / "drift_time.txt").write_text("0.5\n" * n)
    flat = tmp_path / "flat"  # pysot's OPE layout, pytracking's tab-separated integers
    flat.mkdir()
    (flat / "drift.txt").write_text("".join(f"{x + 12:.0f}\t{y:.0f}\t24\t24\n" for x, y, _, _ in gt))
    vot = tmp_path / "vot"  # pysot's VOT layout, got10k's GOT-10k layout with its times of 2 repetitions
    (vot / "drift").mkdir(parents=True)
    (vot / "drift" / "drift_001.txt").write_text("".join(f"{x},{y + 6},24,24\n" for x, y, _, _ in gt))
    (vot / "drift" / "drift_time.txt").write_text("0.25000000,0.50000000\n" * n)
    out = tmp_path / "out"
    rc = main(["eval", str(data), "--results", f"ours={ours}", "--results", f"flat={flat}", "--results",
               f"vot={vot}", "--out", str(out), "--no-progress"])
    assert rc == 0
    scored = json.loads((out / "summary.json").read_text())["trackers"]
    assert list(scored) == ["ours", "flat", "vot"]
    # Read in the ground truth's own pixel frame: IoU 1 passes 20 of the 21 thresholds (IoU > 1 never holds);
    # one pixel off would pass 19. 12 px to the side is IoU 1/3 (7 thresholds), 6 px down IoU 0.6 (12).
    assert scored["ours"]["auc"] == pytest.approx(20 / 21) and scored["ours"]["precision20"] == 1.0
    assert scored["flat"]["auc"] == pytest.approx(7 / 21) and scored["vot"]["auc"] == pytest.approx(12 / 21)
    assert scored["ours"]["fps"] == pytest.approx(2.0) and scored["flat"]["fps"] is None
    assert scored["vot"]["fps"] == pytest.approx(4.0)
    assert all(t["frames"] == n for t in scored.values())
    assert not any((out / name).exists() for name in scored)  # nothing ran: only files were scored
    assert "| ours | 0.952 |" in capsys.readouterr().out

    # Beside trackers that run: they run, and the imported rows join their table and plots.
    rc = main(["eval", str(data), "--trackers", "identity", "--results", f"ours={ours}", "--out", str(out),
               "--no-progress"])
    assert rc == 0
    assert list(json.loads((out / "summary.json").read_text())["trackers"]) == ["identity", "ours"]
    assert (out / "identity" / "synthetic" / "drift.txt").is_file()


def test_eval_results_refused_with_the_reason(tmp_path, caplog):
    data = write_synthetic_dataset(tmp_path, 6)
    good, short, long, garbled, empty = (tmp_path / name for name in ("good", "short", "long", "garbled", "empty"))
    rows = [f"{31 + 2 * i},{41 + i},24,24\n" for i in range(6)]
    for folder, text in ((good, rows), (short, rows[:5]), (long, rows + rows[:1]), (garbled, rows[:3] + ["1\n"])):
        (folder / "synthetic").mkdir(parents=True)
        (folder / "synthetic" / "drift.txt").write_text("".join(text))
    empty.mkdir()
    args = ["eval", str(data), "--out", str(tmp_path / "out"), "--no-progress"]
    for results, says in [("good", "use NAME=DIR"), (f"={good}", "use NAME=DIR"), ("a b=" + str(good), "NAME=DIR"),
                          (f"x={tmp_path / 'nowhere'}", "is not a folder"),
                          (f"x={empty}", "has no result for 1 of the 1 sequences (synthetic/drift"),
                          (f"x={short}", "5 boxes for the 6 frames"), (f"x={long}", "7 boxes for the 6 frames"),
                          (f"x={garbled}", "expected 4 numbers")]:
        caplog.clear()
        assert main(args + ["--results", results]) == 2, results
        assert says in caplog.text, results
    caplog.clear()
    assert main(args + ["--trackers", "identity", "--results", f"identity={good}"]) == 2
    assert "the name is taken" in caplog.text
    assert main(args + ["--results", f"x={good}", "--results", f"x={good}"]) == 2
    # The first frames of a sequence asked for: a longer result file is cut to them.
    assert main(args + ["--results", f"x={long}", "--max-frames", "4"]) == 0
    assert json.loads((tmp_path / "out" / "summary.json").read_text())["trackers"]["x"]["frames"] == 4


def test_pysot_vot_layout_one_pass_results_start_with_1_and_reset_based_ones_are_refused(tmp_path, caplog):
    n = 6
    data = write_synthetic_dataset(tmp_path, n)
    rows = [f"{31 + 2 * i},{41 + i},24,24\n" for i in range(n)]
    long_term, baseline = tmp_path / "long_term", tmp_path / "baseline"
    for folder, lines in ((long_term, ["1\n"] + rows[1:]), (baseline, ["1\n", rows[1], "2\n", "0\n", "1\n", rows[5]])):
        (folder / "drift").mkdir(parents=True)
        (folder / "drift" / "drift_001.txt").write_text("".join(lines))
    out = tmp_path / "out"
    assert main(["eval", str(data), "--results", f"lt={long_term}", "--out", str(out), "--no-progress"]) == 0
    lt = json.loads((out / "summary.json").read_text())["trackers"]["lt"]
    assert lt["auc"] == pytest.approx(20 / 21) and lt["precision20"] == 1.0   # line 1 is the first ground truth
    assert main(["eval", str(data), "--results", f"vot={baseline}", "--out", str(out), "--no-progress"]) == 2
    assert "drift_001.txt:3: '2' marks a VOT reset" in caplog.text and "not one-pass results" in caplog.text


def test_the_matlab_toolkit_s_mat_results_are_read_under_the_tracker_s_name(tmp_path, caplog):
    from scipy.io import savemat

    n = 6
    data = write_synthetic_dataset(tmp_path, n)
    gt = np.loadtxt(data / "synthetic" / "drift" / "groundtruth.txt", delimiter=",")   # 1-based, as `res` is

    def save(path: Path, res: np.ndarray, kind: str = "rect") -> None:
        results = np.empty((1, 1), dtype=object)   # main_running.m: save(..., 'results'), results{1} = res
        results[0, 0] = {"res": res, "type": kind, "fps": 20.0, "len": n, "annoBegin": 1, "startFrame": 1}
        savemat(path, {"results": results})

    toolkit = tmp_path / "results_OPE"
    toolkit.mkdir()
    save(toolkit / "drift_TACF.mat", gt + [0, 6, 0, 0])
    save(toolkit / "drift_KCF.mat", gt)                                   # another tracker of the same folder
    out = tmp_path / "out"
    assert main(["eval", str(data), "--results", f"TACF={toolkit}", "--out", str(out), "--no-progress"]) == 0
    scored = json.loads((out / "summary.json").read_text())["trackers"]["TACF"]
    assert scored["auc"] == pytest.approx(12 / 21) and scored["fps"] == pytest.approx(20.0)   # 6 px down: IoU 0.6
    save(toolkit / "drift_IVT.mat", np.zeros((n, 6)), kind="ivtAff")
    (toolkit / "drift_BAD.mat").write_text("not a MAT file")
    # scipy's parser raises what it trips over: IndexError for 20-126 bytes of text, TypeError or OSError ("could
    # not read bytes", no file named) for a file cut short; each must come out as the file's ValueError
    (toolkit / "drift_TEXT.mat").write_text("not a MAT file, only a line of text\n")
    cut = (toolkit / "drift_KCF.mat").read_bytes()
    (toolkit / "drift_CUT.mat").write_bytes(cut[:127])
    (toolkit / "drift_CUTLATER.mat").write_bytes(cut[:200])
    refused = "not a MATLAB toolkit result"
    for name, says in (("IVT", "type 'ivtAff'; only 'rect'"), ("BAD", refused), ("TEXT", f"drift_TEXT.mat: {refused}"),
                       ("CUT", f"drift_CUT.mat: {refused}"), ("CUTLATER", f"drift_CUTLATER.mat: {refused}"),
                       ("MISSING", "<last part>_MISSING.mat")):
        caplog.clear()
        assert main(["eval", str(data), "--results", f"{name}={toolkit}", "--out", str(out), "--no-progress"]) == 2
        assert says in caplog.text, name


def test_eval_absent_option_is_recorded_and_scores_absent_frames_as_the_toolkits_do(tmp_path, capsys):
    n, jpg = 10, cv2.imencode(".jpg", np.zeros((40, 60, 3), np.uint8))[1].tobytes()
    seq = tmp_path / "data" / "s"
    (seq / "img").mkdir(parents=True)
    for i in range(1, n + 1):
        (seq / "img" / f"{i:06d}.jpg").write_bytes(jpg)
    rows = ["NaN,NaN,NaN,NaN\n" if i in (2, 3, 6, 9) else "21,21,10,10\n" for i in range(n)]
    (seq / "groundtruth.txt").write_text("".join(rows))
    (tmp_path / "perfect").mkdir()
    (tmp_path / "perfect" / "s.txt").write_text("21,21,10,10\n" * n)
    summaries = {}
    for absent in ("skip", "toolkit"):
        out = tmp_path / absent
        assert main(["eval", str(tmp_path / "data"), "--results", f"perfect={tmp_path / 'perfect'}", "--absent",
                     absent, "--out", str(out), "--no-progress"]) == 0
        summaries[absent] = json.loads((out / "summary.json").read_text())
        assert summaries[absent]["protocol"] == {"absent": absent, "absent_frames": 4, "frames": n}
        said = "Frames without a target (NaN or empty ground truth): 4 of 10, " + (
            "left out of the scores" if absent == "skip" else "counted as pysot and the OTB / UAV123 MATLAB toolkit")
        assert said in (out / "summary.md").read_text() and said in capsys.readouterr().out
    assert summaries["skip"]["trackers"]["perfect"]["auc"] == pytest.approx(20 / 21)
    assert summaries["toolkit"]["trackers"]["perfect"]["auc"] == pytest.approx(0.6 * 20 / 21)
    assert summaries["skip"]["trackers"]["perfect"]["precision20"] == 1.0
    assert summaries["toolkit"]["trackers"]["perfect"]["precision20"] == 1.0


def write_otb_two_targets(root: Path, n: int = 4) -> Path:
    """An OTB tree: Jogging with targets 1 and 2, Human4 with target 2 only (as OTB-100 ships them), Boy."""
    jpg = cv2.imencode(".jpg", np.zeros((40, 40, 3), np.uint8))[1].tobytes()
    for folder, targets in (("Jogging", (1, 2)), ("Human4", (2,)), ("Boy", (None,))):
        (root / folder / "img").mkdir(parents=True)
        for i in range(1, n + 1):
            (root / folder / "img" / f"{i:04d}.jpg").write_bytes(jpg)
        for t in targets:
            name = "groundtruth_rect.txt" if t is None else f"groundtruth_rect.{t}.txt"
            (root / folder / name).write_text(f"{5 + (t or 0)},5,10,10\n" * n)
    return root


def test_two_target_otb_results_are_found_under_got10k_s_and_pytracking_s_names(tmp_path, caplog):
    n = 4
    data = write_otb_two_targets(tmp_path / "otb", n)
    box = {"Jogging-1": "6,5,10,10\n", "Jogging-2": "7,5,10,10\n", "Human4-2": "7,5,10,10\n", "Boy": "5,5,10,10\n"}
    layouts = {"got10k": {"Jogging.1": "Jogging-1", "Jogging.2": "Jogging-2", "Human4": "Human4-2", "Boy": "Boy"},
               "pytracking": {"Jogging_1": "Jogging-1", "Jogging_2": "Jogging-2", "Human4_2": "Human4-2", "Boy": "Boy"}}
    for layout, files in layouts.items():
        (tmp_path / layout).mkdir()
        for file, seq in files.items():
            (tmp_path / layout / f"{file}.txt").write_text(box[seq] * n)
    out = tmp_path / "out"
    rc = main(["eval", str(data), "--results", f"got10k={tmp_path / 'got10k'}", "--results",
               f"pytracking={tmp_path / 'pytracking'}", "--out", str(out), "--no-progress"])
    assert rc == 0
    scored = json.loads((out / "summary.json").read_text())["trackers"]
    for layout in layouts:   # each file read for its own target: all of them on the ground truth
        assert sorted(scored[layout]["sequences"]) == ["Boy", "Human4-2", "Jogging-1", "Jogging-2"]
        assert scored[layout]["auc"] == pytest.approx(20 / 21), layout
    # A bare Jogging.txt could be either target of Jogging: not taken for one
    ambiguous = tmp_path / "ambiguous"
    ambiguous.mkdir()
    for file in ("Jogging", "Human4", "Boy"):
        (ambiguous / f"{file}.txt").write_text("5,5,10,10\n" * n)
    assert main(["eval", str(data), "--results", f"x={ambiguous}", "--out", str(out), "--no-progress"]) == 2
    assert "has no result for 2 of the 4 sequences (Jogging-1, Jogging-2;" in caplog.text


AUTHORS_OUTPUT = DATA / "reference" / "authors_tacf"


@pytest.mark.skipif(not AUTHORS_OUTPUT.is_dir() or not SEQUENCES.is_dir(), reason="../shared/data is absent")
def test_the_authors_output_scores_what_the_issue_says(tmp_path, capsys):
    """The authors' MATLAB output on the ten UAV sequences, scored as result files: mean AUC 0.491 (issue 2)."""
    rc = main(["eval", str(SEQUENCES), "--sequences", "UAV123_10fps/*,DTB70/*,UAVDT/*", "--results",
               f"authors={AUTHORS_OUTPUT}", "--out", str(tmp_path), "--no-progress"])
    assert rc == 0
    authors = json.loads((tmp_path / "summary.json").read_text())["trackers"]["authors"]
    assert len(authors["sequences"]) == 10 and authors["frames"] == 1292
    assert round(authors["auc"], 3) == 0.491 and round(authors["precision20"], 3) == 0.669


def test_eval_videos_draw_every_track_and_the_ground_truth(tmp_path):
    n, band = 8, 18 * 4 + 6  # the band above the frame: title, ground truth and two tracks
    frames, _ = synthetic_frames(n, size=(480, 360))
    seq = tmp_path / "data" / "synthetic" / "drift"
    (seq / "img").mkdir(parents=True)
    for i, f in enumerate(frames, 1):
        cv2.imwrite(str(seq / "img" / f"{i:06d}.png"), f)
    (seq / "groundtruth.txt").write_text("".join(f"{31 + 2 * i},{41 + i},24,24\n" for i in range(n)))
    still = tmp_path / "still"  # an imported track that never moves from the ground truth's first box + 200 px
    (still / "synthetic").mkdir(parents=True)
    (still / "synthetic" / "drift.txt").write_text("231,241,24,24\n" * n)
    out = tmp_path / "out"
    assert main(["eval", str(tmp_path / "data"), "--trackers", "identity", "--results", f"still={still}",
                 "--out", str(out), "--videos", "--no-progress"]) == 0
    cap = cv2.VideoCapture(str(out / "videos" / "synthetic" / "drift.mp4"))
    try:
        assert cap.get(cv2.CAP_PROP_FRAME_COUNT) == n
        assert (cap.get(cv2.CAP_PROP_FRAME_WIDTH), cap.get(cv2.CAP_PROP_FRAME_HEIGHT)) == (480, 360 + band)
        for _ in range(n):
            ok, last = cap.read()
            assert ok
    finally:
        cap.release()
    picture = last[band:].astype(int)
    blue, orange = np.array([180, 119, 31]), np.array([14, 127, 255])  # the first two plot colours, BGR
    # identity stays on the first box (30, 40); the target has drifted to (44, 47); "still" sits at (230, 240)
    assert np.abs(picture[40, 35] - blue).max() < 60          # identity's top edge
    assert (picture[47, 62] > 190).all()                      # the ground truth's top edge, white
    assert np.abs(picture[240, 240] - orange).max() < 60      # the imported track's top edge
    assert last[:band, 200:].max() < 60 and last[:band, :200].max() > 200   # the band: text on black, left


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")     # ctypes's report of the drop
@pytest.mark.parametrize("interrupted", [True, False])
def test_a_ctrl_c_that_a_ctypes_callback_drops_still_ends_the_command_as_interrupted(monkeypatch, capsys, interrupted):
    """A Ctrl-C during numba's first compile after an install lands in llvmlite's ctypes callback, which prints the
    KeyboardInterrupt and drops it; numba then fails with "RuntimeError: no compiled object yet": the command ended
    with that traceback, exit 1. Here the callback is libc's qsort's; a RuntimeError without a signal stays one."""
    import ctypes

    from tacf.eval import cli as eval_cli

    def compile_in_a_callback(args):
        def compare(a, b):
            if interrupted:
                signal.raise_signal(signal.SIGINT)      # its KeyboardInterrupt is raised in the callback, and lost
            return 0
        values = (ctypes.c_int * 2)(2, 1)
        compare_type = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p)
        ctypes.CDLL(None).qsort(values, 2, ctypes.sizeof(ctypes.c_int), compare_type(compare))
        raise RuntimeError("no compiled object yet for <Library '_fhog_images'>")
    monkeypatch.setattr(eval_cli, "cmd_track", compile_in_a_callback)
    if interrupted:
        assert main(["track", "clip.mp4", "--box", "1,2,3,4"]) == 130
        assert capsys.readouterr().err.endswith("tacf track: interrupted\n")
    else:
        with pytest.raises(RuntimeError, match="no compiled object yet"):
            main(["track", "clip.mp4", "--box", "1,2,3,4"])


def test_a_count_of_one_sequence_is_singular(tmp_path, caplog):
    """The logs said "1 sequences"."""
    caplog.set_level("INFO", logger="tacf.eval.cli")
    data = write_synthetic_dataset(tmp_path, 4)
    assert main(["bench", "tracker", str(data), "--sequences", "*", "--trackers", "identity", "--no-progress",
                 "--json", str(tmp_path / "bench.json")]) == 0
    assert "generic layout, 1 sequence matching '*'" in caplog.text
    assert "1 sequences" not in caplog.text
