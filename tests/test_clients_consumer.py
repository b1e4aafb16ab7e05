"""The onboard BoxConsumer and the `tacf watch` table, fed by real BoxResult / Health messages over Zenoh.

These tests publish the service's result messages themselves (from a second real Zenoh session), so they
check the consumer's side of the wire contract without a tracker; test_clients.py covers the real service.
"""
from __future__ import annotations

import functools
import io
import logging
import threading
import time

import pytest
import zenoh

import tacf_clients.client as client_module
from tacf_clients.client import TrackingClient
from tacf_clients.consumer import BoxConsumer, TrackedBox, tracked_box
from tacf_clients.local_service import free_port
from tacf_clients.watch import SessionRow, describe_session, render_table, session_table, watch
from tacf_clients.zconfig import ZenohOptions, make_config
from tacf_schemas import box_key, encode, health_key
from tacf_schemas.models import BoxResult, Error, Health, SessionInfo
from tacf_service.loopback import wait_until

pytestmark = pytest.mark.zenoh


def _box(sid: str, seq: int, box=(64.0, 48.0, 32.0, 24.0), ok: bool = True, node: str = "edge1") -> BoxResult:
    now = time.time_ns()
    return BoxResult(node=node, sid=sid, seq=seq, stamp_ns=now - 5_000_000, box=box, width=320, height=240, ok=ok,
                     pme=20.0, score=0.5, scale=1.0, processing_ms=3.0, published_ns=now)


def _health(sid: str, state: str = "tracking", node: str = "edge1") -> Health:
    return Health(node=node, sid=sid, state=state, stamp_ns=time.time_ns(), fps=29.5, processing_ms_mean=3.0,
                  processing_ms_p95=4.5, frame_age_ms=7.0, frames_received=100, frames_processed=98,
                  frames_dropped=2)


class Network:
    """A 'service' session that listens and a 'vehicle' session that connects to it."""

    def __init__(self):
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.service = zenoh.open(make_config(ZenohOptions.listener(endpoint)))
        self.options = ZenohOptions(connect=(endpoint,))
        self.vehicle = zenoh.open(make_config(self.options))

    def put(self, message, leaf: str = "box"):
        key = (box_key if leaf == "box" else health_key)(message.node, message.sid)
        self.service.put(key, encode(message))

    def wait_matched(self, key: str, timeout: float = 5.0):
        publisher = self.service.declare_publisher(key)
        try:
            deadline = time.monotonic() + timeout
            while not publisher.matching_status.matching:
                assert time.monotonic() < deadline, f"nobody subscribed to {key}"
                time.sleep(0.02)
        finally:
            publisher.undeclare()

    def close(self):
        self.vehicle.close()
        self.service.close()


@pytest.fixture
def net():
    n = Network()
    yield n
    n.close()


def test_normalised_boxes_for_gimbal_and_mavlink():
    b = tracked_box(_box("s", 1, box=(64.0, 48.0, 32.0, 24.0)))
    assert b.normalised == pytest.approx((0.2, 0.2, 0.1, 0.1))
    assert b.corners_normalised == pytest.approx((0.2, 0.2, 0.3, 0.3))
    assert b.center == (80.0, 60.0) and b.center_norm == pytest.approx((0.25, 0.25))
    assert 0 < b.age_ms < 1000
    # partly outside the frame: clipped to 0..1
    edge = tracked_box(_box("s", 1, box=(-10.0, 230.0, 40.0, 20.0)))
    assert edge.corners_normalised == pytest.approx((0.0, 230 / 240, 30 / 320, 1.0))


def test_a_consumer_on_a_closed_session_raises_client_closed():
    """It raised zenoh's own ZError ("session closed"), which a caller catching TacfError did not catch."""
    from tacf_clients.errors import ClientClosed

    session = zenoh.open(make_config(ZenohOptions.listener(f"tcp/127.0.0.1:{free_port()}")))
    session.close()
    with pytest.raises(ClientClosed, match="the Zenoh session given to the consumer is closed"):
        BoxConsumer(session)


