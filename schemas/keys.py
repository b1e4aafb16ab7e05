"""The Zenoh key layout, as functions. Nothing else in the project builds tacf keys by hand.

    tacf/<node>/control/<op>          queryable: start, stop, reinit, list, status
    tacf/<node>/sessions/<sid>/box    BoxResult per processed frame
    tacf/<node>/sessions/<sid>/health Health about 1 Hz
    @tacf/<node>                      liveliness token of a service
    @tacf/<node>/<sid>                liveliness token of a live session

<node> and <sid> are ids: one key chunk of [A-Za-z0-9_-]{1,64}. Functions that build keys for *queries*
or *subscriptions* accept "*" in place of an id (e.g. control_key("*", "list") = tacf/*/control/list).
"""
from __future__ import annotations

import re

from .limits import MAX_IMAGE_KEY_CHUNKS, MAX_IMAGE_KEY_LENGTH
from .models import CONTROL_OPS, ID_PATTERN

PREFIX = "tacf"
LIVELINESS_PREFIX = "@tacf"
WILDCARD = "*"

# Matched with fullmatch: Python's `$` also matches before a final newline ('cam\n' passed, a session then
# waited for frames on a key no camera publishes), where pydantic's pattern does not.
_ID_RE = re.compile(ID_PATTERN)
# One chunk of a user image key: a conservative whitelist (no wildcards, no $, #, ?, @, whitespace).
_IMAGE_CHUNK_RE = re.compile(r"[A-Za-z0-9_.~+=,:-]+")


class InvalidIdError(ValueError):
    code = "invalid_id"


class InvalidKeyError(ValueError):
    code = "invalid_key"


def validate_id(value: object, what: str = "id") -> str:
    """Return `value` if it is a valid node or session id, else raise InvalidIdError."""
    if not isinstance(value, str) or not _ID_RE.fullmatch(value):
        raise InvalidIdError(f"invalid {what} {value!r}: expected 1-64 characters of [A-Za-z0-9_-]")
    return value


#: The node a client names to start a session on the least-loaded service, so the one id no service may take.
LEAST_LOADED = "auto"


def validate_node_id(value: object) -> str:
    """validate_id for the id a service takes, which also must not be LEAST_LOADED."""
    if validate_id(value, "node id") == LEAST_LOADED:
        raise InvalidIdError(f"node id {LEAST_LOADED!r} is reserved: clients start sessions 'on {LEAST_LOADED}' "
                             "to mean the least-loaded service")
    return value


def is_valid_id(value: object) -> bool:
    return isinstance(value, str) and bool(_ID_RE.fullmatch(value))


def sanitise_id(text: str, fallback: str = "edge") -> str:
    """Turn arbitrary text (a hostname) into a valid id: invalid characters become '-'."""
    cleaned = re.sub(r"[^A-Za-z0-9_-]", "-", text).strip("-")[:64]
    return cleaned if cleaned else fallback


def validate_image_key(key: object) -> str:
    """Return `key` if it is a plain (wildcard-free) Zenoh key a camera may publish Frames on.

    Rules (ZENOH.md section 5, plus a whitelist): 1-256 characters, 1-16 chunks separated by '/', no empty
    chunk and no leading/trailing '/', chunks of [A-Za-z0-9_.~+=,:-] only (so no '*', '$', '#', '?', '@',
    whitespace), no chunk that is `.` or `..` (a URL path resolves them away: the dashboard's /frame/<key> would
    show another camera), and not under the service's own `tacf/` prefix.
    """
    if not isinstance(key, str) or not key:
        raise InvalidKeyError(f"invalid image key {key!r}: empty or not a string")
    if len(key) > MAX_IMAGE_KEY_LENGTH:
        raise InvalidKeyError(f"invalid image key: longer than {MAX_IMAGE_KEY_LENGTH} characters")
    chunks = key.split("/")
    if len(chunks) > MAX_IMAGE_KEY_CHUNKS:
        raise InvalidKeyError(f"invalid image key {key!r}: more than {MAX_IMAGE_KEY_CHUNKS} chunks")
    for chunk in chunks:
        if not chunk:
            raise InvalidKeyError(f"invalid image key {key!r}: empty chunk (leading, trailing or double '/')")
        if not _IMAGE_CHUNK_RE.fullmatch(chunk):
            raise InvalidKeyError(f"invalid image key {key!r}: chunk {chunk!r} has a character outside "
                                  f"[A-Za-z0-9_.~+=,:-] (wildcards are not allowed)")
        if chunk in (".", ".."):
            raise InvalidKeyError(f"invalid image key {key!r}: a chunk {chunk!r} (URLs of the key would lose it)")
    if chunks[0] in (PREFIX, LIVELINESS_PREFIX):
        raise InvalidKeyError(f"invalid image key {key!r}: the {PREFIX}/ prefix is reserved for the service")
    return key


