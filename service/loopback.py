"""Loopback Zenoh helpers for tests: peer configs, a frame publisher, result collectors (the benchmark and the demo
use tacf_clients' own).

    endpoint = "tcp/127.0.0.1:7447"  # tests take a free port from tacf_clients.local_service.free_port()
    session = zenoh.open(peer_config(connect=[endpoint]))
    with FramePublisher(session, "cam/a", MovingTargetScene(640, 360), fps=10) as feed:
        ...  feed.truth[seq] is the target's box on frame seq
"""
from __future__ import annotations

import json
import logging
import threading
import time

from tacf_schemas import BoxResult, Health, box_key, decode, encode, health_key

log = logging.getLogger(__name__)


def peer_config(listen=(), connect=(), mode: str = "peer"):
    """Loopback-only config: explicit endpoints, multicast scouting off."""
    import zenoh
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    return conf


class FramePublisher:
    """Publishes a scene as Frames on a key at a fixed rate from a thread; remembers each frame's true box.

    With DROP, a camera's congestion control (the default), a loaded machine may lose a frame on the way; lossless
    (BLOCK) is for a test that counts every frame sent."""

    def __init__(self, session, key: str, scene, fps: float = 10.0, encoding: str = "jpeg", quality: int = 85,
                 cache: int = 0, lossless: bool = False) -> None:
        self.key, self.scene, self.fps, self.encoding, self.quality = key, scene, fps, encoding, quality
        self.lossless = lossless
        self.truth: dict[int, tuple] = {}
        self.seq = -1
        self._session = session
        self._publisher = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"publish-{key}", daemon=True)
        self._cache = [self._encode(i) for i in range(cache)]   # pre-encoded frames (loop) for fast rates

    def __enter__(self) -> "FramePublisher":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def start(self) -> "FramePublisher":
        import zenoh
        congestion = zenoh.CongestionControl.BLOCK if self.lossless else zenoh.CongestionControl.DROP
        self._publisher = self._session.declare_publisher(self.key, congestion_control=congestion)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        if self._publisher is not None:
            try:
                self._publisher.undeclare()
            except Exception:
                pass

    def _encode(self, i: int):
        from tacf_schemas.images import encode_frame
        image, box = self.scene.frame(i)
        return encode_frame(image, i, self.encoding, quality=self.quality), box

    def _run(self) -> None:
        period = 1.0 / self.fps
        next_at = time.monotonic()
        i = 0
        while not self._stop.is_set():
            if self._cache:
                frame, box = self._cache[i % len(self._cache)]
                frame = frame.model_copy(update={"seq": i})
            else:
                frame, box = self._encode(i)
            frame = frame.model_copy(update={"stamp_ns": time.time_ns()})
            self.truth[i] = box
            try:
                self._publisher.put(encode(frame))
            except Exception as exc:
                log.debug("put failed: %s", exc)
                return
            self.seq = i
            i += 1
            next_at += period
            delay = next_at - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)
            else:
                next_at = time.monotonic()


def wait_until(predicate, timeout: float, period: float = 0.05):
    """Poll `predicate` until it returns something truthy or `timeout` s pass; return its last value."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(period)
    return predicate()


class SessionResults:
    """Subscribes to one session's boxes and health; keeps them (boxes with their arrival time, ns)."""

    def __init__(self, session, node: str, sid: str) -> None:
        self.boxes: list[tuple[int, BoxResult]] = []
        self.health: list[Health] = []
        self._lock = threading.Lock()
        self._subs = [session.declare_subscriber(box_key(node, sid), self._on_box),
                      session.declare_subscriber(health_key(node, sid), self._on_health)]

    def _on_box(self, sample) -> None:
        result = decode(sample.payload.to_bytes(), BoxResult)
        with self._lock:
            self.boxes.append((time.time_ns(), result))

    def _on_health(self, sample) -> None:
        health = decode(sample.payload.to_bytes(), Health)
        with self._lock:
            self.health.append(health)

    def results(self) -> list[BoxResult]:
        with self._lock:
            return [b for _, b in self.boxes]

    def timed_results(self) -> list[tuple[int, BoxResult]]:
        with self._lock:
            return list(self.boxes)

    def last_health(self) -> Health | None:
        with self._lock:
            return self.health[-1] if self.health else None

    def close(self) -> None:
        for sub in self._subs:
            try:
                sub.undeclare()
            except Exception:
                pass
