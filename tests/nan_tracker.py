"""A tracker factory for the service's tests (`tracker_factory="nan_tracker:nan_tracker"`): the box it was
initialised with, but NaN on every other frame, and a NaN PME on the others, as a buggy plug-in tracker might
give."""
from __future__ import annotations

import math

from slow_tracker import Result


class NanTracker:
    def init(self, frame, box) -> None:
        self.box, self.frames = tuple(float(c) for c in box), 0

    def update(self, frame) -> Result:
        self.frames += 1
        return Result((math.nan,) * 4) if self.frames % 2 else Result(self.box, pme=math.nan)


def nan_tracker(profile: str, overrides: dict) -> NanTracker:
    return NanTracker()
