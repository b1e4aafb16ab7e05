"""The signals that end a process of tacf, and holding them while it cannot act on them yet.

A held (blocked) signal stays pending until it is released, then goes to the handler in place at that moment. A
signal mask is kept across fork and exec, so a child started while they are held starts with them held too.
Windows has no signal mask: there these functions do nothing.
"""
from __future__ import annotations

import signal

# A terminal's Ctrl-C and hangup, `kill`'s and systemd's SIGTERM.
STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGTERM", "SIGINT", "SIGHUP") if hasattr(signal, name))


def hold_stop_signals() -> set | None:
    """Block STOP_SIGNALS in this thread; return the mask to give restore_signal_mask() (None on Windows)."""
    if not hasattr(signal, "pthread_sigmask"):
        return None
    return signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS)


def restore_signal_mask(mask: set | None) -> None:
    """Put back the mask hold_stop_signals() returned; a signal held meanwhile and unblocked by it comes out here."""
    if mask is not None:
        signal.pthread_sigmask(signal.SIG_SETMASK, mask)


def release_stop_signals() -> None:
    """Unblock STOP_SIGNALS in this thread: one held meanwhile goes to the handler now in place. Harmless where none
    is held."""
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)
