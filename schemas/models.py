"""Pydantic models of every message on the wire. Each carries `v`, the schema version.

Boxes are [x, y, w, h]: 0-based float pixels, top-left origin. Times are nanoseconds since the Unix epoch
(`time.time_ns()`), so that ages can be computed across processes on synchronised hosts.

Models forbid unknown fields: a misspelt field is an `invalid_request` error, never silently ignored. A message
received is validated by `WireModel.from_wire`, as strictly as its JSON Schema (schemas/json) states it.
"""
from __future__ import annotations

from bisect import bisect_left
from collections.abc import Callable
from operator import attrgetter
from typing import TYPE_CHECKING, Annotated, Literal, Optional, Union

from pydantic import (BaseModel, BeforeValidator, ConfigDict, Field, StrictBool, StrictFloat, StrictInt, TypeAdapter,
                      model_validator)

from .limits import (MAX_CARRIED_FRAMES, MAX_FRAME_BYTES, MAX_FRAME_HEIGHT, MAX_FRAME_PIXELS, MAX_FRAME_WIDTH,
                     MAX_ID_LENGTH, MAX_IMAGE_KEY_LENGTH, MAX_MESSAGE_LENGTH, MAX_OVERRIDES, SCHEMA_VERSION)

if TYPE_CHECKING:
    from typing_extensions import Self      # typing.Self from Python 3.11; only an annotation here

ID_PATTERN = r"^[A-Za-z0-9_-]{1,64}$"

Encoding = Literal["jpeg", "png", "bgr8", "mono8"]
ENCODINGS: tuple[str, ...] = ("jpeg", "png", "bgr8", "mono8")

SessionState = Literal["starting", "tracking", "lost", "stopped", "failed"]
SESSION_STATES: tuple[str, ...] = ("starting", "tracking", "lost", "stopped", "failed")

ControlOp = Literal["start", "stop", "reinit", "list", "status"]
CONTROL_OPS: tuple[str, ...] = ("start", "stop", "reinit", "list", "status")

ErrorCode = Literal[
    "invalid_request",     # malformed msgpack, wrong or missing fields, wrong version
    "invalid_id",          # a node or session id outside [A-Za-z0-9_-]{1,64} (clients; the service: invalid_request)
    "invalid_key",         # an image key that is not a plain key expression
    "invalid_box",         # outside the init frame, larger than it, or under a pixel (NaN, w <= 0: invalid_request)
    "invalid_config",      # unknown tracker profile or override, or a value TrackerConfig refuses
    "unknown_op",          # control op not in CONTROL_OPS
    "unknown_session",
    "duplicate_session",
    "too_many_sessions",
    "frame_rejected",      # a frame the start or reinit carries is not an image of its stated size (header checks)
    "unavailable",         # shutting down, busy (too many control queries waiting), no worker process to be had: retry
    "internal",            # a bug: reported, never raised across the wire
]
ERROR_CODES: tuple[str, ...] = ErrorCode.__args__  # type: ignore[attr-defined]


def _wire_number(value: object) -> object:
    """A number as it arrives: msgpack from JavaScript carries every number as a float, so an integral float is
    the int it stands for (as JSON Schema's "integer" takes 5.0); a boolean is no number (as in JSON Schema)."""
    if isinstance(value, bool):
        raise ValueError("a boolean is not a number")
    if isinstance(value, float) and value.is_integer():
        return int(value)
    return value


def _wire_array(value: object) -> object:
    """msgpack and JSON have arrays, not tuples: a box arrives as a list."""
    return tuple(value) if isinstance(value, list) else value


#: Applied outside an int's constraints (after the Field), so that the JSON Schema keeps them.
WIRE_INT = BeforeValidator(_wire_number)