def test_iterator_one_session_in_order(net):
    with BoxConsumer(net.vehicle, sid="cam1") as boxes:
        net.wait_matched(box_key("edge1", "cam1"))
        for seq in range(5):
            net.put(_box("cam1", seq))
        net.put(_box("other", 99))                            # another session: filtered out by the key
        got = [boxes.get(timeout=5) for _ in range(5)]
        assert [b.seq for b in got] == [0, 1, 2, 3, 4]
        assert all(isinstance(b, TrackedBox) and b.normalised is not None for b in got)
        assert boxes.get(timeout=0.3) is None


def test_latest_only_across_sessions(net):
    with BoxConsumer(net.vehicle, latest_only=True) as boxes:      # every session of every service
        net.wait_matched(box_key("edge1", "a"))
        for seq in range(20):
            net.put(_box("a", seq))
            net.put(_box("b", 100 + seq, node="edge2"))
            net.put(_box("a", 200 + seq, node="edge2"))          # the same sid on another service: a session too
        assert _wait(lambda: boxes.received == 60)
        newest = {(b.node, b.sid): b.seq for b in iter(lambda: boxes.get(timeout=0.2), None)}
        assert newest == {("edge1", "a"): 19, ("edge2", "b"): 119, ("edge2", "a"): 219}
        assert boxes.dropped == 57
        # the session whose box waits longest comes first: a session sending often does not keep a consumer slower
        # than it from the others
        for box in (_box("a", 20), _box("b", 120, node="edge2"), _box("a", 21)):
            net.put(box)
        assert _wait(lambda: boxes.received == 63)
        assert [(b.sid, b.seq) for b in iter(lambda: boxes.get(timeout=0.2), None)] == [("b", 120), ("a", 21)]


def test_callback_form_and_lost_flag(net):
    got: list[TrackedBox] = []
    done = threading.Event()

    def on_box(b: TrackedBox):
        got.append(b)
        if len(got) == 3:
            done.set()

    with BoxConsumer(net.vehicle, sid="cam1", on_box=on_box):
        net.wait_matched(box_key("edge1", "cam1"))
        net.put(_box("cam1", 1))
        net.put(_box("cam1", 2, ok=False))
        net.service.put(box_key("edge1", "cam1"), b"\x93garbage")    # malformed: dropped, not fatal
        net.put(_box("cam1", 3))
        assert done.wait(5)
    assert [b.ok for b in got] == [True, False, True]


def test_a_full_queue_drops_its_oldest_boxes_and_counts_them(net):
    with BoxConsumer(net.vehicle, sid="cam1", queue_size=3) as boxes:
        net.wait_matched(box_key("edge1", "cam1"))
        for seq in range(5):
            net.put(_box("cam1", seq))
        assert _wait(lambda: boxes.received == 5)
        assert [b.seq for b in iter(lambda: boxes.get(timeout=0.2), None)] == [2, 3, 4]
        assert boxes.dropped == 2


def test_a_callback_that_fails_is_handed_the_next_boxes_all_the_same(net, caplog):
    """One failure of the user's callback (a gimbal's serial link down for a moment) is logged; the boxes after it
    still come, instead of the callback thread ending with it and every later box going unseen."""
    got: list[int] = []

    def on_box(b: TrackedBox):
        got.append(b.seq)
        if b.seq == 1:
            raise RuntimeError("gimbal link down")

    caplog.set_level(logging.ERROR, logger="tacf_clients.stream")
    with BoxConsumer(net.vehicle, sid="cam1", on_box=on_box):
        net.wait_matched(box_key("edge1", "cam1"))
        for seq in (1, 2, 3):
            net.put(_box("cam1", seq))
        assert _wait(lambda: got == [1, 2, 3]), got
    assert any("callback for tacf/*/sessions/cam1/box failed" in r.getMessage() for r in caplog.records)


def test_a_sample_decoded_while_the_stream_closes_is_not_handed_out_after_close(net):
    """close() empties the mailbox; a sample Zenoh was decoding meanwhile landed in it afterwards, and get() (or
    the callback thread) handed it out after close()."""
    from tacf_clients.stream import ResultStream

    decoding, closed = threading.Event(), threading.Event()

    def slow_decode(sample):
        decoding.set()
        closed.wait(5)
        return "late"

    stream = ResultStream(net.vehicle, "test/late", slow_decode)
    net.wait_matched("test/late")
    net.service.put("test/late", b"x")
    assert decoding.wait(5)
    closer = threading.Thread(target=stream.close)
    closer.start()
    assert _wait(lambda: stream.closed)
    closed.set()
    closer.join(10)
    assert not closer.is_alive()
    assert stream.get(timeout=0) is None


