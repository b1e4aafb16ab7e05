"""Who may use the dashboard's web page: an access token, and the host names a page may be served under.

The page can start and stop sessions and shows every camera, so it is not left open:
- Served on a loopback address (the default, 127.0.0.1), only this machine reaches it. What remains is another
  web page in the user's own browser: cross-site POSTs are refused by their content type (dashboard_http.py),
  and a page that rebinds its own DNS name to 127.0.0.1 (DNS rebinding) is refused by its Host header, which
  must name a loopback address or a host given with `--allow-host`.
- Served on any other address, a token is required, one is made up when none is given (as Jupyter does), and
  the printed URL carries it. A browser that opens `/?token=T` gets it as an HttpOnly, SameSite=Strict cookie
  (which no other site's request carries) and is sent on to the page without it; the cookie's name carries the
  server's port, since browsers keep a host's cookies for all its ports (two dashboards on one machine would
  otherwise log each other out). Programs send `Authorization: Bearer T` (Prometheus: `authorization:
  {credentials_file: ...}`), or, if they cannot, add `?token=T` to what they fetch (VLC on /mjpeg/...).
Plain HTTP shows the token to anyone on the path: across a network, serve HTTPS (`--certfile`, `--keyfile`; the
cookie is then Secure) or reach it through an SSH tunnel.
"""
from __future__ import annotations

import hmac
import ipaddress
import re
import secrets

COOKIE = "tacf_dashboard_token"
TOKEN_ENV = "TACF_DASHBOARD_TOKEN"
LOOPBACK_NAMES = frozenset({"localhost", "localhost.localdomain", "ip6-localhost"})
_TOKEN_RE = re.compile(r"[A-Za-z0-9._~-]{16,256}")     # unreserved in URLs, plain in cookies


def is_loopback(host: str) -> bool:
    """True for a loopback name or address (127.0.0.0/8, ::1), with or without brackets."""
    host = host.strip("[]").lower()
    if host in LOOPBACK_NAMES or host.endswith(".localhost"):
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def host_name(host_header: str) -> str:
    """The name in a Host header, without its port: 'a:8080' -> 'a', '[::1]:8080' -> '::1'."""
    host = host_header.strip().lower()
    if host.startswith("["):
        return host[1:host.find("]")] if "]" in host else host[1:]
    return host.rsplit(":", 1)[0] if host.count(":") == 1 else host


class DashboardAccess:
    """The rule for one server: `token` None means none is asked (loopback only, then the Host header is checked)."""

    def __init__(self, token: str | None = None, allow_hosts=()):
        if token is not None and not _TOKEN_RE.fullmatch(token):
            raise ValueError("a dashboard token needs 16 to 256 characters from A-Z a-z 0-9 . _ ~ -")
        self.token = token
        self.allow_hosts = frozenset(host_name(h) for h in allow_hosts)

    @classmethod
    def for_address(cls, host: str, token: str | None = None, allow_hosts=()) -> "DashboardAccess":
        """The default for serving on `host`: a new random token unless it is a loopback address or one is given."""
        if token is None and not is_loopback(host):
            token = secrets.token_urlsafe(24)
        return cls(token, allow_hosts)

    def host_allowed(self, host_header: str | None) -> bool:
        if self.token is not None:
            return True                     # the token decides; the cookie never reaches another site's name
        name = host_name(host_header or "")
        return is_loopback(name) or name in self.allow_hosts

    def is_token(self, candidate: str | None) -> bool:
        return self.token is None or (candidate is not None
                                      and hmac.compare_digest(candidate.encode(), self.token.encode()))

    @staticmethod
    def cookie_name(port: int) -> str:
        return f"{COOKIE}_{port}"

    def presented(self, headers, port: int) -> str | None:
        """The token a request carries: an `Authorization: Bearer` header, else the cookie of the server on
        `port`."""
        scheme, _, value = (headers.get("Authorization") or "").partition(" ")
        if scheme.lower() == "bearer" and value.strip():
            return value.strip()
        # not SimpleCookie: it drops the whole header for one malformed cookie, and browsers send the cookies of
        # every port of this host (other web apps' too)
        for pair in (headers.get("Cookie") or "").split(";"):
            name, sep, value = pair.partition("=")
            if sep and name.strip() == self.cookie_name(port):
                return value.strip()
        return None

    def cookie(self, port: int, secure: bool = False) -> str:
        """The login cookie of the server on `port`; `secure` (over HTTPS) keeps browsers from ever sending it
        over plain HTTP."""
        return (f"{self.cookie_name(port)}={self.token}; Path=/; HttpOnly; SameSite=Strict"
                + ("; Secure" if secure else ""))
