"""One tracker interface for everything evaluated, adapters, and the registry of tracker names.

Interface (got10k's shape): `init(frame_bgr, box)` with box = 0-based x,y,w,h floats, then
`update(frame_bgr) -> box` per frame. After `update`, `ok` (bool) and `pme` (float, NaN when the tracker
has no such measure) describe the last frame. A lost target keeps the last box; it never raises.

Names:
  tacf                  TACF with the default profile (TrackerConfig.profile())
  tacf-<profile>        TACF with a named profile: tacf-paper, tacf-authors, tacf-kcc
  kcc                   the ablation baseline (all three attentions off)
  kcc+sa, kcc+da+ca...  kcc with the named attentions on: sa = spatiotemporal, da = dimensional, ca = context
  <any of those>@field=value[@field=value...]   with TrackerConfig fields replaced (parameter studies):
                        kcc+ca@context_lambda2=16, tacf@lambda1=5e-5@fast_resize=false
  staple                Staple with its own parameters, the scaffolding of the paper's KCC baseline (tacf.staple)
  opencv-csrt, opencv-kcf, opencv-mosse, opencv-mil   OpenCV's trackers (opencv-contrib)
  identity              returns the first box every frame (smoke tests)
"""
from __future__ import annotations

import functools
import math
from typing import Protocol, runtime_checkable

Box = tuple[float, float, float, float]

ATTENTIONS = {"sa": "spatiotemporal_attention", "da": "dimensional_attention", "ca": "context_attention"}
OPENCV_TRACKERS = ("opencv-csrt", "opencv-kcf", "opencv-mosse", "opencv-mil")
# The attentions added to kcc one at a time, then all three: kcc carries the authors' values, so "all three" is
# the `authors` profile; then the default, `paper`, which also changes lambda1 and the attentions' own parameters.
ABLATION = ("kcc", "kcc+sa", "kcc+da", "kcc+ca", "tacf-authors", "tacf")


@runtime_checkable
class BoxTracker(Protocol):
    name: str
    ok: bool
    pme: float

    def init(self, frame, box: Box) -> None: ...

    def update(self, frame) -> Box: ...


class IdentityTracker:
    """Reports the initial box on every frame."""

    def __init__(self, name: str = "identity") -> None:
        self.name, self.ok, self.pme = name, True, math.nan
        self._box: Box | None = None

    def init(self, frame, box: Box) -> None:
        self._box = tuple(float(v) for v in box)

    def update(self, frame) -> Box:
        if self._box is None:
            raise RuntimeError("call init(frame, box) before update(frame)")
        return self._box


class LibraryAdapter:
    """A tracker of this library (tacf.Tracker, tacf.staple.Staple: update returns a TrackResult) behind the
    evaluation interface."""

    def __init__(self, name: str, tracker) -> None:
        self.name, self.ok, self.pme = name, True, math.nan
        self._tracker = tracker

    def init(self, frame, box: Box) -> None:
        self._tracker.init(frame, tuple(float(v) for v in box))
        self.ok, self.pme = True, math.nan

    def update(self, frame) -> Box:
        r = self._tracker.update(frame)
        self.ok, self.pme = bool(r.ok), float(r.pme)
        return tuple(float(v) for v in r.box)


def _opencv_factory(kind: str):
    """The constructor of OpenCV's tracker `kind`; ValueError if this OpenCV lacks it (of the four,
    opencv-python-headless has MIL only: CSRT, KCF and MOSSE are in the contrib modules)."""
    import cv2

    try:
        if kind == "csrt":
            return cv2.TrackerCSRT.create
        if kind == "kcf":
            return cv2.TrackerKCF.create
        if kind == "mil":
            return cv2.TrackerMIL.create
        if kind == "mosse":
            return cv2.legacy.TrackerMOSSE_create
    except AttributeError:
        raise ValueError(f"opencv-{kind} needs OpenCV's contrib modules, which this cv2 {cv2.__version__} lacks: "
                         "install opencv-contrib-python-headless in place of opencv-python-headless") from None
    raise ValueError(f"unknown OpenCV tracker {kind!r}")


