"""TrackingClient against a real `tacf serve` on loopback: every control op, subscriptions, typed errors,
timeouts, and the wildcard list across two services."""
from __future__ import annotations

import functools
import json
import threading
import time

import pytest
import zenoh

from tacf.eval.metrics import box_iou
from tacf_clients.client import TrackingClient
from tacf_clients.demo import HoldingPublisher
from tacf_clients.errors import (ERRORS, AmbiguousNode, DuplicateSession, InvalidBox, InvalidConfig, InvalidId,
                                 InvalidKey, InvalidRequest, NoService, RequestTimeout, ServiceError, UnknownSession)
from tacf_clients.local_service import LocalService, free_port
from tacf_clients.scene import Scene, SceneSource
from tacf_clients.zconfig import ZenohOptions, make_config
from tacf_schemas.models import ERROR_CODES, BoxResult, Health, SessionInfo, SessionList
from tacf_service.loopback import wait_until
from camera_rig import no_service_options

pytestmark = pytest.mark.zenoh

SCENE = Scene.from_spec("scene:320x240")


@pytest.fixture(scope="module")
def service():
    with LocalService(node=f"svc{free_port()}") as svc:
        with zenoh.open(make_config(svc.options)) as session:
            svc.wait_ready(session)
        yield svc


@pytest.fixture
def client(service):
    with TrackingClient(service.options, timeout=5.0) as c:
        yield c


@pytest.fixture
def camera(client, request):
    """The scene published on its own key at 20 fps; it holds its first frame until `camera.hold.clear()`."""
    cam = HoldingPublisher(client.session, SceneSource(SCENE), f"test/cam/{request.node.name[:40]}", 20, "jpeg")
    cam.key = cam.publisher.key
    cam.start()
    assert _wait(lambda: cam.last_seq >= 0)
    yield cam
    cam.close()


_wait = functools.partial(wait_until, timeout=10.0)


def test_error_classes_cover_every_wire_code():
    assert set(ERRORS) == set(ERROR_CODES)
    assert all(issubclass(cls, ServiceError) for cls in ERRORS.values())


def test_the_client_api_takes_one_endpoint_as_a_string_and_exports_least_loaded(service):
    """A newcomer's first client: ZenohOptions(connect="tcp/...") was split into its characters ("Endpoints must be
    of the form ...: t"), and LEAST_LOADED, which the README gives for start(), was not importable from the package."""
    from tacf_clients import LEAST_LOADED

    with TrackingClient(ZenohOptions(connect=service.options.connect[0]), timeout=5.0) as client:
        assert [s.node for s in client.services()] == [service.node]
    assert ZenohOptions(listen="tcp/127.0.0.1:0").listen == ("tcp/127.0.0.1:0",)
    assert LEAST_LOADED == "auto"


def test_an_error_of_a_newer_service_keeps_its_code():
    """A code this client has no class for raises a plain ServiceError: its `code` said "internal" (the class's),
    so a caller, or the dashboard's API that passes it on, took a newer service's refusal for a bug."""
    import msgpack

    port = free_port()
    with zenoh.open(make_config(ZenohOptions.listener(f"tcp/127.0.0.1:{port}"))) as newer:
        def refuse(query):
            with query:
                query.reply_err(msgpack.packb({"v": 2, "code": "rate_limited", "message": "slow down",
                                               "node": "newer"}))

        newer.declare_queryable("tacf/newer/control/*", refuse)
        with TrackingClient(ZenohOptions.loopback(port), timeout=2.0) as client, \
                pytest.raises(ServiceError) as refused:
            client.status("abc", node="newer")
    assert type(refused.value) is ServiceError
    assert (refused.value.code, refused.value.message, refused.value.node) == ("rate_limited", "slow down", "newer")


def test_start_status_list_subscribe_stop(client, camera, service):
    boxes: list[BoxResult] = []
    health: list[Health] = []
    with client.subscribe("life", on_box=boxes.append, on_health=health.append):
        info = client.start(camera.key, SCENE.box(0), sid="life")
        assert isinstance(info, SessionInfo)
        assert (info.sid, info.node, info.image_key) == ("life", service.node, camera.key)
        assert info.state in ("starting", "tracking")
        assert _wait(lambda: len(boxes) >= 10 and health, timeout=40), "boxes and health arrive"
    assert all(b.sid == "life" and b.node == service.node for b in boxes)
    assert health[0].state in ("starting", "tracking")

    listed = {(s.node, s.sid): s for s in client.list()}
    assert (service.node, "life") in listed
    status = client.status("life")
    assert status.sid == "life" and status.state == "tracking"
    assert status.last_seq is not None and status.last_seq >= boxes[0].seq

    stopped = client.stop("life")
    assert stopped.state == "stopped"
    assert "life" not in {s.sid for s in client.list()}
    with pytest.raises(UnknownSession):
        client.status("life")


