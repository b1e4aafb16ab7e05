"""Fuzzing with hypothesis: every wire decoder, the frame decoder and every control op, with random bytes,
random msgpack values and mutated valid payloads (bytes flipped, inserted, deleted; fields retyped, deleted or
added; huge numbers, NaN/inf, negative sizes, huge strings, wrong versions), and hostile frames into a running
session. test_schemas.py and test_service.py hold the hand-written cases and plain random inputs; this file adds
the mutations of valid messages and checks that the service keeps serving after each onslaught.

Properties: a decoder returns a valid message (that survives a re-encode) or raises its typed error, nothing
else; the service answers every control query with a reply model or an Error that is not "internal" (a bug); a
worker survives any frame (same process, no restart) and still tracks good frames afterwards.
"""
from __future__ import annotations

import copy
import math
import time

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from tacf_clients.local_service import free_port  # noqa: E402
from tacf_schemas import (CONTROL_OPS, CONTROL_REPLIES, ERROR_CODES, MODELS, BoxResult, DecodeError, Error, Frame,
                          Health, ListRequest, ReinitRequest, SessionInfo, SessionList, StartRequest, StatusRequest,
                          StopRequest, decode, encode)
from tacf_schemas.images import FrameError, decode_frame, encode_frame
from tacf_schemas.limits import MAX_PAYLOAD_BYTES

FUZZ = settings(deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))

# ---------------------------------------------------------------------------------------------- strategies

#: msgpack headers that announce far more data than follows (str32, bin32, array32, map32, ext32), a timestamp
#: ext, uint64 max and a NaN double: spliced into valid payloads.
_HEADERS = [b"\xdb\xff\xff\xff\xff", b"\xc6\xff\xff\xff\xff", b"\xdd\xff\xff\xff\xff", b"\xdf\xff\xff\xff\xff",
            b"\xc9\xff\xff\xff\xff\x01", b"\xd7\xff" + bytes(8), b"\xcf" + b"\xff" * 8,
            b"\xcb\x7f\xf8" + bytes(6), b"\x91" * 2000]

HOSTILE_VALUES = st.one_of(
    st.sampled_from([None, True, False, 0, -1, 2, 99, 2**63 - 1, 2**63, 2**64 - 1, -2**63, math.nan, math.inf,
                     -math.inf, -0.0, 1e308, 5e-324, -1e308, "", "1", "x" * 100_000, "é/*#?$", b"", bytes(70_000),
                     [], {}, [[[[]]]], [1, 2, 3], [0, 0, -5, -5], [math.nan] * 4, {"v": 1}]),
    st.integers(-2**63, 2**64 - 1), st.floats(), st.text(max_size=16), st.binary(max_size=16),
    st.lists(st.floats(), max_size=6))

MSGPACK_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-2**63, 2**64 - 1) | st.floats() | st.text(max_size=12)
    | st.binary(max_size=12),
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=10), inner, max_size=5),
    max_leaves=12)


@st.composite
def byte_mutations(draw, payload: bytes) -> bytes:
    """1-4 byte-level edits of a payload: bit flip, insertion, deletion, truncation, or a lying msgpack header."""
    data = bytearray(payload)
    for _ in range(draw(st.integers(1, 4))):
        pos = draw(st.integers(0, len(data)))
        kind = draw(st.sampled_from(["flip", "insert", "delete", "truncate", "header"]))
        if kind == "flip" and pos < len(data):
            data[pos] ^= 1 << draw(st.integers(0, 7))
        elif kind == "insert":
            data[pos:pos] = draw(st.binary(min_size=1, max_size=8))
        elif kind == "delete":
            del data[pos:pos + draw(st.integers(1, 8))]
        elif kind == "truncate":
            del data[pos:]
        elif kind == "header":
            data[pos:pos] = draw(st.sampled_from(_HEADERS))
    return bytes(data)


def _containers(value, path=()):
    """The path of every map and array inside a decoded msgpack value, the root first."""
    if isinstance(value, (dict, list)):
        yield path
        for key, item in (value.items() if isinstance(value, dict) else enumerate(value)):
            yield from _containers(item, path + (key,))


