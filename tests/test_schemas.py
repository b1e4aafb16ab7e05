"""Wire schemas: models, msgpack codec, key layout, frame decoding, JSON Schema drift."""
from __future__ import annotations

import json
import math
import subprocess
import sys

import cv2
import jsonschema
import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tacf_schemas import (ALL_LIVELINESS, CONTROL_OPS, MODELS, BoxResult, DecodeError, Error, Frame, Health,
                          InvalidIdError, InvalidKeyError, ListRequest, SessionInfo, SessionList, StartRequest,
                          StopRequest, box_key, control_key, decode, decode_error_reply, encode, health_key,
                          is_deadline_reply, parse_control_key, parse_liveliness_key, parse_session_key, sanitise_id,
                          service_liveliness_key, session_liveliness_key, validate_id, validate_image_key)
from tacf_schemas.export import JSON_DIR, drift, write
from tacf_schemas.images import FrameError, check_frame, decode_frame, encode_frame, jpeg_size, png_size
from tacf_schemas.limits import MAX_FRAME_PIXELS, MAX_PAYLOAD_BYTES
from wire_cases import BEYOND_SCHEMA, CASES


def test_json_schemas_match_models():
    assert drift() == [], "run `python -m tacf_schemas.export` to regenerate schemas/json"


def test_exporting_to_another_folder_keeps_its_own_files(tmp_path):
    """`python -m tacf_schemas.export --dir DIR` deleted every JSON file in DIR that was not a model's schema."""
    (tmp_path / "package.json").write_text('{"keep": true}')
    write(tmp_path)
    assert (tmp_path / "package.json").read_text() == '{"keep": true}'
    assert drift(tmp_path) == [] and (tmp_path / "Frame.json").is_file()


def test_models_import_light():
    code = "import sys, tacf_schemas; print(sorted(m for m in ('numpy', 'cv2', 'zenoh') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def _sample_models():
    health = Health(node="n1", sid="s1", state="tracking", stamp_ns=5, fps=9.5, processing_ms_mean=4.0,
                    processing_ms_p95=6.0, frame_age_ms=12.0, frames_received=10, frames_processed=9,
                    frames_dropped=1, pme=12.5, last_seq=9)
    info = SessionInfo(node="n1", sid="s1", image_key="uav1/cam", profile="authors", state="tracking",
                       box=(1.0, 2.0, 3.0, 4.0), created_ns=1, health=health)
    return [
        Frame(seq=1, stamp_ns=2, encoding="mono8", width=2, height=1, data=b"\x00\xff"),
        StartRequest(image_key="uav1/cam", box=(1, 2, 3, 4), seq=7, overrides={"learning_rate": 0.02}),
        StopRequest(sid="s1"), ListRequest(), health, info,
        SessionList(node="n1", max_sessions=4, sessions=[info]),
        BoxResult(node="n1", sid="s1", seq=3, stamp_ns=4, box=(1.5, 2.5, 3.5, 4.5), width=640, height=360,
                  ok=True, pme=20.0, score=0.5, scale=1.0, processing_ms=3.2, published_ns=9),
        Error(code="unknown_session", message="no session 'x'"),
    ]


@pytest.mark.parametrize("model", _sample_models(), ids=lambda m: type(m).__name__)
def test_roundtrip(model):
    payload = encode(model)
    assert isinstance(payload, bytes)
    assert decode(payload, type(model)) == model
    assert msgpack.unpackb(payload)["v"] == 1


def test_every_model_has_version_and_schema():
    for name, model in MODELS.items():
        assert "v" in model.model_fields, name
        assert model.model_json_schema()["properties"]["v"]["const"] == 1


def test_box_is_a_list_on_the_wire():
    raw = msgpack.unpackb(encode(StartRequest(image_key="a", box=(1, 2, 3, 4))))
    assert raw["box"] == [1.0, 2.0, 3.0, 4.0]


@pytest.mark.parametrize("payload", [
    b"", b"\xc1", b"\x93\x01\x02\x03", msgpack.packb("text"), msgpack.packb({"sid": 5}),
    msgpack.packb({"sid": "a/b"}), msgpack.packb({"sid": "ok", "extra": 1}), msgpack.packb({"v": 2, "sid": "a"}),
    msgpack.packb({1: 2}), b"\xdd\xff\xff\xff\xff",
])
def test_decode_errors_are_typed(payload):
    with pytest.raises(DecodeError) as info:
        decode(payload, StopRequest)
    assert info.value.code in ("malformed", "invalid", "too_large")


