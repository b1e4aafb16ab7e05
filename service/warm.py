"""Imported once by the service's fork server (worker.worker_context): the workers' heavy imports and the
tracker's first-call cost, numba compiling its loops or loading them from its cache (tacf.tracker.compile_loops),
are paid once instead of by every worker at its first frame, and their memory is shared, copy-on-write, by every
worker forked from the server.

Nothing here may start a thread: a forked child has only the thread that forked, and a library whose pool of
threads did not come along waits on it for ever. So BLAS is held to one thread before numpy loads, OpenCV to no
thread pool before its first call, and Zenoh is not imported at all (its runtime does not survive fork, ZENOH.md
2.5; each worker opens its session after the fork).
"""
import gc

from .worker import end_after_grace, hold_blas_to_one_thread, take_group_signals  # imports neither numpy nor Zenoh

# Killed by a signal to the whole process group, this server took every worker's exit report with it: the service
# reported each session failed ("worker exited with code 255"), not stopped. The service stops its workers, then
# this server (which ends when the service's pipe to it closes); a SIGTERM by hand ends it SIGTERM_GRACE_S later.
# The server starts with these signals held (worker.start_with_stop_signals_held), so that a Ctrl-C before this
# line cannot end it with a KeyboardInterrupt traceback on the terminal. Workers forked from here inherit the
# signals ignored, and this SIGTERM handler until they install their own.
take_group_signals(end_after_grace)
hold_blas_to_one_thread()

import cv2  # noqa: E402

cv2.setNumThreads(1)

# The fork server imports this with only ImportError caught: anything else raised here would leave no server to
# fork workers from. A worker meets the same failure again and reports it with its session.
try:
    from tacf.tracker import compile_loops

    compile_loops()
except Exception:  # noqa: BLE001
    pass

# What is loaded by now lives as long as the workers: out of their garbage collector's sight, whose passes would
# otherwise write to every object's header and so copy the shared pages into each worker (Python's gc.freeze docs).
gc.freeze()
