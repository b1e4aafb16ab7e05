"""Prometheus text exposition (format 0.0.4) of the dashboard's view of every session: GET /metrics.

Per session (labels node, sid, image_key): fps, processing latency (mean and p95), frame age, capture-to-
dashboard latency of the newest box, PME, frame counters (received, processed, dropped, rejected, lost), worker
restarts, and the state as a one-hot gauge over every SessionState. Counters are the service's running totals
as of its last health report. Per watched image key: the frames the dashboard read and the messages it could not
decode. Pure functions: the HTTP side passes in the views.
"""
from __future__ import annotations

from collections.abc import Iterable, Mapping

from tacf_schemas.models import SESSION_STATES

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"

# name, type, help, value of a SessionView (None: no sample for that session)
_SESSION_METRICS = (
    ("tacf_session_fps", "gauge", "Frames processed per second over the service's last health window.",
     lambda v: v.health.fps if v.health else None),
    ("tacf_session_processing_ms_mean", "gauge", "Mean per-frame processing time (decode + tracker), ms.",
     lambda v: v.health.processing_ms_mean if v.health else None),
    ("tacf_session_processing_ms_p95", "gauge", "95th percentile per-frame processing time, ms.",
     lambda v: v.health.processing_ms_p95 if v.health else None),
    ("tacf_session_frame_age_ms", "gauge", "Age of the last processed frame when the service reported health, ms.",
     lambda v: v.health.frame_age_ms if v.health else None),
    ("tacf_session_box_latency_ms", "gauge", "Capture to dashboard latency of the newest box, ms.",
     lambda v: (v.box_received_ns - v.box.stamp_ns) / 1e6 if v.box and v.box_received_ns else None),
    ("tacf_session_pme", "gauge", "Peak-to-median energy of the newest box (low: target likely lost).",
     lambda v: v.box.pme if v.box else (v.health.pme if v.health else None)),
    ("tacf_session_frames_received_total", "counter", "Frames the session's worker received.",
     lambda v: v.health.frames_received if v.health else None),
    ("tacf_session_frames_processed_total", "counter", "Frames the session's tracker processed.",
     lambda v: v.health.frames_processed if v.health else None),
    ("tacf_session_frames_dropped_total", "counter",
     "Frames superseded by a newer one before being processed (latest-only).",
     lambda v: v.health.frames_dropped if v.health else None),
    ("tacf_session_frames_rejected_total", "counter", "Frames that could not be decoded or used.",
     lambda v: v.health.frames_rejected if v.health else None),
    ("tacf_session_frames_lost_total", "counter", "Frames processed with the target flagged lost (low PME).",
     lambda v: v.health.frames_lost if v.health else None),
    ("tacf_session_restarts_total", "counter", "Worker restarts after a crash or a hang.",
     lambda v: v.health.restarts if v.health else None),
)


def escape_label(value: str) -> str:
    """A label value as the text format wants it: backslash, double quote and newline escaped."""
    return value.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")


def _labels(pairs: Mapping[str, str]) -> str:
    return "{" + ",".join(f'{k}="{escape_label(str(v))}"' for k, v in pairs.items()) + "}"


def _number(value: float) -> str:
    if value != value:
        return "NaN"
    if value in (float("inf"), float("-inf")):
        return "+Inf" if value > 0 else "-Inf"
    return repr(int(value)) if float(value).is_integer() and abs(value) < 2**53 else repr(float(value))


def render(views: Iterable, *, frame_counts: Mapping[str, tuple[int, int]] | None = None,
           nodes: Mapping[str, int] | None = None, event_clients: int = 0, connections_refused: int = 0,
           up: bool = True) -> str:
    """The /metrics body. views: SessionView-like objects (node, sid, image_key, state, box, box_received_ns,
    health); frame_counts: image key -> (received, rejected) by the dashboard; nodes: node -> max_sessions;
    connections_refused: HTTP connections closed unserved, the dashboard's limit reached."""
    views = list(views)
    lines: list[str] = []

    def family(name: str, kind: str, help_text: str) -> None:
        lines.append(f"# HELP {name} {help_text}")
        lines.append(f"# TYPE {name} {kind}")

    family("tacf_dashboard_up", "gauge", "1 while the dashboard's Zenoh side works.")
    lines.append(f"tacf_dashboard_up {1 if up else 0}")
    family("tacf_dashboard_sessions", "gauge", "Sessions the dashboard knows, by node.")
    per_node: dict[str, int] = {node: 0 for node in (nodes or {})}
    for v in views:
        per_node[v.node] = per_node.get(v.node, 0) + 1
    for node, count in sorted(per_node.items()):
        lines.append(f"tacf_dashboard_sessions{_labels({'node': node})} {count}")
    if nodes:
        family("tacf_service_max_sessions", "gauge", "Session limit of each service that answered the last list.")
        for node, limit in sorted(nodes.items()):
            lines.append(f"tacf_service_max_sessions{_labels({'node': node})} {limit}")
    family("tacf_dashboard_event_clients", "gauge", "Browsers connected to /events.")
    lines.append(f"tacf_dashboard_event_clients {event_clients}")
    family("tacf_dashboard_connections_refused_total", "counter",
           "HTTP connections closed unserved: as many were open as the dashboard serves.")
    lines.append(f"tacf_dashboard_connections_refused_total {connections_refused}")
    if frame_counts:
        family("tacf_dashboard_frames_received_total", "counter",
               "Frames the dashboard read per image key (at most its frame rate cap; the rest are skipped).")
        for key, (received, _) in sorted(frame_counts.items()):
            lines.append(f"tacf_dashboard_frames_received_total{_labels({'image_key': key})} {received}")
        family("tacf_dashboard_frames_rejected_total", "counter",
               "Messages on an image key that the dashboard could not decode as a frame.")
        for key, (_, rejected) in sorted(frame_counts.items()):
            lines.append(f"tacf_dashboard_frames_rejected_total{_labels({'image_key': key})} {rejected}")

    family("tacf_session_state", "gauge", "1 for the session's current state, 0 for the others.")
    for v in views:
        for state in SESSION_STATES:
            labels = _labels({"node": v.node, "sid": v.sid, "image_key": v.image_key or "", "state": state})
            lines.append(f"tacf_session_state{labels} {1 if v.state == state else 0}")
    for name, kind, help_text, value_of in _SESSION_METRICS:
        samples = []
        for v in views:
            value = value_of(v)
            if value is not None:
                labels = _labels({"node": v.node, "sid": v.sid, "image_key": v.image_key or ""})
                samples.append(f"{name}{labels} {_number(value)}")
        if samples:
            family(name, kind, help_text)
            lines.extend(samples)
    return "\n".join(lines) + "\n"