def test_a_start_whose_carried_frames_pass_the_payload_limit_is_too_large():
    """Each frame a start carries is within MAX_FRAME_BYTES, and it may carry eight: decode's payload limit is what
    holds a message to MAX_PAYLOAD_BYTES. With the check removed, or made >=, every test here passed."""
    def start(*sizes: int) -> bytes:
        frames = [Frame(seq=seq, stamp_ns=1, encoding="jpeg", width=16, height=16, data=bytes(size))
                  for seq, size in enumerate(sizes, 1)]
        return encode(StartRequest(image_key="cam", box=(1, 1, 5, 5), seq=1, frames=frames))

    half = MAX_PAYLOAD_BYTES // 2
    over_the_limit = start(half, half)
    at_the_limit = start(half, MAX_PAYLOAD_BYTES - half - (len(over_the_limit) - 2 * half))
    assert len(at_the_limit) == MAX_PAYLOAD_BYTES
    assert len(decode(at_the_limit, StartRequest).frames) == 2
    with pytest.raises(DecodeError) as refused:
        decode(over_the_limit, StartRequest)
    assert refused.value.code == "too_large" and f"exceeds {MAX_PAYLOAD_BYTES}" in refused.value.message


@pytest.mark.parametrize("box", [(0, 0, 0, 5), (0, 0, 5, -1), (math.nan, 0, 1, 1), (0, math.inf, 1, 1), (1, 2, 3)])
def test_start_rejects_bad_boxes(box):
    payload = msgpack.packb({"image_key": "cam", "box": list(box)})
    with pytest.raises(DecodeError):
        decode(payload, StartRequest)


def _frame_fields(**fields):
    return {"seq": 1, "stamp_ns": 2, "encoding": "mono8", "width": 2, "height": 1, "data": b"\x00\xff", **fields}


@pytest.mark.parametrize("model,fields", [
    (Frame, _frame_fields(seq=True)), (Frame, _frame_fields(seq="5")), (Frame, _frame_fields(seq=5.5)),
    (Frame, _frame_fields(width="2")), (Frame, _frame_fields(stamp_ns=False)), (Frame, _frame_fields(v=True)),
    (Frame, _frame_fields(data="\x00\xff")), (Frame, _frame_fields(seq=2.0**63)),
    (StartRequest, {"image_key": "cam", "box": ["1", 2, 3, 4]}),
    (StartRequest, {"image_key": "cam", "box": [1, 2, True, 4]}),
    (StartRequest, {"image_key": "cam", "box": [1, 2, 3, 4], "overrides": {"learning_rate": "0.02"}}),
    (StartRequest, {"image_key": "cam", "box": [1, 2, 3, 4], "overrides": {"use_motion": "true"}}),
    (StartRequest, {"image_key": "cam", "box": [1, 2, 3, 4], "profile": b"authors"}),
    (BoxResult, {"node": "n", "sid": "s", "seq": 1, "stamp_ns": 1, "box": [1, 2, 3, 4], "width": 4, "height": 4,
                 "ok": 1, "pme": 1, "score": 1, "scale": 1, "processing_ms": 1, "published_ns": 1}),
])
def test_decode_is_as_strict_as_the_json_schema(model, fields):
    """pydantic's lax mode took true for an int, "5" for a number and 1 for a bool, which the schema refuses."""
    with pytest.raises(DecodeError) as info:
        decode(msgpack.packb(fields, use_bin_type=True), model)
    assert info.value.code == "invalid"


def test_integral_floats_are_ints_on_the_wire():
    """msgpack from JavaScript sends every number as a float; JSON Schema's integer takes 5.0 too."""
    frame = decode(msgpack.packb(_frame_fields(v=1.0, seq=5.0, width=2.0), use_bin_type=True), Frame)
    assert (frame.seq, frame.width) == (5, 2) and type(frame.seq) is int and type(frame.width) is int
    request = decode(msgpack.packb({"image_key": "cam", "box": [1, 2, 3, 4], "seq": 7.0,
                                    "overrides": {"cell_size": 6, "learning_rate": 0.5, "use_motion": True}}),
                     StartRequest)
    assert request.seq == 7 and request.box == (1.0, 2.0, 3.0, 4.0)
    assert request.overrides == {"cell_size": 6, "learning_rate": 0.5, "use_motion": True}


