"""Wire messages, good and bad, of every message type, as a publisher in any language might send them.

tests/test_schemas.py checks each against the published JSON Schema (schemas/json) and against the decoder
(codec.decode of its msgpack): both must take it or both refuse it, as `valid` says.

Messages are written in JSON's terms. What JSON cannot say is left out of CASES: NaN and infinities (the decoder
refuses them in every float field but a tracker override's, which the service refuses as invalid_config), and
msgpack's bin versus str (bytes fields such as Frame.data take bin only, text fields str only:
test_decode_is_as_strict_as_the_json_schema). BEYOND_SCHEMA lists what the decoder refuses although the schema
cannot state it.
"""
from __future__ import annotations

from typing import NamedTuple

DROP = object()   # _with(..., field=DROP) leaves the field out


class Case(NamedTuple):
    model: str
    label: str
    message: dict
    valid: bool


def _with(base: dict, **changes) -> dict:
    message = {**base, **changes}
    return {k: v for k, v in message.items() if v is not DROP}


FRAME = {"seq": 1, "stamp_ns": 2, "encoding": "mono8", "width": 2, "height": 1, "data": b"\x00\xff"}
START = {"image_key": "uav1/camera/front", "box": [10, 20, 40, 30]}
REINIT = {"sid": "s1", "box": [10.5, 20.5, 40.0, 30.0]}
BOX_RESULT = {"node": "edge", "sid": "s1", "seq": 3, "stamp_ns": 4, "box": [1.5, 2.5, 3.5, 4.5], "width": 640,
              "height": 360, "ok": True, "pme": 20.0, "score": 0.5, "scale": 1.0, "processing_ms": 3.2,
              "published_ns": 9}
HEALTH = {"node": "edge", "sid": "s1", "state": "tracking", "stamp_ns": 5, "fps": 9.5, "processing_ms_mean": 4.0,
          "processing_ms_p95": 6.0}
INFO = {"node": "edge", "sid": "s1", "image_key": "uav1/cam", "profile": "authors", "state": "tracking",
        "box": [1, 2, 3, 4], "created_ns": 1}
ERROR = {"code": "unknown_session", "message": "no session 'x'"}
LONG_TEXT = "x" * 1025

