"""Log lines that could repeat for ever (a camera sending bad frames for days, one switched off for hours), let
through once a period with the count of those held back."""
from __future__ import annotations

import math
import threading
import time
from typing import NamedTuple


class Admitted(NamedTuple):
    held_back: int      # events held back since the last one admitted
    since_s: float      # seconds since the last one admitted (inf for the first)


class LogThrottle:
    """Admits an event at most once a period, counting those held back in between. Thread-safe: Zenoh calls its
    handlers from several threads."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._admitted_at = -math.inf
        self._held_back = 0

    def admit(self, period_s: float) -> Admitted | None:
        """None within period_s of the last event admitted (the period is read at each call: tests shorten it)."""
        now = time.monotonic()
        with self._lock:
            since_s = now - self._admitted_at
            if since_s < period_s:
                self._held_back += 1
                return None
            admitted = Admitted(self._held_back, since_s)
            self._held_back, self._admitted_at = 0, now
        return admitted