def test_an_override_int_past_int64_is_sent_as_the_number_it_is():
    """The model took any int as an override, so `tacf start --set cell_size=99999999999999999999` passed it and
    encode raised msgpack's OverflowError: a traceback, where the service refuses the value (invalid_config)."""
    request = StartRequest(image_key="cam", box=(1, 2, 3, 4), overrides={"cell_size": 10**20, "num_scales": 2**63 - 1})
    assert decode(encode(request), StartRequest).overrides == {"cell_size": 1e20, "num_scales": 2**63 - 1}


def _pairs(*pairs) -> bytes:
    """A msgpack map of these (key, value) pairs in this order, a key possibly twice (packb takes a dict)."""
    return msgpack.Packer().pack_map_pairs(pairs)


@pytest.mark.parametrize("payload,model", [
    (_pairs(("sid", "s1"), ("sid", "s2")), StopRequest),
    (_pairs(*_frame_fields().items(), ("seq", 1000)), Frame),
    (b"\x83" + b"".join(msgpack.packb(x) for x in ("image_key", "cam", "box", [1, 2, 3, 4], "overrides"))
     + _pairs(("cell_size", 4), ("cell_size", 6)), StartRequest),
], ids=["a field", "a frame's seq", "an override"])
def test_a_field_given_twice_is_refused(payload, model):
    """msgpack keeps the last value of a key given twice: the first was dropped without a word (a misspelt field
    is refused so that nothing is silently ignored), and a worker, which peeks at a frame's first "seq" to count
    the frames its ring dropped, read another seq than the decoder."""
    with pytest.raises(DecodeError) as info:
        decode(payload, model)
    assert info.value.code == "malformed" and "twice" in info.value.message


def test_maps_passed_as_a_generator_decode_as_lists_do(monkeypatch):
    """msgpack's pure-Python fallback hands object_pairs_hook a generator up to 1.2.0 (the C extension a list): the
    floors' msgpack 1.0.0, which has no wheel for Python 3.10+, installs as that fallback, and every decode failed."""
    unpackb = msgpack.unpackb

    def as_the_fallback(payload, object_pairs_hook, **kwargs):
        return unpackb(payload, object_pairs_hook=lambda pairs: object_pairs_hook(iter(pairs)), **kwargs)

    monkeypatch.setattr(msgpack, "unpackb", as_the_fallback)
    assert decode(_pairs(("sid", "s1")), StopRequest).sid == "s1"
    with pytest.raises(DecodeError, match="twice"):
        decode(_pairs(("sid", "s1"), ("sid", "s2")), StopRequest)


def _schema_takes(model: str, message: dict) -> bool:
    schema = json.loads((JSON_DIR / f"{model}.json").read_text())
    validator = jsonschema.validators.validator_for(schema)(schema)
    return validator.is_valid(_as_json(message))


