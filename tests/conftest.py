"""Session-wide test setup."""
from __future__ import annotations


def pytest_sessionstart(session) -> None:
    """Compile the tracker's numba loops (fHOG, the colour lookup) once, up front: on a fresh checkout the service
    tests' worker processes would otherwise each compile them at the same time (seconds each) instead of loading
    the on-disk cache."""
    from tacf.tracker import compile_loops

    compile_loops()
