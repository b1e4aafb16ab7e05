"""`tacf mavlink` against a ground station made of pymavlink on loopback UDP: a real `tacf serve`, a camera
publishing the generated scene, the camera component in between. The ground station drags a rectangle
(MAV_CMD_CAMERA_TRACK_RECTANGLE), is shown the box (CAMERA_TRACKING_IMAGE_STATUS) and stops tracking, as
QGroundControl does."""
from __future__ import annotations

import math
import os
import threading
import time
from contextlib import contextmanager

import pytest

from tacf.eval.metrics import box_iou
from tacf_clients.client import DEFAULT_TIMEOUT, START_TIMEOUT, TrackingClient
from tacf_clients.local_service import LocalService, free_port
from tacf_clients.scene import Scene
from tacf_service.loopback import wait_until
from camera_rig import (hold_still, no_service_options, reset_rig, service_and_camera, serving,
                        tacf_command)

pytest.importorskip("pymavlink", reason="pip install -e '.[test]' installs pymavlink")
os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import common as mav  # noqa: E402

from tacf_clients.mavlink import MavlinkCamera, point_box, point_radius, signing_key_from_passphrase  # noqa: E402

pytestmark = pytest.mark.zenoh

SCENE = Scene.from_spec("scene:320x240")
KEY = "test/mavlink/cam"
SID = "mavlink-test-mavlink-cam"
GCS_SYSTEM, GCS_COMPONENT = 255, 190


@pytest.fixture(scope="module")
def rig():
    """Service, camera (held still until a test lets it move), camera component and ground station."""
    with service_and_camera(SCENE, KEY, "mav") as (service, session, camera):
        port = free_port()
        gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=GCS_SYSTEM,
                                         source_component=GCS_COMPONENT, dialect="common")
        component = MavlinkCamera(f"udpout:127.0.0.1:{port}", KEY, options=service.options)
        stop = threading.Event()
        loop = threading.Thread(target=component.serve, args=(stop,), name="mavlink-camera")
        loop.start()
        try:
            # udpin learns its peer from the first packet: the ground station can talk once it heard one
            assert _receive(gcs, "HEARTBEAT") is not None, "the camera component announces itself"
            yield gcs, camera, TrackingClient(session=session, node=service.node, timeout=10.0), component
        finally:
            stop.set()
            loop.join(timeout=10)
            component.close()
            gcs.close()


@pytest.fixture(autouse=True)
def _rig_reset(request):
    yield
    if "rig" in request.fixturenames:
        _, camera, client, _ = request.getfixturevalue("rig")
        reset_rig(camera, client)


@contextmanager
def _own_service(key: str, *serve_args: str):
    """A service of its own (`tacf serve` with serve_args), a camera on `key` and a ground station: yields
    (service, session, gcs, the ground station's port)."""
    import zenoh

    from tacf_clients.demo import HoldingPublisher
    from tacf_clients.scene import SceneSource
    from tacf_clients.zconfig import make_config

    service = LocalService(node=f"mav{free_port()}", extra_args=serve_args)
    with service, zenoh.open(make_config(service.options)) as session:
        service.wait_ready(session)
        camera = HoldingPublisher(session, SceneSource(SCENE), key, 20, "jpeg")
        camera.start()
        port = free_port()
        gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=GCS_SYSTEM,
                                         source_component=GCS_COMPONENT, dialect="common")
        try:
            yield service, session, gcs, port
        finally:
            gcs.close()
            camera.close()


def _receive(gcs, kind: str, timeout: float = 10.0, where=lambda m: True):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        message = gcs.recv_match(type=kind, blocking=True, timeout=0.2)
        if message is not None and where(message):
            return message
    return None


def _command(gcs, command: int, *params: float, component: int = mav.MAV_COMP_ID_CAMERA, system: int = 1,
             timeout: float = 20.0):
    """Send COMMAND_LONG and return its final COMMAND_ACK's result (None: no ACK), past any IN_PROGRESS."""
    params = list(params) + [0.0] * (7 - len(params))
    gcs.mav.command_long_send(system, component, command, 0, *params)
    ack = _receive(gcs, "COMMAND_ACK", timeout,
                   where=lambda m: m.command == command and m.result != mav.MAV_RESULT_IN_PROGRESS)
    return None if ack is None else ack.result


def _normalised_corners(box):
    x, y, w, h = box
    return x / SCENE.width, y / SCENE.height, (x + w) / SCENE.width, (y + h) / SCENE.height


def _status_box(status):
    return (status.rec_top_x * SCENE.width, status.rec_top_y * SCENE.height,
            (status.rec_bottom_x - status.rec_top_x) * SCENE.width,
            (status.rec_bottom_y - status.rec_top_y) * SCENE.height)


def test_announces_a_camera_that_tracks_rectangles_and_points(rig):
    gcs, camera, client, _ = rig
    heartbeat = _receive(gcs, "HEARTBEAT", where=lambda m: m.get_srcComponent() == mav.MAV_COMP_ID_CAMERA)
    assert heartbeat is not None and heartbeat.type == mav.MAV_TYPE_CAMERA
    assert _receive(gcs, "HEARTBEAT", timeout=3) is not None, "a heartbeat every second"
    for request in ((mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_CAMERA_INFORMATION),
                    (mav.MAV_CMD_REQUEST_CAMERA_INFORMATION, 1)):
        assert _command(gcs, *request) == mav.MAV_RESULT_ACCEPTED
        info = _receive(gcs, "CAMERA_INFORMATION")
        assert info is not None and info.flags & mav.CAMERA_CAP_FLAGS_HAS_TRACKING_RECTANGLE
        assert info.flags & mav.CAMERA_CAP_FLAGS_HAS_TRACKING_POINT
        assert (info.resolution_h, info.resolution_v) == (SCENE.width, SCENE.height)
        assert bytes(info.model_name).rstrip(b"\0") == b"TACF tracker"


def test_a_start_waits_as_long_as_the_clients(rig):
    """The component gave every call 5 s, a start too, which a cold service's first start can take longer to
    answer (5.7 s with numba's cache empty): the operator's first TRACK failed while the session started."""
    _, _, _, component = rig
    assert component.client.start_timeout == START_TIMEOUT and component.client.timeout == DEFAULT_TIMEOUT


