"""Pydantic models of every message on the wire. Each carries `v`, the schema version.

Boxes are [x, y, w, h]: 0-based float pixels, top-left origin. Times are nanoseconds since the Unix epoch
(`time.time_ns()`), so that ages can be computed across processes on synchronised hosts.

Models forbid unknown fields: a misspelt field is an `invalid_request` error, never silently ignored.
"""
from __future__ import annotations

import math
from typing import Annotated, Literal, Optional, Union

from pydantic import AfterValidator, BaseModel, ConfigDict, Field

from .limits import (MAX_FRAME_BYTES, MAX_FRAME_HEIGHT, MAX_FRAME_WIDTH, MAX_ID_LENGTH, MAX_IMAGE_KEY_LENGTH,
                     MAX_MESSAGE_LENGTH, MAX_OVERRIDES, SCHEMA_VERSION)

ID_PATTERN = r"^[A-Za-z0-9_-]{1,64}$"

Encoding = Literal["jpeg", "png", "bgr8", "mono8"]
ENCODINGS: tuple[str, ...] = ("jpeg", "png", "bgr8", "mono8")

SessionState = Literal["starting", "tracking", "lost", "stopped", "failed"]
SESSION_STATES: tuple[str, ...] = ("starting", "tracking", "lost", "stopped", "failed")

ControlOp = Literal["start", "stop", "reinit", "list", "status"]
CONTROL_OPS: tuple[str, ...] = ("start", "stop", "reinit", "list", "status")

ErrorCode = Literal[
    "invalid_request",     # malformed msgpack, wrong or missing fields, wrong version
    "invalid_id",          # a node or session id outside [A-Za-z0-9_-]{1,64}
    "invalid_key",         # an image key that is not a plain key expression
    "invalid_box",         # non-finite, non-positive size, or outside the image
    "invalid_config",      # unknown tracker profile or override
    "unknown_op",          # control op not in CONTROL_OPS
    "unknown_session",
    "duplicate_session",
    "too_many_sessions",
    "frame_rejected",      # the init frame could not be decoded
    "unavailable",         # the service is shutting down
    "internal",            # a bug: reported, never raised across the wire
]
ERROR_CODES: tuple[str, ...] = ErrorCode.__args__  # type: ignore[attr-defined]

Id = Annotated[str, Field(pattern=ID_PATTERN, min_length=1, max_length=MAX_ID_LENGTH)]
Seq = Annotated[int, Field(ge=0, lt=2**63)]
StampNs = Annotated[int, Field(ge=0, lt=2**63)]
FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
Count = Annotated[int, Field(ge=0)]


