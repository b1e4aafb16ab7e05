"""`tacf bench tracker`: per-stream speed of a tracker on decoded frames, with OpenCV CSRT measured alongside.

Frames are decoded one at a time, as the tracker asks for them; only init/update calls are timed
(time.perf_counter), in this one process with OpenCV limited to one thread. fps = total frames / total tracker
seconds; `cores` = the process's CPU time over the wall time of the tracker calls (1.0 is one core; more means
threads working, or spinning, on other cores). Before its first timed sequence, every tracker runs once, untimed,
on that sequence's first frames: what a process pays once (loading the compiled fHOG from numba's cache, OpenCV's
lazy set-up) is not a cost per stream, and would otherwise be charged to whichever sequence comes first.
A (tracker, sequence) pair that fails (a first box the tracker cannot start on, an image that cannot be read) is
left out of the speeds and named, with its error, under the tracker's `failed`.
A Ctrl-C ends the run with the report of the pairs finished so far, `interrupted` true.
Each tracker's fps is over the sequences it finished; the ratio to CSRT is over those both finished (`ratio_over`).
"""
from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np

from .datasets import Sequence
from .runner import TrackRun, track_sequence, warm_up
from .trackers import make_tracker

log = logging.getLogger(__name__)

UAV_PREFIXES = ("UAV123", "UAVDT", "DTB70")
PEER = "opencv-csrt"


def is_uav(name: str) -> bool:
    return name.startswith(UAV_PREFIXES)


def _stats(times: np.ndarray) -> dict:
    """The same keys with frames or without (NaN, written as null), so that every tracker's report reads alike."""
    ms = times * 1e3
    total = float(times.sum())
    p50, p95, mean = (np.percentile(ms, 50), np.percentile(ms, 95), ms.mean()) if len(ms) else (np.nan,) * 3
    return {"fps": len(times) / total if total > 0 else float("nan"),
            "ms_per_frame": {"p50": float(p50), "p95": float(p95), "mean": float(mean)},
            "frames": int(len(times)), "seconds": total}


def _fps(runs: list[TrackRun]) -> float:
    return _stats(np.concatenate([run.times for run in runs]))["fps"] if runs else float("nan")


def bench(trackers: list[str], sequences: list[Sequence], max_frames: int | None = None,
          progress: bool = True) -> dict:
    """JSON-ready speed report; trackers[0] is the subject, the others (and opencv-csrt) its peers."""
    import cv2
    from tqdm import tqdm

    cv2.setNumThreads(1)
    names = list(dict.fromkeys(list(trackers) + [PEER]))
    runs: dict[str, dict[str, TrackRun]] = {n: {} for n in names}
    failed: dict[str, dict[str, str]] = {n: {} for n in names}
    interrupted = False
    try:
        for seq in tqdm(sequences, desc="bench", unit="seq", disable=not progress):
            seq = replace(seq, frames=seq.frames[:max_frames], gt=seq.gt[:max_frames])
            for name in names:
                try:
                    warm_up(name, seq)
                    run = track_sequence(make_tracker(name), seq)
                except Exception as exc:  # noqa: BLE001 - as in `tacf eval`, one failed pair must not stop the others
                    failed[name][seq.name] = f"{type(exc).__name__}: {exc}"
                    log.warning("%s on %s failed: %s", name, seq.name, failed[name][seq.name])
                    continue
                runs[name][seq.name] = run
                log.info("%s %s: %.1f fps", name, seq.name, len(run.times) / run.times.sum())
    except KeyboardInterrupt:   # the sequences timed so far are minutes of measurement: report them
        interrupted = True

    def report(name: str) -> dict:
        allt = np.concatenate([run.times for run in runs[name].values()]) if runs[name] else np.zeros(0)
        out = _stats(allt)
        cpu, wall = sum(run.cpu_seconds for run in runs[name].values()), float(allt.sum())
        out["cores"] = cpu / wall if wall > 0 else float("nan")
        out["sequences"] = {s: _stats(run.times) for s, run in runs[name].items()}
        out["failed"] = failed[name]
        return out

    # CSRT's own speed differs several-fold between OpenCV releases (docs/speed.md): say which one this was.
    result = {"tracker": names[0], **report(names[0]), "peers": {n: report(n) for n in names[1:]},
              "opencv": cv2.__version__, "interrupted": interrupted}
    # the ratio compares the sequences both trackers finished: one that only one of them finished (the other failed
    # on it, or a Ctrl-C came first) would weigh on one side. `ratio_over` names them, with the two speeds divided.
    both = [s for s in runs[names[0]] if s in runs[PEER]]
    subject_fps, peer_fps = (_fps([runs[name][s] for s in both]) for name in (names[0], PEER))
    result["ratio_to_" + PEER] = subject_fps / peer_fps if peer_fps > 0 else float("nan")
    result["ratio_over"] = {"sequences": both, "fps": subject_fps, "peer_fps": peer_fps}
    return result
