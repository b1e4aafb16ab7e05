"""The signals that end a process of tacf, and holding them while it cannot act on them yet.

A held (blocked) signal stays pending until it is released, then goes to the handler in place at that moment. A
signal mask is kept across fork and exec, so a child started while they are held starts with them held too.
Windows has no signal mask: there these functions do nothing.
"""
from __future__ import annotations

import signal
import threading

# A terminal's Ctrl-C and hangup, `kill`'s and systemd's SIGTERM.
STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGTERM", "SIGINT", "SIGHUP") if hasattr(signal, name))

# The stop signal interrupt_on_stop_signals() turned into a KeyboardInterrupt last (raised or lost), None before one
_interrupted_by: int | None = None


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


def interrupt_on_stop_signals() -> dict:
    """Make every stop signal raise KeyboardInterrupt in the main thread, as Ctrl-C does by default: a command that
    closes its files and reports its work on Ctrl-C then does so on SIGTERM (`timeout`, a supervisor) and SIGHUP (a
    closed terminal) too, which used to end it on the spot. Returns the handlers replaced, for restore_handlers();
    none off the main thread, where Python takes no handler (a test running `tacf.cli.main` on a thread)."""
    global _interrupted_by
    _interrupted_by = None
    if threading.current_thread() is not threading.main_thread():
        return {}

    def interrupt(signal_number: int, _frame) -> None:
        global _interrupted_by
        _interrupted_by = signal_number
        raise KeyboardInterrupt
    return {sig: signal.signal(sig, interrupt) for sig in STOP_SIGNALS}


def stop_signal_came() -> bool:
    """Whether a stop signal reached the handlers of interrupt_on_stop_signals(), even one whose KeyboardInterrupt
    was lost: raised inside a ctypes callback (llvmlite's, while numba compiles), it is printed and dropped there."""
    return _interrupted_by is not None


def restore_handlers(handlers: dict) -> None:
    for sig, handler in handlers.items():
        signal.signal(sig, handler)


def interrupted_exit_code() -> int:
    """What a shell reports for a command ended by the stop signal behind the last KeyboardInterrupt: 128 and its
    number (130 Ctrl-C, 143 SIGTERM, 129 SIGHUP)."""
    return 128 + (_interrupted_by or signal.SIGINT)
