"""`tacf publish | start | stop | reinit | list | status | nodes | watch | demo | dashboard | foxglove | mavlink`:
the client side from the shell.

Only argparse-level things are imported here; each command imports what it needs when it runs, so that
`tacf --help` stays fast and nothing here ever loads the tracker.
"""
from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from contextlib import contextmanager

from tacf.argument_types import (box, integer, port, positive_number, positive_up_to, quality, seconds, source,
                                 take_negative_numbers)
from tacf.config import PROFILES      # plain data: `tacf demo --profile` is checked before a service starts

mavlink_id = integer(1, 255, "a MAVLink id")
frame_seq = integer(0, what="a frame seq")

ENCODING_CHOICES = ("jpeg", "png", "bgr8", "mono8")
# The Zenoh mode a command opens without --mode or a config file, as its help states it (see _client and
# zconfig.viewer_options).
ONE_SHOT_MODE = "client: the node it connects to answers for the whole network at once"
VIEWER_MODE = "peer; client when every --connect endpoint is on another machine and no --listen is given"


def _install_extra(extra: str) -> str:
    """How to install one of pyproject's optional extras: from the checkout, as tacf itself is (it is not on PyPI,
    where `pip install 'tacf[extra]'` would look)."""
    return f"pip install -e '.[{extra}]' in the tacf checkout"


