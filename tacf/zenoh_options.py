"""ZenohOptions: how a session of the `tacf` command reaches the Zenoh network. One definition for `tacf serve`
(tacf_service.config) and the client commands (tacf_clients.zconfig); each side turns it into a zenoh.Config
with its own defaults.

It lives in tacf, next to tacf.cli, because the two sides never import each other (the client side never loads
tacf_service) and importing tacf_schemas loads pydantic, which `tacf --help` does without. Zenoh itself is
imported only when a config is built.
"""
from __future__ import annotations

import argparse
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import zenoh

# Zenoh's errors end with the Rust source line that raised them ("... at /root/.cargo/.../unicast.rs:338."): noise.
_RUST_LOCATION = re.compile(r"\s*at \S+\.rs:\d+\.?")
# A value Zenoh refuses comes wrapped: Json5Err(Message { msg: "...", location: Some(...) }); the msg says it all.
_JSON5_MESSAGE = re.compile(r'Json5Err\(Message \{ msg: "(?P<msg>(?:[^"\\]|\\.)*)".*', re.DOTALL)
# A config file's comes as JSON error: Message { msg: "...", location: Some(Location { line: L, column: C }) }; there
# the place helps (for a field given twice, that of the object holding it).
_FILE_MESSAGE = re.compile(r'JSON error: Message \{ msg: "(?P<msg>(?:[^"\\]|\\.)*)", '
                           r'location: Some\(Location \{ line: (?P<line>\d+), column: (?P<column>\d+) \}\) \}')
# The files a session's settings name: Zenoh reports one missing or unreadable on a connecting side only as "Unable
# to connect" (a client at once, a service's worker after its 5 s connect timeout)
FILE_SETTINGS = ("transport/link/tls/root_ca_certificate", "transport/link/tls/connect_certificate",
                 "transport/link/tls/connect_private_key", "transport/link/tls/listen_certificate",
                 "transport/link/tls/listen_private_key", "transport/auth/usrpwd/dictionary_file")
# Protocols whose address is HOST:PORT, which Zenoh resolves as Rust's ToSocketAddrs does: split at the last ':', the
# port a number 0-65535, the host a name or an address (IPv6 in brackets). Zenoh checks only <protocol>/<address> when
# a session opens: a peer given "tcp/nonsense" opened without a word and never connected, and `tacf serve` started.
HOST_PORT_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")
_PORT = re.compile(r"\+?\d{1,5}")


def endpoint_host_port(endpoint: str) -> tuple[str, str]:
    """(host, port) of a PROTOCOL/HOST:PORT[?metadata][#config] endpoint, split as Zenoh splits them; an IPv6 host
    keeps its brackets."""
    host, _, port = re.split(r"[?#]", endpoint.partition("/")[2], maxsplit=1)[0].rpartition(":")
    return host, port


def endpoint_problem(endpoint: str) -> str | None:
    """Why `endpoint` can never be reached or listened on, naming it and the expected form; None if it may be (the
    other protocols, unixsock-stream/PATH among them, and an endpoint without a protocol are left to Zenoh)."""
    protocol = endpoint.partition("/")[0]
    if protocol not in HOST_PORT_PROTOCOLS:
        return None
    host, port = endpoint_host_port(endpoint)
    if host and _PORT.fullmatch(port) and int(port) <= 65535:
        return None
    return (f"bad Zenoh endpoint {endpoint!r}: expected {protocol}/HOST:PORT, e.g. {protocol}/192.168.1.10:7447, "
            f"{protocol}/[::1]:7447 or {protocol}/edge.local:7447")


