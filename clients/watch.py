"""`tacf watch`: a live terminal table of the latest box and health of every session (or of one).

The table is rebuilt from the newest BoxResult and Health of each session (latest-only subscription) every
`interval` seconds; on a terminal the screen is redrawn in place, otherwise each refresh is printed in turn.
Rendering is pure (`render_table`) so it can be tested without a terminal.
"""
from __future__ import annotations

import sys
import threading
import time
from dataclasses import dataclass, field
from typing import TextIO

from tacf_clients.client import TrackingClient
from tacf_clients.errors import TacfError, as_invalid_id
from tacf_clients.zconfig import ZenohOptions
from tacf_schemas import keys
from tacf_schemas.models import BoxResult, Health, SessionInfo

STALE_S = 5.0
STOP_CHECK_S = 0.2      # how soon a stop (Ctrl-C) is seen while no data comes
CLEAR = "\x1b[H\x1b[2J"


@dataclass
class SessionRow:
    node: str
    sid: str
    state: str = "?"
    box: BoxResult | None = None
    health: Health | None = None
    updated: float = field(default_factory=time.monotonic)

    def apply(self, item: BoxResult | Health | SessionInfo) -> None:
        if isinstance(item, BoxResult):
            self.box = item
        elif isinstance(item, Health):
            self.health, self.state = item, item.state
        else:
            self.state = item.state
            if item.health is not None:
                self.health = item.health
        self.updated = time.monotonic()


def _fmt_box(box) -> str:
    return "({:.0f}, {:.0f}, {:.0f}, {:.0f})".format(*box)


def _fmt(value, spec: str, missing: str = "-") -> str:
    return missing if value is None else format(value, spec)


def printable(text: object) -> str:
    """str(text) with its control characters (terminal escapes, newlines) written as Python escapes (\\x1b, \\n).
    For the free text a reply carries (a session's image key, profile and message, an error's message): a wildcard
    query is answered by anyone on the Zenoh network, whose text went raw to the operator's terminal."""
    text = str(text)
    return text if text.isprintable() else "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


ENDED = ("stopped", "failed")


def describe_session(info: SessionInfo) -> str:
    """One line about a session, for `tacf start|stop|status`."""
    text = (f"{info.sid} on {info.node}: {info.state}, key {printable(info.image_key)}, "
            f"profile {printable(info.profile)}, box {_fmt_box(info.box)}")
    if info.init_seq is not None:
        text += f", init seq {info.init_seq}"
    if info.health is not None:
        h = info.health
        if info.state not in ENDED:     # an ended session's rates read 0, as if it were broken
            text += f", {h.fps:.1f} fps, {h.processing_ms_p95:.1f} ms p95"
        text += f", processed {h.frames_processed}, lost {h.frames_lost}, dropped {h.frames_dropped}"
        if h.message:                   # why it failed, is lost or waits (no frames, a cropped feed...)
            text += f": {printable(h.message)}"
    return text


def session_table(sessions: list[SessionInfo]) -> str:
    """A plain table of SessionInfos, for `tacf list`."""
    rows = [("NODE", "SID", "STATE", "KEY", "PROFILE", "BOX", "FPS", "PROCESSED", "LOST", "DROPPED")]
    for s in sessions:
        h = s.health
        rows.append((s.node, s.sid, s.state, printable(s.image_key), printable(s.profile), _fmt_box(s.box),
                     _fmt(h and h.fps, ".1f"),
                     _fmt(h and h.frames_processed, "d"), _fmt(h and h.frames_lost, "d"),
                     _fmt(h and h.frames_dropped, "d")))
    return columns(rows)


def render_table(rows: list[SessionRow], now: float | None = None) -> str:
    """The live table: one line per session, newest data."""
    now = time.monotonic() if now is None else now
    out = [("NODE", "SID", "STATE", "SEQ", "BOX x,y,w,h", "OK", "PME", "FPS", "MS p95", "AGE ms", "RECV", "LOST",
            "DROP")]
    for row in sorted(rows, key=lambda r: (r.node, r.sid)):
        b, h = row.box, row.health
        state = row.state + (" (stale)" if now - row.updated > STALE_S and row.state != "stopped" else "")
        out.append((row.node, row.sid, state,
                    _fmt(b and b.seq, "d"), _fmt_box(b.box) if b else "-",
                    ("yes" if b.ok else "LOST") if b else "-", _fmt(b and b.pme, ".1f"),
                    _fmt(h and h.fps, ".1f"), _fmt(h and h.processing_ms_p95, ".1f"),
                    _fmt(h and h.frame_age_ms, ".0f"), _fmt(h and h.frames_received, "d"),
                    _fmt(h and h.frames_lost, "d"), _fmt(h and h.frames_dropped, "d")))
    if len(out) == 1:
        return columns(out) + "\n(no sessions yet)"
    return columns(out)


def columns(rows: list[tuple[str, ...]]) -> str:
    widths = [max(len(str(r[i])) for r in rows) for i in range(len(rows[0]))]
    return "\n".join("  ".join(str(c).ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows)


def watch(options: ZenohOptions | None = None, sid: str = keys.WILDCARD, node: str | None = None,
          interval: float = 0.5, duration: float | None = None, stop: threading.Event | None = None,
          out: TextIO | None = None) -> int:
    """Show the live table until `stop` is set or `duration` seconds pass. Returns an exit code.

    A bad `sid` or `node` raises InvalidId, a session that cannot open ZenohUnavailable."""
    out = out or sys.stdout
    stop = stop or threading.Event()
    redraw = out.isatty()
    rows: dict[tuple[str, str], SessionRow] = {}
    deadline = None if duration is None else time.monotonic() + duration
    if sid != keys.WILDCARD:            # before the list query, which said it waited for a service meanwhile
        with as_invalid_id():
            keys.validate_id(sid, "session id")
    with TrackingClient(options, node=node, timeout=2.0) as client:     # a bad node id is refused before opening
        try:
            services = client.services()
        except TacfError as exc:
            print(f"(list failed: {printable(exc)}; showing live data only)", file=out)
        else:
            # a peer opens without anyone to talk to: say so, then wait for one (unless a Ctrl-C came meanwhile:
            # the query's silence is then no news)
            if not services and not stop.is_set():
                print(f"(no service answered{f' as {node!r}' if node else ''}: waiting for one; is `tacf serve` "
                      "running, and reachable with these Zenoh settings?)", file=out)
            for info in (info for listing in services for info in listing.sessions):
                if sid in (keys.WILDCARD, info.sid):
                    rows.setdefault((info.node, info.sid), SessionRow(info.node, info.sid)).apply(info)

        def draw() -> None:
            text = render_table(list(rows.values()))
            out.write((CLEAR if redraw else "") + f"tacf watch  {time.strftime('%H:%M:%S')}\n{text}\n\n")
            out.flush()

        # on every service unless --node says one: a session seen on one may be started again on another
        with client.results(sid, node=node or keys.WILDCARD, latest_only=True) as stream:
            next_draw = time.monotonic()
            while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
                # wait for data until the next refresh, in slices: a long --interval must not hide a stop (Ctrl-C)
                # or the end of --duration
                item = stream.get(timeout=min(max(0.0, next_draw - time.monotonic()), STOP_CHECK_S))
                if item is not None:
                    rows.setdefault((item.node, item.sid), SessionRow(item.node, item.sid)).apply(item)
                if time.monotonic() < next_draw:
                    continue
                draw()
                next_draw = time.monotonic() + interval
        if not stop.is_set():
            draw()          # what --duration ends on: the first table may have come before any box
    return 0