def test_refuses_what_it_cannot_do_and_ignores_other_components(rig):
    gcs, _, client, component = rig
    for corners in ((0.6, 0.2, 0.4, 0.5), (0.1, 0.1, 0.1, 0.3), (-0.1, 0.2, 0.3, 0.4), (0.1, 0.2, 1.5, 0.4),
                    (math.nan, 0.2, 0.3, 0.4)):
        assert _command(gcs, mav.MAV_CMD_CAMERA_TRACK_RECTANGLE, *corners) == mav.MAV_RESULT_DENIED, corners
    for point in ((1.2, 0.5, 0.1), (0.5, -0.1, 0.1), (0.5, 0.5, 1.5), (0.5, 0.5, math.nan)):
        assert _command(gcs, mav.MAV_CMD_CAMERA_TRACK_POINT, *point) == mav.MAV_RESULT_DENIED, point
    # a drag to the frame's edges (a ground station clamps it to 0..1) is no refusal
    assert wait_until(lambda: component._frame_header() is not None, 10)
    assert _command(gcs, mav.MAV_CMD_CAMERA_TRACK_RECTANGLE, 0.0, 0.5, 0.5, 1.0) == mav.MAV_RESULT_ACCEPTED
    assert _command(gcs, mav.MAV_CMD_CAMERA_STOP_TRACKING) == mav.MAV_RESULT_ACCEPTED
    assert _command(gcs, mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_HEARTBEAT) == mav.MAV_RESULT_UNSUPPORTED
    assert _command(gcs, mav.MAV_CMD_REQUEST_MESSAGE, math.nan) == mav.MAV_RESULT_UNSUPPORTED
    assert _command(gcs, mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_HEARTBEAT, 1e6) == \
        mav.MAV_RESULT_UNSUPPORTED
    assert _command(gcs, mav.MAV_CMD_CAMERA_TRACK_RECTANGLE, 0.1, 0.1, 0.3, 0.3, component=101, timeout=1.5) is None
    # the camera of another vehicle (system 2) on the same MAVLink network: its drag is not for this one
    assert _command(gcs, mav.MAV_CMD_CAMERA_TRACK_RECTANGLE, 0.1, 0.1, 0.3, 0.3, system=2, timeout=1.5) is None
    # broadcast commands it does not handle are the other components' to answer (MAVProxy asks every component for
    # the home position); the ones it handles it answers
    assert _command(gcs, mav.MAV_CMD_GET_HOME_POSITION, component=0, timeout=1.5) is None
    assert _command(gcs, mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_HEARTBEAT, component=0, timeout=1.5) is None
    assert _command(gcs, mav.MAV_CMD_GET_HOME_POSITION) == mav.MAV_RESULT_UNSUPPORTED
    assert _command(gcs, mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_CAMERA_INFORMATION, component=0) == \
        mav.MAV_RESULT_ACCEPTED
    assert _command(gcs, mav.MAV_CMD_CAMERA_STOP_TRACKING) == mav.MAV_RESULT_ACCEPTED, "nothing to stop is fine"
    # broadcast tracking commands that name another camera (param5 of TRACK_RECTANGLE, param1 of STOP_TRACKING) are
    # that camera's: with one component per camera, camera 101's rectangle used to start this one tracking
    other = mav.MAV_COMP_ID_CAMERA + 1
    assert _command(gcs, mav.MAV_CMD_CAMERA_TRACK_RECTANGLE, 0.1, 0.1, 0.3, 0.3, other, component=0,
                    timeout=1.5) is None
    assert _command(gcs, mav.MAV_CMD_CAMERA_STOP_TRACKING, other, component=0, timeout=1.5) is None
    assert _command(gcs, mav.MAV_CMD_CAMERA_STOP_TRACKING, mav.MAV_COMP_ID_CAMERA, component=0) == \
        mav.MAV_RESULT_ACCEPTED
    assert SID not in {info.sid for info in client.list()}


def test_any_command_gets_an_answer_and_the_component_lives_on(rig):
    """Hostile or garbled commands (any id, NaN, infinities, huge and negative values): each gets a COMMAND_ACK,
    no session appears, and the component keeps answering."""
    import random

    gcs, _, client, _ = rig
    rng = random.Random(0)
    specials = [math.nan, math.inf, -math.inf, -1.0, 0.0, 1.0, 0.5, 1e30, -1e30, 2 ** 31, 3.4e38]
    commands = [mav.MAV_CMD_CAMERA_TRACK_RECTANGLE, mav.MAV_CMD_CAMERA_STOP_TRACKING, mav.MAV_CMD_REQUEST_MESSAGE,
                mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAV_CMD_REQUEST_CAMERA_INFORMATION, 0, 65535]
    for command, param in ((mav.MAV_CMD_SET_MESSAGE_INTERVAL, math.nan), (mav.MAV_CMD_SET_MESSAGE_INTERVAL, math.inf),
                           (mav.MAV_CMD_REQUEST_MESSAGE, -math.inf)):
        assert _command(gcs, command, param) == mav.MAV_RESULT_UNSUPPORTED, (command, param)
    for _ in range(60):
        command = rng.choice(commands + [rng.randrange(65536)])
        params = [rng.choice(specials + [rng.uniform(-2, 2)]) for _ in range(7)]
        if command == mav.MAV_CMD_CAMERA_TRACK_RECTANGLE and all(0 <= p <= 1 for p in params[:4]) \
                and params[0] < params[2] and params[1] < params[3]:
            params[2] = params[0]                   # a valid rectangle would start a session: not this test's
        result = _command(gcs, command, *params)
        assert result in (mav.MAV_RESULT_ACCEPTED, mav.MAV_RESULT_DENIED, mav.MAV_RESULT_UNSUPPORTED), \
            (command, params, result)
    assert _command(gcs, mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_CAMERA_TRACKING_IMAGE_STATUS, 0) == \
        mav.MAV_RESULT_ACCEPTED
    # an interval is -1 (off), 0 (the default) or positive: -0.5 turned the status off as if it were -1
    for interval_us in (-0.5, -1.5):
        assert _command(gcs, mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_CAMERA_TRACKING_IMAGE_STATUS,
                        interval_us) == mav.MAV_RESULT_DENIED, interval_us
    assert SID not in {info.sid for info in client.list()}
    assert _receive(gcs, "HEARTBEAT", timeout=3) is not None


def _packed_command(gcs, command: int, *params: float) -> bytes:
    """COMMAND_LONG to the camera as it goes on the wire, for a datagram the test puts together itself."""
    params = list(params) + [0.0] * (7 - len(params))
    return gcs.mav.command_long_encode(1, mav.MAV_COMP_ID_CAMERA, command, 0, *params).pack(gcs.mav)


@pytest.mark.parametrize("cut", [1, 20], ids=["a lone start marker", "a command cut short"])
def test_a_garbled_datagram_costs_no_later_command(rig, cut):
    """Over UDP each datagram holds whole messages. pymavlink parses the link as one stream, so a datagram that
    ends inside a message took the next datagrams to complete it: after a lone 0xFD (MAVLink 2's start marker) the
    next command's own marker read as a length of 253, and the 6 commands that followed went unanswered."""
    gcs = rig[0]
    gcs.write(_packed_command(gcs, mav.MAV_CMD_CAMERA_STOP_TRACKING)[:cut])
    answered = sum(_command(gcs, mav.MAV_CMD_CAMERA_STOP_TRACKING, timeout=2.0) == mav.MAV_RESULT_ACCEPTED
                   for _ in range(10))
    assert answered == 10, f"{answered} of 10 commands answered after the garbled datagram"


def test_every_command_of_a_datagram_is_answered(rig):
    """A datagram may carry several messages back to back (a router batches them): each is answered."""
    gcs = rig[0]
    commands = (mav.MAV_CMD_CAMERA_STOP_TRACKING, mav.MAV_CMD_REQUEST_CAMERA_INFORMATION, mav.MAV_CMD_GET_HOME_POSITION)
    gcs.write(b"".join(_packed_command(gcs, command) for command in commands))
    acks = {}
    while len(acks) < len(commands) and (ack := _receive(gcs, "COMMAND_ACK", timeout=5)) is not None:
        acks[ack.command] = ack.result
    assert acks == {mav.MAV_CMD_CAMERA_STOP_TRACKING: mav.MAV_RESULT_ACCEPTED,
                    mav.MAV_CMD_REQUEST_CAMERA_INFORMATION: mav.MAV_RESULT_ACCEPTED,
                    mav.MAV_CMD_GET_HOME_POSITION: mav.MAV_RESULT_UNSUPPORTED}


def _held_target(camera, component) -> tuple:
    """Hold the camera (a still camera: the target is where the operator drags) until the component's newest
    frame, which a drag is put on, is a held one; the target's box on it. A fixed sleep after the hold left a
    frame from before it as the component's newest on a busy machine."""
    first = hold_still(camera)
    assert wait_until(lambda: (header := component._frame_header()) is not None and header.seq >= first, 10)
    return SCENE.box(camera.index_of(first))