def register(subparsers: argparse._SubParsersAction) -> None:
    from tacf_clients.zconfig import add_zenoh_arguments

    p = subparsers.add_parser("publish", help="publish a video file, image folder, camera or URL as Frames",
                              description="Publish SOURCE as tacf Frames on the Zenoh key --key. SOURCE: a video "
                                          "file, an image folder (or a sequence folder with img/), a camera index "
                                          "or device (/dev/video0), a stream URL, or 'scene' (the generated demo "
                                          "scene).")
    p.add_argument("source", metavar="SOURCE", type=source)
    p.add_argument("--key", "-k", required=True, type=_image_key,
                   help="Zenoh key to publish on, e.g. uav1/camera/front")
    p.add_argument("--fps", type=positive_number, help="rate (default: the source's own, or 30)")
    p.add_argument("--encoding", choices=ENCODING_CHOICES, default="jpeg", help="frame encoding (default jpeg)")
    p.add_argument("--quality", type=quality, default=90, help="JPEG quality 1-100 (default 90)")
    p.add_argument("--loop", action="store_true", help="start over at the end of a file or folder")
    p.add_argument("--no-reconnect", dest="reconnect", action="store_false",
                   help="end when a camera or stream fails or ends (default: reopen it, pausing 0.5 s doubling to "
                        "5 s between attempts; a stream silent for 5 s counts as failed)")
    p.add_argument("--frames", type=integer(1), metavar="N", help="stop after N frames")
    p.add_argument("--wait-subscriber", type=seconds, default=0.0, metavar="SECONDS",
                   help="wait up to SECONDS for a subscriber before the first frame (default: do not wait)")
    add_zenoh_arguments(p)
    p.set_defaults(func=cmd_publish)

    p = subparsers.add_parser("start", help="start a tracking session",
                              description="Start a session that tracks the target in --box on the frames of --key "
                                          "and print it (`started SID on NODE: state, key, ...`; --json: its "
                                          "SessionInfo). The box is put on frame --seq if the service holds it "
                                          "(a feed's last 24 frames, kept only while a session follows the feed), "
                                          "else on the nearest one it holds after it, else on the newest, where a "
                                          "moving target may have left it; "
                                          "`tacf dashboard` sends the frame the box was drawn on with the start.")
    p.add_argument("--key", "-k", required=True, type=_image_key, help="image key the frames are published on")
    p.add_argument("--box", "-b", required=True, type=box, help="initial box x,y,w,h in pixels")
    take_negative_numbers(p)       # a box across the left or top border: --box -5,20,40,30
    p.add_argument("--seq", type=frame_seq, help="seq of the frame the box was drawn on")
    p.add_argument("--profile", help="tracker profile (service default if absent)")
    p.add_argument("--sid", help="session id (generated if absent)")
    p.add_argument("--set", dest="overrides", action="append", default=[], type=_setting, metavar="NAME=VALUE",
                   help="tracker config override (a TrackerConfig field), repeatable")
    _common(p, add_zenoh_arguments, node_help="service (node id) to run it on, or 'auto' for the least-loaded "
                                              "one (fewest sessions, then least tracking load); default: the "
                                              "only service on the network")
    p.set_defaults(func=cmd_start)

    p = subparsers.add_parser("stop", help="stop a tracking session",
                              description="Stop session SID on whichever service runs it and print it as stopped.")
    p.add_argument("sid", metavar="SID")
    _common(p, add_zenoh_arguments)
    p.set_defaults(func=cmd_stop)

    p = subparsers.add_parser("reinit", help="re-initialise a session on a new box",
                              description="Start session SID's tracker again on --box (on frame --seq when the "
                                          "service still holds it), keeping its id, key and counters.")
    p.add_argument("sid", metavar="SID")
    p.add_argument("--box", "-b", required=True, type=box, help="new box x,y,w,h in pixels")
    take_negative_numbers(p)
    p.add_argument("--seq", type=frame_seq, help="seq of the frame the box was drawn on")
    _common(p, add_zenoh_arguments)
    p.set_defaults(func=cmd_reinit)

    p = subparsers.add_parser("list", help="list the sessions of every service on the network",
                              description="List the sessions of every service that answers (--json: one object "
                                          "per service, with its sessions). A service without sessions is a "
                                          "valid answer (exit 0); no service answering is an error: exit 1, "
                                          "with --json after printing [].")
    _common(p, add_zenoh_arguments, node_help="only this service (node id); default: every service on the network")
    p.set_defaults(func=cmd_list)

    p = subparsers.add_parser("status", help="show one session",
                              description="Print session SID: state, key, profile, box, the frame it started on, "
                                          "and its last health (fps, p95 ms and counters, up to a second old).")
    p.add_argument("sid", metavar="SID")
    _common(p, add_zenoh_arguments)
    p.set_defaults(func=cmd_status)

    p = subparsers.add_parser("nodes", help="the services on the network: alive, sessions, load",
                              description="Show each service whose liveliness token is up, with its sessions and "
                                          "tracking load; --follow prints services appearing and disappearing "
                                          "(a killed service within milliseconds) until Ctrl-C. No service on "
                                          "the network is an error: exit 1, with --json after printing [].")
    p.add_argument("--follow", "-f", action="store_true", help="print up/down events instead of a table")
    p.add_argument("--duration", type=positive_number, help="with --follow: exit after this many seconds")
    _common(p, add_zenoh_arguments, node_help=argparse.SUPPRESS, mode_default="client; peer with --follow")
    p.set_defaults(func=cmd_nodes)

    p = subparsers.add_parser("watch", help="live table of boxes and health in the terminal",
                              description="Show the newest box and health of every session (or of session SID) "
                                          "on every service (or on --node's), refreshed every --interval "
                                          "seconds until Ctrl-C, or until --duration ends on a last table of "
                                          "what was received.")
    p.add_argument("sid", metavar="SID", nargs="?", default="*", help="session id (default: all sessions)")
    p.add_argument("--node", help="only this service")
    p.add_argument("--interval", type=positive_number, default=0.5, help="refresh period in seconds (default 0.5)")
    p.add_argument("--duration", type=positive_number, help="exit after this many seconds")
    add_zenoh_arguments(p)
    p.set_defaults(func=cmd_watch)

    p = subparsers.add_parser("demo", help="the whole loop on this machine: service, publisher, session",
                              description="Start a local tracking service, publish SOURCE (default: a generated "
                                          "scene with a moving target), start a session on it, print boxes and "
                                          "health, then stop everything cleanly.")
    p.add_argument("source", metavar="SOURCE", nargs="?", default="scene", type=source,
                   help="video file, image folder, camera index, URL or 'scene' (default)")
    p.add_argument("--box", "-b", type=box,
                   help="initial box x,y,w,h (default: the scene's target, a sequence's groundtruth.txt, "
                        "or a centred box)")
    take_negative_numbers(p)
    p.add_argument("--seconds", type=positive_number, default=10.0, help="how long to track (default 10)")
    p.add_argument("--fps", type=positive_number, default=None,
                   help="frames per second to publish: a video file or folder is replayed at this rate, a camera or "
                        "URL thinned to it (default: a video file's own rate, else 20)")
    p.add_argument("--encoding", choices=ENCODING_CHOICES, default="jpeg")
    p.add_argument("--profile", choices=PROFILES, help="tracker profile (default: the service's default)")
    p.add_argument("--every", type=integer(1), default=None, metavar="N",
                   help="print every Nth box (default: about 3 lines a second)")
    p.set_defaults(func=cmd_demo)

    p = subparsers.add_parser("mavlink", help="MAVLink camera component: QGroundControl starts/stops tracking",
                              description="Be a MAVLink camera component for one image key: a ground station that "
                                          "speaks the camera tracking protocol (QGroundControl) starts a session "
                                          "with MAV_CMD_CAMERA_TRACK_RECTANGLE, stops it with "
                                          "MAV_CMD_CAMERA_STOP_TRACKING and gets CAMERA_TRACKING_IMAGE_STATUS. "
                                          f"Needs pymavlink: {_install_extra('mavlink')}.")
    p.add_argument("--key", "-k", required=True, type=_image_key, help="image key of the camera's frames")
    p.add_argument("--link", required=True,
                   help="pymavlink connection: udpout:GCS_HOST:14550, udpin:0.0.0.0:PORT, tcp:HOST:PORT, "
                        "mcast:[IP:]PORT, unix:PATH or a serial device")
    p.add_argument("--baud", type=integer(1), default=57600, help="serial baud rate (default 57600)")
    p.add_argument("--system", type=mavlink_id, default=1, help="MAVLink system id (default 1: the vehicle's)")
    p.add_argument("--component", type=mavlink_id, default=100, help="MAVLink component id (default 100, camera 1)")
    p.add_argument("--sid", help="session id (default mavlink-<image key>, '/' read as '-'; for a key too long for "
                                 "an id, or with characters other than letters, digits, '_' and '/', one that ends "
                                 "in the key's digest)")
    p.add_argument("--profile", help="tracker profile")
    p.add_argument("--node", help="service (node id) to run the session on")
    p.add_argument("--signing-passphrase-file", metavar="FILE",
                   help="MAVLink 2 signing: sign what is sent and accept only commands signed with the key of "
                        "this file's passphrase (its SHA-256, as MAVProxy's `signing setup` makes it)")
    add_zenoh_arguments(p)
    p.set_defaults(func=cmd_mavlink)

    p = subparsers.add_parser("foxglove", help="Foxglove / Lichtblick live view: frames, boxes, health, start/stop",
                              description="Serve every session to Foxglove (or Lichtblick) over Foxglove's WebSocket "
                                          "protocol on ws://HOST:PORT: /<image key>/image, /<image key>/tracks "
                                          "(the boxes as image annotations), /tacf/<node>/<sid> (JSON health), and "
                                          "the services /tacf/start, /tacf/reinit, /tacf/stop and /tacf/list. "
                                          f"Needs foxglove-sdk: {_install_extra('foxglove')}.")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to serve on (default 127.0.0.1; on any other the services are off unless "
                        "--control: the protocol has no authentication)")
    p.add_argument("--port", type=port, default=8765, help="WebSocket port (default 8765, Foxglove's; 0 = any free)")
    p.add_argument("--control", action=argparse.BooleanOptionalAction, default=None,
                   help="offer the start/stop/reinit/list services (default: on loopback only)")
    p.add_argument("--image-hz", type=positive_number, default=10.0, metavar="HZ",
                   help="images per second and image key at most (default 10: viewers keep what they get)")
    p.add_argument("--record", metavar="FILE.mcap",
                   help="also write everything (images at --image-hz) to this MCAP file, for replay in Foxglove")
    p.add_argument("--allow-origin", dest="allow_origins", action="append", default=[], metavar="ORIGIN",
                   help="let in web pages from this origin, e.g. http://10.0.0.2:8080 (a Lichtblick served there), "
                        "repeatable; '*' any. Let in already: programs, pages from this machine, Foxglove's web app "
                        "and desktop apps")
    p.add_argument("--certfile", metavar="PEM", help="serve wss:// only, with this certificate (chain)")
    p.add_argument("--keyfile", metavar="PEM", help="the certificate's private key (default: in --certfile)")
    p.add_argument("--key", "-k", dest="keys", action="append", default=[], type=_image_key, metavar="IMAGE_KEY",
                   help="image key to show from the start, repeatable (the keys of running sessions are added "
                        "by themselves)")
    p.add_argument("--node", help="only this service (default: every service on the network)")
    add_zenoh_arguments(p, VIEWER_MODE)
    p.set_defaults(func=cmd_foxglove)

    p = subparsers.add_parser("dashboard", help="ground-station web page: live frames, boxes, charts, start/stop",
                              description="Serve the ground-station dashboard on http://HOST:PORT/ (fully offline: "
                                          "no CDN): the live frame of each session with its box, PME and FPS "
                                          "charts, the session list; draw a box on a live frame to start a "
                                          "session. Also /metrics (Prometheus) and /healthz.")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to serve on (default 127.0.0.1; any other address asks for a token)")
    p.add_argument("--port", type=port, default=8080, help="HTTP port (default 8080; 0 = any free port)")
    p.add_argument("--token-file", metavar="FILE",
                   help="the access token, from this file (default: $TACF_DASHBOARD_TOKEN; on an address that is "
                        "not loopback a new one is made up; the printed address carries it)")
    p.add_argument("--certfile", metavar="PEM",
                   help="serve HTTPS with this certificate (chain), e.g. make-certs.sh's service.pem")
    p.add_argument("--keyfile", metavar="PEM", help="the certificate's private key (default: in --certfile)")
    p.add_argument("--allow-host", dest="allow_hosts", action="append", default=[], metavar="NAME",
                   help="a host name the page may be served under besides loopback ones, repeatable (e.g. a "
                        "reverse proxy's); without a token other names are refused, against DNS rebinding")
    p.add_argument("--key", "-k", dest="keys", action="append", default=[], type=_image_key, metavar="IMAGE_KEY",
                   help="image key to show from the start, repeatable (the keys of running sessions are added "
                        "by themselves, and more can be added on the page)")
    p.add_argument("--node", help="only this service (default: every service on the network)")
    # a day of points (about one a second) is what the page's charts draw; 1e307 minutes was 'Infinity' in its JSON
    p.add_argument("--history", type=positive_up_to(24 * 60), default=5.0, metavar="MINUTES",
                   help="minutes of chart history per session (default 5, at most 1440: a day)")
    add_zenoh_arguments(p, VIEWER_MODE)
    p.set_defaults(func=cmd_dashboard)


