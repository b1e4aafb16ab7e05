"""msgpack codec for the wire models: encode(model) -> bytes, decode(bytes, Model) -> model.

decode never lets a msgpack or pydantic exception escape: every failure is a DecodeError with a `code`
("too_large", "malformed", "invalid") and a one-line message fit for an Error reply or a log line.
unique_keys, which refuses a map that gives a key twice, serves the JSON entry points too.
"""
from __future__ import annotations

from collections import Counter
from collections.abc import Iterable
from typing import TypeVar

import msgpack
import pydantic

from .keys import is_valid_id
from .limits import MAX_FRAME_BYTES, MAX_MESSAGE_LENGTH, MAX_MSGPACK_OBJECTS, MAX_PAYLOAD_BYTES
from .models import Error, WireModel

M = TypeVar("M", bound=WireModel)

#: Zenoh encoding string for payloads made here: zenoh.Encoding(MSGPACK_ENCODING).
MSGPACK_ENCODING = "application/msgpack"


class DecodeError(ValueError):
    """A payload that is not a valid message of the expected model."""

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code
        self.message = message


def encode(model: WireModel) -> bytes:
    """msgpack bytes of a model (bytes fields as msgpack bin, boxes as arrays)."""
    return msgpack.packb(model.model_dump(mode="python"), use_bin_type=True)


def decode(payload: bytes | bytearray | memoryview, model: type[M]) -> M:
    """Parse and validate msgpack bytes as `model`; raise DecodeError on anything wrong."""
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise DecodeError("too_large", f"{model.__name__}: payload of {len(payload)} bytes exceeds "
                                       f"{MAX_PAYLOAD_BYTES}")
    obj = _unpack(payload, model.__name__)
    if not isinstance(obj, dict):
        raise DecodeError("invalid", f"{model.__name__}: expected a map, got {type(obj).__name__}")
    try:
        return model.from_wire(obj)
    except pydantic.ValidationError as exc:
        raise DecodeError("invalid", f"{model.__name__}: {_summarise(exc)}") from None
    except (TypeError, ValueError, RecursionError) as exc:  # e.g. unhashable keys deep inside
        raise DecodeError("invalid", f"{model.__name__}: {type(exc).__name__}: {str(exc)[:200]}") from None


class RepeatedKeyError(ValueError):
    """A msgpack map or JSON object that gives a key twice (unique_keys)."""


def unique_keys(pairs: Iterable[tuple[object, object]]) -> dict:
    """A map as a dict, refusing a key given twice: the object_pairs_hook of every msgpack and JSON parse of what
    comes from outside (the wire here; the dashboard's HTTP API, the Foxglove service calls, the state file). Both
    parsers keep the last value, so the first was dropped without a word, and two readers of one message could see
    two messages (the worker, which peeks at a frame's first "seq", read another seq than the decoder). msgpack's C
    extension passes the pairs as a list, its pure-Python fallback (PyPy, MSGPACK_PUREPYTHON, a build without the
    extension such as msgpack 1.0.0's on Python 3.10+, which has no wheel) as a generator up to 1.2.0."""
    pairs = list(pairs)
    fields = dict(pairs)
    if len(fields) != len(pairs):
        twice = next(key for key, count in Counter(key for key, _ in pairs).items() if count > 1)
        raise RepeatedKeyError(f"key {twice!r} given twice")
    return fields


def _unpack(payload: bytes | bytearray | memoryview, name: str) -> object:
    _count_objects(payload, name)
    try:
        return msgpack.unpackb(payload, raw=False, strict_map_key=True, use_list=True, object_pairs_hook=unique_keys,
                               max_bin_len=MAX_FRAME_BYTES, max_str_len=1 << 20,
                               max_array_len=1 << 16, max_map_len=1 << 10, max_ext_len=0)
    except Exception as exc:  # msgpack raises several unrelated types (ValueError, ExtraData, TypeError...)
        raise DecodeError("malformed", f"{name}: malformed msgpack ({type(exc).__name__}: {str(exc)[:200]})") from None