def _positive_size(box: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
    if not all(math.isfinite(c) for c in box):
        raise ValueError("box coordinates must be finite")
    if box[2] <= 0 or box[3] <= 0:
        raise ValueError("box width and height must be > 0")
    return box


#: [x, y, w, h], any finite values (a tracker's output).
Box = tuple[FiniteFloat, FiniteFloat, FiniteFloat, FiniteFloat]
#: [x, y, w, h] with w > 0 and h > 0 (a box a user asks for). Whether it lies inside the image is checked
#: against the init frame by the service.
InitBox = Annotated[Box, AfterValidator(_positive_size)]


class WireModel(BaseModel):
    """Base of every wire message: strict field set, schema version `v`."""
    model_config = ConfigDict(extra="forbid", frozen=True)

    v: Literal[1] = SCHEMA_VERSION


# ---------------------------------------------------------------- frames (camera -> service)

class Frame(WireModel):
    """One video frame on a user image key. `data` is the encoded image (jpeg/png) or raw pixels
    (bgr8: height*width*3 bytes, mono8: height*width bytes, row-major, no padding)."""
    seq: Seq
    stamp_ns: StampNs
    encoding: Encoding
    width: Annotated[int, Field(ge=1, le=MAX_FRAME_WIDTH)]
    height: Annotated[int, Field(ge=1, le=MAX_FRAME_HEIGHT)]
    data: Annotated[bytes, Field(max_length=MAX_FRAME_BYTES)]


# ---------------------------------------------------------------- control requests (client -> service)

class StartRequest(WireModel):
    """Start a session following the target in `box` on the feed `image_key`.

    `seq`: the frame the box was drawn on; the service initialises on that frame when it still holds it, else
    on the newest frame it has (SessionInfo.init_seq says which). `sid`: optional client-chosen session id;
    the service generates one when absent. `profile` / `overrides`: TrackerConfig.profile(profile, **overrides).
    """
    image_key: Annotated[str, Field(min_length=1, max_length=MAX_IMAGE_KEY_LENGTH)]
    box: InitBox
    seq: Optional[Seq] = None
    sid: Optional[Id] = None
    profile: Optional[Annotated[str, Field(max_length=32)]] = None
    overrides: Annotated[dict[str, Union[bool, int, float]], Field(max_length=MAX_OVERRIDES)] = {}


class StopRequest(WireModel):
    sid: Id


class ReinitRequest(WireModel):
    """Re-initialise a running session on a new box (e.g. the operator redraws it)."""
    sid: Id
    box: InitBox
    seq: Optional[Seq] = None


class ListRequest(WireModel):
    pass


class StatusRequest(WireModel):
    sid: Id


# ---------------------------------------------------------------- results (service -> clients)

class BoxResult(WireModel):
    """The tracker's output for one processed frame, on tacf/<node>/sessions/<sid>/box."""
    node: Id
    sid: Id
    seq: Seq                    # the frame's seq
    stamp_ns: StampNs           # the frame's stamp_ns (as published by the camera)
    box: Box
    width: Annotated[int, Field(ge=1, le=MAX_FRAME_WIDTH)]    # the frame's size, so that consumers can
    height: Annotated[int, Field(ge=1, le=MAX_FRAME_HEIGHT)]  # normalise the box without knowing the camera
    ok: bool                    # False: the target is lost (PME under the tracker's threshold)
    pme: FiniteFloat
    score: FiniteFloat
    scale: FiniteFloat
    processing_ms: FiniteFloat  # decode + locating the target: until this box (the model update comes after)
    published_ns: StampNs       # when the service published this result


class Health(WireModel):
    """About once a second per session, on tacf/<node>/sessions/<sid>/health."""
    node: Id
    sid: Id
    state: SessionState
    stamp_ns: StampNs
    fps: FiniteFloat                         # processed frames per second over the last window
    processing_ms_mean: FiniteFloat          # per frame: decode, locate and learn (the box is sent before learning)
    processing_ms_p95: FiniteFloat
    frame_age_ms: Optional[FiniteFloat] = None   # now - stamp_ns of the last processed frame
    frames_received: Count = 0
    frames_processed: Count = 0
    frames_dropped: Count = 0                # superseded by a newer frame before being processed (latest-only)
    frames_rejected: Count = 0               # undecodable, wrong size, wrong fields
    frames_lost: Count = 0                   # processed with the target flagged lost (BoxResult.ok False)
    pme: Optional[FiniteFloat] = None
    last_seq: Optional[Seq] = None
    restarts: Count = 0                      # worker restarts after a crash
    message: Optional[Annotated[str, Field(max_length=MAX_MESSAGE_LENGTH)]] = None


class SessionInfo(WireModel):
    """One session as the service sees it: the reply to start, stop, reinit and status."""
    node: Id
    sid: Id
    image_key: str
    profile: str
    overrides: dict[str, Union[bool, int, float]] = {}
    state: SessionState
    box: Box                                 # the last box (the initial box until the first result)
    init_seq: Optional[Seq] = None           # the frame the tracker was (last) initialised on, when known
    last_seq: Optional[Seq] = None
    created_ns: StampNs
    restarts: Count = 0
    health: Optional[Health] = None          # the latest health report, when there is one


class SessionList(WireModel):
    """The reply to list: every session of one service (a wildcard query gets one SessionList per node)."""
    node: Id
    max_sessions: Count
    sessions: list[SessionInfo] = []


class Error(WireModel):
    """Every failed control op replies with reply_err(Error)."""
    code: ErrorCode
    message: Annotated[str, Field(max_length=MAX_MESSAGE_LENGTH)]
    node: Optional[Id] = None


#: Every wire model, by name: the JSON Schema export and the drift test iterate over this.
MODELS: dict[str, type[WireModel]] = {m.__name__: m for m in (
    Frame, StartRequest, StopRequest, ReinitRequest, ListRequest, StatusRequest,
    BoxResult, Health, SessionInfo, SessionList, Error,
)}

#: The request model and reply model of each control op.
CONTROL_REQUESTS: dict[str, type[WireModel]] = {
    "start": StartRequest, "stop": StopRequest, "reinit": ReinitRequest, "list": ListRequest,
    "status": StatusRequest,
}
CONTROL_REPLIES: dict[str, type[WireModel]] = {
    "start": SessionInfo, "stop": SessionInfo, "reinit": SessionInfo, "list": SessionList,
    "status": SessionInfo,
}
