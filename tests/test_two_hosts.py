"""The ground station on another machine. Two Linux network namespaces joined by a veth pair stand for the edge
box and the ground station (needs root and iproute2; skipped elsewhere). On the edge: `tacf serve` on the link's
address, a camera (`tacf publish scene`) and a session. On the ground: `tacf dashboard --connect` to the edge.
Before the dashboard ran as a Zenoh client there, it showed the session's boxes but never a frame: the camera
listens nowhere the ground can reach (on loopback at most), and peers do not relay for peers (docs/thin_link.md)."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from contextlib import contextmanager

import pytest

from tacf_service.loopback import wait_until

pytestmark = pytest.mark.zenoh

EDGE_ADDRESS = "10.213.0.1"
ENDPOINT = f"tcp/{EDGE_ADDRESS}:7447"
KEY = "uav1/cam"

# Run in the ground namespace: the dashboard's newest frame (status, bytes) and its sessions' boxes.
ASK_DASHBOARD = """
import json, urllib.error, urllib.request
def get(path):
    try:
        with urllib.request.urlopen("http://127.0.0.1:8080" + path, timeout=5) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as e:
        return e.code, b""
status, frame = get("/frame/uav1/cam")
_, state = get("/api/state")
boxes = [s["box"] for s in json.loads(state or b"{}").get("sessions", []) if s.get("box")]
print(json.dumps({"frame_status": status, "frame_bytes": len(frame), "boxes": len(boxes)}))
"""


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, text=True, timeout=10)


@pytest.fixture
def two_hosts():
    """(edge namespace, ground namespace), linked by a veth pair: 10.213.0.1 and 10.213.0.2."""
    if os.geteuid() != 0 or shutil.which("ip") is None:
        pytest.skip("needs root and iproute2 for network namespaces")
    tag = str(os.getpid() % 100000)
    edge, ground = f"tacf-edge{tag}", f"tacf-ground{tag}"
    try:
        try:
            _ip("netns", "add", edge)
            _ip("netns", "add", ground)
            _ip("link", "add", f"tacfe{tag}", "type", "veth", "peer", "name", f"tacfg{tag}")
            for ns, device, address in ((edge, f"tacfe{tag}", EDGE_ADDRESS), (ground, f"tacfg{tag}", "10.213.0.2")):
                _ip("link", "set", device, "netns", ns)
                _ip("-n", ns, "addr", "add", f"{address}/24", "dev", device)
                _ip("-n", ns, "link", "set", "lo", "up")
                _ip("-n", ns, "link", "set", device, "up")
        except subprocess.CalledProcessError as exc:
            pytest.skip(f"cannot link two network namespaces here: {exc.stderr.strip()}")
        yield edge, ground
    finally:
        for ns in (edge, ground):          # takes the veth pair with it, once moved in
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=10)
        subprocess.run(["ip", "link", "del", f"tacfe{tag}"], capture_output=True, timeout=10)  # if it never was


def _in(namespace: str, *command: str) -> list[str]:
    return ["ip", "netns", "exec", namespace, sys.executable, *command]


@contextmanager
def tacf_in(namespace: str, *args: str):
    """`tacf ARGS` running in a namespace; killed after."""
    process = subprocess.Popen(_in(namespace, "-m", "tacf.cli", *args), stdout=subprocess.DEVNULL,
                               stderr=subprocess.PIPE, text=True)
    try:
        yield process
    finally:
        process.kill()
        process.wait(timeout=10)
        process.stderr.close()


def test_a_dashboard_on_the_ground_shows_the_edge_s_frames_and_boxes(two_hosts):
    edge, ground = two_hosts
    with tacf_in(edge, "serve", "--node", "edge", "--listen", ENDPOINT), \
         tacf_in(edge, "publish", "scene", "--key", KEY, "--fps", "10", "--connect", ENDPOINT):
        start = _in(edge, "-m", "tacf.cli", "start", "--connect", ENDPOINT, "--key", KEY, "--box", "100,100,50,40")
        assert wait_until(lambda: subprocess.run(start, capture_output=True, timeout=30).returncode == 0, 60), \
            "no session started on the edge"
        with tacf_in(ground, "dashboard", "--key", KEY, "--connect", ENDPOINT) as board:
            seen = {}

            def frame_and_boxes() -> bool:
                out = subprocess.run(_in(ground, "-c", ASK_DASHBOARD), capture_output=True, text=True, timeout=30)
                seen.update(json.loads(out.stdout or "{}"))
                return seen.get("frame_status") == 200 and seen.get("boxes", 0) > 0

            assert wait_until(frame_and_boxes, 40), (seen, board.poll())
            assert seen["frame_bytes"] > 1000       # a JPEG of the edge's camera, across the link
