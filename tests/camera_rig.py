"""A real service with a camera in front of it, and the `tacf` command in a child process, shared by the tests of
the client-side tools."""
from __future__ import annotations

import subprocess
import sys
import threading
from contextlib import contextmanager

import zenoh

from tacf_clients.demo import HoldingPublisher
from tacf_clients.local_service import LocalService, free_port
from tacf_clients.scene import Scene, SceneSource
from tacf_clients.zconfig import ZenohOptions, make_config
from tacf_service.loopback import wait_until


def no_service_options() -> ZenohOptions:
    """Zenoh options of a session that listens on a free loopback port and reaches no service."""
    return ZenohOptions(connect=(), listen=(f"tcp/127.0.0.1:{free_port()}",))


@contextmanager
def service_and_camera(scene: Scene, key: str, node_prefix: str, fps: float = 20):
    """`tacf serve` in a child process, a session on it, and a camera publishing the generated scene on `key` as
    JPEG (started, holding its first frame until `camera.hold` is cleared): yields (service, session, camera)."""
    with LocalService(node=f"{node_prefix}{free_port()}") as service:
        with zenoh.open(make_config(service.options)) as session:
            service.wait_ready(session)
            camera = HoldingPublisher(session, SceneSource(scene), key, fps, "jpeg")
            camera.start()
            try:
                yield service, session, camera
            finally:
                camera.close()


def reset_rig(camera, client) -> None:
    """After a test on a shared rig: the camera moving again and no session left, whatever the test did. One that
    failed midway left them, and the later tests failed on them too (a session listed, a camera held)."""
    from tacf_clients.errors import TacfError

    camera.hold.clear()
    for info in client.list():
        try:
            client.stop(info.sid, node=info.node)
        except TacfError:
            pass                        # stopped meanwhile


def hold_still(camera, timeout: float = 10.0) -> int:
    """Hold `camera` (it repeats its first frame) and return the seq of the first frame sent held: the frame after
    the one that may have been picked before the hold was set."""
    camera.hold.set()
    first_held = camera.last_seq + 2
    assert wait_until(lambda: camera.last_seq >= first_held, timeout=timeout, period=0.02), "the camera sends on"
    return first_held


@contextmanager
def tacf_command(*args: str, env: dict | None = None):
    """`tacf ARGS` as a user runs it, its output (stdout and stderr) on a pipe; killed if it still runs after."""
    process = subprocess.Popen([sys.executable, "-m", "tacf.cli", *args], stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, text=True, env=env)
    try:
        yield process
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(timeout=5)
        process.stdout.close()


@contextmanager
def serving(server):
    """`server.serve(stop)` (a bridge, a MAVLink component) on a thread of its own while the block runs; yields
    that thread."""
    stop = threading.Event()
    loop = threading.Thread(target=server.serve, args=(stop,), name=f"serving-{type(server).__name__}")
    loop.start()
    try:
        yield loop
    finally:
        stop.set()
        loop.join(timeout=10)