def test_closing_a_stream_after_its_session_stops_its_callback(net):
    """A stream whose Zenoh session closed first (the client's `with` ended) ignored its own close(): it returned at
    once, and the callback thread went on through every box still queued after it, as after no close at all."""
    client = TrackingClient(net.options)
    calls: list[int] = []
    release = threading.Event()

    def on_box(box: BoxResult) -> None:
        calls.append(box.seq)
        release.wait(5)                     # the first box holds the thread: the others queue up

    stream = client.subscribe("cam1", on_box=on_box)
    net.wait_matched(box_key("edge1", "cam1"))
    for seq in range(5):
        net.put(_box("cam1", seq))
    assert _wait(lambda: stream.received == 5)
    client.close()
    assert _wait(lambda: stream.closed)
    threading.Timer(0.3, release.set).start()   # the box in hand finishes while close() waits for the thread
    stream.close()
    assert not stream._thread.is_alive()
    time.sleep(0.3)
    assert calls == [0]


def test_a_subscription_with_a_health_callback_only_is_handed_the_health(net):
    health: list[Health] = []
    with TrackingClient(session=net.vehicle) as client, client.subscribe("cam1", on_health=health.append):
        net.wait_matched(health_key("edge1", "cam1"))
        net.put(_box("cam1", 1))
        net.put(_health("cam1", state="lost"), leaf="health")
        assert _wait(lambda: [h.state for h in health] == ["lost"]), health


def test_consumer_opens_its_own_session(net):
    with BoxConsumer(sid="cam9", options=net.options) as boxes:
        net.wait_matched(box_key("edge1", "cam9"))
        net.put(_box("cam9", 7))
        assert boxes.get(timeout=5).seq == 7
    assert boxes.session.is_closed(), "the session it opened is closed with it"
    with BoxConsumer(net.vehicle, sid="cam9"):
        pass
    assert not net.vehicle.is_closed(), "a session it was given is the caller's"


def test_a_bad_id_is_refused_as_the_client_refuses_it():
    """BoxConsumer let keys.InvalidIdError through, which is not a TacfError, where TrackingClient raises InvalidId;
    it is refused before any Zenoh session is opened."""
    from tacf_clients.errors import InvalidId

    for bad in (dict(sid="bad id"), dict(node="no/slash")):
        with pytest.raises(InvalidId):
            BoxConsumer(options=ZenohOptions(connect=("tcp/127.0.0.1:1",), mode="client"), **bad)


def test_render_table():
    row = SessionRow("edge1", "cam1")
    row.apply(_box("cam1", 42, ok=False))
    row.apply(_health("cam1", state="lost").model_copy(update={"frames_lost": 1}))
    text = render_table([row, SessionRow("edge2", "idle")])
    lines = text.splitlines()
    assert lines[0].split()[:3] == ["NODE", "SID", "STATE"]
    assert "cam1" in lines[1] and "lost" in lines[1] and "LOST" in lines[1] and "42" in lines[1]
    assert "(64, 48, 32, 24)" in lines[1] and "29.5" in lines[1]
    assert lines[0].split()[-3:] == ["RECV", "LOST", "DROP"] and lines[1].split()[-3:] == ["100", "1", "2"]
    assert "no sessions" in render_table([])


def test_the_session_table_puts_each_count_under_its_heading():
    health = _health("s1").model_copy(update={"frames_lost": 1})
    info = SessionInfo(node="edge1", sid="s1", image_key="cam/a", profile="paper", state="tracking",
                       box=(1.0, 2.0, 3.0, 4.0), created_ns=time.time_ns(), health=health)
    header, row = session_table([info]).splitlines()
    assert header.split()[-4:] == ["FPS", "PROCESSED", "LOST", "DROPPED"]
    assert row.split()[-4:] == ["29.5", "98", "1", "2"]


def test_a_row_not_heard_of_for_5_s_is_stale_unless_its_session_stopped():
    tracking, stopped = SessionRow("edge1", "cam1", state="tracking"), SessionRow("edge1", "cam2", state="stopped")
    assert "(stale)" not in render_table([tracking], now=tracking.updated + 4)
    assert "tracking (stale)" in render_table([tracking], now=tracking.updated + 6)
    assert "(stale)" not in render_table([stopped], now=stopped.updated + 60)     # a stopped session sends nothing