def _as_json(value):
    """A message as JSON carries it: bytes (msgpack bin) are the schema's binary strings."""
    if isinstance(value, bytes):
        return value.decode("latin-1")
    if isinstance(value, dict):
        return {k: _as_json(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_as_json(v) for v in value]
    return value


def _decoder_takes(model: str, message: dict) -> bool:
    try:
        decode(msgpack.packb(message, use_bin_type=True), MODELS[model])
    except DecodeError:
        return False
    return True


@pytest.mark.parametrize("case", CASES, ids=lambda case: f"{case.model}: {case.label}")
def test_the_json_schema_and_the_decoder_agree(case):
    """A publisher validating against schemas/json and the service decoding the same message must agree."""
    assert _schema_takes(case.model, case.message) == case.valid, "the JSON schema"
    assert _decoder_takes(case.model, case.message) == case.valid, "the decoder"


def test_the_cases_cover_every_message_type():
    assert {case.model for case in CASES if case.valid} == set(MODELS)
    assert {case.model for case in CASES if not case.valid} == set(MODELS)


@pytest.mark.parametrize("case", BEYOND_SCHEMA, ids=lambda case: f"{case.model}: {case.label}")
def test_what_the_schema_cannot_state_the_decoder_refuses(case):
    assert _schema_takes(case.model, case.message) and not _decoder_takes(case.model, case.message)


def test_every_json_schema_names_its_draft():
    """The schemas are written in 2020-12 (a box's prefixItems): without "$schema" a validator applies its own
    default draft, and under draft 7 (Ajv's default class, jsonschema's Draft7Validator...) prefixItems is no
    keyword, so a box of four strings passed."""
    for name in MODELS:
        schema = json.loads((JSON_DIR / f"{name}.json").read_text())
        assert schema.get("$schema") == "https://json-schema.org/draft/2020-12/schema", name
    schema = json.loads((JSON_DIR / "StartRequest.json").read_text())
    validator = jsonschema.validators.validator_for(schema, default=jsonschema.Draft7Validator)(schema)
    assert not validator.is_valid({"image_key": "cam", "box": ["1", "2", "3", "4"]})


def test_init_box_sizes_are_positive_in_the_json_schema():
    for name in ("StartRequest", "ReinitRequest"):
        items = MODELS[name].model_json_schema()["properties"]["box"]["prefixItems"]
        assert [item.get("exclusiveMinimum") for item in items] == [None, None, 0, 0]


@settings(max_examples=150, deadline=None)
@given(st.binary(max_size=256))
def test_decode_fuzz_never_raises_anything_else(payload):
    for model in (StartRequest, Frame, StopRequest, BoxResult):
        try:
            decode(payload, model)
        except DecodeError:
            pass


json_like = st.recursive(st.none() | st.booleans() | st.integers(-2**63, 2**64 - 1) | st.floats() | st.text(max_size=8)
                         | st.binary(max_size=8), lambda c: st.lists(c, max_size=4)
                         | st.dictionaries(st.text(max_size=8), c, max_size=4), max_leaves=12)


@settings(max_examples=150, deadline=None)
@given(st.dictionaries(st.sampled_from(["v", "image_key", "box", "seq", "sid", "profile", "overrides", "data",
                                        "width", "height", "encoding", "stamp_ns"]), json_like, max_size=8))
def test_decode_fuzz_structured(obj):
    payload = msgpack.packb(obj, use_bin_type=True)
    for model in (StartRequest, Frame):
        try:
            decode(payload, model)
        except DecodeError:
            pass


# ---------------------------------------------------------------- keys

def test_keys():
    assert control_key("edge", "start") == "tacf/edge/control/start"
    assert control_key("*", "list") == "tacf/*/control/list"
    assert box_key("edge", "s-1") == "tacf/edge/sessions/s-1/box"
    assert health_key("edge", "s_1") == "tacf/edge/sessions/s_1/health"
    assert service_liveliness_key("edge") == "@tacf/edge"
    assert session_liveliness_key("edge", "s1") == "@tacf/edge/s1"
    assert parse_session_key("tacf/edge/sessions/s1/box") == ("edge", "s1", "box")
    assert parse_liveliness_key("@tacf/edge/s1") == ("edge", "s1")
    assert parse_liveliness_key("@tacf/edge") == ("edge", None)
    assert parse_control_key("tacf/edge/control/start") == ("edge", "start")
    for not_control in ("tacf/edge/control/explode", "tacf/edge/sessions/s1/box", "tacf/*/control/list",
                        "other/edge/control/stop", "tacf/edge/control/stop/more"):
        with pytest.raises(ValueError):
            parse_control_key(not_control)
    assert ALL_LIVELINESS == "@tacf/**"
    with pytest.raises(ValueError):
        control_key("edge", "explode")
    with pytest.raises(InvalidIdError):
        box_key("a/b", "s")


@pytest.mark.parametrize("bad", ["", "a" * 65, "a/b", "a*", "*", "é", "a b", "a.b", None, 5, "edge\n"])
def test_invalid_ids(bad):
    with pytest.raises(InvalidIdError):
        validate_id(bad)


def test_sanitise_id():
    assert sanitise_id("my.host.local") == "my-host-local"
    assert sanitise_id("...") == "edge"
    validate_id(sanitise_id("x" * 300))


@pytest.mark.parametrize("good", ["uav1/camera/front", "cam", "a-b_c.d/e:1", "cam/v1.2", "cam/.../x", ".cam"])
def test_valid_image_keys(good):
    assert validate_image_key(good) == good


@pytest.mark.parametrize("bad", ["", "/cam", "cam/", "a//b", "cam/*", "cam/**", "ca$*m", "cam#1", "cam?x",
                                 "cam 1", "@admin/x", "tacf/edge/x", "é", "a" * 300, "/".join("a" * 20), None,
                                 "uav1/cam\n", "uav1\n/cam",   # a key read from a file without strip()
                                 "cam/./front", "cam/../front", ".."])  # a URL's path would resolve them away
def test_invalid_image_keys(bad):
    with pytest.raises(InvalidKeyError):
        validate_image_key(bad)


def test_valid_image_keys_are_valid_zenoh_keys():
    zenoh = pytest.importorskip("zenoh")
    for key in ["uav1/camera/front", "a-b_c.d/e:1", "x~y+z=w,v"]:
        zenoh.KeyExpr(validate_image_key(key))


# ---------------------------------------------------------------- frames

@pytest.fixture(scope="module")
def image():
    rng = np.random.default_rng(0)
    return rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)