def test_a_dragged_rectangle_is_tracked_shown_and_stopped(rig, monkeypatch):
    gcs, camera, client, component = rig
    target = _held_target(camera, component)
    boxes_started, start = [], component.client.start
    monkeypatch.setattr(component.client, "start", lambda key, box, **kw: boxes_started.append(box) or
                        start(key, box, **kw))
    assert _command(gcs, mav.MAV_CMD_CAMERA_TRACK_RECTANGLE, *_normalised_corners(target)) == \
        mav.MAV_RESULT_ACCEPTED
    # in pixels, exactly: the IoU below lets a box of the target's height and width through (the scene's 25 x 19)
    assert boxes_started == [pytest.approx(target)]
    info = client.status(SID)
    assert info.image_key == KEY
    status = _receive(gcs, "CAMERA_TRACKING_IMAGE_STATUS",
                      where=lambda m: m.target_data == mav.CAMERA_TRACKING_TARGET_DATA_IN_STATUS)
    assert status is not None and status.tracking_status & mav.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE
    assert status.tracking_mode == mav.CAMERA_TRACKING_MODE_RECTANGLE
    assert status.tracking_status == mav.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE, "held still: tracked, not coasting"
    assert math.isnan(status.radius), "a radius only in point mode"
    assert box_iou(_status_box(status), target) > 0.5, (_status_box(status), target)
    assert abs(status.point_x - (status.rec_top_x + status.rec_bottom_x) / 2) < 1e-4

    started, count = time.monotonic(), 0
    while time.monotonic() - started < 2.0:
        count += _receive(gcs, "CAMERA_TRACKING_IMAGE_STATUS", timeout=0.2) is not None
    assert 8 <= count <= 40, f"{count} statuses in 2 s at the default 10 Hz (1 Hz: 2)"

    # The target moves; the boxes follow it, at the rate the ground station asks for.
    camera.hold.clear()
    moved = _receive(gcs, "CAMERA_TRACKING_IMAGE_STATUS", timeout=20,
                     where=lambda m: m.target_data and box_iou(_status_box(m), target) < 0.3)
    assert moved is not None, "the box moves with the target"
    assert _command(gcs, mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_CAMERA_TRACKING_IMAGE_STATUS,
                    500_000) == mav.MAV_RESULT_ACCEPTED
    started, count = time.monotonic(), 0
    while time.monotonic() - started < 3.0:
        count += _receive(gcs, "CAMERA_TRACKING_IMAGE_STATUS", timeout=0.2) is not None
    assert 2 <= count <= 8, f"{count} statuses in 3 s at 2 Hz"
    assert _command(gcs, mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_CAMERA_TRACKING_IMAGE_STATUS,
                    -1) == mav.MAV_RESULT_ACCEPTED
    _receive(gcs, "CAMERA_TRACKING_IMAGE_STATUS", timeout=0.5)                   # one may be on its way
    assert _receive(gcs, "CAMERA_TRACKING_IMAGE_STATUS", timeout=1.5) is None, "off means off"
    assert _command(gcs, mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_CAMERA_TRACKING_IMAGE_STATUS) == \
        mav.MAV_RESULT_ACCEPTED
    assert _receive(gcs, "CAMERA_TRACKING_IMAGE_STATUS", timeout=5) is not None, "one on request"
    assert _command(gcs, mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_CAMERA_TRACKING_IMAGE_STATUS,
                    0) == mav.MAV_RESULT_ACCEPTED

    # Dragging again re-targets the same session.
    again = _held_target(camera, component)
    assert _command(gcs, mav.MAV_CMD_CAMERA_TRACK_RECTANGLE, *_normalised_corners(again)) == \
        mav.MAV_RESULT_ACCEPTED
    assert client.status(SID).init_seq is not None and client.status(SID).init_seq > info.init_seq

    assert _command(gcs, mav.MAV_CMD_CAMERA_STOP_TRACKING) == mav.MAV_RESULT_ACCEPTED
    idle = _receive(gcs, "CAMERA_TRACKING_IMAGE_STATUS",
                    where=lambda m: m.tracking_status == mav.CAMERA_TRACKING_STATUS_FLAGS_IDLE)
    assert idle is not None and idle.tracking_mode == mav.CAMERA_TRACKING_MODE_NONE and math.isnan(idle.rec_top_x)
    assert _receive(gcs, "CAMERA_TRACKING_IMAGE_STATUS", timeout=1.0) is None, "one IDLE status, then none"
    assert SID not in {s.sid for s in client.list()}

    # A session stopped elsewhere (the dashboard, tacf stop) ends the tracking the ground station sees.
    assert _command(gcs, mav.MAV_CMD_CAMERA_TRACK_RECTANGLE, *_normalised_corners(again)) == \
        mav.MAV_RESULT_ACCEPTED
    client.stop(SID)
    idle = _receive(gcs, "CAMERA_TRACKING_IMAGE_STATUS",
                    where=lambda m: m.tracking_status == mav.CAMERA_TRACKING_STATUS_FLAGS_IDLE)
    assert idle is not None, "an IDLE status once the session is gone"
    camera.hold.clear()


def test_a_point_is_the_square_of_its_radius_around_it_cut_to_the_frame():
    assert point_box((0.5, 0.5, 0.05), 320, 240) == (144.0, 104.0, 32.0, 32.0)
    assert point_box((0.5, 0.5, 0.0), 320, 240) == (159.0, 119.0, 2.0, 2.0)       # 0 is one pixel
    assert point_box((1.0, 0.0, 0.1), 320, 240) == (288.0, 0.0, 32.0, 32.0)        # at a corner: its quarter in view
    assert point_box((0.5, 0.5, 1.0), 320, 240) == (0.0, 0.0, 320.0, 240.0)


def test_a_status_radius_is_the_box_s_half_side_in_image_widths_at_most_one():
    assert point_radius(32.0, 20.0, 320) == pytest.approx(0.05)        # point_box's square, back
    assert point_radius(20.0, 700.0, 320) == 1.0        # a tall box on a portrait frame: MAVLink's radius is 0..1


def test_a_clicked_point_is_tracked_and_shown_in_point_mode(rig):
    """QGroundControl sends TRACK_POINT for a click rather than a drag: it was UNSUPPORTED."""
    gcs, camera, client, component = rig
    target = _held_target(camera, component)
    x, y, w, h = target
    radius = max(w, h) / 2 / SCENE.width
    assert _command(gcs, mav.MAV_CMD_CAMERA_TRACK_POINT, (x + w / 2) / SCENE.width, (y + h / 2) / SCENE.height,
                    radius) == mav.MAV_RESULT_ACCEPTED
    assert client.status(SID).image_key == KEY
    status = _receive(gcs, "CAMERA_TRACKING_IMAGE_STATUS",
                      where=lambda m: m.target_data == mav.CAMERA_TRACKING_TARGET_DATA_IN_STATUS)
    assert status is not None and status.tracking_status & mav.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE
    assert status.tracking_mode == mav.CAMERA_TRACKING_MODE_POINT
    assert box_iou(_status_box(status), target) > 0.5, (_status_box(status), target)
    assert status.radius == pytest.approx(radius, rel=0.3)
    assert _command(gcs, mav.MAV_CMD_CAMERA_STOP_TRACKING) == mav.MAV_RESULT_ACCEPTED
    assert SID not in {s.sid for s in client.list()}
    camera.hold.clear()


