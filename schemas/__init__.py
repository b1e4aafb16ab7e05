"""Wire schemas of the TACF tracking service: pydantic models, msgpack codec, Zenoh key layout.

    from tacf_schemas import StartRequest, encode, decode, control_key
    payload = encode(StartRequest(image_key="uav1/camera/front", box=(10, 20, 40, 30)))
    request = decode(payload, StartRequest)          # DecodeError on anything wrong

Image decoding (numpy/OpenCV) lives in tacf_schemas.images so that this package stays light.
"""
from __future__ import annotations

from .codec import MSGPACK_ENCODING, DecodeError, decode, decode_error_reply, encode, is_deadline_reply
from .keys import (ALL_LIVELINESS, LEAST_LOADED, InvalidIdError, InvalidKeyError, box_key, control_key, health_key,
                   is_valid_id, parse_control_key, parse_liveliness_key, parse_session_key, sanitise_id,
                   service_liveliness_key, session_key, session_liveliness_key, validate_id, validate_image_key,
                   validate_node_id)
from .limits import SCHEMA_VERSION
from .models import (CONTROL_OPS, CONTROL_REPLIES, CONTROL_REQUESTS, ENCODINGS, ERROR_CODES, MODELS,
                     SESSION_STATES, BoxResult, Error, Frame, Health, ListRequest, ReinitRequest, SessionInfo,
                     SessionList, StartRequest, StatusRequest, StopRequest, WireModel, catch_up_subset)

__all__ = [
    "SCHEMA_VERSION", "MSGPACK_ENCODING", "DecodeError", "decode", "decode_error_reply", "encode",
    "is_deadline_reply",
    "ALL_LIVELINESS", "LEAST_LOADED", "InvalidIdError", "InvalidKeyError", "box_key", "control_key", "health_key",
    "is_valid_id", "parse_control_key", "parse_liveliness_key", "parse_session_key", "sanitise_id",
    "service_liveliness_key", "session_key", "session_liveliness_key", "validate_id", "validate_image_key",
    "validate_node_id",
    "CONTROL_OPS", "CONTROL_REPLIES", "CONTROL_REQUESTS", "ENCODINGS", "ERROR_CODES", "MODELS", "SESSION_STATES",
    "BoxResult", "Error", "Frame", "Health", "ListRequest", "ReinitRequest", "SessionInfo", "SessionList",
    "StartRequest", "StatusRequest", "StopRequest", "WireModel", "catch_up_subset",
]