@pytest.mark.parametrize("encoding", ["jpeg", "png", "bgr8"])
def test_frame_roundtrip(image, encoding):
    frame = decode(encode(encode_frame(image, seq=3, encoding=encoding)), Frame)
    out = decode_frame(frame)
    assert out.shape == image.shape and out.dtype == np.uint8
    if encoding != "jpeg":
        assert np.array_equal(out, image)


def test_mono8(image):
    gray = np.ascontiguousarray(image[:, :, 0])
    assert np.array_equal(decode_frame(encode_frame(gray, 1, "mono8")), gray)


@pytest.mark.parametrize("encoding", ["jpeg", "png", "bgr8", "mono8"])
@pytest.mark.parametrize("channels", [0, 2, 4])
def test_an_image_of_other_channels_is_a_value_error(encoding, channels):
    """An HxWx2 image went through to OpenCV, whose cv2.error is not the ValueError the docstring promises."""
    with pytest.raises(ValueError, match="HxWx3"):
        encode_frame(np.zeros((8, 8, channels), np.uint8), 1, encoding)


def test_header_sizes(image):
    assert jpeg_size(encode_frame(image, 1, "jpeg").data) == (64, 48)
    assert png_size(encode_frame(image, 1, "png").data) == (64, 48)


def _frame(**fields):
    base = dict(seq=1, stamp_ns=1, encoding="bgr8", width=4, height=2, data=bytes(24))
    base.update(fields)
    return Frame.model_construct(**base)   # bypass validation to test the decoder's own checks


@pytest.mark.parametrize("fields,code", [
    (dict(encoding="rgb16"), "unsupported_encoding"),
    (dict(data=bytes(23)), "size_mismatch"),
    (dict(encoding="mono8"), "size_mismatch"),
    (dict(width=0, height=0, data=b""), "size_mismatch"),
    (dict(width=8192, height=8192, data=b""), "too_large"),
    (dict(encoding="jpeg", data=b"\xff\xd8\xff\xe0garbage"), "corrupt"),
    (dict(encoding="jpeg", data=b"not a jpeg at all"), "corrupt"),
    (dict(encoding="png", data=b"\x89PNG\r\n\x1a\nbroken"), "corrupt"),
])
def test_frame_errors(fields, code):
    with pytest.raises(FrameError) as info:
        decode_frame(_frame(**fields))
    assert info.value.code == code


@pytest.mark.parametrize("channels", [1, 3, 4])
def test_a_16_bit_png_is_refused_from_its_header(channels):
    """decode_frame refuses 16-bit pixels, but only after OpenCV decoded them all (a 130 kB PNG of 4096x4096 RGBA:
    1 s and 256 MB); check_frame, which the service applies to the frames a start carries, let them through, so
    such a start was accepted and its frame then rejected by the worker, which initialised on another frame."""
    pixels = np.zeros((48, 64, channels) if channels > 1 else (48, 64), np.uint16)
    frame = Frame(seq=1, stamp_ns=1, encoding="png", width=64, height=48,
                  data=cv2.imencode(".png", pixels)[1].tobytes())
    for check in (check_frame, decode_frame):
        with pytest.raises(FrameError) as info:
            check(frame)
        assert info.value.code == "unsupported_encoding"


def test_jpeg_size_mismatch_rejected_before_decoding(image):
    frame = encode_frame(image, 1, "jpeg")
    wrong = frame.model_copy(update={"width": 65})
    with pytest.raises(FrameError) as info:
        decode_frame(wrong)
    assert info.value.code == "size_mismatch"


