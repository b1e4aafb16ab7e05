"""The `tacf` command line: one console script, subcommands registered by their own modules.

Each module in COMMAND_MODULES defines `register(subparsers)`, adding its subcommands with
`set_defaults(func=...)`, and may define `register_bench(bench_subparsers)` for a `tacf bench WHAT`
benchmark; `func(args)` returns the exit code. A command that handles tacf.stop_signals.STOP_SIGNALS itself
says so with `set_defaults(handles_stop_signals=True)` and calls release_stop_signals() once its handlers are in
place; in the others every stop signal raises KeyboardInterrupt, as Ctrl-C does, and one the command does not catch
ends it with a line and the signal's exit code (interrupted_exit_code(): 130 Ctrl-C, 143 SIGTERM, 129 SIGHUP).
Those modules import only argparse-level things at import time, so `tacf publish` never loads the tracker
and `tacf eval` never loads Zenoh.
"""
from __future__ import annotations

import argparse
import importlib
import logging
import os
import sys

from tacf.stop_signals import (hold_stop_signals, interrupt_on_stop_signals, interrupted_exit_code, stop_signal_came,
                               release_stop_signals, restore_handlers, restore_signal_mask)

COMMAND_MODULES = (
    "tacf.eval.cli",         # eval, track, bench tracker
    "tacf_service.cli",      # serve
    "tacf_clients.cli",      # publish, start, stop, reinit, list, status, nodes, watch, demo, mavlink, foxglove,
                             # dashboard
    "tacf_clients.bench",    # bench service
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="tacf", description="TACF UAV tracker and Zenoh tracking service")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    bench = sub.add_parser("bench", help="speed benchmarks (tracker, service)", description="Speed benchmarks.")
    bench_sub = bench.add_subparsers(dest="what", metavar="WHAT", required=True)
    for name in COMMAND_MODULES:
        module = importlib.import_module(name)
        getattr(module, "register", lambda _: None)(sub)
        getattr(module, "register_bench", lambda _: None)(bench_sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = None
    # Held while the command starts: its imports take up to a second on a busy box, and a Ctrl-C among them ended it
    # with a KeyboardInterrupt traceback instead of as a moment later.
    mask = hold_stop_signals()
    handlers = {}
    try:
        try:
            parser = build_parser()
            args = parser.parse_args(argv)
            logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                                format="%(asctime)s %(levelname)s %(name)s: %(message)s")
            if not getattr(args, "func", None):
                parser.print_help()
                return 2
            if not getattr(args, "handles_stop_signals", False):
                handlers = interrupt_on_stop_signals()
                release_stop_signals()
            return int(args.func(args) or 0)
        finally:
            restore_handlers(handlers)
            restore_signal_mask(mask)   # for a caller in this process (tests); a signal still held comes out here
    except (KeyboardInterrupt, RuntimeError) as exc:   # Ctrl-C a command does not handle: a line, not a traceback
        # A Ctrl-C during numba's first compile after an install (5-8 s) lands in llvmlite's ctypes callback, which
        # drops the KeyboardInterrupt; numba then fails with "RuntimeError: no compiled object yet for ...".
        if isinstance(exc, RuntimeError) and not (handlers and stop_signal_came()):
            raise
        print(f"tacf {args.command}: interrupted" if args else "tacf: interrupted", file=sys.stderr)
        return interrupted_exit_code() if handlers else 130     # 128 + the signal's number, as shells report it
    except BrokenPipeError:         # `tacf track ... | head`: the reader has all it wants, as for any Unix filter
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())   # Python's flush at exit would fail again
        return 141                  # 128 + SIGPIPE, as shells report a filter the pipe stopped


if __name__ == "__main__":
    sys.exit(main())