def test_a_faster_status_rate_applies_at_once(rig):
    """A ground station that asks for a faster rate gets the next status at that rate: it used to wait out the
    interval set before (5 s here) first."""
    gcs, camera, _, component = rig
    status_id = mav.MAVLINK_MSG_ID_CAMERA_TRACKING_IMAGE_STATUS
    try:
        target = _held_target(camera, component)
        assert _command(gcs, mav.MAV_CMD_CAMERA_TRACK_RECTANGLE, *_normalised_corners(target)) == \
            mav.MAV_RESULT_ACCEPTED
        assert _command(gcs, mav.MAV_CMD_SET_MESSAGE_INTERVAL, status_id, 5_000_000) == mav.MAV_RESULT_ACCEPTED
        _receive(gcs, "CAMERA_TRACKING_IMAGE_STATUS", timeout=0.5)                   # one due at the old rate
        assert _receive(gcs, "CAMERA_TRACKING_IMAGE_STATUS", timeout=1.0) is None, "one every 5 s"
        assert _command(gcs, mav.MAV_CMD_SET_MESSAGE_INTERVAL, status_id, 100_000) == mav.MAV_RESULT_ACCEPTED
        assert _receive(gcs, "CAMERA_TRACKING_IMAGE_STATUS", timeout=1.0) is not None, "the new rate at once"
    finally:
        assert _command(gcs, mav.MAV_CMD_SET_MESSAGE_INTERVAL, status_id, 0) == mav.MAV_RESULT_ACCEPTED
        assert _command(gcs, mav.MAV_CMD_CAMERA_STOP_TRACKING) == mav.MAV_RESULT_ACCEPTED
        camera.hold.clear()


def test_a_start_answered_too_late_is_stopped_by_a_stop(rig, monkeypatch):
    """A start whose reply came after the timeout may have started the session: the stop that followed said
    ACCEPTED without asking the service, and the session ran on, holding a slot."""
    from tacf_clients.errors import RequestTimeout

    gcs, camera, client, component = rig
    target = _held_target(camera, component)
    start = component.client.start

    def answered_too_late(*args, **kwargs):
        start(*args, **kwargs)
        raise RequestTimeout("no reply on tacf/test/control/start within 5 s")
    monkeypatch.setattr(component.client, "start", answered_too_late)
    try:
        assert _command(gcs, mav.MAV_CMD_CAMERA_TRACK_RECTANGLE, *_normalised_corners(target)) == \
            mav.MAV_RESULT_FAILED
        assert SID in {s.sid for s in client.list()}
        assert _command(gcs, mav.MAV_CMD_CAMERA_STOP_TRACKING) == mav.MAV_RESULT_ACCEPTED
        assert SID not in {s.sid for s in client.list()}
    finally:
        camera.hold.clear()


def test_a_refused_re_target_leaves_the_session_tracking_and_stoppable(rig, monkeypatch):
    """A drag the service refuses while a session runs fails, and changes nothing: the status stays ACTIVE with the
    box (not ERROR, which would say the tracking stopped) and a stop still stops the session."""
    from tacf_clients.errors import TacfError

    gcs, camera, client, component = rig
    target = _held_target(camera, component)
    try:
        assert _command(gcs, mav.MAV_CMD_CAMERA_TRACK_RECTANGLE, *_normalised_corners(target)) == \
            mav.MAV_RESULT_ACCEPTED

        def refused(*args, **kwargs):
            raise TacfError("refused")
        monkeypatch.setattr(component.client, "reinit", refused)
        assert _command(gcs, mav.MAV_CMD_CAMERA_TRACK_RECTANGLE, *_normalised_corners(target)) == \
            mav.MAV_RESULT_FAILED
        monkeypatch.undo()
        assert component.tracking
        assert _receive(gcs, "CAMERA_TRACKING_IMAGE_STATUS", where=lambda m: m.target_data and
                        m.tracking_status & mav.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE) is not None
        assert _command(gcs, mav.MAV_CMD_CAMERA_STOP_TRACKING) == mav.MAV_RESULT_ACCEPTED
        assert SID not in {s.sid for s in client.list()}, "the stop stopped it on the service"
    finally:
        camera.hold.clear()


def test_commands_sent_as_command_int_are_answered_alike(rig):
    """The command protocol lets a ground station send any command as COMMAND_INT instead of COMMAND_LONG (the
    same four float params, then x, y, z): the rectangle starts the session and the stop ends it either way."""
    gcs, camera, client, component = rig
    target = _held_target(camera, component)

    def command_int(command: int, *params: float):
        params = list(params) + [0.0] * (4 - len(params))
        gcs.mav.command_int_send(1, mav.MAV_COMP_ID_CAMERA, mav.MAV_FRAME_GLOBAL, command, 0, 0, *params, 0, 0, 0.0)
        ack = _receive(gcs, "COMMAND_ACK", 20,
                       where=lambda m: m.command == command and m.result != mav.MAV_RESULT_IN_PROGRESS)
        return None if ack is None else ack.result

    assert command_int(mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_CAMERA_INFORMATION) == mav.MAV_RESULT_ACCEPTED
    assert _receive(gcs, "CAMERA_INFORMATION") is not None
    assert command_int(mav.MAV_CMD_CAMERA_TRACK_RECTANGLE, 0.6, 0.2, 0.4, 0.5) == mav.MAV_RESULT_DENIED
    assert command_int(mav.MAV_CMD_CAMERA_TRACK_RECTANGLE, *_normalised_corners(target)) == mav.MAV_RESULT_ACCEPTED
    assert client.status(SID).image_key == KEY
    assert command_int(mav.MAV_CMD_CAMERA_STOP_TRACKING) == mav.MAV_RESULT_ACCEPTED
    assert SID not in {s.sid for s in client.list()}
    camera.hold.clear()


def test_a_session_stopped_elsewhere_is_dragged_again_and_stopped_at_once(rig, monkeypatch):
    """The component notices a session stopped elsewhere (the dashboard, `tacf stop`) only every SESSION_CHECK_S:
    a drag or a stop from the ground station in between is not refused for it. The drag starts the session again,
    the stop is done (ACCEPTED)."""
    import tacf_clients.mavlink

    _, camera, client, rig_component = rig
    monkeypatch.setattr(tacf_clients.mavlink, "SESSION_CHECK_S", 60.0)   # only the check right after a start
    sid, port = "mavlink-elsewhere", free_port()
    gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=GCS_SYSTEM,
                                     source_component=GCS_COMPONENT, dialect="common")
    stop = threading.Event()
    with MavlinkCamera(f"udpout:127.0.0.1:{port}", KEY, session=rig_component.session, sid=sid) as component:
        loop = threading.Thread(target=component.serve, args=(stop,))
        loop.start()
        try:
            assert _receive(gcs, "HEARTBEAT") is not None
            checked, check = threading.Event(), component._check_session

            def check_and_tell() -> int:
                try:
                    return check()
                finally:
                    checked.set()
            component._check_session = check_and_tell
            target = _normalised_corners(_held_target(camera, component))
            assert _command(gcs, mav.MAV_CMD_CAMERA_TRACK_RECTANGLE, *target) == mav.MAV_RESULT_ACCEPTED
            assert checked.wait(10), "the check that follows the start is done"
            for stop_from_the_ground_station in (False, True):
                client.stop(sid)
                assert component.tracking, "not noticed yet"
                if stop_from_the_ground_station:
                    assert _command(gcs, mav.MAV_CMD_CAMERA_STOP_TRACKING) == mav.MAV_RESULT_ACCEPTED
                    assert not component.tracking
                else:
                    assert _command(gcs, mav.MAV_CMD_CAMERA_TRACK_RECTANGLE, *target) == mav.MAV_RESULT_ACCEPTED
                    assert client.status(sid).state in ("starting", "tracking")
        finally:
            stop.set()
            loop.join(timeout=10)
            gcs.close()
            camera.hold.clear()
    assert sid not in {s.sid for s in client.list()}


