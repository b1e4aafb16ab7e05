"""Tracker factories used by worker processes. A factory is named "module:function" so that it can cross
the spawn boundary as a string; it takes (profile, overrides) and returns an object with
init(frame, box) and update(frame) -> result with .box, .ok, .pme, .score, .scale (tacf.Tracker). If it also has
locate(frame) -> result and learn() (tacf.Tracker does), the worker sends the box between the two."""
from __future__ import annotations

import importlib
from typing import Callable

DEFAULT_FACTORY = "tacf_service.trackers:tacf_tracker"


def tacf_tracker(profile: str, overrides: dict):
    from tacf import Tracker, TrackerConfig
    return Tracker(TrackerConfig.profile(profile, **overrides))


def checked_overrides(profile: str, overrides: dict) -> dict:
    """The overrides as TrackerConfig takes them: a float without a fraction given for an int field is that int
    (msgpack from JavaScript sends every number as a float, as the wire protocol allows). Raises ValueError if
    TrackerConfig rejects the profile or an override (tacf.config is light)."""
    import dataclasses

    from tacf.config import TrackerConfig
    int_fields = {f.name for f in dataclasses.fields(TrackerConfig) if f.type == "int"}
    overrides = {name: int(value) if name in int_fields and isinstance(value, float) and value.is_integer()
                 else value for name, value in overrides.items()}
    TrackerConfig.profile(profile, **overrides)
    return overrides


def default_profile() -> str:
    from tacf.config import DEFAULT_PROFILE
    return DEFAULT_PROFILE


def preload(factory: str) -> None:
    """Import the factory's module and, for TACF, compile the tracker's loops, before any assignment (done already
    in a worker forked from the fork server, tacf_service.warm; not in a worker spawned afresh)."""
    module = factory.partition(":")[0]
    importlib.import_module(module)
    if factory == DEFAULT_FACTORY:
        importlib.import_module("tacf.tracker").compile_loops()


def load_factory(path: str) -> Callable:
    module, _, name = path.partition(":")
    return getattr(importlib.import_module(module), name)
