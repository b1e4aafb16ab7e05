"""A minimal control caller (used by tests). The full client API is tacf_clients.

    reply = call(session, "edge", "start", StartRequest(image_key="cam", box=(10, 10, 40, 40)))
    # -> SessionInfo, or raises ControlError(code, message)
"""
from __future__ import annotations

from tacf_schemas import (CONTROL_REPLIES, MSGPACK_ENCODING, Error, ListRequest, WireModel, control_key, decode,
                          decode_error_reply, encode, is_deadline_reply)


class ControlError(Exception):
    def __init__(self, code: str, message: str):
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message


def call(session, node: str, op: str, request: WireModel | bytes | None = None, timeout: float = 5.0):
    """One control request to one node; the reply model, or ControlError: code "no_service" when no queryable
    matched (Zenoh ends such a get at once with no reply), "timeout" when one matched but did not answer in time."""
    import zenoh
    payload = encode(request) if isinstance(request, WireModel) else request
    replies = session.get(control_key(node, op), payload=payload, encoding=zenoh.Encoding(MSGPACK_ENCODING),
                          timeout=timeout)
    for reply in replies:
        return _reply_model(op, reply)
    raise ControlError("no_service", f"no service {node!r} is reachable (nothing serves {control_key(node, op)})")


def list_all(session, timeout: float = 3.0) -> list:
    """tacf/*/control/list: one SessionList per reachable service."""
    import zenoh
    replies = session.get(control_key("*", "list"), payload=encode(ListRequest()),
                          encoding=zenoh.Encoding(MSGPACK_ENCODING), timeout=timeout)
    return [_reply_model("list", r) for r in replies if r.ok is not None]


def _reply_model(op: str, reply):
    if reply.ok is not None:
        return decode(reply.ok.payload.to_bytes(), CONTROL_REPLIES[op])
    error = decode_error_reply(reply.err.payload.to_bytes())
    if isinstance(error, Error):
        raise ControlError(error.code, error.message)
    if is_deadline_reply(error):
        raise ControlError("timeout", f"no reply to {op} in time")
    raise ControlError("transport", error[:200])