def test_a_session_left_running_by_a_killed_component_is_taken_over(rig):
    """A component killed before it could stop its session leaves it running under the same sid: the next
    component's first drag re-targets it, and its stop stops it. A session under that sid on another key is not
    the component's: the drag fails and leaves it alone."""
    from tacf_schemas.images import encode_frame

    gcs, camera, client, component = rig
    target = _held_target(camera, component)
    left = client.start(KEY, target, camera.last_seq, sid=SID)   # as the killed component left it
    assert not component.tracking
    # the drag is on a newer frame than the one left behind
    assert wait_until(lambda: component._frame_header().seq > left.init_seq, 10)
    assert _command(gcs, mav.MAV_CMD_CAMERA_TRACK_RECTANGLE, *_normalised_corners(target)) == \
        mav.MAV_RESULT_ACCEPTED
    taken = client.status(SID)
    assert taken.created_ns == left.created_ns and taken.init_seq > left.init_seq, "the same session, re-targeted"
    status = _receive(gcs, "CAMERA_TRACKING_IMAGE_STATUS",
                      where=lambda m: m.target_data == mav.CAMERA_TRACKING_TARGET_DATA_IN_STATUS)
    assert status is not None and box_iou(_status_box(status), target) > 0.5
    assert _command(gcs, mav.MAV_CMD_CAMERA_STOP_TRACKING) == mav.MAV_RESULT_ACCEPTED
    assert SID not in {s.sid for s in client.list()}

    elsewhere, theirs = "test/mavlink/elsewhere", (200.0, 150.0, 60.0, 50.0)
    client.start(elsewhere, theirs, 0, sid=SID, frames=[encode_frame(SCENE.frame(0), 0)])
    try:
        assert _command(gcs, mav.MAV_CMD_CAMERA_TRACK_RECTANGLE, 0.05, 0.05, 0.2, 0.2) == mav.MAV_RESULT_FAILED
        assert not component.tracking
        assert box_iou(client.status(SID).box, theirs) > 0.9, "not re-targeted"
        # the failed start is not forgotten: the ground station is shown it until it clears it
        assert _receive(gcs, "CAMERA_TRACKING_IMAGE_STATUS",
                        where=lambda m: m.tracking_status == mav.CAMERA_TRACKING_STATUS_FLAGS_ERROR)
        assert _command(gcs, mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_CAMERA_TRACKING_IMAGE_STATUS) == \
            mav.MAV_RESULT_ACCEPTED
        assert _receive(gcs, "CAMERA_TRACKING_IMAGE_STATUS", timeout=1).tracking_status == \
            mav.CAMERA_TRACKING_STATUS_FLAGS_ERROR
        assert component.state == "failed"
        assert _command(gcs, mav.MAV_CMD_CAMERA_STOP_TRACKING) == mav.MAV_RESULT_ACCEPTED
        assert _receive(gcs, "CAMERA_TRACKING_IMAGE_STATUS",
                        where=lambda m: m.tracking_status == mav.CAMERA_TRACKING_STATUS_FLAGS_IDLE)
        assert component.state == "idle"
        assert client.status(SID).image_key == elsewhere, "clearing the failure stops nothing of theirs"
    finally:
        client.stop(SID)
    camera.hold.clear()


def test_the_box_follows_the_target_after_the_camera_restarts():
    """A restarted camera counts seq from 0 again: its boxes are the session's, not ones from before the drag."""
    from tacf_clients.demo import HoldingPublisher
    from tacf_clients.scene import SceneSource

    key = "test/mavlink/restarting"
    with service_and_camera(SCENE, key, "mavr") as (service, session, camera):
        camera.publisher.next_seq = 100_000               # a camera that has been up a while
        port = free_port()
        gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=GCS_SYSTEM,
                                         source_component=GCS_COMPONENT, dialect="common")
        stop = threading.Event()
        with MavlinkCamera(f"udpout:127.0.0.1:{port}", key, options=service.options) as component:
            loop = threading.Thread(target=component.serve, args=(stop,))
            loop.start()
            restarted = None
            try:
                assert _receive(gcs, "HEARTBEAT") is not None
                deadline = time.monotonic() + 10
                while time.monotonic() < deadline and (component._frame_header() is None or
                                                       component._frame_header().seq < 100_000):
                    time.sleep(0.1)
                target = SCENE.box(0)                     # the held camera shows the first frame
                assert _command(gcs, mav.MAV_CMD_CAMERA_TRACK_RECTANGLE, *_normalised_corners(target)) == \
                    mav.MAV_RESULT_ACCEPTED
                assert _receive(gcs, "CAMERA_TRACKING_IMAGE_STATUS",
                                where=lambda m: m.target_data and box_iou(_status_box(m), target) > 0.5), \
                    "the box is shown"
                camera.close()
                restarted = HoldingPublisher(session, SceneSource(SCENE), key, 20, "jpeg")
                restarted.hold.clear()                    # from seq 0, the target moving
                restarted.start()
                moved = _receive(gcs, "CAMERA_TRACKING_IMAGE_STATUS", timeout=20,
                                 where=lambda m: m.target_data and box_iou(_status_box(m), target) < 0.3)
                assert moved is not None, "the box follows the target on the restarted camera's frames"
                assert restarted.last_seq < 100_000
            finally:
                stop.set()
                loop.join(timeout=10)
                gcs.close()
                if restarted is not None:
                    restarted.close()
        listed = TrackingClient(session=session, node=service.node).list()
        assert component.sid not in {info.sid for info in listed}, "closing the component stopped its session"


def test_a_killed_service_turns_the_status_to_error_and_a_restored_one_back_to_active(tmp_path):
    """The component used to go on sending ACTIVE with the last box for ever after the service died: a session
    check that got no answer counted as running. Now the box goes within STALE_BOX_S, the status says ERROR once
    the checks go unanswered, and a service restarted with --state brings the session (and ACTIVE) back."""
    from tacf_clients.mavlink import STALE_BOX_S

    key, sid = "test/mavlink/dying", "mavlink-dying"
    with _own_service(key, "--state", str(tmp_path / "sessions.json")) as (service, session, gcs, port):
        # The component's 2 s timeout (its session checks must go unanswered soon after the kill) is shorter than a
        # first start can take on a loaded box, while the fork server that makes the workers starts: warm it first.
        warm_up = TrackingClient(session=session, node=service.node, timeout=30.0)
        warm_up.start(key, SCENE.box(0), sid="warm-up")
        warm_up.stop("warm-up")
        with MavlinkCamera(f"udpout:127.0.0.1:{port}", key, options=service.options, sid=sid,
                           timeout=2.0) as component, serving(component):
            assert _receive(gcs, "HEARTBEAT") is not None
            assert wait_until(lambda: component._frame_header() is not None, 10)
            assert _command(gcs, mav.MAV_CMD_CAMERA_TRACK_RECTANGLE, *_normalised_corners(SCENE.box(0))) == \
                mav.MAV_RESULT_ACCEPTED
            assert _receive(gcs, "CAMERA_TRACKING_IMAGE_STATUS", where=lambda m: m.target_data), "the box is shown"

            service.process.kill()
            service.process.wait(timeout=10)
            killed = time.monotonic()
            boxless = _receive(gcs, "CAMERA_TRACKING_IMAGE_STATUS", timeout=5, where=lambda m: not m.target_data)
            assert boxless is not None and time.monotonic() - killed < STALE_BOX_S + 1.5, "the box is gone"
            error = _receive(gcs, "CAMERA_TRACKING_IMAGE_STATUS", timeout=15, where=lambda m:
                             m.tracking_status & mav.CAMERA_TRACKING_STATUS_FLAGS_ERROR)
            assert error is not None, "a dead service is an error, not an active track"
            assert not error.tracking_status & mav.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE
            assert _receive(gcs, "CAMERA_TRACKING_IMAGE_STATUS", timeout=2, where=lambda m:
                            not m.tracking_status & mav.CAMERA_TRACKING_STATUS_FLAGS_ERROR) is None, "and stays one"
            assert component.tracking, "the session is still ours: a stop will stop it once the service is back"

            service.start()                          # same port, same state file: the session comes back
            active = _receive(gcs, "CAMERA_TRACKING_IMAGE_STATUS", timeout=30, where=lambda m: m.target_data and
                              m.tracking_status & mav.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE)
            assert active is not None, "the restored session's box is shown as ACTIVE again"
            assert _command(gcs, mav.MAV_CMD_CAMERA_STOP_TRACKING) == mav.MAV_RESULT_ACCEPTED
            client = TrackingClient(session=session, node=service.node)
            assert wait_until(lambda: all(info.sid != sid for info in client.list()), 10), "and stopped there"


