"""Typed exceptions for the client API: every wire `Error.code` maps to one class (ERRORS), plus timeouts and
"nobody answered". Requests that fail validation on the client raise the same classes as the service would.
An unknown code (from a newer service) becomes a plain ServiceError; a test keeps ERRORS in sync with
tacf_schemas' ErrorCode.
"""
from __future__ import annotations

from contextlib import contextmanager


class TacfError(Exception):
    """Base of every client-side error. `code` is the wire error code (or a client-side one)."""

    code = "error"

    def __init__(self, message: str, node: str | None = None):
        super().__init__(message)
        self.message, self.node = message, node

    def __str__(self) -> str:
        # the service's own messages mostly name their node already ("no session 'x' on node 'edge'")
        if not self.node or repr(self.node) in self.message:
            return self.message
        return f"{self.message} (node {self.node})"


# ------------------------------------------------------------------ errors replied by a service

class ServiceError(TacfError):
    """A service replied with an Error."""

    code = "internal"


class InvalidRequest(ServiceError, ValueError):
    code = "invalid_request"


class InvalidId(InvalidRequest):
    code = "invalid_id"


class InvalidKey(InvalidRequest):
    code = "invalid_key"


class InvalidBox(InvalidRequest):
    code = "invalid_box"


class InvalidConfig(InvalidRequest):
    code = "invalid_config"


class UnknownOp(InvalidRequest):
    code = "unknown_op"


class UnknownSession(ServiceError, LookupError):
    code = "unknown_session"


class DuplicateSession(ServiceError):
    code = "duplicate_session"


class TooManySessions(ServiceError):
    code = "too_many_sessions"


class FrameRejected(ServiceError):
    code = "frame_rejected"


class ServiceUnavailable(ServiceError):
    code = "unavailable"


class InternalServiceError(ServiceError):
    code = "internal"


ERRORS: dict[str, type[ServiceError]] = {cls.code: cls for cls in (
    InvalidRequest, InvalidId, InvalidKey, InvalidBox, InvalidConfig, UnknownOp, UnknownSession,
    DuplicateSession, TooManySessions, FrameRejected, ServiceUnavailable, InternalServiceError,
)}


def error_from_wire(code: str, message: str, node: str | None = None) -> ServiceError:
    error = ERRORS.get(code, ServiceError)(message, node)
    error.code = code       # a newer service's code, which no class here names, not ServiceError's "internal"
    return error


# ------------------------------------------------------------------ errors found by the client

class RequestTimeout(TacfError, TimeoutError):
    """A service matched the query but did not answer in time."""

    code = "timeout"


class NoService(TacfError):
    """No tracking service answered (none running, or not reachable with these Zenoh options)."""

    code = "no_service"


class ZenohUnavailable(TacfError):
    """The Zenoh session could not open: as a Zenoh client, no node is reachable at the connect endpoints."""

    code = "zenoh_unavailable"


class ZenohSettingsError(ZenohUnavailable):
    """Zenoh refused its settings: a malformed endpoint, a config file missing or malformed, a listen endpoint
    taken. An error of the command line (or the caller), not of the network."""

    code = "zenoh_settings"


class ClientClosed(TacfError):
    """A call on a TrackingClient after its close() (or after the Zenoh session it was given closed), a BoxConsumer
    given a closed session."""

    code = "closed"


class AmbiguousNode(TacfError):
    """Several services are on the network and the call does not say which one: pass node=... (--node)."""

    code = "ambiguous_node"


class AmbiguousSession(TacfError):
    """The session id exists on several services: pass node=... (--node) to say which."""

    code = "ambiguous_session"


class ProtocolError(TacfError):
    """A reply that is not a valid message of the expected model."""

    code = "protocol"


@contextmanager
def as_invalid_id():
    """tacf_schemas.keys refuses a bad node or session id with InvalidIdError: raise InvalidId, as a service would."""
    from tacf_schemas.keys import InvalidIdError

    try:
        yield
    except InvalidIdError as exc:
        raise InvalidId(str(exc)) from None
