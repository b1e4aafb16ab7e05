"""Session-wide test setup."""
from __future__ import annotations

import numpy as np


def pytest_sessionstart(session) -> None:
    """Compile the tracker's numba loops (fHOG, the colour lookup) once, up front: on a fresh checkout the service
    tests' worker processes would otherwise each compile them at the same time (seconds each) instead of loading
    the on-disk cache. A short track on a colour and a gray frame reaches every variant the tracker uses."""
    from tacf import Tracker

    rng = np.random.default_rng(0)
    colour = rng.integers(0, 256, (96, 128, 3), dtype=np.uint8)
    for frame in (colour, colour[:, :, 0].copy()):
        tracker = Tracker()
        tracker.init(frame, (40, 30, 24, 20))
        tracker.update(np.roll(frame, 2, axis=1))
