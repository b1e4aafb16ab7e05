"""Clients of the TACF tracking service: ground-station API, onboard box consumer, frame publisher, demo, and the
service benchmark (`tacf bench service`, tacf_clients.bench).

    from tacf_clients import TrackingClient, BoxConsumer
    with TrackingClient() as client:                 # loopback defaults, like `tacf serve`
        info = client.start("uav1/camera/front", (410, 220, 60, 40))

Names are imported lazily: `import tacf_clients` loads neither Zenoh nor OpenCV, and nothing here ever imports
the tracker (tacf.tracker, tacf.features).
"""
from __future__ import annotations

import importlib

_LAZY = {
    "TrackingClient": "tacf_clients.client",
    "LEAST_LOADED": "tacf_clients.client",
    "BoxConsumer": "tacf_clients.consumer",
    "TrackedBox": "tacf_clients.consumer",
    "FramePublisher": "tacf_clients.publisher",
    "publish": "tacf_clients.publisher",
    "open_source": "tacf_clients.sources",
    "Scene": "tacf_clients.scene",
    "ZenohOptions": "tacf_clients.zconfig",
    "TacfError": "tacf_clients.errors",
    "ServiceError": "tacf_clients.errors",
    "RequestTimeout": "tacf_clients.errors",
    "NoService": "tacf_clients.errors",
    "UnknownSession": "tacf_clients.errors",
}
__all__ = sorted(_LAZY)


def __getattr__(name: str):
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'tacf_clients' has no attribute {name!r}")