def test_a_session_s_line_says_why_it_failed_or_waits():
    """`tacf status` of a failed session said "failed" and not why, though the health it shows carries the reason."""
    reason = "cannot initialise on seq 0: box (1.0, 1.0, 5000.0, 5000.0) is larger than the 320x240 image"
    health = _health("s1", state="failed").model_copy(update={"message": reason})
    info = SessionInfo(node="edge1", sid="s1", image_key="cam/a", profile="paper", state="failed",
                       box=(1.0, 1.0, 5000.0, 5000.0), created_ns=time.time_ns(), health=health)
    assert describe_session(info).endswith(f"dropped 2: {reason}")
    assert describe_session(info.model_copy(update={"health": _health("s1")})).endswith("dropped 2")
    assert " fps" not in describe_session(info)      # `tacf stop` printed "0.0 fps, 0.0 ms p95" for the ended session
    assert " fps, " in describe_session(info.model_copy(update={"state": "tracking"}))


EVIL = "\x1b]0;owned\x07\x1b[2J\n2026-12-06 12:00:00,000 INFO all good"
EVIL_SHOWN = r"\x1b]0;owned\x07\x1b[2J\n2026-12-06 12:00:00,000 INFO all good"     # as printed


def test_the_free_text_of_a_session_is_printed_escaped():
    """A session's image key, profile and health message are free text in a reply, which anyone on the Zenoh
    network can send (a queryable on tacf/x/control/list answers `tacf list`): `tacf list`, `status`, `start` and
    `stop` printed them raw, terminal escapes and forged lines included."""
    health = _health("s1", state="failed").model_copy(update={"message": "why " + EVIL})
    info = SessionInfo(node="edge1", sid="s1", image_key="cam/" + EVIL, profile="p" + EVIL, state="failed",
                       box=(1.0, 1.0, 5.0, 5.0), created_ns=time.time_ns(), health=health)
    for text in (describe_session(info), session_table([info])):
        assert "\x1b" not in text and "\x07" not in text, text
        assert f"cam/{EVIL_SHOWN}" in text and f"p{EVIL_SHOWN}" in text
    assert "\n" not in describe_session(info) and describe_session(info).endswith(f"why {EVIL_SHOWN}")
    accented = info.model_copy(update={"image_key": "cam/é", "health": None})
    assert describe_session(accented).startswith("s1 on edge1: failed, key cam/é, ")    # printable: as it is


def test_an_error_message_from_the_network_is_printed_escaped(net, capsys):
    """An error reply's message went raw to stderr: `tacf status` asked every node, and a queryable of anyone on
    the network answered with terminal escapes."""
    from tacf.cli import main

    def on_query(query):
        with query:
            query.reply_err(encode(Error(code="unknown_session", message="no " + EVIL, node="evil")))

    queryable = net.service.declare_queryable("tacf/evil/control/*", on_query)
    try:
        with pytest.raises(SystemExit) as exc:
            main(["status", "s1", "--connect", net.options.connect[0], "--timeout", "2"])
    finally:
        queryable.undeclare()
    err = capsys.readouterr().err
    assert exc.value.code == 1 and f"no {EVIL_SHOWN}" in err, err
    assert "\x1b" not in err and len(err.splitlines()) == 1, err


def test_watch_prints_live_rows(net):
    out = io.StringIO()
    stop = threading.Event()
    thread = threading.Thread(target=watch, kwargs=dict(options=net.options, interval=0.2, duration=8, stop=stop,
                                                        out=out))
    thread.start()
    try:
        net.wait_matched(box_key("edge1", "w1"))
        for seq in range(5):
            net.put(_box("w1", seq))
            net.put(_health("w1"), leaf="health")
            time.sleep(0.1)
        assert _wait(lambda: "w1" in out.getvalue() and "tracking" in out.getvalue())
    finally:
        stop.set()
        thread.join(timeout=5)
    assert not thread.is_alive()
    assert "tacf watch" in out.getvalue()
    assert "\x1b" not in out.getvalue(), "no screen clearing where the output is not a terminal (a file, a pipe)"