def test_boxes_follow_the_target_and_reinit(client, camera):
    info = client.start(camera.key, SCENE.box(0), seq=camera.last_seq, sid="follow")
    try:
        boxes = client.iter_boxes("follow", timeout=40)
        first = next(boxes)
        camera.hold.clear()                      # the target starts moving once the session tracks
        later = [b for b in _take(boxes, 25) if camera.index_of(b.seq)]
        assert len(later) >= 10
        overlaps = [box_iou(tuple(b.box), SCENE.box(camera.index_of(b.seq))) for b in later]
        assert sum(o > 0.5 for o in overlaps) >= 0.8 * len(overlaps), overlaps
        assert first.seq < later[0].seq

        seq = camera.last_seq
        truth = SCENE.box(camera.index_of(seq))
        info = client.reinit("follow", truth, seq=seq)
        assert info.sid == "follow" and info.state in ("starting", "tracking")
        after = [b for b in _take(client.iter_boxes("follow", timeout=30), 10) if b.seq >= seq]
        assert after and box_iou(tuple(after[-1].box), SCENE.box(camera.index_of(after[-1].seq))) > 0.3
    finally:
        client.stop(info.sid)


def _take(iterator, n):
    for i, item in enumerate(iterator):
        yield item
        if i + 1 >= n:
            return


def test_results_iterator_latest_only(client, camera):
    client.start(camera.key, SCENE.box(0), sid="latest")
    try:
        with client.results("latest", latest_only=True) as stream:
            assert _wait(lambda: stream.received >= 3, timeout=40)
            before = stream.received
            time.sleep(1.0)                          # a slow reader: older boxes are replaced, not queued
            items = []
            while (item := stream.get(timeout=0)) is not None:
                items.append(item)
            arrived = stream.received - before
        boxes = [i for i in items if isinstance(i, BoxResult)]
        assert arrived >= 5
        assert 1 <= len(boxes) <= 2, "latest-only keeps the newest box per session"
        assert stream.dropped >= arrived - 3
    finally:
        client.stop("latest")


def test_error_replies_raise_typed_exceptions(client, camera, service):
    with pytest.raises(UnknownSession) as exc:
        client.stop("no-such-session")
    assert exc.value.code == "unknown_session" and exc.value.node == service.node
    assert str(exc.value) == f"no session 'no-such-session' on node {service.node!r}"      # the node named once
    with pytest.raises(UnknownSession):
        client.status("no-such-session", node=service.node)
    with pytest.raises(InvalidKey):                       # refused before it is sent
        client.start("bad/*/key", (1, 2, 3, 4))
    with pytest.raises(InvalidBox):
        client.start(camera.key, (10, 10, 0, 5))
    for box in (("10", "10", "20", "20"), (10, 10, True, 20), (10, 10, 20), "abcd", (10**400, 10, 20, 20)):
        with pytest.raises(InvalidBox, match="4 numbers"):       # no numbers, or none a float holds: not sent
            client.start(camera.key, box)
    with pytest.raises(InvalidId):
        client.stop("not a valid id")
    with pytest.raises(InvalidId):                        # as the service would refuse it (`tacf start --sid`)
        client.start(camera.key, SCENE.box(0), sid="not a valid id")
    for text in ("0.02", "true"):                         # typed into a form: refused, not sent as a number
        with pytest.raises(InvalidRequest, match="overrides"):
            client.start(camera.key, SCENE.box(0), sid="textual", overrides={"learning_rate": text})
    with pytest.raises(InvalidConfig):                    # refused by the service
        client.start(camera.key, SCENE.box(0), profile="no-such-profile", sid="badprofile")
    with pytest.raises(InvalidBox):
        client.start(camera.key, (5000, 5000, 20, 20), sid="outside")
    client.start(camera.key, SCENE.box(0), sid="twice")
    try:
        with pytest.raises(DuplicateSession):
            client.start(camera.key, SCENE.box(0), sid="twice")
    finally:
        client.stop("twice")


def test_an_override_int_msgpack_cannot_carry_is_the_service_s_to_refuse(client, camera):
    """`tacf start --set cell_size=99999999999999999999` (or overrides={"cell_size": 10**20}) ended in msgpack's
    OverflowError traceback: now it goes as the number it is and the service names the bound it breaks."""
    with pytest.raises(InvalidConfig, match="cell_size"):
        client.start(camera.key, SCENE.box(0), sid="huge", overrides={"cell_size": 10**20})
    assert "huge" not in {info.sid for info in client.list()}


def test_no_service_and_timeout():
    port = free_port()
    hub = f"tcp/127.0.0.1:{port}"
    with zenoh.open(make_config(ZenohOptions.listener(hub))) as silent:
        # a service that takes queries and never answers them
        held = []
        queryable = silent.declare_queryable("tacf/silent/control/*", held.append)
        with TrackingClient(ZenohOptions.loopback(port), timeout=0.5) as client:
            started = time.monotonic()
            with pytest.raises(RequestTimeout):
                client.status("abc", node="silent")
            assert 0.4 < time.monotonic() - started < 3
            with pytest.raises(RequestTimeout):
                client.list(node="silent")
            queryable.undeclare()
            for query in held:
                query.drop()            # finalise: a query kept alive at exit can abort the interpreter
            held.clear()
            assert client.list() == []
            with pytest.raises(NoService):
                client.start("cam/a", (1, 2, 3, 4))
            with pytest.raises(NoService):
                client.stop("abc")


def _fake_service(session: zenoh.Session, node: str, replies: dict, delay_s: float = 0.0):
    """A queryable answering tacf/<node>/control/<op> with replies[op] (a model, or an Error sent as reply_err) after
    `delay_s`."""
    from tacf_schemas.codec import MSGPACK_ENCODING, encode
    from tacf_schemas.models import Error

    def answer(query):
        time.sleep(delay_s)
        with query:
            reply = replies[str(query.key_expr).rsplit("/", 1)[-1]]
            if isinstance(reply, Error):
                query.reply_err(encode(reply))
            else:
                query.reply(query.key_expr, encode(reply), encoding=zenoh.Encoding(MSGPACK_ENCODING))

    return session.declare_queryable(f"tacf/{node}/control/*", answer)