def _id_or_wildcard(value: str, what: str) -> str:
    return value if value == WILDCARD else validate_id(value, what)


def control_key(node: str, op: str) -> str:
    """tacf/<node>/control/<op>; node may be "*" (query every service), op may be "*" (declare)."""
    if op != WILDCARD and op not in CONTROL_OPS:
        raise ValueError(f"unknown control op {op!r}; expected one of {', '.join(CONTROL_OPS)}")
    return f"{PREFIX}/{_id_or_wildcard(node, 'node id')}/control/{op}"


def session_key(node: str, sid: str) -> str:
    """tacf/<node>/sessions/<sid>: the prefix of a session's box and health keys."""
    return f"{PREFIX}/{_id_or_wildcard(node, 'node id')}/sessions/{_id_or_wildcard(sid, 'session id')}"


def box_key(node: str, sid: str) -> str:
    """tacf/<node>/sessions/<sid>/box; either id may be "*" for subscribing."""
    return session_key(node, sid) + "/box"


def health_key(node: str, sid: str) -> str:
    """tacf/<node>/sessions/<sid>/health; either id may be "*" for subscribing."""
    return session_key(node, sid) + "/health"


def service_liveliness_key(node: str) -> str:
    """@tacf/<node>: the liveliness token of a running service."""
    return f"{LIVELINESS_PREFIX}/{_id_or_wildcard(node, 'node id')}"


def session_liveliness_key(node: str, sid: str) -> str:
    """@tacf/<node>/<sid>: the liveliness token of a live session."""
    return f"{service_liveliness_key(node)}/{_id_or_wildcard(sid, 'session id')}"


#: Subscribe or get on this to see every service and session token.
ALL_LIVELINESS = f"{LIVELINESS_PREFIX}/**"


def parse_control_key(key: str) -> tuple[str, str]:
    """(node, op) from a concrete control key; ValueError if it is not one."""
    parts = str(key).split("/")
    if len(parts) != 4 or parts[0] != PREFIX or parts[2] != "control" or parts[3] not in CONTROL_OPS:
        raise ValueError(f"not a control key: {key!r}")
    return validate_id(parts[1], "node id"), parts[3]


def parse_session_key(key: str) -> tuple[str, str, str]:
    """(node, sid, leaf) from tacf/<node>/sessions/<sid>/<leaf>; ValueError otherwise."""
    parts = str(key).split("/")
    if len(parts) != 5 or parts[0] != PREFIX or parts[2] != "sessions":
        raise ValueError(f"not a session key: {key!r}")
    return validate_id(parts[1], "node id"), validate_id(parts[3], "session id"), parts[4]


def parse_liveliness_key(key: str) -> tuple[str, str | None]:
    """(node, sid) from @tacf/<node>/<sid>, (node, None) from @tacf/<node>; ValueError otherwise."""
    parts = str(key).split("/")
    if len(parts) not in (2, 3) or parts[0] != LIVELINESS_PREFIX:
        raise ValueError(f"not a tacf liveliness key: {key!r}")
    node = validate_id(parts[1], "node id")
    return node, (validate_id(parts[2], "session id") if len(parts) == 3 else None)
