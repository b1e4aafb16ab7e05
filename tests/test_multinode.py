"""Several edge boxes on one Zenoh network: two real `tacf serve` processes on loopback, the second connected to
the first (a gossip mesh, README "Several edge boxes"); a client connected to the first only lists both, starts
sessions on a chosen or the least-loaded node, gets boxes from either, and sees a SIGKILLed node go within 3 s."""
from __future__ import annotations

import time

import pytest

from tacf.cli import main
from tacf_clients.client import LEAST_LOADED, TrackingClient, least_loaded, node_load
from tacf_clients.errors import NoService, TooManySessions
from tacf_clients.local_service import LocalService
from tacf_schemas.models import Health, SessionInfo, SessionList
from tacf_service.loopback import FramePublisher, wait_until
from tacf_service.scene import MovingTargetScene

from closed_pipe import head

pytestmark = pytest.mark.zenoh

A, B = "edge-a", "edge-b"


@pytest.fixture(scope="module")
def network():
    """edge-a listens; edge-b listens on its own port and connects to edge-a."""
    with LocalService(node=A) as a, LocalService(node=B, extra_args=("--connect", a.endpoint)) as b:
        yield a, b


@pytest.fixture(scope="module")
def client(network):
    a, b = network
    with TrackingClient(a.options, timeout=5.0) as c:          # connected to edge-a only
        a.wait_ready(c.session)
        b.wait_ready(c.session)
        assert wait_until(lambda: c.alive_nodes() == [A, B], 10)
        yield c


@pytest.fixture(scope="module")
def camera(client):
    with FramePublisher(client.session, "multi/cam", MovingTargetScene(320, 240, target=48, speed=1.0), fps=10) as feed:
        assert wait_until(lambda: feed.seq >= 0, 10)
        yield feed


def _box_arg(box) -> str:
    return ",".join(f"{v:g}" for v in box)


def _first_box(client: TrackingClient, sid: str, node: str):
    boxes = client.iter_boxes(sid, node=node, timeout=30)
    try:
        return next(boxes, None)
    finally:
        boxes.close()


def _listing(node: str, sessions: int, fps: float = 0.0, max_sessions: int = 8) -> SessionList:
    health = Health(node=node, sid="s", state="tracking", stamp_ns=1, fps=fps, processing_ms_mean=20.0,
                    processing_ms_p95=30.0)
    infos = [SessionInfo(node=node, sid=f"s{i}", image_key="k", profile="kcc", state="tracking",
                         box=(0, 0, 1, 1), created_ns=1, health=health) for i in range(sessions)]
    return SessionList(node=node, max_sessions=max_sessions, sessions=infos)


def test_least_loaded_ranking():
    assert least_loaded([_listing("a", 2), _listing("b", 1)]) == "b"                    # fewest sessions
    assert least_loaded([_listing("a", 1, fps=20), _listing("b", 1, fps=5)]) == "b"     # then tracking load
    assert node_load(_listing("a", 2, fps=20)) == pytest.approx(0.8)                     # 2 x 20 fps x 20 ms
    assert least_loaded([_listing("b", 0), _listing("a", 0)]) == "a"                    # then the node id
    assert least_loaded([_listing("a", 1, max_sessions=1), _listing("b", 3)]) == "b"    # full nodes skipped
    with pytest.raises(TooManySessions):
        least_loaded([_listing("a", 1, max_sessions=1)])
    with pytest.raises(NoService):
        least_loaded([])
    with pytest.raises(ValueError):
        TrackingClient(node=LEAST_LOADED)


def test_two_nodes_list_start_on_a_chosen_or_the_least_loaded_node(network, client, camera, capsys):
    a, b = network
    started = []
    try:
        info = client.start(camera.key, camera.truth[camera.seq], seq=camera.seq, profile="kcc", sid="on-a",
                            node=A)
        started.append(info)
        assert info.node == A
        # edge-a now runs one session and edge-b none: 'auto' picks edge-b, reached through edge-a.
        assert main(["start", "--node", "auto", "--key", camera.key, "--box", _box_arg(camera.truth[camera.seq]),
                     "--seq", str(camera.seq), "--profile", "kcc", "--sid", "auto1", "--connect", a.endpoint]) == 0
        assert f"started auto1 on {B}" in capsys.readouterr().out
        started.append(client.status("auto1"))
        assert started[-1].node == B

        for sid, node in (("on-a", A), ("auto1", B)):       # real frames in, real boxes out, on both boxes
            box = _first_box(client, sid, node)
            assert box is not None and (box.node, box.sid) == (node, sid)

        assert main(["list", "--connect", a.endpoint]) == 0
        out = capsys.readouterr().out
        assert f"{A} (1/8" in out and f"{B} (1/8" in out and "on-a" in out and "auto1" in out
        assert main(["nodes", "--connect", b.endpoint]) == 0         # from the other end as well
        out = capsys.readouterr().out
        assert f"{A}  yes    1/8" in out and f"{B}  yes    1/8" in out
        assert main(["nodes", "--follow", "--duration", "1", "--connect", a.endpoint]) == 0
        out = capsys.readouterr().out
        assert f"up    {A}" in out and f"up    {B}" in out
    finally:
        for info in started:
            client.stop(info.sid, node=info.node)


def test_nodes_follow_read_by_head_ends_quietly(network):
    """`tacf nodes --follow | head -1` never ended: the next line, printed on a Zenoh callback thread, failed there
    with a BrokenPipeError traceback in the log, and the command went on following."""
    a, _ = network
    code, _, err = head(["nodes", "--follow", "--connect", a.endpoint], 0, timeout=30)
    assert (code, err) == (141, ""), err


def test_nodes_with_a_node_shows_that_one_only(network, client, capsys):
    """`tacf nodes --node edge-b` asked edge-b alone for its sessions, then printed edge-a, alive and answering
    every query, as "no answer"."""
    a, _ = network
    assert main(["nodes", "--node", B, "--connect", a.endpoint]) == 0
    rows = capsys.readouterr().out.splitlines()[1:]
    assert [row.split()[:3] for row in rows] == [[B, "yes", "0/8"]]


def test_a_killed_node_is_seen_gone_within_3_s(network, client, camera, capsys):
    a, b = network
    events: list[tuple[float, str, bool]] = []
    client.start(camera.key, camera.truth[camera.seq], seq=camera.seq, profile="kcc", sid="survivor", node=A)
    with client.watch_nodes(lambda node, alive: events.append((time.monotonic(), node, alive))) as watch:
        assert wait_until(lambda: watch.nodes == [A, B], 10)
        killed = time.monotonic()
        b.process.kill()
        assert wait_until(lambda: watch.nodes == [A], 5), events
        seen = next(t for t, node, alive in events if node == B and not alive) - killed
        with capsys.disabled():
            print(f"\nedge-b SIGKILLed: gone for the client after {seen * 1000:.1f} ms")
        assert seen < 3.0
        assert [node for t, node, _ in events if t > killed] == [B]     # edge-a never flickered

    assert client.nodes() == [A] and client.alive_nodes() == [A]
    assert main(["nodes", "--connect", a.endpoint]) == 0
    out = capsys.readouterr().out
    assert A in out and B not in out
    box = _first_box(client, "survivor", A)                  # subscribed after the kill: edge-a keeps tracking
    assert box is not None
    client.stop("survivor", node=A)
