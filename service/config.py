"""Zenoh configurations: the service's (from the command line) and its worker processes'.

The service is a Zenoh peer that listens on loopback only by default. Each worker process opens its own
session in *client* mode connected to one of the service's endpoints (when it listens on none, to the router it
connects to: worker_endpoints); a peer routes for its clients, so a worker receives frames from any camera the
service can reach and its boxes reach every subscriber.
"""
from __future__ import annotations

import json
import re

from tacf.zenoh_options import ZenohOptions, base_config

DEFAULT_LISTEN = "tcp/127.0.0.1:7447"

_UNSPECIFIED_HOSTS = {"0.0.0.0": "127.0.0.1", "[::]": "[::1]"}
# TLS and QUIC to an IPv6 literal fail in zenoh 1.x whatever the certificate says (the bracketed address is not
# taken for an IP address): a worker reaches a [::] listener as localhost, which make-certs.sh certifies
_UNSPECIFIED_HOSTS_SECURE = {"0.0.0.0": "127.0.0.1", "[::]": "localhost"}
_ENDPOINT_RE = re.compile(r"^(?P<proto>[a-z0-9]+)/(?P<host>\[[^\]]*\]|[^:/]+):(?P<port>\d+)(?P<rest>[#?].*)?$")


def _listen_endpoints(options: ZenohOptions) -> tuple[str, ...]:
    """CLI listen endpoints; with no --listen, --connect or config file: loopback only (DEFAULT_LISTEN).
    With --connect (e.g. to a router on this host) or a config file, nothing is added."""
    if options.listen:
        return options.listen
    if options.config_file or options.connect:
        return ()
    return (DEFAULT_LISTEN,)


def service_config(options: ZenohOptions):
    """The service session's config: the file (if any), then the command-line overrides."""
    conf = base_config(options.config_file)
    if options.mode is not None or options.config_file is None:     # without --mode, a file keeps its own
        conf.insert_json5("mode", json.dumps(options.mode or "peer"))
    listen = _listen_endpoints(options)
    if listen or options.config_file is None:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if options.connect or options.config_file is None:
        conf.insert_json5("connect/endpoints", json.dumps(list(options.connect or ())))
    for key, value in options.extra:
        conf.insert_json5(key, value)
    return conf


def own_endpoints(options: ZenohOptions) -> list[str]:
    """The service's listen endpoints as a process on this host reaches them (unspecified hosts mapped to
    loopback); [] when it listens on none with a fixed port."""
    listen = list(_listen_endpoints(options))
    if not listen and options.config_file:
        listen = _configured_list(options, "listen/endpoints")
    endpoints = []
    for endpoint in listen:
        if endpoint.startswith("unixsock-stream/"):     # a socket file on this host: reached as it is
            endpoints.append(endpoint)
            continue
        m = _ENDPOINT_RE.match(endpoint)
        if not m or m.group("port") == "0":
            continue
        unspecified = _UNSPECIFIED_HOSTS_SECURE if m.group("proto") in ("tls", "quic") else _UNSPECIFIED_HOSTS
        host = unspecified.get(m.group("host"), m.group("host"))
        endpoints.append(f"{m.group('proto')}/{host}:{m.group('port')}{m.group('rest') or ''}")
    return endpoints


class WorkerConnectError(ValueError):
    """The worker processes' settings do not let them into the service (a usage error)."""


def worker_endpoints(options: ZenohOptions) -> list[str]:
    """Endpoints a worker process on this host connects to: the service's own (own_endpoints); without any, the
    service's connect endpoints (a router). WorkerConnectError when there is neither."""
    if endpoints := own_endpoints(options):
        return endpoints
    connect = list(options.connect or ())
    if not connect and options.config_file:
        connect = _configured_list(options, "connect/endpoints")
    if connect:
        return connect
    raise WorkerConnectError("worker processes need an endpoint of the service: give --listen with a fixed port "
                             "(or --connect to a router)")


def worker_config(options: ZenohOptions, endpoints: list[str]):
    """A worker's config: client of the service (same file, so TLS/auth settings carry over)."""
    conf = base_config(options.config_file)
    # The service's access control guards its own session, the entry point. Applied again in the worker, it
    # would deny the link to the service (which authenticates as no user), and the worker would get no frames.
    conf.insert_json5("access_control/enabled", "false")
    conf.insert_json5("id", "null")     # a file's fixed Zenoh id is the service's: each worker draws its own
    conf.insert_json5("mode", json.dumps("client"))
    conf.insert_json5("listen/endpoints", json.dumps([]))
    conf.insert_json5("connect/endpoints", json.dumps(endpoints))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/timeout_ms", "5000")
    return conf


def _configured_list(options: ZenohOptions, key: str) -> list[str]:
    """The config file's endpoint list at `key`; a per-mode list ({router: [...], peer: [...]}) is read for the mode
    the service runs in: --mode, or else the file's own."""
    conf = base_config(options.config_file)
    value = json.loads(conf.get_json(key))
    if isinstance(value, dict):
        value = value.get(options.mode or json.loads(conf.get_json("mode")), [])
    return [str(v) for v in value or []]