def test_a_session_whose_worker_the_service_restarts_is_active_again(monkeypatch):
    """A worker that dies is reported failed and restarted by the service. A session check that saw it failed
    latched the component on ERROR: it checked no more, and the ground station never saw the box again while the
    restarted worker tracked on. The service here waits 6 s before the restart, so a check (every 2 s) sees it."""
    import signal

    import zenoh

    from tacf_clients.demo import HoldingPublisher
    from tacf_clients.scene import SceneSource
    from tacf_service import manager
    from tacf_service.app import ServiceOptions, TrackingService
    from tacf_service.config import ZenohOptions
    from tacf_service.loopback import peer_config

    monkeypatch.setattr(manager, "RESTART_BACKOFF_S", (6.0,))
    key, sid, port = "test/mavlink/crashing", "mavlink-crashing", free_port()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    service = TrackingService(ServiceOptions(node=f"mav{free_port()}", zenoh=ZenohOptions(listen=(endpoint,)),
                                             spare_workers=0)).open()
    gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=GCS_SYSTEM,
                                     source_component=GCS_COMPONENT, dialect="common")
    try:
        with zenoh.open(peer_config(connect=[endpoint])) as session:
            camera = HoldingPublisher(session, SceneSource(SCENE), key, 20, "jpeg")
            camera.start()
            try:
                with MavlinkCamera(f"udpout:127.0.0.1:{port}", key, session=session, sid=sid,
                                   node=service.node) as component, serving(component):
                    assert _receive(gcs, "HEARTBEAT") is not None
                    target = _held_target(camera, component)
                    assert _command(gcs, mav.MAV_CMD_CAMERA_TRACK_RECTANGLE, *_normalised_corners(target)) == \
                        mav.MAV_RESULT_ACCEPTED
                    camera.hold.clear()
                    assert _receive(gcs, "CAMERA_TRACKING_IMAGE_STATUS", timeout=20,
                                    where=lambda m: m.target_data) is not None, "the box is shown"

                    os.kill(service.manager.worker_pids()[sid], signal.SIGKILL)
                    error = _receive(gcs, "CAMERA_TRACKING_IMAGE_STATUS", timeout=15, where=lambda m:
                                     m.tracking_status & mav.CAMERA_TRACKING_STATUS_FLAGS_ERROR)
                    assert error is not None, "the failed worker is an error while the service restarts it"
                    active = _receive(gcs, "CAMERA_TRACKING_IMAGE_STATUS", timeout=40, where=lambda m:
                                      m.target_data and m.tracking_status & mav.CAMERA_TRACKING_STATUS_FLAGS_ACTIVE)
                    assert active is not None, "the restarted worker's box is shown as ACTIVE again"
                    assert _command(gcs, mav.MAV_CMD_CAMERA_STOP_TRACKING) == mav.MAV_RESULT_ACCEPTED
                    assert sid not in service.manager.worker_pids()
            finally:
                camera.close()
    finally:
        gcs.close()
        service.close()


@contextmanager
def _component_on_a_quiet_camera(key: str, sid: str, init_wait: float):
    """A service waiting up to `init_wait` s for the frame a start names, a ground station, and the component serving
    them on `key`, which has had one frame and then is quiet: yields (session, service, gcs, component)."""
    import zenoh

    from tacf_clients.zconfig import make_config
    from tacf_schemas.codec import encode
    from tacf_schemas.images import encode_frame

    with LocalService(node=f"mavq{free_port()}", extra_args=("--init-wait", str(init_wait))) as service, \
            zenoh.open(make_config(service.options)) as session:
        service.wait_ready(session)
        port = free_port()
        gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=GCS_SYSTEM,
                                         source_component=GCS_COMPONENT, dialect="common")
        try:
            with MavlinkCamera(f"udpout:127.0.0.1:{port}", key, session=session, sid=sid) as component, \
                    serving(component):
                assert _receive(gcs, "HEARTBEAT") is not None
                session.put(key, encode(encode_frame(SCENE.frame(0), 7)))
                assert wait_until(lambda: component._frame_header() is not None, 10)
                yield session, service, gcs, component
        finally:
            gcs.close()


def test_a_slow_start_is_answered_in_progress_while_the_loop_goes_on_and_a_retransmission_runs_once():
    """The service waits up to --init-wait for the frame a start names; a start on a camera gone quiet takes that
    long. It blocked the loop (no heartbeat, no answer to anything, the ground station retransmitting): now it
    is answered IN_PROGRESS at once, the loop answers meanwhile, and the same command sent again is answered
    IN_PROGRESS, not queued a second time."""
    with _component_on_a_quiet_camera("test/mavlink/quiet", "mavlink-quiet", init_wait=4) as (_, _, gcs, component):
        rectangle = [*_normalised_corners(SCENE.box(0)), 0.0, 0.0, 0.0]
        sent = time.monotonic()

        def track_ack(timeout):
            return _receive(gcs, "COMMAND_ACK", timeout,
                            where=lambda m: m.command == mav.MAV_CMD_CAMERA_TRACK_RECTANGLE)

        gcs.mav.command_long_send(1, mav.MAV_COMP_ID_CAMERA, mav.MAV_CMD_CAMERA_TRACK_RECTANGLE, 0, *rectangle)
        first = track_ack(1.0)
        assert first is not None and first.result == mav.MAV_RESULT_IN_PROGRESS and first.progress == 255
        gcs.mav.command_long_send(1, mav.MAV_COMP_ID_CAMERA, mav.MAV_CMD_CAMERA_TRACK_RECTANGLE, 1, *rectangle)
        assert track_ack(1.0).result == mav.MAV_RESULT_IN_PROGRESS, "the retransmission"
        assert _command(gcs, mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_CAMERA_INFORMATION,
                        timeout=1.0) == mav.MAV_RESULT_ACCEPTED, "other commands are answered meanwhile"
        assert _receive(gcs, "HEARTBEAT", timeout=1.5) is not None, "and the heartbeat goes on"
        final = _receive(gcs, "COMMAND_ACK", 20, where=lambda m: m.command ==
                         mav.MAV_CMD_CAMERA_TRACK_RECTANGLE and m.result != mav.MAV_RESULT_IN_PROGRESS)
        assert final is not None and final.result == mav.MAV_RESULT_ACCEPTED
        assert time.monotonic() - sent > 3, "the start did wait for the frame"
        assert _receive(gcs, "COMMAND_ACK", 3, where=lambda m: m.command ==
                        mav.MAV_CMD_CAMERA_TRACK_RECTANGLE) is None, "one start, one final answer"
        assert component.tracking