@st.composite
def field_mutations(draw, payload: bytes) -> bytes:
    """A valid payload with one field (at any depth) given a hostile value, deleted, or added."""
    value = copy.deepcopy(msgpack.unpackb(payload))
    path = draw(st.sampled_from(list(_containers(value))))
    container = value
    for key in path:
        container = container[key]
    keys = list(container) if isinstance(container, dict) else list(range(len(container)))
    key = draw(st.sampled_from(keys + ["bogus" if isinstance(container, dict) else len(container)]))
    if draw(st.booleans()) and key in keys:
        del container[key]
    elif isinstance(container, list) and key == len(container):
        container.append(draw(HOSTILE_VALUES))
    else:
        container[key] = draw(HOSTILE_VALUES)
    return msgpack.packb(value, use_bin_type=True)


def mutations(payload: bytes) -> st.SearchStrategy[bytes]:
    return byte_mutations(payload) | field_mutations(payload)


# ---------------------------------------------------------------------------------------------- samples

_IMAGE = np.random.default_rng(1).integers(0, 255, (16, 24, 3), dtype=np.uint8)
FRAMES = {"jpeg": encode_frame(_IMAGE, 7, "jpeg"), "png": encode_frame(_IMAGE, 7, "png"),
          "bgr8": encode_frame(_IMAGE, 7, "bgr8"), "mono8": encode_frame(_IMAGE[:, :, 1].copy(), 7, "mono8")}

_HEALTH = Health(node="n1", sid="s1", state="tracking", stamp_ns=5, fps=9.5, processing_ms_mean=4.0,
                 processing_ms_p95=6.0, frame_age_ms=12.0, frames_received=10, frames_processed=9, pme=12.5,
                 last_seq=9, message="ok")
_INFO = SessionInfo(node="n1", sid="s1", image_key="uav1/cam", profile="kcc", overrides={"learning_rate": 0.02},
                    state="tracking", box=(1.0, 2.0, 3.0, 4.0), init_seq=3, last_seq=9, created_ns=1, health=_HEALTH)
#: One valid message of every wire model, with every optional field set so that mutations reach it.
SAMPLES = {
    "Frame": FRAMES["png"],
    "StartRequest": StartRequest(image_key="uav1/cam", box=(1, 2, 3, 4), seq=7, sid="fuzz-sid", profile="kcc",
                                 overrides={"learning_rate": 0.02, "fast_fft": True, "cell_size": 4},
                                 frames=[FRAMES["jpeg"], FRAMES["png"].model_copy(update={"seq": 8})]),
    "StopRequest": StopRequest(sid="fuzz-sid"),
    "ReinitRequest": ReinitRequest(sid="fuzz-sid", box=(1, 2, 3, 4), seq=7, frames=[FRAMES["bgr8"]]),
    "ListRequest": ListRequest(),
    "StatusRequest": StatusRequest(sid="fuzz-sid"),
    "BoxResult": BoxResult(node="n1", sid="s1", seq=3, stamp_ns=4, box=(1.5, 2.5, 3.5, 4.5), width=640, height=360,
                           ok=True, pme=20.0, score=0.5, scale=1.0, processing_ms=3.2, published_ns=9),
    "Health": _HEALTH,
    "SessionInfo": _INFO,
    "SessionList": SessionList(node="n1", max_sessions=4, sessions=[_INFO]),
    "Error": Error(code="unknown_session", message="no session 'x'", node="n1"),
}
PAYLOADS = {name: encode(model) for name, model in SAMPLES.items()}


def test_samples_cover_every_model():
    assert set(SAMPLES) == set(MODELS)


# ---------------------------------------------------------------------------------------------- decoders

def check_decode(payload: bytes, model) -> None:
    """decode returns a valid `model` that survives a re-encode, or raises a typed DecodeError."""
    try:
        message = decode(payload, model)
    except DecodeError as exc:
        assert exc.code in ("too_large", "malformed", "invalid") and len(exc.message) < 2000
        return
    assert type(message) is model
    assert encode(decode(encode(message), model)) == encode(message)


