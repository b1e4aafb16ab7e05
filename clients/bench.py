"""`tacf bench service`: end-to-end latency, drops, memory and CPU of a real `tacf serve` under N camera feeds.

    tacf bench service --feeds 1 6 12 --fps 10 --seconds 30 --json bench.json

For each feed count: starts `tacf serve` in a child process on a free loopback port (no spare worker, so every
worker process is a session), publishes N feeds from this process, each the JPEG files of one real 1280x720
sequence of the data folder, looped, sent as they are (no re-encoding, so the publisher costs almost no CPU and
the service decodes real camera-size JPEGs). Feeds are phase-shifted like unsynchronised cameras. One session
per feed is started on the sequence's first ground-truth box; after a warm-up the run measures, for frames
published inside the window:

- latency_ms: frame stamped and put -> its BoxResult received here (one clock, one machine), p50/p95/p99/max;
- frames_sent, boxes_received, dropped = frames sent that got no box (superseded in a worker's latest-only slot,
  or lost in transit);
- rss_mb_per_session: mean RSS of the worker processes at the window's end, and pss_mb_per_session, their
  proportional set size (pages shared with other processes, libraries and what the fork server loaded for every
  worker, divided among those that map them: what each session really adds); pss_mb_total: the PSS of the service
  and every process it started (workers, fork server, resource tracker), the whole footprint;
- cpu_percent: CPU time of the service and its processes over the window / window length (100 = one core),
  a worker that died in the window (its CPU time up to its death) and the one started in its place included;
- worker_restarts: workers the service restarted in the window (after a crash or a hang), as it counts them;
- over_time: total RSS and PSS (MB) and open file descriptors of the service and its processes, sampled 20
  times over the window, so a long run (`--seconds 600`) is a soak test: all must stay flat (PSS also shows pages
  the workers share with the fork server being copied into each, which RSS cannot).

The processes are found under the service's pid (Linux /proc) at every sample, so a restarted worker is measured
from the first sample after it started.

A looped sequence restarts with the target elsewhere; the session then tracks whatever it holds, which costs
the same per frame, so the figures stay load figures, not accuracy.
"""
from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from tacf.argument_types import integer, positive_number, seconds
from tacf.config import PROFILES      # plain data: checks --profile before a service starts
from tacf.eval.cli import DEFAULT_DATA, report_file  # argparse-level: as `tacf bench tracker` has them

log = logging.getLogger(__name__)

FRAME_SIZE = (1280, 720)
NODE = "bench"
CLOCK_TICKS = os.sysconf("SC_CLK_TCK")
# How long every session may take to send its first box (read at each run, so that a test can shorten it). The
# session starts have already paid for the fork server (the tracker's numba loops loaded, or compiled on a cold
# cache: 4 s); the first boxes of 12 feeds then came within 3 s on 2 cores. The service kills a worker silent for
# 15 s and starts another (tacf_service.pool.WORKER_SILENCE_S): this leaves room for three such restarts.
FIRST_BOX_TIMEOUT_S = 60.0


