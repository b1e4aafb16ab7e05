"""Zenoh configuration for the client side: the options of `tacf serve` (tacf.zenoh_options), with a loopback
default.

Layering (as in zenoh-python's examples/common): `--zenoh-config FILE` first, then the command-line overrides.
Without a file, the defaults keep everything on this machine: peer mode, multicast scouting off, connect to the
service's default endpoint tcp/127.0.0.1:7447, and listen on a random loopback port so that other loopback peers
(for example a service's worker processes) can reach this session through gossip (ZENOH.md §2.3).

Zenoh itself is imported only when a config is built, so that `tacf --help` or `tacf eval` (which register
these arguments) never load it.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
from typing import TYPE_CHECKING

from tacf.argument_types import config_file, endpoint
from tacf.zenoh_options import ZenohOptions, base_config, endpoint_host_port, unreadable_file, zenoh_error_text
from tacf_clients.dashboard_access import is_loopback
from tacf_clients.errors import ZenohSettingsError, ZenohUnavailable

if TYPE_CHECKING:
    import zenoh

DEFAULT_CONNECT = "tcp/127.0.0.1:7447"
LOOPBACK_LISTEN = "tcp/127.0.0.1:0"
# A late listener costs at most ~1 s with this backoff instead of up to 4 s (ZENOH.md §2.4).
FAST_RETRY = {"period_init_ms": 100, "period_max_ms": 1000, "period_increase_factor": 2}


def make_config(options: ZenohOptions | None = None) -> "zenoh.Config":
    """Build a `zenoh.Config` from `options` (None: loopback defaults).

    ZenohSettingsError if Zenoh refuses the config file (missing, malformed) or an endpoint."""
    import zenoh

    options = options or ZenohOptions()
    try:
        return _config(options)
    except zenoh.ZError as exc:
        raise ZenohSettingsError(f"bad Zenoh configuration{options.refusal(exc)}") from exc


def _config(options: ZenohOptions) -> "zenoh.Config":
    conf = base_config(options.config_file)
    if options.config_file is None:
        conf.insert_json5("connect/retry", json.dumps(FAST_RETRY))
        conf.insert_json5("connect/endpoints", json.dumps([DEFAULT_CONNECT]))
        conf.insert_json5("listen/endpoints", json.dumps([LOOPBACK_LISTEN]))
    if options.mode is not None or options.config_file is None:
        conf.insert_json5("mode", json.dumps(options.mode or "peer"))
    if options.connect is not None:
        conf.insert_json5("connect/endpoints", json.dumps(list(options.connect)))
        if options.config_file is None and not options.listen and not all(map(_is_loopback, options.connect)):
            # Connecting to another machine: advertising a loopback locator to it would be wrong.
            conf.insert_json5("listen/endpoints", "[]")
    if options.listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(options.listen)))
    for key, value in options.extra:
        conf.insert_json5(key, value)
    return conf


def viewer_options(options: ZenohOptions) -> ZenohOptions:
    """The options of a client that shows frames (dashboard, Foxglove bridge). From another machine (every
    --connect endpoint off this host, no --listen, --mode or config file) it runs as a Zenoh *client*: it listens
    nowhere then, and as a peer it would get boxes (the service routes its workers') but no frames, since a
    camera on the edge box listens on loopback at most (nowhere when it connects off-host) and peers do not relay
    for peers; the box it connects to routes everything for a client (measured across two network namespaces,
    docs/thin_link.md)."""
    remote = options.connect and not any(map(_is_loopback, options.connect))
    if remote and options.mode is None and options.config_file is None and not options.listen:
        return dataclasses.replace(options, mode="client")
    return options


def _is_loopback(endpoint: str) -> bool:
    """Whether the endpoint is on this host: a Unix socket, localhost, 127.x.y.z or ::1 (localhost was taken for
    another machine's name: a dashboard connecting to tcp/localhost:7447 ran as a Zenoh client)."""
    return endpoint.startswith("unixsock-stream/") or is_loopback(endpoint_host_port(endpoint)[0])


def add_zenoh_arguments(parser: argparse.ArgumentParser, mode_default: str = "peer") -> None:
    """Add --connect, --listen, --zenoh-config (the same names as `tacf serve`) and --mode; `mode_default` says
    in the help which mode the command opens without --mode or a config file."""
    group = parser.add_argument_group("zenoh")
    group.add_argument("--connect", "-e", action="append", default=[], type=endpoint, metavar="ENDPOINT",
                       help=f"endpoint to connect to, repeatable (default {DEFAULT_CONNECT})")
    group.add_argument("--listen", "-l", action="append", default=[], type=endpoint, metavar="ENDPOINT",
                       help=f"endpoint to listen on, repeatable (default {LOOPBACK_LISTEN} when connecting on "
                            "loopback)")
    group.add_argument("--zenoh-config", type=config_file, metavar="FILE",
                       help="Zenoh JSON5 config file (router, TLS, access control); flags override it")
    group.add_argument("--mode", choices=("peer", "client"), help=f"Zenoh session mode (default {mode_default})")


def open_session(options: "ZenohOptions | zenoh.Config | None" = None) -> "zenoh.Session":
    """Open a Zenoh session; use it as a context manager so it is always closed (ZENOH.md §8).

    ZenohUnavailable if it cannot open, as a client with no node reachable does at once (ZENOH.md §1);
    ZenohSettingsError if Zenoh refuses the settings (a listen endpoint taken, say)."""
    import zenoh

    conf = options if isinstance(options, zenoh.Config) else make_config(options)
    if problem := unreadable_file(conf):
        raise ZenohSettingsError(problem)
    _check_protocols(conf)
    try:
        return zenoh.open(conf)
    except zenoh.ZError as exc:
        reason = zenoh_error_text(exc)
        if reason.startswith("Unable to connect"):
            raise ZenohUnavailable(f"no Zenoh node reachable: {reason}") from exc
        raise ZenohSettingsError(f"cannot open a Zenoh session: {reason}") from exc


def _check_protocols(conf) -> None:
    """ZenohSettingsError naming a connect endpoint whose protocol transport/link/protocols leaves out (tcp/ with a
    TLS-only file): Zenoh skips it, and then says only "Unable to connect" as a client, nothing as a peer."""
    protocols = json.loads(conf.get_json("transport/link/protocols"))
    endpoints = json.loads(conf.get_json("connect/endpoints"))
    if not protocols or not isinstance(endpoints, list):      # a per-mode {peer: [...], ...} list: Zenoh's to pick
        return
    for given in endpoints:
        if given.split("/", 1)[0] not in protocols:
            raise ZenohSettingsError(f"cannot connect to {given}: transport/link/protocols allows only "
                                     f"{', '.join(protocols)}")