def test_a_stop_sent_while_a_start_is_in_progress_stops_what_the_start_started():
    """An operator who stops while the start is still in progress (a camera gone quiet) stops the session: the stop
    runs after the start, as the commands came."""
    sid = "mavlink-quiet-stop"
    with _component_on_a_quiet_camera("test/mavlink/quiet-stop", sid, init_wait=3) as quiet:
        session, service, gcs, component = quiet
        gcs.mav.command_long_send(1, mav.MAV_COMP_ID_CAMERA, mav.MAV_CMD_CAMERA_TRACK_RECTANGLE, 0,
                                  *_normalised_corners(SCENE.box(0)), 0.0, 0.0, 0.0)
        assert _receive(gcs, "COMMAND_ACK", 1.0, where=lambda m: m.result == mav.MAV_RESULT_IN_PROGRESS)
        assert _command(gcs, mav.MAV_CMD_CAMERA_STOP_TRACKING) == mav.MAV_RESULT_ACCEPTED
        assert wait_until(lambda: not component._pending, 20), "the start is done"
        assert not component.tracking
        assert sid not in {info.sid for info in TrackingClient(session=session, node=service.node).list()}


def test_no_frame_yet_is_a_temporary_refusal():
    """Before any frame arrives on the key, the rectangle cannot be placed: TEMPORARILY_REJECTED, not a crash."""
    with LocalService(node=f"mav{free_port()}") as service:
        port = free_port()
        gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=GCS_SYSTEM,
                                         source_component=GCS_COMPONENT, dialect="common")
        stop = threading.Event()
        with MavlinkCamera(f"udpout:127.0.0.1:{port}", "test/mavlink/silent", options=service.options) as component:
            loop = threading.Thread(target=component.serve, args=(stop,))
            loop.start()
            try:
                assert _receive(gcs, "HEARTBEAT") is not None
                assert _command(gcs, mav.MAV_CMD_CAMERA_TRACK_RECTANGLE, 0.1, 0.1, 0.3, 0.3) == \
                    mav.MAV_RESULT_TEMPORARILY_REJECTED
            finally:
                stop.set()
                loop.join(timeout=10)
                gcs.close()


def _tcp_ground_station(port: int):
    """A ground station listening on TCP `port` for the component to connect to."""
    return mavutil.mavlink_connection(f"tcpin:127.0.0.1:{port}", source_system=GCS_SYSTEM,
                                      source_component=GCS_COMPONENT, dialect="common")


def test_a_tcp_ground_station_that_goes_away_and_comes_back_is_served_again():
    """Over TCP the component connects to the ground station. When that goes away for longer than pymavlink's
    reconnection tries (3 s), the component tries on rather than dying, and answers the ground station once it is
    back; closing it then works too."""
    port = free_port()
    gcs = _tcp_ground_station(port)
    with MavlinkCamera(f"tcp:127.0.0.1:{port}", "test/mavlink/tcp", options=no_service_options()) as component, \
            serving(component) as loop:
        assert _receive(gcs, "HEARTBEAT") is not None
        gcs.close()
        time.sleep(5.0)
        assert loop.is_alive(), "the component lives on"
        gcs = _tcp_ground_station(port)
        assert _receive(gcs, "HEARTBEAT", timeout=15) is not None, "announces itself again"
        assert _command(gcs, mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_CAMERA_INFORMATION) == \
            mav.MAV_RESULT_ACCEPTED
        gcs.close()
        time.sleep(5.0)                                 # gone again: its link has no socket as it closes
        assert loop.is_alive(), "the component lives on through a heartbeat sent to a ground station gone"


def test_a_tcp_ground_station_away_for_long_is_logged_once_down_and_once_up_again(caplog, capsys):
    """A ground station switched off for hours: the component wrote 1.5 lines a second, pymavlink's prints of each
    reconnection attempt on stdout and a warning of ours every few seconds. Now a warning when the link goes down,
    a line when it is up again, and nothing in between."""
    port = free_port()
    caplog.set_level("INFO", logger="tacf_clients.mavlink")
    gcs = _tcp_ground_station(port)
    try:
        with MavlinkCamera(f"tcp:127.0.0.1:{port}", "test/mavlink/tcp-away",
                           options=no_service_options()) as component, serving(component):
            assert _receive(gcs, "HEARTBEAT") is not None
            capsys.readouterr()
            gcs.close()
            time.sleep(9.0)
            gcs = _tcp_ground_station(port)
            assert _receive(gcs, "HEARTBEAT", timeout=15) is not None, "announces itself again"
            assert _receive(gcs, "HEARTBEAT", timeout=5) is not None
    finally:
        gcs.close()
    assert capsys.readouterr().out.splitlines() == []
    link_lines = [r.getMessage() for r in caplog.records if "MAVLink link" in r.getMessage()]
    assert len(link_lines) == 2, link_lines
    assert "is down" in link_lines[0] and link_lines[1].endswith("is up again")


def test_a_component_listening_on_tcp_lets_go_of_its_port_when_closed():
    """With --link tcpin:HOST:PORT the component listens for the ground station. close() left the listening socket
    open (pymavlink's close() of that link closes only the connection), so a component opened on the port again in
    the same process was refused with 'Address already in use', whether a ground station had come or not."""
    port = free_port()
    for ground_station_comes in (False, True, False):
        component = MavlinkCamera(f"tcpin:127.0.0.1:{port}", "test/mavlink/tcpin", options=no_service_options())
        try:
            if ground_station_comes:
                with serving(component):
                    gcs = mavutil.mavlink_connection(f"tcp:127.0.0.1:{port}", source_system=GCS_SYSTEM,
                                                     source_component=GCS_COMPONENT, dialect="common")
                    assert _receive(gcs, "HEARTBEAT") is not None
                    gcs.close()
        finally:
            component.close()


def test_closing_while_the_service_hangs_ends_without_an_error(caplog):
    """Ctrl-C with the service hung (stopped here) took 17 s and ended in an uncaught zenoh.ZError: a stop that
    waited out its timeout, then a session close that Zenoh gave up on. The stop is skipped when the service did
    not answer, and a close that times out is a warning."""
    import signal

    key, sid = "test/mavlink/hung", "mavlink-hung"
    with _own_service(key) as (service, session, gcs, port):
        component = MavlinkCamera(f"udpout:127.0.0.1:{port}", key, options=service.options, sid=sid, timeout=5.0)
        try:
            with serving(component):
                assert _receive(gcs, "HEARTBEAT") is not None
                assert wait_until(lambda: component._frame_header() is not None, 10)
                assert _command(gcs, mav.MAV_CMD_CAMERA_TRACK_RECTANGLE, *_normalised_corners(SCENE.box(0))) == \
                    mav.MAV_RESULT_ACCEPTED
                os.kill(service.process.pid, signal.SIGSTOP)
                assert wait_until(lambda: component._unanswered_checks >= 1, 15)
            started = time.monotonic()
            component.close()                    # raised zenoh.ZError
            took = time.monotonic() - started
        finally:
            os.kill(service.process.pid, signal.SIGCONT)
    assert took < 5.0 + 11.0, took               # the running check's timeout, and Zenoh's 10 s at most
    assert f"{sid} is left to it" in caplog.text