# msgpack type bytes: the bytes a scalar takes in all, or the width of the length before a str's or bin's body
_SCALAR_BYTES = {0xC0: 1, 0xC2: 1, 0xC3: 1, 0xCA: 5, 0xCB: 9, 0xCC: 2, 0xCD: 3, 0xCE: 5, 0xCF: 9,
                 0xD0: 2, 0xD1: 3, 0xD2: 5, 0xD3: 9}
_LENGTH_BYTES = {0xC4: 1, 0xC5: 2, 0xC6: 4, 0xD9: 1, 0xDA: 2, 0xDB: 4}


def _count_objects(payload: bytes | bytearray | memoryview, name: str) -> None:
    """Refuse a payload of over MAX_MSGPACK_OBJECTS objects before unpacking it: msgpack's length limits hold per
    array or map, and a payload of empty arrays, a byte each, unpacked to 70 times its size in Python objects. Walks
    the type bytes only (str and bin bodies skipped), and stops at what msgpack refuses itself (ext types, the end)."""
    pos, end, pending, count = 0, len(payload), 1, 0
    while pending and pos < end:
        if count == MAX_MSGPACK_OBJECTS:
            raise DecodeError("too_large", f"{name}: more than {MAX_MSGPACK_OBJECTS} msgpack objects")
        count, pending = count + 1, pending - 1
        byte = payload[pos]
        if byte < 0x80 or byte >= 0xE0:             # fixint
            pos += 1
        elif byte < 0xA0:                           # fixmap, fixarray
            pending += (byte & 0x0F) * (2 if byte < 0x90 else 1)
            pos += 1
        elif byte < 0xC0:                           # fixstr
            pos += 1 + (byte & 0x1F)
        elif byte in _SCALAR_BYTES:
            pos += _SCALAR_BYTES[byte]
        elif byte in _LENGTH_BYTES:
            width = _LENGTH_BYTES[byte]
            pos += 1 + width + int.from_bytes(payload[pos + 1:pos + 1 + width], "big")
        elif 0xDC <= byte <= 0xDF:                  # array 16/32, map 16/32
            width = 2 if byte in (0xDC, 0xDE) else 4
            pending += int.from_bytes(payload[pos + 1:pos + 1 + width], "big") * (2 if byte >= 0xDE else 1)
            pos += 1 + width
        else:
            return


def decode_error_reply(payload: bytes | bytearray | memoryview) -> Error | str:
    """A control op's error reply: the service's Error, or, when it is not one, the text of a reply Zenoh made
    itself. At a get's deadline Zenoh replies "timeout" (is_deadline_reply). An Error of a newer service (a code
    this side does not know, a field it added) keeps its code and message, so the caller sees a service error."""
    try:
        return decode(payload, Error)
    except DecodeError:
        pass
    try:
        obj = _unpack(payload, "Error") if len(payload) <= MAX_PAYLOAD_BYTES else None
    except DecodeError:
        obj = None
    if isinstance(obj, dict) and isinstance(obj.get("code"), str) and isinstance(obj.get("message"), str):
        node = obj.get("node")
        return Error.model_construct(code=obj["code"][:64], message=obj["message"][:MAX_MESSAGE_LENGTH],
                                     node=node if is_valid_id(node) else None)
    return bytes(payload).decode("utf-8", "replace")


def is_deadline_reply(error: Error | str) -> bool:
    """Whether decode_error_reply's result is Zenoh's own reply that no queryable answered in time."""
    return isinstance(error, str) and error.strip().lower() == "timeout"


def _summarise(exc: pydantic.ValidationError, limit: int = 3) -> str:
    parts = []
    for err in exc.errors(include_url=False, include_input=False)[:limit]:
        loc = ".".join(str(p) for p in err["loc"]) or "<root>"
        parts.append(f"{loc}: {err['msg']}")
    more = exc.error_count() - limit
    return "; ".join(parts) + (f" (+{more} more)" if more > 0 else "")
