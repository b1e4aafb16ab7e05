"""Run `tacf serve` as a child process on a free loopback port: for `tacf demo` and for tests.

    with LocalService(node="demo") as service:          # started, not yet answering
        with open_session(service.options) as session:   # service.options: ZenohOptions that connect to it
            service.wait_ready(session)                  # returns once the service answers a list query
    # SIGTERM, then SIGKILL after a grace period: the child never outlives the block; its log (in the temporary
    # folder) goes with it unless it failed

The child is a fresh interpreter (subprocess, not fork), so it is safe to start even after this process has
opened Zenoh sessions (ZENOH.md §2.5).
"""
from __future__ import annotations

import logging
import os
import random
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from tacf_clients.zconfig import ZenohOptions

log = logging.getLogger(__name__)


# Ports are picked below the kernel's ephemeral range: a port 0 bind would take one from inside it, where the kernel
# also picks the local port of every outgoing connection, and one took such a port between the check and the
# child service's bind (seen once in CI: "Address already in use").
EPHEMERAL_RANGE_FILE = Path("/proc/sys/net/ipv4/ip_local_port_range")
EPHEMERAL_LOW_ELSEWHERE = 49152                 # the IANA dynamic range, which macOS and Windows use
PICK_SPAN = 12_000                              # 20768-32767 under Linux's default range: clear of 7447 and its kin
_handed_out: set[int] = set()                   # never the same port twice in one process, bound yet or not
_system_random = random.SystemRandom()          # a test's random.seed() must not make two runs pick alike


def ephemeral_range_start() -> int:
    """The lowest port the kernel picks by itself for port 0 binds and outgoing connections."""
    try:
        return int(EPHEMERAL_RANGE_FILE.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return EPHEMERAL_LOW_ELSEWHERE


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago, from below the ephemeral range where it can be."""
    start = ephemeral_range_start()
    low, high = max(1024, start - PICK_SPAN), max(1024, start)
    picks = [port for port in _system_random.sample(range(low, high), k=min(64, high - low)) if port not in _handed_out]
    for port in picks + [0]:                    # port 0 last: a range squeezed to nothing still gets a port
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
            try:
                sock.bind(("127.0.0.1", port))
            except OSError:
                continue
            chosen = sock.getsockname()[1]
        _handed_out.add(chosen)
        return chosen
    raise OSError("no free TCP port on 127.0.0.1")


class LocalServiceError(RuntimeError):
    """The child service did not come up, or exited early."""


class LocalService:
    """`tacf serve --listen tcp/127.0.0.1:<port> --node <node> [extra args]` in a child process."""

    def __init__(self, node: str = "local", port: int | None = None, extra_args: tuple[str, ...] = (),
                 ready_timeout: float = 60.0, log_path: Path | None = None, env: dict[str, str] | None = None):
        self.node, self.port = node, port or free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.extra_args, self.ready_timeout = tuple(extra_args), ready_timeout
        self.log_path = log_path or Path(tempfile.gettempdir()) / f"tacf-serve-{node}-{self.port}.log"
        self._own_log = log_path is None        # made up here: removed after a clean stop, kept after a failure
        self.env = env
        self.process: subprocess.Popen | None = None
        self.returncode: int | None = None       # the child's exit code once stopped

    @property
    def options(self) -> ZenohOptions:
        """Zenoh options for a session that connects to this service."""
        return ZenohOptions.loopback(self.port)

    @property
    def command(self) -> list[str]:
        return [sys.executable, "-m", "tacf.cli", "serve", "--listen", self.endpoint, "--node", self.node,
                *self.extra_args]

    def start(self) -> "LocalService":
        log.debug("starting %s (log %s)", " ".join(self.command), self.log_path)
        env = dict(os.environ if self.env is None else self.env)
        env.setdefault("PYTHONUNBUFFERED", "1")
        with open(self.log_path, "wb") as log_file:
            # A process group of its own: a Ctrl-C in the terminal reaches the command that started it, which
            # stops it in order (after its sessions), not the service under that command's feet.
            self.process = subprocess.Popen(self.command, stdin=subprocess.DEVNULL, stdout=log_file,
                                            stderr=subprocess.STDOUT, env=env, start_new_session=True)
        return self

    def wait_ready(self, client_session, cancel: threading.Event | None = None) -> bool:
        """Poll the control queryable with `client_session` until this node answers: True; False if `cancel`
        was set first; LocalServiceError if the child exits or does not answer within `ready_timeout`."""
        from tacf_clients.client import TrackingClient
        from tacf_clients.errors import TacfError

        deadline = time.monotonic() + self.ready_timeout
        client = TrackingClient(session=client_session, node=self.node, timeout=1.0)
        while time.monotonic() < deadline:
            if cancel is not None and cancel.is_set():
                return False
            self.check_alive()
            try:
                client.services()
                return True
            except TacfError:
                time.sleep(0.1)
        raise LocalServiceError(f"tacf serve did not answer within {self.ready_timeout:g} s; log: {self.log_path}\n"
                                f"{self.log_tail()}")

    def check_alive(self) -> None:
        if self.process is not None and self.process.poll() is not None:
            raise LocalServiceError(f"tacf serve exited with code {self.process.returncode}; log: {self.log_path}\n"
                               f"{self.log_tail()}")

    def log_tail(self, lines: int = 20) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return ""

    def stop(self, grace: float = 5.0) -> int | None:
        """SIGTERM, wait up to `grace` seconds, then SIGKILL. Returns the exit code."""
        process, self.process = self.process, None
        if process is None:
            return None
        if process.poll() is None:
            process.send_signal(signal.SIGTERM)
            try:
                process.wait(timeout=grace)
            except subprocess.TimeoutExpired:
                log.warning("tacf serve did not stop within %g s after SIGTERM: killing it", grace)
                process.kill()
                process.wait(timeout=5)
        log.debug("tacf serve exited with code %s", process.returncode)
        self.returncode = process.returncode
        if self._own_log and process.returncode == 0:
            self.log_path.unlink(missing_ok=True)
        return process.returncode

    def __enter__(self) -> "LocalService":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