@settings(FUZZ, max_examples=300)
@given(st.sampled_from(sorted(MODELS)).flatmap(lambda name: st.tuples(st.just(name), mutations(PAYLOADS[name]))))
@example(("Frame", b"\x91" * 100_000 + b"\xc0"))                        # deep nesting
@example(("SessionList", b"\x81\xa8sessions" + b"\x91" * 5000 + b"\x80"))
@example(("StartRequest", b"\x00" * (MAX_PAYLOAD_BYTES + 1)))
@example(("Health", msgpack.packb({**msgpack.unpackb(PAYLOADS["Health"]), "frames_dropped": 1e300})))  # no uint64
def test_mutated_payloads_decode_or_raise_decode_error(case):
    name, payload = case
    check_decode(payload, MODELS[name])


@settings(FUZZ, max_examples=150)
@given(st.sampled_from(sorted(MODELS)), st.one_of(st.binary(max_size=96), MSGPACK_VALUES.map(msgpack.packb)))
def test_random_payloads_decode_or_raise_decode_error(name, payload):
    check_decode(payload, MODELS[name])


def _array_of_arrays(element: bytes, size: int) -> bytes:
    """msgpack of an array of arrays of 65535 `element`s each, about `size` bytes in all."""
    inner = b"\xdc\xff\xff" + element * 0xFFFF
    count = size // len(inner)
    return b"\xdc" + count.to_bytes(2, "big") + inner * count


@pytest.mark.parametrize("element", [b"\x90", b"\x80", b"\xa2ab", b"\xcd\x01\x00"],
                         ids=["empty arrays", "empty maps", "2-char strings", "uint16s"])
def test_a_payload_of_many_small_objects_is_refused_before_it_is_unpacked(element):
    """msgpack's length limits hold per array or map: 8 MiB of empty arrays, a byte each, unpacked to 566 MiB of
    Python objects, 70 times the payload (a control query or a frame may be 48 MiB; the service decodes queries in
    5 threads at once, and frames of a key in its history and in each worker on it)."""
    import tracemalloc
    payload = _array_of_arrays(element, 2 << 20)
    tracemalloc.start()
    try:
        with pytest.raises(DecodeError) as refused:
            decode(payload, StartRequest)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 16 << 20, f"{peak / 2**20:.0f} MiB to refuse a payload of {len(payload) / 2**20:.0f} MiB"
    assert refused.value.code == "too_large" and "msgpack objects" in refused.value.message


def test_each_key_and_value_of_a_small_map_counts_as_an_object():
    """Maps of 15 pairs, 31 objects each: 5,000 of them are over MAX_MSGPACK_OBJECTS (131,072), and refused as
    such; counted as one object a pair, they were not, and were unpacked (then refused as not a start)."""
    small_map = b"\x8f" + b"".join(b"\xa1" + bytes([ord("a") + i]) + b"\x00" for i in range(15))
    payload = b"\xdd" + (5000).to_bytes(4, "big") + small_map * 5000
    with pytest.raises(DecodeError) as refused:
        decode(payload, StartRequest)
    assert refused.value.code == "too_large" and "msgpack objects" in refused.value.message


def check_image(frame: Frame) -> None:
    """decode_frame returns the frame's pixels at its declared size, or raises a typed FrameError."""
    try:
        image = decode_frame(frame)
    except FrameError as exc:
        assert exc.code in ("unsupported_encoding", "too_large", "size_mismatch", "corrupt")
        return
    assert image.dtype == np.uint8 and image.shape[:2] == (frame.height, frame.width)
    assert image.ndim == 2 or image.shape[2] == 3


@settings(FUZZ, max_examples=300)
@given(st.sampled_from(sorted(FRAMES)).flatmap(lambda enc: byte_mutations(FRAMES[enc].data).map(
           lambda data: FRAMES[enc].model_copy(update={"data": data}))))
def test_mutated_image_data_decodes_or_raises_frame_error(frame):
    check_image(frame)


@settings(FUZZ, max_examples=150)
@given(st.sampled_from(sorted(FRAMES)), st.sampled_from(sorted(FRAMES)),
       st.integers(1, 64) | st.sampled_from([1, 8192]), st.integers(1, 64) | st.sampled_from([1, 8192]))
