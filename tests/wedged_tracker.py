"""A tracker factory whose module never finishes loading (`tracker_factory="wedged_tracker:wedged_tracker"`): a
worker preloads the factory's module first thing, so each of its workers wedges before it says it is warm."""
from __future__ import annotations

import threading

threading.Event().wait()


def wedged_tracker(profile: str, overrides: dict):
    raise AssertionError("never reached: the module does not finish loading")