def _info(node: str) -> SessionInfo:
    """Session "s" of `node`, as a service's reply describes it."""
    return SessionInfo(node=node, sid="s", image_key="cam/a", profile="default", state="tracking", box=(1, 2, 3, 4),
                       created_ns=1)


def test_a_call_takes_no_longer_than_its_timeout_however_many_queries_it_makes():
    """A start with no node lists the services first: each query had the whole timeout, so a service slow to
    answer both made a 1 s call take 1.4 s. Every query of a call now shares its timeout."""
    port = free_port()
    with zenoh.open(make_config(ZenohOptions.listener(f"tcp/127.0.0.1:{port}"))) as slow:
        replies = {"list": SessionList(node="slow", max_sessions=8), "start": _info("slow"), "status": _info("slow")}
        queryable = _fake_service(slow, "slow", replies, delay_s=0.7)
        try:
            with TrackingClient(ZenohOptions.loopback(port), timeout=1.0) as client:
                started = time.monotonic()
                # the service goes on with a start answered too late: a retry would start a second session
                with pytest.raises(RequestTimeout, match="service 'slow' may still start the session: check with "
                                                         "status or list before starting it again"):
                    client.start("cam/a", (1, 2, 3, 4))
                assert time.monotonic() - started < 1.3
                time.sleep(1.0)                       # the late start is answered (to nobody): the queue is clear
                assert client.status("s", node="slow").sid == "s", "one query within the timeout is answered"
        finally:
            queryable.undeclare()


def test_a_service_that_does_not_answer_holds_up_no_lookup_before_a_call():
    """One service that takes queries and never answers (hung, or a drone gone out of reach, which keeps its place
    until its lease ends, 10 s) took the whole timeout of the lookup before a call: a start on the least-loaded
    service and a status by session id alone failed with a timeout that named the service that did answer."""
    from tacf_clients.client import LEAST_LOADED

    port = free_port()
    with zenoh.open(make_config(ZenohOptions.listener(f"tcp/127.0.0.1:{port}"))) as services:
        answering = _fake_service(services, "ok", {"list": SessionList(node="ok", max_sessions=8),
                                                   "start": _info("ok"), "status": _info("ok")})
        held = []
        hung = services.declare_queryable("tacf/hung/control/*", held.append)
        try:
            for call in (lambda client: client.start("cam/a", (1, 2, 3, 4), node=LEAST_LOADED),
                         lambda client: client.status("s")):
                with TrackingClient(ZenohOptions.loopback(port), timeout=2.0) as client:
                    started = time.monotonic()
                    assert call(client).node == "ok"
                    assert time.monotonic() - started < 2.0
        finally:
            answering.undeclare()
            hung.undeclare()
            for query in held:
                query.drop()            # finalise: a query kept alive at exit can abort the interpreter


def test_a_call_to_one_service_refuses_the_wildcard_node():
    """node="*" passed the id check of a key expression, so a start or stop went to every service at once (the
    dashboard's POST /api/start with "node": "*" started the session on each of them)."""
    with TrackingClient(no_service_options(), timeout=0.5) as client:
        for call in (lambda: client.start("cam/a", (1, 2, 3, 4), node="*"), lambda: client.stop("s", node="*"),
                     lambda: client.reinit("s", (1, 2, 3, 4), node="*"), lambda: client.status("s", node="*")):
            with pytest.raises(InvalidId, match="node id"):
                call()


def test_a_start_on_the_least_loaded_service_with_none_says_none_answered():
    """With no service on the network, `start(..., node=LEAST_LOADED)` (`tacf start --node auto`) said "service '*'
    did not answer", as if a service were named '*'."""
    from tacf_clients.client import LEAST_LOADED

    with TrackingClient(no_service_options(), timeout=0.5) as client, pytest.raises(NoService) as none:
        client.start("cam/a", (1, 2, 3, 4), node=LEAST_LOADED)
    assert str(none.value) == "no tracking service answered on tacf/*/control/list"


def test_a_start_on_the_least_loaded_service_refuses_a_node_id_two_services_answer_as():
    """Two boxes flashed from one image answer as one node id: `start()` without node= refused that, but
    node=LEAST_LOADED picked the id and started the session on both (the target tracked twice, once per box)."""
    from tacf_clients.client import LEAST_LOADED
    from tacf_schemas.codec import MSGPACK_ENCODING, encode
    from tacf_schemas.models import SessionList

    info = SessionInfo(node="twin", sid="s", image_key="cam/a", profile="default", state="starting",
                       box=(1, 2, 3, 4), created_ns=1)
    replies = {"list": SessionList(node="twin", max_sessions=8), "start": info}
    started = []
    port = free_port()
    with zenoh.open(make_config(ZenohOptions.listener(f"tcp/127.0.0.1:{port}"))) as boxes:
        def answer(query):
            op = str(query.key_expr).rsplit("/", 1)[-1]
            started.extend([op] if op == "start" else [])
            query.reply(query.key_expr, encode(replies[op]), encoding=zenoh.Encoding(MSGPACK_ENCODING))

        twins = [boxes.declare_queryable("tacf/twin/control/*", answer) for _ in range(2)]
        try:
            with TrackingClient(ZenohOptions.loopback(port), timeout=1.0) as client:
                assert client.nodes() == ["twin", "twin"]
                with pytest.raises(AmbiguousNode, match="several services answer as node 'twin'"):
                    client.start("cam/a", (1, 2, 3, 4), node=LEAST_LOADED)
            assert started == [], "no start was sent"
        finally:
            for queryable in twins:
                queryable.undeclare()