def register_bench(bench_subparsers) -> None:
    p = bench_subparsers.add_parser(
        "service", help="latency, drops, memory and CPU of `tacf serve` under N real 1280x720 JPEG feeds",
        description="Start `tacf serve`, publish N looped real 1280x720 JPEG sequences at --fps and report "
                    "latency, drops, memory and CPU as JSON.")
    p.add_argument("root", metavar="ROOT", type=Path, nargs="?",
                   help=f"folder of annotated sequences (default {DEFAULT_DATA})")
    p.add_argument("--feeds", type=integer(1), nargs="+", default=[1], metavar="N",
                   help="feed counts to run one after the other (default 1)")
    p.add_argument("--fps", type=positive_number, default=10.0, help="frames per second per feed (default 10)")
    p.add_argument("--seconds", type=positive_number, default=20.0, help="measured window per feed count (default 20)")
    p.add_argument("--warmup", type=seconds, default=5.0,
                   help="seconds tracked after every session's first box, before measuring (default 5)")
    p.add_argument("--profile", choices=PROFILES,
                   help="tracker profile of the sessions (default: the service's default)")
    p.add_argument("--json", type=report_file, metavar="OUT", help="write the report here (default: standard output)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_bench_service)


@dataclass(frozen=True)
class Feed:
    """One looped camera: the raw JPEG bytes of a sequence's frames and its first ground-truth box."""
    name: str
    jpegs: tuple[bytes, ...]
    first_box: tuple[float, float, float, float]


def load_feeds(root: Path, count: int) -> list[Feed]:
    """`count` feeds from the 1280x720 sequences under root, reusing sequences when there are fewer."""
    from tacf.eval.datasets import load_sequences
    from tacf.images import read_image

    feeds: list[Feed] = []
    for seq in load_sequences(root):
        if any(Path(p).suffix.lower() not in (".jpg", ".jpeg") for p in seq.frames):
            continue                # the files go out as they are, labelled JPEG
        first = read_image(Path(seq.frames[0]))      # OpenCV crashed on a path not in UTF-8 (a GBK folder)
        if first is None or (first.shape[1], first.shape[0]) != FRAME_SIZE:
            continue
        jpegs = tuple(Path(p).read_bytes() for p in seq.frames)
        feeds.append(Feed(seq.name, jpegs, tuple(float(v) for v in seq.gt[0])))
        if len(feeds) == count:
            break
    if not feeds:
        raise FileNotFoundError(f"no {FRAME_SIZE[0]}x{FRAME_SIZE[1]} JPEG sequences under {root}")
    return [feeds[i % len(feeds)] for i in range(count)]


class FeedPublisher:
    """Publishes every feed at `fps` from one thread, feed i phase-shifted by i / (N fps); records each put.

    One put every 1 / (N fps) in turn, paced by sources.Pacer: after a stall (a GC pause, swapping, SIGSTOP) the
    schedule starts again from now instead of sending every overdue frame back to back, which the service, keeping
    a feed's latest frame only, would count as drops. seq stays contiguous."""

    def __init__(self, session, feeds: list[Feed], fps: float):
        import zenoh

        from tacf_schemas import MSGPACK_ENCODING

        self.feeds, self.fps = feeds, fps
        self.keys = [f"{NODE}/camera{i}" for i in range(len(feeds))]
        self._pubs = [session.declare_publisher(key, encoding=zenoh.Encoding(MSGPACK_ENCODING),
                                                congestion_control=zenoh.CongestionControl.DROP)
                      for key in self.keys]
        self.sent: list[list[int]] = [[] for _ in feeds]   # stamp_ns of every frame put, by feed; index = seq
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="bench-publisher", daemon=True)

    def start(self) -> "FeedPublisher":
        self._thread.start()
        return self

    def _run(self) -> None:
        from tacf_clients.sources import Pacer
        from tacf_schemas import Frame, encode

        width, height = FRAME_SIZE
        n = len(self.feeds)
        pacer = Pacer(n * self.fps)
        tick = 0
        while True:
            pacer.wait(self._stop.is_set)
            if self._stop.is_set():
                break
            i, seq = tick % n, tick // n
            jpeg = self.feeds[i].jpegs[seq % len(self.feeds[i].jpegs)]
            stamp = time.time_ns()
            self._pubs[i].put(encode(Frame(seq=seq, stamp_ns=stamp, encoding="jpeg", width=width, height=height,
                                           data=jpeg)))
            self.sent[i].append(stamp)
            tick += 1

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        for pub in self._pubs:
            pub.undeclare()


def _children(pid: int) -> list[int]:
    """pid's child processes (Linux /proc)."""
    found = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            found += [int(c) for c in (task / "children").read_text().split()]
        except OSError:
            continue
    return found


