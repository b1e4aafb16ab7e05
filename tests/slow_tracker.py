"""A tracker factory for the service's tests (`tracker_factory="slow_tracker:slow_tracker"`): the box it was
initialised with, every frame, after a fixed delay. It shows which init a box comes from, and keeps the worker
busy inside a frame long enough for a control request to arrive meanwhile (SLOW_TRACKER_LOCATE_S, default 0.3 s,
for a worker started by a `tacf serve` subprocess; `brisk_tracker` takes 0.1 s, so that several catch-up frames
fit in the worker's CATCH_UP_BUDGET_S)."""
from __future__ import annotations

import os
import time
from dataclasses import dataclass

LOCATE_S = float(os.environ.get("SLOW_TRACKER_LOCATE_S", "0.3"))


@dataclass(frozen=True)
class Result:
    box: tuple
    ok: bool = True
    pme: float = 50.0
    score: float = 1.0
    scale: float = 1.0


class SlowTracker:
    locate_s = LOCATE_S

    def init(self, frame, box) -> None:
        self.box = tuple(float(c) for c in box)

    def locate(self, frame) -> Result:
        time.sleep(self.locate_s)
        return Result(self.box)

    def learn(self) -> None:
        pass

    def update(self, frame) -> Result:
        return self.locate(frame)


def slow_tracker(profile: str, overrides: dict) -> SlowTracker:
    return SlowTracker()


def brisk_tracker(profile: str, overrides: dict) -> SlowTracker:
    tracker = SlowTracker()
    tracker.locate_s = 0.1
    return tracker


def refusing_tracker(profile: str, overrides: dict) -> SlowTracker:
    """A plug-in that refuses its configuration when it is built, in the worker: the session fails there."""
    raise ValueError(f"this tracker has no profile {profile!r}")