def _common(p: argparse.ArgumentParser, add_zenoh_arguments,
            node_help: str = "service (node id) to address; default: whichever holds the session",
            mode_default: str = ONE_SHOT_MODE) -> None:
    p.add_argument("--node", help=node_help)
    p.add_argument("--timeout", type=positive_number,
                   help="reply timeout in seconds (default 5; 30 for start: a service's first start waits for its "
                        "workers to load the tracker)")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    add_zenoh_arguments(p, mode_default)


# ------------------------------------------------------------------------------------------------ argument types

def _image_key(text: str) -> str:
    """An image key as the service will take it: a bad one is a usage error here, not a traceback later."""
    from tacf_schemas.keys import InvalidKeyError, validate_image_key

    try:
        return validate_image_key(text)
    except InvalidKeyError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _setting(text: str) -> tuple[str, bool | int | float]:
    from tacf.config import parse_setting

    try:
        return parse_setting(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


class StopEvent(threading.Event):
    """Set by a stop signal; `exit_code` is what a shell reports for a command that signal ended (130 for Ctrl-C,
    143 for SIGTERM), which a command stopped part way returns."""
    signal_number = signal.SIGINT

    @property
    def exit_code(self) -> int:
        return 128 + self.signal_number


@contextmanager
def stop_on_signals():
    """A StopEvent set by SIGINT / SIGTERM / SIGHUP (the terminal closed: `tacf demo` used to leave its service
    running) while the block runs (previous handlers restored afterwards)."""
    stop = StopEvent()

    def handler(signal_number: int, _frame) -> None:
        stop.signal_number = signal_number
        stop.set()

    signals = (signal.SIGINT, signal.SIGTERM) + ((signal.SIGHUP,) if hasattr(signal, "SIGHUP") else ())
    previous = {sig: signal.signal(sig, handler) for sig in signals}
    try:
        yield stop
    finally:
        for sig, old in previous.items():
            signal.signal(sig, old)


# ------------------------------------------------------------------------------------------------ commands

def cmd_publish(args: argparse.Namespace) -> int:
    from tacf.zenoh_options import options_from_args
    from tacf_clients.publisher import publish
    from tacf_clients.sources import SourceError, open_source
    from tacf_clients.zconfig import open_session
    from tacf_schemas.images import FrameError

    try:
        source = open_source(args.source, loop=args.loop, reconnect=args.reconnect)
    except (ValueError, FileNotFoundError) as exc:
        print(f"tacf publish: {exc}", file=sys.stderr)
        return 2
    try:
        with stop_on_signals() as stop, source, _reported("publish"), \
                open_session(options_from_args(args)) as session:
            if args.wait_subscriber > 0 and not _wait_subscriber(session, source, args, stop):
                return stop.exit_code   # stopped meanwhile; the session is closed on the way out of the `with`
            stats = publish(session, source, args.key, fps=args.fps, encoding=args.encoding, quality=args.quality,
                            max_frames=args.frames, stop=stop)
    except (SourceError, FrameError) as exc:       # FrameError: frames beyond the wire limits, which no service takes
        print(f"tacf publish: {exc}", file=sys.stderr)
        return 2
    if stats.frames == 0 and not stop.is_set():
        print(f"tacf publish: {args.source}: no frame could be read", file=sys.stderr)
        return 2
    reconnected = f", {source.reconnects} reconnections" if source.reconnects else ""
    print(f"published {stats.frames} frames in {stats.seconds:.1f} s ({stats.fps:.1f} fps, "
          f"{stats.bytes / 1e6:.1f} MB{reconnected}) on {args.key}")
    if not stats.matched:
        print(f"tacf publish: no subscriber ever listened on {args.key}: the frames reached nobody (no session "
              "follows the key, or access control keeps them from the network)", file=sys.stderr)
    if stop.is_set():
        print("tacf publish: interrupted", file=sys.stderr)
        return stop.exit_code
    return 0


def _wait_subscriber(session, source, args: argparse.Namespace, stop: threading.Event) -> bool:
    """Wait as --wait-subscriber says; False when stopped meanwhile (then nothing is to be published)."""
    import time

    from tacf_clients.publisher import FramePublisher

    print(f"waiting up to {args.wait_subscriber:g} s for a subscriber on {args.key}", file=sys.stderr, flush=True)
    deadline = time.monotonic() + args.wait_subscriber
    with FramePublisher(session, args.key) as probe:
        if source.live:     # read on meanwhile: a stream's buffers would keep the frames of the wait for later
            for _ in source.frames(should_stop=lambda: stop.is_set() or probe.matched or time.monotonic() > deadline):
                pass
        matched = probe.wait_matched(deadline - time.monotonic(), stop)
    if stop.is_set():
        print(f"stopped while waiting for a subscriber on {args.key}: nothing published", file=sys.stderr)
        return False
    if not matched:
        print(f"no subscriber on {args.key} after {args.wait_subscriber:g} s: publishing anyway", file=sys.stderr)
    return True


@contextmanager
def _client(args: argparse.Namespace, one_shot: bool = True, json_list: bool = False):
    """A TrackingClient from the command line's options.

    one_shot: the command queries once and exits, so it needs the whole network right after open. Unless told
    otherwise it runs as a Zenoh *client*: the node it connects to routes for it at once, whereas a peer reaches
    the other services through gossip only a moment after open (ZENOH.md 2.3), and missed one in 8 of 20
    measured `list`s.
    json_list: the command prints a JSON list, empty when no node is reachable (see _reported).
    """
    import dataclasses

    from tacf.zenoh_options import options_from_args
    from tacf_clients.client import TrackingClient

    options = options_from_args(args)
    if one_shot and options.mode is None and options.config_file is None:
        options = dataclasses.replace(options, mode="client")
    with _reported(args.command, json_list), \
            TrackingClient(options, node=_queried_node(args), timeout=args.timeout) as client:
        yield client


def _queried_node(args: argparse.Namespace) -> str | None:
    """--node for a command that queries: 'auto' (least loaded) is a choice of start, made there; here it is every
    node, as no --node is."""
    from tacf_clients.client import LEAST_LOADED

    return None if args.node == LEAST_LOADED else args.node


@contextmanager
def _reported(command: str, json_list: bool = False):
    """A client-side error (a bad id, no service answering, no Zenoh node reachable...) as one line on stderr
    and exit code 1, instead of a traceback; Zenoh settings it refused as a usage error, exit code 2.
    json_list: the command's output is a JSON list of services, so no node reachable, where no service can answer,
    prints [] as no service answering does: a script reading it gets JSON either way."""
    from tacf_clients.errors import TacfError, ZenohSettingsError, ZenohUnavailable
    from tacf_clients.watch import printable

    try:
        yield
    except ZenohSettingsError as exc:
        print(f"tacf {command}: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    except TacfError as exc:
        if json_list and isinstance(exc, ZenohUnavailable):
            print("[]")
        # a service's error message, from whoever answered on tacf/*/control/*
        print(f"tacf {command}: {type(exc).__name__}: {printable(exc)}", file=sys.stderr)
        raise SystemExit(1) from None


def _print_info(info, as_json: bool, verb: str = "") -> None:
    from tacf_clients.watch import describe_session

    if as_json:
        print(info.model_dump_json())
    else:
        print((verb + " " if verb else "") + describe_session(info))


def _note_other_frame(asked: int | None, info) -> None:
    """Say so when the box went onto another frame than the one named: the service no longer held it."""
    if asked is not None and info.init_seq is not None and info.init_seq != asked:
        print(f"note: the service did not hold frame {asked}; the box was applied to frame {info.init_seq} "
              f"(a client that sends the frame with the request, as the dashboard does, avoids this)",
              file=sys.stderr)


def cmd_start(args: argparse.Namespace) -> int:
    with _client(args) as client:
        info = client.start(args.key, args.box, seq=args.seq, profile=args.profile, sid=args.sid,
                            overrides=dict(args.overrides), node=args.node)
        _print_info(info, args.json, "started")
        _note_other_frame(args.seq, info)
    return 0


def cmd_stop(args: argparse.Namespace) -> int:
    with _client(args) as client:
        _print_info(client.stop(args.sid), args.json, "stopped")
    return 0


def cmd_reinit(args: argparse.Namespace) -> int:
    with _client(args) as client:
        info = client.reinit(args.sid, args.box, seq=args.seq)
        _print_info(info, args.json, "re-initialised")
        _note_other_frame(args.seq, info)
    return 0


def cmd_status(args: argparse.Namespace) -> int:
    with _client(args) as client:
        _print_info(client.status(args.sid), args.json)
    return 0


def cmd_list(args: argparse.Namespace) -> int:
    from tacf_clients.client import node_load
    from tacf_clients.errors import NoService
    from tacf_clients.watch import session_table

    with _client(args, json_list=args.json) as client:
        try:
            listings = client.services()
        except NoService:           # the --node named did not answer: as no service at all, [] with --json
            listings = []
    if args.json:
        print(json.dumps([json.loads(listing.model_dump_json()) for listing in listings]))
    elif listings:
        sessions = [info for listing in listings for info in listing.sessions]
        nodes = ", ".join(f"{lst.node} ({len(lst.sessions)}/{lst.max_sessions}, load {node_load(lst):.2f})"
                          for lst in listings)
        print(f"services: {nodes}")
        print(session_table(sessions) if sessions else "no sessions")
    if not listings:        # unlike a service without sessions, no service at all is an error, for scripts too
        named = f" (node {args.node!r})" if args.node else ""
        print(f"tacf {args.command}: no tracking service answered{named}", file=sys.stderr)
        return 1
    return 0


def cmd_nodes(args: argparse.Namespace) -> int:
    if args.follow:
        return _follow_nodes(args)
    from tacf_clients.client import node_load
    from tacf_clients.errors import TacfError
    from tacf_clients.watch import columns

    with _client(args, json_list=args.json) as client:
        # --node (accepted, not advertised) shows that service only: the list query asks it alone, and every
        # other live service showed as "no answer"
        alive = [node for node in client.alive_nodes() if client.node in (None, node)]
        listings: dict[str, list] = {}
        try:
            answers = client.services()     # a row per service that answers, even two under one node id
        except TacfError:
            if not alive:
                raise
            answers = []                    # alive but none answered: each gets its "no answer" row
        for listing in answers:
            listings.setdefault(listing.node, []).append(listing)
    rows = []
    for node in sorted(set(alive) | set(listings)):
        for lst in listings.get(node, [None]):  # None: its token is up but it did not answer the list query in time
            rows.append({"node": node, "alive": node in alive, "answers": lst is not None,
                         "sessions": len(lst.sessions) if lst else None,
                         "max_sessions": lst.max_sessions if lst else None,
                         "load": round(node_load(lst), 3) if lst else None})
    if args.json:
        print(json.dumps(rows))
    elif rows:
        print(columns([("NODE", "ALIVE", "SESSIONS", "LOAD")] + [
            (r["node"], "yes" if r["alive"] else "no",
             f"{r['sessions']}/{r['max_sessions']}" if r["answers"] else "no answer",
             f"{r['load']:.2f}" if r["answers"] else "-") for r in rows]))
    if not rows:
        print(f"tacf {args.command}: no tracking service on the network", file=sys.stderr)
        return 1
    return 0


def _follow_nodes(args: argparse.Namespace) -> int:
    from datetime import datetime

    reader_gone = threading.Event()

    def show(node: str, alive: bool) -> None:
        now = datetime.now()
        try:
            if args.json:
                print(json.dumps({"time": now.timestamp(), "node": node, "alive": alive}), flush=True)
            else:
                print(f"{now:%H:%M:%S.%f}"[:-3] + f"  {'up  ' if alive else 'down'}  {node}", flush=True)
        except BrokenPipeError:     # `... | head -1`: on this Zenoh thread it was only logged, and the command ran on
            reader_gone.set()
            stop.set()

    # A peer: it links to every service (gossip), so the loss of the one it connected to is not the loss of all.
    with stop_on_signals() as stop, _client(args, one_shot=False) as client, client.watch_nodes(show):
        stop.wait(args.duration)
    if reader_gone.is_set():
        raise BrokenPipeError       # ends as a filter whose reader left (tacf.cli: exit 141)
    return 0


def cmd_watch(args: argparse.Namespace) -> int:
    from tacf.zenoh_options import options_from_args
    from tacf_clients.watch import watch

    with stop_on_signals() as stop, _reported("watch"):
        return watch(options_from_args(args), sid=args.sid, node=_queried_node(args), interval=args.interval,
                     duration=args.duration, stop=stop)


def cmd_demo(args: argparse.Namespace) -> int:
    from tacf_clients.demo import DemoOptions, run_demo

    with stop_on_signals() as stop:
        try:
            report = run_demo(DemoOptions(source=args.source, box=args.box, seconds=args.seconds, fps=args.fps,
                                          encoding=args.encoding, profile=args.profile, every=args.every),
                              stop=stop)
        except (ValueError, FileNotFoundError) as exc:     # the source cannot be opened or has no frames
            if stop.is_set():       # Ctrl-C while FFmpeg tried to open a stream
                print("tacf demo: interrupted", file=sys.stderr)
                return stop.exit_code
            print(f"tacf demo: {exc}", file=sys.stderr)
            return 2
    if report.interrupted:
        return stop.exit_code
    return 0 if report.ok else 1


def cmd_mavlink(args: argparse.Namespace) -> int:
    from pathlib import Path

    from tacf.zenoh_options import options_from_args
    try:
        from tacf_clients.mavlink import MavlinkCamera, signing_key_from_passphrase
    except ImportError as exc:
        print(f"tacf mavlink: {exc}; install it with: {_install_extra('mavlink')}", file=sys.stderr)
        return 2
    with stop_on_signals() as stop, _reported("mavlink"):
        try:
            key = None
            if args.signing_passphrase_file:
                key = signing_key_from_passphrase(Path(args.signing_passphrase_file).read_text().strip())
            camera = MavlinkCamera(args.link, args.key, options=options_from_args(args), sid=args.sid,
                                   node=args.node, profile=args.profile, system=args.system,
                                   component=args.component, baud=args.baud, signing_key=key)
        except (OSError, ValueError) as exc:
            print(f"tacf mavlink: {exc}", file=sys.stderr)
            return 2
        with camera:
            print(f"tacf mavlink: camera component {args.system}/{args.component} for {args.key} on {args.link} "
                  "(Ctrl-C to stop)", flush=True)
            camera.serve(stop)
    return 0


def cmd_foxglove(args: argparse.Namespace) -> int:
    from tacf.zenoh_options import options_from_args
    try:
        from tacf_clients.foxglove_bridge import FoxgloveBridge
    except ImportError as exc:
        print(f"tacf foxglove: {exc}; install it with: {_install_extra('foxglove')}", file=sys.stderr)
        return 2
    from tacf_clients.dashboard import Dashboard
    from tacf_clients.dashboard_http import tls_context
    from tacf_clients.zconfig import viewer_options

    try:
        if args.keyfile and not args.certfile:
            raise ValueError("--keyfile needs --certfile")
        tls = tls_context(args.certfile, args.keyfile) if args.certfile else None
    except (OSError, ValueError) as exc:       # ssl.SSLError is an OSError
        print(f"tacf foxglove: {exc}", file=sys.stderr)
        return 2
    with stop_on_signals() as stop, _reported("foxglove"):
        try:
            with Dashboard(viewer_options(options_from_args(args)), image_keys=args.keys, node=args.node,
                           max_frame_fps=args.image_hz) as board, \
                 FoxgloveBridge(board, host=args.host, port=args.port, image_hz=args.image_hz,
                                control=args.control, tls=tls, record=args.record,
                                allow_origins=args.allow_origins) as bridge:
                scheme = "wss" if tls else "ws"
                services = "with" if bridge.control else "without"
                print(f"tacf foxglove: open {scheme}://{args.host}:{bridge.port} in Foxglove or Lichtblick (Open "
                      f"connection > Foxglove WebSocket), {services} the control services (Ctrl-C to stop)", flush=True)
                if args.record:
                    print(f"tacf foxglove: recording to {args.record}", flush=True)
                bridge.serve(stop)
        except (OSError, RuntimeError, ValueError) as exc:
            print(f"tacf foxglove: {exc}", file=sys.stderr)
            return 2
    return 0


def cmd_dashboard(args: argparse.Namespace) -> int:
    import os
    import socket
    from pathlib import Path

    from tacf.zenoh_options import options_from_args
    from tacf_clients.dashboard_access import TOKEN_ENV, DashboardAccess
    from tacf_clients.dashboard_http import serve, tls_context
    from tacf_clients.zconfig import viewer_options

    def ready(url: str) -> None:
        print(f"tacf dashboard: open {url} in a browser (Ctrl-C to stop)", flush=True)
        if args.host in ("0.0.0.0", "", "::"):
            print(f"tacf dashboard: from another machine: {url.replace('127.0.0.1', socket.gethostname(), 1)}",
                  flush=True)

    try:
        token = (Path(args.token_file).read_text().strip() if args.token_file else os.environ.get(TOKEN_ENV)) or None
        access = DashboardAccess.for_address(args.host, token, args.allow_hosts)
        if args.keyfile and not args.certfile:
            raise ValueError("--keyfile needs --certfile")
        tls = tls_context(args.certfile, args.keyfile) if args.certfile else None
    except (OSError, ValueError) as exc:       # ssl.SSLError is an OSError
        print(f"tacf dashboard: {exc}", file=sys.stderr)
        return 2
    with stop_on_signals() as stop, _reported("dashboard"):
        try:
            return serve(viewer_options(options_from_args(args)), host=args.host, port=args.port, image_keys=args.keys,
                         node=args.node, history_s=args.history * 60, access=access, tls=tls, stop=stop,
                         on_ready=ready)
        except OSError as exc:
            print(f"tacf dashboard: cannot serve on {args.host}:{args.port}: {exc}", file=sys.stderr)
            return 2
        except ValueError as exc:
            print(f"tacf dashboard: {exc}", file=sys.stderr)
            return 2