def _descendants(pid: int) -> list[int]:
    """pid's child processes, recursively."""
    found, todo = [], [pid]
    while todo:
        children = _children(todo.pop())
        found += children
        todo += children
    return found


def _processes(service_pid: int) -> list[int]:
    """The service and every process under it, parents before their children, found anew at each call: a worker
    the service restarts is a new process."""
    return [service_pid, *_descendants(service_pid)]


def _cpu_seconds(pid: int) -> float:
    """CPU time of pid and of its children that exited and were waited for: utime + stime + cutime + cstime. A
    worker that dies is waited for by its parent (the fork server, or the service when workers are spawned), and
    the kernel then adds all the CPU time it used to that parent's cutime and cstime."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return sum(int(v) for v in fields[11:15]) / CLOCK_TICKS


def _tree_cpu_seconds(service_pid: int) -> float:
    """CPU time of the service and its processes, those that ended included. Read parents first: a worker waited
    for between its parent's read and its own is missed (microseconds), never counted twice."""
    return sum(map(_cpu_seconds, _processes(service_pid)))


def _memory_mb(pid: int, file: str, field: str) -> float | None:
    """A kB field of /proc/<pid>/<file> in MB: ("status", "VmRSS:") or ("smaps_rollup", "Pss:")."""
    try:
        for line in Path(f"/proc/{pid}/{file}").read_text().splitlines():
            if line.startswith(field):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return None


def _total_mb(pids: list[int], file: str, field: str) -> float:
    return sum(_memory_mb(pid, file, field) or 0 for pid in pids)


def _open_fds(pid: int) -> int:
    try:
        return len(os.listdir(f"/proc/{pid}/fd"))
    except OSError:
        return 0


def _mean(values) -> float | None:
    values = [v for v in values if v is not None]
    return round(sum(values) / len(values), 1) if values else None


def _workers(service_pid: int) -> list[int]:
    """The session workers: the children of the service's fork server, or, spawned, the service's own children but
    multiprocessing's resource tracker. By name, not by having no children: a fork server whose only worker has
    just died has none."""
    found = []
    for pid in _children(service_pid):
        try:
            command = Path(f"/proc/{pid}/cmdline").read_bytes()
        except OSError:
            continue
        if b"forkserver" in command:
            found += _children(pid)
        elif b"resource_tracker" not in command:
            found.append(pid)
    return found


def _restarts(client) -> int:
    """Worker restarts of the service's sessions so far, as the service counts them."""
    return sum(info.restarts for info in client.list())


def _percentile(values: list[float], q: float) -> float | None:
    """The nearest-rank percentile: the smallest value with at least a fraction q of the values at or below it."""
    if not values:
        return None
    ordered = sorted(values)
    return round(ordered[max(0, math.ceil(q * len(ordered)) - 1)], 1)


def _pause(seconds: float, stop: threading.Event, service) -> None:
    """Wait `seconds`; KeyboardInterrupt once `stop` is set (SIGINT, SIGTERM, SIGHUP), so that the run's `finally`
    stops the service it started (in a session of its own, no signal to the bench reaches it); LocalServiceError
    once the service has exited (a run measured it dead, then reported a service that did not answer)."""
    if stop.wait(seconds):
        raise KeyboardInterrupt
    service.check_alive()


def _described(client, sid: str) -> str:
    """The session id with its state as its service reports it (and why it failed, if it says), when it answers."""
    from tacf_clients.errors import TacfError

    try:
        info = client.status(sid)
    except TacfError:
        return sid
    why = f": {info.health.message}" if info.health is not None and info.health.message else ""
    restarts = f", worker restarted {info.restarts} times" if info.restarts else ""
    return f"{sid} ({info.state}{why}{restarts})"