def test_a_start_waits_for_a_service_slower_than_the_other_calls_allow():
    """A service's first start waits for its fork server to load the tracker (5.7 s with numba's cache empty): with a
    client's default timeouts a start waits START_TIMEOUT, not the 5 s of the other calls."""
    from tacf_clients.client import DEFAULT_TIMEOUT

    port = free_port()
    with zenoh.open(make_config(ZenohOptions.listener(f"tcp/127.0.0.1:{port}"))) as services:
        cold = _fake_service(services, "cold", {"start": _info("cold")}, delay_s=DEFAULT_TIMEOUT + 0.5)
        try:
            with TrackingClient(ZenohOptions.loopback(port)) as client:
                assert client.start("cam/a", (1, 2, 3, 4), node="cold").node == "cold"
        finally:
            cold.undeclare()


def test_a_session_whose_service_went_away_is_looked_for_again():
    """The client remembers the service of each session; once that service no longer answers (restarted elsewhere,
    out of reach) a call on the session looks for it again instead of failing with NoService."""
    port = free_port()
    with zenoh.open(make_config(ZenohOptions.listener(f"tcp/127.0.0.1:{port}"))) as services:
        with TrackingClient(ZenohOptions.loopback(port), timeout=2.0) as client:
            gone = _fake_service(services, "gone", {"status": _info("gone"), "list": SessionList(node="gone",
                                                                                                max_sessions=8)})
            assert _wait(lambda: client.nodes() == ["gone"])
            assert client.status("s").node == "gone"            # found there, and remembered
            gone.undeclare()
            moved = _fake_service(services, "moved", {"status": _info("moved"), "list": SessionList(node="moved",
                                                                                                   max_sessions=8)})
            try:
                assert _wait(lambda: client.nodes() == ["moved"])
                assert client.status("s").node == "moved"
            finally:
                moved.undeclare()


def test_a_session_looked_for_names_the_error_that_says_more_than_not_here():
    """A status by session id alone asks every service: one that holds the session and fails says more than the
    others' "unknown session"."""
    from tacf_schemas.models import Error

    port = free_port()
    with zenoh.open(make_config(ZenohOptions.listener(f"tcp/127.0.0.1:{port}"))) as services:
        elsewhere = _fake_service(services, "elsewhere", {"status": Error(code="unknown_session",
                                                                          message="no session 's'", node="elsewhere")})
        broken = _fake_service(services, "broken", {"status": Error(code="internal", message="state file unreadable",
                                                                    node="broken")})
        try:
            with TrackingClient(ZenohOptions.loopback(port), timeout=2.0) as client, \
                    pytest.raises(ServiceError, match="state file unreadable"):
                client.status("s")
        finally:
            elsewhere.undeclare()
            broken.undeclare()


def test_a_node_watch_tells_each_service_coming_and_going_once_until_it_is_closed():
    from tacf_schemas import keys

    port = free_port()
    with zenoh.open(make_config(ZenohOptions.listener(f"tcp/127.0.0.1:{port}"))) as services, \
            TrackingClient(ZenohOptions.loopback(port), timeout=2.0) as client:
        first = services.liveliness().declare_token(keys.service_liveliness_key("edge1"))
        events: list[tuple[str, bool]] = []
        with client.watch_nodes(lambda node, alive: events.append((node, alive))) as watch:
            assert _wait(lambda: watch.nodes == ["edge1"])       # up before the watch: from the history
            second = services.liveliness().declare_token(keys.service_liveliness_key("edge2"))
            assert _wait(lambda: watch.nodes == ["edge1", "edge2"])
            first.undeclare()
            assert _wait(lambda: watch.nodes == ["edge2"])
        second.undeclare()                                       # after the watch's close: not told
        third = services.liveliness().declare_token(keys.service_liveliness_key("edge3"))
        time.sleep(0.5)
        third.undeclare()
        assert events == [("edge1", True), ("edge2", True), ("edge1", False)], events


def _cli_error(main, argv: list[str], capsys) -> str:
    """The one line a command prints on stderr when it fails with exit code 1 (SystemExit, not a traceback)."""
    with pytest.raises(SystemExit) as exc:
        main(argv)
    err = capsys.readouterr().err
    assert exc.value.code == 1, err
    assert len(err.splitlines()) == 1, err
    return err.strip()