def test_lying_frame_headers_raise_frame_error(data_of, encoding, width, height):
    """The data of one encoding declared as another, at any size."""
    frame = FRAMES[data_of].model_copy(update={"encoding": encoding, "width": width, "height": height})
    check_image(frame)


@settings(FUZZ, max_examples=150)
@given(st.sampled_from(sorted(FRAMES)).flatmap(lambda enc: mutations(encode(FRAMES[enc]))))
def test_mutated_frames_through_the_wire_decoders(payload):
    try:
        frame = decode(payload, Frame)
    except DecodeError:
        return
    check_image(frame)


@pytest.mark.parametrize("image,ext", [
    (np.zeros((16, 24), np.uint16), ".png"),            # 16-bit
    (np.zeros((16, 24, 4), np.uint8), ".png"),          # BGRA
    (np.zeros((16, 24), np.uint8), ".png"),             # gray
    (np.zeros((16, 24), np.uint8), ".jpg"),             # gray
    (np.zeros((16, 24, 3), np.uint8), ".tiff"),         # not the declared format at all
])
def test_unusual_but_well_formed_images(image, ext):
    import cv2
    data = cv2.imencode(ext, image)[1].tobytes()
    for encoding in ("png", "jpeg"):
        check_image(Frame(seq=1, stamp_ns=1, encoding=encoding, width=24, height=16, data=data))


# ---------------------------------------------------------------------------------------------- the service

zenoh = pytest.importorskip("zenoh")

from tacf_service.app import ServiceOptions, TrackingService  # noqa: E402
from tacf_service.config import ZenohOptions  # noqa: E402
from tacf_service.loopback import (FramePublisher, SessionResults, peer_config,  # noqa: E402
                                   wait_until)
from tacf_service.probe import call  # noqa: E402
from tacf_service.scene import MovingTargetScene  # noqa: E402

NODE = "fuzz"
SCENE = MovingTargetScene(320, 240, target=48, speed=1.0)


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    # two sessions, both taken by `keeper` and `victim`: a fuzzed start that happens to be valid is then
    # refused (too_many_sessions) after its key and config were checked, instead of spawning a worker
    options = ServiceOptions(node=NODE, zenoh=ZenohOptions(listen=(endpoint,)), max_sessions=2, spare_workers=1,
                             init_wait_s=0.5)
    svc = TrackingService(options).open()
    client = zenoh.open(peer_config(connect=[endpoint]))
    yield svc, client
    client.close()
    svc.close()


def start(service, client, **fields):
    svc, _ = service
    assert wait_until(lambda: svc.manager.idle_spares() >= 1, 60), "no warm worker after 60 s"
    return call(client, NODE, "start", StartRequest(profile="kcc", **fields), timeout=10)


def status(client, sid: str) -> SessionInfo:
    return call(client, NODE, "status", StatusRequest(sid=sid))


@pytest.fixture(scope="module")
def keeper(service):
    """A session tracking a live feed, which every fuzz test must leave tracking."""
    _, client = service
    with FramePublisher(client, "fuzz/cam/live", SCENE, fps=10) as feed:
        assert wait_until(lambda: feed.seq >= 2, 10)
        start(service, client, image_key=feed.key, box=feed.truth[feed.seq], seq=feed.seq, sid="keeper")
        results = SessionResults(client, NODE, "keeper")
        yield results
        results.close()


@pytest.fixture(scope="module")
def victim(service):
    """A session on a key the test publishes to by hand (see HostileFeed), started before any frame with a
    box larger than any frame: accepted (nothing to check it against yet), then failed on the first frame."""
    _, client = service
    feed = HostileFeed(client, "fuzz/cam/hostile")
    start(service, client, image_key=feed.key, box=(0.0, 0.0, 1e9, 1e9), sid="victim")
    feed.results = SessionResults(client, NODE, "victim")
    yield feed
    feed.results.close()
    feed.publisher.undeclare()