def run_feeds(feeds: list[Feed], fps: float, seconds: float, warmup: float, profile: str | None,
              progress: bool = True, stop: threading.Event | None = None) -> dict:
    """One benchmark run with len(feeds) feeds; the JSON-ready report. KeyboardInterrupt once `stop` is set before
    the measured window closes (after, the report is made), LocalServiceError when the service fails, TimeoutError
    when a session sends no box."""
    from tqdm import tqdm

    from tacf_clients.client import TrackingClient
    from tacf_clients.errors import TacfError
    from tacf_clients.local_service import LocalService
    from tacf_clients.zconfig import open_session
    from tacf_schemas import BoxResult, Frame

    n = len(feeds)
    stop = stop or threading.Event()
    received: list[tuple[int, BoxResult]] = []
    lock = threading.Lock()

    def on_box(box: BoxResult) -> None:
        now = time.time_ns()
        with lock:
            received.append((now, box))

    service = LocalService(node=NODE, extra_args=("--max-sessions", str(n), "--spare-workers", "0"))
    publisher = session = None
    try:
        service.start()
        session = open_session(service.options)
        if not service.wait_ready(session, cancel=stop):
            raise KeyboardInterrupt
        client = TrackingClient(session=session, node=NODE, timeout=30.0)
        subscription = client.subscribe(on_box=on_box)
        publisher = FeedPublisher(session, feeds, fps).start()
        for i, feed in enumerate(feeds):   # the box of frame 0, sent with frame 0 (the service may not have it)
            first = Frame(seq=0, stamp_ns=time.time_ns(), encoding="jpeg", width=FRAME_SIZE[0], height=FRAME_SIZE[1],
                          data=feed.jpegs[0])
            client.start(publisher.keys[i], feed.first_box, seq=0, frames=[first], profile=profile, sid=f"feed{i}")
        log.info("%d feeds: waiting up to %g s for the first box of every session", n, FIRST_BOX_TIMEOUT_S)
        deadline = time.monotonic() + FIRST_BOX_TIMEOUT_S
        while True:
            with lock:
                without_box = sorted({f"feed{i}" for i in range(n)} - {b.sid for _, b in received})
            if not without_box:
                break
            if time.monotonic() > deadline:
                quick_client = TrackingClient(session=session, node=NODE, timeout=2.0)   # not 30 s a session
                raise TimeoutError(f"no box within {FIRST_BOX_TIMEOUT_S:g} s from "
                                   + ", ".join(_described(quick_client, sid) for sid in without_box))
            _pause(0.1, stop, service)
        _pause(warmup, stop, service)
        service_pid = service.process.pid
        restarts_before = _restarts(client)
        cpu_before, wall_before = _tree_cpu_seconds(service_pid), time.monotonic()
        first_seq = [len(s) for s in publisher.sent]
        over_time = {"seconds": [], "rss_mb": [], "pss_mb": [], "open_fds": []}
        with tqdm(total=round(seconds), desc=f"{n} feed{'s' * (n > 1)}", unit="s", leave=False,
                  bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} s",    # its rate would read "1.00s/s"
                  disable=not progress) as bar:
            while (elapsed := time.monotonic() - wall_before) < seconds:
                if elapsed >= len(over_time["seconds"]) * seconds / 20:
                    processes = _processes(service_pid)
                    over_time["seconds"].append(round(elapsed, 1))
                    over_time["rss_mb"].append(round(_total_mb(processes, "status", "VmRSS:")))
                    over_time["pss_mb"].append(round(_total_mb(processes, "smaps_rollup", "Pss:")))
                    over_time["open_fds"].append(sum(map(_open_fds, processes)))
                next_sample = len(over_time["seconds"]) * seconds / 20
                _pause(max(0.0, min(0.2, next_sample - elapsed, seconds - elapsed)), stop, service)
                bar.update(min(round(seconds), int(time.monotonic() - wall_before)) - bar.n)
        last_seq = [len(s) - 1 for s in publisher.sent]
        cpu_percent = 100 * (_tree_cpu_seconds(service_pid) - cpu_before) / (time.monotonic() - wall_before)
        workers = _workers(service_pid)
        rss = _mean(_memory_mb(pid, "status", "VmRSS:") for pid in workers)
        pss = _mean(_memory_mb(pid, "smaps_rollup", "Pss:") for pid in workers)
        pss_total = round(_total_mb(_processes(service_pid), "smaps_rollup", "Pss:"), 1)
        worker_restarts = _restarts(client) - restarts_before
        # let the boxes of the window's last frames arrive; the window is complete, so a stop signal does not cut
        # this short: the count's report is made, then the signal ends the runs
        time.sleep(2.0)
        service.check_alive()
        with lock:
            sid_index = {f"feed{i}": i for i in range(n)}
            window = [(t, b) for t, b in received
                      if first_seq[sid_index[b.sid]] <= b.seq <= last_seq[sid_index[b.sid]]]
        subscription.close()
        for i in range(n):
            client.stop(f"feed{i}")
    except TacfError:
        service.check_alive()       # a service that exited answers nothing: say that it exited
        raise
    finally:
        if publisher is not None:
            publisher.stop()
        if session is not None:
            session.close()
        service.stop()

    latency = [(t - b.stamp_ns) / 1e6 for t, b in window]
    frames_sent = sum(last - first + 1 for first, last in zip(first_seq, last_seq))
    boxes = len({(b.sid, b.seq) for _, b in window})
    return {
        "feeds": n, "fps_in": fps, "seconds": seconds,
        "latency_ms": {"p50": _percentile(latency, 0.50), "p95": _percentile(latency, 0.95),
                       "p99": _percentile(latency, 0.99), "max": _percentile(latency, 1.0)},
        "frames_sent": frames_sent, "boxes_received": boxes, "dropped": frames_sent - boxes,
        "rss_mb_per_session": rss, "pss_mb_per_session": pss, "pss_mb_total": pss_total,
        "cpu_percent": round(cpu_percent, 1), "cpus": os.cpu_count(), "worker_restarts": worker_restarts,
        "over_time": over_time,
        "sequences": sorted({f.name for f in feeds}), "load_average": [round(v, 2) for v in os.getloadavg()],
    }