def test_command_line_bad_ids_and_no_service_are_one_line_errors(capsys):
    from tacf.cli import main

    port = free_port()
    with zenoh.open(make_config(ZenohOptions.listener(f"tcp/127.0.0.1:{port}"))):     # a node, but no service
        zenoh_args = ["--connect", f"tcp/127.0.0.1:{port}"]
        for argv in (["list"], ["status", "abc"], ["stop", "abc"], ["nodes"], ["watch"],
                     ["start", "--key", "cam/a", "--box", "1,2,3,4"]):
            err = _cli_error(main, [*argv, "--node", "bad/id", *zenoh_args], capsys)
            assert err == (f"tacf {argv[0]}: InvalidId: invalid node id 'bad/id': expected 1-64 characters of "
                           "[A-Za-z0-9_-]")
        err = _cli_error(main, ["watch", "a/b", "--duration", "1", *zenoh_args], capsys)
        assert err.startswith("tacf watch: InvalidId: invalid session id 'a/b'")

        # No service answering is an error (exit 1) with --json as without, which still prints an empty list.
        for argv in (["list"], ["list", "--json"], ["nodes", "--timeout", "0.5"],
                     ["nodes", "--json", "--timeout", "0.5"]):
            assert main([*argv, *zenoh_args]) == 1
            captured = capsys.readouterr()
            assert captured.out.strip() == ("[]" if "--json" in argv else "")
            assert captured.err.startswith(f"tacf {argv[0]}: no tracking service")


def test_closing_the_client_ends_its_streams():
    """Streams ended only when closed themselves: after the client's session closed, iterators waited for ever,
    and a subscribe() callback thread kept the interpreter from exiting at the end of a `with` block."""
    client = TrackingClient(ZenohOptions(listen=(f"tcp/127.0.0.1:{free_port()}",)))
    ended = threading.Event()

    def iterate() -> None:
        for _ in client.iter_boxes("abc", node="edge"):
            pass
        ended.set()
    reader = threading.Thread(target=iterate)
    reader.start()
    # the reader's subscriber is declared (a local one matches): a close before it made iter_boxes raise instead
    probe = client.session.declare_publisher("tacf/edge/sessions/abc/box")
    assert wait_until(lambda: probe.matching_status.matching, 10), "the reader never subscribed"
    probe.undeclare()
    stream = client.subscribe(on_box=lambda box: None)
    client.close()
    reader.join(5)
    assert ended.is_set()
    # the drop hook that closes a stream runs on its own Zenoh thread after close(), not before close() returns
    assert wait_until(lambda: stream.closed, 5)
    assert wait_until(lambda: not stream._thread.is_alive(), 5)


def test_calls_on_a_closed_client_raise_client_closed():
    """Every call after close() raised zenoh's own ZError ("session closed"), which a caller catching TacfError, as
    the client's docs say to, did not catch."""
    from tacf_clients.errors import ClientClosed, TacfError

    client = TrackingClient(ZenohOptions(connect=(), listen=(f"tcp/127.0.0.1:{free_port()}",)), timeout=1.0)
    client.close()
    calls = {"start": lambda: client.start("cam/a", (1, 2, 3, 4), node="edge"), "stop": lambda: client.stop("abc"),
             "status": lambda: client.status("abc"), "reinit": lambda: client.reinit("abc", (1, 2, 3, 4)),
             "list": client.list, "nodes": client.nodes, "alive_nodes": client.alive_nodes,
             "watch_nodes": client.watch_nodes, "subscribe": lambda: client.subscribe("abc"),
             "results": client.results, "iter_boxes": lambda: next(client.iter_boxes("abc"))}
    for name, call in calls.items():
        with pytest.raises(TacfError) as exc:
            call()
        assert isinstance(exc.value, ClientClosed) and str(exc.value) == "client is closed", (name, exc.value)
    client.close()                                      # a second close is no error
    with zenoh.open(make_config(ZenohOptions(connect=(), listen=(f"tcp/127.0.0.1:{free_port()}",)))) as session:
        given = TrackingClient(session=session, timeout=1.0)
    with pytest.raises(ClientClosed, match="the Zenoh session it was given is closed"):
        given.list()


def test_command_line_bad_image_keys_are_usage_errors(capsys):
    from tacf.cli import main

    for argv in (["publish", "scene"], ["start", "--box", "1,2,3,4"], ["mavlink", "--link", "udpin:0.0.0.0:1"],
                 ["dashboard"], ["foxglove"]):
        with pytest.raises(SystemExit) as exc:
            main([*argv, "--key", "cam/*"])
        err = capsys.readouterr().err
        assert exc.value.code == 2 and "argument --key/-k: invalid image key 'cam/*'" in err, (argv, err)


def test_command_line_infinite_numbers_are_usage_errors(capsys):
    """'inf' passed the '> 0' check of times and rates, then came back as tracebacks: a Zenoh timeout out of
    range (list --timeout inf), an Event.wait overflow (nodes --follow --duration inf), a line count that
    is not an integer (demo --fps inf)."""
    from tacf.cli import main

    for argv in (["list", "--timeout", "inf"], ["nodes", "--follow", "--duration", "inf"], ["demo", "--fps", "inf"],
                 ["watch", "--interval", "Infinity"], ["publish", "scene", "--key", "cam/a", "--fps", "inf"]):
        with pytest.raises(SystemExit) as exc:
            main(argv)
        err = capsys.readouterr().err
        assert exc.value.code == 2 and "expected a finite number > 0" in err, (argv, err)


