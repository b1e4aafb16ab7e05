"""Session-wide test setup."""
from __future__ import annotations

import numpy as np


def pytest_sessionstart(session) -> None:
    """Compile the numba fHOG loops once, up front: on a fresh checkout the service tests' worker processes would
    otherwise each compile them at the same time (seconds each) instead of loading the on-disk cache."""
    from tacf.features import fhog

    fhog(np.zeros((8, 8, 3), np.float32))