class HostileFeed:
    """Good frames (with increasing seqs and fresh stamps) and anything else, on one key."""

    def __init__(self, client, key: str) -> None:
        self.key, self.client = key, client
        self.publisher = client.declare_publisher(key)
        self.seq = 0
        self.published = 0
        self.results: SessionResults | None = None

    def put(self, payload: bytes) -> None:
        self.publisher.put(payload)
        self.published += 1

    def good(self) -> int:
        """Publish the next good frame; its seq."""
        self.seq += 1
        self.put(encode(encode_frame(SCENE.frame(self.seq)[0], self.seq, "jpeg", stamp_ns=time.time_ns())))
        return self.seq

    def boxed(self, seq: int) -> bool:
        return any(r.seq == seq for r in self.results.results())


def ask(client, op: str, payload: bytes | None):
    """One query to tacf/<node>/control/<op>: exactly one answer, the op's reply model or an Error."""
    replies = list(client.get(f"tacf/{NODE}/control/{op}", payload=payload, timeout=10))
    assert len(replies) == 1, replies
    reply = replies[0]
    if reply.ok is not None:
        assert op in CONTROL_OPS
        return decode(reply.ok.payload.to_bytes(), CONTROL_REPLIES[op])
    error = decode(reply.err.payload.to_bytes(), Error)      # not a Zenoh timeout string
    assert error.code in ERROR_CODES and error.code != "internal", error
    return error


_REQUESTS = {"start": "StartRequest", "stop": "StopRequest", "reinit": "ReinitRequest", "list": "ListRequest",
             "status": "StatusRequest"}


@settings(FUZZ, max_examples=80)
@given(st.one_of(
    st.sampled_from(CONTROL_OPS).flatmap(lambda op: st.tuples(st.just(op), mutations(PAYLOADS[_REQUESTS[op]]))),
    st.tuples(st.sampled_from(CONTROL_OPS), st.binary(max_size=64) | MSGPACK_VALUES.map(msgpack.packb)),
    st.tuples(st.sampled_from(["explode", "START", "list2", "**", "st$*"]), st.just(PAYLOADS["ListRequest"]))))
@example(("start", b"\x00" * (MAX_PAYLOAD_BYTES + 1)))
@example(("start", msgpack.packb({"image_key": "x" * 100_000, "box": [1, 1, 5, 5]})))
@example(("start", msgpack.packb({"image_key": "fuzz/cam/live", "box": [1, 1, 5, 5],
                                  "overrides": {"cell_size": math.nan, "fixed_area": 1e308}})))
def test_control_ops_answer_every_query_and_keep_serving(service, keeper, victim, case):
    _, client = service
    op, payload = case
    answer = ask(client, op, payload)
    if op in ("stop", "reinit", "status") and not isinstance(answer, Error):
        assert answer.sid != "keeper"                # no mutation may reach the session under watch
    seen = len(keeper.results())
    assert wait_until(lambda: len(keeper.results()) > seen, 10), "the live session stopped producing boxes"


def test_keeper_survived_the_control_fuzz(service, keeper):
    _, client = service
    info = status(client, "keeper")
    assert info.state in ("tracking", "lost") and info.restarts == 0


def test_a_box_larger_than_the_frame_fails_the_session_not_the_worker(service, victim):
    """Before the fix the tracker raised IndexError / cv2.error (out of memory) on such a box, which killed the
    worker; the restarted worker died again on the same box until the crash limit."""
    svc, client = service
    pid = svc.manager.worker_pids()["victim"]
    victim.good()
    failed = wait_until(lambda: status(client, "victim").state == "failed", 20)
    assert failed, status(client, "victim")
    assert "larger than the" in status(client, "victim").health.message
    seq = victim.good()
    reinit = call(client, NODE, "reinit", ReinitRequest(sid="victim", box=SCENE.box(seq), seq=seq))
    assert reinit.state == "starting"
    assert wait_until(lambda: status(client, "victim").state == "tracking", 20)
    assert svc.manager.worker_pids()["victim"] == pid and status(client, "victim").restarts == 0


