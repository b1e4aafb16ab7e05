"""A tracker factory for the benchmark's tests (`--tracker-factory busy_tracker:busy_tracker`): the box it was
initialised with, after spending BUSY_TRACKER_CPU_S (default 0.05 s) of CPU time on the frame, so that the CPU
time a session's workers used is known from the frames they tracked, however loaded the machine is."""
from __future__ import annotations

import os
import time

from slow_tracker import Result

CPU_S = float(os.environ.get("BUSY_TRACKER_CPU_S", "0.05"))


class BusyTracker:
    def init(self, frame, box) -> None:
        self.box = tuple(float(c) for c in box)

    def update(self, frame) -> Result:
        burnt_by = time.thread_time() + CPU_S          # this thread's CPU time: waiting for a core does not count
        while time.thread_time() < burnt_by:
            pass
        return Result(self.box)


def busy_tracker(profile: str, overrides: dict) -> BusyTracker:
    return BusyTracker()