@dataclass(frozen=True)
class ZenohOptions:
    """What the command line says about Zenoh; what it leaves unsaid, each side decides. Pickled into the
    service's worker processes.

    connect: endpoints such as ``tcp/10.0.0.5:7447``; None = the side's default, () = none. A host:port endpoint
        whose port is missing or not a number is refused (ValueError, see endpoint_problem).
    listen: endpoints to listen on; empty = the side's default. One endpoint may be given as a string, here and above.
    config_file: a Zenoh JSON5 configuration (router, TLS, access control); the other fields override it. None = no
        file; "" is refused (ValueError).
    mode: "peer", "client" or "router"; None keeps the file's mode (or peer without a file).
    extra: (key path, JSON5 value) pairs, applied last (a service applies them to its own session, not its workers').
    """

    connect: tuple[str, ...] | None = None
    listen: tuple[str, ...] = ()
    config_file: str | Path | None = None
    mode: str | None = None
    extra: tuple[tuple[str, str], ...] = ()

    def __post_init__(self) -> None:
        # One endpoint given as a string is that endpoint: taken as a sequence, its characters were the endpoints.
        for name in ("connect", "listen"):
            if isinstance(getattr(self, name), str):
                object.__setattr__(self, name, (getattr(self, name),))
        # As on the command line (tacf.argument_types.config_file): an empty path is almost always a variable left
        # unset, and it meant Zenoh's defaults without a word (for a client: listening on every interface).
        if self.config_file == "":
            raise ValueError("config_file is empty: give a Zenoh JSON5 file, or None for the defaults")
        for endpoint in (*(self.connect or ()), *self.listen):
            if problem := endpoint_problem(endpoint):
                raise ValueError(problem)

    def refusal(self, exc: BaseException) -> str:
        """Why Zenoh refused these settings, naming the config file when there is one: ' (FILE): reason'."""
        where = f" ({self.config_file})" if self.config_file else ""
        return f"{where}: {zenoh_error_text(exc)}"

    @classmethod
    def loopback(cls, port: int) -> "ZenohOptions":
        """Options for a session that connects to a service listening on ``tcp/127.0.0.1:<port>``."""
        return cls(connect=(f"tcp/127.0.0.1:{port}",))

    @classmethod
    def listener(cls, endpoint: str) -> "ZenohOptions":
        """Options for a session that only listens on `endpoint` (e.g. a test's hub)."""
        return cls(connect=(), listen=(endpoint,))


def options_from_args(args: argparse.Namespace) -> ZenohOptions:
    """The options given by --connect, --listen, --zenoh-config and --mode (the names every command uses)."""
    return ZenohOptions(connect=tuple(getattr(args, "connect", None) or ()) or None,
                        listen=tuple(getattr(args, "listen", None) or ()),
                        config_file=getattr(args, "zenoh_config", None),
                        mode=getattr(args, "mode", None))


def base_config(config_file: str | Path | None) -> "zenoh.Config":
    """The config file's settings; without a file, Zenoh's defaults with multicast scouting off (no UDP
    multicast on every interface, ZENOH.md §1). Each side then adds its own defaults and the overrides."""
    import zenoh

    if config_file:
        return zenoh.Config.from_file(str(config_file))
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


def unreadable_file(conf: "zenoh.Config") -> str | None:
    """What is wrong with a file the settings give that is not there or that this user may not read (a key that
    make-certs.sh, run as root, left readable by root only), naming the setting and the file; None if nothing."""
    for key in FILE_SETTINGS:
        path = json.loads(conf.get_json(key))
        if not (isinstance(path, str) and path):
            continue
        if not Path(path).is_file():
            return f"{key}: no such file: {path}"
        try:
            Path(path).open("rb").close()
        except OSError as exc:
            return f"{key}: cannot read {path}: {(exc.strerror or str(exc)).lower()}"
    return None


def zenoh_error_text(exc: BaseException) -> str:
    """A zenoh.ZError as one line for a person: without the Rust source locations, the JSON5 wrappers and the line
    breaks (a JSON5 syntax error spans lines)."""
    text = _RUST_LOCATION.sub("", str(exc))
    if match := _JSON5_MESSAGE.search(text):
        text = text[:match.start()] + match.group("msg")
    elif match := _FILE_MESSAGE.search(text):
        text = f"{text[:match.start()]}{match['msg']} (line {match['line']}, column {match['column']})"
    return " ".join(text.split())