@pytest.mark.parametrize("box", [(0.0, 0.0, 1e9, 1e9), (-5000.0, -5000.0, 5100.0, 5100.0), (1e308, 1.0, 1e308, 1.0)])
def test_a_reinit_with_a_box_larger_than_the_frame_is_refused(service, victim, box):
    _, client = service
    victim.good()
    assert wait_until(lambda: victim.boxed(victim.seq) or status(client, "victim").state == "failed", 20)
    answer = ask(client, "reinit", encode(ReinitRequest(sid="victim", box=box)))
    assert isinstance(answer, Error) and answer.code == "invalid_box", answer


# mutations of a frame of the session's feed and of a frame of another size
_FRAME_MUTATIONS = (mutations(encode(encode_frame(SCENE.frame(0)[0], 0, "jpeg", stamp_ns=1)))
                    | mutations(PAYLOADS["Frame"]))


@settings(FUZZ, max_examples=6)
@given(st.lists(_FRAME_MUTATIONS | st.binary(max_size=64) | MSGPACK_VALUES.map(msgpack.packb), min_size=4,
                max_size=10))
@example([msgpack.packb({"seq": 2**64 - 1}), msgpack.packb({"seq": 2**63 - 1}), msgpack.packb({"seq": -1})] * 2)
def test_hostile_frames_into_a_running_session(service, victim, payloads):
    """Each batch of hostile frames is counted (rejected, or dropped when superseded), the worker survives it
    (same process, no restart), and the next good frame is tracked."""
    svc, client = service
    pid = _victim_tracking(svc, client, victim)
    seq = victim.good()                 # the counts before this batch: the Health after a good frame
    assert wait_until(lambda: victim.boxed(seq), 20), status(client, "victim")
    before = wait_until(lambda: _health_after(victim, seq), 5)
    for payload in payloads:
        victim.put(payload)
        time.sleep(0.03)
    seq = victim.good()
    assert wait_until(lambda: victim.boxed(seq), 20), status(client, "victim")
    assert svc.manager.worker_pids()["victim"] == pid
    health = wait_until(lambda: _health_after(victim, seq), 5)
    assert health is not None and health.restarts == 0
    # this batch's, not the session's so far, which were above 0 from the first batch on
    assert health.frames_rejected + health.frames_dropped > before.frames_rejected + before.frames_dropped
    assert health.frames_received < 2**32          # counters stay meaningful whatever seq a payload claims


def test_a_jpeg_of_many_scans_is_rejected_without_decoding_it(service, victim):
    """A progressive JPEG's scans each make the decoder go over the whole image: 2,000 copies of its last scan (33
    bytes each) in a 4096x4096 frame of 130 kB held the worker in cv2.imdecode until its watchdog killed it 15 s
    later, and the session restarted; sent again, it kept the session down."""
    import cv2
    svc, client = service
    pid = _victim_tracking(svc, client, victim)
    data = cv2.imencode(".jpg", np.zeros((4096, 4096), np.uint8), [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])[1].tobytes()
    last_scan = data[data.rindex(b"\xff\xda"):-2]
    data = data[:-2] + last_scan * 2000 + b"\xff\xd9"
    victim.put(encode(Frame(seq=victim.seq + 1, stamp_ns=time.time_ns(), encoding="jpeg", width=4096, height=4096,
                            data=data)))
    victim.seq += 1
    time.sleep(0.2)
    seq = victim.good()
    assert wait_until(lambda: victim.boxed(seq), 5), status(client, "victim")
    assert svc.manager.worker_pids()["victim"] == pid
    health = wait_until(lambda: _health_after(victim, seq), 5)
    assert health is not None and health.restarts == 0 and "2006 scans" in (health.message or "")


def _victim_tracking(svc, client, victim: HostileFeed) -> int:
    """The victim session's worker pid, once it tracks: re-initialised if an earlier batch left it failed."""
    if status(client, "victim").state not in ("tracking", "lost"):
        seq = victim.good()
        call(client, NODE, "reinit", ReinitRequest(sid="victim", box=SCENE.box(seq), seq=seq))
        assert wait_until(lambda: status(client, "victim").state == "tracking", 20)
    return svc.manager.worker_pids()["victim"]


def _health_after(feed: HostileFeed, seq: int):
    health = feed.results.last_health()
    return health if health is not None and health.last_seq is not None and health.last_seq >= seq else None