def test_watch_ends_on_a_table_of_what_it_received(net):
    """With --duration no longer than --interval, the only table came before any box: SEQ and BOX "-"."""
    out = io.StringIO()
    thread = threading.Thread(target=watch, kwargs=dict(options=net.options, interval=60, duration=3, out=out))
    thread.start()
    net.wait_matched(box_key("edge1", "w2"))
    net.put(_box("w2", 17))
    thread.join(timeout=10)
    assert not thread.is_alive()
    last_table = out.getvalue().rstrip().split("tacf watch")[-1]
    assert "w2" in last_table and "17" in last_table and "(64, 48, 32, 24)" in last_table


def test_watch_ends_on_time_and_on_stop_whatever_the_interval(net):
    """A refresh period longer than --duration, or than the wait for Ctrl-C, does not hold the watch: with no
    session sending anything it used to sleep a whole interval before looking at either."""
    started = time.monotonic()
    out = io.StringIO()
    assert watch(options=net.options, interval=60, duration=1, out=out) == 0
    assert time.monotonic() - started < 5
    assert "(no service answered: waiting for one" in out.getvalue()    # it said nothing of that

    stop = threading.Event()
    thread = threading.Thread(target=watch, kwargs=dict(options=net.options, interval=60, stop=stop,
                                                        out=io.StringIO()))
    thread.start()
    time.sleep(1)
    stop.set()
    thread.join(timeout=5)
    assert not thread.is_alive(), "the watch ends soon after Ctrl-C"


def test_watch_stopped_during_its_first_query_says_nothing_of_services(net):
    """A Ctrl-C while the list query waited printed "(no service answered: waiting for one ...)" on the way out."""
    from tacf_schemas import control_key

    stop, out = threading.Event(), io.StringIO()

    def interrupted(query):
        with query:             # the Ctrl-C comes while the query waits; then it ends with no reply
            stop.set()
    queryable = net.service.declare_queryable(control_key("edge1", "list"), interrupted)
    try:
        thread = threading.Thread(target=watch, kwargs=dict(options=net.options, stop=stop, out=out))
        thread.start()
        thread.join(timeout=10)
        assert not thread.is_alive() and stop.is_set() and out.getvalue() == ""
    finally:
        queryable.undeclare()


def test_watch_of_one_session_follows_it_to_another_service(net):
    """`tacf watch SID` subscribed on the node the list found SID on, so a session stopped there and started
    again elsewhere (`tacf start --node auto`, a MAVLink bridge restarting it) never showed again: --node is what
    limits the watch to one service."""
    from tacf_schemas import control_key
    from tacf_schemas.models import SessionList

    info = SessionInfo(node="edge1", sid="moved", image_key="cam/a", profile="paper", state="tracking",
                       box=(1.0, 2.0, 3.0, 4.0), created_ns=time.time_ns())
    other = info.model_copy(update={"sid": "other-session"})       # listed too, and not watched

    def reply(query):
        with query:
            query.reply(control_key("edge1", "list"), encode(SessionList(node="edge1", max_sessions=8,
                                                                         sessions=[info, other])))

    queryable = net.service.declare_queryable(control_key("edge1", "list"), reply)
    out = io.StringIO()
    stop = threading.Event()
    thread = threading.Thread(target=watch, kwargs=dict(options=net.options, sid="moved", interval=0.2, duration=8,
                                                        stop=stop, out=out))
    thread.start()
    try:
        net.wait_matched(box_key("edge1", "moved"))
        net.put(_box("moved", 71, node="edge2"))
        assert _wait(lambda: "edge2" in out.getvalue() and "71" in out.getvalue())
    finally:
        stop.set()
        thread.join(timeout=5)
        queryable.undeclare()
    assert "moved" in out.getvalue() and "other-session" not in out.getvalue()


def test_watch_refuses_a_bad_session_id_before_it_says_anything(net):
    """`tacf watch a/b` first asked every service for its sessions (up to 2 s), printed that it was waiting for a
    service when none answered, and only then refused the id."""
    from tacf_clients.errors import InvalidId

    out = io.StringIO()
    started = time.monotonic()
    with pytest.raises(InvalidId):
        watch(options=net.options, sid="a/b", duration=1, out=out)
    assert out.getvalue() == "" and time.monotonic() - started < 1.5


_wait = functools.partial(wait_until, timeout=5.0, period=0.02)


