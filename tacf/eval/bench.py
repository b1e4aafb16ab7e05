"""`tacf bench tracker`: per-stream speed of a tracker on decoded frames, with OpenCV CSRT measured alongside.

Each sequence is decoded into memory first; only init/update calls are timed (time.perf_counter), in this one
process with OpenCV limited to one thread. fps = total frames / total tracker seconds; `cores` = the process's
CPU time over the wall time while a tracker ran (1.0 is one core; more means threads working, or spinning, on
other cores). Before any timing, every tracker runs once, untimed, on the first frames of the first sequence:
what a process pays once (loading the compiled fHOG from numba's cache, OpenCV's lazy set-up) is not a cost per
stream, and would otherwise be charged to whichever sequence comes first.
"""
from __future__ import annotations

import logging
import time

import numpy as np

from .datasets import Sequence
from .runner import read_frame, track_frames, warm_up
from .trackers import make_tracker

log = logging.getLogger(__name__)

UAV_PREFIXES = ("UAV123", "UAVDT", "DTB70")
PEER = "opencv-csrt"


def is_uav(name: str) -> bool:
    return name.startswith(UAV_PREFIXES)


def _stats(times: np.ndarray) -> dict:
    ms = times * 1e3
    total = float(times.sum())
    return {"fps": len(times) / total if total > 0 else float("nan"),
            "ms_per_frame": {"p50": float(np.percentile(ms, 50)), "p95": float(np.percentile(ms, 95)),
                             "mean": float(ms.mean())},
            "frames": int(len(times)), "seconds": total}


def bench(trackers: list[str], sequences: list[Sequence], max_frames: int | None = None,
          progress: bool = True) -> dict:
    """JSON-ready speed report; trackers[0] is the subject, the others (and opencv-csrt) its peers."""
    import cv2
    from tqdm import tqdm

    cv2.setNumThreads(1)
    names = list(dict.fromkeys(list(trackers) + [PEER]))
    times: dict[str, dict[str, np.ndarray]] = {n: {} for n in names}
    cpu_and_wall = {n: np.zeros(2) for n in names}
    if sequences:
        for name in names:
            warm_up(name, sequences[0])
    for seq in tqdm(sequences, desc="bench", unit="seq", disable=not progress):
        n = len(seq) if max_frames is None else min(len(seq), max_frames)
        frames = [read_frame(p) for p in seq.frames[:n]]
        for name in names:
            cpu, wall = time.process_time(), time.perf_counter()
            run = track_frames(make_tracker(name), frames, seq.gt[0])
            cpu_and_wall[name] += (time.process_time() - cpu, time.perf_counter() - wall)
            times[name][seq.name] = run.times
            log.info("%s %s: %.1f fps", name, seq.name, n / run.times.sum())
        del frames

    def report(name: str) -> dict:
        allt = np.concatenate(list(times[name].values())) if times[name] else np.zeros(0)
        out = _stats(allt) if len(allt) else {"fps": float("nan"), "frames": 0}
        cpu, wall = cpu_and_wall[name]
        out["cores"] = float(cpu / wall) if wall > 0 else float("nan")
        out["sequences"] = {s: _stats(t) for s, t in times[name].items()}
        return out

    main = report(names[0])
    # CSRT's own speed differs several-fold between OpenCV releases (docs/speed.md): say which one this was.
    result = {"tracker": names[0], **main, "peers": {n: report(n) for n in names[1:]}, "opencv": cv2.__version__}
    peer_fps = result["peers"][PEER]["fps"] if PEER != names[0] else main["fps"]
    result["ratio_to_" + PEER] = main["fps"] / peer_fps if peer_fps and np.isfinite(peer_fps) else float("nan")
    return result