def cmd_bench_service(args: argparse.Namespace) -> int:
    from tacf_clients.cli import stop_on_signals
    from tacf_clients.errors import TacfError
    from tacf_clients.local_service import LocalServiceError

    root = args.root or DEFAULT_DATA
    if not root.is_dir():
        log.error("no sequences: %s does not exist (pass ROOT)", root)
        return 2
    try:
        feeds = load_feeds(root, max(args.feeds))
    except FileNotFoundError as exc:
        log.error("%s", exc)
        return 2
    reports, status = [], 0          # the reports of the counts run so far are written whatever ends the runs
    with stop_on_signals() as stop:
        for count in args.feeds:
            try:
                reports.append(run_feeds(feeds[:count], args.fps, args.seconds, args.warmup, args.profile,
                                         progress=not args.no_progress, stop=stop))
                log.info("%d feeds: p95 %s ms, %d of %d frames dropped", count, reports[-1]["latency_ms"]["p95"],
                         reports[-1]["dropped"], reports[-1]["frames_sent"])
            except KeyboardInterrupt:
                pass                # a stop signal before the window closed: the count is not reported
            except (LocalServiceError, TacfError, TimeoutError) as exc:    # a service's: its log's last lines too
                log.error("%d feeds: %s", count, exc)
                status = 1
                break
            if stop.is_set():       # after the window closed too (its report kept), or while the service stopped
                print("tacf bench: interrupted", file=sys.stderr)
                status = stop.exit_code
                break
    if reports:     # the shape the command asked for, however far the runs went: a list for several counts
        text = json.dumps(reports if len(args.feeds) > 1 else reports[0], indent=2) + "\n"
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(text)
            log.info("wrote %s", args.json)
        else:
            sys.stdout.write(text)
    return status