def test_truncated_jpeg_body_is_corrupt_or_decodes(image):
    data = encode_frame(image, 1, "jpeg").data
    for cut in (20, 200, len(data) // 2):
        try:
            out = decode_frame(_frame(encoding="jpeg", width=64, height=48, data=data[:cut]))
            assert out.shape == (48, 64, 3)
        except FrameError:
            pass


def test_the_frame_schema_states_the_pixel_limit():
    """A publisher reading schemas/json/Frame.json learns that the service refuses frames over 16.8 Mpx."""
    schema = json.loads((JSON_DIR / "Frame.json").read_text())
    for field in ("width", "height"):
        assert str(MAX_FRAME_PIXELS) in schema["properties"][field]["description"]


def test_frame_model_caps_dimensions():
    for w, h in [(0, 0), (100000, 10), (10, 100000)]:
        with pytest.raises(DecodeError):
            decode(msgpack.packb({"seq": 1, "stamp_ns": 1, "encoding": "bgr8", "width": w, "height": h,
                                  "data": b""}), Frame)
    assert 4096 * 4096 <= MAX_FRAME_PIXELS


@settings(max_examples=200, deadline=None)
@given(st.sampled_from(["jpeg", "png"]), st.binary(max_size=512))
def test_image_decoder_fuzz(encoding, data):
    frame = _frame(encoding=encoding, width=16, height=16, data=data)
    try:
        decode_frame(frame)
    except FrameError:
        pass


def test_control_ops():
    assert set(CONTROL_OPS) == {"start", "stop", "reinit", "list", "status"}


def test_error_replies_are_the_services_or_zenohs_own():
    error = decode_error_reply(encode(Error(code="unknown_session", message="no session 'x'", node="edge")))
    assert isinstance(error, Error) and error.code == "unknown_session" and not is_deadline_reply(error)
    assert is_deadline_reply(decode_error_reply(b"Timeout")), "what Zenoh replies at a get's deadline"
    text = decode_error_reply(b"\xffsome transport error")
    assert isinstance(text, str) and "transport error" in text and not is_deadline_reply(text)
    assert not is_deadline_reply(decode_error_reply(encode(Error(code="internal", message="timeout"))))


def test_a_newer_service_s_error_keeps_its_code():
    """errors.py promises a plain ServiceError for a code this client does not know; the strict decode failed
    first, and the client raised ProtocolError (also for a known code next to a field a newer service added)."""
    from tacf_clients.errors import ServiceError, UnknownSession, error_from_wire

    for fields, expected in [({"code": "rate_limited", "message": "slow down"}, ServiceError),
                             ({"code": "unknown_session", "message": "no such", "retry_after": 1}, UnknownSession)]:
        error = decode_error_reply(msgpack.packb({"v": 2, **fields, "node": "edge"}))
        assert isinstance(error, Error) and (error.code, error.node) == (fields["code"], "edge")
        assert type(error_from_wire(error.code, error.message, error.node)) is expected
    assert isinstance(decode_error_reply(msgpack.packb({"code": 5, "message": "x"})), str)
    assert decode_error_reply(msgpack.packb({"code": "x", "message": "y", "node": "a/b"})).node is None


def test_catch_up_subset_keeps_the_first_and_ends_on_the_newest():
    from tacf_schemas import catch_up_subset
    assert catch_up_subset(list(range(20)), 6, seq=int) == [0, 3, 6, 10, 13, 16, 19]
    assert catch_up_subset(list(range(5)), 6, seq=int) == [0, 1, 2, 3, 4]
    assert catch_up_subset(list(range(5)), 0, seq=int) == [0]
    assert catch_up_subset([], 3, seq=int) == []


def test_catch_up_subset_spaces_the_frames_by_seq_across_gaps():
    """A box drawn on frame 1 of a 10 fps feed 4 s ago: the dashboard holds that frame (shown), then only the last
    32 received; the service appends the live frames that came before its worker was ready. Spaced by their place
    in the list, the frames after such a gap were thinned so that the tracker's first step grew from 13 frames to
    17 and more as more live frames came (under load), beyond its reach on a moving target."""
    from tacf_schemas import catch_up_subset
    carried = catch_up_subset([1] + list(range(10, 42)), 7, seq=int)
    assert carried == [1, 10, 12, 18, 24, 30, 35, 41]
    for live in range(21):
        used = catch_up_subset(carried + list(range(42, 42 + live)), 6, seq=int)
        steps = [b - a for a, b in zip(used, used[1:])]
        assert used[0] == 1 and used[-1] == 41 + live and max(steps) <= 12, (live, used)
    restarted = [90, 95, 99, 2, 3, 4, 5, 6, 7, 8]       # the camera restarted its seq: spaced by place
    assert catch_up_subset(restarted, 3, seq=int) == [90, 2, 5, 8]