def test_client_side_never_imports_the_tracker_and_the_cli_stays_light():
    import subprocess
    import sys

    code = (
        "import sys, argparse\n"
        "import tacf_clients.cli as cli\n"
        "cli.register(argparse.ArgumentParser().add_subparsers())\n"
        "assert 'zenoh' not in sys.modules and 'cv2' not in sys.modules, 'tacf --help must stay light'\n"
        "import tacf_clients.client, tacf_clients.consumer, tacf_clients.publisher, tacf_clients.demo\n"
        "import tacf_clients.watch, tacf_clients.sources, tacf_clients.scene\n"
        "heavy = [m for m in sys.modules if m.startswith(('tacf.tracker', 'tacf.features', 'tacf_service', "
        "'scipy'))]\n"
        "assert not heavy, heavy\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr


def test_the_tacf_parser_loads_neither_numpy_nor_the_heavy_libraries():
    """Every command's parser (`tacf --help`, and the start of every command) loaded numpy through tacf.config, which
    the commands import for the profile names: 60-110 ms of each start."""
    import subprocess
    import sys

    code = ("import sys, tacf.cli\n"
            "tacf.cli.build_parser()\n"
            "loaded = [m for m in ('numpy', 'scipy', 'cv2', 'zenoh', 'pydantic') if m in sys.modules]\n"
            "assert not loaded, loaded\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr


def test_watch_logs_the_key_of_a_malformed_result_escaped(net, caplog):
    """A Zenoh key may hold control characters: the key of a malformed result went raw into the warning, so that
    any peer could write terminal escapes (clear the screen, set the window title) and forged log lines to the
    terminal of `tacf watch`."""
    caplog.set_level(logging.WARNING, logger="tacf_clients.client")
    key = "tacf/edge1/sessions/\x1b]0;owned\x07\x1b[2J\n2026-12-06 12:00:00,000 INFO all good/box"
    stop = threading.Event()
    thread = threading.Thread(target=watch, kwargs=dict(options=net.options, interval=0.2, duration=8, stop=stop,
                                                        out=io.StringIO()))
    thread.start()
    try:
        net.wait_matched(key)
        net.service.put(key, b"\xc1")
        assert _wait(lambda: any("malformed box" in r.getMessage() for r in caplog.records))
    finally:
        stop.set()
        thread.join(timeout=5)
    warning = next(r.getMessage() for r in caplog.records if "malformed box" in r.getMessage())
    assert "\x1b" not in warning and "\x07" not in warning and "\n" not in warning, warning
    assert "\\x1b]0;owned" in warning


def test_malformed_results_are_warned_of_once_a_period_with_the_count_held_back(net, caplog, monkeypatch):
    """A service on another schema version sends every box and health malformed, one of each per frame and session:
    a warning each, 30 lines a second, scrolled `tacf watch`'s table away."""
    monkeypatch.setattr(client_module, "MALFORMED_WARNING_PERIOD_S", 1.0)
    caplog.set_level(logging.WARNING, logger="tacf_clients.client")
    key = box_key("edge1", "s1")
    with TrackingClient(session=net.vehicle) as client, client.results("s1", node="edge1") as stream:
        net.wait_matched(key)
        for _ in range(50):
            net.service.put(key, b"\xc1")
        assert _wait(lambda: stream.rejected == 50)
        time.sleep(1.0)
        net.service.put(key, b"\xc1")
        assert _wait(lambda: stream.rejected == 51)
    assert not net.vehicle.is_closed(), "the client closes only a session it opened"
    warnings = [r.getMessage() for r in caplog.records if "malformed box" in r.getMessage()]
    assert len(warnings) == 2 and "(49 more malformed results dropped since" in warnings[1], warnings


def test_a_decoder_failure_logs_the_key_escaped(net, caplog):
    """As above, for a decoder that fails: its key went raw into the log."""
    from tacf_clients.stream import ResultStream

    def failing_decode(sample):
        raise RuntimeError("decoder bug")

    caplog.set_level(logging.ERROR, logger="tacf_clients.stream")
    key = "test/\x1b[2J\n2026-12-06 12:00:00,000 INFO all good"
    with ResultStream(net.vehicle, "test/*", failing_decode) as stream:
        net.wait_matched(key)
        net.service.put(key, b"x")
        assert _wait(lambda: stream.rejected == 1)
    message = next(r.getMessage() for r in caplog.records if "cannot decode" in r.getMessage())
    assert "\x1b" not in message and "\n" not in message, message
