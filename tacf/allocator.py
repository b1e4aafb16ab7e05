"""Keep the memory of the per-frame temporaries in the process instead of handing it back to the OS every frame.

Each frame allocates and frees arrays of one to three megabytes (42-channel spectra, stacks of patches, frames).
glibc serves blocks that large with mmap and trims the top of its heap whenever more than a threshold is free,
so the same megabytes were mapped, page-faulted and unmapped frame after frame: a fifth of the tracker's time
went to the kernel (`sys` time 6.7-8.2 s of 53-66 s over the 10 UAV sequences twice). With the mmap and trim
thresholds raised once per process, freed blocks stay in the heap and are reused: `sys` time about 30 % lower
and about 7 % more frames per second (median of four alternating runs), with the same boxes (docs/speed.md).
The cost is that the process keeps its peak heap instead of returning it, a few tens of megabytes for a tracker.

glibc only (Linux); elsewhere nothing is changed.
"""
from __future__ import annotations

import ctypes
import functools
import logging

log = logging.getLogger(__name__)

# mallopt parameters, from glibc's malloc.h
M_TRIM_THRESHOLD = -1
M_TOP_PAD = -2
M_MMAP_THRESHOLD = -3

MMAP_THRESHOLD = 32 * 1024 * 1024  # glibc's ceiling on 64-bit: blocks up to this come from the heap
TRIM_THRESHOLD = 256 * 1024 * 1024  # free heap top kept before trimming
TOP_PAD = 16 * 1024 * 1024  # extra heap requested per growth, so growth is rare


@functools.cache
def keep_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds for this process (once). True when they were applied."""
    try:
        mallopt = ctypes.CDLL(None).mallopt  # glibc and musl export it; musl's ignores every parameter
    except (AttributeError, OSError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    applied = all(mallopt(param, value) == 1 for param, value in
                  ((M_MMAP_THRESHOLD, MMAP_THRESHOLD), (M_TRIM_THRESHOLD, TRIM_THRESHOLD), (M_TOP_PAD, TOP_PAD)))
    log.debug("malloc thresholds %s", "raised" if applied else "left as they were")
    return applied
