"""HealthStats: the counters and timing windows behind a session's Health message."""
from __future__ import annotations

import math
import time
from collections import deque

from tacf_schemas import Health

FPS_WINDOW_S = 2.0
TIMING_WINDOW = 120          # processing times kept for mean / p95


COUNTERS = ("frames_received", "frames_processed", "frames_dropped", "frames_rejected", "frames_lost")


class HealthStats:
    """Updated by the worker's frame loop (one thread); snapshot() builds a Health message, whose counters add
    `earlier_counts` (those of the session's earlier workers, up to their last Health): they count over the
    session's life, not from 0 again after each restart."""

    def __init__(self, earlier_counts: dict[str, int] | None = None) -> None:
        self.earlier_counts = {name: int((earlier_counts or {}).get(name) or 0) for name in COUNTERS}
        self.frames_received = 0
        self.frames_processed = 0
        self.frames_dropped = 0
        self.frames_rejected = 0
        self.frames_lost = 0
        self.last_seq: int | None = None
        self.last_pme: float | None = None
        self.last_stamp_ns: int | None = None
        self._processing_ms: deque[float] = deque(maxlen=TIMING_WINDOW)
        self._processed_at: deque[float] = deque()

    def rejected(self) -> None:
        self.frames_rejected += 1

    def processed(self, seq: int, stamp_ns: int, processing_ms: float | None, pme: float | None, ok: bool,
                  live: bool = True) -> None:
        """A frame used: tracked (with its pme), or the tracker initialised on it (pme None: the last one stays).
        processing_ms None leaves the frame out of the times: an init's (a worker's first takes 0.1-0.2 s) is not
        what a frame costs, and it held the mean above the p95 for the window's 120 frames. live False leaves it out
        of the rate: the init frame and the catch-up after it go back to back from the service's history, and the
        first Health after a start read twice the feed's rate."""
        self.frames_processed += 1
        self.frames_lost += not ok
        self.last_seq, self.last_stamp_ns = seq, stamp_ns
        if pme is not None:
            self.last_pme = pme
        if processing_ms is not None:
            self._processing_ms.append(processing_ms)
        if live:
            self._processed_at.append(time.monotonic())
        self._forget_old_frames()

    def _forget_old_frames(self) -> None:
        """Keep the frames processed within FPS_WINDOW_S, and the newest one before them (fps's start), unless a
        pause longer than the window came between it and them: the feed's rate starts again from the first frame
        after the pause, as from a session's first (counted from the last frame before the pause, a 10 fps feed
        that resumed after 10 s read 1.1 then 2.4 fps in its first two Health). A feed with a frame every window or
        more keeps its start: it has one frame in the window at most."""
        now = time.monotonic()
        while len(self._processed_at) >= 2 and now - self._processed_at[1] >= FPS_WINDOW_S:
            self._processed_at.popleft()
        if len(self._processed_at) >= 3 and self._processed_at[1] - self._processed_at[0] > FPS_WINDOW_S:
            self._processed_at.popleft()

    def fps(self) -> float:
        """Frames processed a second: the frames of the last FPS_WINDOW_S over the time from the newest frame before
        them (or the first frame, while a window has not yet passed or after a longer pause) to now. A Health goes
        out right after a frame, so on a steady feed this is its rate; it falls as soon as the feed stops, to 0 once
        a window has passed without a frame. Counting the frames within the window counted both of its ends, one
        frame too many: a steady 10 fps feed read 10.5 in a third to a half of its Health (and a window not yet
        filled made the first Health read 6.5)."""
        self._forget_old_frames()
        if len(self._processed_at) < 2:
            return 0.0
        span = time.monotonic() - self._processed_at[0]
        return (len(self._processed_at) - 1) / span if span > 0 else 0.0

    def snapshot(self, node: str, sid: str, state: str, restarts: int = 0, message: str | None = None) -> Health:
        times = sorted(self._processing_ms)
        mean = sum(times) / len(times) if times else 0.0
        p95 = times[max(0, math.ceil(0.95 * len(times)) - 1)] if times else 0.0      # nearest rank
        now_ns = time.time_ns()
        age = (now_ns - self.last_stamp_ns) / 1e6 if self.last_stamp_ns else None
        return Health(node=node, sid=sid, state=state, stamp_ns=now_ns, fps=self.fps(),
                      processing_ms_mean=mean, processing_ms_p95=p95, frame_age_ms=age,
                      **{name: self.earlier_counts[name] + getattr(self, name) for name in COUNTERS},
                      pme=self.last_pme, last_seq=self.last_seq, restarts=restarts,
                      message=message[:1024] if message else None)
