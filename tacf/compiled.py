"""The numba loops (fHOG, the colour lookup), compiled with numba's on-disk cache where it can write one.

`numba.njit(cache=True)` needs a writable folder for its cache, the package's own or the user's (~/.cache/numba,
or NUMBA_CACHE_DIR); without one it raises at import, "cannot cache function ...: no locator available", so that
in a read-only container (`docker run --read-only`: the image's compiled cache is there but read-only) `import
tacf.tracker` failed. There the loops are now compiled in the process instead (about 5 s, once per process; the
service's fork server does it once for all its workers).
"""
from __future__ import annotations

import logging

import numba

log = logging.getLogger(__name__)


def compiled(function):
    """numba.njit(cache=True)(function), or numba.njit(function) when numba has nowhere to write its cache."""
    try:
        return numba.njit(cache=True)(function)
    except RuntimeError as exc:
        log.warning("%s; compiling it in this process (NUMBA_CACHE_DIR names a writable folder for the cache)", exc)
        return numba.njit(function)
