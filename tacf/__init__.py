"""TACF: tri-attentional correlation filters for UAV tracking (He, Fu, Lin, Li, Lu; IROS 2020).

    from tacf import Tracker, TrackerConfig
    trk = Tracker(TrackerConfig.profile("paper"))   # the default profile
    trk.init(frame_bgr, (x, y, w, h))
    result = trk.update(frame_bgr)      # TrackResult(box, pme, score, ok, scale)

Names are imported lazily so that `tacf.cli` and the client side never pay for numpy/OpenCV they do not use.
"""
from __future__ import annotations

import importlib

__version__ = "0.1.0"

_LAZY = {
    "Tracker": "tacf.tracker",
    "TrackResult": "tacf.tracker",
    "TrackerConfig": "tacf.config",
}
__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'tacf' has no attribute {name!r}")