def test_an_image_key_too_long_for_an_id_still_gets_its_own_session_id():
    """The default sid, mavlink-<key>, was refused for keys over 56 characters, with an error that did not say that
    --sid would do."""
    from tacf_clients.mavlink import default_sid
    from tacf_schemas.keys import validate_id

    assert default_sid("uav1/camera/front") == "mavlink-uav1-camera-front"
    long_keys = ["fleet/" + "x" * 100 + "/front", "fleet/" + "x" * 100 + "/rear"]
    sids = [validate_id(default_sid(key)) for key in long_keys]
    assert len(set(sids)) == 2 and all(len(sid) == 64 for sid in sids)


def test_image_keys_that_read_alike_get_session_ids_of_their_own():
    """Keys that differ in punctuation only all got mavlink-uav1-cam-front: two bridges then shared one session."""
    from tacf_clients.mavlink import default_sid
    from tacf_schemas.keys import validate_id

    alike = ["uav1/cam/front", "uav1/cam-front", "uav1.cam.front", "uav1/cam:front", "uav1/cam/front-"]
    assert len({validate_id(default_sid(key)) for key in alike}) == len(alike)


def test_tacf_mavlink_command_announces_itself_until_sigterm():
    import signal
    import subprocess
    import sys

    port = free_port()
    gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=GCS_SYSTEM,
                                     source_component=GCS_COMPONENT, dialect="common")
    try:
        with tacf_command("mavlink", "--key", KEY, "--link", f"udpout:127.0.0.1:{port}", "--component", "101",
                          "--connect", f"tcp/127.0.0.1:{free_port()}") as process:
            assert "camera component 1/101 for test/mavlink/cam" in process.stdout.readline()
            heartbeat = _receive(gcs, "HEARTBEAT", timeout=30)
            assert heartbeat is not None and heartbeat.get_srcComponent() == 101
            assert _command(gcs, mav.MAV_CMD_CAMERA_STOP_TRACKING, component=101) == mav.MAV_RESULT_ACCEPTED
            process.send_signal(signal.SIGTERM)
            assert process.wait(timeout=15) == 0
    finally:
        gcs.close()
    done = subprocess.run([sys.executable, "-m", "tacf.cli", "mavlink", "--key", KEY, "--link", "udpout:x:1",
                           "--component", "0"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "--component: '0': expected a MAVLink id 1-255" in done.stderr, done.stderr


@pytest.mark.parametrize("args, says", [
    (("--link", "udpout:no-such-host.invalid:14550"), "cannot resolve host 'no-such-host.invalid'"),
    (("--link", "tcp:no-such-host.invalid:5760"), "cannot resolve host 'no-such-host.invalid'"),
    (("--link", "udpout:127.0.0.1:99999"), "a port of 1 to 65535"),
    (("--link", "udpout:127.0.0.1:65536"), "a port of 1 to 65535"),
    (("--link", "udpout:127.0.0.1:14550", "--sid", ""), "invalid session id ''"),
])
def test_a_bad_endpoint_or_sid_is_a_one_line_error(args, says):
    """An unresolvable udpout host ran for ever sending nothing (pymavlink swallows the error), a port over 65535
    ended in a traceback from the loop, and --sid '' took the default sid."""
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-m", "tacf.cli", "mavlink", "--key", KEY, *args,
                           "--connect", f"tcp/127.0.0.1:{free_port()}"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    assert done.stderr.startswith("tacf mavlink: ") and says in done.stderr, done.stderr


def test_pymavlinks_unix_socket_and_multicast_links_are_taken(tmp_path):
    """--link takes pymavlink's other connections too: they were read as UDP HOST:PORT and refused ("cannot resolve
    host 'mcast:239.255.145.50'"). A ground station (or router) on a Unix socket is served like any other."""
    import socket

    from tacf_clients.mavlink import check_link

    for link in ("mcast:", "mcast:239.255.145.50:14550", "uds:/run/gcs.sock"):
        check_link(link)
    path = str(tmp_path / "gcs.sock")
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as listener:
        listener.bind(path)
        listener.listen(1)
        with MavlinkCamera(f"unix:{path}", KEY, options=no_service_options()) as component, serving(component):
            ground, _ = listener.accept()
            with ground:
                ground.settimeout(10)
                parser = mav.MAVLink(None)
                messages = []
                while not any(m.get_type() == "HEARTBEAT" for m in messages):
                    messages += parser.parse_buffer(ground.recv(1024)) or []
                heartbeat = next(m for m in messages if m.get_type() == "HEARTBEAT")
                assert heartbeat.type == mav.MAV_TYPE_CAMERA


def test_a_serial_link_works_and_a_missing_device_is_a_one_line_error():
    """--link takes a serial device (a radio modem): here a pseudo-terminal, the ground station on its other end.
    pymavlink opens serial devices with pyserial, which the [mavlink] extra must bring (without it: a traceback
    ending in "No module named 'serial'", for a real device as for a mistyped --link)."""
    import pty
    import subprocess
    import sys

    ground, device = pty.openpty()
    try:
        with tacf_command("mavlink", "--key", KEY, "--link", os.ttyname(device), "--baud", "115200",
                          "--connect", f"tcp/127.0.0.1:{free_port()}") as process:
            assert "camera component 1/100" in process.stdout.readline()
            parser = mav.MAVLink(None)
            deadline, heartbeat = time.monotonic() + 30, None
            while heartbeat is None and time.monotonic() < deadline:
                for message in parser.parse_buffer(os.read(ground, 1024)) or []:
                    if message.get_type() == "HEARTBEAT" and message.get_srcComponent() == mav.MAV_COMP_ID_CAMERA:
                        heartbeat = message
            assert heartbeat is not None and heartbeat.type == mav.MAV_TYPE_CAMERA
    finally:
        os.close(ground)
        os.close(device)
    done = subprocess.run([sys.executable, "-m", "tacf.cli", "mavlink", "--key", KEY, "--link", "/dev/ttyNOPE",
                           "--connect", f"tcp/127.0.0.1:{free_port()}"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    assert done.stderr.startswith("tacf mavlink: ") and "/dev/ttyNOPE" in done.stderr, done.stderr


def test_with_signing_only_signed_commands_are_answered():
    """MAVLink 2 signing: the component signs what it sends and answers only commands signed with its key."""
    key = signing_key_from_passphrase("correct horse battery staple")
    assert len(key) == 32 and key != signing_key_from_passphrase("correct horse battery stable")
    port = free_port()
    gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=GCS_SYSTEM,
                                     source_component=GCS_COMPONENT, dialect="common")
    stop = threading.Event()
    with MavlinkCamera(f"udpout:127.0.0.1:{port}", KEY, options=no_service_options(), signing_key=key) as component:
        loop = threading.Thread(target=component.serve, args=(stop,))
        loop.start()
        try:
            assert _receive(gcs, "HEARTBEAT") is not None      # a ground station without a key reads it
            assert _command(gcs, mav.MAV_CMD_CAMERA_STOP_TRACKING, timeout=1.5) is None, "unsigned: ignored"
            gcs.setup_signing(signing_key_from_passphrase("wrong passphrase"), sign_outgoing=True)
            assert _command(gcs, mav.MAV_CMD_CAMERA_STOP_TRACKING, timeout=1.5) is None, "wrong key: ignored"
            gcs.setup_signing(key, sign_outgoing=True)
            heartbeat = _receive(gcs, "HEARTBEAT")
            assert heartbeat is not None and heartbeat.get_signed(), "signed with the key"
            assert _command(gcs, mav.MAV_CMD_CAMERA_STOP_TRACKING) == mav.MAV_RESULT_ACCEPTED
        finally:
            stop.set()
            loop.join(timeout=10)
            gcs.close()
    with pytest.raises(ValueError, match="empty"):
        signing_key_from_passphrase("")