Id = Annotated[str, Field(pattern=ID_PATTERN, min_length=1, max_length=MAX_ID_LENGTH)]
Seq = Annotated[int, Field(ge=0, lt=2**63), WIRE_INT]
StampNs = Annotated[int, Field(ge=0, lt=2**63), WIRE_INT]
# int64, as seqs: unbounded, an integral float such as 1e300 was taken as a 301-digit int that msgpack cannot
# encode again (nor most languages hold)
Count = Annotated[int, Field(ge=0, lt=2**63), WIRE_INT]
Width = Annotated[int, Field(ge=1, le=MAX_FRAME_WIDTH), WIRE_INT]
Height = Annotated[int, Field(ge=1, le=MAX_FRAME_HEIGHT), WIRE_INT]
FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
PositiveFloat = Annotated[float, Field(gt=0, allow_inf_nan=False)]
#: A seq alone, validated as WireModel.from_wire does within a message (the worker peeks at a frame's seq).
SEQ = TypeAdapter(Seq)
#: A tracker config override (TrackerConfig.profile(profile, **overrides)): strict even where a Python caller
#: builds the message, so that "0.5" or "true" typed into a form is refused, not sent as a number. Ints within
#: int64, as msgpack carries them (a larger one raised OverflowError in encode); past it, as the JSON Schema's
#: "number", an int is a float, which the service refuses for an int field (invalid_config).
Override = Union[StrictBool, Annotated[StrictInt, Field(ge=-2**63, lt=2**63)], StrictFloat]

#: [x, y, w, h], any finite values (a tracker's output).
Box = Annotated[tuple[FiniteFloat, FiniteFloat, FiniteFloat, FiniteFloat], BeforeValidator(_wire_array)]
#: [x, y, w, h] with w > 0 and h > 0 (a box a user asks for). Whether it lies inside the image is checked
#: against the init frame by the service.
InitBox = Annotated[tuple[FiniteFloat, FiniteFloat, PositiveFloat, PositiveFloat], BeforeValidator(_wire_array)]


class WireModel(BaseModel):
    """Base of every wire message: strict field set, schema version `v`."""
    model_config = ConfigDict(extra="forbid", frozen=True)

    v: Annotated[Literal[1], WIRE_INT] = SCHEMA_VERSION

    @classmethod
    def from_wire(cls, obj: object) -> Self:
        """A message received (msgpack or JSON decoded), validated as its JSON Schema states it: pydantic's strict
        mode (no "5" for a number, no true for an int, no text for a bool), with integral floats as ints
        (_wire_number). Raises pydantic.ValidationError. Python code building a message uses the constructor."""
        return cls.model_validate(obj, strict=True)


# ---------------------------------------------------------------- frames (camera -> service)

_FRAME_PIXELS = (f"Pixels; width * height must not exceed {MAX_FRAME_PIXELS} ({MAX_FRAME_PIXELS / 1e6:.1f} Mpx): "
                 f"the service rejects a larger frame (Health.frames_rejected).")


class Frame(WireModel):
    """One video frame on a user image key. `data` is the encoded image (jpeg/png) or raw pixels
    (bgr8: height*width*3 bytes, mono8: height*width bytes, row-major, no padding)."""
    seq: Seq
    stamp_ns: StampNs
    encoding: Encoding
    # The pixel limit is the service's (a product of two fields, which JSON Schema cannot check): stated here so
    # that publishers find it in schemas/json/Frame.json.
    width: Annotated[Width, Field(description=_FRAME_PIXELS)]
    height: Annotated[Height, Field(description=_FRAME_PIXELS)]
    data: Annotated[bytes, Field(max_length=MAX_FRAME_BYTES)]


# ---------------------------------------------------------------- control requests (client -> service)

class _InitOnFrame(WireModel):
    """A box drawn on a frame. `seq` names the frame; `frames` may carry it (first), then newer frames, oldest
    first, for the tracker to catch up through. A service keeps the last few frames of a feed only while a
    session follows it, so the first session on a feed never had the frame its box was drawn on, and an
    operator drawing for a few seconds outlasts the frames kept. The service initialises on frame `seq` if it
    holds it, else on the carried frames, else on the nearest frame it holds after `seq`, else (none after it,
    or no `seq`) on the newest (SessionInfo.init_seq says which), then catches up through the newer frames it
    holds."""
    box: InitBox
    seq: Optional[Seq] = None
    frames: Annotated[list[Frame], Field(max_length=MAX_CARRIED_FRAMES)] = []

    @model_validator(mode="after")
    def _frames_start_at_seq(self):
        seqs = [f.seq for f in self.frames]
        if seqs and self.seq is not None and seqs[0] != self.seq:
            raise ValueError(f"the first frame carried is seq {seqs[0]}, not seq {self.seq}")
        if any(newer <= older for older, newer in zip(seqs, seqs[1:])):
            raise ValueError(f"the frames carried are not in increasing seq order: {seqs}")
        return self

    @property
    def drawn_on(self) -> Optional[int]:
        """The seq of the frame the box was drawn on (`seq`, or the first carried frame's)."""
        return self.frames[0].seq if self.frames else self.seq