def test_command_line_ports_out_of_range_are_one_line_errors(capsys):
    """A port outside 0-65535 used to reach socket.bind and end in an OverflowError traceback."""
    from tacf.cli import main

    for argv in (["dashboard", "--port", "70000"], ["foxglove", "--port", "-1"]):
        with pytest.raises(SystemExit) as exc:
            main(argv)
        err = capsys.readouterr().err
        assert exc.value.code == 2 and "a port number 0-65535" in err, (argv, err)
    pytest.importorskip("pymavlink")
    assert main(["mavlink", "--key", "cam/a", "--link", "udpin:127.0.0.1:99999",
                 "--connect", f"tcp/127.0.0.1:{free_port()}"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("tacf mavlink: ") and "a port of 1 to 65535" in err and "Traceback" not in err, err


def test_command_line_without_a_reachable_node_is_a_one_line_error(capsys):
    from tacf.cli import main

    zenoh_args = ["--mode", "client", "--connect", f"tcp/127.0.0.1:{free_port()}"]      # nobody listens there
    for argv in (["list"], ["publish", "scene", "--key", "cam/a"], ["watch"], ["dashboard", "--port", "0"]):
        err = _cli_error(main, [*argv, *zenoh_args], capsys)
        assert err.startswith(f"tacf {argv[0]}: ZenohUnavailable: no Zenoh node reachable: Unable to connect"), err
        assert ".rs:" not in err                      # the Rust source line Zenoh appends is left out


def test_list_and_nodes_print_an_empty_json_list_when_no_node_is_reachable(capsys):
    """Their help says that with no service answering they exit 1 'with --json after printing []'. With no Zenoh
    node to connect to, the usual case on a machine where no service was started, they printed nothing at all, so
    a script reading their JSON got none."""
    from tacf.cli import main

    zenoh_args = ["--connect", f"tcp/127.0.0.1:{free_port()}"]      # nobody listens there
    for argv in (["list", "--json"], ["nodes", "--json"]):
        with pytest.raises(SystemExit) as exc:
            main([*argv, *zenoh_args])
        captured = capsys.readouterr()
        assert exc.value.code == 1 and captured.out.strip() == "[]", (argv, captured)
        assert captured.err.startswith(f"tacf {argv[0]}: ZenohUnavailable: no Zenoh node reachable"), captured.err


def _help(main, command: str, capsys) -> str:
    with pytest.raises(SystemExit):
        main([command, "--help"])
    return " ".join(capsys.readouterr().out.split())


def test_mavlink_link_help_names_the_multicast_and_unix_socket_links(capsys):
    """`tacf mavlink --link` takes pymavlink's mcast: and unix: links, as the README says, but its help listed UDP,
    TCP and serial links only."""
    from tacf.cli import main

    link_help = _help(main, "mavlink", capsys)
    assert "mcast:" in link_help and "unix:" in link_help, link_help


# Run as `tacf COMMAND ...` in a process where the module named first cannot be imported, as where its extra is
# not installed.
_WITHOUT_MODULE = """
import sys
sys.modules[sys.argv[1]] = None       # an import of it raises ImportError
from tacf.cli import main
sys.exit(main(sys.argv[2:]))
"""


def test_an_extra_s_install_hint_installs_it_from_the_checkout(capsys):
    """The help of `tacf mavlink` and `tacf foxglove` and their errors without their extra said `pip install
    'tacf[mavlink]'`: tacf is not on PyPI, so that finds nothing. It is installed from its checkout, with the
    extras as the README installs them."""
    import subprocess
    import sys

    from tacf.cli import main

    for command, module, argv in (("mavlink", "pymavlink", ["--key", "cam/a", "--link", "udpout:127.0.0.1:14550"]),
                                  ("foxglove", "foxglove", ["--port", "0"])):
        hint = f"pip install -e '.[{command}]' in the tacf checkout"
        assert hint in _help(main, command, capsys)
        done = subprocess.run([sys.executable, "-c", _WITHOUT_MODULE, module, command, *argv], capture_output=True,
                              text=True, timeout=60)
        assert done.returncode == 2 and done.stderr.startswith(f"tacf {command}: "), done.stderr
        assert done.stderr.rstrip().endswith(f"install it with: {hint}"), done.stderr
        assert "tacf[" not in done.stderr


def test_command_line_mode_help_says_the_mode_each_command_opens(capsys):
    """Every client command's help said `--mode ... (default peer)`, but the one-shot ones open as Zenoh clients
    unless told otherwise: with no node reachable they fail at once, as only a client does."""
    from tacf.cli import main

    zenoh_args = ["--connect", f"tcp/127.0.0.1:{free_port()}"]      # nobody listens there
    for argv in (["list"], ["status", "abc"], ["stop", "abc"], ["reinit", "abc", "--box", "1,2,3,4"], ["nodes"],
                 ["start", "--key", "cam/a", "--box", "1,2,3,4"]):
        assert "ZenohUnavailable: no Zenoh node reachable" in _cli_error(main, [*argv, *zenoh_args], capsys)
        assert "Zenoh session mode (default client" in _help(main, argv[0], capsys), argv
    for command in ("publish", "watch", "mavlink"):
        assert "Zenoh session mode (default peer)" in _help(main, command, capsys), command
    for command in ("dashboard", "foxglove"):
        assert "(default peer; client when every --connect endpoint is on another machine" in \
            _help(main, command, capsys), command
    assert "--node NODE only this service (node id); default: every service on the network" in \
        _help(main, "list", capsys)


def test_two_services_with_one_node_id_are_named_as_such(service, camera, capsys):
    """Two services under the same --node both answer every query to that node: a start without node=... said
    "2 services on the network (n, n): pass node=...", and passing that node started the session on both;
    `tacf nodes` showed one row for the two. A service refuses to start under a node id already live where it
    connects (tests/test_service_process.py), so the clash here is met by a client that links two services started
    apart, as a ground station linking two boxes flashed from one image would."""
    import dataclasses
    import json

    from tacf.cli import main

    with LocalService(node=service.node) as twin:
        both = dataclasses.replace(service.options, connect=(service.endpoint, twin.endpoint))
        with TrackingClient(both, timeout=5.0) as client:
            assert _wait(lambda: len(client.nodes()) == 2, timeout=30)
            with pytest.raises(AmbiguousNode) as exc:
                client.start(camera.key, SCENE.box(0))
            assert str(exc.value).startswith(f"several services answer as node {service.node!r}: give each its own "
                                             "node id")
        assert main(["nodes", "--json", "--connect", service.endpoint, "--connect", twin.endpoint]) == 0
        assert [row["node"] for row in json.loads(capsys.readouterr().out)] == [service.node] * 2


def test_command_line_bad_zenoh_settings_are_one_line_usage_errors(capsys, tmp_path):
    """A malformed endpoint, a missing or malformed --zenoh-config file, a --listen port in use: Zenoh refuses them,
    which used to escape as a zenoh.ZError traceback, then read 'ZenohUnavailable: bad Zenoh configuration:
    Json5Err(Message { msg: ..., location: ... })' with exit 1, as if the network were down. They are errors of
    the command line: one plain line, exit 2."""
    import socket

    from tacf.cli import main

    broken = tmp_path / "broken.json5"
    broken.write_text("{ mode: ")
    twice = tmp_path / "twice.json5"            # Zenoh refuses a field given twice, in a wrapper of Rust's Debug
    twice.write_text('{\n  mode: "client",\n  scouting: { multicast: { enabled: false, enabled: true } },\n}')
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        taken = f"tcp/127.0.0.1:{busy.getsockname()[1]}"
        for argv, reason in (
                (["list", "--connect", "foo"], "bad Zenoh configuration: Endpoints must be of the form "
                                               "<protocol>/<address>[?<metadata>][#<config>]: foo"),
                (["watch", "--listen", "tcp-127.0.0.1"], "bad Zenoh configuration: Endpoints must be of the form"),
                (["list", "--zenoh-config", str(tmp_path / "missing.json5")],
                 f"bad Zenoh configuration ({tmp_path / 'missing.json5'}): No such file"),
                (["publish", "scene", "--key", "cam/a", "--zenoh-config", str(broken)],
                 f"bad Zenoh configuration ({broken}): "),
                (["list", "--zenoh-config", str(twice)],
                 f"bad Zenoh configuration ({twice}): duplicate field `enabled` (line 3, column 26)"),
                (["publish", "scene", "--key", "cam/a", "--listen", taken],
                 f"cannot open a Zenoh session: Can not create a new TCP listener bound to {taken}")):
            with pytest.raises(SystemExit) as exc:
                main(argv)
            err = capsys.readouterr().err
            assert exc.value.code == 2 and len(err.splitlines()) == 1, err
            assert err.startswith(f"tacf {argv[0]}: {reason}"), err
            assert "Json5Err" not in err and "Message {" not in err and ".rs:" not in err, err


def test_a_host_port_endpoint_without_a_port_is_refused_when_given(capsys):
    """ZenohOptions(connect="tcp/nonsense") opened a peer session without a word, which then never connected, and
    `tacf serve --connect tcp/nonsense` started ("workers connect to tcp/nonsense"): Zenoh checks only the
    <protocol>/<address> shape. Refused at once now, naming the endpoint and the form; every form Zenoh connects
    with is still taken (IPv6 with or without brackets, a host name, metadata and config after the address)."""
    from tacf.cli import main

    for bad in ("tcp/nonsense", "tcp/127.0.0.1", "tcp/127.0.0.1:abc", "tcp/:7447", "udp/10.0.0.5:70000",
                "tcp/127.0.0.1:7447 "):
        for options in ({"connect": bad}, {"listen": (bad,)}):
            with pytest.raises(ValueError, match=f"bad Zenoh endpoint {bad!r}: expected {bad.split('/')[0]}/HOST:PORT"):
                ZenohOptions(**options)
    for argv in (["list", "--connect", "tcp/nonsense"], ["watch", "--listen", "tcp/127.0.0.1"],
                 ["serve", "--connect", "tcp/nonsense"]):
        with pytest.raises(SystemExit) as exc:
            main(argv)
        err = capsys.readouterr().err
        assert exc.value.code == 2 and f"argument {argv[-2]}" in err and f"bad Zenoh endpoint '{argv[-1]}'" in err, err
    port = free_port()
    for good in ("tcp/[::1]:7447", "tcp/::1:7447", "tcp/edge.local:7447", "tcp/127.0.0.1:7447?prio=1-7#iface=lo",
                 "udp/224.0.0.224:7447#iface=eth0", "tls/localhost:7447", "quic/10.0.0.5:7447", "ws/10.0.0.5:7447",
                 "unixsock-stream//run/tacf.sock", "tcp/[::]:0"):
        assert ZenohOptions(connect=good, listen=good).connect == (good,)
    with zenoh.open(make_config(ZenohOptions.listener(f"tcp/[::1]:{port}"))):
        for endpoint in (f"tcp/[::1]:{port}", f"tcp/::1:{port}"):   # a Zenoh client opens only once connected
            with TrackingClient(ZenohOptions(connect=endpoint, mode="client"), timeout=1.0) as client:
                assert client.nodes() == []


def test_list_across_two_services(service, client, camera):
    with LocalService(node=f"second{free_port()}") as second:
        options = ZenohOptions(connect=(service.endpoint, second.endpoint))
        with TrackingClient(options, timeout=5.0) as both:
            second.wait_ready(both.session)
            assert sorted(both.nodes()) == sorted([service.node, second.node])
            with pytest.raises(AmbiguousNode, match="--node"):     # two services: start needs node=... (--node)
                both.start(camera.key, SCENE.box(0))
            info = both.start(camera.key, SCENE.box(0), sid="remote", node=second.node)
            assert info.node == second.node
            client.start(camera.key, SCENE.box(0), sid="local", node=service.node)
            try:
                sessions = {(s.node, s.sid) for s in both.list()}
                assert {(second.node, "remote"), (service.node, "local")} <= sessions
                assert both.status("remote").node == second.node     # found by a wildcard status query
                assert both.stop("remote").state == "stopped"
            finally:
                client.stop("local")


def test_command_line_start_list_status_stop(service, camera, capsys):
    from tacf.cli import main

    zenoh_args = ["--connect", service.endpoint]
    with pytest.raises(SystemExit) as exc:      # a bad --set is refused before anything is sent
        main(["start", "--key", camera.key, "--box", "148,167,25,19", "--set", "num_scales=many", *zenoh_args])
    assert exc.value.code == 2 and "num_scales must be an integer" in capsys.readouterr().err
    assert main(["start", "--key", camera.key, "--box", "148,167,25,19", "--sid", "cli1", "--seq",
                 str(camera.last_seq), "--set", "lambda1=2e-4", "--set", "subcell_peak=false", *zenoh_args]) == 0
    assert f"started cli1 on {service.node}" in capsys.readouterr().out
    assert main(["list", *zenoh_args]) == 0
    out = capsys.readouterr().out
    assert "cli1" in out and service.node in out and "SID" in out
    assert main(["status", "cli1", "--json", *zenoh_args]) == 0
    info = SessionInfo.model_validate_json(capsys.readouterr().out)
    assert info.sid == "cli1" and info.overrides == {"lambda1": 2e-4, "subcell_peak": False}
    for node in ([], ["--node", "auto"]):       # 'auto' is every node, as for list (a traceback, exit 1)
        assert main(["watch", "cli1", "--duration", "1.5", "--interval", "0.5", *node, *zenoh_args]) == 0
        assert "cli1" in capsys.readouterr().out
    # a box across the left border, as written: argparse before 3.14 took "-4,..." for an option
    assert main(["reinit", "cli1", "--box", "-4,167,25,19", "--seq", "0", *zenoh_args]) == 0   # frame 0 long gone
    captured = capsys.readouterr()
    assert "re-initialised cli1" in captured.out and "did not hold frame 0" in captured.err
    assert main(["stop", "cli1", *zenoh_args]) == 0
    assert "stopped cli1" in capsys.readouterr().out
    with pytest.raises(SystemExit) as exc:
        main(["stop", "cli1", *zenoh_args])
    assert exc.value.code == 1
    assert "UnknownSession" in capsys.readouterr().err


def test_command_line_list_of_a_service_that_does_not_answer_prints_an_empty_json_list(service, capsys):
    """`tacf list --json --node N` for a node that does not answer printed nothing at all, though the command
    promises [] with --json whenever no service answers (a script parsing its output then failed on '')."""
    from tacf.cli import main

    zenoh_args = ["--connect", service.endpoint, "--timeout", "1"]
    assert main(["list", "--json", "--node", "nobody", *zenoh_args]) == 1
    captured = capsys.readouterr()
    assert captured.out.strip() == "[]"
    assert captured.err.strip() == "tacf list: no tracking service answered (node 'nobody')", captured.err
    assert main(["list", "--node", "nobody", *zenoh_args]) == 1
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err.strip() == "tacf list: no tracking service answered (node 'nobody')"
    assert main(["list", "--json", "--node", service.node, *zenoh_args]) == 0       # no sessions: a valid answer
    assert [row["node"] for row in json.loads(capsys.readouterr().out)] == [service.node]


def test_nodes_shows_a_service_that_is_alive_but_does_not_answer(tmp_path):
    """With no other service answering, the list query's timeout used to end `tacf nodes` in an error (exit 1)
    instead of the row that says so."""
    import subprocess
    import sys

    port = free_port()
    with zenoh.open(make_config(ZenohOptions.listener(f"tcp/127.0.0.1:{port}"))) as hung:
        token = hung.liveliness().declare_token("@tacf/hung")
        queries = hung.declare_queryable("tacf/hung/control/*", zenoh.handlers.FifoChannel(64))   # never answered
        try:
            done = subprocess.run([sys.executable, "-m", "tacf.cli", "nodes", "--connect", f"tcp/127.0.0.1:{port}",
                                   "--timeout", "1"], capture_output=True, text=True, timeout=60)
        finally:
            queries.undeclare()
            token.undeclare()
    assert done.returncode == 0, done.stderr
    row = next(line for line in done.stdout.splitlines() if line.split()[:1] == ["hung"])
    assert "no answer" in row