def mil_features_fit(width: int, height: int) -> bool:
    """Whether OpenCV's MIL can start on a box of width x height pixels. Its init draws random Haar features in
    the box until each fits: two blocks side by side or stacked (or four, or 2x2) of at least 9 pixels together,
    short of the box's last row and column. Where none can (1xN, 2x10, 3x5, 4x4), init never returns."""
    return max(2 * ((height - 1) // 2) * (width - 1), 2 * ((width - 1) // 2) * (height - 1)) >= 9


class OpenCVAdapter:
    """An OpenCV tracker; recreated on every init (OpenCV ignores a second init), last box kept when lost."""

    def __init__(self, name: str, kind: str) -> None:
        self.name, self.ok, self.pme = name, True, math.nan
        self._create = _opencv_factory(kind)
        self._kind = kind
        self._legacy = kind == "mosse"
        self._tracker = None
        self._box: Box | None = None

    def init(self, frame, box: Box) -> None:
        import cv2

        x, y, w, h = (float(v) for v in box)
        rect = (x, y, w, h) if self._legacy else (round(x), round(y), max(1, round(w)), max(1, round(h)))
        if self._kind == "mil":
            if not mil_features_fit(rect[2], rect[3]):
                raise ValueError(f"opencv-mil cannot start on a {rect[2]}x{rect[3]} box: OpenCV's MIL would search "
                                 "for room for its features for ever")
            # MIL draws its Haar features with libc's rand(), whose state is the process's: seeded here, its boxes
            # no longer depend on what the process ran before (the pairs, --workers, the warm-up; person12_1's AUC
            # was 0.15, 0.38 or 0.56 by that alone)
            _libc().srand(0)
        tracker = self._create()
        try:
            tracker.init(frame, rect)
        except cv2.error as exc:    # a box across a border, or of a pixel or two: an assertion deep inside OpenCV
            reason = str(exc).strip().split("error: ", 1)[-1]   # its file and line are OpenCV's build, not ours
            raise ValueError(f"{self.name} cannot start on the box {(x, y, w, h)} in the {frame.shape[1]}x"
                             f"{frame.shape[0]} image (OpenCV: {reason})") from None
        self._tracker, self._box, self.ok = tracker, (x, y, w, h), True   # refused: the target followed is kept

    def update(self, frame) -> Box:
        if self._tracker is None:
            raise RuntimeError("call init(frame, box) before update(frame)")
        ok, rect = self._tracker.update(frame)
        self.ok = bool(ok)
        if ok:
            self._box = tuple(float(v) for v in rect)
        return self._box


@functools.lru_cache(maxsize=1)
def _libc():
    import ctypes
    import ctypes.util

    return ctypes.CDLL(ctypes.util.find_library("c") or ctypes.util.find_library("msvcrt"))


def tacf_config(name: str):
    """The TrackerConfig a TACF-family name stands for; ValueError for other names."""
    from tacf.config import TrackerConfig

    base, *settings = name.split("@")
    overrides = _overrides(settings, name)
    if base == "tacf":
        return TrackerConfig.profile(**overrides)
    if base.startswith("tacf-"):
        return TrackerConfig.profile(base[len("tacf-"):], **overrides)
    parts = base.split("+")
    if parts[0] != "kcc":
        raise ValueError(f"not a TACF tracker name: {name!r}")
    unknown = [p for p in parts[1:] if p not in ATTENTIONS]
    if unknown or len(set(parts[1:])) != len(parts[1:]):
        raise ValueError(f"bad module list in {name!r}: use kcc followed by +sa, +da, +ca (each once)")
    return TrackerConfig.profile("kcc", **{**{ATTENTIONS[p]: True for p in parts[1:]}, **overrides})


def _overrides(settings: list[str], name: str) -> dict:
    """'field=value' strings as TrackerConfig overrides, each value read as its field's type."""
    from tacf.config import parse_setting

    overrides = {}
    for setting in settings:
        try:
            field, value = parse_setting(setting)
        except ValueError as exc:
            raise ValueError(f"{exc} (in {name!r})") from None
        if field in overrides:
            raise ValueError(f"{field} set twice in {name!r}")
        overrides[field] = value
    return overrides


def check_name(name: str) -> str:
    """`name` if it is a known tracker name that this installation can run (without building the tracker), else
    ValueError."""
    if name in ("identity", "staple"):
        return name
    if name in OPENCV_TRACKERS:
        _opencv_factory(name.split("-", 1)[1])
        return name
    try:
        tacf_config(name)
    except ValueError as exc:
        raise ValueError(f"unknown tracker {name!r} ({exc}); known: tacf, tacf-<profile>, kcc[+sa][+da][+ca], "
                         "each optionally followed by @field=value settings, "
                         f"staple, {', '.join(OPENCV_TRACKERS)}, identity") from None
    return name


@functools.lru_cache(maxsize=None)
def settings_of(name: str) -> str:
    """What a result of tracker `name` depends on besides the frames, as a short digest: its configuration, every
    field of it (so that a setting added later and on by default, as the motion search was, changes it), and the
    tacf and OpenCV versions. `tacf eval` runs a pair recorded under other settings again instead of resuming it."""
    import dataclasses
    import hashlib
    import json

    import cv2

    import tacf

    if name == "staple":
        from tacf.staple import StapleConfig

        config = dataclasses.asdict(StapleConfig())
    else:
        try:
            config = dataclasses.asdict(tacf_config(name))
        except ValueError:                  # identity, OpenCV's: no settings of ours
            config = {}
    described = json.dumps({"tracker": name, "config": config, "tacf": tacf.__version__, "opencv": cv2.__version__},
                           sort_keys=True, default=str)
    return hashlib.sha256(described.encode()).hexdigest()[:16]


def make_tracker(name: str) -> BoxTracker:
    """A fresh tracker for a registry name."""
    if name == "identity":
        return IdentityTracker()
    if name in OPENCV_TRACKERS:
        return OpenCVAdapter(name, name.split("-", 1)[1])
    if name == "staple":
        from tacf.staple import Staple

        return LibraryAdapter(name, Staple())
    from tacf import Tracker

    return LibraryAdapter(name, Tracker(tacf_config(check_name(name))))