def catch_up_subset(frames: list, limit: int, seq: Callable[[object], int] = attrgetter("seq")) -> list:
    """The first frame (the one a box was drawn on), then at most `limit` newer ones evenly spaced in seq, ending
    on the newest: a tracker initialised on the first follows the target's motion through them without falling
    far behind a live feed. (What a client carries with a start, and what the service sends its worker.)

    Spaced by seq, not by place in the list: the list may have gaps (a client holds the frame it showed, then only
    its last frames; the service appends live frames to carried ones), and spacing by place made the steps after
    a gap as large as the gap. Frames whose seq goes back (a camera restarted) are spaced by place."""
    if limit <= 0:
        return list(frames[:1])
    if len(frames) <= limit + 1:
        return list(frames)
    at = [seq(f) for f in frames]
    if any(later <= earlier for earlier, later in zip(at, at[1:])):
        at = list(range(len(frames)))
    picked = [0]
    for i in range(1, limit + 1):
        target = at[0] + (at[-1] - at[0]) * i / limit
        # the frame nearest `target` after the last pick, leaving one frame for each pick still to come
        lo, hi = picked[-1] + 1, len(frames) - 1 - (limit - i)
        j = min(max(bisect_left(at, target), lo), hi)
        if j > lo and target - at[j - 1] < at[j] - target:
            j -= 1
        picked.append(j)
    return [frames[j] for j in picked]


class StartRequest(_InitOnFrame):
    """Start a session following the target in `box` on the feed `image_key`, drawn on frame `seq` (see
    _InitOnFrame for `seq` and `frames`). `sid`: optional client-chosen session id; the service generates one when
    absent. `profile` / `overrides`: TrackerConfig.profile(profile, **overrides).
    """
    image_key: Annotated[str, Field(min_length=1, max_length=MAX_IMAGE_KEY_LENGTH)]
    sid: Optional[Id] = None
    profile: Optional[Annotated[str, Field(max_length=32)]] = None
    overrides: Annotated[dict[str, Override], Field(max_length=MAX_OVERRIDES)] = {}


class StopRequest(WireModel):
    sid: Id


class ReinitRequest(_InitOnFrame):
    """Re-initialise a running session on a new box (e.g. the operator redraws it), drawn on frame `seq`."""
    sid: Id


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
    width: Width                # the frame's size, so that consumers can
    height: Height              # normalise the box without knowing the camera
    ok: bool                    # False: the target is lost (PME under the tracker's floor, or the box left the frame)
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
    # The counters are over the session's life: a restarted worker's go on from the last Health of the one before.
    frames_received: Count = 0               # = processed + dropped + rejected; catch-up frames and seq gaps included
    frames_processed: Count = 0
    frames_dropped: Count = 0                # not processed: superseded (latest-only, seq gaps), duplicate or older,
                                             # before the init or as a stop came, or while the session had no worker
    frames_rejected: Count = 0               # undecodable, wrong size, wrong fields; or the tracker could not use it:
                                             # the init box does not fit it, its update failed, a new aspect ratio
    frames_lost: Count = 0                   # processed with the target flagged lost (BoxResult.ok False)
    pme: Optional[FiniteFloat] = None
    last_seq: Optional[Seq] = None
    restarts: Count = 0                      # worker restarts after a crash or a hang
    # why the session failed or waits; a rejected frame's reason or a size change's, for worker.NOTICE_HOLD_S
    message: Optional[Annotated[str, Field(max_length=MAX_MESSAGE_LENGTH)]] = None


class SessionInfo(WireModel):
    """One session as the service sees it: the reply to start, stop, reinit and status."""
    node: Id
    sid: Id
    image_key: str
    profile: str
    overrides: dict[str, Override] = {}
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
