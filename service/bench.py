"""Service benchmark: processing and end-to-end latency, drops and memory for N concurrent feeds.

    python -m tacf_service.bench --feeds 1 4 --seconds 15            # JSON on stdout

Runs a TrackingService in-process on a free loopback port, publishes N synthetic 1280x720 JPEG feeds at
--fps from a separate Zenoh session (frames pre-encoded so that the publisher costs little CPU), starts one
session per feed once warm workers are ready, discards a warm-up, then measures for --seconds:
processing ms per frame (worker: decode + tracker), end-to-end ms (frame put -> BoxResult received, same
clock), frames dropped / processed (Health), and the RSS of each worker process and of the service.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import statistics
import sys
import threading
import time

log = logging.getLogger("tacf_service.bench")


def _percentile(values: list[float], q: float) -> float | None:
    if not values:
        return None
    ordered = sorted(values)
    return round(ordered[min(len(ordered) - 1, int(q * len(ordered)))], 2)


def _rss_mb(pid: int) -> float | None:
    try:
        for line in open(f"/proc/{pid}/status"):
            if line.startswith("VmRSS:"):
                return round(int(line.split()[1]) / 1024, 1)
    except OSError:
        return None
    return None


def _pss_mb(pid: int) -> float | None:
    """Proportional set size: shared library pages divided among the processes that map them."""
    try:
        for line in open(f"/proc/{pid}/smaps_rollup"):
            if line.startswith("Pss:"):
                return round(int(line.split()[1]) / 1024, 1)
    except OSError:
        return None
    return None


def run_config(feeds: int, seconds: float, width: int, height: int, fps: float, profile: str,
               warmup: float = 3.0) -> dict:
    import zenoh

    from tacf_schemas import BoxResult, Health, StartRequest, StopRequest, box_key, decode, health_key

    from .app import ServiceOptions, TrackingService
    from .config import ZenohOptions
    from .loopback import FramePublisher, free_port, peer_config
    from .probe import call
    from .scene import MovingTargetScene

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    options = ServiceOptions(node="bench", zenoh=ZenohOptions(listen=(endpoint,)), max_sessions=feeds,
                             spare_workers=feeds, log_level=logging.WARNING)
    service = TrackingService(options).open()
    client = zenoh.open(peer_config(connect=[endpoint]))
    lock = threading.Lock()
    received: list[tuple[int, BoxResult]] = []
    health: dict[str, Health] = {}
    measuring = threading.Event()

    def on_box(sample) -> None:
        now = time.time_ns()
        if measuring.is_set():
            with lock:
                received.append((now, decode(sample.payload.to_bytes(), BoxResult)))

    def on_health(sample) -> None:
        h = decode(sample.payload.to_bytes(), Health)
        with lock:
            health[h.sid] = h

    subs = [client.declare_subscriber(box_key("bench", "*"), on_box),
            client.declare_subscriber(health_key("bench", "*"), on_health)]
    publishers = []
    try:
        deadline = time.monotonic() + 120
        while service.manager.idle_spares() < feeds and time.monotonic() < deadline:
            time.sleep(0.2)
        for i in range(feeds):
            scene = MovingTargetScene(width, height, target=96, speed=2.0, seed=i)
            publisher = FramePublisher(client, f"bench/cam{i}", scene, fps=fps, cache=int(fps * 20)).start()
            publishers.append(publisher)
        time.sleep(1.0)
        for i, publisher in enumerate(publishers):
            call(client, "bench", "start", StartRequest(image_key=publisher.key, box=publisher.truth[publisher.seq],
                                                        seq=publisher.seq, sid=f"feed{i}", profile=profile),
                 timeout=10)
        time.sleep(warmup)
        with lock:
            before = {sid: h.model_copy() for sid, h in health.items()}
        first_seq = {f"feed{i}": publisher.seq + 1 for i, publisher in enumerate(publishers)}
        measuring.set()
        time.sleep(seconds)
        measuring.clear()
        time.sleep(1.2)                  # one more health report
        with lock:      # only frames published inside the window (no catch-up of older frames)
            results = [(t, r) for t, r in received if r.seq >= first_seq[r.sid]]
            after = dict(health)
        rss_workers = {sid: _rss_mb(pid) for sid, pid in service.manager.worker_pids().items()}
        pss_workers = {sid: _pss_mb(pid) for sid, pid in service.manager.worker_pids().items()}
        rss_service = _rss_mb(os.getpid())
        for i in range(feeds):
            call(client, "bench", "stop", StopRequest(sid=f"feed{i}"), timeout=5)
    finally:
        for publisher in publishers:
            publisher.stop()
        for sub in subs:
            sub.undeclare()
        client.close()
        service.close()

    processing = [r.processing_ms for _, r in results]
    end_to_end = [(t - r.stamp_ns) / 1e6 for t, r in results]
    to_publish = [(r.published_ns - r.stamp_ns) / 1e6 for _, r in results]     # frame put -> box put
    delivery = [(t - r.published_ns) / 1e6 for t, r in results]                 # box put -> box received
    waiting = [a - r.processing_ms for a, (_, r) in zip(to_publish, results)]    # in transit + latest slot
    published = int(seconds * fps * feeds)
    dropped = sum(after[s].frames_dropped - before.get(s, after[s]).frames_dropped for s in after)
    processed = sum(after[s].frames_processed - before.get(s, after[s]).frames_processed for s in after)
    return {
        "feeds": feeds, "width": width, "height": height, "fps_per_feed": fps, "profile": profile,
        "seconds": seconds, "frames_published": published, "boxes_received": len(results),
        "frames_processed": processed, "frames_dropped": dropped,
        "processing_ms": {"mean": round(statistics.fmean(processing), 2) if processing else None,
                          "p50": _percentile(processing, 0.5), "p95": _percentile(processing, 0.95)},
        "end_to_end_ms": {"p50": _percentile(end_to_end, 0.5), "p95": _percentile(end_to_end, 0.95),
                          "max": _percentile(end_to_end, 1.0)},
        "breakdown_ms_p50_p95": {"frame_wait": [_percentile(waiting, 0.5), _percentile(waiting, 0.95)],
                                 "box_delivery": [_percentile(delivery, 0.5), _percentile(delivery, 0.95)]},
        "rss_mb": {"workers": rss_workers, "service_process_incl_publishers": rss_service},
        "pss_mb": {"workers": pss_workers},
        "load_average": os.getloadavg(),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tacf_service.bench", description=__doc__.splitlines()[0])
    parser.add_argument("--feeds", type=int, nargs="+", default=[1, 4])
    parser.add_argument("--seconds", type=float, default=15.0)
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--height", type=int, default=720)
    parser.add_argument("--fps", type=float, default=10.0)
    parser.add_argument("--profile", default="authors")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    report = {"configs": [run_config(n, args.seconds, args.width, args.height, args.fps, args.profile)
                          for n in args.feeds], "cpus": os.cpu_count()}
    json.dump(report, sys.stdout, indent=2)
    sys.stdout.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
