"""`tacf serve`: the command-line front of the tracking service. Only argparse at import time."""
from __future__ import annotations

import argparse
import logging

from tacf.argument_types import config_file, endpoint, integer, not_empty, seconds


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "serve", help="run the Zenoh tracking service",
        description="Run the TACF tracking service: a Zenoh peer (loopback only by default) answering "
                    "tacf/<node>/control/<op> and running one worker process per session.")
    parser.add_argument("--listen", action="append", default=[], type=endpoint, metavar="ENDPOINT",
                        help="Zenoh listen endpoint (repeatable; default tcp/127.0.0.1:7447 when neither "
                             "--connect nor --zenoh-config is given)")
    parser.add_argument("--connect", action="append", default=[], type=endpoint, metavar="ENDPOINT",
                        help="Zenoh endpoint to connect to, e.g. a router (repeatable)")
    parser.add_argument("--zenoh-config", type=config_file, metavar="FILE",
                        help="Zenoh JSON5 config file (TLS, access control...); --listen/--connect override its "
                             "endpoints")
    parser.add_argument("--mode", choices=("peer", "client", "router"),
                        help="Zenoh mode (default peer, or the --zenoh-config file's)")
    parser.add_argument("--node", metavar="ID", help="service id, [A-Za-z0-9_-]{1,64} (default: the hostname "
                                                    "sanitised, or 'edge')")
    parser.add_argument("--max-sessions", type=integer(1), default=8, metavar="N", help="session limit (default 8)")
    # not_empty: --state "$STATE" with the variable unset ran without persistence, without a word
    parser.add_argument("--state", type=not_empty("a file to keep the sessions in"), metavar="FILE",
                        help="persist sessions in FILE and restore them on start (one service per file: a second one "
                             "refuses to start)")
    parser.add_argument("--state-frames-every", type=seconds, default=5.0, metavar="S",
                        help="store each session's box frame beside --state every S seconds, besides at start, "
                             "re-init and shutdown: after a crash a restored tracker starts up to S back "
                             "(default 5; each store writes a frame to disk)")
    parser.add_argument("--init-wait", type=seconds, default=1.0, metavar="S",
                        help="how long start waits for a first frame to check the box against (default 1 s)")
    parser.add_argument("--spare-workers", type=integer(0), default=1, metavar="N",
                        help="worker processes kept warm so that a start tracks within milliseconds, at most "
                             "--max-sessions (default 1)")
    parser.add_argument("--tracker-factory", default=None, metavar="MODULE:FUNCTION", help=argparse.SUPPRESS)
    parser.set_defaults(func=run, handles_stop_signals=True)   # serve() releases them (tacf.cli)


def run(args: argparse.Namespace) -> int:
    from tacf.zenoh_options import options_from_args
    from tacf_schemas import InvalidIdError, validate_node_id

    from .app import ServiceOptions, default_node_id, serve
    from .trackers import DEFAULT_FACTORY

    log = logging.getLogger("tacf_service")
    node = default_node_id() if args.node is None else args.node     # --node "" is an invalid id, not a default
    try:
        validate_node_id(node)
    except InvalidIdError as exc:
        log.error("%s", exc)
        return 2
    zenoh_options = options_from_args(args)
    options = ServiceOptions(node=node, zenoh=zenoh_options, max_sessions=args.max_sessions, state_file=args.state,
                             tracker_factory=args.tracker_factory or DEFAULT_FACTORY, init_wait_s=args.init_wait,
                             spare_workers=args.spare_workers, state_frame_period_s=args.state_frames_every,
                             log_level=logging.getLogger().getEffectiveLevel())
    return serve(options)