CASES: list[Case] = [
    # ------------------------------------------------------------ Frame
    Case("Frame", "complete", FRAME, True),
    Case("Frame", "with its version", _with(FRAME, v=1), True),
    Case("Frame", "integral floats for ints (msgpack from JavaScript)", _with(FRAME, v=1.0, seq=5.0, width=2.0),
         True),
    Case("Frame", "largest seq", _with(FRAME, seq=2**63 - 1), True),
    Case("Frame", "largest size (its pixels are the service's to refuse)", _with(FRAME, width=8192, height=8192),
         True),
    Case("Frame", "no data", _with(FRAME, data=DROP), False),
    Case("Frame", "negative seq", _with(FRAME, seq=-1), False),
    Case("Frame", "seq past int64", _with(FRAME, seq=2**63), False),
    Case("Frame", "seq as a float past int64", _with(FRAME, seq=2.0**63), False),
    Case("Frame", "seq true", _with(FRAME, seq=True), False),
    Case("Frame", "seq as text", _with(FRAME, seq="1"), False),
    Case("Frame", "seq with a fraction", _with(FRAME, seq=1.5), False),
    Case("Frame", "width 0", _with(FRAME, width=0), False),
    Case("Frame", "width over 8192", _with(FRAME, width=8193), False),
    Case("Frame", "height false", _with(FRAME, height=False), False),
    Case("Frame", "unknown encoding", _with(FRAME, encoding="rgb16"), False),
    Case("Frame", "encoding as a number", _with(FRAME, encoding=5), False),
    Case("Frame", "unknown field", _with(FRAME, colour="red"), False),
    Case("Frame", "version 2", _with(FRAME, v=2), False),
    Case("Frame", "version true", _with(FRAME, v=True), False),
    Case("Frame", "version as text", _with(FRAME, v="1"), False),
    # ------------------------------------------------------------ StartRequest
    Case("StartRequest", "minimal", START, True),
    Case("StartRequest", "complete", _with(START, seq=7, sid="s-1", profile="authors",
                                           overrides={"cell_size": 6, "learning_rate": 0.02, "use_motion": True},
                                           frames=[_with(FRAME, seq=7)]), True),
    Case("StartRequest", "nulls for the optional fields", _with(START, seq=None, sid=None, profile=None), True),
    Case("StartRequest", "seq as an integral float", _with(START, seq=7.0), True),
    Case("StartRequest", "an integral float override (stays a float)", _with(START, overrides={"cell_size": 6.0}),
         True),
    Case("StartRequest", "no box", _with(START, box=DROP), False),
    Case("StartRequest", "no image key", _with(START, image_key=DROP), False),
    Case("StartRequest", "empty image key", _with(START, image_key=""), False),
    Case("StartRequest", "image key too long", _with(START, image_key="k" * 257), False),
    Case("StartRequest", "box width 0", _with(START, box=[10, 20, 0, 30]), False),
    Case("StartRequest", "box height negative", _with(START, box=[10, 20, 40, -1]), False),
    Case("StartRequest", "box of three", _with(START, box=[10, 20, 40]), False),
    Case("StartRequest", "box of five", _with(START, box=[10, 20, 40, 30, 1]), False),
    Case("StartRequest", "box as text", _with(START, box=["10", 20, 40, 30]), False),
    Case("StartRequest", "box with a bool", _with(START, box=[10, 20, True, 30]), False),
    Case("StartRequest", "box as an object", _with(START, box={"x": 10, "y": 20, "w": 40, "h": 30}), False),
    Case("StartRequest", "seq as text", _with(START, seq="7"), False),
    Case("StartRequest", "override as text", _with(START, overrides={"learning_rate": "0.02"}), False),
    Case("StartRequest", "override as text of a bool", _with(START, overrides={"use_motion": "true"}), False),
    Case("StartRequest", "override null", _with(START, overrides={"cell_size": None}), False),
    Case("StartRequest", "too many overrides", _with(START, overrides={f"o{i}": 1 for i in range(65)}), False),
    Case("StartRequest", "profile too long", _with(START, profile="p" * 33), False),
    Case("StartRequest", "sid with a slash", _with(START, sid="a/b"), False),
    Case("StartRequest", "empty sid", _with(START, sid=""), False),
    Case("StartRequest", "too many frames", _with(START, frames=[_with(FRAME, seq=i) for i in range(9)]), False),
    Case("StartRequest", "a frame without its data", _with(START, frames=[_with(FRAME, data=DROP)]), False),
    Case("StartRequest", "unknown field", _with(START, colour="red"), False),
    # ------------------------------------------------------------ StopRequest, StatusRequest, ListRequest
    Case("StopRequest", "sid", {"sid": "s1"}, True),
    Case("StopRequest", "no sid", {}, False),
    Case("StopRequest", "sid as a number", {"sid": 5}, False),
    Case("StopRequest", "sid with a space", {"sid": "a b"}, False),
    Case("StopRequest", "sid too long", {"sid": "s" * 65}, False),
    Case("StatusRequest", "sid", {"sid": "s_1", "v": 1}, True),
    Case("StatusRequest", "sid null", {"sid": None}, False),
    Case("ListRequest", "empty", {}, True),
    Case("ListRequest", "version", {"v": 1}, True),
    Case("ListRequest", "unknown field", {"node": "edge"}, False),
    Case("ListRequest", "version 2", {"v": 2}, False),
    Case("ListRequest", "version true", {"v": True}, False),
    # ------------------------------------------------------------ ReinitRequest
    Case("ReinitRequest", "float box", REINIT, True),
    Case("ReinitRequest", "on a frame", _with(REINIT, seq=3.0, frames=[_with(FRAME, seq=3)]), True),
    Case("ReinitRequest", "no sid", _with(REINIT, sid=DROP), False),
    Case("ReinitRequest", "box width 0", _with(REINIT, box=[1, 2, 0.0, 3]), False),
    Case("ReinitRequest", "overrides (a start's only)", _with(REINIT, overrides={}), False),
    # ------------------------------------------------------------ BoxResult
    Case("BoxResult", "complete", BOX_RESULT, True),
    Case("BoxResult", "a tracker's box may have any finite size", _with(BOX_RESULT, box=[-5, -5, 0, -1]), True),
    Case("BoxResult", "ints for floats", _with(BOX_RESULT, pme=20, score=0, scale=1, processing_ms=3), True),
    Case("BoxResult", "ok as a number", _with(BOX_RESULT, ok=1), False),
    Case("BoxResult", "ok as text", _with(BOX_RESULT, ok="true"), False),
    Case("BoxResult", "pme as text", _with(BOX_RESULT, pme="20.0"), False),
    Case("BoxResult", "score true", _with(BOX_RESULT, score=True), False),
    Case("BoxResult", "no pme", _with(BOX_RESULT, pme=DROP), False),
    Case("BoxResult", "width 0", _with(BOX_RESULT, width=0), False),
    Case("BoxResult", "published before the epoch", _with(BOX_RESULT, published_ns=-1), False),
    # ------------------------------------------------------------ Health
    Case("Health", "minimal", HEALTH, True),
    Case("Health", "complete", _with(HEALTH, frame_age_ms=12.0, frames_received=10, frames_processed=9,
                                     frames_dropped=1, frames_rejected=0, frames_lost=0, pme=12.5, last_seq=9,
                                     restarts=0, message="ok"), True),
    Case("Health", "nulls for the optional fields", _with(HEALTH, frame_age_ms=None, pme=None, last_seq=None,
                                                          message=None), True),
    Case("Health", "unknown state", _with(HEALTH, state="running"), False),
    Case("Health", "fps true", _with(HEALTH, fps=True), False),
    Case("Health", "negative count", _with(HEALTH, frames_dropped=-1), False),
    Case("Health", "count as text", _with(HEALTH, frames_dropped="1"), False),
    Case("Health", "count past int64", _with(HEALTH, frames_received=2**63), False),
    Case("Health", "count as an integral float past int64", _with(HEALTH, frames_received=1e300), False),
    Case("Health", "message too long", _with(HEALTH, message=LONG_TEXT), False),
    # ------------------------------------------------------------ SessionInfo, SessionList
    Case("SessionInfo", "minimal", INFO, True),
    Case("SessionInfo", "with health and overrides", _with(INFO, health=HEALTH, overrides={"cell_size": 6},
                                                           init_seq=3, last_seq=9, restarts=1), True),
    Case("SessionInfo", "no state", _with(INFO, state=DROP), False),
    Case("SessionInfo", "a bad health", _with(INFO, health=_with(HEALTH, fps="9.5")), False),
    Case("SessionInfo", "override as text", _with(INFO, overrides={"cell_size": "6"}), False),
    Case("SessionList", "empty", {"node": "edge", "max_sessions": 4}, True),
    Case("SessionList", "one session", {"node": "edge", "max_sessions": 4.0, "sessions": [INFO]}, True),
    Case("SessionList", "negative capacity", {"node": "edge", "max_sessions": -1}, False),
    Case("SessionList", "capacity as an integral float past int64", {"node": "edge", "max_sessions": 1e300}, False),
    Case("SessionList", "a session missing fields", {"node": "edge", "max_sessions": 4, "sessions": [{"sid": "s"}]},
         False),
    # ------------------------------------------------------------ Error
    Case("Error", "code and message", ERROR, True),
    Case("Error", "with its node", _with(ERROR, node="edge"), True),
    Case("Error", "node null", _with(ERROR, node=None), True),
    Case("Error", "unknown code", _with(ERROR, code="rate_limited"), False),
    Case("Error", "message too long", _with(ERROR, message=LONG_TEXT), False),
    Case("Error", "node with a slash", _with(ERROR, node="a/b"), False),
    Case("Error", "no message", _with(ERROR, message=DROP), False),
]

#: What the decoder refuses although the schema takes it: rules JSON Schema cannot state.
BEYOND_SCHEMA: list[Case] = [
    Case("StartRequest", "the first frame carried is not seq", _with(START, seq=5, frames=[_with(FRAME, seq=6)]),
         False),
    Case("ReinitRequest", "frames carried out of order",
         _with(REINIT, frames=[_with(FRAME, seq=6), _with(FRAME, seq=5)]), False),
]
